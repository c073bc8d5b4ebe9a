"""The RGB loss's weight against shape (shapes data) and category retrieval (embedded data): one picture.

Reads the shape study's rows (``benchmarks/results/shape_benchmark_levers_cpu_2026-11-29.jsonl``,
``shape_benchmark_cpu_2026-11-29.jsonl``) and the ``threedq eval --encoders`` tables under
``benchmarks/results/viewpred_rgb_weight_embedded_cpu_2026-11-29/``, and draws each measure against the weight, a
line per seed, with the references and the embedded guard as horizontal lines.

    python benchmarks/rgb_weight_curve.py --png docs/img/rgb_weight_tradeoff.png
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
WEIGHTS = (0.0, 3.0, 30.0)  # drawn at x = 0, 1, 2 (the tick labels give the weights)
SHAPES_ROWS = {"view prediction on shapes, 500 steps, RGB loss off (rgb_weight 0)": 0.0,
               "view prediction on shapes, 500 steps, rgb_weight 3": 3.0,
               "view prediction on shapes, 500 steps": 30.0}


def shapes_points(files: list[Path]) -> tuple[dict[str, dict[int, list[tuple[float, float]]]], dict[str, float]]:
    """Per measure, per seed, ``(x, y)`` points; and the references of the shapes set."""
    points: dict[str, dict[int, list[tuple[float, float]]]] = {"cosine/strict": {}, "threedq/hungarian_acc": {}}
    refs: dict[str, float] = {}
    for f in files:
        for line in f.read_text().splitlines():
            r = json.loads(line)
            if r.get("dataset") != "shapes":
                continue
            if r["row"] == "references":
                refs.setdefault("raw_bank", r["raw_bank/hungarian_acc"])
                refs.setdefault("pointcloud", r["pointcloud/hungarian_acc"])
            elif r["row"] in SHAPES_ROWS:
                refs.setdefault("raw_strict", r["raw/strict"])
                x = float(WEIGHTS.index(SHAPES_ROWS[r["row"]]))
                for key, per_seed in points.items():
                    per_seed.setdefault(r["seed"], []).append((x, r[key]))
    return points, refs


def embedded_points(folder: Path) -> tuple[dict[str, dict[int, list[tuple[float, float]]]], dict[str, float]]:
    """Per measure, per seed, ``(x, y)`` points of the ``threedq eval --encoders`` tables; the raw crops' numbers."""
    points: dict[str, dict[int, list[tuple[float, float]]]] = {"precision_at_10_paper": {}, "hungarian_acc": {}}
    refs: dict[str, float] = {}
    seen = set()
    for f in sorted(folder.glob("*.json")):
        rows = json.loads(f.read_text())["rows"]
        refs.setdefault("raw_paper", rows["raw crops"]["precision_at_10_paper"])
        refs.setdefault("raw_bank", rows["raw crops"]["hungarian_acc"])
        for name, row in rows.items():
            m = re.fullmatch(r"view prediction rgb_weight (\d+) seed (\d+)", name)
            if m is None or (m[1], m[2]) in seen:
                continue
            seen.add((m[1], m[2]))
            x = float(WEIGHTS.index(float(m[1])))
            for key, per_seed in points.items():
                per_seed.setdefault(int(m[2]), []).append((x, row[key]))
    return points, refs


def figure(shapes_files: list[Path], embedded: Path):
    from threedq.viz.curves import runs_figure

    sp, sref = shapes_points(shapes_files)
    ep, eref = embedded_points(embedded)
    runs = lambda per_seed: [sorted(v) for _, v in sorted(per_seed.items())]  # noqa: E731
    guard = min(y for v in ep["precision_at_10_paper"].values() for x, y in v if x == 2.0)
    panels = [
        ("shapes: strict precision@10", {"seeds": runs(sp["cosine/strict"])},
         [(sref["raw_strict"], "--", "raw crops"), (sref["raw_strict"] + 0.10, ":", "target (raw + 0.10)")]),
        ("shapes: Hungarian K = 50", {"seeds": runs(sp["threedq/hungarian_acc"])},
         [(sref["pointcloud"], "--", "point cloud"), (sref["pointcloud"] + 0.15, ":", "target (point cloud + 0.15)")]),
        ("embedded: paper precision@10 (GT boxes)", {"seeds": runs(ep["precision_at_10_paper"])},
         [(eref["raw_paper"], "--", "raw crops"), (guard, ":", "guard (weight 30, lowest seed)")]),
        ("embedded: Hungarian K = 50 (GT boxes)", {"seeds": runs(ep["hungarian_acc"])},
         [(eref["raw_bank"], "--", "raw crops' bank")]),
    ]
    fig = runs_figure(panels, "RGB loss weight (occupancy 1)", xticks=[0.0, 1.0, 2.0])
    for ax in fig.axes:
        ax.set_xticklabels([f"{w:g}" for w in WEIGHTS])
        ax.legend(fontsize=6)
    return fig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--png", type=Path, default=Path("docs/img/rgb_weight_tradeoff.png"))
    args = ap.parse_args()
    from threedq.viz.png import write_png

    write_png(args.png, figure([RESULTS / "shape_benchmark_cpu_2026-11-29.jsonl",
                                   RESULTS / "shape_benchmark_levers_cpu_2026-11-29.jsonl"],
                                  RESULTS / "viewpred_rgb_weight_embedded_cpu_2026-11-29"))
    print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
