"""Hierarchy emission: the partial breadth-first emission of Pantaleoni & Luebke 2010
(seed Figure 4), turning primitives sorted by Morton code into a binary tree.

A *segment* is a run of sorted primitives that share a node of the tree being emitted;
all its keys agree on the bit planes above the current ``level``. Each pass considers
``p`` bit planes ``[level, level + p)`` at once:

1. *Block splits* (one lane per primitive): primitive ``i`` starts a split at bit plane
   ``level + j`` when the highest bit where ``key[i-1]`` and ``key[i]`` differ is that
   plane and both lie in one segment. Inside a segment such a split is unique for its
   plane and for the ``j`` key bits above it, so it owns the slot ``2^j - 1 + q`` of the
   segment's *treelet*, a complete binary tree of ``P = 2^p - 1`` slots in breadth-first
   order (``q`` = the key's bits on planes ``level .. level+j-1``).
2. *Treelet emission* (one lane per slot, then one per treelet position): every lane
   walks from its segment's root down to its own position, at most ``p`` steps. A slot
   reached by a range of more than ``leaf_size`` primitives and holding a split emits two
   children; a range without a split at a slot passes to the child its keys' bit selects.
   Children are numbered by an exclusive prefix sum over the split flags of all slots,
   two adjacent indices per split. Ranges of at most ``leaf_size`` primitives become
   leaves where they are created; ranges still larger at the bottom of the treelet
   become the next pass's segments (with their heads in key order).

Once every bit plane is used, a segment still larger than ``leaf_size`` holds identical
keys: it is split at its middle index, pass after pass (the same treelet machinery with
``p = 1`` and the split given), so every tree is finite and balanced there.

Each node's record (``node_first``, ``node_count``, ``node_depth``) is written exactly
once, when the node is finalised as an internal node or a leaf.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

from .arrays import namespace_of


NONE = 0xFFFFFFFF  # "no segment": the primitive lies in a finished leaf


@dataclass
class Segments:
    """Open segments, sorted by ``start``: primitive ranges ``[start, end)`` of more than
    ``leaf_size`` primitives, each owned by the node ``node`` at depth ``depth``."""

    start: object  # UInt32[S]
    end: object  # UInt32[S]
    node: object  # UInt32[S]
    depth: object  # UInt32[S]

    def __len__(self) -> int:
        return len(self.start)


@dataclass
class NodeRecords:
    """Node arrays the emission writes into (see kernels/bvh.py), with room for every
    node, and ``total``: how many nodes are allocated so far, a UInt32[1] that stays on
    the device (read it with ``int(total[0])`` once the emission is done)."""

    first: object  # UInt32[capacity]
    count: object  # UInt32[capacity]
    depth: object  # UInt32[capacity]
    total: object  # UInt32[1]


def emit_hierarchy(keys, key_bits: int, level: int, roots, prim_root, records: NodeRecords,
                   leaf_size: int, p: int) -> int:
    """Emit the tree below ``roots`` from bit plane ``level`` down, then split
    identical-key segments at their middle.

    Args:
        keys: UInt32[N] or UInt64[N] Morton codes in sorted order, ``key_bits`` wide.
        key_bits: width of the keys in bits (30 or 60).
        level: the first bit plane to process (0 = the most significant key bit); the
            keys of every root must agree on the planes above it.
        roots: (start, end, node, depth), UInt32[R] each: the ranges ``[start, end)``
            (sorted, non-empty, covering all primitives) below already allocated nodes.
        prim_root: UInt32[N], the root each primitive belongs to.
        records: node arrays, written in place; ``records.total`` grows.
        leaf_size: most primitives in a leaf.
        p: bit planes per pass.
    Returns:
        The number of passes run.
    """
    ns = namespace_of(prim_root)
    segments, remap = _open_roots(*roots, records, leaf_size)
    sid = dr.gather(ns.UInt32, remap, prim_root)
    passes = 0
    while len(segments) > 0 and level < key_bits:
        pe = min(p, key_bits - level)
        splits, sid = _block_splits(keys, key_bits, level, pe, len(segments), sid)
        segments, remap = _emit_treelets(keys, key_bits, level, pe, segments, splits, records, leaf_size)
        sid = _next_segment(keys, key_bits, level, pe, sid, remap)
        level += pe
        passes += 1
    while len(segments) > 0:
        # All keys of each segment are equal: split at the middle index.
        mid = (segments.start + segments.end) >> 1
        segments, _ = _emit_treelets(keys, key_bits, key_bits, 1, segments, mid, records, leaf_size)
        passes += 1
    return passes


def _open_roots(start, end, node, depth, records: NodeRecords, leaf_size: int):
    """Finalise the roots small enough as leaves; return the open ones as Segments and
    UInt32[R] ``remap``: each root's segment index, NONE for the finished."""
    ns = namespace_of(start)
    UInt32 = ns.UInt32
    dr.make_opaque(start, end, node, depth)  # sizes vary: never bake them into kernels
    size = end - start
    is_leaf = size <= leaf_size
    dr.scatter(records.first, start, node, is_leaf)
    dr.scatter(records.count, size, node, is_leaf)
    dr.scatter(records.depth, depth, node, is_leaf)
    dr.eval(records.first, records.count, records.depth)
    keep = dr.compress(~is_leaf)
    remap = dr.full(UInt32, NONE, len(start))
    dr.scatter(remap, dr.arange(UInt32, len(keep)), keep)
    segments = Segments(*(dr.gather(UInt32, a, keep) for a in (start, end, node, depth)))
    return segments, remap


def _plane_bits(keys, key_bits: int, level, pe: int, key):
    """The ``pe`` bits of ``key`` on bit planes ``level .. level+pe-1``, as UInt32."""
    Key = type(keys)
    shift = Key(key_bits - pe) - Key(level)
    return namespace_of(level).UInt32((key >> shift) & ((1 << pe) - 1))


def _block_splits(keys, key_bits: int, level: int, pe: int, segment_count: int, sid):
    """emit_block_splits of Figure 4 (one lane per primitive).

    Returns UInt32[S * P], the primitive that starts the split of each treelet slot (0
    where the slot has none: a split never starts at primitive 0), and ``sid``
    evaluated.
    """
    ns = namespace_of(sid)
    UInt32 = ns.UInt32
    Key = type(keys)
    n = len(keys)
    P = (1 << pe) - 1
    width = 64 if dr.type_v(keys) == dr.VarType.UInt64 else 32

    # ---- Highest bit plane where a primitive differs from its predecessor ----
    # Segment heads differ on a plane above ``level`` (or are primitive 0), so a plane
    # in [level, level + pe) marks a split inside the primitive's segment.
    i = dr.arange(UInt32, n)
    active = (sid != NONE) & (i > 0)
    key = dr.gather(Key, keys, i, active)
    prev = dr.gather(Key, keys, i - 1, active)
    plane = UInt32(dr.lzcnt(key ^ prev)) - (width - key_bits)
    lvl = dr.opaque(UInt32, level)
    is_split = active & (key != prev) & (plane >= lvl) & (plane < lvl + pe)
    j = dr.select(is_split, plane - lvl, 0)

    # ---- Treelet slot: plane j under the j key bits above it ----
    q = UInt32((key >> Key(key_bits - lvl - j)) & ((Key(1) << Key(j)) - 1))
    slot = (UInt32(1) << j) - 1 + q
    splits = dr.zeros(UInt32, segment_count * P)
    dr.scatter(splits, i, sid * P + slot, is_split)
    dr.eval(splits, sid)
    return splits, sid


def _next_segment(keys, key_bits: int, level: int, pe: int, sid, remap):
    """Each primitive's segment after a pass: the treelet bottom position its key's
    ``pe`` bits select (lazy; evaluated by the next pass's block splits)."""
    ns = namespace_of(sid)
    active = sid != NONE
    key = dr.gather(type(keys), keys, dr.arange(ns.UInt32, len(keys)), active)
    q = _plane_bits(keys, key_bits, dr.opaque(ns.UInt32, level), pe, key)
    return dr.select(active, dr.gather(ns.UInt32, remap, sid * (1 << pe) + q, active), ns.UInt32(NONE))


def _descend(keys, key_bits, level, pe, seg, splits, child_base, s, depth_target, q_target, leaf_size):
    """Walk segment ``s``'s treelet from its root to the position at depth
    ``depth_target`` (0..pe) with path bits ``q_target`` (most significant first).

    ``splits`` is the UInt32[S*P] slot table (for middle splits, ``level == key_bits``
    and ``pe == 1``: the middle index of each segment). ``child_base`` (UInt32[S*P], or None to skip node
    numbering) holds the first child index of each slot's split.

    Returns (lo, hi, node, depth, reached, created): the range reaching the position (if
    ``reached``), the node owning it and its depth, and whether that node was created by
    the last step's split.
    """
    ns = namespace_of(s)
    UInt32, Bool = ns.UInt32, ns.Bool
    P = (1 << pe) - 1
    lo = dr.gather(UInt32, seg.start, s)
    hi = dr.gather(UInt32, seg.end, s)
    node = dr.gather(UInt32, seg.node, s)
    depth = dr.gather(UInt32, seg.depth, s)
    reached = dr.full(Bool, True, dr.width(s))
    created = dr.full(Bool, False, dr.width(s))
    middle = level >= key_bits
    for j in range(pe):
        step = reached & (j < depth_target) & (hi - lo > leaf_size)
        reached &= (j >= depth_target) | step
        below = dr.select(step, depth_target - j, 1)  # keep shift amounts in range
        go_right = ((q_target >> (below - 1)) & 1) == 1
        slot = (UInt32(1) << j) - 1 + (q_target >> below)
        sp = dr.gather(UInt32, splits, s * P + slot, step)
        has = step & (sp != 0)
        # ---- A split at this slot: the path enters one of two new children ----
        if child_base is not None:
            c0 = dr.gather(UInt32, child_base, s * P + slot, has)
            node = dr.select(has, c0 + dr.select(go_right, 1, 0), node)
        lo = dr.select(has & go_right, sp, lo)
        hi = dr.select(has & ~go_right, sp, hi)
        depth = dr.select(has, depth + 1, depth)
        # ---- No split: the whole range follows its keys' bit on this plane ----
        passes = step & ~has
        if not middle:
            k = dr.gather(type(keys), keys, lo, passes)
            bit = ((k >> (key_bits - 1 - level - j)) & 1) == 1
            reached &= ~passes | (bit == go_right)
        created = dr.select(step, has, created)
    return lo, hi, node, depth, reached, created


def _emit_treelets(keys, key_bits, level, pe, seg, splits, records: NodeRecords, leaf_size):
    """emit_treelets of Figure 4: write the nodes of every segment's treelet.

    Returns the segments of the next pass and UInt32[S * 2^pe] ``remap``: the index
    among them of every treelet bottom position, NONE where no segment continues."""
    ns = namespace_of(seg.start)
    UInt32 = ns.UInt32
    S = len(seg)
    P = (1 << pe) - 1

    def positions(count, first_depth):
        """Lanes over (segment, position) for ``count`` positions per segment, BFS
        numbered from ``first_depth``'s first position."""
        idx = dr.arange(UInt32, S * count)
        s = idx // count
        pos = idx % count + ((1 << first_depth) - 1)
        d = UInt32(31) - dr.lzcnt(pos + 1)
        q = pos + 1 - (UInt32(1) << d)
        return s, pos, d, q

    # ---- Which slots split (reached by a range larger than a leaf) ----
    s, pos, d, q = positions(P, 0)
    lo, hi, _, _, reached, _ = _descend(keys, key_bits, level, pe, seg, splits, None, s, d, q, leaf_size)
    sp = dr.gather(UInt32, splits, s * P + pos)
    splits_here = reached & (hi - lo > leaf_size) & (sp != 0)
    flag = UInt32(splits_here)
    child_base = dr.select(splits_here, dr.prefix_sum(flag) * 2 + records.total, 0)
    records.total = records.total + 2 * dr.sum(flag)
    dr.eval(child_base, records.total)

    # ---- Node records: internal where a slot splits, leaves where small ranges appear ----
    width = 2 * P + 1
    s, pos, d, q = positions(width, 0)
    lo, hi, node, depth, reached, created = _descend(
        keys, key_bits, level, pe, seg, splits, child_base, s, d, q, leaf_size
    )
    size = hi - lo
    is_slot = pos < P
    slot_index = s * P + dr.minimum(pos, P - 1)
    c0 = dr.gather(UInt32, child_base, slot_index, is_slot)
    split_flag = dr.gather(UInt32, UInt32(splits_here), slot_index, is_slot)
    is_internal = reached & is_slot & (split_flag != 0)
    is_leaf = reached & created & (size <= leaf_size)
    write = is_internal | is_leaf
    dr.scatter(records.first, dr.select(is_internal, c0, lo), node, write)
    dr.scatter(records.count, dr.select(is_internal, 0, size), node, write)
    dr.scatter(records.depth, depth, node, write)
    # The same lanes' bottom positions (pos >= P) are the next pass's candidates: keep
    # their ranges rather than walking the treelets a third time.
    keep = reached & ~is_slot & (size > leaf_size)
    dr.eval(records.first, records.count, records.depth, lo, hi, node, depth, keep)

    # ---- Next pass's segments: ranges still larger than a leaf at the treelet bottom ----
    bottom = dr.arange(UInt32, S * (P + 1))
    lane = (bottom // (P + 1)) * width + P + bottom % (P + 1)
    keep = dr.gather(ns.Bool, keep, lane)
    index = dr.prefix_sum(UInt32(keep))
    last = dr.opaque(UInt32, len(index) - 1)
    kept = dr.gather(UInt32, index, last) + UInt32(dr.gather(ns.Bool, keep, last))
    dr.eval(index, keep, kept)
    count = int(kept[0])
    remap = dr.select(keep, index, NONE)
    # Every entry of the new segments is written below: no need to clear them.
    out = Segments(*(dr.empty(UInt32, count) for _ in range(4)))
    if count:
        for target, value in zip((out.start, out.end, out.node, out.depth), (lo, hi, node, depth)):
            dr.scatter(target, dr.gather(UInt32, value, lane, keep), index, keep)
    dr.eval(out.start, out.end, out.node, out.depth, remap)
    return out, remap
