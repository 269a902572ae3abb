"""``hlbvh sweep``: the trade between build speed and tree quality, measured on one
animated scene, setting by setting, against Mitsuba's native accelerator; it ends by
naming the fastest setting per frame at the chosen samples per pixel.

Usage::

    hlbvh sweep cloth --spp 4 --resolution 320x180 --out out/sweep/cloth
    hlbvh sweep fracture --triangles 1000000 --frames 0:6 --spp 16 --spp-curve 1,4,16,64
    hlbvh sweep cloth --settings hlbvh,lbvh,refit,builder=lbvh+leaf_size=8

Settings (``--settings``)
-------------------------
The grid of builder options and update policies, and ``native`` (Mitsuba's own
accelerator) always measured as the reference: :mod:`hlbvh.comparison.sweep_settings`.

What is measured
----------------
Every setting gets its own loaded scene and :class:`hlbvh.render.frame.FrameRenderer`
(``hlbvh_path``, the same seed per frame for all). First a cold start: every setting
renders the first two frames of ``--frames`` once, untimed (the first compiles the
kernels Dr.Jit's disk cache does not hold, the second is the first update, which
compiles its own); its first build is kept as ``build_cold_ms``. Then the timed pass:
for each frame of ``--frames``, the settings take turns, so all see the same machine
load (the order rotates from frame to frame): the frame's geometry is applied, the
accelerator updated (native: ``params.update()``, Mitsuba's rebuild; ours: build,
rebuild or refit as its policy decides, timed on its own), and the frame rendered at
every spp of ``--spp-curve``. Per setting, over the timed frames:

- ``build_ms``: median time of the accelerator's update; ``decisions``: what the
  updates did (``rebuild``, ``refit``; native: ``native``);
- ``sah_cost``: median SAH cost of our tree (a refit tree drifts);
- ``mrays_primary``, ``mrays_secondary``: closest-hit queries per second (millions)
  after the last frame, on its camera rays (one per pixel centre) and on one cosine
  bounce from each of their hits, traced through the setting's accelerator (best of 3,
  the settings taking turns);
- ``render_ms`` and ``frame_ms`` (= build + render) at ``--spp``, and
  ``frame_ms_spp<N>`` at each spp of the curve: medians;
- ``image.*``: the setting's render at ``--spp`` against native's, frame by frame: the
  largest difference over the frames, the mean, the smallest fraction of pixels within
  :data:`hlbvh.comparison.compare.TOLERANCE` and the lowest PSNR. Native's own row
  compares its render with Mitsuba's C++ ``path`` integrator's (same scene, seed and
  spp; ``--integrator path`` only, else none): the reference checked against one
  that someone else wrote.

The report (``--out``, default ``out/sweep/<scene>``)
-----------------------------------------------------
``report.md``, ``report.html`` (led by a sentence: the fastest setting, its frame time
against native's, and the spp from which native is faster), ``results.json``,
``results.csv`` (one row per setting, native first; the winner marked), ``build_vs_sah.png`` (build ms against SAH cost, the
Pareto front marked) and ``frame_vs_spp.png`` (frame ms against spp for every setting
and native, the spp where native becomes faster marked).
"""

from __future__ import annotations

import os
import statistics
import sys
from pathlib import Path

import drjit as dr
import mitsuba as mi

from hlbvh.cli.options import (add_scene_options, out_flag, render_settings,
                               with_scene_integrator)
from hlbvh.comparison import plots, report
from hlbvh.comparison.bench.trace import primary_rays, secondary_rays
from hlbvh.comparison.compare import TOLERANCE
from hlbvh.comparison.crossover import crossover_spp
from hlbvh.comparison.machine import cpu_model
from hlbvh.comparison.metrics import image_metrics
from hlbvh.comparison.sweep_settings import NATIVE, SETTINGS, Setting, parse_settings
from hlbvh.errors import UserError
from hlbvh.errors import int_flag
from hlbvh.render.frame import FrameRenderer, check_frame_fits
from hlbvh.render.images import as_image
from hlbvh.render.output import output_directory
from hlbvh.render.settings import RenderSettings, check_seed, frames_argument
from hlbvh.render.source import SceneSpec, open_animation
from hlbvh.timing import timed

#: Samples per pixel of the frame-time curve unless ``--spp-curve`` says otherwise.
SPP_CURVE = (1, 4, 16)

#: Frames and samples per pixel unless ``--frames`` and ``--spp`` say otherwise.
DEFAULT_FRAMES = "0:4"
DEFAULT_SPP = 4

_TRACE_REPEATS = 3


# ---------------------------------------------------------------------------------------
# Measuring
# ---------------------------------------------------------------------------------------


def _renderer(animation, setting: Setting, base: RenderSettings, renderers: dict) -> bool:
    """Put ``setting``'s :class:`FrameRenderer` into ``renderers``; False, said on
    stderr, when the scene cannot be rendered so (``static_hlbvh`` and instances)."""
    try:
        renderers[setting.label] = FrameRenderer(animation, setting.render_settings(base))
    except UserError as error:
        reason = str(error).split(" Render this scene with")[0]
        print(f"hlbvh sweep: setting {setting.label} left out: {reason}", file=sys.stderr)
        return False
    return True


def sweep(animation, frames, settings: list[Setting], base: RenderSettings, spp: int,
          spp_curve=SPP_CURVE, progress: bool = True) -> list[dict]:
    """Measure every setting, and native, on ``frames`` of ``animation`` (see the module
    docstring).

    Args:
        animation: the :class:`hlbvh.scenes.AnimatedScene`.
        frames: frame indices, at least two (the first two are the cold start).
        settings: the settings to measure.
        base: resolution, max depth and seed of every render.
        spp: the samples per pixel the table, the error and the winner are at.
        spp_curve: samples per pixel of the frame-time curve (``spp`` is added).
    Returns:
        One row per setting, native first (keys in the module docstring, plus
        ``setting``, ``options``, ``decisions``); a setting the scene cannot be
        rendered with (``static_hlbvh`` over instances) is left out, said on stderr.
    Raises:
        ValueError: fewer than two frames, or a frame that cannot be applied.
        UserError: native refuses the scene (more instances than it takes), or the
            scene takes none of ``settings``.
    """
    from tqdm import tqdm

    frames = frames if isinstance(frames, range) else list(frames)
    if len(frames) < 2:
        raise ValueError(f"frames {frames}: a sweep needs at least two (the first two are "
                         "also rendered once untimed, to compile every kernel)")
    curve = sorted({*spp_curve, spp})
    native = Setting(NATIVE, accel=NATIVE)
    renderers = {NATIVE: FrameRenderer(animation, native.render_settings(base))}
    width, height = renderers[NATIVE].scene.sensors()[0].film().crop_size()
    check_frame_fits(int(width), int(height), curve[-1], "--spp-curve")  # before any render
    settings = [s for s in settings if _renderer(animation, s, base, renderers)]
    if not settings:
        raise UserError(f"{animation.name}: the scene takes none of the settings asked for")
    everyone = [native, *settings]
    cpp_path = (mi.load_dict({"type": "path", "max_depth": base.max_depth})
                if base.integrator == "path" else None)
    cold, runs, images = {}, {s.label: [] for s in everyone}, {}
    with tqdm(total=(len(frames) + 2) * len(everyone), desc=f"sweep {animation.name}",
              unit="render", file=sys.stderr, disable=not progress,
              dynamic_ncols=True) as bar:
        # ---- Cold start: the first two frames once, untimed but for the first build ----
        # (the second frame is the first update: it compiles kernels of its own)
        for setting in everyone:
            bar.set_postfix_str(setting.label)
            for i in frames[:2]:
                run, _ = _frame(renderers[setting.label], i, curve[:1], curve[0])
                cold.setdefault(setting.label, run["build_ms"])
                bar.update()
        # ---- Every frame, the settings taking turns ----
        # The order rotates frame by frame: whatever one setting leaves behind (Embree's
        # worker threads spinning after a native rebuild, caches) falls on each in turn.
        for k, i in enumerate(frames):
            for setting in everyone[k % len(everyone):] + everyone[:k % len(everyone)]:
                bar.set_postfix_str(setting.label)
                run, image = _frame(renderers[setting.label], i, curve, spp)
                images[setting.label] = image
                runs[setting.label].append(run)
                bar.update()
            for setting in settings:
                runs[setting.label][-1]["image"] = image_metrics(images[NATIVE],
                                                                 images[setting.label], TOLERANCE)
            runs[NATIVE][-1]["image"] = None if cpp_path is None else image_metrics(
                as_image(_render(renderers[NATIVE].scene, runs[NATIVE][-1]["seed"], spp,
                                 cpp_path))[..., :3], images[NATIVE], TOLERANCE)
    throughput = _throughput(renderers)
    return [_row(setting, runs[setting.label], cold[setting.label], throughput[setting.label],
                 spp, curve) for setting in everyone]


def _frame(renderer: FrameRenderer, i: int, curve: list[int], spp: int) -> tuple[dict, object]:
    """Frame ``i`` applied, the accelerator updated and the frame rendered at every spp
    of ``curve``: (its numbers, the image at ``spp`` as numpy). KeyboardInterrupt when
    Ctrl-C came during one of the renders."""
    image, row = renderer.render(i, spp=curve[0])
    render_ms = {curve[0]: row["render_ms"]}
    kept = image
    for samples in curve[1:]:
        render_ms[samples], image = timed(_render, renderer.scene, row["seed"], samples)
        if samples == spp:
            kept = image
    if renderer.integrator.should_stop():
        # Ctrl-C inside mi.render: Mitsuba's handler only cancels the integrator, and a
        # sweep writes nothing until it ends, so it stops here.
        raise KeyboardInterrupt
    run = {"build_ms": row["build_ms"], "sah_cost": row["sah_cost"],
           "decision": row["decision"], "render_ms": render_ms, "seed": row["seed"]}
    return run, as_image(kept)[..., :3]


def _render(scene, seed: int, spp: int, integrator=None):
    image = mi.render(scene, integrator=integrator, seed=seed, spp=spp)
    dr.eval(image)
    return image


def _throughput(renderers: dict) -> dict:
    """Per setting: millions of closest-hit queries per second on the current frame's
    camera rays (``primary``) and on one bounce from their hits (``secondary``, spawned
    from native's hits), the best of a few runs after a first that may compile, the
    settings taking turns."""
    native = renderers[NATIVE].scene
    primary = primary_rays(native)
    rays = {"primary": (primary, True), "secondary": (secondary_rays(native, primary), False)}
    dr.eval(rays)
    times = {label: {kind: [] for kind in rays} for label in renderers}
    for _ in range(_TRACE_REPEATS + 1):
        for label, renderer in renderers.items():
            accel = renderer.integrator.accel(renderer.scene)
            for kind, (ray, coherent) in rays.items():
                times[label][kind].append(timed(_trace, accel, ray, coherent)[0])
    return {label: {kind: dr.width(rays[kind][0]) / min(ms[1:]) / 1e3
                    for kind, ms in per_kind.items()}
            for label, per_kind in times.items()}


def _trace(accel, ray, coherent: bool) -> None:
    pi = accel.ray_intersect_preliminary(ray, coherent)
    dr.eval(pi.t, pi.prim_uv, pi.prim_index, pi.shape_index)


def _row(setting: Setting, runs: list[dict], cold_ms: float, throughput: dict, spp: int,
         curve) -> dict:
    """One setting's row: medians and image error over the timed frames."""
    sah = [run["sah_cost"] for run in runs if run["sah_cost"] is not None]
    build = statistics.median(run["build_ms"] for run in runs)
    frame_ms = {samples: statistics.median(run["build_ms"] + run["render_ms"][samples]
                                           for run in runs) for samples in curve}
    errors = [run["image"] for run in runs if run["image"] is not None]
    decisions = [run["decision"] for run in runs]
    return {
        "setting": setting.label,
        "options": setting.description(),
        "decisions": ", ".join(f"{d} x{decisions.count(d)}" for d in dict.fromkeys(decisions)),
        "build_ms": build,
        "build_cold_ms": cold_ms,
        "sah_cost": statistics.median(sah) if sah else None,
        "mrays_primary": throughput["primary"],
        "mrays_secondary": throughput["secondary"],
        "render_ms": statistics.median(run["render_ms"][spp] for run in runs),
        "frame_ms": frame_ms[spp],
        **{f"frame_ms_spp{samples}": frame_ms[samples] for samples in curve},
        "image": {
            "max_abs_diff": max(e["max_abs_diff"] for e in errors),
            "mean_abs_diff": statistics.fmean(e["mean_abs_diff"] for e in errors),
            "fraction_within_tolerance": min(e["fraction_within_tolerance"] for e in errors),
            "psnr_db": min(e["psnr_db"] for e in errors),
        } if errors else None,
    }


# ---------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------


def write_sweep(out_dir, rows: list[dict], recorded: dict, spp: int, curve) -> dict:
    """The two plots and the report of a sweep (see the module docstring).

    Returns:
        ``{"files": {...}, "plots": [...], "winner": row, "fastest_hlbvh": row}``.
    """
    out = Path(out_dir)
    ours = [row for row in rows if row["setting"] != NATIVE]
    note = machine_note(recorded)
    pareto = plots.plot_build_vs_sah(
        out / "build_vs_sah.png", [row["setting"] for row in ours],
        [row["build_ms"] for row in ours], [row["sah_cost"] for row in ours],
        title=f"{recorded['scene_name']}: build time vs SAH cost (medians)", note=note,
    )
    curve = sorted({*curve, spp})
    by_spp = plots.plot_frame_time_vs_spp(
        out / "frame_vs_spp.png", curve,
        {row["setting"]: [row[f"frame_ms_spp{s}"] for s in curve] for row in rows},
        native=NATIVE, title=f"{recorded['scene_name']}: frame time (build + render) vs spp",
        note=note,
    )
    files = report.write_sweep_report(
        out, f"hlbvh sweep: {recorded['scene_name']} at {spp} spp", rows, recorded,
        plots=[pareto, by_spp], objective="frame_ms", label="setting",
        lead=lead_sentence(rows, spp, curve),
    )
    return {"files": files, "plots": [pareto, by_spp], "winner": report.winner(rows),
            "fastest_hlbvh": report.winner(ours)}


def lead_sentence(rows: list[dict], spp: int, curve) -> str:
    """What the page says first, for a person: the fastest hlbvh setting per frame, its
    frame time against native's at ``spp``, and the spp from which native is faster."""
    native = next(row for row in rows if row["setting"] == NATIVE)
    best = report.winner([row for row in rows if row["setting"] != NATIVE])
    ratio = native["frame_ms"] / best["frame_ms"]
    pace = f"{ratio:.2f}x faster than" if ratio >= 1 else f"{1 / ratio:.2f}x slower than"
    curve = sorted(curve)
    ours_ms = [best[f"frame_ms_spp{s}"] for s in curve]
    native_ms = [native[f"frame_ms_spp{s}"] for s in curve]
    crossing = crossover_spp(curve, ours_ms, native_ms)
    if crossing is not None:
        native_wins = f"native is faster per frame from {crossing:.3g} spp on"
    elif ours_ms[0] >= native_ms[0]:
        native_wins = f"native is faster at every spp measured ({curve[0]} to {curve[-1]})"
    else:
        native_wins = f"native is slower at every spp measured, up to {curve[-1]}"
    return (f"The fastest hlbvh setting at {spp} spp is {best['setting']}: "
            f"{best['frame_ms']:.1f} ms a frame, {pace} native's {native['frame_ms']:.1f} ms; "
            f"{native_wins}.")


def machine_note(recorded: dict) -> str | None:
    """What the plots say they were measured on: ``"Intel(R) Xeon(R) ..., 2 cores"``
    (from ``cpu`` and ``cores`` of ``recorded``; ``None`` without them)."""
    if not recorded.get("cpu"):
        return None
    cores = f", {recorded['cores']} cores" if recorded.get("cores") else ""
    return f"measured on {recorded['cpu']}{cores}"


def verdict(result: dict, scene: str, spp: int) -> str:
    """The closing sentence: the fastest setting per frame, with its numbers."""
    best, ours = result["winner"], result["fastest_hlbvh"]
    text = (f"fastest per frame on {scene} at {spp} spp: {best['setting']} "
            f"({best['frame_ms']:.1f} ms per frame")
    if best is ours:
        return text + ")"
    return text + f"); fastest hlbvh setting: {ours['setting']} ({ours['frame_ms']:.1f} ms)"


# ---------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------


def configure(parser) -> None:
    """Options of ``hlbvh sweep``."""
    parser.description = __doc__.split("\n\n")[0]
    add_scene_options(parser, "out/sweep/<scene>", builder_options=False,
                      frames=DEFAULT_FRAMES, spp=DEFAULT_SPP)
    parser.add_argument("--settings", help=f"comma separated: names ({', '.join(SETTINGS)}) "
                                           "or key=value+key=value; default: all names")
    parser.add_argument("--spp-curve", default=",".join(map(str, SPP_CURVE)),
                        help="samples per pixel of the frame-time plot, comma separated "
                             f"(default {','.join(map(str, SPP_CURVE))}; --spp is added)")


def run(args) -> int:
    """``hlbvh sweep``: see the module docstring. Returns the exit status (0)."""
    settings = parse_settings(args.settings)
    spp = DEFAULT_SPP if args.spp is None else int_flag("--spp", args.spp, least=1)
    curve = [int_flag("--spp-curve", s, least=1) for s in args.spp_curve.split(",")]
    base = render_settings(args, spp=spp)
    animation, source, frames = open_animation(SceneSpec.of(
        args.scene, args.frames_dir, args.triangles,
        DEFAULT_FRAMES if args.frames is None else args.frames, args.topology, base.shutter))
    if len(frames) < 2:
        raise UserError(f"--frames {args.frames}: a sweep needs at least two frames")
    base = with_scene_integrator(args, animation, base, "sweep")
    check_seed(base.seed, frames)
    out = output_directory(out_flag(args.out, Path("out/sweep") / Path(args.scene).stem))
    rows = sweep(animation, frames, settings, base, spp, curve, progress=not args.quiet)
    recorded = {"scene_name": animation.name, **source, **_recorded(base),
                "frames": frames_argument(frames), "spp_curve": sorted({*curve, spp}),
                "tolerance": TOLERANCE, "variant": mi.variant(), "mitsuba": mi.__version__,
                "drjit": dr.__version__, "cpu": cpu_model(), "cores": os.cpu_count()}
    result = write_sweep(out, rows, recorded, spp, curve)
    print(f"{result['files']['html']}: {len(rows) - 1} settings and native on "
          f"{animation.name}; {verdict(result, animation.name, spp)}")
    return 0


def _recorded(base: RenderSettings) -> dict:
    record = base.as_dict()
    for key in ("accel", "build_options", "update"):
        record.pop(key)
    return record
