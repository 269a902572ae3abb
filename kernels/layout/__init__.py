"""The traversal layout: the BVH collapsed to a 4-wide tree and packed into one Float
array of 16-float *slots*, which is what traversal reads; and several BVHs joined under
one wide node (:func:`joined`), which is how a scene of several meshes is traced.

The binary tree of :mod:`hlbvh.kernels.tree` becomes a BVH4 by dropping every other level
(the internal nodes at odd depths): a *wide node* is an internal node at even depth,
and its 2-4 children are its binary children, each replaced by its own two children
when it is internal. One traversal step then tests up to four boxes.

The parts, one concept a module:

- :mod:`hlbvh.kernels.layout.slots`: the slot format (fields, references, rows), the one
  place that encodes and decodes it;
- :mod:`hlbvh.kernels.layout.placement`: where each node and triangle goes, depth first;
- :mod:`hlbvh.kernels.layout.packing`: the slots written, and kept per place for the tree
  (``PackState``);
- :mod:`hlbvh.kernels.layout.validation`: the checks a tree made by hand passes first;
- :func:`hlbvh.kernels.refit.refit_packed`: a refit of a tree packed before, which
  writes its slots in the same passes as its boxes, where it was last packed; the next
  :func:`~hlbvh.kernels.layout.packing.packed_records` or :func:`joined` for that place
  takes them as they are.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from ..arrays import concat, namespace_of
from ..tree import Tree
from .packing import is_built, pack, packed_records
from .slots import NODE_SLOTS, SLOT, WIDTH, node_ref, node_rows


@dataclass
class Packed:
    """Slots ready to trace, and the reference of their root (what :func:`joined`
    returns; traversal takes it wherever it takes a BVH)."""

    records: Any
    root: int


def joined(bvhs: list[Tree]) -> Packed:
    """One traversal over up to ``WIDTH`` BVHs: a wide node over their roots (slots 0-1),
    then each BVH's slots in turn, its face indices offset by the faces before it (so a
    hit's face index counts the BVHs' faces in the order given). One BVH is packed as
    it is. A caller that keeps rarely changing BVHs first repacks only the later ones
    (each BVH's slots are cached for its place).

    Raises:
        ValueError: no BVH, or more than ``WIDTH``; and as
            :func:`~hlbvh.kernels.layout.packing.packed_records`.
    """
    if not 1 <= len(bvhs) <= WIDTH:
        raise ValueError(f"joined: {len(bvhs)} BVHs, expected 1 to {WIDTH}")
    if len(bvhs) == 1:
        return Packed(*packed_records(bvhs[0]))
    ns = namespace_of(bvhs[0].node_count)
    UInt32 = ns.UInt32
    parts, roots = [], []
    slot_base, face_base = NODE_SLOTS, 0
    for bvh in bvhs[:-1]:
        records, root = packed_records(bvh, slot_base, face_base)
        parts.append(records)
        roots.append(root)
        slot_base += dr.width(records) // SLOT
        face_base += bvh.prim_count
    # The last BVH (the one that changes) is packed straight into the joined array, behind
    # room for the rest: a copy of its slots would cost a pass over all of them.
    records, root = pack(bvhs[-1], slot_base, face_base, check=not is_built(bvhs[-1]),
                         front=slot_base)
    roots.append(root)
    # The top node: its children are the roots, with the roots' own boxes.
    zero = dr.zeros(UInt32, 1)
    boxes = [(dr.gather(ns.Array3f, b.node_min, zero), dr.gather(ns.Array3f, b.node_max, zero))
             for b in bvhs]
    rows = node_rows([(lo, hi, dr.ones(ns.Bool, 1), UInt32(root))
                      for (lo, hi), root in zip(boxes, roots)])
    return Packed(concat([dr.ravel(ns.ArrayXf(rows))] + parts, into=records), node_ref(0))

