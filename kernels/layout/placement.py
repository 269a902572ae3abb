"""Where a BVH's nodes and triangles go in the packed slots
(:mod:`hlbvh.kernels.layout.slots`): the binary tree becomes a BVH4 by dropping every other
level (the internal nodes at odd depths), and the records are laid out depth first, a wide
node, then its children's subtrees in child order, a leaf's triangles where the leaf stands.
The placement depends on the tree's shape only, so the packer keeps it across refits
(``PackState.plan``, :mod:`hlbvh.kernels.layout.packing`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from ..arrays import concat, namespace_of
from ..tree import Tree
from .slots import MAX_DEPTH, MAX_SLOTS, NODE_SLOTS, leaf_ref, node_ref
from .validation import check_layout, checked_levels, too_deep


@dataclass
class Placement:
    """Where ``placement`` put a tree's records.

    Attributes:
        ref: UInt32[N], every node's reference (a wide node's is its first slot).
        wide: UInt32[W], the wide nodes (internal nodes at even depth), level by level.
        at: UInt32[W], the first slot of each wide node (without the slot base).
        record_of: UInt32[F], the slot of each triangle slot's record.
        total: int, the slot count.
    """

    ref: Any
    wide: Any
    at: Any
    record_of: Any
    total: int


def placement(bvh: Tree, slot_base: int, check: bool):
    """Where ``bvh``'s nodes and triangles go (validated first when ``check``), their
    references counting from slot ``slot_base``: a :class:`Placement`."""
    ns = namespace_of(bvh.node_count)
    UInt32 = ns.UInt32
    n_nodes, n_prims = bvh.size, bvh.prim_count
    first, count = UInt32(bvh.node_first), UInt32(bvh.node_count)
    internal = count == 0
    levels = list(bvh.levels)
    if check:
        levels = checked_levels(first, count, internal, levels, n_nodes, n_prims)
    if len(levels) > MAX_DEPTH:
        raise ValueError(too_deep())
    # The builder's leaves hold at most leaf_size slots; a hand-made tree's are counted.
    widest = int(dr.max(count, axis=None)[0]) if check else bvh.config.leaf_size

    # ---- Up: slots in each subtree (a wide node's own two, a leaf's triangles) ----
    # Two arrays, one per depth parity, each starting with the leaves' triangle counts: a
    # level reads its children's sizes from one and writes its own into the other, so it
    # is one kernel (a read and a write of one array would need the two apart).
    by_parity = [dr.select(internal, 0, count) for _ in range(2)]
    for depth in reversed(range(len(levels))):
        nodes, own, below = levels[depth], by_parity[depth % 2], by_parity[1 - depth % 2]
        left = dr.gather(UInt32, first, nodes)
        extra = dr.opaque(UInt32, NODE_SLOTS if depth % 2 == 0 else 0)
        dr.scatter(own, extra + dr.gather(UInt32, below, left) + dr.gather(UInt32, below, left + 1),
                   nodes)
        dr.eval(own)
    total = int(by_parity[0][0])
    if slot_base + total > MAX_SLOTS:
        raise ValueError(
            f"BVH of {n_prims} triangles in {n_nodes} nodes needs {total} slots; "
            f"traversal supports at most {MAX_SLOTS}"
        )

    # ---- Down: a wide node at p, its first child's subtree at p + 2, the next after ----
    # Positions by depth parity too, both arrays zero but where a node of their parity
    # was placed (the root stays at 0): a node's position is their sum. One lane per
    # child, so each level is one scatter, one kernel.
    placed = [dr.zeros(UInt32, n_nodes) for _ in range(2)]
    for depth, nodes in enumerate(levels):
        lane = dr.arange(UInt32, 2 * dr.width(nodes))
        node, side = dr.gather(UInt32, nodes, lane >> 1), lane & 1
        left = dr.gather(UInt32, first, node)
        after = dr.gather(UInt32, placed[depth % 2], node) + dr.opaque(
            UInt32, NODE_SLOTS if depth % 2 == 0 else 0)
        sizes = by_parity[1 - depth % 2]
        dr.scatter(placed[1 - depth % 2],
                   after + dr.select(side == 1, dr.gather(UInt32, sizes, left), 0), left + side)
        dr.eval(placed[1 - depth % 2])
    position = placed[0] + placed[1]

    base = dr.opaque(UInt32, slot_base)
    ref = dr.select(internal, node_ref(position + base), leaf_ref(position + base, count))
    # Internal nodes at even depth are the wide nodes.
    wide = concat(levels[0::2]) if levels else UInt32()
    at = dr.gather(UInt32, position, wide)
    leaf = ~internal
    record_of = dr.zeros(UInt32, n_prims)
    for k in map(lambda k: dr.opaque(UInt32, k), range(widest)):
        dr.scatter(record_of, position + k, first + k, leaf & (count > k))
    dr.eval(ref, at, record_of)
    if check:
        check_layout(at, record_of, total)
    return Placement(ref, wide, at, record_of, total)

