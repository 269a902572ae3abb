"""The intersectors our integrators trace through: HLBVHs over a Mitsuba scene
(:class:`SceneAccel`) and the scene's own accelerator (:class:`NativeAccel`, Embree on
the LLVM backend, OptiX on CUDA), behind the same three methods as ``mi.Scene``.

Mitsuba 3 does not let Python supply the intersection routine of its native
accelerator, so the integration point is the integrator: every ray query of our
integrators goes to one of these objects, and a hit comes back as a
``mi.PreliminaryIntersection3f`` whose ``shape``/``shape_index``/``prim_index``/
``prim_uv`` are exactly what Mitsuba's own query would have produced, so that
``compute_surface_interaction`` (Mitsuba's code) fills in the surface interaction.

What :class:`SceneAccel` intersects, and what it does not:

* meshes (``obj``, ``ply``, ``serialized``, ``rectangle``, ``cube``, ... anything with
  ``is_mesh()``): their world-space triangles, in the BVHs of two :class:`MeshGroup`
  (see "Per-frame update" below);
* ``sphere``, ``disk``, ``cylinder``: the few analytic shapes, intersected by
  Mitsuba's own per-shape routine (``shape.ray_intersect_preliminary``, called once per
  analytic shape: a call through a shape pointer inside a symbolic loop would trace
  every registered shape, and meshes have no such routine) and merged with the
  BVHs' hit by nearest ``t``;
* instances, curves, SDF grids and ellipsoids: rejected with a ``ValueError`` naming
  the shape (never rendered wrong);
* meshes without triangles: rejected with a ``ValueError`` naming the shape. Mitsuba's
  own ``obj`` and ``ply`` loaders refuse a file without faces, and so does a
  ``params.update()`` that empties a mesh's faces, so such a mesh only comes from
  Python code (``mi.Mesh(name, 0, 0)``), where it is more likely a mistake than an
  intent: an object that silently disappears renders a wrong image without any error;
* a scene without any geometry (only an environment, say) is valid, as it is for
  Mitsuba: every ray misses.

Per-frame update
----------------
:meth:`SceneAccel.update` (after ``params.update()``) rebuilds only what the scene
requires. A mesh's change is seen from the Dr.Jit variable indices of its vertex and
face buffers (a ``params[...]`` assignment gives the mesh new variables; the
accelerator holds the old ones, so their indices cannot be reused meanwhile): no
buffer is compared. The meshes live in two groups, each with its own BVH:

* **static**: the meshes that never changed since the accelerator was built, built
  once; a mesh whose buffers change for the first time leaves it, and the static BVH
  is rebuilt once without it;
* **dynamic**: the meshes that changed at least once, brought up to date on every
  update in which one of them changed, as the :class:`UpdatePolicy` says: refit while
  the tree's SAH cost stays within ``refit_tolerance`` of its last build's, rebuilt
  otherwise (``update="auto"``, the default), rebuilt every time (``"rebuild"``; the
  CSD sort starts from last frame's primitive order when the triangle count is
  unchanged and that order pays), or refit every time (``"refit"``).
  New faces, a changed vertex count or a change of its meshes always rebuild.

Queries trace one tree: a wide node over the groups' BVHs
(:func:`hlbvh.kernels.layout.joined`, static group first, so its slots stay cached
while the dynamic group changes), so a ray pays one traversal whatever the number of
groups. :attr:`SceneAccel.last_update` says what the last update did per group (for
per-frame statistics).

``coherent`` is accepted everywhere for signature compatibility; it is a performance
hint of Embree's and :class:`SceneAccel` traces coherent and incoherent rays alike.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from hlbvh.kernels.arrays import concat
from hlbvh.kernels.bvh import BuildConfig
from hlbvh.kernels.layout import joined
from hlbvh.kernels.traversal import any_hit, closest_hit
from hlbvh.mesh_group import MeshGroup
from hlbvh.policy import ACCELS, DECISIONS, split_options
from hlbvh.queries import NativeAccel, _Accel, _checked_scene
from hlbvh.scene_geometry import mesh_buffers, scene_shapes
from hlbvh.timing import clock_ms


class SceneAccel(_Accel):
    """HLBVHs over the triangles of every mesh of a Mitsuba scene, plus the scene's
    analytic shapes, queried with ``mi.Scene``'s own signatures and updated per frame
    as the module docstring says.

    Args:
        scene: the ``mi.Scene`` (JIT variant: LLVM or CUDA).
        **options: options of :func:`hlbvh.build` (``builder``, ``leaf_size``,
            ``morton_bits``, ``quantization``, ``coarse_bits``, ``p``, ``sah_bins``) and
            of the :class:`UpdatePolicy` (``update``, ``refit_tolerance``).
    Raises:
        ValueError: for an unknown or invalid option (naming it), or for a shape this
            accelerator cannot intersect (see the module docstring), naming the shape.

    Attributes:
        shapes: ``scene.shapes()`` when built. The accelerator keeps the shapes, not
            the scene: an integrator that the scene owns can cache it without a
            reference cycle keeping the scene alive.
        shapes_dr: ``scene.shapes_dr()``, where hits find their shape pointer.
        config: the validated :class:`hlbvh.BuildConfig`.
        policy: the validated :class:`UpdatePolicy`.
        meshes: indices of the meshes in ``shapes``.
        analytic: ``(index into shapes, shape)`` of every analytic shape.
        static, dynamic: the two :class:`MeshGroup`.
        last_update: what the last :meth:`update` (or the construction) did:
            ``decision`` (the most work any group did, one of :data:`DECISIONS`),
            ``ms`` (wall time of the whole update), ``triangles``, ``sah_cost`` (of
            both groups together: each group's SAH cost weighted by its root box's
            area over the area of the box around both, the cost of a ray through that
            box when each group is entered through its root box; None without
            triangles), and ``groups``: ``{"static": ..., "dynamic": ...}``, each
            group's :attr:`MeshGroup.last`.
    """

    name = "hlbvh"

    def __init__(self, scene, **options):
        _checked_scene(scene)
        self.policy, self._build_options = split_options(options)
        self.config = BuildConfig.from_options(**self._build_options)
        self.shapes = list(scene.shapes())
        self.shapes_dr = scene.shapes_dr()
        self.meshes, self.analytic = scene_shapes(self.shapes)
        self.static = MeshGroup("static")
        self.dynamic = MeshGroup("dynamic")
        self.last_update = None
        self._buffers = None  # each mesh's buffers at the last update
        self._traced = []  # the groups with triangles, static first
        self._tree = None  # their joined traversal slots (None: no triangles)
        self._prim_shape = self._prim_local = None  # mesh, in-mesh index per face index
        self.update()

    def is_for(self, scene) -> bool:
        """Whether this accelerator was built over ``scene``'s shapes."""
        shapes = scene.shapes()
        return len(shapes) == len(self.shapes) and all(a is b for a, b in zip(shapes, self.shapes))

    def changed(self) -> bool:
        """Whether a mesh got new vertex or face buffers (a ``params.update()`` with
        new values) since the last update, or a group's last build failed."""
        buffers = mesh_buffers(self.shapes, self.meshes)
        return (self.static.stale or self.dynamic.stale
                or any(_new_buffers(buffers[i], self._buffers[i]) for i in self.meshes))

    def update(self):
        """Bring the BVHs up to date with the meshes' buffers; call it after
        ``params.update()`` changed the scene (a call when nothing changed costs a look
        at each mesh's buffers and records ``"kept"``).

        Returns:
            self.
        Raises:
            ValueError: naming a mesh whose positions became non-finite.
        """
        start = clock_ms()
        buffers = mesh_buffers(self.shapes, self.meshes)
        options, policy = self._build_options, self.policy
        if self._buffers is None:
            # ---- First build: every mesh is static until it changes ----
            self.static.indices = self.meshes
            self.static.update(self.shapes, options, policy, reshaped=True, decision="build")
        else:
            changed = [i for i in self.meshes if _new_buffers(buffers[i], self._buffers[i])]
            # ---- Meshes changing for the first time leave the static group ----
            moved = [i for i in changed if i in self.static.indices]
            self.static.indices = tuple(i for i in self.static.indices if i not in moved)
            self.dynamic.indices = tuple(sorted(self.dynamic.indices + tuple(moved)))
            # ---- Each group follows its meshes (a stale group: after a failed build) ----
            if self.static.stale:
                # Built once for every frame to come: with the static builder.
                self.static.update(self.shapes, policy.static_options(options), policy,
                                   reshaped=True)
            else:
                self.static.keep()
            if changed or self.dynamic.stale:
                reshaped = any(_reshaped(buffers[i], self._buffers[i]) for i in changed)
                self.dynamic.update(self.shapes, options, policy, reshaped)
            else:
                self.dynamic.keep()
        self._buffers = buffers  # only once every group is up to date
        traced = [g for g in (self.static, self.dynamic) if g.bvh is not None]
        if traced != self._traced or any(g.last["decision"] != "kept" for g in traced):
            self._join(traced)
        self.last_update = dict(
            decision=max((g.last["decision"] for g in (self.static, self.dynamic)),
                         key=DECISIONS.index),
            ms=clock_ms() - start,
            triangles=self.static.triangles + self.dynamic.triangles,
            sah_cost=self._sah_cost(),
            groups={g.name: dict(g.last) for g in (self.static, self.dynamic)},
        )
        return self

    def _join(self, traced):
        """One tree over the groups' BVHs (static first: its slots stay cached while
        the dynamic group changes), packed now, not inside some integrator's symbolic
        loop, and the mesh and in-mesh index of each of its face indices."""
        self._traced = traced
        self._tree = joined([g.bvh for g in traced]) if traced else None
        self._prim_shape = concat([g.geometry.prim_shape for g in traced]) if traced else None
        self._prim_local = concat([g.geometry.prim_local for g in traced]) if traced else None

    def _sah_cost(self):
        """SAH cost of both groups together (see :attr:`last_update`)."""
        if len(self._traced) < 2:
            return float(self._traced[0].bvh.stats.sah_cost) if self._traced else None
        boxes = [g.root_box() for g in self._traced]
        union = _half_area([min(lo[k] for lo, _ in boxes) for k in range(3)],
                           [max(hi[k] for _, hi in boxes) for k in range(3)])
        return sum((_half_area(*box) / union if union > 0 else 1.0) * g.bvh.stats.sah_cost
                   for g, box in zip(self._traced, boxes))

    def _preliminary(self, ray, coherent, active, reorder):
        """The groups' closest triangle hit, then each analytic shape's own routine,
        merged by nearest ``t``; ``coherent`` and ``reorder`` change nothing here."""
        n = dr.width(ray)
        active = mi.Bool(active) & dr.full(mi.Bool, True, n)
        t, prim_uv, prim_index, shape_index = self._closest_mesh_hit(ray, active)
        for index, shape in self.analytic:
            pi_s = shape.ray_intersect_preliminary(ray, 0, active)
            closer = pi_s.is_valid() & (pi_s.t < t)
            t = dr.select(closer, pi_s.t, t)
            prim_uv = dr.select(closer, pi_s.prim_uv, prim_uv)
            prim_index = dr.select(closer, pi_s.prim_index, prim_index)
            shape_index = dr.select(closer, index, shape_index)
        pi = dr.zeros(mi.PreliminaryIntersection3f, n)
        pi.valid = active & (t < dr.inf)
        pi.t = dr.select(pi.valid, t, dr.inf)
        pi.prim_uv = mi.Point2f(prim_uv)
        pi.prim_index = dr.select(pi.valid, prim_index, 0)
        pi.shape_index = dr.select(pi.valid, shape_index, 0xFFFFFFFF)
        if dr.width(self.shapes_dr) > 0:  # a scene may have no shape at all
            pi.shape = dr.gather(mi.ShapePtr, self.shapes_dr, pi.shape_index, pi.valid)
        return pi

    def _closest_mesh_hit(self, ray, active):
        """(t, prim_uv, prim_index, shape_index) of the closest triangle hit of the
        groups' joined tree; t infinite where there is none."""
        n = dr.width(ray)
        if self._tree is None:
            return (dr.full(mi.Float, dr.inf, n), dr.zeros(mi.Point2f, n),
                    dr.zeros(mi.UInt32, n), dr.zeros(mi.UInt32, n))
        t, u, v, prim, valid = closest_hit(self._tree, ray.o, ray.d, ray.maxt, active)
        valid = mi.Bool(valid)
        return (dr.select(valid, mi.Float(t), dr.inf), mi.Point2f(mi.Float(u), mi.Float(v)),
                dr.gather(mi.UInt32, self._prim_local, mi.UInt32(prim), valid),
                dr.gather(mi.UInt32, self._prim_shape, mi.UInt32(prim), valid))

    def _test(self, ray, coherent, active):
        active = mi.Bool(active) & dr.full(mi.Bool, True, dr.width(ray))
        hit = dr.zeros(mi.Bool, dr.width(ray))
        if self._tree is not None:
            hit |= mi.Bool(any_hit(self._tree, ray.o, ray.d, ray.maxt, active))
        for _, shape in self.analytic:
            hit |= shape.ray_test(ray, active & ~hit)
        return hit & active


def _half_area(lo, hi) -> float:
    """Half the surface area of the box ``lo``..``hi`` (Python floats: double
    precision, as the SAH cost's areas)."""
    e = [max(h - l, 0.0) for l, h in zip(lo, hi)]
    return e[0] * e[1] + e[1] * e[2] + e[2] * e[0]


def _new_buffers(now: tuple, before: tuple) -> bool:
    """Whether a mesh's (vertex, face) buffers are other variables than before."""
    return now[0].index != before[0].index or now[1].index != before[1].index


def _reshaped(now: tuple, before: tuple) -> bool:
    """Whether a mesh's faces or vertex count changed (a refit cannot follow)."""
    return now[1].index != before[1].index or dr.width(now[0]) != dr.width(before[0])


def make_accel(scene, accel: str = "hlbvh", **options):
    """The intersector named ``accel`` for ``scene``.

    Args:
        scene: the ``mi.Scene``.
        accel: ``"hlbvh"`` (:class:`SceneAccel`) or ``"native"`` (:class:`NativeAccel`).
        **options: :func:`hlbvh.build` and :class:`UpdatePolicy` options, validated in
            both cases (so a typo is caught even while rendering natively) and used by
            ``"hlbvh"``.
    Raises:
        ValueError: for any other ``accel``, or an unknown or invalid option.
    """
    _checked_scene(scene)
    if accel == "hlbvh":
        return SceneAccel(scene, **options)
    if accel == "native":
        split_options(options)
        return NativeAccel(scene)
    raise ValueError(f"accel={accel!r}: expected one of {ACCELS}")
