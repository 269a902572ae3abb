"""Hierarchy emission: the partial breadth-first emission of Pantaleoni & Luebke 2010
(seed Figure 4), turning primitives sorted by Morton code into a binary tree.

A *segment* is a run of sorted primitives that share a node of the tree being emitted;
all its keys agree on the bit planes above the current ``level``. Each pass considers
``p`` bit planes ``[level, level + p)`` at once:

1. *Splits* (found by the treelet walk below): a range of sorted keys that agree on
   the planes above ``level + j`` splits at plane ``level + j`` before its first key
   with a 1 there, found by a binary search over the range (its keys are sorted, so
   that bit is 0 up to some index and 1 after). A range whose keys all have the same
   bit there has no split at that plane and passes to the child that bit selects. The
   splits of a segment's *treelet*, a complete binary tree of ``P = 2^p - 1`` slots in
   breadth-first order (slot ``2^j - 1 + q`` at plane ``level + j`` under the key
   bits ``q`` above it), are those of its reached slots. (The paper finds them with one
   lane per primitive and pass, comparing each key with the previous one; searching
   per slot touches only the slots' ranges and needs no per-primitive segment ids.)
2. *Treelet emission* (one lane per segment, then one per treelet position): a segment's
   lane walks its treelet top-down in breadth-first order, finding the splits as it
   goes. A slot reached by a range of more than ``leaf_size`` primitives and holding a
   split emits two children; a range without a split at a slot passes to the child its
   keys' bit selects. Children are
   numbered by an exclusive prefix sum over the segments' split counts, two adjacent
   indices per split, in (segment, slot) order. Then one lane per position writes its
   record: ranges of at most ``leaf_size`` primitives become leaves where they are
   created; ranges still larger at the bottom of the treelet become the next pass's
   segments (with their heads in key order).

Once every bit plane is used, a segment still larger than ``leaf_size`` holds identical
keys: it is split at its middle index, pass after pass (the same treelet machinery with
``p = 1``, the split the middle), so every tree is finite and balanced there.

Each node's record (``node_first``, ``node_count``, ``node_depth``) is written exactly
once, when the node is finalised as an internal node or a leaf.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

from .arrays import high_half, low_half, namespace_of, pack_halves


NONE = 0xFFFFFFFF  # a range still owned by its segment's node (no split created it)


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


def emit_hierarchy(keys, key_bits: int, level: int, roots, records: NodeRecords,
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
        records: node arrays, written in place; ``records.total`` grows.
        leaf_size: most primitives in a leaf.
        p: bit planes per pass.
    Returns:
        The number of passes run.
    """
    segments = _open_roots(*roots, records, leaf_size)
    passes = 0
    while len(segments) > 0:
        # Past the last bit plane all keys of a segment are equal: middle splits.
        pe = min(p, key_bits - level) if level < key_bits else 1
        segments = _emit_treelets(keys, key_bits, level, pe, segments, records, leaf_size)
        level = min(level + pe, key_bits)
        passes += 1
    return passes


def _open_roots(start, end, node, depth, records: NodeRecords, leaf_size: int):
    """Finalise the roots small enough as leaves; return the open ones as Segments."""
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
    return Segments(*(dr.gather(UInt32, a, keep) for a in (start, end, node, depth)))


def _first_with_bit(keys, key_bits: int, plane: int, lo, hi, active):
    """The first index in ``[lo, hi)`` whose key has a 1 on bit plane ``plane``
    (``hi`` if none), for sorted keys that agree on the planes above it: a binary
    search, one symbolic loop (inactive lanes return ``lo``)."""
    Key = type(keys)
    # Opaque: a literal shift would compile a kernel of its own for every bit plane.
    shift = dr.opaque(Key, key_bits - 1 - plane)

    def body(a, b):
        m = (a + b) >> 1
        one = ((dr.gather(Key, keys, m) >> shift) & 1) == 1
        return dr.select(one, a, m + 1), dr.select(one, m, b)

    a, _ = dr.while_loop(mode="symbolic", state=(lo, dr.select(active, hi, lo)),
                         cond=lambda a, b: a < b, body=body, labels=("a", "b"))
    return a


def _walk_treelets(keys, key_bits, level, pe, seg, leaf_size):
    """Evaluate every segment's treelet top-down, one lane per segment, positions in
    breadth-first order (slots ``0..P-1``, then the ``P+1`` bottom positions).

    A slot reached by a range of more than ``leaf_size`` primitives splits it at its
    plane's split (:func:`_first_with_bit`; for middle splits, ``level == key_bits``,
    at the range's middle index) and gives its two children the halves (they are
    *created*); a range whose keys agree on that plane passes to the child their bit
    selects. The ``k``-th split of a segment's treelet in breadth-first order creates
    its children ``2k, 2k+1`` of the segment's block of new nodes.

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
        step = reached & (hi - lo > leaf_size)
        if level < key_bits:
            sp = _first_with_bit(keys, key_bits, level + (t + 1).bit_length() - 1, lo, hi, step)
            has = step & (sp > lo) & (sp < hi)
            all_ones = sp == lo  # without a split the range follows its keys' bit
        else:
            sp = (lo + hi) >> 1
            has = step
        splits_at.append(has)
        for right in (False, True):
            follows = has if level >= key_bits else has | (step & (all_ones == right))
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


def _emit_treelets(keys, key_bits, level, pe, seg, records: NodeRecords, leaf_size):
    """emit_treelets of Figure 4: write the nodes of every segment's treelet.

    Two kernels: one lane per segment walks its treelet (:func:`_walk_treelets`) and
    stores every position's range with the segment's split and continuing-range
    counts; after a prefix sum over the segments (the first new node and the first
    next-pass segment of each), one lane per position writes its node record and, at
    the bottom, its next-pass segment.

    Returns the segments of the next pass, in (segment, bottom position) order, so
    sorted by ``start``."""
    ns = namespace_of(seg.start)
    UInt32 = ns.UInt32
    S = len(seg)
    P = (1 << pe) - 1
    width = 2 * P + 1

    # ---- One lane per segment: every position's range, the segment's counts ----
    states, splits_at, keeps_at = _walk_treelets(keys, key_bits, level, pe, seg, leaf_size)
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
    counts = pack_halves(n_split, kept)
    dr.eval(tables, counts)

    # ---- First new node and first next-pass segment of every segment ----
    # (the totals read once to the host: the node count then goes back as an opaque
    # value, with no size-1 kernels in between)
    through = dr.cumsum(counts)
    total = int(through[S - 1])
    count, nodes = low_half(total), int(records.total[0])
    before = through - counts
    node_base = high_half(before) * 2 + dr.opaque(UInt32, nodes)
    seg_base = low_half(before)
    records.total = dr.opaque(UInt32, nodes + 2 * high_half(total))
    dr.eval(node_base, seg_base)

    # ---- One lane per position: node records, next-pass segments ----
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
    # Every entry of the new segments is written below: no need to clear them.
    out = Segments(*(dr.empty(UInt32, count) for _ in range(4)))
    if count:
        for target, value in zip((out.start, out.end, out.node, out.depth), (lo, hi, node, depth)):
            dr.scatter(target, value, index, keep)
    dr.eval(records.first, records.count, records.depth, out.start, out.end, out.node,
            out.depth)
    return out
