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
    """Preallocated node arrays the emission writes into (see kernels/bvh.py), and the
    number of nodes allocated so far."""

    first: object  # UInt32[capacity]
    count: object  # UInt32[capacity]
    depth: object  # UInt32[capacity]
    total: int


def open_segments(start, end, node, depth, records: NodeRecords, leaf_size: int) -> Segments:
    """Finalise the given ranges that are small enough as leaves; return the rest.

    Args:
        start, end, node, depth: UInt32[S] ranges ``[start, end)`` (sorted by start, each
            non-empty) and the node that owns each.
        records: node arrays; the leaves are written into them.
        leaf_size: most primitives in a leaf.
    """
    dr.make_opaque(start, end, node, depth)  # sizes vary: never bake them into kernels
    size = end - start
    is_leaf = size <= leaf_size
    dr.scatter(records.first, start, node, is_leaf)
    dr.scatter(records.count, size, node, is_leaf)
    dr.scatter(records.depth, depth, node, is_leaf)
    dr.eval(records.first, records.count, records.depth)
    keep = dr.compress(~is_leaf)
    return Segments(*(dr.gather(type(start), a, keep) for a in (start, end, node, depth)))


def emit_hierarchy(
    keys,
    key_bits: int,
    level: int,
    segments: Segments,
    records: NodeRecords,
    leaf_size: int,
    p: int,
) -> int:
    """Emit the tree below ``segments`` from bit plane ``level`` down, then split
    identical-key segments at their middle.

    Args:
        keys: UInt32[N] or UInt64[N] Morton codes in sorted order, ``key_bits`` wide.
        key_bits: width of the keys in bits (30 or 60).
        level: the first bit plane to process (0 = the most significant key bit); every
            segment's keys must agree on the planes above it.
        segments: the open segments (see :func:`open_segments`).
        records: node arrays with room for every node (``2N - 1`` in all suffices);
            written in place.
        leaf_size: most primitives in a leaf.
        p: bit planes per pass.
    Returns:
        The number of passes run.
    """
    passes = 0
    while len(segments) > 0 and level < key_bits:
        pe = min(p, key_bits - level)
        splits = _block_splits(keys, key_bits, level, pe, segments)
        segments = _emit_treelets(keys, key_bits, level, pe, segments, splits, records, leaf_size)
        level += pe
        passes += 1
    while len(segments) > 0:
        # All keys of each segment are equal: split at the middle index.
        mid = (segments.start + segments.end) >> 1
        segments = _emit_treelets(keys, key_bits, key_bits, 1, segments, mid, records, leaf_size)
        passes += 1
    return passes


def _block_splits(keys, key_bits: int, level: int, pe: int, seg: Segments):
    """emit_block_splits of Figure 4: UInt32[S * P], the primitive index that starts
    the split of each treelet slot, 0 where the slot has none (a split never starts at
    primitive 0)."""
    ns = namespace_of(seg.start)
    UInt32 = ns.UInt32
    n = len(keys)
    P = (1 << pe) - 1
    width = 64 if dr.type_v(keys) == dr.VarType.UInt64 else 32

    # ---- Segment of each primitive: count the segment heads at or before it ----
    heads = dr.zeros(UInt32, n)
    dr.scatter(heads, 1, seg.start)
    seen = dr.cumsum(heads)
    i = dr.arange(UInt32, n)
    in_some = seen > 0
    sid = dr.select(in_some, seen - 1, 0)
    inside = (
        in_some
        & (i > dr.gather(UInt32, seg.start, sid, in_some))
        & (i < dr.gather(UInt32, seg.end, sid, in_some))
    )

    # ---- Highest bit plane where a primitive differs from its predecessor ----
    key = dr.gather(type(keys), keys, i, inside)
    prev = dr.gather(type(keys), keys, i - 1, inside)
    Key = type(keys)
    plane = UInt32(dr.lzcnt(key ^ prev)) - (width - key_bits)
    lvl = dr.opaque(UInt32, level)
    is_split = inside & (key != prev) & (plane >= lvl) & (plane < lvl + pe)
    j = dr.select(is_split, plane - lvl, 0)

    # ---- Treelet slot: plane j under the j key bits above it ----
    q = UInt32((key >> Key(key_bits - lvl - j)) & ((Key(1) << Key(j)) - 1))
    slot = (UInt32(1) << j) - 1 + q
    splits = dr.zeros(UInt32, len(seg) * P)
    dr.scatter(splits, i, sid * P + slot, is_split)
    dr.eval(splits)
    return splits


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
    """emit_treelets of Figure 4: write the nodes of every segment's treelet and return
    the segments of the next pass."""
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
    child_base = dr.prefix_sum(flag) * 2 + dr.opaque(UInt32, records.total)
    split_count = int(dr.sum(flag)[0]) if S * P > 0 else 0
    child_base = dr.select(splits_here, child_base, 0)
    dr.eval(child_base)

    # ---- Node records: internal where a slot splits, leaves where small ranges appear ----
    s, pos, d, q = positions(2 * P + 1, 0)
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
    dr.eval(records.first, records.count, records.depth)
    records.total += 2 * split_count

    # ---- Next pass's segments: ranges still larger than a leaf at the treelet bottom ----
    s, pos, d, q = positions(P + 1, pe)
    lo, hi, node, depth, reached, _ = _descend(
        keys, key_bits, level, pe, seg, splits, child_base, s, d, q, leaf_size
    )
    keep = dr.compress(reached & (hi - lo > leaf_size))
    return Segments(*(dr.gather(UInt32, a, keep) for a in (lo, hi, node, depth)))
