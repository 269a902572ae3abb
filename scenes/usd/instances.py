"""Instances of a USD stage's meshes: shape groups, the instances of them, and where
prims are placed in Mitsuba's Y-up metres.

Every instance proxy's mesh, and a mesh of at least
:data:`hlbvh.scenes.usd.RIGID_INSTANCE_TRIANGLES` triangles that moves by a transform
alone (rigid), is a Mitsuba ``instance`` of a ``shapegroup`` holding the mesh prim's
parts in the prim's own space, its ``to_world`` the prim's transform at each time code:
the proxies of one prototype mesh share one group (one per set of materials, where
bindings outside the prototype differ), so a prototype's triangles are held once, and a
rigid animation moves transforms only (hlbvh rebuilds its top level alone). Meshes whose
material emits stay world-space meshes (Mitsuba refuses area emitters inside shape
groups), as does everything with ``instancing=False`` (world-space copies, a prototype's
triangles once per instance, a rigid mesh's points rewritten every frame).

Point instancers (``UsdGeom.PointInstancer``): each mesh of each prototype is a shape
group (in the prototype root's space) and each point an instance of its prototype's
groups, its ``to_world`` the instancer's transform through the point's position,
orientation and scale at each time code as ``ComputeInstanceTransformsAtTime`` gives
it, inside a frame too (the points move with their frames when any of those is
time-sampled, or time-sampled ``velocities`` or ``angularVelocities`` move them).
Points hidden at the first frame (``invisibleIds``, inactive ids) or scaled to nothing
at some frame are left out; an instancer whose number of points changes over time, or
that names no prototype, is not rendered (each said once).
Needs ``instancing``.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from .meshes import check_finite
from .prims import Sdf, Usd, UsdGeom, _matrix, _transform_varies
from .time_codes import sample_times


@dataclass
class Group:
    """A shape group: a mesh prim's parts in the prim's own space, shared by the
    instances of one prototype mesh."""

    id: str
    parts: list  # _Mesh, local_points their object-space points

    @property
    def triangles(self) -> int:
        return sum(len(part.faces) for part in self.parts)


@dataclass
class Instance:
    """A mesh prim rendered as an instance of a :class:`Group`."""

    id: str
    path: Sdf.Path  # the mesh prim's, or the point instancer's
    motion: str  # "static" or "rigid"
    group: Group
    point: tuple | None = None  # a point instancer's: (its instance index, the mesh's
    #                             transform into its prototype root's space)


@dataclass
class InstancerPoints:
    """What a point instancer renders: each point's prototype index, the prototypes'
    paths, which points are shown, and whether they move."""

    indices: np.ndarray
    targets: list
    shown: np.ndarray
    moving: bool


def digest(array) -> str | None:
    """A digest of a mesh attribute's values or texture coordinates (None stays None)."""
    if array is None:
        return None
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()


def object_points(part) -> np.ndarray:
    """A group part's Mitsuba vertices in its object space."""
    return part.local_points if part.vertex_points is None else part.local_points[part.vertex_points]


def check_instance_transform(where: str, stage_name: str, instance: Instance,
                             matrix: np.ndarray, at: str) -> None:
    """A ValueError naming the stage (``where``), the instance's prim and ``at`` when
    its transform there is not finite or is singular (a scale interpolated through 0
    between two time samples: an instance's transform must be invertible);
    ``stage_name`` is the stage's file name, which the message's way out names."""
    check_finite(where, instance.path, "transform", matrix, at)
    if abs(np.linalg.det(matrix[:3, :3])) <= 1e-30:
        raise ValueError(f"{where}: {instance.path}: its transform at {at} is "
                         f"singular, which a Mitsuba instance cannot take; "
                         f"{stage_name}:instancing=false renders it as a "
                         f"world-space mesh")


class Placements:
    """Where a stage's prims and point instancers' points are, in Mitsuba's Y-up metres
    (``root``: the stage's units and up axis), with the transforms it computed kept."""

    def __init__(self, stage, root: np.ndarray):
        self.stage = stage
        self.root = root
        self._caches: dict = {}  # an XformCache per time code, for invertible()
        self._points_at: dict = {}  # per point instancer, its last time's transforms

    def of(self, prim, cache) -> np.ndarray:
        """The local-to-world 4x4 of ``prim`` (or of the prim at that path) in Mitsuba's
        Y-up metres."""
        if not isinstance(prim, Usd.Prim):
            prim = self.stage.GetPrimAtPath(prim)
        return self.root @ _matrix(cache.GetLocalToWorldTransform(prim))

    def points(self, path, time, base=None) -> np.ndarray:
        """``(N, 4, 4)``: each instance of the point instancer at ``path`` from its
        prototype root's space to the instancer's at ``time``, as pxr evaluates it for a
        renderer drawing the frame at ``base`` (default ``time``):
        ``ComputeInstanceTransformsAtTime(time, base)``, the samples at or before
        ``base`` moved by their ``velocities`` and ``angularVelocities`` where authored,
        else interpolated at ``time``. Every instance, masked or not, so indices stay
        the authored ones; the last time's kept."""
        base = time if base is None else base
        kept = self._points_at
        key = (str(path), time.GetValue(), base.GetValue())
        if key not in kept:
            instancer = UsdGeom.PointInstancer(self.stage.GetPrimAtPath(path))
            xforms = instancer.ComputeInstanceTransformsAtTime(
                time, base, UsdGeom.PointInstancer.IncludeProtoXform,
                UsdGeom.PointInstancer.IgnoreMask)
            kept.pop(next((k for k in kept if k[0] == key[0]), None), None)
            kept[key] = np.array(xforms, np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)
        return kept[key]

    def instances(self, instances: list, cache, base=None) -> dict:
        """Each instance's object-to-world 4x4 (Mitsuba's Y-up metres) in ``cache``'s
        time, by id; a point instancer's points in one batch, for the frame at time code
        ``base`` (default: ``cache``'s time; see :meth:`points`)."""
        result, points = {}, {}
        for instance in instances:
            if instance.point is None:
                result[instance.id] = self.of(instance.path, cache)
            else:
                points.setdefault(str(instance.path), []).append(instance)
        for path, chosen in points.items():
            index = np.array([m.point[0] for m in chosen])
            relative = np.stack([m.point[1] for m in chosen])
            placed = (self.of(path, cache)
                      @ self.points(path, cache.GetTime(), base)[index] @ relative)
            result.update(zip((m.id for m in chosen), placed))
        return result

    def invertible(self, prim, times: list[float]) -> bool:
        """Whether the prim's transform can be an instance's: finite and invertible at
        each of ``times`` (the first frame's, or, when it moves, every time sample of
        its transform's attributes up to the last frame: an animation that scales a
        prop to nothing to hide it keeps the prop a world-space mesh, whose triangles
        then collapse; an instance's transform must be invertible)."""
        for t in times:
            if t not in self._caches:
                self._caches[t] = UsdGeom.XformCache(Usd.TimeCode(t))
            m = _matrix(self._caches[t].GetLocalToWorldTransform(prim))
            if not np.isfinite(m).all() or abs(np.linalg.det(m[:3, :3])) <= 1e-30:
                return False
        return True


def instancer_points(prim, time, placements: Placements, first: float, last: float,
                     where: str, warn) -> InstancerPoints | None:
    """The points of the ``UsdGeom.PointInstancer`` ``prim`` that render, between
    time codes ``first`` and ``last``: those hidden at ``time`` (invisible or
    inactive ids), or whose transform is singular at some time sample, are left
    out. None (said through ``warn``, naming ``where`` and the prim) when it has no
    point, its points name no prototype, or their number changes over time."""
    path = prim.GetPath()
    instancer = UsdGeom.PointInstancer(prim)
    indices = np.array(instancer.GetProtoIndicesAttr().Get(time) or [], np.int64)
    targets = instancer.GetPrototypesRel().GetTargets()
    if not len(indices):
        warn(f"{where}: {path}: a PointInstancer without points at the first "
             f"frame; nothing of it renders")
        return None
    if ((indices < 0) | (indices >= len(targets))).any():
        warn(f"{where}: {path}: a PointInstancer whose protoIndices name "
             f"no prototype (it has {len(targets)}); it is not rendered")
        return None
    shown = np.ones(len(indices), bool)
    mask = instancer.ComputeMaskAtTime(time)
    if len(mask):
        shown &= np.array(mask, bool)
    attributes = [instancer.GetPositionsAttr(), instancer.GetOrientationsAttr(),
                  instancer.GetScalesAttr(), instancer.GetProtoIndicesAttr()]
    if hasattr(instancer, "GetOrientationsfAttr"):  # newer USD: float orientations
        attributes.append(instancer.GetOrientationsfAttr())
    for t in sample_times(attributes, first, last):  # one time's held at a time
        m = placements.points(path, Usd.TimeCode(t))
        if len(m) != len(indices):
            warn(f"{where}: {path}: a PointInstancer whose number of points "
                 f"changes over time is not supported; it is not rendered")
            return None
        shown &= np.isfinite(m).all(axis=(1, 2)) & (
            np.abs(np.linalg.det(np.nan_to_num(m[:, :3, :3]))) > 1e-30)
    # pxr moves the points by time-sampled velocities (a default value alone is ignored)
    moves = [instancer.GetVelocitiesAttr(), instancer.GetAngularVelocitiesAttr()]
    moving = (_transform_varies(prim) or any(a.GetNumTimeSamples() > 1 for a in attributes)
              or any(a.GetNumTimeSamples() > 0 for a in moves))
    return InstancerPoints(indices, targets, shown, moving)
