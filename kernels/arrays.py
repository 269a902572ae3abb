"""The Dr.Jit array types of the backend an input lives on.

Kernels never name ``drjit.llvm`` or ``drjit.cuda``: they ask this module for the types
that match their input, so the same code runs on the LLVM and CUDA backends, with or
without automatic differentiation.
"""

from __future__ import annotations

import types
from typing import Union

import drjit as dr
import numpy as np

def _any_backend(kind: str):
    """The type hint for a ``kind`` array ('Float', 'Array3f', ...) of either JIT
    backend, plain or AD: kernels take the types of their input's backend."""
    return Union[tuple(getattr(m, kind) for m in (dr.llvm, dr.cuda, dr.llvm.ad, dr.cuda.ad))]


#: Type hints of the kernels' arrays (what :func:`namespace_of` hands out, of any backend).
Float, UInt32, UInt64, Bool, Array3f, Array3u = (
    _any_backend(kind) for kind in ("Float", "UInt32", "UInt64", "Bool", "Array3f", "Array3u"))

# Dr.Jit's LLVM backend marks a vector load aligned only when the input's address is a
# multiple of the packet size; its own allocations always are (64 bytes covers AVX-512).
_JIT_ALIGNMENT = 64


def namespace_of(x) -> types.ModuleType:
    """The plain (non-AD) Dr.Jit module (``drjit.llvm`` or ``drjit.cuda``) of array ``x``.

    Exposes ``Float``, ``UInt32``, ``UInt64``, ``Int32``, ``Bool``, ``Array3f``,
    ``Array3u`` and the rest of Dr.Jit's per-backend types. Kernels compute with the
    plain types (no AD bookkeeping); convert inputs with :func:`plain`.
    """
    backend = dr.backend_v(x)
    if backend == dr.JitBackend.LLVM:
        mod = dr.llvm
    elif backend == dr.JitBackend.CUDA:
        mod = dr.cuda
    else:
        raise TypeError(
            f"hlbvh kernels need JIT arrays (LLVM or CUDA backend), got {type(x).__name__}"
        )
    return mod


def plain(x, kind: str):
    """``x`` converted to the plain type ``kind`` ('Float', 'UInt32', 'Array3f', ...)
    of its backend, detached from any AD graph, in Dr.Jit's own memory (no copy when it
    already is all of that).

    Dr.Jit wraps an evaluated numpy array's buffer without copying, and on the LLVM
    backend a buffer at another alignment compiles another kernel: without the copy,
    the same build would compile anew whenever a caller's array landed at a new
    address."""
    t = getattr(namespace_of(x), kind)
    x = x if type(x) is t else t(dr.detach(x) if dr.is_diff_v(x) else x)
    if dr.depth_v(x) > 1:
        parts = [_in_jit_memory(c) for c in x]
        return x if all(p is c for p, c in zip(parts, x)) else t(*parts)
    return _in_jit_memory(x)


def _in_jit_memory(x):
    """``x`` (a flat JIT array) itself when its buffer is aligned as Dr.Jit allocates,
    else an aligned copy (foreign buffers, e.g. from numpy, can sit at any address)."""
    if dr.backend_v(x) != dr.JitBackend.LLVM or x.state != dr.VarState.Evaluated:
        return x  # CUDA copies host arrays to the device; pending values get jit memory
    if dr.width(x) == 0 or np.asarray(x).ctypes.data % _JIT_ALIGNMENT == 0:
        return x
    # A host copy into an aligned buffer, which Dr.Jit maps as it maps any host array:
    # no kernel, so no compile the first time a misaligned input shows up.
    src = np.asarray(x)
    buf = np.empty(src.nbytes + _JIT_ALIGNMENT, np.uint8)
    skip = -buf.ctypes.data % _JIT_ALIGNMENT
    copy = buf[skip : skip + src.nbytes].view(src.dtype)
    copy[:] = src
    return type(x)(copy)


def concat(parts, into=None):
    """The flat JIT arrays ``parts`` (one type) end to end, evaluated; written over the
    start of the array ``into`` when one is given (and ``into`` returned). Unlike
    ``dr.concat``, whose kernel holds each part's size as a literal (a compile for
    every new size), the offsets enter as opaque values."""
    if len(parts) == 1 and into is None:
        return parts[0]
    ns = namespace_of(parts[0])
    out = dr.empty(type(parts[0]), sum(dr.width(p) for p in parts)) if into is None else into
    offset = 0
    for part in parts:
        width = dr.width(part)
        if width:
            dr.scatter(out, part, dr.arange(ns.UInt32, width) + dr.opaque(ns.UInt32, offset))
        offset += width
    dr.eval(out)
    return out


def pack_halves(high, low):
    """UInt64 keys ``high << 32 | low`` of two UInt32 arrays (of one backend): a min,
    a sort or a prefix sum over the keys orders or counts by ``high``, then ``low``."""
    UInt64 = dr.uint64_array_t(type(high) if dr.is_array_v(high) else type(low))
    return (UInt64(high) << 32) | UInt64(low)


def high_half(key):
    """The upper 32 bits of 64-bit ``key`` (UInt64 array: a UInt32 array; int: an int)."""
    return dr.uint32_array_t(type(key))(key >> 32) if dr.is_array_v(key) else key >> 32


def low_half(key):
    """The lower 32 bits of 64-bit ``key`` (UInt64 array: a UInt32 array, by the
    conversion's truncation; int: an int)."""
    return dr.uint32_array_t(type(key))(key) if dr.is_array_v(key) else key & 0xFFFFFFFF
