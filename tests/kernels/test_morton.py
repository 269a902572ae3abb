"""Morton codes (hlbvh.kernels.morton) against a bit-by-bit numpy/Python reference, at
the numerical extremes, and the morton_bits="auto" policy on scenes where the answer
is known."""

from __future__ import annotations

import hlbvh  # noqa: F401  (sets up libLLVM and the variant before drjit is imported)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from hlbvh.kernels.morton import choose_morton_bits, morton_codes, point_bounds

from hlbvh.kernels.arrays import namespace_of

# The plain (non-AD) types of the variant's backend: LLVM here, CUDA where a GPU is.
jit = namespace_of(mi.Float)
Array3f, UInt32, UInt64 = jit.Array3f, jit.UInt32, jit.UInt64


def reference_keys(points, bits, quantization):
    """Keys the obvious way: float32 quantisation as the docstring defines it (numpy
    float32 arithmetic, IEEE like the kernel's), then one key bit at a time in Python
    integers: bit ``3i + 2`` from x, ``3i + 1`` from y, ``3i`` from z."""
    points = np.asarray(points, dtype=np.float32)
    b = bits // 3
    lo, hi = points.min(axis=0), points.max(axis=0)
    extent = hi - lo
    if quantization == "cube":
        extent = np.full(3, extent.max(), dtype=np.float32)
    keys = []
    for p in points:
        cells = []
        for axis in range(3):
            t = (p[axis] - lo[axis]) / extent[axis] if extent[axis] > 0 else np.float32(0)
            cells.append(min(int(np.floor(t * np.float32(2**b))), 2**b - 1))
        key = 0
        for i in range(b):
            for axis in range(3):
                key |= ((cells[axis] >> i) & 1) << (3 * i + 2 - axis)
        keys.append(key)
    return np.array(keys, dtype=np.uint64)


def keys_of(points, bits=30, quantization="cube"):
    c = Array3f(np.ascontiguousarray(np.asarray(points, dtype=np.float32).T))
    lo, hi = point_bounds(c)
    return morton_codes(c, lo, hi, bits, quantization)


def grid_triangles(q, size=1.0, amplitude=0.05):
    """(2·q², 3, 3) float32 triangles of a displaced q×q grid of side ``size``, centred
    on the origin."""
    u = np.linspace(-size / 2, size / 2, q + 1)
    x, y = np.meshgrid(u, u, indexing="ij")
    z = amplitude * size * np.sin(12 * x / size) * np.cos(9 * y / size)
    v = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(q), np.arange(q), indexing="ij")
    a = (i * (q + 1) + j).ravel()
    b, c, d = a + 1, a + q + 1, a + q + 2
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return v[faces].astype(np.float32)


def sphere_triangles(n_lat, radius, center):
    """(4·n_lat², 3, 3) float32 triangles of a UV sphere."""
    theta, phi = np.linspace(0, np.pi, n_lat + 1), np.linspace(0, 2 * np.pi, 2 * n_lat + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)
    v = v.reshape(-1, 3) * radius + np.asarray(center)
    i, j = np.meshgrid(np.arange(n_lat), np.arange(2 * n_lat), indexing="ij")
    a = (i * (2 * n_lat + 1) + j).ravel()
    b, c, d = a + 1, a + 2 * n_lat + 1, a + 2 * n_lat + 2
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return v[faces].astype(np.float32)


def auto_bits(triangles):
    lo_p, hi_p = triangles.min(axis=1), triangles.max(axis=1)
    prim_lo, prim_hi = (Array3f(np.ascontiguousarray(a.T)) for a in (lo_p, hi_p))
    lo, hi = point_bounds((prim_lo + prim_hi) * 0.5)
    return choose_morton_bits(prim_lo, prim_hi, lo, hi)


def test01_point_bounds_are_size_one_device_arrays_equal_to_numpy():
    # Reduced as order-preserving integer bit patterns: check signs, zeros, extremes.
    rng = np.random.default_rng(0)
    extremes = [-3.4e38, 3.4e38, -1e-30, 1e-30, -0.0, 0.0, -1e-45, 1e-45]
    for p in (
        rng.normal(size=(1000, 3)),
        -rng.random((500, 3)) - 1,  # all negative
        rng.choice(extremes, size=(400, 3)),
        rng.choice(extremes[2:6], size=(400, 3)) * np.array([1.0, 1e8, 1e-8]),
    ):
        p = p.astype(np.float32)
        lo, hi = point_bounds(Array3f(np.ascontiguousarray(p.T)))
        assert type(lo) is Array3f and type(hi) is Array3f
        assert dr.width(lo) == 1 and dr.width(hi) == 1
        assert np.array_equal(lo.numpy().ravel(), p.min(axis=0))
        assert np.array_equal(hi.numpy().ravel(), p.max(axis=0))


@pytest.mark.parametrize("quantization", ["cube", "axis"])
@pytest.mark.parametrize("bits", [30, 60])
def test02_keys_equal_the_bit_by_bit_reference(bits, quantization):
    rng = np.random.default_rng(bits)
    p = rng.random((500, 3)) * np.array([3.0, 1.0, 0.25]) - np.array([1.0, 7.0, -2.0])
    keys = keys_of(p, bits, quantization)
    assert type(keys) is (UInt32 if bits == 30 else UInt64)
    assert np.array_equal(keys.numpy().astype(np.uint64), reference_keys(p, bits, quantization))


def test03_bit_layout_x_is_the_most_significant_of_each_triplet():
    # Corners of the unit cube: lo gives 0, hi gives all ones, one axis at hi gives
    # every third bit.
    p = [[0, 0, 0], [1, 1, 1], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    every_third = sum(1 << (3 * i) for i in range(10))
    assert keys_of(p).numpy().tolist() == [
        0,
        2**30 - 1,
        every_third << 2,
        every_third << 1,
        every_third,
    ]
    every_third_60 = sum(1 << (3 * i) for i in range(20))
    assert keys_of(p, 60).numpy().tolist()[1:3] == [2**60 - 1, every_third_60 << 2]


def test04_cube_quantisation_uses_the_largest_extent_on_every_axis():
    # Box [0, 4] x [0, 1] x [0, 0]; the point (1, 1, 0): in the cube of side 4 both x
    # and y are a quarter of the way (cell 256); per axis, y is at the top (cell 1023).
    p = np.array([[0, 0, 0], [4, 1, 0], [1, 1, 0]], dtype=np.float32)

    def cells(key):
        return [sum(((int(key) >> (3 * i + 2 - axis)) & 1) << i for i in range(10)) for axis in range(3)]

    assert cells(keys_of(p, 30, "cube").numpy()[2]) == [256, 256, 0]
    assert cells(keys_of(p, 30, "axis").numpy()[2]) == [256, 1023, 0]


@pytest.mark.parametrize("bits", [30, 60])
@pytest.mark.parametrize("quantization", ["cube", "axis"])
def test05_extreme_inputs_give_finite_in_range_keys(bits, quantization):
    rng = np.random.default_rng(5)
    p = ((rng.random((300, 3)) * 2 - 1) * 1.5).astype(np.float32)
    base = keys_of(p, bits, quantization).numpy()
    limit = 2**bits

    # Power-of-two scaling is exact in float, so keys must not change: 2^-100 ~ 1e-30,
    # 2^100 ~ 1e30, and 2^127 where hi - lo overflows to inf (computed at half scale).
    for scale in (2.0**-100, 2.0**100, 2.0**127):
        scaled = (p.astype(np.float64) * scale).astype(np.float32)
        assert np.isfinite(scaled).all()
        assert np.array_equal(keys_of(scaled, bits, quantization).numpy(), base), scale
    with np.errstate(over="ignore"):
        assert np.isinf(scaled.max(axis=0) - scaled.min(axis=0)).all()  # the last did overflow

    # Flat on one and on two axes: the flat axes contribute 0 bits.
    for flat_axes in ([2], [1, 2]):
        q = p.copy()
        q[:, flat_axes] = 0.5
        keys = keys_of(q, bits, quantization).numpy().astype(np.uint64)
        assert (keys < limit).all()
        assert np.array_equal(keys, reference_keys(q, bits, quantization))
        for axis in flat_axes:
            mask = sum(1 << (3 * i + 2 - axis) for i in range(bits // 3))
            assert not (keys & np.uint64(mask)).any()

    # All centroids equal: every key 0. Near 1e-30 with a tiny extent too.
    assert not keys_of(np.full((50, 3), 3.25), bits, quantization).numpy().any()
    tiny = np.float32(1e-30) + p * np.float32(1e-33)
    keys = keys_of(tiny, bits, quantization).numpy().astype(np.uint64)
    assert (keys < limit).all() and len(np.unique(keys)) > 200

    # Points exactly on hi land in the last cell, not one past it.
    c = Array3f(p.T)
    lo, hi = point_bounds(c)
    on_hi = morton_codes(hi, lo, hi, bits, "axis").numpy()
    assert on_hi.tolist() == [limit - 1]


def test06_centroids_outside_the_box_or_nan_are_clamped_into_the_grid():
    lo, hi = Array3f(0, 0, 0), Array3f(1, 1, 1)
    c = Array3f([-5, 7, float("nan"), float("inf")], [0.5, 0.5, 0.5, 0.5], [0, 0, 0, 0])
    keys = morton_codes(c, lo, hi, 30, "axis").numpy()
    x_bits = [sum(((int(k) >> (3 * i + 2)) & 1) << i for i in range(10)) for k in keys]
    assert x_bits == [0, 1023, 0, 1023]


def test07_ad_inputs_give_plain_keys_of_the_same_backend():
    p = mi.Point3f([0.0, 1.0, 0.25], [0.0, 2.0, 0.5], [0.0, 3.0, 0.75])
    lo, hi = point_bounds(p)
    keys = morton_codes(p, lo, hi)
    assert type(lo) is Array3f and type(keys) is UInt32
    assert np.array_equal(keys.numpy().astype(np.uint64), reference_keys(p.numpy().T, 30, "cube"))


def test08_bad_arguments_raise_value_errors_naming_them():
    c = Array3f([0, 1], [0, 1], [0, 1])
    lo, hi = point_bounds(c)
    with pytest.raises(ValueError, match="bits=32"):
        morton_codes(c, lo, hi, 32)
    with pytest.raises(ValueError, match="quantization='sphere'"):
        morton_codes(c, lo, hi, 30, "sphere")
    with pytest.raises(ValueError, match="empty"):
        point_bounds(Array3f())
    with pytest.raises(TypeError):
        point_bounds(np.zeros((3, 2), dtype=np.float32))


def test09_auto_bits_keeps_30_for_a_regular_grid_and_picks_60_for_a_small_object_on_a_huge_ground():
    ground = grid_triangles(224, size=1000.0, amplitude=0.0)  # 100k triangles
    assert auto_bits(grid_triangles(224)) == 30
    assert auto_bits(ground) == 30
    # A 4k-triangle sphere 1/500 of the ground's size: 4% of the triangles, ~100 times
    # smaller than a 30-bit cell, all in a few cells.
    scene = np.concatenate([ground, sphere_triangles(32, 1.0, [0.0, 0.0, 1.0])])
    assert auto_bits(scene) == 60
    keys = keys_of((scene.min(axis=1) + scene.max(axis=1)) / 2)  # the harm avoided
    _, counts = np.unique(keys.numpy(), return_counts=True)
    assert counts.max() > 100
    # All centroids equal: finer keys would not help.
    assert auto_bits(np.zeros((10, 3, 3), dtype=np.float32)) == 30
