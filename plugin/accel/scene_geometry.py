"""The shapes of a Mitsuba scene as the accelerator takes them: which shapes are
meshes, which are analytic shapes intersected by Mitsuba's own routine, which are only
traced while still (naming the shape when one is refused), and the world-space
triangles of a set of meshes in one buffer, with each triangle's mesh and in-mesh
index."""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from hlbvh.kernels.arrays import concat

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


def describe_shape(shape) -> str:
    """The shape as every message names it: its id and its class."""
    return f"shape {shape.id()!r} ({shape.class_name()})"


class ShapeError(ValueError):
    """A shape of the scene that hlbvh cannot take, in one line naming it.

    Attributes:
        shape: the shape as the message names it (its id and class).
        reason: the message's sentence about the shape alone.
        accel: the ``accel`` option that renders the scene instead (``"native"``), or
            ``None`` where another accelerator would not help; the message ends with
            that advice.
    """

    def __init__(self, shape: str, reason: str, accel: str | None = None):
        advice = f" Use accel={accel!r} for this scene." if accel else ""
        super().__init__(reason + advice)
        self.shape, self.reason, self.accel = shape, reason, accel

    def __reduce__(self):
        """Pickled by its fields (a Dask worker's error reaches the client whole)."""
        return type(self), (self.shape, self.reason, self.accel)


def scene_shapes(shapes, static: str = "hlbvh") -> tuple[tuple, list, tuple]:
    """Sort a scene's shapes into meshes, analytic shapes and the rest.

    Args:
        shapes: ``scene.shapes()``.
        static: the accelerator's ``static`` option. With ``"native"`` the other shapes
            (instances, curves, SDF grids, ellipsoids, ...) are welcome while they stay
            still: Mitsuba's own accelerator traces them. With ``"hlbvh"`` they are
            refused.
    Returns:
        ``(mesh indices, analytic, other indices)``: the indices of the meshes in
        ``shapes``, ``(index, shape)`` of every analytic shape, and the indices of the
        other shapes.
    Raises:
        ShapeError: naming the shape, for a mesh without triangles, and with
            ``static="hlbvh"`` for any shape type our accelerator does not intersect
            (then with ``accel="native"``).
    """
    meshes, analytic, others = [], [], []
    for index, shape in enumerate(shapes):
        if shape.is_mesh():
            if shape.face_count() == 0:
                name = describe_shape(shape)
                raise ShapeError(name, f"{name} has no triangles: it would silently be "
                                 "missing from the image; give it faces or remove it from "
                                 "the scene")
            meshes.append(index)
        elif shape.class_name() in _ANALYTIC:
            analytic.append((index, shape))
        elif static == "native":
            others.append(index)
        else:
            name = describe_shape(shape)
            raise ShapeError(
                name, f"{name}: with static='hlbvh', hlbvh intersects meshes and the "
                f"analytic shapes {', '.join(s.lower() for s in _ANALYTIC)}; instances, "
                "curves, SDF grids and ellipsoids are traced only with static='native' "
                "(the default) while they do not move.", accel="native")
    return tuple(meshes), analytic, tuple(others)


def unmovable_error(shape) -> ValueError:
    """The error for a shape that moved but that hlbvh cannot trace as a moving shape
    (anything but a mesh or an analytic shape: an instance's ``to_world``, a curve's
    control points, an SDF grid): naming it and what to do."""
    return ValueError(
        f"{describe_shape(shape)} moved: hlbvh traces moving meshes and the analytic shapes "
        f"{', '.join(s.lower() for s in _ANALYTIC)}, not moving {shape.class_name()} shapes; "
        "keep it still, or render this scene with accel='native'"
    )


def collect_geometry(shapes, indices=None) -> SceneGeometry:
    """World-space triangles of meshes among ``shapes`` in one vertex/face buffer.

    Args:
        shapes: ``scene.shapes()``; the indices stored refer to this list.
        indices: which meshes (indices into ``shapes``); by default every mesh, after
            :func:`scene_shapes` checked the scene.

    A Python loop over the meshes (a few), none over triangles.
    """
    if indices is None:
        indices = scene_shapes(shapes, "native")[0]
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
    geometry = SceneGeometry(concat(vertices), concat(faces), concat(prim_shape),
                             concat(prim_local))
    dr.eval(geometry.vertices, geometry.faces, geometry.prim_shape, geometry.prim_local)
    return geometry


def check_finite(shapes, indices) -> None:
    """Refuse meshes among ``shapes[i]`` (``i`` in ``indices``) whose vertex positions
    are not all finite, naming the first: Mitsuba's own accelerator would trace them
    without a word, and render a wrong image. One reduction per mesh, evaluated
    together."""
    meshes = [i for i in indices if shapes[i].is_mesh()]
    finite = [dr.all(dr.isfinite(shapes[i].vertex_positions_buffer()), axis=None) for i in meshes]
    if finite:
        dr.eval(*finite)
    for i, ok in zip(meshes, finite):
        if not ok[0]:
            raise _non_finite(shapes[i])


def _non_finite(mesh) -> ValueError:
    return ValueError(f"{describe_shape(mesh)} has non-finite (NaN or infinite) vertex positions: "
                      "fix the mesh or the parameters written into it")


def named_build_error(shapes, indices, error: ValueError) -> ValueError:
    """A build or refit of the meshes ``indices`` failed with ``error``: the same
    error, naming the mesh with non-finite positions when there is one."""
    for index in indices:
        mesh = shapes[index]
        if not dr.all(dr.isfinite(mesh.vertex_positions_buffer()), axis=None):
            return _non_finite(mesh)
    names = ", ".join(repr(shapes[i].id()) for i in indices)
    return ValueError(f"building the HLBVH of the meshes {names} failed: {error}")


def declared_indices(shapes, ids: tuple) -> tuple:
    """Indices into ``shapes`` of the shapes whose ids are ``ids`` (the option
    ``moving``; every shape of an id); ValueError naming the ids that name no shape."""
    wanted = set(ids)
    found = [i for i, shape in enumerate(shapes) if shape.id() in wanted]
    unknown = sorted(set(ids) - {shapes[i].id() for i in found})
    if unknown:
        raise ValueError(f"moving={list(ids)}: no shape of the scene has the id(s) {unknown} "
                         f"(its shapes: {sorted({s.id() for s in shapes})})")
    return tuple(found)
