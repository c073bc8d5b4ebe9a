"""Rotation-max retrieval: similarity at the best yaw and macro precision@K on hand-computed cases."""

from __future__ import annotations

import math

import pytest
import torch

from threedq.geometry import rotate_yaw
from threedq.metrics import RetrievalPrecisionAtK, retrieval_precision_at_k
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
