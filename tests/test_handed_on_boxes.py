"""benchmarks/handed_on_boxes.py: the occlusion measure of a box against a hand-made depth map, the table of the pool
checks against hand-counted boxes."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import handed_on_boxes as hob  # noqa: E402


class TestOccludedFraction:
    K = torch.tensor([[100.0, 0.0, 32.0], [0.0, 100.0, 32.0], [0.0, 0.0, 1.0]])

    def test_hand_computed(self) -> None:
        # camera frame = R (OpenCV axes, z forward); a 0.2 m box 2.0-2.2 m ahead projects to pixels 27..37 both ways
        # (u = 100 x / z + 32 with x = +-0.1 at z = 2); something at 1 m covers columns 0..31 of the image
        aabb = torch.tensor([[-0.1, -0.1, 2.0, 0.1, 0.1, 2.2]])
        depth = torch.full((64, 64), 3.0)
        depth[:, :32] = 1.0
        frac = hob.occluded_fraction(aabb, depth, self.K, torch.eye(4))
        torch.testing.assert_close(frac, torch.tensor([5 / 11]))  # columns 27..31 of 27..37

    def test_nothing_in_front_and_invalid_pixels(self) -> None:
        aabb = torch.tensor([[-0.1, -0.1, 2.0, 0.1, 0.1, 2.2]])
        depth = torch.full((64, 64), 2.1)
        depth[:, :32] = 1.97  # nearer than the box's nearest corner, but within the 5 cm margin
        assert hob.occluded_fraction(aabb, depth, self.K, torch.eye(4)).item() == 0.0
        depth.zero_()  # no valid depth at all
        assert hob.occluded_fraction(aabb, depth, self.K, torch.eye(4)).item() == 0.0


class TestCheckTable:
    def test_hand_counted(self) -> None:
        scores = {"on_object": np.array([1, 1, 0, 1, 0, 0], float),
                  "input_iou": np.array([1.0, 1.0, 1.0, 0.9, 0.2, 0.0]),
                  "scene_iou": np.array([0.9, 0.65, 0.55, 0.3, 0.9, 0.0])}
        rows = {r["check"]: r for r in hob.check_table(scores, 0.5, (0.5, 0.6, 0.7))}
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
        rows = hob.check_table(scores, 0.5, (0.7,))
        assert rows[1]["kept"] == 0 and math.isnan(rows[1]["on_objects"])
