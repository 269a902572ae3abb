"""The nearest hit of a query over several structures, kept as Mitsuba's own query
reports it (:class:`NearestHit`): what :class:`hlbvh.SceneAccel` merges its groups'
hits into."""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


#: The relative difference in ``t`` under which two hits on different shapes tie. Two
#: intersectors (Embree's and our watertight test) round the distance to one plane
#: differently by a few ulps, so coplanar surfaces traced by two structures would
#: otherwise show whichever rounded nearer, pixel by pixel (z-fighting that changes
#: with the structure); 2^-20 is about eight float32 ulps.
TIE = 2.0 ** -20


@dataclass
class NearestHit:
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
    def none(cls, n: int) -> "NearestHit":
        return cls(dr.full(mi.Float, dr.inf, n), dr.zeros(mi.Point2f, n),
                   dr.zeros(mi.UInt32, n), dr.zeros(mi.UInt32, n), dr.zeros(mi.Bool, n),
                   dr.zeros(mi.ShapePtr, n), dr.zeros(mi.ShapePtr, n),
                   dr.zeros(mi.Bool, n), dr.zeros(mi.UInt32, n))

    def reach(self, maxt: mi.Float) -> mi.Float:
        """How far the next structure must look (``maxt`` at most): past the nearest hit
        so far by the tie tolerance, so that it sees a hit that ties with it."""
        return dr.minimum(maxt, self.t * (1.0 + TIE))

    def take(self, t, prim_uv, prim_index, shape_index, instance=None) -> mi.Bool:
        """Take the hit of one more structure (``t`` infinite where it has none) where
        it is nearer, or ties with the nearest so far (:data:`TIE`) on a shape of lower
        index in ``scene.shapes()`` (the one tie rule: whichever structure traced
        either); ``instance``: for a hit inside one of our instances, the instance's
        index (the instance's index is the one compared). Returns where it was taken."""
        index = shape_index if instance is None else instance
        held = dr.select(self.in_instance, self.instance, self.shape_index)
        tie = (dr.abs(t - self.t) <= TIE * dr.minimum(t, self.t)) & (index != held)
        closer = dr.select(tie, index < held, t < self.t)
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
