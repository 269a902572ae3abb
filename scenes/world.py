"""``world``: the flag of ``cloth`` waving over a large static landscape (the scenes
users have: a moving object in a static world)."""

from __future__ import annotations

import functools
import math

import numpy as np

from . import meshes
from .cloth import POLE_SEGMENTS, Cloth
from .procedural import DEFAULT_FRAMES, Part, View, diffuse, positive_int

DEFAULT_WORLD_TRIANGLES = 1_100_000
FLAG_SHARE = 11  # by default the flag holds 1/11 of the triangles (100k of 1.1M)
TERRAIN_SIZE = 160.0  # side of the square landscape, centred on the pole
FLAT_RADIUS = 7.0  # the meadow around the pole is flat out to here
HILLS_RADIUS = 30.0  # the hills reach their full height from here on
HILL_HEIGHT = 5.0


class World(Cloth):
    """The ``cloth`` flag on its pole in the middle of rolling hills.

    Parts: ``flag`` (animated, as in :class:`Cloth`), ``pole`` and ``terrain`` (static:
    a height field of ``2 n^2`` triangles, flat around the pole, hills growing towards
    the horizon). Only the flag moves, so with ``static="native"`` every frame
    rebuilds its triangles alone while Mitsuba's own accelerator traces the landscape.

    Args:
        triangles: the least number of triangles in all (default 1.1M).
        flag_triangles: the least number of the flag's (default: a 1/11 share,
            100k of 1.1M); the terrain takes the rest.
        frames, seed: see :class:`ProceduralScene`.
    """

    name = "world"

    def __init__(self, triangles: int = DEFAULT_WORLD_TRIANGLES,
                 flag_triangles: int | None = None,
                 frames: int = DEFAULT_FRAMES, seed: int = 0):
        super().__init__(triangles=triangles, frames=frames, seed=seed)
        if flag_triangles is None:
            flag_triangles = max(self.triangles // FLAG_SHARE, 8)
        self.flag_triangles = positive_int("flag_triangles", flag_triangles, least=8)
        if self.flag_triangles + 2 + 4 * POLE_SEGMENTS > self.triangles:
            raise ValueError(f"flag_triangles={flag_triangles!r}: more than the scene's "
                             f"triangles={triangles!r} leave to the flag")

    def _flag_budget(self) -> int:
        return self.flag_triangles

    def _terrain_quads(self) -> int:
        """Quads along each side of the terrain."""
        nx, ny = self._grid()
        budget = max(self.triangles - 2 * nx * ny - 4 * POLE_SEGMENTS, 2)
        return max(1, math.ceil(math.sqrt(budget / 2)))

    def triangle_counts(self) -> dict[str, int]:
        counts = super().triangle_counts()
        del counts["ground"]
        n = self._terrain_quads()
        return {**counts, "terrain": 2 * n * n}

    @functools.cached_property
    def _terrain(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices ``(V, 3)`` and faces of the height field (y up, facing up)."""
        return terrain(self._terrain_quads(), self.seed)

    def _build_parts(self) -> dict[str, Part]:
        vertices, faces = self._terrain
        return {**self._flag_parts(),
                "terrain": Part(faces, diffuse((0.30, 0.42, 0.22)), vertices)}

    def _view(self) -> View:
        return View(origin=(9.0, 2.4, 10.0), target=(1.5, 3.3, 0.0), fov=55.0)


def terrain(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rolling hills of ``n`` by ``n`` quads over ``TERRAIN_SIZE`` squared, flat out to
    ``FLAT_RADIUS`` around the origin: vertices ``(V, 3)`` (y up) and faces facing up,
    the hills drawn from ``seed``."""
    rest, faces = meshes.grid(n, n)
    # (u, v) -> (x, -z): the grid's triangles then face +y
    x = (rest[:, 0] - 0.5) * TERRAIN_SIZE
    z = (0.5 - rest[:, 1]) * TERRAIN_SIZE
    rng = np.random.default_rng(seed + 1)
    height = np.zeros_like(x)
    for octave in range(5):
        k = 0.035 * 2.1**octave
        angle, phase = rng.uniform(0, 2 * np.pi, 2)
        height += (np.sin(k * (x * np.cos(angle) + z * np.sin(angle)) + phase)
                   * np.cos(k * 0.7 * (z * np.cos(angle) - x * np.sin(angle)) + phase)
                   / 1.9**octave)
    r = np.hypot(x, z)
    ramp = np.clip((r - FLAT_RADIUS) / (HILLS_RADIUS - FLAT_RADIUS), 0.0, 1.0)
    y = HILL_HEIGHT * ramp * ramp * (3 - 2 * ramp) * (height + 1.2)
    return np.stack([x, y, z], axis=1), faces
