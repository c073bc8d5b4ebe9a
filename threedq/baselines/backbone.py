"""Which ImageNet backbone a ``--weights`` file holds (:class:`~threedq.baselines.resnet.ResNet18`, the paper's, or
:class:`~threedq.baselines.mobilenet.MobileNetV2`, the stand-in), told from its keys, and the network with its weights.

Convention: both networks expose ``features(x)``: ``[B, 3, H, W]`` ImageNet-normalised RGB -> ``[B, C, H/32, W/32]``
(C = ``feature_dim``), what :func:`~threedq.baselines.imagenet.object_features` pools.
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
    """The ImageNet backbone (eval mode, on the CPU) whose weights ``path`` holds: any ``features.*`` key makes it
    :class:`~threedq.baselines.mobilenet.MobileNetV2`, else any ``conv1``/``bn1``/``layer1-4``/``fc`` key
    :class:`~threedq.baselines.resnet.ResNet18` (loaded strictly); ``InputError`` naming the file (and key) otherwise.
    """
    path = Path(path)
    state = read_state_dict(path, _EXPECTED)
    if any(k.startswith("features.") for k in state):
        return load_mobilenet_v2_weights(path, state=state)
    if any(k.split(".", 1)[0] in _RESNET_TOP for k in state):
        return load_resnet18_weights(path, state=state)
    why = "neither torchvision resnet18 weights (conv1.*, layer1-4.*, fc.*) nor MobileNetV2 features (features.*)"
    raise InputError(f"{path}: field '{next(iter(state))}': {why}")


def backbone_fields(net: nn.Module) -> dict[str, Any]:
    """``{"backbone": name (a key of :data:`BACKBONES`), "backbone_label", "feature_stage", "feature_dim"}`` of
    ``net``; ``TypeError`` if it is not one of :data:`BACKBONES`."""
    name = next((n for n, cls in BACKBONES.items() if isinstance(net, cls)), None)
    if name is None:
        raise TypeError(f"not an ImageNet backbone of threedq.baselines: {type(net).__name__}")
    fields = {"backbone_label": net.label, "feature_stage": net.feature_stage, "feature_dim": net.feature_dim}
    return {"backbone": name, **fields}
