"""benchmarks/rgb_weight_curve.py: the points it draws, from hand-made rows of both sources, and the picture."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import load_benchmark

curve = load_benchmark("rgb_weight_curve")


def _shapes_rows(path: Path) -> Path:
    rows = [{"dataset": "shapes", "row": "references", "seed": None, "raw_bank/hungarian_acc": 0.48,
             "pointcloud/hungarian_acc": 0.43},
            {"dataset": "unseen", "row": "view prediction on shapes, 500 steps", "seed": 0, "raw/strict": 0.9,
             "cosine/strict": 0.9, "threedq/hungarian_acc": 0.9}]  # another dataset: left out
    for name, w in curve.SHAPES_ROWS.items():
        for seed in (0, 1):
            rows.append({"dataset": "shapes", "row": name, "seed": seed, "raw/strict": 0.57,
                         "cosine/strict": 0.4 + w / 100 + seed / 1000, "threedq/hungarian_acc": 0.5 - w / 100})
    rows.append({"dataset": "shapes", "row": "view prediction on shapes, 100 steps", "seed": 0, "raw/strict": 0.57,
                 "cosine/strict": 0.1, "threedq/hungarian_acc": 0.1})  # another row: left out
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def _embedded_tables(folder: Path) -> Path:
    folder.mkdir()
    raw = {"precision_at_10_paper": 0.40, "hungarian_acc": 0.44}
    for i, (w, seed, p) in enumerate([(30, 0, 0.479), (0, 0, 0.318), (3, 1, 0.472), (30, 1, 0.493)]):
        rows = {"raw crops": raw, f"view prediction rgb_weight {w} seed {seed}": {"precision_at_10_paper": p,
                                                                                  "hungarian_acc": 0.4},
                "random encoder": {"precision_at_10_paper": 0.2, "hungarian_acc": 0.2}}
        (folder / f"t{i}.json").write_text(json.dumps({"rows": rows}))
    # the same encoder again in another table (e.g. beside a new row) is drawn once
    (folder / "t9.json").write_text(json.dumps({"rows": {"raw crops": raw, "view prediction rgb_weight 30 seed 0": {
        "precision_at_10_paper": 0.1, "hungarian_acc": 0.1}}}))
    return folder


class TestRgbWeightCurve:
    def test_shapes_points_per_seed_at_the_weights_index(self, tmp_path: Path) -> None:
        points, refs = curve.shapes_points([_shapes_rows(tmp_path / "rows.jsonl")])
        assert refs == {"raw_bank": 0.48, "pointcloud": 0.43, "raw_strict": 0.57}
        got = sorted(points["cosine/strict"][1])
        assert [x for x, _ in got] == [0.0, 1.0, 2.0] and [y for _, y in got] == pytest.approx([0.401, 0.431, 0.701])
        assert [y for _, y in sorted(points["threedq/hungarian_acc"][0])] == pytest.approx([0.5, 0.47, 0.2])

    def test_embedded_points_one_per_encoder(self, tmp_path: Path) -> None:
        points, refs = curve.embedded_points(_embedded_tables(tmp_path / "tables"))
        assert refs == {"raw_paper": 0.40, "raw_bank": 0.44}
        assert sorted(points["precision_at_10_paper"][0]) == [(0.0, 0.318), (2.0, 0.479)]
        assert sorted(points["precision_at_10_paper"][1]) == [(1.0, 0.472), (2.0, 0.493)]

    def test_picture(self, tmp_path: Path) -> None:
        from threedq.viz.png import write_png

        fig = curve.figure([_shapes_rows(tmp_path / "rows.jsonl")], _embedded_tables(tmp_path / "tables"))
        assert len(fig.axes) == 4 and [t.get_text() for t in fig.axes[0].get_xticklabels()] == ["0", "3", "30"]
        assert write_png(tmp_path / "c.png", fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
