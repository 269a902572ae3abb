"""Two levels in the traversal (rigid motion): the data a two-level trace reads
(:class:`TwoLevel`, made by :func:`hlbvh.kernels.instances.two_level`) and the step that
enters an instance, transforming the ray into its object space, and the one that leaves
it (:mod:`hlbvh.kernels.traversal` calls them only when tracing two levels). An
instance with keys over the shutter (:attr:`TwoLevel.motion`) takes the ray through the
inverse of its pose at the ray's time instead of its one world-to-object transform."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from .arrays import namespace_of
from .layout.slots import LEAF_BIT, MAX_SLOTS, TRI_FACE, leaf_ref
from .ray_tests import Ray, ray_setup
from .srt import KeyTable, inverse_or_nan

#: Two levels: ``inst`` of a ray at the top level (in no instance).
NO_INSTANCE = 0xFFFFFFFF
#: Two levels: the reference of the marker pushed on entering an instance; popping it
#: restores the world ray (a node reference past every slot: never a real one, and
#: unlike 0x7FFFFFFF not an any-hit query's miss entry once its leaf bit is flipped).
RETURN_REF = 0x7FFFFFFE
assert MAX_SLOTS < RETURN_REF and RETURN_REF ^ LEAF_BIT != 0xFFFFFFFF  # any hit's miss


@dataclass
class TwoLevel:
    """Slots of a two-level hierarchy, as
    :func:`hlbvh.kernels.traversal.closest_instance_hit` and ``any_hit`` trace it: the
    trees of the instances' shared geometry (their face indices counted over all of
    them), then a top-level tree whose leaf slots stand for instances (their face index
    is the instance's index).

    Attributes:
        records: Float, ``SLOT`` per slot; the geometry trees' slots first, then the
            top level's, in room kept for it (the next frame's top level is written
            over it: the array is shared from frame to frame).
        root: reference of the top level's root.
        top_base: the top level's first slot (a leaf slot from here on is an instance).
        to_object: Float (12·M): each instance's world-to-object transform, rows of a
            3x4 matrix (``p_object = A p + b``, A row-major then b).
        group_root: UInt32 (M): reference of each instance's geometry tree.
        motion: the instances' keys over the shutter (an entry without keys: an
            instance still at ``to_object``'s inverse), or None when none has keys; a
            trace then takes each ray's time.
    """

    records: Any
    root: int
    top_base: int
    to_object: Any
    group_root: Any
    groups: GroupSlots | None = None
    motion: KeyTable | None = None


@dataclass
class GroupSlots:
    """The geometry trees' part of :attr:`TwoLevel.records`, kept from frame to frame.

    Attributes:
        records: Float, their slots one tree after the other from slot 0.
        roots: reference of each tree's root (Python ints).
        slots: how many slots they take.
        keys: the Dr.Jit variables of each tree's arrays (a refit or rebuild changes
            them: the slots are then packed again).
        roots_box: each tree's root box (:func:`hlbvh.kernels.instances.root_boxes`).
        room: slots kept behind the trees' for the top level, which is written there.
    """

    records: Any
    roots: list
    slots: int
    keys: tuple
    roots_box: tuple
    room: int


def select_ray(mask, a: Ray, b: Ray) -> Ray:
    """Per lane, ray ``a`` where ``mask``, else ``b``."""
    pick = lambda x, y: dr.select(mask, x, y)  # noqa: E731
    return Ray(o=pick(a.o, b.o), inv_d=pick(a.inv_d, b.inv_d),
               perm=tuple((pick(x0, y0), pick(x1, y1))
                          for (x0, x1), (y0, y1) in zip(a.perm, b.perm)),
               o_p=[pick(x, y) for x, y in zip(a.o_p, b.o_p)],
               shear=tuple(pick(x, y) for x, y in zip(a.shear, b.shear)))


def _object_ray(two_level: TwoLevel, world_o, world_d, k, mask, time=None) -> Ray:
    """The world ray in the object space of instance ``k`` (lanes of ``mask``); an
    instance with keys: through the inverse of its pose at the ray's ``time`` (Float in
    [0, 1] over the shutter), a pose without inverse (a scale of 0 at that time) giving
    a ray of NaN, which nothing hits (:data:`hlbvh.kernels.srt.FLAT`)."""
    ns = namespace_of(world_o.x)
    m = [dr.gather(ns.Float, two_level.to_object, k * 12 + i, mask) for i in range(12)]
    if two_level.motion is not None:
        keyed = two_level.motion.keyed(k, mask)
        moved = inverse_or_nan(two_level.motion.rows_at(k, time, keyed))
        m = [dr.select(keyed, a, b) for a, b in zip(moved, m)]
    o = ns.Array3f(*(dr.fma(m[3 * r], world_o.x, dr.fma(m[3 * r + 1], world_o.y,
                                                         dr.fma(m[3 * r + 2], world_o.z, m[9 + r])))
                     for r in range(3)))
    d = ns.Array3f(*(dr.fma(m[3 * r], world_d.x, dr.fma(m[3 * r + 1], world_d.y,
                                                         m[3 * r + 2] * world_d.z))
                     for r in range(3)))
    return ray_setup(o, d)


def enter_instance(query, rec, s, at_instance, keys):
    """One traversal step's instance entry (``query`` and ``s``: the traversal's query
    and loop state): lanes at an instance slot take its object-space ray and descend
    into its tree; below that they push a return marker and, when the leaf holds more
    instances, the rest of the leaf. Returns the keys to push (the other lanes' as they
    were)."""
    ns = namespace_of(s.cur)
    UInt32 = ns.UInt32
    two = query.two_level
    k = dr.reinterpret_array(UInt32, rec[TRI_FACE])
    ray = dr.if_stmt(
        args=(k, at_instance), cond=at_instance,
        true_fn=lambda k, mask: _object_ray(two, query.world_o, query.world_d, k, mask,
                                            query.time),
        false_fn=lambda k, mask: s.ray, arg_labels=("k", "mask"),
        label="hlbvh_enter_instance", mode="symbolic")
    s.ray = select_ray(at_instance, ray, s.ray)
    s.inst = dr.select(at_instance, k, s.inst)
    root = dr.gather(UInt32, two.group_root, k, at_instance)
    rest = s.cur + 1 < s.end
    left = leaf_ref(s.cur + 1, dr.select(rest, s.end - s.cur - 1, 1))
    marker = dr.full(UInt32, RETURN_REF, query.n)
    entered = (query.entry_of(root, s.node_t), query.entry_of(marker, query.no_t),
               dr.select(rest, query.entry_of(left, s.node_t), query.miss), query.miss)
    return tuple(dr.select(at_instance, e, key) for e, key in zip(entered, keys))
