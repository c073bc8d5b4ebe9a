"""``threedq.metrics.localisation``: objects found per IoU and how the best box misses each, per size band."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from threedq.metrics.localisation import SIZE_BANDS, by_size_band, localisation_errors


def _iou_naive(a: list[float], b: list[float]) -> float:
    inter = 1.0
    for k in range(3):
        inter *= max(0.0, min(a[k + 3], b[k + 3]) - max(a[k], b[k]))
    vol = lambda x: (x[3] - x[0]) * (x[4] - x[1]) * (x[5] - x[2])
    return inter / (vol(a) + vol(b) - inter)


class TestLocalisationErrors:
    def test_smoke_shapes(self) -> None:
        out = localisation_errors(torch.rand(4, 3).repeat(1, 2) + torch.tensor([0, 0, 0, 1, 1, 1.0]), torch.rand(4),
                                  torch.tensor([[0.0, 0, 0, 1, 1, 1], [2, 2, 0, 3, 3, 1]]))
        assert out["found"].shape == (2, 2) and out["log_size_ratio"].shape == (2, 3) and out["best_iou"].shape == (2,)

    def test_hand_computed(self) -> None:
        gt = torch.tensor([[0.0, 0, 0, 1, 1, 1], [5, 5, 0, 6, 6, 1]])
        pred = torch.tensor([[0.1, 0, 0, 1.1, 1, 1], [5, 5, 0, 6, 6, 2]])
        out = localisation_errors(pred, torch.tensor([0.9, 0.8]), gt)
        # object 0: shifted 0.1 m in x -> IoU 0.9 / 1.1, right size; object 1: twice as tall -> IoU 0.5, centre +0.5 z
        assert out["best_iou"] == pytest.approx([0.9 / 1.1, 0.5], abs=1e-6)
        assert out["found"].tolist() == [[True, True], [True, True]]
        assert out["centre_error_xy"] == pytest.approx([0.1, 0.0], abs=1e-6)
        assert out["centre_error_z"] == pytest.approx([0.0, 0.5], abs=1e-6)
        assert out["log_size_ratio"][0] == pytest.approx([0, 0, 0], abs=1e-6)
        assert out["log_size_ratio"][1] == pytest.approx([0, 0, math.log(2)])

    def test_missed_object_and_no_boxes(self) -> None:
        gt = torch.tensor([[0.0, 0, 0, 1, 1, 1], [5, 5, 0, 6, 6, 1]])
        out = localisation_errors(torch.tensor([[0.0, 0, 0, 1, 1, 1]]), torch.tensor([1.0]), gt)
        assert out["found"][:, 1].tolist() == [True, False] and out["best_iou"][1] == 0
        assert np.isnan(out["centre_error_xy"][1]) and np.isnan(out["log_size_ratio"][1]).all()
        none = localisation_errors(torch.zeros(0, 6), torch.zeros(0), gt)
        assert not none["found"].any() and (none["best_iou"] == 0).all()
        assert localisation_errors(torch.zeros(0, 6), torch.zeros(0), torch.zeros(0, 6))["found"].shape == (0, 2)

    def test_one_box_finds_one_object(self) -> None:
        # one box between two objects overlapping both at IoU >= 0.25: it finds one of them, not both
        gt = torch.tensor([[0.0, 0, 0, 1, 1, 1], [0.5, 0, 0, 1.5, 1, 1]])
        out = localisation_errors(torch.tensor([[0.25, 0, 0, 1.25, 1, 1]]), torch.tensor([1.0]), gt)
        assert out["found"][:, 0].sum() == 1 and (out["best_iou"] > 0.25).all()

    def test_best_iou_against_a_naive_loop(self) -> None:
        g = torch.Generator().manual_seed(0)
        lo = torch.rand(7, 3, generator=g) * 2
        pred = torch.cat([lo, lo + 0.2 + torch.rand(7, 3, generator=g)], 1)
        lo = torch.rand(5, 3, generator=g) * 2
        gt = torch.cat([lo, lo + 0.2 + torch.rand(5, 3, generator=g)], 1)
        out = localisation_errors(pred, torch.rand(7, generator=g), gt)
        want = [max(_iou_naive(p.tolist(), q.tolist()) for p in pred) for q in gt]
        assert out["best_iou"] == pytest.approx(want, abs=1e-9)

    def test_exception(self) -> None:
        with pytest.raises(ValueError):
            localisation_errors(torch.zeros(2, 5), torch.zeros(2), torch.zeros(1, 6))
        with pytest.raises(ValueError):
            localisation_errors(torch.tensor([[0.0, 0, 0, 1, 1, 1]]), torch.zeros(2), torch.zeros(1, 6))


class TestBySizeBand:
    def test_hand_computed(self) -> None:
        # a 0.05 m object found at both IoUs, a 0.3 m one found at 0.25 only, a 0.3 m one missed
        gt = torch.tensor([[0.0, 0, 0, 0.05, 0.05, 0.05], [1, 1, 0, 1.3, 1.3, 0.3], [3, 3, 0, 3.3, 3.3, 0.3]])
        pred = torch.tensor([[0.0, 0, 0, 0.05, 0.05, 0.05], [1, 1, 0, 1.3, 1.3, 0.6]])  # IoU 1 and 0.5 - eps
        pred[1, 5] = 0.7  # IoU 0.3 / 0.7 = 0.43: found at 0.25, not at 0.5
        rows = by_size_band([localisation_errors(pred, torch.tensor([1.0, 0.9]), gt)])
        assert [r["band"] for r in rows] == ["0.00-0.10 m", "0.10-0.20 m", "0.20-0.40 m", ">= 0.40 m", "all"]
        small, mid, big, _, everything = rows
        assert (small["objects"], small["found_25"], small["found_50"]) == (1, 1.0, 1.0)
        assert mid["objects"] == 0 and math.isnan(mid["found_25"])
        assert (big["objects"], big["found_25"], big["found_50"]) == (2, 0.5, 0.0)
        assert big["median_centre_error_z"] == pytest.approx(0.2)  # of the overlapped one only
        assert big["median_abs_log_size_ratio"][2] == pytest.approx(math.log(0.7 / 0.3))
        assert everything["objects"] == 3 and everything["found_25"] == pytest.approx(2 / 3)

    def test_flat_row(self) -> None:
        # a 0.5 m wide, 3 cm tall object (found) and a 0.3 m cube (missed): the flat row holds the first only
        gt = torch.tensor([[0.0, 0, 0, 0.5, 0.2, 0.03], [1, 1, 0, 1.3, 1.3, 0.3]])
        pred = torch.tensor([[0.0, 0, 0, 0.5, 0.2, 0.03]])
        rows = by_size_band([localisation_errors(pred, torch.ones(1), gt)], flat_height=0.04)
        assert [r["band"] for r in rows][-2:] == ["flat: < 0.040 m tall", "all"]
        flat = rows[-2]
        assert (flat["objects"], flat["found_25"], flat["found_50"]) == (1, 1.0, 1.0)
        assert rows[-1]["objects"] == 2 and rows[-1]["found_50"] == 0.5
        assert by_size_band([], flat_height=0.04)[-2]["objects"] == 0

    def test_pools_scenes_and_empty(self) -> None:
        one = localisation_errors(torch.tensor([[0.0, 0, 0, 1, 1, 1]]), torch.tensor([1.0]),
                                  torch.tensor([[0.0, 0, 0, 1, 1, 1]]))
        rows = by_size_band([one, one])
        assert rows[-1]["objects"] == 2 and rows[-1]["found_50"] == 1.0 and rows[3]["objects"] == 2
        assert by_size_band([])[-1]["objects"] == 0
        assert SIZE_BANDS[0] == 0 and math.isinf(SIZE_BANDS[-1])
