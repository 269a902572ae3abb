"""``hlbvh bench build``: what a user pays per frame to get a tree ready to trace, ours
against Mitsuba's native rebuild and Embree 4's builders, side by side in one process.

For each mesh (a displaced 1M grid, a 1M random soup, a rounded box subdivided to 1M
triangles, a 100k grid; or every mesh at the ``sizes`` given):

- **ready** (the headline): ``hlbvh.build`` plus
  :func:`hlbvh.kernels.layout.packing.packed_records` (what traversal reads), each timed,
  and their sum; cold (the first of the process: kernels compiled or loaded from Dr.Jit's
  disk cache) and warm (min and median over repeats), kernel launches of a warm call
  (counted on an extra, untimed call: Dr.Jit's kernel history slows every launch);
- the same seeded with the previous frame's order (``previous=``, packing included),
  and a refit, packing included too (a refit tree is traced only once its slots are
  packed again);
- Mitsuba's native rebuild: ``params.update()`` after genuinely new vertex arrays
  (Mitsuba skips the rebuild when handed the array it already holds), Embree HIGH;
- when ``embreex`` is installed (``pip install hlbvh[bench]``), Embree 4 through its C
  API: a LOW and a MEDIUM build of a new scene on the same buffers, and a refit
  (``RTC_BUILD_QUALITY_REFIT`` on a dynamic scene), on all cores;
- ``Mtris/s/core``: triangles per second of the ready time, divided by the cores.

All of a mesh's measurements run round by round, interleaved (native, Embree, each of
ours, then the next round), so that a shared machine's load, which comes and goes,
weighs on every column alike; the ratios use the warm minima.
"""

from __future__ import annotations

import ctypes
import os
import statistics

import drjit as dr
import mitsuba as mi
import numpy as np

import hlbvh
from hlbvh.comparison.bench.trace import displaced_grid, mesh_scene
from hlbvh.comparison.machine import cpu_model
from hlbvh.kernels.layout.packing import packed_records
from hlbvh.scenes import meshes as scene_meshes
from hlbvh.timing import timed, timed_cpu


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


def subdivided_box(triangles: int, exponent: float = 4.0):
    """A rounded box (``scenes.meshes.rounded_box``) midpoint-subdivided (each triangle
    into four, new vertices pushed onto the surface) until it has at least
    ``triangles / 4`` triangles: a mesh whose vertex order is not its spatial order,
    as a modelled mesh after subdivision. Flat ``mi.Float`` / ``mi.UInt32``."""
    levels, base = 0, triangles
    while base > 1000:
        base, levels = base / 4, levels + 1
    n = max(1, round((base / 12) ** 0.5))
    v, f = scene_meshes.rounded_box(n, exponent)
    for _ in range(levels):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = (v[unique[:, 0]] + v[unique[:, 1]]) / 2
        mid /= ((np.abs(mid) ** exponent).sum(1) ** (1 / exponent))[:, None]
        m = inverse.reshape(3, -1) + len(v)  # the midpoints of edges 01, 12, 20
        a, b, c = f.T
        f = np.concatenate([np.stack(t, 1) for t in (
            (a, m[0], m[2]), (m[0], b, m[1]), (m[2], m[1], c), (m[0], m[1], m[2]))])
        v = np.concatenate([v, mid])
    return mi.Float(v.astype(np.float32).ravel()), mi.UInt32(f.astype(np.uint32).ravel())


MESHES = {"grid": displaced_grid, "soup": random_soup, "box": subdivided_box}
#: (mesh, triangles) measured when no sizes are given.
DEFAULT_CASES = (("grid", 1_000_000), ("soup", 1_000_000), ("box", 1_000_000), ("grid", 100_000))


def _summary(times: list[float]) -> dict:
    """Cold (the first), warm min and median (the rest) of a list of ms."""
    return {"cold": times[0], "min": min(times[1:]), "median": statistics.median(times[1:])}


class _Ours:
    """One builder on one mesh: each call of :meth:`round` times a fresh build and its
    packing (ready to trace), a build seeded with the last fresh one, and a refit of
    the first round's tree."""

    def __init__(self, vertices, faces, moved, builder: str):
        self.args, self.moved, self.builder = (vertices, faces), moved, builder
        self.ms = {k: [] for k in ("build", "pack", "ready", "ready_cpu", "seeded", "refit")}
        self.launches, self.bvh, self.refitted = 0, None, None

    def round(self, k: int):
        vertices, faces = self.args
        b_ms, b_cpu, bvh = timed_cpu(lambda: hlbvh.build(vertices, faces, builder=self.builder))
        p_ms, p_cpu, _ = timed_cpu(lambda: packed_records(bvh))
        if k == 1:
            # Counted on an untimed build: recording the kernel history slows every launch.
            dr.set_flag(dr.JitFlag.KernelHistory, True)
            dr.kernel_history()
            packed_records(hlbvh.build(vertices, faces, builder=self.builder))
            self.launches = len(dr.kernel_history())
            dr.set_flag(dr.JitFlag.KernelHistory, False)
        s_ms = timed_cpu(lambda: packed_records(
            hlbvh.build(self.moved, faces, builder=self.builder, previous=bvh)))[0]
        self.refitted = self.refitted or bvh  # one tree refit round after round, as Embree's
        r_ms = timed_cpu(lambda: packed_records(
            self.refitted.refit(self.moved * (1 + 1e-5 * k))))[0]
        for key, value in (("build", b_ms), ("pack", p_ms), ("ready", b_ms + p_ms),
                           ("ready_cpu", b_cpu + p_cpu), ("seeded", s_ms), ("refit", r_ms)):
            self.ms[key].append(value)
        self.bvh = bvh


class _Native:
    """Mitsuba's rebuild after genuinely new vertex arrays (``params.update()``)."""

    def __init__(self, vertices, faces, rounds: int):
        self.params = mi.traverse(mesh_scene(vertices, faces))
        self.key = next(k for k in self.params.keys() if k.endswith("vertex_positions"))
        self.variants = [vertices * (1 + 1e-6 * (k + 1)) for k in range(rounds)]
        dr.eval(self.variants)
        self.ms = []

    def round(self, k: int):
        self.params[self.key] = self.variants[k]
        self.ms.append(timed_cpu(self.params.update)[0])


class _Embree:
    """Embree 4's C API through ctypes, from the library ``embreex`` ships."""

    LOW, MEDIUM, HIGH, REFIT = 0, 1, 2, 3
    _DYNAMIC = 1
    _TRIANGLE, _INDEX, _VERTEX = 0, 0, 1
    _UINT3, _FLOAT3 = 0x5003, 0x9003

    def __init__(self):
        import embreex  # noqa: F401  (loads its libembree4)

        libs = os.path.join(os.path.dirname(os.path.dirname(embreex.__file__)), "embreex.libs")
        name = next(n for n in sorted(os.listdir(libs)) if n.startswith("libembree4"))
        lib = ctypes.CDLL(os.path.join(libs, name))
        p, u, s = ctypes.c_void_p, ctypes.c_uint, ctypes.c_size_t
        for fn, args, res in (
            ("rtcNewDevice", [ctypes.c_char_p], p), ("rtcReleaseDevice", [p], None),
            ("rtcNewScene", [p], p), ("rtcReleaseScene", [p], None),
            ("rtcSetSceneBuildQuality", [p, ctypes.c_int], None),
            ("rtcSetSceneFlags", [p, ctypes.c_int], None), ("rtcCommitScene", [p], None),
            ("rtcNewGeometry", [p, ctypes.c_int], p), ("rtcReleaseGeometry", [p], None),
            ("rtcSetSharedGeometryBuffer", [p, ctypes.c_int, u, ctypes.c_int, p, s, s, s], None),
            ("rtcSetGeometryBuildQuality", [p, ctypes.c_int], None),
            ("rtcCommitGeometry", [p], None), ("rtcAttachGeometry", [p, p], u),
            ("rtcUpdateGeometryBuffer", [p, ctypes.c_int, u], None),
        ):
            getattr(lib, fn).argtypes, getattr(lib, fn).restype = args, res
        self.lib = lib
        self.device = lib.rtcNewDevice(None)

    def _scene(self, vertices: np.ndarray, faces: np.ndarray, quality: int, refit: bool):
        lib = self.lib
        scene = lib.rtcNewScene(self.device)
        lib.rtcSetSceneBuildQuality(scene, self.LOW if refit else quality)
        if refit:
            lib.rtcSetSceneFlags(scene, self._DYNAMIC)
        geom = lib.rtcNewGeometry(self.device, self._TRIANGLE)
        lib.rtcSetSharedGeometryBuffer(geom, self._VERTEX, 0, self._FLOAT3, vertices.ctypes.data,
                                       0, 12, len(vertices) // 3)
        lib.rtcSetSharedGeometryBuffer(geom, self._INDEX, 0, self._UINT3, faces.ctypes.data,
                                       0, 12, len(faces) // 3)
        lib.rtcSetGeometryBuildQuality(geom, self.REFIT if refit else quality)
        lib.rtcCommitGeometry(geom)
        lib.rtcAttachGeometry(scene, geom)
        return scene, geom

    def build_ms(self, vertices, faces, quality: int) -> float:
        """ms to commit a new scene of this quality."""
        scene, geom = self._scene(vertices, faces, quality, refit=False)
        ms, _ = timed(self.lib.rtcCommitScene, scene)
        self.lib.rtcReleaseGeometry(geom), self.lib.rtcReleaseScene(scene)
        return ms

    def refitter(self, vertices, faces):
        """A function of the round ``k`` that moves the vertices of a built dynamic
        scene and returns the ms of its refit."""
        buffer = vertices.copy()
        scene, geom = self._scene(buffer, faces, self.MEDIUM, refit=True)
        self.lib.rtcCommitScene(scene)
        self._keep = (buffer, scene, geom)

        def update():
            self.lib.rtcUpdateGeometryBuffer(geom, self._VERTEX, 0)
            self.lib.rtcCommitGeometry(geom)
            self.lib.rtcCommitScene(scene)

        def refit(k: int) -> float:
            buffer[:] = vertices * np.float32(1 + 1e-4 * (k + 1))
            return timed(update)[0]

        return refit

    def release(self):
        """Free the scene of the last :meth:`refitter`."""
        _, scene, geom = self._keep
        self.lib.rtcReleaseGeometry(geom), self.lib.rtcReleaseScene(scene)


def _embree():
    """An :class:`_Embree`, or None when ``embreex`` is not installed."""
    try:
        return _Embree()
    except ImportError:
        return None


def run(sizes=None, meshes=("grid", "soup", "box"), builders=("hlbvh", "lbvh", "sah"),
        repeats: int = 5, sah_max: int = 200_000) -> list[dict]:
    """Measure every case (``DEFAULT_CASES``, or each mesh at each of ``sizes``) and
    builder (``"sah"`` only up to ``sah_max`` triangles); one dict per row (see the
    module docstring). All measurements of a case run round by round, interleaved, so
    a load that comes and goes on a shared machine affects every column alike."""
    cases = DEFAULT_CASES if sizes is None else [(m, s) for m in meshes for s in sizes]
    cores = os.cpu_count() or 1
    embree = _embree()
    rounds = repeats + 1
    rows = []
    for mesh, size in cases:
        vertices, faces = MESHES[mesh](size)
        moved = vertices * 1.0001
        dr.eval(vertices, faces, moved)
        triangles = len(faces) // 3
        native = _Native(vertices, faces, rounds)
        ours = [_Ours(vertices, faces, moved, b) for b in builders
                if b != "sah" or triangles <= sah_max]
        others = {}
        if embree is not None:
            v_np, f_np = np.ascontiguousarray(vertices.numpy()), np.ascontiguousarray(faces.numpy())
            others = {"embree_low": [], "embree_medium": [], "embree_refit": []}
            embree_refit = embree.refitter(v_np, f_np)
        for k in range(rounds):
            native.round(k)
            if embree is not None:
                others["embree_low"].append(embree.build_ms(v_np, f_np, embree.LOW))
                others["embree_medium"].append(embree.build_ms(v_np, f_np, embree.MEDIUM))
                others["embree_refit"].append(embree_refit(k))
            for o in ours:
                o.round(k)
        if embree is not None:
            embree.release()
        others = {key: _summary(ms) for key, ms in others.items()}
        for o in ours:
            ready = min(o.ms["ready"][1:])
            rows.append({
                "mesh": mesh, "triangles": triangles, "builder": o.builder, "cpu": cpu_model(),
                "cores": cores, "load": os.getloadavg()[0],
                **{key: _summary(o.ms[key]) for key in ("build", "pack", "ready", "seeded", "refit")},
                "ready_cpu_min": min(o.ms["ready_cpu"][1:]), "launches": o.launches,
                "stage_ms": dict(o.bvh.stats.stage_ms), "sah_cost": o.bvh.stats.sah_cost,
                "native": _summary(native.ms), **others,
                "native_over_ready": min(native.ms[1:]) / ready,
                "mtris_per_s_per_core": triangles / ready / 1e3 / cores,
            })
    return rows


def format_table(rows: list[dict]) -> str:
    """The rows as a text table: warm min ms (median in parentheses where it matters)."""
    head = (f"{'mesh':4} {'tris':>7} {'builder':6} {'build':>6} {'pack':>6} {'ready':>13} "
            f"{'cold':>6} {'seeded':>6} {'refit':>6} {'native':>13} {'E.low':>6} {'E.med':>6} "
            f"{'E.refit':>7} {'nat/rdy':>7} {'Mtri/s/c':>8} {'launch':>6} {'SAH':>6}")
    lines = [head, "-" * len(head)]
    fmt = lambda r, k: f"{r[k]['min']:6.1f}" if k in r else f"{'-':>6}"
    for r in rows:
        lines.append(
            f"{r['mesh']:4} {r['triangles']:>7} {r['builder']:6} {r['build']['min']:6.1f} "
            f"{r['pack']['min']:6.1f} {r['ready']['min']:6.1f} ({r['ready']['median']:5.1f}) "
            f"{r['ready']['cold']:6.0f} {r['seeded']['min']:6.1f} {r['refit']['min']:6.1f} "
            f"{r['native']['min']:6.1f} ({r['native']['median']:5.1f}) {fmt(r, 'embree_low')} "
            f"{fmt(r, 'embree_medium')} {fmt(r, 'embree_refit'):>7} "
            f"{r['native_over_ready']:6.2f}x {r['mtris_per_s_per_core']:8.2f} "
            f"{r['launches']:6} {r['sah_cost']:6.2f}")
    for r in rows[:1]:
        stages = " ".join(f"{k}={v:.1f}" for k, v in r["stage_ms"].items())
        lines.append(f"stages of the first row's last build (ms): {stages}")
    cpu = rows[0]["cpu"] if rows else cpu_model()
    cores = rows[0]["cores"] if rows else os.cpu_count()
    lines.append(
        f"ms, warm min over repeats (median); ready = build + pack (packed_records); "
        f"seeded and refit include the pack; "
        f"native = Mitsuba params.update() (Embree HIGH); E.* = Embree 4 LOW/MEDIUM build "
        f"and refit, all interleaved round by round; {cpu}, {cores} cores, load "
        f"{os.getloadavg()[0]:.2f}; variant {mi.variant()}")
    return "\n".join(lines)
