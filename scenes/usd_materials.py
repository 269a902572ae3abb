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
their uv differ); a diffuseColor from a ``UsdPrimvarReader_float3`` reads its
primvar as ``displayColor`` is read; other connected inputs keep their authored
value (said once per material, naming them). Without a material the
``displayColor`` primvar gives a diffuse colour: per point or per face as a Mitsuba
mesh attribute (``vertex_color``, ``face_color``), its mean for other interpolations
(said), else grey.
"""

from __future__ import annotations

import numpy as np

from .usd_prims import (GREY, PREVIEW_DEFAULTS, UsdGeom, UsdShade, _array, _checked,
                        _connected_shader, _input_value, _interface_value, _two_sided,
                        _uv_texture)

#: UsdPreviewSurface inputs whose ``UsdUVTexture`` becomes a Mitsuba ``bitmap``.
TEXTURED_INPUTS = ("diffuseColor", "emissiveColor")


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
        """``(bsdf, emission, colors, st)``: the mesh's BSDF dict, its emission
        (``None``: none; an RGB radiance, or a bitmap's dict for a textured
        emissiveColor), the colour attribute its BSDF reads (``None``: none; see
        :meth:`_display_color`) and the primvar of texture coordinates its bitmaps
        read (``None``: none; ``textures=False``: no bitmaps, see
        :meth:`_unread_input`).

        Inputs connected to a shader: diffuseColor and emissiveColor to a
        ``UsdUVTexture`` read its file; diffuseColor to a ``UsdPrimvarReader_float3``
        reads that primvar per point or face; others keep their authored value (said,
        naming each).

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
            color = self._display_color(prim, mesh, time, point_count, source_faces) or GREY
            reflectance, colors = self._reflectance(color)
            bsdf = {"type": "diffuse", "reflectance": reflectance}
            return (_two_sided(bsdf) if double_sided else bsdf), None, colors, None
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
        base_color, colors, st = {"type": "rgb", "value": list(values["diffuseColor"])}, None, None
        emission = values["emissiveColor"] if any(c > 0 for c in values["emissiveColor"]) \
            else None
        dropped = []
        for name in connected:
            source = _connected_shader(shader.GetInput(name))
            kind = str(source.GetIdAttr().Get()) if source else ""
            if name in TEXTURED_INPUTS and kind == "UsdUVTexture":
                bitmap, wanted, why = _uv_texture(source, time) if textures else \
                    (None, None, "is not mapped")
                if bitmap is None:
                    value = self._unread_input(material, name, values[name], source, why, time)
                elif st not in (None, wanted):
                    value = self._unread_input(material, name, values[name], source,
                                               f"is read over {wanted!r}, not {st!r}", time)
                else:
                    value, st = bitmap, wanted
                if name == "diffuseColor":
                    base_color = value if isinstance(value, dict) else \
                        {"type": "rgb", "value": list(value)}
                else:
                    emission = value if isinstance(value, dict) or any(
                        c > 0 for c in value) else None
            elif name == "diffuseColor" and kind.startswith("UsdPrimvarReader_float"):
                varname = str(_input_value(source.GetInput("varname"), time) or "")
                color = self._display_color(prim, mesh, time, point_count, source_faces,
                                            varname) if varname else None
                if color is None:
                    fallback = source.GetInput("fallback")
                    color = (tuple(float(v) for v in fallback.Get(time))[:3]
                             if fallback and fallback.Get(time) is not None
                             else values[name])
                    self._warn_once(f"{self._where}: {prim.GetPath()}: has no primvar "
                                    f"{varname!r} that {source.GetPath()} reads; "
                                    f"diffuseColor is {tuple(round(c, 4) for c in color)}")
                base_color, colors = self._reflectance(color)
            else:
                dropped.append(f"{name} ({kind or 'a connection'})")
        if dropped:
            self._warn_once(f"{self._where}: {material.GetPath()}: connected inputs "
                            f"{', '.join(dropped)} are not read; their authored values "
                            f"are used")
        bsdf = {"type": "principled",
                "base_color": base_color,
                "roughness": min(max(values["roughness"], 0.0), 1.0),
                "metallic": min(max(values["metallic"], 0.0), 1.0)}
        if double_sided:
            bsdf = _two_sided(bsdf)
        opacity = min(max(values["opacity"], 0.0), 1.0)
        if values["opacityThreshold"] > 0:
            opacity = 1.0 if opacity >= values["opacityThreshold"] else 0.0
        if opacity < 1:
            bsdf = {"type": "mask", "opacity": opacity, "bsdf": bsdf}
        return bsdf, emission, colors, st

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

    @staticmethod
    def _reflectance(color) -> tuple:
        """``(texture dict, colors)`` of :meth:`_display_color`'s colour: an ``rgb``,
        or a ``mesh_attribute`` with the attribute the mesh then holds."""
        if isinstance(color, tuple) and isinstance(color[0], str):
            return {"type": "mesh_attribute", "name": color[0]}, color
        return {"type": "rgb", "value": list(color)}, None

    def _display_color(self, prim, mesh, time, point_count: int, source_faces,
                       name: str = "displayColor"):
        """The colour primvar ``name``: one colour ``(r, g, b)`` when it is constant
        (``None`` without one, or when it does not hold colours); per point (``vertex``/``varying``) or per face
        (``uniform``) as a Mitsuba mesh attribute ``("vertex_color", (V, 3))`` or
        ``("face_color", (F, 3))`` (per triangle); other interpolations, or a mesh whose
        topology is time-sampled (``source_faces`` ``None``), get the mean colour
        (said)."""
        primvar = UsdGeom.PrimvarsAPI(mesh).GetPrimvar(name)
        value = primvar.ComputeFlattened(time) if primvar and primvar.HasValue() else None
        if value is None or len(value) == 0 or np.ndim(value[0]) != 1 or len(value[0]) != 3:
            return None  # none, or not of colours
        colors = _checked(f"{self._where}: {prim.GetPath()}: primvars:{name}",
                          _array(value, 3), least=0)
        if len(colors) == 1 or np.all(colors == colors[0]):
            return tuple(float(c) for c in colors[0])
        interpolation = primvar.GetInterpolation()
        if interpolation in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying) \
                and len(colors) == point_count:
            return ("vertex_color", colors)
        if interpolation == UsdGeom.Tokens.uniform and source_faces is not None \
                and len(source_faces) and len(colors) > int(source_faces.max()):
            return ("face_color", colors[source_faces])
        self._warn(f"{self._where}: {prim.GetPath()}: {name} of interpolation "
                   f"{interpolation!r} varies over the mesh; its mean colour is used")
        return tuple(float(c) for c in colors.mean(axis=0))
