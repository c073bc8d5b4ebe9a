"""What machine a benchmark ran on (printed with every table): :func:`threedq.machine.cpu_name`."""

from __future__ import annotations

from threedq.machine import cpu_name

__all__ = ["cpu_name"]
