"""Binned SAH build (Wald 2007, "On fast construction of SAH-based bounding volume
hierarchies"), top-down and breadth-first, as Dr.Jit array kernels.

One function, :func:`binned_sah`, serves both builders that need it:

- ``"hlbvh"`` builds the SAH top level over the coarse clusters (Pantaleoni & Luebke
  2010, section 4; :func:`top_level`): the items are clusters, each standing for many
  primitives;
- ``"sah"`` builds the whole tree over the triangles: the quality reference.

The tree grows one level at a time and every open node of a level is split at once:

1. *Bin.* Every item's centroid (the centre of its box) falls into one of ``bins``
   equal slices of its node's centroid bounds, on each axis. Per (node, axis, bin) a
   scatter-reduction accumulates the items' weight and the union of their boxes. Only
   occupied bins get storage (a *cell*) in nodes of fewer than ``bins`` items, so a
   level never stores more than three cells per item.
2. *Sweep.* Per node, the ``3·(bins-1)`` split planes between adjacent bins are
   priced with the surface area heuristic ``A(L)·W(L) + A(R)·W(R)`` (C_trav = C_isect
   = 1, ``W`` the summed item weight) and the cheapest plane that leaves both sides
   non-empty wins (the first in axis, then plane order on ties). A node with no such
   plane (all centroids equal, or every plane leaves one side empty) is split at the
   middle index of its item range instead.
3. *Partition.* A prefix sum over the left/right decision of every item gives each
   item its rank inside its child, so the two children own adjacent, contiguous slot
   ranges of ``item_order`` (a stable partition: items keep their relative order).
   The same pass scatter-reduces the children's boxes and centroid bounds.
4. *Emit.* Children get adjacent indices in the next level's block of nodes; a child
   of at most ``leaf_items`` items is a leaf, the others are the next level's open
   nodes. Every split has two non-empty children, so the build always ends.

The host runs only the loop over levels (the tree's depth). Per-level sizes and
offsets enter the kernels through ``dr.opaque``, so the same kernels serve every level
and every input size; min/max/integer reductions make the result bit-identical from
run to run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from .arrays import namespace_of, plain
from .geometry import BOX_RECORD, box_records

#: Most bins per axis (a node's occupied bins are a 64-bit mask).
MAX_BINS = 64

#: Inputs of at most this many items (the HLBVH top level's clusters, small meshes) are
#: split one lane per node, a level in one frozen kernel (:func:`_build_by_node_lanes`);
#: larger ones one lane per item, a level in about twenty launches (:func:`_split_level`).
#: Same trees. (Random boxes, one item a leaf, AMD EPYC 2 cores: 256 items 6 against
#: 36 ms, 4096 34 against 82, 65536 292 against 576.)
NODE_LANES_MAX_ITEMS = 1 << 16

#: Split code of a node split at the middle index of its range (no SAH plane).
_MIDDLE = 0xFFFFFFFF

#: Floats per child row of the node-lane build: lo.xyz, hi.xyz, centroid min.xyz and
#: max.xyz, first slot, item count (the bits of UInt32s), two zeros.
_CHILD = 16

#: Floats per node record in the staging buffer: lo.xyz, hi.xyz, first, count.
_RECORD = 8

#: Scatter-reductions pre-reduce equal targets within a SIMD packet, then use atomics
#: (measured faster than plain atomics here). ReduceMode.Expand, which Auto picks for
#: small targets on LLVM, bakes the target's size into the kernel: every level and every
#: new input size would compile new kernels.
_MODE = dr.ReduceMode.Local


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


def binned_sah(item_min, item_max, item_weight, leaf_items: int, bins: int = 16) -> SahTree:
    """Build a binary tree over boxed items with the binned surface area heuristic.

    Args:
        item_min: Array3f[n]; lower corner of each item's box (finite, ``<= item_max``).
        item_max: Array3f[n]; upper corner of each item's box.
        item_weight: UInt32[n]; how many primitives each item stands for (1 for a
            triangle, the primitive count for a coarse cluster). The cost of a split is
            ``area(L)·weight(L) + area(R)·weight(R)``. Items of weight 0 cost nothing
            and make no plane valid on their own.
        leaf_items: int >= 1; a node of at most this many items becomes a leaf, every
            larger node is split (the SAH top level of ``"hlbvh"`` passes 1).
        bins: int in 2..64; bins per axis. Centroids are binned in the node's centroid
            bounds: ``bin = min(floor((c - cmin) / (cmax - cmin) · bins), bins - 1)``
            (bin 0 on an axis of zero extent). Box extents are divided by the node's
            largest extent before areas are taken, so costs stay finite at any scale.

    Returns:
        A :class:`SahTree` whose arrays live on the backend of ``item_min``.

    Raises:
        TypeError: an input is not a Dr.Jit JIT array.
        ValueError: sizes differ, no items, or ``leaf_items`` / ``bins`` out of range.
    """
    n = _check_inputs(item_min, item_max, item_weight, leaf_items, bins)
    ns = namespace_of(item_min)
    lo = plain(item_min, "Array3f")
    hi = plain(item_max, "Array3f")
    weight = plain(item_weight, "UInt32")
    if n <= NODE_LANES_MAX_ITEMS:
        return _build_by_node_lanes(ns, lo, hi, weight, leaf_items, bins)

    # ---- Root: one node over every item, in input order ----
    root_lo, root_hi = dr.min(lo, axis=1), dr.max(hi, axis=1)
    centroid = _centroid(lo, hi)
    root_open = n > leaf_items
    records = dr.empty(ns.Float, _RECORD * (2 * n - 1))
    _write_records(ns, records, dr.opaque(ns.UInt32, 0), root_lo, root_hi,
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

    return _tree(ns, records, block_start, item_order, levels)


def _tree(ns, records, block_start, item_order, levels) -> SahTree:
    """The :class:`SahTree` of the node ``records`` (``_RECORD`` floats a node), whose
    depth ``d`` nodes are ``block_start[d] .. block_start[d + 1] - 1``."""
    node_total = block_start[-1]
    rec = dr.gather(ns.ArrayXf, records, dr.arange(ns.UInt32, node_total),
                    shape=(_RECORD, node_total))
    marks = dr.zeros(ns.UInt32, node_total)
    if len(block_start) > 2:
        dr.scatter(marks, ns.UInt32(1), ns.UInt32(block_start[1:-1]))
    tree = SahTree(
        node_first=dr.reinterpret_array(ns.UInt32, rec[6]),
        node_count=dr.reinterpret_array(ns.UInt32, rec[7]),
        node_min=ns.Array3f(rec[0], rec[1], rec[2]),
        node_max=ns.Array3f(rec[3], rec[4], rec[5]),
        item_order=item_order,
        levels=levels,
        leaf_depth=dr.cumsum(marks),
        depth=len(block_start) - 1,
    )
    dr.eval(tree.node_first, tree.node_count, tree.node_min, tree.node_max,
            tree.item_order, tree.leaf_depth)
    return tree


@dataclass
class TopLevel:
    """The HLBVH top level (Pantaleoni & Luebke 2010, section 4): a binned-SAH tree over
    the coarse clusters, one cluster per leaf.

    Attributes:
        tree: the :class:`SahTree` over the clusters (items = clusters).
        start, end: UInt32[C], each cluster's slot range ``[start, end)``.
        node, depth: UInt32[C], each cluster's leaf in ``tree`` and that leaf's depth:
            where the cluster's own sub-tree is rooted.
    """

    tree: SahTree
    start: Any
    end: Any
    node: Any
    depth: Any


def top_level(cluster_start, slot_boxes, bins: int = 16) -> TopLevel:
    """The SAH top level over clusters of contiguous slots.

    Args:
        cluster_start: UInt32[C], the first slot of each cluster, ascending, the first
            0 (the CSD sort's ``cluster_start``).
        slot_boxes: the primitives' boxes in slot order, packed records (Float[8·N],
            :func:`hlbvh.kernels.geometry.slot_triangles`).
        bins: bins per axis of the binned SAH.
    Returns:
        :class:`TopLevel`; the cluster boxes are the unions of their slots' boxes, the
        split cost weighs each cluster by its primitive count.
    """
    ns = namespace_of(cluster_start)
    UInt32 = ns.UInt32
    n, clusters = dr.width(slot_boxes) // BOX_RECORD, dr.width(cluster_start)
    after = dr.arange(UInt32, clusters) + 1
    last = after == dr.opaque(UInt32, clusters)
    end = dr.select(last, dr.opaque(UInt32, n), dr.gather(UInt32, cluster_start, after, ~last))

    # ---- Cluster boxes: one lane per cluster walks its slots (no atomics, no per-slot
    # cluster index) ----
    def grow(q, lo, hi):
        s_lo, s_hi = box_records(slot_boxes, q)
        return q + 1, dr.minimum(lo, s_lo), dr.maximum(hi, s_hi)

    _, lo, hi = dr.while_loop(
        mode="symbolic",
        state=(UInt32(cluster_start), dr.full(ns.Array3f, dr.inf, clusters),
               dr.full(ns.Array3f, -dr.inf, clusters)),
        cond=lambda q, lo, hi: q < end, body=grow, labels=("q", "lo", "hi"))
    dr.eval(lo, hi, end)

    # ---- SAH over the clusters; each cluster's leaf is its sub-tree's root ----
    tree = binned_sah(lo, hi, end - cluster_start, 1, bins)
    nodes = dr.arange(UInt32, tree.size)
    leaf = tree.node_count != 0
    leaf_cluster = dr.gather(UInt32, tree.item_order, tree.node_first, leaf)
    node, depth = dr.zeros(UInt32, clusters), dr.zeros(UInt32, clusters)
    dr.scatter(node, nodes, leaf_cluster, leaf)
    dr.scatter(depth, tree.leaf_depth, leaf_cluster, leaf)
    dr.eval(node, depth)
    return TopLevel(tree, cluster_start, end, node, depth)


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
    node_id: Any = None
    slot_first: Any = None
    act_first: Any = None
    count: Any = None
    box_lo: Any = None
    box_hi: Any = None
    cmin: Any = None
    cmax: Any = None
    item: Any = None
    node: Any = None
    item_lo: Any = None
    item_hi: Any = None
    item_weight: Any = None


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


def _build_by_node_lanes(ns, lo, hi, weight, leaf_items: int, bins: int) -> SahTree:
    """:func:`binned_sah` with one lane per node: the same tree, for few items.

    Every level is one kernel whose lanes are the children made by the level above (the
    root first): each writes its node record, and an open one (more than
    ``leaf_items`` items) bins its items in local memory, sweeps the planes and
    partitions its slot range in one go. The kernel is traced once and replayed
    (``dr.freeze``): every array it takes has a size fixed by the item count ``n`` (a
    level has at most ``n`` children, a tree at most ``n - 1`` internal nodes), the
    level's own width enters as an opaque value, so every level of every build of ``n``
    items matches the same recording. A level then costs one replay, a prefix sum and
    one host read (how many nodes are open) instead of about twenty launches. A lane
    works through its items one after the other, so this pays while nodes are small:
    the root lane alone reads every item twice.
    """
    UInt32, Float = ns.UInt32, ns.Float
    n = dr.width(lo)
    centroid = _centroid(lo, hi)
    records = dr.empty(Float, _RECORD * (2 * n - 1))
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
        _FROZEN_LEVEL(rows[0], flags[0], through, records, *sizes, lo, hi, centroid, weight,
                      *slots, item_order, rows[1], flags[1], level_ids, leaf_items, bins)
        levels.append(dr.gather(UInt32, level_ids, dr.arange(UInt32, opened) + sizes[3]))
        width, internal = 2 * opened, internal + opened
        slots.reverse(), rows.reverse(), flags.reverse()
    return _tree(ns, records, block_start, item_order, levels)


def _write_block(rows, is_open, through, records, block, next_block, width):
    """Write the node records of the first ``width`` children of ``rows``, ``is_open``
    (``through``: the inclusive prefix of ``is_open``) from node ``block`` on; return
    what the lanes read."""
    ns = namespace_of(rows)
    UInt32 = ns.UInt32
    lane = dr.arange(UInt32, dr.width(is_open))
    valid = lane < width
    row = dr.gather(ns.ArrayXf, rows, lane, valid, shape=(_CHILD, dr.width(lane)))
    box_lo, box_hi = ns.Array3f(row[0], row[1], row[2]), ns.Array3f(row[3], row[4], row[5])
    first, count = (dr.reinterpret_array(UInt32, row[k]) for k in (12, 13))
    open_lane = valid & (is_open == 1)
    rank = through - 1
    index = dr.select(valid, block + lane, 0)
    _write_records(ns, records, index, box_lo, box_hi,
                   dr.select(open_lane, next_block + 2 * rank, first),
                   dr.select(open_lane, 0, count), valid)
    node = ns.Array3f(row[6], row[7], row[8]), ns.Array3f(row[9], row[10], row[11])
    return lane, open_lane, rank, first, count, box_lo, box_hi, node


def _node_level(rows, is_open, through, records, block, next_block, width, internal, lo, hi,
                centroid, weight, slots_in, slots_out, item_order, rows_out, is_open_out,
                level_ids, leaf_items, bins):
    """One level of :func:`_build_by_node_lanes`, one kernel: the block's records, its
    open nodes split, the next block's rows and open flags, the open nodes' ids (at
    ``internal`` on in ``level_ids``)."""
    ns = namespace_of(rows)
    UInt32 = ns.UInt32
    lane, open_lane, rank, first, count, box_lo, box_hi, node = _write_block(
        rows, is_open, through, records, block, next_block, width)
    left, right, n_left = _split_nodes(ns, lo, hi, centroid, weight, slots_in, slots_out,
                                       item_order, open_lane, first, count, box_lo, box_hi,
                                       *node, leaf_items, bins)
    dr.scatter(rows_out, ns.ArrayXf(_child_rows(ns, left, first, n_left)
                                    + _child_rows(ns, right, first + n_left, count - n_left)),
               rank, open_lane)
    dr.scatter(is_open_out, ns.ArrayXu([UInt32(n_left > leaf_items),
                                        UInt32(count - n_left > leaf_items)]), rank, open_lane)
    dr.scatter(level_ids, block + lane, internal + rank, open_lane)
    dr.eval(records, item_order, slots_out, rows_out, is_open_out, level_ids)


#: Recorded once per item-count parity (and bins) and replayed: every input
#: opaque (with auto_opaque, a new item count recorded the root level anew each build).
_FROZEN_LEVEL = dr.freeze(_node_level, limit=256, warn_after=1 << 30, auto_opaque=False)


def _child_rows(ns, bounds, first, count):
    """The ``_CHILD`` floats of children with ``bounds`` (box lo, hi, centroid min,
    max: Array3f each), first slot and item count."""
    as_float = lambda u: dr.reinterpret_array(ns.Float, ns.UInt32(u))
    zero = dr.zeros(ns.Float, dr.width(first))
    return [c for b in bounds for c in b] + [as_float(first), as_float(count), zero, zero]


def _split_nodes(ns, lo, hi, centroid, weight, slots_in, slots_out, item_order, active,
                 first, count, box_lo, box_hi, cmin, cmax, leaf_items, bins: int):
    """One lane per node (the lanes ``active``): bin the items of slots ``first ..
    first + count - 1`` (``slots_in``) on the three axes, price every plane, partition
    the range stably into the two children (an item whose child is a leaf, of at most
    ``leaf_items`` items, an opaque UInt32, gets its final slot in ``item_order``, the
    others go to ``slots_out``).

    The cost of a plane and the choice among planes are those of :func:`_sweep` (the
    cheapest plane leaving weight on both sides, the first in (axis, plane) order on
    ties, reported as the last occupied bin on its left; a middle split when there is
    none); here every bin is a cell, and an empty bin changes no union or sum.

    Returns ``(left, right, n_left)``: each child's bounds (box lo, hi, centroid min,
    max) and the left child's item count.
    """
    UInt32, Float, Array3f = ns.UInt32, ns.Float, ns.Array3f
    cells = 3 * bins
    extent = box_hi - box_lo
    largest = dr.maximum(extent.x, dr.maximum(extent.y, extent.z))
    s = dr.select(largest > 0, 1 / largest, 1)
    end = dr.select(active, first + count, first)
    # Local memory, carried through every loop's state (a loop that only writes local
    # memory would otherwise be optimised away). Per cell (axis a, bin b at a·bins + b):
    # box (lo.xyz, -hi.xyz), weight, items; per plane after bin p (a·bins + p): the left
    # side's cost share, weight, items, and its last occupied bin.
    mem = (dr.alloc_local(Float, 6 * cells, Float(dr.inf)),
           dr.alloc_local(UInt32, cells, UInt32(0)), dr.alloc_local(UInt32, cells, UInt32(0)),
           dr.alloc_local(Float, cells), dr.alloc_local(UInt32, cells),
           dr.alloc_local(UInt32, cells), dr.alloc_local(UInt32, cells))

    def item_at(q):
        item = dr.gather(UInt32, slots_in, q)
        i_lo, i_hi = dr.gather(Array3f, lo, item), dr.gather(Array3f, hi, item)
        c = dr.gather(Array3f, centroid, item)
        return item, i_lo, i_hi, c, [_bin_index(ns, c[a], cmin[a], cmax[a], bins) for a in range(3)]

    # ---- Bin: every item into its cell on each axis ----
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

    def read_cell(mem, cell):
        r = [mem[0].read(6 * cell + j) for j in range(6)]
        return Array3f(r[0], r[1], r[2]), -Array3f(r[3], r[4], r[5]), mem[1].read(cell)

    # ---- Forward: the left side of the plane after bin p is bins 0..p ----
    def forward(p, mem, *acc):
        left_cost, left_weight, left_items, left_bin = mem[3:]
        acc = list(acc)
        for a in range(3):
            a_lo, a_hi, w, k, last = acc[5 * a: 5 * a + 5]
            cell = a * bins + p
            c_lo, c_hi, c_w = read_cell(mem, cell)
            a_lo, a_hi, w = dr.minimum(a_lo, c_lo), dr.maximum(a_hi, c_hi), w + c_w
            items = mem[2].read(cell)
            k, last = k + items, dr.select(items > 0, p, last)
            left_cost.write(_half_area((a_hi - a_lo) * s) * Float(w), cell)
            left_weight.write(w, cell)
            left_items.write(k, cell)
            left_bin.write(last, cell)
            acc[5 * a: 5 * a + 5] = a_lo, a_hi, w, k, last
        return (p + 1, mem, *acc)

    # Full-width start values made from an input, not from a width: a size baked into
    # the frozen kernel would tie its recording to one item count.
    zeros = dr.minimum(first, dr.opaque(UInt32, 0))
    inf = Array3f(Float(zeros) + dr.inf)
    empty = (inf, -inf)
    p, mem, *_ = dr.while_loop(mode="symbolic",
                               state=(zeros, mem, *(*empty, zeros, zeros, zeros) * 3),
                               cond=lambda p, *_: active & (p + 1 < bins), body=forward)

    # ---- Backward: the plane before bin p, its right side bins p..bins-1 ----
    never = ns.UInt64(zeros) | 0xFFFFFFFFFFFFFFFF

    def backward(p, best, mem, *acc):
        left_cost, left_weight, _, left_bin = mem[3:]
        acc = list(acc)
        for a in range(3):
            a_lo, a_hi, w = acc[3 * a: 3 * a + 3]
            cell = a * bins + p
            c_lo, c_hi, c_w = read_cell(mem, cell)
            a_lo, a_hi, w = dr.minimum(a_lo, c_lo), dr.maximum(a_hi, c_hi), w + c_w
            before = cell - 1
            cost = dr.fma(_half_area((a_hi - a_lo) * s), Float(w), left_cost.read(before))
            key = (ns.UInt64(dr.reinterpret_array(UInt32, cost)) << 32) | ns.UInt64(
                a * bins + left_bin.read(before))
            valid = (left_weight.read(before) > 0) & (w > 0) & (cost < dr.inf)
            best = dr.select(valid & (key < best), key, best)
            acc[3 * a: 3 * a + 3] = a_lo, a_hi, w
        return (p - 1, best, mem, *acc)

    # (p is bins - 1 in the active lanes: where the forward pass stopped)
    _, best, mem, *_ = dr.while_loop(mode="symbolic",
                                     state=(p, never, mem, *(*empty, zeros) * 3),
                                     cond=lambda p, *_: active & (p > 0), body=backward)
    middle = best == never
    code = UInt32(best & 0xFFFFFFFF)
    axis, plane = code // bins, code % bins
    n_left = dr.select(middle, count // 2, mem[5].read(code, active & ~middle))

    # ---- Partition: left items first, each side in slot order ----
    to_leaf = (n_left <= leaf_items, count - n_left <= leaf_items)

    def partition(q, n_l, n_r, *bounds):
        item, i_lo, i_hi, c, b = item_at(q)
        goes_left = dr.select(middle, q - first < count // 2,
                              dr.select(axis == 0, b[0], dr.select(axis == 1, b[1], b[2])) <= plane)
        to = dr.select(goes_left, first + n_l, first + n_left + n_r)
        leafward = dr.select(goes_left, to_leaf[0], to_leaf[1])
        dr.scatter(item_order, item, to, leafward)
        dr.scatter(slots_out, item, to, ~leafward)
        bounds = list(bounds)
        for side, mine in ((0, goes_left), (1, ~goes_left)):
            b_lo, b_hi, c_lo, c_hi = bounds[4 * side: 4 * side + 4]
            bounds[4 * side: 4 * side + 4] = (
                dr.select(mine, dr.minimum(b_lo, i_lo), b_lo),
                dr.select(mine, dr.maximum(b_hi, i_hi), b_hi),
                dr.select(mine, dr.minimum(c_lo, c), c_lo),
                dr.select(mine, dr.maximum(c_hi, c), c_hi))
        return (q + 1, n_l + UInt32(goes_left), n_r + UInt32(~goes_left), *bounds)

    _, _, _, *bounds = dr.while_loop(
        mode="symbolic",
        state=(UInt32(first), zeros, zeros, *(*empty, *empty) * 2),
        cond=lambda q, *_: q < end, body=partition)
    return bounds[:4], bounds[4:], n_left


def _split_level(ns, level: _Level, records, item_order, block_start, leaf_items: int,
                 bins: int) -> _Level:
    """Split every open node of ``level``: write the children's node records and the
    slots of the items that reached a leaf; return the next level's open nodes."""
    K = level.size
    m = dr.width(level.item)
    # first node index of the children's and of the grandchildren's blocks (opaque)
    starts = ns.UInt32(block_start[-1], block_start[-1] + 2 * K)
    child_start, grandchild_start = (dr.gather(ns.UInt32, starts, i) for i in range(2))
    block_start.append(block_start[-1] + 2 * K)

    # ---- Bin and sweep: the split of every node ----
    item_lo, item_hi = level.item_lo, level.item_hi
    centroid = _centroid(item_lo, item_hi)
    packed_bins, cells = _bin(ns, level, item_lo, item_hi, centroid, level.item_weight, bins)
    split_key = _sweep(ns, cells, level, bins)

    # ---- Left/right decision of every item; ranks by a prefix sum ----
    position = dr.arange(ns.UInt32, m)
    split = ns.UInt32(dr.gather(ns.UInt64, split_key, level.node) & 0xFFFFFFFF)
    act_first = dr.gather(ns.UInt32, level.act_first, level.node)
    count = dr.gather(ns.UInt32, level.count, level.node)
    split_bin = (packed_bins >> (8 * dr.minimum(split // bins, 2))) & 0xFF
    left = dr.select(split == _MIDDLE,
                     (position - act_first) < count // 2,
                     split_bin <= split % bins)
    goes_left = ns.UInt32(left)
    left_before = dr.prefix_sum(goes_left)
    dr.eval(goes_left, left_before)

    # ---- Children: counts, slot ranges, open or leaf, next-level positions ----
    child = dr.arange(ns.UInt32, 2 * K)
    parent = child >> 1
    is_right = (child & 1) == 1
    p_first = dr.gather(ns.UInt32, level.act_first, parent)
    p_count = dr.gather(ns.UInt32, level.count, parent)
    p_last = p_first + p_count - 1
    n_left = (dr.gather(ns.UInt32, left_before, p_last) + dr.gather(ns.UInt32, goes_left, p_last)
              - dr.gather(ns.UInt32, left_before, p_first))
    c_count = dr.select(is_right, p_count - n_left, n_left)
    c_slot = dr.gather(ns.UInt32, level.slot_first, parent) + dr.select(is_right, n_left, 0)
    c_open = c_count > leaf_items
    # one inclusive prefix sum counts both: open children (high half), their items (low)
    open_and_items = (ns.UInt64(c_open) << 32) | ns.UInt64(dr.select(c_open, c_count, 0))
    dr.eval(c_count, c_slot, c_open, open_and_items)
    through = dr.cumsum(open_and_items)
    total = through[2 * K - 1]
    K_next, m_next = total >> 32, total & 0xFFFFFFFF

    def next_position(c):
        """(next-level index, first active position) of the open children ``c``."""
        before = dr.gather(ns.UInt64, through, c) - dr.gather(ns.UInt64, open_and_items, c)
        return ns.UInt32(before >> 32), ns.UInt32(before & 0xFFFFFFFF)

    # ---- Partition: move every item to its child, reduce the children's bounds ----
    left_rank = left_before - dr.gather(ns.UInt32, left_before, act_first)
    rank = dr.select(left, left_rank, (position - act_first) - left_rank)
    c = level.node * 2 + dr.select(left, 0, 1)
    to_open = dr.gather(ns.Bool, c_open, c)
    dr.scatter(item_order, level.item, dr.gather(ns.UInt32, c_slot, c) + rank, ~to_open)
    bounds = dr.full(ns.Float, dr.inf, 12 * 2 * K)  # per child: box, centroid bounds
    _reduce_box(bounds, item_lo, item_hi, 2 * c)
    _reduce_box(bounds, centroid, centroid, 2 * c + 1, to_open)
    if K_next:
        index, first = next_position(c)
        moved = (level.item, index, item_lo, item_hi, level.item_weight)
        next_items = tuple(dr.empty(type(x), m_next) for x in moved)
        for target, value in zip(next_items, moved):
            dr.scatter(target, value, first + rank, to_open)
    dr.eval()

    # ---- Emit the children's node records and the next level's open nodes ----
    box_lo, box_hi = _read_box(ns, bounds, 2 * child)
    next_index = next_position(child)[0]
    _write_records(ns, records, child_start + child, box_lo, box_hi,
                   dr.select(c_open, grandchild_start + 2 * next_index, c_slot),
                   dr.select(c_open, 0, c_count))
    if not K_next:
        dr.eval()
        return _Level(size=0)
    next_child = dr.empty(ns.UInt32, K_next)
    dr.scatter(next_child, child, next_index, c_open)
    dr.eval()
    box_lo, box_hi = _read_box(ns, bounds, 2 * next_child)
    cmin, cmax = _read_box(ns, bounds, 2 * next_child + 1)
    nxt = _Level(
        size=K_next,
        node_id=child_start + next_child,
        slot_first=dr.gather(ns.UInt32, c_slot, next_child),
        act_first=next_position(next_child)[1],
        count=dr.gather(ns.UInt32, c_count, next_child),
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
    item_bin = [_bin_index(ns, centroid[a], cmin[a], cmax[a], bins) for a in range(3)]
    packed_bins = item_bin[0] | (item_bin[1] << 8) | (item_bin[2] << 16)

    # ---- Occupied bins of the nodes of fewer than `bins` items (others: all bins) ----
    occupied = dr.zeros(ns.UInt64, 3 * K)
    small = dr.gather(ns.UInt32, level.count, level.node) < bins
    for a in range(3):
        dr.scatter_reduce(dr.ReduceOp.Or, occupied, ns.UInt64(1) << ns.UInt64(item_bin[a]),
                          level.node * 3 + a, small, mode=_MODE)
    dr.eval(packed_bins)
    item_bin = [(packed_bins >> (8 * a)) & 0xFF for a in range(3)]
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
    non-empty, the first in (axis, plane) order on ties, or ``_MIDDLE`` when no plane
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
    extent = dr.gather(ns.Array3f, level.box_hi, node) - dr.gather(ns.Array3f, level.box_lo, node)
    largest = dr.maximum(extent.x, dr.maximum(extent.y, extent.z))
    s = dr.select(largest > 0, 1 / largest, 1)
    left_cost = dr.empty(ns.Float, dr.width(cells.weight))
    left_weight = dr.empty(ns.UInt32, dr.width(cells.weight))
    empty_box = (dr.full(ns.Array3f, dr.inf, 3 * K), dr.full(ns.Array3f, -dr.inf, 3 * K))

    def add_cell(q, lo, hi, w):
        """(lo, hi, w) grown by the lane's cell ``q``."""
        c_lo, c_hi = _read_box(ns, cells.box, cells.first + q)
        w = w + dr.gather(ns.UInt32, cells.weight, cells.first + q)
        return dr.minimum(lo, c_lo), dr.maximum(hi, c_hi), w

    # ---- Forward: the left side of the plane after cell q is cells 0..q ----
    def forward(q, lo, hi, w):
        lo, hi, w = add_cell(q, lo, hi, w)
        dr.scatter(left_cost, _half_area((hi - lo) * s) * ns.Float(w), cells.first + q)
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
    def backward(q, bin_of_q, lo, hi, w, best_cost, best_bin):
        lo, hi, w = add_cell(q, lo, hi, w)
        last_left_bin = _highest_bit(ns, cells.occupied & ((ns.UInt64(1) << ns.UInt64(bin_of_q)) - 1))
        before = cells.first + q - 1
        cost = dr.fma(_half_area((hi - lo) * s), ns.Float(w), dr.gather(ns.Float, left_cost, before))
        better = (dr.gather(ns.UInt32, left_weight, before) > 0) & (w > 0) & (cost <= best_cost)
        best_cost = dr.select(better, cost, best_cost)
        best_bin = dr.select(better, last_left_bin, best_bin)
        return q - 1, last_left_bin, lo, hi, w, best_cost, best_bin

    *_, best_cost, best_bin = dr.while_loop(
        mode="symbolic",
        state=(cells.count - 1, _highest_bit(ns, cells.occupied), *empty_box,
               dr.zeros(ns.UInt32, 3 * K), dr.full(ns.Float, dr.inf, 3 * K),
               dr.zeros(ns.UInt32, 3 * K)),
        cond=lambda q, *_: q > 0,
        body=backward,
        labels=("q", "bin_of_q", "lo", "hi", "w", "best_cost", "best_bin"),
    )

    # ---- Per node the least (cost, axis, plane): one min over packed keys ----
    key = (ns.UInt64(dr.reinterpret_array(ns.UInt32, best_cost)) << 32) | ns.UInt64(
        (lane % 3) * bins + best_bin)
    key = dr.select(best_cost < dr.inf, key, 0xFFFFFFFFFFFFFFFF)
    return dr.block_reduce(dr.ReduceOp.Min, key, 3)


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


def _write_records(ns, records, index, box_lo, box_hi, first, count, active=True):
    """One wide scatter of node records (lo, hi, first, count) at node ``index``."""
    as_float = lambda u: dr.reinterpret_array(ns.Float, ns.UInt32(u))
    value = ns.ArrayXf([box_lo.x, box_lo.y, box_lo.z, box_hi.x, box_hi.y, box_hi.z,
                        as_float(first), as_float(count)])
    dr.scatter(records, value, index, active)


def _centroid(lo, hi):
    """Centre of a box (the point that is binned)."""
    return (lo + hi) * 0.5


def _bin_index(ns, c, cmin, cmax, bins: int):
    """Bin of centroid coordinate ``c`` among ``bins`` equal slices of [cmin, cmax]."""
    extent = cmax - cmin
    f = (c - cmin) / extent * bins
    f = dr.select((extent > 0) & (f < bins), f, dr.select(extent > 0, bins - 1, 0))
    return ns.UInt32(f)


def _half_area(d):
    """Half the surface area of a box of extent ``d`` (the SAH needs only ratios)."""
    return dr.fma(d.x, d.y + d.z, d.y * d.z)


def _check_inputs(item_min, item_max, item_weight, leaf_items, bins) -> int:
    """Item count after checking types, sizes and options (ValueError/TypeError)."""
    for name, x in (("item_min", item_min), ("item_max", item_max), ("item_weight", item_weight)):
        if not dr.is_jit_v(x):
            raise TypeError(f"binned_sah: {name} must be a Dr.Jit JIT array, got {type(x).__name__}")
    n = dr.width(item_min)
    if n == 0:
        raise ValueError("binned_sah: no items (item_min is empty); pass at least one box")
    if dr.width(item_max) != n or dr.width(item_weight) != n:
        raise ValueError(
            f"binned_sah: item_min, item_max and item_weight must have one entry per item "
            f"(got {n}, {dr.width(item_max)}, {dr.width(item_weight)})"
        )
    if not isinstance(leaf_items, int) or isinstance(leaf_items, bool) or leaf_items < 1:
        raise ValueError(f"binned_sah: leaf_items={leaf_items!r}: expected an int >= 1")
    if not isinstance(bins, int) or isinstance(bins, bool) or not 2 <= bins <= MAX_BINS:
        raise ValueError(f"binned_sah: bins={bins!r}: expected an int in 2..{MAX_BINS}")
    return n
