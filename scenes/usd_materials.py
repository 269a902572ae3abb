"""The materials of a USD stage's meshes as Mitsuba BSDFs: ``UsdPreviewSurface``
(diffuse colour, a diffuse texture, roughness, metallic, opacity, emission),
``displayColor`` as the fallback, grey otherwise; a mixin of
:class:`hlbvh.scenes.usd.UsdScene`.

``UsdPreviewSurface`` bound with ``UsdShade.MaterialBindingAPI``: diffuseColor,
roughness, metallic to ``principled``; opacity below 1 through a ``mask``
(``opacityThreshold`` makes it a cutout); emissiveColor to an ``area`` emitter on
the mesh. A diffuseColor or emissiveColor read from a ``UsdUVTexture`` becomes a
``bitmap`` over the mesh's texture coordinates (the ``UsdPrimvarReader_float2``'s
primvar, ``st`` by default; per point, or faceVarying with the points split where
their uv differ). An input read from a primvar reader (:data:`READERS`) takes that
primvar as ``displayColor`` is read: one value, or per point or face a Mitsuba mesh
attribute (``vertex_color``/``face_color`` for diffuseColor, ``vertex_roughness``,
... for the others); emissiveColor, and opacity cut by ``opacityThreshold``, take
its mean when it varies (said: Mitsuba's area emitter samples one radiance or a
texture, not a mesh attribute, and a cutout is not an interpolated opacity). Other
connected inputs keep their authored value (said once per material, naming them).
Without a material the ``displayColor`` primvar gives a diffuse colour, else grey.
"""

from __future__ import annotations

import numpy as np

from .usd_prims import (GREY, PREVIEW_DEFAULTS, UsdGeom, UsdShade, _array, _checked,
                        _connected_shader, _input_value, _interface_value, _two_sided,
                        _uv_texture)

#: UsdPreviewSurface inputs whose ``UsdUVTexture`` becomes a Mitsuba ``bitmap``.
TEXTURED_INPUTS = ("diffuseColor", "emissiveColor")

#: UsdPreviewSurface inputs read from a primvar reader, and the reader each takes.
READERS = {"diffuseColor": "UsdPrimvarReader_float3",
           "emissiveColor": "UsdPrimvarReader_float3",
           "roughness": "UsdPrimvarReader_float", "metallic": "UsdPrimvarReader_float",
           "opacity": "UsdPrimvarReader_float"}


class _Materials:
    """The materials of a USD stage's meshes, as methods of :class:`UsdScene`."""

    def _texcoords(self, prim, mesh, time, name: str, point_count: int, corners,
                   topology_varies: bool):
        """The texture coordinates of primvar ``name`` as Mitsuba's uv (``(s, 1 - t)``:
        USD's t runs up the image, Mitsuba's v down): ``(None, None, (V, 2))`` per
        point, or, faceVarying, ``(vertex_points, faces, (V', 2))`` with the points
        split where the uv differ. ``None`` (said) when the mesh has no such primvar,
        it is of another interpolation or the topology is time-sampled."""
        primvar = UsdGeom.PrimvarsAPI(mesh).GetPrimvar(name)
        values = primvar.Get(time) if primvar and primvar.HasValue() else None
        interpolation = primvar.GetInterpolation() if primvar else None
        why = None
        if values is None:
            why = f"has no primvar {name!r}"
        elif topology_varies:
            why = "has a time-sampled topology"
        elif interpolation not in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying,
                                   UsdGeom.Tokens.faceVarying):
            why = f"has {name!r} of interpolation {interpolation!r}"
        if why is None:
            values = _array(values, 2)
            indices = primvar.GetIndices(time) if primvar.IsIndexed() else None
            indices = (np.arange(len(values)) if indices is None
                       else np.array(indices, dtype=np.int64))
            if interpolation != UsdGeom.Tokens.faceVarying and len(indices) == point_count:
                st = values[indices]
                return None, None, np.stack([st[:, 0], 1 - st[:, 1]], axis=1)
            face_vertex = np.array(mesh.GetFaceVertexIndicesAttr().Get(time), dtype=np.int64)
            if interpolation == UsdGeom.Tokens.faceVarying and len(indices) == len(face_vertex):
                keys = np.stack([face_vertex, indices], axis=1)
                unique, inverse = np.unique(keys, axis=0, return_inverse=True)
                st = values[unique[:, 1]]
                return (unique[:, 0], inverse.reshape(-1)[corners].astype(np.uint32),
                        np.stack([st[:, 0], 1 - st[:, 1]], axis=1))
            why = f"has {name!r} of another length than its {interpolation} count"
        self._warn(f"{self._where}: {prim.GetPath()}: {why}; its textures are not "
                   f"mapped (their authored values are used)")
        return None

    def _material_parts(self, prim, mesh, time, topology_varies: bool, source_faces,
                        polygon_count: int) -> list:
        """``[(prim whose material binds, triangle selection)]``: the whole mesh, or,
        with ``materialBind`` GeomSubsets, one part per subset (its faces, its bound
        material) and one for the faces no subset takes (the mesh's material). A part
        is a Mitsuba mesh of its own holding all the mesh's points. A mesh whose
        topology is time-sampled is not split (said)."""
        everything = np.ones(len(source_faces), dtype=bool)
        subsets = [subset for subset in UsdGeom.Subset.GetAllGeomSubsets(mesh)
                   if subset.GetFamilyNameAttr().Get() == "materialBind"
                   and subset.GetElementTypeAttr().Get() == UsdGeom.Tokens.face]
        if not subsets:
            return [(prim, everything)]
        if topology_varies:
            self._warn(f"{self._where}: {prim.GetPath()}: its topology is time-sampled, so "
                       f"its {len(subsets)} GeomSubsets are not split out; the whole mesh "
                       f"takes the mesh's own material")
            return [(prim, everything)]
        taken = np.zeros(polygon_count, dtype=bool)
        parts = []
        for subset in subsets:
            polygons = np.array(subset.GetIndicesAttr().Get(time) or [], dtype=np.int64)
            polygons = polygons[(polygons >= 0) & (polygons < polygon_count)]
            chosen = np.isin(source_faces, polygons) & ~taken[source_faces]
            taken[polygons] = True
            if chosen.any():
                parts.append((subset.GetPrim(), chosen))
        rest = ~taken[source_faces]
        return ([(prim, rest)] if rest.any() else []) + parts

    def _material(self, prim, mesh, double_sided: bool, time, point_count: int,
                  source_faces, textures: bool = True) -> tuple:
        """``(bsdf, emission, attributes, st)``: the mesh's BSDF dict, its emission
        (``None``: none; an RGB radiance, or a bitmap's dict for a textured
        emissiveColor), the Mitsuba mesh attributes its BSDF reads (``{name: (N, width)
        values}``, see :meth:`_primvar`) and the primvar of texture coordinates its
        bitmaps read (``None``: none; ``textures=False``: no bitmaps, see
        :meth:`_unread_input`).

        Inputs connected to a shader: diffuseColor and emissiveColor to a
        ``UsdUVTexture`` read its file; an input of :data:`READERS` to its primvar
        reader reads that primvar (:meth:`_reader_value`); others keep their authored
        value (said, naming each).

        Raises:
            ValueError: an input that is not finite, or a negative colour, naming the
                shader and the input.
        """
        material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
        shader = None
        if material:
            source = material.ComputeSurfaceSource()
            shader = source[0] if source and source[0] else None
            if shader is not None and shader.GetIdAttr().Get() != "UsdPreviewSurface":
                self._warn(f"{self._where}: {material.GetPath()}: surface shader "
                           f"{shader.GetIdAttr().Get()!r} is not a UsdPreviewSurface; "
                           f"{prim.GetPath()} renders grey")
                shader = None
        if shader is None:
            color = self._primvar(prim, mesh, time, point_count, source_faces) or GREY
            reflectance, attributes = _texture_of(color)
            bsdf = {"type": "diffuse", "reflectance": reflectance}
            return (_two_sided(bsdf) if double_sided else bsdf), None, attributes, None
        values, connected = {}, []
        for name, default in PREVIEW_DEFAULTS.items():
            shader_input = shader.GetInput(name)
            from_interface, value = _interface_value(shader_input, time)
            if shader_input and shader_input.HasConnectedSource() and not from_interface:
                connected.append(name)
            values[name] = _checked(
                f"{self._where}: {shader.GetPath()}: inputs:{name}",
                default if value is None else tuple(float(v) for v in value)
                if isinstance(default, tuple) else float(value),
                least=0 if isinstance(default, tuple) else None)
        mapped, attributes, st = {}, {}, None
        dropped = []
        for name in connected:
            source = _connected_shader(shader.GetInput(name))
            kind = str(source.GetIdAttr().Get()) if source else ""
            if name in TEXTURED_INPUTS and kind == "UsdUVTexture":
                bitmap, wanted, why = _uv_texture(source, time, self._where) if textures else \
                    (None, None, "is not mapped")
                if bitmap is None:
                    value = self._unread_input(material, name, values[name], source, why, time)
                elif st not in (None, wanted):
                    value = self._unread_input(material, name, values[name], source,
                                               f"is read over {wanted!r}, not {st!r}", time)
                else:
                    value, st = bitmap, wanted
                if isinstance(value, dict):
                    mapped[name] = value
                else:
                    values[name] = value
            elif READERS.get(name) == kind:
                cut = name == "opacity" and values["opacityThreshold"] > 0
                value = self._reader_value(prim, mesh, name, source, values[name], time,
                                           point_count, source_faces, cut)
                texture, read = _texture_of(value)
                if read:
                    mapped[name] = texture
                    attributes.update(read)
                else:
                    values[name] = value
            else:
                dropped.append(f"{name} ({kind or 'a connection'})")
        if dropped:
            self._warn_once(f"{self._where}: {material.GetPath()}: connected inputs "
                            f"{', '.join(dropped)} are not read; their authored values "
                            f"are used")
        bsdf = {"type": "principled",
                "base_color": mapped.get("diffuseColor") or
                {"type": "rgb", "value": list(values["diffuseColor"])},
                "roughness": mapped.get("roughness") or
                min(max(values["roughness"], 0.0), 1.0),
                "metallic": mapped.get("metallic") or min(max(values["metallic"], 0.0), 1.0)}
        if double_sided:
            bsdf = _two_sided(bsdf)
        opacity = min(max(values["opacity"], 0.0), 1.0)
        if values["opacityThreshold"] > 0:
            opacity = 1.0 if opacity >= values["opacityThreshold"] else 0.0
        if "opacity" in mapped or opacity < 1:
            bsdf = {"type": "mask", "opacity": mapped.get("opacity", opacity), "bsdf": bsdf}
        emission = mapped.get("emissiveColor") or (
            values["emissiveColor"] if any(c > 0 for c in values["emissiveColor"]) else None)
        return bsdf, emission, attributes, st

    def _reader_value(self, prim, mesh, name: str, reader, authored, time, point_count: int,
                      source_faces, cut: bool):
        """The value of input ``name`` (authored value ``authored``: a colour tuple or
        a number) read through primvar reader ``reader``: the reader's primvar as
        :meth:`_primvar` gives it (one value, or per point or face ``(attribute name,
        values)``, scalars clamped to [0, 1]); its mean when it varies and the input
        is emissiveColor, or opacity cut by opacityThreshold (``cut``). The reader's
        ``fallback``, else ``authored``, when the mesh has no such primvar of the
        input's width (said once)."""
        width = 3 if isinstance(authored, tuple) else 1
        varname = str(_input_value(reader.GetInput("varname"), time) or "")
        single = ("Mitsuba's area emitter samples one radiance or a texture, not a "
                  "mesh attribute" if name == "emissiveColor" else
                  "a cutout (opacityThreshold) is not an interpolated opacity" if cut
                  else None)
        value = self._primvar(prim, mesh, time, point_count, source_faces, varname, width,
                              "color" if name == "diffuseColor" else name, single) \
            if varname else None
        if value is None:
            fallback = _input_value(reader.GetInput("fallback"), time)
            value = authored if fallback is None else \
                tuple(float(v) for v in np.ravel(fallback))[:3] if width == 3 \
                else float(np.ravel(fallback)[0])
            self._warn_once(f"{self._where}: {prim.GetPath()}: has no primvar {varname!r} "
                            f"of {'colours' if width == 3 else 'numbers'} that "
                            f"{reader.GetPath()} reads; {name} is {_shown(value)}")
        elif width == 1 and isinstance(value, tuple):
            value = (value[0], np.clip(value[1], 0.0, 1.0))
        return value

    def _unread_input(self, material, name: str, authored: tuple, texture, why: str,
                      time) -> tuple:
        """The value of input ``name`` whose ``UsdUVTexture`` is not read (``why``
        says why; said once per material and input): the texture's ``fallback`` where
        authored; else black for emissiveColor (UsdUVTexture's own fallback: an
        unread texture does not make a mesh glow) and the input's authored value for
        the others."""
        fallback = texture.GetInput("fallback")
        if fallback and fallback.HasAuthoredValue():
            value = tuple(float(v) for v in fallback.Get(time))[:3]
        elif name == "emissiveColor":
            value = (0.0, 0.0, 0.0)
        else:
            value = authored
        if why != "is not mapped":
            self._warn_once(f"{self._where}: {material.GetPath()}: inputs:{name}'s texture "
                            f"{texture.GetPath()} {why}; {name} is "
                            f"{tuple(round(c, 4) for c in value)}")
        return value

    def _primvar(self, prim, mesh, time, point_count: int, source_faces,
                 name: str = "displayColor", width: int = 3, attribute: str = "color",
                 single: str | None = None):
        """Primvar ``name`` of colours (``width`` 3, none negative) or numbers
        (``width`` 1): one value (a tuple of 3, or a float) when it is constant
        (``None`` without one, or when its values are of another width); per point
        (``vertex``/``varying``) or per face (``uniform``) as a Mitsuba mesh attribute
        ``("vertex_<attribute>", (V, width))`` or ``("face_<attribute>", (F, width))``
        (per triangle). Other interpolations, a mesh whose topology is time-sampled
        (``source_faces`` ``None``), or a use that takes one value (``single`` says
        why) get the mean (said)."""
        primvar = UsdGeom.PrimvarsAPI(mesh).GetPrimvar(name)
        value = primvar.ComputeFlattened(time) if primvar and primvar.HasValue() else None
        if value is None or len(value) == 0 or \
                (np.ndim(value[0]) != 1 or len(value[0]) != 3 if width == 3
                 else np.ndim(value[0]) != 0):
            return None  # none, or not of this width
        values = _checked(f"{self._where}: {prim.GetPath()}: primvars:{name}",
                          _array(value, width), least=0 if width == 3 else None)
        one = (lambda v: tuple(float(c) for c in v)) if width == 3 else \
            (lambda v: float(v[0]))
        if len(values) == 1 or np.all(values == values[0]):
            return one(values[0])
        interpolation = primvar.GetInterpolation()
        if single is None and interpolation in (UsdGeom.Tokens.vertex,
                                                UsdGeom.Tokens.varying) \
                and len(values) == point_count:
            return (f"vertex_{attribute}", values)
        if single is None and interpolation == UsdGeom.Tokens.uniform \
                and source_faces is not None and len(source_faces) \
                and len(values) > int(source_faces.max()):
            return (f"face_{attribute}", values[source_faces])
        mean = one(values.mean(axis=0))
        self._warn(f"{self._where}: {prim.GetPath()}: {name} of interpolation "
                   f"{interpolation!r} varies over the mesh"
                   f"{'' if single is None else f' ({single})'}; its mean "
                   f"{_shown(mean)} is used")
        return mean


def _texture_of(value) -> tuple:
    """``(Mitsuba texture, mesh attributes)`` of a value :meth:`_Materials._primvar`
    gives: an ``rgb`` or a number and none, or a ``mesh_attribute`` and the attribute
    the mesh then holds."""
    if isinstance(value, tuple) and isinstance(value[0], str):
        return {"type": "mesh_attribute", "name": value[0]}, {value[0]: value[1]}
    if isinstance(value, tuple):
        return {"type": "rgb", "value": list(value)}, {}
    return value, {}


def _shown(value) -> str:
    """A colour or a number as a line says it (4 decimals)."""
    if isinstance(value, tuple):
        return str(tuple(round(c, 4) for c in value))
    return str(round(value, 4))
