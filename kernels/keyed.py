"""Keyed trees, for the motion blur of deforming meshes: one tree topology, its packed
slots at ``S + 1`` evenly spaced times over the shutter (the *keys*), each ray traced at
its own time.

A deforming mesh gives its vertex positions at keys ``0 .. S`` (key ``k`` at time
``k / S`` of the shutter, normalised to [0, 1]). The tree is built once (which triangles
go together), then refit at every key (:func:`hlbvh.kernels.refit.refit`: a tree
packed before takes the fused refit, which writes each key's slots with the same
topology). A ray at time ``t`` reads keys ``k = min(floor(t·S), S - 1)`` and ``k + 1``
and interpolates, with ``f = t·S - k``, the child boxes of each wide node it visits and
the vertices of each triangle it tests; then it makes the still tree's tests (Ize's
conservative slab test, Woop's watertight triangle test,
:mod:`hlbvh.kernels.ray_tests`). The traversal loop is the still one
(:mod:`hlbvh.kernels.traversal`): a keyed tree only changes how a slot is read.

**Layout.** Slot ``s`` of key ``k`` is slot ``s·(S+1) + k`` of one Float array, so a ray
reads a slot's two keys from two adjacent 64-byte lines. References (slot numbers) are
the still tree's. Memory: ``S + 1`` times the still tree's slots.

**The interpolation**, in float, with ``g = 1 - f`` (the weight of key ``k``):

- a vertex is :func:`lerp_vertex`: ``fma(g, a, f·b)``, or ``a`` itself where both keys
  are equal. The fma form is *monotone* in ``a`` and in ``b`` (a product by a
  non-negative weight, then an fma, each rounds monotonically), *exact* at the keys
  (``f = 0`` gives ``a``, ``f = 1`` gives ``b``), and the select makes it exact where
  the keys are equal: a keyed tree whose keys are equal traces bit-identically to the
  still tree. It is *the same for every triangle that shares a vertex* (same inputs,
  same output), so the watertight test stays watertight at every time;
- a box bound is :func:`_box_float`: the same fma form moved outward by at least one
  ulp. A bound below a vertex at both keys stays below the monotone form of that
  vertex, and the monotone form of a still vertex is within an ulp of the vertex: the
  widened box contains the interpolated triangle (linear bounds as Embree's,
  conservative in float arithmetic too).

A float ``fma(f, b - a, a)`` is not monotone (the rounding of ``b - a`` can put a
vertex outside its interpolated box, ``docs/motion.md``). :func:`lerp` is the same
monotone interpolation in double, for the mid-shutter pose.

**Zero-area triangles.** The still tree packs them with NaN vertices (never hit). A
keyed tree keeps the real vertices of a triangle that has an area at some key (a mesh
scaled through zero is flat at one instant, not over two whole segments) and packs NaN
only for a triangle flat at every key. (At the instant it is flat, such a triangle's
determinant is zero and the watertight test reports no hit, or, where rounding leaves a
sliver, a hit on the sliver.)

**Which pose to build.** :func:`build_keyed` builds the topology over the mid-shutter
positions (key ``S/2``, or the two middle keys interpolated at one half). A refit
tree's boxes grow with how far the mesh has moved since the pose the tree was built
for; the middle of the shutter is never more than half a shutter away from a ray's
time, key 0 a whole shutter.

**The tree's quality over the shutter** (:func:`sah_over_shutter`): a node's box at
time ``t`` of a segment is linear in ``t``, so its half area is a quadratic in ``t``
whose integral Simpson's rule gives exactly (the ends and the box of the averaged
corners). The expected SAH cost of a ray at a uniform time is the weighted sum of those
integrals over the root's integral (a uniform scaling of the mesh over the shutter
leaves it unchanged). Over the still SAH of a tree built at mid-shutter, it is the
degradation of keying: 1 where the mesh moves rigidly, large where the motion scrambles
the triangles that the mid-shutter tree put together. Where it passes a tolerance and
the builder is ``"sah"``, ``topology="auto"`` also builds over each triangle's box over
the whole shutter (the union of its key boxes, whose areas the binned SAH weighs: it
keeps apart triangles whose paths cross) and keeps whichever of the two has the lower
SAH over the shutter. The Morton builders (``"hlbvh"``, ``"lbvh"``) order triangles by
their box centres, which for a linear motion are the mid-shutter centres: over the
union boxes they build the mid-shutter topology again (up to the top level's splits),
so ``"auto"`` does not pay for a second build there (the A/B:
docs/decisions.md#keyed-topology).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from typing import Any, Sequence

import drjit as dr

from .arrays import Float, UInt32, namespace_of
from .bounds import node_bounds
from .build import build
from .geometry import BOX_RECORD, as_faces, as_points, triangle_boxes, triangles_of
from .layout.packing import pack_state, packed_records
from .layout.slots import NODE_REF, SLOT, TRI_FACE, TRI_P
from .refit import RefitState, refit, refit_packed, slot_faces
from .tree import Tree

#: A keyed tree's floats are addressed with 32-bit indices.
MAX_FLOATS = 2**32 - 1
#: Fields of a wide node's 32 floats that are box coordinates (interpolated); the rest
#: are child references and padding, the same at every key.
_NODE_BOX_FIELDS = NODE_REF
#: The first of them that is an upper bound (lower bounds first, then upper).
_NODE_HI = NODE_REF // 2
#: Fields of a triangle slot that are its vertices (interpolated).
_TRI_VERTEX_FIELDS = range(TRI_P[0], TRI_P[2] + 3)
assert list(_TRI_VERTEX_FIELDS) == list(range(9)) and TRI_FACE == 9


@dataclass
class KeyedTree:
    """A tree's packed slots at ``keys`` evenly spaced times (what :func:`keyed_tree`
    returns; traversal takes it with a ``time`` per ray, through :meth:`keys_at`: a
    :class:`hlbvh.kernels.traversal.TimedTree`).

    Attributes:
        records: Float, ``SLOT`` floats per slot and key: slot ``s`` of key ``k`` at
            slot ``s·keys + k``.
        root: the root's reference (a slot number of the still layout).
        keys: ``S + 1`` (at least 2).
        slots: slots of one key (the still tree's slot count).
        bvh: the tree whose topology the slots have (as given: not refit here), for the
            next frame's :func:`keyed_tree`.
        sah: the topology's expected SAH cost over the shutter
            (:func:`sah_over_shutter`), where :func:`build_keyed` made the tree; else
            None.
        still_sah: the SAH cost of a tree built over the mid-shutter pose, at that
            pose (what a still frame at mid-shutter traces), where :func:`build_keyed`
            made the tree.
        topology: which pose :func:`build_keyed` built the topology over
            (:data:`TOPOLOGIES`), None for :func:`keyed_tree`'s.
    """

    records: Any
    root: int
    keys: int
    slots: int
    bvh: Tree
    sah: float | None = None
    still_sah: float | None = None
    topology: str | None = None

    @property
    def degradation(self) -> float | None:
        """:attr:`sah` over :attr:`still_sah`: what keying costs the tree's quality
        (1: none), None where not measured."""
        if self.sah is None or not self.still_sah:
            return None
        return self.sah / self.still_sah

    @property
    def segments(self) -> int:
        """``S``: the intervals between keys."""
        return self.keys - 1

    def keys_at(self, time: Float) -> "RayKeys":
        """What rays at ``time`` read (:func:`ray_keys`)."""
        return ray_keys(self, time)


@dataclass
class RayKeys:
    """What a ray of a keyed trace reads, fixed through its traversal loop.

    Attributes:
        stride: the tree's key count (slots of one place).
        k: UInt32, the ray's first key (its slot ``s`` is read at ``s·stride + k`` and
            the next).
        f: Float, the weight of key ``k + 1`` (``t·S - k``, in [0, 1]).
        g: Float, the weight of key ``k`` (``1 - f``).
        known: Bool, the ray has a time (not NaN); the others miss.
    """

    stride: int
    k: Any
    f: Any
    g: Any
    known: Any

    def slot(self, records: Float, base: UInt32, n: int) -> list:
        """The 32 floats of slot ``base`` at each ray's keys ``k`` and ``k + 1`` (two
        packet gathers of adjacent 64-byte lines), not yet interpolated."""
        ns = namespace_of(records)
        at = base * self.stride + self.k
        return [*dr.gather(ns.ArrayXf, records, at, shape=(SLOT, n)),
                *dr.gather(ns.ArrayXf, records, at + 1, shape=(SLOT, n))]

    def triangle(self, rec: list) -> list:
        """The triangle record at the ray's time from :meth:`slot`'s 32 floats: the
        vertices interpolated, the rest key ``k``'s."""
        f, g = self.f, self.g
        return [lerp_vertex(rec[i], rec[SLOT + i], f, g) if i in _TRI_VERTEX_FIELDS
                else rec[i] for i in range(SLOT)]

    def node(self, first: list, second: list) -> list:
        """A wide node's 32 floats at the ray's time, from :meth:`slot`'s reads of its
        two slots: the child boxes interpolated, the references key ``k``'s."""
        rec = first[:SLOT] + second[:SLOT]
        nxt = first[SLOT:] + second[SLOT:]
        f, g = self.f, self.g
        return [_box_float(rec[i], nxt[i], f, g, i < _NODE_HI) if i < _NODE_BOX_FIELDS
                else rec[i] for i in range(2 * SLOT)]


# ---------------------------------------------------------------------------------------
# Making a keyed tree
# ---------------------------------------------------------------------------------------


def checked_keys(keys, faces, top: int | None = None) -> list:
    """The keys as flat Float[3·V] arrays, after checking that there are at least two,
    that every key holds as many vertices as key 0, enough for ``faces`` (flat UInt32),
    and only finite values.

    Raises:
        TypeError: ``keys`` is not a sequence of Dr.Jit arrays (naming the key).
        ValueError: fewer than two keys; a key of another vertex count than key 0's, or
            with a NaN or infinite coordinate, naming the key (``keys[k]``); faces that
            index past the keys' vertices.
    """
    if dr.is_array_v(keys) or not isinstance(keys, Sequence):
        raise TypeError("keys: expected a list of the vertex positions at each key "
                        f"(flat Float 3·V or Array3f, S + 1 of them), got {type(keys).__name__}")
    if len(keys) < 2:
        raise ValueError(f"keys: {len(keys)} given, a keyed tree needs at least 2 (S + 1 "
                         "keys over the shutter, S >= 1)")
    points = []
    for k, key in enumerate(keys):
        try:
            p = as_points(key)
        except (TypeError, ValueError) as error:
            raise type(error)(f"keys[{k}]: {str(error).removeprefix('vertices: ')}") \
                from None
        if k and len(p) != len(points[0]):
            raise ValueError(f"keys[{k}]: {len(p) // 3} vertices, but keys[0] has "
                             f"{len(points[0]) // 3}: every key holds the same vertices")
        points.append(p)
    bad = [dr.count(~dr.isfinite(p)) for p in points]
    if top is None:
        largest = dr.max(faces) if len(faces) else dr.zeros(type(faces), 1)
    dr.eval(bad, largest if top is None else ())  # every reduction, then one wait
    top = int(largest[0]) if top is None else top
    v = len(points[0]) // 3
    for k, count in enumerate(bad):
        if int(count[0]):
            raise ValueError(f"keys[{k}]: {int(count[0])} of {3 * v} coordinates are "
                             "non-finite (NaN or infinite); fix or drop those vertices")
    if v == 0 or top >= v:
        raise ValueError(f"keys: the faces index vertex {top}, but each key holds {v} "
                         "vertices")
    return points


def keyed_tree(bvh: Tree, keys) -> KeyedTree:
    """The slots of ``bvh``'s topology at every key: a refit per key (fused with its
    packing for a builder's tree), each key's slots copied to their places in the keyed
    layout. ``bvh`` is left as it was (refit on a copy that shares its caches' plans).

    Args:
        bvh: the tree (any pose: the keys give the positions; :func:`build_keyed` says
            which pose to build it over).
        keys: ``S + 1`` arrays of vertex positions (S >= 1), each a flat Float (3·V) or
            Array3f (V), of the faces ``bvh`` was built over.
    Returns:
        a :class:`KeyedTree`.
    Raises:
        TypeError, ValueError: as :func:`checked_keys`, naming the key; ValueError when
            the keyed slots would exceed 32-bit float indices.
    """
    return _keyed(bvh, checked_keys(keys, bvh.faces))


def _keyed(bvh: Tree, points: list) -> KeyedTree:
    """:func:`keyed_tree` of checked keys (flat Float arrays)."""
    count = len(points)
    ns = namespace_of(bvh.node_count)
    UInt32_, Float_ = ns.UInt32, ns.Float
    work = _working_copy(bvh)
    packed = pack_state(work)
    if packed.last != (0, 0, 0):  # last packed elsewhere (joined): pack here
        packed.records = None
    _, root = packed_records(work)  # the slots' place (kept for bvh when it was traced)
    total = packed.plan[1].total
    if SLOT * count * total + SLOT > MAX_FLOATS:
        raise ValueError(f"keys: {count} keys of {total} slots need {SLOT * count * total} "
                         f"floats; a keyed tree holds at most {MAX_FLOATS}")
    records = dr.empty(Float_, SLOT * count * total)
    record_of = packed.plan[1].record_of  # each triangle slot's slot
    place = dr.arange(UInt32_, total)
    flat_somewhere = dr.zeros(ns.Bool, bvh.prim_count)
    flat_everywhere = dr.ones(ns.Bool, bvh.prim_count)
    faces = slot_faces(work)[0]
    for k, p in enumerate(points):
        key = dr.opaque(UInt32_, k)
        # A builder's tree: the fused refit writes the key's slots in place. Another
        # (made by hand): refit through its binary levels, packed, the slots copied.
        if not refit_packed(work, p, faces, (records, count, k)):
            refit(work, p)
            rows = dr.gather(ns.ArrayXf, packed_records(work)[0], place, shape=(SLOT, total))
            dr.scatter(records, rows, place * count + key)
        # The still packing's mark of a zero-area triangle: NaN vertices.
        flat = dr.isnan(dr.gather(Float_, records, (record_of * count + key) * SLOT + TRI_P[0]))
        flat_somewhere |= flat
        flat_everywhere &= flat
        dr.eval(records, flat_somewhere, flat_everywhere)
    _unflatten(records, count, points, bvh, record_of, flat_somewhere & ~flat_everywhere)
    # The plans the refits made depend on the topology only (each keyed by it): kept for
    # bvh, so that the next frame's keys refit without making them again (the
    # placement only where bvh was last packed at slot 0, as here).
    bvh.kept[RefitState] = work.kept_state(RefitState)
    if pack_state(bvh).last in (None, (0, 0, 0)):
        pack_state(bvh).plan = packed.plan
    return KeyedTree(records=records, root=root, keys=count, slots=total, bvh=bvh)


#: What :func:`build_keyed` builds a keyed tree's topology over: ``"mid"``, the
#: mid-shutter pose; ``"union"``, each triangle's box over the whole shutter;
#: ``"auto"``, the mid-shutter pose, and with the ``"sah"`` builder the union too where
#: the mid-shutter tree's SAH over the shutter degrades past a tolerance, the better of
#: the two kept (module docstring).
TOPOLOGIES = ("auto", "mid", "union")


def build_keyed(keys, faces, topology: str = "mid", tolerance: float = 1.05,
                **options) -> KeyedTree:
    """Build a tree over the mid-shutter positions (:func:`mid_shutter`) or over each
    triangle's box over the shutter (:func:`union_tree`), key it (:func:`keyed_tree`)
    and measure its SAH cost over the shutter (:func:`sah_over_shutter`).

    Args:
        keys: as :func:`keyed_tree`.
        faces: flat UInt32 (3·F) or Array3u (F).
        topology: one of :data:`TOPOLOGIES`.
        tolerance: with ``"auto"``, the degradation (SAH over the shutter over the
            still SAH at mid-shutter) the mid-shutter topology may reach before the
            union topology is built too, with the ``"sah"`` builder (the update
            policy's ``refit_tolerance``: the same bound on a tree's drift from a fresh
            build).
        options: ``hlbvh.build``'s (``builder``, ``leaf_size``, ``config``, ...).
    Returns:
        a :class:`KeyedTree` with ``sah``, ``still_sah`` and ``topology`` set.
    Raises:
        ValueError: an unknown ``topology``; bad keys, as :func:`checked_keys`.
    """
    if topology not in TOPOLOGIES:
        raise ValueError(f"topology={topology!r}: expected one of {TOPOLOGIES}")
    faces = as_faces(faces)
    points = checked_keys(keys, faces)
    mid = build(mid_shutter(points), faces, **options)
    still_sah = float(mid.stats.sah_cost)
    kept = None
    if topology != "union":
        kept = _measured(_keyed(mid, points), points, still_sah, "mid")
        if topology == "mid" or kept.degradation <= tolerance or mid.config.builder != "sah":
            return kept
    other = _measured(_keyed(union_tree(points, faces, **options), points), points,
                      still_sah, "union")
    return other if kept is None or other.sah < kept.sah else kept


def _measured(keyed: KeyedTree, points: list, still_sah: float, topology: str) -> KeyedTree:
    """``keyed`` with its SAH over the shutter, the still SAH and its topology."""
    keyed.sah, keyed.still_sah, keyed.topology = \
        sah_over_shutter(keyed.bvh, points), still_sah, topology
    return keyed


def union_tree(points: list, faces, **options) -> Tree:
    """A tree whose topology is built over each triangle's box over the whole shutter
    (the union of its boxes at the keys ``points``, flat Float arrays), its boxes and
    triangles then refit to the mid-shutter pose.

    The builders take triangles: each face is given to ``hlbvh.build`` as the flat
    triangle ``(lo, hi, hi)`` of its union box, whose box and centroid (what the
    builders read) are the union box's; the tree then takes the real faces (slot
    ``i`` holds face ``prim_ids[i]`` in both) and is refit to the mid-shutter pose.
    """
    ns = namespace_of(faces)
    face = dr.unravel(ns.Array3u, faces)
    lo = hi = None
    for p in points:
        for c in range(3):
            v = dr.gather(ns.Array3f, p, face[c])
            lo = v if lo is None else dr.minimum(lo, v)
            hi = v if hi is None else dr.maximum(hi, v)
    n = dr.width(face[0])
    box_points = dr.empty(ns.Float, 9 * n)
    at = dr.arange(ns.UInt32, n) * 9
    for c, corner in enumerate((lo, hi, hi)):
        for axis in range(3):
            dr.scatter(box_points, corner[axis], at + 3 * c + axis)
    tree = build(box_points, dr.arange(ns.UInt32, 3 * n), **options)
    tree = dataclasses.replace(tree, faces=faces, kept={})
    return refit(tree, mid_shutter(points))


def sah_over_shutter(bvh: Tree, keys) -> float:
    """The expected SAH cost of ``bvh``'s topology keyed over ``keys`` (as
    :func:`keyed_tree` takes them, checked as it checks them) for a ray at a uniform
    time in the shutter: the node boxes at each key (the keyed tree's, before the ulp
    it widens them by), each node's half area integrated exactly over each segment
    (Simpson's rule: the area of a box whose corners move linearly is a quadratic in
    time), weighted as
    :func:`hlbvh.kernels.bounds.sah_cost` weighs a node (1 an internal node, its
    triangle count a leaf) and divided by the root's integral. Equal keys give
    ``sah_cost`` of that pose. In double precision, as ``sah_cost``."""
    ns = namespace_of(bvh.node_count)
    Array3d, Float64 = ns.Array3f64, ns.Float64
    points = checked_keys(keys, bvh.faces)
    faces = slot_faces(bvh)[0]

    def half_area(e):
        return e.x * e.y + e.y * e.z + e.z * e.x

    integral, last = dr.zeros(Float64, bvh.size), None
    n = dr.width(faces[0])
    at = dr.arange(ns.UInt32, n)
    zero = dr.zeros(ns.Float, n)
    for p in points:
        # the slots' boxes as node_bounds reads them (the triangles themselves not kept)
        lo, hi = triangle_boxes(triangles_of(p, faces))
        boxes = dr.empty(ns.Float, BOX_RECORD * n)
        dr.scatter(boxes, ns.ArrayXf([lo.x, lo.y, lo.z, hi.x, hi.y, hi.z, zero, zero]), at)
        dr.eval(boxes)
        lo, hi = node_bounds(bvh.node_first, bvh.node_count, boxes, bvh.levels,
                             bvh.config.leaf_size)
        extent = dr.maximum(Array3d(hi) - Array3d(lo), 0.0)
        if last is not None:
            integral += (half_area(last) + 4.0 * half_area(0.5 * (last + extent))
                         + half_area(extent)) / 6.0
        last = extent
        dr.eval(integral, last)
    root = dr.gather(Float64, integral, dr.zeros(ns.UInt32, 1))
    rel = dr.select(root > 0, integral / dr.select(root > 0, root, 1.0), 1.0)
    weight = dr.select(bvh.node_count == 0, 1.0, Float64(bvh.node_count))
    return float(dr.sum(rel * weight)[0])


def mid_shutter(points: list) -> Float:
    """Flat Float[3·V]: the positions at the middle of the shutter, key ``S/2`` (S
    even) or the two middle keys interpolated at one half (as a ray at time 0.5
    sees them)."""
    s = len(points) - 1
    if s % 2 == 0:
        return points[s // 2]
    Float64 = dr.float64_array_t(type(points[0]))
    half = Float64(0.5)
    return lerp(points[s // 2], points[s // 2 + 1], half, half)


def _working_copy(bvh: Tree) -> Tree:
    """``bvh`` with its own arrays, statistics and stage states (the states' entries
    shared: what a refit replaces is replaced on the copy only)."""
    stats = copy.copy(bvh.stats)
    stats.stage_ms = dict(bvh.stats.stage_ms)
    kept = {kind: copy.copy(state) for kind, state in bvh.kept.items()}
    return dataclasses.replace(bvh, stats=stats, kept=kept)


def _unflatten(records, count, points, bvh, record_of, partly_flat):
    """Write the real vertices of ``partly_flat`` triangles (Bool per triangle slot:
    flat at some keys, not at all) at every key, over the NaN the packing gave them
    where they were flat. Usually there are none: a count, and nothing else."""
    if not int(dr.count(partly_flat)[0]):
        return
    ns = namespace_of(record_of)
    slot = dr.compress(partly_flat)
    face = dr.gather(ns.Array3u, as_faces(bvh.faces), dr.gather(ns.UInt32, bvh.prim_ids, slot))
    first = dr.gather(ns.UInt32, record_of, slot) * count
    for k, p in enumerate(points):
        at = (first + k) * SLOT
        for c in range(3):
            vertex = dr.gather(ns.Array3f, p, face[c])
            for axis in range(3):
                dr.scatter(records, vertex[axis], at + TRI_P[c] + axis)
    dr.eval(records)


# ---------------------------------------------------------------------------------------
# Reading a keyed tree (the traversal's slot reads, :mod:`hlbvh.kernels.traversal`)
# ---------------------------------------------------------------------------------------


def lerp(a, b, f, g):
    """``a`` and ``b`` (Float arrays, or lists of them) interpolated with Float64
    weights ``f`` (of ``b``) and ``g = 1 - f`` (of ``a``): ``float32(fma(f, b, g·a))``
    in double. Monotone in ``a`` and ``b``, exact at ``f = 0``, ``f = 1`` and
    ``a == b`` (module docstring)."""
    if isinstance(a, (list, tuple)):
        return [lerp(x, y, f, g) for x, y in zip(a, b)]
    if dr.depth_v(a) > 1:
        return type(a)(*(lerp(x, y, f, g) for x, y in zip(a, b)))
    Float64 = type(f)
    return type(a)(dr.fma(f, Float64(b), g * Float64(a)))


def lerp_vertex(a, b, f, g):
    """A vertex at the ray's time in float: ``fma(g, a, f·b)``, monotone in ``a`` and
    ``b`` (``f, g >= 0``), ``a`` itself where both keys are equal."""
    return dr.select(a == b, a, dr.fma(g, a, f * b))


def _box_float(a, b, f, g, low: bool):
    """A box bound at the ray's time in float: ``fma(g, a, f·b)`` moved outward by at
    least one ulp, so that it bounds every :func:`lerp_vertex` vertex it bounded at
    both keys (the monotone form is within an ulp of a still vertex's exact value)."""
    x = dr.fma(g, a, f * b)
    step = dr.maximum(dr.abs(x) * 2.0**-23, 1e-30)
    return x - step if low else x + step


def ray_keys(keyed: KeyedTree, time: Float) -> RayKeys:
    """The keys and weights of rays at ``time`` (Float, normalised to the shutter;
    clamped to [0, 1]; NaN: ``known`` False)."""
    ns = namespace_of(time)
    s = keyed.segments
    known = ~dr.isnan(time)
    x = dr.clip(dr.select(known, time, 0.0), 0.0, 1.0) * s
    k = dr.minimum(ns.UInt32(dr.floor(x)), s - 1)
    f = x - ns.Float(k)  # exact: x and k within a factor two (or k = 0)
    return RayKeys(stride=keyed.keys, k=k, f=f, g=1.0 - f, known=known)
