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
  rays through runs of neighbouring pixels, as a render's lanes trace them, and a
  diffuse bounce from where they land) through each
  structure that is current, taken on the first render, as the slope between the whole
  sample and half of it (a launch's fixed cost, which a render's single kernel does not
  pay per query, cancels); ``"scene"`` is timed once it is current (after it was
  chosen), and until then counted at the still world's rate alone (a ray through the
  whole scene walks at least that tree);
* **queries per sample**: from the same sample: a camera ray, and for each surface a
  path reaches a shadow ray and a bounce, which continues where the bounce met a
  surface (:func:`queries_per_sample`), up to the integrator's depth;
* **the renders themselves**: each render's time through the structure it used, by
  its number of samples. A structure that rendered is estimated from its own renders
  (at that number of samples, or along the line through its two nearest); one that did
  not, from a structure that did plus the difference of their queries (the shading of
  a sample costs the same whichever structure traces it). A probe's queries are not a
  render's (a few thousand rays timed on a busy machine, shadow rays are any-hit
  queries; its estimate of our penalty varies by a factor of two between runs),
  and the line through one measured sample count says little about another, so at
  each number of samples the structures that could still win and whose own renders do
  not draw a line yet (measured at fewer than two sample counts; their estimate within
  :data:`TRY_MARGIN` of the best frame measured there, their update alone at least
  :data:`MIN_SAVING_MS` below it)
  are tried once there (a structure's very first render compiles its kernel and is not
  counted), and from then on judged by their own renders.

A structure replaces the current one only when its estimated frame is at least
:data:`SWITCH_MARGIN` and :data:`MIN_SAVING_MS` cheaper, so noise in the measurements
does not flip the choice from frame to frame.

The probe is paid only where it could move the choice (:meth:`CostModel.worth_probing`,
docs/decisions.md#first-frames): it builds the native group, times our refit and
traces its rays through each structure, about a steady frame's time or more, while
the first frame already pays the still world's sub-scene build. So the first frames
are traced by our HLBVH unmeasured, and the probe waits for a render of it to be
timed (the first render compiles its kernel and is not), then runs only if another
structure's update alone, at Mitsuba's build rate measured on the still world's
sub-scene, leaves room below that frame: where it does not, no speed of its rays can
make it win.
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
#: The least saving (ms a frame) for which the choice moves or tries a structure: below
#: it differences are within the noise of a frame's timings (a tiny scene's structures
#: all cost about a millisecond, and processes measuring the same scene would choose
#: differently by chance), and a move costs a compile and a catch-up update.
MIN_SAVING_MS = 2.0
#: How close (relative) to the best frame measured at a render's number of samples
#: another structure's estimate must come for it to be tried there.
TRY_MARGIN = 0.3
#: Embree's build rate assumed before any sub-scene build was measured (ms a triangle).
DEFAULT_BUILD_MS_PER_TRIANGLE = 4e-4
#: Weight of a new measurement in a running mean.
_NEW = 0.5


@dataclass(frozen=True)
class Probe:
    """A sample of a render's own rays (:func:`hlbvh.accel.preparation.render_sample`):
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


def _along(times: dict, samples: int, fixed: float = 0.0) -> float:
    """A render time at ``samples`` from ``times`` (``{samples: ms}``): the one measured
    there, else on the line through the two nearest measured (a render's fixed cost and
    a cost per sample), else through the one measured and ``fixed`` (the fixed cost
    other structures' renders showed)."""
    if samples in times:
        return times[samples]
    near = sorted(times, key=lambda n: abs(n - samples))[:2]
    if len(near) == 1:
        n0, t0 = near[0], times[near[0]]
        fixed = min(fixed, t0)
        return fixed + (t0 - fixed) * samples / n0
    (n0, n1), (t0, t1) = near, (times[near[0]], times[near[1]])
    slope = max((t1 - t0) / (n1 - n0), 0.0)
    return max(t0 + slope * (samples - n0), 0.0)


def _fixed_ms(renders: dict) -> float:
    """A render's fixed cost (launch, film), from the structures measured at two or
    more sample counts (the intercept of the line through their two smallest)."""
    intercepts = []
    for times in renders.values():
        if len(times) >= 2:
            n0, n1 = sorted(times)[:2]
            slope = (times[n1] - times[n0]) / (n1 - n0)
            intercepts.append(max(times[n0] - slope * n0, 0.0))
    return min(intercepts, default=0.0)


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
        renders: each structure's render times by number of samples (``{structure:
            {samples: ms}}``, each a running mean), from its second render on (the
            first compiles the render's kernel with that structure in it).
    """

    update_ms: dict = field(default_factory=dict)
    query_ns: dict = field(default_factory=dict)
    build_ms_per_triangle: float = DEFAULT_BUILD_MS_PER_TRIANGLE
    hit_fractions: tuple | None = None
    renders: dict = field(default_factory=dict)
    compiled: set = field(default_factory=set)  # structures past their first render

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

    def record_render(self, structure: str, ms: float, samples: int):
        """A render of ``samples`` samples through ``structure`` took ``ms`` (not counted
        for a structure's first render, which compiles its kernel)."""
        if structure not in self.compiled:
            self.compiled.add(structure)
            return
        if samples > 0:
            times = self.renders.setdefault(structure, {})
            old = times.get(samples)
            times[samples] = ms if old is None else (1 - _NEW) * old + _NEW * ms

    def queries(self, budget: RayBudget) -> float:
        """Queries a sample of ``budget`` makes (:func:`queries_per_sample`), from the
        probe's hit fractions (every ray meeting a surface before a probe)."""
        camera, bounce = self.hit_fractions or (1.0, 1.0)
        return queries_per_sample(camera, bounce, budget.depth)

    def worth_probing(self, budget: RayBudget, current: str, allowed, triangles: dict) -> bool:
        """Whether timing the other structures' queries could move the choice for a
        render of ``budget`` (see the module docstring): once a render through
        ``current`` was timed, when another of ``allowed`` has an update alone (as
        measured, else at the build rate) at least :data:`MIN_SAVING_MS` below
        ``current``'s estimated frame. ``triangles`` as :meth:`frame_ms`."""
        if not self.renders.get(current):
            return False
        frame = self.frame_ms(current, budget, triangles)
        return any(self.update_estimate(s, triangles) < frame - MIN_SAVING_MS
                   for s in allowed if s != current)

    def frame_ms(self, structure: str, budget: RayBudget, triangles: dict) -> float | None:
        """Estimated frame time through ``structure`` (its update and its render), None
        when neither a render nor a probe timed it. ``triangles``: the triangles each
        structure rebuilds (``"native"``: the moving meshes', ``"scene"``: the whole
        scene's)."""
        render = self.render_ms(structure, budget)
        return None if render is None else self.update_estimate(structure, triangles) + render

    def update_estimate(self, structure: str, triangles: dict) -> float:
        """Its update as measured, else Mitsuba's build rate times the triangles it
        rebuilds (ours before a first build: nothing)."""
        update = self.update_ms.get(structure)
        if update is None:
            update = (self.build_ms_per_triangle * triangles.get(structure, 0)
                      if structure != "hlbvh" else 0.0)
        return update

    def render_ms(self, structure: str, budget: RayBudget) -> float | None:
        """A render of ``budget`` through ``structure``: from its own renders; otherwise
        from a structure that rendered, plus the difference of their queries (probe);
        otherwise the queries alone (comparable among structures no render timed)."""
        fixed = _fixed_ms(self.renders)
        if structure in self.renders:
            return _along(self.renders[structure], budget.samples, fixed)
        ns = self._query_ns(structure)
        if ns is None:
            return None
        queries = budget.samples * self.queries(budget) * 1e-6
        for other, times in self.renders.items():
            other_ns = self._query_ns(other)
            if other_ns is not None:
                return _along(times, budget.samples, fixed) + queries * (ns - other_ns)
        return queries * ns

    def _query_ns(self, structure: str) -> float | None:
        """A query's cost through ``structure``; the whole scene's, until timed, counted
        at the still world's (a ray through it walks at least that tree)."""
        ns = self.query_ns.get(structure)
        return self.query_ns.get("still") if ns is None and structure == "scene" else ns

    def choose(self, budget: RayBudget, current: str, allowed=STRUCTURES,
               triangles: dict | None = None) -> tuple[str, dict]:
        """The structure to trace the moving meshes with for a render of ``budget``, and
        each allowed structure's estimated frame time (ms; None when unknown). Keeps
        ``current`` unless another is :data:`SWITCH_MARGIN` and :data:`MIN_SAVING_MS`
        cheaper."""
        estimates = {s: self.frame_ms(s, budget, triangles or {}) for s in allowed}
        known = {s: ms for s, ms in estimates.items() if ms is not None}
        if not known:
            return current, estimates
        best = min(known, key=known.get)
        here = [s for s in known if budget.samples in self.renders.get(s, {})]
        if here:
            # Try, at this number of samples, each structure that could still win: its
            # estimate near the best measured here, and its update alone below it
            measured = min(known[s] for s in here)
            untried = [s for s in known if s not in here
                       and len(self.renders.get(s, ())) < 2  # no line of its own yet
                       and known[s] <= (1 + TRY_MARGIN) * measured
                       and self.update_estimate(s, triangles or {}) < measured - MIN_SAVING_MS]
            if untried:
                return (current if current in untried else min(untried, key=known.get)), estimates
        if current in known and (known[best] >= (1 - SWITCH_MARGIN) * known[current]
                                 or known[current] - known[best] < MIN_SAVING_MS):
            return current, estimates
        return best, estimates
