"""Benchmark of the embedded dataset generator: scenes per second, including rendering and writing, into a temporary
folder; prints a markdown table (scenes, views, resolution, workers, seconds, scenes/s, views/s, MB written).

    python benchmarks/bench_generate.py --scenes 1000 --workers 2
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

from threedq.data.generate import generate_dataset
from threedq.data.generator_config import GeneratorConfig
from threedq.machine import cpu_name


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", type=int, default=1000, help="number of scenes (default 1000)")
    p.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--views", type=int, default=28, help="views per scene (default 28)")
    p.add_argument("--size", type=int, default=128, help="image height = width in pixels (default 128)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-shadows", action="store_true", help="render without cast shadows")
    p.add_argument("--progress", action="store_true", help="show the progress bar")
    args = p.parse_args(argv)

    config = GeneratorConfig(image_size=(args.size, args.size), num_views=args.views, shadows=not args.no_shadows)
    with tempfile.TemporaryDirectory(prefix="threedq-bench-") as tmp:
        t0 = time.perf_counter()
        index = generate_dataset(
            tmp, args.scenes, seed=args.seed, config=config, workers=args.workers, progress=args.progress
        )
        seconds = time.perf_counter() - t0
        written = sum(f.stat().st_size for f in Path(tmp).rglob("*") if f.is_file())
    n = len(index.scenes)
    print(f"machine: {cpu_name()}, {__import__('os').cpu_count()} logical CPUs; python {platform.python_version()}")
    print()
    print("| scenes | views | resolution | workers | seconds | scenes/s | views/s | MB written |")
    print("|---:|---:|---|---:|---:|---:|---:|---:|")
    print(
        f"| {n} | {args.views} | {args.size}x{args.size} | {args.workers} | {seconds:.1f} | "
        f"{n / seconds:.2f} | {n * args.views / seconds:.0f} | {written / 1e6:.1f} |"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
