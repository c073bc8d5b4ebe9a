"""``benchmarks/scaling_curve.py``: its points against hand-computed means and ranges of given rows."""

from __future__ import annotations

import json
from pathlib import Path

from conftest import load_benchmark

scaling = load_benchmark("scaling_curve")


def _write(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))


def _row(variant: str, seed: int, steps: int, retrieval: float, hungarian: float | None, sps: float) -> dict:
    return {"variant": variant, "seed": seed, "steps": steps, "cosine/paper": retrieval,
            "occupancy/hungarian": hungarian, "s_per_step": sps, "device": "cpu"}


class TestPoints:
    def test_hand_computed(self, tmp_path: Path) -> None:
        _write(tmp_path / "feature_recipes_long_cpu_2026-11-28.jsonl",
               [_row("default", 0, 1700, 0.5, 0.6, 0.6), _row("default", 1, 1700, 0.4, 0.5, 0.5),
                _row("default", 0, 3400, 0.7, 0.8, 0.55), _row("other", 0, 1700, 0.9, 0.9, 0.1)])
        _write(tmp_path / "scaling" / "grid_rows.jsonl",
               [_row("grid 32x32x16", 0, 1700, 0.3, None, 0.3), _row("grid 32x32x16", 1, 850, 0.9, 0.9, 0.3)])
        pts = scaling.points(tmp_path)
        steps = [p for p in pts if p["axis"] == "steps"]
        assert [(p["x"], p["seeds"]) for p in steps] == [(1700, 2), (3400, 1)]
        assert abs(steps[0]["retrieval"] - 0.45) < 1e-12 and steps[0]["retrieval_range"] == (0.4, 0.5)
        assert abs(steps[0]["hungarian"] - 0.55) < 1e-12 and steps[0]["s_per_step"] == 0.5  # the fastest run
        grid = [p for p in pts if p["axis"] == "grid"]
        # the grid compares at 1700 steps only; a row without Hungarian gives no Hungarian
        assert [(p["x"], p["retrieval"]) for p in grid] == [(32, 0.3), (64, 0.45)] and "hungarian" not in grid[0]
        assert "| grid | 32 x 32 x 16 (8 cm) | 1700 | 1 | 0.300 (0.300-0.300) | - | 0.300 | cpu |" in scaling.table(pts)
