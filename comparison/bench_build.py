"""``hlbvh bench build``: our builders against Mitsuba's native rebuild, side by side.

For each mesh (a displaced grid and a random triangle soup) and size, in one process:

- our build per builder: cold (the first build of the process, kernels compiled or
  loaded from Dr.Jit's disk cache, compile seconds from the kernel history), warm (min
  and median over repeats), per-stage warm times, kernel launches, SAH cost;
- our build seeded with the previous order (temporal coherence) and a refit;
- Mitsuba's native rebuild: ``params.update()`` after new vertex positions (genuinely
  new arrays every time, DRJIT_NOTES pitfall 9), Embree at high quality;
- the ratio native / ours (higher is better for us).
"""

from __future__ import annotations

import statistics
import time

import drjit as dr
import mitsuba as mi

import hlbvh
from hlbvh.comparison.bench_trace import displaced_grid, mesh_scene


def random_soup(triangles: int, seed: int = 7, size: float = 0.02):
    """``triangles`` random triangles of about ``size`` scattered in [-1, 1]³, as flat
    ``mi.Float`` vertices (3·3·F) and ``mi.UInt32`` faces (3·F)."""
    rng = mi.PCG32(triangles, seed)
    centre = mi.Point3f(*(rng.next_float32() * 2 - 1 for _ in range(3)))
    corners = []
    for _ in range(3):
        corners.append(centre + size * (mi.Vector3f(*(rng.next_float32() for _ in range(3))) - 0.5))
    vertices = dr.ravel(mi.Point3f(*(dr.concat([c[k] for c in corners]) for k in range(3))))
    # Vertex v of triangle t sits at index v·F + t.
    t = dr.arange(mi.UInt32, triangles)
    faces = dr.ravel(mi.Vector3u(t, t + triangles, t + 2 * triangles))
    return vertices, faces


MESHES = {"grid": displaced_grid, "soup": random_soup}


def _timed(fn, repeats: int):
    """(cold ms, [warm ms...], last output) of ``fn``, outputs evaluated, device synced."""
    times, out = [], None
    for _ in range(repeats + 1):
        dr.sync_thread()
        start = time.perf_counter()
        out = fn()
        dr.sync_thread()
        times.append(1e3 * (time.perf_counter() - start))
    return times[0], times[1:], out


def _stats_of(fn, repeats: int):
    """(cold ms, warm min ms, warm median ms, launches of one warm call, compile s of the
    cold call, the last result)."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    cold, warm, out = _timed(fn, repeats)
    history = dr.kernel_history()
    per_call = len(history) // (repeats + 1)
    compile_s = 0.0
    for k in history:
        compile_s += (k.get("codegen_time", 0) + k.get("backend_time", 0)) / 1e3
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    return cold, min(warm), statistics.median(warm), per_call, compile_s, out


def _native_rebuild(vertices, faces, repeats: int):
    """(cold, warm min, warm median) ms of Mitsuba's rebuild after new positions."""
    scene = mesh_scene(vertices, faces)
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("vertex_positions"))
    variants = [vertices * (1 + 1e-6 * k) for k in range(repeats + 1)]
    dr.eval(variants)
    times = []
    for v in variants:
        params[key] = v
        dr.sync_thread()
        t0 = time.perf_counter()
        params.update()
        dr.sync_thread()
        times.append((time.perf_counter() - t0) * 1e3)
    return times[0], min(times[1:]), statistics.median(times[1:])


def run(sizes=(100_000, 1_000_000), meshes=("grid", "soup"), builders=("hlbvh", "lbvh", "sah"),
        repeats: int = 5, sah_max: int = 1_000_000) -> list[dict]:
    """Measure every (mesh, size, builder); one dict per row (see module docstring)."""
    rows = []
    for mesh in meshes:
        for size in sizes:
            vertices, faces = MESHES[mesh](size)
            dr.eval(vertices, faces)
            native = _native_rebuild(vertices, faces, repeats)
            moved = vertices * 1.0001
            dr.eval(moved)
            for builder in builders:
                if builder == "sah" and size > sah_max:
                    continue
                cold, wmin, wmed, launches, compile_s, bvh = _stats_of(
                    lambda: hlbvh.build(vertices, faces, builder=builder), repeats
                )
                stages = dict(bvh.stats.stage_ms)
                _, seeded_min, _, _, _, seeded = _stats_of(
                    lambda: hlbvh.build(moved, faces, builder=builder, previous=bvh), repeats
                )
                _, refit_min, _, _, _, _ = _stats_of(lambda: bvh.refit(moved), repeats)
                rows.append({
                    "mesh": mesh, "triangles": len(faces) // 3, "builder": builder,
                    "cold_ms": cold, "warm_min_ms": wmin, "warm_median_ms": wmed,
                    "seeded_min_ms": seeded_min, "refit_min_ms": refit_min,
                    "launches": launches, "compile_s": compile_s,
                    "stage_ms": stages, "sah_cost": bvh.stats.sah_cost,
                    "csd_runs": bvh.stats.csd_runs, "csd_runs_seeded": seeded.stats.csd_runs,
                    "native_cold_ms": native[0], "native_min_ms": native[1],
                    "native_median_ms": native[2],
                    "native_over_ours": native[1] / wmin,
                })
    return rows


def format_table(rows: list[dict]) -> str:
    head = (
        f"{'mesh':5} {'tris':>8} {'builder':7} {'cold':>8} {'warm':>8} {'median':>8} "
        f"{'seeded':>8} {'refit':>7} {'native':>8} {'native/ours':>11} {'SAH':>7} "
        f"{'launch':>6}  stages (warm ms)"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        stages = " ".join(f"{k}={v:.1f}" for k, v in r["stage_ms"].items())
        lines.append(
            f"{r['mesh']:5} {r['triangles']:>8} {r['builder']:7} {r['cold_ms']:8.1f} "
            f"{r['warm_min_ms']:8.1f} {r['warm_median_ms']:8.1f} {r['seeded_min_ms']:8.1f} "
            f"{r['refit_min_ms']:7.1f} {r['native_min_ms']:8.1f} {r['native_over_ours']:10.2f}x "
            f"{r['sah_cost']:7.2f} {r['launches']:6}  {stages}"
        )
    lines.append("times in ms; warm = min over repeats; native = Mitsuba params.update() "
                 f"(Embree); variant {mi.variant()}")
    return "\n".join(lines)
