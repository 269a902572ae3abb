"""Numerical extremes: scaled and translated scenes, a tiny detailed object on a huge
ground, degenerate geometry, the rays ray tracers get wrong, and long runs.

The references: Mitsuba's native intersector (Embree) where it is meaningful, and the
brute-force intersector of ``tests/reference.py`` (Möller–Trumbore in float64 on the
same float32 vertices) where float32 itself is the question: Embree stops finding hits
on scenes smaller than ~1e-12 or larger than ~1e18 (it works in float32 without a
fallback), so at those scales only the brute force says what the right answer is.

Agreement is measured as in the other traversal tests: the same hit/miss, and the same
primitive unless the two hits lie at the same ``t`` (a tie: an edge or a coplanar
neighbour). Each scale is held to the agreement measured at scale 1, within
``MARGIN``.
"""

from __future__ import annotations

import gc
import warnings

import numpy as np
import pytest

import hlbvh
import drjit as dr
import mitsuba as mi

from bvh_check import check_bvh, rows
from meshes import grid
from reference import brute_force

MARGIN = 0.002  # agreement may fall this much below scale 1's (5 of 2500 rays)
T_REL = 1e-5  # relative error of t against the float64 reference (measured: < 1e-6)
TIE_REL = 1e-6  # two hits this close in t are a tie


# ---------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------


def mesh_scene(V, F) -> mi.Scene:
    """A Mitsuba scene holding one mesh with vertices ``V`` (n, 3) and faces ``F``."""
    mesh = mi.Mesh("mesh", len(V), len(F))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ravel(np.asarray(V, np.float32)))
    params["faces"] = mi.UInt32(np.ravel(np.asarray(F, np.uint32)))
    params.update()
    return mi.load_dict({"type": "scene", "mesh": mesh})


def as_ray(o, d, maxt=None) -> mi.Ray3f:
    ray = mi.Ray3f(mi.Point3f(np.asarray(o, np.float32).T), mi.Vector3f(np.asarray(d, np.float32).T))
    if maxt is not None:
        ray.maxt = mi.Float(np.broadcast_to(np.float32(maxt), (len(o),)).copy())
    return ray


def hits_of(pi) -> dict:
    """A PreliminaryIntersection3f as numpy: valid, t, prim."""
    valid = pi.is_valid().numpy()
    return {"valid": valid, "t": np.where(valid, pi.t.numpy(), np.inf),
            "prim": np.where(valid, pi.prim_index.numpy().astype(np.int64), -1)}


def _agree_per_ray(a: dict, b: dict) -> np.ndarray:
    """Per ray: hits ``a`` and ``b`` agree (same hit/miss, and the same primitive or a
    tie in t)."""
    both = a["valid"] & b["valid"]
    with np.errstate(invalid="ignore"):
        tie = both & (np.abs(a["t"] - b["t"]) <= TIE_REL * np.abs(b["t"]))
    return (a["valid"] == b["valid"]) & (~both | (a["prim"] == b["prim"]) | tie)


def agreement(a: dict, b: dict) -> float:
    """Fraction of rays on which hits ``a`` and ``b`` agree (see :func:`_agree_per_ray`)."""
    return float(np.mean(_agree_per_ray(a, b)))


def t_error(a: dict, ref: dict, V, F, o, d) -> float:
    """Largest error of ``a``'s t on the rays where it hits the same primitive as
    ``ref``, relative to ``max(t, r) / cos`` (as in tests/kernels/test_traversal.py): ``r``
    the distance from the origin to the triangle's farthest vertex (float32 coordinates
    carry an error proportional to their size) and ``cos`` the cosine between ray and
    normal (a grazing hit's t is ill-conditioned)."""
    same = a["valid"] & ref["valid"] & (a["prim"] == ref["prim"])
    if not same.any():
        return 0.0
    corners = np.asarray(V, np.float64)[np.asarray(F, np.int64)[ref["prim"][same]]]
    o, d = np.asarray(o, np.float64)[same], np.asarray(d, np.float64)[same]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    cos = np.abs(np.sum(normal * d, 1)) / np.linalg.norm(normal, axis=1) / np.linalg.norm(d, axis=1)
    reach = np.max(np.linalg.norm(corners - o[:, None], axis=2), 1) / np.linalg.norm(d, axis=1)
    scale = np.maximum(ref["t"][same], reach) / cos
    return float(np.max(np.abs(a["t"][same] - ref["t"][same]) / scale))


def assert_native_or_brute_force(ours: dict, native: dict, V, F, o, d, rate: float = 1e-3):
    """Ours agrees with native on all but ``rate`` of the rays, and where they differ
    the float64 brute force (run on those rays only) sides with ours."""
    pick = lambda h, rows: {k: v[rows] for k, v in h.items()}  # noqa: E731
    differ = np.flatnonzero(~_agree_per_ray(ours, native))
    assert len(differ) <= rate * len(o), f"{len(differ)} of {len(o)} rays differ from native"
    if len(differ):
        ref = brute_force(V, F, o[differ], d[differ])
        ref = {"valid": ref["valid"], "t": ref["t"], "prim": ref["prim"]}
        assert agreement(pick(ours, differ), ref) == 1, "native is right where we differ"


def grid_rays(count: int, seed: int):
    """Rays from above a unit grid towards random points of it (unit directions)."""
    rng = np.random.default_rng(seed)
    o = np.stack([rng.uniform(-0.2, 1.2, count), rng.uniform(-0.2, 1.2, count),
                  rng.uniform(0.5, 1.5, count)], 1)
    target = np.stack([rng.uniform(0, 1, count), rng.uniform(0, 1, count), np.zeros(count)], 1)
    d = target - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def trace_three_ways(V, F, o, d) -> dict:
    """Hits of the same float32 rays by SceneAccel (closest and shadow query), by
    Mitsuba's native intersector and by the float64 brute force."""
    V, F = np.asarray(V, np.float32), np.asarray(F, np.uint32)
    o, d = np.asarray(o, np.float32), np.asarray(d, np.float32)
    scene = mesh_scene(V, F)
    ray = as_ray(o, d)
    accel = hlbvh.SceneAccel(scene, static="hlbvh")
    ref = brute_force(V, F, o, d)
    return {
        "ours": hits_of(accel.ray_intersect_preliminary(ray)),
        "ours_test": accel.ray_test(ray).numpy(),
        "native": hits_of(scene.ray_intersect_preliminary(ray)),
        "brute": {"valid": ref["valid"], "t": ref["t"], "prim": ref["prim"]},
        "rays": (V, F, o, d),
    }


# ---------------------------------------------------------------------------------------
# 1. Scale and translation
# ---------------------------------------------------------------------------------------

GRID_V, GRID_F = grid(30)  # 1800 triangles, displaced, over [0, 1]^2
RAY_O, RAY_D = grid_rays(2500, seed=0)


@pytest.fixture(scope="module")
def at_scale_one() -> dict:
    """Agreements at scale 1, the level every other scale is held to."""
    h = trace_three_ways(GRID_V, GRID_F, RAY_O, RAY_D)
    return {"ours_brute": agreement(h["ours"], h["brute"]),
            "ours_native": agreement(h["ours"], h["native"]),
            "native_brute": agreement(h["native"], h["brute"])}


def _check_against_scale_one(h: dict, base: dict):
    """Ours against the brute force always, against native where native itself still
    agrees with the brute force as well as at scale 1."""
    assert agreement(h["ours"], h["brute"]) >= base["ours_brute"] - MARGIN
    assert np.mean(h["ours_test"] == h["brute"]["valid"]) >= base["ours_brute"] - MARGIN
    assert t_error(h["ours"], h["brute"], *h["rays"]) <= T_REL
    if agreement(h["native"], h["brute"]) >= base["native_brute"] - MARGIN:
        assert agreement(h["ours"], h["native"]) >= base["ours_native"] - MARGIN


_UNDERFLOW_BAND = pytest.mark.xfail(strict=True, reason=(
    "traversal.py: for scenes ~1e-17..1e-12 wide the float32 numerator of t (a product of "
    "three coordinate differences, ~s^3) underflows to zero while the determinant (~s^2) "
    "does not, so the double-precision fallback is not taken and t = 0 is rejected: every "
    "hit is lost (at 1e-11 t is still off by 20%)"))


@pytest.mark.parametrize("scale", [1e-30, pytest.param(1e-15, marks=_UNDERFLOW_BAND),
                                   1e-10, 1.0, 1e10, 1e30])
def test01_scaled_scene_hits_agree_as_well_as_at_scale_one(scale, at_scale_one):
    assert at_scale_one["ours_brute"] >= 0.999 and at_scale_one["ours_native"] >= 0.999
    V = (GRID_V.astype(np.float64) * scale).astype(np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # within range: no warning
        h = trace_three_ways(V, GRID_F, RAY_O * scale, RAY_D)
    _check_against_scale_one(h, at_scale_one)


@pytest.mark.parametrize("offset, size", [(1e6, 1.0), (1e8, 1e3)])
def test02_translated_scene_hits_agree_as_well_as_at_the_origin(offset, size, at_scale_one):
    """The grid moved ``offset`` away from the origin on every axis. Float32 snaps its
    vertices to the spacing there (1/16 at 1e6, 8 at 1e8: a unit grid at 1e8 would be
    a single point, so it is 1e3 wide there); the brute force traces the same snapped
    triangles. Embree misses ~35% of the hits on the snapped unit grid at 1e6, so there
    only the brute force is the reference (the check is automatic)."""
    V = (GRID_V.astype(np.float64) * size + offset).astype(np.float32)
    h = trace_three_ways(V, GRID_F, RAY_O * size + offset, RAY_D)
    assert h["brute"]["valid"].mean() > 0.5  # the snapped grid still catches most rays
    _check_against_scale_one(h, at_scale_one)


@pytest.mark.parametrize("scale, message", [(1e-33, "below 2\\*\\*-100"), (1e38, "beyond 2\\*\\*125")])
def test03_builder_warns_past_the_float32_range(scale, message):
    V = (GRID_V.astype(np.float64) * scale).astype(np.float32)
    with pytest.warns(UserWarning, match=message):
        hlbvh.build(mi.Float(V.ravel()), mi.UInt32(GRID_F.ravel()))


def _sah_float64(bvh) -> float:
    """SAH cost of a tree (C_trav = C_isect = 1, relative to the root) in numpy float64."""
    lo, hi = rows(bvh.node_min).astype(np.float64), rows(bvh.node_max).astype(np.float64)
    e = np.maximum(hi - lo, 0)
    area = e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0]
    count = bvh.node_count.numpy()
    return float(np.sum(area / area[0] * np.where(count == 0, 1, count)))


@pytest.mark.parametrize("scale", [1e-30, 1.0, 1e30, 1e38])
def test04_reported_sah_cost_is_the_trees_cost_at_every_scale(scale):
    V = (GRID_V.astype(np.float64) * scale).astype(np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bvh = hlbvh.build(mi.Float(V.ravel()), mi.UInt32(GRID_F.ravel()), builder="lbvh")
    assert bvh.stats.sah_cost == pytest.approx(_sah_float64(bvh), rel=1e-6)


@pytest.mark.xfail(strict=True, reason=(
    "sah.py: the binned SAH scales extents by 1/largest, which for a scene wider than "
    "2**126 is subnormal and flushed to zero by Dr.Jit's CPU kernels: every candidate "
    "split costs 0 and the tree degenerates (SAH 34-36 instead of 21-22, depth 30-32 "
    "instead of 11 on an 1800-triangle grid); build warns past 2**125"))
@pytest.mark.parametrize("builder", ["hlbvh", "sah"])
def test05_sah_builders_keep_their_quality_near_the_float32_maximum(builder):
    one = hlbvh.build(mi.Float(GRID_V.ravel()), mi.UInt32(GRID_F.ravel()), builder=builder)
    V = (GRID_V.astype(np.float64) * 1e38).astype(np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        huge = hlbvh.build(mi.Float(V.ravel()), mi.UInt32(GRID_F.ravel()), builder=builder)
    assert _sah_float64(huge) <= 1.05 * _sah_float64(one)


# ---------------------------------------------------------------------------------------
# 2. Extent ratio: a tiny detailed object on a huge ground
# ---------------------------------------------------------------------------------------


def uv_sphere(rings: int, radius: float, center) -> tuple[np.ndarray, np.ndarray]:
    """A bumpy UV sphere of 2·rings² triangles (float64 vertices, int64 faces)."""
    theta = np.linspace(0, np.pi, rings + 1)
    phi = np.linspace(0, 2 * np.pi, rings + 1)[:-1]
    T, P = np.meshgrid(theta, phi, indexing="ij")
    r = radius * (1 + 0.05 * np.sin(7 * T) * np.cos(5 * P))
    V = np.stack([r * np.sin(T) * np.cos(P), r * np.sin(T) * np.sin(P), r * np.cos(T)], -1)
    i, j = (a.ravel() for a in np.meshgrid(np.arange(rings), np.arange(rings), indexing="ij"))
    a, b, c, d = i * rings + j, i * rings + (j + 1) % rings, (i + 1) * rings + j, (i + 1) * rings + (j + 1) % rings
    F = np.concatenate([np.stack([a, c, d], 1), np.stack([a, d, b], 1)])
    return V.reshape(-1, 3) + np.asarray(center), F


def ground(tiles: int, size: float) -> tuple[np.ndarray, np.ndarray]:
    """A flat square of ``tiles``² quads (two triangles each) centred on the origin."""
    xs = np.linspace(-size / 2, size / 2, tiles + 1)
    x, y = np.meshgrid(xs, xs, indexing="ij")
    V = np.stack([x, y, np.zeros_like(x)], -1).reshape(-1, 3)
    a = (np.arange(tiles)[:, None] * (tiles + 1) + np.arange(tiles)[None, :]).ravel()
    F = np.concatenate([np.stack([a, a + 1, a + tiles + 2], 1), np.stack([a, a + tiles + 2, a + tiles + 1], 1)])
    return V, F


def object_on_ground(tiles: int):
    """A ~100k-triangle object in a 1e-3 box resting on a ground 1e4 wide (ratio 1e7,
    beyond what even 60-bit keys resolve: 2^20 cells per axis), and rays from a camera
    2e-3 away, half at the object, half at the ground around it."""
    Vo, Fo = uv_sphere(224, 5e-4, [0.0, 0.0, 5e-4])
    Vg, Fg = ground(tiles, 1e4)
    V = np.concatenate([Vg, Vo]).astype(np.float32)
    F = np.concatenate([Fg, Fo + len(Vg)]).astype(np.uint32)
    rng = np.random.default_rng(7)
    count = 20_000
    o = np.array([0.0, -2e-3, 1.5e-3]) + rng.normal(size=(count, 3)) * 1e-5
    target = np.concatenate([rng.uniform(Vo.min(0), Vo.max(0), (count // 2, 3)),
                             rng.uniform([-5e-3, -5e-3, 0], [5e-3, 5e-3, 0], (count - count // 2, 3))])
    d = target - o
    return V, F, (Vo.min(0), Vo.max(0)), o.astype(np.float32), (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def local_sah(bvh, lo, hi) -> float:
    """SAH cost of the part of the tree inside the box ``[lo, hi]`` relative to that
    box: what a ray that enters the object's box pays (the whole tree's SAH cost is
    dominated by the ground and hardly sees the object)."""
    n_lo, n_hi = rows(bvh.node_min).astype(np.float64), rows(bvh.node_max).astype(np.float64)
    inside = np.all(n_lo >= lo - 1e-9, 1) & np.all(n_hi <= hi + 1e-9, 1)
    e = np.maximum(n_hi - n_lo, 0)
    area = e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0]
    eo = hi - lo
    count = bvh.node_count.numpy()
    return float(np.sum((area / (eo[0] * eo[1] + eo[1] * eo[2] + eo[2] * eo[0]) * np.where(count == 0, 1, count))[inside]))


@pytest.fixture(scope="module")
def tiny_on_huge():
    V, F, box, o, d = object_on_ground(100)
    scene = mesh_scene(V, F)
    native = hits_of(scene.ray_intersect_preliminary(as_ray(o, d)))
    return V, F, box, o, d, native


#: (builder, morton_bits, quantization); the local SAH each gives is in issue 6's note.
OBJECT_CONFIGS = [("hlbvh", "auto", "cube"), ("hlbvh", 30, "cube"), ("hlbvh", 60, "cube"),
                  ("lbvh", "auto", "cube"), ("sah", 30, "cube")]


@pytest.fixture(scope="module")
def sah_local_cost(tiny_on_huge) -> float:
    V, F, box, *_ = tiny_on_huge
    return local_sah(hlbvh.build(mi.Float(V.ravel()), mi.UInt32(F.ravel()), builder="sah"), *box)


@pytest.mark.parametrize("builder, bits, quantization", OBJECT_CONFIGS)
def test06_tiny_object_on_huge_ground_hits_equal_native(builder, bits, quantization,
                                                        tiny_on_huge, sah_local_cost):
    V, F, box, o, d, native = tiny_on_huge
    bvh = hlbvh.build(mi.Float(V.ravel()), mi.UInt32(F.ravel()), builder=builder,
                      morton_bits=bits, quantization=quantization)
    check_bvh(bvh, V, F, 4)
    ours = hits_of(bvh.intersect(as_ray(o, d)))
    # Embree misses a few rays at the vertex the ground's four central tiles share.
    assert_native_or_brute_force(ours, native, V, F, o, d)
    cost = local_sah(bvh, *box)
    print(f"{builder} {bits} {quantization} -> {bvh.stats.morton_bits} {bvh.stats.quantization}: "
          f"local SAH {cost:.1f} (sah {sah_local_cost:.1f}), SAH {bvh.stats.sah_cost:.2f}, "
          f"depth {bvh.stats.depth}")
    if bits == "auto":
        # 1e7 between ground and object: beyond 60-bit cells (2^20 per axis), so the
        # auto key is 60-bit rank, and the object's sub-tree is near the full SAH's
        # (with cube keys, 30 or 60 bits alike, it costs ~14 times as much).
        assert (bvh.stats.morton_bits, bvh.stats.quantization) == (60, "rank")
        assert cost <= 1.5 * sah_local_cost


def test07_auto_key_keeps_30_bit_cubes_on_a_regular_grid_and_rank_cells_are_ranks():
    V, F = grid(160)  # 51k triangles
    bvh = hlbvh.build(mi.Float(V.ravel()), mi.UInt32(F.ravel()), morton_bits="auto")
    assert (bvh.stats.morton_bits, bvh.stats.quantization) == (30, "cube")
    # Rank keys against numpy: cell = floor(rank * 2^b / N), equal values share a rank.
    from hlbvh.kernels.morton import morton_codes

    rng = np.random.default_rng(3)
    c = np.round(rng.normal(size=(5000, 3)) ** 3, 2).astype(np.float32)  # many ties
    c[:10] = -0.0
    keys = morton_codes(mi.Point3f(c.T), mi.Point3f(0, 0, 0), mi.Point3f(1, 1, 1), 30, "rank").numpy()
    cell = [np.minimum(np.searchsorted(np.sort(c[:, k] + 0), c[:, k] + 0) * 1024 // 5000, 1023)
            for k in range(3)]
    expected = np.zeros(5000, np.int64)
    for bit in range(10):
        for k in range(3):
            expected |= ((cell[k] >> bit) & 1) << (3 * bit + 2 - k)
    np.testing.assert_array_equal(keys, expected)


@pytest.mark.xfail(strict=True, reason=(
    "traversal.py: Woop's t = (U·az + V·bz + W·cz)/det sums distances to the triangle's "
    "vertices, each rounded to 2^-24 of itself; on a ground triangle 1e4 wide that is "
    "~3e-4 of absolute error in t, 10% of a 3e-3 hit distance: the ground is reported in "
    "front of or behind the tiny object on ~28% of these rays (Embree computes t from the "
    "plane, exact for an axis-aligned ground)"))
def test08_tiny_object_on_a_two_triangle_ground_hits_equal_native():
    V, F, box, o, d = object_on_ground(1)
    native = hits_of(mesh_scene(V, F).ray_intersect_preliminary(as_ray(o, d)))
    bvh = hlbvh.build(mi.Float(V.ravel()), mi.UInt32(F.ravel()))
    assert_native_or_brute_force(hits_of(bvh.intersect(as_ray(o, d))), native, V, F, o, d)


# ---------------------------------------------------------------------------------------
# 3. Degenerate geometry
# ---------------------------------------------------------------------------------------


def _degenerate_meshes() -> dict:
    """Meshes a builder or an intersector can trip over, each with a grid of ordinary
    triangles around the odd ones so rays have something to find."""
    rng = np.random.default_rng(11)
    V, F = grid(20)
    n = len(V)

    def plus(extra_v, extra_f):
        return np.concatenate([V, extra_v]).astype(np.float32), np.concatenate([F, extra_f + n])

    points = np.repeat(rng.random((60, 3)), 3, axis=0)  # all three vertices equal
    a, b, t = rng.random((60, 3)), rng.random((60, 3)), rng.random((60, 1))
    collinear = np.stack([a, b, a + t * (b - a)], 1).reshape(-1, 3)
    # 2000 triangles whose boxes all have the same centre (so all keys are equal):
    # vertices c ± h and c + s·h, |s| <= 1 per axis.
    h = rng.uniform(0.05, 0.4, (2000, 1, 3)) * [1, 1, 0.2]
    s = rng.uniform(-1, 1, (2000, 1, 3))
    same_centre = (0.5 + np.concatenate([h, -h, s * h], 1)).reshape(-1, 3)
    meshes = {
        "zero_area_points": plus(points, np.arange(180).reshape(-1, 3)),
        "collinear": plus(collinear, np.arange(180).reshape(-1, 3)),
        "duplicates": (V, np.concatenate([F, F, F[:, ::-1]])),
        "same_centre": plus(same_centre, np.arange(6000).reshape(-1, 3)),
    }
    for axis in range(3):  # the grid flattened onto the plane x, y or z = 0.25
        P = V.copy()
        P[:, [axis, 2]] = P[:, [2, axis]]
        P[:, axis] = 0.25
        meshes[f"plane_{'xyz'[axis]}"] = (P, F)
    return meshes


DEGENERATE = _degenerate_meshes()


def _rays_at(V, count, seed):
    """Rays from a box around the mesh towards random vertices (jittered), plus as many
    axis-parallel ones through random points of the box."""
    rng = np.random.default_rng(seed)
    lo, hi = V.min(0), V.max(0)
    size = max(float((hi - lo).max()), 1e-3)
    o = (lo + hi) / 2 + rng.uniform(-1, 1, (count, 3)) * size
    d = V[rng.integers(0, len(V), count)] + rng.normal(size=(count, 3)) * size * 0.01 - o
    axis = rng.integers(0, 3, count)
    o_axis = rng.uniform(lo - 0.1, hi + 0.1, (count, 3))
    d_axis = np.zeros((count, 3))
    d_axis[np.arange(count), axis] = rng.choice([-1.0, 1.0], count)
    o_axis[np.arange(count), axis] = np.where(d_axis[np.arange(count), axis] > 0, lo[axis] - 1, hi[axis] + 1)
    o, d = np.concatenate([o, o_axis]), np.concatenate([d, d_axis])
    return o.astype(np.float32), (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh", "sah"])
@pytest.mark.parametrize("name", list(DEGENERATE))
def test09_degenerate_geometry_builds_valid_trees_and_hits_equal_brute_force(builder, name):
    V, F = DEGENERATE[name]
    F = F.astype(np.uint32)
    bvh = hlbvh.build(mi.Float(V.ravel()), mi.UInt32(F.ravel()), builder=builder, leaf_size=4)
    check_bvh(bvh, V, F, 4)
    o, d = _rays_at(V, 600, seed=len(name))
    ray = as_ray(o, d)
    ours = hits_of(bvh.intersect(ray))
    ref = brute_force(V, F, o, d)
    assert agreement(ours, ref) == 1
    assert t_error(ours, ref, V, F, o, d) <= T_REL
    np.testing.assert_array_equal(bvh.occluded(ray).numpy(), ref["valid"])


def test09b_rays_through_a_zero_area_triangle_never_hit_it():
    V = np.array([[0, 0, 0], [0, 0, 2.5e-4], [0, 0, 5e-4], [1, 1, 1], [1, 1, 1.5], [1, 1, 2]], np.float32)
    F = np.array([[0, 1, 2], [3, 4, 5]], np.uint32)
    rng = np.random.default_rng(1)
    o = np.concatenate([rng.normal(size=(2000, 3)) * 1e-3 + [0, 0, 2.5e-4],
                        rng.normal(size=(2000, 3)) + [1, 1, 1.5]]).astype(np.float32)
    d = (np.repeat([[0, 0, 2.5e-4], [1, 1, 1.5]], 2000, axis=0) - o).astype(np.float32)
    scene = mesh_scene(V, F)
    ray = as_ray(o, d)
    assert not scene.ray_intersect_preliminary(ray).is_valid().numpy().any()
    pi = hlbvh.SceneAccel(scene, static="hlbvh").ray_intersect_preliminary(ray)
    assert not pi.is_valid().numpy().any()
    assert not np.isnan(np.array(pi.compute_surface_interaction(ray).n)).any()


# ---------------------------------------------------------------------------------------
# 4. The rays ray tracers get wrong, through every query
# ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def grid_scene():
    V, F = grid(40)
    scene = mesh_scene(V, F)
    return V, F, scene, hlbvh.SceneAccel(scene, static="hlbvh"), hlbvh.build(mi.Float(V.ravel()), mi.UInt32(F.ravel()))


def queries(grid_scene, ray) -> dict:
    """Hits of ``ray`` by every query: bvh.intersect/occluded, SceneAccel's
    ray_intersect_preliminary/ray_test, and native's."""
    V, F, scene, accel, bvh = grid_scene
    return {
        "bvh": hits_of(bvh.intersect(ray)), "bvh_test": bvh.occluded(ray).numpy(),
        "accel": hits_of(accel.ray_intersect_preliminary(ray)), "accel_test": accel.ray_test(ray).numpy(),
        "native": hits_of(scene.ray_intersect_preliminary(ray)), "native_test": scene.ray_test(ray).numpy(),
    }


def assert_all_queries_agree(q: dict, ref: dict):
    for name in ("bvh", "accel"):
        assert agreement(q[name], ref) == 1, name
        np.testing.assert_array_equal(q[f"{name}_test"], ref["valid"], err_msg=name)
        assert np.all(np.isinf(q[name]["t"][~q[name]["valid"]]))


@pytest.mark.parametrize("direction", [(0, 0, -1), (1, 0, 0), (0, -1, 0), (0, 1, -1)])
def test10_axis_parallel_rays_equal_brute_force_and_native(direction, grid_scene):
    V, F = grid_scene[:2]
    rng = np.random.default_rng(2)
    count = 2000
    d = np.tile(np.asarray(direction, np.float64) / np.linalg.norm(direction), (count, 1))
    o = np.stack([rng.uniform(-0.1, 1.1, count), rng.uniform(-0.1, 1.1, count),
                  rng.uniform(-0.06, 0.06, count)], 1) - 2 * d  # start outside the grid
    o, d = o.astype(np.float32), d.astype(np.float32)
    ref = brute_force(V, F, o, d)
    q = queries(grid_scene, as_ray(o, d))
    assert_all_queries_agree(q, ref)
    assert agreement(q["accel"], q["native"]) >= 1 - 1e-3


def test11_rays_through_shared_edges_and_vertices_never_slip_through(grid_scene):
    """Vertical rays through the grid's interior edges and vertices (x = i/40 exactly):
    every one must hit. Measured: none slips through ours; Embree lets 62 of 9,500
    through (772 with coherent=True)."""
    rng = np.random.default_rng(5)
    count = 10_000
    x = rng.integers(1, 40, count) / np.float32(40)
    y = np.where(rng.random(count) < 0.5, rng.integers(1, 40, count) / np.float32(40),
                 rng.uniform(0.01, 0.99, count))
    o = np.stack([x, y, np.ones(count)], 1).astype(np.float32)
    d = np.tile(np.float32([0, 0, -1]), (count, 1))
    q = queries(grid_scene, as_ray(o, d))
    for name in ("bvh", "accel"):
        assert q[name]["valid"].all() and q[f"{name}_test"].all(), name


def test12_rays_along_a_shared_edge_in_a_flat_mesh_miss_cleanly():
    """Rays lying in the plane of a flat grid, along its edges (and along its
    diagonals): every triangle is seen edge-on (zero determinant), so every query is
    a clean miss, as for the brute force; nothing hangs."""
    V, F = grid(10)
    V = V * np.float32([1, 1, 0])
    xs = np.arange(11, dtype=np.float32) / 10
    o = np.concatenate([np.stack([xs, np.full(11, -1), np.zeros(11)], 1),   # along x = i/10
                        np.stack([np.full(11, -1), xs, np.zeros(11)], 1),   # along y = i/10
                        np.stack([xs - 1, np.full(11, -1), np.zeros(11)], 1)]).astype(np.float32)
    d = np.concatenate([np.tile([0, 1, 0], (11, 1)), np.tile([1, 0, 0], (11, 1)),
                        np.tile([1, 1, 0], (11, 1)) / np.sqrt(2)]).astype(np.float32)
    ref = brute_force(V, F, o, d)
    assert not ref["valid"].any()
    scene = mesh_scene(V, F)
    q = queries((V, F, scene, hlbvh.SceneAccel(scene, static="hlbvh"), hlbvh.build(mi.Float(V.ravel()), mi.UInt32(F.ravel()))),
                as_ray(o, d))
    assert_all_queries_agree(q, ref)


def test13_rays_spawned_on_a_surface_do_not_hit_it_and_equal_native(grid_scene):
    """Rays leaving native primary hits with Mitsuba's ``si.spawn_ray`` offsets, into
    both hemispheres: no query hits the triangle the ray starts on at t ~ 0, and the
    hits equal native's."""
    V, F, scene, accel, bvh = grid_scene
    rng = np.random.default_rng(9)
    count = 10_000
    o = np.stack([rng.uniform(0, 1, count), rng.uniform(0, 1, count), np.ones(count)], 1)
    d = np.tile([0.0, 0.0, -1.0], (count, 1)) + rng.normal(size=(count, 3)) * 0.2
    si = scene.ray_intersect(as_ray(o, d / np.linalg.norm(d, axis=1, keepdims=True)))
    si = dr.gather(mi.SurfaceInteraction3f, si, mi.UInt32(np.flatnonzero(si.is_valid().numpy())))
    count = dr.width(si)
    assert count > 5000
    w = rng.normal(size=(count, 3))
    spawned = si.spawn_ray(mi.Vector3f(np.float32(w / np.linalg.norm(w, axis=1, keepdims=True)).T))
    q = queries(grid_scene, spawned)
    start = si.prim_index.numpy()
    for name in ("bvh", "accel"):
        self_hit = q[name]["valid"] & (q[name]["prim"] == start) & (q[name]["t"] < 1e-3)
        assert not self_hit.any(), f"{name}: {self_hit.sum()} self-intersections"
        assert agreement(q[name], q["native"]) >= 1 - 1e-3
        assert np.mean(q[f"{name}_test"] == q["native_test"]) >= 1 - 1e-3


@pytest.mark.parametrize("maxt, hits", [(0.0, False), (-1.0, False), (np.nan, False),
                                        (0.5, False), (2.0, True), (np.inf, True)])
def test14_maxt_is_honoured_by_every_query(maxt, hits, grid_scene):
    """Vertical rays from z = 1 onto the grid (|z| <= 0.05): maxt 0, negative or NaN
    miss, 0.5 falls short, 2 and inf hit. (Native ``ray_test`` reports every ray with a
    negative maxt as occluded; its preliminary query misses.)"""
    rng = np.random.default_rng(4)
    o = np.stack([rng.uniform(0, 1, 500), rng.uniform(0, 1, 500), np.ones(500)], 1)
    d = np.tile([0.0, 0.0, -1.0], (500, 1))
    q = queries(grid_scene, as_ray(o, d, maxt))
    for name in ("bvh", "accel", "native"):
        assert np.all(q[name]["valid"] == hits), name
    for name in ("bvh_test", "accel_test"):
        assert np.all(q[name] == hits), name
    if maxt >= 0 or np.isnan(maxt):
        assert np.all(q["native_test"] == hits)


@pytest.mark.parametrize("o, d", [
    ((0.5, 0.5, 1), (0, 0, 0)),          # zero direction
    ((0.5, 0.5, 1), (np.nan, 0, -1)),    # NaN direction
    ((0.5, 0.5, 1), (0, np.inf, -1)),    # infinite direction
    ((np.nan, 0.5, 1), (0, 0, -1)),      # NaN origin
    ((0.5, -np.inf, 1), (0, 0, -1)),     # infinite origin
    ((0.5, 0.5, 1), (1e-45, 0, -1e-45)),  # subnormal direction
])
def test15_nan_zero_and_infinite_rays_miss_cleanly(o, d, grid_scene):
    o = np.tile(np.float32(o), (100, 1))
    d = np.tile(np.float32(d), (100, 1))
    q = queries(grid_scene, as_ray(o, d))
    for name in ("bvh", "accel"):
        assert not q[name]["valid"].any() and not q[f"{name}_test"].any(), name
        assert np.all(np.isinf(q[name]["t"]))


# ---------------------------------------------------------------------------------------
# 7. Long runs
# ---------------------------------------------------------------------------------------


def rss_mb() -> float:
    """Resident memory of this process (VmRSS) in MB, after a garbage collection and
    with Dr.Jit's cache of freed device memory released (what is left is live)."""
    gc.collect()
    dr.flush_malloc_cache()
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024


def deformed(x: mi.Point3f, frame: int) -> mi.Float:
    """Frame ``frame`` of a rippling deformation of points ``x``, as a flat Float. The
    phase is opaque: a literal would compile a new kernel every frame, and that (not
    the builder) would grow the process by ~25 KB per frame."""
    phase = dr.opaque(mi.Float, 0.1 * frame)
    z = x.z + 0.05 * dr.sin(5 * x.x + phase) * dr.cos(3 * x.y - phase)
    v = dr.ravel(mi.Point3f(x.x, x.y, z))
    dr.eval(v)
    return v


def assert_flat(rss: dict, bound_mb: float = 12.0):
    """Memory after the last frame within ``bound_mb`` of frame 20's. (Time is not
    asserted: tests never assert on time; bench frame measures it.)"""
    assert rss["last"] - rss[20] <= bound_mb, rss


@pytest.mark.slow
def test16_200_rebuilds_with_temporal_reuse_keep_memory_flat():
    """A 100k-triangle deforming mesh rebuilt 200 times, each build seeded with the
    previous one's order. (Measured once for 500 frames: 155.0 MB at frame 10, 157.0 MB
    at frame 500.)"""
    V, F = grid(224)
    x, faces = mi.Point3f(V.T), mi.UInt32(F.ravel())
    bvh, rss = None, {}
    for frame in range(200):
        bvh = hlbvh.build(deformed(x, frame), faces, previous=bvh)
        if frame + 1 == 20:
            rss[20] = rss_mb()
    rss["last"] = rss_mb()
    assert_flat(rss)


@pytest.mark.slow
def test17_scene_accel_updates_and_traces_keep_memory_flat():
    """A 20k-triangle mesh of a Mitsuba scene deformed through ``params.update()``,
    then ``SceneAccel.update()`` and a trace, 100 times."""
    V, F = grid(100)
    scene = mesh_scene(V, F)
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("vertex_positions"))
    accel = hlbvh.SceneAccel(scene, static="hlbvh")
    rng = np.random.default_rng(0)
    ray = as_ray(np.stack([rng.random(20_000), rng.random(20_000), np.ones(20_000)], 1),
                 np.tile([0.0, 0.0, -1.0], (20_000, 1)))
    x, rss = mi.Point3f(V.T), {}
    for frame in range(100):
        params[key] = deformed(x, frame)
        params.update()
        accel.update()
        hit = accel.ray_intersect_preliminary(ray).is_valid()
        if frame + 1 == 20:
            rss[20] = rss_mb()
        assert dr.all(hit)
    rss["last"] = rss_mb()
    assert_flat(rss)


def _kernel_hashes(fn) -> set:
    """Hashes of the kernels ``fn()`` launched."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        fn()
        return {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


def test18_tracing_a_tree_of_another_size_runs_the_same_kernels():
    """Per-frame work must not compile: tracing the same rays through trees over 1800
    and 1682 triangles launches kernels with the same hashes."""
    ray = as_ray(*grid_rays(1000, seed=3))
    trees = [hlbvh.build(mi.Float(V.ravel()), mi.UInt32(F.ravel())) for V, F in (grid(30), grid(29))]
    hashes = [_kernel_hashes(lambda: dr.eval(bvh.intersect(ray).t)) for bvh in trees]
    assert hashes[0] == hashes[1], f"{len(hashes[0] ^ hashes[1])} kernels differ"
