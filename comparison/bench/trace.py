"""Trace benchmark: our traversal kernels against Mitsuba's native intersector (Embree
on the LLVM backend, OptiX on CUDA) on the same rays, in the same process.

For each scene (a displaced grid of about ``size`` triangles per entry of ``sizes``,
Cornell box, and the main job's cloth scene), three ray sets, the three kinds a path
tracer traces:

- ``coherent``: primary camera rays, one per pixel centre of the scene's sensor;
- ``incoherent``: secondary rays, one cosine-distributed bounce from each primary hit
  (spawned from Mitsuba's surface interaction, on the side the camera sees);
- ``shadow``: from each primary hit to a point sampled on the scene's emitters (to a
  point above the scene when it has none), ending there (``maxt``);

and two queries: ``closest`` (ours: :func:`hlbvh.kernels.traversal.closest_hit`;
native: ``scene.ray_intersect_preliminary(ray, coherent=...)``) and ``any``
(:func:`~hlbvh.kernels.traversal.any_hit` vs ``scene.ray_test``). Each measurement
evaluates the query's outputs and waits for the device (``dr.sync_thread``) before
the clock stops. ``cold`` is the first call in the process (tracing, and compiling
unless Dr.Jit's kernel cache on disk already holds the kernel); ``min``/``median`` are
over ``repeats`` warm calls. ``cpu`` is the process's CPU time over the same calls
(all threads, ``time.process_time``): on a machine shared with other work, wall time
also counts the time other processes hold the cores, CPU time hardly does, so
``ratio_cpu`` (from the minima) is the steadier comparison there (pass ``threads=1``
to measure one core). ``agree`` is the fraction of rays whose hit/miss and primitive
(closest) or occlusion (any) equal the native result.

Where our time goes: ``steps`` is the mean number of traversal steps (wide nodes and
triangles visited) per ray, ``p90`` and ``max`` its tail, and ``lanes`` the fraction of
the lane-steps paid for that did work: rays run in packets of the SIMD width
(consecutive rays), and a packet steps until its slowest ray is done.

Run: ``python -m hlbvh.comparison.bench.trace`` (the CLI's ``hlbvh bench trace``).
"""

from __future__ import annotations

import os
import statistics
import time

import drjit as dr
import mitsuba as mi

from hlbvh.comparison.machine import simd_isa
from hlbvh.kernels import traversal
from hlbvh.kernels.traversal import any_hit, closest_hit

#: The frame of the cloth animation traced (mid-animation: the flag is folded).
CLOTH_FRAME = 6


# ---------------------------------------------------------------------------------------
# Scenes and rays
# ---------------------------------------------------------------------------------------


def displaced_grid(triangles: int):
    """A square height field over [-1, 1]² with about ``triangles`` triangles, displaced
    by a few overlapping sine waves (hills and ripples).

    Returns:
        ``(vertices, faces)``: flat ``mi.Float`` (3·V) and ``mi.UInt32`` (3·F),
        F = 2·(n-1)² for the n×n vertex grid closest to ``triangles``.
    """
    n = max(2, round((triangles / 2) ** 0.5) + 1)
    i = dr.arange(mi.UInt32, n * n)
    ix, iy = i % n, i // n
    x = mi.Float(ix) * (2.0 / (n - 1)) - 1
    y = mi.Float(iy) * (2.0 / (n - 1)) - 1
    z = 0.15 * dr.sin(3.1 * x) * dr.cos(2.3 * y) + 0.02 * dr.sin(40 * x + 13 * y)
    vertices = dr.ravel(mi.Point3f(x, y, z))
    q = dr.arange(mi.UInt32, (n - 1) * (n - 1))
    a = (q // (n - 1)) * n + q % (n - 1)
    b, c, d = a + 1, a + n, a + n + 1
    faces = dr.ravel(mi.Vector3u(dr.concat([a, a]), dr.concat([b, d]), dr.concat([d, c])))
    return vertices, faces


def mesh_scene(vertices, faces, sensor: dict | None = None):
    """A Mitsuba scene holding one mesh with these flat vertex/face buffers (and the
    given sensor dict, if any)."""
    mesh = mi.Mesh("mesh", len(vertices) // 3, len(faces) // 3)
    params = mi.traverse(mesh)
    params["vertex_positions"] = vertices
    params["faces"] = faces
    params.update()
    scene = {"type": "scene", "mesh": mesh}
    if sensor is not None:
        scene["sensor"] = sensor
    return mi.load_dict(scene)


def _grid_sensor(resolution: int) -> dict:
    return {
        "type": "perspective",
        "fov": 45,
        "to_world": mi.ScalarTransform4f().look_at(
            origin=[0, -2.4, 1.6], target=[0, 0, 0], up=[0, 0, 1]
        ),
        "film": {"type": "hdrfilm", "width": resolution, "height": resolution},
    }


def primary_rays(scene) -> mi.Ray3f:
    """One ray through each pixel centre of the scene's first sensor."""
    sensor = scene.sensors()[0]
    w, h = sensor.film().crop_size()
    i = dr.arange(mi.UInt32, w * h)
    pos = mi.Point2f((mi.Float(i % w) + 0.5) / w, (mi.Float(i // w) + 0.5) / h)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    return mi.Ray3f(ray)


def secondary_rays(scene, primary: mi.Ray3f, seed: int = 1) -> mi.Ray3f:
    """A cosine-distributed bounce from every primary hit (misses dropped), on the side
    of the surface the primary ray came from."""
    si = scene.ray_intersect(primary, mi.RayFlags.All, True)
    rng = mi.PCG32(dr.width(si.t), seed)
    local = mi.warp.square_to_cosine_hemisphere(
        mi.Point2f(rng.next_float32(), rng.next_float32())
    )
    local.z = dr.mulsign(local.z, si.wi.z)
    ray = si.spawn_ray(si.to_world(local))
    keep = dr.compress(si.is_valid())
    return dr.gather(mi.Ray3f, ray, keep)


def shadow_rays(scene, primary: mi.Ray3f, seed: int = 2) -> mi.Ray3f:
    """From every primary hit (misses dropped) to a point sampled on the scene's
    emitters, or to a point above the scene's bounding box when it has none; ``maxt``
    ends each ray just short of its target."""
    si = scene.ray_intersect(primary, mi.RayFlags.All, True)
    keep = dr.compress(si.is_valid())
    si = dr.gather(type(si), si, keep)
    if scene.emitters():
        rng = mi.PCG32(dr.width(si.t), seed)
        ds, _ = scene.sample_emitter_direction(
            si, mi.Point2f(rng.next_float32(), rng.next_float32()), False)
        target = ds.p
    else:
        box = scene.bbox()
        target = mi.Point3f(box.center() + mi.Vector3f(0, 0, 2 * dr.max(box.extents())))
    return si.spawn_ray_to(target)


def _packet_width() -> int:
    """SIMD lanes per packet of the variant's backend (a CUDA warp: 32)."""
    if dr.backend_v(mi.Float) == dr.JitBackend.CUDA:
        return 32
    return 16 if simd_isa() == "AVX-512" else 8


def _step_profile(bvh, ray, any_hit: bool) -> dict:
    """Where a ray kind's traversal time goes: ``steps`` (mean steps per ray),
    ``steps_p90`` and ``steps_max`` (the tail, which decides what a packet pays),
    ``lanes`` (fraction of the packets' lane-steps that did work)."""
    import numpy as np

    count = traversal.steps(bvh, ray.o, ray.d, ray.maxt, any_hit=any_hit).numpy()
    if len(count) == 0:
        return {"steps": 0.0, "steps_p90": 0.0, "steps_max": 0, "lanes": 1.0}
    width = _packet_width()
    padded = np.zeros(-(-len(count) // width) * width, count.dtype)
    padded[:len(count)] = count
    paid = width * padded.reshape(-1, width).max(axis=1).sum()
    return {"steps": float(count.mean()), "steps_p90": float(np.percentile(count, 90)),
            "steps_max": int(count.max()),
            "lanes": float(count.sum() / paid) if paid else 1.0}


def _scene_triangles(scene):
    """All mesh triangles of ``scene`` in one buffer, with each triangle's shape and
    local primitive index (for comparing primitives with the native result)."""
    from hlbvh.accel.scene_geometry import collect_geometry

    g = collect_geometry(scene.shapes())
    return g.vertices, g.faces, g.prim_shape, g.prim_local


# ---------------------------------------------------------------------------------------
# Timing
# ---------------------------------------------------------------------------------------


def _run(fn) -> tuple[float, float, object]:
    """(wall ms, process CPU ms, output) of one call of ``fn``, its outputs evaluated
    and the device synced."""
    dr.sync_thread()
    start, cpu = time.perf_counter(), time.process_time()
    out = fn()
    dr.eval(out)
    dr.sync_thread()
    return 1e3 * (time.perf_counter() - start), 1e3 * (time.process_time() - cpu), out


def _timed_pair(ours, native, repeats: int):
    """Cold and warm times of two queries, alternating ours and native on every
    repeat so that both see the same machine load.

    Returns:
        ``((cold, [warm...], [warm cpu...], output), (...))`` for ours, native.
    """
    runs = {ours: [], native: []}
    cpus = {ours: [], native: []}
    outs = {}
    for _ in range(repeats + 1):
        for fn in (ours, native):
            ms, cpu, outs[fn] = _run(fn)
            runs[fn].append(ms)
            cpus[fn].append(cpu)
    return tuple((runs[fn][0], runs[fn][1:], cpus[fn][1:], outs[fn]) for fn in (ours, native))


def _measure(scene, bvh, prim_shape, prim_local, ray, kind: str, repeats: int):
    """Rows for closest and any hit of ``ray`` (of ``kind``) against ``scene``
    (native) and ``bvh``."""
    coherent = kind == "coherent"
    dr.eval(ray)
    rows = []
    rays = dr.width(ray.o)

    def ours_closest():
        t, u, v, prim, valid = closest_hit(bvh, ray.o, ray.d, ray.maxt)
        return t, u, v, prim, valid

    def native_closest():
        pi = scene.ray_intersect_preliminary(ray, coherent=coherent)
        return pi.t, pi.prim_uv, pi.prim_index, pi.shape_index

    def ours_any():
        return any_hit(bvh, ray.o, ray.d, ray.maxt)

    def native_any():
        return scene.ray_test(ray, coherent=coherent)

    for query, ours, native in (
        ("closest", ours_closest, native_closest),
        ("any", ours_any, native_any),
    ):
        (o_cold, o_warm, o_cpu, o_out), (n_cold, n_warm, n_cpu, n_out) = _timed_pair(
            ours, native, repeats)
        if query == "closest":
            _, _, _, prim, valid = o_out
            n_valid = dr.isfinite(n_out[0])
            shape = dr.gather(mi.UInt32, prim_shape, prim, valid)
            local = dr.gather(mi.UInt32, prim_local, prim, valid)
            same = (valid == n_valid) & (
                ~valid | ((shape == n_out[3]) & (local == n_out[2]))
            )
        else:
            same = mi.Bool(o_out) == n_out
        ours_min, native_min = min(o_warm), min(n_warm)
        rows.append({
            "rays": rays,
            "kind": kind,
            "query": query,
            **_step_profile(bvh, ray, any_hit=query == "any"),
            "ours_cold_ms": o_cold,
            "ours_min_ms": ours_min,
            "ours_median_ms": statistics.median(o_warm),
            "native_cold_ms": n_cold,
            "native_min_ms": native_min,
            "native_median_ms": statistics.median(n_warm),
            "ours_mrays": rays / ours_min / 1e3,
            "native_mrays": rays / native_min / 1e3,
            "ratio": native_min / ours_min,
            "ratio_median": statistics.median(n_warm) / statistics.median(o_warm),
            "ours_cpu_ms": min(o_cpu),
            "native_cpu_ms": min(n_cpu),
            "ratio_cpu": min(n_cpu) / min(o_cpu),
            "agree": dr.count(same)[0] / rays,
        })
    return rows


# ---------------------------------------------------------------------------------------
# Benchmark
# ---------------------------------------------------------------------------------------


def cloth_scene(resolution: int, frame: int = CLOTH_FRAME):
    """The README's main-job scene (``hlbvh.scenes`` "cloth": a 200k-triangle flag on a
    pole over a ground quad) at ``frame``, square film of ``resolution`` pixels."""
    from hlbvh import scenes

    animation = scenes.get("cloth")
    scene = mi.load_dict(animation.scene_dict(resolution=(resolution, resolution), spp=1))
    scenes.apply_frame(scene, None, animation.frame(frame))
    return scene


def run(sizes=(1_000_000,), repeats: int = 5, resolution: int = 512,
        cornell: bool = True, build=None, threads: int | None = None,
        cloth: bool = True, **options) -> list[dict]:
    """Measure traversal speed, ours vs native, on the same rays.

    Args:
        sizes: triangle counts of the displaced grids to trace.
        repeats: warm runs per measurement (after one cold run).
        resolution: the camera's width and height in pixels (rays = resolution²).
        cornell: also trace Cornell box (``mi.cornell_box()``).
        cloth: also trace the main job's cloth scene (:func:`cloth_scene`).
        build: ``build(vertices, faces, **options) -> BVH``; ``hlbvh.build`` when None.
        threads: Dr.Jit's worker threads while tracing (``None``: as they are).
        options: builder options (``builder="hlbvh"``, ``leaf_size``, ...).
    Returns:
        One dict per (scene, ray kind, query): ``scene``, ``triangles``, ``rays``,
        ``kind`` (``coherent``, ``incoherent``, ``shadow``), ``query``, ``steps``,
        ``steps_p90``, ``steps_max``, ``lanes`` (:func:`_step_profile`),
        ``ours_/native_`` ``cold_ms``/``min_ms``/``median_ms``/``cpu_ms`` (the least
        process CPU time of the warm runs), ``ours_mrays``, ``native_mrays`` (from the
        minimum), ``ratio`` (ours/native throughput, from the
        minima), ``ratio_median`` (from the medians), ``ratio_cpu`` (from the CPU
        times), ``agree``, ``build_ms``.
    Raises:
        ValueError: ``threads`` below 1.
    """
    if threads is not None and threads < 1:
        raise ValueError(f"threads={threads}: expected at least 1 (or None)")
    if build is None:
        from hlbvh import build
    scenes = []
    for size in sizes:
        vertices, faces = displaced_grid(size)
        scenes.append((f"grid {size // 1000}k", mesh_scene(vertices, faces,
                                                            _grid_sensor(resolution))))
    if cornell:
        box = mi.cornell_box()
        box["sensor"]["film"]["width"] = box["sensor"]["film"]["height"] = resolution
        scenes.append(("cornell box", mi.load_dict(box)))
    if cloth:
        scenes.append(("cloth", cloth_scene(resolution)))

    rows = []
    for name, scene in scenes:
        vertices, faces, prim_shape, prim_local = _scene_triangles(scene)
        start = time.perf_counter()
        bvh = build(vertices, faces, **options)
        build_ms = 1e3 * (time.perf_counter() - start)
        primary = primary_rays(scene)
        kinds = {"coherent": primary, "incoherent": secondary_rays(scene, primary),
                 "shadow": shadow_rays(scene, primary)}
        default_threads = dr.thread_count()
        try:
            if threads is not None:
                dr.set_thread_count(threads)
            for kind, ray in kinds.items():
                for row in _measure(scene, bvh, prim_shape, prim_local, ray, kind, repeats):
                    rows.append({"scene": name, "triangles": len(faces) // 3,
                                 "build_ms": build_ms, **row})
        finally:
            dr.set_thread_count(default_threads)
    return rows


def format_table(rows: list[dict]) -> str:
    """The rows as a fixed-width text table."""
    head = (f"{'scene':<12} {'tris':>8} {'rays':>8} {'rays kind':<10} {'query':<7} "
            f"{'ours Mr/s':>9} {'Embree':>8} {'ratio':>6} {'(med)':>6} {'(cpu)':>6} "
            f"{'ours min/med/cold ms':>22} {'native min/med/cold ms':>24} {'agree':>9} "
            f"{'steps':>6} {'p90':>4} {'max':>5} {'lanes':>6}")
    lines = [head, "-" * len(head)]
    for r in rows:
        ours = f"{r['ours_min_ms']:.1f}/{r['ours_median_ms']:.1f}/{r['ours_cold_ms']:.0f}"
        nat = (f"{r['native_min_ms']:.1f}/{r['native_median_ms']:.1f}/"
               f"{r['native_cold_ms']:.0f}")
        lines.append(
            f"{r['scene']:<12} {r['triangles']:>8} {r['rays']:>8} {r['kind']:<10} "
            f"{r['query']:<7} {r['ours_mrays']:>9.2f} {r['native_mrays']:>8.2f} "
            f"{r['ratio']:>6.2f} {r['ratio_median']:>6.2f} {r['ratio_cpu']:>6.2f} "
            f"{ours:>22} {nat:>24} "
            f"{100 * r['agree']:>8.4f}% {r['steps']:>6.1f} {r['steps_p90']:>4.0f} "
            f"{r['steps_max']:>5} {100 * r['lanes']:>5.0f}%"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    """Print the trace benchmark table (``hlbvh bench trace``)."""
    import argparse

    parser = argparse.ArgumentParser(prog="hlbvh bench trace", description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1_000_000],
                        help="triangle counts of the displaced grids (default 1000000)")
    parser.add_argument("--repeats", type=int, default=5, help="warm runs (default 5)")
    parser.add_argument("--resolution", type=int, default=512,
                        help="camera width and height in pixels (default 512)")
    parser.add_argument("--no-cornell", action="store_true", help="skip Cornell box")
    parser.add_argument("--no-cloth", action="store_true",
                        help="skip the main job's cloth scene")
    parser.add_argument("--builder", default="hlbvh", help="hlbvh | lbvh | sah")
    parser.add_argument("--threads", type=int, default=None,
                        help="Dr.Jit worker threads while tracing (default: as they are)")
    args = parser.parse_args(argv)
    rows = run(sizes=args.sizes, repeats=args.repeats, resolution=args.resolution,
               cornell=not args.no_cornell, cloth=not args.no_cloth, builder=args.builder,
               threads=args.threads)
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    threads = dr.thread_count() if args.threads is None else args.threads
    print(f"hlbvh trace benchmark ({mi.variant()}, builder={args.builder}, "
          f"{threads} threads, load average {load})")
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
