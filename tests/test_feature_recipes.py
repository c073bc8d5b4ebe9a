"""benchmarks/feature_recipes.py: the table of its rows (hand-made rows), and scoring a checkpoint per crop shape."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from conftest import load_benchmark

feature_recipes = load_benchmark("feature_recipes")


def _row(variant: str, crop: str, paper: float, raw_paper: float, seed: int | None = None) -> dict:
    refs = {f"{k}/{m}": v for k, v in (("raw", raw_paper), ("descriptor", 0.3)) for m in ("strict", "paper", "top1")}
    return {"variant": variant, "seed": seed, "steps": 0, "s_per_step": float("nan"), "crop": crop,
            "cosine/strict": paper - 0.05, "cosine/paper": paper, "cosine/top1": 0.5, "ceiling/strict": 0.9,
            "ceiling/paper": 0.95, "pool": 7, **refs}


class TestTable:
    def test_mean_and_range_over_runs_and_references_per_crop(self) -> None:
        rows = [_row("vp", "hull", 0.40, 0.35, 0), _row("vp", "hull", 0.50, 0.35, 1),
                _row("vp, cube crop", "cube", 0.60, 0.37, 0), _row("vp, cube crop", "cube", 0.62, 0.37, 1)]
        lines = feature_recipes.table(rows).splitlines()
        vp = next(line for line in lines if line.startswith("| vp |"))
        assert "| 2 |" in vp and "0.450 (0.400-0.500)" in vp
        cube = next(line for line in lines if line.startswith("| vp, cube crop |"))
        assert "0.610 (0.600-0.620)" in cube
        assert any(line.startswith("| raw crops | 0.350 | 0.350 |") for line in lines)
        assert any(line.startswith("| raw crops, cube crop | 0.370 | 0.370 |") for line in lines)
        assert sum("descriptor" in line for line in lines) == 1  # of the hull crops only

    def test_recipes_on_other_data_get_their_own_references(self) -> None:
        """Two recipes scored on two renderings of the same scenes (e.g. 128 and 256 px): a raw crops row each."""
        rows = [_row("128 px", "hull", 0.50, 0.35, 0), _row("256 px", "hull", 0.52, 0.38, 0)]
        lines = feature_recipes.table(rows).splitlines()
        assert any(line.startswith("| raw crops, rows of 128 px | 0.350 |") for line in lines)
        assert any(line.startswith("| raw crops, rows of 256 px | 0.380 |") for line in lines)
        assert not any(line.startswith("| raw crops |") for line in lines)
        assert sum(line.startswith("| colour + size descriptor (of the hull crops) |") for line in lines) == 1  # shared

    def test_rows_written_before_the_crop_field_are_hull(self) -> None:
        row = _row("old", "hull", 0.4, 0.3)
        del row["crop"]
        assert "| raw crops | 0.300 |" in feature_recipes.table([row])


class TestCurves:
    def test_points_per_recipe_and_seed_sorted_by_steps(self) -> None:
        rows = [dict(_row("vp", "hull", p, 0.35, seed), steps=n) for seed, n, p in
                ((0, 3400, 0.55), (0, 1700, 0.50), (1, 1700, 0.48), (1, 3400, 0.52))]
        rows.append(_row("scored", "hull", 0.6, 0.35))  # a scored checkpoint: no steps, no curve
        pts = feature_recipes.curve_points(rows, "cosine/paper")
        assert pts == {"vp": {0: [(1700, 0.50), (3400, 0.55)], 1: [(1700, 0.48), (3400, 0.52)]}}

    def test_references_shared_grey_else_one_per_recipe(self) -> None:
        rows = [dict(_row("a", "hull", 0.5, 0.35, 0), steps=10), dict(_row("b", "hull", 0.5, 0.35, 0), steps=10)]
        assert feature_recipes.curve_references(rows, "cosine/paper") == [(0.35, "--", "raw crops", None),
                                                                          (0.3, ":", "descriptor", None)]
        rows.append(dict(_row("c", "hull", 0.5, 0.35, 0), steps=10))
        rows[1]["raw/paper"] = 0.38
        assert feature_recipes.curve_references(rows, "cosine/paper")[:2] == [(0.35, "--", "raw crops (a, c)", None),
                                                                              (0.38, "--", "raw crops (b)", "b")]

    def test_png(self, tmp_path: Path) -> None:
        from threedq.viz.png import write_png

        rows = [dict(_row("vp", "hull", 0.4 + 0.01 * n, 0.35, 0), steps=n) for n in (1, 2, 3)]
        path = write_png(tmp_path / "curves.png", feature_recipes.curves_figure(rows))
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


class TestScoreCheckpoints:
    def test_one_row_and_one_per_channel_slice(self, tmp_path: Path, tiny_dataset: Path) -> None:
        from threedq.stages.base import EncoderStage

        torch.manual_seed(0)
        ckpt = tmp_path / "enc.pt"
        torch.save(EncoderStage().encoder.state_dict(), ckpt)  # an encoder state dict is a checkpoint too
        out = tmp_path / "rows.jsonl"
        feature_recipes.score_checkpoints([f"enc={ckpt}"], str(tiny_dataset), out, probe=False,
                                          channels=slice(0, 8))
        rows = [json.loads(line) for line in out.read_text().splitlines()]
        assert [r["variant"] for r in rows] == ["enc", "enc, channels 0:8"]
        assert rows[0]["raw/top1"] == rows[1]["raw/top1"]  # the raw crops are not sliced


class TestChannels:
    def test_slice_of_the_learned_crops_only(self) -> None:
        crops = {"learned": torch.arange(2 * 6 * 8.0).view(2, 6, 2, 2, 2), "gallery_learned": torch.ones(2, 6, 2, 2, 2),
                 "raw": torch.zeros(2, 4, 2, 2, 2)}
        out = feature_recipes._channels(crops, slice(0, 2))
        assert torch.equal(out["learned"], crops["learned"][:, :2]) and out["gallery_learned"].shape[1] == 2
        assert out["raw"] is crops["raw"] and feature_recipes._channels(crops, None) is crops

    def test_a_slice_outside_the_crops_is_refused(self) -> None:
        crops = {"learned": torch.zeros(2, 6, 2, 2, 2)}
        for bad in (slice(0, 7), slice(3, 3), slice(-1, 2)):
            with pytest.raises(ValueError, match="--channels"):
                feature_recipes._channels(crops, bad)


class TestCluster:
    def test_quarter_turned_copies_are_posed_exactly(self) -> None:
        """Three random shapes, 20 copies each turned by quarter turns (exact on the voxel grid): every bank groups
        copies of one shape and poses them against each other without error (the relative yaw of two copies)."""
        from threedq.geometry import rotate_yaw

        g = torch.Generator().manual_seed(0)
        shapes = torch.rand(3, 4, 8, 8, 8, generator=g)
        labels = torch.arange(3).repeat_interleave(20)
        quarter = torch.randint(0, 4, (60,), generator=g)
        yaw = quarter.double() * torch.pi / 2
        crops = torch.stack([rotate_yaw(shapes[c][None], yaw[i : i + 1].float())[0] for i, c in enumerate(labels)])
        boxes = torch.zeros(60, 7, dtype=torch.float64)
        boxes[:, 6] = yaw
        objects = {"learned": crops, "raw": torch.ones(60, 4, 8, 8, 8), "labels": labels, "boxes": boxes}
        out = feature_recipes._cluster(objects, objects, num_classes=3)
        for sim in ("cosine", "occupancy"):
            assert out[f"{sim}/yaw_median_deg"] == 0.0
            assert 0.0 < out[f"{sim}/hungarian"] <= 1.0

