"""The README's numbers, regenerated: ``hlbvh bench`` (build, trace, frame) at modest
sizes and an ``hlbvh sweep``, written to ``docs/`` with the machine they ran on.

Run (a few minutes on two cores; run it on an otherwise idle machine)::

    .venv/bin/python -m hlbvh.comparison.readme_figures [--out docs]

It writes:

- ``docs/bench.md``: the machine (CPU model from ``/proc/cpuinfo``, cores, Dr.Jit's
  threads, Dr.Jit, Mitsuba and Python versions, the variant, the load average before and
  after), the command, then the tables of ``hlbvh bench build``, ``trace`` and
  ``frame`` as those commands print them, and the sweep's table and verdict;
- ``docs/bench.json``: the same rows for machines;
- ``docs/sweep.png``: the sweep's build time against SAH cost, the Pareto front marked;
  ``docs/sweep_frame_vs_spp.png``: its frame time against spp, crossovers marked.

The sizes are the module's ``SIZES`` (every knob has an option, see ``--help``); the
sweep's full report goes to a temporary directory and only its plots and rows are kept.
``--replot`` draws the two plots again from ``docs/bench.json`` without measuring.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import sys
import tempfile
from pathlib import Path

import drjit as dr
import mitsuba as mi

from hlbvh.comparison import sweep
from hlbvh.comparison.bench import (build as bench_build, frame as bench_frame,
                                    trace as bench_trace)
from hlbvh.comparison.machine import cpu_model
from hlbvh.comparison.tables import flatten, markdown_table, read_results, to_json
from hlbvh.render.images import atomic_output
from hlbvh.render.settings import RenderSettings
from hlbvh.render.source import SceneSpec, open_animation

#: What the README's figures are measured on (each overridable on the command line).
SIZES = {
    "build_sizes": [100_000, 1_000_000],
    "sah_max": 100_000,  # the "sah" builder only up to this size (it is the slow one)
    "trace_sizes": [1_000_000],
    "frame_sizes": [200_000],
    "frame_scenes": ["cloth", "fracture"],
    # The scene users have, at its own size (0: left out): a flag over a 1M landscape.
    "world_triangles": 1_100_000,
    "sweep_scene": "cloth",
    "sweep_triangles": 200_000,
    # A few settings that span the trade, so the plots stay readable (``all``: the grid).
    "sweep_settings": "hlbvh,lbvh,sah,axis,leaf8,refit,auto,static_hlbvh",
    "resolution": 256,
    "repeats": 3,
    "spp": 4,
    "spp_curve": [1, 4, 16],
    "frames": "0:4",
}

#: Columns of the sweep table in ``bench.md`` (all of them are in ``bench.json``).
_SWEEP_COLUMNS = ("setting", "build_ms", "sah_cost", "mrays_primary", "mrays_secondary",
                  "render_ms", "frame_ms", "image.max_abs_diff",
                  "image.fraction_within_tolerance")


def machine() -> dict:
    """What the numbers were measured on: CPU model, cores, Dr.Jit's threads, versions,
    variant, load average now."""
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "drjit_threads": dr.thread_count(),
        "drjit": dr.__version__,
        "mitsuba": mi.__version__,
        "python": platform.python_version(),
        "variant": mi.variant(),
        "load_average": [round(x, 2) for x in os.getloadavg()],
    }


def measure(sizes: dict, progress: bool = True) -> dict:
    """Run the three benchmarks and the sweep with ``sizes`` (keys of :data:`SIZES`).

    Returns:
        ``{"machine_before", "build", "trace", "frame", "sweep", "sweep_plots",
        "verdict", "machine_after"}``; the plots in a temporary directory.
    """
    log = (lambda text: print(text, file=sys.stderr, flush=True)) if progress else (lambda text: None)
    results = {"machine_before": machine()}
    log("readme_figures: bench build")
    results["build"] = bench_build.run(sizes=sizes["build_sizes"], repeats=sizes["repeats"],
                                       sah_max=sizes["sah_max"])
    log("readme_figures: bench trace")
    results["trace"] = bench_trace.run(sizes=sizes["trace_sizes"], repeats=sizes["repeats"],
                                       resolution=sizes["resolution"])
    log("readme_figures: bench frame")
    frame = dict(repeats=sizes["repeats"], resolution=sizes["resolution"],
                 spps=sizes["spp_curve"], drift_frames=20)
    results["frame"] = (bench_frame.run(scenes=["world"], sizes=[sizes["world_triangles"]],
                                        **frame) if sizes["world_triangles"] else [])
    results["frame"] += bench_frame.run(scenes=sizes["frame_scenes"],
                                        sizes=sizes["frame_sizes"], **frame)
    log("readme_figures: sweep")
    animation, _, frames = open_animation(SceneSpec(
        sizes["sweep_scene"], triangles=str(sizes["sweep_triangles"]), frames=sizes["frames"]))
    base = RenderSettings(resolution=(sizes["resolution"], sizes["resolution"]),
                          spp=sizes["spp"])
    chosen = None if sizes["sweep_settings"] == "all" else sizes["sweep_settings"]
    rows = sweep.sweep(animation, frames, sweep.parse_settings(chosen), base, sizes["spp"],
                       sizes["spp_curve"], progress=progress)
    recorded = {"scene_name": animation.name, "triangles": animation.triangles,
                "resolution": sizes["resolution"], "spp": sizes["spp"],
                "frames": sizes["frames"], "cpu": results["machine_before"]["cpu"],
                "cores": results["machine_before"]["cores"]}
    plots_dir = Path(tempfile.mkdtemp(prefix="hlbvh-readme-"))
    written = sweep.write_sweep(plots_dir, rows, recorded, sizes["spp"], sizes["spp_curve"])
    results["sweep"] = [flatten(row) for row in rows]
    results["sweep_plots"] = written["plots"]
    results["verdict"] = sweep.verdict(written, animation.name, sizes["spp"])
    results["machine_after"] = machine()
    return results


def write(out_dir, results: dict, sizes: dict, command: str) -> dict[str, Path]:
    """Write ``bench.md``, ``bench.json``, ``sweep.png`` and ``sweep_frame_vs_spp.png``
    into ``out_dir`` (atomically, each file whole)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    before, after = results["machine_before"], results["machine_after"]
    day = datetime.date.today().isoformat()
    lines = [
        "# Benchmarks",
        "",
        f"Measured on {day} with `{command}` (regenerate the same way; the README shows "
        "these tables).",
        "",
        f"- CPU: {before['cpu']}, {before['cores']} cores, Dr.Jit threads: "
        f"{before['drjit_threads']}",
        f"- Dr.Jit {before['drjit']}, Mitsuba {before['mitsuba']} ({before['variant']}), "
        f"Python {before['python']}",
        f"- load average (1, 5, 15 min) before: {_load(before)}; after: {_load(after)}. Every "
        "ratio is measured side by side in one process, so both sides see the same load.",
        "",
        f"## Build (`hlbvh bench build --sizes {_join(sizes['build_sizes'])} "
        f"--repeats {sizes['repeats']}`; builder sah only up to {sizes['sah_max']} triangles)",
        "",
        "```",
        bench_build.format_table(results["build"]),
        "```",
        "",
        f"## Trace (`hlbvh bench trace --sizes {_join(sizes['trace_sizes'])} "
        f"--resolution {sizes['resolution']} --repeats {sizes['repeats']}`)",
        "",
        "```",
        bench_trace.format_table(results["trace"]),
        "```",
        "",
        f"## Frame (`python -m hlbvh.comparison.bench.frame --scenes "
        f"{','.join(sizes['frame_scenes'])} --sizes {_join(sizes['frame_sizes'])} "
        f"--resolution {sizes['resolution']} --spp {_join(sizes['spp_curve'])} "
        f"--repeats {sizes['repeats']} --drift-frames 20`"
        + (f", and `--scenes world --sizes {sizes['world_triangles']}` with the same options"
           if sizes["world_triangles"] else "") + ")",
        "",
        "```",
        bench_frame.format_table(results["frame"]),
        "```",
        "",
        f"## Sweep (`hlbvh sweep {sizes['sweep_scene']} --triangles "
        f"{sizes['sweep_triangles']} --resolution {sizes['resolution']} --spp {sizes['spp']} "
        f"--spp-curve {_join(sizes['spp_curve'])} --frames {sizes['frames']}"
        + ("" if sizes["sweep_settings"] == "all" else f" --settings {sizes['sweep_settings']}")
        + "`)",
        "",
        markdown_table(results["sweep"], _SWEEP_COLUMNS),
        "",
        f"**{results['verdict'][0].upper()}{results['verdict'][1:]}.**",
        "",
        "![build time vs SAH cost](sweep.png)",
        "",
        "![frame time vs spp](sweep_frame_vs_spp.png)",
        "",
    ]
    files = {"md": out / "bench.md", "json": out / "bench.json",
             "sweep": out / "sweep.png", "frame_vs_spp": out / "sweep_frame_vs_spp.png"}
    with atomic_output(files["md"]) as temporary:
        temporary.write_text("\n".join(lines), encoding="utf-8")
    document = {key: value for key, value in results.items() if key != "sweep_plots"}
    with atomic_output(files["json"]) as temporary:
        temporary.write_text(json.dumps(to_json(document), indent=1, allow_nan=False) + "\n")
    for key, plot in zip(("sweep", "frame_vs_spp"), results["sweep_plots"]):
        with atomic_output(files[key]) as temporary:
            shutil.copyfile(plot, temporary)
    return files


def replot(out_dir, bench_json) -> list[Path]:
    """Draw ``sweep.png`` and ``sweep_frame_vs_spp.png`` again from the sweep rows and
    the machine recorded in ``bench_json`` (no measurement: for a change of the plots
    alone). Returns the two plots."""
    document = read_results(bench_json)
    rows, before = document["sweep"], document["machine_before"]
    spp = sorted(int(key[len("frame_ms_spp"):]) for key in rows[0] if key.startswith("frame_ms_spp"))
    recorded = {"scene_name": SIZES["sweep_scene"], "cpu": before["cpu"], "cores": before["cores"]}
    with tempfile.TemporaryDirectory(prefix="hlbvh-readme-") as where:
        written = sweep.write_sweep(where, rows, recorded, spp[0], spp)
        files = [Path(out_dir) / "sweep.png", Path(out_dir) / "sweep_frame_vs_spp.png"]
        for plot, target in zip(written["plots"], files):
            with atomic_output(target) as temporary:
                shutil.copyfile(plot, temporary)
    return files


def _load(record: dict) -> str:
    return ", ".join(f"{x:.1f}" for x in record["load_average"])


def _join(values) -> str:
    return ",".join(str(v) for v in values)


def main(argv=None) -> int:
    """``python -m hlbvh.comparison.readme_figures``: measure and write ``docs/``."""
    parser = argparse.ArgumentParser(prog="python -m hlbvh.comparison.readme_figures",
                                     description=__doc__.split("\n\n")[0])
    ints = lambda text: [int(v) for v in text.split(",")]  # noqa: E731
    parser.add_argument("--out", default="docs", help="output directory (default docs)")
    for key, value in SIZES.items():
        kind = ints if isinstance(value, list) and isinstance(value[0], int) else (
            (lambda text: text.split(",")) if isinstance(value, list) else type(value))
        parser.add_argument(f"--{key.replace('_', '-')}", dest=key, type=kind, default=value,
                            help=f"default {value}")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    parser.add_argument("--replot", action="store_true",
                        help="only draw the two plots again from OUT/bench.json (no measurement)")
    args = parser.parse_args(argv)
    if args.replot:
        files = replot(args.out, Path(args.out) / "bench.json")
        print(f"{files[0]}, {files[1]}: drawn from {Path(args.out) / 'bench.json'}")
        return 0
    sizes = {key: getattr(args, key) for key in SIZES}
    given = " ".join(argv if argv is not None else sys.argv[1:])
    command = f".venv/bin/python -m hlbvh.comparison.readme_figures {given}".strip()
    results = measure(sizes, progress=not args.quiet)
    files = write(args.out, results, sizes, command)
    print(f"{files['md']}: {results['verdict']}; plots {files['sweep']}, "
          f"{files['frame_vs_spp']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
