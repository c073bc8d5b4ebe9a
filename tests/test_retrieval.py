"""Rotation-max retrieval: similarity at the best yaw, macro precision@K under both protocols, ceilings, top-1."""

from __future__ import annotations

import math

import pytest
import torch

from threedq.geometry import rotate_yaw
from threedq.metrics import (
    RetrievalPrecisionAtK,
    per_class_precision_at_k,
    precision_ceiling,
    retrieval_confusion,
    retrieval_precision_at_k,
    same_object_top1,
)
from threedq.quantization.rotation_search import rotation_max_similarity


def _blobs(n: int, size: int = 8, seed: int = 0) -> torch.Tensor:
    """Random smooth asymmetric volumes with a zero border (rotation loses nothing)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 2, size, size, size, generator=g)
    x = torch.nn.functional.avg_pool3d(x, 3, 1, 1)
    x[..., :2, :] = 0
    x[..., -2:, :] = 0
    x[..., :, :2] = 0
    x[..., :, -2:] = 0
    return x


class TestRotationMaxSimilarity:
    def test_recovers_a_known_yaw(self) -> None:
        q = _blobs(3)
        angle = torch.full((3,), math.radians(90))
        g = rotate_yaw(q, angle)
        sim, idx = rotation_max_similarity(q, g, num_angles=36)
        assert torch.allclose(sim.diagonal(), torch.ones(3), atol=1e-5)
        assert idx.diagonal().tolist() == [9, 9, 9]  # 9 x 10 deg

    def test_matches_naive_loop(self) -> None:
        q, g = _blobs(4, seed=1), _blobs(5, seed=2)
        sim, idx = rotation_max_similarity(q, g, num_angles=12, chunk=3)
        for i in range(4):
            for j in range(5):
                best = max(
                    (torch.nn.functional.cosine_similarity(
                        rotate_yaw(q[i : i + 1], torch.tensor([2 * math.pi * a / 12])).flatten(), g[j].flatten(), dim=0
                    ).item(), a)
                    for a in range(12)
                )
                assert sim[i, j].item() == pytest.approx(best[0], abs=1e-5)
                assert idx[i, j].item() == best[1]

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="same shape|one shape"):
            rotation_max_similarity(torch.zeros(2, 1, 4, 4, 4), torch.zeros(2, 2, 4, 4, 4))


class TestPrecisionAtK:
    def test_hand_computed(self) -> None:
        # 4 items: labels a a b b. Similarities make item 0 retrieve [1, 2], item 1 [2, 0],
        # item 2 [3, 0], item 3 [0, 2] (diagonal excluded).
        sim = torch.tensor(
            [[9, 5, 4, 1], [3, 9, 5, 1], [4, 1, 9, 6], [5, 1, 4, 9]], dtype=torch.float
        )
        labels = torch.tensor([0, 0, 1, 1])
        # k=1: hits 1, 0, 1, 0 -> class a 0.5, class b 0.5 -> 0.5
        assert retrieval_precision_at_k(sim, labels, labels, 1, exclude_diagonal=True).item() == pytest.approx(0.5)
        # k=2: hits 1/2, 1/2, 1/2, 1/2 -> 0.5
        assert retrieval_precision_at_k(sim, labels, labels, 2, exclude_diagonal=True).item() == pytest.approx(0.5)

    def test_macro_average(self) -> None:
        # class 0 has 3 perfect queries, class 1 one query with no hit: macro = (1 + 0) / 2, not 3/4.
        sim = torch.tensor([[0, 1, 1, 0], [1, 0, 1, 0], [1, 1, 0, 0], [1, 1, 1, 0]], dtype=torch.float)
        labels = torch.tensor([0, 0, 0, 1])
        assert retrieval_precision_at_k(sim, labels, labels, 1, exclude_diagonal=True).item() == pytest.approx(0.5)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="k must be"):
            retrieval_precision_at_k(torch.zeros(3, 3), torch.zeros(3), torch.zeros(3), 3, exclude_diagonal=True)

    def test_metric_equals_functional(self) -> None:
        crops = _blobs(6, seed=3)
        labels = torch.tensor([0, 1, 0, 1, 2, 2])
        m = RetrievalPrecisionAtK(k=2, num_angles=8)
        m.update(crops[:4], labels[:4])
        m.update(crops[4:], labels[4:])
        sim, _ = rotation_max_similarity(crops, crops, 8)
        ref = retrieval_precision_at_k(sim, labels, labels, 2, exclude_diagonal=True)
        assert m.compute().item() == pytest.approx(ref.item())


class TestProtocols:
    """Strict (leave-one-out) vs paper (twin in the gallery) protocol, the ceiling and the same-object top-1 rate."""

    def test_counting_the_twin_changes_precision_at_10(self) -> None:
        # 12 objects: category 0 has 2 (objects 0, 1), category 1 has 10. Paper protocol: gallery row i is query i's
        # twin, most similar to it; strict: the queries are the gallery and never retrieve themselves.
        labels = torch.tensor([0, 0] + [1] * 10)
        sim = torch.eye(12) * 2 + (labels[:, None] == labels[None, :]).float()  # same category 1, twin 3
        # strict, k = 10: category 0 finds its 1 other member (1/10), category 1 its 9 others (9/10) -> 0.5
        assert retrieval_precision_at_k(sim, labels, labels, 10, exclude_diagonal=True).item() == pytest.approx(0.5)
        # paper, k = 10: the twin is a hit too: 2/10 and 10/10 -> 0.6
        assert retrieval_precision_at_k(sim, labels, labels, 10).item() == pytest.approx(0.6)
        assert same_object_top1(sim).item() == 1.0
        # the ceilings of the two protocols on these labels are what perfect features reach
        assert precision_ceiling(labels, labels, 10, exclude_diagonal=True).item() == pytest.approx(0.5)
        assert precision_ceiling(labels, labels, 10).item() == pytest.approx(0.6)

    @pytest.mark.parametrize("k", [1, 3, 10])
    @pytest.mark.parametrize("strict", [True, False])
    def test_ceiling_equals_brute_force(self, k: int, strict: bool) -> None:
        g = torch.Generator().manual_seed(k)
        labels = torch.randint(0, 7, (40,), generator=g)
        # perfect features: every same-category item above every other, random order inside each group
        perfect = (labels[:, None] == labels[None, :]).double() + 0.1 * torch.rand(40, 40, generator=g, dtype=torch.float64)
        brute = retrieval_precision_at_k(perfect, labels, labels, k, exclude_diagonal=strict)
        assert precision_ceiling(labels, labels, k, exclude_diagonal=strict).item() == pytest.approx(brute.item())

    def test_same_object_top1_hand_computed(self) -> None:
        sim = torch.tensor([[5.0, 1.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 3.0]])
        assert same_object_top1(sim).item() == pytest.approx(2 / 3)  # query 1's nearest is object 0, not its twin
        with pytest.raises(ValueError, match="square"):
            same_object_top1(torch.zeros(2, 3))

    def test_confusion_against_a_naive_loop(self) -> None:
        g = torch.Generator().manual_seed(0)
        labels = torch.randint(0, 4, (15,), generator=g)
        sim = torch.rand(15, 15, generator=g)
        for strict in (True, False):
            conf = retrieval_confusion(sim, labels, labels, 4, k=3, exclude_diagonal=strict)
            ref = torch.zeros(4, 4, dtype=torch.long)
            for i in range(15):
                row = sim[i].clone()
                if strict:
                    row[i] = -float("inf")
                for j in row.topk(3).indices.tolist():
                    ref[labels[i], labels[j]] += 1
            assert torch.equal(conf, ref)

    def test_per_class_is_what_the_macro_average_averages(self) -> None:
        g = torch.Generator().manual_seed(1)
        labels = torch.randint(0, 5, (30,), generator=g)
        sim = torch.rand(30, 30, generator=g)
        classes, prec = per_class_precision_at_k(sim, labels, labels, 4)
        assert torch.equal(classes, labels.unique())
        assert prec.mean().item() == pytest.approx(retrieval_precision_at_k(sim, labels, labels, 4).item())

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="k must be"):
            precision_ceiling(torch.zeros(3), torch.zeros(3), 3, exclude_diagonal=True)
        with pytest.raises(ValueError, match="one length"):
            precision_ceiling(torch.zeros(3), torch.zeros(4), 2, exclude_diagonal=True)


class TestRetrievalTable:
    """Both protocols from crops: a gallery that is the queries turned by a known yaw finds every twin."""

    def test_rotated_gallery_is_found_by_the_rotation_search(self) -> None:
        from threedq.pipeline.evaluation import retrieval_table

        q = _blobs(12, seed=4)
        labels = torch.tensor([0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3])
        gallery = rotate_yaw(q, torch.full((12,), math.radians(90)))
        raw = torch.rand(12, 4, 8, 8, 8, generator=torch.Generator().manual_seed(5))
        aabb = torch.cat([torch.zeros(12, 3), torch.rand(12, 3, generator=torch.Generator().manual_seed(6)) + 0.1], 1)
        crops = {"labels": labels, "learned": q, "gallery_learned": gallery, "raw": raw, "gallery_raw": raw,
                 "aabb": aabb}
        table, sims = retrieval_table(crops, k=2, num_angles=36, search="exact", coarse_labels=labels // 2)
        paper = table["protocols"]["paper"]
        assert paper["same_object_top1"]["learned"] == 1.0  # every twin is the nearest at its 90 deg yaw
        assert paper["same_object_top1"]["colour_size_descriptor"] == 1.0  # identical raw crops and boxes
        assert table["protocols"]["strict"]["ceiling"] == pytest.approx(1.0)  # 3 per category fill k = 2 slots
        assert paper["coarse"]["num_classes"] == 2 and 0 <= paper["coarse"]["precision_at_k"]["learned"] <= 1
        assert sims["paper/learned"].shape == (12, 12) and table["precision_at_k"] == table["protocols"]["strict"][
            "precision_at_k"]
        strict_only, _ = retrieval_table({"labels": labels, "learned": q}, k=2, num_angles=36, search="exact")
        assert set(strict_only["protocols"]) == {"strict"}
