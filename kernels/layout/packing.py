"""Packing a tree into the slots traversal reads (:mod:`hlbvh.kernels.layout.slots`), and
what is kept between packs (:class:`PackState`, the packer's entry in ``Tree.kept``): the
slots of each place, the placement of the tree's shape
(:mod:`hlbvh.kernels.layout.placement`), and slots written elsewhere for a place (a fused
refit's, :func:`hand_over`).

A tree as the builder returned it (``bvh.built_topology`` matches its arrays) is packed
from its own levels without validation; any other is validated first
(:mod:`hlbvh.kernels.layout.validation`).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

from ..arrays import namespace_of
from ..tree import Tree
from .placement import Placement, placement
from .slots import SLOT, is_leaf, node_rows, triangle_rows


@dataclass
class PackState:
    """What the packer keeps for one tree between calls (``tree.kept_state(PackState)``,
    :func:`pack_state`). Every entry but ``last`` is a pair ``(key, value)`` (or None),
    the key naming the Dr.Jit variables (and the place) it was made for: an entry is
    used only while its key still matches.

    Attributes:
        records: ``(arrays and place, (records, root))``: the packed slots
            (:func:`packed_records`).
        plan: ``((topology, slot base), Placement)``: where each node and triangle goes
            (:func:`hlbvh.kernels.layout.placement.placement`); a refit keeps it.
        last: ``(slot_base, face_base, front)`` of the last pack meant for tracing:
            where a fused refit writes its slots.
        ready: ``(arrays and place, records)``: slots written elsewhere for that place
            (:func:`hand_over`), taken as they are by the next pack there.
    """

    records: tuple | None = None
    plan: tuple | None = None
    last: tuple | None = None
    ready: tuple | None = None


def pack_state(tree: Tree) -> PackState:
    """The packer's :class:`PackState` of ``tree`` (empty before its first pack)."""
    return tree.kept_state(PackState)


def hand_over(tree: Tree, place: tuple, records):
    """Keep ``records``, the slots of ``tree`` as it is now written elsewhere for
    ``place`` (``(slot_base, face_base, front)``: a fused refit writes them), for the
    next pack at that place to take as they are."""
    pack_state(tree).ready = ((arrays_key(tree),) + place, records)


def packed_records(bvh: Tree, slot_base: int = 0, face_base: int = 0):
    """The packed slots of ``bvh`` (:mod:`hlbvh.kernels.layout.slots`), built on first use
    and kept in its :class:`PackState` (keyed by the Dr.Jit variables of its arrays, so a
    refit, which assigns new arrays, repacks on the next call, from the placement kept
    for the tree's shape).

    Args:
        bvh: the BVH.
        slot_base: the slot the records will start at (references count from there:
            see :func:`hlbvh.kernels.layout.joined`).
        face_base: added to every face index.

    Returns:
        ``(records, root)``: Float (``SLOT`` per slot) and the Python int reference of
        the root.
    Raises:
        ValueError: an empty tree, one deeper than ``MAX_DEPTH`` levels, a leaf of more
            than ``MAX_LEAF_SIZE`` triangles, more than ``MAX_SLOTS`` slots, or a
            corrupt tree (a child or leaf range outside its arrays, a node reached twice
            or never, a slot in no leaf or in two).
    """
    key = arrays_key(bvh) + (slot_base, face_base)
    state = pack_state(bvh)
    kept = state.records
    if kept is not None and kept[0] == key:
        return kept[1]
    records = pack(bvh, slot_base, face_base, check=not is_built(bvh))
    state.records = (key, records)
    return records


def arrays_key(bvh: Tree) -> tuple:
    """The Dr.Jit variables of every array the slots are packed from."""
    arrays = (bvh.node_min, bvh.node_max, bvh.node_first, bvh.node_count, bvh.prim_ids,
              bvh.tri_p0, bvh.tri_p1, bvh.tri_p2)
    return tuple(c.index for a in arrays for c in (a if dr.depth_v(a) > 1 else (a,)))


def is_built(bvh: Tree) -> bool:
    """Whether ``bvh`` is a tree as the builder returned it (``built_topology`` still
    matches its arrays)."""
    return bvh.built_topology is not None and bvh.built_topology == bvh.topology_key()


def check_tree(bvh: Tree):
    """Validate ``bvh`` as :func:`packed_records` validates a tree made by hand, whoever
    made it (the tests call it on every builder's trees, whose packing skips it).

    Raises:
        ValueError: as :func:`packed_records`.
    """
    pack(bvh, 0, 0, check=True)


def pack(bvh: Tree, slot_base: int, face_base: int, check: bool, front: int = 0):
    """``(records, root)`` of ``bvh`` (see :func:`packed_records`), validated first when
    ``check``; the records start with ``front`` slots left for the caller to fill.

    Where each node and triangle goes depends on the tree's shape only, so it is kept on
    the tree (``PackState.plan``, keyed by :meth:`Tree.topology_key` and ``slot_base``): a refit,
    which changes boxes and triangles only, is packed again without the per-level
    passes that place the nodes. A pack that validates (``check``) places anew."""
    if bvh.size == 0 or bvh.prim_count == 0:
        raise ValueError("BVH is empty: build it from at least one triangle")
    plan_key = (bvh.topology_key(), slot_base)
    state = pack_state(bvh)
    plan = state.plan
    if check or plan is None or plan[0] != plan_key:
        plan = state.plan = (plan_key, placement(bvh, slot_base, check))
    placed: Placement = plan[1]
    root = int(placed.ref[0])
    if not check:  # (a validation, e.g. check_tree, is not where the tree is traced)
        state.last = (slot_base, face_base, front)  # where a refit writes its slots
    ready = state.ready
    place = (slot_base, face_base, front)
    if not check and ready is not None and ready[0] == (arrays_key(bvh),) + place:
        state.ready = None  # handed over: the caller may write into its front
        return ready[1], root
    return _write_records(bvh, placed, face_base, front), root



def _write_records(bvh, placed: Placement, face_base, front):
    """The slots of ``bvh`` placed as ``placed`` says, after ``front`` slots left for
    the caller."""
    ref, wide, at, record_of, total = (placed.ref, placed.wide, placed.at, placed.record_of,
                                       placed.total)
    ns = namespace_of(bvh.node_count)
    UInt32, Float, ArrayXf = ns.UInt32, ns.Float, ns.ArrayXf
    n_prims = bvh.prim_count
    # Not zeroed: the wide nodes and triangles write every slot whole (check_layout
    # refuses a hand-made tree for which they would not; check_tree, a builder's).
    records = dr.empty(Float, SLOT * (front + total))
    front = dr.opaque(UInt32, front)

    # ---- Wide nodes: children's boxes and references ----
    if dr.width(wide):
        rows = _wide_rows(bvh, UInt32(bvh.node_first), ref, wide)
        # Each scatter into one target is a kernel of its own: the rows are gathered
        # once, not once per slot.
        dr.eval(rows)
        dr.scatter(records, ArrayXf(rows[:SLOT]), at + front)
        dr.scatter(records, ArrayXf(rows[SLOT:]), at + front + 1)

    # ---- Triangles: each slot's record where its leaf stands ----
    slot = dr.arange(UInt32, n_prims)
    p = [dr.gather(ns.Array3f, q, slot) for q in (bvh.tri_p0, bvh.tri_p1, bvh.tri_p2)]
    dr.scatter(records, ArrayXf(triangle_rows(p, bvh.prim_ids, face_base)), record_of + front)
    dr.eval(records)
    return records



#: Floats per node in the packing's staging records: lo.xyz, hi.xyz, reference, first.
_NODE_RECORD = 8
#: Offsets of a staged record's fields.
_STAGED_LO, _STAGED_HI, _STAGED_REF, _STAGED_FIRST = 0, 3, 6, 7


def _wide_rows(bvh, first, ref, wide):
    """The 32 floats of each wide node in ``wide`` (:mod:`hlbvh.kernels.layout.slots`).

    Every node's box, reference and first child are staged first as one 32-byte record
    (one coherent pass over the nodes), so a wide node reads each of its binary and
    grandchildren with one packet gather: node numbers are far apart in a large tree,
    and six box coordinates in six arrays were six cache misses a child (measured in
    docs/decisions.md#packing)."""
    ns = namespace_of(first)
    UInt32, Float = ns.UInt32, ns.Float
    n = dr.width(first)
    as_float = lambda u: dr.reinterpret_array(Float, UInt32(u))
    staged = dr.empty(Float, _NODE_RECORD * n)
    dr.scatter(staged, ns.ArrayXf([*bvh.node_min, *bvh.node_max, as_float(ref),
                                   as_float(first)]), dr.arange(UInt32, n))
    dr.eval(staged)

    def node_at(node, active=True):
        """(lo, hi, reference, first) of the staged records ``node``."""
        r = dr.gather(ns.ArrayXf, staged, node, active, shape=(_NODE_RECORD, dr.width(node)))
        lo, hi = (ns.Array3f(*(r[at + a] for a in range(3))) for at in (_STAGED_LO, _STAGED_HI))
        return (lo, hi, dr.reinterpret_array(UInt32, r[_STAGED_REF]),
                dr.reinterpret_array(UInt32, r[_STAGED_FIRST]))

    children = []
    left = dr.gather(UInt32, first, wide)
    for side in (0, 1):
        c_lo, c_hi, c_ref, c_first = node_at(left + side)
        c_internal = ~is_leaf(c_ref)
        # An internal child (odd depth) hands over its two children; a leaf stays.
        g_lo, g_hi, g_ref, _ = node_at(c_first, c_internal)
        children.append((dr.select(c_internal, g_lo, c_lo), dr.select(c_internal, g_hi, c_hi),
                         dr.ones(ns.Bool, dr.width(wide)), dr.select(c_internal, g_ref, c_ref)))
        g_lo, g_hi, g_ref, _ = node_at(c_first + 1, c_internal)
        children.append((g_lo, g_hi, c_internal, g_ref))
    return node_rows(children)

