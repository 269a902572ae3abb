"""Keyed-tree benchmark (motion blur of a deforming mesh, :mod:`hlbvh.kernels.keyed`):
traversal of a keyed tree against the still tree on the same rays, and what keying costs.

The mesh is ``trace``'s displaced grid (about ``size`` triangles) under a
travelling wave: key ``k`` of ``S`` adds ``amplitude · sin(6x + 2π·phase·(k/S - 1/2))``
to z (half a wave over the shutter), so every vertex moves. The rays are camera rays through every pixel centre of a
``resolution``² view of the grid (coherent), each at a uniform random time in the
shutter, as Mitsuba's sensors draw them.

Rows (each traced with closest hit, and any hit on the same rays):

- ``still``: the tree built over the mid-shutter pose, traced without time (today's
  kernel);
- ``keyed S=1 equal``: that tree keyed with two equal keys (the mid pose): the same
  geometry as ``still``, so the difference is the interpolation's price alone;
- ``keyed S=1`` / ``keyed S=4``: keyed over the moving keys, built over the
  mid-shutter pose; ``keyed S=4 (built at key 0)``: the same keys, the tree built over
  key 0 instead (which pose to build).

Times are minima over ``repeats`` warm calls, the rows alternating on every repeat so
that all see the same load; wall time, and the process's CPU time (all threads), which
on a machine shared with other work counts the cores' time this process held and is
the steadier comparison there; ``steps`` the mean traversal steps per ray. ``keying
ms/key`` is :func:`~hlbvh.kernels.keyed.keyed_tree`'s time over its key count (a refit per key
and the copy into the keyed layout), beside ``BVH.refit``'s for one pose; ``MB/key`` the
slots of one key.

**Topology A/B** (``--topology-ab SCENE``, :func:`topology_ab`): a procedural scene's
moving meshes keyed over a wide shutter as a blurred frame keys them, the keyed tree
built over the mid-shutter pose and over each triangle's box over the shutter
(:func:`hlbvh.kernels.keyed.build_keyed`'s ``"mid"`` and ``"union"``), each tree's SAH
over the shutter beside its closest- and any-hit time on the same rays (the scene's
camera rays through every pixel, then a cosine bounce from each primary hit, each at a
uniform random time), the trees taking turns on every repeat: which topology traces
faster, and whether the SAH over the shutter says so (docs/decisions.md#keyed-topology).

Run: ``python -m hlbvh.comparison.bench.keyed [--size N] [--resolution R] [--repeats K]``,
or ``python -m hlbvh.comparison.bench.keyed --topology-ab cloth [--shutter 1]
[--triangles N] [--resolution WxH] [--motion-keys S]``.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import drjit as dr
import mitsuba as mi

import hlbvh
from hlbvh import scenes
from hlbvh.comparison.bench.trace import (_grid_sensor, displaced_grid, mesh_scene,
                                          primary_rays, secondary_rays)
from hlbvh.comparison.machine import cpu_model
from hlbvh.kernels.keyed import build_keyed, keyed_tree
from hlbvh.kernels.layout.packing import packed_records
from hlbvh.kernels.layout.slots import SLOT
from hlbvh.kernels.traversal import any_hit, closest_hit, steps
from hlbvh.render.frame import FrameRenderer
from hlbvh.render.settings import RenderSettings
from hlbvh.timing import timed_cpu


def wave_keys(vertices: mi.Float, segments: int, amplitude: float = 0.05,
              phase: float = 0.5) -> list:
    """``segments + 1`` keys of the flat ``vertices`` under a travelling wave in z."""
    p = dr.unravel(mi.Point3f, vertices)
    keys = []
    for k in range(segments + 1):
        shift = 2 * math.pi * phase * (k / segments - 0.5)
        moved = mi.Point3f(p.x, p.y, p.z + amplitude * dr.sin(6 * p.x + shift))
        keys.append(dr.ravel(moved))
    dr.eval(keys)
    return keys


def _run(fn) -> tuple[float, float]:
    """(wall ms, process CPU ms) of one call, its outputs evaluated."""
    ms, cpu, _ = timed_cpu(lambda: dr.eval(fn()))
    return ms, cpu


def _best(fn, repeats: int) -> tuple[float, float]:
    """The least wall and CPU ms of ``repeats`` warm calls (one call first: compiles)."""
    runs = [_run(fn) for _ in range(repeats + 1)][1:]
    return min(r[0] for r in runs), min(r[1] for r in runs)


def run(size: int = 1_000_000, resolution: int = 512, repeats: int = 7, leaf_size: int = 4,
        amplitude: float = 0.05):
    vertices, faces = displaced_grid(size)
    ray = primary_rays(mesh_scene(vertices, faces, _grid_sensor(resolution)))
    n = dr.width(ray.o)
    rng = mi.PCG32(n, 7)
    time_ = rng.next_float32()
    dr.eval(ray, time_)

    mid = wave_keys(vertices, 2, amplitude)[1]  # the wave at mid-shutter
    still = hlbvh.build(mid, faces, leaf_size=leaf_size)
    trees, build_ms = {"still": (still, None)}, {}
    keys = {s: wave_keys(vertices, s, amplitude) for s in (1, 4)}
    other = hlbvh.build(mid, faces, leaf_size=leaf_size)
    packed_records(other)  # a traced tree: refit fused with its packing
    refit_ms = _best(lambda: other.refit(keys[1][0]).node_min, repeats)
    tree = keyed_tree(still, [mid, mid])
    trees["keyed S=1 equal"] = (tree, time_)
    for s in (1, 4):
        build_ms[f"keyed S={s}"] = tuple(
            ms / (s + 1) for ms in _best(lambda: keyed_tree(still, keys[s]).records, repeats))
        trees[f"keyed S={s}"] = (keyed_tree(still, keys[s]), time_)
    at_key0 = hlbvh.build(keys[4][0], faces, leaf_size=leaf_size)
    trees["keyed S=4 (built at key 0)"] = (keyed_tree(at_key0, keys[4]), time_)

    rows = []
    for query, fn in (("closest", closest_hit), ("any", any_hit)):
        calls = {name: (lambda t=t, tm=tm: fn(t, ray.o, ray.d, ray.maxt, time=tm))
                 for name, (t, tm) in trees.items()}
        for call in calls.values():
            _run(call)  # compile
        best = {name: (math.inf, math.inf) for name in calls}
        for _ in range(repeats):  # the rows in turn: all see the same load
            for name, call in calls.items():
                best[name] = tuple(map(min, best[name], _run(call)))
        for name, (t, tm) in trees.items():
            count = steps(t, ray.o, ray.d, ray.maxt, any_hit=query == "any", time=tm)
            slots = t.slots if hasattr(t, "slots") else dr.width(
                packed_records(t)[0]) // SLOT
            rows.append({"query": query, "tree": name, "ns_per_ray": 1e6 * best[name][0] / n,
                         "vs_still": best[name][0] / best["still"][0],
                         "cpu_ns_per_ray": 1e6 * best[name][1] / n,
                         "cpu_vs_still": best[name][1] / best["still"][1],
                         "steps": dr.mean(mi.Float(count))[0],
                         "refit_ms_per_key": build_ms.get(name),
                         "mb_per_key": slots * SLOT * 4 / 2**20})
    return {"rays": n, "triangles": len(faces) // 3, "refit_ms": refit_ms, "amplitude": amplitude,
            "cpu": cpu_model(), "rows": rows}


def topology_ab(scene: str, triangles: int = 1_000_000, shutter: float = 1.0,
                motion_keys: int = 1, resolution: tuple = (480, 270), repeats: int = 5,
                frame: int = 1, builder: str = "hlbvh") -> dict:
    """The keyed tree of ``scene``'s moving meshes over a shutter of ``shutter`` frames
    around frame ``frame``, built by ``builder`` over the mid-shutter pose and over the
    triangles' boxes over the shutter, traced on the same rays in turn; see the module
    docstring."""
    animation = scenes.get(scene, triangles=triangles, frames=frame + 2)
    renderer = FrameRenderer(animation, RenderSettings(
        resolution=resolution, spp=1, shutter=(-shutter / 2, shutter / 2),
        motion_keys=motion_keys, moving_accel="hlbvh"))
    renderer.render(frame)  # keys the moving meshes as a blurred frame does
    group = renderer.integrator.scene_accel.dynamic
    size = dr.width(group.key_points) // group.keyed.keys
    points = [dr.gather(mi.Float, group.key_points, dr.arange(mi.UInt32, size) + k * size)
              for k in range(group.keyed.keys)]
    faces = group.geometry.faces
    primary = primary_rays(renderer.scene)
    rays = [primary, secondary_rays(renderer.scene, primary)]
    o, d = (mi.Vector3f(*(dr.concat([getattr(r, f)[c] for r in rays]) for c in range(3)))
            for f in ("o", "d"))
    maxt = dr.concat([r.maxt for r in rays])
    n = dr.width(o)
    time_ = mi.PCG32(n, 11).next_float32()
    dr.eval(o, d, maxt, time_)
    trees = {t: build_keyed(points, faces, topology=t, builder=builder)
             for t in ("mid", "union")}
    rows = []
    for query, fn in (("closest", closest_hit), ("any", any_hit)):
        calls = {t: (lambda tree=tree: fn(tree, o, d, maxt, time=time_))
                 for t, tree in trees.items()}
        for call in calls.values():
            _run(call)  # compile
        best = {t: (math.inf, math.inf) for t in calls}
        for _ in range(repeats):  # in turn: both see the same load
            for t, call in calls.items():
                best[t] = tuple(map(min, best[t], _run(call)))
        for t, tree in trees.items():
            count = steps(tree, o, d, maxt, any_hit=query == "any", time=time_)
            rows.append({"query": query, "topology": t, "sah": tree.sah,
                         "degradation": tree.degradation,
                         "ns_per_ray": 1e6 * best[t][0] / n,
                         "cpu_ns_per_ray": 1e6 * best[t][1] / n,
                         "cpu_vs_mid": best[t][1] / best["mid"][1],
                         "steps": dr.mean(mi.Float(count))[0]})
    return {"scene": scene, "frame": frame, "builder": builder,
            "triangles": len(faces) // 3, "rays": n, "shutter": shutter,
            "motion_keys": motion_keys, "cpu": cpu_model(), "rows": rows,
            "load": os.getloadavg()[0]}


def format_topology_ab(result: dict) -> str:
    lines = ["| query | topology | SAH over shutter | / still SAH at mid | ns/ray (wall) | "
             "CPU ns/ray | CPU / mid | steps/ray |", "|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['query']} | {r['topology']} | {r['sah']:.3f} | "
                     f"{r['degradation']:.3f} | {r['ns_per_ray']:.0f} | "
                     f"{r['cpu_ns_per_ray']:.0f} | {r['cpu_vs_mid']:.2f}× | {r['steps']:.1f} |")
    lines.append(f"\n{result['scene']} frame {result['frame']}, {result['builder']} builder: "
                 f"{result['triangles']} moving triangles, shutter {result['shutter']} "
                 f"frame, S={result['motion_keys']}, {result['rays']} rays (camera and one "
                 f"bounce); {result['cpu']}; load average {result['load']:.1f}")
    return "\n".join(lines)


def format_table(result: dict) -> str:
    lines = ["| query | tree | ns/ray (wall) | / still | CPU ns/ray | / still | steps/ray "
             "| keying ms/key (wall / CPU) | MB/key |", "|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        refit = "" if r["refit_ms_per_key"] is None else \
            "{:.1f} / {:.1f}".format(*r["refit_ms_per_key"])
        lines.append(f"| {r['query']} | {r['tree']} | {r['ns_per_ray']:.0f} | "
                     f"{r['vs_still']:.2f}× | {r['cpu_ns_per_ray']:.0f} | "
                     f"{r['cpu_vs_still']:.2f}× | {r['steps']:.1f} | {refit} | "
                     f"{r['mb_per_key']:.1f} |")
    lines.append(f"\n{result['triangles']} triangles (wave amplitude {result['amplitude']}), "
                 f"{result['rays']} camera rays, "
                 f"{result['cpu']}; BVH.refit of one pose (fused with its packing) "
                 "{:.1f} / {:.1f} ms (wall / CPU)".format(*result["refit_ms"]))
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1_000_000)
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--amplitude", type=float, default=0.05)
    parser.add_argument("--topology-ab", metavar="SCENE", default=None,
                        help="the mid-shutter against the union-box topology on SCENE")
    parser.add_argument("--triangles", type=int, default=1_000_000)
    parser.add_argument("--shutter", type=float, default=1.0, help="frames, centred")
    parser.add_argument("--motion-keys", type=int, default=1)
    parser.add_argument("--frame", type=int, default=1, help="the frame (--topology-ab)")
    parser.add_argument("--builder", default="hlbvh", help="the builder (--topology-ab)")
    parser.add_argument("--frame-resolution", default="480x270", help="WxH (--topology-ab)")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    if args.topology_ab:
        width, height = (int(v) for v in args.frame_resolution.split("x"))
        print(format_topology_ab(topology_ab(args.topology_ab, args.triangles, args.shutter,
                                             args.motion_keys, (width, height),
                                             args.repeats, args.frame, args.builder)))
    else:
        print(format_table(run(args.size, args.resolution, args.repeats,
                               amplitude=args.amplitude)))
    print(f"({time.perf_counter() - start:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
