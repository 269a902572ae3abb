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

Run: ``hlbvh bench frame [--sizes ...] [--resolution 512|1920x1080] [--spp 1,4,16]
[--repeats N]``, or
``python -m hlbvh.comparison.bench_frame --help`` for every knob.
"""

from __future__ import annotations

import os
import statistics

import drjit as dr
import mitsuba as mi
import numpy as np

import hlbvh
from hlbvh.comparison.crossover import crossover_spp, describe
from hlbvh.errors import UserError
from hlbvh.accel.instance_group import group_of
from hlbvh.accel.instance_shading import group_members, is_instance
from hlbvh.kernels.instances import refit_top_level, two_level
from hlbvh.accel.native_group import shape_groups
from hlbvh.accel.scene_geometry import collect_geometry
from hlbvh.scenes import get as get_scene, parse as parse_scene
from hlbvh.render.frame import FrameRenderer
from hlbvh.accel.policy import UpdatePolicy
from hlbvh.render.settings import INTEGRATORS, SCENE_INTEGRATORS, RenderSettings
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


def run(repeats: int = 3, sizes=(1_000_000,), resolution=512, builder: str = "hlbvh",
        scenes=SCENES, spps=SPPS, drift_frames: int = 100, max_depth: int = 8,
        native: bool = True, integrator: str | None = None) -> list[dict]:
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
    Returns:
        One dict per (scene, size, spp) with the keys :data:`ROW_KEYS` (build and drift
        values repeat over a scene's spp rows; times in ms).
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
    return rows


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
    return "\n".join(lines)


def _slash(*values, digits: int = 1) -> str:
    """Values joined by ``/``; ``-`` for one not measured (None)."""
    return "/".join("-" if v is None else f"{v:.{digits}f}" for v in values)


def _number(value, width: int) -> str:
    return f"{'-':>{width}}" if value is None else f"{value:{width}.1f}"


def _ratio(value) -> str:
    """``nat/ours``, or that there is none (native refused the scene's instances, or
    was not run)."""
    return f"{'no nat.':>8}" if value is None else f"{value:7.2f}x"


def main(argv=None) -> int:
    """Print the frame benchmark (``python -m hlbvh.comparison.bench_frame``)."""
    import argparse
    import json

    parser = argparse.ArgumentParser(prog="python -m hlbvh.comparison.bench_frame",
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
    parser.add_argument("--json", action="store_true", help="print JSON rows")
    args = parser.parse_args(argv)
    width, _, height = args.resolution.partition("x")
    rows = run(repeats=args.repeats, sizes=args.sizes,
               resolution=(int(width), int(height or width)),
               builder=args.builder, scenes=args.scenes.split(","), spps=args.spp,
               drift_frames=args.drift_frames, max_depth=args.max_depth,
               native=not args.no_native)
    print(json.dumps(rows, indent=1) if args.json else format_table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
