"""A USD stage's frames and time codes: frame ``i`` is time code ``startTimeCode + i``,
up to ``endTimeCode`` included, as pxr reports them (an ``endTimeCode`` authored alone
starts at 0); a stage without an authored ``endTimeCode`` has one frame, at its start
time code. Also where attributes take their authored values (:func:`sample_times`), so
a check over the frames costs what the stage authors, not how many frames it holds."""

from __future__ import annotations

import math

from .prims import Gf, UsdGeom

#: The most frames a stage's time range may hold: frame ``i`` renders with seed
#: ``--seed + i``, and seeds are 32-bit.
MAX_FRAMES = 2**32

#: The largest time code magnitude taken: past it, float64 time codes no longer step by
#: 1, so ``startTimeCode + i`` would not name distinct frames.
MAX_TIME_CODE = 2.0**52


def check_time_codes(stage, where: str) -> None:
    """Refuse a stage whose start or end time code is not finite, lies past
    :data:`MAX_TIME_CODE`, or whose range holds more than :data:`MAX_FRAMES` frames, in
    one short line (such a range cannot be counted or rendered frame by frame)."""
    start, end = float(stage.GetStartTimeCode()), float(stage.GetEndTimeCode())
    for name, value in (("startTimeCode", start), ("endTimeCode", end)):
        if not math.isfinite(value) or abs(value) > MAX_TIME_CODE:
            raise ValueError(f"{where}: {name} {value:.6g}: expected a finite time code "
                             f"within +-2^52 (frame i is at startTimeCode + i)")
    if end - start >= MAX_FRAMES:
        raise ValueError(f"{where}: startTimeCode..endTimeCode {start:.6g}..{end:.6g} holds "
                         f"more than 2^32 frames (a frame's seed is 32-bit)")


def frame_range(stage, where: str) -> tuple[float, int]:
    """``(start time code, frame count)`` of a stage checked by
    :func:`check_time_codes`; a ValueError naming ``where`` when its ``endTimeCode`` is
    before its ``startTimeCode``."""
    check_time_codes(stage, where)
    start = float(stage.GetStartTimeCode())
    # pxr's range: an endTimeCode authored alone runs from time code 0 to it
    # (HasAuthoredTimeCodeRange needs both); a startTimeCode alone is one frame.
    if not stage.HasAuthoredMetadata("endTimeCode"):
        return start, 1
    end = float(stage.GetEndTimeCode())
    if end < start:
        raise ValueError(f"{where}: endTimeCode {end:g} is before startTimeCode {start:g}")
    return start, int(math.floor(end - start)) + 1


def transform_attributes(prim) -> list:
    """The xformOp attributes of ``prim`` and of its ancestors: what its world
    transform is computed from."""
    found = []
    while prim and not prim.IsPseudoRoot():
        xformable = UsdGeom.Xformable(prim)
        if xformable:
            found += [op.GetAttr() for op in xformable.GetOrderedXformOps()]
        prim = prim.GetParent()
    return found


def sample_times(attributes, first: float, last: float) -> list[float]:
    """``first``, ``last`` and every time sample of ``attributes`` between them,
    sorted: the time codes where the attributes take their authored values (between
    two samples a value is interpolated, outside them held), so a check made there
    costs what the stage authors, not how many frames its range holds."""
    times = {first, last}
    interval = Gf.Interval(first, last)
    for attribute in attributes:
        times.update(attribute.GetTimeSamplesInInterval(interval))
    return sorted(times)
