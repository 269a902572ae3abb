"""``hlbvh_prb``: Mitsuba's ``prb`` (path replay backpropagation) with every ray query
through an hlbvh intersector, so that a shape optimisation's mesh, rewritten every
iteration, is followed by our accelerator instead of Mitsuba's whole-scene rebuild."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from hlbvh.accel.keys import camera_ray
from .common import AccelIntegrator, mis_weight, skip_area_emitters

_ad = mi.ad.integrators.common  # Mitsuba's differentiable-integrator base classes


def _preliminary(accel, ray, coherent, active):
    """The closest hit along ``ray`` found without derivatives, as Mitsuba's scene
    finds it: the ray is detached, the hit's fields carry no gradient; only the
    surface interaction computed from it is attached to the shapes' parameters."""
    return accel.ray_intersect_preliminary(dr.detach(ray), coherent, active)


#: The most memory the primal pass's answers kept for the replay may take; beyond it
#: the replay traces its rays again.
REPLAY_CACHE_BYTES = 1 << 30
#: Bytes a path keeps per vertex: a preliminary intersection (eight 32-bit words) and a
#: shadow ray's answer.
_BYTES_PER_VERTEX = 36
#: Vertices per path the answers' store holds at first; it doubles while paths go on
#: past it, so that its size follows the deepest path of the render, not max_depth.
REPLAY_FIRST_DEPTHS = 8


class _Traced:
    """A pass's ray queries, traced (a plain render, a forward pass, or a backward pass
    whose answers do not fit): the interface :class:`_ReplayHits` keeps them through."""

    def closest(self, accel, slot, ray, coherent, active, replay: bool):
        """The closest hit of vertex ``slot`` along ``ray`` (:func:`_preliminary`)."""
        return _preliminary(accel, ray, coherent, active)

    def shadow(self, accel, slot, ray, active, replay: bool):
        """Whether the shadow ray of vertex ``slot``'s emitter sample is blocked."""
        return accel.ray_test(ray, active)

    def keep_camera(self, pi):
        """Keep what the camera ray found (slot 0), after hidden emitters were skipped."""

    def stretches(self):
        """The path loop's stretches, one loop each: here one, the whole path."""
        yield

    def goes_on(self, active, depth):
        """The path loop's condition in the current stretch: the lanes still active."""
        return active

    def stretch_ended(self, active, sampler, state):
        """After a stretch, with the lanes still ``active`` and the loop's ``state``
        (the sampler apart): nothing to do when the loop ran in one stretch."""


class _ReplayHits(_Traced):
    """The answers of a backward pass's primal queries, kept for its replay, which
    traces the same rays (same sampler, same seed): slot ``d`` holds what a path's
    vertex ``d`` was found by (slot 0: the camera ray, past hidden emitters), and the
    answer of the shadow ray of its emitter sample. The replay then asks the
    intersector nothing but the points of textured emitters, instead of tracing every
    ray of the primal pass again.

    The store is sized by the paths, not by ``max_depth``: the primal pass runs its
    loop in stretches, the first of :data:`REPLAY_FIRST_DEPTHS` vertices; while a path
    is still active at a stretch's end, the loop's state is evaluated, the store
    doubles (up to ``max_depth``) and the next stretch continues the paths. Where the
    doubled store would pass :data:`REPLAY_CACHE_BYTES`, it is given up: the rest of
    the primal pass is traced in one stretch and so is the replay (:attr:`kept`)."""

    def __init__(self, n: int, max_depth: int):
        self.n = n
        self.loops = self._loops(max_depth)
        self.depths = self._first_depths(max_depth)
        self.hits = dr.zeros(mi.PreliminaryIntersection3f, n * (self.depths + 1))
        self.occluded = dr.zeros(mi.Bool, n * self.depths)
        self.lane = dr.arange(mi.UInt32, n)
        self.kept = True        # the store holds every answer the replay reads
        self.recorded = False   # the primal pass has ended
        self._more = False      # a path went on past the store's last stretch

    @staticmethod
    def _loops(max_depth: int) -> int:
        """Iterations of a path's loop at most: it runs at least once (``max_depth`` 0
        too); it keeps vertices 0..loops-1 and the hit of the ray leaving the last
        (inactive, but written)."""
        return max(max_depth, 1)

    @classmethod
    def _first_depths(cls, max_depth: int) -> int:
        """Vertices a path keeps in the first stretch."""
        return min(cls._loops(max_depth), REPLAY_FIRST_DEPTHS)

    @staticmethod
    def _fits(n: int, depths: int) -> bool:
        """Whether ``n`` paths may keep the answers of ``depths`` vertices each
        (:data:`REPLAY_CACHE_BYTES`)."""
        return n * (depths + 1) * _BYTES_PER_VERTEX <= REPLAY_CACHE_BYTES

    @classmethod
    def fits(cls, n: int, max_depth: int) -> bool:
        """Whether a render of ``n`` paths may keep its answers of the first stretch."""
        return cls._fits(n, cls._first_depths(max_depth))

    def _index(self, slot, last: int):
        """Where path lanes keep slot ``slot`` (clamped to ``last``: a write past the
        buffer would corrupt memory, whatever a path did)."""
        return dr.minimum(mi.UInt32(slot), last) * self.n + self.lane

    def closest(self, accel, slot, ray, coherent, active, replay: bool):
        """The closest hit of vertex ``slot`` (a UInt32 per path): kept in the primal
        pass, read back in the replay."""
        if replay:
            return dr.gather(mi.PreliminaryIntersection3f, self.hits,
                             self._index(slot, self.depths))
        pi = _preliminary(accel, ray, coherent, active)
        if self.kept:
            dr.scatter(self.hits, pi, self._index(slot, self.depths))
        return pi

    def shadow(self, accel, slot, ray, active, replay: bool):
        """Whether the shadow ray of vertex ``slot``'s emitter sample is blocked."""
        if replay:
            return dr.gather(mi.Bool, self.occluded, self._index(slot, self.depths - 1)) & active
        occluded = accel.ray_test(ray, active)
        if self.kept:
            dr.scatter(self.occluded, occluded, self._index(slot, self.depths - 1))
        return occluded

    def keep_camera(self, pi):
        dr.scatter(self.hits, pi, self.lane)

    def stretches(self):
        """The primal pass's stretches: one, then one more per doubling of the store
        while paths go on (:meth:`stretch_ended`); the replay's loop runs in one."""
        if self.recorded:
            yield
            return
        yield
        while self._more:
            self._grow()
            yield
        self.recorded = True

    def goes_on(self, active, depth):
        """The primal pass's lanes active with a vertex left in the store (a path's
        depth is its loop iteration while it is active); every active lane where the
        store reaches ``max_depth``, or once it was given up, and in the replay."""
        if self.recorded or not self.kept or self.depths >= self.loops:
            return active
        return active & (depth < self.depths)

    def stretch_ended(self, active, sampler, state):
        """The loop's state evaluated (the next stretch starts from it, in a kernel of
        its own) where a path goes on past the store; whether one does."""
        self._more = False
        if not self.recorded and self.kept and self.depths < self.loops:
            sampler.schedule_state()
            dr.eval(active, state, self.hits, self.occluded)
            self._more = bool(dr.any(active))

    def _grow(self):
        """The store doubled (up to ``max_depth`` vertices), its slots copied; given up
        (:attr:`kept` false) where the doubled one would not fit."""
        depths = min(2 * self.depths, self.loops)
        if not self._fits(self.n, depths):
            self.kept, self.hits, self.occluded = False, None, None
            return
        self.hits = self._grown(mi.PreliminaryIntersection3f, self.hits, depths + 1)
        self.occluded = self._grown(mi.Bool, self.occluded, depths)
        self.depths = depths

    def _grown(self, kind, kept, slots: int):
        """``kept`` copied to the first slots of a store of ``slots`` slots (slot-major,
        so its slots keep their places)."""
        grown = dr.zeros(kind, self.n * slots)
        dr.scatter(grown, kept, dr.arange(mi.UInt32, dr.width(kept)))
        return grown


def _attached_emitter_sample(accel, scene, si, ds, em_weight, active):
    """The emitter sample ``ds`` and its weight, drawn without derivatives, attached
    again (as ``prb`` does in its replay): the direction follows the shading point
    (and, for a textured area emitter, the point it hits on the emitter, found
    through the intersector), the weight is the emitter's value re-evaluated with
    derivatives over the detached pdf, and the solid angle to area change of
    variables follows a moving shading point."""
    flags = ds.emitter.flags()
    on_surface = mi.has_flag(flags, mi.EmitterFlags.Surface)
    infinite = mi.has_flag(flags, mi.EmitterFlags.Infinite)
    textured = active & on_surface & mi.has_flag(flags, mi.EmitterFlags.SpatiallyVarying)

    # A ray that starts just short of the emitter point (its visibility is known)
    ray = si.spawn_ray_to(ds.p)
    ray.o = dr.fma(ray.d, ray.maxt, ray.o)
    ray.maxt = dr.largest(ray.maxt)
    si_em = accel.surface_interaction(_preliminary(accel, ray, False, textured), ray,
                                      mi.RayFlags.All, textured)
    attached = dr.select(textured, mi.DirectionSample3f(scene, si_em, si),
                         dr.zeros(mi.DirectionSample3f))
    attached.d = dr.select(textured, attached.d, dr.normalize(ds.p - si.p))
    attached.d = dr.select(infinite, ds.d, attached.d)
    ds = dr.replace_grad(ds, attached)

    jacobian = _ad.solid_angle_to_area_jacobian(si.p, dr.detach(ds.p), dr.detach(ds.n),
                                                active & on_surface)
    value = scene.eval_emitter_direction(si, ds, active)
    inv_pdf = dr.select(ds.pdf != 0, dr.rcp(ds.pdf), 0)
    em_weight = dr.replace_grad(em_weight, value * dr.detach(inv_pdf))
    return ds, em_weight * dr.relative_grad(jacobian)


def _vertex_radiance(si, si_next, ray_next, bsdf, bsdf_ctx, L, Le, Lr_dir, active):
    """The radiance leaving vertex ``si`` with its derivatives: the emission ``Le``
    and emitter sample ``Lr_dir`` (attached already), plus the radiance reflected
    from the rest of the path, ``L`` (known from the primal pass, detached), carried
    by the relative derivatives of the BSDF value towards the next vertex ``si_next``
    and of the solid angle to area change of variables (which move with the
    vertices)."""
    next_valid = si_next.is_valid()
    jacobian = _ad.solid_angle_to_area_jacobian(si.p, si_next.p, si_next.n,
                                                active & next_valid)
    wo_world = dr.replace_grad(ray_next.d, dr.select(next_valid,
                                                     dr.normalize(si_next.p - si.p),
                                                     ray_next.d))
    bsdf_val = bsdf.eval(bsdf_ctx, si, si.to_local(wo_world), active)
    return Le + Lr_dir + L * dr.relative_grad(bsdf_val) * dr.relative_grad(jacobian)


def _emitter_radiance(accel, scene, sampler, si, bsdf, bsdf_ctx, β, primal: bool,
                      active, queries=_Traced(), slot=None):
    """``Lr_dir``: the radiance an emitter sample brings to ``si`` through the BSDF,
    weighted by multiple importance against BSDF sampling, its visibility tested
    through the intersector (Mitsuba's ``test_visibility=True``); in the replay the
    sample is attached again (:func:`_attached_emitter_sample`) and the value
    carries derivatives. ``queries``: how the pass asks (:class:`_Traced`, or the
    answers kept for the replay, vertex ``slot``)."""
    ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), False, active)
    active = active & (ds.pdf != 0.0)
    shadow_ray = dr.detach(si.spawn_ray_to(ds.p))
    occluded = queries.shadow(accel, slot, shadow_ray, active, replay=not primal)
    em_weight[occluded] = 0.0
    ds.pdf[occluded] = 0.0
    active &= ~occluded

    with dr.resume_grad(when=not primal):
        if not primal:
            ds, em_weight = _attached_emitter_sample(accel, scene, si, ds, em_weight, active)
        wo = si.to_local(ds.d)
        bsdf_value_em, bsdf_pdf_em = bsdf.eval_pdf(bsdf_ctx, si, wo, active)
        mis_em = dr.select(ds.delta, 1, mis_weight(ds.pdf, bsdf_pdf_em))
        return β * mis_em * bsdf_value_em * em_weight


def _propagated(mode, δL, si, si_next, ray_next, bsdf, bsdf_ctx, L, Le, Lr_dir, active):
    """``δL`` after the derivatives of the radiance leaving vertex ``si``
    (:func:`_vertex_radiance`, recorded with gradients resumed) are propagated:
    backward from ``δL * Lo`` (``δL`` unchanged), or forward, ``δL`` plus ``Lo``'s
    derivative.

    Raises:
        ValueError: in a symbolic render, that radiance depends on no parameter
            (no scene parameter prb differentiates has gradients enabled).
    """
    with dr.resume_grad():
        Lo = _vertex_radiance(si, si_next, ray_next, bsdf, bsdf_ctx, L, Le, Lr_dir, active)
        if dr.flag(dr.JitFlag.SymbolicCalls) and not dr.grad_enabled(Lo):
            raise ValueError(
                "hlbvh_prb: the render's derivative depends on no parameter: "
                "enable gradients (dr.enable_grad) on a scene parameter that prb "
                "differentiates")
        if mode == dr.ADMode.Backward:
            dr.backward_from(δL * Lo)
            return δL
        return δL + dr.forward_to(Lo)


class PRBIntegrator(_ad.RBIntegrator):
    r"""
    .. _integrator-hlbvh_prb:

    Path replay backpropagation through an hlbvh intersector (:monosp:`hlbvh_prb`)
    -----------------------------------------------------------------------------

    .. pluginparameters::

     * - accel, builder, leaf_size, morton_bits, quantization, coarse_bits, p,
         sah_bins, static, moving, update, ...
       - |string| / |int|
       - The intersector and its options, as for ``hlbvh_path``.
     * - max_depth, rr_depth, hide_emitters
       - |int| / |bool|
       - As for Mitsuba's ``prb`` (defaults 6, 5 and |false|).

    The algorithm of Mitsuba's ``prb``: a primal pass, then a replay of the same paths
    (same sampler, same seed) that propagates derivatives vertex by vertex, in forward
    mode (``render_forward``) or backward mode (``render_backward``), through
    ``mi.render(scene, params)`` and Mitsuba's optimisers alike. It has ``prb``'s
    limits: no projective sampling (visibility discontinuities are not
    differentiated) and detached BSDF sampling.

    In backward mode the replay does not trace its rays again: the primal pass keeps
    what each of its queries answered, in a store as deep as its deepest path (not
    ``max_depth``), and the replay reads it back (where it fits in
    :data:`REPLAY_CACHE_BYTES`).

    The rays go through the chosen intersector: camera and continuation rays, shadow
    rays of emitter samples (Mitsuba's ``test_visibility=True`` would trace them
    through the scene), the rays past hidden area emitters and the rays that locate a
    textured area emitter's point. Every hit is found on a detached ray and expanded
    by Mitsuba (``compute_surface_interaction``), which attaches the interaction to
    the mesh's vertex positions as Mitsuba's own ``ray_intersect`` does; so
    derivatives reach vertex positions and every parameter ``prb`` differentiates.

    The accelerator is brought up to date at the start of ``render``,
    ``render_forward`` and ``render_backward``; with ``accel="hlbvh"``,
    ``hlbvh.traverse(scene)``'s ``update(optimizer)`` skips Mitsuba's rebuild and the
    meshes the optimiser rewrites become the moving ones. With the same seed,
    ``accel="native"`` gives ``prb``'s image and gradients.

    .. tabs::

        .. code-tab:: python

            'type': 'hlbvh_prb',
            'accel': 'hlbvh',
            'max_depth': 3
    """

    def __init__(self, props):
        super().__init__(props)
        # The intersector and its options, kept by an AccelIntegrator: a nanobind
        # class takes one base, so this class cannot also derive from it.
        self._tracer = AccelIntegrator(props)
        self._tracer.max_depth = self.max_depth  # the depth its ray budget reads
        # Inside render_backward: the primal pass keeps its answers for the replay
        self._keep_hits, self._hits = False, None

    @property
    def accel_name(self) -> str:
        """``"hlbvh"`` or ``"native"`` (what :func:`hlbvh.traverse` reads)."""
        return self._tracer.accel_name

    def update_accel(self, scene, *args, **kwargs):
        """:meth:`AccelIntegrator.update_accel`, without derivative tracking: the
        meshes' vertex buffers may be an optimiser's parameters, and a build or refit
        over them must record nothing."""
        with dr.suspend_grad():
            return self._tracer.update_accel(scene, *args, **kwargs)

    def accel(self, scene):
        """:meth:`AccelIntegrator.accel`: the intersector as the last update left it."""
        return self._tracer.accel(scene)

    def updated(self):
        """:meth:`AccelIntegrator.updated`: a block whose renders trust the
        accelerator the caller just brought up to date."""
        return self._tracer.updated()

    def _bring_up_to_date(self, scene):
        """Update the accelerator at the start of a render, as
        :meth:`AccelIntegrator.render` does (not inside an :meth:`updated` block):
        both passes of a differentiable render (the primal pass and its replay) then
        trace the same accelerator, taken by ``sample()`` without another look."""
        with dr.suspend_grad():
            self._tracer.sample_accel(scene)

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        self._bring_up_to_date(scene)
        return super().render(scene, sensor, seed, spp, develop, evaluate)

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        self._bring_up_to_date(scene)
        self._refuse_blur()
        return super().render_forward(scene, params, sensor, seed, spp)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        """Mitsuba's backward pass (a primal pass, then its replay), the primal pass's
        ray answers kept for the replay (:class:`_ReplayHits`) where they fit."""
        self._bring_up_to_date(scene)
        self._refuse_blur()
        self._keep_hits, self._hits = True, None
        try:
            return super().render_backward(scene, params, grad_in, sensor, seed, spp)
        finally:
            self._keep_hits, self._hits = False, None

    def _refuse_blur(self):
        """Refuse derivatives through meshes with motion keys: their hits are shaded at
        each ray's time from the keys, which carry no derivative to the mesh's
        parameters (a primal render of them is fine)."""
        accel = self._tracer.scene_accel
        if accel is not None and accel.dynamic.keyed is not None:
            raise ValueError("hlbvh_prb: a moving mesh has motion keys (an open shutter); "
                             "derivatives through a blurred mesh are not supported: render "
                             "its gradients with the shutter closed (no keys)")

    def _queries(self, primal: bool, n: int):
        """How a pass of ``n`` paths asks: the answers it keeps (a backward pass's
        primal pass) or replays (its replay), else :class:`_Traced` (a plain render, a
        forward pass, or too many paths)."""
        if not self._keep_hits:
            return _Traced()
        if primal:
            self._hits = _ReplayHits(n, self.max_depth) if _ReplayHits.fits(
                n, self.max_depth) else None
            return self._hits or _Traced()
        hits = self._hits
        return hits if hits is not None and hits.kept and hits.n == n else _Traced()

    @dr.syntax
    def sample(self, mode, scene, sampler, ray, δL, state_in, active, **kwargs):
        """One path per ray, as ``prb`` traces it: in ``dr.ADMode.Primal`` the
        radiance; otherwise the replay, which starts from the primal radiance
        ``state_in`` and subtracts each vertex's contribution while propagating its
        derivatives (``δL``: the adjoint radiance in backward mode; the returned
        derivative in forward mode). Returns (radiance or its derivative, valid,
        no AOVs, the primal radiance)."""
        accel = self.accel(scene)
        ray = camera_ray(scene, ray)
        primal = mode == dr.ADMode.Primal
        bsdf_ctx = mi.BSDFContext()

        # --------------------- Loop state ---------------------

        ray = mi.Ray3f(dr.detach(ray))
        depth = mi.UInt32(0)
        L = mi.Spectrum(0 if primal else state_in)    # radiance (replay: what remains)
        δL = mi.Spectrum(δL if δL is not None else 0)  # adjoint / derivative radiance
        β = mi.Spectrum(1)                             # path throughput
        η = mi.Float(1)                                # product of relative IORs
        active = mi.Bool(active)
        queries = self._queries(primal, dr.width(ray))
        replay = not primal and isinstance(queries, _ReplayHits)
        if dr.hint(replay, mode="scalar"):
            # The primal pass's kernel, once, with what the replay reads of it
            dr.eval(state_in, queries.hits, queries.occluded)
            pi = queries.closest(accel, 0, ray, True, active, replay=True)
        else:  # kept after hidden emitters are skipped (keep_camera)
            pi = _preliminary(accel, ray, True, active)    # camera rays are coherent

        ray_prev = mi.Ray3f(ray)
        pi_prev = dr.zeros(mi.PreliminaryIntersection3f)
        si_prev = dr.zeros(mi.SurfaceInteraction3f)
        bsdf_pdf_prev = mi.Float(1.0)
        bsdf_delta_prev = mi.Bool(True)

        if dr.hint(self.hide_emitters and not replay, mode="scalar"):
            # Continue past every area emitter the camera ray meets first
            skip = pi.is_valid() & (pi.shape.emitter() != None) & active  # noqa: E711
            si_skip = accel.surface_interaction(pi, ray, mi.RayFlags.Minimal, skip)
            pi[skip] = skip_area_emitters(accel, si_skip.spawn_ray(ray.d), True, skip)
        if dr.hint(not replay, mode="scalar"):
            queries.keep_camera(pi)

        for _ in queries.stretches():  # one stretch; more where the kept answers grow
            while dr.hint(queries.goes_on(active, depth), max_iterations=self.max_depth,
                          label=f"hlbvh_prb ({mode.name})"):
                active_next = mi.Bool(active)

                # The interaction, attached to the shapes' parameters when differentiating
                with dr.resume_grad(when=not primal):
                    si = accel.surface_interaction(pi, ray, mi.RayFlags.All)
                    if dr.hint(not primal, mode="scalar"):
                        if depth >= 1:
                            # The incoming direction follows the previous vertex's motion
                            si_prev = dr.replace_grad(si_prev, accel.surface_interaction(
                                pi_prev, ray_prev, mi.RayFlags.Minimal))
                            here = dr.detach(si)
                            si.wi = dr.replace_grad(
                                si.wi, here.to_local(dr.normalize(si_prev.p - here.p)))

                bsdf = si.bsdf(ray)

                # --------------------- Emission hit by the last bounce ---------------------

                if dr.hint(self.hide_emitters, mode="scalar"):
                    active_next &= ~((depth == 0) & ~si.is_valid())
                ds = mi.DirectionSample3f(scene, si=si, ref=si_prev)
                mis = mis_weight(bsdf_pdf_prev,
                                 scene.pdf_emitter_direction(si_prev, ds, ~bsdf_delta_prev))
                with dr.resume_grad(when=not primal):
                    Le = β * mis * ds.emitter.eval(si, active_next)

                # --------------------- Emitter sample ---------------------

                active_next &= (depth + 1 < self.max_depth) & si.is_valid()
                active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                Lr_dir = _emitter_radiance(accel, scene, sampler, si, bsdf, bsdf_ctx, β, primal,
                                           active_em, queries, depth)

                # --------------------- BSDF sample (detached) ---------------------

                bsdf_sample, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(),
                                                       sampler.next_2d(), active_next)
                L = (L + Le + Lr_dir) if primal else (L - Le - Lr_dir)
                ray_next = si.spawn_ray(si.to_world(bsdf_sample.wo))
                η *= bsdf_sample.eta
                β *= bsdf_weight
                si_prev = dr.detach(si, True)
                bsdf_pdf_prev = bsdf_sample.pdf
                bsdf_delta_prev = mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta)

                # --------------------- Russian roulette ---------------------

                β_max = dr.max(mi.unpolarized_spectrum(β))
                active_next &= β_max != 0
                rr_prob = dr.minimum(β_max * η**2, 0.95)
                rr_active = depth >= self.rr_depth
                β[rr_active] *= dr.rcp(rr_prob)
                rr_continue = sampler.next_1d() < rr_prob
                active_next &= ~rr_active | rr_continue

                pi_next = queries.closest(accel, depth + 1, ray_next, False, active_next, replay)

                # --------------------- Derivatives of this vertex ---------------------

                if dr.hint(not primal, mode="scalar"):
                    si_next = accel.surface_interaction(pi_next, ray_next, mi.RayFlags.Minimal,
                                                        active_next)
                    δL = _propagated(mode, δL, si, si_next, ray_next, bsdf, bsdf_ctx, L, Le,
                                     Lr_dir, active_next)

                # Group lanes by the shape they hit next (CUDA; a no-op on LLVM)
                hint = dr.reinterpret_array(mi.UInt32, pi_next.shape)
                depth = dr.reorder_threads((hint << 1) | dr.select(active_next, 1, 0), 16, depth)

                depth[si.is_valid()] += 1
                active = active_next
                pi_prev, pi = pi, pi_next
                ray_prev, ray = ray, ray_next
            queries.stretch_ended(active, sampler, (
                ray, depth, L, δL, β, η, pi, ray_prev, pi_prev, si_prev, bsdf_pdf_prev,
                bsdf_delta_prev))

        return (L if primal else δL), depth != 0, [], L

    def to_string(self):
        return (f"hlbvh_prb[{self._tracer._options_string()}, max_depth={self.max_depth}, "
                f"rr_depth={self.rr_depth}]")


mi.register_integrator("hlbvh_prb", lambda props: PRBIntegrator(props))
