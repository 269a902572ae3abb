"""What the two binned-SAH layouts (:mod:`hlbvh.kernels.sah.node_lanes`, one lane per
node, and :mod:`hlbvh.kernels.sah.item_lanes`, one lane per item) share: the tree they
return, its staging records, the binning of a centroid, and the plane sweep's
arithmetic (a side grown by a bin, its cost share, a plane's cost, the key that orders
planes), written once so both layouts choose the same plane bit for bit.

The sweep (Wald 2007): per node and axis, the ``bins - 1`` planes between adjacent bins
are priced with the surface area heuristic ``A(L)·W(L) + A(R)·W(R)``. A forward walk
stores the left side's share ``A(L)·W(L)`` of every plane (:func:`side_cost`), a
backward walk grows the right side and prices the plane (:func:`plane_cost`); the
cheapest plane with weight on both sides wins, the first in (axis, plane) order on
ties: the least :func:`plane_key`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from ..arrays import pack_halves
from ..geometry import half_area

#: Most bins per axis (a node's occupied bins are a 64-bit mask).
MAX_BINS = 64

#: Split code of a node split at the middle index of its range (no SAH plane).
MIDDLE = 0xFFFFFFFF

#: The key of no plane (above every :func:`plane_key`).
NO_PLANE = 0xFFFFFFFFFFFFFFFF

#: Floats per node record in the staging buffer: lo.xyz, hi.xyz, first, count.
RECORD = 8
#: Offsets of a staged record's fields: box corners, first child or slot, item count.
RECORD_LO, RECORD_HI, RECORD_FIRST, RECORD_COUNT = 0, 3, 6, 7


@dataclass
class SahTree:
    """A binary tree over items, in the node layout of :mod:`hlbvh.kernels.bvh`.

    Root at index 0, the two children of a node adjacent and at larger indices than
    their parent; nodes are numbered level by level (all nodes of depth ``d`` precede
    those of depth ``d+1``). ``T`` is the node count, ``n_items`` the item count.

    Attributes:
        node_first: UInt32[T]; internal node: index of its left child (the right child
            is ``node_first + 1``); leaf: first slot of its items in ``item_order``.
        node_count: UInt32[T]; 0 for an internal node, else the leaf's item count
            (slots ``node_first .. node_first + node_count - 1``).
        node_min: Array3f[T]; lower corner of the union of the node's item boxes.
        node_max: Array3f[T]; upper corner of that union.
        item_order: UInt32[n_items]; slot -> item index. Every item has exactly one
            slot; a leaf owns a contiguous range of slots, and so does every subtree.
        levels: list of UInt32 arrays, the internal nodes of depth 0, 1, 2, ... (root
            first; empty when the root is a leaf; not evaluated yet when the tree was
            built one lane per node: evaluate each on its own).
        leaf_depth: UInt32[T]; the depth of every node (root 0).
        depth: number of node levels (1 for a single leaf).
    """

    node_first: Any
    node_count: Any
    node_min: Any
    node_max: Any
    item_order: Any
    levels: list
    leaf_depth: Any
    depth: int

    @property
    def size(self) -> int:
        """Number of nodes ``T``."""
        return dr.width(self.node_count)


def write_records(ns, records, index, box_lo, box_hi, first, count, active=True):
    """One wide scatter of node records (lo, hi, first, count) at node ``index``."""
    as_float = lambda u: dr.reinterpret_array(ns.Float, ns.UInt32(u))
    value = ns.ArrayXf([box_lo.x, box_lo.y, box_lo.z, box_hi.x, box_hi.y, box_hi.z,
                        as_float(first), as_float(count)])
    dr.scatter(records, value, index, active)


def record_fields(ns, rec):
    """``(lo, hi, first, count)`` of gathered records ``rec`` (``RECORD`` rows)."""
    lo, hi = (ns.Array3f(*(rec[at + a] for a in range(3))) for at in (RECORD_LO, RECORD_HI))
    first, count = (dr.reinterpret_array(ns.UInt32, rec[at]) for at in (RECORD_FIRST, RECORD_COUNT))
    return lo, hi, first, count


def tree_from_records(ns, records, block_start, item_order, levels) -> SahTree:
    """The :class:`SahTree` of the node ``records`` (``RECORD`` floats a node), whose
    depth ``d`` nodes are ``block_start[d] .. block_start[d + 1] - 1``."""
    node_total = block_start[-1]
    rec = dr.gather(ns.ArrayXf, records, dr.arange(ns.UInt32, node_total),
                    shape=(RECORD, node_total))
    marks = dr.zeros(ns.UInt32, node_total)
    if len(block_start) > 2:
        dr.scatter(marks, ns.UInt32(1), ns.UInt32(block_start[1:-1]))
    node_min, node_max, node_first, node_count = record_fields(ns, rec)
    tree = SahTree(
        node_first=node_first,
        node_count=node_count,
        node_min=node_min,
        node_max=node_max,
        item_order=item_order,
        levels=levels,
        leaf_depth=dr.cumsum(marks),
        depth=len(block_start) - 1,
    )
    dr.eval(tree.node_first, tree.node_count, tree.node_min, tree.node_max,
            tree.item_order, tree.leaf_depth)
    return tree


def box_centroid(lo, hi):
    """Centre of a box (the point that is binned)."""
    return (lo + hi) * 0.5


def bin_index(ns, c, cmin, cmax, bins: int):
    """Bin of centroid coordinate ``c`` among ``bins`` equal slices of [cmin, cmax]."""
    extent = cmax - cmin
    f = (c - cmin) / extent * bins
    f = dr.select((extent > 0) & (f < bins), f, dr.select(extent > 0, bins - 1, 0))
    return ns.UInt32(f)


# ---- The plane sweep's arithmetic ----


def extent_scale(box_lo, box_hi):
    """``1 / largest extent`` of a node's box (1 for a point): extents are scaled by it
    before areas are taken, so costs neither overflow nor underflow at any scale."""
    extent = box_hi - box_lo
    largest = dr.maximum(extent.x, dr.maximum(extent.y, extent.z))
    return dr.select(largest > 0, 1 / largest, 1)


def grow(lo, hi, w, c_lo, c_hi, c_w):
    """A side ``(lo, hi, w)`` grown by a bin's box ``(c_lo, c_hi)`` and weight ``c_w``."""
    return dr.minimum(lo, c_lo), dr.maximum(hi, c_hi), w + c_w


def side_cost(Float, lo, hi, w, s):
    """A side's share ``A·W`` of a plane's cost (extents scaled by ``s``)."""
    return half_area((hi - lo) * s) * Float(w)


def plane_cost(Float, lo, hi, w, s, left_cost):
    """The cost of a plane: the right side's share (``lo, hi, w``) plus the left's."""
    return dr.fma(half_area((hi - lo) * s), Float(w), left_cost)


def plane_key(UInt32, cost, code):
    """UInt64: the key of a plane of ``cost`` (finite, >= 0: its bits order as the
    floats do) and split code ``axis·bins + bin``; the least key is the plane chosen."""
    return pack_halves(dr.reinterpret_array(UInt32, cost), code)


def cheaper(best, key, cost, left_weight, right_weight):
    """``best`` or the plane ``key`` of ``cost``, whichever is chosen: a plane counts
    when both sides hold weight and its cost is finite, and the least key wins."""
    valid = (left_weight > 0) & (right_weight > 0) & (cost < dr.inf)
    return dr.select(valid & (key < best), key, best)
