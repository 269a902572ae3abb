"""The binned SAH one lane per item (:func:`build_by_item_lanes`): every level of the
tree in about twenty launches whatever its node count, for inputs too large for one
lane per node (:mod:`hlbvh.kernels.sah.node_lanes`) to pay. A level's steps are those of
:mod:`hlbvh.kernels.sah`: bin (a scatter-reduction per (node, axis, bin) into *cells*,
only occupied bins stored in nodes of fewer than ``bins`` items), sweep (one lane per
(node, axis) over its cells, the arithmetic of :mod:`hlbvh.kernels.sah.planes`),
partition (a prefix sum over the items' left/right decisions), emit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from ..arrays import Array3f, Float, UInt32, high_half, low_half, pack_halves
from .planes import (MIDDLE, NO_PLANE, RECORD, SahTree, bin_index, box_centroid, cheaper,
                     extent_scale, grow, plane_cost, plane_key, side_cost,
                     tree_from_records, write_records)

#: Scatter-reductions pre-reduce equal targets within a SIMD packet, then use atomics
#: (measured faster than plain atomics here). ReduceMode.Expand, which Auto picks for
#: small targets on LLVM, bakes the target's size into the kernel: every level and every
#: new input size would compile new kernels.
_MODE = dr.ReduceMode.Local

#: Bits of an item's bin on one axis in its packed bins (bins <= 64 fit).
_BIN_BITS = 8


def build_by_item_lanes(ns, lo, hi, weight, leaf_items: int, bins: int) -> SahTree:
    """:func:`hlbvh.kernels.sah.binned_sah` one lane per item, a level at a time.

    Args:
        ns: the backend's namespace; lo, hi: Array3f[n] item boxes (plain); weight:
            UInt32[n]; leaf_items, bins: as ``binned_sah`` takes them.
    """
    n = dr.width(lo)
    # ---- Root: one node over every item, in input order ----
    root_lo, root_hi = dr.min(lo, axis=1), dr.max(hi, axis=1)
    centroid = box_centroid(lo, hi)
    root_open = n > leaf_items
    records = dr.empty(ns.Float, RECORD * (2 * n - 1))
    write_records(ns, records, dr.opaque(ns.UInt32, 0), root_lo, root_hi,
                  dr.opaque(ns.UInt32, 1 if root_open else 0),
                  dr.opaque(ns.UInt32, 0 if root_open else n))
    item_order = dr.empty(ns.UInt32, n) if root_open else dr.arange(ns.UInt32, n)
    level = _Level(
        size=1 if root_open else 0,
        node_id=dr.opaque(ns.UInt32, 0),
        slot_first=dr.opaque(ns.UInt32, 0),
        act_first=dr.opaque(ns.UInt32, 0),
        count=dr.opaque(ns.UInt32, n),
        box_lo=root_lo,
        box_hi=root_hi,
        cmin=dr.min(centroid, axis=1),
        cmax=dr.max(centroid, axis=1),
        item=dr.arange(ns.UInt32, n),
        node=dr.zeros(ns.UInt32, n),
        item_lo=lo,
        item_hi=hi,
        item_weight=weight,
    )

    # ---- Split all open nodes of a level at once, until none is left ----
    levels = []
    block_start = [0, 1]  # first node index of each depth's block, and one past the end
    while level.size:
        levels.append(level.node_id)
        level = _split_level(ns, level, records, item_order, block_start, leaf_items, bins)

    return tree_from_records(ns, records, block_start, item_order, levels)


@dataclass
class _Level:
    """The ``size`` open nodes of one depth and the items they hold.

    Per open node (UInt32[size] / Array3f[size]): ``node_id`` its index in the tree,
    ``slot_first`` its first slot in ``item_order``, ``act_first`` its first position in
    the active item arrays, ``count`` its item count, ``box_lo``/``box_hi`` its box,
    ``cmin``/``cmax`` the bounds of its items' centroids. Per active item (UInt32[m],
    grouped by node, in slot order): ``item`` the item index, ``node`` the position of
    its node in this level.
    """

    size: int
    node_id: UInt32 = None
    slot_first: UInt32 = None
    act_first: UInt32 = None
    count: UInt32 = None
    box_lo: Array3f = None
    box_hi: Array3f = None
    cmin: Array3f = None
    cmax: Array3f = None
    item: UInt32 = None
    node: UInt32 = None
    item_lo: Array3f = None
    item_hi: Array3f = None
    item_weight: Float = None


@dataclass
class _Cells:
    """The binned items of one level. A (node, axis) lane ``3·node + axis`` owns
    ``count`` cells from ``first`` on, one per bit of ``occupied`` (its occupied bins,
    or all bins when the node has at least ``bins`` items), in bin order; a cell holds
    the union of its items' boxes (``box``, Float[6·cells] of lo.xyz, -hi.xyz) and
    their summed ``weight``."""

    occupied: Any  # UInt64[3K]
    count: Any  # UInt32[3K]
    first: Any  # UInt32[3K]
    box: Any
    weight: Any


def _split_level(ns, level: _Level, records, item_order, block_start, leaf_items: int,
                 bins: int) -> _Level:
    """Split every open node of ``level``: write the children's node records and the
    slots of the items that reached a leaf; return the next level's open nodes."""
    K = level.size
    # first node index of the children's and of the grandchildren's blocks (opaque)
    starts = ns.UInt32(block_start[-1], block_start[-1] + 2 * K)
    child_start, grandchild_start = (dr.gather(ns.UInt32, starts, i) for i in range(2))
    block_start.append(block_start[-1] + 2 * K)

    # ---- Bin and sweep: the split of every node ----
    centroid = box_centroid(level.item_lo, level.item_hi)
    packed_bins, cells = _bin(ns, level, level.item_lo, level.item_hi, centroid,
                              level.item_weight, bins)
    split_key = _sweep(ns, cells, level, bins)

    # ---- Left/right decision of every item; ranks by a prefix sum ----
    items = _decide(ns, level, packed_bins, split_key, bins)

    # ---- Children: counts, slot ranges, open or leaf, next-level positions ----
    children = _children(ns, level, items, leaf_items)

    # ---- Partition: move every item to its child, reduce the children's bounds ----
    bounds, next_items = _partition(ns, level, items, children, centroid, item_order)

    # ---- Emit the children's node records and the next level's open nodes ----
    return _emit(ns, children, bounds, next_items, records, child_start, grandchild_start)


def _pack_bins(item_bin):
    """UInt32: an item's bins on the three axes, axis ``a``'s in bits ``8a .. 8a+7``."""
    return item_bin[0] | (item_bin[1] << _BIN_BITS) | (item_bin[2] << (2 * _BIN_BITS))


def _bin_on(packed_bins, axis):
    """The bin on ``axis`` (an int or a UInt32 in 0..2) of :func:`_pack_bins`' words."""
    return (packed_bins >> (_BIN_BITS * axis)) & ((1 << _BIN_BITS) - 1)


@dataclass
class _Items:
    """The left/right decision of a level's active items (UInt32/Bool[m]): ``left``,
    ``goes_left`` (as 0/1), ``left_before`` (an exclusive prefix sum of it), each item's
    ``position`` and its node's first position ``act_first``."""

    left: Any
    goes_left: Any
    left_before: Any
    position: Any
    act_first: Any


def _decide(ns, level: _Level, packed_bins, split_key, bins: int) -> _Items:
    """Which child every active item goes to: by its bin on the split's axis, or by its
    position for a middle split."""
    position = dr.arange(ns.UInt32, dr.width(level.item))
    split = low_half(dr.gather(ns.UInt64, split_key, level.node))
    act_first = dr.gather(ns.UInt32, level.act_first, level.node)
    count = dr.gather(ns.UInt32, level.count, level.node)
    split_bin = _bin_on(packed_bins, dr.minimum(split // bins, 2))
    left = dr.select(split == MIDDLE,
                     (position - act_first) < count // 2,
                     split_bin <= split % bins)
    goes_left = ns.UInt32(left)
    left_before = dr.prefix_sum(goes_left)
    dr.eval(goes_left, left_before)
    return _Items(left, goes_left, left_before, position, act_first)


@dataclass
class _Children:
    """The ``2K`` children of a level's nodes (UInt32/Bool[2K], left then right of each
    node): ``child`` 0..2K-1, their item counts, first slots and whether they are open
    (more than ``leaf_items`` items); ``open_and_items`` and its inclusive prefix sum
    ``through`` (open children in the high half, their items in the low one), and the
    next level's node and item counts ``K_next``, ``m_next``."""

    child: Any
    count: Any
    slot: Any
    open: Any
    open_and_items: Any
    through: Any
    K_next: int
    m_next: int

    def next_position(self, c):
        """(next-level index, first active position) of the open children ``c``."""
        UInt64 = type(self.through)
        before = dr.gather(UInt64, self.through, c) - dr.gather(UInt64, self.open_and_items, c)
        return high_half(before), low_half(before)


def _children(ns, level: _Level, items: _Items, leaf_items: int) -> _Children:
    """Counts, slot ranges, open or leaf, and next-level positions of the children."""
    K = level.size
    child = dr.arange(ns.UInt32, 2 * K)
    parent = child >> 1
    is_right = (child & 1) == 1
    p_first = dr.gather(ns.UInt32, level.act_first, parent)
    p_count = dr.gather(ns.UInt32, level.count, parent)
    p_last = p_first + p_count - 1
    n_left = (dr.gather(ns.UInt32, items.left_before, p_last)
              + dr.gather(ns.UInt32, items.goes_left, p_last)
              - dr.gather(ns.UInt32, items.left_before, p_first))
    c_count = dr.select(is_right, p_count - n_left, n_left)
    c_slot = dr.gather(ns.UInt32, level.slot_first, parent) + dr.select(is_right, n_left, 0)
    c_open = c_count > leaf_items
    # one inclusive prefix sum counts both: open children (high half), their items (low)
    open_and_items = pack_halves(ns.UInt32(c_open), dr.select(c_open, c_count, 0))
    dr.eval(c_count, c_slot, c_open, open_and_items)
    through = dr.cumsum(open_and_items)
    total = through[2 * K - 1]
    return _Children(child, c_count, c_slot, c_open, open_and_items, through,
                     high_half(total), low_half(total))


def _partition(ns, level: _Level, items: _Items, children: _Children, centroid, item_order):
    """Move every item to its child (its final slot in ``item_order`` when the child is
    a leaf, the next level's active arrays otherwise) and reduce the children's boxes
    and centroid bounds. Returns ``(bounds, next_items)``: Float[12·2K] (per child a box
    record then a centroid-bounds record, :func:`_reduce_box`) and the next level's
    ``(item, node, item_lo, item_hi, item_weight)`` (None when no child is open)."""
    left, left_before, position, act_first = (items.left, items.left_before, items.position,
                                              items.act_first)
    left_rank = left_before - dr.gather(ns.UInt32, left_before, act_first)
    rank = dr.select(left, left_rank, (position - act_first) - left_rank)
    c = level.node * 2 + dr.select(left, 0, 1)
    to_open = dr.gather(ns.Bool, children.open, c)
    dr.scatter(item_order, level.item, dr.gather(ns.UInt32, children.slot, c) + rank, ~to_open)
    bounds = dr.full(ns.Float, dr.inf, 12 * dr.width(children.child))
    _reduce_box(bounds, level.item_lo, level.item_hi, 2 * c)
    _reduce_box(bounds, centroid, centroid, 2 * c + 1, to_open)
    next_items = None
    if children.K_next:
        index, first = children.next_position(c)
        moved = (level.item, index, level.item_lo, level.item_hi, level.item_weight)
        next_items = tuple(dr.empty(type(x), children.m_next) for x in moved)
        for target, value in zip(next_items, moved):
            dr.scatter(target, value, first + rank, to_open)
    dr.eval()
    return bounds, next_items


def _emit(ns, children: _Children, bounds, next_items, records, child_start,
          grandchild_start) -> _Level:
    """Write the children's node records (at ``child_start`` on; an open child's
    children at ``grandchild_start`` on) and return the next level's open nodes."""
    child, c_open = children.child, children.open
    box_lo, box_hi = _read_box(ns, bounds, 2 * child)
    next_index = children.next_position(child)[0]
    write_records(ns, records, child_start + child, box_lo, box_hi,
                  dr.select(c_open, grandchild_start + 2 * next_index, children.slot),
                  dr.select(c_open, 0, children.count))
    if not children.K_next:
        dr.eval()
        return _Level(size=0)
    next_child = dr.empty(ns.UInt32, children.K_next)
    dr.scatter(next_child, child, next_index, c_open)
    dr.eval()
    box_lo, box_hi = _read_box(ns, bounds, 2 * next_child)
    cmin, cmax = _read_box(ns, bounds, 2 * next_child + 1)
    nxt = _Level(
        size=children.K_next,
        node_id=child_start + next_child,
        slot_first=dr.gather(ns.UInt32, children.slot, next_child),
        act_first=children.next_position(next_child)[1],
        count=dr.gather(ns.UInt32, children.count, next_child),
        box_lo=box_lo, box_hi=box_hi, cmin=cmin, cmax=cmax,
    )
    nxt.item, nxt.node, nxt.item_lo, nxt.item_hi, nxt.item_weight = next_items
    dr.eval(nxt.node_id, nxt.slot_first, nxt.act_first, nxt.count, nxt.box_lo, nxt.box_hi,
            nxt.cmin, nxt.cmax)
    return nxt


def _bin(ns, level: _Level, item_lo, item_hi, centroid, item_weight, bins: int):
    """Bin the active items of ``level`` on the three axes of their nodes.

    Returns:
        ``(packed_bins, cells)``: UInt32[m] with the item's bin on axis ``a`` in bits
        ``8a .. 8a+7``, and the level's :class:`_Cells`.
    """
    K, m = level.size, dr.width(level.item)
    cmin = dr.gather(ns.Array3f, level.cmin, level.node)
    cmax = dr.gather(ns.Array3f, level.cmax, level.node)
    item_bin = [bin_index(ns, centroid[a], cmin[a], cmax[a], bins) for a in range(3)]
    packed_bins = _pack_bins(item_bin)

    # ---- Occupied bins of the nodes of fewer than `bins` items (others: all bins) ----
    occupied = dr.zeros(ns.UInt64, 3 * K)
    small = dr.gather(ns.UInt32, level.count, level.node) < bins
    for a in range(3):
        dr.scatter_reduce(dr.ReduceOp.Or, occupied, ns.UInt64(1) << ns.UInt64(item_bin[a]),
                          level.node * 3 + a, small, mode=_MODE)
    dr.eval(packed_bins)
    item_bin = [_bin_on(packed_bins, a) for a in range(3)]
    big = dr.gather(ns.UInt32, level.count, dr.arange(ns.UInt32, 3 * K) // 3) >= bins
    occupied = dr.select(big, (1 << bins) - 1, occupied)
    n_cells = ns.UInt32(dr.popcnt(occupied))
    dr.eval(occupied, n_cells)
    first = dr.prefix_sum(n_cells)

    # ---- Per cell: union of the items' boxes and their summed weight ----
    size = 3 * min(bins * K, m)  # no fewer than the cells in use, without reading them
    cell_box = dr.full(ns.Float, dr.inf, 6 * size)
    cell_weight = dr.zeros(ns.UInt32, size)
    for a in range(3):
        lane = level.node * 3 + a
        below = dr.gather(ns.UInt64, occupied, lane) & ((ns.UInt64(1) << ns.UInt64(item_bin[a])) - 1)
        cell = dr.gather(ns.UInt32, first, lane) + ns.UInt32(dr.popcnt(below))
        _reduce_box(cell_box, item_lo, item_hi, cell)
        dr.scatter_reduce(dr.ReduceOp.Add, cell_weight, item_weight, cell, mode=_MODE)
    dr.eval()
    return packed_bins, _Cells(occupied, n_cells, first, cell_box, cell_weight)


def _sweep(ns, cells: _Cells, level: _Level, bins: int):
    """Per node (UInt64[K]): a key whose low half is the split code ``axis·bins + p``
    of the cheapest plane ``p`` (bins 0..p on the left) that leaves both sides
    non-empty, the first in (axis, plane) order on ties, or ``MIDDLE`` when no plane
    qualifies; the high half holds the plane's cost.

    One lane per (node, axis) walks its cells twice: forward to store the cost share of
    every left side, backward to price each plane with its right side. A plane between
    two occupied bins is reported as the last occupied bin on its left, the lowest of
    the planes that make the same partition. Extents are divided by the node's largest
    extent, so areas neither overflow nor underflow at extreme coordinates.
    """
    K = level.size
    lane = dr.arange(ns.UInt32, 3 * K)
    node = lane // 3
    s = extent_scale(dr.gather(ns.Array3f, level.box_lo, node),
                     dr.gather(ns.Array3f, level.box_hi, node))
    left_cost = dr.empty(ns.Float, dr.width(cells.weight))
    left_weight = dr.empty(ns.UInt32, dr.width(cells.weight))
    empty_box = (dr.full(ns.Array3f, dr.inf, 3 * K), dr.full(ns.Array3f, -dr.inf, 3 * K))

    def add_cell(q, lo, hi, w):
        """(lo, hi, w) grown by the lane's cell ``q``."""
        c_lo, c_hi = _read_box(ns, cells.box, cells.first + q)
        return grow(lo, hi, w, c_lo, c_hi, dr.gather(ns.UInt32, cells.weight, cells.first + q))

    # ---- Forward: the left side of the plane after cell q is cells 0..q ----
    def forward(q, lo, hi, w):
        lo, hi, w = add_cell(q, lo, hi, w)
        dr.scatter(left_cost, side_cost(ns.Float, lo, hi, w, s), cells.first + q)
        dr.scatter(left_weight, w, cells.first + q)
        return q + 1, lo, hi, w

    dr.while_loop(
        mode="symbolic",
        state=(dr.zeros(ns.UInt32, 3 * K), *empty_box, dr.zeros(ns.UInt32, 3 * K)),
        cond=lambda q, lo, hi, w: q + 1 < cells.count,
        body=forward,
        labels=("q", "lo", "hi", "w"),
    )

    # ---- Backward: the right side of the plane before cell q is cells q..end ----
    axis_code = (lane % 3) * bins

    def backward(q, bin_of_q, lo, hi, w, best):
        lo, hi, w = add_cell(q, lo, hi, w)
        last_left_bin = _highest_bit(ns, cells.occupied & ((ns.UInt64(1) << ns.UInt64(bin_of_q)) - 1))
        before = cells.first + q - 1
        cost = plane_cost(ns.Float, lo, hi, w, s, dr.gather(ns.Float, left_cost, before))
        best = cheaper(best, plane_key(ns.UInt32, cost, axis_code + last_left_bin), cost,
                       dr.gather(ns.UInt32, left_weight, before), w)
        return q - 1, last_left_bin, lo, hi, w, best

    *_, best = dr.while_loop(
        mode="symbolic",
        state=(cells.count - 1, _highest_bit(ns, cells.occupied), *empty_box,
               dr.zeros(ns.UInt32, 3 * K), dr.full(ns.UInt64, NO_PLANE, 3 * K)),
        cond=lambda q, *_: q > 0,
        body=backward,
        labels=("q", "bin_of_q", "lo", "hi", "w", "best"),
    )

    # ---- Per node the least (cost, axis, plane) of its three axes ----
    return dr.block_reduce(dr.ReduceOp.Min, best, 3)


def _highest_bit(ns, mask):
    """Index of the highest set bit of a non-zero UInt64 mask (UInt32)."""
    return ns.UInt32(63 - dr.lzcnt(mask))


def _reduce_box(target, box_lo, box_hi, index, active=True):
    """Min-reduce the box (lo.xyz, -hi.xyz) into the record ``target[6·index ..+5]``."""
    for j, value in enumerate((box_lo.x, box_lo.y, box_lo.z, -box_hi.x, -box_hi.y, -box_hi.z)):
        dr.scatter_reduce(dr.ReduceOp.Min, target, value, index * 6 + j, active, mode=_MODE)


def _read_box(ns, target, index):
    """The box (lo, hi) that :func:`_reduce_box` stored at ``index``."""
    r = [dr.gather(ns.Float, target, index * 6 + j) for j in range(6)]
    return ns.Array3f(r[0], r[1], r[2]), -ns.Array3f(r[3], r[4], r[5])

