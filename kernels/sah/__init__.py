"""Binned SAH build (Wald 2007, "On fast construction of SAH-based bounding volume
hierarchies"), top-down and breadth-first, as Dr.Jit array kernels.

One function, :func:`binned_sah`, serves both builders that need it:

- ``"hlbvh"`` builds the SAH top level over the coarse clusters (Pantaleoni & Luebke
  2010, section 4; :mod:`hlbvh.kernels.top_level`): the items are clusters, each
  standing for many primitives;
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

The same trees come from two layouts of the work: one lane per node, a level in one
frozen kernel (:mod:`hlbvh.kernels.sah.node_lanes`, for few items), or one lane per
item, a level in about twenty launches (:mod:`hlbvh.kernels.sah.item_lanes`); the
sweep's arithmetic both share is :mod:`hlbvh.kernels.sah.planes`.
"""

from __future__ import annotations

import drjit as dr

from ..arrays import namespace_of, plain
from .item_lanes import build_by_item_lanes
from .node_lanes import build_by_node_lanes
from .planes import MAX_BINS, SahTree

__all__ = ["MAX_BINS", "NODE_LANES_MAX_ITEMS", "SahTree", "binned_sah"]

#: Inputs of at most this many items (the HLBVH top level's clusters, small meshes) are
#: split one lane per node (:mod:`~hlbvh.kernels.sah.node_lanes`), larger ones one lane
#: per item (:mod:`~hlbvh.kernels.sah.item_lanes`). Same trees; where the two cross is
#: measured in docs/decisions.md#sah-top-level.
NODE_LANES_MAX_ITEMS = 1 << 16


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
    build_by = build_by_node_lanes if n <= NODE_LANES_MAX_ITEMS else build_by_item_lanes
    return build_by(ns, lo, hi, weight, leaf_items, bins)


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
