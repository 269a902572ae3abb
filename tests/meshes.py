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
