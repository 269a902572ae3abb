"""``flock``: thousands of birds, instances of one bird mesh, flying over still hills
(rigid motion: each frame moves transforms, no vertex)."""

from __future__ import annotations

import functools
import math

import mitsuba as mi
import numpy as np

from . import meshes
from .animated import FrameGeometry
from .procedural import (DEFAULT_FRAMES, Part, ProceduralScene, View, diffuse, mesh_object,
                         positive_int)
from .rigid_motion import affines
from .world import terrain

DEFAULT_BIRDS = 10_000
DEFAULT_FLOCK_TRIANGLES = 500_000  # the hills'
FLOCK_HEIGHT = 12.0  # the flock's centre above the meadow
FLOCK_RADIUS = 22.0  # the birds' farthest distance from the flock's centre


class Flock(ProceduralScene):
    """``birds`` instances of one bird (a body and a pair of wings, about
    ``bird_triangles`` triangles) circling a centre that drifts over rolling hills.

    Parts: ``terrain`` (static, ``triangles`` triangles), the shape group ``bird`` and
    the instances ``bird_0`` .. ``bird_{birds-1}`` (animated: each frame gives each its
    ``to_world``). Each bird keeps its radius, height, speed and phase, turns to face
    its direction of flight and banks into the turn; every motion is a transform, so an
    accelerator that follows transforms rebuilds only its top level.

    Mitsuba's own renderer expands hits inside instances at a compile cost that grows
    with the number of instances (docs/decisions.md#instance-hit-expansion):
    render the full flock with
    ``accel="hlbvh"``; native references need a few hundred birds at most.

    Args:
        triangles: the hills' least number of triangles (default 500k).
        birds: the number of birds.
        bird_triangles: the bird mesh's least number of triangles.
        frames, seed: see :class:`ProceduralScene`.
    """

    name = "flock"

    def __init__(self, triangles: int = DEFAULT_FLOCK_TRIANGLES, frames: int = DEFAULT_FRAMES,
                 seed: int = 0, birds: int = DEFAULT_BIRDS, bird_triangles: int = 300):
        super().__init__(triangles, frames, seed)
        self.birds = positive_int("birds", birds)
        self.bird_triangles = positive_int("bird_triangles", bird_triangles, least=24)

    def __repr__(self) -> str:
        return super().__repr__()[:-1] + (
            f", birds={self.birds}, bird_triangles={self.bird_triangles})")

    # ---- Sizes and parts ------------------------------------------------------------

    def _terrain_quads(self) -> int:
        return max(1, math.ceil(math.sqrt(self.triangles / 2)))

    def _bird_resolution(self) -> tuple[int, int]:
        """``n`` of the body and of the wings (``12 n^2`` triangles each)."""
        body = max(1, math.ceil(math.sqrt(self.bird_triangles * 0.6 / 12)))
        wings = max(1, math.ceil(math.sqrt(self.bird_triangles * 0.4 / 12)))
        return body, wings

    def triangle_counts(self) -> dict[str, int]:
        body, wings = self._bird_resolution()
        per_bird = 12 * body * body + 12 * wings * wings
        return {"terrain": 2 * self._terrain_quads() ** 2,
                **{bird: per_bird for bird in self.animated_ids()}}

    @functools.cached_property
    def _bird(self) -> tuple[np.ndarray, np.ndarray]:
        """The bird in its own frame (x forward, y up), about 1 long: a body and a flat
        pair of wings across it."""
        body_n, wings_n = self._bird_resolution()
        body, body_faces = meshes.rounded_box(body_n, 2.0)
        body = body * [0.5, 0.14, 0.14]
        wings, wing_faces = meshes.rounded_box(wings_n, 6.0)
        wings = wings * [0.16, 0.02, 0.75] + [0.02, 0.04, 0.0]
        faces = np.concatenate([body_faces, wing_faces.astype(np.int64) + len(body)])
        return np.concatenate([body, wings]), faces.astype(np.uint32)

    def _build_parts(self) -> dict[str, Part]:
        vertices, faces = terrain(self._terrain_quads(), self.seed)
        return {"terrain": Part(faces, diffuse((0.30, 0.42, 0.22)), vertices)}

    @functools.cached_property
    def _paths(self) -> dict[str, np.ndarray]:
        """Per bird: orbit radius, height, angular speed, phase, wobble phase, size."""
        rng = np.random.default_rng(self.seed)
        k = self.birds
        return {
            "radius": FLOCK_RADIUS * np.sqrt(rng.uniform(0.05, 1.0, k)),
            "height": rng.normal(0.0, 2.0, k),
            "speed": rng.uniform(0.35, 0.6, k),
            "phase": rng.uniform(0.0, 2 * np.pi, k),
            "wobble": rng.uniform(0.0, 2 * np.pi, k),
            "size": rng.uniform(0.5, 0.8, k),
        }

    # ---- Motion ---------------------------------------------------------------------

    def transforms(self, t: float) -> np.ndarray:
        """Every bird's ``to_world`` at time ``t``: ``(birds, 4, 4)``, vectorised."""
        p = self._paths
        angle = p["phase"] + p["speed"] * t
        centre = np.array([6.0 * math.sin(0.13 * t), FLOCK_HEIGHT, 4.0 * math.cos(0.11 * t)])
        position = centre + np.stack([
            p["radius"] * np.cos(angle),
            p["height"] + 0.6 * np.sin(1.7 * t + p["wobble"]),
            p["radius"] * np.sin(angle)], axis=1)
        forward = np.stack([-np.sin(angle), 0.0 * angle, np.cos(angle)], axis=1)
        side = np.stack([-np.cos(angle), 0.0 * angle, -np.sin(angle)], axis=1)  # inward
        bank = 0.35 + 0.1 * np.sin(2.3 * t + p["wobble"])
        up = np.array([0.0, 1.0, 0.0]) * np.cos(bank)[:, None] + side * np.sin(bank)[:, None]
        side = np.cross(forward, up)  # a right-handed frame: no mirroring
        return affines(np.stack([forward, up, side], axis=2) * p["size"][:, None, None],
                       position)

    def animated_ids(self) -> list[str]:
        return [f"bird_{k}" for k in range(self.birds)]

    def static_ids(self) -> list[str]:
        return ["terrain"]

    def frame(self, i: int) -> dict[str, FrameGeometry]:
        return self._transform_frame(i)

    def _animated_positions(self, t: float, i: int) -> dict[str, np.ndarray]:
        return {}  # the birds move by their transforms (frame)

    def scene_dict(self, resolution=None, spp=None, integrator=None) -> dict:
        """See :meth:`ProceduralScene.scene_dict`; the birds as instances of the shape
        group ``bird``, at frame 0."""
        scene = super().scene_dict(resolution, spp, integrator)
        vertices, faces = self._bird
        scene["bird"] = {"type": "shapegroup",
                         "bird_mesh": mesh_object("bird_mesh", vertices, faces,
                                                  diffuse((0.12, 0.11, 0.10)))}
        for bird, m in zip(self.animated_ids(), self.transforms(0.0)):
            scene[bird] = {"type": "instance", "shape": {"type": "ref", "id": "bird"},
                           "to_world": mi.ScalarTransform4f(m.astype(np.float32))}
        return scene

    def _view(self) -> View:
        return View(origin=(0.0, 26.0, 58.0), target=(0.0, 9.0, 0.0), fov=60.0)

