"""Refit: new vertex positions, same faces, same tree: recompute the triangles in slot
order and the boxes only. A tree packed for traversal before is refit and repacked in one
go (:func:`refit_packed`, the *fused* refit: its slots written in the same passes as its
boxes, where it was last packed); any other through its binary levels
(:func:`hlbvh.kernels.bounds.node_bounds`)."""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from typing import Any

import drjit as dr

from .arrays import Array3f, Array3u, Float, namespace_of
from .bounds import node_bounds, sah_cost
from .geometry import (BOX_RECORD, box_records, checked_vertices, slot_triangles,
                       triangles_of)
from .layout.packing import hand_over, is_built, pack_state
from .layout.placement import Placement
from .layout.slots import SLOT, TRI_HI, TRI_LO, box_rows, node_rows, triangle_rows
from .tree import Tree


@dataclass
class RefitState:
    """What the refit keeps for one tree between calls (``tree.kept_state(RefitState)``),
    each entry a pair ``(key, value)`` (or None) used only while its key still matches.

    Attributes:
        faces: ``(faces and order, (Array3u[F], largest index))``: each slot's face's
            vertex indices (:func:`slot_faces`).
        plan: ``(placement key, _RefitPlan)``: where the fused refit reads each box from
            (:func:`refit_packed`).
    """

    faces: tuple | None = None
    plan: tuple | None = None


def refit(bvh: Tree, vertices: Float | Array3f) -> Tree:
    """Update ``bvh`` in place for new vertex positions.

    Args:
        bvh: a :class:`hlbvh.kernels.tree.Tree`.
        vertices: flat Float (3·V) or Array3f (V), the same V as the build's or more
            (the faces decide which are read).
    Returns:
        ``bvh``, with its triangles, boxes, ``stats.sah_cost`` and
        ``stats.stage_ms['refit']`` updated.
    """
    t0 = time.perf_counter()
    faces, top = slot_faces(bvh)
    points = checked_vertices(vertices, bvh.faces, top)
    if not refit_packed(bvh, points, faces):
        tri, boxes = slot_triangles(triangles_of(points, faces))
        bvh.tri_p0, bvh.tri_p1, bvh.tri_p2 = tri[0], tri[1], tri[2]
        bvh.node_min, bvh.node_max = node_bounds(
            bvh.node_first, bvh.node_count, boxes, bvh.levels, bvh.config.leaf_size
        )
    dr.sync_thread()
    bvh.stats.stage_ms["refit"] = (time.perf_counter() - t0) * 1e3
    bvh.stats.sah_cost = functools.partial(sah_cost, bvh.node_min, bvh.node_max, bvh.node_count)
    return bvh


def slot_faces(bvh: Tree):
    """``(Array3u[F], int)``: the vertex indices of each slot's face and the largest of
    them, computed on the first refit and kept for ``bvh`` (``RefitState.faces``, keyed by
    its ``faces`` and ``prim_ids`` arrays), so that a refit reads three vertices a slot rather than its
    face first, and checks the vertex count without a pass over the faces."""
    key = (bvh.faces.index, bvh.prim_ids.index)
    state = bvh.kept_state(RefitState)
    kept = state.faces
    if kept is None or kept[0] != key:
        faces = dr.gather(namespace_of(bvh.faces).Array3u, bvh.faces, bvh.prim_ids)
        largest = dr.max(bvh.faces)
        dr.eval(faces, largest)
        kept = state.faces = (key, (faces, int(largest[0])))
    return kept[1]


# ---- The fused refit: boxes and slots in one pass over the wide levels ----


def refit_packed(bvh: Tree, points: Float, slot_faces: Array3u, key: tuple | None = None) -> bool:
    """Refit ``bvh`` for new vertex ``points`` and write its slots in the same passes,
    where it was last packed (:func:`_write_packed`). The BVH's triangle arrays are left
    as lazy reads of ``points`` (computed only if read).

    A refit through the binary tree and a pack after it write the triangles in slot order
    and read them again, and walk the binary levels twice (boxes, then wide nodes); this
    walks the wide levels once and never stores the slot-order triangles.

    Args:
        bvh: a tree as the builder returned it, packed before (else nothing is done).
        points: flat Float[3·V] vertex positions, checked.
        slot_faces: Array3u[F], the vertex indices of each slot's face.
        key: ``(records, keys, k)``: write the slots as key ``k`` of a keyed tree's
            ``records`` instead (slot ``s`` at ``s·keys + k``,
            :mod:`hlbvh.kernels.keyed`); the node boxes and the slots kept for the next
            pack are then left as they were.
    Returns:
        Whether it refit ``bvh`` (False: the caller refits through the binary tree).
    """
    packed = pack_state(bvh)
    last, plan = packed.last, packed.plan
    if last is None or plan is None or not is_built(bvh) or \
            plan[0] != (bvh.topology_key(), last[0]):
        return False
    ns = namespace_of(bvh.node_count)
    p = [dr.gather(ns.Array3f, points, slot_faces[k]) for k in range(3)]
    bvh.tri_p0, bvh.tri_p1, bvh.tri_p2 = p  # lazy: computed only if read
    _write_packed(bvh, last, plan, points, slot_faces, key)
    return True


def _write_packed(bvh, place, plan, points, slot_faces, key=None):
    """The slots of ``bvh`` at ``place`` and its node boxes: one pass over the leaves
    (each leaf's lane writes its triangles' records and takes the union of their boxes)
    and one per wide level (deepest first). Boxes move as 8-float records, one packet
    gather each, not as six scalar gathers.

    Sets ``bvh.node_min``/``node_max`` and hands the slots over to the next
    :func:`~hlbvh.kernels.layout.packing.packed_records` or
    :func:`~hlbvh.kernels.layout.joined` that asks for ``place``
    (:func:`~hlbvh.kernels.layout.packing.hand_over`). (Used by a refit: for a new build,
    whose placement and plan are made anew, this measured no faster than the binary bounds
    and a pack; see docs/decisions.md#refit.)

    Args:
        bvh: a tree as the builder returned it (its shape only is read).
        place: ``(slot_base, face_base, front)`` as
            :func:`hlbvh.kernels.layout.packing.pack` takes them.
        plan: the tree's placement at ``slot_base`` (``PackState.plan``).
        points: flat Float[3·V] vertex positions.
        slot_faces: Array3u[F], the vertex indices of each slot's face.
        key: as :func:`refit_packed`'s.
    """
    _, face_base, front = place
    total = plan[1].total
    ns = namespace_of(bvh.node_count)
    UInt32, Float, ArrayXf = ns.UInt32, ns.Float, ns.ArrayXf
    refit = _refit_plan(bvh, plan)
    if key is None:
        records = dr.empty(Float, SLOT * (front + total))
        front_o = dr.opaque(UInt32, front)
        stride, at = 1, (lambda slot: slot + front_o)
    else:  # slot s of key k at s·keys + k (the place's front and base are 0 there)
        records, stride, k = key
        k = dr.opaque(UInt32, k)
        at = lambda slot: slot * stride + k  # noqa: E731

    # ---- Leaves: their triangles' records, and the union of their boxes ----
    boxes = dr.empty(Float, BOX_RECORD * bvh.size)  # every node's box, a record each
    leaf_node, leaf_record, leaf_count, leaf_slot, widest = refit.leaves
    lo, hi = _leaf_triangles(records, points, slot_faces, bvh.prim_ids, face_base,
                             leaf_slot, at(leaf_record), leaf_count, widest, stride)
    dr.scatter(boxes, ArrayXf(box_rows(lo, hi)), leaf_node)
    dr.eval(records, boxes)

    # ---- Wide nodes, deepest level first: rows from their children's boxes ----
    for nodes, slots, children in reversed(refit.wide_levels):
        rows, own = _wide_level_rows(boxes, nodes, children)
        # Read (and every gather of `boxes` released) before writing into it: a pending
        # read would make the scatter copy the array. One scatter a target: each is a
        # kernel of its own.
        dr.eval(rows, own)
        dr.scatter(records, ArrayXf(rows[:SLOT]), at(slots))
        dr.scatter(records, ArrayXf(rows[SLOT:]), at(slots) + stride)
        dr.scatter(boxes, ArrayXf(own), nodes)
        dr.eval(records, boxes)
    if key is not None:
        return

    # ---- Every node's box in one pass: a binary node at odd depth (no record of its
    # own) is the union of its two children, the others their own record ----
    node = dr.arange(UInt32, bvh.size)
    left = dr.select(refit.odd, bvh.node_first, node)
    (a_lo, a_hi), (b_lo, b_hi) = (box_records(boxes, c) for c in (left, left + UInt32(refit.odd)))
    bvh.node_min = dr.minimum(a_lo, b_lo)
    bvh.node_max = dr.maximum(a_hi, b_hi)
    dr.eval(bvh.node_min, bvh.node_max)
    hand_over(bvh, place, records)


def _leaf_triangles(records, points, slot_faces, prim_ids, face_base, first_slot,
                    first_record, count, widest, stride=1):
    """Write the triangle records of leaves (slots ``first_slot ..``, ``count`` of
    them, records from ``first_record`` on, ``stride`` apart) and return the union of
    their boxes, ``(lo, hi)`` Array3f per leaf: one lane a leaf walks its triangles (a
    symbolic loop, so the record scatter is one kernel with the boxes, and no record is
    read back).
    Every lane takes ``widest`` steps (the most triangles in a leaf, a UInt32[1]): a
    short leaf repeats its last triangle, writing the same record again, because the
    masked gathers of lanes that stopped early cost more."""
    ns = namespace_of(first_slot)
    Array3f, n = ns.Array3f, dr.width(first_slot)
    last = count - 1

    def body(k, lo, hi):
        j = dr.minimum(k, last)
        slot = first_slot + j
        face = dr.gather(ns.Array3u, slot_faces, slot)
        p = [dr.gather(Array3f, points, face[c]) for c in range(3)]
        rows = triangle_rows(p, dr.gather(ns.UInt32, prim_ids, slot), face_base)
        dr.scatter(records, ns.ArrayXf(rows), first_record + (j if stride == 1 else j * stride))
        return (k + 1, dr.minimum(lo, Array3f(*rows[TRI_LO:TRI_LO + 3])),
                dr.maximum(hi, Array3f(*rows[TRI_HI:TRI_HI + 3])))

    _, lo, hi = dr.while_loop(
        mode="symbolic",
        state=(dr.zeros(ns.UInt32, n), dr.full(Array3f, dr.inf, n), dr.full(Array3f, -dr.inf, n)),
        cond=lambda k, lo, hi: k < widest, body=body, labels=("k", "lo", "hi"))
    return lo, hi


def _wide_level_rows(boxes, nodes, children):
    """The 32 floats of the wide ``nodes`` and their own box rows, from their
    ``children`` ``(node, present, reference)`` whose box records are in ``boxes``."""
    rows_of = []
    for child, present, child_ref in children:
        # An absent child reads child 0's box, then dropped: an unmasked packet gather
        # costs far less than a masked one.
        rows_of.append((*box_records(boxes, child), present, child_ref))
    # Child 0 is always there; the others only widen the box where present.
    lo, hi = rows_of[0][0], rows_of[0][1]
    for c_lo, c_hi, present, _ in rows_of[1:]:
        lo = dr.select(present, dr.minimum(lo, c_lo), lo)
        hi = dr.select(present, dr.maximum(hi, c_hi), hi)
    return node_rows(rows_of), box_rows(lo, hi)



@dataclass
class _RefitPlan:
    """Where the fused refit (:func:`refit_packed`) reads each box from, kept per tree:
    ``leaves`` (node, first record, count and first slot of every leaf, and the most
    triangles in one, a UInt32[1]), ``wide_levels`` (per wide level, root first: its
    nodes, their first slots, and per child ``(node, present, reference)``), ``odd``
    (per node: whether it is internal at an odd depth)."""

    leaves: tuple
    wide_levels: list
    odd: Any


def _refit_plan(bvh, plan) -> _RefitPlan:
    """The :class:`_RefitPlan` of ``bvh`` for its placement ``plan``, made on the first
    fused refit and kept while the placement is (``RefitState.plan``)."""
    state = bvh.kept_state(RefitState)
    kept = state.plan
    if kept is not None and kept[0] == plan[0]:
        return kept[1]
    ns = namespace_of(bvh.node_count)
    UInt32 = ns.UInt32
    placed: Placement = plan[1]
    ref, record_of, total = placed.ref, placed.record_of, placed.total
    slot_base = dr.opaque(UInt32, plan[0][1])
    first, count = UInt32(bvh.node_first), UInt32(bvh.node_count)
    levels = []
    for nodes in bvh.levels[0::2]:
        left = dr.gather(UInt32, first, nodes)
        children = []
        for side in (0, 1):
            # As packing._wide_rows orders them: an internal binary child hands over its two.
            b = left + side
            internal = dr.gather(UInt32, count, b) == 0
            g = dr.gather(UInt32, first, b, internal)
            c0 = dr.select(internal, g, b)
            for node, present in ((c0, dr.full(ns.Bool, True, dr.width(b))), (g + 1, internal)):
                children.append((dr.select(present, node, c0), present,
                                 dr.gather(UInt32, ref, node, present)))
        slots = dr.gather(UInt32, ref, nodes) - slot_base  # a wide node's ref is its slot
        dr.eval(slots, children)
        levels.append((nodes, slots, children))
    # The leaves in the order of their records (a leaf's record is its first slot's).
    leaf = count > 0
    by_record = dr.zeros(UInt32, total)
    leaf_record = dr.gather(UInt32, record_of, first, leaf)
    dr.scatter(by_record, dr.arange(UInt32, bvh.size) + 1, leaf_record, leaf)
    leaf_record = dr.compress(by_record != 0)  # record positions, ascending
    leaf_node = dr.gather(UInt32, by_record, leaf_record) - 1
    leaf_count = dr.gather(UInt32, count, leaf_node)
    leaves = (leaf_node, leaf_record, leaf_count, dr.gather(UInt32, first, leaf_node),
              dr.max(leaf_count))
    odd = dr.zeros(ns.Bool, bvh.size)
    for level in bvh.levels[1::2]:
        dr.scatter(odd, True, level)
    dr.eval(leaves, odd)
    result = _RefitPlan(leaves=leaves, wide_levels=levels, odd=odd)
    state.plan = (plan[0], result)
    return result

