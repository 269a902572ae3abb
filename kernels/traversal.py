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
- **The box and triangle tests** (:mod:`hlbvh.kernels.ray_tests`): Ize's conservative
  slab test, so rounding never culls a box the ray touches, and Woop's watertight
  ray/triangle test, so no ray slips between two triangles that share an edge or a
  vertex, at any scale.

**Two levels** (:class:`TwoLevel`, rigid motion): the top level's leaf slots stand for
instances. A ray reaching one takes the instance's object-space ray (world-to-object
transform, direction not normalised, so ``t`` stays the world ray's), pushes a return
marker and the rest of the leaf, and descends into the instance's tree; popping the
marker restores the world ray. The one-level kernel is the same as without this path.
Instances with keys over the shutter (:attr:`TwoLevel.motion`) take the ray through
their pose at the ray's time (``time=``); without keys the kernel is unchanged.

A hit is reported at the smallest ``t`` with ``0 < t <= maxt``. Rays with a NaN or
infinite component, a zero direction, ``maxt <= 0`` or ``maxt`` NaN are clean misses.

Short stack: the top ``REGISTERS`` entries of each lane's stack live in loop
registers, the rest in local memory (``dr.alloc_local``), which only a packet in which
some lane pushes past the registers, or pops with none held, touches (in a symbolic
if). A wide node pushes at most three entries and the packer refuses trees deeper than
``slots.MAX_DEPTH`` binary levels, so ``STACK_SIZE`` entries always suffice; the
packer also refuses cycles and shared subtrees, so every ray ends.

**Trees read at each ray's time** (:class:`TimedTree`: a
:class:`~hlbvh.kernels.keyed.KeyedTree`, deforming motion blur): the same loop, with
each slot read at the ray's two neighbouring keys and interpolated at its time (child
boxes, triangle vertices) before the same two tests. The tree gives the per-ray reader
(its ``keys_at``), so this module knows the interface, not the keyed module, which
builds and refits trees and so sits above traversal. Which reads a query makes is
chosen in Python when the kernel is traced, so the still kernel is unchanged.

The slots are packed once per BVH (or per set of BVHs, :func:`layout.joined`) and
kept for it: call :func:`~hlbvh.kernels.layout.packing.packed_records` (or ``joined``)
outside any symbolic loop if the traversal is then traced inside one, since packing
evaluates arrays.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import drjit as dr

from .arrays import Bool, Float, high_half, low_half, namespace_of, pack_halves, plain
from .layout import Packed
from .layout.packing import packed_records
from .layout.slots import LEAF_BIT, MAX_DEPTH, SLOT, TRI_FACE, WIDTH, open_ref
from .ray_tests import (TFAR_SCALE, Ray, ray_setup, select_max, select_min, slab_test,
                        triangle_test)
from .tree import Tree
from .two_level import NO_INSTANCE, RETURN_REF, TwoLevel, enter_instance, select_ray

#: Entries of the per-lane traversal stack: a wide node pushes at most three, one wide
#: level per two of the deepest tree that packs.
STACK_SIZE = (WIDTH - 1) * MAX_DEPTH // 2
#: Of these, the top entries held in loop registers (the rest in local memory). At
#: least the WIDTH - 1 that one node pushes: the push moves older entries out to local
#: memory, never the new ones, so fewer registers would drop a child
#: (docs/decisions.md#stack-registers).
REGISTERS = 4
assert REGISTERS >= WIDTH - 1
#: The compare-exchange pairs that sort a wide node's ``WIDTH`` (four) child entries.
_SORTING_NETWORK = ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2))
assert WIDTH == 4, "the sorting network sorts four entries"
_MISS = 0xFFFFFFFFFFFFFFFF  # the entry of a child the ray misses (sorts last)
_MISS32 = 0xFFFFFFFF  # the same for any hit's 32-bit entries


class TimedTree(Protocol):
    """Slots read at each ray's time (:class:`~hlbvh.kernels.keyed.KeyedTree`): its
    ``records`` and ``root``, and ``keys_at(time)``, the reader of the rays at ``time``
    (Float in [0, 1] over the shutter), with ``known`` (Bool: the ray has a time),
    ``stride`` (slots of one place), ``slot(records, base, n)`` (the raw reads of slots
    ``base``), ``triangle(rec)`` and ``node(first, second)`` (a triangle record and a
    wide node's 32 floats at the ray's time, from those reads)."""

    records: Any
    root: int

    def keys_at(self, time: Float) -> Any: ...


# ---------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------


def closest_hit(bvh: Tree | Packed | TimedTree, o: dr.ArrayBase, d: dr.ArrayBase,
                maxt: Float | float, active: Bool | bool = True, time: Float | float | None = None):
    """Nearest intersection of each ray with the BVH's triangles.

    Args:
        bvh: a tree (``hlbvh.BVH``), or the :class:`~hlbvh.kernels.layout.Packed` slots
            of several (:func:`~hlbvh.kernels.layout.joined`), or a :class:`TimedTree`
            (a :class:`~hlbvh.kernels.keyed.KeyedTree`: a deforming mesh at S+1 times).
        o: Array3f (or ``mi.Point3f``) ray origins, width R (or 1).
        d: Array3f (or ``mi.Vector3f``) ray directions, width R (or 1); need not be
            normalised (``t`` is in units of ``d``).
        maxt: Float (or Python float) largest accepted ``t``, width R or 1.
        active: Bool (or Python bool) mask; inactive rays miss.
        time: Float (or Python float) each ray's time in the shutter, normalised to
            [0, 1] (the caller maps ``ray.time``); needed by a timed tree, which is
            traced at that time (values outside [0, 1] are clamped, a NaN time misses);
            ignored by the others (still geometry is the same at every time).
    Returns:
        ``(t, u, v, prim, valid)``: Float ``t`` (``inf`` on a miss), Float ``u``, ``v``
        with ``p = (1-u-v)·p0 + u·p1 + v·p2`` of the face's vertices, UInt32 ``prim``
        the input face index (0 on a miss), Bool ``valid``; all of width R, plain
        (non-AD) arrays of the input's backend.
    """
    return _trace(bvh, o, d, maxt, active, any_hit=False, time=time)


def any_hit(bvh: Tree | Packed | TimedTree, o: dr.ArrayBase, d: dr.ArrayBase,
            maxt: Float | float, active: Bool | bool = True, time: Float | float | None = None):
    """Whether each ray hits any triangle at ``0 < t <= maxt`` (stops at the first hit):
    a Bool of width R. Arguments as in :func:`closest_hit`."""
    return _trace(bvh, o, d, maxt, active, any_hit=True, time=time)


def steps(bvh: Tree | Packed | TimedTree, o: dr.ArrayBase, d: dr.ArrayBase,
          maxt: Float | float, active: Bool | bool = True, any_hit: bool = False,
          time: Float | float | None = None):
    """Loop iterations of each ray in :func:`closest_hit` (:func:`any_hit`), same arguments:
    UInt32 (R), one per wide node and triangle visited (a packet costs its slowest lane's)."""
    return _trace(bvh, o, d, maxt, active, any_hit, count_steps=True, time=time)


def intersect(bvh: Tree | Packed | TimedTree, ray, active: Bool | bool = True,
              time: Float | float | None = None):
    """Closest hit of ``ray`` (anything with ``o``, ``d``, ``maxt``) as a
    ``mi.PreliminaryIntersection3f``: ``valid``, ``t`` (``inf`` on a miss),
    ``prim_uv``, ``prim_index`` (the input face index); ``shape``, ``shape_index`` and
    ``instance`` are left null/zero for the caller to fill. ``time``: as in
    :func:`closest_hit` (normalised to the shutter: not ``ray.time`` itself)."""
    import mitsuba as mi

    t, u, v, prim, valid = closest_hit(bvh, ray.o, ray.d, ray.maxt, active, time)
    pi = dr.zeros(mi.PreliminaryIntersection3f, dr.width(t))
    pi.valid = mi.Bool(valid)
    pi.t = mi.Float(t)
    pi.prim_uv = mi.Point2f(u, v)
    pi.prim_index = mi.UInt32(prim)
    return pi


def occluded(bvh: Tree | Packed | TimedTree, ray, active: Bool | bool = True,
             time: Float | float | None = None):
    """Whether anything lies on ``ray`` at ``0 < t <= ray.maxt``: a ``mi.Bool``
    (``time`` as in :func:`intersect`)."""
    import mitsuba as mi

    return mi.Bool(any_hit(bvh, ray.o, ray.d, ray.maxt, active, time))


def closest_instance_hit(two_level: TwoLevel, o, d, maxt, active=True, time=None):
    """:func:`closest_hit` through a :class:`TwoLevel` hierarchy: a ray that enters an
    instance's box is transformed into the instance's object space (its direction not
    normalised, so ``t`` is the world ray's) and traced through the instance's tree.
    ``time``: each ray's time normalised to the shutter, needed where instances have
    keys (:attr:`TwoLevel.motion`: each is entered at its pose at that time).

    Returns:
        ``(t, u, v, prim, inst, valid)``: as :func:`closest_hit`, ``prim`` counted over
        the instanced trees' faces, and UInt32 ``inst`` the hit's instance.
    """
    return _trace(two_level, o, d, maxt, active, any_hit=False, time=time)


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


# ---- The stack entries and the box test ----


@dataclass
class _Query:
    """What a query reads besides the ray: the slots, and the kind of stack entries.

    Stack entries. Closest hit: ``t_near bits << 32 | reference`` (t_near >= 0, so the
    bits order as the floats do: sorting entries sorts by distance). Any hit: the
    reference with its leaf bit flipped (leaves sort before nodes: a leaf may end the
    query at once), no distance."""

    records: Any  # Float, SLOT per slot
    n: int  # rays
    any_hit: bool
    no_t: Any  # Float[n] zeros: an any-hit entry's distance
    two_level: Any = None  # TwoLevel: instances at the top level's leaf slots, or None
    world_o: Any = None  # Array3f: the world rays' origins (two levels)
    world_d: Any = None  # Array3f: their directions (two levels)
    keys: Any = None  # a timed tree: what each ray reads (TimedTree.keys_at), or None
    time: Any = None  # Float: each ray's normalised time (two levels with keyed instances)

    @property
    def Entry(self):
        return dr.uint32_array_t(type(self.records)) if self.any_hit else \
            dr.uint64_array_t(type(self.records))

    @property
    def miss(self):
        return _MISS32 if self.any_hit else _MISS

    def slot(self, base):
        """The 16 floats of slot ``base``: one packet gather (a vector load per lane
        and a transpose, far cheaper than a gather per float). A keyed tree: the 32
        floats of the slot at the ray's two keys, interpolated by :meth:`triangle` or
        :meth:`node` once the lane knows which the slot is."""
        if self.keys is not None:
            return self.keys.slot(self.records, base, self.n)
        ns = namespace_of(self.records)
        return dr.gather(ns.ArrayXf, self.records, base, shape=(SLOT, self.n))

    def triangle(self, rec):
        """The triangle record the watertight test reads, from what :meth:`slot` read."""
        return rec if self.keys is None else self.keys.triangle(rec)

    def node(self, rec, cur):
        """The 32 floats of the wide node whose first slot (at ``cur``) :meth:`slot`
        read: its second slot is read here."""
        if self.keys is not None:
            return self.keys.node(rec, self.slot(cur + 1))
        return [*rec, *self.slot(cur + 1)]

    def face_at(self, slot):
        """The Float index of the face index field of triangle slots ``slot``."""
        if self.keys is not None:
            slot = slot * self.keys.stride  # key 0 (every key holds the same face)
        return slot * SLOT + TRI_FACE

    def entry_of(self, ref, t_near):
        if self.any_hit:
            return ref ^ LEAF_BIT
        return pack_halves(dr.reinterpret_array(type(ref), t_near), ref)

    def ref_of(self, entry):
        return entry ^ LEAF_BIT if self.any_hit else low_half(entry)

    def t_of(self, entry):
        return self.no_t if self.any_hit else \
            dr.reinterpret_array(type(self.no_t), high_half(entry))


def _box_test(query: _Query, ray: Ray, rec, cur, t_best):
    """The wide node whose first slot is ``rec`` (at slot ``cur``; its second slot
    is read here): entries of the children the ray enters before ``t_best``, sorted
    ascending, a missed or absent child as ``miss`` (so the hit ones come first)."""
    rec = query.node(rec, cur)
    keys = []
    limit = t_best * TFAR_SCALE
    for k in range(WIDTH):
        ref, t_near, hit = slab_test(ray, rec, k, limit)
        keys.append(dr.select(hit, query.entry_of(ref, t_near), query.miss))
    for i, j in _SORTING_NETWORK:
        keys[i], keys[j] = select_min(keys[i], keys[j]), select_max(keys[i], keys[j])
    return tuple(keys)


# ---- The short stack ----


class _Stack:
    """Short stack: ``REGISTERS`` entries in loop registers (top first), the rest in
    local memory, touched only by a packet in which some lane pushes past the registers
    or pops with none held (in a symbolic if)."""

    def __init__(self, Entry, n: int, size: int = STACK_SIZE, ordered: bool = False):
        self.Entry, self.n = Entry, n
        self.memory = dr.alloc_local(Entry, size)
        # One level writes a spill of several entries newest deepest: harmless, as
        # every entry is popped in the end and only the pruning order changes. Two
        # levels need the stack's order (a return marker must come out last).
        self.ordered = ordered

    def _spill(self, held, depth, count, sp, spilled):
        """Move the ``spilled`` oldest register entries to local memory, oldest
        deepest, before ``count`` new entries push them out."""
        for i in range(WIDTH - 1):
            oldest = _pick_entry(held, depth - 1 - i)
            self.memory.write(oldest, sp + (i if self.ordered else spilled - 1 - i),
                              active=spilled > i)
        return sp + spilled

    def _no_spill(self, held, depth, count, sp, spilled):
        return sp

    def _fill(self, sp, mask):
        return self.memory.read(sp, active=mask)

    def _no_fill(self, sp, mask):
        return dr.zeros(self.Entry, self.n)

    def push(self, held, depth, sp, keys, count):
        """Push ``keys[1..count]`` (the hit children after the nearest, nearest on
        top). Returns ``(held, depth, sp)``. The packer's depth limit bounds what a
        ray can push by ``STACK_SIZE``, so nothing here overflows."""
        spilled = dr.maximum(depth + count, REGISTERS) - REGISTERS
        sp = dr.if_stmt(args=(held, depth, count, sp, spilled), cond=spilled > 0,
                        true_fn=self._spill, false_fn=self._no_spill, label="hlbvh_spill",
                        mode="symbolic")
        new = []
        for j in range(REGISTERS):
            value = held[j]
            for c in range(1, WIDTH):
                value = dr.select(count == c, keys[j + 1] if j < c else held[j - c], value)
            new.append(value)
        depth = dr.minimum(depth + count, REGISTERS)
        return new, depth, sp

    def pop(self, held, depth, sp, mask):
        """Pop an entry on the lanes of ``mask`` (each holding one, in registers or in
        local memory). Returns ``(entry, held, depth, sp)``."""
        from_register = mask & (depth > 0)
        filling = mask & (depth == 0)
        sp = dr.select(filling, sp - 1, sp)
        filled = dr.if_stmt(args=(sp, filling), cond=filling, true_fn=self._fill,
                            false_fn=self._no_fill, label="hlbvh_fill", mode="symbolic")
        entry = dr.select(from_register, held[0], filled)
        held = [dr.select(from_register, below, above)
                for above, below in zip(held, held[1:] + held[-1:])]
        depth = dr.select(from_register, depth - 1, depth)
        return entry, held, depth, sp


# ---- The loop ----


@dataclass
class _TraceState:
    """A ray's traversal state (every variable at full width: a width-1 start value
    would make Dr.Jit share one local-memory slot between all lanes)."""

    cur: Any  # UInt32: slot to process (a wide node's first slot, or a triangle's)
    end: Any  # UInt32: one past the leaf's last triangle slot (0 at a wide node)
    node_t: Any  # Float: entry distance of the current node (or leaf)
    entering: Any  # Bool: first step at this node (or leaf)
    held: list  # REGISTERS entries: the top of the stack, top first
    depth: Any  # UInt32: entries held in registers
    sp: Any  # UInt32: entries in local memory
    alive: Any  # Bool: still traversing
    t_best: Any  # Float: closest hit so far (or maxt)
    u_best: Any  # Float: its barycentric u
    v_best: Any  # Float: its barycentric v
    hit_slot: Any  # UInt32: slot of the closest hit's triangle
    found: Any  # Bool: a hit so far
    steps: Any = None  # UInt32: loop iterations (count_steps only)
    # Two levels only (None otherwise):
    ray: Any = None  # Ray: the ray the tests read, in the current instance's object space
    inst: Any = None  # UInt32: the instance the ray is in (NO_INSTANCE at the top level)
    returning: Any = None  # Bool: the last pop left an instance (this step only pops)
    hit_inst: Any = None  # UInt32: the instance of the closest hit's triangle


def _start(ns, query: _Query, root: int, alive, maxt, count_steps: bool,
           ray: Ray) -> _TraceState:
    """The state of rays starting at reference ``root``. Two levels: the root enters
    the kernel as an opaque value (the top level is rebuilt every frame, and its root's
    reference as a literal would compile the kernel anew whenever it moved)."""
    n = query.n
    two = query.two_level is not None
    start = (dr.opaque(ns.UInt32, root) + dr.zeros(ns.UInt32, n)) if two else \
        dr.full(ns.UInt32, root, n)
    cur, end = open_ref(start)
    return _TraceState(
        cur=cur, end=end, node_t=dr.zeros(ns.Float, n), entering=dr.full(ns.Bool, True, n),
        held=[dr.zeros(query.Entry, n) for _ in range(REGISTERS)],
        depth=dr.zeros(ns.UInt32, n), sp=dr.zeros(ns.UInt32, n), alive=alive,
        t_best=dr.select(alive, maxt, dr.inf), u_best=dr.zeros(ns.Float, n),
        v_best=dr.zeros(ns.Float, n), hit_slot=dr.zeros(ns.UInt32, n),
        found=dr.zeros(ns.Bool, n),
        steps=dr.zeros(ns.UInt32, n) if count_steps else None,
        ray=ray if two else None,
        inst=dr.full(ns.UInt32, NO_INSTANCE, n) if two else None,
        returning=dr.zeros(ns.Bool, n) if two else None,
        hit_inst=dr.full(ns.UInt32, NO_INSTANCE, n) if two else None)


def _step(query: _Query, world: Ray, stack: _Stack, s: _TraceState) -> _TraceState:
    """One iteration: a lane in a leaf tests one triangle (or, with two levels, enters
    the instance of a top-level leaf slot), a lane at a wide node its children's boxes;
    then each goes to the leaf's next triangle, the nearest child hit, or the entry it
    pops."""
    ns = namespace_of(s.cur)
    UInt32, Bool, Float, n = ns.UInt32, ns.Bool, ns.Float, query.n
    two = query.two_level is not None
    ray = s.ray if two else world
    rec = query.slot(s.cur)  # a triangle, or a wide node's first slot
    in_leaf = s.cur < s.end
    # A node (or leaf) popped from beyond the closest hit so far is skipped.
    stale = dr.zeros(Bool, n) if query.any_hit else \
        s.entering & (s.node_t > s.t_best * TFAR_SCALE)
    if two:
        stale |= s.returning  # the step after leaving an instance only pops
        # opaque: the top level's first slot moves when the groups' trees change
        at_instance = in_leaf & ~stale & (
            s.cur >= dr.opaque(type(s.cur), query.two_level.top_base))

    # ---- A lane in a leaf: test one triangle ----
    at_triangle = in_leaf & ~stale
    if two:
        at_triangle &= ~at_instance
    hit, t, u, v = dr.if_stmt(
        args=(rec, s.t_best), cond=at_triangle,
        true_fn=lambda rec, t_max: triangle_test(ray, query.triangle(rec), t_max),
        false_fn=lambda rec, t_max: (dr.zeros(Bool, n), dr.zeros(Float, n),
                                     dr.zeros(Float, n), dr.zeros(Float, n)),
        arg_labels=("rec", "t_best"), rv_labels=("hit", "t", "u", "v"),
        label="hlbvh_triangle", mode="symbolic",
    )
    hit &= at_triangle
    s.t_best = dr.select(hit, t, s.t_best)
    s.u_best = dr.select(hit, u, s.u_best)
    s.v_best = dr.select(hit, v, s.v_best)
    s.hit_slot = dr.select(hit, s.cur, s.hit_slot)
    s.found |= hit
    if two:
        s.hit_inst = dr.select(hit, s.inst, s.hit_inst)

    # ---- A lane at a wide node: test its children's boxes, push all but the first ----
    at_node = ~in_leaf & ~stale
    keys = dr.if_stmt(
        args=(rec, s.cur, s.t_best), cond=at_node,
        true_fn=lambda rec, cur, t_best: _box_test(query, ray, rec, cur, t_best),
        false_fn=lambda rec, cur, t_best: tuple(dr.full(query.Entry, query.miss, n)
                                                for _ in range(WIDTH)),
        arg_labels=("rec", "cur", "t_best"),
        rv_labels=tuple(f"key{k}" for k in range(WIDTH)),
        label="hlbvh_boxes", mode="symbolic",
    )
    if two:
        # ---- A lane at an instance: into its group's tree, object space ----
        keys = enter_instance(query, rec, s, at_instance, keys)
    hits = [k != query.miss for k in keys]
    count = sum((UInt32(h) for h in hits[2:]), UInt32(hits[1]))
    s.held, s.depth, s.sp = stack.push(s.held, s.depth, s.sp, keys, count)

    # ---- Next step: the leaf's next triangle, the first child, or a pop ----
    more = in_leaf & ~stale & (s.cur + 1 < s.end)
    if two:
        more &= ~at_instance
    if query.any_hit:
        more &= ~hit
        s.alive &= ~hit
    descend = hits[0]
    has = (s.depth > 0) | (s.sp > 0)
    take = ~more & ~descend & has & s.alive
    popped, s.held, s.depth, s.sp = stack.pop(s.held, s.depth, s.sp, take)
    s.alive &= more | descend | take
    entry = dr.select(take, popped, keys[0])
    ref = query.ref_of(entry)
    next_cur, next_end = open_ref(ref)
    if two:
        # ---- A popped return marker: back in the world, this instance done ----
        leaving = take & (ref == RETURN_REF)
        s.ray = select_ray(leaving, world, s.ray)
        s.inst = dr.select(leaving, NO_INSTANCE, s.inst)
        s.returning = leaving
        next_cur, next_end = dr.select(leaving, 0, next_cur), dr.select(leaving, 0, next_end)
    s.cur = dr.select(more, s.cur + 1, next_cur)
    s.end = dr.select(more, s.end, next_end)
    s.node_t = dr.select(more, s.node_t, query.t_of(entry))
    s.entering = ~more
    if s.steps is not None:
        s.steps = s.steps + 1
    return s


def _trace(bvh, o, d, maxt, active, any_hit, count_steps=False, time=None):
    if not dr.is_array_v(o) or not dr.is_array_v(d):
        raise TypeError("ray origin and direction must be Dr.Jit Array3f/Point3f/Vector3f")
    keys_at = getattr(bvh, "keys_at", None)  # a TimedTree's
    timed = keys_at is not None or (isinstance(bvh, TwoLevel) and bvh.motion is not None)
    if timed and time is None:
        raise ValueError("a keyed tree is traced at each ray's time: pass time= (Float in "
                         "[0, 1] over the shutter)")
    ns = namespace_of(o)
    Float, UInt32, Bool = ns.Float, ns.UInt32, ns.Bool
    widths = {dr.width(x) for x in (o, d, maxt, active, time) if dr.is_array_v(x)} - {1}
    if len(widths) > 1:
        raise ValueError(f"ray arrays of different widths {sorted(widths)}: expected one")
    n = widths.pop() if widths else 1
    if n == 0:
        if count_steps or any_hit:
            return UInt32() if count_steps else Bool()
        return (Float(), Float(), Float(), UInt32()) + \
            ((UInt32(),) if isinstance(bvh, TwoLevel) else ()) + (Bool(),)
    two_level = bvh if isinstance(bvh, TwoLevel) else None
    if keys_at is not None or isinstance(bvh, (Packed, TwoLevel)):
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
    keys = None
    if keys_at is not None:  # (a Python-level choice: the still kernel is not touched)
        keys = keys_at(_broadcast(time, "Float", ns, n))
        alive &= keys.known
    ray = ray_setup(o, d)
    query = _Query(records=records, n=n, any_hit=any_hit, no_t=dr.zeros(Float, n),
                   two_level=two_level, world_o=o, world_d=d, keys=keys,
                   time=_broadcast(time, "Float", ns, n)
                   if two_level is not None and two_level.motion is not None else None)
    # Two levels: a tree under a tree, and the two entries an instance pushes.
    stack = _Stack(query.Entry, n, STACK_SIZE) if two_level is None else \
        _Stack(query.Entry, n, 2 * STACK_SIZE + 2, ordered=True)

    # Two levels: the loop carries a ray of its own (loop state must not share arrays
    # with what the body reads as the world ray).
    state = _start(ns, query, root, alive, maxt, count_steps,
                   ray_setup(dr.copy(o), dr.copy(d)) if two_level is not None else None)
    state, = dr.while_loop(state=(state,), cond=lambda s: s.alive,
                           body=lambda s: (_step(query, ray, stack, s),), labels=("ray",),
                           label="hlbvh_trace", mode="symbolic")
    if count_steps:
        return state.steps
    valid = state.found
    if any_hit:
        return valid
    prim = dr.reinterpret_array(UInt32, dr.gather(Float, records,
                                                  query.face_at(state.hit_slot), valid))
    hit = (dr.select(valid, state.t_best, dr.inf), dr.select(valid, state.u_best, 0),
           dr.select(valid, state.v_best, 0), dr.select(valid, prim, 0))
    if two_level is not None:
        return (*hit, dr.select(valid, state.hit_inst, NO_INSTANCE), valid)
    return (*hit, valid)
