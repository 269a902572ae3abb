"""The materials of a USD stage's meshes as Mitsuba BSDFs: ``UsdPreviewSurface``
(diffuse colour, a diffuse texture, roughness, metallic, opacity, emission),
``displayColor`` as the fallback, grey otherwise; a mixin of
:class:`hlbvh.scenes.usd.UsdScene`."""

from __future__ import annotations

import numpy as np

from .usd_prims import (GREY, PREVIEW_DEFAULTS, UsdGeom, UsdShade, _array, _two_sided,
                        _uv_texture)


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
        """``(bsdf, emission, colors, st)``: the mesh's BSDF dict, emitted radiance
        (``None``: none), the colour attribute its BSDF reads (``None``: none; see
        :meth:`_display_color`) and the primvar of texture coordinates a bitmap of it
        reads (``None``: none; ``textures=False``: the textured inputs' authored values
        instead)."""
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
            color = self._display_color(prim, mesh, time, point_count, source_faces)
            if isinstance(color, tuple) and isinstance(color[0], str):
                reflectance = {"type": "mesh_attribute", "name": color[0]}
                colors = color
            else:
                reflectance, colors = {"type": "rgb", "value": list(color)}, None
            bsdf = {"type": "diffuse", "reflectance": reflectance}
            return (_two_sided(bsdf) if double_sided else bsdf), None, colors, None
        values, textured = {}, []
        for name, default in PREVIEW_DEFAULTS.items():
            shader_input = shader.GetInput(name)
            value = shader_input.Get(time) if shader_input else None
            if shader_input and shader_input.HasConnectedSource():
                textured.append(name)
            values[name] = default if value is None else (
                tuple(float(v) for v in value) if isinstance(default, tuple) else float(value))
        base_color = {"type": "rgb", "value": list(values["diffuseColor"])}
        st = None
        if textures and "diffuseColor" in textured:
            bitmap = _uv_texture(shader.GetInput("diffuseColor"), time)
            if bitmap is not None:
                base_color, st = bitmap
                textured.remove("diffuseColor")
        if textured:
            self._warn_once(f"{self._where}: {material.GetPath()}: textured inputs "
                            f"({', '.join(textured)}) are not read; their authored values "
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
        emission = values["emissiveColor"]
        return bsdf, (emission if any(c > 0 for c in emission) else None), None, st

    def _display_color(self, prim, mesh, time, point_count: int, source_faces):
        """The ``displayColor`` primvar: one colour ``(r, g, b)`` when it is constant
        (grey without one); per point (``vertex``/``varying``) or per face
        (``uniform``) as a Mitsuba mesh attribute ``("vertex_color", (V, 3))`` or
        ``("face_color", (F, 3))`` (per triangle); other interpolations, or a mesh whose
        topology is time-sampled (``source_faces`` ``None``), get the mean colour
        (said)."""
        primvar = mesh.GetDisplayColorPrimvar()
        value = primvar.ComputeFlattened(time) if primvar and primvar.HasValue() else None
        if value is None or len(value) == 0:
            return GREY
        colors = _array(value, 3)
        if len(colors) == 1 or np.all(colors == colors[0]):
            return tuple(float(c) for c in colors[0])
        interpolation = primvar.GetInterpolation()
        if interpolation in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying) \
                and len(colors) == point_count:
            return ("vertex_color", colors)
        if interpolation == UsdGeom.Tokens.uniform and source_faces is not None \
                and len(source_faces) and len(colors) > int(source_faces.max()):
            return ("face_color", colors[source_faces])
        self._warn(f"{self._where}: {prim.GetPath()}: displayColor of interpolation "
                   f"{interpolation!r} varies over the mesh; its mean colour is used")
        return tuple(float(c) for c in colors.mean(axis=0))
