"""Motion-blur benchmark: a frame of an animation with an open shutter, rendered three
ways side by side in one process, and our still frame beside them.

- ``ours blurred``: our accelerator traces every ray at its time through the moving
  meshes' keys (``--motion-keys`` intervals: a build and a refit per key);
- ``ours sub-frames`` and ``native sub-frames``: the mean of ``--sub-frames`` renders
  of the geometry at stratified times, spp over the sub-frames each (an update of our
  accelerator, or Mitsuba's whole-scene rebuild, per sub-frame): the same estimator in
  expectation, what a Mitsuba user does today;
- ``ours still``: the frame at its instant (shutter closed), at the same spp.

Each time is a whole frame (geometry, keys, updates, render; everything between two
images), the minimum and median of ``--repeats`` frames after one that compiles, the
ways alternating frame by frame so that all see the same load. The keyed trees'
memory is reported beside the still tree's of the same meshes (``(S+1)x`` the slots,
plus the keys' positions).

Run: ``python -m hlbvh.comparison.bench_blur [--scene world] [--triangles N]
[--resolution WxH] [--spp N] [--shutter 0.5] [--motion-keys S] [--sub-frames K]
[--repeats R]``.
"""

from __future__ import annotations

import argparse
import statistics

import drjit as dr

from hlbvh import scenes
from hlbvh.comparison.machine import cpu_model
from hlbvh.kernels.packing import packed_records
from hlbvh.render.frame import FrameRenderer
from hlbvh.render.settings import RenderSettings
from hlbvh.timing import timed

WAYS = ("ours blurred", "ours sub-frames", "native sub-frames", "ours still")


def run(scene: str, triangles: int, resolution: tuple, spp: int, shutter: float,
        motion_keys: int, sub_frames: int, repeats: int) -> dict:
    """Time each way over ``repeats`` warm frames; returns ``{way: [ms, ...]}`` and the
    memory figures."""
    animation = scenes.get(scene, triangles=triangles, frames=repeats + 2)
    blur = dict(shutter=(-shutter / 2, shutter / 2), motion_keys=motion_keys,
                sub_frames=sub_frames)
    base = dict(resolution=resolution, spp=spp)
    renderers = {
        "ours blurred": FrameRenderer(animation, RenderSettings(**base, **blur,
                                                                moving_accel="hlbvh")),
        "ours sub-frames": FrameRenderer(animation, RenderSettings(**base, **blur,
                                                                   moving_accel="hlbvh")),
        "native sub-frames": FrameRenderer(animation, RenderSettings(**base, **blur,
                                                                     accel="native")),
        "ours still": FrameRenderer(animation, RenderSettings(**base)),
    }
    times = {way: [] for way in WAYS}
    for i in range(repeats + 1):
        for way in WAYS:
            renderer = renderers[way]
            if way == "ours sub-frames":
                ms, image = timed(lambda: renderer.accumulated(i, i, spp))
            else:
                ms, (image, _) = timed(lambda: renderer.render(i))
            dr.eval(image)
            if i:  # the first frame compiles
                times[way].append(ms)
    group = renderers["ours blurred"].integrator.scene_accel.dynamic
    keyed_mb = 4 * (dr.width(group.keyed.records) + dr.width(group.key_points)) / 2**20
    still_mb = 4 * dr.width(packed_records(group.keyed.bvh)[0]) / 2**20
    return dict(times=times, keyed_mb=keyed_mb, still_mb=still_mb)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hlbvh.comparison.bench_blur",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="world")
    parser.add_argument("--triangles", type=int, default=1_000_000)
    parser.add_argument("--resolution", default="480x270", help="WxH")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--shutter", type=float, default=0.5, help="frames, centred")
    parser.add_argument("--motion-keys", type=int, default=1)
    parser.add_argument("--sub-frames", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.resolution.split("x"))
    result = run(args.scene, args.triangles, (width, height), args.spp, args.shutter,
                 args.motion_keys, args.sub_frames, args.repeats)
    times = result["times"]
    blurred = statistics.median(times["ours blurred"])
    print(f"{args.scene} {args.triangles} triangles, {width}x{height}, {args.spp} spp, "
          f"shutter {args.shutter} frame, S={args.motion_keys}, K={args.sub_frames}; "
          f"CPU: {cpu_model()}")
    print(f"{'way':20s} {'min ms':>9s} {'median ms':>10s} {'x ours blurred':>15s}")
    for way in WAYS:
        median = statistics.median(times[way])
        print(f"{way:20s} {min(times[way]):9.1f} {median:10.1f} {median / blurred:15.2f}")
    print(f"moving meshes' keyed tree {result['keyed_mb']:.1f} MB (slots at every key and "
          f"the keys' positions), still tree {result['still_mb']:.1f} MB: "
          f"{result['keyed_mb'] / result['still_mb']:.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
