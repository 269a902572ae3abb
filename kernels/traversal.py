"""Ray traversal of the packed 4-wide BVH (:mod:`hlbvh.kernels.layout`): closest hit
and any hit.

Each ray runs one symbolic ``dr.while_loop``. Every iteration reads one 64-byte slot
(one packet gather, whatever the lane finds there; a wide node reads its second slot
too) and advances every lane by one step:
a lane at a wide node tests its up to four children's boxes, a lane inside a leaf tests
one triangle. The two tests sit in symbolic ifs, so a packet whose lanes are all at
nodes (or all in leaves) skips the other test, and no lane waits for the rest of its
packet to finish a phase. The loop and its ifs are symbolic whatever Dr.Jit's
``JitFlag.SymbolicLoops`` and ``SymbolicConditionals`` say, so an integrator running
its own loops evaluated still gets one traversal kernel per query.

- **Ordered visit**: the hit children of a wide node are sorted by a four-entry
  sorting network; the ray goes to the first and pushes the others, so the next pop
  is the nearest of them. Closest hit sorts by entry distance and skips a popped entry
  whose distance lies beyond the closest hit so far; any hit, which any occluder ends,
  sorts leaves before nodes (a leaf may end the query at once) and keeps no distance.
- **Conservative slab test** (Ize, "Robust BVH ray traversal", JCGT 2013): the exit
  distance of a box is scaled by ``1 + 2·gamma(3)`` so rounding never culls a box the
  ray touches; so is the closest hit so far when a box's entry distance is compared
  with it. Reciprocal directions come from directions clamped away from zero
  (``|d| >= FLT_MIN``, sign kept), so no ``0 · inf = NaN`` reaches the min/max.
- **Watertight ray/triangle test** (Woop, Benthin & Wald, JCGT 2013): vertices are
  translated to the ray origin, permuted so the ray's dominant axis is z and sheared so
  the ray becomes the z axis. Every vertex is transformed the same way whichever
  triangle it belongs to, and the 2D edge functions U, V, W of a shared edge are exact
  negatives of each other, so no ray slips between two triangles that share an edge or
  a vertex. A hit is accepted with barycentrics ``U/det, V/det, W/det`` down to
  ``-BARYCENTRIC_MARGIN`` (2**-20): this also closes the one-ulp cracks where two
  separately modelled meshes meet (the walls of Cornell box), as Embree does. Triangles
  whose edge functions overflow or underflow float32 (coordinates beyond ~1e19 or below
  ~1e-19 relative to the ray origin) or whose determinant rounds to zero are recomputed
  in double precision, so scenes at 1e+30 and 1e-30 scale trace correctly. Zero-area
  triangles are packed with NaN vertices and never hit.

A hit is reported at the smallest ``t`` with ``0 < t <= maxt``. Rays with a NaN or
infinite component, a zero direction, ``maxt <= 0`` or ``maxt`` NaN are clean misses.

Short stack: the top ``REGISTERS`` (4) entries of each lane's stack live in loop
registers, the rest in local memory (``dr.alloc_local``), which only a packet in which
some lane pushes past the registers, or pops with none held, touches (in a symbolic
if). A wide node pushes at most three entries and the packer refuses trees deeper than
``layout.MAX_DEPTH`` binary levels, so ``STACK_SIZE`` entries always suffice; the
packer also refuses cycles and shared subtrees, so every ray ends.

The slots are packed once per BVH (or per set of BVHs, :func:`layout.joined`) and
cached on it: call :func:`packed_records` (or ``joined``) outside any symbolic loop if
the traversal is then traced inside one, since packing evaluates arrays.
"""

from __future__ import annotations

import drjit as dr

from . import layout
from .arrays import namespace_of, plain
from .layout import packed_records  # noqa: F401  (what traversal reads, built on first use)

#: Entries of the per-lane traversal stack: a wide node pushes at most three, one wide
#: level per two of the deepest tree that packs.
STACK_SIZE = (layout.WIDTH - 1) * layout.MAX_DEPTH // 2
#: Of these, the top entries held in loop registers (the rest in local memory). At
#: least the WIDTH - 1 that one node pushes: the push moves older entries out to local
#: memory, never the new ones, so fewer registers would drop a child (measured: 2 lost
#: hits on up to 6% of rays).
REGISTERS = 4
assert REGISTERS >= layout.WIDTH - 1
_MISS = 0xFFFFFFFFFFFFFFFF  # the entry of a child the ray misses (sorts last)
_MISS32 = 0xFFFFFFFF  # the same for any hit's 32-bit entries
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
        bvh: an ``hlbvh.BVH``, or the :class:`~hlbvh.kernels.layout.Packed` slots of
            several (:func:`~hlbvh.kernels.layout.joined`).
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


def steps(bvh, o, d, maxt, active=True, any_hit=False):
    """Loop iterations each ray takes in :func:`closest_hit` (or :func:`any_hit`): one
    per wide node and per triangle it visits; for benchmarks (a packet of rays costs
    its slowest lane's steps). Arguments as in :func:`closest_hit`; UInt32 of width R."""
    return _trace(bvh, o, d, maxt, active, any_hit, count_steps=True)


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
# Traversal
# ---------------------------------------------------------------------------------------


def _broadcast(x, kind, ns, n):
    """``x`` as a plain ``kind`` array of width exactly ``n`` (an evaluated variable, so
    no literal of width 1 can enter the loop state: Dr.Jit would share one
    local-memory stack between all lanes)."""
    x = plain(x, kind) if dr.is_array_v(x) else getattr(ns, kind)(x)
    if dr.width(x) == n:
        return x
    return dr.gather(getattr(ns, kind), x, dr.opaque(ns.UInt32, 0, n))


def _pick_entry(held, k):
    """Per-lane register entry ``held[k]`` (``k`` a UInt32 below ``len(held)``; any
    value elsewhere)."""
    value = held[0]
    for j in range(1, len(held)):
        value = dr.select(k == j, held[j], value)
    return value


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


def _trace(bvh, o, d, maxt, active, any_hit, count_steps=False):
    if not dr.is_array_v(o) or not dr.is_array_v(d):
        raise TypeError("ray origin and direction must be Dr.Jit Array3f/Point3f/Vector3f")
    ns = namespace_of(o)
    Float, UInt32, UInt64, Bool, Array3f = ns.Float, ns.UInt32, ns.UInt64, ns.Bool, ns.Array3f
    widths = {dr.width(x) for x in (o, d, maxt, active) if dr.is_array_v(x)} - {1}
    if len(widths) > 1:
        raise ValueError(f"ray arrays of different widths {sorted(widths)}: expected one")
    n = widths.pop() if widths else 1
    if n == 0:
        return UInt32() if count_steps else Bool() if any_hit else \
            (Float(), Float(), Float(), UInt32(), Bool())
    if isinstance(bvh, layout.Packed):
        records, root = bvh.records, bvh.root
    else:
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

    def slot(base):
        """The 16 floats of slot ``base``: one packet gather (a vector load per lane
        and a transpose, far cheaper than a gather per float)."""
        return dr.gather(ns.ArrayXf, records, base, shape=(layout.SLOT, n))

    def vertex(rec, offset):
        """A triangle vertex translated, permuted and sheared into ray space."""
        p = [rec[offset + i] for i in range(3)]
        a = [dr.select(m0, p[0], dr.select(m1, p[1], p[2])) - oc
             for (m0, m1), oc in zip(perm, o_p)]
        return a[0] - shear_x * a[2], a[1] - shear_y * a[2], shear_z * a[2]

    def woop(rec, t_max):
        """Watertight intersection with the triangle in ``rec``: (hit, t, u, v)."""
        ax, ay, az = vertex(rec, layout.TRI_P[0])
        bx, by, bz = vertex(rec, layout.TRI_P[1])
        cx, cy, cz = vertex(rec, layout.TRI_P[2])
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
        return inside & (t > 0) & (t <= t_max), t, b1, b2

    def no_triangle(rec, t_max):
        return dr.zeros(Bool, n), dr.zeros(Float, n), dr.zeros(Float, n), dr.zeros(Float, n)

    # Stack entries. Closest hit: ``t_near bits << 32 | reference`` (t_near >= 0, so
    # the bits order as the floats do: sorting entries sorts by distance). Any hit: the
    # reference with its leaf bit flipped (leaves sort before nodes: a leaf may end the
    # query at once), no distance.
    Entry = UInt32 if any_hit else UInt64
    miss = _MISS32 if any_hit else _MISS

    def entry_of(ref, t_near):
        if any_hit:
            return ref ^ layout.LEAF_BIT
        return (UInt64(dr.reinterpret_array(UInt32, t_near)) << 32) | UInt64(ref)

    def ref_of(entry):
        return entry ^ layout.LEAF_BIT if any_hit else UInt32(entry)

    def t_of(entry):
        return node_t if any_hit else dr.reinterpret_array(Float, UInt32(entry >> 32))

    def children(rec, cur, t_best):
        """The wide node whose first slot is ``rec`` (at slot ``cur``; its second slot
        is read here): entries of the children the ray enters before ``t_best``, sorted
        ascending, a missed or absent child as ``miss`` (so the hit ones come first)."""
        rec = [*rec, *slot(cur + 1)]
        keys = []
        limit = t_best * _TFAR_SCALE
        for k in range(layout.WIDTH):
            ref = dr.reinterpret_array(UInt32, rec[layout.NODE_REF + k])
            t0 = [(rec[layout.NODE_LO[i] + k] - o[i]) * inv_d[i] for i in range(3)]
            t1 = [(rec[layout.NODE_HI[i] + k] - o[i]) * inv_d[i] for i in range(3)]
            near = [_min(a, b) for a, b in zip(t0, t1)]
            far = [_max(a, b) for a, b in zip(t0, t1)]
            t_near = _max(_max(near[0], near[1]), _max(near[2], 0.0))
            t_far = _min(_min(far[0], far[1]), far[2])
            hit = (t_near <= _min(t_far * _TFAR_SCALE, limit)) & (ref != layout.EMPTY)
            keys.append(dr.select(hit, entry_of(ref, t_near), miss))
        # A sorting network of four.
        for i, j in ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2)):
            keys[i], keys[j] = _min(keys[i], keys[j]), _max(keys[i], keys[j])
        return tuple(keys)

    def no_children(rec, cur, t_best):
        return tuple(dr.full(Entry, miss, n) for _ in range(layout.WIDTH))

    # ---- Short stack: REGISTERS entries in registers (top first), the rest in local
    # memory, touched only by a packet in which some lane pushes past the registers or
    # pops with none held ----
    memory = dr.alloc_local(Entry, STACK_SIZE)

    def spill(held, depth, count, sp, spilled):
        """Move the ``spilled`` oldest register entries to local memory, oldest
        deepest, before ``count`` new entries push them out."""
        for i in range(layout.WIDTH - 1):
            oldest = _pick_entry(held, depth - 1 - i)
            memory.write(oldest, sp + (spilled - 1 - i), active=spilled > i)
        return sp + spilled

    def no_spill(held, depth, count, sp, spilled):
        return sp

    def fill(sp, mask):
        return memory.read(sp, active=mask)

    def no_fill(sp, mask):
        return dr.zeros(Entry, n)

    def push(held, depth, sp, keys, count):
        """Push ``keys[1..count]`` (the hit children after the nearest, nearest on
        top). Returns ``(held, depth, sp)``. The packer's depth limit bounds what a
        ray can push by ``STACK_SIZE``, so nothing here overflows."""
        spilled = dr.maximum(depth + count, REGISTERS) - REGISTERS
        sp = dr.if_stmt(args=(held, depth, count, sp, spilled), cond=spilled > 0,
                        true_fn=spill, false_fn=no_spill, label="hlbvh_spill",
                        mode="symbolic")
        new = []
        for j in range(REGISTERS):
            value = held[j]
            for c in range(1, layout.WIDTH):
                value = dr.select(count == c, keys[j + 1] if j < c else held[j - c], value)
            new.append(value)
        depth = dr.minimum(depth + count, REGISTERS)
        return new, depth, sp

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

    # ---- Loop state (every variable at full width: a width-1 start value would make
    # Dr.Jit share one local-memory slot between all lanes) ----
    cur, end = layout.open_ref(dr.full(UInt32, root, n))  # slot to process; end of leaf
    node_t = dr.zeros(Float, n)  # entry distance of the current node (or leaf)
    entering = dr.full(Bool, True, n)  # first step at this node (or leaf)
    held = [dr.zeros(Entry, n) for _ in range(REGISTERS)]  # stack registers, top first
    depth = dr.zeros(UInt32, n)  # entries held in registers
    sp = dr.zeros(UInt32, n)  # entries in local memory
    t_best = dr.select(alive, maxt, dr.inf)  # closest hit so far (or maxt)
    u_best = dr.zeros(Float, n)
    v_best = dr.zeros(Float, n)
    hit_slot = dr.zeros(UInt32, n)  # slot of the closest hit's triangle
    found = dr.zeros(Bool, n)
    counted = dr.zeros(UInt32, n)  # loop iterations (count_steps only)
    state = (cur, end, node_t, entering, held, depth, sp, alive, t_best, u_best, v_best,
             hit_slot, found) + ((counted,) if count_steps else ())
    labels = ("cur", "end", "node_t", "entering", "held", "depth", "sp", "alive", "t_best",
              "u_best", "v_best", "hit_slot", "found") + (("steps",) if count_steps else ())

    def trace_cond(cur, end, node_t, entering, held, depth, sp, alive, *rest):
        return alive

    def trace_body(cur, end, node_t, entering, held, depth, sp, alive, t_best, u_best,
                   v_best, hit_slot, found, *counted):
        rec = slot(cur)  # a triangle, or a wide node's first slot
        in_leaf = cur < end
        # A node (or leaf) popped from beyond the closest hit so far is skipped.
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
        hit_slot = dr.select(hit, cur, hit_slot)
        found |= hit

        # ---- A lane at a wide node: test its children's boxes, go to the first ----
        at_node = ~in_leaf & ~stale
        keys = dr.if_stmt(
            args=(rec, cur, t_best), cond=at_node, true_fn=children, false_fn=no_children,
            arg_labels=("rec", "cur", "t_best"), rv_labels=tuple(f"key{k}" for k in range(4)),
            label="hlbvh_boxes", mode="symbolic",
        )
        hits = [k != miss for k in keys]
        count = UInt32(hits[1]) + UInt32(hits[2]) + UInt32(hits[3])
        held, depth, sp = push(held, depth, sp, keys, count)

        # ---- Next step: the leaf's next triangle, the first child, or a pop ----
        more = in_leaf & ~stale & (cur + 1 < end)
        if any_hit:
            more &= ~hit
            alive &= ~hit
        descend = hits[0]
        has = (depth > 0) | (sp > 0)
        take = ~more & ~descend & has & alive
        popped, held, depth, sp = pop(held, depth, sp, take)
        alive &= more | descend | take
        entry = dr.select(take, popped, keys[0])
        next_cur, next_end = layout.open_ref(ref_of(entry))
        cur = dr.select(more, cur + 1, next_cur)
        end = dr.select(more, end, next_end)
        node_t = dr.select(more, node_t, t_of(entry))
        entering = ~more
        return (cur, end, node_t, entering, held, depth, sp, alive, t_best, u_best, v_best,
                hit_slot, found) + tuple(c + 1 for c in counted)

    state = dr.while_loop(state=state, cond=trace_cond, body=trace_body, labels=labels,
                          label="hlbvh_trace", mode="symbolic")
    if count_steps:
        return state[-1]
    t_best, u_best, v_best, hit_slot, valid = state[8:13]
    if any_hit:
        return valid
    prim = dr.reinterpret_array(UInt32, dr.gather(Float, records,
                                                  hit_slot * layout.SLOT + layout.TRI_FACE, valid))
    return (dr.select(valid, t_best, dr.inf), dr.select(valid, u_best, 0),
            dr.select(valid, v_best, 0), dr.select(valid, prim, 0), valid)
