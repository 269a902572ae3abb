"""References for the traversal tests, in plain numpy, written the obvious way.

- :func:`brute_force` intersects every ray with every triangle (Möller–Trumbore in
  float64) and keeps the nearest hit: the reference our traversal must equal.
- :func:`median_split_bvh` builds a BVH (the layout of ``hlbvh.kernels.bvh``) by
  recursive median splits on the widest centroid axis: a second builder, independent
  of ``hlbvh.build``, so traversal can be tested against trees nobody tuned for it.
- :func:`tree_sah_cost` scores any tree of that layout by the SAH, boxes recomputed
  from its triangles, and :func:`sweep_sah_bvh` builds the textbook top-down SAH tree
  (every split of the centroid order on each axis costed): the reference the builders'
  tree quality is measured against, sharing no code with ``hlbvh``'s SAH.
- :func:`triangle_grid` and :func:`random_soup` make small test meshes.
"""

from __future__ import annotations

import numpy as np


# ---------------------------------------------------------------------------------------
# Meshes
# ---------------------------------------------------------------------------------------


def triangle_grid(nx: int, ny: int, z: float = 0.0):
    """A flat grid of ``nx`` by ``ny`` unit squares in the plane ``z``, two triangles per
    square, vertices at integer coordinates.

    Returns:
        (vertices float32 (V, 3), faces uint32 (2·nx·ny, 3))
    """
    xs, ys = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), indexing="xy")
    vertices = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], axis=1)
    faces = []
    for j in range(ny):
        for i in range(nx):
            a = j * (nx + 1) + i
            b, c, d = a + 1, a + nx + 1, a + nx + 2
            faces += [(a, b, d), (a, d, c)]
    return vertices.astype(np.float32), np.array(faces, dtype=np.uint32)


def random_soup(count: int, seed: int, size: float = 0.2):
    """``count`` random triangles in the unit cube, each within a box of edge ``size``.

    Returns:
        (vertices float32 (3·count, 3), faces uint32 (count, 3))
    """
    rng = np.random.default_rng(seed)
    centers = rng.random((count, 1, 3))
    vertices = (centers + size * (rng.random((count, 3, 3)) - 0.5)).reshape(-1, 3)
    faces = np.arange(3 * count, dtype=np.uint32).reshape(count, 3)
    return vertices.astype(np.float32), faces


# ---------------------------------------------------------------------------------------
# Brute-force intersector
# ---------------------------------------------------------------------------------------


def brute_force_t(vertices, faces, o, d, maxt):
    """Distance from every ray to every triangle (Möller–Trumbore, float64).

    Args:
        vertices: (V, 3) positions; faces: (F, 3) indices.
        o, d: (R, 3) ray origins and directions; maxt: (R,) or scalar.
    Returns:
        (t, u, v), each (R, F) float64: ``t`` is ``inf`` where the ray misses the
        triangle or the hit is not in (0, maxt]; ``u``, ``v`` are the barycentrics of
        ``p1`` and ``p2``.
    """
    p = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]  # (F, 3, 3)
    p0, e1, e2 = p[:, 0], p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    o = np.asarray(o, np.float64)[:, None, :]
    d = np.asarray(d, np.float64)[:, None, :]
    maxt = np.broadcast_to(np.asarray(maxt, np.float64), (o.shape[0],))[:, None]
    with np.errstate(all="ignore"):
        pvec = np.cross(d, e2)
        det = np.sum(e1 * pvec, axis=-1)
        s = o - p0
        u = np.sum(s * pvec, axis=-1) / det
        qvec = np.cross(s, e1)
        v = np.sum(d * qvec, axis=-1) / det
        t = np.sum(e2 * qvec, axis=-1) / det
        hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t <= maxt)
    return np.where(hit, t, np.inf), u, v


def brute_force(vertices, faces, o, d, maxt=np.inf):
    """Nearest hit of every ray (see :func:`brute_force_t`).

    Returns:
        dict with ``t`` (R,) (``inf`` on a miss), ``u``, ``v``, ``prim`` (R,) int64
        (-1 on a miss), ``valid`` (R,) bool, and ``t_all`` (R, F) for tie checks.
    """
    t_all, u_all, v_all = brute_force_t(vertices, faces, o, d, maxt)
    prim = np.argmin(t_all, axis=1)
    rows = np.arange(len(prim))
    t = t_all[rows, prim]
    valid = np.isfinite(t)
    return {
        "t": t,
        "u": np.where(valid, u_all[rows, prim], 0.0),
        "v": np.where(valid, v_all[rows, prim], 0.0),
        "prim": np.where(valid, prim, -1),
        "valid": valid,
        "t_all": t_all,
    }


# ---------------------------------------------------------------------------------------
# Median-split BVH builder
# ---------------------------------------------------------------------------------------


def median_split_bvh(vertices, faces, leaf_size: int = 4):
    """A BVH over a triangle mesh by recursive median splits, in the layout of
    ``hlbvh.kernels.bvh.BVH``.

    A node with more than ``leaf_size`` triangles sorts them by centroid along the
    widest axis of its centroid bounds and gives the lower half to its left child.
    Children are stored as adjacent pairs (right = left + 1), in depth-first order.

    Args:
        vertices: (V, 3) float positions; faces: (F, 3) integer indices, F >= 1.
    Returns:
        an ``hlbvh.BVH`` with arrays of the current Mitsuba variant's backend.
    """
    def split(prims, centroid, lo_tri, hi_tri):
        if len(prims) <= leaf_size:
            return None
        c = centroid[prims]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        prims = prims[np.argsort(c[:, axis], kind="stable")]
        half = len(prims) // 2
        return prims[:half], prims[half:]

    return _top_down_bvh(vertices, faces, leaf_size, split, "median")


# ---------------------------------------------------------------------------------------
# SAH: the cost of a tree, and a top-down builder that sweeps every split
# ---------------------------------------------------------------------------------------


def _half_area(lo, hi):
    e = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def tree_sah_cost(vertices, faces, node_first, node_count, prim_ids) -> float:
    """The SAH cost of a tree in the layout of ``hlbvh.kernels.bvh.BVH`` (C_trav =
    C_isect = 1, relative to the root's surface area): the sum over the nodes reached
    from the root of A(node)/A(root), each leaf's term times its triangle count. Every
    node's box is computed here from the triangles below it (float64), not read from
    the tree. A root of zero area weighs every node 1.

    Args:
        vertices: (V, 3); faces: (F, 3); node_first, node_count, prim_ids: numpy arrays
            (``bvh.node_first.numpy()``, ...): a leaf holds the slots
            ``first .. first+count-1`` (faces ``prim_ids[slot]``), an internal node
            (count 0) its children at ``first`` and ``first + 1``.
    """
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
    lo_tri, hi_tri = tri.min(axis=1), tri.max(axis=1)
    first = np.asarray(node_first, np.int64)
    count = np.asarray(node_count, np.int64)
    slot_face = np.asarray(prim_ids, np.int64)
    terms = []  # (area, weight) per node

    def box(node):
        if count[node] > 0:
            faces_here = slot_face[first[node]:first[node] + count[node]]
            lo, hi = lo_tri[faces_here].min(axis=0), hi_tri[faces_here].max(axis=0)
            terms.append((_half_area(lo, hi), count[node]))
            return lo, hi
        (lo_l, hi_l), (lo_r, hi_r) = box(first[node]), box(first[node] + 1)
        lo, hi = np.minimum(lo_l, lo_r), np.maximum(hi_l, hi_r)
        terms.append((_half_area(lo, hi), 1))
        return lo, hi

    root = _half_area(*box(0))
    area, weight = np.array(terms, np.float64).T
    return float(np.sum((area / root if root > 0 else 1.0) * weight))


def sweep_sah_bvh(vertices, faces, leaf_size: int = 4):
    """A BVH by the textbook top-down SAH build, every split considered: at each node,
    for each axis, the triangles sorted by centroid and every prefix/suffix split of
    that order costed as A(left)·N(left) + A(right)·N(right) (boxes of the triangles,
    float64); the cheapest split over the three axes is taken. A node of at most
    ``leaf_size`` triangles becomes a leaf when that is cheaper (N against
    1 + the split's cost / A(node)); a larger one is always split. Layout as
    :func:`median_split_bvh` (``stats.builder == "sweep-sah"``)."""

    def split(prims, centroid, lo_tri, hi_tri):
        n = len(prims)
        if n == 1:
            return None
        best = (np.inf, None, None)
        for axis in range(3):
            order = prims[np.argsort(centroid[prims, axis], kind="stable")]
            lo, hi = lo_tri[order], hi_tri[order]
            left = _half_area(np.minimum.accumulate(lo), np.maximum.accumulate(hi))[:-1]
            right = _half_area(np.minimum.accumulate(lo[::-1]),
                               np.maximum.accumulate(hi[::-1]))[::-1][1:]
            k = np.arange(1, n)
            cost = left * k + right * (n - k)
            j = int(np.argmin(cost))
            if cost[j] < best[0]:
                best = (cost[j], order, j + 1)
        cost, order, k = best
        area = _half_area(lo_tri[prims].min(axis=0), hi_tri[prims].max(axis=0))
        if n <= leaf_size and (area <= 0 or n <= 1 + cost / area):
            return None
        return order[:k], order[k:]

    return _top_down_bvh(vertices, faces, leaf_size, split, "sweep-sah")


def _top_down_bvh(vertices, faces, leaf_size, split, name):
    """The BVH of recursive ``split(prims, centroid, lo_tri, hi_tri)`` calls (a pair of
    index arrays, or None for a leaf), in the layout of ``hlbvh.kernels.bvh.BVH``."""
    import drjit as dr  # noqa: F401
    import mitsuba as mi

    from hlbvh.kernels.arrays import namespace_of
    from hlbvh.kernels.bvh import BVH, BuildConfig, BuildStats

    vertices = np.asarray(vertices, np.float32)
    faces = np.asarray(faces, np.uint32)
    tri = vertices[faces.astype(np.int64)]  # (F, 3, 3)
    lo_tri, hi_tri = tri.min(axis=1), tri.max(axis=1)
    centroid = tri.mean(axis=1)
    lo64, hi64 = lo_tri.astype(np.float64), hi_tri.astype(np.float64)

    node_min, node_max, node_first, node_count, depth_of = [], [], [], [], []
    order = []  # slot -> face

    def new_node(depth):
        for a in (node_min, node_max, node_first, node_count):
            a.append(None)
        depth_of.append(depth)
        return len(node_count) - 1

    def fill(node, prims, depth):
        node_min[node] = lo_tri[prims].min(axis=0)
        node_max[node] = hi_tri[prims].max(axis=0)
        halves = split(prims, centroid, lo64, hi64)
        if halves is None:
            node_first[node] = len(order)
            node_count[node] = len(prims)
            order.extend(prims.tolist())
            return
        left = new_node(depth + 1)
        new_node(depth + 1)
        node_first[node] = left
        node_count[node] = 0
        fill(left, halves[0], depth + 1)
        fill(left + 1, halves[1], depth + 1)

    fill(new_node(0), np.arange(len(faces)), 0)

    ns = namespace_of(mi.Float(0))
    order = np.array(order, dtype=np.int64)
    node_count = np.array(node_count, dtype=np.uint32)
    depth_of = np.array(depth_of)
    internal = np.flatnonzero(node_count == 0)
    levels = [
        ns.UInt32(internal[depth_of[internal] == k].astype(np.uint32))
        for k in range(depth_of.max() + 1)
        if np.any(depth_of[internal] == k)
    ]
    p = tri[order]
    stats = BuildStats(
        builder=name,
        prim_count=len(faces),
        node_count=len(node_count),
        leaf_count=len(node_count) - len(internal),
        depth=int(depth_of.max()) + 1,  # levels of nodes, as hlbvh.build counts them
    )
    return BVH(
        node_min=ns.Array3f(np.array(node_min, np.float32).T),
        node_max=ns.Array3f(np.array(node_max, np.float32).T),
        node_first=ns.UInt32(np.array(node_first, np.uint32)),
        node_count=ns.UInt32(node_count),
        prim_ids=ns.UInt32(order.astype(np.uint32)),
        tri_p0=ns.Array3f(p[:, 0].T),
        tri_p1=ns.Array3f(p[:, 1].T),
        tri_p2=ns.Array3f(p[:, 2].T),
        faces=ns.UInt32(faces.ravel()),
        levels=levels,
        config=BuildConfig(leaf_size=leaf_size),
        stats=stats,
    )
