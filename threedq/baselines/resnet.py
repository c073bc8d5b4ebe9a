"""ImageNet ResNet-18 features of objects (the paper's "ResNet", "ResNetRet" and "ResNetClass" baselines).

:class:`ResNet18` is torchvision's ``resnet18`` written out with exactly torchvision's ``state_dict`` layout
(``conv1``, ``bn1``, ``layer1.0.conv1`` ... ``layer4.1.bn2``, ``layerN.0.downsample.{0,1}``, ``fc``), so torchvision's
ImageNet file loads into it strictly; :func:`load_resnet18_weights` reads a file the user supplies. Object features:
:func:`~threedq.baselines.imagenet.object_features` of ``layer4`` (re-exported here).

Convention: images ``[B, 3, H, W]`` RGB in [0, 1]; boxes in image pixels (see :mod:`threedq.geometry.boxes2d`).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from threedq.baselines.imagenet import IMAGENET_MEAN, IMAGENET_STD, check_state_dict, object_features, read_state_dict

__all__ = [
    "IMAGENET_MEAN", "IMAGENET_STD", "RESNET18_PARAMETERS", "ResNet18", "load_resnet18_weights", "object_features"
]  # fmt: skip

#: Parameters of torchvision's ``resnet18`` (1000 classes).
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
            conv = nn.Conv2d(in_channels, channels, 1, stride, bias=False)
            self.downsample = nn.Sequential(conv, nn.BatchNorm2d(channels))

    def forward(self, x: Tensor) -> Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        identity = x if self.downsample is None else self.downsample(x)
        return self.relu(out + identity)


class ResNet18(nn.Module):
    """ResNet-18 with torchvision's parameter names, shapes and initialisation (``num_classes``: outputs of ``fc``):
    ``[B, 3, H, W]`` ImageNet-normalised RGB -> :meth:`features`: ``[B, 512, ceil(H/32), ceil(W/32)]`` (``layer4``);
    :meth:`forward`: ``[B, num_classes]``."""

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
        for i, (c, w) in enumerate(zip((64, 64, 128, 256), (64, 128, 256, 512))):
            setattr(self, f"layer{i + 1}", nn.Sequential(BasicBlock(c, w, 1 if i == 0 else 2), BasicBlock(w, w)))
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
                          state: dict[str, Tensor] | None = None) -> ResNet18:  # fmt: skip
    """A :class:`ResNet18` (``model``, or a new one; eval mode) with the weights of ``path``, a torchvision ``resnet18``
    state dict, loaded strictly. ``state``: the file's tensors, when the caller has read them already.

    Raises:
        InputError: one line naming the file and the first missing / unexpected / mis-shaped key.
    """
    path = Path(path)
    obj = read_state_dict(path, "torchvision resnet18 weights") if state is None else state
    model = model or ResNet18()
    check_state_dict(path, obj, model.state_dict(), "ResNet-18")
    model.load_state_dict(obj, strict=True)
    return model.eval()
