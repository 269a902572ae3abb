"""The HLBVH top level (Pantaleoni & Luebke 2010, section 4): a binned-SAH tree over
the coarse clusters, each cluster (the primitives that share the top ``coarse_bits``
Morton bits, which the CSD sort found) one leaf, whose own sub-tree the hierarchy
emission then builds below it from bit plane ``coarse_bits`` down."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from .arrays import namespace_of
from .emission import NodeRecords
from .geometry import BOX_RECORD, box_records
from .sah import SahTree, binned_sah


@dataclass
class TopLevel:
    """The SAH tree over the coarse clusters, one cluster per leaf.

    Attributes:
        tree: the :class:`~hlbvh.kernels.sah.SahTree` over the clusters (items =
            clusters).
        start, end: UInt32[C], each cluster's slot range ``[start, end)``.
        node, depth: UInt32[C], each cluster's leaf in ``tree`` and that leaf's depth:
            where the cluster's own sub-tree is rooted.
    """

    tree: SahTree
    start: Any
    end: Any
    node: Any
    depth: Any

    @property
    def roots(self) -> tuple:
        """``(start, end, node, depth)`` of the clusters: the emission's roots."""
        return self.start, self.end, self.node, self.depth

    def write_internal(self, records: NodeRecords):
        """Write the tree's internal nodes into ``records`` (their first child and depth;
        the leaves are the clusters' sub-tree roots, which the emission writes), and set
        ``records.total`` past the tree."""
        UInt32 = namespace_of(self.start).UInt32
        internal = self.tree.node_count == 0
        nodes = dr.arange(UInt32, self.tree.size)
        dr.scatter(records.first, self.tree.node_first, nodes, internal)
        dr.scatter(records.count, 0, nodes, internal)
        dr.scatter(records.depth, self.tree.leaf_depth, nodes, internal)
        records.total = dr.opaque(UInt32, self.tree.size)


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
