"""``benchmarks/robustness.py``: condition names, the table's means and ranges over seeds, the curve picture, and the
adaptation row read from a hand-written ``threedq em`` work dir."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from conftest import load_benchmark

robustness = load_benchmark("robustness")

METRICS = ("pseudo_map_50", "detector_map_50", "precision_at_10", "precision_at_10_paper", "hungarian_acc",
           "fewshot_acc", "yaw_median_deg")


def _row(mode: str, cond: str, seed: int, sensor: bool, value: float) -> dict:
    return {"mode": mode, "condition": cond, "seed": seed, "sensor_captures": sensor, **dict.fromkeys(METRICS, value)}


class TestRobustnessBenchmark:
    def test_conditions(self) -> None:
        assert robustness.condition("level0.5") == (0.5, None)
        assert robustness.condition("pose_drift") == (1.0, ["pose_drift"])
        with pytest.raises(SystemExit, match="condition 'blur'"):
            robustness.condition("blur")

    def test_table_mean_and_range_over_seeds(self) -> None:
        rows = [_row("adapted", "level1", 0, True, 0.4), _row("adapted", "level1", 1, True, 0.6),
                _row("frozen", "level0", 0, False, 0.9),
                {"mode": "adapted", "condition": "level2", "seed": 0, "sensor_captures": False,
                 "failed": "threedq: error: too few boxes"}]
        lines = robustness.table(rows).splitlines()
        assert lines[2].startswith("| frozen | renders | quantizer | level0 | 0 | 0.900 |")  # frozen first
        assert "| adapted | sensor captures | quantizer | level1 | 0, 1 | 0.500 (0.400-0.600) |" in lines[4]
        assert "stopped: threedq: error: too few boxes" in lines[3]

    def test_table_keeps_each_quantizer_and_detector_apart(self) -> None:
        """Rows without ``quantizer_config`` (``detector_config``) are the one-view quantizer's (the default detector's);
        other configs get their own line."""
        rows = [_row("adapted", "level1", 0, True, 0.4),
                {**_row("adapted", "level1", 0, True, 0.8), "quantizer_config": "stages/quantizer_multiview.yaml"}]
        lines = robustness.table(rows).splitlines()
        assert lines[2].startswith("| adapted | sensor captures | quantizer | level1 | 0 | 0.400 |")
        assert lines[3].startswith("| adapted | sensor captures | quantizer_multiview | level1 | 0 | 0.800 |")
        rows.append({**rows[-1], "detector_config": "stages/detector_sensor.yaml", "pseudo_map_50": 0.9})
        lines = robustness.table(rows).splitlines()
        assert lines[4].startswith("| adapted | sensor captures | quantizer_multiview + detector_sensor | level1 | 0 | "
                                   "0.900 |")
        rows.append({**rows[-1], "viewpred": "copy", "pseudo_map_50": 0.7})
        lines = robustness.table(rows).splitlines()
        assert lines[5].startswith("| adapted | sensor captures | quantizer_multiview + detector_sensor + view "
                                   "prediction on the copy | level1 | 0 | 0.700 |")

    def test_curve_png(self, tmp_path: Path) -> None:
        rows = [_row(m, c, 0, s, v) for m in ("frozen", "adapted") for s in (False, True)
                for c, v in (("level0", 0.8), ("level1", 0.6), ("level2", 0.4))]
        rows += [{**_row("adapted", c, 0, True, v), "quantizer_config": robustness.QUANTIZER,
                  "detector_config": robustness.DETECTOR} for c, v in (("level0", 0.9), ("level1", 0.8))]
        robustness.curve_png(rows, tmp_path / "c.png")
        assert (tmp_path / "c.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    def test_adapted_row_reads_the_run(self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        """The adaptation row: pseudo-boxes and warm start from the detector evaluation, the rest from the last
        round (the run itself replaced by a hand-written metrics.json)."""
        clean, work = tmp_path / "clean", tmp_path / "work"
        (clean / "train").mkdir(parents=True)
        (clean / "index.json").write_text("{}")
        (clean / "train" / "a.npz").write_bytes(b"scene")
        work.mkdir()

        commands = []

        def fake_run(cmd, **kwargs):
            commands.append(cmd)
            run = Path(cmd[cmd.index("--work_dir") + 1])
            run.mkdir(parents=True)
            (run / "metrics.json").write_text(json.dumps({
                "detector_eval": {"pseudo_boxes": {"map_50": 0.9}, "detector": {"map_50": 0.7}},
                "table3": [{"map_50": 0.7}, {"map_50": 0.8, "precision_at_10": 0.4, "precision_at_10_paper": 0.45}],
                "round_results": [{"quantization": {"threedq": {"hungarian_acc": 0.5, "fewshot_acc": 0.55,
                                                                "yaw_median_deg": 12.0}}}]}))
            return type("P", (), {"returncode": 0, "stdout": "", "stderr": ""})()

        monkeypatch.setattr(robustness.subprocess, "run", fake_run)
        row = robustness.adapted_row(tmp_path / "main", work, clean, "level0", 1, True)
        assert {k: row[k] for k in ("pseudo_map_50", "warm_start_map_50", "detector_map_50", "precision_at_10",
                                    "hungarian_acc", "yaw_median_deg")} == {
            "pseudo_map_50": 0.9, "warm_start_map_50": 0.7, "detector_map_50": 0.8, "precision_at_10": 0.4,
            "hungarian_acc": 0.5, "yaw_median_deg": 12.0}
        assert "sensor_captures: true" in (work / "data_level0_sensor.yaml").read_text()
        # the capture DataModules' quantizer and detector presets by default, named in the run's folder
        assert commands[0][commands[0].index("--quantizer_config") + 1] == "stages/quantizer_multiview.yaml"
        assert commands[0][commands[0].index("--detector_config") + 1] == "stages/detector_scene.yaml"
        run = Path(commands[0][commands[0].index("--work_dir") + 1])
        assert run.name == "adapted_level0_sensor_quantizer_multiview_detector_scene_s1"
        # level 0 is the clean folder, linked (its proposal caches are the copy's own)
        assert (work / "data_level0" / "train" / "a.npz").read_bytes() == b"scene"
        assert (work / "data_level0" / "train" / "a.npz").stat().st_ino == (clean / "train" / "a.npz").stat().st_ino
        ckpt = tmp_path / "main/00_viewpred/checkpoints/last.ckpt"
        assert commands[0][commands[0].index("--viewpred_ckpt") + 1] == str(ckpt)
        # view prediction trained on the copy: no checkpoint handed in, its own run folder
        robustness.adapted_row(tmp_path / "main", work, clean, "level0", 1, True, viewpred="copy")
        assert "--viewpred_ckpt" not in commands[1]
        assert Path(commands[1][commands[1].index("--work_dir") + 1]).name.endswith("_detector_scene_vpcopy_s1")


def test_pseudo_box_rows_on_the_tiny_data(tiny_dataset: Path, tmp_path: Path) -> None:
    """The quick first-stage table: per condition, both parameter sets; level 0's renders row is the DataModule's own
    pseudo-boxes (the same parameters) scored against the GT hulls."""
    from threedq.datamodules.scene_folder import SceneFolderDataModule
    from threedq.pipeline.detection_eval import box_sets_map, gt_hulls
    from threedq.scene import load_index

    tiny_dataset = Path(shutil.copytree(tiny_dataset, tmp_path / "data"))  # the DataModule caches into its folder
    rows = robustness.pseudo_box_rows(tiny_dataset, ["level0", "pose_drift"], scenes=2)
    assert [(r["condition"], r["read_as"]) for r in rows] == [
        ("level0", "renders"), ("level0", "sensor captures"), ("pose_drift", "renders"), ("pose_drift", "sensor captures")]
    files = load_index(tiny_dataset).files("test")[:2]
    dm = SceneFolderDataModule(str(tiny_dataset), sensor_captures=False)
    boxes = dm.pseudo_boxes("test")
    ref = box_sets_map(gt_hulls(tiny_dataset, files), {f: boxes[f] for f in files}, progress=False)
    assert rows[0]["map_50"] == pytest.approx(ref["map_50"]) and rows[0]["map_25"] == pytest.approx(ref["map_25"])
    table = robustness.pseudo_box_table(rows, 2).splitlines()
    assert table[0].startswith("| condition (2 test scenes) |") and table[3].startswith("| pose_drift | ")
