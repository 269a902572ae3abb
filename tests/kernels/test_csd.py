"""The CSD sort (hlbvh.kernels.csd) against numpy's stable sort, on coherent keys (Morton
codes of a grid mesh, sorted and nearly sorted), random keys and many duplicates, from
the identity, a random permutation and a previous frame's order."""

from __future__ import annotations

import hlbvh  # noqa: F401  (sets up libLLVM and the variant before drjit is imported)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from hlbvh.kernels.csd import CsdResult, csd_sort, seed_pays
from hlbvh.kernels.morton import morton_codes, point_bounds

from hlbvh.kernels.arrays import namespace_of

# The plain (non-AD) types of the variant's backend: LLVM here, CUDA where a GPU is.
jit = namespace_of(mi.Float)
Array3f, UInt32, UInt64 = jit.Array3f, jit.UInt32, jit.UInt64


def reference(keys, start):
    """What CSD must return: the start order, stably sorted by key (numpy)."""
    return start[np.argsort(keys[start], kind="stable")]


def reference_runs(keys, start, key_bits, coarse_bits):
    """Runs of equal coarse keys in start order, and distinct coarse keys (numpy)."""
    coarse = keys[start] >> np.uint64(key_bits - coarse_bits)
    return 1 + np.count_nonzero(coarse[1:] != coarse[:-1]), len(np.unique(coarse))


def check(keys, key_bits, coarse_bits, start=None):
    """Run csd_sort and compare everything it returns with the numpy references."""
    keys = np.asarray(keys)
    Key = UInt32 if keys.dtype == np.uint32 else UInt64
    start_np = np.arange(len(keys)) if start is None else np.asarray(start)
    result = csd_sort(Key(keys), key_bits, coarse_bits, None if start is None else UInt32(start_np))
    assert isinstance(result, CsdResult)
    assert type(result.order) is UInt32 and type(result.sorted_keys) is Key
    expected = reference(keys, start_np)
    assert np.array_equal(result.order.numpy(), expected)
    assert np.array_equal(result.sorted_keys.numpy(), keys[expected])
    runs, clusters = reference_runs(keys.astype(np.uint64), start_np, key_bits, coarse_bits)
    assert (result.runs, result.coarse_clusters) == (runs, clusters)
    assert 0 <= result.resorted <= len(keys)
    return result


def grid_centroids(q, t=0.0):
    """Triangle centroids of a displaced q×q grid mesh (2·q² triangles, the two of a quad
    adjacent, rows in order): coherent but not Morton-ordered."""
    u = np.linspace(0, 1, q + 1)
    x, y = np.meshgrid(u, u, indexing="ij")
    z = 0.05 * np.sin(12 * x + t) * np.cos(9 * y - 0.5 * t)
    v = np.stack([x, y, z], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(q), np.arange(q), indexing="ij")
    a = (i * (q + 1) + j).ravel()
    b, c, d = a + 1, a + q + 1, a + q + 2
    tris = np.stack([np.stack([a, b, d], 1), np.stack([a, d, c], 1)], 1).reshape(-1, 3)
    return v[tris].mean(axis=1).astype(np.float32)


def morton(centroids, bits=30):
    c = Array3f(np.ascontiguousarray(centroids.T))
    lo, hi = point_bounds(c)
    return morton_codes(c, lo, hi, bits).numpy()


def test01_paper_example_compresses_to_five_runs():
    # The slides' example: {7,7,1,1,1,3,3,4,5,5} -> runs {7,1,3,4,5} of lengths
    # {2,3,2,1,2}, decompressed to {1,1,1,3,3,4,5,5,7,7}; keys are 3 bits, all coarse.
    keys = np.array([7, 7, 1, 1, 1, 3, 3, 4, 5, 5], dtype=np.uint32)
    result = check(keys, 3, 3)
    assert result.runs == 5 and result.coarse_clusters == 5 and result.resorted == 0
    assert result.order.numpy().tolist() == [2, 3, 4, 5, 6, 7, 8, 9, 0, 1]


@pytest.mark.parametrize("n", [1, 2, 1000, 100_000])
def test02_coherent_keys_equal_numpy_stable_sort_from_identity_random_and_previous_orders(n):
    rng = np.random.default_rng(n)
    q = int(np.ceil(np.sqrt(n / 2)))
    keys = morton(grid_centroids(q))[:n] if n > 2 else np.array([5, 3][:n], dtype=np.uint32)
    moved = morton(grid_centroids(q, 0.05))[:n] if n > 2 else keys[::-1].copy()
    n = len(keys)
    previous = reference(keys, np.arange(n)).astype(np.uint32)
    for coarse_bits in (0, 12, 30):
        check(keys, 30, coarse_bits)
        check(keys, 30, coarse_bits, rng.permutation(n).astype(np.uint32))
        same = check(keys, 30, coarse_bits, previous)
        assert same.resorted == 0  # the previous order already sorts these keys
        check(moved, 30, coarse_bits, previous)
        check(np.sort(keys), 30, coarse_bits)


@pytest.mark.parametrize("n", [1000, 100_000])
@pytest.mark.parametrize("coarse_bits", [0, 3, 12, 30])
def test03_random_keys_and_many_duplicates_equal_numpy_stable_sort(n, coarse_bits):
    rng = np.random.default_rng(coarse_bits)
    perm = rng.permutation(n).astype(np.uint32)
    for keys in (
        rng.integers(0, 2**30, n, dtype=np.uint32),  # random
        rng.integers(0, 8, n, dtype=np.uint32),  # few distinct keys
        rng.integers(0, 4, n, dtype=np.uint32) << 27 | rng.integers(0, 3, n, dtype=np.uint32),
        np.full(n, 12345, dtype=np.uint32),  # all equal
    ):
        check(keys, 30, coarse_bits)
        check(keys, 30, coarse_bits, perm)


def test04_only_unsorted_voxels_are_resorted():
    # Two runs: voxel 1 (out of key order), then voxel 0 (in order). After the runs
    # are sorted only voxel 1's keys are sorted again.
    keys = np.array([1 << 27 | 5, 1 << 27 | 4, 1 << 27 | 6, 1, 2, 3], dtype=np.uint32)
    result = check(keys, 30, 3)
    assert result.runs == 2 and result.coarse_clusters == 2 and result.resorted == 3
    assert result.order.numpy().tolist() == [3, 4, 5, 1, 0, 2]

    # Voxel 0 in two runs, each in order, but the second starts below where the first
    # ended (5 > 3): only voxel 0 is resorted; voxels 1 and 2 are in order.
    v1, v2 = 1 << 27, 2 << 27
    keys = np.array([1, 5, v1 | 1, v1 | 2, 3, 6, v1 | 3, v1 | 4, v2, v2, v2 | 1, v2 | 9])
    result = check(keys.astype(np.uint32), 30, 3)
    assert result.runs == 5 and result.coarse_clusters == 3 and result.resorted == 4


def test05_incoherent_keys_are_sorted_whole():
    # More runs than half the keys: no compression, the keys are sorted directly.
    keys = np.array([1 << 27 | 5, 1, 1 << 27 | 4, 2, 1 << 27 | 6, 3], dtype=np.uint32)
    result = check(keys, 30, 3)
    assert result.runs == 6 and result.coarse_clusters == 2 and result.resorted == 6


@pytest.mark.parametrize("coarse_bits", [0, 12, 45, 60])
def test06_sixty_bit_keys_sort_as_uint64(coarse_bits):
    rng = np.random.default_rng(60)
    keys = morton(grid_centroids(40), bits=60)
    assert keys.dtype == np.uint64 and keys.max() >> 60 == 0
    check(keys, 60, coarse_bits)
    check(keys, 60, coarse_bits, rng.permutation(len(keys)).astype(np.uint32))
    random = rng.integers(0, 2**60, 5000, dtype=np.uint64)
    check(random, 60, coarse_bits)
    check(random & np.uint64(0xF000_0000_0000_00FF), 60, coarse_bits)  # duplicates


def test07_start_order_accepts_lists_numpy_and_ad_arrays():
    keys = UInt32([5, 3, 3, 1])
    expected = [3, 1, 2, 0]
    for start in ([3, 2, 1, 0], np.array([3, 2, 1, 0], dtype=np.uint32), mi.UInt32([3, 2, 1, 0])):
        assert csd_sort(keys, 30, 3, start).order.numpy().tolist() == [3, 2, 1, 0]
    assert csd_sort(mi.UInt32([5, 3, 3, 1]), 30, 3).order.numpy().tolist() == expected


def test08_empty_keys_give_an_empty_result():
    result = csd_sort(UInt32(), 30, 12)
    assert dr.width(result.order) == 0 and dr.width(result.sorted_keys) == 0
    assert (result.runs, result.coarse_clusters, result.resorted) == (0, 0, 0)


def test09_bad_arguments_raise_errors_naming_them():
    keys = UInt32([5, 3, 3, 1])
    with pytest.raises(ValueError, match="4 keys"):
        csd_sort(keys, 30, 3, [0, 1, 2])
    for not_a_permutation in ([0, 0, 1, 2], [0, 1, 2, 4], [3, 3, 0, 0]):
        with pytest.raises(ValueError, match="not a permutation"):
            csd_sort(keys, 30, 3, not_a_permutation)
    with pytest.raises(ValueError, match="wider than key_bits=3"):
        csd_sort(UInt32([1, 8]), 3, 3)
    with pytest.raises(ValueError, match="coarse_bits=33"):
        csd_sort(keys, 30, 33)
    with pytest.raises(ValueError, match="key_bits=40"):
        csd_sort(keys, 40, 3)
    with pytest.raises(TypeError, match="UInt32 or UInt64"):
        csd_sort(jit.Float([1.0, 2.0]), 30, 3)
    with pytest.raises(TypeError, match="UInt32 or UInt64"):
        csd_sort(np.array([1, 2], dtype=np.uint32), 30, 3)


def test10_a_new_size_or_run_count_compiles_no_new_kernel():
    # Sizes must enter kernels as opaque values (a Python int is baked in as a literal):
    # every frame of an animation has a new run count, and a recompile costs more than
    # the sort.
    rng = np.random.default_rng(9)

    def sort_some(n):
        # One call down each path: runs with some voxels resorted, already sorted,
        # incoherent, and 64-bit keys.
        keys = np.sort(rng.integers(0, 2**30, n, dtype=np.uint32))
        start = np.concatenate([np.arange(3 * n // 4), 3 * n // 4 + rng.permutation(n - 3 * n // 4)])
        start = start.astype(np.uint32)
        partly = csd_sort(UInt32(keys), 30, 3, start)
        assert 0 < partly.resorted < n and partly.runs <= n // 2
        assert csd_sort(UInt32(keys), 30, 12).resorted == 0
        assert csd_sort(UInt32(rng.permutation(keys)), 30, 12).runs > n // 2
        assert 0 < csd_sort(UInt64(keys.astype(np.uint64) << 30), 60, 6, start).resorted < n
    sort_some(3000)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        sort_some(2000)
        sort_some(2500)
        compiled = [e for e in dr.kernel_history() if e.get("cache_hit") == 0]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert compiled == []


@pytest.mark.parametrize("coarse_bits", [6, 12])
def test11_a_start_order_is_dropped_only_where_the_sort_would_sort_every_key(coarse_bits):
    """seed_pays keeps last frame's order when the keys did not change or changed in one
    corner of the mesh, and drops it (a random order, a mesh that moved everywhere)
    only where csd_sort, started from it, sorts every key anyway."""
    rng = np.random.default_rng(coarse_bits)
    q = 224  # 100,352 triangles
    keys = morton(grid_centroids(q))
    previous = reference(keys, np.arange(len(keys))).astype(np.uint32)
    corner = grid_centroids(q)
    corner[:200] += np.float32(0.002)  # a few triangles of the first row moved
    cases = {
        "unchanged": (keys, True),
        "a corner moved": (morton(corner), True),
        "moved everywhere": (morton(grid_centroids(q, 0.5)), None),
        "random order": (rng.permutation(keys), False),
    }
    for name, (new_keys, expected) in cases.items():
        pays = seed_pays(UInt32(new_keys), 30, coarse_bits, UInt32(previous))
        if expected is not None:
            assert pays == expected, name
        if not pays:
            assert check(new_keys, 30, coarse_bits, previous).resorted == len(keys), name
