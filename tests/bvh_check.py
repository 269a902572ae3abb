"""Structural checks of a built BVH, written the obvious way in numpy (tests only)."""

from __future__ import annotations

import drjit as dr
import numpy as np

from hlbvh.kernels.layout.packing import check_tree


def rows(a) -> np.ndarray:
    """An Array3f as an (n, 3) numpy array."""
    if dr.depth_v(a) == 2:
        return np.stack([a.x.numpy(), a.y.numpy(), a.z.numpy()], 1)
    return np.asarray(a.numpy() if hasattr(a, "numpy") else a)


def check_bvh(bvh, V: np.ndarray, F: np.ndarray, leaf_size: int) -> dict:
    """Assert the invariants every builder promises; return a few measures.

    - prim_ids is a permutation of the faces and tri_p* hold their vertices in slot order;
    - the tree reached from the root covers every slot exactly once, by leaves of
      1..leaf_size primitives; siblings are adjacent and children follow their parent;
    - every leaf box contains its triangles and every child box lies inside its parent's
      (equality of floats: boxes are unions, so containment is exact);
    - the packer's own validation passes (:func:`hlbvh.kernels.layout.packing.check_tree`:
      parents, ranges, levels and the packed slots), which it skips for the builder's
      trees when packing them per frame.
    """
    first = bvh.node_first.numpy().astype(np.int64)
    count = bvh.node_count.numpy().astype(np.int64)
    lo, hi = rows(bvh.node_min), rows(bvh.node_max)
    pid = bvh.prim_ids.numpy().astype(np.int64)
    nF = len(F)
    assert sorted(pid.tolist()) == list(range(nF)), "prim_ids is not a permutation"
    tri = V[F[pid]]  # (F, 3, 3) in slot order
    for k, p in enumerate((bvh.tri_p0, bvh.tri_p1, bvh.tri_p2)):
        assert np.array_equal(rows(p), tri[:, k].astype(np.float32)), f"tri_p{k} wrong"

    covered = np.zeros(nF, dtype=np.int64)
    seen = np.zeros(len(count), dtype=bool)
    stack, depth_max, leaves = [(0, 0)], 0, 0
    while stack:
        n, d = stack.pop()
        assert not seen[n], f"node {n} reached twice"
        seen[n] = True
        depth_max = max(depth_max, d)
        if count[n] > 0:
            leaves += 1
            assert count[n] <= leaf_size, f"leaf {n} holds {count[n]} > {leaf_size}"
            s = slice(first[n], first[n] + count[n])
            covered[s] += 1
            t = tri[s].reshape(-1, 3)
            assert np.all(t.min(0) >= lo[n]) and np.all(t.max(0) <= hi[n]), f"leaf {n} box"
        else:
            c = first[n]
            assert n < c and c + 1 < len(count), f"children of {n} at {c}"
            for ch in (c, c + 1):
                assert np.all(lo[ch] >= lo[n]) and np.all(hi[ch] <= hi[n]), f"child {ch} box"
                stack.append((ch, d + 1))
    assert seen.all(), "nodes unreachable from the root"
    assert np.all(covered == 1), "a slot is not in exactly one leaf"
    assert bvh.stats.node_count == len(count) and bvh.stats.leaf_count == leaves
    assert bvh.stats.depth == depth_max + 1
    assert bvh.built_topology == bvh.topology_key()
    check_tree(bvh)
    return {"leaves": leaves, "depth": depth_max + 1}
