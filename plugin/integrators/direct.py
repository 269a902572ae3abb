"""``hlbvh_direct``: Mitsuba's ``direct`` integrator with every ray query through an
hlbvh intersector."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from hlbvh.accel.keys import camera_ray
from .common import AccelIntegrator, mis_weight, skip_area_emitters, visible_emitter_sample


def _sample_count(props, name: str, default: int) -> int:
    """The non-negative integer property ``name`` (``default`` when absent)."""
    value = props.get(name, default)
    if value < 0:
        raise ValueError(f"{name}={value}: expected a value >= 0")
    return value


class DirectIntegrator(AccelIntegrator):
    r"""
    .. _integrator-hlbvh_direct:

    Direct illumination through an hlbvh intersector (:monosp:`hlbvh_direct`)
    -------------------------------------------------------------------------

    .. pluginparameters::

     * - accel, builder, leaf_size, morton_bits, quantization, coarse_bits, p,
         sah_bins, static, moving, update, ...
       - |string| / |int|
       - The intersector and its options, as for ``hlbvh_path``.
     * - shading_samples
       - |int|
       - Sets both ``emitter_samples`` and ``bsdf_samples``. (Default: 1)
     * - emitter_samples
       - |int|
       - Emitter samples per camera ray. (Default: ``shading_samples``)
     * - bsdf_samples
       - |int|
       - BSDF samples per camera ray. (Default: ``shading_samples``)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: |false|)

    The algorithm of Mitsuba's C++ ``direct`` integrator: the emitters seen by the
    camera ray, then ``emitter_samples`` emitter samples and ``bsdf_samples`` BSDF
    samples at its first hit, combined by the power heuristic over both techniques'
    sample counts, with the same sampler calls (and masks) in the same order. Its
    rays go through the chosen intersector: the camera ray (``coherent=True``), the
    emitter samples' shadow rays (Mitsuba's ``test_visibility=True`` would trace them
    through the scene) and the BSDF samples' rays.

    So, with a ``box`` reconstruction filter and the same sampler seed,
    ``accel="native"`` renders bit-identically to ``direct``.

    .. tabs::

        .. code-tab:: python

            'type': 'hlbvh_direct',
            'accel': 'hlbvh',
            'emitter_samples': 2,
            'bsdf_samples': 1
    """

    def __init__(self, props):
        super().__init__(props)
        if "shading_samples" in props and ("emitter_samples" in props
                                           or "bsdf_samples" in props):
            raise ValueError("shading_samples cannot be given with emitter_samples or "
                             "bsdf_samples (it sets both)")
        shading = _sample_count(props, "shading_samples", 1)
        self.emitter_samples = _sample_count(props, "emitter_samples", shading)
        self.bsdf_samples = _sample_count(props, "bsdf_samples", shading)
        total = self.emitter_samples + self.bsdf_samples
        if total == 0:
            raise ValueError("emitter_samples + bsdf_samples = 0: take at least one sample")
        # In single precision, as Mitsuba computes them (a technique without samples
        # never uses its weight)
        one = np.float32(1)
        with np.errstate(divide="ignore"):
            self.weight_bsdf = float(one / np.float32(self.bsdf_samples))
            self.weight_emitter = float(one / np.float32(self.emitter_samples))
        self.frac_bsdf = float(np.float32(self.bsdf_samples) / np.float32(total))
        self.frac_emitter = float(np.float32(self.emitter_samples) / np.float32(total))

    def sample(self, scene, sampler, ray, medium=None, active=True):
        accel = self.sample_accel(scene)
        ray = camera_ray(scene, ray)
        active = mi.Bool(active)
        si = accel.ray_intersect(ray, mi.RayFlags.All, True, active)
        result = mi.Spectrum(0.0)

        # ------------------------ Visible emitters ------------------------

        if self.hide_emitters:
            # Continue past every area emitter the camera ray meets; the hit behind
            # them is expanded along the camera ray, as Mitsuba does
            skip = si.is_valid() & (si.shape.emitter() != None) & active  # noqa: E711
            pi = skip_area_emitters(accel, si.spawn_ray(ray.d), True, skip)
            si[skip] = accel.surface_interaction(pi, ray, mi.RayFlags.All, skip)
        else:
            result += si.emitter(scene, active).eval(si, active)

        valid_ray = active & si.is_valid()
        active &= si.is_valid()

        # ------------------------ Emitter sampling ------------------------

        ctx = mi.BSDFContext()
        bsdf = si.bsdf(ray)
        sample_emitter = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        for _ in range(self.emitter_samples):
            ds, emitter_val, active_e = visible_emitter_sample(
                scene, accel, si, sampler.next_2d(sample_emitter), sample_emitter)

            wo = si.to_local(ds.d)
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, wo, active_e)
            bsdf_val = si.to_world_mueller(bsdf_val, -wo, si.wi)
            mis = dr.select(ds.delta, 1.0,
                            mis_weight(ds.pdf * self.frac_emitter, bsdf_pdf * self.frac_bsdf)
                            * self.weight_emitter)
            result[active_e] = result + mis * bsdf_val * emitter_val

        # ------------------------- BSDF sampling --------------------------

        for _ in range(self.bsdf_samples):
            # Mitsuba's build evaluates the arguments of its bsdf->sample(ctx, si,
            # next_1d, next_2d, active) right to left: the 2D sample is drawn first
            sample_2 = sampler.next_2d(active)
            sample_1 = sampler.next_1d(active)
            bs, bsdf_val = bsdf.sample(ctx, si, sample_1, sample_2, active)
            bsdf_val = si.to_world_mueller(bsdf_val, -bs.wo, si.wi)
            active_b = active & dr.any(mi.unpolarized_spectrum(bsdf_val) != 0.0)

            si_bsdf = accel.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), active_b)
            emitter = si_bsdf.emitter(scene, active_b)
            active_b &= emitter != None  # noqa: E711 (JIT compare)

            emitter_val = emitter.eval(si_bsdf, active_b)
            delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            ds = mi.DirectionSample3f(scene, si_bsdf, si)
            emitter_pdf = dr.select(delta, 0.0, scene.pdf_emitter_direction(si, ds, active_b))
            result[active_b] = result + (
                bsdf_val * emitter_val
                * mis_weight(bs.pdf * self.frac_bsdf, emitter_pdf * self.frac_emitter)
                * self.weight_bsdf)

        return result, valid_ray, []

    def to_string(self):
        return (f"hlbvh_direct[{self._options_string()}, emitter_samples="
                f"{self.emitter_samples}, bsdf_samples={self.bsdf_samples}]")


mi.register_integrator("hlbvh_direct", lambda props: DirectIntegrator(props))
