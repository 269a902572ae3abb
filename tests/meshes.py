"""Small test meshes made with numpy (tests only)."""

from __future__ import annotations

import numpy as np


def grid(n: int, amplitude: float = 0.05):
    """A displaced n x n grid of 2 n^2 triangles over [0, 1]^2: (V (float32), F (uint32))."""
    xs = np.linspace(0.0, 1.0, n + 1)
    x, y = np.meshgrid(xs, xs, indexing="ij")
    z = amplitude * np.sin(x * 20) * np.cos(y * 17)
    V = np.stack([x, y, z], -1).reshape(-1, 3).astype(np.float32)
    a = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    b, c = a + 1, a + n + 1
    F = np.concatenate([np.stack([a, b, c + 1], 1), np.stack([a, c + 1, c], 1)])
    return V, F.astype(np.uint32)


def soup(count: int, seed: int = 0, size: float = 0.05):
    """``count`` random triangles of about ``size`` in the unit cube."""
    rng = np.random.default_rng(seed)
    centre = rng.random((count, 1, 3))
    V = (centre + size * (rng.random((count, 3, 3)) - 0.5)).reshape(-1, 3).astype(np.float32)
    return V, np.arange(3 * count, dtype=np.uint32).reshape(-1, 3)


KEY_KINDS = ("random", "few_values", "sparse_bits")


def random_sorted_keys(key_bits: int, kind: str, arrays: int = 6):
    """``arrays`` sorted arrays of 2..399 Morton-like keys of ``key_bits`` bits
    (``uint64`` above 32 bits, else ``uint32``): uniformly ``"random"``, ``"few_values"``
    (six distinct top-bit patterns) or ``"sparse_bits"`` (half the bits always zero).

    Seeded by the arguments' values (not ``hash()``, which differs per process for
    strings), so every run tests the same keys and a failure can be replayed."""
    rng = np.random.default_rng([key_bits, KEY_KINDS.index(kind)])
    dtype = np.uint64 if key_bits > 32 else np.uint32
    out = []
    for _ in range(arrays):
        n = int(rng.integers(2, 400))
        if kind == "random":
            keys = rng.integers(0, 2**key_bits, n, dtype=np.uint64)
        elif kind == "few_values":
            keys = rng.integers(0, 6, n).astype(np.uint64) << np.uint64(key_bits - 3)
        else:
            keys = rng.integers(0, 2**key_bits, n, dtype=np.uint64) & np.uint64(0x0F0F0F0F0F0F0F0F)
        out.append(np.sort(keys % np.uint64(2**key_bits)).astype(dtype))
    return out


def empty_mesh_loads() -> bool:
    """Whether a scene holding a mesh without faces can be loaded at all: Mitsuba's
    OptiX scene build (the CUDA variants) aborts the whole process on one, so the tests
    of our message for such a mesh run where Embree builds the scene."""
    import mitsuba as mi

    return not mi.variant().startswith("cuda")
