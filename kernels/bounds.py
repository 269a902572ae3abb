"""Node bounds, bottom-up, and the tree measures that need them (SAH cost, levels).

Boxes are computed level by level from the deepest internal nodes to the root, one
gather kernel and one scatter kernel per level, so no kernel ever waits on another lane
(no atomics, no in-kernel synchronisation). Leaves take the union of their triangles'
boxes; an internal node the union of its two children's. (One bottom-up pass in which
the second child to arrive at a node carries on, as Karras 2012 and Apetrei 2014 do,
was measured slower here; see docs/decisions.md#bounds-per-level.)
"""

from __future__ import annotations

import drjit as dr

from .arrays import namespace_of
from .geometry import box_records


def internal_levels(node_count, node_depth) -> list:
    """The internal nodes of each depth, root first: a list of UInt32 arrays.

    A counting sort by depth (``dr.detail.block_mkperm``, the stable bucketing under
    Dr.Jit's radix sort), leaves in a last bucket that is dropped; a histogram gives the
    level sizes, the one host read. The order inside a level is the node order.

    Args:
        node_count: UInt32[N] 0 for internal nodes (see kernels/bvh.py).
        node_depth: UInt32[N] depth of every node, root 0.
    """
    ns = namespace_of(node_count)
    UInt32 = ns.UInt32
    internal = node_count == 0
    levels_n = int(dr.max(dr.select(internal, node_depth + 1, 0))[0])
    if levels_n == 0:
        return []
    bucket = dr.select(internal, node_depth, dr.opaque(UInt32, levels_n))
    dr.eval(bucket)
    per_level = dr.zeros(UInt32, levels_n + 1)
    dr.scatter_reduce(dr.ReduceOp.Add, per_level, UInt32(1), bucket, mode=dr.ReduceMode.Local)
    order = dr.detail.block_mkperm(bucket, dr.width(bucket), levels_n + 1)
    levels, start = [], 0
    for size in per_level.numpy().tolist()[:-1]:  # a few dozen counts
        level = dr.gather(UInt32, order, dr.arange(UInt32, size) + dr.opaque(UInt32, start))
        # One at a time: levels of equal size evaluated together fuse into one kernel
        # with an output per level, a new kernel for every new such count.
        dr.eval(level)
        levels.append(level)
        start += size
    return levels


def node_bounds(node_first, node_count, slot_boxes, levels, leaf_size: int):
    """Boxes of every node.

    Args:
        node_first, node_count: UInt32[N] the tree (see kernels/bvh.py).
        slot_boxes: the triangle boxes in slot order, packed records
            (:func:`hlbvh.kernels.geometry.slot_triangles`).
        levels: internal nodes per depth (:func:`internal_levels`).
        leaf_size: most primitives in a leaf.
    Returns:
        (node_min, node_max), Array3f[N] each.
    """
    ns = namespace_of(node_first)
    Array3f = ns.Array3f

    # ---- Leaves: the union of their triangles' boxes ----
    node_min = dr.full(Array3f, dr.inf, len(node_first))
    node_max = dr.full(Array3f, -dr.inf, len(node_first))
    for k in range(leaf_size):
        has = node_count > k  # a masked gather reads 0, so select the identity
        lo, hi = box_records(slot_boxes, node_first + k, has)
        node_min = dr.select(has, dr.minimum(node_min, lo), node_min)
        node_max = dr.select(has, dr.maximum(node_max, hi), node_max)
    dr.eval(node_min, node_max)

    # ---- Internal nodes, deepest level first: the union of the two children ----
    for nodes in reversed(levels):
        left = dr.gather(type(node_first), node_first, nodes)
        lo = dr.minimum(dr.gather(Array3f, node_min, left), dr.gather(Array3f, node_min, left + 1))
        hi = dr.maximum(dr.gather(Array3f, node_max, left), dr.gather(Array3f, node_max, left + 1))
        dr.eval(lo, hi)  # a pending read of the arrays would make the scatter copy them
        dr.scatter(node_min, lo, nodes)
        dr.scatter(node_max, hi, nodes)
        dr.eval(node_min, node_max)
    return node_min, node_max


def sah_cost(node_min, node_max, node_count) -> float:
    """SAH cost with C_trav = C_isect = 1, normalised by the root's surface area:
    sum over internal nodes of A(n)/A(root) plus sum over leaves of count·A(n)/A(root).
    A root of zero area (all primitives on a point or a segment) weighs every node 1.

    Extents and areas are taken in double precision, so the cost is the same at any
    scale a float32 scene can have: in float32 an area overflows beyond extents of
    ~1e19, underflows below ~1e-19, and dividing by an extent beyond 2**126 goes through
    a subnormal reciprocal, which Dr.Jit's CPU kernels flush to zero (every node then
    weighed 1: an 1800-triangle grid at 1e38 reported 2295 instead of 34)."""
    ns = namespace_of(node_count)
    Array3d = ns.Array3f64

    def half_area(lo, hi):
        e = dr.maximum(Array3d(hi) - Array3d(lo), 0)
        return e.x * e.y + e.y * e.z + e.z * e.x

    area = half_area(node_min, node_max)
    # The root's from its own box: a gather from `area` would evaluate it in a pass of
    # its own before the sum's.
    zero = dr.zeros(ns.UInt32, 1)
    root = half_area(dr.gather(ns.Array3f, node_min, zero), dr.gather(ns.Array3f, node_max, zero))
    rel = dr.select(root > 0, area / dr.select(root > 0, root, 1), 1)
    weight = dr.select(node_count == 0, 1, type(area)(node_count))
    return float(dr.sum(rel * weight)[0])


def leaf_histogram(node_count, leaf_size: int) -> list[int]:
    """Number of leaves holding 1, 2, ..., leaf_size primitives."""
    ns = namespace_of(node_count)
    hist = dr.zeros(ns.UInt32, leaf_size + 1)
    dr.scatter_reduce(dr.ReduceOp.Add, hist, 1, dr.minimum(node_count, leaf_size), node_count > 0)
    return hist.numpy().tolist()[1:]
