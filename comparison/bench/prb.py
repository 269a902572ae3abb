"""``hlbvh bench prb``: an iteration of a shape optimisation, ``hlbvh_prb`` over our
accelerator against Mitsuba's ``prb``, measured side by side in one process.

The loop is the ``world`` scene's (``size`` triangles: the flag's vertex positions
optimised by ``mi.ad.Adam``, the landscape still) at ``resolution``², 4 spp,
``max_depth`` 3; an iteration is a differentiable render (``mi.render(scene,
params)``: prb's primal pass), an L2 loss against a target image (the flag of a
later frame, rendered once beforehand), its backward pass (prb's replay), Adam's
step and ``params.update(opt)``:

- ``prb``: Mitsuba's ``prb`` with ``mi.traverse``'s parameters: every update rebuilds
  the scene's accelerator (the landscape with the flag);
- ``hlbvh``: ``hlbvh_prb`` with ``accel="hlbvh"`` (its defaults: the still landscape
  through Mitsuba's accelerator, built once; the flag, declared moving, through our
  BVH) with :func:`hlbvh.traverse`'s parameters: the update refreshes the flag
  alone, and our accelerator rebuilds or refits the flag's BVH at the start of the
  render (counted in the iteration).

Both start from the same pose with the same seeds and take turns iteration by
iteration (both see the same machine load). ``cold`` is the first iteration (kernels
compiled unless Dr.Jit's disk cache holds them); ``min``/``median`` are over the
``repeats`` after it; ``update`` is the median ``params.update(opt)``; ``ratio`` is
prb's median over ours. ``agree`` is the share of the flag's vertex coordinates on
which the two loops agree (within :data:`AGREE`) after the last iteration. Adam moves
a coordinate by about its learning rate per step however small its gradient, so a
vertex whose few samples differ between the two (a ray through a shared edge taken
by the neighbouring triangle) ends up to a step apart; the rest descend alike.
"""

from __future__ import annotations

import statistics

import drjit as dr
import mitsuba as mi
import numpy as np

import hlbvh
from hlbvh.scenes import apply_frame, get as get_scene
from hlbvh.timing import timed

#: The optimised mesh of ``world`` and the key of its vertex positions.
FLAG = "flag"
KEY = f"{FLAG}.vertex_positions"
SPP = 4
MAX_DEPTH = 3
TARGET_FRAME = 10
LEARNING_RATE = 1e-3
#: Coordinates of the two loops' flags closer than this agree.
AGREE = 1e-5

#: Keys of every row :func:`run` returns.
ROW_KEYS = ("scene", "triangles", "resolution", "spp", "max_depth", "builder", "repeats",
            "prb_cold_ms", "prb_min_ms", "prb_median_ms", "prb_update_ms",
            "hlbvh_cold_ms", "hlbvh_min_ms", "hlbvh_median_ms", "hlbvh_update_ms",
            "ratio", "agree")


def run(repeats: int = 5, sizes=(1_100_000,), resolution: int = 256,
        builder: str = "hlbvh") -> list[dict]:
    """Time ``repeats + 1`` optimisation iterations of each loop per size.

    Args:
        repeats: warm iterations after the cold one.
        sizes: triangles of the ``world`` scene (the flag takes 1/11 of them).
        resolution: image side in pixels.
        builder: our builder (``"hlbvh"``, ``"lbvh"`` or ``"sah"``).
    Returns:
        One dict per size with the keys :data:`ROW_KEYS` (times in ms).
    Raises:
        ValueError: ``repeats`` below 1, or a bad size or builder.
    """
    if repeats < 1:
        raise ValueError(f"repeats={repeats}: expected at least 1")
    hlbvh.BuildConfig.from_options(builder=builder)
    rows = []
    for size in sizes:
        world = get_scene("world", triangles=size, frames=TARGET_FRAME + 1)
        target = _target(world, resolution)
        loops = {
            "prb": _Loop(world, resolution, dict(type="prb", max_depth=MAX_DEPTH), target),
            "hlbvh": _Loop(world, resolution,
                           dict(type="hlbvh_prb", accel="hlbvh", max_depth=MAX_DEPTH,
                                builder=builder, moving=",".join(world.animated_ids())),
                           target),
        }
        for _ in range(repeats + 1):
            for loop in loops.values():
                loop.step()
        row = {"scene": "world", "triangles": world.triangle_count(),
               "resolution": resolution, "spp": SPP, "max_depth": MAX_DEPTH,
               "builder": builder, "repeats": repeats}
        for name, loop in loops.items():
            row.update({f"{name}_{k}": v for k, v in loop.summary().items()})
        row["ratio"] = row["prb_median_ms"] / row["hlbvh_median_ms"]
        apart = np.abs(loops["prb"].vertices() - loops["hlbvh"].vertices())
        row["agree"] = float(np.mean(apart <= AGREE))
        rows.append(row)
    return rows


def _scene(world, resolution: int, integrator: dict) -> mi.Scene:
    return mi.load_dict(world.scene_dict(resolution=(resolution, resolution), spp=SPP,
                                         integrator=integrator))


def _target(world, resolution: int) -> mi.TensorXf:
    """The image the loops descend towards: the flag at frame :data:`TARGET_FRAME`,
    rendered by Mitsuba's prb."""
    scene = _scene(world, resolution, dict(type="prb", max_depth=MAX_DEPTH))
    apply_frame(scene, None, world.frame(TARGET_FRAME))
    image = mi.render(scene, seed=10**6)
    dr.eval(image)
    return image


class _Loop:
    """One optimisation loop: its scene (frame 0), parameters, Adam and the times of
    its iterations."""

    def __init__(self, world, resolution: int, integrator: dict, target: mi.TensorXf):
        self.scene = _scene(world, resolution, integrator)
        ours = integrator["type"] == "hlbvh_prb"
        self.params = hlbvh.traverse(self.scene) if ours else mi.traverse(self.scene)
        apply_frame(self.scene, self.params, world.frame(0))
        self.target = target
        self.opt = mi.ad.Adam(lr=LEARNING_RATE)
        self.opt[KEY] = self.params[KEY]
        self.params.update(self.opt)
        self.iteration_ms, self.update_ms = [], []

    def step(self):
        """One iteration, timed whole (render, loss, backward pass, step, update) and
        its update alone."""
        def iteration():
            image = mi.render(self.scene, self.params, seed=len(self.iteration_ms))
            dr.backward(dr.mean(dr.square(image - self.target)))
            self.opt.step()
            ms, _ = timed(self.params.update, self.opt)
            self.update_ms.append(ms)
            dr.eval(self.params[KEY])

        ms, _ = timed(iteration)
        self.iteration_ms.append(ms)

    def summary(self) -> dict:
        warm = self.iteration_ms[1:]
        return {"cold_ms": self.iteration_ms[0], "min_ms": min(warm),
                "median_ms": statistics.median(warm),
                "update_ms": statistics.median(self.update_ms[1:])}

    def vertices(self) -> np.ndarray:
        return np.array(self.params[KEY])


def format_table(rows: list[dict]) -> str:
    """The rows as a fixed-width text table, a header line naming the loop."""
    head = (f"{'scene':<6} {'tris':>9} {'res':>4} {'prb min/med/cold ms':>22} "
            f"{'update':>7} {'hlbvh min/med/cold ms':>22} {'update':>7} {'ratio':>6} "
            f"{'agree':>9}")
    lines = [f"hlbvh prb benchmark ({mi.variant()}, {SPP} spp, max_depth {MAX_DEPTH}, "
             f"Adam on the flag's vertices; ratio = prb median / hlbvh median)",
             head, "-" * len(head)]
    for r in rows:
        prb, ours = (f"{r[f'{n}_min_ms']:.0f}/{r[f'{n}_median_ms']:.0f}/"
                     f"{r[f'{n}_cold_ms']:.0f}" for n in ("prb", "hlbvh"))
        lines.append(
            f"{r['scene']:<6} {r['triangles']:>9} {r['resolution']:>4} {prb:>22} "
            f"{r['prb_update_ms']:>7.1f} {ours:>22} {r['hlbvh_update_ms']:>7.1f} "
            f"{r['ratio']:>5.2f}x {100 * r['agree']:>8.4f}%")
    return "\n".join(lines)
