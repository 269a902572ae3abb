"""Ray traversal of the BVH: closest hit and any hit.

Each ray runs one symbolic ``dr.while_loop`` with a per-lane short stack (registers
over local memory, see below). Every iteration advances every lane by one step: a lane at an
internal node tests both children's boxes, a lane inside a leaf tests one triangle.
The two tests sit in symbolic ifs, so a packet whose lanes are all at nodes (or all
in leaves) skips the other test. Unlike Aila & Laine's *while-while* loops (descend
until every lane of the packet reaches a leaf, then intersect), no lane waits for the
rest of its packet to finish a phase; measured here 1.1-1.4x faster on a 1M-triangle
grid and 2x on Cornell box. The loop and its ifs are symbolic whatever Dr.Jit's
``JitFlag.SymbolicLoops`` and ``SymbolicConditionals`` say: an integrator running
its own loops evaluated still gets one traversal kernel per query (an evaluated
traversal launched kernels on every step: minutes for a thousand rays).

- **Ordered visit**: both children's boxes are tested together; the nearer child is
  visited first, the farther one is pushed with its entry distance, and a popped node
  whose entry distance lies beyond the closest hit so far is skipped. Any hit, which
  any occluder ends, visits the left child first instead: its record is the next one
  (see the layout below), and that measured 1.07-1.12x faster on incoherent shadow-like
  rays of a 1M-triangle grid and 1.04-1.07x on ``hlbvh_path`` renders.
- **Conservative slab test** (Ize, "Robust BVH ray traversal", JCGT 2013): the exit
  distance of a box is scaled by ``1 + 2·gamma(3)`` so rounding never culls a box the
  ray touches; so is the closest hit so far when a box's entry distance is compared
  with it (a triangle lying on a box face at exactly ``maxt`` is still found).
  Reciprocal directions come from directions clamped away from zero (``|d| >=
  FLT_MIN``, sign kept), so no ``0 · inf = NaN`` reaches the min/max.
- **Watertight ray/triangle test** (Woop, Benthin & Wald, JCGT 2013): vertices are
  translated to the ray origin, permuted so the ray's dominant axis is z and sheared so
  the ray becomes the z axis. Every vertex is transformed the same way whichever
  triangle it belongs to, and the 2D edge functions U, V, W of a shared edge are exact
  negatives of each other, so no ray slips between two triangles that share an edge or
  a vertex. A hit is accepted with barycentrics ``U/det, V/det, W/det`` down to
  ``-BARYCENTRIC_MARGIN`` (2**-20): this also closes the one-ulp cracks where two
  separately modelled meshes meet (the walls of Cornell box), as Embree does, and makes
  the paper's double-precision recomputation of an edge function that rounds to zero
  unnecessary (zero is inside either way). Triangles whose edge functions overflow or
  underflow float32 (coordinates beyond ~1e19 or below ~1e-19 relative to the ray
  origin) or whose determinant rounds to zero are recomputed in double precision, so
  scenes at 1e+30 and 1e-30 scale trace correctly.

A hit is reported at the smallest ``t`` with ``0 < t <= maxt``. Rays with a NaN or
infinite component, a zero direction, ``maxt <= 0`` or ``maxt`` NaN are clean misses.

Packed records (built once per BVH and cached on it, see :func:`packed_records`): the
arrays of ``hlbvh.kernels.bvh`` are repacked into one Float array of 16-float records
(64 bytes, one cache line), so that each step is one packet gather, whatever the lane
is doing. An internal node has one record; a leaf has none of its own, only its
triangles' records, one per triangle:

========================  ===============================================================
internal node, ``0..5``   its left child's box: lo x, y, z, hi x, y, z
``6..11``                 its right child's box
``12, 13``                left and right child's references (the bits of a UInt32);
                          14, 15 zero padding
triangle, ``0..8``        p0, p1, p2 (in the face's order)
``9``                     the input face index (the bits of a UInt32)
``10``                    1 for a zero-area triangle (never hit), else 0; 11..15 zero
========================  ===============================================================

The records are laid out depth first (pre-order, left child first): a node's record,
then its left subtree's records, then its right subtree's, a leaf's triangles in slot
order where the leaf stands. A ray that descends often steps to the next record, which
the cache (or its adjacent-line prefetch) already holds: measured 1.11-1.18x faster on
a 1M-triangle grid than nodes in index order followed by all triangles (no change on
Cornell box, which fits in L1), and packing is no slower. The order comes from the
tree's ``levels`` (one pass up for subtree sizes, one down for positions); a hand-made
tree whose ``levels`` do not describe it exactly (checked: every internal node and
leaf triangle got a record of its own and no record is empty) is packed in index order
instead: node ``i`` at record ``i``, the triangle in slot ``s`` at ``N + s``. Storing
the face index in the triangle's record also spares a gather after the loop.

A *reference* names a node: an internal node by its record (bit 31 clear); a leaf by
``LEAF_BIT | first_record << 4 | (count - 1)`` so a leaf needs no record of its own (this
bounds leaves to 16 triangles and the records to 2**27, about 2**26 triangles). The
cache is keyed by the Dr.Jit variable indices of the BVH's arrays, so a refit (which
assigns new box and vertex arrays) repacks on the next trace; code that modifies those
arrays in place must call :func:`forget_records`.

Short stack: the top ``STACK_REGISTERS`` (4) entries of each lane's stack live in
loop registers, the rest in local memory (``dr.alloc_local``), which is only touched,
in a symbolic if, by a packet in which some lane pushes onto four held entries or pops
with none held. Rays rarely hold more than a few entries (on a 1M-triangle grid 1-2 on
average, under 4 on 75-90% of pushes), while every local-memory access costs a packet a
scatter or gather plus Dr.Jit's test for a uniform index: measured 1.08-1.2x faster
than a stack wholly in local memory accessed on every step (2, 3 or 6 registers: no
better). The spill's if returns the new stack pointer: Dr.Jit drops a ``dr.if_stmt``
without outputs and runs its local-memory write masked on every step. An entry holds
the node's reference and entry distance (any hit: the reference only).

Tried and not kept (process CPU time, one thread, against this code): sorting the rays
of a query by origin cell, direction octant or cell before tracing and scattering the
results back (``block_mkperm`` over 12-bit keys) gained at most 1.08-1.11x on
incoherent rays of a 1M-triangle grid and lost 1.04-1.25x elsewhere, coherent rays
included: rays generated per pixel already come ordered by origin, and inside an
integrator's symbolic loop nothing can be sorted anyway. Two triangles per leaf step:
0.8-0.88x. Box slabs as ``fma(x, 1/d, -o/d)``: not conservative for origins far from
the box (the rounding of ``o/d`` is not bounded by the slab distance). Testing for
possible hits before the triangle test's two divisions, and the shear from the
reciprocal direction: 0.93-1.03x. Leaf sizes 2 or 8 instead of the builder's 4: no
better. In ``hlbvh_path`` a packet steps while any of its lanes still traverses: on a
200k-triangle cloth frame a third of the lane-steps paid for are active ones (a fifth
for shadow rays through the cloth), which only fewer steps per ray or compacted rays
would change.

Stack guard: the stack holds ``STACK_SIZE`` (64) entries; ordered traversal pushes at
most one entry per level, so a tree of depth <= 64 never overflows, and deeper trees
are refused with a ValueError before tracing. A corrupt tree that still overflows the
stack, or that makes a ray take more steps than the tree has nodes and triangles (a
cycle), ends that ray deterministically as a miss (any hit: not occluded). Child
references and leaf ranges are checked when the records are packed, so no gather
leaves its array.

Call :func:`packed_records` once outside any symbolic loop (when the BVH is built or
refit) if the traversal is then traced inside one: packing evaluates arrays.
"""

from __future__ import annotations

import drjit as dr

from .arrays import namespace_of, plain

#: Entries of the per-lane traversal stack.
STACK_SIZE = 64
#: Of these, the top entries held in loop registers (the rest in local memory).
STACK_REGISTERS = 4
#: Bit 31 of a reference marks a leaf.
LEAF_BIT = 0x80000000
#: Most triangles a leaf may hold (its count - 1 lives in the reference's low 4 bits).
MAX_LEAF_SIZE = 16
#: Most records (internal nodes plus triangles) a BVH may pack into (the first record
#: of a leaf lives in bits 4..30 of its reference).
MAX_RECORDS = 1 << 27

_RECORD = 16  # floats per packed node or triangle record
_TRIANGLE_TAG = 0x80000000  # a record holding a triangle, the slot in the low bits
_NOTHING = 0xFFFFFFFF  # a record holding nothing (index-order layout only)
_TRIANGLE_TAG = 0x80000000  # a record holding a triangle (the slot in the low bits)
_NOTHING = 0xFFFFFFFF  # a record holding nothing
_FLT_MIN = 2.0**-126  # smallest normal float: 1 / _FLT_MIN is finite
_EPS = 2.0**-24  # unit roundoff of float32
_GAMMA3 = 3 * _EPS / (1 - 3 * _EPS)  # gamma(3) of Pharr et al., as in Ize 2013
_TFAR_SCALE = 1 + 2 * _GAMMA3
#: A hit is accepted with barycentrics down to ``-BARYCENTRIC_MARGIN``: this closes
#: cracks of up to ~1e-6 of a triangle's size between separately modelled meshes that
#: meet at a seam (the walls of Mitsuba's Cornell box do), where Embree reports a hit.
BARYCENTRIC_MARGIN = 2.0**-20


# ---------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------


def closest_hit(bvh, o, d, maxt, active=True):
    """Nearest intersection of each ray with the BVH's triangles.

    Args:
        bvh: an ``hlbvh.BVH``.
        o: Array3f (or ``mi.Point3f``) ray origins, width R (or 1).
        d: Array3f (or ``mi.Vector3f``) ray directions, width R (or 1); need not be
            normalised (``t`` is in units of ``d``).
        maxt: Float (or Python float) largest accepted ``t``, width R or 1.
        active: Bool (or Python bool) mask; inactive rays miss.
    Returns:
        ``(t, u, v, prim, valid)``: Float ``t`` (``inf`` on a miss), Float ``u``, ``v``
        with ``p = (1-u-v)·p0 + u·p1 + v·p2`` of the face's vertices, UInt32 ``prim``
        the input face index (0 on a miss), Bool ``valid``; all of width R, plain
        (non-AD) arrays of the input's backend.
    """
    return _trace(bvh, o, d, maxt, active, any_hit=False)


def any_hit(bvh, o, d, maxt, active=True):
    """Whether each ray hits any triangle at ``0 < t <= maxt`` (stops at the first hit).

    Arguments as in :func:`closest_hit`. Returns a Bool of width R.
    """
    return _trace(bvh, o, d, maxt, active, any_hit=True)


def intersect(bvh, ray, active=True):
    """Closest hit of ``ray`` (anything with ``o``, ``d``, ``maxt``) as a
    ``mi.PreliminaryIntersection3f``: ``valid``, ``t`` (``inf`` on a miss),
    ``prim_uv``, ``prim_index`` (the input face index); ``shape``, ``shape_index`` and
    ``instance`` are left null/zero for the caller to fill."""
    import mitsuba as mi

    t, u, v, prim, valid = closest_hit(bvh, ray.o, ray.d, ray.maxt, active)
    pi = dr.zeros(mi.PreliminaryIntersection3f, dr.width(t))
    pi.valid = mi.Bool(valid)
    pi.t = mi.Float(t)
    pi.prim_uv = mi.Point2f(u, v)
    pi.prim_index = mi.UInt32(prim)
    return pi


def occluded(bvh, ray, active=True):
    """Whether anything lies on ``ray`` at ``0 < t <= ray.maxt``: a ``mi.Bool``."""
    import mitsuba as mi

    return mi.Bool(any_hit(bvh, ray.o, ray.d, ray.maxt, active))


# ---------------------------------------------------------------------------------------
# Packed records
# ---------------------------------------------------------------------------------------


def packed_records(bvh):
    """The packed node and triangle records of ``bvh`` (layout in the module docstring),
    built on first use and cached on the BVH object.

    Returns:
        ``(records, root)``: Float (16 per record) and the Python int reference of the
        root.
    Raises:
        ValueError: the tree is deeper than ``STACK_SIZE``, has a leaf of more than 16
            triangles, more than ``MAX_RECORDS`` records, or a child/leaf range outside
            its arrays.
    """
    arrays = (bvh.node_min, bvh.node_max, bvh.node_first, bvh.node_count, bvh.prim_ids,
              bvh.tri_p0, bvh.tri_p1, bvh.tri_p2)
    key = tuple(c.index for a in arrays for c in (a if dr.depth_v(a) > 1 else (a,)))
    key += tuple(level.index for level in bvh.levels)
    cache = getattr(bvh, "_traversal_records", None)
    if cache is not None and cache[0] == key:
        return cache[1]
    records = _pack(bvh)
    bvh._traversal_records = (key, records)
    return records


def forget_records(bvh):
    """Drop the cached packed records of ``bvh`` (after changing its arrays in place)."""
    bvh._traversal_records = None


def _pack(bvh):
    ns = namespace_of(bvh.node_count)
    UInt32, Float, ArrayXf = ns.UInt32, ns.Float, ns.ArrayXf
    n_nodes, n_prims = bvh.size, bvh.prim_count

    # ---- Validate: depth, leaf sizes, child and slot ranges ----
    depth = max(bvh.stats.depth, len(bvh.levels))
    if depth > STACK_SIZE:
        raise ValueError(
            f"BVH depth {depth} exceeds the traversal stack ({STACK_SIZE} entries): "
            "rebuild with a builder that bounds the depth"
        )
    if n_nodes + n_prims > MAX_RECORDS:
        raise ValueError(
            f"BVH has {n_prims} triangles in {n_nodes} nodes; traversal supports at most "
            f"{MAX_RECORDS} nodes plus triangles (about {MAX_RECORDS // 2} triangles)"
        )
    if n_nodes == 0 or n_prims == 0:
        raise ValueError("BVH is empty: build it from at least one triangle")
    first, count = UInt32(bvh.node_first), UInt32(bvh.node_count)
    internal = count == 0
    # Sizes enter kernels as opaque values: a literal would compile new kernels for
    # every tree of a new size, i.e. every frame of an animation (pitfall 6).
    nodes_o, prims_o = dr.opaque(UInt32, n_nodes), dr.opaque(UInt32, n_prims)
    bad = dr.select(
        internal,
        first + 1 >= nodes_o,
        (count > MAX_LEAF_SIZE) | (first + count > prims_o) | (first + count < first),
    )
    if dr.any(bad, axis=None):
        raise ValueError(
            "corrupt BVH: a child index or leaf range lies outside the node/slot "
            f"arrays, or a leaf holds more than {MAX_LEAF_SIZE} triangles"
        )
    widest = int(dr.max(count, axis=None)[0])

    # ---- Layout: what each record holds ----
    position, total = _depth_first(bvh.levels, first, count, internal, n_prims)
    holds = None
    if position is not None:
        holds = _holdings(position, total, first, count, internal, widest)
        if not _exact(holds, position, total, first, count, internal, widest):
            holds = None
    if holds is None:  # index order: node i at record i, slot s at record N + s
        position = dr.select(internal, dr.arange(UInt32, n_nodes), nodes_o + first)
        total = n_nodes + n_prims
        holds = _holdings(position, total, first, count, internal, widest)
    is_node = (holds & _TRIANGLE_TAG) == 0
    is_triangle = ~is_node & (holds != _NOTHING)
    item = holds & ~UInt32(_TRIANGLE_TAG)

    # ---- Node rows: both children's boxes and references ----
    # Each node's box and reference as an 8-float row in index order, read twice (the
    # children of a node are adjacent) by packet gathers.
    ref = dr.select(internal, position, LEAF_BIT | (position << 4) | (count - 1))
    lo, hi = bvh.node_min, bvh.node_max
    half = dr.ravel(ArrayXf([lo.x, lo.y, lo.z, hi.x, hi.y, hi.z,
                             dr.reinterpret_array(Float, ref), dr.zeros(Float, n_nodes)]))
    left = dr.gather(UInt32, first, item, is_node)
    one = dr.gather(ArrayXf, half, left, is_node, shape=(8, total))
    other = dr.gather(ArrayXf, half, left + 1, is_node, shape=(8, total))
    zero = dr.zeros(Float, total)
    rows = [one[i] for i in range(6)] + [other[i] for i in range(6)] + [one[6], other[6]]
    rows += [zero] * (_RECORD - len(rows))

    # ---- Triangle rows: the three vertices and the face index ----
    tri_rows = [c for p in (bvh.tri_p0, bvh.tri_p1, bvh.tri_p2)
                for c in dr.gather(ns.Array3f, p, item, is_triangle)]
    face = dr.gather(UInt32, UInt32(bvh.prim_ids), item, is_triangle)
    tri_rows.append(dr.reinterpret_array(Float, face))
    # A zero-area triangle (collinear vertices) is never hit, as in Embree: its normal
    # would be NaN. After the shear its determinant may round away from zero, so the
    # flag is taken here, from the unsheared edges.
    # In double precision: float32 products underflow at 1e-30 and overflow at 1e20.
    p0, p1, p2 = (ns.Array3f64(dr.gather(ns.Array3f, p, item, is_triangle))
                  for p in (bvh.tri_p0, bvh.tri_p1, bvh.tri_p2))
    normal = dr.cross(p1 - p0, p2 - p0)
    flat = (normal.x == 0) & (normal.y == 0) & (normal.z == 0)
    tri_rows.append(dr.select(flat, Float(1), Float(0)))
    tri_rows += [zero] * (_RECORD - len(tri_rows))

    records = dr.ravel(ArrayXf([dr.select(is_node, a, b) for a, b in zip(rows, tri_rows)]))
    dr.eval(records)
    return records, int(ref[0])


def _depth_first(levels, first, count, internal, n_prims):
    """Depth-first record positions from the tree's ``levels`` (internal nodes per
    depth, root first): one pass up for each subtree's number of records, one pass down
    for the positions.

    Returns:
        ``(position, total)``: UInt32[N] the record of each internal node and the first
        record of each leaf, and the number of records; ``(None, 0)`` when ``levels``
        cannot describe the tree (no levels, or a record count out of range).
    """
    UInt32 = type(first)
    n_nodes = dr.width(first)
    if not levels:
        return None, 0
    # ---- Up: records in each subtree (a leaf: its triangles) ----
    size = dr.select(internal, 0, count)
    for nodes in reversed(levels):
        left = dr.gather(UInt32, first, nodes)
        grown = 1 + dr.gather(UInt32, size, left) + dr.gather(UInt32, size, left + 1)
        dr.eval(grown)  # read before writing into the same array (pitfall 5)
        dr.scatter(size, grown, nodes)
    total = int(size[0])
    if not 0 < total <= n_nodes + n_prims:
        return None, 0
    # ---- Down: a node at p, its left child at p + 1, its right after the left subtree ----
    position = dr.zeros(UInt32, n_nodes)
    for nodes in levels:
        left = dr.gather(UInt32, first, nodes)
        after = dr.gather(UInt32, position, nodes) + 1
        right = after + dr.gather(UInt32, size, left)
        dr.eval(after, right)
        dr.scatter(position, after, left)
        dr.scatter(position, right, left + 1)
    return position, total


def _holdings(position, total, first, count, internal, widest):
    """UInt32[total]: what each record holds: an internal node's index, or
    ``_TRIANGLE_TAG | slot``, or ``_NOTHING``. Positions beyond ``total`` are dropped."""
    UInt32 = type(first)
    holds = dr.full(UInt32, _NOTHING, total)
    total_o = dr.opaque(UInt32, total)
    dr.scatter(holds, dr.arange(UInt32, dr.width(first)), position,
               internal & (position < total_o))
    for k in range(widest):
        dr.scatter(holds, _TRIANGLE_TAG | (first + k), position + k,
                   ~internal & (count > k) & (position + k < total_o))
    return holds


def _exact(holds, position, total, first, count, internal, widest):
    """Whether the layout ``position`` gives every internal node and every triangle of
    every leaf a record of its own and leaves no record empty (no two of them wrote
    the same record, none fell outside, and as many were written as there are)."""
    UInt32 = type(first)
    ok = dr.full(type(internal), True, dr.width(first))
    for k in range(max(widest, 1)):
        owner = ~internal & (count > k)
        expected = _TRIANGLE_TAG | (first + k)
        if k == 0:
            owner |= internal
            expected = dr.select(internal, dr.arange(UInt32, dr.width(first)), expected)
        fits = position + k < dr.opaque(UInt32, total)
        held_here = dr.gather(UInt32, holds, position + k, owner & fits)
        ok &= ~owner | (fits & (held_here == expected))
    return bool(dr.all(ok, axis=None)[0]) and not dr.any(holds == _NOTHING, axis=None)[0]


# ---------------------------------------------------------------------------------------
# Traversal
# ---------------------------------------------------------------------------------------


def _broadcast(x, kind, ns, n):
    """``x`` as a plain ``kind`` array of width exactly ``n`` (an evaluated variable, so
    no literal of width 1 can enter the loop state; see DRJIT_NOTES pitfall 1)."""
    x = plain(x, kind) if dr.is_array_v(x) else getattr(ns, kind)(x)
    if dr.width(x) == n:
        return x
    return dr.gather(getattr(ns, kind), x, dr.opaque(ns.UInt32, 0, n))


def _min(a, b):
    """Minimum of two NaN-free arrays (one compare and blend; ``dr.minimum`` also
    handles NaN and signed zeros at a few times the cost)."""
    return dr.select(a < b, a, b)


def _max(a, b):
    """Maximum of two NaN-free arrays (see :func:`_min`)."""
    return dr.select(a > b, a, b)


def _pick(v, k0, k1):
    """Per-lane component ``k`` of Array3f ``v``, with masks ``k0 = (k == 0)`` and
    ``k1 = (k == 1)``."""
    return dr.select(k0, v.x, dr.select(k1, v.y, v.z))


def _ratios(ax, ay, az, bx, by, bz, cx, cy, cz, edges, det, t_scaled):
    """Barycentrics (w, u, v) and distance t from float32 edge functions (Woop et al.:
    ``b_i = edge_i / det``, ``t = T / det``); ``det != 0`` here."""
    inv_det = dr.rcp(det)
    return edges[0] * inv_det, edges[1] * inv_det, edges[2] * inv_det, t_scaled / det


def _ratios_in_double(ax, ay, az, bx, by, bz, cx, cy, cz, edges, det, t_scaled):
    """:func:`_ratios` with the edge functions and T recomputed in double precision
    from the float32 sheared vertices (products of two floats are exact in double, so
    the signs are exact too). A zero determinant (a triangle seen edge-on, or
    degenerate) gives NaN: no hit."""
    Float, F64 = type(ax), dr.float64_array_t(type(ax))
    ax, ay, az, bx, by, bz, cx, cy, cz = (F64(x) for x in (ax, ay, az, bx, by, bz, cx, cy, cz))
    e0, e1, e2 = cx * by - cy * bx, ax * cy - ay * cx, bx * ay - by * ax
    det64 = e0 + e1 + e2
    inv_det = dr.select(det64 != 0, 1.0 / det64, dr.nan)
    t64 = (e0 * az + e1 * bz + e2 * cz) * inv_det
    return Float(e0 * inv_det), Float(e1 * inv_det), Float(e2 * inv_det), Float(t64)


def _trace(bvh, o, d, maxt, active, any_hit):
    if not dr.is_array_v(o) or not dr.is_array_v(d):
        raise TypeError("ray origin and direction must be Dr.Jit Array3f/Point3f/Vector3f")
    ns = namespace_of(o)
    Float, UInt32, Bool, Array3f = ns.Float, ns.UInt32, ns.Bool, ns.Array3f
    widths = {dr.width(x) for x in (o, d, maxt, active) if dr.is_array_v(x)} - {1}
    if len(widths) > 1:
        raise ValueError(f"ray arrays of different widths {sorted(widths)}: expected one")
    n = widths.pop() if widths else 1
    if n == 0:
        return Bool() if any_hit else (Float(), Float(), Float(), UInt32(), Bool())
    records, root = packed_records(bvh)

    o = _broadcast(o, "Array3f", ns, n)
    d = _broadcast(d, "Array3f", ns, n)
    maxt = _broadcast(maxt, "Float", ns, n)
    active = _broadcast(active, "Bool", ns, n)

    # ---- Per-ray set-up ----
    finite = dr.all(dr.isfinite(o)) & dr.all(dr.isfinite(d))
    alive = active & finite & dr.any(d != 0) & (maxt > 0)
    # Slab test: reciprocal of the direction clamped away from zero (sign kept).
    d_safe = dr.select(dr.abs(d) < _FLT_MIN, dr.copysign(Array3f(_FLT_MIN), d), d)
    inv_d = dr.rcp(d_safe)
    # Watertight test: kz = dominant axis, (kx, ky) the others, swapped when d[kz] < 0
    # to keep the winding (Woop et al. 2013, Fig. 1).
    ad = dr.abs(d)
    kz = dr.select((ad.x >= ad.y) & (ad.x >= ad.z), UInt32(0),
                   dr.select(ad.y >= ad.z, UInt32(1), UInt32(2)))
    kx = dr.select(kz == 2, 0, kz + 1)
    ky = dr.select(kx == 2, 0, kx + 1)
    dz = _pick(d, kz == 0, kz == 1)
    kx, ky = dr.select(dz < 0, ky, kx), dr.select(dz < 0, kx, ky)
    perm = ((kx == 0, kx == 1), (ky == 0, ky == 1), (kz == 0, kz == 1))
    o_p = [_pick(o, *m) for m in perm]
    shear_x = _pick(d, *perm[0]) / dz
    shear_y = _pick(d, *perm[1]) / dz
    shear_z = dr.rcp(dz)

    def slab(rec, base, t_max):
        """Entry distance and hit mask of the box in ``rec[base : base+6]``."""
        t0 = [(rec[base + i] - o[i]) * inv_d[i] for i in range(3)]
        t1 = [(rec[base + 3 + i] - o[i]) * inv_d[i] for i in range(3)]
        lo = [_min(a, b) for a, b in zip(t0, t1)]
        hi = [_max(a, b) for a, b in zip(t0, t1)]
        t_near = _max(_max(lo[0], lo[1]), _max(lo[2], 0.0))
        t_far = _min(_min(hi[0], hi[1]), hi[2])
        return t_near, t_near <= _min(t_far, t_max) * _TFAR_SCALE

    def vertex(rec, base):
        """A triangle vertex translated, permuted and sheared into ray space."""
        p = [rec[base + i] for i in range(3)]
        a = [dr.select(m0, p[0], dr.select(m1, p[1], p[2])) - oc
             for (m0, m1), oc in zip(perm, o_p)]
        return a[0] - shear_x * a[2], a[1] - shear_y * a[2], shear_z * a[2]

    def woop(rec, t_max):
        """Watertight intersection with the triangle in ``rec``: (hit, t, u, v)."""
        ax, ay, az = vertex(rec, 0)
        bx, by, bz = vertex(rec, 3)
        cx, cy, cz = vertex(rec, 6)
        edges = (cx * by - cy * bx, ax * cy - ay * cx, bx * ay - by * ax)
        det = edges[0] + edges[1] + edges[2]
        t_scaled = dr.fma(edges[0], az, dr.fma(edges[1], bz, edges[2] * cz))
        # Products of coordinates beyond ~1e19 overflow and below ~1e-19 underflow in
        # float32: redo those triangles (and zero determinants) in double precision.
        in_range = dr.isfinite(t_scaled) & dr.isfinite(det) & (det != 0)
        b0, b1, b2, t = dr.if_stmt(
            args=(ax, ay, az, bx, by, bz, cx, cy, cz, edges, det, t_scaled),
            cond=in_range,
            true_fn=_ratios,
            false_fn=_ratios_in_double,
            arg_labels=("ax", "ay", "az", "bx", "by", "bz", "cx", "cy", "cz", "edges",
                        "det", "t_scaled"),
            rv_labels=("b0", "b1", "b2", "t"),
            label="hlbvh_woop_range", mode="symbolic",
        )
        inside = (b0 >= -BARYCENTRIC_MARGIN) & (b1 >= -BARYCENTRIC_MARGIN) \
            & (b2 >= -BARYCENTRIC_MARGIN)
        hit = inside & (t > 0) & (t <= t_max) & (rec[10] == 0)  # rec[10]: zero area
        return hit, t, b1, b2

    def box_pair(rec, t_best):
        """Entry distances and hit masks of an internal node's two children."""
        return slab(rec, 0, t_best) + slab(rec, 6, t_best)

    def no_box(rec, t_best):
        return dr.zeros(Float, n), dr.zeros(Bool, n), dr.zeros(Float, n), dr.zeros(Bool, n)

    def no_triangle(rec, t_best):
        return dr.zeros(Bool, n), dr.zeros(Float, n), dr.zeros(Float, n), dr.zeros(Float, n)

    def enter(ref):
        """Record range of the node ``ref`` names: ``(cur, end)``, a leaf's triangles
        at ``cur .. end-1``; ``end = 0`` for an internal node (so ``cur < end`` says
        whether a lane is in a leaf)."""
        leaf = (ref & LEAF_BIT) != 0
        first = (ref & ~UInt32(LEAF_BIT)) >> 4
        return dr.select(leaf, first, ref), dr.select(leaf, first + (ref & 15) + 1, 0)

    # ---- Short stack: STACK_REGISTERS entries in registers, the rest in local memory ----
    # Any hit: the closest hit stays maxt, which every pushed entry already passed, so
    # entries are bare references (no entry distance, no staleness).
    Entry = UInt32 if any_hit else ns.UInt64
    memory = dr.alloc_local(Entry, STACK_SIZE - STACK_REGISTERS)

    def spill(entry, sp, mask):
        memory.write(entry, sp, active=mask)
        return dr.select(mask, sp + 1, sp)

    def no_spill(entry, sp, mask):
        return sp

    def fill(sp, mask):
        return memory.read(sp, active=mask)

    def no_fill(sp, mask):
        return dr.zeros(Entry, n)

    def push(held, depth, sp, entry, mask):
        """Push ``entry`` on the lanes of ``mask``; the bottom register spills to local
        memory when all are in use. Returns ``(held, depth, sp, overflow)``."""
        spilling = mask & (depth == STACK_REGISTERS)
        overflow = spilling & (sp >= STACK_SIZE - STACK_REGISTERS)
        spilling &= ~overflow
        mask &= ~overflow
        sp = dr.if_stmt(args=(held[-1], sp, spilling), cond=spilling, true_fn=spill,
                        false_fn=no_spill, label="hlbvh_spill", mode="symbolic")
        held = [dr.select(mask, above, below)
                for above, below in zip([entry] + held[:-1], held)]
        depth = dr.select(mask & (depth < STACK_REGISTERS), depth + 1, depth)
        return held, depth, sp, overflow

    def pop(held, depth, sp, mask):
        """Pop an entry on the lanes of ``mask`` (each holding one, in registers or in
        local memory). Returns ``(entry, held, depth, sp)``."""
        from_register = mask & (depth > 0)
        filling = mask & (depth == 0)
        sp = dr.select(filling, sp - 1, sp)
        filled = dr.if_stmt(args=(sp, filling), cond=filling, true_fn=fill,
                            false_fn=no_fill, label="hlbvh_fill", mode="symbolic")
        entry = dr.select(from_register, held[0], filled)
        held = [dr.select(from_register, below, above)
                for above, below in zip(held, held[1:] + held[-1:])]
        depth = dr.select(from_register, depth - 1, depth)
        return entry, held, depth, sp

    # ---- Loop state (every variable at full width, pitfall 1) ----
    cur, end = enter(dr.full(UInt32, root, n))  # record to process; end of its leaf
    node_t = dr.zeros(Float, n)  # entry distance of the current node's box
    entering = dr.full(Bool, True, n)  # first step at this node (or leaf)
    # stack entries, top first: t_near bits << 32 | reference (any hit: the reference)
    held = [dr.zeros(Entry, n) for _ in range(STACK_REGISTERS)]
    depth = dr.zeros(UInt32, n)  # entries held in registers
    sp = dr.zeros(UInt32, n)  # entries in local memory
    t_best = dr.select(alive, maxt, dr.inf)  # closest hit so far (or maxt)
    u_best = dr.zeros(Float, n)
    v_best = dr.zeros(Float, n)
    prim_best = dr.zeros(UInt32, n)  # input face index of the closest hit
    found = dr.zeros(Bool, n)
    steps = dr.zeros(UInt32, n)  # loop iterations (cycle guard)
    corrupt = dr.zeros(Bool, n)  # the ray hit a stack overflow or a cycle
    max_steps = dr.opaque(UInt32, bvh.size + bvh.prim_count)
    state = (cur, end, node_t, entering, held, depth, sp, alive, steps, corrupt, t_best,
             u_best, v_best, prim_best, found)
    labels = ("cur", "end", "node_t", "entering", "held", "depth", "sp", "alive", "steps",
              "corrupt", "t_best", "u_best", "v_best", "prim_best", "found")

    def trace_cond(cur, end, node_t, entering, held, depth, sp, alive, *rest):
        return alive

    def trace_body(cur, end, node_t, entering, held, depth, sp, alive, steps, corrupt,
                   t_best, u_best, v_best, prim_best, found):
        rec = dr.gather(ns.ArrayXf, records, cur, shape=(_RECORD, n))
        in_leaf = cur < end
        # A node (or leaf) entered beyond the closest hit so far is skipped.
        stale = dr.zeros(Bool, n) if any_hit else entering & (node_t > t_best * _TFAR_SCALE)

        # ---- A lane in a leaf: test one triangle ----
        at_triangle = in_leaf & ~stale
        hit, t, u, v = dr.if_stmt(
            args=(rec, t_best), cond=at_triangle, true_fn=woop, false_fn=no_triangle,
            arg_labels=("rec", "t_best"), rv_labels=("hit", "t", "u", "v"),
            label="hlbvh_triangle", mode="symbolic",
        )
        hit &= at_triangle
        t_best = dr.select(hit, t, t_best)
        u_best = dr.select(hit, u, u_best)
        v_best = dr.select(hit, v, v_best)
        prim_best = dr.select(hit, dr.reinterpret_array(UInt32, rec[9]), prim_best)
        found |= hit

        # ---- A lane at an internal node: test both children's boxes ----
        at_node = ~in_leaf & ~stale
        t_l, hit_l, t_r, hit_r = dr.if_stmt(
            args=(rec, t_best), cond=at_node, true_fn=box_pair, false_fn=no_box,
            arg_labels=("rec", "t_best"), rv_labels=("t_l", "hit_l", "t_r", "hit_r"),
            label="hlbvh_boxes", mode="symbolic",
        )
        hit_l &= at_node
        hit_r &= at_node
        ref_l = dr.reinterpret_array(UInt32, rec[12])
        ref_r = dr.reinterpret_array(UInt32, rec[13])
        left_first = hit_l if any_hit else hit_l & (~hit_r | (t_l <= t_r))
        near, near_t = dr.select(left_first, ref_l, ref_r), dr.select(left_first, t_l, t_r)
        far, far_t = dr.select(left_first, ref_r, ref_l), dr.select(left_first, t_r, t_l)
        # Both children hit: go to ``near`` (the nearer; any hit: the left), push the other.
        entry = far if any_hit else \
            ns.UInt64(far) | (ns.UInt64(dr.reinterpret_array(UInt32, far_t)) << 32)
        held, depth, sp, overflow = push(held, depth, sp, entry, hit_l & hit_r)

        # ---- Next step: the leaf's next triangle, the nearer child, or a pop ----
        more = in_leaf & ~stale & (cur + 1 < end)
        if any_hit:
            more &= ~hit
            alive &= ~hit
        pop_here = ~more & ~(hit_l | hit_r)
        has = (depth > 0) | (sp > 0)
        take = pop_here & has & alive
        popped, held, depth, sp = pop(held, depth, sp, take)
        alive &= ~(pop_here & ~has)
        ref = dr.select(take, UInt32(popped), near)
        ref_t = near_t if any_hit else \
            dr.select(take, dr.reinterpret_array(Float, UInt32(popped >> 32)), near_t)
        next_cur, next_end = enter(ref)
        cur = dr.select(more, cur + 1, next_cur)
        end = dr.select(more, end, next_end)
        node_t = dr.select(more, node_t, ref_t)
        entering = ~more

        steps += 1
        cycle = steps > max_steps
        corrupt |= overflow | cycle
        alive &= ~(overflow | cycle)
        return (cur, end, node_t, entering, held, depth, sp, alive, steps, corrupt, t_best,
                u_best, v_best, prim_best, found)

    state = dr.while_loop(state=state, cond=trace_cond, body=trace_body, labels=labels,
                          label="hlbvh_trace", mode="symbolic")
    corrupt, t_best, u_best, v_best, prim_best, found = state[9:]
    valid = found & ~corrupt
    if any_hit:
        return valid
    return (dr.select(valid, t_best, dr.inf), dr.select(valid, u_best, 0),
            dr.select(valid, v_best, 0), dr.select(valid, prim_best, 0), valid)
