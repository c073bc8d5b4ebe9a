"""What scale buys the view-prediction features: training steps, image size and grid size against retrieval (paper
protocol precision@10) and Hungarian accuracy (K = 50), from the rows of ``benchmarks/feature_recipes.py`` in
``benchmarks/results/``. Prints the table and draws ``--png``::

    python benchmarks/feature_recipes.py --cluster --seeds 0 1 --eval_steps 1700 --data_dir data/clevr_veggie \\
        --variant "grid 32x32x16=--model.init_args.grid_resolution=[32,32,16]" \\
        --variant "grid 48x48x24=--model.init_args.grid_resolution=[48,48,24]" --out grid_rows.jsonl
    python benchmarks/scaling_curve.py --png docs/img/scaling_curve.png
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"
RETRIEVAL, HUNGARIAN = "cosine/paper", "occupancy/hungarian"
#: (axis, setting, rows file under results/, variant in it, x value on the axis's plot)
SERIES = (
    ("steps", "half widths, CPU", "feature_recipes_long_cpu_2026-11-28.jsonl", "default", None),
    ("steps", "paper widths, H100", "feature_recipes_h100_2026-11-25.jsonl", "default", None),
    ("image size", "128 px", "feature_recipes_long_cpu_2026-11-28.jsonl", "default", 128),
    ("image size", "256 px", "feature_recipes_256px_cpu_2026-11-28.jsonl", "256 px", 256),
    ("grid", "32 x 32 x 16 (8 cm)", "scaling/grid_rows.jsonl", "grid 32x32x16", 32),
    ("grid", "48 x 48 x 24 (5.3 cm)", "scaling/grid_rows.jsonl", "grid 48x48x24", 48),
    ("grid", "64 x 64 x 32 (4 cm, the main job's)", "feature_recipes_long_cpu_2026-11-28.jsonl", "default", 64),
)
FIXED_STEPS = 1700  # the image-size and grid series compare at the main job's steps


def points(root: Path = RESULTS) -> list[dict[str, Any]]:
    """One point per (series, steps): the mean and range over the seeds of retrieval and Hungarian accuracy."""
    out = []
    for axis, setting, rows_file, variant, x in SERIES:
        path = root / rows_file
        if not path.is_file():
            continue
        rows = [r for r in map(json.loads, path.read_text().splitlines()) if r.get("variant") == variant]
        if axis != "steps":
            rows = [r for r in rows if r["steps"] == FIXED_STEPS]
        for steps in sorted({r["steps"] for r in rows}):
            at = [r for r in rows if r["steps"] == steps]
            p = {"axis": axis, "setting": setting, "x": steps if x is None else x, "steps": steps, "seeds": len(at),
                 "device": at[0]["device"]}
            for key, name in ((RETRIEVAL, "retrieval"), (HUNGARIAN, "hungarian")):
                v = [r[key] for r in at if r.get(key) is not None]
                if v:
                    p[name], p[f"{name}_range"] = statistics.fmean(v), (min(v), max(v))
            p["s_per_step"] = min(r["s_per_step"] for r in at)  # the fastest run: another job may have shared the CPU
            out.append(p)
    return out


def table(pts: list[dict[str, Any]]) -> str:
    lines = ["| scale | setting | steps | runs | paper p@10 | Hungarian (K = 50) | s per step (fastest run) | machine |",
             "|---|---|---|---|---|---|---|---|"]
    for p in pts:
        cells = []
        for name in ("retrieval", "hungarian"):
            lo, hi = p.get(f"{name}_range", (None, None))
            cells.append(f"{p[name]:.3f} ({lo:.3f}-{hi:.3f})" if name in p else "-")
        sps = f"{p['s_per_step']:.3f}"
        lines.append(f"| {p['axis']} | {p['setting']} | {p['steps']} | {p['seeds']} | {cells[0]} | {cells[1]} | {sps} "
                     f"| {p['device']} |")
    return "\n".join(lines)


def _draw(ax: Any, pts: list[dict[str, Any]], label: str) -> None:
    """Retrieval (solid) and Hungarian (dashed) through ``pts`` in order of x, the seeds' range as bars."""
    for name, style in (("retrieval", "-o"), ("hungarian", "--s")):
        s = sorted((p for p in pts if name in p), key=lambda p: p["x"])
        if s:
            err = [[p[name] - p[f"{name}_range"][0] for p in s], [p[f"{name}_range"][1] - p[name] for p in s]]
            ax.errorbar([p["x"] for p in s], [p[name] for p in s], yerr=err, fmt=style, ms=3, lw=1, capsize=2,
                        label=f"{name}{label}")


def figure(pts: list[dict[str, Any]]) -> Any:
    """Retrieval and Hungarian against steps, image size and grid cells (the mean of the seeds, bars: their range)."""
    from threedq.viz.png import new_figure

    fig = new_figure(figsize=(10, 3.2), dpi=110)
    for i, (axis, xlabel) in enumerate((("steps", "view-prediction steps"), ("image size", "image size (px)"),
                                        ("grid", "grid cells along x (2.56 m)"))):
        ax = fig.add_subplot(1, 3, i + 1)
        on_axis = [p for p in pts if p["axis"] == axis]
        if axis == "steps":
            for setting in dict.fromkeys(p["setting"] for p in on_axis):
                _draw(ax, [p for p in on_axis if p["setting"] == setting], f" ({setting})")
        else:
            _draw(ax, on_axis, "")
        ax.axhline(0.81, color="grey", ls=":", lw=1, label="paper's retrieval (0.81)")
        ax.axhline(0.77, color="grey", ls="-.", lw=1, label="paper's Hungarian (0.77)")
        ax.set_ylim(0.3, 0.85)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6)
    return fig


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--png", type=Path, help="draw the curves to this file")
    args = ap.parse_args()
    pts = points()
    print(table(pts))
    if args.png:
        from threedq.viz.png import write_png

        write_png(args.png, figure(pts))
        print(f"\nwrote {args.png}")


if __name__ == "__main__":
    main()
