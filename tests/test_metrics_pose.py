"""Relative yaw error within prototypes: exact errors, the sign convention, symmetric categories, DDP merge."""

from __future__ import annotations

import math

import pytest
import torch

from threedq.geometry import rotate_yaw
from threedq.metrics.pose import RelativeYawError, relative_yaw_error, relative_yaw_errors
from threedq.quantization.rotation_search import rotation_max_similarity


def _rad(deg: list[float] | torch.Tensor) -> torch.Tensor:
    return torch.deg2rad(torch.as_tensor(deg, dtype=torch.float64))


def _deg(rad: torch.Tensor) -> list[float]:
    """Errors in degrees, sorted (pairs come grouped and ordered by residual, not by input order)."""
    return sorted(round(v, 6) for v in torch.rad2deg(rad).tolist())


def _zeros(n: int) -> torch.Tensor:
    return torch.zeros(n, dtype=torch.long)


class TestRelativeYawErrors:
    def test_perfect_estimates_give_zero(self) -> None:
        g = torch.Generator().manual_seed(0)
        gt = (torch.rand(30, generator=g, dtype=torch.float64) - 0.5) * 4 * math.pi  # beyond [-pi, pi)
        clusters = torch.randint(0, 3, (30,), generator=g)
        cats = torch.randint(0, 2, (30,), generator=g)
        const = torch.tensor([0.3, -2.0, 5.0], dtype=torch.float64)[clusters]  # one canonical pose per prototype
        est = const - gt  # alignment yaw = -GT yaw + const
        errors = relative_yaw_errors(est, gt, cats, clusters, [1, 1])
        groups = torch.bincount(clusters * 2 + cats, minlength=6)
        assert errors.numel() == int((groups * (groups - 1) // 2).sum())
        assert errors.abs().max().item() < 1e-12

    def test_injected_error_is_measured_exactly(self) -> None:
        gt = _rad([10.0, 100.0, -170.0, 175.0])
        est = 0.7 - gt + _rad([0.0, 15.0, 0.0, -190.0])  # object 3: -190 deg == +170 deg
        errors = relative_yaw_errors(est, gt, _zeros(4), torch.tensor([0, 0, 1, 1]), [1])
        assert _deg(errors) == [15.0, 170.0]
        out = relative_yaw_error(est, gt, _zeros(4), torch.tensor([0, 0, 1, 1]), [1])
        assert out["median_deg"].item() == pytest.approx(92.5)  # mean of the two middle values
        assert out["acc_10"].item() == 0.0 and out["acc_20"].item() == 0.5
        assert out["num_pairs"].item() == 2

    def test_wrapped_to_zero_pi(self) -> None:
        g = torch.Generator().manual_seed(1)
        est = torch.rand(20, generator=g, dtype=torch.float64) * 20 - 10
        gt = torch.rand(20, generator=g, dtype=torch.float64) * 20 - 10
        errors = relative_yaw_errors(est, gt, _zeros(20), _zeros(20), [1])
        assert errors.numel() == 190
        assert errors.min().item() >= 0.0 and errors.max().item() <= math.pi + 1e-12

    def test_sign_convention(self) -> None:
        """Alignment yaws are -GT + const; the opposite sign is caught as an error."""
        gt = _rad([0.0, 30.0, 100.0])
        right = 0.7 - gt
        wrong = 0.7 + gt  # as if y were the object's orientation
        assert relative_yaw_errors(right, gt, _zeros(3), _zeros(3), [1]).abs().max().item() < 1e-12
        # Pairs (0,1), (0,2), (1,2): the wrong sign doubles each relative yaw: 60, 200 -> 160, 140 deg.
        assert _deg(relative_yaw_errors(wrong, gt, _zeros(3), _zeros(3), [1])) == [60.0, 140.0, 160.0]

    def test_sign_convention_with_rotate_yaw(self) -> None:
        """Objects are rotated copies of one shape; their alignment yaw comes from the real matcher."""
        g = torch.Generator().manual_seed(0)
        proto = torch.nn.functional.avg_pool3d(torch.rand(1, 2, 12, 12, 12, generator=g), 3, 1, 1)
        yy, xx = torch.meshgrid(torch.arange(12.0) - 5.5, torch.arange(12.0) - 5.5, indexing="ij")
        proto = proto * ((yy**2 + xx**2) <= 4.5**2).float()  # zero outside a disc: rotation loses nothing
        gt_deg = torch.tensor([0.0, 40.0, 90.0, 130.0, 200.0, 310.0])
        objects = rotate_yaw(proto.expand(6, -1, -1, -1, -1).contiguous(), torch.deg2rad(gt_deg))
        _, angle = rotation_max_similarity(objects, proto, num_angles=36)  # rotating object by it aligns it
        est = angle[:, 0].double() * (2 * math.pi / 36)
        assert torch.equal(angle[:, 0] * 10, (-gt_deg).remainder(360).long())
        errors = relative_yaw_errors(est, _rad(gt_deg), _zeros(6), _zeros(6), [1])
        assert errors.numel() == 15 and errors.max().item() < 1e-9
        flipped = relative_yaw_errors(-est, _rad(gt_deg), _zeros(6), _zeros(6), [1])
        assert flipped.max().item() > math.radians(90)

    def test_only_same_cluster_and_category(self) -> None:
        gt = _rad([0.0, 50.0, 120.0, 10.0])
        est = -gt
        cats = torch.tensor([0, 0, 1, 0])
        clusters = torch.tensor([0, 0, 0, 1])
        # Only (0, 1) pairs: 2 is another category, 3 is in another prototype.
        assert relative_yaw_errors(est, gt, cats, clusters, [1, 1]).numel() == 1

    def test_symmetric_categories_excluded(self) -> None:
        n = 4
        gt = _rad([0.0, 30.0, 60.0, 90.0])
        est = _rad([5.0, 5.0, 5.0, 5.0])  # wrong for everything
        for order in ([2], [4], [0], [3]):
            out = relative_yaw_error(est, gt, _zeros(n), _zeros(n), order)
            assert out["num_pairs"].item() == 0 and math.isnan(out["median_deg"].item())
        cats = torch.tensor([0, 0, 1, 1])
        errors = relative_yaw_errors(est, gt, cats, _zeros(n), [1, 2])
        assert _deg(errors) == [30.0]  # only the order-1 pair

    def test_modulo_the_period_of_a_symmetric_category(self) -> None:
        """A 4-fold category (a cube): a pair estimated a quarter turn plus 5 deg off is 5 deg off; the asymmetric
        category beside it gives no pair at order 4, and a continuous symmetry has no yaw to score."""
        gt = _rad([0.0, 30.0, 0.0, 30.0])
        est = _rad([0.0, -30.0 + 95.0, 0.0, 0.0])  # object 1 off by 95 deg, object 3 off by 30 deg
        cats = torch.tensor([0, 0, 1, 1])
        assert _deg(relative_yaw_errors(est, gt, cats, _zeros(4), [4, 1], order=4)) == [5.0]
        assert _deg(relative_yaw_errors(est, gt, cats, _zeros(4), [4, 2], order=2)) == [30.0]  # 30 mod 180
        assert _deg(relative_yaw_errors(est, gt, cats, _zeros(4), [4, 1])) == [30.0]
        with pytest.raises(ValueError, match="order must be an int >= 1"):
            relative_yaw_errors(est, gt, cats, _zeros(4), [4, 1], order=0)

    def test_cap_is_deterministic_and_order_independent(self) -> None:
        g = torch.Generator().manual_seed(3)
        gt = torch.rand(200, generator=g, dtype=torch.float64) * 6
        est = -gt + torch.randn(200, generator=g, dtype=torch.float64) * 0.2
        a = relative_yaw_errors(est, gt, _zeros(200), _zeros(200), [1], max_pairs_per_group=500, seed=1)
        assert a.numel() == 500
        perm = torch.randperm(200, generator=g)
        b = relative_yaw_errors(est[perm], gt[perm], _zeros(200), _zeros(200), [1], max_pairs_per_group=500, seed=1)
        assert torch.equal(a, b)
        full = relative_yaw_errors(est, gt, _zeros(200), _zeros(200), [1], max_pairs_per_group=20000)
        assert full.numel() == 19900
        assert abs(a.median().item() - full.median().item()) < 0.05

    def test_exception(self) -> None:
        x, i = torch.zeros(3, dtype=torch.float64), _zeros(3)
        with pytest.raises(ValueError, match="one length"):
            relative_yaw_errors(x, torch.zeros(2), i, i, [1])
        with pytest.raises(ValueError, match=r"categories must lie in \[0, 1\)"):
            relative_yaw_errors(x, x, torch.tensor([0, 1, 0]), i, [1])
        with pytest.raises(ValueError, match="clusters must be >= 0"):
            relative_yaw_errors(x, x, i, torch.tensor([0, -1, 0]), [1])
        with pytest.raises(ValueError, match="floating-point"):
            relative_yaw_errors(i, x, i, i, [1])
        with pytest.raises(ValueError, match="finite"):
            relative_yaw_errors(torch.tensor([0.0, float("nan"), 0.0]), x, i, i, [1])
        with pytest.raises(ValueError, match="integer"):
            relative_yaw_errors(x, x, x, i, [1])
        with pytest.raises(ValueError, match="symmetry_order"):
            relative_yaw_errors(x, x, i, i, [-1])


class TestRelativeYawErrorMetric:
    def _case(self, seed: int = 0) -> tuple[torch.Tensor, ...]:
        g = torch.Generator().manual_seed(seed)
        n = 40
        gt = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
        est = 1.0 - gt + torch.randn(n, generator=g, dtype=torch.float64) * 0.3
        cats = torch.randint(0, 3, (n,), generator=g)
        clusters = torch.randint(0, 4, (n,), generator=g)
        return est, gt, cats, clusters

    def test_equals_functional(self) -> None:
        est, gt, cats, clusters = self._case()
        metric = RelativeYawError(symmetry_order=[1, 4, 0])
        for s in range(0, 40, 9):
            metric.update(est[s : s + 9], gt[s : s + 9], cats[s : s + 9], clusters[s : s + 9])
        out = metric.compute()
        expected = relative_yaw_error(est, gt, cats, clusters, [1, 4, 0])
        assert out.keys() == expected.keys() == {"median_deg", "acc_10", "acc_20", "num_pairs"}
        for key in out:
            assert torch.equal(out[key], expected[key])

    def test_merge_state_equals_one_metric(self) -> None:
        """DDP-like: two 'ranks' see interleaved halves; pairs across ranks are still formed."""
        est, gt, cats, clusters = self._case(seed=1)
        full = RelativeYawError([1, 1, 2])
        full.update(est, gt, cats, clusters)
        m1, m2 = RelativeYawError([1, 1, 2]), RelativeYawError([1, 1, 2])
        m1.update(est[::2], gt[::2], cats[::2], clusters[::2])
        m2.update(est[1::2], gt[1::2], cats[1::2], clusters[1::2])
        m1.merge_state(m2)
        a, b = m1.compute(), full.compute()
        assert a["num_pairs"].item() > 0
        for key in a:
            assert torch.equal(a[key], b[key])

    def test_states_and_empty(self) -> None:
        metric = RelativeYawError([1])
        for name in ("est_yaw", "gt_yaw", "categories", "clusters"):
            assert metric._reductions[name].__name__ == "dim_zero_cat"
        assert metric.full_state_update is False
        with pytest.warns(UserWarning, match="before the ``update``"):
            out = metric.compute()
        assert out["num_pairs"].item() == 0 and math.isnan(out["acc_10"].item())

    def test_thresholds(self) -> None:
        gt = _rad([0.0, 0.0, 0.0])
        est = _rad([0.0, 10.0, 25.0])
        metric = RelativeYawError([1])
        metric.update(est, gt, _zeros(3), _zeros(3))
        out = metric.compute()  # errors 10, 25, 15
        assert out["acc_10"].item() == pytest.approx(1 / 3)  # inclusive: exactly 10 deg counts
        assert out["acc_20"].item() == pytest.approx(2 / 3)
        assert out["median_deg"].item() == pytest.approx(15.0)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="max_pairs_per_group"):
            RelativeYawError([1], max_pairs_per_group=0)
        metric = RelativeYawError([1, 2])
        with pytest.raises(ValueError, match=r"categories must lie in \[0, 2\)"):
            metric.update(torch.zeros(1), torch.zeros(1), torch.tensor([2]), torch.tensor([0]))
