"""The plots of the comparison harness, drawn with matplotlib's Agg canvas (no display,
no pyplot state) and written as PNG atomically; each plot function returns the path.

- :func:`plot_build_times`: build ms per frame, native rebuild vs hlbvh.
- :func:`plot_build_vs_sah`: build time against SAH cost per builder setting, the Pareto
  front (:func:`pareto_front`) marked: the settings no other setting beats on both.
- :func:`plot_frame_time_vs_spp`: frame time (build + render) against samples per pixel
  per setting and native, with the spp where native becomes faster
  (:func:`crossover_spp`) marked.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from hlbvh.images import atomic_output

_NATIVE_STYLE = {"color": "black", "linestyle": "--", "marker": "s"}


def pareto_front(x: Sequence[float], y: Sequence[float]) -> list[int]:
    """Indices of the points no other point dominates, both coordinates minimised.

    A point dominates another when it is no worse in both coordinates and better in one;
    equal points do not dominate each other, so both stay on the front. Points with a
    non-finite coordinate are never on the front.

    Args:
        x, y: the two costs (e.g. build ms and SAH cost), one entry per setting.

    Returns:
        The indices on the front, sorted by ``x`` (then ``y``).
    """
    x, y = _paired(x, y, "x", "y")
    finite = np.isfinite(x) & np.isfinite(y)
    no_worse = (x[None, :] <= x[:, None]) & (y[None, :] <= y[:, None])
    better = (x[None, :] < x[:, None]) | (y[None, :] < y[:, None])
    dominated = np.any(no_worse & better & finite[None, :], axis=1)
    front = np.flatnonzero(finite & ~dominated)
    return sorted(front.tolist(), key=lambda index: (x[index], y[index]))


def crossover_spp(
    spp: Sequence[float], ours_ms: Sequence[float], native_ms: Sequence[float]
) -> float | None:
    """The samples per pixel at which native becomes at least as fast per frame as ours.

    Frame time is build time plus a render time proportional to spp, so between two
    measured spp it is interpolated linearly; the crossover is the first spp where
    ``ours_ms - native_ms`` goes from negative to zero or positive.

    Args:
        spp: measured samples per pixel, strictly increasing.
        ours_ms, native_ms: frame times at those spp.

    Returns:
        The crossover spp, or ``None`` when there is none inside the measured range (ours
        is faster at every spp, or native already at the smallest: compare the first
        entries to tell which).
    """
    spp, ours = _paired(spp, ours_ms, "spp", "ours_ms")
    _, native = _paired(spp, native_ms, "spp", "native_ms")
    if not np.all(np.diff(spp) > 0):
        raise ValueError(f"spp={spp.tolist()}: expected strictly increasing values")
    gap = ours - native
    for i in range(len(gap) - 1):
        if gap[i] < 0 <= gap[i + 1]:
            return float(spp[i] + (spp[i + 1] - spp[i]) * (-gap[i]) / (gap[i + 1] - gap[i]))
    return None


def plot_build_times(
    path, frames: Sequence[int], native_ms: Sequence[float], hlbvh_ms: Sequence[float],
    title: str = "Build time per frame",
) -> Path:
    """Build ms per frame: native rebuild (``params.update()``) and hlbvh, one line
    each, the ratio in the legend."""
    frames_, native = _paired(frames, native_ms, "frames", "native_ms")
    _, ours = _paired(frames, hlbvh_ms, "frames", "hlbvh_ms")
    figure, axes = _figure(title)
    ratio = np.median(native) / np.median(ours) if np.median(ours) > 0 else math.inf
    axes.plot(frames_, native, label="native rebuild", **_NATIVE_STYLE)
    axes.plot(frames_, ours, marker="o", label=f"hlbvh (median {ratio:.3g}x faster)")
    axes.set_xlabel("frame")
    axes.xaxis.set_major_locator(MaxNLocator(integer=True))
    axes.set_ylabel("build time [ms]")
    axes.set_ylim(bottom=0)
    axes.legend()
    return _save(figure, path)


def plot_build_vs_sah(
    path, labels: Sequence[str], build_ms: Sequence[float], sah_cost: Sequence[float],
    title: str = "Build time vs tree quality",
) -> Path:
    """Each setting as a point (build ms, SAH cost), labelled; the Pareto front drawn as
    a step line through its points (lower left is better)."""
    build, sah = _paired(build_ms, sah_cost, "build_ms", "sah_cost")
    if len(labels) != len(build):
        raise ValueError(f"labels: {len(labels)} labels for {len(build)} points")
    front = pareto_front(build, sah)
    figure, axes = _figure(title)
    axes.scatter(build, sah, color="tab:gray", label="setting")
    axes.step(build[front], sah[front], where="post", color="tab:red", alpha=0.6)
    axes.scatter(build[front], sah[front], color="tab:red", zorder=3, label="Pareto front")
    for label, x, y in zip(labels, build, sah):
        axes.annotate(str(label), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    axes.set_xlabel("build time [ms]")
    axes.set_ylabel("SAH cost")
    axes.legend()
    return _save(figure, path)


def plot_frame_time_vs_spp(
    path, spp: Sequence[float], frame_ms: Mapping[str, Sequence[float]],
    native: str = "native", title: str = "Frame time vs samples per pixel",
) -> Path:
    """Frame time (build + render) against spp for every setting in ``frame_ms`` (label
    -> ms at each ``spp``), the ``native`` entry dashed; where a setting's line crosses
    native's, the crossover spp is marked and written."""
    if native not in frame_ms:
        raise ValueError(f"frame_ms: no {native!r} entry to compare the settings with")
    samples, native_ms = _paired(spp, frame_ms[native], "spp", f"frame_ms[{native!r}]")
    # Frame time is linear in spp: draw the piecewise-linear interpolation (curved on the
    # log axis), so the marked crossovers lie on the lines.
    if not (np.all(samples > 0) and np.all(np.diff(samples) > 0)):
        raise ValueError(f"spp={samples.tolist()}: expected positive, strictly increasing values")
    dense = np.geomspace(samples[0], samples[-1], 256)
    figure, axes = _figure(title)
    (line,) = axes.plot(dense, np.interp(dense, samples, native_ms), color="black", linestyle="--")
    axes.plot(samples, native_ms, color="black", marker="s", linestyle="none")
    line.set_label(native)
    for label, series in frame_ms.items():
        if label == native:
            continue
        _, ours = _paired(spp, series, "spp", f"frame_ms[{label!r}]")
        (line,) = axes.plot(dense, np.interp(dense, samples, ours), label=label)
        axes.plot(samples, ours, marker="o", linestyle="none", color=line.get_color())
        crossing = crossover_spp(samples, ours, native_ms)
        if crossing is not None:
            at = float(np.interp(crossing, samples, native_ms))
            axes.plot([crossing], [at], marker="X", markersize=11, color=line.get_color())
            axes.annotate(
                f"{crossing:.3g} spp", (crossing, at), textcoords="offset points",
                xytext=(6, -12), color=line.get_color(),
            )
    axes.set_xscale("log", base=2)
    axes.set_xlabel("samples per pixel")
    axes.set_ylabel("frame time [ms]")
    axes.set_ylim(bottom=0)
    axes.legend()
    return _save(figure, path)


def _paired(a: Sequence[float], b: Sequence[float], name_a: str, name_b: str):
    """Two equally long, non-empty 1-D float64 arrays."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.ndim != 1 or b.ndim != 1 or len(a) != len(b) or len(a) == 0:
        raise ValueError(
            f"{name_a} and {name_b}: expected two non-empty lists of equal length, "
            f"got shapes {a.shape} and {b.shape}"
        )
    return a, b


def _figure(title: str):
    figure = Figure(figsize=(7, 4.5), dpi=100, layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    axes.set_title(title)
    axes.grid(True, alpha=0.3)
    return figure, axes


def _save(figure: Figure, path) -> Path:
    path = Path(path)
    with atomic_output(path) as temporary:
        figure.savefig(temporary, format="png")
    return path
