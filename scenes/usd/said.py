"""What a USD stage says, said once: USD's own diagnostics (multi-line C++ output on
stderr) as one warning line per distinct message, and references or payloads that do
not resolve as one line per missing asset, MaterialX documents (which usd-core cannot
read) as one line per file naming the materials bound there."""

from __future__ import annotations

import functools
import re
import sys
from pathlib import Path

import numpy as np

from .prims import _stderr_captured


def grouped_arcs(arcs: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """``(who, what USD said)`` once per distinct unresolved asset, sorted: ``who`` is
    the prim's path, or the first path and how many other prims reference the same
    missing file (548 references to one missing file are one line, the same line for
    every command)."""
    grouped: dict[str, list[str]] = {}
    for path, said in arcs:
        grouped.setdefault(said, []).append(path)
    result = []
    for said, paths in sorted(grouped.items()):
        paths.sort()
        who = paths[0] if len(paths) == 1 else f"{paths[0]} and {len(paths) - 1} other prims"
        result.append((who, said))
    return result


def materialx_arcs(arcs: list[tuple[str, str]]) -> tuple[dict[str, list[str]], list]:
    """``({.mtlx file: the prim paths referencing it}, the other arcs)`` of ``(prim
    path, what USD said)`` arcs: a reference to a MaterialX document that exists does
    not compose because usd-core (pxr's wheels) has no ``.mtlx`` file format (pxr
    built without MaterialX), not because the file is missing; it is said as such
    (:func:`materialx_line`)."""
    found, others = {}, []
    for who, said in arcs:
        match = re.search(r"@([^@]*\.mtlx)@", said)
        if match and Path(match.group(1)).is_file():
            found.setdefault(match.group(1), []).append(who)
        else:
            others.append((who, said))
    return found, others


def materialx_line(where: str, file: str, prims: list[str], bound: list[str]) -> str:
    """The line for the references (on ``prims``) to MaterialX document ``file``,
    naming the materials meshes are bound to under them (``bound``)."""
    prims = sorted(prims)
    who = prims[0] if len(prims) == 1 else f"{prims[0]} and {len(prims) - 1} other prims"
    named = (f"the materials bound there ({bound[0]}"
             f"{f' and {len(bound) - 1} more' if len(bound) > 1 else ''})"
             if bound else "its materials")
    return (f"{where}: {who}: MaterialX file {Path(file).name!r} is not read: usd-core "
            f"reads no .mtlx (no MaterialX file format in pxr's wheels), so {named} do "
            f"not exist on the stage and have no UsdPreviewSurface to fall back on; "
            f"their meshes render their displayColor, else grey")


def usd_quiet(method):
    """``method`` of a :class:`hlbvh.scenes.usd.UsdScene` with USD's own diagnostics (multi-line C++
    output on stderr) said as one warning line per distinct message, once per stage,
    and numpy's floating-point warnings off (the values that matter are checked and
    named); lines already ours (``hlbvh: ...``) pass through unchanged."""
    @functools.wraps(method)
    def wrapped(self, *args, **kwargs):
        with np.errstate(all="ignore"), _stderr_captured() as said:
            result = method(self, *args, **kwargs)
        for line in said:
            if line.startswith("hlbvh: "):
                print(line, file=sys.stderr)
            elif line.strip():
                text = " ".join(line.split(" -- ", 1)[-1].split())
                self._warn_once(f"{self._where}: USD says: {text[:300]}")
        return result
    return wrapped


def nothing_renderable(where: str, unresolved: list[str], said: list[str]) -> ValueError:
    """The error of a stage (``where``) where nothing renders, saying why in short: the
    references or payloads that do not resolve (``unresolved``), and the first two
    lines ``said`` about what was seen and left out (a point instancer's reason)."""
    why = (f"; references or payloads that do not resolve: {', '.join(unresolved)}"
           if unresolved else "")
    skipped = [line.removeprefix(f"{where}: ") for line in said
               if "not rendered" in line and "reference or payload" not in line]
    if skipped:
        more = f" (and {len(skipped) - 2} more)" if len(skipped) > 2 else ""
        why += "; " + "; ".join(skipped[:2]) + more
    return ValueError(f"{where}: nothing renderable (no visible UsdGeom.Mesh "
                      f"of purpose default or render){why}")
