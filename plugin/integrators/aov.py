"""``hlbvh_aov``: what the camera ray hits first, per pixel, through an hlbvh
intersector."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from hlbvh.accel.keys import camera_ray
from .common import AccelIntegrator

#: Output channels, in the order they follow the film's colour (and alpha) channels.
CHANNELS = ("depth", "shape_index", "prim_index",
            "normal.X", "normal.Y", "normal.Z",
            "position.X", "position.Y", "position.Z",
            "motion.X", "motion.Y")


class AOVIntegrator(AccelIntegrator):
    r"""
    .. _integrator-hlbvh_aov:

    Primary-hit outputs through an hlbvh intersector (:monosp:`hlbvh_aov`)
    ----------------------------------------------------------------------

    .. pluginparameters::

     * - accel
       - |string|
       - ``"hlbvh"`` (default) or ``"native"``: which intersector traces the camera
         rays.
     * - builder, leaf_size, morton_bits, quantization, coarse_bits, p, sah_bins
       - |string| / |int|
       - Options of ``hlbvh.build``.

    Traces each camera ray once (``coherent=True``) and writes, after the film's
    colour channels (R, G, B, and A with ``pixel_format="rgba"``):

    ========================  ==========================================================
    channel                   value (on a miss)
    ========================  ==========================================================
    ``depth``                 distance ``t`` along the ray (0)
    ``shape_index``           index of the hit shape in ``scene.shapes()`` (-1)
    ``prim_index``            index of the hit primitive inside its shape (-1); exact
                              up to 2^24 primitives (the film stores float32)
    ``normal.X/Y/Z``          world-space shading normal (0)
    ``position.X/Y/Z``        world-space hit position (0)
    ``motion.X/Y``            screen-space motion of the hit over the shutter, in
                              pixels per unit of ``ray.time`` (per frame in ``hlbvh
                              render``, whose shutter is in frames; Cycles' Vector
                              pass): the hit's point on its mesh's first and last
                              motion key projected through the first sensor, +X
                              right, +Y down the film; 0 on still shapes (0)
    ========================  ==========================================================

    R, G, B hold the shading normal mapped to [0, 1] (``0.5·n + 0.5``) for a quick
    look; alpha is 1 where the ray hit something.

    The film averages every channel over a pixel's samples: render with one sample
    per pixel and a ``box`` filter when comparing indices; with the same seed, the
    ``"native"`` and ``"hlbvh"`` renders trace the very same rays, so their channels
    can be compared pixel by pixel.

    .. tabs::

        .. code-tab:: python

            'type': 'hlbvh_aov',
            'accel': 'native'
    """

    def aov_names(self):
        return list(CHANNELS)

    def sample(self, scene, sampler, ray, medium=None, active=True):
        accel = self.sample_accel(scene)
        ray = mi.Ray3f(camera_ray(scene, ray))
        pi = accel.ray_intersect_preliminary(ray, True, active)
        si = accel.surface_interaction(pi, ray, mi.RayFlags.All, active)
        hit = mi.Bool(active) & pi.is_valid()
        n = dr.select(hit, si.sh_frame.n, 0.0)
        p = dr.select(hit, si.p, 0.0)
        motion = dr.select(hit, _screen_motion(scene, accel, pi, si, hit), 0.0)
        aovs = [
            dr.select(hit, si.t, 0.0),
            dr.select(hit, mi.Float(pi.shape_index), -1.0),
            dr.select(hit, mi.Float(pi.prim_index), -1.0),
            n.x, n.y, n.z,
            p.x, p.y, p.z,
            motion.x, motion.y,
        ]
        color = mi.Spectrum(dr.select(hit, dr.fma(n, 0.5, 0.5), 0.0))
        return color, hit, aovs

    def to_string(self):
        return f"hlbvh_aov[{self._options_string()}]"


def _screen_motion(scene, accel, pi, si, active) -> mi.Vector2f:
    """Pixels per unit of ``ray.time`` the hits move on the first sensor's film over
    the shutter (zero where they do not move, or without a sensor)."""
    p_open, p_close, length = accel.points_over_shutter(pi, si, active)
    if not scene.sensors() or p_open is p_close:  # nothing moves inside the frame
        return dr.zeros(mi.Vector2f, dr.width(pi.t))
    sensor = scene.sensors()[0]

    def film_position(p):
        it = dr.zeros(mi.Interaction3f, dr.width(pi.t))
        it.p = p
        ds, _ = sensor.sample_direction(it, mi.Point2f(0.5), active)
        return ds.uv

    return (film_position(p_close) - film_position(p_open)) * (1.0 / length)


mi.register_integrator("hlbvh_aov", lambda props: AOVIntegrator(props))
