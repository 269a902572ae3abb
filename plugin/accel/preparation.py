"""What :meth:`hlbvh.SceneAccel.prepare` measures beside the choice
(:mod:`hlbvh.accel.choice`) and what it reports: the probe (a sample of a render's own
rays, and the time of a query through each structure that can trace the moving
meshes), the whole scene's rebuild when it traces them, and :class:`Prepared`, the
record of one preparation that integrators and the frame renderer read."""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from hlbvh.accel.choice import Probe
from hlbvh.kernels.arrays import concat
from hlbvh.timing import clock_ms

#: Camera rays (and as many bounces) a probe of the moving meshes' structures traces:
#: its query times only seed the choice (the renders decide), so few: 50-60 ms warm on
#: `world` at 480x270 on 2 EPYC cores, once per accelerator.
PROBE_RAYS = 4096
#: Consecutive pixels of a probe's run (a render's lanes are consecutive pixels too).
PROBE_RUN = 64


@dataclass(frozen=True)
class Prepared:
    """What one :meth:`~hlbvh.SceneAccel.prepare` did.

    Attributes:
        ms: its wall time (with the accelerator's construction, for the first): the
            updates, the probe and the whole scene's rebuild.
        decision: the most work a group did (one of
            :data:`hlbvh.accel.policy.DECISIONS`), ``"native"`` where no group did any
            and the whole scene was rebuilt.
        sah_cost: the SAH cost of our BVHs traced together (``last_update["sah_cost"]``).
        traced_by: what traces the moving meshes for the render (``"hlbvh"``,
            ``"native"`` or ``"scene"``).
        scene_rebuild_ms: the whole scene's rebuild, None when there was none.
        probed: whether the structures' queries were timed.
    """

    ms: float
    decision: str
    sah_cost: float | None
    traced_by: str
    scene_rebuild_ms: float | None
    probed: bool


def render_sample(accel, sensor, n: int = PROBE_RAYS) -> Probe:
    """A sample of what a render of ``sensor`` traces, fixed by a seed: ``n`` camera
    rays in runs of :data:`PROBE_RUN` consecutive pixels (in the film's row order, from
    random starts; a random position inside each pixel), and from where each lands
    (through ``accel``) a bounce in a cosine-distributed direction about the surface's
    normal on the camera's side (a diffuse bounce; a camera ray that missed bounces
    again from the camera), with the fractions of each that meet a surface. In runs, as
    a render's lanes are: neighbouring lanes trace neighbouring pixels, and their
    bounces start near each other. Rays through random pixels made our traversal's
    packets diverge as no render's do, and put its cost per query at two to four times
    what the renders showed."""
    width, height = (int(v) for v in sensor.film().size())
    run = min(PROBE_RUN, width * height)
    rng = np.random.default_rng(7)
    starts = rng.integers(0, width * height - run + 1, max(n // run, 1))
    pixel = (starts[:, None] + np.arange(run)[None, :]).ravel()
    n = pixel.size
    u = rng.random((4, n)).astype(np.float32)
    film = mi.Point2f(mi.Float(((pixel % width) + u[0]) / width),
                      mi.Float(((pixel // width) + u[1]) / height))
    camera, _ = sensor.sample_ray(0.0, 0.5, film, mi.Point2f(0.5, 0.5))
    si = accel.ray_intersect(camera)
    local = mi.warp.square_to_cosine_hemisphere(mi.Point2f(mi.Float(u[2]), mi.Float(u[3])))
    frame = mi.Frame3f(dr.select(dr.dot(si.n, camera.d) > 0, -si.n, si.n))
    bounce = si.spawn_ray(frame.to_world(local))
    valid = si.is_valid()
    origins = dr.select(valid, bounce.o, camera.o)
    directions = dr.select(valid, bounce.d, camera.d)
    bounced = accel.ray_intersect_preliminary(mi.Ray3f(origins, directions)).is_valid() & valid
    rays = mi.Ray3f(mi.Point3f(*[concat([camera.o[k], origins[k]]) for k in range(3)]),
                    mi.Vector3f(*[concat([camera.d[k], directions[k]]) for k in range(3)]))
    camera_hits, bounce_hits = dr.count(valid)[0], dr.count(bounced)[0]
    dr.eval(rays)
    return Probe(rays, camera_hits / n, bounce_hits / max(camera_hits, 1))


def time_structures(accel, sample: Probe):
    """Time the closest-hit queries of ``sample``'s rays through the still world alone
    and through it with each structure that may trace the moving meshes (ours and the
    native sub-scene, each brought up to date first, :meth:`SceneAccel.query_through`),
    and record them and the sample's hit fractions in the moving meshes' costs. What
    traces the moving meshes now is left as it was."""
    moving = accel.moving_meshes
    costs = moving.costs
    costs.hit_fractions = (sample.camera_hits, sample.bounce_hits)
    for structure in [s for s in ("hlbvh", "native") if s in moving.allowed()]:
        costs.record_queries(structure, query_ns(accel.query_through(structure), sample.rays))
    costs.record_queries("still", query_ns(accel.query_through("still"), sample.rays))
    moving.probed = True


def rebuild_scene(scene, shapes: list, moving: tuple, moving_meshes, rays=None) -> float:
    """Rebuild ``scene``'s own accelerator over its shapes as they are now, for the
    whole scene to trace the moving meshes (``"scene"``), record its cost in
    ``moving_meshes`` and return it (ms); ``rays``: a probe's rays to time a query
    through it with, when not timed yet.

    The shapes are told first that they changed, from our own record of motion
    (``moving``: indices into ``shapes``), not from Mitsuba's marks: any Mitsuba
    (sub-)scene built over a shape since its last write (the moving meshes' native
    group, or another scene holding the same mesh) cleared the mark that write left,
    and the scene would rebuild nothing. At the first rebuild every shape is told
    (writes made before the accelerator existed are in no record of ours), the moving
    ones after. A mesh is told its positions and normals changed, so it keeps the
    normals it was given; telling one costs about a millisecond per million triangles
    (its box)."""
    told = moving if moving_meshes.scene_rebuilt_once else range(len(shapes))
    start = clock_ms()
    for i in told:
        shape = shapes[i]
        shape.parameters_changed(["vertex_positions", "vertex_normals"]
                                 if shape.is_mesh() else [])
    scene.parameters_changed([])
    ms = clock_ms() - start
    ns = query_ns(scene.ray_intersect_preliminary, rays) if rays is not None else None
    moving_meshes.scene_rebuilt(ms, ns)
    return ms


def query_ns(query, ray, run: int = 64) -> float:
    """Nanoseconds a closest-hit ``query(ray)`` costs per ray, without the launch's
    fixed cost: the slope between the whole of ``ray`` and its half (every other block
    of ``run`` consecutive rays, so rays traced side by side stay side by side), each
    the fastest of two runs after one that may compile (the device synchronised); the
    mean over the whole where noise makes the slope meaningless."""
    n = dr.width(ray)
    run = max(min(run, n // 2), 1)
    i = dr.arange(mi.UInt32, (n // (2 * run)) * run)
    half = dr.gather(type(ray), ray, (i // run) * (2 * run) + i % run)

    def fastest(r) -> float:
        best = float("inf")
        for _ in range(2):
            start = clock_ms()
            pi = query(r)
            dr.eval(pi.t, pi.prim_index, pi.shape_index)
            best = min(best, clock_ms() - start)
        return best

    fastest(half)  # compiles what the runs below launch
    whole, part = fastest(ray), fastest(half)
    slope = (whole - part) * 1e6 / max(n - dr.width(half), 1)
    return slope if slope > 0 else whole * 1e6 / max(n, 1)
