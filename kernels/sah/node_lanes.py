"""The binned SAH one lane per node (:func:`build_by_node_lanes`): the same tree as
one lane per item (:mod:`hlbvh.kernels.sah.item_lanes`), for few items (the HLBVH top
level's coarse clusters, small meshes).

Every level is one kernel whose lanes are the children made by the level above (the
root first): each writes its node record, and an open one (more than ``leaf_items``
items) bins its items in local memory, sweeps the planes and partitions its slot range
in one go. The kernel is traced once and replayed (``dr.freeze``): every array it takes
has a size fixed by the item count ``n`` (a level has at most ``n`` children, a tree at
most ``n - 1`` internal nodes), the level's own width enters as an opaque value, so
every level of every build of ``n`` items matches the same recording. A level then
costs one replay, a prefix sum and one host read (how many nodes are open) instead of
about twenty launches. A lane works through its items one after the other, so this
pays while nodes are small: the root lane alone reads every item twice.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

from ..arrays import Array3f, Float, UInt32, low_half, namespace_of
from .planes import (NO_PLANE, RECORD, SahTree, bin_index, box_centroid, cheaper,
                     extent_scale, grow, plane_cost, plane_key, side_cost,
                     tree_from_records, write_records)

#: Floats per child row: lo.xyz, hi.xyz, centroid min.xyz and max.xyz, first slot, item
#: count (the bits of UInt32s), two zeros.
_CHILD = 16
#: Offsets of a child row's fields.
_CHILD_LO, _CHILD_HI, _CHILD_CMIN, _CHILD_CMAX, _CHILD_FIRST, _CHILD_COUNT = 0, 3, 6, 9, 12, 13


def build_by_node_lanes(ns, lo, hi, weight, leaf_items: int, bins: int) -> SahTree:
    """:func:`hlbvh.kernels.sah.binned_sah` one lane per node, a level a kernel.

    Args:
        ns: the backend's namespace; lo, hi: Array3f[n] item boxes (plain); weight:
            UInt32[n]; leaf_items, bins: as ``binned_sah`` takes them.
    """
    UInt32, Float = ns.UInt32, ns.Float
    n = dr.width(lo)
    centroid = box_centroid(lo, hi)
    records = dr.empty(Float, RECORD * (2 * n - 1))
    # Written as items reach their leaves (a root leaf keeps its items in input order).
    item_order = dr.empty(UInt32, n) if n > leaf_items else dr.arange(UInt32, n)
    # Read by one level, written for the next: slot -> item in the open nodes' ranges,
    # the children's rows and open flags (the first `width` entries in use; room for an
    # even count, as the two children of a node are written as one packet).
    slots = [dr.arange(UInt32, n), dr.empty(UInt32, n)]
    room = n + n % 2
    rows = [dr.empty(Float, _CHILD * room), dr.empty(Float, _CHILD * room)]
    flags = [dr.empty(UInt32, room), dr.empty(UInt32, room)]
    level_ids = dr.empty(UInt32, n)  # the internal nodes, level after level

    # ---- The root: the one child of a level above the tree ----
    root = dr.zeros(UInt32, 1)
    dr.scatter(rows[0], ns.ArrayXf(_child_rows(
        ns, [dr.min(lo, axis=1), dr.max(hi, axis=1), dr.min(centroid, axis=1),
             dr.max(centroid, axis=1)], dr.opaque(UInt32, 0), dr.opaque(UInt32, n))), root)
    # Opaque, so the top level (leaves of one cluster) and a static tree (leaves of
    # two triangles) replay one compiled kernel rather than one each.
    leaf_items = dr.opaque(UInt32, leaf_items)
    dr.scatter(flags[0], UInt32(dr.opaque(UInt32, n) > leaf_items), root)
    # Every input evaluated, so that all levels meet the frozen kernel in one state.
    dr.eval(centroid, item_order, slots, rows, flags, level_ids)
    levels, block_start, width, internal = [], [0], 1, 0
    while True:
        through = dr.cumsum(flags[0])  # inclusive: an open child's rank is through - 1
        opened = int(through[width - 1])
        block, next_block = block_start[-1], block_start[-1] + width
        block_start.append(next_block)
        sizes = [dr.opaque(UInt32, v) for v in (block, next_block, width, internal)]
        if not opened:
            _write_block(rows[0], flags[0], through, records, *sizes[:3])
            dr.eval(records)
            break
        _FROZEN_LEVEL(_Level(rows[0], flags[0], through, *sizes, lo, hi, centroid, weight,
                             records, *slots, item_order, rows[1], flags[1], level_ids,
                             leaf_items, bins))
        levels.append(dr.gather(UInt32, level_ids, dr.arange(UInt32, opened) + sizes[3]))
        width, internal = 2 * opened, internal + opened
        slots.reverse(), rows.reverse(), flags.reverse()
    return tree_from_records(ns, records, block_start, item_order, levels)


@dataclass
class _Node:
    """The node of each lane, as its row in the level above says: box, centroid bounds
    (Array3f), first slot and item count (UInt32)."""

    box_lo: Array3f
    box_hi: Array3f
    cmin: Array3f
    cmax: Array3f
    first: UInt32
    count: UInt32


def _child_fields(ns, row) -> _Node:
    """The :class:`_Node` of gathered child rows ``row`` (``_CHILD`` rows)."""
    box = [ns.Array3f(*(row[at + a] for a in range(3)))
           for at in (_CHILD_LO, _CHILD_HI, _CHILD_CMIN, _CHILD_CMAX)]
    first, count = (dr.reinterpret_array(ns.UInt32, row[at]) for at in (_CHILD_FIRST, _CHILD_COUNT))
    return _Node(*box, first, count)


def _child_rows(ns, bounds, first, count):
    """The ``_CHILD`` floats of children with ``bounds`` (box lo, hi, centroid min,
    max: Array3f each), first slot and item count."""
    as_float = lambda u: dr.reinterpret_array(ns.Float, ns.UInt32(u))
    zero = dr.zeros(ns.Float, dr.width(first))
    return [c for b in bounds for c in b] + [as_float(first), as_float(count), zero, zero]


def _write_block(rows, is_open, through, records, block, next_block, width):
    """Write the node records of the first ``width`` children of ``rows``, ``is_open``
    (``through``: the inclusive prefix of ``is_open``) from node ``block`` on; return
    ``(lane, open_lane, rank, node)``: each lane's open flag, rank among the open
    children, and :class:`_Node`."""
    ns = namespace_of(rows)
    UInt32 = ns.UInt32
    lane = dr.arange(UInt32, dr.width(is_open))
    valid = lane < width
    node = _child_fields(ns, dr.gather(ns.ArrayXf, rows, lane, valid, shape=(_CHILD, dr.width(lane))))
    open_lane = valid & (is_open == 1)
    rank = through - 1
    index = dr.select(valid, block + lane, 0)
    write_records(ns, records, index, node.box_lo, node.box_hi,
                  dr.select(open_lane, next_block + 2 * rank, node.first),
                  dr.select(open_lane, 0, node.count), valid)
    return lane, open_lane, rank, node


@dataclass
class _Level:
    """What one level of :func:`build_by_node_lanes` reads and writes: the frozen
    kernel's one argument (``dr.freeze`` takes a dataclass's fields as it takes
    positional arrays, and sees the ones the kernel writes in place).

    Attributes:
        rows, is_open, through: this level's children as the level above wrote them:
            Float (``_CHILD`` per child), UInt32 open flags and their inclusive prefix.
        block, next_block, width, internal: opaque UInt32: the level's first node, the
            next level's, its number of children, the internal nodes before it.
        lo, hi, centroid: Array3f (n): the items' boxes and centroids.
        weight: UInt32 (n): the items' weights.
        records: Float: the node records, written.
        slots_in, slots_out: UInt32 (n): slot -> item in the open nodes' ranges, read
            for this level and written for the next.
        item_order: UInt32 (n): the final slot of each item that reached a leaf, written.
        rows_out, is_open_out: the next level's children and open flags, written.
        level_ids: UInt32 (n): the internal nodes, written from ``internal`` on.
        leaf_items: opaque UInt32: most items in a leaf.
        bins: bins per axis.
    """

    rows: Float
    is_open: UInt32
    through: UInt32
    block: UInt32
    next_block: UInt32
    width: UInt32
    internal: UInt32
    lo: Array3f
    hi: Array3f
    centroid: Array3f
    weight: UInt32
    records: Float
    slots_in: UInt32
    slots_out: UInt32
    item_order: UInt32
    rows_out: Float
    is_open_out: UInt32
    level_ids: UInt32
    leaf_items: UInt32
    bins: int


def _node_level(level: _Level):
    """One level of :func:`build_by_node_lanes`, one kernel: the block's records, its
    open nodes split, the next block's rows and open flags, the open nodes' ids (at
    ``internal`` on in ``level_ids``)."""
    ns = namespace_of(level.rows)
    UInt32 = ns.UInt32
    lane, open_lane, rank, node = _write_block(level.rows, level.is_open, level.through,
                                               level.records, level.block, level.next_block,
                                               level.width)
    first, count = node.first, node.count
    left, right, n_left = _split_nodes(
        ns, (level.lo, level.hi, level.centroid, level.weight, level.slots_in),
        level.slots_out, level.item_order, open_lane, node, level.leaf_items, level.bins)
    dr.scatter(level.rows_out,
               ns.ArrayXf(_child_rows(ns, left, first, n_left)
                          + _child_rows(ns, right, first + n_left, count - n_left)),
               rank, open_lane)
    dr.scatter(level.is_open_out, ns.ArrayXu([UInt32(n_left > level.leaf_items),
                                              UInt32(count - n_left > level.leaf_items)]),
               rank, open_lane)
    dr.scatter(level.level_ids, level.block + lane, level.internal + rank, open_lane)
    dr.eval(level.records, level.item_order, level.slots_out, level.rows_out,
            level.is_open_out, level.level_ids)


#: Recorded once per item-count parity (and bins) and replayed: every input
#: opaque (with auto_opaque, a new item count recorded the root level anew each build).
_FROZEN_LEVEL = dr.freeze(_node_level, limit=256, warn_after=1 << 30, auto_opaque=False)


def _split_nodes(ns, items, slots_out, item_order, active, node: _Node, leaf_items, bins: int):
    """One lane per node (the lanes ``active``): bin the items of slots ``first ..
    first + count - 1`` (``slots_in``) on the three axes, price every plane, partition
    the range stably into the two children (an item whose child is a leaf, of at most
    ``leaf_items`` items, an opaque UInt32, gets its final slot in ``item_order``, the
    others go to ``slots_out``).

    The cost of a plane and the choice among planes are those of the item-lane sweep
    (:mod:`hlbvh.kernels.sah.planes`: the cheapest plane leaving weight on both sides,
    the first in (axis, plane) order on ties, reported as the last occupied bin on its
    left; a middle split when there is none); here every bin is a cell, and an empty
    bin changes no union or sum.

    Args:
        items: ``(lo, hi, centroid, weight, slots_in)``: the items' boxes, centroids and
            weights, and slot -> item in the open nodes' ranges.
    Returns ``(left, right, n_left)``: each child's bounds (box lo, hi, centroid min,
    max) and the left child's item count.
    """
    UInt32, Float = ns.UInt32, ns.Float
    cells = 3 * bins
    s = extent_scale(node.box_lo, node.box_hi)
    end = dr.select(active, node.first + node.count, node.first)
    # Local memory, carried through every loop's state (a loop that only writes local
    # memory would otherwise be optimised away). Per cell (axis a, bin b at a·bins + b):
    # box (lo.xyz, -hi.xyz), weight, items; per plane after bin p (a·bins + p): the left
    # side's cost share, weight, items, and its last occupied bin.
    mem = (dr.alloc_local(Float, 6 * cells, Float(dr.inf)),
           dr.alloc_local(UInt32, cells, UInt32(0)), dr.alloc_local(UInt32, cells, UInt32(0)),
           dr.alloc_local(Float, cells), dr.alloc_local(UInt32, cells),
           dr.alloc_local(UInt32, cells), dr.alloc_local(UInt32, cells))

    def item_at(q):
        """(item, box lo, hi, centroid, bins on the three axes) of slot ``q``."""
        lo, hi, centroid, _, slots_in = items
        item = dr.gather(UInt32, slots_in, q)
        i_lo, i_hi = dr.gather(ns.Array3f, lo, item), dr.gather(ns.Array3f, hi, item)
        c = dr.gather(ns.Array3f, centroid, item)
        return item, i_lo, i_hi, c, [bin_index(ns, c[a], node.cmin[a], node.cmax[a], bins)
                                     for a in range(3)]

    mem = _bin_items(ns, item_at, items[3], node.first, end, mem, bins)
    # Full-width start values made from an input, not from a width: a size baked into
    # the frozen kernel would tie its recording to one item count.
    zeros = dr.minimum(node.first, dr.opaque(UInt32, 0))
    inf = ns.Array3f(Float(zeros) + dr.inf)
    empty = (inf, -inf)
    best, mem = _sweep_bins(ns, mem, active, s, zeros, empty, bins)
    middle = best == NO_PLANE
    code = low_half(best)
    n_left = dr.select(middle, node.count // 2, mem[5].read(code, active & ~middle))
    plane = (middle, code // bins, code % bins)
    left, right = _partition(ns, item_at, slots_out, item_order, node, end, plane, n_left,
                             leaf_items, zeros, empty)
    return left, right, n_left


def _bin_items(ns, item_at, weight, first, end, mem, bins):
    """Every item of slots ``first .. end - 1`` into its cell on each axis: the cells'
    boxes (lo, -hi), weights and item counts in local memory ``mem``."""
    UInt32 = ns.UInt32

    def bin_item(q, mem):
        cell_box, cell_weight, cell_items = mem[:3]
        item, i_lo, i_hi, _, b = item_at(q)
        w = dr.gather(UInt32, weight, item)
        for a in range(3):
            cell = a * bins + b[a]
            for j, v in enumerate((i_lo.x, i_lo.y, i_lo.z, -i_hi.x, -i_hi.y, -i_hi.z)):
                cell_box.write(dr.minimum(cell_box.read(6 * cell + j), v), 6 * cell + j)
            cell_weight.write(cell_weight.read(cell) + w, cell)
            cell_items.write(cell_items.read(cell) + 1, cell)
        return q + 1, mem

    _, mem = dr.while_loop(mode="symbolic", state=(UInt32(first), mem),
                           cond=lambda q, mem: q < end, body=bin_item, labels=("q", "mem"))
    return mem


def _read_cell(ns, mem, cell):
    """(lo, hi, weight) of the local-memory cell ``cell``."""
    r = [mem[0].read(6 * cell + j) for j in range(6)]
    return ns.Array3f(r[0], r[1], r[2]), -ns.Array3f(r[3], r[4], r[5]), mem[1].read(cell)


@dataclass
class _Side:
    """One side of the planes on one axis, grown a bin at a time (a sweep's loop state)."""

    lo: Array3f  # the union of its bins' boxes
    hi: Array3f
    w: UInt32  # their summed weight
    items: UInt32 | None = None  # their item count (forward sweep only)
    last: UInt32 | None = None  # the last occupied bin (forward sweep only)


def _sweep_bins(ns, mem, active, s, zeros, empty, bins):
    """The plane sweep over a lane's bins on all three axes: ``(best, mem)``, the least
    :func:`~hlbvh.kernels.sah.planes.plane_key` (all ones when no plane qualifies) and
    the local memory with every plane's left side stored."""
    UInt32, Float = ns.UInt32, ns.Float

    # ---- Forward: the left side of the plane after bin p is bins 0..p ----
    def forward(p, mem, sides):
        left_cost, left_weight, left_items, left_bin = mem[3:]
        for a, side in enumerate(sides):
            cell = a * bins + p
            side.lo, side.hi, side.w = grow(side.lo, side.hi, side.w, *_read_cell(ns, mem, cell))
            items = mem[2].read(cell)
            side.items, side.last = side.items + items, dr.select(items > 0, p, side.last)
            left_cost.write(side_cost(Float, side.lo, side.hi, side.w, s), cell)
            left_weight.write(side.w, cell)
            left_items.write(side.items, cell)
            left_bin.write(side.last, cell)
        return p + 1, mem, sides

    p, mem, _ = dr.while_loop(
        mode="symbolic", state=(zeros, mem, [_Side(*empty, zeros, zeros, zeros) for _ in range(3)]),
        cond=lambda p, mem, sides: active & (p + 1 < bins), body=forward,
        labels=("p", "mem", "left"))

    # ---- Backward: the plane before bin p, its right side bins p..bins-1 ----
    def backward(p, best, mem, sides):
        left_cost, left_weight, _, left_bin = mem[3:]
        for a, side in enumerate(sides):
            cell = a * bins + p
            side.lo, side.hi, side.w = grow(side.lo, side.hi, side.w, *_read_cell(ns, mem, cell))
            before = cell - 1
            cost = plane_cost(Float, side.lo, side.hi, side.w, s, left_cost.read(before))
            best = cheaper(best, plane_key(UInt32, cost, a * bins + left_bin.read(before)),
                           cost, left_weight.read(before), side.w)
        return p - 1, best, mem, sides

    # (p is bins - 1 in the active lanes: where the forward pass stopped)
    never = ns.UInt64(zeros) | NO_PLANE
    _, best, mem, _ = dr.while_loop(
        mode="symbolic", state=(p, never, mem, [_Side(*empty, zeros) for _ in range(3)]),
        cond=lambda p, best, mem, sides: active & (p > 0), body=backward,
        labels=("p", "best", "mem", "right"))
    return best, mem


@dataclass
class _Bounds:
    """A child's bounds, grown an item at a time (the partition's loop state)."""

    box_lo: Array3f  # the union of its items' boxes
    box_hi: Array3f
    cmin: Array3f  # the bounds of its items' centroids
    cmax: Array3f

    def grown(self, mine, i_lo, i_hi, c):
        """Grown by the item of box ``(i_lo, i_hi)``, centroid ``c`` where ``mine``."""
        return _Bounds(dr.select(mine, dr.minimum(self.box_lo, i_lo), self.box_lo),
                       dr.select(mine, dr.maximum(self.box_hi, i_hi), self.box_hi),
                       dr.select(mine, dr.minimum(self.cmin, c), self.cmin),
                       dr.select(mine, dr.maximum(self.cmax, c), self.cmax))


def _partition(ns, item_at, slots_out, item_order, node: _Node, end, plane, n_left, leaf_items,
               zeros, empty):
    """Move the items of the lane's range to its children, left items first, each side
    in slot order (an item whose child is a leaf to ``item_order``, the others to
    ``slots_out``); ``plane`` is ``(middle, axis, bin)``. Returns the children's bounds
    (box lo, hi, centroid min, max), left then right."""
    UInt32 = ns.UInt32
    first, count = node.first, node.count
    middle, axis, split_bin = plane
    to_leaf = (n_left <= leaf_items, count - n_left <= leaf_items)

    def partition(q, n_l, n_r, children):
        item, i_lo, i_hi, c, b = item_at(q)
        goes_left = dr.select(middle, q - first < count // 2,
                              dr.select(axis == 0, b[0], dr.select(axis == 1, b[1], b[2])) <= split_bin)
        to = dr.select(goes_left, first + n_l, first + n_left + n_r)
        leafward = dr.select(goes_left, to_leaf[0], to_leaf[1])
        dr.scatter(item_order, item, to, leafward)
        dr.scatter(slots_out, item, to, ~leafward)
        children = [child.grown(mine, i_lo, i_hi, c)
                    for child, mine in zip(children, (goes_left, ~goes_left))]
        return q + 1, n_l + UInt32(goes_left), n_r + UInt32(~goes_left), children

    *_, children = dr.while_loop(
        mode="symbolic",
        state=(UInt32(first), zeros, zeros, [_Bounds(*empty, *empty) for _ in range(2)]),
        cond=lambda q, n_l, n_r, children: q < end, body=partition,
        labels=("q", "n_l", "n_r", "children"))
    return [[b.box_lo, b.box_hi, b.cmin, b.cmax] for b in children]
