"""The shared skeleton of the procedural scenes: parts, studio, triangle budget.

A procedural scene is a set of *parts* (one Mitsuba mesh each, static or animated)
under a sun and a sky, seen by a perspective camera. A subclass says what its parts
are, where the camera stands and how the animated parts move; this class turns that
into a ``mi.load_dict`` description and per-frame :class:`FrameGeometry`.

Meshes enter the description as ``mi.Mesh`` objects built here (no files): Mitsuba's
loader never merges an already-built object with others, so every part keeps its id
with the default ``optimize=True``. Each part also gets its own BSDF object.

Conventions shared by all procedural scenes: y is up, the ground is the plane
``y = 0``, time ``t = i / FPS`` seconds at frame ``i``, all randomness drawn from
``numpy.random.default_rng`` seeded by the scene's ``seed`` (per-frame randomness by
``(seed, i)``), so a scene's geometry and frames are the same on every run and backend.
"""

from __future__ import annotations

import abc
import functools
import numbers
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from .animated import AnimatedScene, FrameGeometry, checked_resolution
from .normals import vertex_normals

FPS = 24
DEFAULT_RESOLUTION = (640, 360)
DEFAULT_SPP = 16
DEFAULT_INTEGRATOR = {"type": "path", "max_depth": 8}
DEFAULT_TRIANGLES = 200_000
DEFAULT_FRAMES = 60
GROUND_SIZE = 60.0


@dataclass(frozen=True)
class Part:
    """One shape of a procedural scene.

    Attributes:
        faces: uint32 ``(F, 3)`` vertex indices, fixed for the whole animation.
        bsdf: the Mitsuba BSDF dict of the part.
        positions: float ``(V, 3)`` world-space vertices of a static part; ``None`` for an
            animated part (its positions come from the scene's frames).
        smooth: per-vertex normals (smooth shading) when true, face normals otherwise.
    """

    faces: np.ndarray
    bsdf: dict
    positions: np.ndarray | None = None
    smooth: bool = True

    @property
    def animated(self) -> bool:
        return self.positions is None


@dataclass(frozen=True)
class View:
    """Where the camera stands (``origin``), what it looks at (``target``), and its
    horizontal field of view in degrees."""

    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    fov: float = 45.0


class ProceduralScene(AnimatedScene):
    """Base of the scenes :func:`hlbvh.scenes.get` builds.

    Args:
        triangles: the least number of triangles the scene holds (animated and static
            together); the scene rounds up to its tessellation, a few percent at most
            for budgets of a few thousand and more. :meth:`triangle_counts` gives the
            exact figure without building any geometry.
        frames: the number of frames (``frame_count``), ``FPS`` frames per second.
        seed: seed of every random choice of the scene.
    """

    def __init__(
        self, triangles: int = DEFAULT_TRIANGLES, frames: int = DEFAULT_FRAMES, seed: int = 0
    ):
        self.triangles = positive_int("triangles", triangles)
        self.frame_count = positive_int("frames", frames)
        if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
            raise ValueError(f"seed={seed!r}: expected a non-negative int")
        self.seed = int(seed)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(triangles={self.triangles}, "
            f"frames={self.frame_count}, seed={self.seed})"
        )

    # ---- What a subclass provides ------------------------------------------------

    @abc.abstractmethod
    def _build_parts(self) -> dict[str, Part]:
        """Every part of the scene by id (built once, then cached in :attr:`parts`)."""

    @abc.abstractmethod
    def _animated_positions(self, t: float, i: int) -> dict[str, np.ndarray]:
        """World-space vertices ``(V, 3)`` of every animated part at time ``t`` (frame
        ``i``)."""

    @abc.abstractmethod
    def _view(self) -> View:
        """The camera."""

    @abc.abstractmethod
    def triangle_counts(self) -> dict[str, int]:
        """Closed-form triangles per part id (no geometry built)."""

    def _sun_direction(self) -> tuple[float, float, float]:
        """Direction the sunlight travels (towards the ground)."""
        return (-0.45, -1.0, -0.35)

    # ---- The AnimatedScene contract ----------------------------------------------

    @functools.cached_property
    def parts(self) -> dict[str, Part]:
        """The scene's parts by id, built on first use."""
        return self._build_parts()

    def animated_ids(self) -> list[str]:
        return [pid for pid, part in self.parts.items() if part.animated]

    def static_ids(self) -> list[str]:
        return [pid for pid, part in self.parts.items() if not part.animated]

    def frame(self, i: int) -> dict[str, FrameGeometry]:
        i = self._check_frame_index(i)
        positions = self._animated_positions(i / FPS, i)
        return {
            pid: FrameGeometry(np.ascontiguousarray(p, dtype=np.float32).reshape(-1))
            for pid, p in positions.items()
        }

    def _transform_frame(self, i: int) -> dict[str, FrameGeometry]:
        """Frame ``i`` of a scene whose animated shapes are instances moved by their
        transforms, ``self.transforms(t)`` (``(K, 4, 4)``, in ``animated_ids()``'s
        order)."""
        i = self._check_frame_index(i)
        return {shape_id: FrameGeometry(to_world=m)
                for shape_id, m in zip(self.animated_ids(), self.transforms(i / FPS))}

    def scene_dict(self, resolution: tuple[int, int] | None = None, spp: int | None = None,
                   integrator: dict | None = None) -> dict:
        """See :meth:`AnimatedScene.scene_dict`. Defaults: ``DEFAULT_RESOLUTION``,
        ``DEFAULT_SPP``, ``DEFAULT_INTEGRATOR``. The animated parts hold frame 0."""
        width, height = checked_resolution(DEFAULT_RESOLUTION if resolution is None else resolution)
        spp = positive_int("spp", DEFAULT_SPP if spp is None else spp)
        view = self._view()
        scene = {
            "type": "scene",
            "integrator": dict(DEFAULT_INTEGRATOR if integrator is None else integrator),
            "camera": {
                "type": "perspective",
                "fov": view.fov,
                "fov_axis": "x",
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=view.origin, target=view.target, up=(0, 1, 0)
                ),
                "sampler": {"type": "independent", "sample_count": spp},
                "film": {
                    "type": "hdrfilm",
                    "width": width,
                    "height": height,
                    "rfilter": {"type": "box"},
                },
            },
            "sun": {
                "type": "directional",
                "direction": self._sun_direction(),
                "irradiance": {"type": "rgb", "value": [3.2, 3.0, 2.7]},
            },
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.32, 0.38, 0.48]}},
        }
        first = self._animated_positions(0.0, 0)
        for pid, part in self.parts.items():
            positions = first[pid] if part.animated else part.positions
            scene[pid] = mesh_object(pid, positions, part.faces, part.bsdf, part.smooth)
        return scene


def mesh_object(
    name: str, positions: np.ndarray, faces: np.ndarray, bsdf: dict, smooth: bool = True
) -> mi.Mesh:
    """A Mitsuba triangle mesh with its own BSDF, built in memory.

    Args:
        name: the mesh's name in Mitsuba's logs (the scene dict key sets its id).
        positions: float ``(V, 3)`` world-space vertices.
        faces: integer ``(F, 3)`` vertex indices.
        bsdf: a Mitsuba BSDF dict, instantiated for this mesh alone.
        smooth: per-vertex normals (computed by :func:`vertex_normals`, the same bits on
            every load) or flat faces.
    """
    positions = np.ascontiguousarray(positions, dtype=np.float32).reshape(-1, 3)
    faces = np.ascontiguousarray(faces, dtype=np.uint32).reshape(-1, 3)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    mesh = mi.Mesh(name, len(positions), len(faces), props=props, has_vertex_normals=smooth)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(positions.reshape(-1))
    params["faces"] = mi.UInt32(faces.reshape(-1))
    if smooth:
        params["vertex_normals"] = vertex_normals(params["vertex_positions"], params["faces"])
    params.update()
    return mesh


# ---- Materials and static pieces shared by the scenes --------------------------------


def diffuse(rgb, two_sided: bool = False) -> dict:
    """A Lambertian BSDF dict of colour ``rgb``; ``two_sided`` for open surfaces."""
    bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(rgb)}}
    return {"type": "twosided", "material": bsdf} if two_sided else bsdf


def glossy(rgb, roughness: float = 0.35) -> dict:
    """A glossy dielectric BSDF dict, plastic-like (``principled``: unlike
    ``roughplastic`` it needs no precomputed tables, so it loads in no time)."""
    return {
        "type": "principled",
        "base_color": {"type": "rgb", "value": list(rgb)},
        "roughness": roughness,
    }


def ground(rgb=(0.45, 0.45, 0.42), size: float = GROUND_SIZE) -> Part:
    """A square ground of side ``size`` on ``y = 0`` centred on the origin, 2 triangles."""
    corners = np.array([[-1, 0, -1], [-1, 0, 1], [1, 0, 1], [1, 0, -1]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)
    return Part(faces, diffuse(rgb), corners * (size / 2), smooth=False)


def positive_int(what: str, value, least: int = 1) -> int:
    """``value`` as an int after checking it is an integer ``>= least``; a ValueError
    naming ``what`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < least:
        raise ValueError(f"{what}={value!r}: expected an int >= {least}")
    return int(value)
