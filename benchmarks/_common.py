"""Helpers shared by the benchmark scripts: the machine line of a table, markdown tables, JSON-lines rows."""

from __future__ import annotations

import datetime
import json
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any


def machine() -> str:
    """``<cpu>, <n> threads, torch <version>, <date>``: where and when a benchmark ran."""
    import torch

    from threedq.machine import cpu_name

    return f"{cpu_name()}, {torch.get_num_threads()} threads, torch {torch.__version__}, {datetime.date.today()}"


def sync(device: Any) -> None:
    """Wait for the queued kernels of ``device`` (a ``torch.device`` or its name; nothing on a CPU)."""
    import torch

    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def table(head: Sequence[str], rows: Iterable[Sequence[Any]] = ()) -> str:
    """A markdown table: the ``head`` cells, a ``|---|`` rule, a line per row of cells."""
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return "\n".join(lines + ["| " + " | ".join(map(str, r)) + " |" for r in rows])


def append_row(out: Path, row: dict[str, Any]) -> None:
    """Append ``row`` to the JSON-lines file ``out`` (its folder made)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("a") as f:
        f.write(json.dumps(row) + "\n")


def read_rows(path: Path) -> list[dict[str, Any]]:
    """The rows of a JSON-lines file (blank lines skipped)."""
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def mean_range(values: Sequence[float], digits: int = 3) -> str:
    """``mean (min-max)`` of ``values`` (just the mean for one value; ``-`` for none), NaN and None skipped."""
    values = [v for v in values if v is not None and not math.isnan(v)]
    if not values:
        return "-"
    f = f"{{:.{digits}f}}"
    m = f.format(sum(values) / len(values))
    return m + (f" ({f.format(min(values))}-{f.format(max(values))})" if len(values) > 1 else "")
