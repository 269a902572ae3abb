"""The plots of the comparison harness, drawn with matplotlib's Agg canvas (no display,
no pyplot state) and written as PNG atomically; each plot function returns the path.

- :func:`plot_per_frame`: build or frame time per frame, native vs hlbvh.
- :func:`plot_build_vs_sah`: build time against SAH cost per builder setting, the Pareto
  front (:func:`pareto_front`) marked: the settings no other setting beats on both.
- :func:`plot_frame_time_vs_spp`: frame time (build + render) against samples per pixel
  per setting and native, the measured points joined, the spp where native becomes
  faster (:func:`hlbvh.comparison.crossover.crossover_spp`) marked and in the legend.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FormatStrFormatter, MaxNLocator

from hlbvh.comparison.crossover import crossover_spp, describe
from hlbvh.render.images import atomic_output

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


def plot_per_frame(
    path, frames: Sequence[int], native_ms: Sequence[float], hlbvh_ms: Sequence[float],
    quantity: str = "build time", title: str = "Build time per frame",
    native_label: str = "native rebuild",
) -> Path:
    """``quantity`` in ms per frame, native and hlbvh one line each, how many times
    faster hlbvh is (median over median) in the legend."""
    frames_, native = _paired(frames, native_ms, "frames", "native_ms")
    _, ours = _paired(frames, hlbvh_ms, "frames", "hlbvh_ms")
    figure, axes = _figure(title)
    ratio = np.median(native) / np.median(ours) if np.median(ours) > 0 else math.inf
    axes.plot(frames_, native, label=native_label, **_NATIVE_STYLE)
    speed = (f"{ratio:.3g}x faster" if ratio >= 1 else
             f"{1 / ratio:.3g}x slower" if ratio > 0 else "native's is zero")
    axes.plot(frames_, ours, marker="o", label=f"hlbvh (median {speed})")
    axes.set_xlabel("frame")
    axes.xaxis.set_major_locator(MaxNLocator(integer=True))
    axes.set_ylabel(f"{quantity} [ms]")
    axes.set_ylim(bottom=0)
    axes.legend()
    return _save(figure, path)


def plot_build_vs_sah(
    path, labels: Sequence[str], build_ms: Sequence[float], sah_cost: Sequence[float],
    title: str = "Build time vs tree quality", note: str | None = None,
) -> Path:
    """Each setting as a point (build ms, SAH cost), labelled; the Pareto front drawn as
    a step line through its points (lower left is better); ``note`` (the machine) under
    the plot."""
    build, sah = _paired(build_ms, sah_cost, "build_ms", "sah_cost")
    if len(labels) != len(build):
        raise ValueError(f"labels: {len(labels)} labels for {len(build)} points")
    front = pareto_front(build, sah)
    figure, axes = _figure(title, note)
    axes.scatter(build, sah, color="tab:gray", label="setting")
    axes.step(build[front], sah[front], where="post", color="tab:red", alpha=0.6)
    axes.scatter(build[front], sah[front], color="tab:red", zorder=3, label="Pareto front")
    # SAH costs within a hair of each other: a y range of at least 2% of the cost, so
    # the ticks read as the near-equal values they are, not as a 0.1% spread.
    low, high = float(np.min(sah)), float(np.max(sah))
    middle, half = (low + high) / 2, max((high - low) / 2 * 1.15, 0.01 * abs(high))
    if half > 0:
        axes.set_ylim(middle - half, middle + half)
    # Labels of points that lie close together on the axes are stacked, not drawn on
    # each other.
    x_span = max(float(np.ptp(build)), 1e-9)
    y_span = 2 * half if half > 0 else 1.0
    placed = []
    for k in np.lexsort((sah, build)):
        near = sum(1 for x, y in placed
                   if abs(x - build[k]) <= 0.08 * x_span and abs(y - sah[k]) <= 0.05 * y_span)
        axes.annotate(str(labels[k]), (build[k], sah[k]), textcoords="offset points",
                      xytext=(4, 4 + 10 * near), fontsize=8)
        placed.append((build[k], sah[k]))
    axes.ticklabel_format(axis="y", useOffset=False)
    axes.set_xlabel("build time [ms]")
    axes.set_ylabel("SAH cost")
    axes.legend()
    return _save(figure, path)


def plot_frame_time_vs_spp(
    path, spp: Sequence[float], frame_ms: Mapping[str, Sequence[float]],
    native: str = "native", title: str = "Frame time vs samples per pixel",
    note: str | None = None,
) -> Path:
    """Frame time (build + render) against spp for every setting in ``frame_ms`` (label
    -> ms at each ``spp``), native dashed.

    Only measured points are drawn, joined by straight segments on a linear spp axis
    (frame time is linear in spp between them: the segments are what
    :func:`hlbvh.comparison.crossover.crossover_spp` interpolates, so a marked crossover
    lies on both lines). Each setting's crossover is written in its legend entry, so no
    two labels can overlap; ``note`` (the machine: CPU model, cores) is written under
    the plot.
    """
    figure = frame_time_figure(spp, frame_ms, native, title, note)
    return _save(figure, path)


def frame_time_figure(spp, frame_ms, native="native", title="Frame time vs samples per pixel",
                      note=None) -> Figure:
    """The figure :func:`plot_frame_time_vs_spp` saves."""
    if native not in frame_ms:
        raise ValueError(f"frame_ms: no {native!r} entry to compare the settings with")
    samples, native_ms = _paired(spp, frame_ms[native], "spp", f"frame_ms[{native!r}]")
    if not (np.all(samples > 0) and np.all(np.diff(samples) > 0)):
        raise ValueError(f"spp={samples.tolist()}: expected positive, strictly increasing values")
    figure, axes = _figure(title, note)
    axes.plot(samples, native_ms, label=native, **_NATIVE_STYLE)
    for label, series in frame_ms.items():
        if label == native:
            continue
        _, ours = _paired(spp, series, "spp", f"frame_ms[{label!r}]")
        (line,) = axes.plot(samples, ours, marker="o",
                            label=f"{label}: native faster from {describe(samples, ours, native_ms)}")
        crossing = crossover_spp(samples, ours, native_ms)
        if crossing is not None:
            at = float(np.interp(crossing, samples, native_ms))
            axes.plot([crossing], [at], marker="X", markersize=10, linestyle="none",
                      color=line.get_color())
    axes.set_xticks(samples)
    axes.xaxis.set_major_formatter(FormatStrFormatter("%g"))
    axes.set_xlim(0, samples[-1] * 1.04)
    axes.set_xlabel("samples per pixel (measured at the ticks; X: crossover)")
    axes.set_ylabel("frame time [ms]")
    axes.set_ylim(bottom=0)
    axes.legend(fontsize=8, loc="upper left")
    return figure


def _paired(a: Sequence[float], b: Sequence[float], name_a: str, name_b: str):
    """Two equally long, non-empty 1-D float64 arrays."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.ndim != 1 or b.ndim != 1 or len(a) != len(b) or len(a) == 0:
        raise ValueError(
            f"{name_a} and {name_b}: expected two non-empty lists of equal length, "
            f"got shapes {a.shape} and {b.shape}"
        )
    return a, b


def _figure(title: str, note: str | None = None):
    figure = Figure(figsize=(7, 4.5), dpi=100, layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    axes.set_title(title)
    if note:
        figure.supxlabel(note, fontsize=8, color="dimgray")
    axes.grid(True, alpha=0.3)
    return figure, axes


def _save(figure: Figure, path) -> Path:
    path = Path(path)
    with atomic_output(path) as temporary:
        figure.savefig(temporary, format="png")
    return path
