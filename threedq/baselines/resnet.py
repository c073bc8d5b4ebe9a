"""ImageNet ResNet-18 features of objects (the paper's "ResNet", "ResNetRet" and "ResNetClass" baselines).

:class:`ResNet18` is torchvision's ``resnet18`` architecture written out here, with exactly torchvision's
``state_dict`` layout (``conv1``, ``bn1``, ``layer1.0.conv1`` ... ``layer4.1.bn2``, ``layerN.0.downsample.{0,1}``,
``fc``), so torchvision's ImageNet file (e.g. ``resnet18-f37072fd.pth``) loads into it with
``torch.load(weights_only=True)`` and a strict ``load_state_dict``. It is hand-written because torchvision's
wheels for this torch are CUDA builds whose import fails on a CPU-only torch (``operator torchvision::nms does
not exist``), and timm needs torchvision. Nothing is downloaded: :func:`load_resnet18_weights` reads a file the
user supplies.

Object features (paper Sec. 4.3, "average-pool features within the projected (ground-truth) 2D object
boxes"): the image is resized to ``input_size`` (224 by default, ImageNet's scale), normalised with ImageNet's
mean and std, run to the last stage (``layer4``, 512 channels, stride 32) and averaged inside each projected
box with :func:`~threedq.geometry.boxes2d.roi_average_pool`.

Convention: images ``[B, 3, H, W]`` RGB in [0, 1]; boxes in image pixels (see :mod:`threedq.geometry.boxes2d`).
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from threedq.errors import InputError
from threedq.geometry.boxes2d import roi_average_pool

__all__ = ["IMAGENET_MEAN", "IMAGENET_STD", "RESNET18_PARAMETERS", "ResNet18", "load_resnet18_weights", "object_features"]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: Parameters of torchvision's ``resnet18`` (1000 classes), the figure torchvision's model card gives.
RESNET18_PARAMETERS = 11_689_512


class BasicBlock(nn.Module):
    """Two 3x3 convolutions with a residual connection (torchvision's ``BasicBlock``, names included)."""

    def __init__(self, in_channels: int, channels: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, channels, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(channels)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(channels, channels, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(channels)
        self.downsample = None
        if stride != 1 or in_channels != channels:
            self.downsample = nn.Sequential(nn.Conv2d(in_channels, channels, 1, stride, bias=False),
                                            nn.BatchNorm2d(channels))

    def forward(self, x: Tensor) -> Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        identity = x if self.downsample is None else self.downsample(x)
        return self.relu(out + identity)


class ResNet18(nn.Module):
    """ResNet-18 (He et al. 2016) with torchvision's parameter names and shapes.

    Args:
        num_classes: outputs of ``fc`` (1000 for ImageNet weights).

    Shape:
        - Input: ``[B, 3, H, W]`` ImageNet-normalised RGB.
        - :meth:`features`: ``[B, 512, ceil(H/32), ceil(W/32)]`` (``layer4``); :meth:`forward`: ``[B, num_classes]``.

    Convention: torchvision's ``resnet18`` (zero-padded convolutions, max-pool 3x3 stride 2 padding 1).
    """

    def __init__(self, num_classes: int = 1000) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        widths, c = (64, 128, 256, 512), 64
        for i, w in enumerate(widths):
            stride = 1 if i == 0 else 2
            setattr(self, f"layer{i + 1}", nn.Sequential(BasicBlock(c, w, stride), BasicBlock(w, w)))
            c = w
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        self.fc = nn.Linear(512, num_classes)
        for m in self.modules():  # torchvision's initialisation
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def features(self, x: Tensor) -> Tensor:
        """The last stage's map ``[B, 512, h, w]`` (before the global average pool)."""
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))

    def forward(self, x: Tensor) -> Tensor:
        return self.fc(torch.flatten(self.avgpool(self.features(x)), 1))


def load_resnet18_weights(path: str | Path, model: ResNet18 | None = None) -> ResNet18:
    """A :class:`ResNet18` (eval mode) with the weights of ``path``, a torchvision ``resnet18`` state dict.

    Loaded with ``torch.load(weights_only=True)``; every key and shape must match (a checkpoint dict with a
    ``state_dict`` entry is accepted too).

    Raises:
        InputError: one line naming the file and the first missing / unexpected / mis-shaped key.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"--weights {path}: no such file")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises several types for corrupt or unsafe files
        first = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), type(e).__name__)
        raise InputError(f"{path}: field '<file>': not a tensor file torch.load(weights_only=True) reads ({first[:160]})") from e
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or not all(isinstance(v, Tensor) for v in obj.values()):
        raise InputError(f"{path}: field '<file>': expected a state dict of tensors (torchvision resnet18 weights)")
    model = model or ResNet18()
    own = model.state_dict()
    missing = [k for k in own if k not in obj]
    if missing:
        raise InputError(f"{path}: field '{missing[0]}': missing ({len(missing)} ResNet-18 key(s) missing; not "
                         "torchvision resnet18 weights?)")
    unexpected = [k for k in obj if k not in own]
    if unexpected:
        raise InputError(f"{path}: field '{unexpected[0]}': unexpected key ({len(unexpected)} not in ResNet-18)")
    for k, v in own.items():
        if obj[k].shape != v.shape:
            raise InputError(f"{path}: field '{k}': shape {tuple(obj[k].shape)}, ResNet-18 has {tuple(v.shape)}")
    model.load_state_dict(obj, strict=True)
    return model.eval()


@torch.no_grad()
def object_features(model: ResNet18, rgb: Tensor, boxes2d: Tensor, input_size: int = 224) -> Tensor:
    """ResNet-18 ``layer4`` features average-pooled inside each box.

    Args:
        model: the network (used in its current mode; :func:`load_resnet18_weights` returns it in eval mode).
        rgb: ``[B, 3, H, W]`` in [0, 1].
        boxes2d: ``[B, M, 4]`` image-pixel boxes of ``rgb`` (``(u0, v0, u1, v1)``).
        input_size: the image is resized (bilinear) to ``input_size x input_size`` before the network.

    Returns:
        ``[B, M, 512]`` features.

    Convention: boxes stay in the original image's pixels; the resize is accounted for by
    :func:`~threedq.geometry.boxes2d.roi_average_pool` (both cover the same continuous image extent).
    """
    H, W = rgb.shape[-2:]
    x = F.interpolate(rgb, size=(input_size, input_size), mode="bilinear", align_corners=False, antialias=True)
    mean, std = x.new_tensor(IMAGENET_MEAN).view(1, 3, 1, 1), x.new_tensor(IMAGENET_STD).view(1, 3, 1, 1)
    feats = model.features((x - mean) / std)
    return roi_average_pool(feats, boxes2d, (H, W))
