"""``twist``: a closed bar bending and twisting on the ground (skinning-like deformation)."""

from __future__ import annotations

import functools
import math

import numpy as np

from . import meshes
from .procedural import Part, ProceduralScene, View, ground, glossy

HALF_WIDTH = 0.35
HEIGHT = 3.0
PROFILE_EXPONENT = 4.0  # a rounded square, so the twist shows
PERIMETER = 7.4 * HALF_WIDTH  # of that rounded square, near enough to shape the grid


class Twist(ProceduralScene):
    """A closed, capped bar with a rounded-square cross-section, standing on the
    ground, that twists about its axis, bends over in a slowly turning direction and
    bulges, its foot fixed.

    Parts: ``bar`` (animated, ``2 segments rings + 2 segments`` triangles: the side grid
    and two capping fans), ``ground`` (static). The deformation is smooth along the bar,
    as a skinned character's limb: each cross-section is rotated about the axis by an
    angle growing with height, scaled, then carried along an arc of the bend's
    curvature. Every vertex moves every frame; the topology never changes.

    Args: see :class:`ProceduralScene`.
    """

    name = "twist"

    def _tessellation(self) -> tuple[int, int]:
        """Quads around the bar (segments) and along it (rings), keeping them square."""
        budget = max(self.triangles - 2, 16)
        segments = max(8, math.ceil(math.sqrt(budget / 2 * PERIMETER / HEIGHT)))
        rings = max(1, math.ceil((budget - 2 * segments) / (2 * segments)))
        return segments, rings

    def triangle_counts(self) -> dict[str, int]:
        segments, rings = self._tessellation()
        return {"bar": 2 * segments * rings + 2 * segments, "ground": 2}

    @functools.cached_property
    def _bar(self) -> tuple[np.ndarray, np.ndarray]:
        """The straight bar: rest vertices ``(V, 3)`` (foot at y = 0) and faces."""
        rest, faces = meshes.capped_tube(*self._tessellation(), exponent=PROFILE_EXPONENT)
        return rest * np.array([HALF_WIDTH, HEIGHT, HALF_WIDTH]), faces

    @functools.cached_property
    def _phases(self) -> np.ndarray:
        """Phases of the twist, bend, bend direction and bulge cycles."""
        return np.random.default_rng(self.seed).uniform(0.0, 2 * np.pi, 4)

    def _build_parts(self) -> dict[str, Part]:
        return {
            "bar": Part(self._bar[1], glossy((0.10, 0.45, 0.55))),
            "ground": ground(),
        }

    def _animated_positions(self, t: float, i: int) -> dict[str, np.ndarray]:
        rest = self._bar[0]
        x, y, z = rest[:, 0], rest[:, 1], rest[:, 2]
        h = y / HEIGHT
        p_twist, p_bend, p_direction, p_bulge = self._phases
        # ---- Twist and bulge each cross-section about the axis ----
        theta = 1.25 * np.pi * math.sin(2 * np.pi * t / 2.5 + p_twist) * h
        scale = 1.0 + 0.18 * np.sin(np.pi * h) * math.sin(2 * np.pi * t / 1.3 + p_bulge)
        cos_t, sin_t = np.cos(theta) * scale, np.sin(theta) * scale
        x, z = x * cos_t - z * sin_t, x * sin_t + z * cos_t
        # ---- Bend the axis into an arc of curvature kappa towards direction alpha ----
        kappa = 0.9 / HEIGHT * math.sin(2 * np.pi * t / 1.7 + p_bend)
        alpha = 0.6 * t + p_direction
        s = x * math.cos(alpha) + z * math.sin(alpha)  # offset towards the bend
        q = -x * math.sin(alpha) + z * math.cos(alpha)  # offset across it (unchanged)
        phi = kappa * y
        sin_over_phi = np.sinc(phi / np.pi)  # sin(phi) / phi, 1 at phi = 0
        one_minus_cos_over_phi = np.sin(phi / 2) * np.sinc(phi / (2 * np.pi))
        s_bent = s * np.cos(phi) + y * one_minus_cos_over_phi
        y_bent = y * sin_over_phi - s * np.sin(phi)
        x_bent = s_bent * math.cos(alpha) - q * math.sin(alpha)
        z_bent = s_bent * math.sin(alpha) + q * math.cos(alpha)
        return {"bar": np.stack([x_bent, y_bent, z_bent], axis=1)}

    def _view(self) -> View:
        return View(origin=(5.0, 2.8, 7.2), target=(0.0, 1.6, 0.0), fov=42.0)
