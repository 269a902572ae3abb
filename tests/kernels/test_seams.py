"""Seams between separately modelled meshes: two quads that meet with a crack of an
ulp or two (as the walls of Mitsuba's Cornell box do, to about an ulp) are one
surface to a ray, as they are to Embree. Without the barycentric margin of the
triangle test, rays through the crack would see through the wall."""

import drjit as dr
import hlbvh
import mitsuba as mi
import numpy as np
import pytest


def _two_quads(gap: float = 0.0, ulps: int = 0):
    """Quads [0, left] x [0, 1] and [1, 2] x [0, 1] at z = 0, sharing no vertex, with
    ``left`` ``gap`` or ``ulps`` float32 steps below 1."""
    right = 1.0
    left = np.float32(right - gap)
    for _ in range(ulps):
        left = np.nextafter(left, np.float32(0))
    v = np.array([[0, 0, 0], [left, 0, 0], [left, 1, 0], [0, 1, 0],
                  [right, 0, 0], [2, 0, 0], [2, 1, 0], [right, 1, 0]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], np.uint32)
    return v, f, float(left)


@pytest.mark.parametrize("ulps", [2, 3])
def test01_rays_through_a_crack_of_a_few_ulps_hit_the_wall(ulps):
    """The four triangles in one leaf (a root leaf of the SAH builder), so that the
    triangle test alone decides: a ray parallel to an axis meets a node box without
    slack in that axis."""
    v, f, left = _two_quads(ulps=ulps)
    assert left < 1.0
    bvh = hlbvh.build(mi.Float(v.ravel()), mi.UInt32(f.ravel()), builder="sah", leaf_size=4)
    assert bvh.stats.node_count == 1
    # Straight down through the crack, at every float32 x strictly inside it
    xs = [np.nextafter(np.float32(left), np.float32(2))]
    while np.nextafter(xs[-1], np.float32(2)) < 1.0:
        xs.append(np.nextafter(xs[-1], np.float32(2)))
    xs = np.array(xs, np.float32)
    assert len(xs) == ulps - 1
    ys = np.linspace(0.1, 0.9, 16, dtype=np.float32)
    x, y = np.meshgrid(xs, ys)
    n = x.size
    ray = mi.Ray3f(mi.Point3f(mi.Float(x.ravel()), mi.Float(y.ravel()), dr.full(mi.Float, 1, n)),
                   mi.Vector3f(0, 0, -1))
    pi = bvh.intersect(ray)
    assert dr.all(pi.is_valid())
    np.testing.assert_allclose(np.array(pi.t), 1.0, rtol=1e-6)
    assert dr.all(bvh.occluded(ray))


def test02_a_real_gap_stays_open():
    """The margin closes cracks of about a millionth of a triangle, not holes: rays
    through a gap of a thousandth miss."""
    v, f, left = _two_quads(gap=1e-3)
    bvh = hlbvh.build(mi.Float(v.ravel()), mi.UInt32(f.ravel()))
    ray = mi.Ray3f(mi.Point3f((left + 1.0) / 2, 0.5, 1), mi.Vector3f(0, 0, -1))
    assert not dr.any(bvh.intersect(ray).is_valid())
    assert not dr.any(bvh.occluded(ray))
