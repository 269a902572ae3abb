"""Traversal kernels (closest hit, any hit) against a brute-force intersector, against
Mitsuba's native intersector, and on the inputs where ray tracers go wrong: shared
edges and vertices, axis-parallel rays, maxt, rays starting on a surface, NaN rays,
corrupt and too-deep trees."""

from __future__ import annotations

import numpy as np
import pytest

import hlbvh  # noqa: F401  (sets up libLLVM and the variant before drjit is used)
import drjit as dr
import mitsuba as mi

from reference import brute_force, median_split_bvh, random_soup, triangle_grid  # noqa: E402

from hlbvh.kernels import layout, traversal  # noqa: E402
from hlbvh.kernels.arrays import namespace_of  # noqa: E402
from hlbvh.kernels.bvh import BVH, BuildConfig, BuildStats  # noqa: E402
from hlbvh.kernels.layout import packing  # noqa: E402
from hlbvh.kernels.layout import slots as slot_format  # noqa: E402
from hlbvh.kernels.traversal import any_hit, closest_hit  # noqa: E402

BUILDERS = ("median", "lbvh", "hlbvh", "sah")
T_REL = 1e-6  # relative tolerance on t against the float64 reference (see below)
UV_ABS = 1e-5  # tolerance on the barycentrics (scaled as t's, see below)


# ---------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------


def build(vertices, faces, builder, leaf_size=4):
    """A BVH from our reference median-split builder or from ``hlbvh.build``."""
    if builder == "median":
        return median_split_bvh(vertices, faces, leaf_size)
    return hlbvh.build(mi.Float(np.ravel(vertices)), mi.UInt32(np.ravel(faces)),
                       builder=builder, leaf_size=leaf_size)


def random_rays(rng, count, lo=-0.2, hi=1.2):
    """Float32 origins uniform in a box, directions from a normal distribution."""
    o = (lo + (hi - lo) * rng.random((count, 3))).astype(np.float32)
    d = rng.normal(size=(count, 3)).astype(np.float32)
    return o, d


def trace(bvh, o, d, maxt=np.inf, active=True):
    """closest_hit and any_hit on numpy rays; numpy results."""
    O, D = mi.Point3f(np.asarray(o, np.float32).T), mi.Vector3f(np.asarray(d, np.float32).T)
    if np.ndim(maxt):
        maxt = mi.Float(np.asarray(maxt, np.float32))
    t, u, v, prim, valid = closest_hit(bvh, O, D, maxt, active)
    occluded = any_hit(bvh, O, D, maxt, active)
    return {"t": t.numpy(), "u": u.numpy(), "v": v.numpy(), "prim": prim.numpy(),
            "valid": valid.numpy(), "any": occluded.numpy()}


def assert_matches_reference(ours, ref, vertices, faces, o, d):
    """Same validity; same primitive unless the reference has an equal-t tie; t within
    T_REL relative; barycentrics within UV_ABS where the primitive is the same.

    "Relative" is relative to ``max(t, r) / cos``: ``r`` the distance (in units of
    ``|d|``) from the origin to the hit triangle's farthest vertex, since float32
    coordinates carry an absolute error proportional to their size (a hit at
    ``t = 1e-4`` on a triangle 0.5 away cannot be located to 1e-10); ``cos`` the cosine
    between ray and triangle normal, since a grazing ray's hit distance is
    ill-conditioned.
    """
    np.testing.assert_array_equal(ours["valid"], ref["valid"])
    np.testing.assert_array_equal(ours["any"], ref["valid"])
    hit = ref["valid"]
    rows = np.flatnonzero(hit)
    t_ref = ref["t"][hit]
    corners = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)[ref["prim"][hit]]]
    dirs = np.asarray(d, np.float64)[hit]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    cos = np.abs(np.sum(normal * dirs, axis=1)) / np.linalg.norm(normal, axis=1)
    reach = np.max(np.linalg.norm(corners - np.asarray(o, np.float64)[hit, None], axis=2),
                   axis=1) / np.linalg.norm(np.asarray(d, np.float64)[hit], axis=1)
    error = np.abs(ours["t"][hit] - t_ref)
    bound = T_REL * np.maximum(t_ref, reach) / cos
    assert np.all(error <= bound), np.max(error / bound)
    assert np.all(np.isinf(ours["t"][~hit]))
    same = ours["prim"][hit] == ref["prim"][hit]
    t_of_ours = ref["t_all"][rows, ours["prim"][hit].astype(np.int64)]
    tie = np.abs(t_of_ours - t_ref) <= T_REL * t_ref
    assert np.all(same | tie), f"{np.sum(~(same | tie))} rays hit a farther primitive"
    # Barycentrics: the same conditioning, in units of the triangle's size.
    size = np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2), axis=1)
    uv_bound = UV_ABS * np.maximum(1.0, np.maximum(t_ref, reach) / size) / cos
    for k in ("u", "v"):
        uv_error = np.abs(ours[k][hit] - ref[k][hit])[same]
        assert np.all(uv_error <= uv_bound[same]), np.max(uv_error / uv_bound[same])


# ---------------------------------------------------------------------------------------
# Against the brute-force intersector
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("builder", BUILDERS)
@pytest.mark.parametrize("leaf_size", [1, 4, 16])
def test01_random_soup_matches_brute_force(builder, leaf_size):
    rng = np.random.default_rng(1)
    vertices, faces = random_soup(300, seed=2)
    bvh = build(vertices, faces, builder, leaf_size)
    o, d = random_rays(rng, 3000)
    ref = brute_force(vertices, faces, o, d)
    assert ref["valid"].sum() > 300  # the test exercises hits, not just misses
    assert_matches_reference(trace(bvh, o, d), ref, vertices, faces, o, d)


@pytest.mark.parametrize("builder", BUILDERS)
def test02_tilted_grid_matches_brute_force(builder):
    rng = np.random.default_rng(3)
    vertices, faces = triangle_grid(12, 10)
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    vertices = (vertices / 10 @ rotation.T + 0.3).astype(np.float32)
    bvh = build(vertices, faces, builder)
    o, d = random_rays(rng, 3000, -1.0, 1.5)
    # Aim two thirds of the rays at points on or just beyond the grid.
    uv = rng.random((2000, 2)) * [1.4, 1.2] - 0.1
    target = np.column_stack([uv, np.zeros(2000)]) * [1.2, 1.0, 0] @ rotation.T + 0.3
    d[:2000] = (target - o[:2000]).astype(np.float32)
    ref = brute_force(vertices, faces, o, d)
    assert ref["valid"].sum() > 1000
    assert_matches_reference(trace(bvh, o, d), ref, vertices, faces, o, d)


def test03_single_triangle_root_leaf():
    """A tree that is a single leaf (fewer triangles than the leaf size)."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    faces = np.array([[0, 1, 2]], np.uint32)
    for builder in BUILDERS:
        bvh = build(vertices, faces, builder)
        o = np.array([[0.25, 0.25, 1], [0.9, 0.9, 1], [0.25, 0.25, -1]], np.float32)
        d = np.array([[0, 0, -2], [0, 0, -1], [0, 0, 1]], np.float32)
        ours = trace(bvh, o, d)
        np.testing.assert_array_equal(ours["valid"], [True, False, True])
        np.testing.assert_allclose(ours["t"][[0, 2]], [0.5, 1.0])
        np.testing.assert_allclose(ours["u"][0], 0.25)
        np.testing.assert_allclose(ours["v"][0], 0.25)


# ---------------------------------------------------------------------------------------
# Watertightness: shared edges and vertices
# ---------------------------------------------------------------------------------------


def _grid_targets(n):
    """Interior vertices and points on interior edges (axis and diagonal) of an n×n
    grid of unit squares, in the grid's own coordinates (float64)."""
    points = [(i, j) for i in range(1, n) for j in range(1, n)]
    for f in (0.25, 0.5, 1 / 3, 0.7):
        points += [(i + f, j) for i in range(n) for j in range(1, n)]  # horizontal
        points += [(i, j + f) for i in range(1, n) for j in range(n)]  # vertical
        points += [(i + f, j + f) for i in range(n) for j in range(n)]  # diagonals
    return np.array(points, np.float64)


@pytest.mark.parametrize("builder", ["median", "hlbvh"])
def test04_rays_at_shared_edges_and_vertices_never_slip_through(builder):
    n = 8
    targets = _grid_targets(n)
    rng = np.random.default_rng(4)
    # Axis-aligned grid at integer coordinates: the rays pass exactly through the
    # edges and vertices. Rays straight down, and oblique from random origins above
    # and below.
    vertices, faces = triangle_grid(n, n)
    bvh = build(vertices, faces, builder)
    p = np.column_stack([targets, np.zeros(len(targets))]).astype(np.float32)
    o = np.concatenate([p + [0, 0, 1]] + [
        p + (rng.random((len(p), 3)) - 0.5) * [6, 6, 0] + [0, 0, z] for z in (2, -3, 5)
    ]).astype(np.float32)
    p = np.tile(p, (4, 1))
    ours = trace(bvh, o, p - o)
    assert ours["valid"].all(), f"{np.sum(~ours['valid'])} of {len(o)} rays slipped through"
    assert ours["any"].all()
    np.testing.assert_allclose(ours["t"], 1.0, rtol=1e-5)

    # The same grid rotated and shifted: targets rounded to float32 lie within rounding
    # of the edges, on one side or the other; every ray must still hit.
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    shift = np.array([0.37, -1.25, 2.5])
    tilted = (vertices.astype(np.float64) @ rotation.T + shift).astype(np.float32)
    bvh = build(tilted, faces, builder)
    normal = rotation[:, 2]
    p = (np.column_stack([targets, np.zeros(len(targets))]) @ rotation.T + shift)
    rays_o, rays_d = [], []
    for side in (1, -1):
        for _ in range(3):
            o = p + side * (2 + rng.random((len(p), 1))) * normal \
                + (rng.random((len(p), 3)) - 0.5) * 3
            rays_o.append(o)
            rays_d.append(p - o)
    o = np.concatenate(rays_o).astype(np.float32)
    d = np.concatenate(rays_d).astype(np.float32)
    ours = trace(bvh, o, d)
    assert ours["valid"].all(), f"{np.sum(~ours['valid'])} of {len(o)} rays slipped through"
    assert ours["any"].all()


@pytest.mark.parametrize("builder", ["median", "lbvh"])
def test05_axis_parallel_rays_match_brute_force(builder):
    rng = np.random.default_rng(5)
    # A random soup and a grid whose boxes are flat (zero extent in z).
    soup_v, soup_f = random_soup(200, seed=6)
    grid_v, grid_f = triangle_grid(6, 6)
    grid_v = grid_v / 6
    for vertices, faces in ((soup_v, soup_f), (grid_v, grid_f)):
        bvh = build(vertices, faces, builder)
        o, d = [], []
        for axis in range(3):
            for sign in (1, -1):
                direction = np.zeros(3)
                direction[axis] = sign
                origin = rng.random((400, 3)) * 1.2 - 0.1
                origin[:, axis] = 0.5 - 2 * sign
                o.append(origin)
                d.append(np.tile(direction, (400, 1)))
        o = np.concatenate(o).astype(np.float32)
        d = np.concatenate(d).astype(np.float32)
        ref = brute_force(vertices, faces, o, d)
        assert ref["valid"].sum() > 100
        assert_matches_reference(trace(bvh, o, d), ref, vertices, faces, o, d)


# ---------------------------------------------------------------------------------------
# maxt, t <= 0, degenerate rays
# ---------------------------------------------------------------------------------------


def test06_maxt_is_honoured():
    rng = np.random.default_rng(7)
    vertices, faces = random_soup(300, seed=8)
    bvh = build(vertices, faces, "median")
    o, d = random_rays(rng, 3000)
    ref = brute_force(vertices, faces, o, d)
    hit = ref["valid"]

    for maxt in (0.0, -1.0):
        ours = trace(bvh, o, d, maxt)
        assert not ours["valid"].any() and not ours["any"].any()

    # Half the nearest distance: nothing is nearer, so every ray misses.
    half = np.where(hit, 0.5 * ref["t"], 1.0)
    ours = trace(bvh, o[hit], d[hit], half[hit])
    assert not ours["valid"].any() and not ours["any"].any()

    # maxt exactly at our own hit distance: the hit is kept (0 < t <= maxt).
    full = trace(bvh, o, d)
    ours = trace(bvh, o[hit], d[hit], full["t"][hit])
    assert ours["valid"].all() and ours["any"].all()
    np.testing.assert_array_equal(ours["t"], full["t"][hit])

    # Random maxt per ray against the brute force with the same maxt, except rays whose
    # nearest hit is within rounding of maxt.
    maxt = (rng.random(len(o)) * 2).astype(np.float32)
    ref = brute_force(vertices, faces, o, d, maxt.astype(np.float64))
    t_any = np.min(np.where(np.isfinite(ref["t_all"]), ref["t_all"], np.inf), axis=1)
    near = np.abs(brute_force(vertices, faces, o, d)["t"] - maxt) <= 1e-5 * maxt
    ours = trace(bvh, o, d, maxt)
    keep = ~near
    np.testing.assert_array_equal(ours["valid"][keep], ref["valid"][keep])
    np.testing.assert_array_equal(ours["any"][keep], ref["valid"][keep])
    assert np.all(t_any[ours["valid"]] <= maxt[ours["valid"]] * (1 + 1e-5))

    ours = trace(bvh, o, d, np.inf)
    np.testing.assert_array_equal(ours["valid"], full["valid"])

    # A flat grid (its boxes have zero height) hit at exactly t = maxt = 1, and missed
    # with maxt one ulp below (dyadic origins: every quantity is exact).
    grid_v, grid_f = triangle_grid(5, 5)
    bvh = build(grid_v, grid_f, "median", leaf_size=1)
    o = np.column_stack([rng.integers(0, 320, (200, 2)) / 64, np.ones(200)]).astype(np.float32)
    d = np.tile(np.float32([0, 0, -1]), (200, 1))
    ours = trace(bvh, o, d, np.ones(200, np.float32))
    assert ours["valid"].all() and ours["any"].all()
    np.testing.assert_array_equal(ours["t"], 1.0)
    ours = trace(bvh, o, d, np.full(200, np.nextafter(np.float32(1), np.float32(0))))
    assert not ours["valid"].any() and not ours["any"].any()


def test07_no_hit_at_or_behind_the_origin():
    # Rays starting exactly on the plane of a grid (z = 0, exact coordinates): with z
    # the dominant axis of the direction the transformed z of every vertex is exactly
    # 0, so t = 0 and the grid is not hit. With another dominant axis, rounding may put
    # a hit a few ulps in front of the origin (as in Embree; Mitsuba offsets spawned
    # rays for that reason), but never at t <= 0.
    vertices, faces = triangle_grid(4, 4)
    bvh = build(vertices, faces, "median")
    rng = np.random.default_rng(9)
    o = np.column_stack([rng.random((500, 2)) * 4, np.zeros(500)]).astype(np.float32)
    d = rng.normal(size=(500, 3)).astype(np.float32)
    d[:250, 2] = np.sign(d[:250, 2]) * (np.abs(d[:250, :2]).max(axis=1) + 0.1)
    ours = trace(bvh, o, d)
    assert not ours["valid"][:250].any() and not ours["any"][:250].any()
    assert np.all(ours["t"][ours["valid"]] > 0)
    assert np.all(ours["t"][ours["valid"]] < 1e-5)

    # A triangle behind the origin is never hit; one in front is.
    o = np.array([[1.5, 1.5, 1.0], [1.5, 1.5, -1.0]], np.float32)
    d = np.array([[0, 0, 1], [0, 0, 1]], np.float32)
    ours = trace(bvh, o, d)
    np.testing.assert_array_equal(ours["valid"], [False, True])

    # On random meshes every reported hit has t > 0.
    soup_v, soup_f = random_soup(200, seed=10)
    bvh = build(soup_v, soup_f, "median")
    start = soup_v[soup_f[:, 0]]  # origins at vertices of the soup
    ours = trace(bvh, start, rng.normal(size=start.shape))
    assert np.all(ours["t"][ours["valid"]] > 0)


def test08_nan_inf_and_zero_rays_miss_cleanly():
    vertices, faces = random_soup(100, seed=11)
    bvh = build(vertices, faces, "median")
    nan, inf = np.nan, np.inf
    centroid = vertices[faces[0]].mean(axis=0)
    good_o, good_d = [centroid[0], centroid[1], -1.0], [0.0, 0.0, 1.0]
    cases = [  # (origin, direction, maxt)
        ([nan, good_o[1], -1], good_d, inf),
        (good_o, [0, nan, 1], inf),
        (good_o, [0, 0, 0], inf),
        ([inf, good_o[1], -1], good_d, inf),
        (good_o, [0, 0, inf], inf),
        (good_o, good_d, nan),
        (good_o, good_d, -1.0),
        (good_o, good_d, 0.0),
        (good_o, [0, 0, -0.0], inf),
    ]
    o = np.array([c[0] for c in cases] + [good_o], np.float32)
    d = np.array([c[1] for c in cases] + [good_d], np.float32)
    maxt = np.array([c[2] for c in cases] + [inf], np.float32)
    ours = trace(bvh, o, d, maxt)
    ref = brute_force(vertices, faces, o[-1:], d[-1:])
    assert ref["valid"][0]  # the control ray hits the soup
    np.testing.assert_array_equal(ours["valid"], [False] * len(cases) + [True])
    np.testing.assert_array_equal(ours["any"], ours["valid"])
    assert np.all(np.isinf(ours["t"][:-1]))
    # The mask: inactive rays miss too.
    active = mi.Bool([True] * len(cases) + [False])
    ours = trace(bvh, o, d, maxt, active)
    assert not ours["valid"].any() and not ours["any"].any()


@pytest.mark.parametrize("scale", [1e30, 1e-30])
def test09_huge_and_tiny_coordinates(scale):
    """Edge functions of coordinates near 1e30 overflow float32 and near 1e-30
    underflow: those triangles are redone in double precision."""
    rng = np.random.default_rng(21)
    vertices, faces = random_soup(200, seed=22)
    o, d = random_rays(rng, 2000)
    vertices = (vertices.astype(np.float64) * scale).astype(np.float32)
    o = (o.astype(np.float64) * scale).astype(np.float32)
    ref = brute_force(vertices, faces, o, d)
    assert ref["valid"].sum() > 150
    for builder in ("median", "hlbvh"):
        bvh = build(vertices, faces, builder)
        assert_matches_reference(trace(bvh, o, d), ref, vertices, faces, o, d)


# ---------------------------------------------------------------------------------------
# API: types, widths, Dr.Jit's debug checks
# ---------------------------------------------------------------------------------------


def test10_intersect_and_occluded_return_mitsuba_types():
    rng = np.random.default_rng(12)
    vertices, faces = random_soup(200, seed=13)
    bvh = build(vertices, faces, "hlbvh")
    o, d = random_rays(rng, 500)
    origin = mi.Point3f(o.T)
    dr.enable_grad(origin)  # AD inputs are accepted and detached
    ray = mi.Ray3f(origin, mi.Vector3f(d.T))
    pi = bvh.intersect(ray)
    assert isinstance(pi, mi.PreliminaryIntersection3f)
    ref = brute_force(vertices, faces, o, d)
    np.testing.assert_array_equal(pi.is_valid().numpy(), ref["valid"])
    hit = ref["valid"]
    np.testing.assert_allclose(pi.t.numpy()[hit], ref["t"][hit], rtol=T_REL)
    assert np.all(np.isinf(pi.t.numpy()[~hit]))
    np.testing.assert_array_equal(pi.prim_index.numpy()[hit], ref["prim"][hit])
    np.testing.assert_allclose(pi.prim_uv.numpy()[0][hit], ref["u"][hit], atol=UV_ABS)
    occ = bvh.occluded(ray)
    assert isinstance(occ, mi.Bool)
    np.testing.assert_array_equal(occ.numpy(), ref["valid"])
    # maxt of the ray is honoured.
    ray.maxt = mi.Float(0.5 * np.where(hit, ref["t"], 1.0))
    assert not dr.any(bvh.occluded(ray)) and not dr.any(bvh.intersect(ray).is_valid())


def test11_debug_mode_finds_no_out_of_bounds_access(capfd):
    """Dr.Jit's debug mode range-checks every local-memory (stack) and gather access;
    a loop-state variable of width 1 (which makes all lanes share one local-memory
    stack) would show up here as wrong hits or as out-of-bounds reports. Rays of
    width 1 are broadcast."""
    rng = np.random.default_rng(14)
    vertices, faces = random_soup(400, seed=15)
    bvh = build(vertices, faces, "lbvh", leaf_size=2)
    o, d = random_rays(rng, 2000)
    o[:] = o[0]  # one origin for all rays: passed as a width-1 array
    ref = brute_force(vertices, faces, o, d)
    with dr.scoped_set_flag(dr.JitFlag.Debug, True):
        t, u, v, prim, valid = closest_hit(bvh, mi.Point3f(o[0]), mi.Vector3f(d.T),
                                           mi.Float(np.inf))
        occ = any_hit(bvh, mi.Point3f(o[0]), mi.Vector3f(d.T), np.inf, mi.Bool(True))
        dr.eval(t, u, v, prim, valid, occ)
    err = capfd.readouterr().err
    assert "out-of-bounds" not in err and "out of bounds" not in err, err
    ours = {"t": t.numpy(), "u": u.numpy(), "v": v.numpy(), "prim": prim.numpy(),
            "valid": valid.numpy(), "any": occ.numpy()}
    assert_matches_reference(ours, ref, vertices, faces, o, d)


def test12_traced_inside_a_symbolic_loop():
    """Integrators trace rays inside their own symbolic loops: with the records packed
    beforehand (as an accelerator does when it builds), closest_hit and any_hit nest."""
    rng = np.random.default_rng(23)
    vertices, faces = random_soup(300, seed=24)
    bvh = build(vertices, faces, "hlbvh")
    packing.packed_records(bvh)
    o, d = random_rays(rng, 1000)
    origin, direction = mi.Point3f(o.T), mi.Vector3f(d.T)

    def body(i, t_sum, hits):
        t, _, _, _, valid = closest_hit(bvh, origin, direction, mi.Float(np.inf))
        occluded = any_hit(bvh, origin, direction, np.inf)
        return i + 1, t_sum + dr.select(valid, t, 0), hits + mi.UInt32(occluded)

    state = (dr.zeros(mi.UInt32, 1000), dr.zeros(mi.Float, 1000), dr.zeros(mi.UInt32, 1000))
    _, t_sum, hits = dr.while_loop(state, lambda i, t_sum, hits: i < 2, body,
                                   labels=("i", "t_sum", "hits"), mode="symbolic")
    ref = brute_force(vertices, faces, o, d)
    np.testing.assert_allclose(t_sum.numpy(), 2 * np.where(ref["valid"], ref["t"], 0),
                               rtol=1e-5)
    np.testing.assert_array_equal(hits.numpy(), 2 * ref["valid"])


def test13_bad_arguments_raise_and_no_rays_give_empty_results():
    vertices, faces = random_soup(50, seed=16)
    bvh = build(vertices, faces, "median")
    with pytest.raises(ValueError, match="widths"):
        closest_hit(bvh, mi.Point3f([0, 1], [0, 1], [0, 1]), mi.Vector3f([0, 1, 2], 0, 1),
                    np.inf)
    with pytest.raises(TypeError, match="Array3f"):
        closest_hit(bvh, (0, 0, 0), mi.Vector3f(0, 0, 1), np.inf)
    # No rays: empty results.
    results = closest_hit(bvh, mi.Point3f(), mi.Vector3f(), mi.Float())
    assert [dr.width(x) for x in results] == [0] * 5
    assert dr.width(any_hit(bvh, mi.Point3f(), mi.Vector3f(), np.inf)) == 0


# ---------------------------------------------------------------------------------------
# Corrupt and too-deep trees
# ---------------------------------------------------------------------------------------


def _caterpillar(levels, depth_in_stats):
    """A hand-made chain tree over ``levels`` stacked squares (two triangles each, one
    leaf per square): node k has the leaf of square k and the subtree of squares
    k+1... as children, so a ray from above pushes one entry per level."""
    ns = namespace_of(mi.Float)
    squares = np.arange(levels) * 0.01
    vertices, faces = [], []
    for k, z in enumerate(squares):
        vertices += [[0, 0, z], [1, 0, z], [0, 1, z], [1, 1, z]]
        faces += [[4 * k, 4 * k + 1, 4 * k + 3], [4 * k, 4 * k + 3, 4 * k + 2]]
    vertices, faces = np.array(vertices, np.float32), np.array(faces, np.uint32)
    # Nodes: internal node k at index 2k (k < levels-1), its leaf at 2k+1, its
    # subtree at 2k+2; the last square is the leaf at index 2(levels-1).
    lo, hi, first, count = [], [], [], []
    for k in range(levels):
        if k < levels - 1:
            lo.append([0, 0, squares[k]]); hi.append([1, 1, squares[-1]])
            first.append(2 * k + 1); count.append(0)
            lo.append([0, 0, squares[k]]); hi.append([1, 1, squares[k]])
            first.append(2 * k); count.append(2)
        else:
            lo.append([0, 0, squares[k]]); hi.append([1, 1, squares[k]])
            first.append(2 * k); count.append(2)
    p = vertices[faces]
    return BVH(
        node_min=ns.Array3f(np.array(lo, np.float32).T),
        node_max=ns.Array3f(np.array(hi, np.float32).T),
        node_first=ns.UInt32(np.array(first, np.uint32)),
        node_count=ns.UInt32(np.array(count, np.uint32)),
        prim_ids=ns.UInt32(np.arange(len(faces), dtype=np.uint32)),
        tri_p0=ns.Array3f(p[:, 0].T), tri_p1=ns.Array3f(p[:, 1].T),
        tri_p2=ns.Array3f(p[:, 2].T),
        faces=ns.UInt32(faces.ravel()), levels=[], config=BuildConfig(leaf_size=2),
        stats=BuildStats(depth=depth_in_stats),
    )


def test14_too_deep_tree_is_refused_and_the_deepest_that_packs_traces():
    """A chain deeper than the traversal stack allows is refused when packed, whatever
    its statistics say (the packer measures the depth itself); the deepest chain that
    packs traces: rays from above hit the top square, rays from below the lowest."""
    too_deep = slot_format.MAX_DEPTH + 10
    for depth_in_stats in (too_deep - 1, 0):
        with pytest.raises(ValueError, match="depth"):
            trace(_caterpillar(too_deep, depth_in_stats=depth_in_stats), [[0.5, 0.5, 2]],
                  [[0, 0, -1]])
    levels = slot_format.MAX_DEPTH
    bvh = _caterpillar(levels, depth_in_stats=0)
    top = (levels - 1) * 0.01
    o = np.array([[0.3, 0.6, 2.0], [0.3, 0.6, -1.0], [0.3, 0.6, 0.5 * 0.01]], np.float32)
    d = np.array([[0, 0, -1], [0, 0, 1], [0, 0, -1]], np.float32)
    with dr.scoped_set_flag(dr.JitFlag.Debug, True):
        ours = trace(bvh, o, d)
    np.testing.assert_array_equal(ours["valid"], [True, True, True])
    np.testing.assert_allclose(ours["t"], [2.0 - top, 1.0, 0.5 * 0.01], rtol=1e-5)


def test15_cycle_or_shared_subtree_is_refused():
    """A tree with a cycle (the root's left child has the root as a child) or a
    subtree reached twice is refused when packed, naming the problem, before any ray
    could loop in it."""
    vertices, faces = random_soup(64, seed=17)
    bvh = median_split_bvh(vertices, faces, 4)
    first = bvh.node_first.numpy()
    cycle = first.copy()
    cycle[first[0]] = 0  # the root's left child now has the root as its children
    shared = first.copy()
    right = first[0] + 1
    inner = np.flatnonzero(bvh.node_count.numpy() == 0)
    shared[right] = first[inner[inner != 0][0]] if first[right] != 0 else first[right]
    for broken, pattern in ((cycle, "cycle|child of two"), (shared, "child of two")):
        bvh = median_split_bvh(vertices, faces, 4)
        bvh.node_first = type(bvh.node_first)(broken)
        with pytest.raises(ValueError, match=pattern):
            trace(bvh, [[0.5, 0.5, -1.0]], [[0, 0, 1]])


def test16_out_of_range_children_and_leaves_raise():
    vertices, faces = random_soup(40, seed=18)
    for field, value in (("node_first", 10**6), ("node_count", 17)):
        bvh = median_split_bvh(vertices, faces, 4)
        arr = getattr(bvh, field).numpy()
        target = 0 if field == "node_first" else int(np.flatnonzero(arr)[0])
        arr[target] = value
        setattr(bvh, field, type(getattr(bvh, field))(arr))
        with pytest.raises(ValueError, match="corrupt BVH"):
            trace(bvh, [[0.5, 0.5, -1]], [[0, 0, 1]])
    # Two leaves over the same primitive slots (and none over another leaf's).
    bvh = median_split_bvh(vertices, faces, 4)
    first, count = bvh.node_first.numpy(), bvh.node_count.numpy()
    leaves = np.flatnonzero(count)
    first[leaves[1]] = first[leaves[0]]
    bvh.node_first = type(bvh.node_first)(first)
    with pytest.raises(ValueError, match="corrupt BVH"):
        trace(bvh, [[0.5, 0.5, -1]], [[0, 0, 1]])


def test17_refit_is_seen_by_the_next_trace():
    rng = np.random.default_rng(19)
    vertices, faces = random_soup(300, seed=20)
    bvh = build(vertices, faces, "hlbvh")
    o, d = random_rays(rng, 1000)
    assert_matches_reference(trace(bvh, o, d), brute_force(vertices, faces, o, d),
                             vertices, faces, o, d)
    moved = (vertices * [1.0, 0.5, 1.0] + [0.1, 0.3, 0.0]).astype(np.float32)
    bvh.refit(mi.Float(moved.ravel()))
    assert_matches_reference(trace(bvh, o, d), brute_force(moved, faces, o, d),
                             moved, faces, o, d)


# ---------------------------------------------------------------------------------------
# Against Mitsuba's native intersector (Embree) on ~100k triangles
# ---------------------------------------------------------------------------------------


def _on_edge(u, v, tol=1e-4):
    return np.minimum(np.minimum(u, v), 1 - u - v) < tol


def assert_matches_native(ours, pi, prim_key, n_prim_key):
    """Our closest hits against a native ``PreliminaryIntersection3f``: the primitive
    keys must agree except at ties, i.e. where a hit lies on a triangle edge (grazing a
    shared edge, or the seam between two meshes) and the distances agree (or one side
    found nothing there). Returns the fraction of rays that differ at all, and the mask
    of rays with a hit on an edge (ours or native)."""
    t, u, v, valid = ours["t"], ours["u"], ours["v"], ours["valid"]
    n_t = pi.t.numpy()
    n_u, n_v = pi.prim_uv.numpy()
    n_valid = np.isfinite(n_t)
    differ = (valid != n_valid) | (valid & n_valid & (prim_key != n_prim_key))
    edge = (valid & _on_edge(u, v)) | (n_valid & _on_edge(n_u, n_v))
    with np.errstate(invalid="ignore"):
        same_t = ~(valid & n_valid) | (np.abs(t - n_t) <= 1e-5 * n_t)
    unexplained = differ & ~(edge & same_t)
    assert unexplained.sum() == 0, f"{unexplained.sum()} rays disagree off edges"
    both = valid & n_valid
    # Hits a few ulps from the origin (a spawned ray grazing its own surface) agree in
    # absolute terms only, hence atol (the scenes here are of size ~1).
    np.testing.assert_allclose(t[both], n_t[both], rtol=1e-5, atol=1e-6)
    return differ.mean(), edge


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh", "sah"])
def test18_matches_mitsuba_native_on_100k_triangles(builder):
    from hlbvh.comparison.bench.trace import (displaced_grid, mesh_scene, primary_rays,
                                              secondary_rays, _grid_sensor)

    vertices, faces = displaced_grid(100_000)
    scene = mesh_scene(vertices, faces, _grid_sensor(320))
    bvh = hlbvh.build(vertices, faces, builder=builder)
    primary = primary_rays(scene)
    secondary = secondary_rays(scene, primary)
    total = 0
    for ray in (primary, secondary):
        t, u, v, prim, valid = [x.numpy() for x in closest_hit(bvh, ray.o, ray.d, ray.maxt)]
        occ = any_hit(bvh, ray.o, ray.d, ray.maxt).numpy()
        np.testing.assert_array_equal(occ, valid)
        for coherent in (True, False):
            pi = scene.ray_intersect_preliminary(ray, coherent=coherent)
            ours = {"t": t, "u": u, "v": v, "valid": valid}
            differ, edge = assert_matches_native(ours, pi, prim, pi.prim_index.numpy())
            assert differ <= 1e-4
            occ_differ = scene.ray_test(ray, coherent=coherent).numpy() != occ
            assert np.all(edge[occ_differ]) and occ_differ.mean() <= 1e-4
        total += len(t)
    assert total > 100_000


def test19_matches_mitsuba_native_on_cornell_box():
    from hlbvh.accel.scene_geometry import collect_geometry
    from hlbvh.comparison.bench.trace import primary_rays, secondary_rays

    box = mi.cornell_box()
    box["sensor"]["film"]["width"] = box["sensor"]["film"]["height"] = 128
    scene = mi.load_dict(box)
    g = collect_geometry(scene.shapes())
    bvh = hlbvh.build(g.vertices, g.faces)
    primary = primary_rays(scene)
    for ray in (primary, secondary_rays(scene, primary)):
        t, u, v, prim, valid = [x.numpy() for x in closest_hit(bvh, ray.o, ray.d, ray.maxt)]
        pi = scene.ray_intersect_preliminary(ray, coherent=False)
        key = g.prim_shape.numpy()[prim].astype(np.int64) << 32 | g.prim_local.numpy()[prim]
        n_key = pi.shape_index.numpy().astype(np.int64) << 32 | pi.prim_index.numpy()
        ours = {"t": t, "u": u, "v": v, "valid": valid}
        # Camera rays along the image diagonals run exactly into the box's corners.
        assert assert_matches_native(ours, pi, key, n_key)[0] < 1e-2


# ---------------------------------------------------------------------------------------
# Record layout
# ---------------------------------------------------------------------------------------


def _walk_wide_tree(records, root):
    """Decode the packed slots the obvious way (numpy, one node at a time), from the
    layout's documented fields: returns ``(children, reached)``, for every child of
    every wide node its box and the triangle slots of its subtree, and the triangle
    slots reached from the root in the order reached."""
    rec = records.numpy().reshape(-1, slot_format.SLOT)
    children, reached = [], []

    def subtree(ref):
        if ref & slot_format.LEAF_BIT:
            first = (ref & 0x7FFFFFFF) >> 4
            slots = list(range(first, first + (ref & 15) + 1))
            reached.extend(slots)
            return slots
        node = rec[ref:ref + slot_format.NODE_SLOTS].ravel()
        refs = node[slot_format.NODE_REF:slot_format.NODE_REF + slot_format.WIDTH].view(np.uint32)
        assert 2 <= np.sum(refs != slot_format.EMPTY), "a wide node has 2-4 children"
        slots = []
        for k, child in enumerate(refs):
            if child == slot_format.EMPTY:
                continue
            lo = np.array([node[slot_format.NODE_LO[a] + k] for a in range(3)])
            hi = np.array([node[slot_format.NODE_HI[a] + k] for a in range(3)])
            below = subtree(int(child))
            children.append((lo, hi, below))
            slots += below
        return slots

    subtree(int(root))
    return children, reached


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh", "sah", "median"])
@pytest.mark.parametrize("mesh", ["soup", "grid"])
def test20_wide_tree_invariants(builder, mesh):
    """The packed 4-wide tree of every builder: every triangle in exactly one leaf,
    with its own vertices and face index; every wide node with 2-4 children; every
    child box containing all the triangles below it; the root's first child right after
    the root's two slots (depth first); and hits equal to the brute force."""
    rng = np.random.default_rng(25)
    if mesh == "soup":
        vertices, faces = random_soup(400, seed=26)
    else:
        vertices, faces = triangle_grid(12, 12)
        vertices = (vertices / 12).astype(np.float32)
        vertices[:, 2] = 0.3 * vertices[:, 0] + 0.2
    bvh = build(vertices, faces, builder, leaf_size=3)
    records, root = packing.packed_records(bvh)
    children, reached = _walk_wide_tree(records, root)
    assert len(set(reached)) == len(reached) == len(faces), "each slot in exactly one leaf"
    rec = records.numpy().reshape(-1, slot_format.SLOT)
    face = rec[reached, slot_format.TRI_FACE].view(np.uint32)
    np.testing.assert_array_equal(np.sort(face), np.arange(len(faces)))
    for k, p in enumerate(slot_format.TRI_P):
        np.testing.assert_array_equal(rec[reached, p:p + 3], vertices[faces[face, k]])
    for lo, hi, slots in children:
        tri = rec[slots][:, :9].reshape(-1, 3)
        assert np.all(lo <= tri.min(axis=0)) and np.all(hi >= tri.max(axis=0)), (lo, hi)
    if not root & slot_format.LEAF_BIT:
        node = rec[root:root + slot_format.NODE_SLOTS].ravel()
        first = int(node[slot_format.NODE_REF:slot_format.NODE_REF + 1].view(np.uint32)[0])
        assert (first & 0x7FFFFFFF) >> (4 if first & slot_format.LEAF_BIT else 0) == \
            root + slot_format.NODE_SLOTS
    o, d = random_rays(rng, 2000)
    assert_matches_reference(trace(bvh, o, d), brute_force(vertices, faces, o, d),
                             vertices, faces, o, d)


def test20b_zero_area_triangles_pack_as_nan():
    """A zero-area triangle's record holds NaN vertices (it is never hit); the others
    keep their own."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], np.float32)
    faces = np.array([[0, 1, 2], [0, 1, 3]], np.uint32)
    bvh = build(vertices, faces, "lbvh")
    records, root = packing.packed_records(bvh)
    _, reached = _walk_wide_tree(records, root)
    rec = records.numpy().reshape(-1, slot_format.SLOT)[reached]
    flat = rec[:, slot_format.TRI_FACE].view(np.uint32) == 0
    assert np.all(np.isnan(rec[flat, :9])) and np.all(np.isfinite(rec[~flat, :9]))


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh", "sah", "median"])
def test20c_refit_repacks_as_a_fresh_pack(builder):
    """A refit tree is packed again from the placement kept with the tree (no per-level
    passes): its slots equal, bit for bit, those of packing the refit tree from scratch,
    alone and joined behind another tree, and trace as the brute force does; and
    check_tree still refuses the tree once its shape is made corrupt."""
    vertices, faces = random_soup(300, seed=40)
    moved = (vertices * 1.07 + 0.01).astype(np.float32)
    other = build(*random_soup(50, seed=41), "lbvh")
    bvh = build(vertices, faces, builder)
    packing.packed_records(bvh)
    layout.joined([other, bvh])
    bvh.refit(mi.Float(np.ravel(moved)))
    kept, kept_root = packing.packed_records(bvh)
    kept_joined = layout.joined([other, bvh])
    packing.pack_state(bvh).plan = None  # place anew
    fresh, fresh_root = packing.pack(bvh, 0, 0, check=True)
    assert kept_root == fresh_root
    np.testing.assert_array_equal(kept.numpy().view(np.uint32), fresh.numpy().view(np.uint32))
    packing.pack_state(bvh).plan = None
    packing.pack_state(bvh).records = None
    fresh_joined = layout.joined([other, bvh])
    np.testing.assert_array_equal(kept_joined.records.numpy().view(np.uint32),
                                  fresh_joined.records.numpy().view(np.uint32))
    o, d = random_rays(np.random.default_rng(42), 500)
    assert_matches_reference(trace(bvh, o, d), brute_force(moved, faces, o, d), moved, faces,
                             o, d)
    if builder != "median":
        count = bvh.node_count.numpy()
        count[0] = 1  # the root made a leaf: the other nodes are reached from nowhere
        bvh.node_count = type(bvh.node_count)(count)
        with pytest.raises(ValueError, match="corrupt|never|reached"):
            packing.check_tree(bvh)


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh", "sah"])
@pytest.mark.parametrize("leaf_size", [1, 4, 7])
@pytest.mark.parametrize("triangles", [3, 400])
def test20d_fused_refit_equals_the_refit_of_the_binary_tree(builder, leaf_size, triangles):
    """A packed tree is refit and repacked in one go (``refit.refit_packed``: triangle
    records, leaves, one pass per wide level); an unpacked twin is refit through the
    binary tree and packed after. Node boxes, triangles, SAH cost and slots are the same
    bit for bit, alone and joined behind another tree, over two refits; also for a tree
    that is one leaf, and with a zero-area triangle."""
    vertices, faces = random_soup(triangles, seed=44)
    vertices[faces[1][2]] = vertices[faces[1][0]]  # a zero-area triangle (NaN record)
    other = build(*random_soup(60, seed=45), "lbvh")
    for joined in (False, True):
        fused = build(vertices, faces, builder, leaf_size)
        layout.joined([other, fused]) if joined else packing.packed_records(fused)
        for step in (1, 2):
            moved = mi.Float(np.ravel(vertices * (1 + 0.05 * step) + 0.02 * step).astype(np.float32))
            fused.refit(moved)
            assert packing.pack_state(fused).ready is not None  # the fused path ran
            twin = build(vertices, faces, builder, leaf_size)
            assert packing.pack_state(twin).last is None  # never packed: the binary path
            twin.refit(moved)
            for name in ("node_min", "node_max", "tri_p0", "tri_p1", "tri_p2"):
                np.testing.assert_array_equal(np.array(getattr(fused, name)),
                                              np.array(getattr(twin, name)), err_msg=name)
            assert fused.stats.sah_cost == twin.stats.sah_cost
            if joined:
                ours, theirs = layout.joined([other, fused]).records, layout.joined([other, twin]).records
            else:
                ours, theirs = packing.packed_records(fused)[0], packing.packed_records(twin)[0]
            np.testing.assert_array_equal(ours.numpy().view(np.uint32), theirs.numpy().view(np.uint32))


def test21_symbolic_even_when_loops_are_evaluated():
    """With Dr.Jit's loops switched to evaluated mode (``JitFlag.SymbolicLoops`` off,
    e.g. for an integrator that wants wavefront kernels), the traversal's own loop and
    ifs stay symbolic: a handful of kernel launches (an evaluated traversal launches
    kernels on every step, and took minutes for 1000 rays), and the same hits."""
    rng = np.random.default_rng(27)
    vertices, faces = random_soup(300, seed=28)
    bvh = build(vertices, faces, "hlbvh")
    packing.packed_records(bvh)
    o, d = random_rays(rng, 1000)
    with dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, False), \
            dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        ours = trace(bvh, o, d)
        launches = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    # closest and any hit, one kernel each, and a few conversions of the rays
    assert len(launches) < 10, len(launches)
    assert_matches_reference(ours, brute_force(vertices, faces, o, d), vertices, faces, o, d)


# ---------------------------------------------------------------------------------------
# The trace benchmark's own bookkeeping
# ---------------------------------------------------------------------------------------


def test22_bench_trace_rows_threads_and_agreement():
    """``bench_trace.run`` on a small grid: one row per ray kind and query with wall
    and CPU times, our hits agreeing with the native ones, the thread count restored
    afterwards, and a bad thread count refused."""
    from hlbvh.comparison.bench import trace as bench_trace

    threads = dr.thread_count()
    rows = bench_trace.run(sizes=(2000,), repeats=1, resolution=24, cornell=False, cloth=False,
                           threads=1)
    assert dr.thread_count() == threads
    assert [(r["kind"], r["query"]) for r in rows] == [
        ("coherent", "closest"), ("coherent", "any"),
        ("incoherent", "closest"), ("incoherent", "any"),
        ("shadow", "closest"), ("shadow", "any")]
    for r in rows:
        assert r["ours_cpu_ms"] > 0 and r["native_cpu_ms"] > 0
        assert r["ratio_cpu"] == pytest.approx(r["native_cpu_ms"] / r["ours_cpu_ms"])
        assert 0.99 <= r["agree"] <= 1
        assert r["steps"] >= 1 and 0 < r["lanes"] <= 1
    # The step profile is that of the rows' own rays and query: the camera rays of the
    # same grid, counted here with traversal.steps on the same (deterministic) build.
    vertices, faces = bench_trace.displaced_grid(2000)
    scene = bench_trace.mesh_scene(vertices, faces, bench_trace._grid_sensor(24))
    bvh = hlbvh.build(*bench_trace._scene_triangles(scene)[:2])
    primary = bench_trace.primary_rays(scene)
    for r in rows[:2]:
        count = traversal.steps(bvh, primary.o, primary.d, primary.maxt,
                                any_hit=r["query"] == "any").numpy()
        assert r["rays"] == len(count) == 24 * 24
        assert r["steps"] == pytest.approx(count.mean())
        assert r["steps_p90"] == pytest.approx(np.percentile(count, 90))
        assert r["steps_max"] == count.max()
    assert "(cpu)" in bench_trace.format_table(rows)
    with pytest.raises(ValueError, match="threads"):
        bench_trace.run(sizes=(2000,), repeats=1, resolution=8, cornell=False, cloth=False,
                        threads=0)


def test23_steps_count_the_nodes_and_triangles_visited():
    """``traversal.steps``: a ray into a one-triangle tree (a root leaf) takes one
    step, a ray that misses everything (or is invalid) none beyond the root's test, and
    a ray through a larger tree at least a node and a triangle."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    faces = np.array([[0, 1, 2]], np.uint32)
    bvh = build(vertices, faces, "lbvh")
    o = mi.Point3f([0.2, 0.2, np.nan], [0.2, 0.2, 0.0], [1, 1, 1])
    d = mi.Vector3f([0, 0, 0], [0, 0, 0], [-1, 1, -1])
    np.testing.assert_array_equal(traversal.steps(bvh, o, d, np.inf).numpy(), [1, 1, 0])
    vertices, faces = random_soup(200, seed=30)
    bvh = build(vertices, faces, "hlbvh")
    o, d = random_rays(np.random.default_rng(31), 500)
    hit = trace(bvh, o, d)["valid"]
    count = traversal.steps(bvh, mi.Point3f(o.T), mi.Vector3f(d.T), np.inf).numpy()
    assert np.all(count[hit] >= 2) and np.all(count >= 1)
