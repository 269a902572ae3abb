"""Two levels for rigid motion: instances of shared geometry (Mitsuba's shape groups),
each with its own transform, under a top-level tree over their world boxes. The
geometry's trees are built once; when instances move, only the top level is rebuilt,
by the same builder (:func:`hlbvh.build`) over the instances' boxes, which is what
HLBVH's builder is made for (few primitives, rebuilt every frame).

The result is a :class:`hlbvh.kernels.two_level.TwoLevel`: every geometry tree's slots,
then the top level's, in one array (the trees' part packed once); the traversal enters an instance at its top-level
leaf slot with the ray in the instance's object space.

Instances moving inside the shutter (motion blur) come with a
:class:`~hlbvh.kernels.srt.KeyTable`: their top-level boxes hold their whole motion
(:func:`hlbvh.kernels.srt.swept_boxes`), and the traversal takes a ray into such an
instance through its pose at the ray's time.
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import numpy as np

from .arrays import concat, namespace_of, plain
from .build import build
from .bvh import BVH, BuildConfig
from .layout.packing import arrays_key, packed_records
from .layout.slots import NODE_SLOTS, SLOT
from .srt import KEY, KeyTable, inverse, swept_boxes
from .two_level import GroupSlots, TwoLevel


class BadTransform(ValueError):
    """An instance's transform that cannot be inverted.

    Attributes:
        index: which instance (its position in the instances given).
        what: what is wrong with the transform (``"not finite"``, ``"singular (a
            scale of 0)"``), for a caller that names the instance its own way.
    """

    def __init__(self, index: int, what: str):
        super().__init__(f"instance {index}: its transform is {what}")
        self.index = index
        self.what = what

    def __reduce__(self):
        """Pickled by its fields (a Dask worker's error reaches the client whole)."""
        return type(self), (self.index, self.what)


def root_boxes(group_bvhs: list[BVH]) -> tuple:
    """``(lo, hi)``: each geometry tree's root box, Array3f (one entry a tree)."""
    ns = namespace_of(group_bvhs[0].node_count)
    lo = ns.Array3f(*(concat([_first(b.node_min[i]) for b in group_bvhs]) for i in range(3)))
    hi = ns.Array3f(*(concat([_first(b.node_max[i]) for b in group_bvhs]) for i in range(3)))
    dr.eval(lo, hi)
    return lo, hi


def world_boxes(group_bvhs: list[BVH], instance_group, to_world, roots=None):
    """The world box of each instance: its geometry's root box through its transform.

    Args:
        group_bvhs: the geometry trees (object space).
        instance_group: UInt32 (M): each instance's tree, an index into ``group_bvhs``.
        to_world: Float (12·M): each instance's object-to-world transform, rows of a
            3x4 matrix (``p_world = A p + b``, A row-major, then b).
        roots: the trees' :func:`root_boxes`, where the caller keeps them.
    Returns:
        ``(lo, hi)``: Array3f (M) each.
    """
    ns = namespace_of(instance_group)
    instance_group, to_world = plain(instance_group, "UInt32"), plain(to_world, "Float")
    lo_g, hi_g = roots if roots is not None else root_boxes(group_bvhs)
    lo_o = dr.gather(ns.Array3f, lo_g, instance_group)
    hi_o = dr.gather(ns.Array3f, hi_g, instance_group)
    m = _rows(ns, to_world, dr.width(instance_group))
    lo = ns.Array3f(dr.inf, dr.inf, dr.inf)
    hi = ns.Array3f(-dr.inf, -dr.inf, -dr.inf)
    for corner in range(8):
        c = ns.Array3f(*(dr.select(((corner >> i) & 1) == 1, hi_o[i], lo_o[i]) for i in range(3)))
        p = _apply(m, c, True)
        lo, hi = dr.minimum(lo, p), dr.maximum(hi, p)
    return lo, hi


def two_level(group_bvhs: list[BVH], instance_group, to_world,
              config: BuildConfig | None = None, previous: BVH | None = None,
              kept: TwoLevel | None = None, motion: KeyTable | None = None):
    """The two-level hierarchy of instances of ``group_bvhs``.

    Args:
        group_bvhs, instance_group, to_world: as :func:`world_boxes`; every transform
            invertible.
        config: the top level's builder config (defaults), its leaves of one instance
            whatever its ``leaf_size`` (:func:`top_level_config`).
        previous: last frame's top-level BVH, seeding its CSD sort.
        kept: last frame's result, whose geometry trees' slots are reused when
            ``group_bvhs`` are the same trees.
        motion: the instances' keys over the shutter (an entry without keys is still
            at ``to_world``), or None: no instance moves inside the shutter. A keyed
            instance's ``to_world`` is not used by the traversal (its pose at the ray's
            time is), and may be singular.
    Returns:
        ``(TwoLevel, top-level BVH)``. Face indices in the geometry trees count over
        ``group_bvhs`` in order (a hit's ``prim`` minus the faces of the trees before
        its own is the face in its tree).
    Raises:
        BadTransform: (a ValueError) naming the first instance whose transform is not
            invertible or not finite.
    """
    groups = group_slots(group_bvhs, kept, dr.width(instance_group))
    to_object, vertices, faces = _top_input(group_bvhs, groups, instance_group, to_world,
                                            motion)
    top = build(vertices, faces, previous=previous, config=top_level_config(config))
    return _assembled(top, groups, instance_group, to_object, motion), top


def top_level_config(config: BuildConfig | None) -> BuildConfig:
    """``config`` (or the defaults) with leaves of one instance: entering an instance
    costs a ray transform and a few traversal steps whether the ray meets its geometry
    or not, so every instance gets its own box, tested before the ray enters it (leaves
    of four entered three instances in vain for one hit)."""
    return dataclasses.replace(config or BuildConfig(), leaf_size=1)


def refit_top_level(top: BVH, group_bvhs: list[BVH], instance_group, to_world,
                    kept: TwoLevel | None = None,
                    motion: KeyTable | None = None) -> TwoLevel:
    """The two-level hierarchy with ``top``, the top level :func:`two_level` built over
    the same instances in the same order, refit in place to their new boxes (the same
    tree: cheaper than a build, slower to trace as the instances move away from where
    it was built; ``top.stats.sah_cost`` says how much). Arguments as
    :func:`two_level`'s.

    Raises:
        BadTransform: as :func:`two_level`.
    """
    groups = group_slots(group_bvhs, kept, dr.width(instance_group))
    to_object, vertices, _ = _top_input(group_bvhs, groups, instance_group, to_world,
                                        motion)
    top.refit(vertices)
    return _assembled(top, groups, instance_group, to_object, motion)


def _top_input(group_bvhs, groups: GroupSlots, instance_group, to_world,
               motion: KeyTable | None = None) -> tuple:
    """``(world-to-object rows, vertices, faces)``: the inverse transforms, and one
    proxy triangle an instance whose box is the instance's world box (over its whole
    motion, for an instance with keys) (the top level's primitives)."""
    ns = namespace_of(instance_group)
    instance_group, to_world = plain(instance_group, "UInt32"), plain(to_world, "Float")
    M = dr.width(instance_group)
    segments = None if motion is None else np.array(motion.segments, np.int64)
    still = None if motion is None else ns.Bool(segments == 0)
    to_object = _inverse_rows(ns, to_world, M, still)  # first: it names a bad transform
    lo, hi = world_boxes(group_bvhs, instance_group, to_world, groups.roots_box)
    if motion is not None:
        lo, hi = _swept(ns, lo, hi, groups.roots_box, instance_group, motion, segments)
    vertices = dr.zeros(ns.Float, 9 * M)
    k = dr.arange(ns.UInt32, M)
    for v, p in enumerate((lo, hi, lo)):
        for i in range(3):
            dr.scatter(vertices, p[i], k * 9 + 3 * v + i)
    faces = dr.arange(ns.UInt32, 3 * M)
    return to_object, vertices, faces


def _swept(ns, lo, hi, roots, instance_group, motion: KeyTable, segments) -> tuple:
    """``lo``, ``hi`` with each keyed instance's box replaced by the box of its whole
    motion (:func:`hlbvh.kernels.srt.swept_boxes`, on the host: a few floats per key)."""
    keyed = np.flatnonzero(segments)
    base = np.array(motion.base, np.int64)
    table = np.array(motion.keys, np.float64).reshape(-1, KEY)
    which = np.array(instance_group, np.int64)[keyed]
    object_lo = np.array(roots[0], np.float64).reshape(3, -1).T[which]
    object_hi = np.array(roots[1], np.float64).reshape(3, -1).T[which]
    keys = [table[base[i]:base[i] + segments[i] + 1] for i in keyed]
    swept_lo, swept_hi = swept_boxes(keys, object_lo, object_hi)
    at = ns.UInt32(keyed.astype(np.uint32))
    lo, hi = ns.Array3f(lo), ns.Array3f(hi)
    for box, swept in ((lo, swept_lo), (hi, swept_hi)):
        for i in range(3):
            dr.scatter(box[i], ns.Float(swept[:, i].astype(np.float32)), at)
    return lo, hi


def _assembled(top: BVH, groups: GroupSlots, instance_group, to_object,
               motion: KeyTable | None = None) -> TwoLevel:
    """The slots: every geometry tree's (packed once), then the top level's, written
    into the room kept behind them (the trees' slots are not copied again)."""
    ns = namespace_of(instance_group)
    records, root = packed_records(top, groups.slots)
    group_root = dr.gather(ns.UInt32, ns.UInt32(groups.roots), plain(instance_group, "UInt32"))
    if dr.width(records) <= SLOT * groups.room:
        dr.scatter(groups.records, records,
                   dr.arange(ns.UInt32, dr.width(records)) + SLOT * groups.slots)
        records = groups.records
    else:  # (the room holds any top level over as many instances as it was made for)
        records = concat([groups.records, records])
    dr.eval(records, group_root)
    return TwoLevel(records=records, root=root, top_base=groups.slots, to_object=to_object,
                    group_root=group_root, groups=groups, motion=motion)


def group_slots(group_bvhs: list[BVH], kept: TwoLevel | None = None,
                instances: int = 0) -> GroupSlots:
    """The geometry trees' slots, one after the other from slot 0, face indices counted
    over them in order, and room behind them for the top level over ``instances``
    instances; ``kept``'s when it was made of the same trees with room enough (a rigid
    motion leaves them as they were: only the top level after them changes)."""
    keys = tuple(arrays_key(b) for b in group_bvhs)
    room = top_level_room(instances)
    if kept is not None and kept.groups.keys == keys and kept.groups.room >= room:
        return kept.groups
    parts, roots, slot_base, face_base = [], [], 0, 0
    for bvh in group_bvhs:
        records, group_root = packed_records(bvh, slot_base, face_base)
        parts.append(records)
        roots.append(group_root)
        slot_base += dr.width(records) // SLOT
        face_base += bvh.prim_count
    ns = namespace_of(group_bvhs[0].node_count)
    records = concat(parts + [dr.zeros(ns.Float, SLOT * room)])
    dr.eval(records)
    return GroupSlots(records=records, roots=roots, slots=slot_base, keys=keys,
                      roots_box=root_boxes(group_bvhs), room=room)


def top_level_room(instances: int) -> int:
    """Slots that hold any top level over ``instances`` instances: a leaf slot each,
    and at most one wide node (``NODE_SLOTS``) per internal node, of which a binary
    tree over them has fewer than ``instances``."""
    return instances * (NODE_SLOTS + 1)


def _first(x):
    """The first entry of a flat array (a width-1 array)."""
    return dr.gather(type(x), x, dr.zeros(dr.uint32_array_t(type(x)), 1))


def _rows(ns, flat, M):
    """The 12 floats per instance of ``flat`` as a list of 12 Float (M)."""
    k = dr.arange(ns.UInt32, M) * 12
    return [dr.gather(ns.Float, flat, k + i) for i in range(12)]


def _apply(m, p, translate: bool):
    """``A p (+ b)`` for the rows ``m`` (12 Float) and Array3f ``p``."""
    return type(p)(*(dr.fma(m[3 * r], p.x, dr.fma(m[3 * r + 1], p.y,
                                                  dr.fma(m[3 * r + 2], p.z,
                                                         m[9 + r] if translate else 0.0)))
                     for r in range(3)))


def _inverse_rows(ns, to_world, M, checked=None):
    """Each instance's world-to-object rows (A⁻¹, -A⁻¹ b), as a Float (12·M).

    Raises:
        ValueError: a transform whose matrix is singular or not finite, among the
            instances of ``checked`` (Bool per instance; all when None)."""
    m = _rows(ns, to_world, M)
    inv, det = inverse(m)
    finite = dr.all(dr.isfinite(ns.ArrayXf(m)), axis=0)
    bad = ~finite | (det == 0)
    if checked is not None:
        bad &= checked
    if dr.any(bad, axis=None):
        k = int(dr.compress(bad)[0])
        raise BadTransform(k, "not finite" if not finite[k] else "singular (a scale of 0)")
    out = dr.zeros(ns.Float, 12 * M)
    k = dr.arange(ns.UInt32, M) * 12
    for i, value in enumerate(inv):
        dr.scatter(out, value, k + i)
    return out

