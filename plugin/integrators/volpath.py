"""``hlbvh_volpath``: Mitsuba's ``volpath`` integrator (participating media) with every
ray query through an hlbvh intersector."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from hlbvh.accel.keys import camera_ray
from .common import AccelIntegrator, depth_properties, mis_weight, skip_area_emitters


def _channel_value(spectrum, channel):
    """The entry ``channel`` of an unpolarized spectrum in RGB variants (the colour
    channel that drives the distance sampling), its first entry otherwise (spectral
    variants sample distances with the first wavelength)."""
    value = mi.Float(spectrum[0])
    if mi.is_rgb:
        value[channel == 1] = spectrum[1]
        value[channel == 2] = spectrum[2]
    return value


def _channel_mean(spectrum):
    """The mean of a spectrum's entries as Mitsuba's C++ computes it: their sum times
    the reciprocal of their count. Dr.Jit's Python ``dr.mean`` of a colour scales the
    sum by the lane count over the total entry count instead, which rounds
    differently in the last bit (so would the null and real scattering weights of a
    heterogeneous medium)."""
    return dr.sum(spectrum) * (1.0 / dr.size_v(spectrum))


def _sampled_channel(sampler, active):
    """The colour channel whose extinction samples this path's distances: drawn
    uniformly in RGB variants, 0 otherwise."""
    channel = mi.UInt32(0)
    if mi.is_rgb:
        n_channels = dr.size_v(mi.Spectrum)
        channel = mi.UInt32(dr.minimum(sampler.next_1d(active) * n_channels, n_channels - 1))
    return channel


def _roulette(sampler, throughput, eta, depth, rr_depth: int, max_depth: int, active):
    """``(throughput, active)`` after Russian roulette past ``rr_depth`` (a surviving
    path's throughput divided by its survival probability) and the depth limit; a path
    of zero throughput ends."""
    throughput = mi.Spectrum(throughput)
    active = active & dr.any(mi.unpolarized_spectrum(throughput) != 0.0)
    q = dr.minimum(dr.max(mi.unpolarized_spectrum(throughput)) * dr.square(eta), 0.95)
    perform_rr = depth > rr_depth
    active &= (sampler.next_1d(active) < q) | ~perform_rr
    throughput[perform_rr] = throughput * dr.rcp(dr.detach(q))
    active &= depth < max_depth
    return throughput, active


def _free_flight(accel, sampler, ray, medium, channel, si, needs_intersection, throughput,
                 active_medium, is_spectral):
    """A distance sampled in ``medium`` along ``ray`` (bounded by the surface hit, found
    through ``accel`` where ``needs_intersection``), the throughput of spectral media
    weighted by their transmittance over its pdf. Returns ``(mei, ray, si,
    needs_intersection, throughput, escaped_medium, active_medium)``: the lanes that
    left the medium (no interaction before the surface) and those still in it."""
    ray, si, throughput = mi.Ray3f(ray), mi.SurfaceInteraction3f(si), mi.Spectrum(throughput)
    mei = medium.sample_interaction(ray, sampler.next_1d(active_medium), channel,
                                    active_medium)
    ray.maxt[active_medium & medium.is_homogeneous() & mei.is_valid()] = mei.t
    intersect = needs_intersection & active_medium
    si[intersect] = accel.ray_intersect(ray, intersect)
    needs_intersection = needs_intersection & ~active_medium

    mei.t[active_medium & (si.t < mei.t)] = dr.inf
    tr, free_flight_pdf = medium.transmittance_eval_pdf(mei, si, is_spectral)
    tr_pdf = _channel_value(free_flight_pdf, channel)
    throughput[is_spectral] = throughput * dr.select(tr_pdf > 0.0, tr / tr_pdf, 0.0)
    escaped_medium = active_medium & ~mei.is_valid()
    return (mei, ray, si, needs_intersection, throughput, escaped_medium,
            active_medium & mei.is_valid())


def _sample_phase(phase, phase_ctx, mei, sampler, active):
    """``(wo, weight, pdf)``: a direction sampled from the medium's phase function
    (Mitsuba's build draws the 2D sample first)."""
    phase = mi.PhaseFunctionPtr(phase)
    phase[~active] = dr.zeros(mi.PhaseFunctionPtr)
    sample_2 = sampler.next_2d(active)
    sample_1 = sampler.next_1d(active)
    return phase.sample(phase_ctx, mei, sample_1, sample_2, active)


def _past_hidden_emitters(accel, si, ray, depth, intersect):
    """``si`` where the camera ray continues past every area emitter it meets
    (``hide_emitters``), through ``accel``."""
    si = mi.SurfaceInteraction3f(si)
    skip = (si.is_valid() & (si.shape.emitter() != None)  # noqa: E711
            & (depth == 0) & intersect)
    ray_skip = si.spawn_ray(ray.d)
    pi = skip_area_emitters(accel, ray_skip, True, skip)
    si[skip] = accel.surface_interaction(pi, ray_skip, mi.RayFlags.All, skip)
    return si


def _sample_bsdf(bsdf, ctx, si, sampler, active):
    """``(BSDFSample3f, weight in world space)``: the BSDF sampled at ``si`` (the 2D
    sample first, as for the phase function)."""
    sample_2 = sampler.next_2d(active)
    sample_1 = sampler.next_1d(active)
    bs, bsdf_weight = bsdf.sample(ctx, si, sample_1, sample_2, active)
    return bs, si.to_world_mueller(bsdf_weight, -bs.wo, si.wi)


class VolpathIntegrator(AccelIntegrator):
    r"""
    .. _integrator-hlbvh_volpath:

    Volumetric path tracer through an hlbvh intersector (:monosp:`hlbvh_volpath`)
    -----------------------------------------------------------------------------

    .. pluginparameters::

     * - accel, builder, leaf_size, morton_bits, quantization, coarse_bits, p,
         sah_bins, static, moving, update, ...
       - |string| / |int|
       - The intersector and its options, as for ``hlbvh_path``.
     * - max_depth
       - |int|
       - Longest path depth (-1: unbounded). (Default: -1)
     * - rr_depth
       - |int|
       - Path depth after which Russian roulette starts. (Default: 5)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: |false|)

    The algorithm of Mitsuba's C++ ``volpath`` integrator: free-flight distances
    sampled in homogeneous and heterogeneous media (delta tracking against the
    majorant, with null scattering), real scattering through the medium's phase
    function, surfaces with their BSDFs, null interfaces between media, emitter
    sampling from surfaces and from inside media with the transmittance of the
    shadow segment estimated by ratio tracking, Russian roulette, and, in RGB variants,
    a colour channel drawn per path for the distances; the same sampler calls (and
    masks) in the same order.

    Every ray query goes through the chosen intersector: the first and every later
    segment's surface hit (the one that bounds a distance sampled in a medium too),
    the rays past hidden area emitters, and each shadow ray's segments between
    interfaces. So, with a ``box`` reconstruction filter and the same sampler seed,
    ``accel="native"`` renders bit-identically to ``volpath``.

    .. tabs::

        .. code-tab:: python

            'type': 'hlbvh_volpath',
            'accel': 'hlbvh',
            'max_depth': 16
    """

    def __init__(self, props):
        super().__init__(props)
        self.max_depth, self.rr_depth = depth_properties(props)

    @dr.syntax
    def sample(self, scene, sampler, ray, medium=None, active=True):
        accel = self.sample_accel(scene)
        ray = mi.Ray3f(camera_ray(scene, ray))  # ray differentials are not used
        active = mi.Bool(active)
        valid_ray = mi.Bool(not self.hide_emitters and scene.environment() is not None)
        eta = mi.Float(1.0)
        throughput = mi.Spectrum(1.0)
        result = mi.Spectrum(0.0)
        medium = dr.zeros(mi.MediumPtr) if medium is None else mi.MediumPtr(medium)
        specular_chain = active & (not self.hide_emitters)
        depth = mi.UInt32(0)
        channel = _sampled_channel(sampler, active)

        si = dr.zeros(mi.SurfaceInteraction3f)
        needs_intersection = mi.Bool(True)
        last_scatter_event = dr.zeros(mi.Interaction3f)
        last_scatter_direction_pdf = mi.Float(1.0)

        while dr.hint(active, label="hlbvh_volpath"):
            throughput, active = _roulette(sampler, throughput, eta, depth, self.rr_depth,
                                           self.max_depth, active)

            # --------------------- Sampling the medium -----------------------
            active_medium = active & (medium != None)  # noqa: E711 (JIT compare)
            active_surface = active & ~active_medium
            is_spectral = active_medium & medium.has_spectral_extinction()
            not_spectral = ~is_spectral & active_medium
            (mei, ray, si, needs_intersection, throughput, escaped_medium,
             active_medium) = _free_flight(accel, sampler, ray, medium, channel, si,
                                           needs_intersection, throughput, active_medium,
                                           is_spectral)

            # Null and real scattering
            null_scatter_prob = _channel_mean(mei.sigma_n / mei.combined_extinction)
            null_scatter = sampler.next_1d(active_medium) < null_scatter_prob
            act_null_scatter = null_scatter & active_medium
            act_medium_scatter = ~act_null_scatter & active_medium
            throughput[is_spectral & act_null_scatter] = (
                throughput * (mei.sigma_n / null_scatter_prob))
            depth[act_medium_scatter] += 1
            last_scatter_event[act_medium_scatter] = mei

            active &= depth < self.max_depth
            act_medium_scatter &= active
            ray.o[act_null_scatter] = mei.p
            si.t[act_null_scatter] = si.t - mei.t

            throughput[is_spectral & act_medium_scatter] = throughput * (
                mei.sigma_s / _channel_mean(mei.sigma_t / mei.combined_extinction))
            throughput[not_spectral & act_medium_scatter] = throughput * (
                mei.sigma_s / mei.sigma_t)

            phase_ctx = mi.PhaseFunctionContext(sampler)
            phase = mei.medium.phase_function()

            # Emitter sampling from the medium
            sample_emitters = mei.medium.use_emitter_sampling()
            valid_ray |= act_medium_scatter
            specular_chain &= ~act_medium_scatter
            specular_chain |= act_medium_scatter & ~sample_emitters
            active_e = act_medium_scatter & sample_emitters
            result[active_e] = result + self._phase_emission(
                accel, scene, sampler, mei, phase, phase_ctx, medium, channel, throughput,
                active_e)

            # Phase function sampling
            wo, phase_weight, phase_pdf = _sample_phase(phase, phase_ctx, mei, sampler,
                                                        act_medium_scatter)
            act_medium_scatter &= phase_pdf > 0.0
            ray[act_medium_scatter] = mei.spawn_ray(wo)
            needs_intersection |= act_medium_scatter
            last_scatter_direction_pdf[act_medium_scatter] = phase_pdf
            throughput[act_medium_scatter] = throughput * phase_weight

            # ---------------------- Surface interactions ---------------------
            active_surface |= escaped_medium
            intersect = active_surface & needs_intersection
            si[intersect] = accel.ray_intersect(ray, intersect)
            if dr.hint(self.hide_emitters, mode="scalar"):
                si = _past_hidden_emitters(accel, si, ray, depth, intersect)

            # Emitters hit
            active_e, contrib = self._emission_hit(
                scene, si, active_surface, depth, specular_chain, throughput,
                last_scatter_event, last_scatter_direction_pdf)
            result[active_e] = result + contrib

            active_surface &= si.is_valid()
            ctx = mi.BSDFContext()
            bsdf = si.bsdf(ray)

            # Emitter sampling from the surface
            active_e = (active_surface & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                        & (depth + 1 < self.max_depth))
            result[active_e] = result + self._bsdf_emission(
                accel, scene, sampler, si, bsdf, ctx, medium, channel, throughput, active_e)

            # BSDF sampling
            bs, bsdf_weight = _sample_bsdf(bsdf, ctx, si, sampler, active_surface)
            throughput[active_surface] = throughput * bsdf_weight
            eta[active_surface] = eta * bs.eta
            ray[active_surface] = si.spawn_ray(si.to_world(bs.wo))
            needs_intersection |= active_surface

            non_null_bsdf = active_surface & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
            depth[non_null_bsdf] += 1
            last_scatter_event[non_null_bsdf] = si
            last_scatter_direction_pdf[non_null_bsdf] = bs.pdf

            valid_ray |= non_null_bsdf
            specular_chain |= non_null_bsdf & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            specular_chain &= ~(active_surface
                                & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Smooth))
            medium[active_surface & si.is_medium_transition()] = si.target_medium(ray.d)
            active &= active_surface | active_medium

        return result, valid_ray, []

    def _phase_emission(self, accel, scene, sampler, mei, phase, phase_ctx, medium, channel,
                        throughput, active):
        """The contribution of an emitter sample seen from the medium interaction
        ``mei``: its attenuated value (:meth:`_sample_emitter`) through the phase
        function, weighted by multiple importance against phase sampling."""
        emitted, ds = self._sample_emitter(accel, mei, False, scene, sampler, medium,
                                           channel, active)
        phase_val, phase_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, active)
        return throughput * phase_val * emitted * mis_weight(
            ds.pdf, dr.select(ds.delta, 0.0, phase_pdf))

    def _emission_hit(self, scene, si, active_surface, depth, specular_chain, throughput,
                      last_scatter_event, last_scatter_direction_pdf):
        """``(active, contribution)`` of the emitter the path's last segment hit at
        ``si``: counted in full on the camera ray and after a specular chain, else
        weighted by multiple importance against emitter sampling from the last
        scattering event; directly seen emitters left out with ``hide_emitters``."""
        count_direct = (active_surface & (depth == 0)) | specular_chain
        emitter = si.emitter(scene)
        active_e = (active_surface & (emitter != None)  # noqa: E711
                    & ~((depth == 0) & self.hide_emitters))
        ds = mi.DirectionSample3f(scene, si, last_scatter_event)
        emitter_pdf = scene.pdf_emitter_direction(last_scatter_event, ds, active_e)
        emitted = emitter.eval(si, active_e)
        contrib = dr.select(count_direct, throughput * emitted,
                            throughput * mis_weight(last_scatter_direction_pdf, emitter_pdf)
                            * emitted)
        return active_e, contrib

    def _bsdf_emission(self, accel, scene, sampler, si, bsdf, ctx, medium, channel,
                       throughput, active):
        """The contribution of an emitter sample seen from the surface ``si``: its
        attenuated value (:meth:`_sample_emitter`) through the BSDF, weighted by
        multiple importance against BSDF sampling."""
        emitted, ds = self._sample_emitter(accel, si, True, scene, sampler, medium,
                                           channel, active)
        wo = si.to_local(ds.d)
        bsdf_val = si.to_world_mueller(bsdf.eval(ctx, si, wo, active), -wo, si.wi)
        bsdf_pdf = bsdf.pdf(ctx, si, wo, active)
        return throughput * bsdf_val * mis_weight(
            ds.pdf, dr.select(ds.delta, 0.0, bsdf_pdf)) * emitted

    @dr.syntax
    def _sample_emitter(self, accel, ref, on_surface, scene, sampler, medium, channel,
                        active):
        """An emitter sample seen from ``ref`` and its contribution attenuated along
        the shadow ray: ratio tracking through media, null interfaces crossed (their
        null transmission), any other surface blocking it; every segment's surface
        hit through ``accel``.

        Args:
            ref: the SurfaceInteraction3f (``on_surface``) or MediumInteraction3f.
            medium: the MediumPtr ``ref`` lies in (a surface that is a medium
                transition hands the ray to the medium on the emitter's side).
        Returns:
            (Spectrum: the emitter's weight times the transmittance,
            DirectionSample3f).
        """
        active = mi.Bool(active)
        transmittance = mi.Spectrum(1.0)
        ds, emitter_val = scene.sample_emitter_direction(ref, sampler.next_2d(active), False,
                                                         active)
        emitter_val[ds.pdf == 0.0] = 0.0
        active &= ds.pdf != 0.0

        ray = ref.spawn_ray_to(ds.p)
        max_dist = mi.Float(ray.maxt)
        medium = mi.MediumPtr(medium)
        if dr.hint(on_surface, mode="scalar"):
            medium[ref.is_medium_transition()] = ref.target_medium(ray.d)

        total_dist = mi.Float(0.0)
        si = dr.zeros(mi.SurfaceInteraction3f)
        needs_intersection = mi.Bool(True)

        while dr.hint(active, label="hlbvh_volpath_emitter"):
            remaining_dist = max_dist - total_dist
            ray.maxt = mi.Float(remaining_dist)
            active &= remaining_dist > 0.0

            active_medium = active & (medium != None)  # noqa: E711 (JIT compare)
            active_surface = active & ~active_medium

            # Ratio tracking through the medium
            mei = medium.sample_interaction(ray, sampler.next_1d(active_medium), channel,
                                            active_medium)
            ray.maxt[active_medium & medium.is_homogeneous() & mei.is_valid()] = dr.minimum(
                mei.t, remaining_dist)
            intersect = needs_intersection & active_medium
            si[intersect] = accel.ray_intersect(ray, intersect)
            mei.t[active_medium & (si.t < mei.t)] = dr.inf
            needs_intersection &= ~active_medium

            is_spectral = medium.has_spectral_extinction() & active_medium
            not_spectral = ~is_spectral & active_medium
            t = dr.minimum(remaining_dist, dr.minimum(mei.t, si.t)) - mei.mint
            tr = dr.exp(-t * mei.combined_extinction)
            free_flight_pdf = dr.select((si.t < mei.t) | (mei.t > remaining_dist), tr,
                                        tr * mei.combined_extinction)
            tr_pdf = _channel_value(free_flight_pdf, channel)
            transmittance[is_spectral] = transmittance * dr.select(tr_pdf > 0.0, tr / tr_pdf,
                                                                   0.0)

            # A distance past the emitter ends the segment there
            total_dist[active_medium & (mei.t > remaining_dist) & mei.is_valid()] = ds.dist
            mei.t[active_medium & (mei.t > remaining_dist)] = dr.inf

            escaped_medium = active_medium & ~mei.is_valid()
            active_medium &= mei.is_valid()
            is_spectral &= active_medium
            not_spectral &= active_medium

            total_dist[active_medium] = total_dist + mei.t
            ray.o[active_medium] = mei.p
            si.t[active_medium] = si.t - mei.t
            transmittance[is_spectral] = transmittance * mei.sigma_n
            transmittance[not_spectral] = transmittance * (mei.sigma_n / mei.combined_extinction)

            # Surfaces: null interfaces let the ray through, others block it
            intersect = active_surface & needs_intersection
            si[intersect] = accel.ray_intersect(ray, intersect)
            needs_intersection &= ~intersect
            active_surface |= escaped_medium
            total_dist[active_surface] = total_dist + si.t

            active_surface &= si.is_valid() & active & ~active_medium
            bsdf = si.bsdf(ray)
            bsdf_val = bsdf.eval_null_transmission(si, active_surface)
            bsdf_val = si.to_world_mueller(bsdf_val, si.wi, si.wi)
            transmittance[active_surface] = transmittance * bsdf_val

            ray[active_surface] = si.spawn_ray(ray.d)
            ray.maxt = mi.Float(remaining_dist)
            needs_intersection |= active_surface

            active &= ((active_medium | active_surface)
                       & dr.any(mi.unpolarized_spectrum(transmittance) != 0.0))
            medium[active_surface & si.is_medium_transition()] = si.target_medium(ray.d)

        return transmittance * emitter_val, ds

    def to_string(self):
        return (f"hlbvh_volpath[{self._options_string()}, max_depth={self.max_depth}, "
                f"rr_depth={self.rr_depth}]")


mi.register_integrator("hlbvh_volpath", lambda props: VolpathIntegrator(props))
