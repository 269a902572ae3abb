"""The materials of a USD stage's meshes as Mitsuba BSDFs: ``UsdPreviewSurface``
(diffuse colour, a diffuse texture, roughness, metallic, opacity, emission),
``displayColor`` as the fallback, grey otherwise; a mixin of
:class:`hlbvh.scenes.usd.UsdScene`.

``UsdPreviewSurface`` bound with ``UsdShade.MaterialBindingAPI``: diffuseColor,
roughness, metallic to ``principled``; opacity below 1 through a ``mask``
(``opacityThreshold`` makes it a cutout); emissiveColor to an ``area`` emitter on
the mesh. A diffuseColor, emissiveColor, opacity or normal read from a
``UsdUVTexture`` becomes a ``bitmap`` over the mesh's texture coordinates (the
``UsdPrimvarReader_float2``'s primvar, ``st`` by default; per point, or faceVarying
with the points split where their uv differ), through the ``UsdTransform2d`` shaders
between them as the bitmap's ``to_uv``; the image rewritten where Mitsuba would read
it otherwise than the input needs (scale and bias, a ``raw`` colour space, one
channel for opacity, cut at ``opacityThreshold``). A textured opacity becomes the
``mask``'s opacity; a textured normal a ``normalmap`` around the BSDF, in Mitsuba's
shading frame: tangent along dP/ds, bitangent the normal cross the tangent, which is
along +t where the st layout is not mirrored (UsdPreviewSurface's frame: tangent +s,
bitangent +t; a mirrored uv island's green channel reads flipped). An input read
from a primvar reader (:data:`READERS`) takes that primvar as ``displayColor`` is
read: one value, or per point or face a Mitsuba mesh attribute (``vertex_color``/``face_color`` for diffuseColor, ``vertex_roughness``,
... for the others); emissiveColor, and opacity cut by ``opacityThreshold``, take
its mean when it varies (said: Mitsuba's area emitter samples one radiance or a
texture, not a mesh attribute, and a cutout is not an interpolated opacity). Other
connected inputs keep their authored value (said once per material, naming them).
Without a material the ``displayColor`` primvar gives a diffuse colour, else grey. So
does a material whose surface is MaterialX only (``outputs:mtlx:surface``; a material
with ``outputs:surface`` too renders that UsdPreviewSurface), and a binding to a
material of a referenced ``.mtlx`` file, which does not compose: usd-core reads no
MaterialX (said, naming the material and the file).
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import mitsuba as mi
import numpy as np

from .prims import (GREY, PREVIEW_DEFAULTS, UsdGeom, UsdShade, _array, _checked,
                    _connected_shader, _input_value, _interface_value, _local_asset,
                    _unreadable_image, _written_once)

#: UsdPreviewSurface inputs whose ``UsdUVTexture`` becomes a Mitsuba ``bitmap``, and
#: what each reads of the image (see :func:`_texture_image`).
TEXTURED_INPUTS = {"diffuseColor": "color", "emissiveColor": "color",
                   "opacity": "opacity", "normal": "normal"}

#: UsdUVTexture's wrap modes as Mitsuba's bitmap's (``black`` clamps).
_WRAPS = {"repeat": "repeat", "mirror": "mirror", "clamp": "clamp", "black": "clamp",
          "useMetadata": "repeat"}

#: st to Mitsuba's uv, ``(s, 1 - t)``, as a homogeneous 3x3 matrix (its own inverse).
_ST_TO_UV = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 1.0], [0.0, 0.0, 1.0]])

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

    def _material(self, prim, mesh, time, point_count: int,
                  source_faces, textures: bool = True) -> tuple:
        """``(bsdf, emission, attributes, st)``: the mesh's BSDF dict, its emission
        (``None``: none; an RGB radiance, or a bitmap's dict for a textured
        emissiveColor), the Mitsuba mesh attributes its BSDF reads (``{name: (N, width)
        values}``, see :meth:`_primvar`) and the primvar of texture coordinates its
        bitmaps read (``None``: none; ``textures=False``: no bitmaps, see
        :meth:`_unread_input`).

        Inputs connected to a shader: diffuseColor, emissiveColor, opacity and
        normal to a ``UsdUVTexture`` read its file (:func:`_uv_texture`); an input
        of :data:`READERS` to its primvar reader reads that primvar
        (:meth:`_reader_value`); others keep their authored value (said, naming
        each).

        Raises:
            ValueError: an input that is not finite, or a negative colour, naming the
                shader and the input.
        """
        material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
        shader = None
        if not material:
            self._unbuilt.update(_bound_paths(prim))
        else:
            source = material.ComputeSurfaceSource()
            shader = source[0] if source and source[0] else None
            materialx = material.GetSurfaceOutput("mtlx")
            if shader is None and materialx and materialx.HasConnectedSource():
                kind = _connected_shader(materialx)
                self._warn_once(f"{self._where}: {material.GetPath()}: its surface is "
                                f"MaterialX only (outputs:mtlx:surface, "
                                f"{kind.GetIdAttr().Get() if kind else 'a connection'!s}), "
                                f"whose definitions (.mtlx) usd-core does not read, and it "
                                f"has no UsdPreviewSurface (outputs:surface) to fall back "
                                f"on; its meshes render their displayColor, else grey")
            if shader is not None and shader.GetIdAttr().Get() != "UsdPreviewSurface":
                self._warn(f"{self._where}: {material.GetPath()}: surface shader "
                           f"{shader.GetIdAttr().Get()!r} is not a UsdPreviewSurface; "
                           f"{prim.GetPath()} renders grey")
                shader = None
        if shader is None:
            color = self._primvar(prim, mesh, time, point_count, source_faces) or GREY
            reflectance, attributes = _texture_of(color)
            bsdf = {"type": "diffuse", "reflectance": reflectance}
            return bsdf, None, attributes, None
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
        normal = shader.GetInput("normal")
        if normal and normal.HasConnectedSource():
            connected.append("normal")
            values["normal"] = None  # flat unless its texture is read
        mapped, attributes, st = {}, {}, None
        dropped = []
        for name in connected:
            source = _connected_shader(shader.GetInput(name))
            kind = str(source.GetIdAttr().Get()) if source else ""
            if name in TEXTURED_INPUTS and kind == "UsdUVTexture":
                bitmap, wanted, why = _uv_texture(
                    source, _connected_output(shader.GetInput(name)), TEXTURED_INPUTS[name],
                    time, self._where, values["opacityThreshold"] if name == "opacity"
                    else 0.0) if textures else (None, None, "is not mapped")
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
        if "normal" in mapped:
            bsdf = {"type": "normalmap", "normalmap": mapped["normal"], "bsdf": bsdf}
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
        the others (``None``, flat, for normal). Opacity takes the fallback's alpha."""
        fallback = texture.GetInput("fallback")
        if fallback and fallback.HasAuthoredValue() and name == "opacity":
            value = float(np.ravel(fallback.Get(time))[-1])
        elif fallback and fallback.HasAuthoredValue() and name != "normal":
            value = tuple(float(v) for v in fallback.Get(time))[:3]
        elif name == "emissiveColor":
            value = (0.0, 0.0, 0.0)
        else:
            value = authored
        if why != "is not mapped":
            self._warn_once(f"{self._where}: {material.GetPath()}: inputs:{name}'s texture "
                            f"{texture.GetPath()} {why}; {name} is "
                            f"{'flat' if value is None else _shown(value)}")
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


def _bound_paths(prim) -> list[str]:
    """The material paths ``prim``'s direct ``material:binding``, or the nearest
    ancestor's, targets (the binding that did not compute a material)."""
    while prim and not prim.IsPseudoRoot():
        targets = UsdShade.MaterialBindingAPI(prim).GetDirectBindingRel().GetTargets()
        if targets:
            return [str(path) for path in targets]
        prim = prim.GetParent()
    return []


def _connected_output(shader_input) -> str:
    """The name of the shader output an input is connected to (``rgb``, ``a``, ...),
    followed as :func:`_connected_shader` follows it."""
    outputs = shader_input.GetValueProducingAttributes(shaderOutputsOnly=True)
    return UsdShade.Output(outputs[0]).GetBaseName() if outputs else ""


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


def _st_transform(texture, time, where: str) -> tuple:
    """``(3x3 matrix, primvar reader or None)``: the ``UsdTransform2d`` shaders a
    ``UsdUVTexture``'s ``st`` is read through, composed as one homogeneous matrix on
    st (each ``result = in * scale * rotate + translation``, the rotation
    counter-clockwise in degrees, as UsdPreviewSurface's specification defines it;
    identity without one), and the shader that feeds the innermost one's ``in``.

    Raises:
        ValueError: a scale, rotation or translation that is not finite, naming the
            stage (``where``), the shader and the input.
    """
    matrix = np.eye(3)
    shader, seen = _connected_shader(texture.GetInput("st")), set()
    while shader is not None and shader.GetIdAttr().Get() == "UsdTransform2d" \
            and shader.GetPath() not in seen:
        seen.add(shader.GetPath())
        inputs = {}
        for key, default in (("scale", (1.0, 1.0)), ("rotation", 0.0),
                             ("translation", (0.0, 0.0))):
            value = _input_value(shader.GetInput(key), time)
            inputs[key] = _checked(f"{where}: {shader.GetPath()}: inputs:{key}", np.ravel(
                np.asarray(default if value is None else value, dtype=np.float64)))
        angle = math.radians(float(inputs["rotation"][0]))
        cos, sin = math.cos(angle), math.sin(angle)
        (sx, sy), (tx, ty) = inputs["scale"][:2], inputs["translation"][:2]
        matrix = matrix @ np.array([[cos * sx, -sin * sy, tx], [sin * sx, cos * sy, ty],
                                    [0.0, 0.0, 1.0]])
        shader = _connected_shader(shader.GetInput("in"))
    return matrix, shader


def _uv_texture(texture, output: str, reads: str, time, where: str,
                threshold: float = 0.0) -> tuple:
    """``(bitmap texture dict or None, st primvar name, why not)`` of a
    ``UsdUVTexture`` shader read through its output ``output`` (``rgb``, ``r``, ...,
    ``a``) by an input that ``reads`` ``"color"``, ``"opacity"`` or ``"normal"``: its
    file as a Mitsuba ``bitmap`` over the primvar its ``st`` is read from (a
    ``UsdPrimvarReader_float2``'s, ``st`` by default), the ``UsdTransform2d`` between
    them as the bitmap's ``to_uv`` (on Mitsuba's uv, :data:`_ST_TO_UV`), the image
    rewritten by :func:`_texture_image` unless Mitsuba reads it as the input needs it
    (a colour without scale, bias or ``raw`` colour space). An opacity cut at
    ``threshold`` (> 0) is looked up nearest-texel: the cut is made per texel, where
    UsdPreviewSurface cuts the filtered value, which differ within a texel of the
    edge. No bitmap when the file is not given, does not resolve, or is not an image
    Mitsuba reads (``why not`` says which).

    Raises:
        ValueError: a scale, bias or st transform that is not finite, naming the stage
            (``where``), the shader and the input.
    """
    asset = _input_value(texture.GetInput("file"), time)
    if asset is None or not asset.path:
        return None, None, "has no file"
    if not asset.resolvedPath:
        return None, None, f"{asset.path!r} does not resolve"
    filename = _local_asset(asset.resolvedPath)
    problem = "cannot be read from its package" if filename is None \
        else _unreadable_image(filename)
    if problem is not None:
        return None, None, f"{asset.path!r} {problem}"
    factors = []
    for key, identity in (("scale", 1.0), ("bias", 0.0)):
        value = _input_value(texture.GetInput(key), time)
        value = (identity,) * 4 if value is None else tuple(float(v) for v in _checked(
            f"{where}: {texture.GetPath()}: inputs:{key}", np.ravel(value)))
        factors.append((value + (identity,) * 4)[:4])
    space = str(_input_value(texture.GetInput("sourceColorSpace"), time) or "auto")
    channel = "rgba".index(output) if output in ("r", "g", "b", "a") else 0
    if reads != "color" or space == "raw" or factors != [(1.0,) * 4, (0.0,) * 4]:
        filename = _texture_image(filename, reads, channel, *factors, space == "raw",
                                  threshold)
    matrix, reader = _st_transform(texture, time, where)
    name = str((_input_value(reader.GetInput("varname"), time) if reader is not None
                else None) or "st")
    wrap = texture.GetInput("wrapS")
    wrap = str(wrap.Get(time)) if wrap and wrap.Get(time) else "useMetadata"
    bitmap = {"type": "bitmap", "filename": filename, "wrap_mode": _WRAPS.get(wrap, "repeat")}
    if not np.array_equal(matrix, np.eye(3)):
        bitmap["to_uv"] = mi.ScalarTransform3f(_ST_TO_UV @ matrix @ _ST_TO_UV)
    if reads == "opacity" and threshold > 0:
        bitmap["filter_type"] = "nearest"
    return bitmap, name, None


def _texture_image(filename: str, reads: str, channel: int, scale: tuple, bias: tuple,
                   raw: bool, threshold: float) -> str:
    """The image at ``filename`` as a ``UsdUVTexture`` outputs it to an input that
    ``reads`` it, written once as an OpenEXR to ``hlbvh-textures/<SHA-256 of the
    image's bytes and these arguments>/`` in the temporary folder (Mitsuba's bitmap
    has no scale or bias of its own; :func:`_written_once`). The pixels are linear
    RGBA (``raw``: the file's values as they are, the ``raw`` source colour space;
    else decoded where the file is sRGB; alpha 1 where it has none) times ``scale``
    plus ``bias`` (4 values each), then: ``"color"``: RGB, below 0 made 0 (no colour
    holds it); ``"opacity"``: the one channel ``channel`` clamped to [0, 1], cut to 0
    or 1 at ``threshold`` where it is above 0; ``"normal"``: the tangent-space normal
    in [-1, 1] stored as ``(n + 1) / 2``, which Mitsuba's ``normalmap`` maps back."""
    key = hashlib.sha256(Path(filename).read_bytes() + repr(
        (reads, channel, scale, bias, raw, threshold)).encode())

    def write(path: str) -> None:
        bitmap = mi.Bitmap(filename)
        if raw:
            bitmap.set_srgb_gamma(False)
        pixels = np.array(bitmap.convert(mi.Bitmap.PixelFormat.RGBA, mi.Struct.Type.Float32,
                                         srgb_gamma=False)) * np.array(scale) + np.array(bias)
        if reads == "color":
            pixels = np.maximum(pixels[..., :3], 0.0)
        elif reads == "opacity":
            pixels = np.clip(pixels[..., channel:channel + 1], 0.0, 1.0)
            if threshold > 0:
                pixels = (pixels >= threshold).astype(np.float32)
        else:
            pixels = (pixels[..., :3] + 1.0) / 2.0
        mi.Bitmap(np.ascontiguousarray(pixels, dtype=np.float32)).write(path)

    return _written_once("hlbvh-textures", key.hexdigest(), f"{Path(filename).stem}.exr",
                         write)
