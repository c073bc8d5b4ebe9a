"""``benchmarks/pose.py``: its yaw summary against known yaws, the direct pair search on rotated copies, its table."""

from __future__ import annotations

import math

import torch
from conftest import load_benchmark

from threedq.geometry import rotate_yaw, yaw_angles

pose = load_benchmark("pose")


def _test(yaws_deg: list[float], labels: list[int]) -> dict:
    boxes = torch.zeros(len(yaws_deg), 7, dtype=torch.float64)
    boxes[:, 6] = torch.deg2rad(torch.tensor(yaws_deg, dtype=torch.float64))
    return {"boxes": boxes, "labels": torch.tensor(labels)}


class TestYawSummary:
    def test_perfect_and_one_step_off(self):
        test = _test([0, 30, 60, 90, 0, 90], [0, 0, 0, 0, 1, 1])  # category 1 is 4-fold
        clusters = torch.zeros(6, dtype=torch.long)
        perfect = torch.tensor([0, 33, 30, 27, 0, 0])  # y = -g in steps of 10 deg; the cube's quarter turn is free
        s = pose.yaw_summary(perfect, clusters, test, [1, 4])
        assert s["asym_median_deg"] == 0 and s["asym_acc_10"] == 1 and s["asym_pairs"] == 6 and s["asym_objects"] == 4
        assert s["4fold_median_deg"] == 0 and math.isnan(s["2fold_median_deg"])
        off = perfect.clone()
        off[0] = 1  # object 0 one step (10 deg) off: its 3 pairs are 10 deg off, the other 3 exact
        s = pose.yaw_summary(off, clusters, test, [1, 4])
        assert s["asym_median_deg"] == 5.0 and s["asym_acc_10"] == 1 and s["asym_acc_20"] == 1


class TestPairYawError:
    def test_rotated_copies(self):
        """Copies of one asymmetric crop turned by known yaws, labelled with those yaws: the direct search finds
        every relative yaw (error 0); with the GT yaws shuffled, it does not."""
        g = torch.Generator().manual_seed(0)
        base = torch.zeros(1, 2, 8, 16, 16, dtype=torch.float64)
        base[:, :, 2:6, 4:12, 5:8] = torch.rand(1, 2, 4, 8, 3, generator=g, dtype=torch.float64) + 0.5
        base[:, :, 2:6, 9:12, 8:12] = 1.0
        steps = torch.tensor([0, 5, 12, 20, 27])
        crops = torch.cat([rotate_yaw(base, yaw_angles(36, dtype=torch.float64)[s][None]) for s in steps])
        test = _test([10.0 * float(s) for s in steps], [0] * 5)
        assert pose.pair_yaw_error(crops, test, [1]) == 0.0
        wrong = _test([10.0 * float(s) for s in steps[[2, 0, 4, 1, 3]]], [0] * 5)
        assert pose.pair_yaw_error(crops, wrong, [1]) > 30


class TestTable:
    def test_means_and_ranges(self):
        rows = [{"dataset": "unseen", "row": "enc", "seed": s, "objects": 9, "asym_median_deg": v, "asym_acc_10": a}
                for s, v, a in ((0, 10.0, 0.5), (1, 20.0, 0.7))]
        rows.append({"dataset": "unseen", "row": "random yaw", "seed": 0, "objects": 9, "asym_median_deg": 88.0})
        rows.append({"dataset": "unseen", "row": "enc", "input_views": 3, "boxes": "detected", "seed": 0, "objects": 7,
                     "asym_objects": 3.0, "asym_median_deg": 12.0})
        md = pose.table(rows).splitlines()
        assert md[2].startswith("| unseen | GT | 1 | enc | 2 | 9 |  | 15.0 (10.0-20.0) | 0.60 (0.50-0.70) |")
        assert md[3].startswith("| unseen | GT | 1 | random yaw | 1 | 9 |  | 88.0 |  |")
        assert md[4].startswith("| unseen | detected | 3 | enc | 1 | 7 | 3 | 12.0 |")
