"""What machine a measurement ran on: the CPU's model name, its logical CPUs and the instruction sets that change
bf16 numbers and speed, printed beside every benchmark table and recorded with every main job
(:mod:`threedq.pipeline.results_pages`). Numbers from different CPU types differ (AMD, Intel with or without
bf16/AMX), so each result names its CPU."""

from __future__ import annotations

import os
import platform
from pathlib import Path

__all__ = ["cpu_name"]

#: ``/proc/cpuinfo`` flags named in :func:`cpu_name`, most telling first: AMX and AVX512-BF16 run bf16 matrix
#: products natively; without them bf16 is emulated (threedq's CLI then trains in float32).
_FEATURES = (("amx_bf16", "AMX"), ("avx512_bf16", "AVX512-BF16"))
#: the widest vector set, named when none of the above is there
_VECTORS = (("avx512f", "AVX-512"), ("avx2", "AVX2"))


def describe_cpu(cpuinfo: str, logical_cpus: int | None) -> str:
    """``"<model name> (<n> logical CPUs with <features>)"`` from the text of ``/proc/cpuinfo``; ``""`` without a model
    name. Features: AMX and AVX512-BF16 where the flags say so, else the widest of AVX-512 and AVX2."""
    model, flags = "", set()
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "model name" and not model:
            model = value.strip()
        elif key.strip() == "flags" and not flags:
            flags = set(value.split())
    if not model:
        return ""
    names = [name for flag, name in _FEATURES if flag in flags]
    if not names:
        names = [name for flag, name in _VECTORS if flag in flags][:1]
    inner = f"{logical_cpus} logical CPUs" if logical_cpus else ""
    if names:
        inner += (" with " if inner else "") + " and ".join(names)
    return f"{model} ({inner})" if inner else model


def cpu_name() -> str:
    """This machine's CPU as :func:`describe_cpu` writes it (Linux ``/proc/cpuinfo``), else the platform's processor
    string."""
    try:
        name = describe_cpu(Path("/proc/cpuinfo").read_text(), os.cpu_count())
    except OSError:
        name = ""
    return name or platform.processor() or platform.machine() or "unknown CPU"
