"""3D box IoU, NMS, matching and dataset-level mAP: Monte-Carlo volumes, naive loops, brute-force AP, DDP merge."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from threedq.boxes import aabb_iomin_3d, aabb_iou_3d, best_aabb_iou, nms_3d
from threedq.metrics import DetectionMAP, average_precision, match_detections


def _random_boxes(n: int, g: torch.Generator, lo: float = 0.0, hi: float = 0.6) -> torch.Tensor:
    """``[n, 6]`` boxes with min corner in ``[lo, hi]^3`` and extents in ``[0.4, 1.0]``."""
    mins = lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)
    sizes = 0.4 + 0.6 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    return torch.cat([mins, mins + sizes], dim=1)


def _py_iou(a: list[float], b: list[float]) -> float:
    """Plain-Python IoU of two boxes (reference for the NMS loop)."""
    inter = 1.0
    for k in range(3):
        inter *= max(0.0, min(a[k + 3], b[k + 3]) - max(a[k], b[k]))
    va = (a[3] - a[0]) * (a[4] - a[1]) * (a[5] - a[2])
    vb = (b[3] - b[0]) * (b[4] - b[1]) * (b[5] - b[2])
    union = va + vb - inter
    return inter / union if union > 0 else 0.0


def _py_iomin(a: list[float], b: list[float]) -> float:
    """Plain-Python intersection over the smaller volume (reference for the NMS loop)."""
    inter = 1.0
    for k in range(3):
        inter *= max(0.0, min(a[k + 3], b[k + 3]) - max(a[k], b[k]))
    va = (a[3] - a[0]) * (a[4] - a[1]) * (a[5] - a[2])
    vb = (b[3] - b[0]) * (b[4] - b[1]) * (b[5] - b[2])
    return inter / min(va, vb) if min(va, vb) > 0 else 0.0


def _naive_nms(boxes: list[list[float]], scores: list[float], thr: float, iomin: float = 1.0) -> list[int]:
    remaining = sorted(range(len(scores)), key=lambda i: -scores[i])
    keep = []
    while remaining:
        best = remaining.pop(0)
        keep.append(best)
        remaining = [
            i for i in remaining
            if _py_iou(boxes[best], boxes[i]) <= thr and _py_iomin(boxes[best], boxes[i]) <= iomin
        ]
    return keep


def _brute_force_ap(scores: list[float], tp: list[bool], num_gt: int) -> float:
    """Threshold at every distinct score, then integrate max precision at recall >= r over r in [0, 1]."""
    points = []  # (recall, precision) of "keep every detection with score >= s"
    for s in sorted(set(scores), reverse=True):
        kept = [t for sc, t in zip(scores, tp) if sc >= s]
        points.append((sum(kept) / num_gt, sum(kept) / len(kept)))
    levels = sorted({r for r, _ in points} | {0.0})
    area = 0.0
    for prev, r in itertools.pairwise(levels):
        area += (r - prev) * max(p for rr, p in points if rr >= r)
    return area


def _frame(boxes: torch.Tensor, scores: list[float]) -> dict[str, torch.Tensor]:
    return {"boxes": boxes, "scores": torch.tensor(scores, dtype=torch.float64)}


UNIT = [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]


class TestBestAabbIou:
    def test_against_a_naive_loop(self) -> None:
        g = torch.Generator().manual_seed(1)
        a, b = _random_boxes(5, g), _random_boxes(4, g)
        got = best_aabb_iou(a, b)
        assert got.shape == (5,)
        for i in range(5):
            assert float(got[i]) == pytest.approx(max(float(aabb_iou_3d(a[i:i + 1], b[j:j + 1])[0, 0]) for j in range(4)))

    def test_empty_sets(self) -> None:
        g = torch.Generator().manual_seed(2)
        assert torch.equal(best_aabb_iou(_random_boxes(3, g), torch.zeros(0, 6)), torch.zeros(3))
        assert best_aabb_iou(torch.zeros(0, 6), _random_boxes(2, g)).shape == (0,)


class TestAabbIou3d:
    def test_smoke_shape(self) -> None:
        g = torch.Generator().manual_seed(0)
        iou = aabb_iou_3d(_random_boxes(4, g), _random_boxes(3, g))
        assert iou.shape == (4, 3) and iou.dtype == torch.float64
        assert bool(((iou >= 0) & (iou <= 1)).all())
        assert aabb_iou_3d(torch.zeros(0, 6), _random_boxes(3, g).float()).shape == (0, 3)
        assert aabb_iou_3d(torch.tensor([[0, 0, 0, 2, 1, 1]]), torch.tensor([[1, 0, 0, 3, 1, 1]])).is_floating_point()

    def test_feature_hand(self) -> None:
        a = torch.tensor([UNIT])
        cases = {
            "identical": ([0.0, 0, 0, 1, 1, 1], 1.0),
            "disjoint": ([2.0, 2, 2, 3, 3, 3], 0.0),
            "touching": ([1.0, 0, 0, 2, 1, 1], 0.0),
            "half_overlap": ([0.5, 0, 0, 1.5, 1, 1], 1 / 3),  # inter 0.5, union 1.5
            "contained": ([0.25, 0.25, 0.25, 0.75, 0.75, 0.75], 0.125),  # 0.5^3 inside 1
            "contains": ([-1.0, -1, -1, 1, 1, 1], 1 / 8),
            "corner": ([0.5, 0.5, 0.5, 1.5, 1.5, 1.5], 0.125 / 1.875),
        }
        for name, (box, expected) in cases.items():
            b = torch.tensor([box])
            assert aabb_iou_3d(a, b).item() == pytest.approx(expected, abs=1e-7), name
            assert aabb_iou_3d(b, a).item() == pytest.approx(expected, abs=1e-7), name

    def test_degenerate_is_zero_not_nan(self) -> None:
        flat = torch.tensor([[0.0, 0, 0.5, 1, 1, 0.5], [0.3, 0.3, 0.3, 0.3, 0.3, 0.3]])  # zero-volume boxes
        iou = aabb_iou_3d(flat, torch.cat([flat, torch.tensor([UNIT])]))
        assert not bool(iou.isnan().any())
        assert torch.equal(iou, torch.zeros(2, 3, dtype=iou.dtype))

    def test_symmetric(self) -> None:
        g = torch.Generator().manual_seed(1)
        a, b = _random_boxes(5, g), _random_boxes(6, g)
        assert torch.allclose(aabb_iou_3d(a, b), aabb_iou_3d(b, a).T)
        assert torch.allclose(aabb_iou_3d(a, a).diagonal(), torch.ones(5, dtype=torch.float64))

    def test_matches_monte_carlo(self) -> None:
        """IoU vs. volumes estimated from 200k uniform points in each pair's joint bounding box."""
        g = torch.Generator().manual_seed(2)
        a, b = _random_boxes(3, g), _random_boxes(2, g)
        iou = aabb_iou_3d(a, b)
        n = 200_000
        for i in range(3):
            for j in range(2):
                lo, hi = torch.minimum(a[i, :3], b[j, :3]), torch.maximum(a[i, 3:], b[j, 3:])
                pts = lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)
                in_a = ((pts >= a[i, :3]) & (pts <= a[i, 3:])).all(dim=1)
                in_b = ((pts >= b[j, :3]) & (pts <= b[j, 3:])).all(dim=1)
                estimate = (in_a & in_b).sum().item() / (in_a | in_b).sum().item()
                assert iou[i, j].item() == pytest.approx(estimate, abs=5e-3), (i, j)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"a: expected a tensor of shape \[N, 6\]"):
            aabb_iou_3d(torch.zeros(6), torch.zeros(1, 6))
        with pytest.raises(ValueError, match=r"b: expected a tensor of shape \[N, 6\]"):
            aabb_iou_3d(torch.zeros(1, 6), torch.zeros(1, 7))
        with pytest.raises(ValueError, match="b: max < min in box 1"):
            aabb_iou_3d(torch.zeros(1, 6), torch.tensor([UNIT, [1.0, 0, 0, 0, 1, 1]]))
        with pytest.raises(ValueError, match="finite"):
            aabb_iou_3d(torch.tensor([[0.0, 0, 0, float("nan"), 1, 1]]), torch.zeros(1, 6))
        with pytest.raises(ValueError, match=r"a: expected"):
            aabb_iou_3d([UNIT], torch.zeros(1, 6))  # type: ignore[arg-type]


class TestAabbIomin3d:
    def test_feature_hand(self) -> None:
        big = torch.tensor([[0.0, 0, 0, 4, 4, 4]])
        boxes = torch.tensor([
            [1.0, 1, 1, 2, 2, 2],  # inside: 1 (IoU only 1/64)
            [3.0, 0, 0, 5, 4, 4],  # half inside: 16 / 32
            [5.0, 5, 5, 6, 6, 6],  # apart: 0
        ])
        assert aabb_iomin_3d(big, boxes).tolist() == [[1.0, 0.5, 0.0]]
        assert aabb_iou_3d(big, boxes)[0, 0].item() == pytest.approx(1 / 64)
        assert torch.equal(aabb_iomin_3d(boxes, big), aabb_iomin_3d(big, boxes).T)

    def test_degenerate_is_zero_not_nan(self) -> None:
        flat = torch.tensor([[0.5, 0.5, 0.5, 0.5, 1.0, 1.0]])
        assert aabb_iomin_3d(flat, torch.tensor([UNIT])).tolist() == [[0.0]]

    def test_matches_monte_carlo(self) -> None:
        """Intersection over the smaller volume vs. 200k uniform points in each pair's joint bounding box."""
        g = torch.Generator().manual_seed(4)
        a, b = _random_boxes(3, g), _random_boxes(2, g)
        iomin = aabb_iomin_3d(a, b)
        n = 200_000
        for i in range(3):
            for j in range(2):
                lo, hi = torch.minimum(a[i, :3], b[j, :3]), torch.maximum(a[i, 3:], b[j, 3:])
                pts = lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)
                in_a = ((pts >= a[i, :3]) & (pts <= a[i, 3:])).all(dim=1)
                in_b = ((pts >= b[j, :3]) & (pts <= b[j, 3:])).all(dim=1)
                estimate = (in_a & in_b).sum().item() / min(in_a.sum().item(), in_b.sum().item())
                assert iomin[i, j].item() == pytest.approx(estimate, abs=1e-2), (i, j)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"b: expected a tensor of shape \[N, 6\]"):
            aabb_iomin_3d(torch.zeros(1, 6), torch.zeros(1, 7))


class TestNms3d:
    def test_feature_hand(self) -> None:
        boxes = torch.tensor([
            UNIT,
            [0.1, 0.0, 0.0, 1.1, 1.0, 1.0],  # IoU 0.818 with box 0
            [0.3, 0.0, 0.0, 1.3, 1.0, 1.0],  # IoU 0.538 with box 0, 0.667 with box 1
            [5.0, 5.0, 5.0, 6.0, 6.0, 6.0],  # far away
        ])
        scores = torch.tensor([0.5, 0.9, 0.4, 0.1])
        assert nms_3d(boxes, scores, 0.5).tolist() == [1, 3]  # 0 and 2 suppressed by 1
        assert nms_3d(boxes, scores, 0.7).tolist() == [1, 2, 3]  # 0 suppressed (0.818), 2 not (0.667)
        assert nms_3d(boxes, scores, 1.0).tolist() == [1, 0, 2, 3]  # nothing suppressed, score order
        assert nms_3d(boxes, scores, 0.0).tolist() == [1, 3]

    def test_matches_naive_loop(self) -> None:
        g = torch.Generator().manual_seed(3)
        for n in (1, 5, 20, 40):
            boxes = _random_boxes(n, g, hi=2.0)
            scores = torch.rand(n, generator=g, dtype=torch.float64)
            for thr in (0.1, 0.25, 0.5):
                keep = nms_3d(boxes, scores, thr)
                assert keep.dtype == torch.long
                assert keep.tolist() == _naive_nms(boxes.tolist(), scores.tolist(), thr), (n, thr)
                assert bool((scores[keep].diff() <= 0).all())

    def test_nested_boxes_need_iomin(self) -> None:
        boxes = torch.tensor([[0.0, 0, 0, 1, 1, 1], [0.1, 0.1, 0.1, 0.5, 0.5, 0.6], [0.9, 0, 0, 1.9, 1, 1]])
        scores = torch.tensor([0.9, 0.8, 0.7])
        assert nms_3d(boxes, scores, 0.1).tolist() == [0, 1, 2]  # nested box: IoU 0.08, kept
        assert nms_3d(boxes, scores, 0.1, iomin_threshold=0.5).tolist() == [0, 2]  # side neighbour: 0.1, kept

    def test_iomin_matches_naive_loop(self) -> None:
        g = torch.Generator().manual_seed(5)
        for n in (5, 30):
            boxes = _random_boxes(n, g, hi=2.0)
            scores = torch.rand(n, generator=g, dtype=torch.float64)
            for thr, iomin in ((0.25, 0.5), (1.0, 0.3), (0.1, 0.8)):
                keep = nms_3d(boxes, scores, thr, iomin_threshold=iomin)
                assert keep.tolist() == _naive_nms(boxes.tolist(), scores.tolist(), thr, iomin), (n, thr, iomin)

    def test_empty(self) -> None:
        keep = nms_3d(torch.zeros(0, 6), torch.zeros(0), 0.5)
        assert keep.shape == (0,) and keep.dtype == torch.long

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"scores: expected shape \[2\]"):
            nms_3d(torch.tensor([UNIT, UNIT]), torch.zeros(3), 0.5)
        with pytest.raises(ValueError, match="iou_threshold"):
            nms_3d(torch.tensor([UNIT]), torch.zeros(1), 1.5)
        with pytest.raises(ValueError, match="iomin_threshold"):
            nms_3d(torch.tensor([UNIT]), torch.zeros(1), 0.5, iomin_threshold=-0.1)
        with pytest.raises(ValueError, match="boxes: max < min"):
            nms_3d(torch.tensor([[1.0, 0, 0, 0, 1, 1]]), torch.zeros(1), 0.5)
        with pytest.raises(ValueError, match="finite"):
            nms_3d(torch.tensor([UNIT]), torch.tensor([float("inf")]), 0.5)


class TestAveragePrecision:
    def test_feature_hand(self) -> None:
        ap = average_precision
        assert ap(torch.tensor([0.9, 0.8, 0.7]), torch.tensor([True, True, True]), 3) == pytest.approx(1.0)
        # One FP ranked first: recall 1/2, 1 at precision 1/2, 2/3 -> envelope 2/3 over [0, 1].
        assert ap(torch.tensor([0.9, 0.8, 0.7]), torch.tensor([False, True, True]), 2) == pytest.approx(2 / 3)
        # FP ranked last costs nothing: recall 1 is reached at precision 1.
        assert ap(torch.tensor([0.9, 0.8, 0.1]), torch.tensor([True, True, False]), 2) == pytest.approx(1.0)
        # A missed GT: recall stops at 2/3.
        assert ap(torch.tensor([0.9, 0.8]), torch.tensor([True, True]), 3) == pytest.approx(2 / 3)
        # Interleaved: TP FP TP FP TP, 5 GT: recall .2 .4 .6 at precision 1, 2/3, 3/5.
        flags = torch.tensor([1, 0, 1, 0, 1])
        assert ap(torch.tensor([5.0, 4, 3, 2, 1]), flags, 5) == pytest.approx(0.2 * 1 + 0.2 * 2 / 3 + 0.2 * 3 / 5)

    def test_edge_cases(self) -> None:
        assert math.isnan(average_precision(torch.zeros(0), torch.zeros(0, dtype=torch.bool), 0))
        assert math.isnan(average_precision(torch.tensor([0.5]), torch.tensor([False]), 0))
        assert average_precision(torch.zeros(0), torch.zeros(0, dtype=torch.bool), 4) == 0.0
        assert average_precision(torch.tensor([0.5, 0.4]), torch.tensor([False, False]), 1) == 0.0

    def test_ties_are_order_free(self) -> None:
        # Equal scores enter together: TP/FP order inside a tie does not matter.
        s = torch.tensor([0.9, 0.5, 0.5])
        a = average_precision(s, torch.tensor([True, False, True]), 2)
        b = average_precision(s, torch.tensor([True, True, False]), 2)
        assert a == b == pytest.approx(0.5 * 1 + 0.5 * 2 / 3)

    def test_matches_brute_force(self) -> None:
        g = torch.Generator().manual_seed(4)
        for trial in range(300):
            d = int(torch.randint(1, 9, (1,), generator=g))
            # Half the trials draw from few distinct values, to exercise ties.
            scores = torch.randint(0, 4 if trial % 2 else 1000, (d,), generator=g).double()
            flags = torch.rand(d, generator=g) < 0.5
            num_gt = int(flags.sum()) + int(torch.randint(0, 3, (1,), generator=g))
            if num_gt == 0:
                continue
            expected = _brute_force_ap(scores.tolist(), flags.tolist(), num_gt)
            assert average_precision(scores, flags, num_gt) == pytest.approx(expected, abs=1e-12), trial

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"is_true_positive: expected a 1-D tensor of shape \[2\]"):
            average_precision(torch.zeros(2), torch.zeros(3, dtype=torch.bool), 3)
        with pytest.raises(ValueError, match="scores: expected a 1-D"):
            average_precision(torch.zeros(2, 1), torch.zeros(2, dtype=torch.bool), 3)
        with pytest.raises(ValueError, match="num_gt"):
            average_precision(torch.zeros(2), torch.zeros(2, dtype=torch.bool), -1)
        with pytest.raises(ValueError, match="3 true positives but num_gt is 2"):
            average_precision(torch.zeros(3), torch.ones(3, dtype=torch.bool), 2)
        with pytest.raises(ValueError, match="0/1"):
            average_precision(torch.zeros(2), torch.tensor([0, 2]), 3)


class TestMatchDetections:
    def test_duplicate_is_false_positive(self) -> None:
        gt = torch.tensor([UNIT])
        pred = torch.tensor([UNIT, [0.05, 0, 0, 1.05, 1, 1]])
        assert match_detections(pred, torch.tensor([0.8, 0.9]), gt, 0.5).tolist() == [False, True]  # score wins
        assert match_detections(pred, torch.tensor([0.9, 0.8]), gt, 0.5).tolist() == [True, False]

    def test_falls_back_to_best_free_gt(self) -> None:
        gt = torch.tensor([UNIT, [0.2, 0, 0, 1.2, 1, 1]])
        pred = torch.tensor([[0.1, 0, 0, 1.1, 1, 1], [0.15, 0, 0, 1.15, 1, 1]])  # both overlap both GTs
        assert match_detections(pred, torch.tensor([0.9, 0.8]), gt, 0.5).tolist() == [True, True]
        # Below threshold with every GT: FP.
        far = torch.tensor([[0.6, 0, 0, 1.6, 1, 1]])
        assert match_detections(far, torch.tensor([1.0]), torch.tensor([UNIT]), 0.5).tolist() == [False]

    def test_threshold_is_inclusive(self) -> None:
        pred, gt = torch.tensor([[0.0, 0, 0, 2, 1, 1]]), torch.tensor([UNIT])  # IoU exactly 1/2
        assert match_detections(pred, torch.tensor([1.0]), gt, 0.5).tolist() == [True]
        assert match_detections(pred, torch.tensor([1.0]), gt, 0.51).tolist() == [False]

    def test_empty(self) -> None:
        out = match_detections(torch.zeros(0, 6), torch.zeros(0), torch.tensor([UNIT]), 0.5)
        assert out.shape == (0,) and out.dtype == torch.bool
        assert match_detections(torch.tensor([UNIT]), torch.ones(1), torch.zeros(0, 6), 0.5).tolist() == [False]

    def test_counts_bounded(self) -> None:
        g = torch.Generator().manual_seed(5)
        pred, gt = _random_boxes(30, g, hi=1.5), _random_boxes(6, g, hi=1.5)
        tp = match_detections(pred, torch.rand(30, generator=g), gt, 0.25)
        assert tp.shape == (30,) and 0 < int(tp.sum()) <= 6

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="iou_threshold"):
            match_detections(torch.tensor([UNIT]), torch.ones(1), torch.tensor([UNIT]), 0.0)
        with pytest.raises(ValueError, match=r"pred_scores: expected a 1-D tensor of shape \[1\]"):
            match_detections(torch.tensor([UNIT]), torch.ones(2), torch.tensor([UNIT]), 0.5)
        with pytest.raises(ValueError, match="gt_boxes"):
            match_detections(torch.tensor([UNIT]), torch.ones(1), torch.zeros(1, 7), 0.5)


def _random_frames(num_frames: int, seed: int) -> tuple[list[dict], list[dict]]:
    """GT boxes plus noisy copies, duplicates and clutter, with distinct scores."""
    g = torch.Generator().manual_seed(seed)
    preds, targets = [], []
    for _ in range(num_frames):
        gt = _random_boxes(int(torch.randint(0, 5, (1,), generator=g)), g, hi=3.0)
        noisy = gt + 0.15 * torch.randn(gt.shape, generator=g, dtype=torch.float64)
        noisy = torch.cat([noisy[:, :3].minimum(noisy[:, 3:]), noisy[:, :3].maximum(noisy[:, 3:])], dim=1)
        clutter = _random_boxes(int(torch.randint(0, 4, (1,), generator=g)), g, hi=3.0)
        boxes = torch.cat([noisy, noisy[: len(noisy) // 2], clutter])
        preds.append({"boxes": boxes, "scores": torch.rand(len(boxes), generator=g, dtype=torch.float64)})
        targets.append({"boxes": gt})
    return preds, targets


class TestDetectionMAP:
    def test_smoke_keys(self) -> None:
        metric = DetectionMAP()
        metric.update([_frame(torch.tensor([[0.0, 0, 0, 1.5, 1, 1]]), [0.9])], [{"boxes": torch.tensor([UNIT])}])
        out = metric.compute()
        assert set(out) == {"map_25", "map_50", "num_gt", "num_det"}
        assert out["map_25"].item() == 1.0 and out["map_50"].item() == 1.0
        assert out["num_gt"].item() == 1 and out["num_det"].item() == 1
        assert DetectionMAP(iou_thresholds=(0.7, 0.375)).keys == ("map_70", "map_37.5")

    def test_matches_pooled_functional(self) -> None:
        preds, targets = _random_frames(12, seed=6)
        metric = DetectionMAP(iou_thresholds=(0.25, 0.5))
        for s in range(0, 12, 5):
            metric.update(preds[s : s + 5], targets[s : s + 5])
        out = metric.compute()
        scores = torch.cat([p["scores"] for p in preds]).float()  # the metric keeps float32 scores
        num_gt = sum(len(t["boxes"]) for t in targets)
        for key, thr in (("map_25", 0.25), ("map_50", 0.5)):
            tp = torch.cat([match_detections(p["boxes"], p["scores"], t["boxes"], thr) for p, t in zip(preds, targets)])
            assert out[key].item() == pytest.approx(average_precision(scores, tp, num_gt), abs=1e-6)
        assert 0 < out["map_50"].item() <= out["map_25"].item() < 1
        assert out["num_gt"].item() == num_gt and out["num_det"].item() == len(scores)

    def test_dataset_level_not_per_frame_mean(self) -> None:
        # Frame A: one GT, found with score 0.9 (AP 1). Frame B: one GT, an FP at 0.95 above the TP at 0.1 (AP 1/2).
        gt = {"boxes": torch.tensor([UNIT])}
        far = [5.0, 5, 5, 6, 6, 6]
        preds = [_frame(torch.tensor([UNIT]), [0.9]), _frame(torch.tensor([far, UNIT]), [0.95, 0.1])]
        metric = DetectionMAP(iou_thresholds=(0.5,))
        metric.update(preds, [gt, gt])
        per_frame = [average_precision(p["scores"], match_detections(p["boxes"], p["scores"], gt["boxes"], 0.5), 1)
                     for p in preds]
        assert sum(per_frame) / 2 == pytest.approx(0.75)
        # Pooled ranking FP(0.95) TP(0.9) TP(0.1), 2 GT: precision 1/2 then 2/3 -> envelope 2/3.
        assert metric.compute()["map_50"].item() == pytest.approx(2 / 3)

    def test_frames_without_gt_or_detections(self) -> None:
        metric = DetectionMAP(iou_thresholds=(0.5,))
        metric.update([_frame(torch.tensor([UNIT]), [0.9]), _frame(torch.zeros(0, 6), [])],
                      [{"boxes": torch.tensor([UNIT])}, {"boxes": torch.tensor([[2.0, 2, 2, 3, 3, 3]])}])
        metric.update([_frame(torch.tensor([UNIT]), [0.95])], [{"boxes": torch.zeros(0, 6)}])  # FP, no GT
        out = metric.compute()
        assert out["map_50"].item() == pytest.approx(0.5 * 0.5)  # FP first, recall stops at 1/2
        assert out["num_gt"].item() == 2 and out["num_det"].item() == 2

    def test_merge_state_equals_one_metric(self) -> None:
        """DDP-like: two 'ranks' see halves of the frames; merged cat/sum states give the metric of everything."""
        preds, targets = _random_frames(10, seed=7)
        full = DetectionMAP()
        full.update(preds, targets)
        m1, m2 = DetectionMAP(), DetectionMAP()
        m1.update(preds[:6], targets[:6])
        m2.update(preds[6:], targets[6:])
        m1.merge_state(m2)  # concatenates rank 2 first: the result must not depend on order
        merged, expected = m1.compute(), full.compute()
        assert set(merged) == set(expected)
        for key in expected:
            assert torch.equal(merged[key], expected[key]), key

    def test_states_are_cat_and_sum(self) -> None:
        metric = DetectionMAP()
        for name in ("det_scores", "det_tp"):
            assert metric._reductions[name].__name__ == "dim_zero_cat"
        assert metric._reductions["num_gt"].__name__ == "dim_zero_sum"
        assert metric.full_state_update is False

    def test_reset_and_empty(self) -> None:
        metric = DetectionMAP()
        with pytest.warns(UserWarning, match="before the ``update``"):
            out = metric.compute()
        assert math.isnan(out["map_25"].item()) and out["num_gt"].item() == 0 and out["num_det"].item() == 0
        metric.update([_frame(torch.tensor([UNIT]), [0.9])], [{"boxes": torch.tensor([UNIT])}])
        metric.reset()
        assert metric.num_gt.item() == 0 and metric.det_scores == []

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="iou_thresholds"):
            DetectionMAP(iou_thresholds=(0.5, 1.5))
        with pytest.raises(ValueError, match="distinct"):
            DetectionMAP(iou_thresholds=(0.5, 0.5))
        with pytest.raises(ValueError, match="non-empty"):
            DetectionMAP(iou_thresholds=())
        metric = DetectionMAP()
        good = _frame(torch.tensor([UNIT]), [0.9])
        with pytest.raises(ValueError, match="one entry per frame"):
            metric.update([good], [])
        with pytest.raises(ValueError, match=r"preds\[0\] lacks the key 'scores'"):
            metric.update([{"boxes": torch.tensor([UNIT])}], [{"boxes": torch.tensor([UNIT])}])
        with pytest.raises(ValueError, match=r"targets\[1\]\['boxes'\]: expected a tensor of shape \[N, 6\]"):
            metric.update([good, good], [{"boxes": torch.tensor([UNIT])}, {"boxes": torch.zeros(1, 7)}])
        with pytest.raises(ValueError, match=r"preds\[0\]\['scores'\]: expected a 1-D tensor of shape \[1\]"):
            metric.update([_frame(torch.tensor([UNIT]), [0.9, 0.1])], [{"boxes": torch.tensor([UNIT])}])
        with pytest.raises(TypeError, match="list of dicts"):
            metric.update(good, [{"boxes": torch.tensor([UNIT])}])  # type: ignore[arg-type]
        assert metric.det_scores == [] and metric.num_gt.item() == 0  # bad batches left no trace
