"""``hlbvh render``: an animated scene rendered frame by frame to EXR and PNG, with
per-frame statistics; interrupted renders resume where they stopped.

Usage::

    hlbvh render cloth --frames 0:24 --resolution 640x360 --spp 16 --out out/cloth
    hlbvh render fracture --triangles 1000000 --frames 8 --accel native
    hlbvh render scene.xml --frames-dir frames/ --integrator aov --out out/mine

``SCENE`` is a procedural scene (``hlbvh.scenes.names()``: cloth, twist, fracture,
rigid, soup, world, flock; ``--triangles`` sets its size, ``NAME:KEY=VALUE,...`` its
own options, e.g. ``flock:birds=200``) or a Mitsuba XML file whose animated meshes
are read from ``--frames-dir`` (see :class:`hlbvh.scenes.SequenceScene`).
``--frames A:B`` renders frames ``A .. B-1``, ``--frames A:B:STEP`` every ``STEP``-th
of them (a preview of a long shot; ``A::STEP`` to the last frame), ``--frames N`` the
first ``N``; the default is every frame of the scene (60 for procedural scenes, whose
motion goes on past that: any ``B`` is allowed there). A range the text alone shows
to be wrong (empty, a step below 1) is refused before the scene is opened.
``--resolution W`` means ``W×W``.

Each frame
----------
1. its geometry is written into the loaded scene with :func:`hlbvh.scenes.apply_frame`,
   whose ``params.update()`` makes Mitsuba rebuild its own accelerator (Embree on the
   LLVM backend) whatever ``--accel`` says;
2. with ``--accel hlbvh`` our :class:`hlbvh.SceneAccel` follows (built, rebuilt or
   refit, as its ``update`` policy decides), timed on its own;
3. ``mi.render(scene, seed=seed + frame)``: the same seed for a frame whatever the
   accelerator, so renders of both are comparable pixel by pixel (box filter);
4. ``frame_NNNN.exr`` (linear float32, every film channel: R, G, B, and the AOVs of
   ``--integrator aov``) and ``frame_NNNN.png`` (8-bit sRGB of R, G, B) are written
   through :mod:`hlbvh.render.images`, each to a temporary file renamed into place;
5. its row (:data:`hlbvh.render.frame.STATS_FIELDS`) is added to ``stats.csv`` and ``stats.json``, both
   rewritten whole and atomically.

The integrator is the scene's own when it names ``path`` (run as ``hlbvh_path``, which
mirrors it), ``hlbvh_path`` or ``hlbvh_aov``, with its properties (``accel``,
``max_depth``, the builder's); ``--integrator``, ``--accel``, ``--max-depth``, the builder
options and ``--update`` each replace what the scene says, and one line on stderr says
what they override. A scene with another integrator is refused unless ``--integrator``
replaces it; a scene without one, and the procedural scenes, take ``path`` with
``--max-depth`` 8 and ``hlbvh``.

A frame is complete when its EXR and its PNG decode whole, at the film's size, and
its row is in ``stats.json``. Ctrl-C stops after the frame in flight (written whole:
Mitsuba's own handler, installed during ``mi.render``, only marks the integrator
cancelled, and the loop stops on it), exit status 130. Running the same
command again renders only the frames of the range that are not complete (after an
interrupt: from the one that was being rendered; a truncated or emptied file: that
frame again), rewrites ``stats.csv`` from ``stats.json`` (a kill between the two writes
is healed), and removes the temporary files a killed process left. A write that fails
(a full disk) leaves no partial file and stops with one line; the frames before it stay
complete. ``stats.json`` records the settings (scene, size, the resolution and spp the
scene renders at, integrator and its properties, accelerator, builder options, seed,
and for an XML scene a SHA-256 of the file, its includes and every file a ``filename``
property names); rendering into a directory that holds frames of other settings, or
of the scene before an edit, is refused, so one directory never mixes two renders.
One render writes into a directory at a time: it holds the directory's lock file
(:data:`hlbvh.render.output.LOCK_NAME`, naming its pid and host); a second is refused, and a lock left by a
process that died is taken over. Frame ranges are iterated, never listed, and the seed
of the last frame, the film's size and the samples per frame are checked against what
Dr.Jit and the machine's memory hold before any frame is rendered.

Statistics (``stats.json``: ``{"settings": {...}, "frames": [row, ...]}``)
--------------------------------------------------------------------------
``frame``, ``accel``, ``triangles`` (of every mesh at that frame), ``seed``;
``geometry_ms`` (reading or generating the frame and writing it into the scene),
``mitsuba_update_ms`` (Mitsuba's ``params.update()``: its own accelerator's rebuild),
``build_ms`` (``hlbvh``: our accelerator's update; ``native``: ``params.update()``,
the native rebuild), ``render_ms``; ``sah_cost`` of our BVH (C_trav = C_isect = 1,
normalised by the root's area; empty for ``native``, Embree does not report one);
``decision``: ``build`` (first frame), ``rebuild``, ``refit``, ``kept`` (nothing
moved), or ``native`` (Mitsuba rebuilt its accelerator). Times are wall-clock
milliseconds with the device synchronised; the first frame of a process includes
compiling kernels that Dr.Jit's disk cache did not hold.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from hlbvh.cli.options import add_scene_options, out_flag, scene_render_settings, shutter_settings
from hlbvh.errors import UserError, int_flag
from hlbvh.render.animation import render_animation
from hlbvh.render.settings import frames_text
from hlbvh.render.source import SceneSpec, open_animation, usd_stage


def configure(parser) -> None:
    """Options of ``hlbvh render`` (values are checked in :func:`run`, so every
    mistake is reported in one line)."""
    parser.description = __doc__.split("\n\n")[0]
    add_scene_options(parser, "out/render/<scene>-<accel>")
    parser.add_argument("--integrator",
                        help="path, direct, volpath (hlbvh_path, hlbvh_direct, "
                             "hlbvh_volpath) or aov (hlbvh_aov); default: the scene's own "
                             "(Mitsuba's path, direct or volpath run as ours, or one of "
                             "ours, with its properties), else path")
    parser.add_argument("--accel", help="hlbvh or native; default: the scene's integrator's, "
                                        "else hlbvh")
    parser.add_argument("--cluster", help="local:N: render on a Dask LocalCluster of N worker "
                                          "processes on this machine")
    parser.add_argument("--scheduler", help="ADDRESS (tcp://host:8786) of a running Dask "
                                            "scheduler whose workers see --out and the scene")
    parser.add_argument("--chunk-size", help="frames per task with --cluster/--scheduler "
                                             "(default: at least two chunks per worker, at "
                                             "most 16 frames)")


def run(args) -> int:
    """``hlbvh render``: see the module docstring. Returns the exit status (0)."""
    shutter = shutter_settings(args).get("shutter", (0.0, 0.0))  # a USD stage's skinning span
    spec = SceneSpec.of(args.scene, args.frames_dir, args.triangles, args.frames, args.topology,
                        shutter)
    animation, source, frames = open_animation(spec)
    settings, overrides = scene_render_settings(args, animation, args.scene)
    if overrides is not None:
        print(f"hlbvh render: {overrides}", file=sys.stderr)
    out = out_flag(args.out, Path("out/render") / f"{Path(args.scene).stem}-{settings.accel}")
    if args.cluster is None and args.scheduler is None:
        if args.chunk_size is not None:
            raise UserError("--chunk-size cuts the frames of --cluster or --scheduler runs")
        rows, rendered = render_animation(animation, frames, out, settings, source,
                                          progress=not args.quiet)
    else:
        try:
            from hlbvh.render import cluster
        except ModuleNotFoundError as error:
            raise UserError(f"--cluster and --scheduler need Dask's distributed ({error}): "
                            f"pip install 'hlbvh[cluster]'") from None
        chunk = None if args.chunk_size is None else int_flag("--chunk-size", args.chunk_size, 1)
        whole = SceneSpec.of(args.scene, args.frames_dir, args.triangles, frames, args.topology,
                             shutter)
        rows, rendered = cluster.render_on_cluster(
            animation, whole.absolute(), frames, out, settings, source, cluster=args.cluster,
            scheduler=args.scheduler, chunk_size=chunk, progress=not args.quiet)
    ours = [row for row in rows if row["frame"] in frames]
    print(f"{out}: frames {frames_text(frames)} of {_scene_name(args.scene, animation)} with "
          f"{settings.accel}{_shutter_text(settings)}: {len(rendered)} rendered, "
          f"{len(frames) - len(rendered)} already complete; "
          f"median build {_median(ours, 'build_ms'):.1f} ms, render "
          f"{_median(ours, 'render_ms'):.1f} ms; statistics in {out / 'stats.csv'}")
    return 0


def _shutter_text(settings) -> str:
    """What the summary says of an open shutter: its frames, and what traced the
    moving meshes through it."""
    if not settings.shutter_open:
        return ""
    open_, close = settings.shutter
    how = ("moving meshes traced by our BVH at each ray's time; Mitsuba's structures "
           "have one pose" if settings.accel == "hlbvh" else
           f"each frame the mean of {settings.sub_frames} sub-frames, a rebuild each")
    return f", shutter {open_:g}..{close:g} of a frame ({how})"


def _scene_name(scene: str, animation) -> str:
    """What the summary calls the scene: a USD stage's or an XML scene's file name
    (the animation's own name is only its kind, ``usd`` or ``sequence``), else the
    procedural scene's name."""
    stage = usd_stage(scene, True)
    if stage is not None:
        return stage[0].name
    return Path(scene).name if Path(scene).suffix.lower() == ".xml" else animation.name


def _median(rows: list[dict], key: str) -> float:
    values = [row[key] for row in rows if row.get(key) is not None]
    return float(np.median(values)) if values else float("nan")
