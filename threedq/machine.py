"""What machine a measurement ran on: the CPU's model name, its logical CPUs and the instruction sets that change
bf16 numbers and speed (torch's capabilities, :func:`cpu_capabilities`)."""

from __future__ import annotations

import platform
from typing import Any

import torch

__all__ = ["cpu_capabilities", "cpu_name", "describe_cpu"]

#: capabilities named in :func:`describe_cpu`: those that run bf16 matrix products natively
_FEATURES = (("amx_bf16", "AMX"), ("avx512_bf16", "AVX512-BF16"))
#: the widest vector set, named when none of the above is there
_VECTORS = (("avx512_f", "AVX-512"), ("avx2", "AVX2"))


def cpu_capabilities() -> dict[str, Any]:
    """This CPU's capabilities as torch reads them (``torch._C._cpu._get_cpu_capability``: ``cpu_name``,
    ``num_logical_cores``, ``architecture`` and one flag per instruction set); ``{}`` where torch cannot say."""
    try:
        return dict(torch._C._cpu._get_cpu_capability())
    except (AttributeError, RuntimeError):
        return {}


def describe_cpu(cpu: dict[str, Any]) -> str:
    """``"<cpu_name> (<n> logical CPUs with <features>)"`` from capabilities as :func:`cpu_capabilities` gives them;
    ``""`` without a name. Features: AMX and AVX512-BF16 where the capabilities say so, else the widest of AVX-512
    and AVX2."""
    model = str(cpu.get("cpu_name") or "").strip()
    if not model:
        return ""
    names = [n for flag, n in _FEATURES if cpu.get(flag)] or [n for flag, n in _VECTORS if cpu.get(flag)][:1]
    count = cpu.get("num_logical_cores")
    inner = " with ".join(part for part in (f"{count} logical CPUs" if count else "", " and ".join(names)) if part)
    return f"{model} ({inner})" if inner else model


def cpu_name() -> str:
    """This machine's CPU as :func:`describe_cpu` writes it, else the platform's processor string."""
    return describe_cpu(cpu_capabilities()) or platform.processor() or platform.machine() or "unknown CPU"
