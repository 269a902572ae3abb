"""The Dr.Jit array types of the backend an input lives on.

Kernels never name ``drjit.llvm`` or ``drjit.cuda``: they ask this module for the types
that match their input, so the same code runs on the LLVM and CUDA backends, with or
without automatic differentiation.
"""

from __future__ import annotations

import types

import drjit as dr


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
    of its backend, detached from any AD graph (no copy when it already is one)."""
    t = getattr(namespace_of(x), kind)
    return x if type(x) is t else t(dr.detach(x) if dr.is_diff_v(x) else x)
