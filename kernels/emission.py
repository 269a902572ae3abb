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
2. *Treelet emission* (one lane per segment, then one per treelet position): a segment's
   lane walks its treelet top-down in breadth-first order. A slot reached by a range of
   more than ``leaf_size`` primitives and holding a split emits two children; a range
   without a split at a slot passes to the child its keys' bit selects. Children are
   numbered by an exclusive prefix sum over the segments' split counts, two adjacent
   indices per split, in (segment, slot) order. Then one lane per position writes its
   record: ranges of at most ``leaf_size`` primitives become leaves where they are
   created; ranges still larger at the bottom of the treelet become the next pass's
   segments (with their heads in key order).

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


def _walk_treelets(keys, key_bits, level, pe, seg, splits, leaf_size):
    """Evaluate every segment's treelet top-down, one lane per segment, positions in
    breadth-first order (slots ``0..P-1``, then the ``P+1`` bottom positions).

    A slot reached by a range of more than ``leaf_size`` primitives and holding a split
    gives its two children the halves of the range (they are *created*); without a
    split, the range passes to the child its keys' bit on that plane selects (for
    middle splits, ``level == key_bits``, every open slot holds one). The ``k``-th
    split of a segment's treelet in breadth-first order creates its children
    ``2k, 2k+1`` of the segment's block of new nodes.

    Returns ``(states, splits_at, keeps_at)``: per position the tuple ``(lo, hi,
    depth, owner, reached, created)`` (``owner``: the created child's offset ``2k +
    side`` in the block, NONE for a range still owned by the segment's node), per slot
    whether it splits, and per bottom position whether a range larger than a leaf
    continues there.
    """
    ns = namespace_of(seg.start)
    UInt32, Bool = ns.UInt32, ns.Bool
    P = (1 << pe) - 1
    s = dr.arange(UInt32, len(seg))
    lanes = dr.width(s)
    states = [(dr.gather(UInt32, seg.start, s), dr.gather(UInt32, seg.end, s),
               dr.gather(UInt32, seg.depth, s), dr.full(UInt32, NONE, lanes),
               dr.full(Bool, True, lanes), dr.full(Bool, False, lanes))]
    splits_at, rank = [], dr.zeros(UInt32, lanes)
    for t in range(P):
        lo, hi, depth, owner, reached, _ = states[t]
        plane = level + (t + 1).bit_length() - 1
        step = reached & (hi - lo > leaf_size)
        sp = dr.gather(UInt32, splits, s * P + t, step)
        has = step & (sp != 0)
        splits_at.append(has)
        if level < key_bits:
            k = dr.gather(type(keys), keys, lo, step & ~has)
            bit_right = ((k >> (key_bits - 1 - plane)) & 1) == 1
        for right in (False, True):
            follows = has | (step & (bit_right == right if level < key_bits else True))
            states.append((
                dr.select(has & right, sp, lo),
                dr.select(has & (not right), sp, hi),
                dr.select(has, depth + 1, depth),
                dr.select(has, 2 * rank + (1 if right else 0), owner),
                follows,
                has,
            ))
        rank += UInt32(has)
    keeps_at = [reached & (hi - lo > leaf_size) for lo, hi, _, _, reached, _ in states[P:]]
    return states, splits_at, keeps_at


def _emit_treelets(keys, key_bits, level, pe, seg, splits, records: NodeRecords, leaf_size):
    """emit_treelets of Figure 4: write the nodes of every segment's treelet.

    Two kernels: one lane per segment walks its treelet (:func:`_walk_treelets`) and
    stores every position's range with the segment's split and continuing-range
    counts; after a prefix sum over the segments (the first new node and the first
    next-pass segment of each), one lane per position writes its node record and, at
    the bottom, its next-pass segment.

    Returns the segments of the next pass and UInt32[S * 2^pe] ``remap``: the index
    among them of every treelet bottom position, NONE where no segment continues."""
    ns = namespace_of(seg.start)
    UInt32, Bool = ns.UInt32, ns.Bool
    S = len(seg)
    P = (1 << pe) - 1
    width = 2 * P + 1

    # ---- One lane per segment: every position's range, the segment's counts ----
    states, splits_at, keeps_at = _walk_treelets(keys, key_bits, level, pe, seg, splits, leaf_size)
    flags = [UInt32(reached) | (UInt32(created) << 1) for *_, reached, created in states]
    flags[:P] = [f | (UInt32(has) << 2) for f, has in zip(flags[:P], splits_at)]
    keep_rank, kept = [], dr.zeros(UInt32, S)
    for keep in keeps_at:
        keep_rank.append(kept)
        kept = kept + UInt32(keep)
    n_split = sum((UInt32(h) for h in splits_at), dr.zeros(UInt32, S))
    s = dr.arange(UInt32, S)
    columns = [[st[c] for st in states] for c in range(4)] + [flags, [dr.zeros(UInt32, S)] * P + keep_rank]
    tables = [dr.empty(UInt32, S * width) for _ in columns]
    for table, column in zip(tables, columns):
        dr.scatter(table, ns.ArrayXu(column), s)
    counts = (ns.UInt64(n_split) << 32) | ns.UInt64(kept)
    dr.eval(tables, counts)

    # ---- First new node and first next-pass segment of every segment ----
    through = dr.cumsum(counts)
    total = dr.gather(ns.UInt64, through, dr.opaque(UInt32, S - 1))
    dr.eval(through, total)
    count = int((total & 0xFFFFFFFF)[0])
    before = through - counts
    node_base = UInt32(before >> 32) * 2 + records.total
    seg_base = UInt32(before & 0xFFFFFFFF)
    records.total = records.total + UInt32(total >> 32) * 2
    dr.eval(node_base, seg_base, records.total)

    # ---- One lane per position: node records, next-pass segments, remap ----
    lane = dr.arange(UInt32, S * width)
    ls, pos = lane // width, lane % width
    lo, hi, depth, owner, flag, rank = (dr.gather(UInt32, t, lane) for t in tables)
    base = dr.gather(UInt32, node_base, ls)
    node = dr.select(owner == NONE, dr.gather(UInt32, seg.node, ls), base + owner)
    reached, created, splits_here = (((flag >> b) & 1) == 1 for b in range(3))
    size = hi - lo
    # the children of a split slot: the node numbers of positions 2·pos + 1, + 2
    first_child = base + dr.gather(UInt32, tables[3], ls * width + dr.minimum(2 * pos + 1, width - 1))
    is_internal = reached & splits_here
    is_leaf = reached & created & (size <= leaf_size)
    write = is_internal | is_leaf
    dr.scatter(records.first, dr.select(is_internal, first_child, lo), node, write)
    dr.scatter(records.count, dr.select(is_internal, 0, size), node, write)
    dr.scatter(records.depth, depth, node, write)
    bottom = pos >= P
    keep = bottom & reached & (size > leaf_size)
    index = dr.gather(UInt32, seg_base, ls) + rank
    remap = dr.empty(UInt32, S * (P + 1))
    dr.scatter(remap, dr.select(keep, index, NONE), ls * (P + 1) + pos - P, bottom)
    # Every entry of the new segments is written below: no need to clear them.
    out = Segments(*(dr.empty(UInt32, count) for _ in range(4)))
    if count:
        for target, value in zip((out.start, out.end, out.node, out.depth), (lo, hi, node, depth)):
            dr.scatter(target, value, index, keep)
    dr.eval(records.first, records.count, records.depth, out.start, out.end, out.node,
            out.depth, remap)
    return out, remap
