"""The meshes of a USD stage (``UsdGeom.Mesh``), read in named steps: what the prim
holds (:func:`read_mesh`), its shading normals (:func:`shading_normals`), its parts as
the Mitsuba meshes they become (:func:`mesh_parts`), and its world-space geometry at a
frame (:func:`world_geometry`).

Only what renders: visible prims of purpose ``default`` or ``render``, traversed through
instance proxies. Each mesh is handed to Mitsuba in world space, its points transformed
through every ancestor's transform at each time code; polygons are triangulated as fans
(exact for convex polygons, as DCC exports are), holes dropped. A subdivision scheme
other than ``none`` renders the control cage with smooth vertex normals (said once per
stage). Authored vertex normals are used on meshes that do not move (a moving mesh's
normals are recomputed every frame by :func:`hlbvh.scenes.apply_frame`);
every mesh's BSDF is seen from both sides, ``doubleSided`` or not, as Storm draws it
(:func:`~.prims._two_sided`).

Motion, from the time samples: *deforming* (its points are time-sampled, or moved by
time-sampled ``velocities``), *rigid* (only a transform, its own or an ancestor's, is),
*static* (nothing is). Points are pxr's at each time code (:func:`points_at`):
interpolated between time samples, and where ``velocities`` (and ``accelerations``) are
authored, extrapolated from the sample at or before the frame being rendered, as
``UsdGeomPointBased.ComputePointsAtTime`` computes them for renderers.

Per-face materials: a mesh with ``materialBind`` GeomSubsets becomes one Mitsuba mesh
per subset (id from the subset's path, its faces, its bound material) plus one for the
faces no subset takes, each holding all the mesh's points and moving with it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..animated import FrameGeometry
from .prims import (UsdGeom, _Mesh, _Stats, _array, _has_normals, _transform_varies,
                    _triangulate, _vertex_normals, _visibility_varies)
from .skinning import skel_binding


@dataclass
class MeshPrim:
    """What a ``UsdGeom.Mesh`` prim holds at the first frame, as :func:`read_mesh`
    found it."""

    mesh: UsdGeom.Mesh
    path: object  # Sdf.Path
    motion: str  # "static", "deforming" or "rigid"
    topology_varies: bool
    points: np.ndarray  # (V, 3) float64, the prim's own space
    faces: np.ndarray  # (F, 3) triangles
    source_faces: np.ndarray  # (F,) the polygon of each triangle
    corners: np.ndarray  # each triangle corner's face-vertex index
    polygon_count: int
    scheme: object  # the subdivision scheme token, or None
    normals: np.ndarray | None  # (V, 3) authored vertex normals


def check_finite(where: str, path, what: str, values: np.ndarray, at: str) -> None:
    """A ValueError naming the stage (``where``), the prim, ``what`` (``"points"``,
    ``(V, 3)``, or ``"transform"``, a 4x4) and ``at`` when ``values`` holds a NaN or an
    infinity."""
    bad = ~np.isfinite(values)
    if not bad.any():
        return
    if what == "points":
        first = int(np.flatnonzero(bad.any(axis=1))[0])
        raise ValueError(f"{where}: {path}: its points at {at} are not finite "
                         f"(point {first} of {len(values)})")
    raise ValueError(f"{where}: {path}: its {what} at {at} is not finite")


def renders(imageable, time) -> bool:
    """Whether an imageable prim (and so its subtree) renders: visible at ``time`` (the
    first frame's), of purpose default or render."""
    if imageable.ComputeVisibility(time) == UsdGeom.Tokens.invisible:
        return False
    purpose = imageable.ComputePurpose()
    return purpose in (UsdGeom.Tokens.default_, UsdGeom.Tokens.render)


def moves_by_velocity(mesh) -> bool:
    """Whether pxr moves the mesh's points by its ``velocities``: both time-sampled (pxr
    reads the velocities at the points' own samples; a default value alone is ignored)."""
    return (mesh.GetPointsAttr().GetNumTimeSamples() > 0
            and mesh.GetVelocitiesAttr().GetNumTimeSamples() > 0)


def points_at(mesh, time, base) -> np.ndarray:
    """A mesh's points in its own space at ``time`` (a ``Usd.TimeCode``), as pxr
    evaluates them for a renderer drawing the frame at ``base``: where velocities move
    them (:func:`moves_by_velocity`), ``ComputePointsAtTime(time, base)`` (the sample at
    or before ``base`` plus velocity, and half acceleration, times the time between, in
    seconds); else the points attribute at ``time`` (linear between samples)."""
    if moves_by_velocity(mesh):
        return _array(mesh.ComputePointsAtTime(time, base), 3)
    return _array(mesh.GetPointsAttr().Get(time), 3)


def mesh_motion(prim, mesh) -> tuple[bool, bool, str]:
    """``(deforming, topology_varies, motion)`` of a mesh prim from its time samples:
    its points time-sampled (deforming), its faces time-sampled, and its motion,
    ``"deforming"`` (either), ``"rigid"`` (only a transform, its own or an
    ancestor's, is) or ``"static"``."""
    deforming = mesh.GetPointsAttr().GetNumTimeSamples() > 1 or moves_by_velocity(mesh)
    topology_varies = any(a.GetNumTimeSamples() > 1 for a in (
        mesh.GetFaceVertexCountsAttr(), mesh.GetFaceVertexIndicesAttr()))
    rigid = not deforming and _transform_varies(prim)
    motion = "deforming" if deforming or topology_varies else "rigid" if rigid else "static"
    return deforming, topology_varies, motion


def read_mesh(prim, time, where: str, warn, skinned: bool, group_only: bool,
              stats: _Stats) -> MeshPrim | None:
    """The mesh prim ``prim`` at ``time``, what is not rendered of it said through
    ``warn`` (naming ``where`` and the prim) and what is said once per stage noted in
    ``stats``; None (said) when it has no points or faces. ``skinned``: the stage's
    UsdSkel skinning was baked; ``group_only``: a point instancer's prototype, whose
    first frame's points render.

    Raises:
        ValueError: naming the stage and the prim: its points are not finite, or its
            faceVertexCounts and faceVertexIndices are not valid faces of its points.
    """
    mesh = UsdGeom.Mesh(prim)
    path = prim.GetPath()
    deforming, topology_varies, motion = mesh_motion(prim, mesh)
    if prim.HasAPI(skel_binding()) and not deforming and not skinned:
        warn(f"{where}: {path}: bound to a UsdSkel skeleton whose skinning "
             f"is not applied (bake it into points); its rest points render")
    points = points_at(mesh, time, time)
    check_finite(where, path, "points", points, f"time code {time.GetValue():g}")
    faces, source_faces, corners = _triangulate(mesh, time, len(points), path,
                                                where, with_faces=True)
    if len(points) == 0 or len(faces) == 0:
        warn(f"{where}: {path}: a mesh without points or faces; it is not rendered")
        return None
    if group_only and motion != "static":
        warn(f"{where}: {path}: a point instancer's prototype whose points "
             f"are time-sampled renders its first frame's points")
        motion = "static"
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    if (counts < 3).any():
        warn(f"{where}: {path}: {int((counts < 3).sum())} face(s) of fewer "
             f"than 3 vertices are left out")
    if _visibility_varies(prim):
        warn(f"{where}: {path}: its visibility is time-sampled; its value "
             f"at the first frame holds for every frame")
    scheme = mesh.GetSubdivisionSchemeAttr().Get()
    normals = _vertex_normals(mesh, time, len(points))
    if normals is None and _has_normals(mesh):
        stats.face_varying.append(str(path))
    if scheme not in (None, UsdGeom.Tokens.none):
        stats.subdivided.append(str(path))
    return MeshPrim(mesh, path, motion, topology_varies, points, faces, source_faces,
                    corners, len(counts), scheme, normals)


def shading_normals(read: MeshPrim, transform: np.ndarray, instanced: bool,
                    stats: _Stats) -> np.ndarray | None:
    """The authored vertex normals a mesh renders with, unit length: in world space
    (``transform``, the prim's local-to-world), or in the prim's own space for an
    instance (which takes them to world space itself); None when it has none, or when
    it moves outside an instance (its normals are then recomputed every frame, noted
    in ``stats``)."""
    normals = read.normals
    if normals is not None and read.motion != "static" and not instanced:
        stats.moving_normals.append(str(read.path))
        normals = None
    if normals is not None:
        if not instanced:  # to world space (an instance takes them there itself)
            linear = transform[:3, :3]
            normals = normals @ (np.linalg.inv(linear) if np.linalg.det(linear) != 0
                                 else np.linalg.pinv(linear))
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals / np.where(length > 0, length, 1)
    return normals


def mesh_parts(read: MeshPrim, parts: list, normals, uv, transform: np.ndarray,
               instanced: bool) -> list[_Mesh]:
    """The Mitsuba meshes (ids not yet given) of a mesh prim's ``parts``, each
    ``(prim, triangle selection, bsdf, emission, mesh attributes, texture primvar)``:
    ``normals`` from :func:`shading_normals`, ``uv`` the texture coordinates (see
    ``_texcoords``; faceVarying ones split the points where their uv differ), faces
    turned where ``transform`` mirrors a world-space mesh so they keep facing out."""
    faces = read.faces
    vertex_points = None
    if uv is not None and uv[0] is not None:  # faceVarying: split by (point, uv)
        vertex_points, faces, texcoords = uv
    elif uv is not None:
        texcoords = uv[2]
    mirrored = not instanced and bool(np.linalg.det(transform[:3, :3]) < 0)
    if mirrored:
        faces = faces[:, ::-1].copy()  # a mirroring transform: keep the faces outward
    meshes = []
    for part, chosen, bsdf, emission, attributes, st in parts:
        if vertex_points is not None:  # per-point attributes follow the split points
            attributes = {name: values[vertex_points] if name.startswith("vertex_")
                          else values for name, values in attributes.items()}
        meshes.append(_Mesh(
            id="", path=read.path, motion="static" if instanced else read.motion,
            faces=faces[chosen], topology_varies=read.topology_varies,
            smooth=normals is not None or read.scheme not in (None, UsdGeom.Tokens.none),
            bsdf=bsdf, emission=emission,
            normals=None if normals is None
            else normals if vertex_points is None else normals[vertex_points],
            attributes=attributes, point_count=len(read.points), mirrored=mirrored,
            local_points=read.points if read.motion == "rigid" or instanced else None,
            vertex_points=vertex_points,
            texcoords=None if uv is None else texcoords))
    return meshes


def world_geometry(placements, mesh: _Mesh, time, cache, at: str, where: str, base=None):
    """``(points (V, 3) float64 world space, faces (F, 3) or None)`` of a mesh at
    ``time`` (``at`` names it: the frame and time code) for the frame rendered at
    ``base`` (``None``: ``time``; see :func:`points_at`), placed by ``placements``
    (:class:`hlbvh.scenes.usd.instances.Placements`): faces when its topology is
    time-sampled, or when its transform mirrors at this time and not at the first
    frame (or the reverse), so its faces keep facing out.

    Raises:
        ValueError: naming the stage (``where``), the mesh and ``at``: its transform or
            its points are not finite.
    """
    prim = placements.stage.GetPrimAtPath(mesh.path)
    if mesh.local_points is not None:
        local = mesh.local_points
    else:
        local = points_at(UsdGeom.Mesh(prim), time, time if base is None else base)
    transform = placements.of(prim, cache)
    check_finite(where, mesh.path, "transform", transform, at)
    check_finite(where, mesh.path, "points", local, at)
    points = local @ transform[:3, :3].T + transform[:3, 3]
    if mesh.vertex_points is not None:
        points = points[mesh.vertex_points]
    faces = None
    mirrored = bool(np.linalg.det(transform[:3, :3]) < 0)
    if mesh.topology_varies:
        faces = _triangulate(UsdGeom.Mesh(prim), time, len(local), mesh.path, where)
        if mirrored:
            faces = faces[:, ::-1].copy()
    elif mirrored != mesh.mirrored:
        faces = mesh.faces[:, ::-1].copy()
    return points, faces


def mesh_frame(placements, mesh: _Mesh, time, cache, at: str, where: str,
               given: set, base=None) -> FrameGeometry:
    """A moving mesh's world-space points (float32) at ``time`` (``at`` names it) for
    the frame rendered at ``base`` (:func:`world_geometry`), and
    its faces where :func:`world_geometry` gives them, where its point count differs
    from the first frame's, and for every later call once the mesh was given faces
    (``given``: the ids given faces so far, updated), so whichever frames came before,
    the frame applied is the same.

    Raises:
        ValueError: naming the stage (``where``), the mesh and ``at``: its point count
            changed while its faces did not, too few for them (and see
            :func:`world_geometry`).
    """
    points, faces = world_geometry(placements, mesh, time, cache, at, where, base)
    if faces is None and mesh.vertex_points is None \
            and len(points) <= int(mesh.faces.max(initial=0)):
        raise ValueError(f"{where}: mesh {mesh.path} has {len(points)} points "
                         f"at {at}, too few for its faces")
    if faces is None and (mesh.id in given or (
            mesh.vertex_points is None and len(points) != mesh.point_count)):
        faces = mesh.faces  # a new vertex count, or back to the first frame's
    if faces is not None:
        given.add(mesh.id)
    return FrameGeometry(
        np.ascontiguousarray(points, dtype=np.float32).reshape(-1),
        None if faces is None else faces.reshape(-1))


def stats_lines(stats: _Stats, where: str) -> list[str]:
    """The lines said once per stage (``where``) about its meshes, from ``stats``:
    subdivision surfaces rendered as their cage, normals that are not per vertex,
    moving meshes whose authored normals are recomputed."""
    lines = []
    if stats.subdivided:
        lines.append(f"{where}: {len(stats.subdivided)} mesh(es) with a subdivision "
                     f"scheme ({stats.subdivided[0]}, ...) render their control cage, "
                     f"with smooth normals")
    if stats.face_varying:
        lines.append(f"{where}: {len(stats.face_varying)} mesh(es) with normals "
                     f"that are not per vertex ({stats.face_varying[0]}, ...): vertex "
                     f"normals are computed from the points instead")
    if stats.moving_normals:
        lines.append(f"{where}: {len(stats.moving_normals)} moving mesh(es) with "
                     f"authored normals ({stats.moving_normals[0]}, ...): their normals "
                     f"are recomputed from the points every frame")
    return lines
