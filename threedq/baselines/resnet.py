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
box with :func:`~threedq.geometry.boxes2d.roi_average_pool` (:func:`~threedq.baselines.imagenet.object_features`, shared
with the MobileNetV2 stand-in of :mod:`threedq.baselines.mobilenet`; re-exported here).

Convention: images ``[B, 3, H, W]`` RGB in [0, 1]; boxes in image pixels (see :mod:`threedq.geometry.boxes2d`).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from threedq.baselines.imagenet import IMAGENET_MEAN, IMAGENET_STD, check_state_dict, object_features, read_state_dict

__all__ = ["IMAGENET_MEAN", "IMAGENET_STD", "RESNET18_PARAMETERS", "ResNet18", "load_resnet18_weights", "object_features"]

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

    #: the backbone as the tables name it, its pooled stage and that stage's channels
    label = "ImageNet ResNet-18"
    feature_stage = "layer4"
    feature_dim = 512

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


def load_resnet18_weights(path: str | Path, model: ResNet18 | None = None,
                          state: dict[str, Tensor] | None = None) -> ResNet18:
    """A :class:`ResNet18` (eval mode) with the weights of ``path``, a torchvision ``resnet18`` state dict.

    Loaded with ``torch.load(weights_only=True)`` (:func:`~threedq.baselines.imagenet.read_state_dict`); every key and
    shape must match (a checkpoint dict with a ``state_dict`` entry is accepted too).

    Args:
        path: the file.
        model: load into this network (default: a new :class:`ResNet18`).
        state: the file's tensors, when the caller has read them already (``path`` is then only named in errors).

    Raises:
        InputError: one line naming the file and the first missing / unexpected / mis-shaped key.
    """
    path = Path(path)
    obj = read_state_dict(path, "torchvision resnet18 weights") if state is None else state
    model = model or ResNet18()
    check_state_dict(path, obj, model.state_dict(), "ResNet-18")
    model.load_state_dict(obj, strict=True)
    return model.eval()
