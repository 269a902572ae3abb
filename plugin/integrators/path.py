"""``hlbvh_path``: Mitsuba's ``path`` integrator with every ray query through an
hlbvh intersector."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from hlbvh.accel.keys import camera_ray
from .common import (AccelIntegrator, depth_properties, mis_weight, skip_area_emitters,
                     spec_fma, visible_emitter_sample)


class PathIntegrator(AccelIntegrator):
    r"""
    .. _integrator-hlbvh_path:

    Path tracer through an hlbvh intersector (:monosp:`hlbvh_path`)
    ---------------------------------------------------------------

    .. pluginparameters::

     * - accel
       - |string|
       - ``"hlbvh"``: trace every ray through one HLBVH built over the scene's meshes
         (plus Mitsuba's own routine for spheres, disks and cylinders).
         ``"native"``: trace through the scene's own accelerator (Embree / OptiX),
         the reference. (Default: ``"hlbvh"``)
     * - builder, leaf_size, morton_bits, quantization, coarse_bits, p, sah_bins
       - |string| / |int|
       - Options of ``hlbvh.build`` (``builder`` is ``"hlbvh"``, ``"lbvh"`` or
         ``"sah"``). Validated even with ``accel="native"``.
     * - max_depth
       - |int|
       - Longest path depth (-1: unbounded). 1 renders only directly visible
         emitters, 2 direct illumination, and so on. (Default: -1)
     * - rr_depth
       - |int|
       - Path depth at which Russian roulette starts. (Default: 5)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: |false|)

    The same algorithm as Mitsuba's C++ ``path`` integrator, step for step: emitter
    sampling and BSDF sampling combined by multiple importance sampling (power
    heuristic), Russian roulette, and the same sampler calls in the same order. The
    only change is where rays go: the emitter sample is drawn without Mitsuba's
    visibility test and its shadow ray is traced through the chosen intersector, as
    are camera rays (``coherent=True``) and continuation rays (``coherent=False``).

    So, with a ``box`` reconstruction filter and the same sampler seed,
    ``accel="native"`` renders bit-identically to ``path``, and ``accel="hlbvh"``
    differs from it only where the two intersectors' hits differ in the last bits
    (or, on edges, in the triangle hit).

    The intersector is built on the first render of a scene and kept; it is updated
    automatically when a mesh of the scene received new buffers through
    ``params.update()``.

    .. tabs::

        .. code-tab:: xml

            <integrator type="hlbvh_path">
                <string name="accel" value="hlbvh"/>
                <string name="builder" value="hlbvh"/>
                <integer name="max_depth" value="8"/>
            </integrator>

        .. code-tab:: python

            'type': 'hlbvh_path',
            'accel': 'hlbvh',
            'builder': 'hlbvh',
            'max_depth': 8
    """

    def __init__(self, props):
        super().__init__(props)
        self.max_depth, self.rr_depth = depth_properties(props)

    @dr.syntax
    def sample(self, scene, sampler, ray, medium=None, active=True):
        if dr.hint(self.max_depth == 0, mode="scalar"):
            return mi.Spectrum(0.0), mi.Bool(False), []
        accel = self.sample_accel(scene)
        bsdf_ctx = mi.BSDFContext()

        # --------------------- Configure loop state ----------------------

        ray = mi.Ray3f(camera_ray(scene, ray))       # Current ray
        throughput = mi.Spectrum(1.0)                # Path throughput weight
        result = mi.Spectrum(0.0)                    # Radiance accumulator
        eta = mi.Float(1.0)                          # Product of relative IOR changes
        depth = mi.UInt32(0)                         # Depth of the current vertex
        valid_ray = mi.Bool(                         # Alpha: did the path see anything?
            not self.hide_emitters and scene.environment() is not None
        )
        prev_si = dr.zeros(mi.Interaction3f)         # Previous vertex
        prev_bsdf_pdf = mi.Float(1.0)                # BSDF pdf of the previous bounce
        prev_bsdf_delta = mi.Bool(True)              # Was it a delta lobe?
        active = mi.Bool(active)                     # Lanes still tracing

        # Camera rays are coherent
        pi = accel.ray_intersect_preliminary(ray, True, active)

        # ---------------------- Hide area emitters ----------------------

        if dr.hint(self.hide_emitters, mode="scalar"):
            skip = pi.is_valid() & (pi.shape.emitter() != None) & active  # noqa: E711
            si = accel.surface_interaction(pi, ray, mi.RayFlags.Minimal, skip)
            pi_after_skip = skip_area_emitters(accel, si.spawn_ray(ray.d), True, skip)
            pi = dr.select(skip, pi_after_skip, pi)

        while dr.hint(active, label="hlbvh_path"):
            si = accel.surface_interaction(pi, ray, mi.RayFlags.All)

            # ---------------------- Direct emission ----------------------

            ds = mi.DirectionSample3f(scene, si, prev_si)
            em_pdf = scene.pdf_emitter_direction(prev_si, ds, ~prev_bsdf_delta)
            mis_bsdf = mis_weight(prev_bsdf_pdf, em_pdf)
            result = spec_fma(throughput, ds.emitter.eval(si, prev_bsdf_pdf > 0.0) * mis_bsdf,
                              result)

            # Continue tracing the path at this point?
            active_next = (depth + 1 < self.max_depth) & si.is_valid()

            bsdf = si.bsdf(ray)

            # ---------------------- Emitter sampling ----------------------

            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds, em_weight, active_em = visible_emitter_sample(
                scene, accel, si, sampler.next_2d(), active_em)
            wo = si.to_local(ds.d)

            # ------ Evaluate BSDF * cos(theta) and sample direction -------

            sample_1 = sampler.next_1d()
            sample_2 = sampler.next_2d()
            bsdf_val, bsdf_pdf, bsdf_sample, bsdf_weight = bsdf.eval_pdf_sample(
                bsdf_ctx, si, wo, sample_1, sample_2)

            # --------------- Emitter sampling contribution ----------------

            bsdf_val = si.to_world_mueller(bsdf_val, -wo, si.wi)
            mis_em = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, bsdf_pdf))
            result[active_em] = spec_fma(throughput, bsdf_val * em_weight * mis_em, result)

            # ---------------------- BSDF sampling ----------------------

            bsdf_weight = si.to_world_mueller(bsdf_weight, -bsdf_sample.wo, si.wi)
            ray = si.spawn_ray(si.to_world(bsdf_sample.wo))

            # ------ Update loop variables based on current interaction ------

            throughput *= bsdf_weight
            eta *= bsdf_sample.eta
            valid_ray |= active & si.is_valid() & ~mi.has_flag(bsdf_sample.sampled_type,
                                                               mi.BSDFFlags.Null)
            prev_si = mi.Interaction3f(si)
            prev_bsdf_pdf = bsdf_sample.pdf
            prev_bsdf_delta = mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta)

            # -------------------- Stopping criterion ---------------------

            depth[si.is_valid()] += 1
            throughput_max = dr.max(mi.unpolarized_spectrum(throughput))
            rr_prob = dr.minimum(throughput_max * dr.square(eta), 0.95)
            rr_active = depth >= self.rr_depth
            rr_continue = sampler.next_1d() < rr_prob
            throughput[rr_active] *= dr.rcp(dr.detach(rr_prob))
            active = active_next & (~rr_active | rr_continue) & (throughput_max != 0.0)

            # Continuation rays are incoherent
            pi = accel.ray_intersect_preliminary(ray, False, active)

        return dr.select(valid_ray, result, 0.0), valid_ray, []

    def to_string(self):
        return (f"hlbvh_path[{self._options_string()}, max_depth={self.max_depth}, "
                f"rr_depth={self.rr_depth}]")


mi.register_integrator("hlbvh_path", lambda props: PathIntegrator(props))
