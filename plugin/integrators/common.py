"""What every hlbvh integrator shares: the ``accel`` parameter and the accelerator's
options (the builder's and the per-frame update policy) read from the scene
description, the intersector built on the first render of a scene, kept and updated
at the start of every render, and the path-tracing helpers (MIS weight, skipping of
directly visible area emitters) written against an intersector instead of the scene.

The module is reloaded by :func:`hlbvh.register` after a variant change, so that
:class:`AccelIntegrator` derives from the current variant's ``mi.SamplingIntegrator``.
"""

from __future__ import annotations

import contextlib

import drjit as dr
import mitsuba as mi

from hlbvh.accel import NativeAccel, SceneAccel
from hlbvh.accel.choice import RayBudget
from hlbvh.timing import clock_ms
from hlbvh.accel.policy import ACCELS, BUILD_OPTIONS, UPDATE_OPTIONS, split_options


class AccelIntegrator(mi.SamplingIntegrator):
    """A sampling integrator whose ray queries go through an hlbvh intersector.

    Properties (besides ``mi.SamplingIntegrator``'s):
        accel: ``"hlbvh"`` (default) or ``"native"``.
        builder, leaf_size, morton_bits, quantization, coarse_bits, p, sah_bins:
            options of :func:`hlbvh.build` (see :class:`hlbvh.BuildConfig`).
        static: what traces the shapes that do not move: ``"native"`` (default: the
            scene's own accelerator over a sub-scene of them, any shape type; only
            what moves goes through our BVH) or ``"hlbvh"`` (every mesh through our
            watertight traversal).
        moving: ids of the shapes that will move, comma separated (they skip the
            static structure from the start).
        update, refit_tolerance, static_builder, static_leaf_size: the per-frame policy
            of the accelerator (``"auto"``, the default, ``"rebuild"``, ``"fresh"`` or
            ``"refit"``; the SAH drift ``"auto"`` accepts, default 1.05; the builder
            and leaf size of the static group with ``static="hlbvh"``;
            see :class:`hlbvh.accel.policy.UpdatePolicy`).

    The accelerator is built on the first render of a scene and kept for the next
    renders of that scene; it is built anew when another scene is rendered, and
    updated (only what moved) when a shape of the scene changed (``params.update()``,
    or the cheaper update of :func:`hlbvh.traverse`).
    """

    def __init__(self, props):
        super().__init__(props)
        if not dr.is_jit_v(mi.Float):
            raise ValueError(
                f"hlbvh integrators need a JIT variant (llvm_* or cuda_*), not "
                f"{mi.variant()!r}: call mi.set_variant(...) and hlbvh.register()"
            )
        self.accel_name = props.get("accel", "hlbvh")
        if self.accel_name not in ACCELS:
            raise ValueError(
                f"integrator property accel={self.accel_name!r}: expected one of {ACCELS}"
            )
        self.accel_options = {name: props[name] for name in BUILD_OPTIONS + UPDATE_OPTIONS
                              if name in props}
        self._policy, self._config = split_options(self.accel_options)  # parsed once
        self._accel = None
        self._budget = None  # the ray budget of the render being prepared (update_accel)
        self._rendering = False  # inside render (see render)
        self._updated = False  # inside updated() (see render)

    def update_accel(self, scene, sensor=0, spp: int = 0):
        """Bring the intersector of ``scene`` up to date for a render of ``sensor`` at
        ``spp`` samples per pixel (0: the sensor's sampler's) and return it.

        ``"native"``: a :class:`~hlbvh.NativeAccel`, made per call (it costs nothing,
        and a cached one would keep the scene alive through the scene's reference to
        this integrator). ``"hlbvh"``: a :class:`~hlbvh.SceneAccel`, built on the first
        call for a scene, built anew for another scene, and asked to prepare for this
        render (:meth:`~SceneAccel.prepare`: only the meshes whose buffers changed
        updated, a look at each mesh's buffers when none did; what traces the moving
        meshes chosen for this render's ray budget of film, samples and depth; where
        that is the whole scene, ``"scene"``, the scene's own accelerator rebuilt if
        anything moved, and :meth:`accel` hands out the scene's own queries); its
        ``prepared`` says what this call did.
        """
        if self.accel_name == "native":
            return NativeAccel(scene)
        sensor = _sensor(scene, sensor)
        self._budget = self.ray_budget(scene, sensor, spp)
        if self._accel is None or not self._accel.is_for(scene):
            self._accel = SceneAccel(scene, policy=self._policy, config=self._config)
        self._accel.prepare(scene, self._budget, sensor)
        return self._accel

    def accel(self, scene):
        """The intersector of ``scene`` as the last :meth:`update_accel` left it (the one
        :meth:`render` traces), without looking at the meshes; built by
        :meth:`update_accel` only when none exists for ``scene`` yet (``sample`` called
        outside a render). The scene's own queries where the whole scene traces the
        moving meshes (``"scene"``)."""
        if self.accel_name == "hlbvh" and self._accel is not None and self._accel.is_for(scene):
            if self._accel.moving_structure == "scene":  # instances expanded as ours are
                return NativeAccel(scene, shading=self._accel.shading)
            return self._accel
        return self.update_accel(scene)

    @property
    def scene_accel(self) -> SceneAccel | None:
        """The :class:`~hlbvh.SceneAccel` this integrator keeps (None with
        ``accel="native"`` or before a render): its groups and ``last_update``, whatever
        :meth:`accel` hands out (the scene's own queries where the whole scene traces
        the moving meshes)."""
        return self._accel

    def ray_budget(self, scene, sensor=0, spp: int = 0) -> RayBudget:
        """What a render of ``sensor`` (an index or a sensor) at ``spp`` samples per pixel
        (0: its sampler's) traces: film pixels times samples, and this integrator's
        depth (``max_depth``; 1 for integrators without one)."""
        sensor = _sensor(scene, sensor)
        if sensor is None:
            return RayBudget(samples=0, depth=1)
        size = sensor.film().crop_size()
        spp = spp or sensor.sampler().sample_count()
        depth = getattr(self, "max_depth", 1)
        return RayBudget(samples=int(size[0]) * int(size[1]) * int(spp),
                         depth=-1 if depth >= 0xFFFFFFFF else int(depth))

    def sample_accel(self, scene):
        """The intersector a ``sample()`` traces: inside this integrator's
        :meth:`render` (or an :meth:`updated` block), the one it brought up to date
        (:meth:`accel`); otherwise brought up to date here (:meth:`update_accel`).
        The second case is a wrapper integrator's render (Mitsuba's ``moment``,
        ``aov``, ``stokes``), which calls this integrator's ``sample()`` directly, so
        a render through the wrapper follows the shapes that moved since the last, and
        traces what :meth:`accel` hands out (the scene's own queries where the whole
        scene traces the moving meshes)."""
        if not (self._rendering or self._updated):
            self.update_accel(scene)
        return self.accel(scene)

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        """Bring the intersector up to date (:meth:`update_accel`), then render as
        Mitsuba's sampling integrator does.

        The update runs before the render's kernel is recorded, so the first render of
        a scene records the same kernel as every later one (a build inside the
        recording changes the kernel: the second render would compile it again).
        """
        if self._rendering:  # Mitsuba's render by sensor index calls this again
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        if self._updated:
            self.accel(scene)
        else:
            self.update_accel(scene, sensor, spp)
        self._rendering = True
        start = clock_ms()
        try:
            image = super().render(scene, sensor, seed, spp, develop, evaluate)
        finally:
            self._rendering = False
        accel = self._accel
        if accel is not None and accel.is_for(scene) and self._budget is not None:
            dr.eval(image)  # what Mitsuba evaluates right after: timed for the choice
            accel.record_render(clock_ms() - start, self._budget.samples)
        return image

    @contextlib.contextmanager
    def updated(self):
        """A block whose renders trust the accelerator that :meth:`update_accel` just
        made: the caller changes no shape inside it, so :meth:`render` skips its look at
        every shape (for a scene of 10k instances, ~0.15 s a render)."""
        self._updated = True
        try:
            yield self
        finally:
            self._updated = False

    def _options_string(self) -> str:
        options = "".join(f", {k}={v!r}" for k, v in self.accel_options.items())
        return f"accel={self.accel_name!r}{options}"


def _sensor(scene, sensor):
    """``sensor``, or the scene's sensor of that index (None where it has none)."""
    if isinstance(sensor, int):
        return scene.sensors()[sensor] if scene.sensors() else None
    return sensor


#: The largest value of a Mitsuba integer property (``max_depth``, ``rr_depth``): Mitsuba
#: stores them as 32-bit signed integers and refuses larger ones, so ours do too.
MAX_INTEGER_PROPERTY = 2**31 - 1


def depth_properties(props) -> tuple[int, int]:
    """``max_depth`` and ``rr_depth`` of a path-tracing integrator, read and checked
    as Mitsuba's ``MonteCarloIntegrator`` reads them: integers (not floats, booleans or
    strings), ``max_depth`` -1 (the default, unbounded, returned as 2^32 - 1) or in
    0 .. :data:`MAX_INTEGER_PROPERTY`, ``rr_depth`` in 1 .. :data:`MAX_INTEGER_PROPERTY`
    (default 5): the values Mitsuba's ``path`` accepts, so a scene loads under ours
    exactly when it loads under Mitsuba's.

    Raises:
        ValueError: naming the property, its value and the range expected.
    """
    depths = []
    for name, default, least, expected in (
            ("max_depth", -1, -1, "-1 (unbounded) or an integer in 0.."),
            ("rr_depth", 5, 1, "an integer in 1..")):
        value = props.get(name, default)
        if (isinstance(value, bool) or not isinstance(value, int)
                or not least <= value <= MAX_INTEGER_PROPERTY):
            raise ValueError(f"{name}={value!r}: expected {expected}{MAX_INTEGER_PROPERTY} "
                             f"(Mitsuba's integer properties are 32-bit)")
        depths.append(value)
    max_depth, rr_depth = depths
    return (max_depth if max_depth != -1 else 0xFFFFFFFF), rr_depth


def mis_weight(pdf_a, pdf_b):
    """Power heuristic (exponent 2) of sampling technique a against b; 0 where it is
    not finite. Detached: MIS weights carry no derivative."""
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    w = a2 / (a2 + b2)
    return dr.detach(dr.select(dr.isfinite(w), w, 0.0))


def spec_fma(a, b, c):
    """``a·b + c`` for spectra: a fused multiply-add, or a Mueller-matrix product and
    a sum in polarized variants."""
    return a * b + c if mi.is_polarized else dr.fma(a, b, c)


def visible_emitter_sample(scene, accel, si, sample, active):
    """An emitter sample from ``si`` with its visibility tested through ``accel``:
    Mitsuba's ``sample_emitter_direction`` with ``test_visibility=True`` would trace
    the shadow ray through the scene's own accelerator instead.

    Args:
        scene: the scene whose emitters are sampled.
        accel: the intersector that tests the shadow ray.
        si: the SurfaceInteraction3f sampled from.
        sample: the Point2f sample.
        active: Bool, the lanes that sample.
    Returns:
        ``(ds, weight, active)``: the DirectionSample3f and emitter weight, both zero
        (``ds.pdf`` included) where the emitter is occluded, and the lanes whose sample
        is valid and visible.
    """
    ds, weight = scene.sample_emitter_direction(si, sample, False, active)
    active = active & (ds.pdf != 0.0)
    occluded = accel.ray_test(si.spawn_ray_to(ds.p), active)
    weight[occluded] = 0.0
    ds.pdf[occluded] = 0.0
    return ds, weight, active & ~occluded


@dr.syntax
def skip_area_emitters(accel, ray, coherent, active):
    """The first hit along ``ray`` that is not on an area emitter.

    Repeatedly intersects ``ray`` and continues past every emitting surface it meets
    (how ``hide_emitters`` hides area lights seen directly), as Mitsuba's
    ``Integrator::skip_area_emitters`` does with the scene.

    Args:
        accel: the intersector.
        ray: Ray3f.
        coherent: forwarded to every query.
        active: Bool, the lanes to process.
    Returns:
        PreliminaryIntersection3f of the first non-emitting surface (or a miss).
    """

    pi = dr.zeros(mi.PreliminaryIntersection3f, dr.width(ray))
    ray = mi.Ray3f(ray)
    active = mi.Bool(active)
    while dr.hint(active, label="hlbvh_skip_area_emitters"):
        pi = accel.ray_intersect_preliminary(ray, coherent)
        active &= pi.is_valid() & (pi.shape.emitter() != None)  # noqa: E711 (JIT compare)
        si = accel.surface_interaction(pi, ray, mi.RayFlags.Minimal, active)
        ray = si.spawn_ray(ray.d)
    return pi
