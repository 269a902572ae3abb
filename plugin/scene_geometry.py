"""The meshes of a Mitsuba scene as the builder takes them: which shapes are meshes,
which are analytic shapes intersected by Mitsuba's own routine, which are refused
(naming the shape), and the world-space triangles of a set of meshes in one buffer,
with each triangle's mesh and in-mesh index."""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

#: Analytic shape types intersected by Mitsuba's own per-shape routine.
_ANALYTIC = ("Sphere", "Disk", "Cylinder")


@dataclass
class SceneGeometry:
    """The world-space triangles of some meshes of a scene, on the scene's device.

    Attributes:
        vertices: Float (3·V): the meshes' positions, concatenated.
        faces: UInt32 (3·F): their triangles, indices into ``vertices`` (each mesh's
            indices offset by the vertices before it).
        prim_shape: UInt32 (F): for each triangle, the index of its mesh in
            ``scene.shapes()``.
        prim_local: UInt32 (F): for each triangle, its index inside its mesh.
    """

    vertices: mi.Float
    faces: mi.UInt32
    prim_shape: mi.UInt32
    prim_local: mi.UInt32

    @property
    def prim_count(self) -> int:
        return len(self.prim_shape)


def _describe(shape) -> str:
    return f"shape {shape.id()!r} ({shape.class_name()})"


def scene_shapes(shapes) -> tuple[tuple, list]:
    """Sort a scene's shapes into meshes and analytic shapes.

    Args:
        shapes: ``scene.shapes()``.
    Returns:
        ``(mesh indices, analytic)``: the indices of the meshes in ``shapes``, and
        ``(index, shape)`` of every analytic shape.
    Raises:
        ValueError: naming the shape, for an instance, a curve, an SDF grid, ellipsoids
            or any other shape type this accelerator does not intersect, and for a
            mesh without triangles.
    """
    meshes, analytic = [], []
    for index, shape in enumerate(shapes):
        if shape.is_mesh():
            if shape.face_count() == 0:
                raise ValueError(
                    f"{_describe(shape)} has no triangles: it would silently be missing "
                    "from the image; give it faces or remove it from the scene"
                )
            meshes.append(index)
        elif shape.class_name() in _ANALYTIC:
            analytic.append((index, shape))
        else:
            raise ValueError(
                f"{_describe(shape)}: hlbvh intersects meshes and the analytic shapes "
                f"{', '.join(s.lower() for s in _ANALYTIC)}; instances, shape groups, "
                "curves, SDF grids and ellipsoids are not supported yet. Use "
                "accel='native' for this scene."
            )
    return tuple(meshes), analytic


def collect_geometry(shapes, indices=None) -> SceneGeometry:
    """World-space triangles of meshes among ``shapes`` in one vertex/face buffer.

    Args:
        shapes: ``scene.shapes()``; the indices stored refer to this list.
        indices: which meshes (indices into ``shapes``); by default every mesh, after
            :func:`scene_shapes` checked the scene.

    A Python loop over the meshes (a few), none over triangles.
    """
    if indices is None:
        indices = scene_shapes(shapes)[0]
    vertices, faces, prim_shape, prim_local = [], [], [], []
    vertex_base = 0
    for index in indices:
        mesh = shapes[index]
        face_count = mesh.face_count()
        vertices.append(mesh.vertex_positions_buffer())
        # (the first mesh's indices as they are: no pass over them)
        faces.append(mesh.faces_buffer() + dr.opaque(mi.UInt32, vertex_base) if vertex_base
                     else mesh.faces_buffer())
        prim_shape.append(dr.full(mi.UInt32, index, face_count))
        prim_local.append(dr.arange(mi.UInt32, face_count))
        vertex_base += mesh.vertex_count()
    if not indices:
        return SceneGeometry(mi.Float(), mi.UInt32(), mi.UInt32(), mi.UInt32())
    geometry = SceneGeometry(_concat(vertices), _concat(faces), _concat(prim_shape),
                             _concat(prim_local))
    dr.eval(geometry.vertices, geometry.faces, geometry.prim_shape, geometry.prim_local)
    return geometry


def _concat(arrays):
    """The arrays end to end (one array is returned as it is: no copy)."""
    return arrays[0] if len(arrays) == 1 else dr.concat(arrays)


def mesh_buffers(shapes, indices) -> dict:
    """``{index: (vertex buffer, face buffer)}`` of the meshes ``shapes[i]``: the arrays
    themselves, whose JIT variable indices tell whether a mesh got new buffers. Held,
    they keep their indices from being given to other arrays."""
    return {i: (shapes[i].vertex_positions_buffer(), shapes[i].faces_buffer()) for i in indices}


def _named_error(shapes, indices, error: ValueError) -> ValueError:
    """A build or refit of the meshes ``indices`` failed with ``error``: the same
    error, naming the mesh with non-finite positions when there is one."""
    for index in indices:
        mesh = shapes[index]
        if not dr.all(dr.isfinite(mesh.vertex_positions_buffer()), axis=None):
            return ValueError(
                f"{_describe(mesh)} has non-finite (NaN or infinite) vertex positions: "
                "fix the mesh or the parameters written into it"
            )
    names = ", ".join(repr(shapes[i].id()) for i in indices)
    return ValueError(f"building the HLBVH of the meshes {names} failed: {error}")
