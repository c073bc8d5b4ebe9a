"""Where bf16 runs natively, and the trainer precision a run gets on a CPU where it does not (float32:
:func:`cpu_precision`)."""

from __future__ import annotations

import platform
from typing import Any

import torch

from threedq.machine import cpu_capabilities

__all__ = ["BF16_PRECISIONS", "bf16_is_native", "cpu_bf16_is_native", "cpu_precision"]

#: Lightning's ``Trainer(precision=...)`` values that compute in bf16.
BF16_PRECISIONS = ("bf16-mixed", "bf16-true", "bf16")


def cpu_bf16_is_native(cpu: dict[str, Any] | None = None) -> bool:
    """Whether this CPU has bf16 instructions: AVX512-BF16 or AMX-BF16 on x86, what oneDNN says elsewhere.

    ``cpu``: the capabilities to judge (default: this machine's, :func:`~threedq.machine.cpu_capabilities`).
    """
    if cpu is None:
        cpu = cpu_capabilities()
    if cpu.get("architecture", platform.machine()) in ("x86_64", "AMD64", "i386", "x86"):
        return bool(cpu.get("avx512_bf16") or cpu.get("amx_bf16"))
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def bf16_is_native(cpu: dict[str, Any] | None = None) -> bool:
    """Whether bf16 runs natively here: a GPU that supports it, else a CPU with bf16 instructions.

    ``cpu``: judge these CPU capabilities instead of this machine (no GPU is then considered).
    """
    if cpu is None and torch.cuda.is_available():
        return bool(torch.cuda.is_bf16_supported())
    return cpu_bf16_is_native(cpu)


def cpu_precision(precision: Any, on_cpu: bool, native: bool | None = None) -> tuple[Any, str | None]:
    """The precision a run on this machine gets for the asked ``precision``, and a line saying why if it changed.

    A bf16 precision (:data:`BF16_PRECISIONS`) on a CPU without bf16 instructions becomes ``"32-true"``; anything
    else is kept. ``native``: whether the CPU has bf16 instructions (default: :func:`cpu_bf16_is_native`).

    Returns:
        ``(precision, note)``: ``note`` is ``None`` when nothing changed.
    """
    if not on_cpu or str(precision) not in BF16_PRECISIONS:
        return precision, None
    if native is None:
        native = cpu_bf16_is_native()
    if native:
        return precision, None
    return "32-true", (f"trainer.precision {precision} -> 32-true: this CPU has no bf16 instructions (AVX512-BF16 or "
                       "AMX), where bf16 is emulated at 2x (AVX-512) to about 60x (AVX2) the float32 time "
                       "(docs/benchmarks.md)")
