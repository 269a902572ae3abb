"""The ``hlbvh`` command line: doctor, render, compare, sweep, bench."""

from __future__ import annotations

import argparse
import sys


class UserError(Exception):
    """A mistake in what the user asked for: printed as one line, exit status 2."""


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
    # A real kernel: LLVM 15 only fails here, not at import.
    x = dr.arange(mi.Float, 1024)
    ok = float(dr.sum(dr.minimum(x, 3.5))[0]) == 3.5 * 1020 + 0 + 1 + 2 + 3
    print(f"kernel     {'ok' if ok else 'WRONG RESULT'}")
    return 0 if ok else 1


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="hlbvh", description=__doc__)
    sub = ap.add_subparsers(dest="command", required=True)
    sub.add_parser("doctor", help="report Dr.Jit, Mitsuba, the libLLVM in use, variants")
    return ap


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        return {"doctor": _doctor}[args.command](args)
    except UserError as e:
        print(f"hlbvh {args.command}: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
