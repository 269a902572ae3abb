"""``hlbvh bench frame``: what an animation costs per frame, our HLBVH against
Mitsuba's native rebuild, measured side by side in one process.

For each scene and size: ``world`` (the case users have: a 100k-triangle flag moving
over a 1M-triangle static landscape, ``size`` triangles in all, so Mitsuba rebuilds
the landscape every frame and we rebuild the flag alone), then the worst cases, where
everything deforms (the deforming ``cloth`` and ``twist``, the fracturing
``fracture``):

**Build**, over the animated meshes (the geometry that moves; static shapes are a few
triangles), with :func:`hlbvh.build` on frames ``0 .. drift_frames-1``:

- ``fresh``: a build per frame from scratch (no temporal reuse);
- ``seeded``: a build per frame seeded with the previous frame's BVH (``previous=``: the
  CSD sort starts from last frame's primitive order);
- ``refit``: frame 0's tree refit to each frame (same topology, new boxes);
- SAH drift: SAH cost of frame 0's tree refit to frame ``i`` over that of a fresh build
  of frame ``i`` (1 = as good as a rebuild); its value at the last frame and its largest.

In a scene whose motion is instances' transforms (``flock``, ``rigid:instanced=true``,
``fracture:instanced=true``; a scene's options follow its name), the same three are
the instances' two-level update instead: their world boxes and the top level over them
built fresh, seeded, or frame 0's top level refit (the groups' BVHs are built once);
``instances`` counts them, and a scene with more instances than Mitsuba's renderer
takes (:data:`hlbvh.render.frame.MOST_NATIVE_INSTANCES`) has hlbvh rows alone, native shown
as refused.

``cold`` is frame 0's build (the first of the scene in the process: kernels compiled
unless Dr.Jit's disk cache holds them); ``min``/``median`` are over frames ``1 ..``.

**Frame time** at ``resolution``² and each ``spp``, through
:class:`hlbvh.render.frame.FrameRenderer` (what ``hlbvh render`` does), ``repeats + 1``
consecutive frames per spp, every frame a new pose, the two accelerators taking turns
frame by frame (both see the same machine load):

- ``hlbvh``: ``hlbvh_path`` with ``accel="hlbvh"`` and its defaults (the still shapes
  through Mitsuba's accelerator, ``static="native"``); frame = build (our
  accelerator's update for the new pose, as its default policy decides: refit or
  rebuild) + render;
- ``native``: ``hlbvh_path`` with ``accel="native"`` (bit-identical to Mitsuba's C++
  ``path`` and as fast: every query goes to the scene's Embree BVH); frame =
  ``params.update()`` (Mitsuba's rebuild of its accelerator) + render.

hlbvh frames write the new geometry through :func:`hlbvh.traverse`'s parameters, so
Mitsuba does not rebuild its unused Embree tree; what Mitsuba still spends refreshing the scene is reported
(``mitsuba_update_ms``, 0 on hlbvh frames) and not counted in the hlbvh frame. ``cold`` is the first frame at that spp (for the first spp: the scene's
first build and kernel compilation).

The **motion overhead** of each accelerator is its median frame over native's median
render of the same frames without a rebuild (``native_render_ms``): what an animated
frame costs over a still one, 1.0 the limit. ``moving`` says what traced the moving
meshes on hlbvh's frames (``moving_accel="auto"`` chooses per render by measured cost,
:mod:`hlbvh.accel.choice`: ``hlbvh``, ``native`` or ``scene``).

The **crossover** is the spp from which native is faster per frame, from the median
frame times (:func:`hlbvh.comparison.crossover.crossover_spp`: interpolated between
measured spp; ``None`` when native is faster at every measured spp or at none, the
table says which).

**Motion blur** (``--shutter``, as ``hlbvh render`` parses it; ``--motion-keys``,
``--sub-frames``): each scene's frame with the shutter open, four ways side by side in
one process, taking turns frame by frame (:func:`blur_runs`):

- ``ours blurred``: our accelerator traces every ray at its time through the moving
  meshes' keys (a build and a refit per key, :mod:`hlbvh.kernels.keyed`);
- ``ours sub-frames`` and ``native sub-frames``: the mean of ``sub_frames`` renders of
  the geometry at stratified times, the spp over the sub-frames each (an update of our
  accelerator, or Mitsuba's whole-scene rebuild, per sub-frame): the same estimator
  in expectation, what a Mitsuba user does today;
- ``ours still``: the frame at its instant (shutter closed), at the same spp.

Each time is a whole frame (geometry, keys, updates, render: everything between two
images). The row gains the medians, ``native_sub_over_blurred`` (> 1: our blurred
frame faster), ``own_sub_over_blurred``, ``blur_overhead`` (blurred over still), the
keyed trees' memory over the still tree's (``keyed_memory_ratio``) and the keyed
tree's SAH over the shutter over the still SAH at mid-shutter (``keyed_degradation``).
With ``equal_error`` (``--equal-error``) each scene is also measured for time to
equal error (:func:`time_to_equal_error`).

Run: ``hlbvh bench frame [--sizes ...] [--resolution 512|1920x1080] [--spp 1,4,16]
[--repeats N] [--shutter 0.5 [--motion-keys S] [--sub-frames K] [--equal-error]]``, or
``python -m hlbvh.comparison.bench.frame --help`` for every knob.
"""

from __future__ import annotations

import dataclasses
import math
import os
import statistics

import drjit as dr
import mitsuba as mi
import numpy as np

import hlbvh
from hlbvh.accel.instance_group import group_of
from hlbvh.accel.instance_shading import group_members, is_instance
from hlbvh.accel.native_group import shape_groups
from hlbvh.accel.policy import UpdatePolicy
from hlbvh.accel.scene_geometry import collect_geometry
from hlbvh.cli.options import shutter_settings
from hlbvh.comparison.crossover import crossover_spp, describe
from hlbvh.errors import UserError
from hlbvh.kernels.instances import refit_top_level, two_level
from hlbvh.kernels.layout.packing import packed_records
from hlbvh.render.frame import FrameRenderer
from hlbvh.render.settings import INTEGRATORS, SCENE_INTEGRATORS, RenderSettings
from hlbvh.scenes import get as get_scene, parse as parse_scene
from hlbvh.timing import timed

#: The accelerator's default per-frame policy, which the hlbvh frames run under.
_POLICY = UpdatePolicy()

SCENES = ("world", "cloth", "twist", "fracture")
SPPS = (1, 4, 16)

#: Keys of every row :func:`run` returns.
ROW_KEYS = (
    "scene", "triangles", "instances", "builder", "integrator", "resolution", "spp",
    "drift_frames",
    "build_cold_ms", "build_min_ms", "build_median_ms",
    "seeded_min_ms", "seeded_median_ms", "refit_min_ms", "refit_median_ms",
    "sah_fresh", "sah_drift_last", "sah_drift_max",
    "hlbvh_build_ms", "hlbvh_render_ms", "mitsuba_update_ms",
    "hlbvh_frame_cold_ms", "hlbvh_frame_min_ms", "hlbvh_frame_median_ms",
    "native_update_ms", "native_render_ms",
    "native_frame_cold_ms", "native_frame_min_ms", "native_frame_median_ms",
    "native_over_hlbvh", "crossover_spp", "hlbvh_motion_overhead", "native_motion_overhead",
    "moving_accel",
)

#: The ways a frame with an open shutter is timed (``--shutter``), in the order they
#: take turns (see the module docstring).
BLUR_WAYS = ("ours blurred", "ours sub-frames", "native sub-frames", "ours still")

#: Keys a row gains with ``--shutter`` (times in ms, medians over the warm frames).
BLUR_KEYS = (
    "shutter", "motion_keys", "sub_frames", "blurred_min_ms", "blurred_median_ms",
    "own_sub_frames_median_ms", "native_sub_frames_median_ms", "still_median_ms",
    "native_sub_over_blurred", "own_sub_over_blurred", "blur_overhead",
    "keyed_memory_ratio", "keyed_degradation",
)


def run(repeats: int = 3, sizes=(1_000_000,), resolution=512, builder: str = "hlbvh",
        scenes=SCENES, spps=SPPS, drift_frames: int = 100, max_depth: int = 8,
        native: bool = True, integrator: str | None = None, shutter=None,
        motion_keys: int = 1, sub_frames: int = 16, equal_error: bool = False) -> list[dict]:
    """Measure build, refit, SAH drift and frame time per scene, size and spp.

    Args:
        repeats: warm frames per spp after the cold one.
        sizes: triangle counts of the scenes (``triangles=`` of :func:`hlbvh.scenes.get`).
        resolution: image side in pixels, or ``(width, height)``.
        builder: ``"hlbvh"``, ``"lbvh"`` or ``"sah"``.
        scenes: procedural scene names.
        spps: samples per pixel of the frame-time runs (2 or more for a crossover).
        drift_frames: frames of the build, refit and SAH drift runs (>= 2).
        max_depth: longest path of the path tracer.
        native: measure native's frames too (False: hlbvh's alone, native shown as not
            run, for scenes whose native render takes minutes; then our BVH traces the
            moving meshes on every frame, ``moving_accel="hlbvh"``, since the choice
            would hand them to Mitsuba's native group or whole scene, which is the
            render this option leaves out).
        integrator: the ``--integrator`` choice both accelerators render with
            (``"path"``, ``"direct"``, ``"volpath"``); None: the one the scene's own
            integrator runs as, else ``"path"``.
        shutter: ``(open, close)`` in frames, open (``open < close``): the motion blur
            runs too (module docstring), ``motion_keys`` intervals between keys,
            ``sub_frames`` sub-frames; None (or closed): not.
        equal_error: with ``shutter``, each scene's time to equal error
            (:func:`time_to_equal_error`) in its rows under ``equal_error``.
    Returns:
        One dict per (scene, size, spp) with the keys :data:`ROW_KEYS` (build and drift
        values repeat over a scene's spp rows; times in ms), and :data:`BLUR_KEYS` with
        an open ``shutter``.
    Raises:
        ValueError: an unknown scene or builder, or counts out of range.
    """
    if repeats < 1 or drift_frames < 2 or not spps:
        raise ValueError(f"repeats={repeats}, drift_frames={drift_frames}, spps={spps}: "
                         "expected repeats >= 1, drift_frames >= 2 and at least one spp")
    hlbvh.BuildConfig.from_options(builder=builder)
    resolution = (resolution, resolution) if isinstance(resolution, int) else tuple(resolution)
    rows = []
    for spec in scenes:
        name, options = parse_scene(spec)
        for size in sizes:
            render_frames = len(spps) * (repeats + 1)
            animation = get_scene(name, triangles=size,
                                   frames=max(drift_frames, render_frames), **options)
            kind = integrator or _integrator(animation)
            renderers = _renderers(animation, resolution, max_depth, builder, native, kind)
            scene = renderers["hlbvh"].scene
            build = (_top_level_runs(animation, scene, builder, drift_frames)
                     if _transforms_only(animation) else
                     _build_runs(animation, scene, builder, drift_frames))
            frames = _frame_runs(renderers, spps, repeats)
            nothing = {spp: dict.fromkeys(_FRAME_KEYS) for spp in spps}
            frames.setdefault("native", nothing)  # native refused the scene
            crossover = (_crossover(spps, frames["hlbvh"], frames["native"])
                         if "native" in renderers else None)
            instances = sum(is_instance(s) for s in scene.shapes())
            blurred = error = None
            if shutter is not None and shutter[1] > shutter[0]:
                ways = blur_renderers(animation, resolution, shutter, motion_keys, sub_frames,
                                      max_depth, builder, kind, native)
                blurred = blur_runs(ways, spps, repeats)
                if equal_error:
                    error = time_to_equal_error(ways)
            for spp in spps:
                ours, native = frames["hlbvh"][spp], frames["native"][spp]
                rows.append({
                    "scene": spec, "triangles": renderers["hlbvh"].triangle_count(),
                    "instances": instances,
                    "builder": builder, "integrator": kind, "resolution": resolution,
                    "spp": spp,
                    "drift_frames": drift_frames, **build,
                    "hlbvh_build_ms": ours["build_ms"], "hlbvh_render_ms": ours["render_ms"],
                    "mitsuba_update_ms": ours["mitsuba_update_ms"],
                    "hlbvh_frame_cold_ms": ours["cold_ms"], "hlbvh_frame_min_ms": ours["min_ms"],
                    "hlbvh_frame_median_ms": ours["median_ms"],
                    "native_update_ms": native["build_ms"],
                    "native_render_ms": native["render_ms"],
                    "native_frame_cold_ms": native["cold_ms"],
                    "native_frame_min_ms": native["min_ms"],
                    "native_frame_median_ms": native["median_ms"],
                    "native_over_hlbvh": (native["min_ms"] / ours["min_ms"]
                                          if native["min_ms"] is not None else None),
                    "crossover_spp": crossover,
                    "hlbvh_motion_overhead": _overhead(ours["median_ms"], native),
                    "native_motion_overhead": _overhead(native["median_ms"], native),
                    "moving_accel": ours["moving_accel"],
                })
                if blurred is not None:
                    rows[-1].update(blur_row(blurred, spp, shutter, motion_keys, sub_frames))
                if error is not None:
                    rows[-1]["equal_error"] = error
    return rows


def blur_renderers(animation, resolution, shutter, motion_keys: int, sub_frames: int,
                   max_depth: int = 8, builder: str = "hlbvh", integrator: str = "path",
                   native: bool = True) -> dict:
    """``{way: FrameRenderer}`` of :data:`BLUR_WAYS` (``native sub-frames`` left out
    where native refuses the scene or is not asked for)."""
    base = dict(resolution=tuple(resolution), max_depth=max_depth, integrator=integrator,
                build_options={"builder": builder})
    blur = dict(shutter=tuple(shutter), motion_keys=motion_keys, sub_frames=sub_frames)
    settings = {
        "ours blurred": RenderSettings(**base, **blur, moving_accel="hlbvh"),
        "ours sub-frames": RenderSettings(**base, **blur, moving_accel="hlbvh"),
        "native sub-frames": RenderSettings(**base, **blur, accel="native"),
        "ours still": RenderSettings(**base),
    }
    renderers = {}
    for way in BLUR_WAYS:
        if way == "native sub-frames" and not native:
            continue
        try:
            renderers[way] = FrameRenderer(animation, settings[way])
        except UserError:
            if way != "native sub-frames":
                raise
    return renderers


def _blur_frame(renderer, way: str, i: int, spp: int):
    """``(ms, image)``: frame ``i`` rendered the way ``way`` renders it, timed whole."""
    if way == "ours sub-frames":
        ms, image = timed(lambda: renderer.accumulated(i, renderer.settings.seed + i, spp))
    else:
        ms, (image, _) = timed(lambda: renderer.render(i, spp=spp))
    dr.eval(image)
    return ms, image


def blur_runs(renderers: dict, spps, repeats: int, first: int = 0) -> dict:
    """``{"times": {spp: {way: [ms, ...]}}, "keyed_memory_ratio", "keyed_degradation"}``:
    each way of ``renderers`` timed on ``repeats`` warm frames per spp (after one that
    compiles), frames ``first ..``, the ways taking turns frame by frame."""
    times = {spp: {way: [] for way in renderers} for spp in spps}
    frame = first
    for spp in spps:
        for k in range(repeats + 1):
            for way, renderer in renderers.items():
                ms, _ = _blur_frame(renderer, way, frame, spp)
                if k:  # the first frame compiles
                    times[spp][way].append(ms)
            frame += 1
    group = renderers["ours blurred"].integrator.scene_accel.dynamic
    ratio = degradation = None
    if group.keyed is not None:
        keyed = dr.width(group.keyed.records) + dr.width(group.key_points)
        ratio = keyed / dr.width(packed_records(group.keyed.bvh)[0])
        degradation = group.keyed.degradation
    return {"times": times, "keyed_memory_ratio": ratio, "keyed_degradation": degradation}


def blur_row(blurred: dict, spp: int, shutter, motion_keys: int, sub_frames: int) -> dict:
    """The :data:`BLUR_KEYS` of one spp's row."""
    times = blurred["times"][spp]
    median = {way: statistics.median(ms) if ms else None
              for way, ms in ((w, times.get(w)) for w in BLUR_WAYS)}
    ours = median["ours blurred"]

    def over(way):
        return None if median[way] is None else median[way] / ours

    return {
        "shutter": list(shutter), "motion_keys": motion_keys, "sub_frames": sub_frames,
        "blurred_min_ms": min(times["ours blurred"]), "blurred_median_ms": ours,
        "own_sub_frames_median_ms": median["ours sub-frames"],
        "native_sub_frames_median_ms": median["native sub-frames"],
        "still_median_ms": median["ours still"],
        "native_sub_over_blurred": over("native sub-frames"),
        "own_sub_over_blurred": over("ours sub-frames"),
        "blur_overhead": ours / median["ours still"],
        "keyed_memory_ratio": blurred["keyed_memory_ratio"],
        "keyed_degradation": blurred["keyed_degradation"],
    }


#: :func:`time_to_equal_error`'s defaults: our blurred frame's spp levels, native's
#: accumulation's (over its sub-frames, at least one sample each), and the reference's
#: spp (two renders of half of it).
ERROR_SPPS = (4, 16, 64)
NATIVE_ERROR_SPPS = (16, 32, 64)
REFERENCE_SPP = 256


def time_to_equal_error(renderers: dict, frame: int = 0, spps=ERROR_SPPS,
                native_spps=NATIVE_ERROR_SPPS, reference_spp: int = REFERENCE_SPP) -> dict:
    """Time to equal error against a high-spp reference, for our blurred frame and
    native's sub-frame accumulation, on frame ``frame``.

    The reference is our blurred frame at ``reference_spp`` (two renders of half of it,
    other seeds): of the two estimators of the same image it is the one that converges
    to the shutter's time integral itself (native's ``K`` sub-frames converge to the
    mean of ``K`` instants, a strobed image whose difference is a floor on its error),
    and at ``reference_spp`` it costs seconds where native's would cost minutes of
    rebuilds. The reference's own noise is taken out of each RMSE: the squared RMSE of
    an image against the reference, less the reference's variance (a quarter of the
    mean squared difference of its two halves), is the image's own squared error.

    For each method and spp level: the whole frame's time and the RMSE (over pixels and
    R, G, B). Each method's time to reach a common RMSE is interpolated on log-log axes
    between its two levels around it (extrapolated from its two nearest where it never
    reached it: ``extrapolated`` says so); the common RMSE is the geometric mean of the
    range both methods' levels span (where they overlap; else the lower of the two
    methods' least RMSEs).

    Returns:
        ``{"reference_spp", "reference_noise_rmse", "levels": {way: [{"spp", "ms",
        "rmse"}, ...]}, "target_rmse", "time_ms": {way: ms}, "extrapolated": {way: bool},
        "native_over_ours"}`` (native's entries absent where it is not in ``renderers``).
    """
    ours = renderers["ours blurred"]
    base = ours.settings
    halves = []
    try:
        for seed in (base.seed + 1_000_003, base.seed + 2_000_003):  # not the levels' seeds
            ours.settings = dataclasses.replace(base, seed=seed)
            halves.append(np.asarray(_blur_frame(ours, "ours blurred", frame,
                                                 reference_spp // 2)[1], np.float64)[..., :3])
    finally:
        ours.settings = base
    reference = 0.5 * (halves[0] + halves[1])
    noise = 0.25 * float(np.mean((halves[0] - halves[1]) ** 2))
    levels = {}
    for way, spp_levels in (("ours blurred", spps), ("native sub-frames", native_spps)):
        if way not in renderers:
            continue
        _blur_frame(renderers[way], way, frame, spp_levels[0])  # compiles
        levels[way] = []
        for spp in spp_levels:
            ms, image = _blur_frame(renderers[way], way, frame, spp)
            mse = float(np.mean((np.asarray(image, np.float64)[..., :3] - reference) ** 2))
            levels[way].append({"spp": spp, "ms": ms,
                                "rmse": math.sqrt(max(mse - noise, 0.0))})
    target = _common_rmse([[p["rmse"] for p in points] for points in levels.values()])
    time_ms, extrapolated = {}, {}
    for way, points in levels.items():
        time_ms[way], extrapolated[way] = _time_at(points, target)
    result = {"reference_spp": reference_spp, "reference_noise_rmse": math.sqrt(noise),
              "levels": levels, "target_rmse": target, "time_ms": time_ms,
              "extrapolated": extrapolated}
    if "native sub-frames" in time_ms:
        result["native_over_ours"] = time_ms["native sub-frames"] / time_ms["ours blurred"]
    return result


def _common_rmse(per_way: list) -> float:
    """The RMSE the methods are compared at (see :func:`time_to_equal_error`)."""
    low = max(min(r) for r in per_way)
    high = min(max(r) for r in per_way)
    return math.sqrt(low * high) if low <= high else min(min(r) for r in per_way)


def _time_at(points: list, rmse: float) -> tuple[float, bool]:
    """The time at which a method's RMSE is ``rmse``, interpolated log-log between its
    levels (by falling RMSE), and whether it had to be extrapolated."""
    ordered = sorted(points, key=lambda p: -p["rmse"])
    rmses = [p["rmse"] for p in ordered]
    inside = rmses[-1] <= rmse <= rmses[0]
    j = next((k for k in range(len(ordered) - 1) if rmses[k + 1] <= rmse), len(ordered) - 2)
    a, b = ordered[max(j, 0)], ordered[max(j, 0) + 1]
    if a["rmse"] <= 0 or b["rmse"] <= 0 or a["rmse"] == b["rmse"]:
        return (a["ms"] if abs(a["rmse"] - rmse) <= abs(b["rmse"] - rmse) else b["ms"]), \
            not inside
    slope = (math.log(b["ms"]) - math.log(a["ms"])) / (math.log(b["rmse"]) - math.log(a["rmse"]))
    return math.exp(math.log(a["ms"]) + slope * (math.log(rmse) - math.log(a["rmse"]))), \
        not inside


#: Keys of :func:`_frame_runs`' result per accelerator and spp.
_FRAME_KEYS = ("cold_ms", "min_ms", "median_ms", "build_ms", "render_ms", "mitsuba_update_ms",
               "moving_accel")


def _overhead(frame_ms, native: dict) -> float | None:
    """``frame_ms`` over native's median render without its rebuild (None where native
    was not run)."""
    still = native["render_ms"]
    return None if frame_ms is None or not still else frame_ms / still


def _integrator(animation) -> str:
    """The ``--integrator`` choice a scene is timed with: the one its own integrator
    runs as (``volpath`` for the ``fog`` scene), else ``path``."""
    own = animation.integrator_description()
    kind = None if own is None else SCENE_INTEGRATORS.get(own["type"])
    return "path" if kind in (None, "aov") else kind


def _renderers(animation, resolution: int, max_depth: int, builder: str,
               native: bool = True, integrator: str = "path") -> dict:
    """``{"hlbvh": FrameRenderer, "native": FrameRenderer}``, without native where it
    refuses the scene (more instances than Mitsuba's renderer takes) or not
    ``native`` (and then hlbvh's traces the moving meshes with our BVH: see
    :func:`run`)."""
    renderers = {}
    for accel in ("hlbvh", "native") if native else ("hlbvh",):
        try:
            renderers[accel] = FrameRenderer(animation, RenderSettings(
                resolution=tuple(resolution), integrator=integrator,
                max_depth=max_depth, accel=accel, build_options={"builder": builder},
                moving_accel=None if native else "hlbvh"))
        except UserError:
            if accel == "hlbvh":
                raise
    return renderers


def _transforms_only(animation) -> bool:
    """Whether every animated shape moves by its ``to_world`` alone (instances)."""
    frame = animation.frame(0)
    return bool(frame) and all(g.to_world is not None for g in frame.values())


def _top_level_runs(animation, scene, builder: str, drift_frames: int) -> dict:
    """For a scene whose motion is instances' transforms: the two-level update our
    accelerator does per frame (the instances' world boxes and the top level over
    them; the groups' BVHs are built once, before) over ``drift_frames`` frames:
    :func:`hlbvh.kernels.instances.two_level` fresh and seeded, and
    :func:`~hlbvh.kernels.instances.refit_top_level` of frame 0's top level, whose SAH
    drift is measured against each frame's fresh top level as a mesh tree's is."""
    config = hlbvh.BuildConfig.from_options(builder=builder)
    shapes = {shape.id(): shape for shape in scene.shapes()}
    ids = animation.animated_ids()
    groups, bvhs, which, used = shape_groups(scene), [], [], {}
    for shape_id in ids:
        group = group_of(shapes[shape_id], groups, "is timed")
        if id(group) not in used:
            members = group_members(group)
            geometry = collect_geometry(members, list(range(len(members))))
            used[id(group)] = len(bvhs)
            bvhs.append(hlbvh.build(geometry.vertices, geometry.faces, config=config))
        which.append(used[id(group)])
    which = mi.UInt32(which)

    def rows(i: int) -> mi.Float:
        frame = animation.frame(i)
        m = np.stack([np.asarray(frame[s].to_world, np.float32) for s in ids])
        flat = mi.Float(np.concatenate([m[:, :3, :3].reshape(-1, 9), m[:, :3, 3]], 1).ravel())
        dr.eval(flat)
        return flat

    fresh_ms, seeded_ms, refit_ms, drift = [], [], [], []
    seeded = refit = None
    for i in range(drift_frames):
        transforms = rows(i)
        ms, (_, fresh) = timed(lambda: two_level(bvhs, which, transforms, config))
        fresh_ms.append(ms)
        if i == 0:
            seeded = fresh
            refit = two_level(bvhs, which, transforms, config)[1]  # refit in place
            continue
        ms, (_, seeded) = timed(lambda: two_level(bvhs, which, transforms, config,
                                                  previous=seeded))
        seeded_ms.append(ms)
        ms, _ = timed(lambda: refit_top_level(refit, bvhs, which, transforms))
        refit_ms.append(ms)
        drift.append(refit.stats.sah_cost / fresh.stats.sah_cost)
    return _build_summary(fresh_ms, seeded_ms, refit_ms, drift, fresh.stats.sah_cost)


def _animated_mesh(animation, scene):
    """Faces of the animated meshes of ``scene`` in one buffer (indices offset) and a
    function giving their concatenated positions at frame ``i``."""
    meshes = {shape.id(): shape for shape in scene.shapes()}
    ids = animation.animated_ids()
    faces, base = [], 0
    for shape_id in ids:
        faces.append(meshes[shape_id].faces_buffer() + base)
        base += meshes[shape_id].vertex_count()

    def positions(i: int) -> mi.Float:
        frame = animation.frame(i)
        vertices = dr.concat([mi.Float(np.asarray(frame[s].positions)) for s in ids])
        dr.eval(vertices)
        return vertices

    faces = dr.concat(faces)
    dr.eval(faces)
    return faces, positions


def _build_runs(animation, scene, builder: str, drift_frames: int) -> dict:
    """Fresh, seeded and refit times over ``drift_frames`` frames, and the SAH drift."""
    faces, positions = _animated_mesh(animation, scene)
    fresh_ms, seeded_ms, refit_ms, drift = [], [], [], []
    tree = seeded = fresh = None
    for i in range(drift_frames):
        vertices = positions(i)
        ms, fresh = timed(lambda: hlbvh.build(vertices, faces, builder=builder))
        fresh_ms.append(ms)
        if i == 0:
            tree = seeded = fresh
            continue
        ms, seeded = timed(lambda: hlbvh.build(vertices, faces, builder=builder,
                                                previous=seeded))
        seeded_ms.append(ms)
        ms, _ = timed(lambda: tree.refit(vertices))
        refit_ms.append(ms)
        drift.append(tree.stats.sah_cost / fresh.stats.sah_cost)
    return _build_summary(fresh_ms, seeded_ms, refit_ms, drift, fresh.stats.sah_cost)


def _build_summary(fresh_ms, seeded_ms, refit_ms, drift, sah_fresh: float) -> dict:
    """The build keys of a row: frame 0's fresh build is the cold one, the others warm."""
    return {
        "build_cold_ms": fresh_ms[0], "build_min_ms": min(fresh_ms[1:]),
        "build_median_ms": statistics.median(fresh_ms[1:]),
        "seeded_min_ms": min(seeded_ms), "seeded_median_ms": statistics.median(seeded_ms),
        "refit_min_ms": min(refit_ms), "refit_median_ms": statistics.median(refit_ms),
        "sah_fresh": sah_fresh, "sah_drift_last": drift[-1], "sah_drift_max": max(drift),
    }


def _frame_runs(renderers: dict, spps, repeats: int) -> dict:
    """Per accelerator and spp: cold, min and median frame time, and median build,
    render and Mitsuba update times over the warm frames. Every render is of a new
    frame; the accelerators take turns frame by frame, so both see the same machine
    load."""
    rows = {accel: {spp: [] for spp in spps} for accel in renderers}
    frame = 0
    for spp in spps:
        for _ in range(repeats + 1):
            for accel, renderer in renderers.items():
                rows[accel][spp].append(renderer.render(frame, spp=spp)[1])
            frame += 1
    results = {}
    for accel, per_spp in rows.items():
        results[accel] = {}
        for spp, runs in per_spp.items():
            frame_ms = [r["build_ms"] + r["render_ms"] for r in runs]
            warm = runs[1:]
            results[accel][spp] = {
                "cold_ms": frame_ms[0], "min_ms": min(frame_ms[1:]),
                "median_ms": statistics.median(frame_ms[1:]),
                "build_ms": statistics.median(r["build_ms"] for r in warm),
                "render_ms": statistics.median(r["render_ms"] for r in warm),
                "mitsuba_update_ms": statistics.median(r["mitsuba_update_ms"] for r in warm),
                "moving_accel": "/".join(sorted({r["moving_accel"] for r in warm
                                                 if r["moving_accel"]})) or None,
            }
    return results


def _crossover(spps, ours: dict, native: dict) -> float | None:
    """:func:`hlbvh.comparison.crossover.crossover_spp` of the median frame times."""
    spps = sorted(set(spps))
    return crossover_spp(spps, [ours[s]["median_ms"] for s in spps],
                         [native[s]["median_ms"] for s in spps])


def _crossover_text(rows: list[dict], row: dict) -> str:
    """The crossover of ``row``'s scene and size in words (``describe``)."""
    same = sorted((r for r in rows if (r["scene"], r["triangles"]) == (row["scene"], row["triangles"])),
                  key=lambda r: r["spp"])
    if any(r["native_frame_median_ms"] is None for r in same):
        return "-"
    return describe([r["spp"] for r in same], [r["hlbvh_frame_median_ms"] for r in same],
                    [r["native_frame_median_ms"] for r in same])


def format_table(rows: list[dict]) -> str:
    """Two fixed-width tables: builds per scene, frame times per scene and spp."""
    w = max([9] + [len(r["scene"]) for r in rows])  # scene column: names with options
    head = (f"{'scene':{w}} {'tris':>8} {'fresh cold/min/med':>20} {'seeded min/med':>15} "
            f"{'refit min/med':>14} {'SAH':>6} {'drift last/max':>15}")
    lines = ["per-frame build (ms), hlbvh.build over the animated meshes (scenes whose "
             "motion is transforms: the instances' top level, kernels.instances.two_level "
             "and refit_top_level)", head, "-" * len(head)]
    seen = set()
    for r in rows:
        if (r["scene"], r["triangles"]) in seen:
            continue
        seen.add((r["scene"], r["triangles"]))
        lines.append(
            f"{r['scene']:{w}} {r['triangles']:>8} "
            f"{_slash(r['build_cold_ms'], r['build_min_ms'], r['build_median_ms']):>20} "
            f"{_slash(r['seeded_min_ms'], r['seeded_median_ms']):>15} "
            f"{_slash(r['refit_min_ms'], r['refit_median_ms']):>14} {r['sah_fresh']:6.2f} "
            f"{_slash(r['sah_drift_last'], r['sah_drift_max'], digits=3):>15} "
            f"(over {r['drift_frames']} frames"
            + (f", {r['instances']} instances)" if r["instances"] else ")")
        )
    head = (f"{'scene':{w}} {'tris':>8} {'spp':>4} | {'build':>7} {'render':>8} "
            f"{'frame min/med/cold':>20} | {'update':>7} {'render':>8} "
            f"{'frame min/med/cold':>20} | {'nat/ours':>8} {'crossover':>10} | "
            f"{'overhead ours/nat':>17} {'moving':>7}")
    plugin = "/".join(dict.fromkeys(INTEGRATORS[r["integrator"]] for r in rows)) or "hlbvh_path"
    lines += ["", "frame time (ms) at {}x{}".format(*rows[0]["resolution"])
              if rows else "frame time (ms)",
              f"{'':{w + 15}}| {f'hlbvh ({plugin}, accel=hlbvh)':^37} | "
              f"{f'native ({plugin}, accel=native)':^37} |", head, "-" * len(head)]
    for r in rows:
        crossover = _crossover_text(rows, r)
        lines.append(
            f"{r['scene']:{w}} {r['triangles']:>8} {r['spp']:>4} | {r['hlbvh_build_ms']:7.1f} "
            f"{r['hlbvh_render_ms']:8.1f} "
            f"{_slash(r['hlbvh_frame_min_ms'], r['hlbvh_frame_median_ms'], r['hlbvh_frame_cold_ms']):>20} | "
            f"{_number(r['native_update_ms'], 7)} {_number(r['native_render_ms'], 8)} "
            f"{_slash(r['native_frame_min_ms'], r['native_frame_median_ms'], r['native_frame_cold_ms']):>20} | "
            f"{_ratio(r['native_over_hlbvh'])} {crossover:>10} | "
            f"{_slash(r['hlbvh_motion_overhead'], r['native_motion_overhead'], digits=2):>17} "
            f"{r['moving_accel'] or '-':>7}"
        )
    if rows:
        update = statistics.median(r["mitsuba_update_ms"] for r in rows)
        lines.append(
            f"frame = build + render (median of warm frames for build/render; min/median/cold "
            f"of the sum). nat/ours = native frame / hlbvh frame (min; > 1: hlbvh faster). "
            f"crossover = spp from which native is faster per frame. overhead = frame / "
            f"native's render of the frame without a rebuild (1.0: a still frame's cost). "
            f"moving = what traced the moving meshes on hlbvh's frames. hlbvh frames rendered "
            f"through Mitsuba also pay its own params.update() rebuild (median "
            f"{update:.1f} ms here), not counted. builder={rows[0]['builder']}, update="
            f"{_POLICY.update} (refit_tolerance {_POLICY.refit_tolerance}), variant "
            f"{mi.variant()}, {os.cpu_count()} cores, load average "
            f"{os.getloadavg()[0]:.1f} at the end"
        )
    lines += blur_table(rows)
    return "\n".join(lines)


def blur_table(rows: list[dict]) -> list[str]:
    """The motion-blur lines of ``rows`` measured with a shutter (none without): per
    scene and spp, the four ways' median frames and the ratios; then each scene's time
    to equal error."""
    blurred = [r for r in rows if r.get("blurred_median_ms") is not None]
    if not blurred:
        return []
    w = max([9] + [len(r["scene"]) for r in blurred])
    first = blurred[0]
    head = (f"{'scene':{w}} {'tris':>8} {'spp':>4} | {'blurred':>8} {'own sub':>8} "
            f"{'nat. sub':>9} {'still':>8} | {'nat/blur':>8} {'own/blur':>8} "
            f"{'blur/still':>10} | {'memory':>6} {'SAH/still':>9}")
    lines = ["", f"motion blur (ms a whole frame, median): shutter "
             f"{first['shutter'][0]:g}:{first['shutter'][1]:g} of a frame, "
             f"S={first['motion_keys']} key intervals, K={first['sub_frames']} sub-frames",
             head, "-" * len(head)]
    for r in blurred:
        lines.append(
            f"{r['scene']:{w}} {r['triangles']:>8} {r['spp']:>4} | "
            f"{r['blurred_median_ms']:8.1f} {_number(r['own_sub_frames_median_ms'], 8)} "
            f"{_number(r['native_sub_frames_median_ms'], 9)} {r['still_median_ms']:8.1f} | "
            f"{_ratio(r['native_sub_over_blurred'])} {_ratio(r['own_sub_over_blurred'])} "
            f"{r['blur_overhead']:10.2f} | {_times(r['keyed_memory_ratio'], 6)} "
            f"{_times(r['keyed_degradation'], 9)}")
    lines.append("blurred = ours, each ray at its time through the moving meshes' keys; own "
                 "sub / nat. sub = the mean of K sub-frames, our accelerator updated / "
                 "Mitsuba's rebuilt per sub-frame; still = ours, shutter closed. nat/blur, "
                 "own/blur: > 1, the blurred frame faster. memory = keyed tree and keys over "
                 "the still tree; SAH/still = the keyed tree's SAH over the shutter over the "
                 "still tree's at mid-shutter")
    seen = set()
    for r in blurred:
        error = r.get("equal_error")
        if error is None or r["scene"] in seen:
            continue
        seen.add(r["scene"])
        parts = []
        for way, points in error["levels"].items():
            at = ", ".join(f"{p['spp']} spp {p['ms']:.0f} ms RMSE {p['rmse']:.4f}"
                           for p in points)
            parts.append(f"  {way}: {at}; RMSE {error['target_rmse']:.4f} in "
                         f"{error['time_ms'][way]:.0f} ms"
                         + (" (extrapolated)" if error["extrapolated"][way] else ""))
        ratio = error.get("native_over_ours")
        lines += [f"{r['scene']}: time to equal error against our blurred frame at "
                  f"{error['reference_spp']} spp (its own noise RMSE "
                  f"{error['reference_noise_rmse']:.4f}, taken out)"
                  + (f": native's accumulation takes {ratio:.1f}x ours" if ratio else ""),
                  *parts]
    return lines


def _times(value, width: int) -> str:
    return f"{'-':>{width}}" if value is None else f"{value:{width - 1}.2f}x"


def _slash(*values, digits: int = 1) -> str:
    """Values joined by ``/``; ``-`` for one not measured (None)."""
    return "/".join("-" if v is None else f"{v:.{digits}f}" for v in values)


def _number(value, width: int) -> str:
    return f"{'-':>{width}}" if value is None else f"{value:{width}.1f}"


def _ratio(value) -> str:
    """``nat/ours``, or that there is none (native refused the scene's instances, or
    was not run)."""
    return f"{'no nat.':>8}" if value is None else f"{value:7.2f}x"


def blur_options(args) -> dict:
    """``--shutter``, ``--motion-keys``, ``--sub-frames`` (parsed as ``hlbvh render``
    parses them: :func:`hlbvh.cli.options.shutter_settings`) and ``--equal-error`` as
    :func:`run`'s keywords.

    Raises:
        UserError: a malformed value, or ``--equal-error`` without an open shutter.
    """
    fields = shutter_settings(args)
    if args.equal_error and not (fields.get("shutter") and
                                 fields["shutter"][1] > fields["shutter"][0]):
        raise UserError("--equal-error: it times blurred frames; give an open --shutter "
                        "(0.5, or OPEN:CLOSE) too")
    return {**fields, **({"equal_error": True} if args.equal_error else {})}


def main(argv=None) -> int:
    """Print the frame benchmark (``python -m hlbvh.comparison.bench.frame``)."""
    import argparse
    import json

    parser = argparse.ArgumentParser(prog="python -m hlbvh.comparison.bench.frame",
                                     description=__doc__.split("\n\n")[0])
    ints = lambda text: [int(v) for v in text.split(",")]  # noqa: E731
    parser.add_argument("--scenes", default=",".join(SCENES), help="comma separated")
    parser.add_argument("--sizes", type=ints, default=[1_000_000], help="triangle counts")
    parser.add_argument("--spp", type=ints, default=list(SPPS), help="samples per pixel")
    parser.add_argument("--resolution", default="512", help="image side in pixels, or WxH")
    parser.add_argument("--repeats", type=int, default=3, help="warm frames per spp")
    parser.add_argument("--drift-frames", type=int, default=100,
                        help="frames of the build, refit and SAH drift runs")
    parser.add_argument("--builder", default="hlbvh", help="hlbvh | lbvh | sah")
    parser.add_argument("--max-depth", type=int, default=8, help="longest path")
    parser.add_argument("--no-native", action="store_true",
                        help="hlbvh's frames alone, the moving meshes traced by our BVH "
                             "(native's render of some instanced scenes takes minutes)")
    parser.add_argument("--shutter", default=None,
                        help="motion blur too: a length in frames (0.5) or OPEN:CLOSE")
    parser.add_argument("--motion-keys", default=None, help="key intervals (with --shutter)")
    parser.add_argument("--sub-frames", default=None, help="sub-frames (with --shutter)")
    parser.add_argument("--equal-error", action="store_true",
                        help="with --shutter: time to equal error against a 256-spp reference")
    parser.add_argument("--json", action="store_true", help="print JSON rows")
    args = parser.parse_args(argv)
    width, _, height = args.resolution.partition("x")
    rows = run(repeats=args.repeats, sizes=args.sizes,
               resolution=(int(width), int(height or width)),
               builder=args.builder, scenes=args.scenes.split(","), spps=args.spp,
               drift_frames=args.drift_frames, max_depth=args.max_depth,
               native=not args.no_native, **blur_options(args))
    print(json.dumps(rows, indent=1) if args.json else format_table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
