"""The ``hlbvh`` command line: doctor, render, compare, sweep, bench."""

from __future__ import annotations

import argparse
import errno
import os
import sys

# The command line runs as hlbvh.cli.command, also through python -m hlbvh.cli.
from hlbvh.errors import UserError


def _doctor(args) -> int:
    import os

    import drjit as dr
    import mitsuba as mi

    import hlbvh
    from hlbvh import environment

    print(f"hlbvh      {hlbvh.__version__}")
    print(f"python     {sys.version.split()[0]}")
    print(f"drjit      {dr.__version__}")
    print(f"mitsuba    {mi.__version__}")
    print(f"libLLVM    {os.environ.get('DRJIT_LIBLLVM_PATH')}")
    print(f"LLVM ok    {dr.has_backend(dr.JitBackend.LLVM)}")
    print(f"CUDA ok    {dr.has_backend(dr.JitBackend.CUDA)}")
    print(f"variant    {mi.variant()}")
    print(f"variants   {', '.join(mi.variants())}")
    found = ", ".join(f"{p} (LLVM {m})" for m, p in environment.candidates())
    print(f"libLLVMs   {found or 'none found'}")
    print(f"usd-core   {_usd_core()}")
    # A real kernel: LLVM 15 only fails here, not at import.
    x = dr.arange(mi.Float, 1024)
    ok = float(dr.sum(dr.minimum(x, 3.5))[0]) == 3.5 * 1020 + 0 + 1 + 2 + 3
    print(f"kernel     {'ok' if ok else 'WRONG RESULT'}")
    return 0 if ok else 1


def _usd_core() -> str:
    """The installed usd-core (pxr), which USD stages need: its version and pxr's, or
    how to install it."""
    from importlib import metadata

    try:
        from pxr import Usd
    except ImportError:
        return "not installed (pip install usd-core)"
    try:
        package = metadata.version("usd-core")
    except metadata.PackageNotFoundError:  # pxr from another build (a DCC's, from source)
        package = "not from pip"
    return f"{package} (pxr {'.'.join(map(str, Usd.GetVersion()))})"


# Each verb lives in its own module with ``configure(parser)`` and ``run(args) -> int``;
# modules are imported only when their verb runs.
_VERBS = {
    "render": ("hlbvh.cli.render", "render an animation to EXR/PNG with per-frame statistics"),
    "compare": ("hlbvh.comparison.compare", "native vs hlbvh, frame by frame, with a report"),
    "sweep": ("hlbvh.comparison.sweep", "the speed/accuracy trade of builder settings"),
    "bench": ("hlbvh.comparison.bench", "build, trace, frame and prb benchmarks against native"),
}


def _parser() -> argparse.ArgumentParser:
    import importlib

    ap = argparse.ArgumentParser(prog="hlbvh", description=__doc__)
    sub = ap.add_subparsers(dest="command", required=True)
    doctor = "report Dr.Jit, Mitsuba, the libLLVM in use, variants, usd-core"
    sub.add_parser("doctor", help=doctor, description=doctor[0].upper() + doctor[1:])
    for verb, (module, help_text) in _VERBS.items():
        # the description a verb's configure() does not replace
        p = sub.add_parser(verb, help=help_text,
                           description=help_text[0].upper() + help_text[1:])
        try:
            importlib.import_module(module).configure(p)
        except ModuleNotFoundError as e:
            if e.name != module:
                raise
            p.set_defaults(_missing=module)
    return ap


def main(argv=None) -> int:
    import importlib

    from hlbvh.environment import end_of_start_up

    try:
        parser = _parser()
    except KeyboardInterrupt:
        print("hlbvh: interrupted", file=sys.stderr)
        return 130
    end_of_start_up()
    args = parser.parse_args(argv)
    try:
        if args.command == "doctor":
            return _doctor(args)
        if getattr(args, "_missing", None):
            raise UserError(f"'{args.command}' is not available in this build ({args._missing} is missing)")
        return importlib.import_module(_VERBS[args.command][0]).run(args)
    except UserError as e:
        print(f"hlbvh {args.command}: {e}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError) as e:
        # Errors about what the user gave (scene files, options, meshes): one line, no
        # traceback.
        print(f"hlbvh {args.command}: {e}", file=sys.stderr)
        return 2
    except OSError as error:
        if error.errno != errno.ENAMETOOLONG:
            raise
        print(f"hlbvh {args.command}: {_name_too_long(error.filename)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"hlbvh {args.command}: interrupted", file=sys.stderr)
        return 130
    except MemoryError as error:
        # numpy's "Unable to allocate 5.33 GiB for an array with shape ..." (a scene's
        # geometry too large for this machine): one line, as for every size the
        # options bound
        print(f"hlbvh {args.command}: out of memory ({error}); ask for less (--triangles, "
              f"--resolution, --spp) or use a machine with more memory", file=sys.stderr)
        return 2
    except Exception as error:
        # Dr.Jit re-raises a Ctrl-C that arrives inside a traced loop or a custom
        # operation as a RuntimeError caused by the KeyboardInterrupt.
        if not _interrupted(error):
            raise
        print(f"hlbvh {args.command}: interrupted", file=sys.stderr)
        return 130


def _name_too_long(path) -> str:
    """The line for a path the file system refuses as too long (``--out``, a scene, a
    file under them): the path shortened, its longest name's length in bytes."""
    text = os.fsdecode(path) if path is not None else ""
    longest = max((len(os.fsencode(name)) for name in text.split(os.sep)), default=0)
    shown = text if len(text) <= 80 else f"{text[:48]}...{text[-24:]}"
    return (f"path {shown!r} is too long for the file system ({len(os.fsencode(text))} "
            f"bytes, its longest name {longest} bytes; a name may hold at most 255 bytes "
            f"on most file systems)")


def _interrupted(error: BaseException) -> bool:
    """Whether ``error`` was raised from or during a ``KeyboardInterrupt``."""
    while error is not None:
        if isinstance(error, KeyboardInterrupt):
            return True
        error = error.__cause__ or error.__context__
    return False


if __name__ == "__main__":
    sys.exit(main())
