"""The two tests a ray makes in the traversal (:mod:`hlbvh.kernels.traversal`), on the
slots of :mod:`hlbvh.kernels.layout.slots`, and the per-ray constants they share.

- **Conservative slab test** (Ize, "Robust BVH ray traversal", JCGT 2013): the exit
  distance of a box is scaled by ``1 + 2·gamma(3)`` so rounding never culls a box the
  ray touches; so is the closest hit so far when a box's entry distance is compared
  with it. Reciprocal directions come from directions clamped away from zero
  (``|d| >= FLT_MIN``, sign kept), so no ``0 · inf = NaN`` reaches the min/max.
- **Watertight ray/triangle test** (Woop, Benthin & Wald, JCGT 2013): vertices are
  translated to the ray origin, permuted so the ray's dominant axis is z and sheared so
  the ray becomes the z axis. Every vertex is transformed the same way whichever
  triangle it belongs to, and the 2D edge functions U, V, W of a shared edge are exact
  negatives of each other, so no ray slips between two triangles that share an edge or
  a vertex. A hit is accepted with barycentrics ``U/det, V/det, W/det`` down to
  ``-BARYCENTRIC_MARGIN`` (2**-20): this also closes the one-ulp cracks where two
  separately modelled meshes meet (the walls of Cornell box), as Embree does. Triangles
  whose edge functions overflow or underflow float32 (coordinates beyond ~1e19 or below
  ~1e-19 relative to the ray origin) or whose determinant rounds to zero are recomputed
  in double precision, so scenes at 1e+30 and 1e-30 scale trace correctly. Zero-area
  triangles are packed with NaN vertices and never hit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from .layout.slots import EMPTY, NODE_HI, NODE_LO, NODE_REF, TRI_P

_FLT_MIN = 2.0**-126  # smallest normal float: 1 / _FLT_MIN is finite
_EPS = 2.0**-24  # unit roundoff of float32
_GAMMA3 = 3 * _EPS / (1 - 3 * _EPS)  # gamma(3) of Pharr et al., as in Ize 2013
TFAR_SCALE = 1 + 2 * _GAMMA3
#: A hit is accepted with barycentrics down to ``-BARYCENTRIC_MARGIN``: this closes
#: cracks of up to ~1e-6 of a triangle's size between separately modelled meshes that
#: meet at a seam (the walls of Mitsuba's Cornell box do), where Embree reports a hit.
BARYCENTRIC_MARGIN = 2.0**-20


def select_min(a, b):
    """Minimum of two NaN-free arrays (one compare and blend; ``dr.minimum`` also
    handles NaN and signed zeros at a few times the cost)."""
    return dr.select(a < b, a, b)


def select_max(a, b):
    """Maximum of two NaN-free arrays (see :func:`select_min`)."""
    return dr.select(a > b, a, b)


def _pick(v, k0, k1):
    """Per-lane component ``k`` of Array3f ``v``, with masks ``k0 = (k == 0)`` and
    ``k1 = (k == 1)``."""
    return dr.select(k0, v.x, dr.select(k1, v.y, v.z))


def slab_test(ray: Ray, rec, k: int, limit):
    """Child ``k`` of the wide node whose two slots are ``rec`` (32 floats):
    ``(ref, t_near, hit)``, its reference, entry distance, and whether the ray enters
    its box before ``limit`` (the closest hit so far, scaled)."""
    UInt32 = dr.uint32_array_t(type(limit))
    ref = dr.reinterpret_array(UInt32, rec[NODE_REF + k])
    t0 = [(rec[NODE_LO[i] + k] - ray.o[i]) * ray.inv_d[i] for i in range(3)]
    t1 = [(rec[NODE_HI[i] + k] - ray.o[i]) * ray.inv_d[i] for i in range(3)]
    near = [select_min(a, b) for a, b in zip(t0, t1)]
    far = [select_max(a, b) for a, b in zip(t0, t1)]
    t_near = select_max(select_max(near[0], near[1]), select_max(near[2], 0.0))
    t_far = select_min(select_min(far[0], far[1]), far[2])
    hit = (t_near <= select_min(t_far * TFAR_SCALE, limit)) & (ref != EMPTY)
    return ref, t_near, hit


def _ratios(ax, ay, az, bx, by, bz, cx, cy, cz, edges, det, t_scaled):
    """Barycentrics (w, u, v) and distance t from float32 edge functions (Woop et al.:
    ``b_i = edge_i / det``, ``t = T / det``); ``det != 0`` here."""
    inv_det = dr.rcp(det)
    return edges[0] * inv_det, edges[1] * inv_det, edges[2] * inv_det, t_scaled / det


def _ratios_in_double(ax, ay, az, bx, by, bz, cx, cy, cz, edges, det, t_scaled):
    """:func:`_ratios` with the edge functions and T recomputed in double precision
    from the float32 sheared vertices (products of two floats are exact in double, so
    the signs are exact too). A zero determinant (a triangle seen edge-on, or
    degenerate) gives NaN: no hit."""
    Float, F64 = type(ax), dr.float64_array_t(type(ax))
    ax, ay, az, bx, by, bz, cx, cy, cz = (F64(x) for x in (ax, ay, az, bx, by, bz, cx, cy, cz))
    e0, e1, e2 = cx * by - cy * bx, ax * cy - ay * cx, bx * ay - by * ax
    det64 = e0 + e1 + e2
    inv_det = dr.select(det64 != 0, 1.0 / det64, dr.nan)
    t64 = (e0 * az + e1 * bz + e2 * cz) * inv_det
    return Float(e0 * inv_det), Float(e1 * inv_det), Float(e2 * inv_det), Float(t64)


@dataclass
class Ray:
    """What a ray's tests read, fixed through the loop (one entry per ray)."""

    o: Any  # Array3f origin
    inv_d: Any  # Array3f reciprocal of the direction clamped away from zero (slab test)
    perm: tuple  # masks (k == 0, k == 1) of kx, ky, kz: the watertight test's axes
    o_p: list  # the origin's coordinates on kx, ky, kz
    shear: tuple  # (d[kx] / d[kz], d[ky] / d[kz], 1 / d[kz])


def ray_setup(o, d) -> Ray:
    """The per-ray constants of the slab and watertight tests."""
    Array3f, UInt32 = type(o), dr.uint32_array_t(type(o.x))
    # Slab test: reciprocal of the direction clamped away from zero (sign kept).
    d_safe = dr.select(dr.abs(d) < _FLT_MIN, dr.copysign(Array3f(_FLT_MIN), d), d)
    inv_d = dr.rcp(d_safe)
    # Watertight test: kz = dominant axis, (kx, ky) the others, swapped when d[kz] < 0
    # to keep the winding (Woop et al. 2013, Fig. 1).
    ad = dr.abs(d)
    kz = dr.select((ad.x >= ad.y) & (ad.x >= ad.z), UInt32(0),
                   dr.select(ad.y >= ad.z, UInt32(1), UInt32(2)))
    kx = dr.select(kz == 2, 0, kz + 1)
    ky = dr.select(kx == 2, 0, kx + 1)
    dz = _pick(d, kz == 0, kz == 1)
    kx, ky = dr.select(dz < 0, ky, kx), dr.select(dz < 0, kx, ky)
    perm = ((kx == 0, kx == 1), (ky == 0, ky == 1), (kz == 0, kz == 1))
    o_p = [_pick(o, *m) for m in perm]
    shear = (_pick(d, *perm[0]) / dz, _pick(d, *perm[1]) / dz, dr.rcp(dz))
    return Ray(o=o, inv_d=inv_d, perm=perm, o_p=o_p, shear=shear)


def _vertex(ray: Ray, rec, offset):
    """A triangle vertex translated, permuted and sheared into ray space."""
    p = [rec[offset + i] for i in range(3)]
    a = [dr.select(m0, p[0], dr.select(m1, p[1], p[2])) - oc
         for (m0, m1), oc in zip(ray.perm, ray.o_p)]
    return a[0] - ray.shear[0] * a[2], a[1] - ray.shear[1] * a[2], ray.shear[2] * a[2]


def triangle_test(ray: Ray, rec, t_max):
    """Watertight intersection with the triangle in ``rec``: (hit, t, u, v)."""
    ax, ay, az = _vertex(ray, rec, TRI_P[0])
    bx, by, bz = _vertex(ray, rec, TRI_P[1])
    cx, cy, cz = _vertex(ray, rec, TRI_P[2])
    edges = (cx * by - cy * bx, ax * cy - ay * cx, bx * ay - by * ax)
    det = edges[0] + edges[1] + edges[2]
    t_scaled = dr.fma(edges[0], az, dr.fma(edges[1], bz, edges[2] * cz))
    # Products of coordinates beyond ~1e19 overflow and below ~1e-19 underflow in
    # float32: redo those triangles (and zero determinants) in double precision.
    in_range = dr.isfinite(t_scaled) & dr.isfinite(det) & (det != 0)
    b0, b1, b2, t = dr.if_stmt(
        args=(ax, ay, az, bx, by, bz, cx, cy, cz, edges, det, t_scaled),
        cond=in_range,
        true_fn=_ratios,
        false_fn=_ratios_in_double,
        arg_labels=("ax", "ay", "az", "bx", "by", "bz", "cx", "cy", "cz", "edges",
                    "det", "t_scaled"),
        rv_labels=("b0", "b1", "b2", "t"),
        label="hlbvh_woop_range", mode="symbolic",
    )
    inside = (b0 >= -BARYCENTRIC_MARGIN) & (b1 >= -BARYCENTRIC_MARGIN) \
        & (b2 >= -BARYCENTRIC_MARGIN)
    return inside & (t > 0) & (t <= t_max), t, b1, b2
