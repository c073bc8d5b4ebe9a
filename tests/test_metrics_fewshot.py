"""Few-shot labelling through prototypes (Table 1 protocol): propagation rule, selection, DDP-style merge."""

from __future__ import annotations

import math

import pytest
import torch

from threedq.metrics.fewshot import FewShotAccuracy, few_shot_accuracy, select_labelled

# Hand-made case: 4 prototypes (+1 empty), 3 categories, labelled examples given explicitly.
CLUSTERS = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 3, 3, 3, 3])
LABELS = torch.tensor([0, 0, 1, 1, 1, 2, 2, 2, 0, 2, 2, 1, 1, 2])
LABELLED = torch.tensor([0, 2, 4, 5, 6, 10, 11])


def _random_case(n: int = 60, k: int = 6, c: int = 4, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    labels = torch.randint(0, c, (n,), generator=g)
    noisy = torch.rand(n, generator=g) < 0.3
    clusters = torch.where(noisy, torch.randint(0, k, (n,), generator=g), labels)  # mostly pure clusters
    return clusters, labels


class TestFewShotAccuracy:
    def test_feature_hand_computed(self) -> None:
        out = few_shot_accuracy(CLUSTERS, LABELS, num_clusters=5, labelled_indices=LABELLED)
        # Prototype 0: labelled {0, 1} -> tie -> 0. Prototype 1: labelled {1, 2, 2} -> 2.
        # Prototype 2: nothing labelled -> -1. Prototype 3: labelled {2, 1} -> tie -> 1 (smallest id).
        # Prototype 4: empty -> -1.
        assert out["cluster_labels"].tolist() == [0, 2, -1, 1, -1]
        # Not labelled: 1 (0 ok), 3 (1 wrong), 7 (2 ok), 8, 9 (no label: wrong), 12 (1 ok), 13 (2 wrong).
        assert out["accuracy"].item() == pytest.approx(3 / 7)
        assert out["labelled_indices"].tolist() == LABELLED.tolist()

    def test_perfect_clusters_any_seed(self) -> None:
        labels = torch.arange(4).repeat_interleave(5)
        clusters = (labels + 1) % 4
        for seed in range(5):
            out = few_shot_accuracy(clusters, labels, shots=2, seed=seed)
            assert out["accuracy"].item() == 1.0
            assert out["cluster_labels"].tolist() == [3, 0, 1, 2]
            assert out["labelled_indices"].numel() == 8

    def test_merged_cluster_tie(self) -> None:
        # Two categories in one prototype, one shot each: a tie, won by category 0.
        out = few_shot_accuracy(torch.zeros(6, dtype=torch.long), torch.tensor([1, 1, 1, 0, 0, 0]), shots=1)
        assert out["cluster_labels"].tolist() == [0]
        assert out["accuracy"].item() == pytest.approx(2 / 4)

    def test_all_labelled_is_nan(self) -> None:
        out = few_shot_accuracy(torch.tensor([0, 1]), torch.tensor([0, 1]), shots=2)
        assert math.isnan(out["accuracy"].item())
        assert out["labelled_indices"].tolist() == [0, 1]

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="same length"):
            few_shot_accuracy(torch.tensor([0, 1]), torch.tensor([0]))
        with pytest.raises(ValueError, match="shots"):
            few_shot_accuracy(torch.tensor([0, 1]), torch.tensor([0, 1]), shots=0)
        with pytest.raises(ValueError, match=r"clusters must lie in \[0, 2\)"):
            few_shot_accuracy(torch.tensor([0, 2]), torch.tensor([0, 1]), num_clusters=2)
        with pytest.raises(ValueError, match="labels must lie"):
            few_shot_accuracy(torch.tensor([0, 1]), torch.tensor([0, -1]))
        with pytest.raises(ValueError, match="labelled_indices"):
            few_shot_accuracy(torch.tensor([0, 1]), torch.tensor([0, 1]), labelled_indices=torch.tensor([2]))


class TestSelectLabelled:
    def test_counts_per_category(self) -> None:
        labels = torch.tensor([2, 0, 2, 2, 1, 0, 2, 0, 0])  # n_c = 4, 1, 4 (category 1 has one object)
        idx = select_labelled(labels, shots=2, seed=3)
        assert idx.tolist() == sorted(idx.tolist())
        assert torch.bincount(labels[idx], minlength=3).tolist() == [2, 1, 2]

    def test_deterministic_and_seeded(self) -> None:
        clusters, labels = _random_case()
        a = select_labelled(labels, 2, seed=7, clusters=clusters)
        assert torch.equal(a, select_labelled(labels, 2, seed=7, clusters=clusters))
        chosen = {tuple(select_labelled(labels, 2, seed=s, clusters=clusters).tolist()) for s in range(6)}
        assert len(chosen) > 1

    def test_order_independent(self) -> None:
        """Permuting the objects (e.g. another DDP gather order) changes nothing measurable."""
        clusters, labels = _random_case(seed=4)
        perm = torch.randperm(labels.numel(), generator=torch.Generator().manual_seed(9))
        for seed in range(4):
            a = few_shot_accuracy(clusters, labels, shots=2, seed=seed, num_clusters=6)
            b = few_shot_accuracy(clusters[perm], labels[perm], shots=2, seed=seed, num_clusters=6)
            assert torch.equal(a["accuracy"], b["accuracy"])
            assert torch.equal(a["cluster_labels"], b["cluster_labels"])
            idx_a, idx_b = a["labelled_indices"], b["labelled_indices"]
            pairs_a = sorted(zip(clusters[idx_a].tolist(), labels[idx_a].tolist(), strict=True))
            pairs_b = sorted(zip(clusters[perm][idx_b].tolist(), labels[perm][idx_b].tolist(), strict=True))
            assert pairs_a == pairs_b


class TestFewShotAccuracyMetric:
    def test_equals_functional(self) -> None:
        clusters, labels = _random_case(seed=1)
        metric = FewShotAccuracy(num_clusters=6, num_classes=4, shots=2, seed=5)
        for s in range(0, labels.numel(), 11):
            metric.update(clusters[s : s + 11], labels[s : s + 11])
        expected = few_shot_accuracy(clusters, labels, shots=2, seed=5, num_clusters=6)["accuracy"]
        assert torch.equal(metric.compute(), expected)

    def test_merge_state_equals_one_metric(self) -> None:
        """DDP-like: two 'ranks' see halves; merge_state concatenates (rank 2 first) and still agrees."""
        clusters, labels = _random_case(seed=2)
        full = FewShotAccuracy(6, 4, shots=2, seed=0)
        full.update(clusters, labels)
        m1, m2 = FewShotAccuracy(6, 4, shots=2, seed=0), FewShotAccuracy(6, 4, shots=2, seed=0)
        m1.update(clusters[::2], labels[::2])  # interleaved halves, like a DistributedSampler
        m2.update(clusters[1::2], labels[1::2])
        m1.merge_state(m2)
        assert torch.equal(m1.compute(), full.compute())

    def test_states_are_cat_lists(self) -> None:
        metric = FewShotAccuracy(3, 3)
        assert metric.clusters == [] and metric.labels == []
        assert metric._reductions["clusters"].__name__ == "dim_zero_cat"
        assert metric.full_state_update is False

    def test_reset_and_empty(self) -> None:
        metric = FewShotAccuracy(2, 2, shots=1)
        metric.update(torch.tensor([0, 0, 1, 1]), torch.tensor([0, 0, 1, 1]))
        assert metric.compute().item() == 1.0
        metric.reset()
        with pytest.warns(UserWarning, match="before the ``update``"):
            assert math.isnan(metric.compute().item())

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="shots"):
            FewShotAccuracy(2, 2, shots=0)
        metric = FewShotAccuracy(2, 3)
        with pytest.raises(ValueError, match=r"labels must lie in \[0, 3\)"):
            metric.update(torch.tensor([0, 1]), torch.tensor([0, 3]))
        with pytest.raises(ValueError, match=r"clusters must lie in \[0, 2\)"):
            metric.update(torch.tensor([0, 2]), torch.tensor([0, 1]))


class TestLinearProbe:
    """A linear probe trained on every labelled training object (Table 2's reference row), scored on test objects."""

    def _clusters(self, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
        g = torch.Generator().manual_seed(seed)
        labels = torch.arange(n) % 3
        centres = torch.tensor([[4.0, 0.0], [0.0, 4.0], [-4.0, -4.0]])
        return centres[labels] + 0.3 * torch.randn(n, 2, generator=g), labels

    def test_separable_classes_are_all_right(self) -> None:
        from threedq.metrics import linear_probe

        xtr, ytr = self._clusters(30, 0)
        xte, yte = self._clusters(12, 1)
        out = linear_probe(xtr, ytr, xte, yte)
        assert out["accuracy"].item() == 1.0 and torch.equal(out["predicted"], yte)

    def test_units_do_not_matter(self) -> None:
        from threedq.metrics import linear_probe

        xtr, ytr = self._clusters(30, 2)
        xte, yte = self._clusters(30, 3)
        xtr[:, 0] += 0.5 * torch.randn(30, generator=torch.Generator().manual_seed(4))  # overlapping classes
        scale = torch.tensor([1000.0, 0.001])
        a = linear_probe(xtr, ytr, xte, yte)["predicted"]
        b = linear_probe(xtr * scale + 7, ytr, xte * scale + 7, yte)["predicted"]
        assert (a == b).float().mean().item() >= 0.95  # standardised: the same classifier up to L-BFGS rounding

    def test_exception(self) -> None:
        from threedq.metrics import linear_probe

        with pytest.raises(ValueError, match="width"):
            linear_probe(torch.zeros(4, 2), torch.zeros(4, dtype=torch.long), torch.zeros(4, 3),
                         torch.zeros(4, dtype=torch.long))
