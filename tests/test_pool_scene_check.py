"""benchmarks/pool_scene_check.py: the table of the pool checks against hand-counted boxes."""

from __future__ import annotations

import math

import numpy as np
from conftest import load_benchmark

psc = load_benchmark("pool_scene_check")


class TestCheckTable:
    def test_hand_counted(self) -> None:
        scores = {"on_object": np.array([1, 1, 0, 1, 0, 0], float),
                  "input_iou": np.array([1.0, 1.0, 1.0, 0.9, 0.2, 0.0]),
                  "scene_iou": np.array([0.9, 0.65, 0.55, 0.3, 0.9, 0.0])}
        rows = {r["check"]: r for r in psc.check_table(scores, 0.5, (0.5, 0.6, 0.7))}
        assert rows["every box"]["kept"] == 6 and rows["every box"]["on_objects"] == 0.5
        assert rows["input view >= 0.5"]["kept"] == 4 and rows["input view >= 0.5"]["on_objects"] == 0.75
        assert rows["input view >= 0.5, scene >= 0.5"]["kept"] == 3
        assert math.isclose(rows["input view >= 0.5, scene >= 0.5"]["on_objects"], 2 / 3)
        assert rows["input view >= 0.5, scene >= 0.6"]["kept"] == 2
        assert rows["input view >= 0.5, scene >= 0.6"]["on_objects"] == 1.0
        assert rows["input view >= 0.5, scene >= 0.7"]["kept"] == 1
        assert math.isclose(rows["input view >= 0.5, scene >= 0.7"]["kept_share"], 1 / 6)

    def test_nothing_kept(self) -> None:
        scores = {"on_object": np.array([1.0]), "input_iou": np.array([0.1]), "scene_iou": np.array([0.1])}
        rows = psc.check_table(scores, 0.5, (0.7,))
        assert rows[1]["kept"] == 0 and math.isnan(rows[1]["on_objects"])
