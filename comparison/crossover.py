"""The samples per pixel from which Mitsuba's native accelerator is faster per frame
than ours: the one definition the frame benchmark, the sweep and their plots share.

A frame costs a build (constant in spp) plus a render (proportional to spp), so
between two measured spp the frame time is a straight line and linear interpolation
between the measured medians is exact there. The crossover is where the two
interpolated lines first meet, going up in spp; it depends only on the two measured spp
around it. Outside the measured range nothing is claimed (``None``): an extrapolated
crossover would read as a measurement.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def crossover_spp(
    spp: Sequence[float], ours_ms: Sequence[float], native_ms: Sequence[float]
) -> float | None:
    """The samples per pixel at which native becomes at least as fast per frame as ours.

    Args:
        spp: measured samples per pixel, strictly increasing.
        ours_ms, native_ms: frame times at those spp.

    Returns:
        The first spp where ``ours_ms - native_ms`` goes from negative to zero or
        positive, linearly interpolated; ``None`` when there is none inside the measured
        range (ours is faster at every spp, or native already at the smallest: compare
        the first entries to tell which, see :func:`describe`).

    Raises:
        ValueError: the lists differ in length, are empty, or ``spp`` is not increasing.
    """
    spp, ours, native = (np.asarray(v, dtype=np.float64) for v in (spp, ours_ms, native_ms))
    if not (spp.ndim == ours.ndim == native.ndim == 1 and len(spp) == len(ours) == len(native)
            and len(spp)):
        raise ValueError(f"spp, ours_ms, native_ms: expected three non-empty lists of equal "
                         f"length, got shapes {spp.shape}, {ours.shape}, {native.shape}")
    if not np.all(np.diff(spp) > 0):
        raise ValueError(f"spp={spp.tolist()}: expected strictly increasing values")
    gap = ours - native
    for i in range(len(gap) - 1):
        if gap[i] < 0 <= gap[i + 1]:
            return float(spp[i] + (spp[i + 1] - spp[i]) * (-gap[i]) / (gap[i + 1] - gap[i]))
    return None


def describe(spp: Sequence[float], ours_ms: Sequence[float],
             native_ms: Sequence[float]) -> str:
    """The crossover in words for tables and legends: ``"4.24 spp"``, ``"< 1 spp"``
    (native is at least as fast at every measured spp) or ``"> 16 spp"`` (ours is faster
    at every measured spp)."""
    crossing = crossover_spp(spp, ours_ms, native_ms)
    if crossing is not None:
        return f"{crossing:.3g} spp"
    if ours_ms[0] >= native_ms[0]:
        return f"< {spp[0]:g} spp"
    return f"> {spp[-1]:g} spp"
