"""The traversal layout: the BVH collapsed to a 4-wide tree and packed into one Float
array of 16-float *slots*, which is what traversal reads. This module is the one place
that encodes and decodes it; nothing else shifts or masks a reference by hand.

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

Child boxes are kept in full float32: quantising them to bytes relative to the node's
box (one slot a node) halved the bytes read but cost more in decoding than the second
packet gather it saved, on this CPU.

A *reference* names a child: a wide node by its first slot (bit 31 clear); a leaf by
``LEAF_BIT | first_slot << 4 | (count - 1)`` (at most ``MAX_LEAF_SIZE`` triangles, and
the slots below ``MAX_SLOTS``), so a leaf needs no record of its own.

A tree made by hand (or one whose topology arrays were reassigned) is validated before it
is packed: child and leaf ranges inside the arrays, every node the child of exactly one
node, and the packed slots covering every slot exactly once (a cycle, a shared subtree,
an out-of-range child, stale levels or a slot in no leaf or in two is a ValueError); its
depths come from a breadth-first walk when its levels do not hold every internal node.
A tree as the builder returned it (``bvh.built_topology`` matches its arrays) is packed
from its own levels without those checks, which cost a third of the packing and a host
round trip each: the tests run them on every builder's trees (:func:`check_tree`).

A refit of a tree packed before writes its slots in the same passes as its boxes
(:func:`refit_packed`, called by ``hlbvh.kernels.refit``), where it was last packed; the
next :func:`packed_records` or :func:`joined` for that place takes them as they are.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from .arrays import concat, namespace_of
from .geometry import BOX_RECORD

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


def leaf_ref(first_slot, count):
    """The reference of a leaf whose ``count`` triangles start at ``first_slot``."""
    return LEAF_BIT | (first_slot << 4) | (count - 1)


def node_ref(slot):
    """The reference of a wide node whose record starts at ``slot``."""
    return slot


def open_ref(ref):
    """``(cur, end)`` for a reference: a leaf's triangle slots ``cur .. end-1``; a wide
    node's first slot with ``end = 0`` (so ``cur < end`` says a lane is in a leaf)."""
    leaf = (ref & LEAF_BIT) != 0
    first = (ref & ~type(ref)(LEAF_BIT)) >> 4
    return dr.select(leaf, first, ref), dr.select(leaf, first + (ref & 15) + 1, 0)


@dataclass
class Packed:
    """Slots ready to trace, and the reference of their root (what :func:`joined`
    returns; traversal takes it wherever it takes a BVH)."""

    records: Any
    root: int


def joined(bvhs) -> Packed:
    """One traversal over up to ``WIDTH`` BVHs: a wide node over their roots (slots 0-1),
    then each BVH's slots in turn, its face indices offset by the faces before it (so a
    hit's face index counts the BVHs' faces in the order given). One BVH is packed as
    it is. A caller that keeps rarely changing BVHs first repacks only the later ones
    (each BVH's slots are cached for its place).

    Raises:
        ValueError: no BVH, or more than ``WIDTH``; and as :func:`packed_records`.
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
    records, root = _pack(bvhs[-1], slot_base, face_base, check=not _built(bvhs[-1]),
                          front=slot_base)
    roots.append(root)
    # The top node: its children are the roots, with the roots' own boxes.
    zero = dr.zeros(UInt32, 1)
    boxes = [(dr.gather(ns.Array3f, b.node_min, zero), dr.gather(ns.Array3f, b.node_max, zero))
             for b in bvhs]
    rows = _node_rows([(lo, hi, dr.ones(ns.Bool, 1), UInt32(root))
                       for (lo, hi), root in zip(boxes, roots)])
    return Packed(concat([dr.ravel(ns.ArrayXf(rows))] + parts, into=records), node_ref(0))


def packed_records(bvh, slot_base: int = 0, face_base: int = 0):
    """The packed slots of ``bvh`` (layout in the module docstring), built on first use
    and cached on the BVH object (keyed by the Dr.Jit variables of its arrays, so a
    refit, which assigns new arrays, repacks on the next call, from the placement kept
    for the tree's shape).

    Args:
        bvh: the BVH.
        slot_base: the slot the records will start at (references count from there:
            see :func:`joined`).
        face_base: added to every face index.

    Returns:
        ``(records, root)``: Float (``SLOT`` per slot) and the Python int reference of
        the root.
    Raises:
        ValueError: an empty tree, one deeper than ``MAX_DEPTH`` levels, a leaf of more
            than ``MAX_LEAF_SIZE`` triangles, more than ``MAX_SLOTS`` slots, or a
            corrupt tree (a child or leaf range outside its arrays, a node reached twice
            or never, a slot in no leaf or in two).
    """
    key = _arrays_key(bvh) + (slot_base, face_base)
    cache = getattr(bvh, "_traversal_records", None)
    if cache is not None and cache[0] == key:
        return cache[1]
    records = _pack(bvh, slot_base, face_base, check=not _built(bvh))
    bvh._traversal_records = (key, records)
    return records


def _arrays_key(bvh) -> tuple:
    """The Dr.Jit variables of every array the slots are packed from."""
    arrays = (bvh.node_min, bvh.node_max, bvh.node_first, bvh.node_count, bvh.prim_ids,
              bvh.tri_p0, bvh.tri_p1, bvh.tri_p2)
    return tuple(c.index for a in arrays for c in (a if dr.depth_v(a) > 1 else (a,)))


def _built(bvh) -> bool:
    """Whether ``bvh`` is a tree as the builder returned it (see the module docstring)."""
    return bvh.built_topology is not None and bvh.built_topology == bvh.topology_key()


def check_tree(bvh):
    """Validate ``bvh`` as :func:`packed_records` validates a tree made by hand, whoever
    made it (the tests call it on every builder's trees, whose packing skips it).

    Raises:
        ValueError: as :func:`packed_records`.
    """
    _pack(bvh, 0, 0, check=True)


def _pack(bvh, slot_base, face_base, check: bool, front: int = 0):
    """``(records, root)`` of ``bvh`` (see :func:`packed_records`), validated first when
    ``check``; the records start with ``front`` slots left for the caller to fill.

    Where each node and triangle goes depends on the tree's shape only, so it is kept on
    the BVH (``_pack_plan``, keyed by :meth:`BVH.topology_key` and ``slot_base``): a refit,
    which changes boxes and triangles only, is packed again without the per-level
    passes that place the nodes. A pack that validates (``check``) places anew."""
    if bvh.size == 0 or bvh.prim_count == 0:
        raise ValueError("BVH is empty: build it from at least one triangle")
    plan_key = (bvh.topology_key(), slot_base)
    plan = getattr(bvh, "_pack_plan", None)
    if check or plan is None or plan[0] != plan_key:
        plan = bvh._pack_plan = (plan_key, _placement(bvh, slot_base, check))
    ref, wide, at, record_of, total = plan[1]
    if not check:  # (a validation, e.g. check_tree, is not where the tree is traced)
        bvh._last_pack = (slot_base, face_base, front)  # where a refit writes its slots
    ready = getattr(bvh, "_ready_records", None)
    place = (slot_base, face_base, front)
    if not check and ready is not None and ready[0] == (_arrays_key(bvh),) + place:
        bvh._ready_records = None  # handed over: the caller may write into its front
        return ready[1], int(ref[0])
    return _write_records(bvh, ref, wide, at, record_of, total, face_base, front), int(ref[0])


def _placement(bvh, slot_base, check: bool):
    """Where ``bvh``'s nodes and triangles go (validated first when ``check``):
    ``(ref, wide, at, record_of, total)``, each node's reference, the wide nodes and
    their slots, each triangle's slot, and the slot count."""
    ns = namespace_of(bvh.node_count)
    UInt32 = ns.UInt32
    n_nodes, n_prims = bvh.size, bvh.prim_count
    first, count = UInt32(bvh.node_first), UInt32(bvh.node_count)
    internal = count == 0
    levels = list(bvh.levels)
    if check:
        levels = _checked_levels(first, count, internal, levels, n_nodes, n_prims)
    if len(levels) > MAX_DEPTH:
        raise ValueError(_too_deep())
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
        _check_layout(at, record_of, total)
    return ref, wide, at, record_of, total


def _write_records(bvh, ref, wide, at, record_of, total, face_base, front):
    """The slots of ``bvh`` placed as :func:`_placement` says, after ``front`` slots
    left for the caller."""
    ns = namespace_of(bvh.node_count)
    UInt32, Float, ArrayXf = ns.UInt32, ns.Float, ns.ArrayXf
    n_prims = bvh.prim_count
    # Not zeroed: the wide nodes and triangles write every slot whole (_check_layout
    # refuses a hand-made tree for which they would not; check_tree, a builder's).
    records = dr.empty(Float, SLOT * (front + total))
    front = dr.opaque(UInt32, front)

    # ---- Wide nodes: children's boxes and references ----
    if dr.width(wide):
        rows = _wide_rows(bvh, UInt32(bvh.node_first), ref, wide)
        # Each scatter into one target is a kernel of its own: the rows are gathered
        # once, not once per slot.
        dr.eval(rows)
        dr.scatter(records, ArrayXf(rows[:SLOT]), at + front)
        dr.scatter(records, ArrayXf(rows[SLOT:]), at + front + 1)

    # ---- Triangles: each slot's record where its leaf stands ----
    slot = dr.arange(UInt32, n_prims)
    p = [dr.gather(ns.Array3f, q, slot) for q in (bvh.tri_p0, bvh.tri_p1, bvh.tri_p2)]
    dr.scatter(records, ArrayXf(_triangle_rows(p, bvh.prim_ids, face_base)), record_of + front)
    dr.eval(records)
    return records


def _triangle_rows(p, prim_ids, face_base):
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


def refit_packed(bvh, points, slot_faces) -> bool:
    """Refit ``bvh`` for new vertex ``points`` and write its slots in the same passes,
    where it was last packed (:func:`_write_packed`). The BVH's triangle arrays are left
    as lazy reads of ``points`` (computed only if read).

    A refit through the binary tree and a pack after it write the triangles in slot order
    and read them again, and walk the binary levels twice (boxes, then wide nodes); this
    walks the wide levels once and never stores the slot-order triangles.

    Args:
        bvh: a tree as the builder returned it, packed before (else nothing is done).
        points: flat Float[3·V] vertex positions, checked.
        slot_faces: Array3u[F], the vertex indices of each slot's face.
    Returns:
        Whether it refit ``bvh`` (False: the caller refits through the binary tree).
    """
    last = getattr(bvh, "_last_pack", None)
    plan = getattr(bvh, "_pack_plan", None)
    if last is None or plan is None or not _built(bvh) or \
            plan[0] != (bvh.topology_key(), last[0]):
        return False
    ns = namespace_of(bvh.node_count)
    p = [dr.gather(ns.Array3f, points, slot_faces[k]) for k in range(3)]
    bvh.tri_p0, bvh.tri_p1, bvh.tri_p2 = p  # lazy: computed only if read
    _write_packed(bvh, last, plan, points, slot_faces)
    return True


def _write_packed(bvh, place, plan, points, slot_faces):
    """The slots of ``bvh`` at ``place`` and its node boxes: one pass over the leaves
    (each leaf's lane writes its triangles' records and takes the union of their boxes)
    and one per wide level (deepest first). Boxes move as 8-float records, one packet
    gather each, not as six scalar gathers.

    Sets ``bvh.node_min``/``node_max`` and keeps the slots for the next
    :func:`packed_records` or :func:`joined` that asks for ``place``. (Used by a refit:
    for a new build, whose placement and plan are made anew, this measured no faster
    than the binary bounds and a pack; see docs/decisions.md.)

    Args:
        bvh: a tree as the builder returned it (its shape only is read).
        place: ``(slot_base, face_base, front)`` as :func:`_pack` takes them.
        plan: the tree's placement at ``slot_base`` (``bvh._pack_plan``).
        points: flat Float[3·V] vertex positions.
        slot_faces: Array3u[F], the vertex indices of each slot's face.
    """
    slot_base, face_base, front = place
    total = plan[1][4]
    ns = namespace_of(bvh.node_count)
    UInt32, Float, Array3f, ArrayXf = ns.UInt32, ns.Float, ns.Array3f, ns.ArrayXf
    refit = _refit_plan(bvh, plan)
    records = dr.empty(Float, SLOT * (front + total))
    front_o = dr.opaque(UInt32, front)

    # ---- Leaves: their triangles' records, and the union of their boxes ----
    boxes = dr.empty(Float, BOX_RECORD * bvh.size)  # every node's box, a record each
    leaf_node, leaf_record, leaf_count, leaf_slot, widest = refit.leaves
    lo, hi = _leaf_triangles(records, points, slot_faces, bvh.prim_ids, face_base,
                             leaf_slot, leaf_record + front_o, leaf_count, widest)
    dr.scatter(boxes, ArrayXf(_box_rows(lo, hi)), leaf_node)
    dr.eval(records, boxes)

    # ---- Wide nodes, deepest level first: rows from their children's boxes ----
    for nodes, slots, children in reversed(refit.wide_levels):
        rows, own = _wide_level_rows(boxes, nodes, children)
        # Read (and every gather of `boxes` released) before writing into it: a pending
        # read would make the scatter copy the array. One scatter a target: each is a
        # kernel of its own.
        dr.eval(rows, own)
        dr.scatter(records, ArrayXf(rows[:SLOT]), slots + front_o)
        dr.scatter(records, ArrayXf(rows[SLOT:]), slots + front_o + 1)
        dr.scatter(boxes, ArrayXf(own), nodes)
        dr.eval(records, boxes)

    # ---- Every node's box in one pass: a binary node at odd depth (no record of its
    # own) is the union of its two children, the others their own record ----
    node = dr.arange(UInt32, bvh.size)
    left = dr.select(refit.odd, bvh.node_first, node)
    a, b = (dr.gather(ArrayXf, boxes, c, shape=(BOX_RECORD, bvh.size))
            for c in (left, left + UInt32(refit.odd)))
    bvh.node_min = dr.minimum(Array3f(*a[0:3]), Array3f(*b[0:3]))
    bvh.node_max = dr.maximum(Array3f(*a[3:6]), Array3f(*b[3:6]))
    dr.eval(bvh.node_min, bvh.node_max)
    bvh._ready_records = ((_arrays_key(bvh), slot_base, face_base, front), records)


def _leaf_triangles(records, points, slot_faces, prim_ids, face_base, first_slot,
                    first_record, count, widest):
    """Write the triangle records of leaves (slots ``first_slot ..``, ``count`` of
    them, records from ``first_record`` on) and return the union of their boxes,
    ``(lo, hi)`` Array3f per leaf: one lane a leaf walks its triangles (a symbolic loop,
    so the record scatter is one kernel with the boxes, and no record is read back).
    Every lane takes ``widest`` steps (the most triangles in a leaf, a UInt32[1]): a
    short leaf repeats its last triangle, writing the same record again, because the
    masked gathers of lanes that stopped early cost more."""
    ns = namespace_of(first_slot)
    Array3f, n = ns.Array3f, dr.width(first_slot)
    last = count - 1

    def body(k, lo, hi):
        j = dr.minimum(k, last)
        slot = first_slot + j
        face = dr.gather(ns.Array3u, slot_faces, slot)
        p = [dr.gather(Array3f, points, face[c]) for c in range(3)]
        rows = _triangle_rows(p, dr.gather(ns.UInt32, prim_ids, slot), face_base)
        dr.scatter(records, ns.ArrayXf(rows), first_record + j)
        return (k + 1, dr.minimum(lo, Array3f(*rows[TRI_LO:TRI_LO + 3])),
                dr.maximum(hi, Array3f(*rows[TRI_HI:TRI_HI + 3])))

    _, lo, hi = dr.while_loop(
        mode="symbolic",
        state=(dr.zeros(ns.UInt32, n), dr.full(Array3f, dr.inf, n), dr.full(Array3f, -dr.inf, n)),
        cond=lambda k, lo, hi: k < widest, body=body, labels=("k", "lo", "hi"))
    return lo, hi


def _wide_level_rows(boxes, nodes, children):
    """The 32 floats of the wide ``nodes`` and their own box rows, from their
    ``children`` ``(node, present, reference)`` whose box records are in ``boxes``."""
    ns = namespace_of(nodes)
    Array3f = ns.Array3f
    rows_of = []
    for child, present, child_ref in children:
        # An absent child reads child 0's box, then dropped: an unmasked packet gather
        # costs far less than a masked one.
        r = dr.gather(ns.ArrayXf, boxes, child, shape=(BOX_RECORD, dr.width(nodes)))
        rows_of.append((Array3f(*r[0:3]), Array3f(*r[3:6]), present, child_ref))
    # Child 0 is always there; the others only widen the box where present.
    lo, hi = rows_of[0][0], rows_of[0][1]
    for c_lo, c_hi, present, _ in rows_of[1:]:
        lo = dr.select(present, dr.minimum(lo, c_lo), lo)
        hi = dr.select(present, dr.maximum(hi, c_hi), hi)
    return _node_rows(rows_of), _box_rows(lo, hi)


def _box_rows(lo, hi):
    """The 8 floats of box records (lo.xyz, hi.xyz, two zeros)."""
    zero = dr.zeros(type(lo.x), dr.width(lo.x))
    return [lo.x, lo.y, lo.z, hi.x, hi.y, hi.z, zero, zero]


@dataclass
class _RefitPlan:
    """Where the fused refit (:func:`refit_packed`) reads each box from, kept per tree:
    ``leaves`` (node, first record, count and first slot of every leaf, and the most
    triangles in one, a UInt32[1]), ``wide_levels`` (per wide level, root first: its
    nodes, their first slots, and per child ``(node, present, reference)``), ``odd``
    (per node: whether it is internal at an odd depth)."""

    leaves: tuple
    wide_levels: list
    odd: Any


def _refit_plan(bvh, plan) -> _RefitPlan:
    """The :class:`_RefitPlan` of ``bvh`` for its placement ``plan``, made on the first
    fused refit and kept with the placement."""
    kept = getattr(bvh, "_refit_plan", None)
    if kept is not None and kept[0] == plan[0]:
        return kept[1]
    ns = namespace_of(bvh.node_count)
    UInt32 = ns.UInt32
    ref, _, _, record_of, total = plan[1]
    slot_base = dr.opaque(UInt32, plan[0][1])
    first, count = UInt32(bvh.node_first), UInt32(bvh.node_count)
    levels = []
    for nodes in bvh.levels[0::2]:
        left = dr.gather(UInt32, first, nodes)
        children = []
        for side in (0, 1):
            # As _wide_rows orders them: an internal binary child hands over its two.
            b = left + side
            internal = dr.gather(UInt32, count, b) == 0
            g = dr.gather(UInt32, first, b, internal)
            c0 = dr.select(internal, g, b)
            for node, present in ((c0, dr.full(ns.Bool, True, dr.width(b))), (g + 1, internal)):
                children.append((dr.select(present, node, c0), present,
                                 dr.gather(UInt32, ref, node, present)))
        slots = dr.gather(UInt32, ref, nodes) - slot_base  # a wide node's ref is its slot
        dr.eval(slots, children)
        levels.append((nodes, slots, children))
    # The leaves in the order of their records (a leaf's record is its first slot's).
    leaf = count > 0
    by_record = dr.zeros(UInt32, total)
    leaf_record = dr.gather(UInt32, record_of, first, leaf)
    dr.scatter(by_record, dr.arange(UInt32, bvh.size) + 1, leaf_record, leaf)
    leaf_record = dr.compress(by_record != 0)  # record positions, ascending
    leaf_node = dr.gather(UInt32, by_record, leaf_record) - 1
    leaf_count = dr.gather(UInt32, count, leaf_node)
    leaves = (leaf_node, leaf_record, leaf_count, dr.gather(UInt32, first, leaf_node),
              dr.max(leaf_count))
    odd = dr.zeros(ns.Bool, bvh.size)
    for level in bvh.levels[1::2]:
        dr.scatter(odd, True, level)
    dr.eval(leaves, odd)
    result = _RefitPlan(leaves=leaves, wide_levels=levels, odd=odd)
    bvh._refit_plan = (plan[0], result)
    return result


def _checked_levels(first, count, internal, levels, n_nodes, n_prims):
    """The internal nodes by depth to pack a tree made by hand by, after checking its
    child and leaf ranges and parents (ValueError): its own ``levels`` when they hold
    every internal node (the packed layout is then checked slot by slot, so stale levels
    cannot pass), a walk from the root otherwise."""
    UInt32 = type(first)
    # Sizes enter kernels as opaque values: a literal would compile new kernels for
    # every tree of a new size, i.e. every frame of an animation.
    nodes_o, prims_o = dr.opaque(UInt32, n_nodes), dr.opaque(UInt32, n_prims)
    bad = dr.select(internal, first + 1 >= nodes_o,
                    (count > MAX_LEAF_SIZE) | (first + count > prims_o) | (first + count < first))
    if dr.any(bad, axis=None)[0]:
        raise ValueError(
            "corrupt BVH: a child index or leaf range lies outside the node/slot "
            f"arrays, or a leaf holds more than {MAX_LEAF_SIZE} triangles"
        )
    _check_parents(first, internal, n_nodes)
    if sum(dr.width(level) for level in levels) != int(dr.count(internal)[0]):
        levels = _levels(first, internal, n_nodes)
    return levels


#: Floats per node in the packing's staging records: lo.xyz, hi.xyz, reference, first.
_NODE_RECORD = 8


def _wide_rows(bvh, first, ref, wide):
    """The 32 floats of each wide node in ``wide`` (layout in the module docstring).

    Every node's box, reference and first child are staged first as one 32-byte record
    (one coherent pass over the nodes), so a wide node reads each of its binary and
    grandchildren with one packet gather: node numbers are far apart in a large tree,
    and six box coordinates in six arrays were six cache misses a child (a 1M grid:
    18.5 ms for the wide nodes, most of the packing)."""
    ns = namespace_of(first)
    UInt32, Float = ns.UInt32, ns.Float
    n = dr.width(first)
    as_float = lambda u: dr.reinterpret_array(Float, UInt32(u))
    staged = dr.empty(Float, _NODE_RECORD * n)
    dr.scatter(staged, ns.ArrayXf([*bvh.node_min, *bvh.node_max, as_float(ref),
                                   as_float(first)]), dr.arange(UInt32, n))
    dr.eval(staged)

    def node_at(node, active=True):
        """(lo, hi, reference, first) of the staged records ``node``."""
        r = dr.gather(ns.ArrayXf, staged, node, active, shape=(_NODE_RECORD, dr.width(node)))
        return (ns.Array3f(r[0], r[1], r[2]), ns.Array3f(r[3], r[4], r[5]),
                dr.reinterpret_array(UInt32, r[6]), dr.reinterpret_array(UInt32, r[7]))

    children = []
    left = dr.gather(UInt32, first, wide)
    for side in (0, 1):
        c_lo, c_hi, c_ref, c_first = node_at(left + side)
        c_internal = (c_ref & LEAF_BIT) == 0
        # An internal child (odd depth) hands over its two children; a leaf stays.
        g_lo, g_hi, g_ref, _ = node_at(c_first, c_internal)
        children.append((dr.select(c_internal, g_lo, c_lo), dr.select(c_internal, g_hi, c_hi),
                         dr.ones(ns.Bool, dr.width(wide)), dr.select(c_internal, g_ref, c_ref)))
        g_lo, g_hi, g_ref, _ = node_at(c_first + 1, c_internal)
        children.append((g_lo, g_hi, c_internal, g_ref))
    return _node_rows(children)


def _node_rows(children):
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


def _levels(first, internal, n_nodes):
    """Internal nodes by depth, root first, from a breadth-first walk (every node has
    one parent, :func:`_check_parents`, so the walk meets each node once, or loops in a
    cycle, which the node count bounds); ValueError when deeper than ``MAX_DEPTH``."""
    ns = namespace_of(first)
    UInt32 = ns.UInt32
    levels = []
    nodes = dr.arange(UInt32, 1 if bool(internal[0]) else 0)
    visited = 1
    while dr.width(nodes):
        visited += 2 * dr.width(nodes)
        if visited > n_nodes:
            raise ValueError("corrupt BVH: the tree holds a cycle (a node is its own ancestor)")
        if len(levels) == MAX_DEPTH:
            raise ValueError(_too_deep())
        levels.append(nodes)
        # Both children of every node (no dr.concat: it would bake the width in).
        pair = dr.arange(UInt32, 2 * dr.width(nodes))
        children = dr.gather(UInt32, first, dr.gather(UInt32, nodes, pair >> 1)) + (pair & 1)
        nodes = dr.gather(UInt32, children,
                          dr.compress(dr.gather(ns.Bool, internal, children)))
    return levels


def _too_deep() -> str:
    return (f"BVH depth above {MAX_DEPTH} levels exceeds the traversal stack: rebuild "
            "with a builder that bounds the depth")


def _check_parents(first, internal, n_nodes):
    """ValueError unless every node but the root is the child of exactly one node (and
    the root of none): a shared subtree or a cycle through the root fails here."""
    UInt32 = type(first)
    parents = dr.zeros(UInt32, n_nodes)
    left = dr.compress(internal)
    children = dr.gather(UInt32, first, left)
    # Local, not Expand: Expand's kernel holds the array's size (a compile per size).
    for child in (children, children + 1) if dr.width(children) else ():
        dr.scatter_add(parents, UInt32(1), child, mode=dr.ReduceMode.Local)
    expected = dr.select(dr.arange(UInt32, n_nodes) == 0, 0, 1)  # the root has no parent
    if not dr.all(parents == expected, axis=None)[0]:
        raise ValueError(
            "corrupt BVH: a node is the child of two nodes, or of none, or the root is a "
            "child (a cycle)"
        )


def _check_layout(node_slot, record_of, total):
    """ValueError unless the wide nodes' two slots each and the triangles' one slot
    each cover every slot exactly once: what stale levels, an unreachable part of the
    tree, or a primitive slot in no leaf or in two (two triangles on one record, none
    on another) would break."""
    UInt32 = type(record_of)
    written = dr.zeros(UInt32, total)
    node_slots = [node_slot, node_slot + 1] if dr.width(node_slot) else []
    for slots in node_slots + [record_of]:
        dr.scatter_add(written, UInt32(1), slots, mode=dr.ReduceMode.Local)
    if not dr.all(written == 1, axis=None)[0]:
        raise ValueError(
            "corrupt BVH: its levels, child links or leaf ranges do not describe one tree "
            "holding every primitive slot once"
        )
