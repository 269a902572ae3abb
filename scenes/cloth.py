"""``cloth``: a flag waving on a pole over a meadow (coherent deformation)."""

from __future__ import annotations

import functools
import math

import numpy as np

from . import meshes
from .procedural import Part, ProceduralScene, View, diffuse, ground

FLAG_LENGTH = 3.0  # along x, away from the pole
FLAG_HEIGHT = 2.0  # along y
FLAG_BOTTOM = 2.2  # height of the flag's lower edge at the pole
POLE_HEIGHT = 4.6
POLE_RADIUS = 0.06
POLE_SEGMENTS = 48
WAVES = 3


class Cloth(ProceduralScene):
    """A rectangular flag pinned along one edge to a pole, rippled by travelling waves.

    Parts: ``flag`` (animated, a regular grid of ``2 nx ny`` triangles, two-sided),
    ``pole`` and ``ground`` (static). The flag's displacement normal to its plane is a
    sum of ``WAVES`` travelling sine waves whose amplitude grows from zero at the pole
    to its free end, and the free end sags and lifts with the wind: every vertex moves
    every frame, neighbours move alike (the coherent case: Morton order barely changes).

    Args: see :class:`ProceduralScene` (the flag takes all triangles but the pole's
    and the ground's).
    """

    name = "cloth"

    def _flag_budget(self) -> int:
        """The least number of triangles of the flag: all but the static parts'."""
        return max(self.triangles - self._static_triangles(), 8)

    def _grid(self) -> tuple[int, int]:
        """Quads of the flag along x and y, the flag's aspect ratio kept."""
        budget = self._flag_budget()
        aspect = FLAG_LENGTH / FLAG_HEIGHT
        ny = max(2, math.ceil(math.sqrt(budget / (2 * aspect))))
        nx = max(2, math.ceil(budget / (2 * ny)))
        return nx, ny

    @staticmethod
    def _static_triangles() -> int:
        return 2 + 4 * POLE_SEGMENTS

    @functools.cached_property
    def _flag(self) -> tuple[np.ndarray, np.ndarray]:
        """The flat flag: rest vertices ``(V, 3)`` in the xy plane (pole at x = 0) and
        faces."""
        rest, faces = meshes.grid(*self._grid())
        return rest * np.array([FLAG_LENGTH, FLAG_HEIGHT, 0.0]), faces

    @functools.cached_property
    def _waves(self) -> np.ndarray:
        """``(WAVES, 5)``: wavenumber along x, slant along y, angular speed, amplitude
        and phase of each wave."""
        rng = np.random.default_rng(self.seed)
        return np.stack(
            [
                rng.uniform(2.0, 4.5, WAVES),
                rng.uniform(-1.0, 1.0, WAVES),
                rng.uniform(5.0, 9.0, WAVES),
                rng.uniform(0.15, 0.30, WAVES),
                rng.uniform(0.0, 2 * np.pi, WAVES),
            ],
            axis=1,
        )

    def triangle_counts(self) -> dict[str, int]:
        nx, ny = self._grid()
        return {"flag": 2 * nx * ny, "pole": 4 * POLE_SEGMENTS, "ground": 2}

    def _build_parts(self) -> dict[str, Part]:
        return {**self._flag_parts(), "ground": ground((0.30, 0.42, 0.22))}

    def _flag_parts(self) -> dict[str, Part]:
        """The flag and its pole."""
        pole, pole_faces = meshes.capped_tube(POLE_SEGMENTS, 1)
        pole = pole * np.array([POLE_RADIUS, POLE_HEIGHT, POLE_RADIUS])
        return {
            "flag": Part(self._flag[1], diffuse((0.75, 0.12, 0.10), two_sided=True)),
            "pole": Part(pole_faces, diffuse((0.8, 0.8, 0.78)), pole),
        }

    def _animated_positions(self, t: float, i: int) -> dict[str, np.ndarray]:
        rest = self._flag[0]
        x, y = rest[:, 0], rest[:, 1]
        reach = x / FLAG_LENGTH  # 0 at the pole, 1 at the free end
        k, slant, omega, amplitude, phase = (w[:, None] for w in self._waves.T)
        ripple = (amplitude * np.sin(k * x + slant * y - omega * t + phase)).sum(axis=0)
        z = reach**1.2 * ripple
        sag = 0.25 * reach**2 * (1.0 + 0.35 * math.sin(1.3 * t))
        return {"flag": np.stack([x + POLE_RADIUS, y + FLAG_BOTTOM - sag, z], axis=1)}

    def _view(self) -> View:
        return View(origin=(6.4, 3.0, 5.6), target=(2.1, 2.7, 0.0), fov=45.0)
