"""Hungarian-matched unsupervised classification accuracy: hand-computed cases, brute force, DDP-style merge."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from threedq.metrics.clustering import HungarianAccuracy, cluster_confusion, hungarian_accuracy, matching


def _brute_force(confusion: torch.Tensor) -> int:
    """Best one-to-one matched count over every injection of the smaller side into the larger."""
    k, c = confusion.shape
    if k <= c:
        return max(sum(int(confusion[i, cols[i]]) for i in range(k)) for cols in itertools.permutations(range(c), k))
    return max(sum(int(confusion[rows[j], j]) for j in range(c)) for rows in itertools.permutations(range(k), c))


class TestConfusion:
    def test_feature(self) -> None:
        clusters = torch.tensor([0, 0, 1, 2, 2, 2])
        labels = torch.tensor([1, 1, 0, 0, 1, 1])
        expected = torch.tensor([[0, 2], [1, 0], [1, 2]])
        assert torch.equal(cluster_confusion(clusters, labels, 3, 2), expected)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="same length"):
            cluster_confusion(torch.tensor([0, 1]), torch.tensor([0]), 2, 2)
        with pytest.raises(ValueError, match=r"clusters must lie in \[0, 2\)"):
            cluster_confusion(torch.tensor([0, 2]), torch.tensor([0, 0]), 2, 2)
        with pytest.raises(ValueError, match=r"labels must lie in \[0, 2\)"):
            cluster_confusion(torch.tensor([0, 1]), torch.tensor([-1, 0]), 2, 2)
        with pytest.raises(ValueError, match="integer"):
            cluster_confusion(torch.tensor([0.0, 1.0]), torch.tensor([0, 0]), 2, 2)
        with pytest.raises(ValueError, match="1-D"):
            cluster_confusion(torch.zeros(2, 2, dtype=torch.long), torch.zeros(2, 2, dtype=torch.long), 2, 2)


class TestHungarianAccuracy:
    def test_feature_square(self) -> None:
        # Clusters are a relabelling of classes 0->2, 1->0, 2->1, with one object of class 0 in cluster 1.
        confusion = torch.tensor([[0, 0, 4], [1, 0, 3], [0, 2, 0]])
        # Hand: best is 0->2 (4), 1->0 (1), 2->1 (2) = 7 of 10, not 0->2, 1->2 (many-to-one).
        assert hungarian_accuracy(confusion).item() == pytest.approx(0.7)
        rows, cols = matching(confusion)
        assert rows.tolist() == [0, 1, 2] and cols.tolist() == [2, 0, 1]

    def test_more_clusters_than_classes(self) -> None:
        # K = 4 prototypes, C = 2 classes: only 2 prototypes are matched, the rest count as wrong.
        confusion = torch.tensor([[3, 0], [2, 0], [0, 4], [0, 1]])
        assert hungarian_accuracy(confusion).item() == pytest.approx(7 / 10)
        rows, cols = matching(confusion)
        assert rows.tolist() == [0, 2] and cols.tolist() == [0, 1]

    def test_fewer_clusters_than_classes(self) -> None:
        # K = 1 prototype holds everything: only its best class counts.
        confusion = torch.tensor([[2, 5, 3]])
        assert hungarian_accuracy(confusion).item() == pytest.approx(0.5)
        rows, cols = matching(confusion)
        assert rows.tolist() == [0] and cols.tolist() == [1]

    def test_perfect_permutation(self) -> None:
        labels = torch.arange(5).repeat_interleave(3)
        clusters = (labels * 2 + 1) % 5  # a bijection of ids
        assert hungarian_accuracy(cluster_confusion(clusters, labels, 5, 5)).item() == 1.0

    @pytest.mark.parametrize("k", [1, 2, 3, 4, 5])
    @pytest.mark.parametrize("c", [1, 2, 3, 4, 5])
    def test_matches_brute_force(self, k: int, c: int) -> None:
        g = torch.Generator().manual_seed(100 * k + c)
        for _ in range(3):
            confusion = torch.randint(0, 7, (k, c), generator=g)
            confusion[0, 0] += 1  # N > 0
            best = _brute_force(confusion)
            assert hungarian_accuracy(confusion).item() == pytest.approx(best / int(confusion.sum()), abs=1e-6)
            rows, cols = matching(confusion)
            assert rows.numel() == min(k, c)
            assert len(set(rows.tolist())) == rows.numel() and len(set(cols.tolist())) == cols.numel()
            assert int(confusion[rows, cols].sum()) == best

    def test_empty(self) -> None:
        assert math.isnan(hungarian_accuracy(torch.zeros(3, 2, dtype=torch.long)).item())

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"\[K, C\]"):
            hungarian_accuracy(torch.zeros(3))
        with pytest.raises(ValueError, match="non-negative"):
            hungarian_accuracy(torch.tensor([[1, -1]]))


class TestHungarianAccuracyMetric:
    def test_smoke_and_batches(self) -> None:
        g = torch.Generator().manual_seed(0)
        clusters, labels = torch.randint(0, 6, (50,), generator=g), torch.randint(0, 4, (50,), generator=g)
        metric = HungarianAccuracy(num_clusters=6, num_classes=4)
        for s in range(0, 50, 7):
            metric.update(clusters[s : s + 7], labels[s : s + 7])
        expected = hungarian_accuracy(cluster_confusion(clusters, labels, 6, 4))
        assert torch.equal(metric.compute(), expected)
        metric.reset()
        assert int(metric.confusion.sum()) == 0
        with pytest.warns(UserWarning, match="before the ``update``"):
            assert math.isnan(metric.compute().item())

    def test_merge_state_equals_one_metric(self) -> None:
        """DDP-like: two 'ranks' each see half; merged states give the metric of everything."""
        g = torch.Generator().manual_seed(1)
        clusters, labels = torch.randint(0, 5, (40,), generator=g), torch.randint(0, 3, (40,), generator=g)
        full = HungarianAccuracy(5, 3)
        full.update(clusters, labels)
        m1, m2 = HungarianAccuracy(5, 3), HungarianAccuracy(5, 3)
        m1.update(clusters[:23], labels[:23])
        m2.update(clusters[23:], labels[23:])
        assert torch.equal(m1.confusion + m2.confusion, full.confusion)  # the "sum" all-reduce
        m1.merge_state(m2)
        assert torch.equal(m1.confusion, full.confusion)
        assert torch.equal(m1.compute(), full.compute())

    def test_many_to_one_is_not_counted(self) -> None:
        hungarian = HungarianAccuracy(num_clusters=4, num_classes=2)
        hungarian.update(torch.tensor([0, 0, 1, 2, 3]), torch.tensor([0, 0, 0, 1, 1]))
        assert hungarian.compute().item() == pytest.approx(3 / 5)

    def test_state_is_summed(self) -> None:
        metric = HungarianAccuracy(3, 2)
        assert metric._reductions["confusion"].__name__ == "dim_zero_sum"
        assert metric.full_state_update is False

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="num_clusters"):
            HungarianAccuracy(0, 2)
        metric = HungarianAccuracy(2, 2)
        with pytest.raises(ValueError, match=r"clusters must lie in \[0, 2\)"):
            metric.update(torch.tensor([2]), torch.tensor([0]))
        with pytest.raises(ValueError, match="same length"):
            metric.update(torch.tensor([0, 1]), torch.tensor([0]))
