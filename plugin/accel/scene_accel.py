"""The intersectors our integrators trace through: :class:`SceneAccel` (only what moves
through our HLBVHs, the rest through the scene's own accelerator, or everything
through ours) and :class:`NativeAccel` (the scene's own accelerator, Embree on the
LLVM backend, OptiX on CUDA), behind the same three methods as ``mi.Scene``.

Mitsuba 3 does not let Python supply the intersection routine of its native
accelerator, so the integration point is the integrator: every ray query of our
integrators goes to one of these objects, and a hit comes back as a
``mi.PreliminaryIntersection3f`` whose ``t``/``prim_uv``/``prim_index``/``shape``/
``shape_index``/``instance`` are exactly what Mitsuba's own query would have produced,
so that ``compute_surface_interaction`` (Mitsuba's code) fills in the surface
interaction.

Groups by motion
----------------
Every shape starts *static*; a shape is *moving* once it was declared so (option
``moving``, ids; the animations of :mod:`hlbvh.scenes` declare their animated shapes)
or once it changed (see :mod:`hlbvh.accel.motion`). Then it stays moving.

* ``static="native"`` (default): the static shapes, of any type Mitsuba intersects
  (meshes, analytic shapes, instances, curves, SDF grids, ellipsoids), are traced by
  Mitsuba's own accelerator over a sub-scene of those shapes
  (:class:`hlbvh.accel.native_group.NativeGroup`), built on the first update and rebuilt
  only when a shape leaves it (``last_update["groups"]["static"]["left"]`` names it).
  Moving meshes are in the dynamic :class:`MeshGroup`'s HLBVH; moving ``sphere``,
  ``disk`` and ``cylinder`` shapes are intersected by their own routine
  (``shape.ray_intersect_preliminary``, once per shape: a call through a shape
  pointer inside a symbolic loop would trace every registered shape); moving instances
  go through our two-level hierarchy (:class:`hlbvh.accel.instance_group.InstanceGroup`: their
  groups' BVHs built once, the top level rebuilt when one moves); any other shape that
  moves is refused with a ``ValueError`` naming it.
* ``static="hlbvh"``: every mesh in our BVHs (the static :class:`MeshGroup`, built
  once with the static builder, and the dynamic one), traced by our watertight
  traversal; the analytic shapes by their own routine; instances, curves, SDF grids
  and ellipsoids are refused, naming the shape.

A query asks each structure and keeps the nearest hit. Ties (the same ``t`` from two
structures) go to the structure asked first: the static one, then the dynamic meshes,
then the analytic shapes in scene order; ``ray_test`` stops asking once a ray is
occluded.

Meshes without triangles are refused, naming the shape: Mitsuba's own ``obj`` and
``ply`` loaders refuse a file without faces, so such a mesh comes from Python code
(``mi.Mesh(name, 0, 0)``) or a ``params.update()`` that emptied it, where it is more
likely a mistake than an intent. A scene without geometry is valid: every ray misses.

Per-frame update
----------------
:meth:`SceneAccel.update` (after the scene changed: ``params.update()``, or
:func:`hlbvh.traverse`'s cheaper update) brings the groups up to date, doing only what
the scene requires: the dynamic group is refit or rebuilt as the
:class:`UpdatePolicy` says (``update="auto"``, the default: refit while the tree's SAH
cost stays within ``refit_tolerance`` of its last build's, rebuilt otherwise;
``"rebuild"``, with the CSD sort seeded by last frame's order where that pays;
``"fresh"``; ``"refit"``); new faces, a changed vertex count or a change of its meshes
always rebuild. A query on an accelerator whose meshes changed since its last update
is refused (naming the mesh): it would answer from old geometry.
:attr:`SceneAccel.last_update` says what the last update did per group.

``coherent`` is passed on to Mitsuba's accelerator (a hint of Embree's); our traversal
traces coherent and incoherent rays alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from hlbvh.kernels.arrays import concat
from hlbvh.kernels.bvh import BuildConfig
from hlbvh.kernels.geometry import half_area
from hlbvh.kernels.layout import joined
from hlbvh.kernels.traversal import any_hit, closest_hit
from hlbvh.accel.choice import STRUCTURES, CostModel, Probe, RayBudget
from hlbvh.accel.instance_group import InstanceGroup, group_of
from hlbvh.accel.instance_shading import InstanceShading, is_instance
from hlbvh.kernels.traversal import closest_instance_hit
from hlbvh.accel.mesh_group import MeshGroup
from hlbvh.accel.motion import MeshState, shape_states
from hlbvh.accel.native_group import NativeGroup, shape_groups
from hlbvh.accel.policy import ACCELS, DECISIONS, UpdatePolicy, split_options
from hlbvh.accel.queries import NativeAccel, SceneQueries as _Accel, checked_scene as _checked_scene
from hlbvh.accel.scene_geometry import describe_shape as _describe, scene_shapes, unmovable_error
from hlbvh.timing import clock_ms


class SceneAccel(_Accel):
    """The ray queries of a Mitsuba scene, with ``mi.Scene``'s own signatures, over
    the groups the module docstring describes, updated per frame.

    Args:
        scene: the ``mi.Scene`` (JIT variant: LLVM or CUDA).
        policy, config: the :class:`UpdatePolicy` and :class:`hlbvh.BuildConfig`, for
            a caller that parsed its options already (:func:`split_options`);
            otherwise from ``options``.
        **options: options of :func:`hlbvh.build` (``builder``, ``leaf_size``,
            ``morton_bits``, ``quantization``, ``coarse_bits``, ``p``, ``sah_bins``) and
            of the :class:`UpdatePolicy` (``static``, ``moving``, ``update``,
            ``refit_tolerance``, ``static_builder``, ``static_leaf_size``).
    Raises:
        ValueError: for an unknown or invalid option (naming it), an id in ``moving``
            that names no shape of the scene, or a shape this accelerator cannot
            intersect (see the module docstring), naming the shape.

    Attributes:
        shapes: ``scene.shapes()`` when built. The accelerator keeps the shapes, not
            the scene: an integrator that the scene owns can cache it without a
            reference cycle keeping the scene alive.
        shapes_dr: ``scene.shapes_dr()``, where hits find their shape pointer.
        config: the validated :class:`hlbvh.BuildConfig`.
        policy: the validated :class:`UpdatePolicy`.
        meshes: indices of the meshes in ``shapes``.
        analytic: ``(index into shapes, shape)`` of every analytic shape.
        moving: indices into ``shapes`` of the shapes that move, ascending.
        static: the static group: a :class:`NativeGroup` (``static="native"``) or a
            :class:`MeshGroup` (``static="hlbvh"``).
        dynamic: the moving meshes' :class:`MeshGroup` (our HLBVH over them).
        native_moving: the moving meshes' :class:`NativeGroup` (a Mitsuba sub-scene of
            them, built anew when they moved).
        moving_structure: what traces the moving meshes now: ``"hlbvh"`` (:attr:`dynamic`),
            ``"native"`` (:attr:`native_moving`) or ``"scene"`` (the whole scene through
            Mitsuba's own accelerator, which the integrator then queries instead of this
            object); forced by ``moving_accel`` or chosen per render by :meth:`plan`.
        costs: the :class:`hlbvh.accel.choice.CostModel` that chooses it.
        instances: the moving instances' :class:`InstanceGroup` (``static="native"``;
            None with ``"hlbvh"``).
        last_update: what the last :meth:`update` (or the construction) did:
            ``decision`` (the most work any group did, one of :data:`DECISIONS`),
            ``ms`` (wall time of the whole update), ``triangles``, ``sah_cost`` (of the
            groups our BVHs trace together: each group's SAH cost weighted by its root
            box's area over the area of the box around them, the cost of a ray through
            that box when each group is entered through its root box; None without
            triangles in our BVHs), ``moving`` (ids of the moving shapes), and
            ``groups``: ``{"static": ..., "dynamic": ..., "native_moving": ...}``, each
            group's ``last``; ``moving_accel``: ``chosen`` (:attr:`moving_structure`),
            ``estimates_ms`` (each structure's estimated frame at the last :meth:`plan`,
            None before one), ``update_ms`` and ``query_ns`` (the measured costs) and
            ``queries_per_sample``.
    """

    name = "hlbvh"

    def __init__(self, scene, *, policy: UpdatePolicy | None = None,
                 config: BuildConfig | None = None, **options):
        _checked_scene(scene)
        if policy is None or config is None:
            policy, config = split_options(options)
        elif options:
            raise TypeError("SceneAccel: pass policy and config, or options, not both")
        self.policy, self.config = policy, config
        self.shapes = list(scene.shapes())
        self.shapes_dr = scene.shapes_dr()
        native = self.policy.static == "native"
        self.meshes, self.analytic, others = scene_shapes(self.shapes, self.policy.static)
        self._others = set(others)  # shapes our BVHs do not intersect
        self.moving = _declared(self.shapes, self.policy.moving)
        groups = shape_groups(scene) if native else []
        self.static = NativeGroup(groups) if native else MeshGroup("static")
        self.dynamic = MeshGroup("dynamic")
        self.native_moving = NativeGroup([], name="native_moving")
        forced = policy.moving_accel
        if forced == "native" and not native_moving_possible():
            raise ValueError(
                "moving_accel='native': a second Mitsuba scene traced in the same kernel as "
                "the still world's is refused by OptiX on CUDA; use 'scene', 'hlbvh' or "
                "'auto' there")
        self.moving_structure = forced if forced in ("native", "scene") else "hlbvh"
        self.costs = CostModel()
        self._estimates = None  # each structure's estimated frame at the last plan()
        # Structures whose view of the moving meshes is out of date: the scene's own
        # accelerator may predate writes made before this accelerator existed.
        self._behind = {"scene"}
        self._probed = False  # whether the query costs were measured
        known = {}  # id(instance) -> its shape group, told once for both uses

        def told(instance, matrix=None):
            if id(instance) not in known:
                known[id(instance)] = group_of(instance, groups, matrix=matrix)
            return known[id(instance)]

        self.instances = InstanceGroup(groups, config, told) if native else None
        self.shading = (InstanceShading(self.shapes, told)
                        if native and any(is_instance(s) for s in self.shapes) else None)
        for i in self.moving:
            self._check_movable(i)
        self.last_update = None
        self._handles = {}  # each shape's parameter handles (hlbvh.accel.motion)
        self._states = None  # each shape's state at the last update
        self._current = False  # whether the last update succeeded
        self._traced = []  # the mesh groups with triangles our BVHs trace, static first
        self._tree = None  # their joined traversal slots (None: no triangles)
        self._prim_shape = self._prim_local = None  # mesh, in-mesh index per face index
        self.update()

    def is_for(self, scene) -> bool:
        """Whether this accelerator was built over ``scene``'s shapes."""
        shapes = scene.shapes()
        return len(shapes) == len(self.shapes) and all(a is b for a, b in zip(shapes, self.shapes))

    def changed(self) -> bool:
        """Whether a shape changed (a ``params.update()`` with new values) since the
        last update, or a group's last build failed."""
        states = shape_states(self.shapes, range(len(self.shapes)), self._handles)
        return self._stale_groups() or any(
            states[i].moved(self._states[i]) for i in range(len(self.shapes)))

    def update(self):
        """Bring the groups up to date with the scene's shapes; call it after the scene
        changed (a call when nothing changed costs a look at each shape, see
        :mod:`hlbvh.accel.motion`, and records ``"kept"``).

        Returns:
            self.
        Raises:
            ValueError: naming a mesh whose positions became non-finite or whose faces
                were emptied, or a shape that moved but cannot be traced moving. The
                accelerator is then left as it was, and refuses queries until an
                update succeeds.
        """
        start = clock_ms()
        self._current = False  # until every group is up to date
        states = shape_states(self.shapes, range(len(self.shapes)), self._handles)
        first = self._states is None
        changed = [] if first else [i for i in states if states[i].moved(self._states[i])]
        # ---- Shapes that changed for the first time start moving ----
        started = sorted(set(changed) - set(self.moving))
        for i in changed:
            self._check_movable(i)
        moving = tuple(sorted(self.moving + tuple(started)))
        # ---- The static group: everything that never moved ----
        self._update_static(moving, started, first)
        self.moving = moving
        # ---- The moving meshes, in the structure that traces them now ----
        meshes = set(self.meshes)
        self.dynamic.indices = tuple(i for i in moving if i in meshes)
        dynamic_changed = [i for i in changed if i in self.dynamic.indices]
        structure = self.moving_structure
        if dynamic_changed or started:  # the structures not updated below fall behind
            self._behind |= {"hlbvh", "native"} - {structure}
        if changed:
            self._behind.add("scene")
        if structure == "hlbvh":
            self._update_dynamic(states, dynamic_changed, first)
        else:
            self.dynamic.keep()
        if structure == "native":
            self._update_native_moving(moved=bool(dynamic_changed or started))
        else:
            self.native_moving.keep()
        # ---- The moving instances: the top level over them ----
        if self.shading is not None:
            self.shading.refresh([i for i in changed if is_instance(self.shapes[i])])
        moving_instances = tuple(i for i in moving if is_instance(self.shapes[i]))
        if not set(moving_instances).isdisjoint(changed):
            self._behind.add("instances")
        if self.instances is not None and structure != "scene":
            table = self.shading if self.shading is not None and self.shading.usable else None
            self.instances.update(self.shapes, moving_instances,
                                  moved="instances" in self._behind,
                                  rows_of=table.rows_of if table else None,
                                  policy=self.policy)
            self._behind.discard("instances")
        elif self.instances is not None:
            self.instances.keep()
        self._states, self._current = states, True
        traced = [g for g in (self.static, self.dynamic) if isinstance(g, MeshGroup) and g.bvh
                  and (g is not self.dynamic or structure == "hlbvh")]
        if traced != self._traced or any(g.last["decision"] != "kept" for g in traced):
            self._join(traced)
        groups = (self.static, self.dynamic, self.native_moving) + (
            (self.instances,) if self.instances else ())
        self.last_update = dict(
            decision=max((g.last["decision"] for g in groups), key=DECISIONS.index),
            ms=clock_ms() - start,
            triangles=self.static.triangles + self.dynamic.triangles,
            sah_cost=self._sah_cost(),
            moving=[self.shapes[i].id() for i in self.moving],
            groups={g.name: dict(g.last) for g in groups},
            moving_accel=self._choice_record(),
        )
        return self

    # ---- What traces the moving meshes: the choice by cost (hlbvh.accel.choice) ----

    def _update_dynamic(self, states, changed: list, first: bool):
        """Our HLBVH over the moving meshes, refit or rebuilt as the policy says (rebuilt
        when it fell behind while another structure traced them)."""
        behind = "hlbvh" in self._behind
        if (first and self.dynamic.indices) or changed or self.dynamic.stale or behind:
            reshaped = first or behind or any(
                states[i].reshaped(self._states[i]) for i in changed)
            self.dynamic.update(self.shapes, self.config, self.policy, reshaped,
                                decision="build" if first else "rebuild")
            if self.dynamic.indices and not first and not behind:
                # a frame's update as the policy makes it (not a first or catch-up build)
                self.costs.record_update("hlbvh", self.dynamic.last["ms"])
            elif self.dynamic.indices and "hlbvh" not in self.costs.update_ms:
                self.costs.record_update("hlbvh", self.dynamic.last["ms"])
        else:
            self.dynamic.keep()
        self._behind.discard("hlbvh")

    def _update_native_moving(self, moved: bool = False):
        """The Mitsuba sub-scene of the moving meshes, built anew when they ``moved`` (or
        moved while another structure traced them)."""
        self.native_moving.update(self.shapes, self.dynamic.indices,
                                  moved=moved or "native" in self._behind)
        if self.native_moving.last["decision"] != "kept" and self.dynamic.indices:
            self.costs.record_update("native", self.native_moving.last["ms"])
        self._behind.discard("native")

    def _allowed(self) -> tuple:
        """The structures ``moving_accel`` lets :meth:`plan` choose among (on CUDA not the
        native moving group: see :func:`native_moving_possible`)."""
        forced = self.policy.moving_accel
        if forced != "auto":
            return (forced,)
        if not isinstance(self.static, NativeGroup):
            return ("hlbvh",)
        return STRUCTURES if native_moving_possible() else ("hlbvh", "scene")

    def plan(self, budget: RayBudget, probe: Probe | None = None) -> str:
        """Choose what traces the moving meshes for a render of ``budget`` (the
        integrator calls this after :meth:`update`, and updates again when the choice
        moved), by the measured costs of :mod:`hlbvh.accel.choice`; ``probe`` (a sample
        of the render's own rays) times each structure's queries when they were not
        timed yet. Returns :attr:`moving_structure`."""
        allowed = self._allowed()
        if len(allowed) == 1 or not self.dynamic.indices:
            self.moving_structure = allowed[0] if len(allowed) == 1 else self.moving_structure
            return self.moving_structure
        if not self._probed and probe is not None:
            self.probe(probe)
        triangles = {"native": sum(self.shapes[i].face_count() for i in self.dynamic.indices),
                     "scene": sum(s.face_count() for s in self.shapes if s.is_mesh())}
        self.moving_structure, self._estimates = self.costs.choose(
            budget, self.moving_structure, allowed, triangles)
        return self.moving_structure

    def probe(self, probe: Probe):
        """Time the closest-hit queries of ``probe``'s rays through the still world alone
        and through it with each structure of the moving meshes (ours and the native
        sub-scene, each brought up to date first), and record them and the probe's hit
        fractions in :attr:`costs`."""
        if not self._current or not isinstance(self.static, NativeGroup):
            return
        ray = probe.rays
        self.costs.hit_fractions = (probe.camera_hits, probe.bounce_hits)
        current = self.moving_structure
        self.costs.record_build_rate(self.static.build_ms, self.static.triangles)
        for structure in [s for s in ("hlbvh", "native") if s in self._allowed()]:
            self.moving_structure = structure
            if structure == "hlbvh" and ("hlbvh" in self._behind or self.dynamic.bvh is None):
                self._update_dynamic(self._states, [], False)
            if structure == "native":
                self._update_native_moving()
            self._join([g for g in (self.dynamic,) if g.bvh is not None and structure == "hlbvh"])
            self.costs.record_queries(structure, query_ns(self.ray_intersect_preliminary, ray))
        self.moving_structure = "still"
        self._join([])
        self.costs.record_queries("still", query_ns(self.ray_intersect_preliminary, ray))
        self.moving_structure = current
        self._join([self.dynamic] if current == "hlbvh" and self.dynamic.bvh is not None else [])
        self._probed = True

    def record_render(self, ms: float, samples: int):
        """A render of ``samples`` samples through :attr:`moving_structure` took ``ms``
        (the integrator times its renders; the costs learn from them)."""
        self.costs.record_render(self.moving_structure, ms, samples)

    def scene_rebuilt(self, ms: float, ns: float | None = None):
        """The integrator rebuilt the whole scene's own accelerator (``"scene"``) in
        ``ms``; ``ns``: the time of a query through it, when the integrator timed one."""
        self.costs.record_update("scene", ms)
        self._behind.discard("scene")
        if ns is not None:
            self.costs.record_queries("scene", ns)

    def absorb(self, earlier: dict):
        """Make :attr:`last_update` tell what ``earlier`` (the update just before it, in
        the same frame: before :meth:`plan` moved the choice) did too: the most work of
        both, their time together, and each group's record of the one that did more."""
        now = self.last_update
        rank = DECISIONS.index
        now["decision"] = max(now["decision"], earlier["decision"], key=rank)
        now["ms"] += earlier["ms"]
        for name, group in earlier["groups"].items():
            if rank(group["decision"]) > rank(now["groups"][name]["decision"]):
                now["groups"][name] = group

    def mark_moving_dirty(self):
        """Tell the moving shapes that they changed, so that the scene's next
        ``parameters_changed`` rebuilds its own accelerator over them: a Mitsuba
        (sub-)scene built over a shape since it last changed (the moving meshes' native
        group) has already cleared the mark its change left. A mesh is told its
        positions and normals changed (so it keeps the normals it was given)."""
        for i in self.moving:
            shape = self.shapes[i]
            shape.parameters_changed(["vertex_positions", "vertex_normals"]
                                     if shape.is_mesh() else [])

    @property
    def needs_probe(self) -> bool:
        """Whether :meth:`plan` would still time the structures (``moving_accel="auto"``
        with moving meshes, and no probe yet)."""
        return not self._probed and len(self._allowed()) > 1 and bool(self.dynamic.indices)

    @property
    def scene_behind(self) -> bool:
        """Whether the scene's own accelerator misses motion since its last rebuild (the
        ``"scene"`` structure: a rebuild is due before it is queried)."""
        return "scene" in self._behind

    def _choice_record(self) -> dict:
        return dict(chosen=self.moving_structure, estimates_ms=self._estimates,
                    update_ms=dict(self.costs.update_ms), query_ns=dict(self.costs.query_ns),
                    hit_fractions=self.costs.hit_fractions)

    def surface_interaction(self, pi, ray, ray_flags=mi.RayFlags.All, active=True):
        """``pi.compute_surface_interaction(ray, ray_flags, active)``; in a scene with
        instances, expanded without Mitsuba's call through a shape pointer, whose kernel
        grows with the number of instances (:mod:`hlbvh.accel.instance_shading`)."""
        if self.shading is None:
            return pi.compute_surface_interaction(ray, ray_flags, active)
        return self.shading.surface_interaction(pi, ray, ray_flags, active)

    def _check_movable(self, i: int):
        """Refuse a change this accelerator cannot follow: a shape that cannot be traced
        moving (instances can, with ``static="native"``), or a mesh whose faces were
        emptied."""
        shape = self.shapes[i]
        if i in self._others and not (self.instances is not None and is_instance(shape)):
            raise unmovable_error(shape)
        if shape.is_mesh() and shape.face_count() == 0:
            raise ValueError(f"{_describe(shape)} has no triangles any more: it would "
                             "silently be missing from the image; give it faces")

    def _update_static(self, moving: tuple, started: list, first: bool):
        """The static group over every shape (``"native"``) or mesh (``"hlbvh"``) not in
        ``moving``; ``started``: the shapes that just started moving."""
        if isinstance(self.static, NativeGroup):
            moving = set(moving)
            still = tuple(i for i in range(len(self.shapes)) if i not in moving)
            self.static.update(self.shapes, still, [self.shapes[i].id() for i in started])
            return
        moving = set(moving)
        self.static.indices = tuple(i for i in self.meshes if i not in moving)
        if first or self.static.stale:
            # Built once for every frame to come: with the static builder, unless no
            # shape was declared moving (the accelerator's first tree over everything).
            config = (self.config if first and not self.moving
                      else self.policy.static_config(self.config))
            self.static.update(self.shapes, config, self.policy, reshaped=True,
                               decision="build" if first else "rebuild")
        else:
            self.static.keep()

    def _stale_groups(self) -> bool:
        return any(g.stale for g in (self.static, self.dynamic)) \
            or (self.instances is not None and self.instances.stale)

    def _check_current(self):
        """Refuse a query after a failed update, or when a mesh or a shape group's shape
        changed since the last update (the trees hold its old geometry), naming the
        mesh. Looks at the meshes' buffers and the groups' shapes only: a look at every
        shape would cost a traversal per query."""
        if not self._current:
            raise RuntimeError("SceneAccel: its last update() failed (see the error it "
                               "raised); fix the scene and call update() before tracing")
        if self.moving_structure == "scene":
            raise RuntimeError("SceneAccel: the whole scene traces the moving meshes "
                               "(moving_accel 'scene'): query the scene itself, as the "
                               "integrator does, after its accelerator was rebuilt")
        for i in self.meshes:
            shape = self.shapes[i]
            if MeshState(shape.vertex_positions_buffer(), shape.faces_buffer()).moved(
                    self._states[i]):
                raise RuntimeError(
                    f"SceneAccel: {_describe(shape)} changed since the accelerator's last "
                    "update(); call update() before tracing (it would answer from the old "
                    "geometry)")
        if self.static.stale or (self.instances is not None and self.instances.stale):
            raise RuntimeError(
                "SceneAccel: a shape group's shapes changed since the accelerator's last "
                "update(); call update() before tracing (it would answer from the old "
                "geometry)")

    def _join(self, traced):
        """One tree over our groups' BVHs (static first: its slots stay cached while
        the dynamic group changes), packed now, not inside some integrator's symbolic
        loop, and the mesh and in-mesh index of each of its face indices."""
        self._traced = traced
        self._tree = joined([g.bvh for g in traced]) if traced else None
        self._prim_shape = concat([g.geometry.prim_shape for g in traced]) if traced else None
        self._prim_local = concat([g.geometry.prim_local for g in traced]) if traced else None

    def _sah_cost(self):
        """SAH cost of our groups together (see :attr:`last_update`)."""
        if len(self._traced) < 2:
            return float(self._traced[0].bvh.stats.sah_cost) if self._traced else None
        boxes = [g.root_box() for g in self._traced]
        union = _half_area([min(lo[k] for lo, _ in boxes) for k in range(3)],
                           [max(hi[k] for _, hi in boxes) for k in range(3)])
        return sum((_half_area(*box) / union if union > 0 else 1.0) * g.bvh.stats.sah_cost
                   for g, box in zip(self._traced, boxes))

    def _routine_shapes(self):
        """``(index, shape)`` of the analytic shapes traced by their own routine: all of
        them with ``static="hlbvh"``, the moving ones with ``"native"``."""
        if isinstance(self.static, NativeGroup):
            return [(i, s) for i, s in self.analytic if i in self.moving]
        return self.analytic

    def _preliminary(self, ray, coherent, active, reorder):
        """The static group's closest hit, then the moving meshes' (our BVHs' or their
        native sub-scene's), then the instances', then each analytic shape's own
        routine, merged by nearest ``t`` (ties to the earlier)."""
        self._check_current()
        n = dr.width(ray)
        active = mi.Bool(active) & dr.full(mi.Bool, True, n)
        hit = _Hit.none(n)
        native = isinstance(self.static, NativeGroup) and self.static.scene is not None
        if native:
            hit.take_native(self.static.preliminary(ray, coherent, active, reorder))
        # Each later structure looks no further than the nearest hit so far.
        ray = mi.Ray3f(ray)
        if self._tree is not None:
            ray.maxt = dr.minimum(ray.maxt, hit.t)
            hit.take(*self._closest_mesh_hit(ray, active))
        if self.moving_structure == "native" and self.native_moving.scene is not None:
            ray.maxt = dr.minimum(ray.maxt, hit.t)
            hit.take_native(self.native_moving.preliminary(ray, coherent, active, reorder))
        if self.instances is not None and self.instances.tree is not None:
            ray.maxt = dr.minimum(ray.maxt, hit.t)
            t_i, u_i, v_i, prim_i, inst_i, valid_i = closest_instance_hit(
                self.instances.tree, ray.o, ray.d, ray.maxt, active)
            valid_i = mi.Bool(valid_i)
            local, in_group, inst_index = self.instances.hit_fields(
                mi.UInt32(prim_i), mi.UInt32(inst_i), valid_i)
            hit.take(dr.select(valid_i, mi.Float(t_i), dr.inf),
                     mi.Point2f(mi.Float(u_i), mi.Float(v_i)), local, in_group,
                     instance=inst_index)
        for index, shape in self._routine_shapes():
            ray.maxt = dr.minimum(ray.maxt, hit.t)
            pi_s = shape.ray_intersect_preliminary(ray, 0, active)
            hit.take(dr.select(pi_s.is_valid(), pi_s.t, dr.inf), pi_s.prim_uv,
                     pi_s.prim_index, dr.full(mi.UInt32, index, n))
        return hit.preliminary(active, self.shapes_dr)

    def _closest_mesh_hit(self, ray, active):
        """(t, prim_uv, prim_index, shape_index) of the closest triangle hit of our
        groups' joined tree; t infinite where there is none."""
        t, u, v, prim, valid = closest_hit(self._tree, ray.o, ray.d, ray.maxt, active)
        valid = mi.Bool(valid)
        return (dr.select(valid, mi.Float(t), dr.inf), mi.Point2f(mi.Float(u), mi.Float(v)),
                dr.gather(mi.UInt32, self._prim_local, mi.UInt32(prim), valid),
                dr.gather(mi.UInt32, self._prim_shape, mi.UInt32(prim), valid))

    def _test(self, ray, coherent, active):
        self._check_current()
        active = mi.Bool(active) & dr.full(mi.Bool, True, dr.width(ray))
        hit = dr.zeros(mi.Bool, dr.width(ray))
        if isinstance(self.static, NativeGroup) and self.static.scene is not None:
            hit |= self.static.test(ray, coherent, active)
        if self._tree is not None:
            hit |= mi.Bool(any_hit(self._tree, ray.o, ray.d, ray.maxt, active & ~hit))
        if self.moving_structure == "native" and self.native_moving.scene is not None:
            hit |= self.native_moving.test(ray, coherent, active & ~hit)
        if self.instances is not None and self.instances.tree is not None:
            hit |= mi.Bool(any_hit(self.instances.tree, ray.o, ray.d, ray.maxt, active & ~hit))
        for _, shape in self._routine_shapes():
            hit |= shape.ray_test(ray, active & ~hit)
        return hit & active


@dataclass
class _Hit:
    """The nearest hit so far of a query over several structures, as Mitsuba reports
    it: ``t`` (infinite: none), ``prim_uv``, ``prim_index``, ``shape_index``; where a
    Mitsuba (sub-)scene gave it, its ``shape`` and ``instance`` pointers
    (``from_native``); inside one of our instances, the instance's index into
    ``scene.shapes()`` (``instance``, where ``in_instance``)."""

    t: mi.Float
    prim_uv: mi.Point2f
    prim_index: mi.UInt32
    shape_index: mi.UInt32
    from_native: mi.Bool
    shape: mi.ShapePtr
    instance_ptr: mi.ShapePtr
    in_instance: mi.Bool
    instance: mi.UInt32

    @classmethod
    def none(cls, n: int) -> "_Hit":
        return cls(dr.full(mi.Float, dr.inf, n), dr.zeros(mi.Point2f, n),
                   dr.zeros(mi.UInt32, n), dr.zeros(mi.UInt32, n), dr.zeros(mi.Bool, n),
                   dr.zeros(mi.ShapePtr, n), dr.zeros(mi.ShapePtr, n),
                   dr.zeros(mi.Bool, n), dr.zeros(mi.UInt32, n))

    def take(self, t, prim_uv, prim_index, shape_index, instance=None) -> mi.Bool:
        """Take the hit of one more structure (``t`` infinite where it has none) where
        it is strictly nearer, so ties keep the earlier; ``instance``: for a hit inside
        one of our instances, the instance's index. Returns where it was taken."""
        closer = t < self.t
        self.t = dr.select(closer, t, self.t)
        self.prim_uv = dr.select(closer, mi.Point2f(prim_uv), self.prim_uv)
        self.prim_index = dr.select(closer, prim_index, self.prim_index)
        self.shape_index = dr.select(closer, shape_index, self.shape_index)
        self.from_native &= ~closer
        inside = closer & (instance is not None)
        self.in_instance = dr.select(closer, inside, self.in_instance)
        if instance is not None:
            self.instance = dr.select(closer, instance, self.instance)
        return closer

    def take_native(self, pi: mi.PreliminaryIntersection3f):
        """Take a Mitsuba (sub-)scene's hit (its ``shape_index`` already the index
        into ``scene.shapes()`` for a hit outside an instance), pointers included."""
        closer = self.take(dr.select(pi.is_valid(), pi.t, dr.inf), pi.prim_uv,
                           pi.prim_index, pi.shape_index)
        self.from_native |= closer
        self.shape = dr.select(closer, pi.shape, self.shape)
        self.instance_ptr = dr.select(closer, pi.instance, self.instance_ptr)

    def preliminary(self, active: mi.Bool, shapes_dr) -> mi.PreliminaryIntersection3f:
        """The hit as Mitsuba's query reports it: shape pointers gathered for our own
        hits, a hit inside one of our instances with no shape pointer, the shape's index
        in its group, and the instance."""
        n = dr.width(self.t)
        result = dr.zeros(mi.PreliminaryIntersection3f, n)
        result.valid = active & (self.t < dr.inf)
        result.t = dr.select(result.valid, self.t, dr.inf)
        result.prim_uv = mi.Point2f(self.prim_uv)
        result.prim_index = dr.select(result.valid, self.prim_index, 0)
        result.shape_index = dr.select(result.valid, self.shape_index, 0xFFFFFFFF)
        if dr.width(shapes_dr) > 0:  # a scene may have no shape at all
            native = result.valid & self.from_native
            inside = result.valid & self.in_instance
            ours = result.valid & ~native & ~inside
            result.shape = dr.gather(mi.ShapePtr, shapes_dr, result.shape_index, ours)
            result.shape = dr.select(native, self.shape, result.shape)
            result.instance = dr.select(native, self.instance_ptr, result.instance)
            result.instance = dr.select(
                inside, dr.gather(mi.ShapePtr, shapes_dr, self.instance, inside),
                result.instance)
        return result


def native_moving_possible() -> bool:
    """Whether the moving meshes can have a Mitsuba sub-scene of their own beside the
    still world's: a kernel traces one OptiX scene at most (Dr.Jit disables the queries
    of a second, leaving rays unanswered), so not on CUDA; Embree takes any number."""
    return dr.backend_v(mi.Float) != dr.JitBackend.CUDA


def query_ns(query, ray) -> float:
    """Nanoseconds a closest-hit ``query(ray)`` costs per ray, without the launch's
    fixed cost: the slope between the whole of ``ray`` and its even half, each the
    fastest of two runs after one that may compile (the device synchronised); the mean
    over the whole where noise makes the slope meaningless."""
    n = dr.width(ray)
    half = dr.gather(type(ray), ray, dr.arange(mi.UInt32, n // 2) * 2)

    def fastest(r) -> float:
        best = float("inf")
        for _ in range(2):
            start = clock_ms()
            pi = query(r)
            dr.eval(pi.t, pi.prim_index, pi.shape_index)
            best = min(best, clock_ms() - start)
        return best

    fastest(half)  # compiles what the runs below launch
    whole, part = fastest(ray), fastest(half)
    slope = (whole - part) * 1e6 / max(n - n // 2, 1)
    return slope if slope > 0 else whole * 1e6 / max(n, 1)


def _declared(shapes, ids: tuple) -> tuple:
    """Indices into ``shapes`` of the shapes whose ids are ``ids`` (every shape of an
    id); ValueError naming the ids that name no shape."""
    wanted = set(ids)
    found = [i for i, shape in enumerate(shapes) if shape.id() in wanted]
    unknown = sorted(set(ids) - {shapes[i].id() for i in found})
    if unknown:
        raise ValueError(f"moving={list(ids)}: no shape of the scene has the id(s) {unknown} "
                         f"(its shapes: {sorted({s.id() for s in shapes})})")
    return tuple(found)


def _half_area(lo, hi) -> float:
    """Half the surface area of the box ``lo``..``hi`` (lists of Python floats), in
    double precision as the SAH cost's areas."""
    extent = dr.maximum(dr.scalar.Array3f64(hi) - dr.scalar.Array3f64(lo), 0.0)
    return float(half_area(extent))


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
    if accel not in ACCELS:
        raise ValueError(f"accel={accel!r}: expected one of {ACCELS}")
    policy, config = split_options(options)
    if accel == "hlbvh":
        return SceneAccel(scene, policy=policy, config=config)
    return NativeAccel(scene)
