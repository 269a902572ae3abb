"""Morton codes: primitive centroids quantised in the scene's bounds, their bits
interleaved, the key the HLBVH sorts by (Pantaleoni & Luebke 2010, after Lauterbach et
al. 2009).

A key of ``3·b`` bits holds ``b`` bits per axis: ``b = 10`` gives 30-bit keys in a
``UInt32``, ``b = 20`` gives 60-bit keys in a ``UInt64``. In each triplet of key bits
``x`` is the most significant and ``z`` the least: bit ``3i + 2`` of the key is bit ``i``
of the quantised ``x``, bit ``3i + 1`` that of ``y``, bit ``3i`` that of ``z``. The top
``3m`` bits of a key therefore name the centroid's cell in a ``2^m``-per-axis grid over
the same box: the coarse voxels of the CSD sort (:mod:`hlbvh.kernels.csd`).

Three functions, each of Dr.Jit arrays of the input's backend:

- :func:`point_bounds`: the box of a point set, as size-1 arrays (no host read);
- :func:`morton_codes`: the keys of centroids in a box;
- :func:`choose_key`: the ``morton_bits="auto"`` policy (30 or 60 bits, and rank
  quantisation when even 60-bit cells cannot tell the primitives apart);
  :func:`choose_morton_bits` is its bit count.

Numerical extremes are handled in the quantiser rather than by the caller: a box with
zero extent on an axis (flat scenes, all centroids equal) quantises that axis to 0, an
extent that would overflow to ``inf`` as ``hi - lo`` (coordinates near ``±3e38``) is
computed at half scale, and non-finite or out-of-box centroids are clamped into the
grid, so every key is a valid ``3·b``-bit integer.
"""

from __future__ import annotations

import drjit as dr

from .arrays import namespace_of, plain

MORTON_BITS = (30, 60)
#: How centroids are quantised to key cells (:func:`morton_codes`).
QUANTIZATIONS = ("cube", "axis", "rank")

# A primitive is "small" when its largest extent is below this fraction of a 30-bit
# cell (see choose_morton_bits for the argument and the measurements).
_SMALL_PRIM_CELL_FRACTION = 0.25
# 60-bit keys are chosen when at least this share of the primitives is small.
_SMALL_PRIM_SHARE = 0.01


def point_bounds(points):
    """The axis-aligned box of a point set, computed on the device.

    Args:
        points: Array3f[N], N >= 1 (e.g. the primitive centroids).

    Returns:
        ``(lo, hi)``: two Array3f[1] of the points' backend (plain, non-AD), the
        per-axis minimum and maximum. Nothing is read back to the host. Non-finite
        points give non-finite bounds.

    Raises:
        ValueError: ``points`` is empty.
    """
    points = plain(points, "Array3f")
    if dr.width(points) == 0:
        raise ValueError("point_bounds: points is empty; pass at least one point")
    # Float min/max reductions propagate NaN and run several times slower than integer
    # ones on the CPU (docs/decisions.md#centroid-bounds), so reduce the floats'
    # bit patterns, mapped to Int32 values that order like the floats.
    ns = namespace_of(points)
    ordered = ns.Array3i(*(_ordered_bits(ns, points[k]) for k in range(3)))
    dr.eval(ordered)
    lo, hi = dr.min(ordered, axis=1), dr.max(ordered, axis=1)  # axis=1: over the points
    return tuple(
        ns.Array3f(*(dr.reinterpret_array(ns.Float, _ordered_bits(ns, b[k])) for k in range(3)))
        for b in (lo, hi)
    )


def _ordered_bits(ns, x):
    """The IEEE bits of Float ``x`` as Int32 values that order like the floats
    (negatives get their magnitude bits flipped); applied to such Int32 values (as an
    ``Int32``), the same map gives the bits back."""
    bits = x if dr.type_v(x) == dr.VarType.Int32 else dr.reinterpret_array(ns.Int32, x)
    return bits ^ ((bits >> 31) & 0x7FFFFFFF)


def morton_codes(centroids, lo, hi, bits: int = 30, quantization: str = "cube"):
    """Morton keys of centroids quantised in the box ``[lo, hi]``.

    Each coordinate is mapped to ``t = (c - lo) / extent`` in [0, 1], quantised to
    ``b = bits / 3`` bits as ``min(floor(t · 2^b), 2^b - 1)`` (a centroid exactly on
    ``hi`` lands in the last cell) and the three ``b``-bit integers are interleaved,
    ``x`` the most significant bit of each triplet (module docstring).

    Args:
        centroids: Array3f[N], the primitives' centroids (AD arrays are detached).
        lo, hi: Array3f[1] (or [N]), the box to quantise in, normally
            :func:`point_bounds` of ``centroids``. Centroids outside it are clamped to
            the nearest cell; non-finite ones get cell 0.
        bits: 30 (10 bits per axis, UInt32 keys) or 60 (20 bits per axis, UInt64 keys).
        quantization: ``"cube"`` quantises every axis over the largest extent of the
            box, origin ``lo``, so cells are cubes (a flat scene keeps square cells and
            uses fewer of the grid's cells on its short axes); ``"axis"`` stretches the
            grid to the box's extent on each axis; ``"rank"`` quantises each axis by
            the centroid's rank along it (cell ``floor(r · 2^b / N)``, ``r`` the number
            of centroids strictly below on that axis, so equal coordinates share a
            cell): the cells adapt to where the primitives are, each slab of cells
            holding about the same number of centroids, which tells a tiny detailed
            object on a huge ground apart where no fixed grid can (``lo``, ``hi`` are
            not used; three sorts of N values, so it is the slowest).

    Returns:
        UInt32[N] keys below ``2^30`` for ``bits=30``; UInt64[N] keys below ``2^60``
        for ``bits=60``. An axis of zero extent contributes 0 bits (all centroids equal
        gives N zero keys); no key is ever derived from a NaN or a division by zero.

    Raises:
        ValueError: ``bits`` or ``quantization`` is not one of the values above.
    """
    if bits not in MORTON_BITS:
        raise ValueError(f"morton_codes: bits={bits!r}: expected 30 or 60")
    if quantization not in QUANTIZATIONS:
        raise ValueError(
            f"morton_codes: quantization={quantization!r}: expected one of {QUANTIZATIONS}"
        )
    ns = namespace_of(centroids)
    c, lo, hi = (plain(v, "Array3f") for v in (centroids, lo, hi))
    axis_bits = bits // 3
    cells = float(1 << axis_bits)

    if quantization == "rank":
        cell = [_rank_cells(ns, c[k], axis_bits) for k in range(3)]
    else:
        cell = _grid_cells(ns, c, lo, hi, axis_bits, quantization == "cube")

    # ---- Interleave: x y z x y z ... from the most significant bit ----
    Key = ns.UInt32 if bits == 30 else ns.UInt64
    x, y, z = (_spread_bits(Key(v), axis_bits) for v in cell)
    return (x << 2) | (y << 1) | z


def _grid_cells(ns, c, lo, hi, axis_bits: int, cube: bool) -> list:
    """The cells (UInt32 per axis) of centroids ``c`` in a grid of ``2^axis_bits`` cells
    per axis over the box ``[lo, hi]`` (a cube over its largest extent if ``cube``)."""
    cells = float(1 << axis_bits)

    # ---- Extent of the box, at half scale where hi - lo would overflow ----
    scale = dr.select(dr.all(dr.isfinite(hi - lo)), ns.Float(1.0), ns.Float(0.5))
    extent = dr.fma(scale, hi, -scale * lo)
    if cube:
        side = dr.max(extent)  # the largest of x, y, z
        extent = ns.Array3f(side, side, side)

    # ---- Quantise each axis: t in [0, 1] -> integer cell in [0, 2^b - 1] ----
    offset = dr.fma(scale, c, -scale * lo)
    cell = []
    for k in range(3):
        t = dr.select(extent[k] > 0, offset[k] / extent[k], 0.0)
        t = dr.select(t > 0, t, 0.0)  # negative and NaN -> 0
        cell.append(ns.UInt32(dr.minimum(t * cells, cells - 1.0)))
    return cell


def _rank_cells(ns, x, axis_bits: int):
    """UInt32 cell ``floor(r · 2^axis_bits / N)`` of each value of Float ``x`` (N of
    them), ``r`` its rank: how many values are strictly smaller (equal values share a
    rank, so the same coordinate always lands in the same cell). Non-finite values sort
    by their bits (they do not occur in a build: vertices are checked)."""
    n = dr.width(x)
    x = dr.select(x == 0, 0.0, x)  # -0 and +0: one coordinate
    key = dr.reinterpret_array(ns.UInt32, _ordered_bits(ns, x)) ^ 0x80000000  # unsigned order
    order = dr.argsort(key)
    sorted_key = dr.gather(ns.UInt32, key, order)
    i = dr.arange(ns.UInt32, n)
    head = (i == 0) | (sorted_key != dr.gather(ns.UInt32, sorted_key, dr.maximum(i, 1) - 1))
    run_start = dr.compress(head)  # slot of the first value of each run of equal values
    rank = dr.gather(ns.UInt32, run_start, dr.cumsum(ns.UInt32(head)) - 1)
    cell = ns.UInt32(ns.Float64(rank) * ((1 << axis_bits) / n))  # < 2^axis_bits, exact
    out = dr.empty(ns.UInt32, n)
    dr.scatter(out, cell, order)
    return out


def choose_key(prim_lo, prim_hi, lo, hi, quantization: str = "cube") -> tuple[int, str]:
    """The ``morton_bits="auto"`` policy: the key width and quantisation the scene
    needs.

    As :func:`choose_morton_bits` (30 bits unless 1% of the primitives are small
    against a 30-bit cell, then 60), and, when 1% of the primitives are small even
    against a 60-bit cell (cells 2^20 times smaller than the scene: a 1e-3 object with
    100k triangles on a ground 1e4 wide), ``"rank"`` quantisation with 60-bit keys:
    the object then gets the cells it needs wherever it is (what that gains, and why rank
    keys are not chosen otherwise: docs/decisions.md#rank-keys).

    Args:
        prim_lo, prim_hi: Array3f[N], each primitive's bounding box.
        lo, hi: Array3f[1], the box the keys are quantised in (the centroid bounds).
        quantization: the quantisation asked for, kept unless rank is needed.

    Returns:
        ``(bits, quantization)``: 30 or 60, and ``quantization`` or ``"rank"`` (one
        host read of two counts).
    """
    prim_lo, prim_hi, lo, hi = (plain(v, "Array3f") for v in (prim_lo, prim_hi, lo, hi))
    n = dr.width(prim_lo)
    if n == 0:
        raise ValueError("choose_key: no primitives; pass at least one box")
    # Half scale on both sides keeps hi - lo finite near the float range's ends.
    cell = dr.max(dr.fma(0.5, hi, -0.5 * lo)) * (2.0 / 1024.0)  # a 30-bit cell
    size = dr.max(dr.fma(0.5, prim_hi, -0.5 * prim_lo)) * 2.0  # per primitive
    small_30 = dr.count(size < cell * _SMALL_PRIM_CELL_FRACTION)
    small_60 = dr.count(size < cell * (_SMALL_PRIM_CELL_FRACTION / 1024.0))
    dr.eval(small_30, small_60)
    if small_60[0] >= _SMALL_PRIM_SHARE * n:
        return 60, "rank"
    return (60 if small_30[0] >= _SMALL_PRIM_SHARE * n else 30), quantization


def choose_morton_bits(prim_lo, prim_hi, lo, hi) -> int:
    """The ``morton_bits="auto"`` policy: 60 when 30-bit keys cannot tell the scene's
    primitives apart, else 30.

    With 10 bits per axis the box ``[lo, hi]`` is cut into cubes of side
    ``cell = max extent / 1024`` (the ``"cube"`` quantisation). A surface tessellated
    into primitives of size ``s`` puts about ``(cell / s)^2`` of them into one cell,
    all with the same key; the emission can then only split them by index, so their
    leaves overlap. A primitive counts as *small* when its largest extent is below
    ``cell / 4`` (about 16 or more per cell on a surface: four leaves' worth at the
    default ``leaf_size = 4``), and 60-bit keys (cells 1024 times finer) are chosen
    when at least 1% of the primitives are small. A share, not the median or the mean:
    a small detailed object on a huge, finely tessellated ground holds few of the
    primitives but all of the collisions, and the median and mean extent are those of
    the ground (measured in docs/decisions.md#key-width; ``tests/kernels/test_morton.py``
    checks such scenes). Thin slivers fanning around one point (a UV sphere's poles) collide
    without being small; a criterion on extents cannot see them. All centroids equal
    (zero extent) gives 30: finer cells would not separate them either.

    Args:
        prim_lo, prim_hi: Array3f[N], each primitive's bounding box.
        lo, hi: Array3f[1], the box the keys are quantised in (the centroid bounds).

    Returns:
        30 or 60 (a Python int; one value is read back to the host).
    """
    return choose_key(prim_lo, prim_hi, lo, hi)[0]


def _spread_bits(v, axis_bits: int):
    """``v``'s low ``axis_bits`` bits moved to every third position: bit ``i`` to bit
    ``3i``, the bits between cleared.

    The moves are done in ``log2(axis_bits)`` steps from the largest shift down: bit
    ``i`` moves by ``2·i = sum over k of b_k(i)·2^(k+1)`` (``b_k`` its binary digits),
    so step ``k`` shifts a copy of every bit left by ``2^(k+1)`` and a mask keeps, of
    the two copies, the one where that bit must be after this step. The masks are
    computed here from that rule rather than written as magic constants.

    Args:
        v: UInt32 (``axis_bits <= 10``) or UInt64 (``axis_bits <= 21``), values below
            ``2^axis_bits``.
    """
    for k in reversed(range(max(axis_bits - 1, 1).bit_length())):
        mask = 0
        for i in range(axis_bits):
            moved = sum(((i >> j) & 1) << (j + 1) for j in range(k, 8))
            mask |= 1 << (i + moved)
        v = (v | (v << (1 << (k + 1)))) & mask
    return v
