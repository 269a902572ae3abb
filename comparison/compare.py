"""``hlbvh compare``: every frame of an animation rendered with Mitsuba's native
accelerator and with ours, the same integrator, seed and box filter, judged against
Monte Carlo noise and timed, in a report directory.

Usage::

    hlbvh compare cloth --frames 0:8 --resolution 320x180 --spp 4 --out out/compare/cloth
    hlbvh compare fracture --triangles 1000000 --frames 4 --builder lbvh --update refit
    hlbvh compare scene.xml --frames-dir frames/ --frames 0:10
    hlbvh compare world --frames 0:12 --spp 4 --blur-frame 6 --shutter 0.5 --sub-frames 4

``SCENE``, ``--frames``, ``--resolution``, ``--spp``, ``--triangles``, the builder
options, ``--update``, ``--max-depth`` and ``--seed`` mean what they mean for
``hlbvh render`` (see :mod:`hlbvh.cli.render`), which does the rendering.

What is rendered
----------------
Four renders of every frame, and a fifth of some, each an ``hlbvh render`` into a
subdirectory of ``--out`` (frames written whole, statistics per frame; an interrupted
compare resumes, and a directory holding frames of other settings is refused):

==================  =====================================================================
``native/``         ``hlbvh_path`` with ``accel="native"`` (bit-identical to Mitsuba's
                    C++ ``path``): the reference
``hlbvh/``          ``hlbvh_path`` with ``accel="hlbvh"``: ours, same seed per frame
``hits-native/``    ``hlbvh_aov`` at 1 spp, native: the first shape and primitive per pixel
                    (at the frame's instant, also with ``--shutter``)
``hits-hlbvh/``     ``hlbvh_aov`` at 1 spp, ours (the very same camera rays)
``native-noise/``   ``native/`` rendered again with another seed (:func:`noise_seed`),
                    only for the frames where ours is not bit-identical to native's: the
                    noise ours is judged against. A bit-identical frame needs no judge,
                    and most frames of a scene our BVH does not trace (the native group
                    or the whole scene chosen) are; a frame ours traced costs one more
                    native render, the price of telling a Monte Carlo sample from a
                    defect
==================  =====================================================================

``--blur-frame N`` renders the frames still (the shutter closed) and frame ``N`` once
more with the shutter open (``--shutter``, 0.5 of a frame when not given; its
``--motion-keys``, ``--sub-frames``): a whole compare of that frame into ``blur/`` (ours
blurred through the moving meshes' keys, native's mean of sub-frames, each judged
against native's noise as any frame), whose pair and difference the report shows
beside frame ``N``'s still pair, whose judgement the verdict states and the exit
status includes, and whose numbers frame ``N``'s row holds under ``blur``.

What is compared, per frame
---------------------------
- ``noise``: the verdict of the frame, :func:`hlbvh.comparison.metrics.noise_judge` of
  ours against native, with ``native-noise/`` as the noise: block means of ours minus
  native in units of their noise, over blocks from 8x8 pixels to the whole image (the
  bias test), and ``passed`` when no block reaches
  :data:`~hlbvh.comparison.metrics.NOISE_LIMIT`; ``seed``, the noise render's (``None``:
  bit-identical, not rendered). Paths of ours that part from native's on a tie (a ray
  through a shared edge hitting the neighbouring triangle) are other samples of the
  same image and pass; other geometry, a stale frame or a wrong shading moves block
  means and fails;
- ``image``: :func:`hlbvh.comparison.metrics.image_metrics` of ours against native over
  R, G, B, figures that describe and do not judge: largest and mean absolute difference,
  fraction of pixels bit-identical, fraction within ``--tolerance`` (default
  :data:`TOLERANCE`), PSNR, pixels NaN or infinite in one render only;
- ``hits``: :func:`hlbvh.comparison.metrics.hit_agreement` of the two AOV renders:
  fraction of pixels whose camera ray hits the same shape and primitive first;
- ``build_ms``: native = Mitsuba's ``params.update()`` (its full rebuild), hlbvh = our
  accelerator's update (build, rebuild or refit: ``decision``); ``build_speedup`` =
  native / hlbvh; ``render_ms`` of each; ``frame_ms`` = build + render (an hlbvh frame
  rendered through Mitsuba today also pays Mitsuba's own rebuild: not counted, it
  measures the algorithm); ``motion_overhead`` of each = its frame over native's render
  of the frame without a rebuild (1.0: an animated frame that costs what a still frame
  costs); ``moving_accel``: what traced the moving meshes on hlbvh's frame (chosen by
  cost: ``hlbvh``, ``native`` or ``scene``); ``sah_cost`` of our tree.

The first frame of each render includes compiling the kernels Dr.Jit's disk cache did
not hold. The four renders run one after the other, so their times see the machine
load of their own moment: ``hlbvh bench frame`` alternates the accelerators frame by
frame when the timing is the question.

The report (``--out``)
----------------------
``report.md`` and ``report.html`` (the verdict, :func:`verdict`; the plots; per frame
the native image, ours and the false-colour difference side by side, its scale written
beside it; then the settings and one row per frame), ``results.json`` and
``results.csv`` (the same rows), ``diff/frame_NNNN.png`` (the difference maps of the
frames compared, an older run's other frames removed; all on one scale, logarithmic
from :data:`DIFFERENCE_FLOOR` to the largest difference of any frame, so frames can be
compared by eye; the top is recorded as ``difference_scale``), ``frame_ms.png`` and
``build_ms.png`` (frame and build time per frame, both accelerators).

Exit status
-----------
0 when ours is within Monte Carlo noise of native's on every frame (``noise.passed``),
1 when a frame is not (the verdict names the frames and the block), 2 for a user
error; so a script can tell a pass from a failure.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import asdict, replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from hlbvh.render import images
from hlbvh.comparison import plots, report
from hlbvh.comparison.metrics import NOISE_LIMIT, hit_agreement, image_metrics, noise_judge
from hlbvh.errors import UserError
from hlbvh.render.source import SceneSpec, open_animation
from hlbvh.cli.options import (add_scene_options, out_flag, render_settings,
                               with_scene_integrator)
from hlbvh.render.output import frame_name, output_directory
from hlbvh.render.animation import render_animation
from hlbvh.render.settings import (MAX_SEED, RenderSettings, check_seed, frames_argument,
                                   frames_text)

#: Largest absolute per-channel difference of a pixel counted as within tolerance in
#: the report's figure (not the verdict): the absolute part of
#: tests/integrators/test_integrators.py::test11's tolerance, several times the worst pixel
#: difference seen there (docs/decisions.md#compare-tolerance).
TOLERANCE = 5e-4

#: The bottom of the difference maps' logarithmic scale: about one float32 step at 1
#: (2^-23 = 1.2e-7), so a difference in the last bits of a pixel shows, and a one-pixel
#: edge tie at the top of the scale does not turn every other pixel black.
DIFFERENCE_FLOOR = 1e-7

#: The accelerators in the order they are rendered and shown: the reference first.
ACCELS = ("native", "hlbvh")

#: Image metrics shown per frame (all of them are in ``results.json`` under ``image``).
_IMAGE_COLUMNS = ("max_abs_diff", "mean_abs_diff", "fraction_identical",
                  "fraction_within_tolerance", "psnr_db", "nonfinite_mismatch_pixels")
#: The judge's figures shown per frame (its ``fraction_identical`` is ``image``'s).
_NOISE_COLUMNS = ("passed", "largest_z", "largest_z_block", "image_z", "blocks_over_limit",
                  "nonfinite_pixels", "noise_rms")


# ---------------------------------------------------------------------------------------
# The comparison
# ---------------------------------------------------------------------------------------


def compare_animation(animation, frames, out_dir, settings: RenderSettings,
                      source: dict | None = None, tolerance: float = TOLERANCE,
                      progress: bool = True, blur: tuple | None = None) -> dict:
    """Render ``frames`` of ``animation`` with both accelerators, compare them and write
    the report (see the module docstring).

    Args:
        animation: the :class:`hlbvh.scenes.AnimatedScene`.
        frames: the frame indices (e.g. ``range(0, 8)``).
        out_dir: the report directory (created if needed).
        settings: how to render; ``accel`` and ``integrator`` are set here per render.
        source: what identifies the scene (JSON values), recorded with the settings.
        tolerance: the figure ``fraction_within_tolerance``'s (see :data:`TOLERANCE`).
        progress: progress bars on stderr.
        blur: ``(frame, RenderSettings)``: that frame (one of ``frames``) compared once
            more with those settings' open shutter into ``blur/``, shown beside its
            still pair (the module docstring); None: not.
    Returns:
        ``{"rows": [one dict per frame], "files": {"md": ..., "html": ..., "json": ...,
        "csv": ...}, "plots": [...]}``.
    Raises:
        UserError: a subdirectory holds frames rendered with other settings.
        ValueError: a frame's geometry cannot be read or applied.
    """
    out = Path(out_dir)
    stats = {}
    for accel in ACCELS:
        colour = replace(settings, accel=accel,
                         integrator="path" if settings.integrator == "aov" else settings.integrator)
        rows, _ = render_animation(animation, frames, out / accel, colour, source, progress)
        stats[accel] = {row["frame"]: row for row in rows}
        # (at each frame's instant: the first hit of a blurred pixel has no one answer)
        hits = replace(settings, accel=accel, integrator="aov", spp=1, shutter=(0.0, 0.0))
        render_animation(animation, frames, out / f"hits-{accel}", hits, source, progress)

    # ---- Metrics per frame, judged against native's noise ----
    pairs = {i: tuple(images.read_exr(out / accel / f"{frame_name(i)}.exr", ["R", "G", "B"])
                      for accel in ACCELS) for i in frames}
    noise = _noise_renders(animation, out, settings, source, pairs, progress)
    rows = []
    for i in frames:
        name = f"{frame_name(i)}.exr"
        native, ours = pairs[i]
        hits = hit_agreement(*(images.read_exr(out / f"hits-{accel}" / name,
                                               ["shape_index", "prim_index"])
                               for accel in ACCELS))
        judged = noise_judge(ours, native, noise.get(i))
        judged["seed"] = noise_seed(settings.seed) + i if i in noise else None
        rows.append(_frame_row(i, stats["native"][i], stats["hlbvh"][i],
                               image_metrics(native, ours, tolerance), judged, hits))
        # Two black images are equal whatever the accelerators did: said by the verdict.
        rows[-1]["black"] = not (native.any() or ours.any())
        rows[-1]["shutter"] = (dict(open=settings.shutter[0], close=settings.shutter[1],
                                    sub_frames=settings.sub_frames)
                               if settings.shutter_open else None)

    # ---- Difference maps, one scale for every frame; an older run's others removed ----
    scale = max((row["image"]["max_abs_diff"] for row in rows), default=0.0) or 1.0
    low = DIFFERENCE_FLOOR if scale > DIFFERENCE_FLOOR else None
    shown = {f"{frame_name(i)}.png" for i in frames}
    for stale in (out / "diff").glob("frame_*.png"):
        if stale.name not in shown:
            stale.unlink()
    pictures = {}
    for i, (native, ours) in pairs.items():
        difference = images.write_difference_map(out / "diff" / f"{frame_name(i)}.png",
                                                  native, ours, vmax=scale, vmin=low)
        pictures[i] = {"native": out / "native" / f"{frame_name(i)}.png",
                       "hlbvh": out / "hlbvh" / f"{frame_name(i)}.png", "diff": difference}

    captions = {}
    if blur is not None:
        captions = _blurred_pair(animation, out, rows, pictures, blur, source, tolerance,
                                 progress)

    # ---- Plots and report ----
    per_frame = [
        plots.plot_per_frame(
            out / f"{key}.png", frames, [row[key]["native"] for row in rows],
            [row[key]["hlbvh"] for row in rows], quantity=quantity, native_label=native,
            title=f"{animation.name}: {quantity} per frame")
        for key, quantity, native in (("frame_ms", "frame time (build + render)", "native"),
                                      ("build_ms", "build time", "native rebuild"))
    ]
    recorded = {**(source or {}), **settings.as_dict(), "frames": frames_argument(frames),
                "tolerance": tolerance, "difference_scale": scale, "variant": mi.variant(),
                "mitsuba": mi.__version__, "drjit": dr.__version__}
    for key in ("accel", "integrator"):
        recorded.pop(key)
    # Every builder option and the policy as used, defaults included.
    recorded["build_options"] = asdict(settings.config)
    recorded["update"] = settings.policy.update
    caption = ("difference (largest over R, G, B; one scale for every frame): "
               + (f"log scale, black = {low:.0e} or less (or identical), pale yellow = "
                  f"{scale:.3g}" if low else f"black = identical, pale yellow = {scale:.3g}")
               + "; cyan = NaN/inf in one render only")
    if blur is not None:
        recorded["blur_frame"] = blur[0]
        recorded["blur_shutter"] = list(blur[1].shutter)
    files = report.write_report(out, f"hlbvh compare: {animation.name}", rows, pictures,
                                recorded, plots=per_frame, verdict=verdict(rows),
                                captions={"diff": caption, **captions})
    return {"rows": rows, "files": files, "plots": per_frame}


def _blurred_pair(animation, out: Path, rows: list, pictures: dict, blur: tuple, source,
                  tolerance: float, progress: bool) -> dict:
    """Frame ``blur[0]`` compared with the open shutter of ``blur[1]`` into ``blur/``
    (:func:`compare_animation` of that frame): its images added to the frame's
    pictures, its numbers to the frame's row under ``blur``. Returns the captions of
    the images added."""
    i, settings = blur
    inner = compare_animation(animation, range(i, i + 1), out / "blur", settings, source, tolerance,
                              progress)["rows"][0]
    row = next(r for r in rows if r["frame"] == i)
    row["blur"] = {"shutter": inner["shutter"], "frame_ms": inner["frame_ms"],
                   "passed": inner["noise"]["passed"],
                   "largest_z": inner["noise"]["largest_z"],
                   "max_abs_diff": inner["image"]["max_abs_diff"],
                   "report": "blur/report.html"}
    name = f"{frame_name(i)}.png"
    pictures[i].update({"native blurred": out / "blur" / "native" / name,
                        "hlbvh blurred": out / "blur" / "hlbvh" / name,
                        "diff blurred": out / "blur" / "diff" / name})
    shutter = inner["shutter"]
    return {"native blurred": f"native, shutter {shutter['open']:g}..{shutter['close']:g}: "
                              f"the mean of {shutter['sub_frames']} sub-frames",
            "hlbvh blurred": "hlbvh (ours), blurred: each ray at its time",
            "diff blurred": "difference of the blurred pair (its own scale: blur/report.html)"}


def blur_verdict(rows: list[dict]) -> str:
    """The verdict's sentence on the blurred pair of ``--blur-frame`` (empty without
    one): each frame time, and whether ours is within noise of native's accumulation."""
    row = next((r for r in rows if r.get("blur")), None)
    if row is None:
        return ""
    blur = row["blur"]
    ours, native = blur["frame_ms"]["hlbvh"], blur["frame_ms"]["native"]
    judged = (f"within Monte Carlo noise of native's (largest block |z| "
              f"{abs(blur['largest_z']):.2f})" if blur["passed"] else
              f"NOT within Monte Carlo noise of native's (largest block |z| "
              f"{abs(blur['largest_z']):.1f}, limit {NOISE_LIMIT:g})")
    return (f" Frame {row['frame']} blurred (shutter {blur['shutter']['open']:g}.."
            f"{blur['shutter']['close']:g}, beside its still pair; blur/report.html): "
            f"hlbvh {ours:.1f} ms, native's {blur['shutter']['sub_frames']} sub-frames "
            f"{native:.1f} ms ({native / ours:.1f}x); ours is {judged}.")


def noise_seed(seed: int) -> int:
    """The seed of frame 0's noise render (frame ``i``'s is this plus ``i``): one from
    ``seed``, so that no frame's noise render shares its seed with the frame's own (two
    renders of one seed are one sample), and fixed by ``seed`` alone, so that a compare
    resumed over other frames finds the same noise renders (below half of
    :data:`~hlbvh.render.settings.MAX_SEED` one up, so frames of any count fit; above,
    one down)."""
    return seed + 1 if seed <= MAX_SEED // 2 else seed - 1


def _noise_renders(animation, out: Path, settings: RenderSettings, source, pairs: dict,
                   progress: bool) -> dict:
    """Native rendered again with :func:`noise_seed` (into ``native-noise/``) for the
    frames where ours is not bit-identical to native's, the noise the judge measures
    against: ``{frame: image}``. A bit-identical frame costs no render."""
    differ = [i for i, (native, ours) in pairs.items()
              if not np.array_equal(native.view(np.uint32), ours.view(np.uint32))]
    if not differ:
        return {}
    colour = replace(settings, accel="native", seed=noise_seed(settings.seed),
                     integrator="path" if settings.integrator == "aov" else settings.integrator)
    render_animation(animation, differ, out / "native-noise", colour, source, progress)
    return {i: images.read_exr(out / "native-noise" / f"{frame_name(i)}.exr", ["R", "G", "B"])
            for i in differ}


def _frame_row(i: int, native: dict, ours: dict, image: dict, judged: dict,
               hits: dict) -> dict:
    """One frame's numbers: what both renders measured, the judge's verdict
    (:func:`~hlbvh.comparison.metrics.noise_judge`, its noise render's seed) and the
    figures of how the images compare."""
    build = {"native": native["build_ms"], "hlbvh": ours["build_ms"]}
    render = {"native": native["render_ms"], "hlbvh": ours["render_ms"]}
    return {
        "frame": i,
        "triangles": ours["triangles"],
        "decision": ours["decision"],
        "build_ms": build,
        "build_speedup": build["native"] / build["hlbvh"] if build["hlbvh"] > 0 else math.inf,
        "render_ms": render,
        "frame_ms": {accel: build[accel] + render[accel] for accel in ACCELS},
        # frame time over native's render of the frame without a rebuild (1.0: a still
        # frame's cost)
        "motion_overhead": {accel: (build[accel] + render[accel]) / render["native"]
                            if render["native"] > 0 else math.inf for accel in ACCELS},
        "moving_accel": ours["moving_accel"],
        "sah_cost": ours["sah_cost"],
        "noise": {**{key: judged[key] for key in _NOISE_COLUMNS}, "seed": judged["seed"]},
        "image": {key: image[key] for key in _IMAGE_COLUMNS},
        "hits": {"fraction_agree": hits["fraction_agree"],
                 "fraction_shape_agree": hits["fraction_shape_agree"],
                 "differ_pixels": hits["pixels"] - hits["agree_pixels"]},
    }


#: What may trace the moving meshes on hlbvh's frames (the rows' ``moving_accel``), as
#: the verdict names it.
_STRUCTURES = {
    "hlbvh": "our HLBVH",
    "native": "a Mitsuba sub-scene of the moving meshes (the native group)",
    "scene": "the whole scene (Mitsuba's own accelerator, rebuilt)",
}

#: What hlbvh's frames traced by one of Mitsuba's structures compare: said of every
#: frame, and of that structure's frames among others.
_MITSUBA_MEANS = {
    "native": ("this does not compare our BVH on the moving meshes",
               "the native group's frames do not compare our BVH on the moving meshes"),
    "scene": ("this compares Mitsuba with itself",
              "the whole scene's frames compare Mitsuba with itself"),
}


def traced_by(rows: list[dict]) -> str:
    """The verdict's sentence on what traced the moving meshes on hlbvh's frames (chosen
    per render by measured cost, or forced by ``--moving-accel``) and what the
    comparison then compares: where one of Mitsuba's structures traced them, native
    against native, and ``--moving-accel hlbvh`` is the comparison of our BVH. Empty
    for rows that do not say."""
    counts = {name: sum(row.get("moving_accel") == name for row in rows)
              for name in _STRUCTURES}
    used = [name for name in _STRUCTURES if counts[name]]
    if not used:
        return ""
    if len(used) == 1:
        said = (f"{_STRUCTURES[used[0]][0].upper()}{_STRUCTURES[used[0]][1:]} traced the "
                f"moving meshes on every frame of hlbvh's")
    else:
        said = "What traced the moving meshes on hlbvh's frames: " + ", ".join(
            f"{_STRUCTURES[name]} on {counts[name]} of {len(rows)}" for name in used)
    mitsuba = [_MITSUBA_MEANS[name][len(used) > 1] for name in used if name != "hlbvh"]
    if not mitsuba:
        return f"{said}. "
    return (f"{said}: {'; '.join(mitsuba)}; --moving-accel hlbvh forces our BVH, the "
            f"comparison of hlbvh itself. ")


def verdict(rows: list[dict]) -> str:
    """The paragraph the report opens with: frame time of each accelerator (median over
    the frames), the median build speedup, whether ours is within Monte Carlo noise of
    native's on every frame (or both black on every frame, which tells nothing) with the
    largest block ``|z|`` against the limit, the frames beyond it and where, and what
    traced the moving meshes on hlbvh's frames (:func:`traced_by`); then the
    figures: bit-identical pixels, the largest pixel difference, how often the camera
    rays hit the same primitive first."""
    judged = [row["noise"] for row in rows]
    image = [row["image"] for row in rows]
    ours = statistics.median(row["frame_ms"]["hlbvh"] for row in rows)
    native = statistics.median(row["frame_ms"]["native"] for row in rows)
    faster = f"{native / ours:.2f}x faster" if ours <= native else f"{ours / native:.2f}x slower"
    worst = max(rows, key=lambda row: abs(row["noise"]["largest_z"]))
    limit = f"limit {NOISE_LIMIT:g}: block means of hlbvh - native over native's own noise"
    failed = [row["frame"] for row in rows if not row["noise"]["passed"]]
    nonfinite = sum(m["nonfinite_pixels"] for m in judged)
    images = ("both accelerators' images are black on every frame (nothing lights the "
              "scene), so their agreement says nothing about hlbvh"
              if all(row.get("black") for row in rows) else
              f"within Monte Carlo noise of native's on every frame (largest block |z| "
              f"{abs(worst['noise']['largest_z']):.2f}, {limit})"
              if not failed else
              f"NOT within Monte Carlo noise of native's on {len(failed)} of {len(rows)} "
              f"frames ({', '.join(map(str, failed))}; largest block |z| "
              f"{abs(worst['noise']['largest_z']):.1f} on frame {worst['frame']}, "
              f"{worst['noise']['largest_z_block']}; {limit}"
              + (f"; {nonfinite} pixels NaN or infinite in hlbvh's alone" if nonfinite else "")
              + ")")
    identical = [100 * m["fraction_identical"] for m in image]
    overhead = {accel: statistics.median(row["motion_overhead"][accel] for row in rows)
                for accel in ACCELS}
    shutter = rows[0].get("shutter")
    costs = (
        f"Motion blur over {shutter['open']:g}..{shutter['close']:g} of a frame: hlbvh "
        f"traces each ray at its time through the moving meshes' keys, native renders the "
        f"mean of {shutter['sub_frames']} sub-frames (a rebuild each, its only way). "
        if shutter else
        f"Motion overhead (a frame "
        f"over native's render of it without a rebuild; 1.0 is a still frame): hlbvh "
        f"{overhead['hlbvh']:.2f}, native {overhead['native']:.2f}. "
        f"Median build speedup "
        f"{statistics.median(r['build_speedup'] for r in rows):.2f}x (Mitsuba's rebuild / "
        f"ours). ")
    return (
        f"A frame (build + render, median of {len(rows)}) takes {ours:.1f} ms with hlbvh "
        f"and {native:.1f} ms with native: hlbvh is {faster}. {traced_by(rows)}{costs}"
        f"Images: {images}. Pixels bit-identical to native's: "
        f"{min(identical):.1f}-{max(identical):.1f}% a frame; largest pixel difference "
        f"{max(m['max_abs_diff'] for m in image):.3g}. Camera rays hit the same primitive "
        f"first on at least {100 * min(r['hits']['fraction_agree'] for r in rows):.3f}% "
        f"of pixels.{blur_verdict(rows)}"
    )


# ---------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------


def configure(parser) -> None:
    """Options of ``hlbvh compare``."""
    parser.description = __doc__.split("\n\n")[0]
    parser.epilog = ("exit status: 0 when hlbvh's images are within Monte Carlo noise of "
                     "native's on every frame (block means of their difference, 8x8 pixels "
                     "to the whole image, against native's own noise, another seed's render), "
                     "1 when a frame is not, 2 for a user error")
    add_scene_options(parser, "out/compare/<scene>")
    parser.add_argument("--tolerance", default=repr(TOLERANCE),
                        help=f"per-channel difference under which a pixel counts in the "
                             f"report's figure 'pixels within tolerance' (default "
                             f"{TOLERANCE}); the verdict is judged by noise, not by it")
    parser.add_argument("--blur-frame", default=None, metavar="N",
                        help="render the frames still, and frame N once more with the "
                             "shutter open (--shutter, 0.5 when not given; --motion-keys, "
                             "--sub-frames), judged the same way, shown beside its still "
                             "pair (a whole compare of it in OUT/blur)")


def run(args) -> int:
    """``hlbvh compare``: see the module docstring. Returns the exit status: 0 when
    hlbvh's images are within Monte Carlo noise of native's on every frame, 1 when not."""
    settings = render_settings(args)
    tolerance = _tolerance(args.tolerance)
    # --blur-frame: the frames still, the shutter (0.5 when not given) for the blurred pair
    shutter = settings.shutter if settings.shutter_open or args.blur_frame is None \
        else BLUR_SHUTTER
    animation, source, frames = open_animation(SceneSpec.of(
        args.scene, args.frames_dir, args.triangles, args.frames, args.topology, shutter))
    settings = with_scene_integrator(args, animation, settings, "compare")
    check_seed(settings.seed, frames)
    blur = None
    if args.blur_frame is not None:
        blur = (_blur_frame(args.blur_frame, frames), replace(settings, shutter=shutter))
        settings = replace(settings, shutter=(0.0, 0.0))
    out = output_directory(out_flag(args.out, Path("out/compare") / Path(args.scene).stem))
    result = compare_animation(animation, frames, out, settings, source, tolerance,
                               progress=not args.quiet, blur=blur)
    print(f"{result['files']['html']}: frames {frames_text(frames)} of "
          f"{animation.name}, native vs hlbvh. {verdict(result['rows'])}")
    return 0 if all(row["noise"]["passed"] and row.get("blur", {}).get("passed", True)
                    for row in result["rows"]) else 1


#: The shutter of ``--blur-frame``'s pair where ``--shutter`` is not given: half a frame
#: centred on it (a 180-degree shutter).
BLUR_SHUTTER = (-0.25, 0.25)


def _blur_frame(text: str, frames) -> int:
    """``--blur-frame``: one of the frames compared."""
    try:
        frame = int(text)
    except ValueError:
        frame = None
    if frame not in list(frames):
        raise UserError(f"--blur-frame {text!r}: expected one of the frames compared "
                        f"({frames_text(frames)})")
    return frame


def _tolerance(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise UserError(f"--tolerance {text!r}: expected a finite number >= 0")
    return value
