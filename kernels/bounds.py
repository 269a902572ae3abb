"""Node bounds, bottom-up, and the tree measures that need them (SAH cost, levels).

Boxes are computed level by level from the deepest internal nodes to the root, one
gather kernel and one scatter kernel per level, so no kernel ever waits on another lane
(no atomics, no in-kernel synchronisation). Leaves take the union of their triangles'
boxes; an internal node the union of its two children's.
"""

from __future__ import annotations

import drjit as dr

from .arrays import namespace_of


def triangle_boxes(tri):
    """Array3f[F] lower and upper corners of each triangle's box; ``tri`` a Matrix3f
    whose rows are the vertices (see kernels/geometry.py)."""
    return dr.minimum(dr.minimum(tri[0], tri[1]), tri[2]), dr.maximum(dr.maximum(tri[0], tri[1]), tri[2])


def internal_levels(node_count, node_depth) -> list:
    """The internal nodes of each depth, root first: a list of UInt32 arrays.

    A counting sort by depth: an atomic counter per depth gives every internal node its
    rank within its level (the order inside a level is irrelevant to every user).

    Args:
        node_count: UInt32[N] 0 for internal nodes (see kernels/bvh.py).
        node_depth: UInt32[N] depth of every node, root 0.
    """
    ns = namespace_of(node_count)
    UInt32 = ns.UInt32
    internal = node_count == 0
    if not dr.any(internal)[0]:
        return []
    levels_n = int(dr.max(dr.select(internal, node_depth, 0))[0]) + 1
    per_level = dr.zeros(UInt32, levels_n)
    rank = dr.scatter_inc(per_level, node_depth, internal)
    dr.eval(rank, per_level)
    sizes = per_level.numpy().tolist()  # a few dozen counts
    offset = dr.prefix_sum(per_level)
    order = dr.zeros(UInt32, sum(sizes))
    nodes = dr.arange(UInt32, len(node_count))
    dr.scatter(order, nodes, dr.gather(UInt32, offset, node_depth, internal) + rank, internal)
    dr.eval(order)
    levels, start = [], 0
    for size in sizes:
        levels.append(dr.gather(UInt32, order, dr.arange(UInt32, size) + dr.opaque(UInt32, start)))
        start += size
    dr.eval(levels)
    return levels


def node_bounds(node_first, node_count, tri_lo, tri_hi, levels, leaf_size: int):
    """Boxes of every node.

    Args:
        node_first, node_count: UInt32[N] the tree (see kernels/bvh.py).
        tri_lo, tri_hi: Array3f[F] triangle boxes in slot order.
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
        lo = dr.gather(Array3f, tri_lo, node_first + k, has)
        hi = dr.gather(Array3f, tri_hi, node_first + k, has)
        node_min = dr.select(has, dr.minimum(node_min, lo), node_min)
        node_max = dr.select(has, dr.maximum(node_max, hi), node_max)
    dr.eval(node_min, node_max)

    # ---- Internal nodes, deepest level first: the union of the two children ----
    for nodes in reversed(levels):
        left = dr.gather(type(node_first), node_first, nodes)
        lo = dr.minimum(dr.gather(Array3f, node_min, left), dr.gather(Array3f, node_min, left + 1))
        hi = dr.maximum(dr.gather(Array3f, node_max, left), dr.gather(Array3f, node_max, left + 1))
        dr.eval(lo, hi)  # read before writing into the same arrays (pitfall 5)
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
    Array3d = namespace_of(node_count).Array3f64
    e = dr.maximum(Array3d(node_max) - Array3d(node_min), 0)
    area = e.x * e.y + e.y * e.z + e.z * e.x
    root = dr.gather(type(area), area, 0)
    rel = dr.select(root > 0, area / dr.select(root > 0, root, 1), 1)
    weight = dr.select(node_count == 0, 1, type(area)(node_count))
    return float(dr.sum(rel * weight)[0])


def leaf_histogram(node_count, leaf_size: int) -> list[int]:
    """Number of leaves holding 1, 2, ..., leaf_size primitives."""
    ns = namespace_of(node_count)
    hist = dr.zeros(ns.UInt32, leaf_size + 1)
    dr.scatter_reduce(dr.ReduceOp.Add, hist, 1, dr.minimum(node_count, leaf_size), node_count > 0)
    return hist.numpy().tolist()[1:]
