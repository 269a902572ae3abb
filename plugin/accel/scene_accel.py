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

import drjit as dr
import mitsuba as mi

from hlbvh.kernels.arrays import concat
from hlbvh.kernels.bvh import BuildConfig
from hlbvh.kernels.geometry import half_area
from hlbvh.kernels.layout import joined
from hlbvh.kernels.traversal import any_hit, closest_hit
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
        dynamic: the moving meshes' :class:`MeshGroup`.
        instances: the moving instances' :class:`InstanceGroup` (``static="native"``;
            None with ``"hlbvh"``).
        last_update: what the last :meth:`update` (or the construction) did:
            ``decision`` (the most work any group did, one of :data:`DECISIONS`),
            ``ms`` (wall time of the whole update), ``triangles``, ``sah_cost`` (of the
            groups our BVHs trace together: each group's SAH cost weighted by its root
            box's area over the area of the box around them, the cost of a ray through
            that box when each group is entered through its root box; None without
            triangles in our BVHs), ``moving`` (ids of the moving shapes), and
            ``groups``: ``{"static": ..., "dynamic": ...}``, each group's ``last``.
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
        # ---- The moving meshes ----
        meshes = set(self.meshes)
        self.dynamic.indices = tuple(i for i in moving if i in meshes)
        dynamic_changed = [i for i in changed if i in self.dynamic.indices]
        if (first and self.dynamic.indices) or dynamic_changed or self.dynamic.stale:
            reshaped = first or any(
                states[i].reshaped(self._states[i]) for i in dynamic_changed)
            self.dynamic.update(self.shapes, self.config, self.policy, reshaped,
                                decision="build" if first else "rebuild")
        else:
            self.dynamic.keep()
        # ---- The moving instances: the top level over them ----
        if self.shading is not None:
            self.shading.refresh([i for i in changed if is_instance(self.shapes[i])])
        if self.instances is not None:
            moving_instances = tuple(i for i in moving if is_instance(self.shapes[i]))
            table = self.shading if self.shading is not None and self.shading.usable else None
            self.instances.update(self.shapes, moving_instances,
                                  moved=not set(moving_instances).isdisjoint(changed),
                                  rows_of=table.rows_of if table else None,
                                  policy=self.policy)
        self._states, self._current = states, True
        traced = [g for g in (self.static, self.dynamic) if isinstance(g, MeshGroup) and g.bvh]
        if traced != self._traced or any(g.last["decision"] != "kept" for g in traced):
            self._join(traced)
        groups = (self.static, self.dynamic) + ((self.instances,) if self.instances else ())
        self.last_update = dict(
            decision=max((g.last["decision"] for g in groups), key=DECISIONS.index),
            ms=clock_ms() - start,
            triangles=self.static.triangles + self.dynamic.triangles,
            sah_cost=self._sah_cost(),
            moving=[self.shapes[i].id() for i in self.moving],
            groups={g.name: dict(g.last) for g in groups},
        )
        return self

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
        """The static group's closest hit, then our BVHs', then each analytic shape's
        own routine, merged by nearest ``t`` (ties to the earlier)."""
        self._check_current()
        n = dr.width(ray)
        active = mi.Bool(active) & dr.full(mi.Bool, True, n)
        native = isinstance(self.static, NativeGroup) and self.static.scene is not None
        if native:
            pi = self.static.preliminary(ray, coherent, active, reorder)
            t = dr.select(pi.is_valid(), pi.t, dr.inf)
            prim_uv, prim_index, shape_index = pi.prim_uv, pi.prim_index, pi.shape_index
            from_native = pi.is_valid()
        else:
            t, prim_uv = dr.full(mi.Float, dr.inf, n), dr.zeros(mi.Point2f, n)
            prim_index, shape_index = dr.zeros(mi.UInt32, n), dr.zeros(mi.UInt32, n)
            from_native = dr.zeros(mi.Bool, n)
        # Each later structure looks no further than the nearest hit so far.
        ray = mi.Ray3f(ray)
        if self._tree is not None:
            ray.maxt = dr.minimum(ray.maxt, t)
            t, prim_uv, prim_index, shape_index, from_native = _nearer(
                self._closest_mesh_hit(ray, active), t, prim_uv, prim_index, shape_index,
                from_native)
        from_instance = dr.zeros(mi.Bool, n)
        if self.instances is not None and self.instances.tree is not None:
            ray.maxt = dr.minimum(ray.maxt, t)
            t_i, u_i, v_i, prim_i, inst_i, valid_i = closest_instance_hit(
                self.instances.tree, ray.o, ray.d, ray.maxt, active)
            valid_i = mi.Bool(valid_i)
            local, in_group, inst_index = self.instances.hit_fields(
                mi.UInt32(prim_i), mi.UInt32(inst_i), valid_i)
            closer = valid_i & (mi.Float(t_i) < t)
            t = dr.select(closer, mi.Float(t_i), t)
            prim_uv = dr.select(closer, mi.Point2f(mi.Float(u_i), mi.Float(v_i)), prim_uv)
            prim_index = dr.select(closer, local, prim_index)
            shape_index = dr.select(closer, in_group, shape_index)
            from_native &= ~closer
            from_instance = closer
        for index, shape in self._routine_shapes():
            ray.maxt = dr.minimum(ray.maxt, t)
            pi_s = shape.ray_intersect_preliminary(ray, 0, active)
            closer = pi_s.is_valid() & (pi_s.t < t)
            t, prim_uv, prim_index, shape_index, from_native = _nearer(
                (dr.select(pi_s.is_valid(), pi_s.t, dr.inf), pi_s.prim_uv, pi_s.prim_index,
                 dr.full(mi.UInt32, index, n)), t, prim_uv, prim_index, shape_index,
                from_native)
            from_instance &= ~closer
        result = dr.zeros(mi.PreliminaryIntersection3f, n)
        result.valid = active & (t < dr.inf)
        result.t = dr.select(result.valid, t, dr.inf)
        result.prim_uv = mi.Point2f(prim_uv)
        result.prim_index = dr.select(result.valid, prim_index, 0)
        result.shape_index = dr.select(result.valid, shape_index, 0xFFFFFFFF)
        if dr.width(self.shapes_dr) > 0:  # a scene may have no shape at all
            ours = result.valid & ~from_native & ~from_instance
            result.shape = dr.gather(mi.ShapePtr, self.shapes_dr, result.shape_index, ours)
            if native:
                result.shape = dr.select(from_native, pi.shape, result.shape)
                result.instance = dr.select(from_native, pi.instance, result.instance)
            if self.instances is not None and self.instances.tree is not None:
                # As Mitsuba reports a hit inside an instance: no shape pointer, the
                # shape's index in its group, the instance.
                result.shape = dr.select(from_instance, dr.zeros(mi.ShapePtr, n), result.shape)
                result.instance = dr.select(
                    from_instance, dr.gather(mi.ShapePtr, self.shapes_dr, inst_index,
                                             from_instance), result.instance)
        return result

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
        if self.instances is not None and self.instances.tree is not None:
            hit |= mi.Bool(any_hit(self.instances.tree, ray.o, ray.d, ray.maxt, active & ~hit))
        for _, shape in self._routine_shapes():
            hit |= shape.ray_test(ray, active & ~hit)
        return hit & active


def _nearer(hit, t, prim_uv, prim_index, shape_index, from_native):
    """The nearest-hit fields after one more structure's ``hit`` (t, prim_uv,
    prim_index, shape_index): taken where strictly nearer, so ties keep the earlier."""
    t_h, uv_h, prim_h, shape_h = hit
    closer = t_h < t
    return (dr.select(closer, t_h, t), dr.select(closer, uv_h, prim_uv),
            dr.select(closer, prim_h, prim_index), dr.select(closer, shape_h, shape_index),
            from_native & ~closer)


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
