"""The one wall clock of hlbvh's timings: milliseconds measured after the device
finished its queued work, so that a time covers the kernels it launched and not only
their recording."""

from __future__ import annotations

import time

import drjit as dr


def clock_ms() -> float:
    """Milliseconds since an arbitrary origin, read after ``dr.sync_thread()``."""
    dr.sync_thread()
    return time.perf_counter() * 1e3


def timed(fn, *args, **kwargs):
    """``(ms, fn(*args, **kwargs))``: the wall time of the call between two
    :func:`clock_ms` readings."""
    start = clock_ms()
    result = fn(*args, **kwargs)
    return clock_ms() - start, result


def timed_cpu(fn, *args, **kwargs):
    """``(wall ms, process CPU ms, fn(*args, **kwargs))``: :func:`timed` with the CPU
    time of every thread of the process beside it (how busy the cores were)."""
    cpu = time.process_time()
    ms, result = timed(fn, *args, **kwargs)
    return ms, (time.process_time() - cpu) * 1e3, result
