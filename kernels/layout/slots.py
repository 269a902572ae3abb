"""The packed slot format traversal reads: the constants, references and rows of
16-float *slots*. This module is the one place that encodes and decodes it; nothing
else shifts or masks a reference by hand. (:mod:`hlbvh.kernels.layout` says how a BVH
becomes slots.)

The binary tree of ``hlbvh.kernels.bvh`` becomes a BVH4 by dropping every other level
(the internal nodes at odd depths): a *wide node* is an internal node at even depth,
and its 2-4 children are its binary children, each replaced by its own two children
when it is internal. One traversal step then tests up to four boxes, and a ray takes
about 40% fewer steps than through the binary tree.

Records, laid out depth first (a wide node, then its children's subtrees in child
order, a leaf's triangles where the leaf stands), so a ray that descends often reads
the slots after the one it read:

=====================  ========================================================
wide node (2 slots)    ``NODE_LO[a] + k``, ``NODE_HI[a] + k``: child ``k``'s box on
                       axis ``a`` (k = 0..3, structure of arrays, float32 as the
                       builder computed them); ``NODE_REF + k``: child ``k``'s
                       reference (the bits of a UInt32), ``EMPTY`` for none
triangle (1 slot)      ``TRI_P[0..2]``: p0, p1, p2 in the face's order, all NaN for a
                       zero-area triangle (never hit: its normal would be NaN);
                       ``TRI_FACE``: the input face index (the bits of a UInt32);
                       ``TRI_LO``, ``TRI_HI``: the triangle's box (traversal does
                       not read it; a refit's leaf box is the union of these rows)
=====================  ========================================================

A *reference* names a child: a wide node by its first slot (bit 31 clear); a leaf by
``LEAF_BIT | first_slot << 4 | (count - 1)`` (at most ``MAX_LEAF_SIZE`` triangles, and
the slots below ``MAX_SLOTS``), so a leaf needs no record of its own.
(Child boxes are kept in full float32: docs/decisions.md#wide-bvh4 has what quantising them cost.)
"""

from __future__ import annotations

import drjit as dr

from ..arrays import namespace_of

#: Floats per slot: a triangle takes one, a wide node two.
SLOT = 16
#: Slots of a wide node.
NODE_SLOTS = 2
#: Children of a wide node.
WIDTH = 4
#: Bit 31 of a reference marks a leaf.
LEAF_BIT = 0x80000000
#: Most triangles a leaf may hold (its count - 1 lives in the reference's low 4 bits).
MAX_LEAF_SIZE = 16
#: Slots a BVH may pack into (a leaf's first slot lives in bits 4..30 of its reference;
#: the largest value is kept free for ``EMPTY``).
MAX_SLOTS = (1 << 27) - 1
#: The reference of a missing child.
EMPTY = 0xFFFFFFFF
#: Most binary levels a tree may have: ordered traversal of a wide node pushes at most
#: ``WIDTH - 1`` entries, one wide level per two binary levels.
MAX_DEPTH = 2 * 42

#: Offsets of a wide node's fields in its two slots (per axis, four children).
NODE_LO = (0, 4, 8)
NODE_HI = (12, 16, 20)
NODE_REF = 24
#: Offsets of a triangle's fields in its slot.
TRI_P = (0, 3, 6)
TRI_FACE = 9
#: The triangle's box (lower and upper corner), written with the triangle.
TRI_LO = 10
TRI_HI = 13
#: Bits of a leaf reference below its first slot: its triangle count - 1.
LEAF_COUNT_BITS = 4
_LEAF_COUNT_MASK = (1 << LEAF_COUNT_BITS) - 1


def leaf_ref(first_slot, count):
    """The reference of a leaf whose ``count`` triangles start at ``first_slot``."""
    return LEAF_BIT | (first_slot << LEAF_COUNT_BITS) | (count - 1)


def node_ref(slot):
    """The reference of a wide node whose record starts at ``slot``."""
    return slot


def is_leaf(ref):
    """Whether references ``ref`` name leaves."""
    return (ref & LEAF_BIT) != 0


def leaf_first(ref):
    """The first triangle slot of leaf references ``ref``."""
    return (ref & ~type(ref)(LEAF_BIT)) >> LEAF_COUNT_BITS


def leaf_count(ref):
    """The triangle count of leaf references ``ref``."""
    return (ref & _LEAF_COUNT_MASK) + 1


def open_ref(ref):
    """``(cur, end)`` for a reference: a leaf's triangle slots ``cur .. end-1``; a wide
    node's first slot with ``end = 0`` (so ``cur < end`` says a lane is in a leaf)."""
    leaf = is_leaf(ref)
    first = leaf_first(ref)
    return dr.select(leaf, first, ref), dr.select(leaf, first + leaf_count(ref), 0)


def triangle_rows(p, prim_ids, face_base):
    """The 16 floats of the triangles with vertices ``p`` (three Array3f) and face
    indices ``prim_ids + face_base``."""
    ns = namespace_of(prim_ids)
    Float, UInt32 = ns.Float, ns.UInt32
    # Zero-area (collinear vertices, in double: float32 products underflow at 1e-30 and
    # overflow at 1e20) are never hit, as in Embree; NaN vertices fail every test.
    p64 = [ns.Array3f64(q) for q in p]
    normal = dr.cross(p64[1] - p64[0], p64[2] - p64[0])
    flat = (normal.x == 0) & (normal.y == 0) & (normal.z == 0)
    tri = [dr.select(flat, dr.nan, c) for q in p for c in q]
    tri.append(dr.reinterpret_array(Float, UInt32(prim_ids) + dr.opaque(UInt32, face_base)))
    lo = dr.minimum(dr.minimum(p[0], p[1]), p[2])
    hi = dr.maximum(dr.maximum(p[0], p[1]), p[2])
    return tri + [lo.x, lo.y, lo.z, hi.x, hi.y, hi.z]


def node_rows(children):
    """The 32 floats of wide nodes with up to ``WIDTH`` ``children``, each ``(lo, hi,
    present, ref)``: their boxes and references (an absent child: a zero box and
    ``EMPTY``)."""
    ns = namespace_of(children[0][3])
    Float = ns.Float
    children = children + [children[-1][:2] + (ns.Bool(False), ns.UInt32(EMPTY))] * (
        WIDTH - len(children))
    rows = [dr.select(present, box[a], 0.0) for box_index in (0, 1) for a in range(3)
            for box, present in ((c[box_index], c[2]) for c in children)]
    rows += [dr.reinterpret_array(Float, dr.select(present, ref, EMPTY))
             for _, _, present, ref in children]
    return rows + [dr.zeros(Float, dr.width(rows[0]))] * (NODE_SLOTS * SLOT - len(rows))



def box_rows(lo, hi):
    """The 8 floats of box records (lo.xyz, hi.xyz, two zeros)."""
    zero = dr.zeros(type(lo.x), dr.width(lo.x))
    return [lo.x, lo.y, lo.z, hi.x, hi.y, hi.z, zero, zero]

