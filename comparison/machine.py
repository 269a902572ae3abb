"""The machine a benchmark ran on, as every published table names it."""

from __future__ import annotations

import platform


def cpu_model() -> str:
    """The CPU's model name, family and model numbers and vector instruction set
    (``/proc/cpuinfo``; ``platform.processor()`` elsewhere): one name ("AMD EPYC") covers
    CPUs with 8 and with 16 lanes per packet, whose ratios to Embree differ."""
    fields = _cpuinfo()
    name = fields.get("model name") or platform.processor() or "unknown CPU"
    if "cpu family" in fields and "model" in fields:
        name += f" (family {fields['cpu family']} model {fields['model']}"
        isa = simd_isa()
        return name + (f", {isa})" if isa else ")")
    return name


def simd_isa() -> str:
    """"AVX-512", "AVX2" or "" (unknown): what Dr.Jit's LLVM kernels vectorise to here
    (16 or 8 float lanes a packet)."""
    flags = _cpuinfo().get("flags", "").split()
    return "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else ""


def _cpuinfo() -> dict:
    """The first processor's fields of ``/proc/cpuinfo`` (empty where there is none)."""
    fields = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    break
                key, _, value = line.partition(":")
                fields[key.strip()] = value.strip()
    except OSError:
        pass
    return fields
