"""Motion-blur benchmark of one scene at one spp: ``hlbvh bench frame --shutter``'s
four ways (:func:`hlbvh.comparison.bench.frame.blur_runs`: our blurred frame, our own
and native's sub-frame accumulations, our still frame, side by side in one process)
without the frame benchmark's build, drift and still-frame runs, and optionally the
time to equal error (:func:`hlbvh.comparison.bench.frame.time_to_equal_error`).

Run: ``python -m hlbvh.comparison.bench.blur [--scene world] [--triangles N]
[--resolution WxH] [--spp N] [--shutter 0.5] [--motion-keys S] [--sub-frames K]
[--repeats R] [--equal-error]``.
"""

from __future__ import annotations

import argparse
import os

from hlbvh import scenes
from hlbvh.comparison.bench.frame import (blur_renderers, blur_row, blur_runs, blur_table,
                                          time_to_equal_error)
from hlbvh.comparison.machine import cpu_model


def run(scene: str, triangles: int, resolution: tuple, spp: int, shutter: float,
        motion_keys: int, sub_frames: int, repeats: int, equal_error: bool = False) -> dict:
    """The row of ``scene`` at ``spp`` (``bench frame``'s blur keys, and
    ``equal_error`` where asked), the shutter ``shutter`` frames centred on each
    frame."""
    animation = scenes.get(scene, triangles=triangles, frames=repeats + 2)
    window = (-shutter / 2, shutter / 2)
    renderers = blur_renderers(animation, resolution, window, motion_keys, sub_frames)
    row = {"scene": scene, "triangles": renderers["ours blurred"].triangle_count(), "spp": spp,
           **blur_row(blur_runs(renderers, [spp], repeats), spp, window, motion_keys,
                      sub_frames)}
    if equal_error:
        row["equal_error"] = time_to_equal_error(renderers)
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hlbvh.comparison.bench.blur",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="world")
    parser.add_argument("--triangles", type=int, default=1_000_000)
    parser.add_argument("--resolution", default="480x270", help="WxH")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--shutter", type=float, default=0.5, help="frames, centred")
    parser.add_argument("--motion-keys", type=int, default=1)
    parser.add_argument("--sub-frames", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--equal-error", action="store_true",
                        help="time to equal error against our blurred frame at 256 spp")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.resolution.split("x"))
    row = run(args.scene, args.triangles, (width, height), args.spp, args.shutter,
              args.motion_keys, args.sub_frames, args.repeats, args.equal_error)
    print("\n".join(blur_table([row])[1:]))
    print(f"{width}x{height}; CPU: {cpu_model()}; load average {os.getloadavg()[0]:.1f} "
          "at the end")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
