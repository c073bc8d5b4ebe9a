"""Tests for threedq.quantization.rotation_search: polar resampling, the polar spectrum and the fast rotation search."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from threedq.geometry import rotate_yaw, yaw_angles
from threedq.quantization.rotation_search import rotation_max_similarity
from threedq.quantization.rotation_search import (
    RotationSearchResult,
    all_pairs_rotation_max,
    best_prototype_and_yaw,
    cylindrical_resample,
    polar_interpolation_matrix,
    polar_spectrum,
    yaw_confidence,
    yaw_margin,
)

A = 36


def blob_crops(n: int, channels: int = 8, size: int = 16, gaussians: int = 4, seed: int = 0) -> torch.Tensor:
    """``[n, channels, size, size, size]`` smooth asymmetric crops: a few anisotropic Gaussians near the axis,
    each with its own random channel signature (distinct crops are far apart, no rotational symmetry)."""
    gen = torch.Generator().manual_seed(seed)
    coords = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    zz, yy, xx = (t[None, None] for t in torch.meshgrid(coords, coords, coords, indexing="ij"))
    rad = 0.28 * size * torch.rand(n, gaussians, generator=gen, dtype=torch.float64).sqrt()
    ang = 2 * math.pi * torch.rand(n, gaussians, generator=gen, dtype=torch.float64)
    cx, cy = (rad * torch.cos(ang))[..., None, None, None], (rad * torch.sin(ang))[..., None, None, None]
    cz = ((torch.rand(n, gaussians, generator=gen, dtype=torch.float64) * 2 - 1) * 0.25 * size)[..., None, None, None]
    sig = (size / 16) * (1.2 + 1.5 * torch.rand(n, gaussians, 3, generator=gen, dtype=torch.float64))
    sx, sy, sz = (sig[..., i, None, None, None] for i in range(3))
    g = torch.exp(-((xx - cx) ** 2 / (2 * sx**2) + (yy - cy) ** 2 / (2 * sy**2) + (zz - cz) ** 2 / (2 * sz**2)))
    w = torch.randn(n, gaussians, channels, generator=gen, dtype=torch.float64) + 0.5
    return torch.einsum("ngzyx,ngc->nczyx", g, w).float()


def smooth_random_crops(n: int, channels: int = 4, size: int = 16, seed: int = 0) -> torch.Tensor:
    """Random smooth content (blurred Gaussian noise) filling the whole crop, corners included."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n, channels, size, size, size, generator=gen)
    for _ in range(2):
        x = F.avg_pool3d(x, 3, stride=1, padding=1)
    return x


def rotated_copies(
    bank: torch.Tensor, n: int, noise: float = 0.05, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Objects = bank item k rotated by -a steps (+ noise): rotating object by a aligns it with item k."""
    gen = torch.Generator().manual_seed(seed)
    k = torch.randint(bank.shape[0], (n,), generator=gen)
    a = torch.randint(A, (n,), generator=gen)
    obj = rotate_yaw(bank[k], -yaw_angles(A)[a])
    obj = obj + noise * obj.std() * torch.randn(obj.shape, generator=gen)
    return obj, k, a


def naive_scores(objects: torch.Tensor, prototypes: torch.Tensor, num_angles: int = A) -> torch.Tensor:
    """Reference ``[N, K, A]``: every object rotated by every angle with rotate_yaw, cosine with every prototype."""
    out = torch.empty(objects.shape[0], prototypes.shape[0], num_angles, dtype=objects.dtype)
    angles = yaw_angles(num_angles, dtype=objects.dtype)
    protos = F.normalize(prototypes.flatten(1), dim=1)
    for i in range(objects.shape[0]):
        rotated = rotate_yaw(objects[i : i + 1], angles[None])[0]  # [A, C, Z, Y, X]
        out[i] = (protos @ F.normalize(rotated.flatten(1), dim=1).T)  # [K, A]
    return out


def circular_step_distance(a: torch.Tensor, b: torch.Tensor, n: int = A) -> torch.Tensor:
    d = (a - b).abs() % n
    return torch.minimum(d, n - d)


class TestPolarInterpolationMatrix:
    def test_smoke(self) -> None:
        w = polar_interpolation_matrix(16, 16)
        assert w.shape == (8 * 36, 256) and w.dtype == torch.float32

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="num_angles must be a positive int"):
            polar_interpolation_matrix(8, 8, 0)
        with pytest.raises(ValueError, match="num_radii must be a positive int"):
            polar_interpolation_matrix(8, 8, 12, 0)

    @pytest.mark.parametrize(("ny", "nx", "num_angles", "num_radii"), [(8, 8, 12, None), (7, 9, 5, 3), (16, 16, 36, 8)])
    def test_cardinality(self, ny: int, nx: int, num_angles: int, num_radii: int | None) -> None:
        r = num_radii or math.ceil(min(ny, nx) / 2)
        assert polar_interpolation_matrix(ny, nx, num_angles, num_radii).shape == (r * num_angles, ny * nx)

    def test_feature_cached(self) -> None:
        assert polar_interpolation_matrix(10, 10, 12) is polar_interpolation_matrix(10, 10, 12)

    @pytest.mark.parametrize(("ny", "nx"), [(8, 8), (7, 9), (16, 16)])
    def test_feature_matches_grid_sample(self, ny: int, nx: int) -> None:
        num_angles, num_radii = 12, 5
        w = polar_interpolation_matrix(ny, nx, num_angles, num_radii, area_weighted=False, dtype=torch.float64)
        img = torch.randn(3, 1, ny, nx, dtype=torch.float64)
        r = (torch.arange(num_radii, dtype=torch.float64) + 0.5) * (min(ny, nx) / 2 / num_radii)
        phi = yaw_angles(num_angles, dtype=torch.float64)
        px = (nx - 1) / 2 + r[:, None] * torch.cos(phi)
        py = (ny - 1) / 2 + r[:, None] * torch.sin(phi)
        grid = torch.stack(((2 * px + 1) / nx - 1, (2 * py + 1) / ny - 1), dim=-1)[None].expand(3, -1, -1, -1)
        ref = F.grid_sample(img, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        torch.testing.assert_close(img.flatten(1) @ w.T, ref.flatten(1))

    def test_feature_area_weights_integrate_the_disc(self) -> None:
        # constant slice: sum of squared area-weighted samples = disc area pi rho^2 (in voxels)
        w = polar_interpolation_matrix(16, 16, 36, dtype=torch.float64)
        ones = torch.ones(256, dtype=torch.float64)
        assert (w @ ones).square().sum().item() == pytest.approx(math.pi * 8**2, rel=1e-9)


class TestCylindricalResample:
    def test_smoke(self) -> None:
        out = cylindrical_resample(torch.rand(2, 3, 4, 16, 16))
        assert out.shape == (2, 3, 4, 8, 36) and out.dtype == torch.float32

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"crops must have shape \[N, C, Z, Y, X\]"):
            cylindrical_resample(torch.rand(3, 4, 16, 16))
        with pytest.raises(ValueError, match="floating-point"):
            cylindrical_resample(torch.zeros(1, 1, 2, 4, 4, dtype=torch.long))

    @pytest.mark.parametrize(("shape", "num_angles", "num_radii", "expected"), [
        ((1, 1, 1, 8, 8), 12, None, (1, 1, 1, 4, 12)),
        ((2, 3, 5, 7, 9), 7, 2, (2, 3, 5, 2, 7)),
    ])
    def test_cardinality(self, shape: tuple[int, ...], num_angles: int, num_radii: int | None,
                         expected: tuple[int, ...]) -> None:
        assert cylindrical_resample(torch.rand(shape), num_angles, num_radii).shape == expected

    def test_feature_quarter_turn_is_a_roll(self) -> None:
        # a quarter turn of a square grid is an exact permutation, and 9 steps of 10 deg are a quarter turn
        x = torch.rand(2, 3, 2, 10, 10, dtype=torch.float64)
        rotated = rotate_yaw(x, torch.full((2,), math.pi / 2, dtype=torch.float64))
        torch.testing.assert_close(cylindrical_resample(rotated), torch.roll(cylindrical_resample(x), 9, dims=-1))

    def test_feature_inner_product_approximates_the_disc(self) -> None:
        # smooth content inside the inscribed disc: area-weighted polar inner products ~ Cartesian ones (bilinear
        # interpolation smooths peaks a little, ~2.5% here)
        coords = torch.arange(16, dtype=torch.float64) - 7.5
        zz, yy, xx = torch.meshgrid(coords, coords, coords, indexing="ij")

        def gauss(cx: float, cy: float, cz: float, s: float) -> torch.Tensor:
            return torch.exp(-((xx - cx) ** 2 + (yy - cy) ** 2 + (zz - cz) ** 2) / (2 * s**2))

        x = torch.stack((gauss(2, -1, 0, 2.0), gauss(-1.5, 2.5, 1, 2.5)))[None]
        y = torch.stack((gauss(1, -2, 0, 2.5), gauss(-1, 1.5, 1, 2.0)))[None]
        cx, cy = cylindrical_resample(x), cylindrical_resample(y)
        assert (cx * cy).sum().item() == pytest.approx((x * y).sum().item(), rel=0.05)
        assert (cx * cx).sum().item() == pytest.approx((x * x).sum().item(), rel=0.05)

    def test_gradcheck(self) -> None:
        x = torch.rand(2, 1, 2, 4, 4, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda t: cylindrical_resample(t, 6), (x,))


class TestPolarSpectrum:
    def test_feature_equals_correlation_of_cylinders(self) -> None:
        # without band limit, the fused resampling + DFT gives exactly the correlation of the resampled cylinders
        # along the angle: <roll(cx_n, s), cy_m> at every shift s
        x, y = torch.randn(3, 2, 3, 8, 8, dtype=torch.float64), torch.randn(4, 2, 3, 8, 8, dtype=torch.float64)
        cx, cy = cylindrical_resample(x, 12), cylindrical_resample(y, 12)
        qs = polar_spectrum(x, 12, bandlimit=False)
        torch.testing.assert_close(qs.norm, cx.flatten(1).norm(dim=1))
        sim, angle = all_pairs_rotation_max(x, y, 12, bandlimit=False)
        corr = torch.stack([torch.roll(cx, s, -1).flatten(1) @ cy.flatten(1).T for s in range(12)], dim=-1)
        corr = corr / (cx.flatten(1).norm(dim=1)[:, None, None] * cy.flatten(1).norm(dim=1)[:, None])
        torch.testing.assert_close(sim, corr.max(dim=2).values)
        assert torch.equal(angle, corr.argmax(dim=2))

    def test_feature_bandlimit_keeps_smooth_content(self) -> None:
        x = blob_crops(3, channels=2, seed=5)
        full = polar_spectrum(x, bandlimit=False)
        limited = polar_spectrum(x, bandlimit=True)
        assert limited.coef.shape[1] < 0.75 * full.coef.shape[1]
        torch.testing.assert_close(limited.norm, full.norm, rtol=1e-3, atol=0)


class TestBestPrototypeAndYaw:
    def test_smoke(self) -> None:
        res = best_prototype_and_yaw(torch.rand(3, 2, 4, 8, 8), torch.rand(5, 2, 4, 8, 8), 12)
        assert isinstance(res, RotationSearchResult)
        assert res.prototype.dtype == torch.long and res.angle.dtype == torch.long

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="one shape"):
            best_prototype_and_yaw(torch.rand(3, 2, 4, 8, 8), torch.rand(5, 3, 4, 8, 8))
        with pytest.raises(ValueError, match="method must be one of"):
            best_prototype_and_yaw(torch.rand(3, 2, 4, 8, 8), torch.rand(5, 2, 4, 8, 8), method="slow")
        with pytest.raises(ValueError, match="num_angles"):
            best_prototype_and_yaw(torch.rand(3, 2, 4, 8, 8), torch.rand(5, 2, 4, 8, 8), num_angles=0)
        with pytest.raises(ValueError, match="objects must have shape"):
            best_prototype_and_yaw(torch.rand(3, 4, 8, 8), torch.rand(5, 2, 4, 8, 8))

    @pytest.mark.parametrize("method", ["fast", "exact"])
    @pytest.mark.parametrize(("n", "k", "num_angles"), [(1, 1, 1), (4, 3, 12)])
    def test_cardinality(self, method: str, n: int, k: int, num_angles: int) -> None:
        res = best_prototype_and_yaw(torch.rand(n, 2, 4, 8, 8), torch.rand(k, 2, 4, 8, 8), num_angles, method)
        assert res.prototype.shape == res.angle.shape == res.score.shape == (n,)
        assert res.scores.shape == (n, k, num_angles)
        torch.testing.assert_close(res.score, res.scores.flatten(1).max(dim=1).values)

    @pytest.mark.parametrize("method", ["fast", "exact"])
    def test_feature_known_yaw_recovery(self, method: str) -> None:
        protos = blob_crops(6, seed=1)
        steps = torch.tensor([0, 1, 5, 9, 17, 23, 35])
        k = torch.tensor([0, 1, 2, 3, 4, 5, 0])
        objects = rotate_yaw(protos[k], -yaw_angles(A)[steps])
        res = best_prototype_and_yaw(objects, protos, A, method)
        assert res.prototype.tolist() == k.tolist()
        assert res.angle.tolist() == steps.tolist()
        assert (res.score > 0.97).all()

    def test_feature_exact_matches_naive(self) -> None:
        protos, objects = blob_crops(4, channels=2, seed=2), blob_crops(3, channels=2, seed=3)
        res = best_prototype_and_yaw(objects, protos, A, "exact", chunk=2)
        torch.testing.assert_close(res.scores, naive_scores(objects, protos), atol=1e-5, rtol=1e-5)

    @pytest.mark.parametrize("compute_dtype", [None, torch.bfloat16])
    def test_feature_fast_matches_naive_structured(self, compute_dtype: torch.dtype | None) -> None:
        # prototype bank of distinct smooth asymmetric blobs; objects = rotated copies (+ noise): unambiguous
        protos = blob_crops(20, seed=10)
        objects, k, a = rotated_copies(protos, 40, seed=11)
        naive = naive_scores(objects, protos).flatten(1).argmax(dim=1)
        fast = best_prototype_and_yaw(objects, protos, A, "fast", compute_dtype=compute_dtype)
        assert torch.equal(naive // A, k) and torch.equal(naive % A, a)  # the case is unambiguous
        assert torch.equal(fast.prototype, naive // A)
        assert torch.equal(fast.angle, naive % A)

    def test_feature_fast_matches_naive_random(self) -> None:
        # random smooth content filling the crop (corners included): the fast cosine (inscribed cylinder) differs
        # from the naive one (full cube), but the best prototype agrees and the angle within one step
        protos = smooth_random_crops(12, seed=20)
        objects, k, _ = rotated_copies(protos, 16, noise=0.3, seed=21)
        naive = naive_scores(objects, protos).flatten(1).argmax(dim=1)
        fast = best_prototype_and_yaw(objects, protos, A, "fast")
        assert torch.equal(fast.prototype, naive // A) and torch.equal(naive // A, k)
        assert (circular_step_distance(fast.angle, naive % A) <= 1).all()

    def test_feature_score_is_cosine(self) -> None:
        x = blob_crops(2, seed=4)
        res = best_prototype_and_yaw(x, x * 3.0, A, "fast")
        assert res.prototype.tolist() == [0, 1] and res.angle.tolist() == [0, 0]
        torch.testing.assert_close(res.score, torch.ones(2), atol=1e-5, rtol=0)
        assert (res.scores <= 1 + 1e-5).all()


class TestAllPairsRotationMax:
    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="one shape"):
            all_pairs_rotation_max(torch.rand(2, 1, 4, 4, 4), torch.rand(2, 2, 4, 4, 4))
        with pytest.raises(ValueError, match="method must be one of"):
            all_pairs_rotation_max(torch.rand(2, 1, 4, 4, 4), torch.rand(2, 1, 4, 4, 4), method="fft")

    @pytest.mark.parametrize("method", ["fast", "exact"])
    def test_cardinality(self, method: str) -> None:
        sim, angle = all_pairs_rotation_max(torch.rand(3, 2, 4, 8, 8), torch.rand(5, 2, 4, 8, 8), 12, method, chunk=2)
        assert sim.shape == angle.shape == (3, 5) and angle.dtype == torch.long

    def test_feature_exact_is_the_reference(self) -> None:
        q, g = blob_crops(3, channels=2, seed=6), blob_crops(4, channels=2, seed=7)
        for ours, ref in zip(all_pairs_rotation_max(q, g, 12, "exact"), rotation_max_similarity(q, g, 12)):
            torch.testing.assert_close(ours, ref)
        for ours, ref in zip(rotation_max_similarity(q, g, 12, method="fast"), all_pairs_rotation_max(q, g, 12)):
            torch.testing.assert_close(ours, ref)

    def test_feature_self_similarity(self) -> None:
        x = blob_crops(4, seed=8)
        sim, angle = all_pairs_rotation_max(x, x, A)
        torch.testing.assert_close(sim.diagonal(), torch.ones(4), atol=1e-5, rtol=0)
        assert angle.diagonal().tolist() == [0, 0, 0, 0]
        # sim(q, g) at angle a equals sim(g, q) at angle -a (a roll is orthogonal)
        torch.testing.assert_close(sim, sim.T, atol=1e-5, rtol=0)
        assert torch.equal((angle + angle.T) % A, torch.zeros_like(angle))

    @pytest.mark.parametrize("compute_dtype", [None, torch.bfloat16])
    def test_feature_top1_agreement_structured(self, compute_dtype: torch.dtype | None) -> None:
        gallery = blob_crops(40, seed=30)
        query, k, a = rotated_copies(gallery, 30, seed=31)
        exact_sim, exact_angle = rotation_max_similarity(query, gallery, A)
        fast_sim, fast_angle = all_pairs_rotation_max(query, gallery, A, compute_dtype=compute_dtype)
        top_exact, top_fast = exact_sim.argmax(dim=1), fast_sim.argmax(dim=1)
        assert torch.equal(top_exact, k)
        assert (top_fast == top_exact).float().mean().item() == 1.0
        rows = torch.arange(30)
        assert torch.equal(fast_angle[rows, top_fast], exact_angle[rows, top_exact])
        assert torch.equal(exact_angle[rows, k], a)


class TestYawMargin:
    def test_smoke(self):
        m = yaw_margin(torch.rand(3, 12), torch.zeros(3, dtype=torch.long), 1)
        assert m.shape == (3,)

    def test_exception(self):
        with pytest.raises(ValueError, match="scores, angle"):
            yaw_margin(torch.rand(3, 12), torch.zeros(2, dtype=torch.long), 1)
        with pytest.raises(ValueError, match="exclude"):
            yaw_margin(torch.rand(3, 12), torch.zeros(3, dtype=torch.long), 6)
        with pytest.raises(ValueError, match="exclude"):
            yaw_margin(torch.rand(3, 12), torch.zeros(3, dtype=torch.long), -1)

    def test_hand_computed(self):
        s = torch.tensor([[0.9, 0.85, 0.1, 0.2, 0.3, 0.86],   # neighbours (within 1 step) do not count: 0.9 - 0.3
                          [0.5, 0.1, 0.1, 0.5, 0.1, 0.1]])    # a half-turn symmetric score: margin 0
        m = yaw_margin(s, torch.tensor([0, 0]), 1)
        assert torch.allclose(m, torch.tensor([0.6, 0.0]))

    def test_against_naive_loop(self):
        g = torch.Generator().manual_seed(0)
        s = torch.rand(20, 36, generator=g, dtype=torch.float64)
        angle = s.argmax(1)
        m = yaw_margin(s, angle, 3)
        for n in range(20):
            others = [float(s[n, b]) for b in range(36) if min((b - angle[n]) % 36, (angle[n] - b) % 36) > 3]
            assert math.isclose(float(m[n]), float(s[n, angle[n]]) - max(others), abs_tol=1e-12)
        assert (m >= 0).all()

    def test_confidence_reads_the_chosen_prototype(self):
        """yaw_confidence is yaw_margin on the row of the prototype the search chose (here the second of two)."""
        scores = torch.full((1, 2, 12), 0.1)
        scores[0, 0, 4] = 0.7  # a prototype not chosen, with a clear peak
        scores[0, 1, 2], scores[0, 1, 7] = 0.9, 0.85  # the chosen one: a rival 5 steps away
        res = RotationSearchResult(torch.tensor([1]), torch.tensor([2]), torch.tensor([0.9]), scores)
        assert torch.allclose(yaw_confidence(res, 1), torch.tensor([0.05]))

    def test_rotated_copy_is_confident_symmetric_is_not(self):
        """An L-shaped crop against itself turned by 90 degrees: the search finds the turn with a clear margin;
        a cylinder matches every yaw as well: margin near 0."""
        crop = torch.zeros(1, 1, 8, 16, 16, dtype=torch.float64)
        crop[..., 3:5, 4:12] = 1
        crop[..., 4:12, 4:6] = 1
        turned = rotate_yaw(crop, torch.tensor([math.pi / 2], dtype=torch.float64))
        res = best_prototype_and_yaw(turned, crop, 36, method="exact")
        assert int(res.angle[0]) == 27  # turning it back by -90 deg (270) aligns it
        assert float(yaw_margin(res.scores[:, 0], res.angle, 3)[0]) > 0.2
        yy, xx = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
        disc = (((yy - 7.5) ** 2 + (xx - 7.5) ** 2) < 25).double().expand(1, 1, 8, 16, 16).clone()
        res = best_prototype_and_yaw(disc, disc, 36, method="exact")
        assert float(yaw_margin(res.scores[:, 0], res.angle, 3)[0]) < 0.02
