"""The scenes a per-scene benchmark runs on, and its timing rule (shared by the ``bench_*`` scripts that take
``--data_dir`` and ``--scenes``)."""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any


def scene_arguments(doc: str | None) -> argparse.Namespace:
    """The command line of a per-scene benchmark: ``--data_dir`` (default: generate) and ``--scenes`` (default 30)."""
    ap = argparse.ArgumentParser(description=(doc or "").split("\n")[0])
    ap.add_argument("--data_dir", type=Path, default=None)
    ap.add_argument("--scenes", type=int, default=30)
    return ap.parse_args()


def bench_scenes(data_dir: Path | None, count: int, split: str) -> tuple[Path, Any, list[Any]]:
    """``count + 1`` scene records of ``split`` (the first is a warm-up): the first of ``data_dir`` (a dataset
    folder), else that many scenes generated with the embedded generator's defaults (seed 0) into a temporary folder.

    Returns:
        the folder the scenes came from (a temporary one is gone when this returns), its ``DatasetIndex`` and the
        records (read without validation).
    """
    from threedq.scene import load_index, load_scene

    with tempfile.TemporaryDirectory() as tmp:
        data = data_dir
        if data is None:
            from threedq.data.generate import generate_dataset

            data = Path(tmp) / "scenes"
            fractions = {"train": (1.0, 0.0, 0.0), "val": (0.0, 1.0, 0.0), "test": (0.0, 0.0, 1.0)}[split]
            generate_dataset(data, num_scenes=count + 1, seed=0, split_fractions=fractions, progress=False)
        index = load_index(data)
        records = [load_scene(data / f, validate=False) for f in index.files(split)[: count + 1]]
    return data, index, records


def median_ms(fn: Callable[[Any], Any], items: Sequence[Any]) -> float:
    """Median milliseconds of ``fn(item)`` over ``items[1:]``, after ``fn(items[0])`` as a warm-up."""
    fn(items[0])
    times = []
    for item in items[1:]:
        t0 = time.perf_counter()
        fn(item)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)
