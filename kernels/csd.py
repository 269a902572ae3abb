"""The compress-sort-decompress (CSD) sort of Morton keys (Garanzha & Loop 2010, as used
by HLBVH, Pantaleoni & Luebke 2010; seed slides "Compress-Sort-Decompress").

Meshes are spatially coherent: consecutive primitives of a mesh, and the primitives in
last frame's order, mostly fall into the same coarse voxel. CSD exploits it:

1. **Compress**: run-length encode the keys, taken in a start order (identity, or a
   previous frame's order), on their top ``3m`` bits (the coarse key): one run per
   maximal stretch of equal coarse keys.
2. **Sort** the runs by their coarse key (a ``3m``-bit stable radix sort of the runs
   only, often far fewer than the keys).
3. **Decompress**: run-length decode the sorted runs back into primitives. Now the
   primitives are grouped by coarse voxel, in ascending voxel order, and inside a voxel
   in start order.
4. **Fine sort** inside each coarse voxel on the remaining bits. Only voxels that are
   not in key order are touched: their keys are gathered, stably sorted on all their
   bits (the voxel's top bits are equal) and put back on their own slots.

Three shortcuts give the same result for less. When the keys are already in order in
the start order (last frame's order, keys unchanged or moved without reordering), one
pass that finds no descent returns the start order. When the compression does not
compress (more runs than half the keys: an incoherent soup), or when more than half of
the keys lie in voxels that would need their fine sort, the keys (in start order) are
sorted whole: same stable order, less work than decoding the runs and gathering those
keys. Whether a voxel needs its fine sort is read off the runs before decoding them:
a run holding a descent, or a run starting below where the voxel's previous run ended.

What the run bookkeeping costs against a plain sort, from last frame's order and
without it, is in docs/decisions.md#csd-sort.

Whether last frame's order is worth starting from at all is estimated first
(:func:`seed_pays`) from a sample of neighbouring pairs in that order: where the sample
says the sort would fall back to sorting every key anyway (as many descents inside runs
as runs: the mesh moved by more than a fine cell everywhere), the caller starts from
scratch and saves the two gathers through the start order.

The result equals a full stable sort of the keys taken in start order:
``start[argsort(keys[start], stable)]`` (ties keep their start order).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from .arrays import namespace_of, plain

# Most bits per pass of the LSD radix sort. CPU: 15 sorts 30-bit keys in two passes
# and 60-bit ones in four, and a 12-bit coarse key still in one (a pass of 15 bits
# costs little more than one of 10 at 1M keys, see docs/decisions.md#radix-width); GPU: Dr.Jit's
# own choice in dr.argsort (8, shared memory is smaller).
_RADIX_BITS = {dr.JitBackend.LLVM: 15, dr.JitBackend.CUDA: 8}
# Below this many keys, keys wider than one pass are sorted 10 bits a pass on the CPU:
# a pass's 2^15 buckets cost more than a third pass (docs/decisions.md#radix-width).
_WIDE_RADIX_FROM = 1 << 18


@dataclass
class CsdResult:
    """What :func:`csd_sort` returns.

    Attributes:
        order: UInt32[N], slot -> primitive index; a permutation of ``0..N-1``.
        sorted_keys: keys[order], same type as the keys (UInt32 or UInt64), ascending.
        runs: number of runs of equal coarse keys in start order (the compressed
            length; about N when nothing is coherent, the number of occupied voxels
            when the start order already groups them).
        coarse_clusters: number of distinct coarse keys (occupied coarse voxels).
        cluster_start: UInt32[coarse_clusters], the first slot of each coarse voxel in
            sorted order, ascending: the clusters of the HLBVH top level.
        resorted: number of keys the fine sort had to sort: those in coarse voxels
            not in key order after decompression (0 when the start order already
            sorts the keys; N when the keys were sorted directly).
    """

    order: Any
    sorted_keys: Any
    runs: int
    coarse_clusters: int
    resorted: int
    cluster_start: Any = None


def csd_sort(keys, key_bits: int, coarse_bits: int, start_order=None) -> CsdResult:
    """Stable sort of Morton keys by compress-sort-decompress (module docstring).

    Args:
        keys: UInt32[N] or UInt64[N], every key below ``2^key_bits``.
        key_bits: width of the keys (1..32 for UInt32, 1..64 for UInt64), e.g. 30 or 60.
        coarse_bits: the top bits that name a coarse voxel (``3m``), 0..key_bits. 0 is
            one voxel (a plain stable sort); ``key_bits`` sorts runs of whole keys.
        start_order: UInt32[N] permutation of ``0..N-1`` (e.g. last frame's
            ``order``) to start from; None for the identity. Anything convertible to
            the keys' UInt32 type (a list, a numpy array) is accepted.

    Returns:
        :class:`CsdResult`; ``order`` equals
        ``start[numpy.argsort(keys[start], kind="stable")]`` exactly.

    Raises:
        TypeError: ``keys`` is not a UInt32 or UInt64 JIT array.
        ValueError: a bit count out of range, a key wider than ``key_bits``, or a
            ``start_order`` that is not a permutation of ``0..N-1``.
    """
    ns, keys = _checked_keys(keys, key_bits)
    if not isinstance(coarse_bits, int) or not 0 <= coarse_bits <= key_bits:
        raise ValueError(
            f"csd_sort: coarse_bits={coarse_bits!r}: expected an int in 0..{key_bits} "
            "(at most key_bits)"
        )
    Key, UInt32 = type(keys), ns.UInt32
    n = dr.width(keys)
    start = dr.arange(UInt32, n) if start_order is None else _checked_order(ns, start_order, n)
    if n == 0:
        return CsdResult(start, keys, runs=0, coarse_clusters=0, resorted=0,
                         cluster_start=dr.zeros(UInt32, 0))

    # ---- Compress: run-length encode the coarse keys in start order ----
    key = dr.gather(Key, keys, start)
    coarse = _coarse_keys(key, key_bits, coarse_bits)
    runs = _compress(key, coarse)
    if not dr.any(runs.descent)[0]:
        # Already sorted in start order: each run is a whole voxel, nothing moves.
        return CsdResult(start, key, runs.count, coarse_clusters=runs.count, resorted=0,
                         cluster_start=runs.start)
    if runs.count > n // 2 or runs.inner_descents[0] >= runs.count:
        # Incoherent keys (a random soup): the runs are about as many as the keys, and
        # sorting and decoding them would cost more than sorting the keys themselves.
        # Or as many descents inside runs as there are runs (a mesh that moved by more
        # than a fine cell since the start order was taken): nearly every voxel would
        # need its fine sort, so the keys are sorted whole at once.
        order, sorted_keys = _sorted_whole(key, key_bits, start)
        sorted_coarse = _coarse_keys(sorted_keys, key_bits, coarse_bits)
        voxel_start = dr.compress((runs.slot == 0) | (
            sorted_coarse != dr.gather(type(coarse), sorted_coarse, runs.before)))
        return CsdResult(order, sorted_keys, runs.count, coarse_clusters=dr.width(voxel_start),
                         resorted=n, cluster_start=voxel_start)
    # Sizes enter kernels as opaque values, so a new run count compiles nothing.
    end = dr.opaque(UInt32, n)

    # ---- Sort the runs by coarse key (stable: equal voxels keep start order) ----
    moved = _sort_runs(runs, coarse, coarse_bits, end)

    # ---- Which coarse voxels will not be in key order after decompression ----
    voxels = _voxels_out_of_order(key, runs, moved, end)
    if voxels.resorted > n // 2:
        # Most voxels need their fine sort: sorting all keys in start order gives the
        # same stable order, for less than decoding the runs and gathering those keys.
        order, sorted_keys = _sorted_whole(key, key_bits, start)
        return CsdResult(order, sorted_keys, runs.count, voxels.count, resorted=n,
                         cluster_start=voxels.start)

    # ---- Decompress: run-length decode the sorted runs into slots ----
    source, slot_run = _decompress(runs, moved, n)
    sorted_keys = dr.gather(Key, key, source)

    # ---- Fine sort inside each coarse voxel that is not in key order ----
    if voxels.resorted:
        dr.eval(source, sorted_keys)
        voxel_of_run = dr.cumsum(UInt32(moved.voxel_head)) - 1
        in_unsorted = dr.gather(ns.Bool, dr.gather(ns.Bool, voxels.unsorted, voxel_of_run),
                                slot_run)
        fine, sorted_keys = _voxel_sort(sorted_keys, key_bits, in_unsorted)
        source = dr.gather(UInt32, source, fine)
    order = dr.gather(UInt32, start, source)
    dr.eval(order, sorted_keys, voxels.start)
    return CsdResult(order, sorted_keys, runs.count, voxels.count, voxels.resorted, voxels.start)


@dataclass
class _Runs:
    """The runs of equal coarse keys in start order (the compressed keys). Per slot of
    the start order (UInt32/Bool[N]): ``slot``, ``before`` (the slot before it, 0 for
    0), ``descent`` (its key is below the one before); ``start``: UInt32[R] each run's
    first slot; ``count``: R; ``inner_descents``: UInt32[1] descents inside runs."""

    slot: Any
    before: Any
    descent: Any
    start: Any
    count: int
    inner_descents: Any


def _compress(key, coarse) -> _Runs:
    """Run-length encode the coarse keys ``coarse`` of ``key`` (both in start order)."""
    Key, Coarse = type(key), type(coarse)
    UInt32 = dr.uint32_array_t(Key)
    n = dr.width(key)
    slot = dr.arange(UInt32, n)
    before = dr.maximum(slot, 1) - 1
    run_head = (slot == 0) | (coarse != dr.gather(Coarse, coarse, before))
    descent = (slot > 0) & (key < dr.gather(Key, key, before))
    dr.eval(key, run_head, descent)
    run_start = dr.compress(run_head)  # UInt32[R]
    return _Runs(slot=slot, before=before, descent=descent, start=run_start,
                 count=dr.width(run_start), inner_descents=dr.count(descent & ~run_head))


@dataclass
class _SortedRuns:
    """The runs in coarse-key order (UInt32/Bool[R]): ``src_start``/``src_end`` their
    slots in start order, ``dst_start`` their first slot once decoded, ``voxel_head``
    whether a run starts a coarse voxel, ``run`` 0..R-1."""

    src_start: Any
    src_end: Any
    dst_start: Any
    voxel_head: Any
    run: Any


def _sort_runs(runs: _Runs, coarse, coarse_bits: int, end) -> _SortedRuns:
    """Sort the runs by coarse key, stably (equal voxels keep start order)."""
    Coarse = type(coarse)
    UInt32 = dr.uint32_array_t(Coarse)
    run_end = _next_or(runs.start, end)
    run_key = dr.gather(Coarse, coarse, runs.start)
    by_key, sorted_run_key = _radix_sort(run_key, coarse_bits)
    src_start = dr.gather(UInt32, runs.start, by_key)
    src_end = dr.gather(UInt32, run_end, by_key)
    dst_start = dr.prefix_sum(src_end - src_start)
    run = dr.arange(UInt32, runs.count)
    voxel_head = (run == 0) | (
        sorted_run_key != dr.gather(Coarse, sorted_run_key, dr.maximum(run, 1) - 1)
    )
    dr.eval(src_start, src_end, dst_start, voxel_head)
    return _SortedRuns(src_start, src_end, dst_start, voxel_head, run)


@dataclass
class _Voxels:
    """The coarse voxels after the runs' sort: ``start`` UInt32[C] each voxel's first
    slot, ``count`` C, ``unsorted`` Bool[C] whether it is out of key order, and
    ``resorted`` the keys in those voxels."""

    start: Any
    count: int
    unsorted: Any
    resorted: int


def _voxels_out_of_order(key, runs: _Runs, moved: _SortedRuns, end) -> _Voxels:
    """Which coarse voxels will not be in key order after decompression.

    A voxel is out of order when one of its runs holds a descent, or when a run ends
    above the key its successor in the voxel starts with; both are read at the run
    ends, from a prefix count of the descents in start order."""
    Key = type(key)
    UInt32 = dr.uint32_array_t(Key)
    src_start, src_end, run = moved.src_start, moved.src_end, moved.run
    descents = dr.cumsum(UInt32(runs.descent))
    inner = dr.gather(UInt32, descents, src_end - 1) != dr.gather(UInt32, descents, src_start)
    prev_run = dr.maximum(run, 1) - 1
    step_down = ~moved.voxel_head & (
        dr.gather(Key, key, dr.gather(UInt32, src_end, prev_run) - 1)
        > dr.gather(Key, key, src_start)
    )
    bad_run = UInt32(inner | step_down)  # over sorted runs
    bad_runs = dr.cumsum(bad_run)
    voxel_first_run = dr.compress(moved.voxel_head)  # UInt32[C]
    voxel_last_run = _next_or(voxel_first_run, dr.opaque(UInt32, runs.count)) - 1
    # Bad runs of a voxel: the inclusive count at its last run minus that before its first.
    unsorted = dr.gather(UInt32, bad_runs, voxel_last_run) != (
        dr.gather(UInt32, bad_runs, voxel_first_run) - dr.gather(UInt32, bad_run, voxel_first_run)
    )
    voxel_start = dr.gather(UInt32, moved.dst_start, voxel_first_run)
    voxel_size = _next_or(voxel_start, end) - voxel_start
    resorted = int(dr.sum(dr.select(unsorted, voxel_size, 0))[0])
    return _Voxels(voxel_start, dr.width(voxel_first_run), unsorted, resorted)


def _decompress(runs: _Runs, moved: _SortedRuns, n: int):
    """Run-length decode the sorted runs into slots: ``(source, slot_run)``, UInt32[N]
    each slot's position in start order and the sorted run it belongs to."""
    UInt32 = type(runs.slot)
    is_dst_start = dr.zeros(UInt32, n)
    dr.scatter(is_dst_start, UInt32(1), moved.dst_start)
    slot_run = dr.cumsum(is_dst_start) - 1
    source = (dr.gather(UInt32, moved.src_start, slot_run) + runs.slot
              - dr.gather(UInt32, moved.dst_start, slot_run))
    return source, slot_run


#: Neighbouring pairs of the start order sampled by :func:`seed_pays`: one every so many.
_SEED_SAMPLE_STRIDE = 64


def seed_pays(keys, key_bits: int, coarse_bits: int, start_order) -> bool:
    """Whether :func:`csd_sort` can gain from starting at ``start_order`` (last frame's
    order) rather than at the identity.

    The sort falls back to sorting every key when the start order has more runs of
    equal coarse keys than half the keys (it does not group the voxels), or as many
    descents inside runs as there are runs (the mesh moved by more than a fine cell
    nearly everywhere, so nearly every coarse voxel would need its fine sort); then the
    start order only costs two gathers through it. Both counts are estimated from every
    ``_SEED_SAMPLE_STRIDE``-th neighbouring pair of the start order (one small kernel
    and a host read): False when run heads are more than half the sampled pairs, or
    when the sampled descents exceed twice the sampled run heads plus a margin of 8
    (sampling noise).

    Args:
        keys: UInt32[N] or UInt64[N], the keys to sort; ``key_bits``, ``coarse_bits`` as
            :func:`csd_sort` takes them.
        start_order: UInt32[N], a permutation of ``0..N-1`` (not checked here).
    """
    ns = namespace_of(keys)
    UInt32, Key = ns.UInt32, type(keys)
    pairs = dr.width(keys) // _SEED_SAMPLE_STRIDE
    if pairs == 0:
        return True  # a few keys: trying costs nothing
    second = dr.arange(UInt32, pairs) * _SEED_SAMPLE_STRIDE + 1
    a, b = (dr.gather(Key, keys, dr.gather(UInt32, UInt32(start_order), i))
            for i in (second - 1, second))
    head = _coarse_keys(a, key_bits, coarse_bits) != _coarse_keys(b, key_bits, coarse_bits)
    heads, descents = dr.count(head), dr.count((b < a) & ~head)
    dr.eval(heads, descents)
    heads, descents = int(heads[0]), int(descents[0])
    return 2 * heads <= pairs and descents <= 2 * heads + 8


def _sorted_whole(key, key_bits: int, start):
    """``(order, sorted_keys)`` of a plain stable sort of ``key`` (keys in start
    order), evaluated."""
    by_key, sorted_keys = _radix_sort(key, key_bits)
    order = dr.gather(namespace_of(start).UInt32, start, by_key)
    dr.eval(order, sorted_keys)
    return order, sorted_keys


def _next_or(first, end):
    """For sorted segment starts ``first`` (UInt32[S]), each segment's end: the next
    start, and ``end`` (an opaque UInt32) for the last."""
    ns = namespace_of(first)
    i = dr.arange(ns.UInt32, dr.width(first))
    last = dr.opaque(ns.UInt32, dr.width(first) - 1)
    return dr.select(i < last, dr.gather(ns.UInt32, first, i + 1, i < last), end)


def _coarse_keys(keys, key_bits: int, coarse_bits: int):
    """The top ``coarse_bits`` of each key (its coarse voxel): UInt32 when they fit,
    else the keys' own type; zeros when ``coarse_bits`` is 0."""
    ns = namespace_of(keys)
    Coarse = ns.UInt32 if coarse_bits <= 32 else type(keys)
    if coarse_bits == 0:
        return dr.zeros(Coarse, dr.width(keys))
    return Coarse(keys >> (key_bits - coarse_bits))


def _voxel_sort(keys, key_bits, resort):
    """The stable sort of ``keys`` (grouped by coarse voxel, voxels ascending) that only
    moves keys inside the voxels flagged in ``resort``.

    Args:
        keys: UInt32[N] or UInt64[N], grouped by coarse voxel in ascending order.
        key_bits: significant bits of the keys.
        resort: Bool[N], true on every slot of a voxel to sort, false on every slot of
            a voxel already in key order.

    Returns:
        ``(perm, sorted_keys)``: UInt32[N] with slot ``i`` of the sorted sequence
        taking ``keys[perm[i]]``, and that sequence.
    """
    ns = namespace_of(keys)
    # Whole voxels are gathered in ascending voxel order, so a stable sort of the
    # gathered keys keeps them grouped and puts each voxel back onto its own slots.
    slots = dr.compress(resort)
    by_key, _ = _radix_sort(dr.gather(type(keys), keys, slots), key_bits)
    perm = dr.arange(ns.UInt32, dr.width(keys))
    dr.scatter(perm, dr.gather(ns.UInt32, slots, by_key), slots)
    return perm, dr.gather(type(keys), keys, perm)


def _radix_sort(values, bits: int):
    """Stable ascending sort of unsigned integers below ``2^bits``: an LSD radix sort
    with as few passes as the key width needs (``dr.argsort`` always sorts all 32 or 64
    bits), each pass one ``dr.detail.block_mkperm`` (the primitive under
    ``dr.argsort``).

    Args:
        values: UInt32[K] or UInt64[K].
        bits: significant low bits of ``values`` (higher bits are ignored).

    Returns:
        ``(perm, sorted_values)``: UInt32[K] permutation with ``values[perm]``
        ascending, ties in index order; and ``values[perm]`` (the last pass's gather).
    """
    ns = namespace_of(values)
    count = dr.width(values)
    if bits == 0 or count <= 1:
        return dr.arange(ns.UInt32, count), values
    radix = _RADIX_BITS[dr.backend_v(values)]
    if bits > radix and count < _WIDE_RADIX_FROM:
        radix = min(radix, 10)
    passes = -(-bits // radix)
    width = -(-bits // passes)  # balanced passes: 30 bits -> 10 + 10 + 10
    Value = type(values)
    perm = None
    for p in range(passes):
        digit = ns.UInt32((values >> (p * width)) & Value((1 << width) - 1))
        dr.eval(digit, values)
        step = dr.detail.block_mkperm(digit, count, 1 << width)
        values = dr.gather(Value, values, step)
        perm = step if perm is None else dr.gather(ns.UInt32, perm, step)
    return perm, values


def _checked_keys(keys, key_bits):
    """``(namespace, keys)`` with keys a plain UInt32/UInt64 array and every key below
    ``2^key_bits``; TypeError / ValueError otherwise."""
    if not dr.is_jit_v(keys) or dr.type_v(keys) not in (dr.VarType.UInt32, dr.VarType.UInt64):
        raise TypeError(
            f"csd_sort: keys must be a UInt32 or UInt64 Dr.Jit array (Morton codes), "
            f"got {type(keys).__name__}"
        )
    ns = namespace_of(keys)
    wide = dr.type_v(keys) == dr.VarType.UInt64
    keys = plain(keys, 'UInt64' if wide else 'UInt32')
    limit = 64 if wide else 32
    if not isinstance(key_bits, int) or not 1 <= key_bits <= limit:
        raise ValueError(
            f"csd_sort: key_bits={key_bits!r}: expected an int in 1..{limit} for "
            f"{'UInt64' if wide else 'UInt32'} keys"
        )
    if key_bits < limit and dr.width(keys) and dr.max(keys)[0] >> key_bits:
        raise ValueError(
            f"csd_sort: a key is {int(dr.max(keys)[0])}, wider than key_bits={key_bits}; "
            "pass the width the keys were made with"
        )
    return ns, keys


def _checked_order(ns, start_order, n):
    """``start_order`` as a plain UInt32 array of ``n`` entries, checked to look like a
    permutation of 0..n-1."""
    order = plain(ns.UInt32(start_order), 'UInt32')
    if dr.width(order) != n:
        raise ValueError(
            f"csd_sort: start_order has {dr.width(order)} entries for {n} keys; pass the "
            "order of a previous sort of the same primitives (or None)"
        )
    if n == 0:
        return order
    # A range check (gathers stay in bounds) and the sums of the entries and of their
    # squares (both mod 2^32), which catch a repeated index unless other entries make
    # up for it in both; an exact check would cost a random scatter over N.
    largest, total, squares = dr.max(order), dr.sum(order), dr.sum(order * order)
    dr.eval(largest, total, squares)
    if (
        largest[0] >= n
        or total[0] != n * (n - 1) // 2 % 2**32
        or squares[0] != (n - 1) * n * (2 * n - 1) // 6 % 2**32
    ):
        raise ValueError(
            "csd_sort: start_order is not a permutation of 0..N-1 (an index is out of "
            "range or repeats); pass the order of a previous sort of the same primitives"
        )
    return order
