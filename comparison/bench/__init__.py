"""``hlbvh bench``: the standard benchmark suite, every number a ratio to Mitsuba's
native builder or traversal measured side by side in one process, warm and cold.

    hlbvh bench build [--sizes 100000,1000000] [--repeats 5] [--json]
    hlbvh bench trace [--sizes 1000000] [--resolution 512] [--json]
    hlbvh bench frame [--scenes world,flock:birds=1000] [--no-native] [...]
                      [--shutter 0.5 [--motion-keys S] [--sub-frames K] [--equal-error]]
                                      (see hlbvh.comparison.bench.frame)
"""

from __future__ import annotations

import importlib
import json

from hlbvh.errors import UserError
from hlbvh.kernels.bvh import BUILDERS
from hlbvh.cli.options import choice, parse_resolution
from hlbvh.errors import int_flag
from hlbvh.scenes.animated import MAX_TRIANGLES

_SUITES = {
    "build": "hlbvh.comparison.bench.build",
    "trace": "hlbvh.comparison.bench.trace",
    "frame": "hlbvh.comparison.bench.frame",
    "prb": "hlbvh.comparison.bench.prb",
}


#: What ``bench frame --integrator`` takes: the integrators that render animations.
BENCH_INTEGRATORS = ("path", "direct", "volpath")


def configure(parser) -> None:
    parser.add_argument("suite", choices=sorted(_SUITES), help="which benchmark to run")
    parser.add_argument("--sizes", default=None,
                        help="triangle counts, comma separated (suite default when omitted)")
    parser.add_argument("--repeats", default="5", help="warm runs after the cold one (default 5)")
    parser.add_argument("--builder", default=None,
                        help=f"builders, comma separated ({', '.join(BUILDERS)})")
    parser.add_argument("--resolution", default="512",
                        help="image side in pixels (default 512); bench frame also takes "
                             "WxH (1920x1080)")
    parser.add_argument("--spp", default=None,
                        help="bench frame: samples per pixel, comma separated (default "
                             "1,4,16)")
    parser.add_argument("--scenes", default=None,
                        help="bench frame: procedural scenes, comma separated, each with its "
                             "options as NAME:KEY=VALUE+KEY=VALUE (e.g. "
                             "flock:birds=1000,rigid:instanced=true)")
    parser.add_argument("--integrator", default=None,
                        help="bench frame: path, direct or volpath for every scene (default: "
                             "the one the scene's own integrator runs as, else path)")
    parser.add_argument("--no-native", action="store_true",
                        help="bench frame: hlbvh's frames alone (native's render of "
                             "scenes of many instances takes minutes)")
    parser.add_argument("--shutter", default=None,
                        help="bench frame: motion blur too, the shutter as hlbvh render "
                             "takes it (0.5, or --shutter=-0.25:0.25): our blurred frame "
                             "against native's and our own sub-frame accumulation and our "
                             "still frame")
    parser.add_argument("--motion-keys", default=None,
                        help="bench frame --shutter: key intervals over the shutter")
    parser.add_argument("--sub-frames", default=None,
                        help="bench frame --shutter: sub-frames of the accumulations")
    parser.add_argument("--equal-error", action="store_true",
                        help="bench frame --shutter: time to equal error against a "
                             "256-spp reference (minutes on world)")
    parser.add_argument("--json", action="store_true", help="print JSON rows, not a table")


def run(args) -> int:
    """``hlbvh bench``: every option checked (one line naming it, exit status 2), then
    the suite's ``run``."""
    kwargs = {"repeats": int_flag("--repeats", args.repeats, least=1)}
    if args.sizes is not None:
        kwargs["sizes"] = [int_flag("--sizes", s.strip(), least=1, most=MAX_TRIANGLES)
                           for s in args.sizes.split(",")]
    builders = None if args.builder is None else [b.strip() for b in args.builder.split(",")]
    for builder in builders or ():
        if builder not in BUILDERS:
            raise UserError(f"--builder {args.builder!r}: {builder!r} is not one of "
                            f"{', '.join(BUILDERS)}")
    if args.suite == "build":
        if builders:
            kwargs["builders"] = builders
    elif args.suite == "frame":
        kwargs["resolution"] = parse_resolution(args.resolution)
    else:
        kwargs["resolution"] = int_flag("--resolution", args.resolution, least=1)
    if args.suite != "build" and builders:
        if len(builders) > 1:
            raise UserError(f"--builder {args.builder!r}: bench {args.suite} takes one builder")
        kwargs["builder"] = builders[0]
    if args.suite != "frame" and (args.scenes is not None or args.no_native
                                  or args.spp is not None or args.integrator is not None
                                  or args.shutter is not None or args.motion_keys is not None
                                  or args.sub_frames is not None or args.equal_error):
        raise UserError(f"--scenes, --spp, --integrator, --no-native, --shutter, "
                        f"--motion-keys, --sub-frames and --equal-error are for bench frame, "
                        f"not bench {args.suite}")
    if args.integrator is not None:
        kwargs["integrator"] = choice("--integrator", args.integrator, BENCH_INTEGRATORS)
    if args.spp is not None:
        kwargs["spps"] = [int_flag("--spp", s.strip(), least=1, most=2**20)
                          for s in args.spp.split(",")]
    if args.scenes is not None:
        kwargs["scenes"] = _scene_specs(args.scenes)
    if args.no_native:
        kwargs["native"] = False
    module = importlib.import_module(_SUITES[args.suite])
    if args.suite == "frame":
        kwargs.update(module.blur_options(args))
    rows = module.run(**kwargs)
    print(json.dumps(rows, indent=1, default=str) if args.json else module.format_table(rows))
    return 0


def _scene_specs(text: str) -> list[str]:
    """``--scenes``: comma-separated scenes, a scene's own options joined by ``+``
    (``rigid:instanced=true+objects=40``: commas separate scenes here), each checked."""
    from hlbvh import scenes

    specs = [part.strip().replace("+", ",") for part in text.split(",") if part.strip()]
    if not specs:
        raise UserError(f"--scenes {text!r}: no scene named")
    for spec in specs:
        try:
            scenes.parse(spec)
        except ValueError as error:
            raise UserError(f"--scenes: {error}") from None
    return specs
