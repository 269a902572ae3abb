"""``hlbvh bench``: the standard benchmark suite, every number a ratio to Mitsuba's
native builder or traversal measured side by side in one process, warm and cold.

    hlbvh bench build [--sizes 100000,1000000] [--repeats 5] [--json]
    hlbvh bench trace [--sizes 1000000] [--resolution 512] [--json]
    hlbvh bench frame [...]           (see hlbvh.comparison.bench_frame)
"""

from __future__ import annotations

import importlib
import json

_SUITES = {
    "build": "hlbvh.comparison.bench_build",
    "trace": "hlbvh.comparison.bench_trace",
    "frame": "hlbvh.comparison.bench_frame",
}


def configure(parser) -> None:
    parser.add_argument("suite", choices=sorted(_SUITES), help="which benchmark to run")
    parser.add_argument("--sizes", default=None,
                        help="triangle counts, comma separated (suite default when omitted)")
    parser.add_argument("--repeats", type=int, default=5, help="warm runs after the cold one")
    parser.add_argument("--builder", default=None, help="builders, comma separated")
    parser.add_argument("--resolution", type=int, default=512, help="image side in pixels")
    parser.add_argument("--json", action="store_true", help="print JSON rows, not a table")


def run(args) -> int:
    module = importlib.import_module(_SUITES[args.suite])
    kwargs = {"repeats": args.repeats}
    if args.sizes:
        kwargs["sizes"] = [int(s) for s in args.sizes.split(",")]
    if args.suite == "build":
        if args.builder:
            kwargs["builders"] = args.builder.split(",")
    else:
        kwargs["resolution"] = args.resolution
        if args.builder:
            kwargs["builder"] = args.builder
    rows = module.run(**kwargs)
    print(json.dumps(rows, indent=1, default=str) if args.json else module.format_table(rows))
    return 0
