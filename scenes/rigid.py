"""``rigid``: many rigid bodies bouncing around a courtyard whose floor, walls and
columns never move."""

from __future__ import annotations

import functools
import math
import numbers

import numpy as np

import mitsuba as mi

from . import meshes
from .animated import FrameGeometry
from .procedural import (
    DEFAULT_FRAMES,
    DEFAULT_TRIANGLES,
    FPS,
    Part,
    ProceduralScene,
    View,
    diffuse,
    ground,
    glossy,
    mesh_object,
    positive_int,
)
from .rigid_motion import affines, random_unit_vectors, rotation_matrices

HALF_SIZE = 6.0  # the courtyard spans [-HALF_SIZE, HALF_SIZE] in x and z
WALL_HEIGHT = 2.5
WALL_THICKNESS = 0.3
COLUMN_RADIUS = 0.28
COLUMNS_PER_WALL = 5
PROTOTYPES = ("sphere", "box", "torus")
PALETTE = (
    (0.80, 0.20, 0.15), (0.15, 0.45, 0.80), (0.90, 0.70, 0.15), (0.20, 0.65, 0.30),
    (0.60, 0.25, 0.70), (0.95, 0.45, 0.10), (0.15, 0.70, 0.70), (0.85, 0.85, 0.80),
)


class Rigid(ProceduralScene):
    """Bodies (spheres, rounded boxes, tori) bouncing along circular paths while they
    spin, in a courtyard of static floor, walls and columns.

    Parts: ``bodies_0`` .. ``bodies_{groups-1}`` (animated; group ``g`` holds every
    body ``k`` with ``k % groups == g``, all copies of one prototype in one colour, each
    moving on its own), ``walls`` and ``columns`` (static: three walls and
    ``3 COLUMNS_PER_WALL`` columns along them), ``ground`` (static). A body keeps its
    shape and only moves and turns: the triangles of one body stay together while the
    bodies move apart, and most of the scene's area (floor, walls, columns) never
    changes.

    Triangles: ``static_fraction`` of the budget goes to the columns (finely
    tessellated), the rest to the bodies, ``12 n^2`` triangles each.

    With ``instanced=True`` the same bodies move as Mitsuba instances instead: group
    ``g`` is a shape group holding one body of its prototype (``12 n_g^2`` triangles,
    ``n_g = n + g``: no two groups have the same triangle count, which is how an
    accelerator tells an instance's group), body ``k`` the instance ``body_k`` of group
    ``k % groups``, and each frame gives each body its ``to_world`` (rigid motion as
    transforms: nothing is re-tessellated, an accelerator that follows transforms
    rebuilds only its top level). The better model of rigid bodies; the mesh variant
    stays the default, the case of engines that bake rigid motion into vertices.

    Args:
        objects: the number of bodies.
        groups: the number of body meshes (Mitsuba shapes) they are spread over;
            ``groups = objects`` gives one shape per body.
        static_fraction: share of the triangles in the static environment (0..0.9).
        instanced: the bodies as instances of ``groups`` shape groups.
        others: see :class:`ProceduralScene`.
    """

    name = "rigid"

    def __init__(
        self,
        triangles: int = DEFAULT_TRIANGLES,
        frames: int = DEFAULT_FRAMES,
        seed: int = 0,
        objects: int = 240,
        groups: int = 8,
        static_fraction: float = 0.2,
        instanced: bool = False,
    ):
        super().__init__(triangles, frames, seed)
        if not isinstance(instanced, bool):
            raise ValueError(f"instanced={instanced!r}: expected True or False")
        self.instanced = instanced
        self.objects = positive_int("objects", objects)
        self.groups = positive_int("groups", groups)
        if self.groups > self.objects:
            raise ValueError(f"groups={groups!r}: expected at most objects ({objects})")
        if not isinstance(static_fraction, numbers.Real) or not 0.0 <= static_fraction <= 0.9:
            raise ValueError(f"static_fraction={static_fraction!r}: expected a number in 0..0.9")
        self.static_fraction = float(static_fraction)

    def __repr__(self) -> str:
        return super().__repr__()[:-1] + (
            f", objects={self.objects}, groups={self.groups}, "
            f"static_fraction={self.static_fraction}"
            + (", instanced=True)" if self.instanced else ")")
        )

    # ---- Sizes -----------------------------------------------------------------------

    def _column_tessellation(self) -> tuple[int, int]:
        """Segments and rings of each column, quads about square."""
        columns = 3 * COLUMNS_PER_WALL
        per_column = max(math.ceil(self.triangles * self.static_fraction) // columns, 32)
        ratio = 2 * np.pi * COLUMN_RADIUS / WALL_HEIGHT
        segments = max(8, math.ceil(math.sqrt(per_column / 2 * ratio)))
        rings = max(1, math.ceil((per_column - 2 * segments) / (2 * segments)))
        return segments, rings

    def _static_triangles(self) -> int:
        segments, rings = self._column_tessellation()
        return 2 + 3 * 12 + 3 * COLUMNS_PER_WALL * (2 * segments * rings + 2 * segments)

    def _group_sizes(self) -> np.ndarray:
        """Bodies per group: body ``k`` is in group ``k % groups``."""
        return np.bincount(np.arange(self.objects) % self.groups, minlength=self.groups)

    def _group_resolutions(self) -> list[int]:
        """``n`` of each group (its bodies have ``12 n^2`` triangles each): the largest
        ``n`` that stays under the bodies' budget everywhere, then one step finer, group
        after group, until the budget is met."""
        sizes = self._group_sizes()
        budget = max(self.triangles - self._static_triangles(), 12 * self.objects)
        n = max(1, math.isqrt(budget // (12 * self.objects)))
        if self.instanced:  # n + g: a count of its own for every group
            return [max(1, n - self.groups // 2) + g for g in range(self.groups)]
        resolutions = [n] * self.groups
        total = 12 * n * n * self.objects
        for g in range(self.groups):
            if total >= budget:
                break
            total += 12 * (2 * n + 1) * int(sizes[g])
            resolutions[g] = n + 1
        return resolutions

    def triangle_counts(self) -> dict[str, int]:
        segments, rings = self._column_tessellation()
        resolutions = self._group_resolutions()
        if self.instanced:
            counts = {body: 12 * resolutions[k % self.groups] ** 2
                      for k, body in enumerate(self.animated_ids())}
        else:
            counts = {
                f"bodies_{g}": 12 * n * n * int(k)
                for g, (n, k) in enumerate(zip(resolutions, self._group_sizes()))
            }
        counts["walls"] = 3 * 12
        counts["columns"] = 3 * COLUMNS_PER_WALL * (2 * segments * rings + 2 * segments)
        counts["ground"] = 2
        return counts

    # ---- Geometry --------------------------------------------------------------------

    @functools.cached_property
    def _prototypes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The body shape of each group at unit reach (largest vertex distance 1):
        sphere, rounded box and torus in turn, ``12 n^2`` triangles."""
        shapes = []
        for g, n in enumerate(self._group_resolutions()):
            kind = PROTOTYPES[g % len(PROTOTYPES)]
            if kind == "torus":
                positions, faces = meshes.torus(0.7, 0.3, 3 * n, 2 * n)
            else:
                positions, faces = meshes.rounded_box(n, 2.0 if kind == "sphere" else 6.0)
            shapes.append((positions / np.linalg.norm(positions, axis=1).max(), faces))
        return shapes

    @functools.cached_property
    def _paths(self) -> dict[str, np.ndarray]:
        """Per body (arrays of length ``objects``): size, orbit radius, angular speed
        and phase, bounce height, frequency and phase, spin axis ``(K, 3)`` and rate."""
        rng = np.random.default_rng(self.seed)
        k = self.objects
        size = rng.uniform(0.2, 0.45, k)
        farthest = HALF_SIZE - WALL_THICKNESS - 2 * COLUMN_RADIUS - 0.3
        return {
            "size": size,
            "orbit": rng.uniform(0.8, farthest - size),
            "speed": rng.choice([-1.0, 1.0], k) * rng.uniform(0.25, 0.8, k),
            "phase": rng.uniform(0.0, 2 * np.pi, k),
            "bounce": rng.uniform(0.3, 2.0, k),
            "frequency": rng.uniform(0.6, 1.6, k),
            "bounce_phase": rng.uniform(0.0, np.pi, k),
            "axis": random_unit_vectors(rng, k),
            "spin": rng.uniform(0.5, 4.0, k),
        }

    def _build_parts(self) -> dict[str, Part]:
        parts = {}
        for g, count in enumerate(self._group_sizes() if not self.instanced else []):
            rest, faces = self._prototypes[g]
            vertex_count = len(rest)
            copies = faces[None].astype(np.int64) + vertex_count * np.arange(count)[:, None, None]
            parts[f"bodies_{g}"] = Part(
                copies.reshape(-1, 3).astype(np.uint32), glossy(PALETTE[g % len(PALETTE)])
            )
        walls, wall_faces = _walls()
        parts["walls"] = Part(wall_faces, diffuse((0.72, 0.66, 0.58)), walls, smooth=False)
        columns, column_faces = _columns(*self._column_tessellation())
        parts["columns"] = Part(column_faces, diffuse((0.85, 0.84, 0.80)), columns)
        parts["ground"] = ground((0.50, 0.47, 0.42))
        return parts

    def _poses(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Every body's centre ``(K, 3)`` and turn times size ``(K, 3, 3)`` at ``t``."""
        paths = self._paths
        angle = paths["phase"] + paths["speed"] * t
        radius = paths["size"]
        height = radius + paths["bounce"] * np.abs(
            np.sin(np.pi * paths["frequency"] * t + paths["bounce_phase"])
        )
        centres = np.stack(
            [paths["orbit"] * np.cos(angle), height, paths["orbit"] * np.sin(angle)], axis=1
        )
        turns = rotation_matrices(paths["axis"], paths["spin"] * t) * radius[:, None, None]
        return centres, turns

    def _animated_positions(self, t: float, i: int) -> dict[str, np.ndarray]:
        if self.instanced:
            return {}  # the bodies move by their transforms (frame)
        centres, turns = self._poses(t)
        positions = {}
        for g in range(self.groups):
            rest = self._prototypes[g][0]
            bodies = np.arange(g, self.objects, self.groups)
            moved = np.einsum("kij,vj->kvi", turns[bodies], rest) + centres[bodies][:, None, :]
            positions[f"bodies_{g}"] = moved.reshape(-1, 3)
        return positions

    # ---- The instanced variant ---------------------------------------------------------

    def animated_ids(self) -> list[str]:
        if self.instanced:
            return [f"body_{k}" for k in range(self.objects)]
        return super().animated_ids()

    def transforms(self, t: float) -> np.ndarray:
        """Every body's ``to_world`` at time ``t`` (``(objects, 4, 4)``): the motion
        of the mesh variant as transforms of the unit-reach prototypes."""
        centres, turns = self._poses(t)
        return affines(turns, centres)

    def frame(self, i: int) -> dict[str, FrameGeometry]:
        return self._transform_frame(i) if self.instanced else super().frame(i)

    def frame_at(self, time: float) -> dict[str, FrameGeometry]:
        """See :meth:`AnimatedScene.frame_at`; instanced: every body's exact pose at
        ``time`` (its path and spin at a fractional frame, not an interpolation)."""
        if not self.instanced:
            return super().frame_at(time)
        time = min(max(float(time), 0.0), float(self.frame_count - 1))
        return {shape_id: FrameGeometry(to_world=m)
                for shape_id, m in zip(self.animated_ids(), self.transforms(time / FPS))}

    def scene_dict(self, resolution=None, spp=None, integrator=None) -> dict:
        """See :meth:`ProceduralScene.scene_dict`; instanced: the shape groups
        ``group_0`` .. and the bodies ``body_k`` as their instances, at frame 0."""
        scene = super().scene_dict(resolution, spp, integrator)
        if self.instanced:
            for g, (rest, faces) in enumerate(self._prototypes):
                scene[f"group_{g}"] = {"type": "shapegroup", f"prototype_{g}": mesh_object(
                    f"prototype_{g}", rest, faces, glossy(PALETTE[g % len(PALETTE)]))}
            for k, (body, m) in enumerate(zip(self.animated_ids(), self.transforms(0.0))):
                scene[body] = {"type": "instance",
                               "shape": {"type": "ref", "id": f"group_{k % self.groups}"},
                               "to_world": mi.ScalarTransform4f(m.astype(np.float32))}
        return scene

    def _view(self) -> View:
        return View(origin=(0.0, 6.0, 14.5), target=(0.0, 0.6, -0.5), fov=52.0)


def _box(lower, upper) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box, 8 vertices and 12 outward triangles."""
    corners = np.array(
        [[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float64
    )
    positions = np.asarray(lower) + corners * (np.asarray(upper) - np.asarray(lower))
    faces = np.array(
        [
            [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5],  # x = 0, x = 1
            [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],  # y = 0, y = 1
            [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],  # z = 0, z = 1
        ],
        dtype=np.uint32,
    )
    return positions, faces


def _merge(pieces) -> tuple[np.ndarray, np.ndarray]:
    """One mesh of several ``(positions, faces)``."""
    offsets = np.cumsum([0] + [len(p) for p, _ in pieces[:-1]])
    positions = np.concatenate([p for p, _ in pieces])
    faces = np.concatenate([f.astype(np.int64) + o for (_, f), o in zip(pieces, offsets)])
    return positions, faces.astype(np.uint32)


def _walls() -> tuple[np.ndarray, np.ndarray]:
    """The back, left and right walls of the courtyard (the front stays open)."""
    h, t, top = HALF_SIZE, WALL_THICKNESS, WALL_HEIGHT
    return _merge(
        [
            _box((-h - t, 0.0, -h - t), (h + t, top, -h)),
            _box((-h - t, 0.0, -h), (-h, top, h)),
            _box((h, 0.0, -h), (h + t, top, h)),
        ]
    )


def _columns(segments: int, rings: int) -> tuple[np.ndarray, np.ndarray]:
    """Columns standing along the inner side of the three walls."""
    unit, faces = meshes.capped_tube(segments, rings)
    unit = unit * np.array([COLUMN_RADIUS, WALL_HEIGHT, COLUMN_RADIUS])
    inset = HALF_SIZE - COLUMN_RADIUS - 0.05
    along = np.linspace(-HALF_SIZE + 1.0, HALF_SIZE - 1.0, COLUMNS_PER_WALL)
    feet = np.concatenate(
        [
            np.stack([along, np.full_like(along, -inset)], axis=1),
            np.stack([np.full_like(along, -inset), along], axis=1),
            np.stack([np.full_like(along, inset), along], axis=1),
        ]
    )
    return _merge([(unit + [x, 0.0, z], faces) for x, z in feet])
