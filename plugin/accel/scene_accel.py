"""The intersector our integrators trace through, :class:`SceneAccel`: a Mitsuba scene's
three ray queries (``mi.Scene``'s signatures) over groups sorted by motion, each hit
with exactly the fields Mitsuba's own query gives (``t``, ``prim_uv``, ``prim_index``,
``shape``, ``shape_index``, ``instance``), so that Mitsuba's
``compute_surface_interaction`` shades it. Mitsuba does not let Python supply its
accelerator's intersection routine, so the integrator is the integration point.

A shape is *moving* once declared (option ``moving``) or once it changed
(:mod:`hlbvh.accel.motion`), and stays so. With ``static="native"`` (default) the still
shapes, of any type, are a Mitsuba sub-scene built once (:mod:`hlbvh.accel.native_group`;
rebuilt when a shape leaves it); the moving meshes are traced by our HLBVH, a Mitsuba
sub-scene of them, or the whole scene, as :mod:`hlbvh.accel.moving` chooses per render;
moving instances go under our top level (:mod:`hlbvh.accel.instance_group`); moving
spheres, disks and cylinders by their own routine (a call through a shape pointer in a
symbolic loop would trace every registered shape); any other moving shape is refused,
naming it. With ``static="hlbvh"`` every mesh is in our BVHs and traced by our
watertight traversal; instances, curves and the like are refused.

A query asks each structure that traces the scene now, one after the other through the
same two queries (:mod:`hlbvh.accel.structures`), and keeps the nearest hit
(:class:`NearestHit`); hits of two structures that tie (:data:`hlbvh.accel.hits.TIE`)
go to the shape of lower index in ``scene.shapes()``, whichever structure traced it.
Meshes without triangles are refused, naming them (more likely a mistake than an
intent); a scene without geometry misses everywhere. :meth:`SceneAccel.update` does
only what changed (the dynamic group refit or rebuilt as the :class:`UpdatePolicy`
says); a query after a change the accelerator has not followed is refused, naming the
mesh. ``coherent`` is passed on to Mitsuba's accelerator; our traversal traces
coherent and incoherent rays alike.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from hlbvh.accel.choice import RayBudget
from hlbvh.accel.hits import NearestHit
from hlbvh.accel.instance_group import InstanceGroup, group_of
from hlbvh.accel.instance_shading import InstanceShading, is_instance
from hlbvh.accel.mesh_group import MeshGroup, joined_sah_cost
from hlbvh.accel.keyed_shading import at_ray_time, shutter_points
from hlbvh.accel.keys import motion_keys, moves_in_shutter
from hlbvh.accel.motion import MeshState, shape_states
from hlbvh.accel.moving import MovingMeshes, still_share
from hlbvh.accel.groups import Change
from hlbvh.accel.native_group import NativeGroup, shape_groups
from hlbvh.accel.policy import ACCELS, DECISIONS, UpdatePolicy, split_options
from hlbvh.accel.preparation import Prepared, rebuild_scene, render_sample, time_structures
from hlbvh.accel.queries import NativeAccel, SceneQueries, checked_scene
from hlbvh.accel.scene_geometry import (declared_indices, describe_shape, scene_shapes,
                                        unmovable_error)
from hlbvh.accel.structures import MeshTree, scene_structures
from hlbvh.kernels.bvh import BuildConfig
from hlbvh.timing import clock_ms


class SceneAccel(SceneQueries):
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
            object); forced by ``moving_accel`` or chosen per render by :meth:`prepare`.
        prepared: what the last :meth:`prepare` did (:class:`Prepared`; None before one).
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
            ``estimates_ms`` (each structure's estimated frame at the last choice,
            None before one), ``update_ms`` and ``query_ns`` (the measured costs) and
            ``queries_per_sample``.
    """

    name = "hlbvh"

    def __init__(self, scene, *, policy: UpdatePolicy | None = None,
                 config: BuildConfig | None = None, **options):
        start = clock_ms()
        checked_scene(scene)
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
        self.moving = declared_indices(self.shapes, self.policy.moving)
        groups = shape_groups(scene) if native else []
        self.static = NativeGroup(groups) if native else MeshGroup("static")
        self.moving_meshes = MovingMeshes(policy.moving_accel, choosable=native)
        self._instances_behind = False  # moving instances moved while the scene traced them
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
        self._joined_tree = None  # their joined tree, a MeshTree (None: no triangles)
        self._keyed = None  # the group traced at each ray's time (motion keys), if any
        self._keyed_tree = self._keyed_faces = None  # its MeshTree, each shape's first face
        self._structures = []  # what queries ask, in order (hlbvh.accel.structures)
        self._sample = None  # a render's rays the probe times structures with, made once
        self.prepared = None
        self.update()
        self._construction_ms = clock_ms() - start  # counted in the first prepare()

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
        # (a mesh with motion keys moves inside the frame, even unchanged since the last)
        keyed = {i for i in self.meshes if motion_keys(self.shapes[i]) is not None} | {
            i for i, s in enumerate(self.shapes) if is_instance(s) and moves_in_shutter(s)}
        started = sorted((set(changed) | keyed) - set(self.moving))
        for i in changed:
            self._check_movable(i)
        moving = tuple(sorted(self.moving + tuple(started)))
        # ---- The static group: everything that never moved ----
        self._update_static(moving, started, first)
        self.moving = moving
        # ---- The moving meshes, in the structure that traces them now ----
        meshes = set(self.meshes)
        self.dynamic.indices = tuple(i for i in moving if i in meshes)
        self.moving_meshes.still_share = still_share(self.shapes, self.dynamic.indices)
        dynamic_changed = [i for i in changed if i in self.dynamic.indices]
        structure = self.moving_structure
        self.moving_meshes.keyed = bool(keyed)
        structure = "hlbvh" if self.moving_meshes.keyed else structure
        self.moving_meshes.fell_behind(bool(dynamic_changed or started), bool(changed))
        self.moving_meshes.update(self.shapes, states, None if first else self._states,
                                  dynamic_changed, self.config, self.policy)
        # ---- The moving instances: the top level over them ----
        if self.shading is not None:
            self.shading.refresh([i for i in changed if is_instance(self.shapes[i])])
        moving_instances = tuple(i for i in moving if is_instance(self.shapes[i]))
        self.moving_meshes.instances = bool(moving_instances)
        self._instances_behind |= not set(moving_instances).isdisjoint(changed)
        if self.instances is not None and structure != "scene":
            table = self.shading if self.shading is not None and self.shading.usable else None
            self.instances.rows_of = table.rows_of if table else None
            self.instances.update(Change(self.shapes, moving_instances,
                                         moved=self._instances_behind, policy=self.policy))
            self._instances_behind = False
        elif self.instances is not None:
            self.instances.keep()
        self._states, self._current = states, True
        traced = [g for g in (self.static, self.dynamic) if g.bvh is not None
                  and (g is not self.dynamic or structure == "hlbvh")]
        if traced != self._traced or any(g.last.decision != "kept" for g in traced):
            self._join(traced)
        self._arrange()  # the sub-scenes, instances and routines may have changed too
        groups = (self.static, self.dynamic, self.native_moving) + (
            (self.instances,) if self.instances else ())
        self.last_update = dict(
            decision=max((g.last.decision for g in groups), key=DECISIONS.index),
            ms=clock_ms() - start,
            triangles=self.static.triangles + self.dynamic.triangles,
            sah_cost=joined_sah_cost(self._traced),
            moving=[self.shapes[i].id() for i in self.moving],
            groups={g.name: g.last.as_dict() for g in groups},
            moving_accel=self.moving_meshes.record(),
        )
        return self

    # ---- What traces the moving meshes: the choice by cost (hlbvh.accel.moving) ----

    @property
    def dynamic(self) -> MeshGroup:
        """Our HLBVH over the moving meshes (:attr:`MovingMeshes.ours`)."""
        return self.moving_meshes.ours

    @property
    def native_moving(self) -> NativeGroup:
        """The moving meshes' Mitsuba sub-scene (:attr:`MovingMeshes.native`)."""
        return self.moving_meshes.native

    @property
    def moving_structure(self) -> str:
        """What traces the moving meshes now (:attr:`MovingMeshes.structure`)."""
        return self.moving_meshes.structure

    def prepare(self, scene, budget: RayBudget, sensor=None) -> Prepared:
        """Bring the accelerator up to date with ``scene`` (this accelerator's scene) for
        a render of ``budget`` through ``sensor``, and choose what traces the moving
        meshes (:mod:`hlbvh.accel.choice`): the one call an integrator makes before a
        render. In turn: the choice by the costs measured so far and the update that
        follows it (the construction's own update, for the first call); the probe, while
        the choice has structures left to time and timing them could move it
        (:meth:`MovingMeshes.needs_probe`; :func:`time_structures`, over a sample of
        ``sensor``'s rays made once, :func:`render_sample`); the choice again, and
        the newly chosen structure's catch-up update; the whole scene's rebuild when it
        traces the moving meshes and missed motion (:func:`rebuild_scene`). Returns the
        record, also kept in :attr:`prepared`.

        Raises:
            ValueError: as :meth:`update`.
        """
        start = clock_ms()
        moving = self.moving_meshes
        first, self._construction_ms = self._construction_ms, None
        if first is None:  # (the construction's update chose nothing: it had no budget)
            moving.plan(budget, self.shapes)
            self.update()
        chosen, done = moving.structure, self.last_update
        if self.static.native:  # Mitsuba's build rate, from its still world's sub-scene
            moving.costs.record_build_rate(self.static.build_ms, self.static.triangles)
        probed = (sensor is not None and self._current and self.static.native
                  and moving.needs_probe(budget, self.shapes))
        if probed:
            if self._sample is None:
                self._sample = render_sample(self, sensor)
            time_structures(self, self._sample)
        if moving.plan(budget, self.shapes) != chosen:
            self.update()  # the newly chosen structure catches up
            self._absorb(done)
        rebuilt = None
        if moving.structure == "scene" and moving.scene_behind:
            timed = "scene" not in moving.costs.query_ns and self._sample is not None
            rebuilt = rebuild_scene(scene, self.shapes, self.moving, moving,
                                    self._sample.rays if timed else None)
        decision = self.last_update["decision"]
        self.prepared = Prepared(
            ms=(first or 0.0) + clock_ms() - start,
            decision="native" if rebuilt is not None and decision == "kept" else decision,
            sah_cost=self.last_update["sah_cost"], traced_by=moving.structure,
            scene_rebuild_ms=rebuilt, probed=bool(probed))
        return self.prepared

    def query_through(self, structure: str):
        """The closest-hit query (a function of a ray) through the still world and
        ``structure`` tracing the moving meshes (``"hlbvh"``, ``"native"``; ``"still"``:
        the still world alone), brought up to date first (ours: built when it has no
        tree or missed motion, and its refit timed, :meth:`MovingMeshes.measure_ours`),
        for the probe to time. What traces the moving meshes now is left as it was."""
        moving = self.moving_meshes
        if structure == "hlbvh":
            if self.dynamic.bvh is None or moving.behind("hlbvh"):
                moving.update_ours(self.shapes, self._states, self._states, [],
                                   self.config, self.policy)
            moving.measure_ours(self.shapes, self.config, self.policy)
        elif structure == "native":
            moving.update_native(self.shapes)
        ours = structure == "hlbvh" and self.dynamic.bvh is not None
        structures = scene_structures(
            self.static if self.static.native else None,
            MeshTree.joined_groups([self.dynamic]) if ours else None, None,
            self.native_moving if structure == "native" else None, self.instances,
            self._routine_shapes())
        return lambda ray: self._closest(structures, ray, False, True, (False, 0, 0))

    def record_render(self, ms: float, samples: int):
        """A render of ``samples`` samples through :attr:`moving_structure` took ``ms``
        (the integrator times its renders; the costs learn from them)."""
        self.moving_meshes.costs.record_render(self.moving_structure, ms, samples)

    def _absorb(self, earlier: dict):
        """Make :attr:`last_update` tell what ``earlier`` (the update just before it, in
        the same preparation: before the choice moved) did too: the most work of both,
        their time together, and each group's record of the one that did more."""
        now = self.last_update
        rank = DECISIONS.index
        now["decision"] = max(now["decision"], earlier["decision"], key=rank)
        now["ms"] += earlier["ms"]
        for name, group in earlier["groups"].items():
            if rank(group["decision"]) > rank(now["groups"][name]["decision"]):
                now["groups"][name] = group

    def surface_interaction(self, pi, ray, ray_flags=mi.RayFlags.All, active=True):
        """``pi.compute_surface_interaction(ray, ray_flags, active)``; in a scene with
        instances, expanded without Mitsuba's call through a shape pointer, whose kernel
        grows with the number of instances (:mod:`hlbvh.accel.instance_shading`)."""
        if self.shading is None:
            si = pi.compute_surface_interaction(ray, ray_flags, active)
        else:
            si = self.shading.surface_interaction(pi, ray, ray_flags, active)
        if self._keyed is not None:  # a mesh with motion keys: where it is at ray.time
            si = at_ray_time(si, pi, ray, self._keyed, self._keyed_faces,
                             self._keyed_tree.time(ray), active)
        return si

    def points_over_shutter(self, pi, si, active=True):
        """Where each hit is at the shutter's open and close (a hit on a mesh with
        motion keys: its barycentric point on the first and the last key's triangle; on
        an instance with keys: its object-space point through the poses there; any
        other: the hit itself), and the keys' shutter length (1 without keys; the
        meshes' where both have keys)."""
        p_open, p_close, length = si.p, si.p, 1.0
        moved = None if self.shading is None else self.shading.shutter_points(pi, si, active)
        if moved is not None:
            ends, on, (open_, close) = moved[:2], moved[2], moved[3]
            p_open, p_close = (dr.select(on, p, si.p) for p in ends)
            length = close - open_
        if self._keyed is None:
            return p_open, p_close, length
        ends = shutter_points(pi, self._keyed, self._keyed_faces, active)
        open_, close = self._keyed.shutter
        return (dr.select(ends[2], ends[0], p_open), dr.select(ends[2], ends[1], p_close),
                close - open_)

    def _check_movable(self, i: int):
        """Refuse a change this accelerator cannot follow: a shape that cannot be traced
        moving (instances can, with ``static="native"``), or a mesh whose faces were
        emptied."""
        shape = self.shapes[i]
        if i in self._others and not (self.instances is not None and is_instance(shape)):
            raise unmovable_error(shape)
        if shape.is_mesh() and shape.face_count() == 0:
            raise ValueError(f"{describe_shape(shape)} has no triangles any more: it would "
                             "silently be missing from the image; give it faces")

    def _update_static(self, moving: tuple, started: list, first: bool):
        """The static group over every shape (``"native"``) or mesh (``"hlbvh"``) not in
        ``moving``; ``started``: the shapes that just started moving."""
        if self.static.native:
            moving = set(moving)
            still = tuple(i for i in range(len(self.shapes)) if i not in moving)
            self.static.update(Change(self.shapes, still,
                                      left=tuple(self.shapes[i].id() for i in started)))
            return
        moving = set(moving)
        # Built once for every frame to come: with the static builder, unless no shape
        # was declared moving (the accelerator's first tree over everything).
        config = (self.config if first and not self.moving
                  else self.policy.static_config(self.config))
        self.static.update(Change(self.shapes, tuple(i for i in self.meshes if i not in moving),
                                  reshaped=first, first=first, policy=self.policy,
                                  config=config))

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
                    f"SceneAccel: {describe_shape(shape)} changed since the accelerator's last "
                    "update(); call update() before tracing (it would answer from the old "
                    "geometry)")
        if self.static.stale or (self.instances is not None and self.instances.stale):
            raise RuntimeError(
                "SceneAccel: a shape group's shapes changed since the accelerator's last "
                "update(); call update() before tracing (it would answer from the old "
                "geometry)")

    def _join(self, traced):
        """One tree over our groups' BVHs (:meth:`MeshTree.joined_groups`), and the
        structures queries ask listed anew. A group with motion keys is traced on its
        own, at each ray's time (:attr:`_keyed`)."""
        self._traced = traced
        keyed = [g for g in traced if g.keyed is not None]
        self._keyed = keyed[0] if keyed else None
        still = [g for g in traced if g.keyed is None]
        self._joined_tree = MeshTree.joined_groups(still) if still else None
        self._keyed_tree = self._keyed_faces = None
        if self._keyed is not None:  # each shape's first face in the keyed group
            group = self._keyed
            self._keyed_tree = MeshTree.keyed_group(group)
            counts = [self.shapes[i].face_count() for i in group.indices]
            first = [0xFFFFFFFF] * len(self.shapes)
            for i, base in zip(group.indices, [sum(counts[:j]) for j in range(len(counts))]):
                first[i] = base
            self._keyed_faces = mi.UInt32(first)
        self._arrange()

    def _arrange(self):
        """List the structures that trace the scene now (:func:`scene_structures`), in
        the order queries ask them: the still world's sub-scene (``static="native"``),
        our joined tree, the keyed tree, the moving meshes' sub-scene while it traces
        them, the instances' tree, the analytic shapes' own routines. Called where the
        groups change (:meth:`update`, :meth:`_join`), not per query."""
        self._structures = scene_structures(
            self.static if self.static.native else None, self._joined_tree, self._keyed_tree,
            self.native_moving if self.moving_structure == "native" else None,
            self.instances, self._routine_shapes())

    def _routine_shapes(self):
        """``(index, shape)`` of the analytic shapes traced by their own routine: all of
        them with ``static="hlbvh"``, the moving ones with ``"native"``."""
        if self.static.native:
            return [(i, s) for i, s in self.analytic if i in self.moving]
        return self.analytic

    def _preliminary(self, ray, coherent, active, reorder):
        """Each structure's closest hit in turn, merged by nearest ``t`` (ties as
        :meth:`NearestHit.take` breaks them); each looks no further than the nearest
        hit so far (it narrows the ray's ``maxt``, on a copy of the ray)."""
        self._check_current()
        return self._closest(self._structures, ray, coherent, active, reorder)

    def _closest(self, structures, ray, coherent, active, reorder):
        """The nearest of ``structures``' closest hits (:meth:`_preliminary`)."""
        n = dr.width(ray)
        active = mi.Bool(active) & dr.full(mi.Bool, True, n)
        hit = NearestHit.none(n)
        ray = mi.Ray3f(ray)
        for structure in structures:
            structure.closest(ray, active, hit, coherent, reorder)
        return hit.preliminary(active, self.shapes_dr)

    def _test(self, ray, coherent, active):
        """Whether any structure occludes the ray; each asked only for the lanes the
        ones before it left unoccluded."""
        self._check_current()
        active = mi.Bool(active) & dr.full(mi.Bool, True, dr.width(ray))
        hit = dr.zeros(mi.Bool, dr.width(ray))
        for structure in self._structures:
            hit |= structure.occluded(ray, active & ~hit, coherent)
        return hit & active


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
    checked_scene(scene)
    if accel not in ACCELS:
        raise ValueError(f"accel={accel!r}: expected one of {ACCELS}")
    policy, config = split_options(options)
    if accel == "hlbvh":
        return SceneAccel(scene, policy=policy, config=config)
    return NativeAccel(scene)
