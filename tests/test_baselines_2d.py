"""The 2D baselines' pieces: projected 2D boxes, box crops / RoI average pooling, ResNet-18 (torchvision layout),
few-shot Ret / Class, the 2D U-Net. References: hand-computed cases, plain loops, float64 gradcheck."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from threedq.baselines.resnet import RESNET18_PARAMETERS, ResNet18, load_resnet18_weights, object_features
from threedq.errors import InputError
from threedq.geometry import crop_boxes_2d, project_boxes_2d, roi_average_pool
from threedq.metrics import linear_probe_accuracy, nearest_shot_accuracy, select_labelled
from threedq.nets import RGBDDecoder2D, UNet2D


def _pose(t: tuple[float, float, float]) -> torch.Tensor:
    """Camera-to-R: camera axes = R axes (z forward), camera at ``t``."""
    T = torch.eye(4)
    T[:3, 3] = torch.tensor(t)
    return T


class TestProjectBoxes2d:
    def test_feature(self) -> None:
        """Axis-aligned box 2 m ahead, K = f 100, c (50, 40): corners at z 1.9 and 2.1 -> hand-computed hull."""
        K = torch.tensor([[[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]]])
        box = torch.tensor([[[0.0, 0.0, 2.0, 0.4, 0.2, 0.2, 0.0]]])  # x +-0.2, y +-0.1, z 1.9..2.1
        b2, valid = project_boxes_2d(box, K, _pose((0, 0, 0))[None], (80, 100))
        exp = [50 - 100 * 0.2 / 1.9, 40 - 100 * 0.1 / 1.9, 50 + 100 * 0.2 / 1.9, 40 + 100 * 0.1 / 1.9]
        np.testing.assert_allclose(b2[0, 0].numpy(), exp, rtol=1e-5)
        assert bool(valid[0, 0])

    def test_clipped_and_behind(self) -> None:
        K = torch.tensor([[[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]]])
        boxes = torch.tensor([[[3.0, 0.0, 2.0, 0.4, 0.2, 0.2, 0.0], [0.0, 0.0, -2.0, 0.4, 0.2, 0.2, 0.0],
                               [0.8, 0.0, 2.0, 0.4, 0.2, 0.2, 0.0]]])
        b2, valid = project_boxes_2d(boxes, K, _pose((0, 0, 0))[None], (80, 100))
        assert valid.tolist() == [[False, False, True]]  # right of the image; behind the camera; partly inside
        assert float(b2[0, 2, 2]) == 99.5  # clipped at the right image edge

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"boxes must have shape \[B, M, 7\]"):
            project_boxes_2d(torch.zeros(1, 7), torch.eye(3)[None], torch.eye(4)[None], (8, 8))
        with pytest.raises(ValueError, match="K and R_T_cam"):
            project_boxes_2d(torch.zeros(2, 1, 7), torch.eye(3)[None], torch.eye(4)[None], (8, 8))


def naive_bilinear(img: np.ndarray, u: float, v: float) -> np.ndarray:
    C, H, W = img.shape
    out = np.zeros(C)
    x0, y0 = math.floor(u), math.floor(v)
    for dy in (0, 1):
        for dx in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            if 0 <= xi < W and 0 <= yi < H:
                out += (1 - abs(u - xi)) * (1 - abs(v - yi)) * img[:, yi, xi]
    return out


class TestCropAndPool:
    def test_full_image_box_is_identity(self) -> None:
        img = torch.rand(2, 3, 8, 8)
        box = torch.tensor([-0.5, -0.5, 7.5, 7.5]).expand(2, 1, 4)
        torch.testing.assert_close(crop_boxes_2d(img, box, 8)[:, 0], img)

    def test_shapes_and_exception(self) -> None:
        out = crop_boxes_2d(torch.rand(2, 5, 16, 12), torch.tensor([[0.0, 0, 4, 4]]).expand(2, 3, 4), 6)
        assert out.shape == (2, 3, 5, 6, 6)
        assert roi_average_pool(torch.rand(2, 5, 4, 3), torch.rand(2, 3, 4), (16, 12)).shape == (2, 3, 5)
        with pytest.raises(ValueError, match=r"boxes2d must have shape \[B, M, 4\]"):
            crop_boxes_2d(torch.rand(2, 5, 16, 12), torch.rand(3, 1, 4))
        with pytest.raises(ValueError, match="size must be a positive int"):
            crop_boxes_2d(torch.rand(1, 5, 16, 12), torch.rand(1, 1, 4), 0)

    def test_roi_average_pool_equals_naive_loop(self) -> None:
        """Mean of 4 x 4 bilinear samples at the sub-cell centres of the box mapped to the feature map (loop)."""
        gen = torch.Generator().manual_seed(0)
        feats = torch.rand(2, 3, 4, 5, generator=gen, dtype=torch.float64)
        H, W = 32, 40  # stride 8
        boxes = torch.tensor([[[3.0, 5.0, 20.0, 11.0], [0.0, 0.0, 39.0, 31.0]], [[10.0, 12.0, 12.0, 14.0], [30.0, 2.0, 39.5, 30.0]]],
                             dtype=torch.float64)
        got = roi_average_pool(feats, boxes, (H, W), samples=4)
        for b in range(2):
            for m in range(2):
                u0, v0, u1, v1 = boxes[b, m].tolist()
                acc = np.zeros(3)
                for i in range(4):
                    for j in range(4):
                        u = u0 + (j + 0.5) * (u1 - u0) / 4
                        v = v0 + (i + 0.5) * (v1 - v0) / 4
                        acc += naive_bilinear(feats[b].numpy(), (u + 0.5) * 5 / W - 0.5, (v + 0.5) * 4 / H - 0.5)
                np.testing.assert_allclose(got[b, m].numpy(), acc / 16, atol=1e-12)

    def test_constant_map_pools_to_constant(self) -> None:
        """A box well inside a constant map pools to that constant, whatever its size (sub-cell boxes too)."""
        feats = torch.full((1, 2, 4, 4), 3.0)
        boxes = torch.tensor([[[10.0, 10.0, 11.0, 11.0], [8.0, 4.0, 20.0, 25.0]]])
        torch.testing.assert_close(roi_average_pool(feats, boxes, (32, 32)), torch.full((1, 2, 2), 3.0))

    def test_gradcheck(self) -> None:
        img = torch.rand(1, 2, 6, 7, dtype=torch.float64, requires_grad=True)
        box = torch.tensor([[[1.2, 0.7, 4.9, 4.1]]], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda x, b: crop_boxes_2d(x, b, 3), (img, box))


def resnet18_table() -> dict[str, tuple[int, ...]]:
    """torchvision resnet18's state-dict keys and shapes, written from its architecture description
    (He et al. Table 1, torchvision's module names), independently of threedq's module."""
    t: dict[str, tuple[int, ...]] = {"conv1.weight": (64, 3, 7, 7)}

    def bn(name: str, c: int) -> None:
        for k in ("weight", "bias", "running_mean", "running_var"):
            t[f"{name}.{k}"] = (c,)
        t[f"{name}.num_batches_tracked"] = ()

    bn("bn1", 64)
    cin = 64
    for layer, c in enumerate((64, 128, 256, 512), start=1):
        for block in (0, 1):
            p = f"layer{layer}.{block}"
            t[f"{p}.conv1.weight"] = (c, cin if block == 0 else c, 3, 3)
            bn(f"{p}.bn1", c)
            t[f"{p}.conv2.weight"] = (c, c, 3, 3)
            bn(f"{p}.bn2", c)
            if block == 0 and layer > 1:
                t[f"{p}.downsample.0.weight"] = (c, cin, 1, 1)
                bn(f"{p}.downsample.1", c)
        cin = c
    t["fc.weight"], t["fc.bias"] = (1000, 512), (1000,)
    return t


class TestResNet18:
    def test_torchvision_layout(self) -> None:
        net = ResNet18()
        assert sum(p.numel() for p in net.parameters()) == RESNET18_PARAMETERS == 11_689_512
        sd = net.state_dict()
        table = resnet18_table()
        assert list(sd) == list(table)  # torchvision's key order too
        assert {k: tuple(v.shape) for k, v in sd.items()} == table
        assert table["layer3.0.downsample.0.weight"] == (256, 128, 1, 1) and len(table) == 122

    def test_load_round_trip_and_bad_files(self, tmp_path: Path) -> None:
        torch.manual_seed(0)
        src = ResNet18()
        path = tmp_path / "resnet18.pth"
        torch.save(src.state_dict(), path)
        net = load_resnet18_weights(path)
        assert not net.training
        x = torch.rand(1, 3, 64, 64)
        torch.testing.assert_close(net(x), src.eval()(x))
        sd = src.state_dict()
        bad = {k: v for k, v in sd.items() if k != "layer2.0.downsample.1.running_var"}
        torch.save(bad, tmp_path / "missing.pth")
        with pytest.raises(InputError, match=r"missing.pth: field 'layer2.0.downsample.1.running_var': missing") as e:
            load_resnet18_weights(tmp_path / "missing.pth")
        assert "\n" not in str(e.value)
        torch.save({**sd, "fc.weight": torch.zeros(10, 512)}, tmp_path / "shape.pth")
        with pytest.raises(InputError, match=r"shape.pth: field 'fc.weight': shape \(10, 512\)"):
            load_resnet18_weights(tmp_path / "shape.pth")
        torch.save({**sd, "extra.weight": torch.zeros(1)}, tmp_path / "extra.pth")
        with pytest.raises(InputError, match=r"extra.pth: field 'extra.weight': unexpected"):
            load_resnet18_weights(tmp_path / "extra.pth")
        (tmp_path / "junk.pth").write_bytes(b"not a tensor file")
        with pytest.raises(InputError, match=r"junk.pth: field '<file>'") as e:
            load_resnet18_weights(tmp_path / "junk.pth")
        assert "\n" not in str(e.value)
        with pytest.raises(InputError, match="no such file"):
            load_resnet18_weights(tmp_path / "absent.pth")

    def test_object_features(self) -> None:
        """Shapes, and the pooling is the box's: equal to roi_average_pool of the network's own map."""
        torch.manual_seed(0)
        net = ResNet18().eval()
        rgb = torch.rand(2, 3, 32, 32)
        boxes = torch.tensor([[[2.0, 3.0, 20.0, 25.0]], [[10.0, 0.0, 31.0, 12.0]]])
        f = object_features(net, rgb, boxes, input_size=64)
        assert f.shape == (2, 1, 512)
        x = torch.nn.functional.interpolate(rgb, size=(64, 64), mode="bilinear", align_corners=False, antialias=True)
        mean, std = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1), torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
        torch.testing.assert_close(f, roi_average_pool(net.features((x - mean) / std), boxes, (32, 32)))


class TestFewShotRetClass:
    def test_nearest_shot_hand_computed(self) -> None:
        # 2 categories, 1 shot each (seeded draw), features on a line: hand-check every prediction
        feats = torch.tensor([[1.0, 0.0], [0.9, 0.1], [0.0, 1.0], [0.2, 0.8], [0.7, 0.3]])
        labels = torch.tensor([0, 0, 1, 1, 1])
        out = nearest_shot_accuracy(feats, labels, shots=1, seed=0)
        shots = select_labelled(labels, 1, 0)
        assert out["labelled_indices"].tolist() == shots.tolist()
        f = torch.nn.functional.normalize(feats, dim=1)
        expect = [int(labels[shots][(f[i] @ f[shots].T).argmax()]) for i in range(5)]
        rest = [i for i in range(5) if i not in shots.tolist()]
        acc = np.mean([expect[i] == int(labels[i]) for i in rest])
        assert out["predicted"][rest].tolist() == [expect[i] for i in rest]
        assert float(out["accuracy"]) == pytest.approx(acc)

    def test_nearest_shot_literal(self) -> None:
        feats = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 0.1], [0.1, 1.0], [1.0, 1.2]])
        labels = torch.tensor([0, 1, 0, 1, 0])
        out = nearest_shot_accuracy(feats, labels, shots=1, seed=0, )
        # whichever shots are drawn, object 4 (closer to the y axis) is labelled 1: wrong unless it is a shot
        if 4 not in out["labelled_indices"].tolist():
            assert int(out["predicted"][4]) == 1

    def test_linear_probe_separable(self) -> None:
        """Three categories in three well-separated directions with noise: a linear classifier on 2 shots each
        labels every other object correctly; on scrambled labels it cannot."""
        gen = torch.Generator().manual_seed(0)
        centres = torch.eye(3) * 5
        labels = torch.arange(60) % 3
        feats = centres[labels] + 0.5 * torch.randn(60, 3, generator=gen)
        out = linear_probe_accuracy(feats, labels, shots=2, seed=0)
        assert float(out["accuracy"]) == 1.0
        assert out["labelled_indices"].numel() == 6
        scrambled = labels[torch.randperm(60, generator=gen)]
        assert float(linear_probe_accuracy(feats, scrambled, shots=2, seed=0)["accuracy"]) < 0.7

    def test_undefined_and_exceptions(self) -> None:
        out = linear_probe_accuracy(torch.rand(2, 3), torch.tensor([0, 1]), shots=2)
        assert math.isnan(float(out["accuracy"]))
        assert math.isnan(float(nearest_shot_accuracy(torch.rand(2, 3), torch.tensor([0, 1]))["accuracy"]))
        with pytest.raises(ValueError, match="features must be a float tensor"):
            nearest_shot_accuracy(torch.rand(3), torch.tensor([0, 1, 1]))
        with pytest.raises(ValueError, match="labels must have 3 entries"):
            linear_probe_accuracy(torch.rand(3, 2), torch.tensor([0, 1]))
        with pytest.raises(ValueError, match="shots must be a positive int"):
            nearest_shot_accuracy(torch.rand(3, 2), torch.tensor([0, 1, 1]), shots=0)


class TestUNet2D:
    def test_shapes_and_norm(self) -> None:
        net = UNet2D(4, 32).eval()
        y = net(torch.rand(2, 4, 32, 24))
        assert y.shape == (2, 32, 16, 12)
        torch.testing.assert_close(y.norm(dim=1), torch.ones(2, 16, 12))
        rgb, depth = RGBDDecoder2D(32)(y)
        assert rgb.shape == (2, 3, 32, 24) and depth.shape == (2, 1, 32, 24) and float(rgb.detach().abs().max()) <= 0.5

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"x must have shape \[B, 4, H, W\]"):
            UNet2D()(torch.rand(1, 3, 16, 16))
        with pytest.raises(ValueError, match="divisible by 8"):
            UNet2D()(torch.rand(1, 4, 12, 16))

    def test_gradcheck(self) -> None:
        net = UNet2D(4, 3, channels=(2, 2, 2), normalize=False).double().eval()  # the norm runs in float32
        x = torch.rand(1, 4, 8, 8, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(net, (x,))
