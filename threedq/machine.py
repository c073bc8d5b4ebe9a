"""What machine a measurement ran on: the CPU's model name, printed beside every benchmark table and recorded with
every main job (:mod:`threedq.pipeline.results_pages`). Numbers from different CPU types differ (AMD, Intel with or
without bf16/AMX), so each result names its CPU."""

from __future__ import annotations

import platform
from pathlib import Path

__all__ = ["cpu_name"]


def cpu_name() -> str:
    """CPU model name (Linux ``/proc/cpuinfo``), else the platform's processor string."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"
