"""Which structure traces the moving meshes for a render, chosen by measured cost.

Three structures can trace a scene's moving meshes (with ``static="native"``):

* ``"hlbvh"``: our HLBVH, refit or rebuilt (seeded) in milliseconds, traced by our
  traversal, which costs more per ray than Embree or OptiX;
* ``"native"``: a Mitsuba sub-scene of the moving meshes alone, built anew by Mitsuba's
  own accelerator when they change (Embree's or OptiX's build, about ten times our
  update for the same triangles), traced at Mitsuba's rate;
* ``"scene"``: the whole scene through Mitsuba's own accelerator, rebuilt when anything
  moved (the still world's triangles rebuilt too), where a ray walks one tree instead
  of two.

A frame costs the structure's update plus its ray queries: ``update_ms + samples x
queries_per_sample x query_ns``. Mitsuba's rebuild is a fixed cost per frame, our
traversal's penalty grows with the film and the samples, so the cheapest structure
depends on the render: ours for previews, Mitsuba's for final frames. What the model
uses, all measured on this machine and this scene:

* **update**: each structure's update time, measured when it runs (a running mean);
  before a Mitsuba structure first runs, its triangles times Embree's (or OptiX's) rate
  measured on the still world's sub-scene build;
* **query**: the time per query of the same sample of the render's own rays (camera
  rays through random pixels, and a diffuse bounce from where they land) through each
  structure that is current, taken on the first render, as the slope between the whole
  sample and half of it (a launch's fixed cost, which a render's single kernel does not
  pay per query, cancels); ``"scene"`` is timed once it is current (after it was
  chosen), and until then counted at the still world's rate alone (a ray through the
  whole scene walks at least that tree);
* **queries per sample**: from the same sample: a camera ray, and for each surface a
  path reaches a shadow ray and a bounce, which continues where the bounce met a
  surface (:func:`queries_per_sample`), up to the integrator's depth.

The shading of a sample costs the same whichever structure traces it, so only these
differences decide.

A structure replaces the current one only when its estimated frame is at least
:data:`SWITCH_MARGIN` cheaper, so noise in the measurements does not flip the choice
from frame to frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

#: The structures that can trace the moving meshes.
STRUCTURES = ("hlbvh", "native", "scene")
#: The depth counted for an unbounded integrator (``max_depth`` -1).
DEPTH_CAP = 64
#: How much cheaper (relative) another structure's frame must be for the choice to move.
SWITCH_MARGIN = 0.05
#: Embree's build rate assumed before any sub-scene build was measured (ms a triangle).
DEFAULT_BUILD_MS_PER_TRIANGLE = 4e-4
#: Weight of a new measurement in a running mean.
_NEW = 0.5


@dataclass(frozen=True)
class Probe:
    """A sample of a render's own rays (:func:`hlbvh.integrators.common.probe`):
    ``rays`` (camera rays, then as many bounces), and the fractions of its camera rays
    and of its bounces that met a surface."""

    rays: Any
    camera_hits: float
    bounce_hits: float


@dataclass(frozen=True)
class RayBudget:
    """What a render will trace: ``samples`` (film pixels x samples per pixel) and the
    integrator's ``depth`` (its ``max_depth``; -1 unbounded)."""

    samples: int
    depth: int


def queries_per_sample(camera_hits: float, bounce_hits: float, depth: int) -> float:
    """Ray queries a path-traced sample makes: its camera ray; at each of the surfaces
    it reaches (at most ``depth``, :data:`DEPTH_CAP` when -1), a shadow ray and a
    bounce ray. ``camera_hits``: the fraction of camera rays that meet a surface;
    ``bounce_hits``: the fraction of bounces that meet another."""
    depth = DEPTH_CAP if depth < 0 else max(depth, 1)
    surfaces = camera_hits * sum(bounce_hits ** k for k in range(depth))
    return 1.0 + 2.0 * surfaces


@dataclass
class CostModel:
    """Measured costs of each structure and the choice they make (see the module
    docstring).

    Attributes:
        update_ms: each structure's update time (running mean), once measured.
        query_ns: each structure's time per ray query, once measured.
        build_ms_per_triangle: Mitsuba's build rate, from the still world's build.
        hit_fractions: ``(camera_hits, bounce_hits)`` of the probe's rays, once
            measured (None before).
    """

    update_ms: dict = field(default_factory=dict)
    query_ns: dict = field(default_factory=dict)
    build_ms_per_triangle: float = DEFAULT_BUILD_MS_PER_TRIANGLE
    hit_fractions: tuple | None = None

    def record_update(self, structure: str, ms: float):
        """An update of ``structure`` took ``ms``."""
        old = self.update_ms.get(structure)
        self.update_ms[structure] = ms if old is None else (1 - _NEW) * old + _NEW * ms

    def record_build_rate(self, ms: float, triangles: int):
        """Mitsuba built a (sub-)scene of ``triangles`` triangles in ``ms``: its rate, when
        the build was large enough to say it (10k triangles)."""
        if triangles >= 10_000 and ms > 0:
            self.build_ms_per_triangle = ms / triangles

    def record_queries(self, structure: str, ns: float):
        """A query through ``structure`` took ``ns`` (a probe's mean)."""
        self.query_ns[structure] = ns

    def queries(self, budget: RayBudget) -> float:
        """Queries a sample of ``budget`` makes (:func:`queries_per_sample`), from the
        probe's hit fractions (every ray meeting a surface before a probe)."""
        camera, bounce = self.hit_fractions or (1.0, 1.0)
        return queries_per_sample(camera, bounce, budget.depth)

    def frame_ms(self, structure: str, budget: RayBudget, triangles: dict) -> float | None:
        """Estimated frame time through ``structure`` (update and queries), None when its
        query cost is not known. ``triangles``: the triangles each structure rebuilds
        (``"native"``: the moving meshes', ``"scene"``: the whole scene's)."""
        ns = self.query_ns.get(structure)
        if structure == "scene" and ns is None:
            ns = self.query_ns.get("still")
        if ns is None:
            return None
        update = self.update_ms.get(structure)
        if update is None:
            update = (self.build_ms_per_triangle * triangles.get(structure, 0)
                      if structure != "hlbvh" else 0.0)
        return update + budget.samples * self.queries(budget) * ns * 1e-6

    def choose(self, budget: RayBudget, current: str, allowed=STRUCTURES,
               triangles: dict | None = None) -> tuple[str, dict]:
        """The structure to trace the moving meshes with for a render of ``budget``, and
        each allowed structure's estimated frame time (ms; None when unknown). Keeps
        ``current`` unless another is :data:`SWITCH_MARGIN` cheaper."""
        estimates = {s: self.frame_ms(s, budget, triangles or {}) for s in allowed}
        known = {s: ms for s, ms in estimates.items() if ms is not None}
        if not known:
            return current, estimates
        best = min(known, key=known.get)
        if current in known and known[best] >= (1 - SWITCH_MARGIN) * known[current]:
            return current, estimates
        return best, estimates
