"""``soup``: random triangles scattered anew every frame (the incoherent worst case)."""

from __future__ import annotations

import functools

import numpy as np

from .procedural import Part, ProceduralScene, View, diffuse, ground

LOWER = np.array([-2.0, 0.5, -2.0], dtype=np.float32)  # the box the soup fills
UPPER = np.array([2.0, 3.5, 2.0], dtype=np.float32)
SPREAD = 1.5  # triangle reach in units of the mean spacing of their centres


class Soup(ProceduralScene):
    """Triangles with random centres in a box above the ground, random shapes and
    orientations, all of them re-drawn every frame: nothing of one frame's order or
    bounds carries over to the next, so temporal reuse cannot help and every build
    starts from scratch.

    Parts: ``soup`` (animated; vertex ``3 k + c`` is corner ``c`` of triangle ``k``, the
    faces never change), ``ground`` (static). Each corner lies within
    ``SPREAD`` times the mean spacing of the centres from its triangle's centre, so
    triangles overlap their neighbours. Frame ``i`` draws from the seed ``(seed, i)``.

    Args: see :class:`ProceduralScene`.
    """

    name = "soup"

    def _soup_triangles(self) -> int:
        return max(self.triangles - 2, 1)

    def triangle_counts(self) -> dict[str, int]:
        return {"soup": self._soup_triangles(), "ground": 2}

    @functools.cached_property
    def _faces(self) -> np.ndarray:
        return np.arange(3 * self._soup_triangles(), dtype=np.uint32).reshape(-1, 3)

    def _build_parts(self) -> dict[str, Part]:
        return {
            "soup": Part(self._faces, diffuse((0.85, 0.55, 0.15), two_sided=True), smooth=False),
            "ground": ground(),
        }

    def _animated_positions(self, t: float, i: int) -> dict[str, np.ndarray]:
        count = self._soup_triangles()
        rng = np.random.default_rng([self.seed, i])
        extent = UPPER - LOWER
        spacing = float(np.cbrt(np.prod(extent) / count))
        centres = LOWER + rng.random((count, 1, 3), dtype=np.float32) * extent
        corners = rng.random((count, 3, 3), dtype=np.float32) * 2.0 - 1.0
        return {"soup": (centres + corners * (SPREAD * spacing)).reshape(-1, 3)}

    def _view(self) -> View:
        return View(origin=(0.0, 3.0, 10.5), target=(0.0, 1.8, 0.0), fov=45.0)
