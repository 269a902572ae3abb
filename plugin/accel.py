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
  update in which one of them changed, as the :class:`UpdatePolicy` says: rebuilt
  (``update="rebuild"``, the default; the CSD sort starts from last frame's primitive
  order when the triangle count is unchanged), refit (``"refit"``), or refit while the
  tree's SAH cost stays within ``refit_tolerance`` of its last build's (``"auto"``).
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

import dataclasses
import math
import numbers
import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from hlbvh.kernels.build import build
from hlbvh.kernels.bvh import BUILDERS, BuildConfig
from hlbvh.kernels.arrays import concat
from hlbvh.kernels.layout import joined
from hlbvh.kernels.traversal import any_hit, closest_hit

ACCELS = ("hlbvh", "native")
#: Per-frame policies of :meth:`SceneAccel.update` (option ``update``).
UPDATES = ("rebuild", "fresh", "refit", "auto")
#: The options of :func:`hlbvh.build` an accelerator accepts.
BUILD_OPTIONS = tuple(f.name for f in dataclasses.fields(BuildConfig))
#: The accelerator's own options (:class:`UpdatePolicy`).
UPDATE_OPTIONS = ("update", "refit_tolerance", "static_builder")
#: What an update did to a group, from the least work to the most: ``kept`` (nothing
#: changed), ``refit``, ``rebuild``, ``build`` (the accelerator's first build).
DECISIONS = ("kept", "refit", "rebuild", "build")

#: Analytic shape types intersected by Mitsuba's own per-shape routine.
_ANALYTIC = ("Sphere", "Disk", "Cylinder")


# ---------------------------------------------------------------------------------------
# Options
# ---------------------------------------------------------------------------------------


@dataclass
class UpdatePolicy:
    """How :meth:`SceneAccel.update` brings the dynamic group up to date when only its
    meshes' vertex positions changed (new faces or vertex counts always rebuild).

    Attributes:
        update: ``"rebuild"`` (default): a new BVH every update, its CSD sort seeded
            with last frame's order (temporal coherence); always the best tree.
            ``"fresh"``: the same without the seed (temporal reuse off, for
            comparison). ``"refit"``: the tree of the
            last build with new boxes (:meth:`hlbvh.BVH.refit`), much cheaper, never
            wrong, but slower to trace as the geometry moves away from the pose it was
            built for. ``"auto"``: refit, then rebuild if the refit tree's SAH cost
            exceeds ``refit_tolerance`` times the SAH cost of the group's last build.
        refit_tolerance: the drift ``"auto"`` accepts, a number >= 1 (default 1.3).
        static_builder: the builder of the static group once meshes have moved out of
            it (``"sah"`` by default: it is built once and traced every frame, so the
            best tree pays; measured on the cloth scene's ground and pole: SAH cost 7.9
            with "hlbvh", 4.5 with "sah", 1.5x the primary rays per second), or
            ``"same"`` for the scene's own builder.
    """

    update: str = "rebuild"
    refit_tolerance: float = 1.3
    static_builder: str = "sah"

    def validated(self) -> "UpdatePolicy":
        """Self, after checking both fields; raises ValueError naming the bad one."""
        if self.update not in UPDATES:
            raise ValueError(f"update={self.update!r}: expected one of {UPDATES}")
        tolerance = self.refit_tolerance
        if (isinstance(tolerance, (bool, str)) or not isinstance(tolerance, numbers.Real)
                or not math.isfinite(tolerance) or tolerance < 1):
            raise ValueError(
                f"refit_tolerance={tolerance!r}: expected a finite number >= 1 (the SAH "
                "cost a refit tree may reach, relative to a fresh build's)"
            )
        self.refit_tolerance = float(tolerance)
        if self.static_builder not in BUILDERS + ("same",):
            raise ValueError(
                f"static_builder={self.static_builder!r}: expected one of {BUILDERS + ('same',)}"
            )
        return self


def split_options(options: dict) -> tuple[UpdatePolicy, dict]:
    """The update policy and the builder's options among an accelerator's options,
    both validated.

    Args:
        options: keyword options: :data:`UPDATE_OPTIONS` and :data:`BUILD_OPTIONS`.
    Returns:
        ``(UpdatePolicy, build options dict)``.
    Raises:
        ValueError: an unknown option or a bad value, naming it.
    """
    known = BUILD_OPTIONS + UPDATE_OPTIONS
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ValueError(
            f"unknown accelerator option(s) {unknown}: expected some of {sorted(known)}"
        )
    policy = UpdatePolicy(**{k: v for k, v in options.items() if k in UPDATE_OPTIONS})
    build_options = {k: v for k, v in options.items() if k not in UPDATE_OPTIONS}
    BuildConfig.from_options(**build_options)
    return policy.validated(), build_options


# ---------------------------------------------------------------------------------------
# The scene's geometry
# ---------------------------------------------------------------------------------------


@dataclass
class SceneGeometry:
    """The world-space triangles of some meshes of a scene, on the scene's device.

    Attributes:
        vertices: Float (3·V): the meshes' positions, concatenated.
        faces: UInt32 (3·F): their triangles, indices into ``vertices`` (each mesh's
            indices offset by the vertices before it).
        prim_shape: UInt32 (F): for each triangle, the index of its mesh in
            ``scene.shapes()``.
        prim_local: UInt32 (F): for each triangle, its index inside its mesh.
    """

    vertices: mi.Float
    faces: mi.UInt32
    prim_shape: mi.UInt32
    prim_local: mi.UInt32

    @property
    def prim_count(self) -> int:
        return len(self.prim_shape)


def _describe(shape) -> str:
    return f"shape {shape.id()!r} ({shape.class_name()})"


def scene_shapes(shapes) -> tuple[tuple, list]:
    """Sort a scene's shapes into meshes and analytic shapes.

    Args:
        shapes: ``scene.shapes()``.
    Returns:
        ``(mesh indices, analytic)``: the indices of the meshes in ``shapes``, and
        ``(index, shape)`` of every analytic shape.
    Raises:
        ValueError: naming the shape, for an instance, a curve, an SDF grid, ellipsoids
            or any other shape type this accelerator does not intersect, and for a
            mesh without triangles.
    """
    meshes, analytic = [], []
    for index, shape in enumerate(shapes):
        if shape.is_mesh():
            if shape.face_count() == 0:
                raise ValueError(
                    f"{_describe(shape)} has no triangles: it would silently be missing "
                    "from the image; give it faces or remove it from the scene"
                )
            meshes.append(index)
        elif shape.class_name() in _ANALYTIC:
            analytic.append((index, shape))
        else:
            raise ValueError(
                f"{_describe(shape)}: hlbvh intersects meshes and the analytic shapes "
                f"{', '.join(s.lower() for s in _ANALYTIC)}; instances, shape groups, "
                "curves, SDF grids and ellipsoids are not supported yet. Use "
                "accel='native' for this scene."
            )
    return tuple(meshes), analytic


def collect_geometry(shapes, indices=None) -> SceneGeometry:
    """World-space triangles of meshes among ``shapes`` in one vertex/face buffer.

    Args:
        shapes: ``scene.shapes()``; the indices stored refer to this list.
        indices: which meshes (indices into ``shapes``); by default every mesh, after
            :func:`scene_shapes` checked the scene.

    A Python loop over the meshes (a few), none over triangles.
    """
    if indices is None:
        indices = scene_shapes(shapes)[0]
    vertices, faces, prim_shape, prim_local = [], [], [], []
    vertex_base = 0
    for index in indices:
        mesh = shapes[index]
        face_count = mesh.face_count()
        vertices.append(mesh.vertex_positions_buffer())
        faces.append(mesh.faces_buffer() + dr.opaque(mi.UInt32, vertex_base))
        prim_shape.append(dr.full(mi.UInt32, index, face_count))
        prim_local.append(dr.arange(mi.UInt32, face_count))
        vertex_base += mesh.vertex_count()
    if not indices:
        return SceneGeometry(mi.Float(), mi.UInt32(), mi.UInt32(), mi.UInt32())
    geometry = SceneGeometry(_concat(vertices), dr.concat(faces), dr.concat(prim_shape),
                             dr.concat(prim_local))
    dr.eval(geometry.vertices, geometry.faces, geometry.prim_shape, geometry.prim_local)
    return geometry


def _concat(arrays):
    """The arrays end to end (one array is returned as it is: no copy)."""
    return arrays[0] if len(arrays) == 1 else dr.concat(arrays)


def mesh_buffers(shapes, indices) -> dict:
    """``{index: (vertex buffer, face buffer)}`` of the meshes ``shapes[i]``: the arrays
    themselves, whose JIT variable indices tell whether a mesh got new buffers. Held,
    they keep their indices from being given to other arrays."""
    return {i: (shapes[i].vertex_positions_buffer(), shapes[i].faces_buffer()) for i in indices}


def _named_error(shapes, indices, error: ValueError) -> ValueError:
    """A build or refit of the meshes ``indices`` failed with ``error``: the same
    error, naming the mesh with non-finite positions when there is one."""
    for index in indices:
        mesh = shapes[index]
        if not dr.all(dr.isfinite(mesh.vertex_positions_buffer()), axis=None):
            return ValueError(
                f"{_describe(mesh)} has non-finite (NaN or infinite) vertex positions: "
                "fix the mesh or the parameters written into it"
            )
    names = ", ".join(repr(shapes[i].id()) for i in indices)
    return ValueError(f"building the HLBVH of the meshes {names} failed: {error}")


def _clock() -> float:
    """Milliseconds since an arbitrary origin, after the device finished its work."""
    dr.sync_thread()
    return time.perf_counter() * 1e3


def _bind_overloads(args: tuple, long_names: tuple, given: dict) -> dict:
    """Bind the positional arguments after ``ray`` the way ``mi.Scene``'s overloads do.

    ``mi.Scene.ray_intersect`` and ``ray_test`` each have a short overload
    ``f(ray, active)`` and a long one ``f(ray, <long_names...>, active)``: a single
    positional argument is ``active``; several fill ``long_names`` then ``active`` in
    order.

    Args:
        args: the positional arguments after ``ray``.
        long_names: the long overload's parameter names before ``active``.
        given: the keyword arguments, defaults filled in, with ``active`` None when not
            passed by keyword.
    Returns:
        ``given`` with the positional arguments bound and ``active`` never None.
    """
    names = long_names + ("active",)
    if len(args) == 1 and given["active"] is None:
        names = ("active",)
    elif len(args) > len(names):
        raise TypeError(f"expected at most {len(names) + 1} positional arguments (ray, "
                        f"{', '.join(names)}), got {len(args) + 1}")
    bound = dict(given)
    for name, value in zip(names, args):
        bound[name] = value
    if bound["active"] is None:
        bound["active"] = True
    return bound


def _checked_scene(scene):
    """``scene``, after checking it is a loaded ``mi.Scene`` (TypeError otherwise)."""
    if not isinstance(scene, mi.Scene):
        raise TypeError(
            f"scene: expected a loaded mi.Scene (mi.load_file / mi.load_dict), got "
            f"{type(scene).__name__}"
        )
    return scene


def _checked_ray(ray):
    """``ray``, after checking it is a ray (anything with ``o``, ``d`` and ``maxt``, as
    ``mi.Ray3f``); TypeError otherwise."""
    if not all(hasattr(ray, name) for name in ("o", "d", "maxt")):
        raise TypeError(f"ray: expected an mi.Ray3f, got {type(ray).__name__}")
    return ray


def _no_rays(ray) -> bool:
    """Whether ``ray`` holds no rays (its origins or directions are empty; ``maxt``
    and ``time`` may still be width-1 defaults)."""
    return dr.width(ray.o) == 0 or dr.width(ray.d) == 0


class _Accel:
    """The three query methods of ``mi.Scene`` with its signatures, keyword names and
    defaults (every overload: ``ray_intersect(ray, active)`` and ``ray_test(ray,
    active)`` included, and the keyword-only ``reorder``, ``reorder_hint``,
    ``reorder_hint_bits``, which are thread-reordering hints for CUDA), bound here once
    and handed to a subclass's ``_preliminary``, ``_intersect`` and ``_test``."""

    def ray_intersect_preliminary(self, ray, coherent=False, active=True, *, reorder=False,
                                  reorder_hint=0, reorder_hint_bits=0):
        """``mi.Scene.ray_intersect_preliminary``: the closest hit's parameters.

        Args:
            ray: ``mi.Ray3f`` (``maxt`` honoured; hits at t <= 0 are never reported).
            coherent: hint that the rays are coherent (camera rays). It changes
                Embree's answer on a few edge rays, so pass what Mitsuba would.
            active: Bool mask.
        Returns:
            ``mi.PreliminaryIntersection3f`` with ``t``, ``prim_uv``, ``prim_index``
            (local to the shape), ``shape_index`` (into ``scene.shapes()``), ``shape``,
            ``instance`` null; on a miss ``valid`` False and ``t`` infinite.
        """
        if _no_rays(_checked_ray(ray)):
            return dr.zeros(mi.PreliminaryIntersection3f, 0)
        return self._preliminary(ray, coherent, active, (reorder, reorder_hint, reorder_hint_bits))

    def ray_intersect(self, ray, *args, ray_flags=mi.RayFlags.All, coherent=False, active=None,
                      reorder=False, reorder_hint=0, reorder_hint_bits=0):
        """``mi.Scene.ray_intersect``: ``(ray, active=True)`` or
        ``(ray, ray_flags, coherent, active=True)``.

        Returns:
            ``mi.SurfaceInteraction3f`` computed by Mitsuba from the closest hit.
        """
        a = _bind_overloads(args, ("ray_flags", "coherent"),
                            dict(ray_flags=ray_flags, coherent=coherent, active=active))
        if _no_rays(_checked_ray(ray)):
            return dr.zeros(mi.SurfaceInteraction3f, 0)
        return self._intersect(ray, a["ray_flags"], a["coherent"], a["active"],
                               (reorder, reorder_hint, reorder_hint_bits))

    def ray_test(self, ray, *args, coherent=False, active=None):
        """``mi.Scene.ray_test``: ``(ray, active=True)`` or ``(ray, coherent, active=True)``.

        Returns:
            Bool per ray: whether anything lies on it at 0 < t <= ``ray.maxt``.
        """
        a = _bind_overloads(args, ("coherent",), dict(coherent=coherent, active=active))
        if _no_rays(_checked_ray(ray)):
            return dr.zeros(mi.Bool, 0)  # Mitsuba's own query aborts the process on it
        return self._test(ray, a["coherent"], a["active"])

    def _intersect(self, ray, ray_flags, coherent, active, reorder):
        """The closest hit, expanded by Mitsuba, as ``mi.Scene.ray_intersect`` does."""
        pi = self._preliminary(ray, coherent, active, reorder)
        return pi.compute_surface_interaction(ray, ray_flags, active)


class NativeAccel(_Accel):
    """The scene's own accelerator (Embree or OptiX) behind the same interface as
    :class:`SceneAccel`: the reference our images are compared against. Every query is
    the scene's, with the same arguments.

    Args:
        scene: the ``mi.Scene``. Mitsuba rebuilds its accelerator itself in
            ``params.update()``, so :meth:`update` has nothing to do.
    """

    name = "native"

    def __init__(self, scene):
        self.scene = scene

    def update(self):
        """Nothing to do: ``params.update()`` already rebuilt Mitsuba's accelerator.

        Returns:
            self.
        """
        return self

    def _preliminary(self, ray, coherent, active, reorder):
        return self.scene.ray_intersect_preliminary(ray, coherent, *reorder, active)

    def _intersect(self, ray, ray_flags, coherent, active, reorder):
        return self.scene.ray_intersect(ray, ray_flags, coherent, *reorder, active)

    def _test(self, ray, coherent, active):
        return self.scene.ray_test(ray, coherent, active)


# ---------------------------------------------------------------------------------------
# Groups of meshes sharing one BVH
# ---------------------------------------------------------------------------------------


class MeshGroup:
    """Meshes of a scene that share one BVH, and what the last update did to it.

    Args:
        name: what the group is called in statistics (``"static"``, ``"dynamic"``).

    Attributes:
        name: as given.
        indices: indices into ``scene.shapes()`` of the group's meshes, ascending.
        geometry: the :class:`SceneGeometry` of the meshes as last built or refit.
        bvh: the group's :class:`hlbvh.BVH`; None while the group has no triangles.
        built_sah: SAH cost of the group's last build, against which ``"auto"``
            measures a refit tree's drift.
        builds, refits: how often the group was built and refit so far.
        last: what the group's last update did: ``decision`` (one of
            :data:`DECISIONS`), ``ms`` (wall time, device synchronised, including the
            packing of the traversal records), ``triangles``, ``sah_cost`` (of the tree
            now; None without triangles), ``seeded`` (a build whose CSD sort started
            from the previous tree's order), ``drift`` (a refit tree's SAH cost over
            ``built_sah``; None when the update did not refit).
    """

    def __init__(self, name: str):
        self.name = name
        self.indices: tuple = ()
        self.geometry = None
        self.bvh = None
        self.built_sah = None
        self.builds = 0
        self.refits = 0
        self.last = None
        self._built_indices = ()  # the meshes the tree was built over
        self.keep()

    @property
    def triangles(self) -> int:
        return 0 if self.geometry is None else self.geometry.prim_count

    @property
    def stale(self) -> bool:
        """Whether the group's meshes are not those its BVH was built over (they
        changed, and the build that followed failed or has not run yet)."""
        return self.indices != self._built_indices

    def update(self, shapes, build_options: dict, policy: UpdatePolicy, reshaped: bool,
               decision: str = "rebuild"):
        """Bring the BVH up to date with the meshes' current buffers.

        Args:
            shapes: ``scene.shapes()``.
            build_options: options of :func:`hlbvh.build`.
            policy: the :class:`UpdatePolicy`.
            reshaped: the meshes' faces or vertex counts changed (forces a rebuild; so
                does a change of :attr:`indices` since the last build).
            decision: what to call a rebuild in :attr:`last` (``"build"`` for the
                accelerator's first one).
        """
        start = _clock()
        seeded, drift = False, None
        reshaped = reshaped or self.bvh is None or self.stale
        if reshaped or policy.update in ("rebuild", "fresh"):
            seeded = self._build(shapes, build_options, seed=policy.update != "fresh")
        else:
            drift = self._refit(shapes)
            decision = "refit"
            if policy.update == "auto" and drift > policy.refit_tolerance:
                seeded = self._build(shapes, build_options)
                decision = "rebuild"
        self.last = dict(
            decision=decision, ms=_clock() - start, triangles=self.triangles,
            sah_cost=None if self.bvh is None else float(self.bvh.stats.sah_cost),
            seeded=seeded, drift=drift,
        )

    def keep(self):
        """Record that the last update left the group as it was."""
        self.last = dict(
            decision="kept", ms=0.0, triangles=self.triangles,
            sah_cost=None if self.bvh is None else float(self.bvh.stats.sah_cost),
            seeded=False, drift=None,
        )

    def root_box(self) -> tuple[list, list]:
        """Lower and upper corner of the BVH's root box, as Python floats."""
        return ([float(c[0]) for c in self.bvh.node_min],
                [float(c[0]) for c in self.bvh.node_max])

    def _build(self, shapes, build_options, seed: bool = True) -> bool:
        """A new BVH over the meshes' current triangles, its CSD sort seeded with the
        previous tree's order when ``seed`` and the triangle count is unchanged; whether
        it was. On failure the group is left as it was (and rebuilds on its next
        update)."""
        previous = self.bvh if seed else None
        geometry = collect_geometry(shapes, self.indices)
        bvh = None
        if geometry.prim_count:
            try:
                bvh = build(geometry.vertices, geometry.faces, previous=previous, **build_options)
            except ValueError as error:
                raise _named_error(shapes, self.indices, error) from error
        self.geometry, self.bvh, self._built_indices = geometry, bvh, self.indices
        self.built_sah = None if bvh is None else bvh.stats.sah_cost
        self.builds += 1
        return bvh is not None and previous is not None and previous.prim_count == bvh.prim_count

    def _refit(self, shapes) -> float:
        """The same tree with boxes for the meshes' new positions; its SAH drift."""
        vertices = _concat([shapes[i].vertex_positions_buffer() for i in self.indices])
        try:
            self.bvh.refit(vertices)
        except ValueError as error:
            raise _named_error(shapes, self.indices, error) from error
        self.geometry.vertices = vertices
        self.refits += 1
        return self.bvh.stats.sah_cost / self.built_sah


# ---------------------------------------------------------------------------------------
# Our accelerator
# ---------------------------------------------------------------------------------------


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
        start = _clock()
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
                static_options = dict(options)
                if policy.static_builder != "same":
                    static_options["builder"] = policy.static_builder
                self.static.update(self.shapes, static_options, policy, reshaped=True)
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
            ms=_clock() - start,
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
