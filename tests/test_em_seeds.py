"""``benchmarks/em_seeds.py``: several ``threedq em`` runs per arm, mean and range over seeds, the round-0 check.

Two hand-written work dirs (a ``metrics.json`` each, the layout ``threedq em`` writes) against hand-computed means,
ranges and checks.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import load_benchmark

em_seeds = load_benchmark("em_seeds")


def _run(tmp_path: Path, name: str, strict: list[float], paper: list[float], fewshot: list[float | None],
         mining_s: list[float]) -> Path:
    work = tmp_path / name
    work.mkdir()
    rows = [{"round": r, "precision_at_10": s, "precision_at_10_paper": p, "same_object_top1": 0.5,
             "hungarian_acc": 0.4, "map_50": 0.8} for r, (s, p) in enumerate(zip(strict, paper))]
    results = [{"quantization": {"threedq": {"fewshot_acc": f}}} for f in fewshot]
    (work / "metrics.json").write_text(json.dumps({"table3": rows, "round0_result": results[0],
                                                   "round_results": results[1:]}))
    for r, sec in enumerate(mining_s, start=1):
        (work / f"r{r:02d}_mining").mkdir()
        (work / f"r{r:02d}_mining" / "stage.json").write_text(json.dumps({"seconds": sec}))
    return work


class TestEmSeeds:
    def test_read_run(self, tmp_path):
        w = _run(tmp_path, "a", [0.30, 0.35, 0.28], [0.4, 0.41, 0.42], [0.3, None, 0.5], [100.0, 120.0])
        run = em_seeds.read_run(w)
        assert sorted(run) == [0, 1, 2]
        assert run[1]["precision_at_10"] == 0.35 and run[2]["precision_at_10_paper"] == 0.42
        assert run[0]["fewshot_acc"] == 0.3 and run[1]["fewshot_acc"] is None and run[2]["fewshot_acc"] == 0.5
        assert run[0]["mining_seconds"] is None and run[2]["mining_seconds"] == 120.0

    def test_mean_range_and_round0(self, tmp_path):
        a = em_seeds.read_run(_run(tmp_path, "a", [0.30, 0.35, 0.28], [0.4, 0.41, 0.42], [0.3, 0.3, 0.3], [100, 120]))
        b = em_seeds.read_run(_run(tmp_path, "b", [0.32, 0.33, 0.34], [0.4, 0.39, 0.45], [0.3, 0.3, 0.3], [110, 90]))
        mean, rng, n = em_seeds.mean_range([a[2]["precision_at_10"], b[2]["precision_at_10"]])
        assert mean == pytest.approx(0.31) and rng == pytest.approx(0.06) and n == 2
        assert em_seeds.mean_range([None, None]) is None
        assert em_seeds.holds_round0(a, "precision_at_10") is False  # 0.28 < 0.30 at round 2
        assert em_seeds.holds_round0(b, "precision_at_10") is True
        assert em_seeds.holds_round0(b, "precision_at_10_paper") is False  # 0.39 < 0.40 at round 1
        md = em_seeds.summary_markdown({"x": ["a", "b"]}, {"x": [a, b]})
        assert "| 2 | x | 2 | 0.310 (0.060) | 0.435 (0.030) |" in md
        assert "| x | a | no | yes |" in md and "| x | b | yes | no |" in md
        assert "| 0.800 (0.000) | 105.0 (10.0) |" in md and "| 0.800 (0.000) | 105.0 (30.0) |" in md  # rounds 1, 2

    def test_read_renamed_copy(self, tmp_path):
        # a metrics.json kept under another name, alone: the same rows; the mining seconds from its mining_results
        w = _run(tmp_path, "a", [0.30, 0.35, 0.28], [0.4, 0.41, 0.42], [0.3, None, 0.5], [100.0, 120.0])
        m = json.loads((w / "metrics.json").read_text())
        m["mining_results"] = [{"seconds": 101.0}, {"seconds": 121.0}]
        copy = tmp_path / "kept" / "metrics_seed0.json"
        copy.parent.mkdir()
        copy.write_text(json.dumps(m))
        run, ref = em_seeds.read_run(copy), em_seeds.read_run(w)
        for r in (0, 1, 2):
            assert {k: v for k, v in run[r].items() if k != "mining_seconds"} == \
                {k: v for k, v in ref[r].items() if k != "mining_seconds"}
        assert [run[r]["mining_seconds"] for r in (0, 1, 2)] == [None, 101.0, 121.0]
        with pytest.raises(SystemExit, match="no metrics.json"):
            em_seeds.read_run(tmp_path / "kept" / "absent.json")

    def test_missing_metrics(self, tmp_path):
        with pytest.raises(SystemExit, match="no metrics.json"):
            em_seeds.read_run(tmp_path)
        (tmp_path / "metrics.json").write_text("{}")
        with pytest.raises(SystemExit, match="not a threedq em metrics.json"):
            em_seeds.read_run(tmp_path)

    def test_main_writes_png(self, tmp_path, capsys):
        _run(tmp_path, "a", [0.30, 0.35], [0.4, 0.41], [0.3, 0.3], [100])
        png = tmp_path / "out.png"
        em_seeds.main(["--arm", f"x={tmp_path / 'a'}", "--png", str(png)])
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert "| 1 | x | 1 | 0.350 | 0.410 |" in capsys.readouterr().out
        with pytest.raises(SystemExit, match="expected NAME=DIR"):
            em_seeds.main(["--arm", "nodirs="])

    def test_kept_rows(self, tmp_path, capsys):
        # a results folder's rows.jsonl: one row per run, each metric a list over its rounds
        rows = [{"run": f"metrics_x_seed{s}.json", "arm": "x", "data": "embedded", "seed": s, "rounds": [0, 1],
                 "precision_at_10": [0.30, 0.35 + s / 100], "precision_at_10_paper": [0.4, 0.41],
                 "hungarian_acc": [0.4, 0.5], "mining_seconds": [None, 100.0]} for s in (0, 1)]
        path = tmp_path / "rows.jsonl"
        path.write_text("".join(json.dumps(r) + "\n" for r in rows))
        run = em_seeds.read_run(f"{path}#metrics_x_seed1.json")
        assert run[1]["precision_at_10"] == 0.36 and run[1]["mining_seconds"] == 100.0
        assert run[0]["fewshot_acc"] is None  # a metric the row does not keep
        with pytest.raises(SystemExit, match="no row of run"):
            em_seeds.read_run(f"{path}#metrics_absent.json")
        em_seeds.main(["--rows", str(path)])
        assert "| 1 | embedded: x | 2 | 0.355 (0.010) | 0.410 (0.000) |" in capsys.readouterr().out
