"""The moving instances of a scene (rigid motion), traced through our two-level
hierarchy: one BVH per shape group they use, built once, and a top level over the
instances' world boxes (:func:`hlbvh.kernels.instances.two_level`), brought up to
date whenever one of them moves as the update policy says: with ``"auto"`` refit while
its SAH cost stays within the tolerance of its last build's, rebuilt otherwise (as the
meshes' BVHs are; a refit of 10k boxes costs a fraction of a rebuild). A group whose
own shapes change (``params["group.mesh.vertex_positions"]``) has its BVH built again
and the top level rebuilt. The moving-instances group of :class:`hlbvh.SceneAccel`
with ``static="native"``.

Instances given keys over the shutter (:func:`hlbvh.accel.keys.set_instance_keys`)
carry them into the two-level tree (a :class:`~hlbvh.kernels.srt.KeyTable`): their
top-level boxes hold their whole motion, and a ray enters each at its pose at the
ray's time. New keys count as motion (the top level is refit or rebuilt).

Mitsuba does not say which shape group an instance uses (an instance's parameters are
its ``to_world`` alone), so it is found from what Mitsuba does say: the group whose box,
through the instance's ``to_world``, is the instance's box, and whose primitive count is
the instance's. An instance that matches no group, or several groups of other geometry,
is refused naming it.
"""

from __future__ import annotations

import re

import drjit as dr
import mitsuba as mi
import numpy as np

from hlbvh.kernels.arrays import concat
from hlbvh.kernels.build import build
from hlbvh.kernels.bvh import BuildConfig
from hlbvh.kernels.instances import BadTransform, refit_top_level, two_level
from hlbvh.kernels.srt import KeyTable
from hlbvh.accel.groups import Change, InstanceUpdate
from hlbvh.accel.instance_shading import group_members, to_world_rows
from hlbvh.accel.keys import instances_keys
from hlbvh.accel.motion import member_states, members_changed
from hlbvh.accel.policy import RefitOrRebuild
from hlbvh.accel.scene_geometry import ShapeError, collect_geometry, describe_shape
from hlbvh.timing import clock_ms


class InstanceGroup:
    """Moving instances, their groups' BVHs and the top level over them.

    Args:
        groups: the scene's shape groups.
        config: the builder config of the groups' BVHs and of the top level.
        group_of: a function giving the shape group an instance uses, where the caller
            tells it already; :func:`group_of` otherwise.

    Attributes:
        name: ``"instances"``.
        indices: indices into ``scene.shapes()`` of the instances, ascending.
        tree: the :class:`hlbvh.kernels.two_level.TwoLevel` traced; None without
            instances.
        rows_of: ``rows_of(indices)``, the instances' transforms as one Float (12 an
            instance), where the caller holds them; None to read them from the shapes.
        last: what the last update did (:class:`~hlbvh.accel.groups.InstanceUpdate`:
            ``"build"``, ``"rebuild"`` or ``"refit"`` of the top level only, or
            ``"kept"``; ``triangles`` instanced).
    """

    name = "instances"
    native = False  # our two levels trace it (hlbvh.accel.groups.Group)
    bvh = None  # its trees are the two levels' (tree), not a BVH of the joined ones

    def __init__(self, groups: list, config: BuildConfig, group_of=None):
        self.groups, self.config = groups, config
        self._told = group_of
        self.indices: tuple = ()
        self.tree = None
        self.rows_of = None
        self.last = None
        self._group_of = {}  # instance index -> group position in self._used
        self._used = []  # the groups the instances use, in the order of their BVHs
        self._bvhs = []  # their BVHs (object space)
        self._top = None  # the top level's BVH of the last update
        self._prims = None  # per instanced face: (its mesh's index in its group, local)
        self._parts = []  # each used group's share of _prims
        self._states = []  # each used group's meshes' states when its BVH was built
        self._members = []  # each used group's meshes
        self._handles = {}  # their parameter handles (hlbvh.accel.motion)
        self._scene_index = None  # UInt32: each instance's index in scene.shapes()
        self._built_sah = None  # the top level's SAH cost at its last build
        self._policy = RefitOrRebuild()  # what "auto" remembers of past refits
        self._keys = None  # the instances' keys at the last update (instances_keys)
        self.keep()

    @property
    def triangles(self) -> int:
        return sum(b.prim_count for b in self._bvhs) if self.tree is not None else 0

    def keep(self):
        self.last = InstanceUpdate(decision="kept", ms=0.0, triangles=self.triangles,
                                   sah_cost=self._sah(), instances=len(self.indices),
                                   groups=len(self._used))

    @property
    def stale(self) -> bool:
        """Whether a group's own shapes changed since its BVH was built."""
        return bool(self._deformed())

    def _sah(self):
        return None if self._top is None else float(self._top.stats.sah_cost)

    def update(self, change: Change):
        """Trace the instances ``change.indices``: their groups' BVHs built for instances
        seen for the first time, the top level built when the set changed, and refit or
        rebuilt as ``change.policy`` says when they moved. Their transforms come from
        :attr:`rows_of` where the caller holds them already; read here otherwise.

        Raises:
            ValueError: naming an instance whose group cannot be told, whose group holds
                other shapes than meshes, or whose transform is singular or not finite.
        """
        shapes, indices, moved, rows_of = (change.shapes, tuple(change.indices),
                                           change.moved, self.rows_of)
        deformed = self._deformed()
        keys, shutter = instances_keys([shapes[i] for i in indices])
        rekeyed = not _same_keys(keys, self._keys)
        self._keys = keys
        if indices == self.indices and not moved and not deformed and not rekeyed:
            self.keep()
            return
        start = clock_ms()
        for k in deformed:  # a group's own shapes changed: its BVH is built again
            self._bvhs[k], self._parts[k], self._states[k] = self._group_bvh(self._used[k])
        if deformed:
            self._prims = tuple(concat(list(column)) for column in zip(*self._parts))
        first = self.tree is None
        same_set = indices == self.indices and not first and not deformed
        groups_before = len(self._used)
        for i in indices:
            if i not in self._group_of:
                self._group_of[i] = self._group_position(shapes[i])
        self.indices = indices
        chosen, drift = "build", None
        if not indices:
            self.tree, self._top = None, None
        else:
            rows = (rows_of(indices) if rows_of is not None else
                    concat([v for i in indices for v in to_world_rows(shapes[i])]))
            which = mi.UInt32([self._group_of[i] for i in indices])
            motion = None if keys is None else KeyTable.of(mi, keys, shutter)
            try:
                chosen, _, drift = self._policy.update(
                    change.policy,
                    not same_set or len(self._used) != groups_before,
                    lambda seed: self._build_top(which, rows, seed, motion),
                    lambda: self._refit_top(which, rows, motion))
            except BadTransform as error:
                name = describe_shape(shapes[indices[error.index]])
                raise ShapeError(name, f"{name}: its to_world is {error.what}") from None
        self._scene_index = mi.UInt32(list(indices))
        decision = "build" if first else chosen
        self.last = InstanceUpdate(decision=decision, ms=clock_ms() - start,
                                   triangles=self.triangles, sah_cost=self._sah(),
                                   instances=len(indices), groups=len(self._used),
                                   drift=drift,
                                   groups_rebuilt=[self._used[k].id() for k in deformed])

    def _deformed(self) -> list[int]:
        """Positions of the groups whose shapes changed (a mesh's buffers, another
        shape's box or parameters) since their BVH was built."""
        return [k for k, (members, states) in enumerate(zip(self._members, self._states))
                if members_changed(members, states, self._handles)]

    def _build_top(self, which, rows, seed: bool, motion=None) -> bool:
        """A new top level (its CSD sort seeded with the last one's order when
        ``seed``), over the instances' keys ``motion`` where they have some; whether
        the seed was used."""
        previous = self._top if seed else None
        self.tree, self._top = two_level(self._bvhs, which, rows, self.config,
                                         previous=previous, kept=self.tree, motion=motion)
        self._built_sah = self._top.stats.sah_cost
        return bool(self._top.stats.csd_seeded)

    def _refit_top(self, which, rows, motion=None) -> float:
        """The top level refit to the instances' new boxes; its SAH drift."""
        self.tree = refit_top_level(self._top, self._bvhs, which, rows, kept=self.tree,
                                    motion=motion)
        return self._top.stats.sah_cost / self._built_sah

    def hit_fields(self, prim, inst, valid):
        """Mitsuba's fields of instance hits: ``(prim_index, shape_index (the shape's
        index in its group), index of the instance in scene.shapes())``."""
        in_group, local = self._prims
        return (dr.gather(mi.UInt32, local, prim, valid),
                dr.gather(mi.UInt32, in_group, prim, valid),
                dr.gather(mi.UInt32, self._scene_index, inst, valid))

    def _group_position(self, instance) -> int:
        """The position (in ``self._used``) of the group ``instance`` uses, its BVH
        built when it is new."""
        group = (self._told(instance) if self._told is not None
                 else group_of(instance, self.groups, "moved"))
        if any(g is group for g in self._used):
            return next(k for k, g in enumerate(self._used) if g is group)
        self._add_group(group, instance)
        return len(self._used) - 1

    def _add_group(self, group, instance):
        """The group's BVH and its faces' fields, for the first instance of it."""
        members = group_members(group)
        if not members or not all(m.is_mesh() for m in members):
            raise ValueError(f"{describe_shape(instance)} moved, and its shape group holds shapes "
                             "other than meshes, which hlbvh cannot trace moving; keep it "
                             "still or render with accel='native'")
        bvh, part, states = self._group_bvh(group)
        self._used.append(group)
        self._members.append(members)
        self._bvhs.append(bvh)
        self._parts.append(part)
        self._states.append(states)
        self._prims = tuple(concat(list(column)) for column in zip(*self._parts))

    def _group_bvh(self, group) -> tuple:
        """``(BVH over the group's meshes in object space, its faces' (mesh in group,
        face in mesh), the meshes' states)``."""
        members = group_members(group)
        geometry = collect_geometry(members, list(range(len(members))))
        bvh = build(geometry.vertices, geometry.faces, config=self.config)
        return bvh, (geometry.prim_shape, geometry.prim_local), member_states(members, self._handles)


def _same_keys(a, b) -> bool:
    """Whether two :func:`instances_keys` lists hold the same keys objects."""
    if a is None or b is None:
        return a is b
    return len(a) == len(b) and all(x is y for x, y in zip(a, b))


def group_of(instance, groups: list, why: str = "is traced by hlbvh", matrix=None):
    """The shape group of ``groups`` that ``instance`` uses: the one whose box, through
    the instance's ``to_world``, is the instance's box, and whose primitive count is the
    instance's (Mitsuba does not expose the link); among several such groups (copies of
    one geometry with other materials, as USD prototypes often are), the one whose id
    the instance's description names. ``why`` says in errors why it is asked for;
    ``matrix``: the instance's ``to_world`` as a 4x4 numpy array, where the caller read
    it already.

    Raises:
        ValueError: naming the instance, when no group or several groups match.
    """
    box = instance.bbox()
    count = instance.effective_primitive_count()
    if matrix is None:
        matrix = np.array(mi.traverse(instance)["to_world"].matrix, np.float64).reshape(4, 4)
    found = [g for g in groups if g.primitive_count() == count
             and _same_box(_transformed(g.bbox(), matrix), box)]
    if not found:
        raise ValueError(f"{describe_shape(instance)} {why}, and no shape group of the scene "
                         "matches its box and primitive count; render it with "
                         "accel='native'")
    if len(found) > 1:
        named = [g for g in found if g.id() == _group_name(instance)]
        found = named if len(named) == 1 else found
    if len(found) > 1:
        raise ValueError(f"{describe_shape(instance)} {why}, and {len(found)} shape groups "
                         "match its box and primitive count: which it instances "
                         "cannot be told; give the groups different geometry, or "
                         "render with accel='native'")
    return found[0]


def _group_name(instance) -> str | None:
    """The id of the shape group ``instance`` uses, as Mitsuba's description of the
    instance gives it (``shapegroup = ShapeGroup[name = "..."``), or None."""
    found = re.search(r'shapegroup\s*=\s*ShapeGroup\[\s*name\s*=\s*"([^"]*)"', str(instance))
    return found.group(1) if found else None


def _transformed(box, matrix: np.ndarray):
    """The box around ``box``'s corners through the 4x4 ``matrix``."""
    bits = (np.arange(8)[:, None] >> np.arange(3)) & 1
    corners = np.where(bits == 1, np.array(box.max, np.float64), np.array(box.min, np.float64))
    p = corners @ matrix[:3, :3].T + matrix[:3, 3]
    return list(p.min(axis=0)), list(p.max(axis=0))


def _same_box(ours, box) -> bool:
    lo, hi = ours
    scale = max(1.0, *(abs(v) for v in lo + hi))
    return all(abs(a - b) <= 1e-4 * scale for a, b in zip(lo + hi, list(box.min) + list(box.max)))
