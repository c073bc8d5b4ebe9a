"""2.5DQ-Nets' in-plane rotation search and 2D prototype banks: the yaw search of one-slice volumes.

A 2D crop ``[C, H, W]`` (row y down) is the one-slice volume ``[C, 1, H, W]``, whose yaw is an in-plane rotation,
clockwise as displayed (content at +x moves towards +y). References are independent of the code under test: a
float64 numpy rotate-and-compare loop (its own bilinear sampler), exact quarter turns (``torch.rot90``) and rotated
copies with known angles.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from threedq.geometry.rotate import rotate_yaw
from threedq.metrics import cluster_confusion, hungarian_accuracy
from threedq.quantization.prototypes import PrototypeBank, fit_prototype_bank
from threedq.quantization.rotation_search import all_pairs_rotation_max, best_prototype_and_yaw

A = 36
METHODS = ("exact", "fast")


def best_prototype_and_angle(objects: torch.Tensor, prototypes: torch.Tensor, num_angles: int = A,
                             method: str = "fast"):
    """The in-plane search of ``[N, C, H, W]`` crops: the yaw search of their one-slice volumes."""
    return best_prototype_and_yaw(objects.unsqueeze(2), prototypes.unsqueeze(2), num_angles, method)


def rotate_inplane(images: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """``[N, C, H, W]`` crops turned in the image plane: the yaw of their one-slice volumes."""
    return rotate_yaw(images.unsqueeze(2), angle).squeeze(-3)


def blobs2d(n: int, channels: int = 4, size: int = 16, gaussians: int = 4, seed: int = 0) -> torch.Tensor:
    """``[n, C, S, S]`` smooth asymmetric 2D crops: a few anisotropic Gaussians inside the inscribed disc, each
    with its own channel signature."""
    gen = torch.Generator().manual_seed(seed)
    c = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    yy, xx = (t[None, None] for t in torch.meshgrid(c, c, indexing="ij"))
    rad = 0.3 * size * torch.rand(n, gaussians, generator=gen, dtype=torch.float64).sqrt()
    ang = 2 * math.pi * torch.rand(n, gaussians, generator=gen, dtype=torch.float64)
    cx, cy = (rad * torch.cos(ang))[..., None, None], (rad * torch.sin(ang))[..., None, None]
    sig = (size / 16) * (1.2 + 1.5 * torch.rand(n, gaussians, 2, generator=gen, dtype=torch.float64))
    g = torch.exp(-((xx - cx) ** 2 / (2 * sig[..., 0, None, None] ** 2) + (yy - cy) ** 2 / (2 * sig[..., 1, None, None] ** 2)))
    w = torch.randn(n, gaussians, channels, generator=gen, dtype=torch.float64) + 0.5
    return torch.einsum("ngyx,ngc->ncyx", g, w).float()


def naive_rotate(img: np.ndarray, t: float) -> np.ndarray:
    """float64 bilinear rotation of ``[C, H, W]`` about the centre; output pixel p takes the input at R(-t) p."""
    C, H, W = img.shape
    out = np.zeros_like(img, dtype=np.float64)
    cx, cy = (W - 1) / 2, (H - 1) / 2
    for i in range(H):
        for j in range(W):
            x, y = j - cx, i - cy
            sx, sy = x * math.cos(t) + y * math.sin(t) + cx, -x * math.sin(t) + y * math.cos(t) + cy
            x0, y0 = math.floor(sx), math.floor(sy)
            for dy in (0, 1):
                for dx in (0, 1):
                    xi, yi = x0 + dx, y0 + dy
                    if 0 <= xi < W and 0 <= yi < H:
                        wgt = (1 - abs(sx - xi)) * (1 - abs(sy - yi))
                        out[:, i, j] += wgt * img[:, yi, xi]
    return out


def naive_search(objects: torch.Tensor, prototypes: torch.Tensor, num_angles: int) -> np.ndarray:
    """``[N, K, A]`` cosine of every object rotated by every angle with every prototype (a plain loop)."""
    obj, pro = objects.double().numpy(), prototypes.double().numpy()
    out = np.zeros((len(obj), len(pro), num_angles))
    for n in range(len(obj)):
        for a in range(num_angles):
            r = naive_rotate(obj[n], 2 * math.pi * a / num_angles).ravel()
            for k in range(len(pro)):
                p = pro[k].ravel()
                out[n, k, a] = r @ p / (np.linalg.norm(r) * np.linalg.norm(p) + 1e-12)
    return out


class TestInplaneSearch:
    def test_smoke(self) -> None:
        res = best_prototype_and_angle(blobs2d(2), blobs2d(3, seed=1))
        assert res.scores.shape == (2, 3, A)

    @pytest.mark.parametrize("method", METHODS)
    @pytest.mark.parametrize("n, k, a", [(1, 1, 36), (5, 3, 12), (4, 2, 1)])
    def test_cardinality(self, method: str, n: int, k: int, a: int) -> None:
        res = best_prototype_and_angle(blobs2d(n), blobs2d(k, seed=1), a, method)
        assert res.prototype.shape == res.angle.shape == res.score.shape == (n,)
        assert res.scores.shape == (n, k, a)
        assert int(res.angle.max()) < a and int(res.prototype.max()) < k
        sim, ang = all_pairs_rotation_max(blobs2d(n).unsqueeze(2), blobs2d(k, seed=1).unsqueeze(2), a, method)
        assert sim.shape == ang.shape == (n, k)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="prototypes must be a floating-point"):
            best_prototype_and_angle(torch.rand(2, 4, 8, 8), torch.ones(3, 4, 8, 8, dtype=torch.long))
        with pytest.raises(ValueError, match="one shape"):
            best_prototype_and_angle(torch.rand(2, 4, 8, 8), torch.rand(3, 4, 6, 6))
        with pytest.raises(ValueError, match="method"):
            best_prototype_and_angle(torch.rand(2, 4, 8, 8), torch.rand(3, 4, 8, 8), method="slow")

    @pytest.mark.parametrize("method", METHODS)
    def test_quarter_turn_recovered(self, method: str) -> None:
        """An exact quarter turn (torch.rot90, no interpolation): content at +x moved to +y is +90 deg, so the
        object needs 270 deg (index 27) to align with its prototype."""
        protos = blobs2d(3, seed=2)
        obj = torch.rot90(protos, -1, dims=(-2, -1))  # (+x -> +y): the convention's +90 deg
        res = best_prototype_and_angle(obj, protos, A, method)
        assert res.prototype.tolist() == [0, 1, 2]
        assert res.angle.tolist() == [27, 27, 27]
        assert torch.all(res.score > 0.99)

    @pytest.mark.parametrize("method", METHODS)
    def test_known_angle_recovered(self, method: str) -> None:
        """Objects rotated by the independent float64 sampler by -a steps are aligned by +a."""
        protos = blobs2d(4, size=16, seed=3)
        steps = [3, 11, 20, 31]
        obj = torch.stack([torch.from_numpy(naive_rotate(protos[i].double().numpy(), -2 * math.pi * s / A)).float()
                           for i, s in enumerate(steps)])
        res = best_prototype_and_angle(obj, protos, A, method)
        assert res.prototype.tolist() == [0, 1, 2, 3]
        assert res.angle.tolist() == steps

    @pytest.mark.parametrize("method", METHODS)
    def test_matches_naive_loop(self, method: str) -> None:
        """One body for both kernels: best (prototype, angle) equal the naive rotate-and-compare loop; the exact
        kernel's scores equal it too (the fast one's cosine is over the inscribed disc, so only its argmax)."""
        protos = blobs2d(3, size=10, seed=4)
        gen = torch.Generator().manual_seed(0)
        obj = torch.stack([rotate_inplane(protos[i % 3 : i % 3 + 1], -torch.tensor([2 * math.pi * a / 12]))[0]
                           for i, a in enumerate(torch.randint(12, (5,), generator=gen).tolist())])
        obj = obj + 0.02 * torch.randn(obj.shape, generator=gen)
        ref = naive_search(obj, protos, 12)
        res = best_prototype_and_angle(obj, protos, 12, method)
        flat = ref.reshape(len(obj), -1).argmax(1)
        assert res.prototype.tolist() == (flat // 12).tolist()
        assert res.angle.tolist() == (flat % 12).tolist()
        if method == "exact":
            np.testing.assert_allclose(res.scores.double().numpy(), ref, atol=1e-5)

    def test_gradcheck(self) -> None:
        img = torch.rand(2, 2, 6, 6, dtype=torch.float64, requires_grad=True)
        ang = torch.tensor([0.3, -1.1], dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda x: rotate_inplane(x, ang), (img,))


class TestPrototypeBank2D:
    def test_depth_one_bank_shapes(self) -> None:
        bank = PrototypeBank(5, 4, 8, 36, depth=1)
        assert bank.prototypes.shape == (5, 4, 1, 8, 8)
        with pytest.raises(ValueError, match=r"expected shape \[N, 4, 1, 8, 8\]"):
            bank.assign(torch.rand(2, 4, 8, 8, 8))

    def test_em_clusters_rotated_copies(self) -> None:
        """Three 2D patterns seen at random in-plane angles: the 36-angle EM separates them, a no-rotation bank
        (1 angle) of the same size does worse."""
        base = blobs2d(3, size=12, seed=5)
        gen = torch.Generator().manual_seed(1)
        labels = torch.arange(30) % 3
        steps = torch.randint(A, (30,), generator=gen)
        crops = rotate_inplane(base[labels], -2 * math.pi * steps.double().float() / A)
        crops = (crops + 0.02 * torch.randn(crops.shape, generator=gen)).unsqueeze(2)  # [N, C, 1, S, S]
        bank = fit_prototype_bank(crops, 3, iterations=5, num_angles=A, init_threshold=0.8)
        res = bank.assign(crops)
        acc = float(hungarian_accuracy(cluster_confusion(res.prototype, labels, 3, 3)))
        assert acc == 1.0
        flat = fit_prototype_bank(crops, 3, iterations=5, num_angles=1).assign(crops)
        assert float(hungarian_accuracy(cluster_confusion(flat.prototype, labels, 3, 3))) < 1.0
        # relative angles within a cluster are the true ones (mod 36)
        for c in range(3):
            idx = (labels == c).nonzero().flatten()
            rel = (res.angle[idx] - res.angle[idx[0]]) % A
            true = (steps[idx] - steps[idx[0]]) % A
            assert torch.all(((rel - true) % A == 0) | ((rel - true) % A == 1) | ((rel - true) % A == A - 1))
