"""Tests for benchmarks/yaw_common_pairs.py: two runs' yaw errors on all, common and own pairs, by hand."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import load_benchmark

from threedq.boxes import boxes_to_aabb

ycp = load_benchmark("yaw_common_pairs")

# one scene, five objects: three of the asymmetric category 0 (GT yaws 0, 30, 60 deg), two of the 4-fold category 1
GT_YAW_DEG = [0.0, 30.0, 60.0, 0.0, 45.0]
CATEGORIES = [0, 0, 0, 1, 1]


def _data(tmp_path: Path) -> Path:
    data = tmp_path / "data"
    (data / "test").mkdir(parents=True)
    boxes = np.array([[x, 0.0, 0.1, 0.3, 0.1, 0.2, math.radians(y)] for x, y in zip((-0.8, -0.4, 0.0, 0.4, 0.8), GT_YAW_DEG)],
                     np.float32)
    np.savez(data / "test" / "scene_000000.npz", boxes=boxes, categories=np.array(CATEGORIES, np.int64))
    (data / "index.json").write_text(json.dumps({"symmetry_order": [1, 4]}))
    return data


def _run(tmp_path: Path, data: Path, name: str, prototypes: list[int], angle_index: list[int]) -> Path:
    boxes = np.load(data / "test" / "scene_000000.npz")["boxes"].astype(np.float64)
    aabb = boxes_to_aabb(boxes)
    objects = [{"scene": "test/scene_000000.npz", "box": aabb[i].tolist(), "prototype": p, "angle_index": a,
                "similarity": 0.9} for i, (p, a) in enumerate(zip(prototypes, angle_index))]
    ev = tmp_path / name / "r00_eval"
    ev.mkdir(parents=True)
    (ev / "objects_test.json").write_text(json.dumps({"about": "", "num_angles": 36, "objects": objects}))
    return tmp_path / name


class TestYawCommonPairs:
    def test_hand_computed(self, tmp_path: Path) -> None:
        data = _data(tmp_path)
        # run a: the three category-0 objects in one prototype, posed with residuals (yaw + GT yaw) 0, 0, 10 deg:
        # pairs (0,1) 0, (0,2) 10, (1,2) 10 deg. Run b: objects 0 and 1 together (residuals 0, -10: 10 deg), 2 alone.
        # The category-1 objects share a prototype in both runs but are 4-fold symmetric: no pairs.
        a = _run(tmp_path, data, "a", [4, 4, 4, 9, 9], [0, 33, 31, 0, 5])
        b = _run(tmp_path, data, "b", [5, 5, 7, 2, 2], [0, 32, 0, 0, 5])
        table = ycp.main(["--data_dir", str(data), "--run", f"a={a}", "--run", f"b={b}", "--out", str(tmp_path / "t.md")])
        row = table.splitlines()[-1]
        assert row == "| 0 | 10.0 (3) | 10.0 (1) | 1 | 0.0 | 10.0 | 2, 10.0 | 0, nan |"
        assert (tmp_path / "t.md").read_text() == table + "\n"

    def test_compare_against_the_library_on_the_common_pairs(self, tmp_path: Path) -> None:
        data = _data(tmp_path)
        a = ycp.read_objects(_run(tmp_path, data, "a", [4, 4, 4, 9, 9], [0, 33, 31, 0, 5]) / "r00_eval/objects_test.json",
                             data)
        b = ycp.read_objects(_run(tmp_path, data, "b", [5, 5, 7, 2, 2], [0, 32, 0, 0, 5]) / "r00_eval/objects_test.json",
                             data)
        row = ycp.compare(a, b, [1, 4])
        assert (row["pairs_a"], row["pairs_b"], row["common"], row["only_a"], row["only_b"]) == (3, 1, 1, 2, 0)
        assert row["common_a"] == pytest.approx(0.0, abs=1e-5) and row["common_b"] == pytest.approx(10.0)  # float32 GT
        # the same run twice: every pair is common, and the numbers are the run's own
        same = ycp.compare(a, a, [1, 4])
        assert same["common"] == 3 and same["common_a"] == same["all_a"] == pytest.approx(10.0)

    def test_a_box_on_no_object_is_refused(self, tmp_path: Path) -> None:
        data = _data(tmp_path)
        run = _run(tmp_path, data, "a", [4, 4, 4, 9, 9], [0, 33, 31, 0, 5])
        path = run / "r00_eval" / "objects_test.json"
        d = json.loads(path.read_text())
        d["objects"][0]["box"] = [2.0, 2.0, 0.0, 2.1, 2.1, 0.1]
        path.write_text(json.dumps(d))
        with pytest.raises(SystemExit, match=r"objects_test.json: a box of test/scene_000000.npz overlaps no GT object"):
            ycp.read_objects(path, data)

    def test_needs_two_runs(self, tmp_path: Path) -> None:
        with pytest.raises(SystemExit):
            ycp.main(["--data_dir", str(tmp_path), "--run", "a=x"])
