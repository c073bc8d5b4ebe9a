"""How long ``threedq view --save`` takes to record a run and how big the recording is, by the point budget
(:func:`threedq.pipeline.view.run_view` into a temporary ``.rrd``: wall time, size and what it holds).

    python benchmarks/bench_view.py --run runs/em                     # 2000 and 6000 points per scene
    python benchmarks/bench_view.py --run runs/em --points 6000 20000
"""

from __future__ import annotations

import argparse
import datetime
import tempfile
from pathlib import Path

import torch

from threedq.machine import cpu_name
from threedq.pipeline.view import run_view


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--run", default="runs/em", help="a threedq em work folder (or a threedq parse folder)")
    ap.add_argument("--data_dir", default=None, help="its dataset folder (default: the one the run read)")
    ap.add_argument("--points", type=int, nargs="+", default=[2000, 6000], help="points per scene, one row each")
    args = ap.parse_args()
    print(f"{datetime.date.today()}, {cpu_name()}, {torch.get_num_threads()} threads, run {args.run}\n")
    print("| points per scene | scenes | points | boxes per round | seconds | MB |")
    print("|---|---|---|---|---|---|")
    for n in args.points:
        with tempfile.TemporaryDirectory() as tmp:
            c = run_view(args.run, save=str(Path(tmp) / "run.rrd"), data_dir=args.data_dir, points_per_scene=n,
                         progress=False)
        boxes = ", ".join(str(v) for v in c["boxes"].values())
        print(f"| {n} | {c['scenes']} | {c['points']} | {boxes} | {c['seconds']:.1f} | {c['megabytes']:.1f} |")


if __name__ == "__main__":
    main()
