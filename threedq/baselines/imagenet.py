"""What the ImageNet backbones of the 2D baselines share: the weight-file reader, ImageNet's normalisation and the
features of objects average-pooled in their projected 2D boxes (the paper's "ResNet", "ResNetRet" and "ResNetClass"
rows).

Convention: images ``[B, 3, H, W]`` RGB in [0, 1]; boxes in image pixels ``(u0, v0, u1, v1)`` (see
:mod:`threedq.geometry.boxes2d`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from threedq.errors import InputError
from threedq.geometry.boxes2d import roi_average_pool

__all__ = ["IMAGENET_MEAN", "IMAGENET_STD", "check_state_dict", "object_features", "read_state_dict"]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def read_state_dict(path: str | Path, expected: str) -> dict[str, Tensor]:
    """The state dict ``{key: tensor}`` stored in ``path`` (``torch.load(weights_only=True)``, on the CPU; a
    checkpoint's ``state_dict`` entry too), in the file's order; ``InputError``
    ``<path>: field '<key>': <what is wrong>`` otherwise (``expected``: what it should hold)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"--weights {path}: no such file")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for corrupt or unsafe files
        first = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), type(e).__name__)
        why = f"not a tensor file torch.load(weights_only=True) reads ({first[:160]})"
        raise InputError(f"{path}: field '<file>': {why}") from e
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or not obj:
        raise InputError(f"{path}: field '<file>': expected a non-empty state dict of tensors ({expected})")
    bad = next((k for k, v in obj.items() if not isinstance(v, Tensor)), None)
    if bad is not None:
        why = f"not a tensor ({type(obj[bad]).__name__}); expected a state dict of tensors ({expected})"
        raise InputError(f"{path}: field '{bad}': {why}")
    return dict(obj)


def check_state_dict(path: str | Path, state: Mapping[str, Tensor], own: Mapping[str, Tensor], name: str,
                     origin: Mapping[str, str] | None = None) -> None:  # fmt: skip
    """Raise ``InputError`` naming the file ``path`` and the first missing, then unexpected, then mis-shaped key unless
    ``state`` (the file's tensors, in the model's layout) has exactly the keys and shapes of ``own`` (the model's
    ``state_dict()``). ``name``: the model; ``origin``: ``{model key: key in the file}`` where keys were renamed."""
    origin = origin or {}

    def fail(key: str, why: str) -> InputError:
        return InputError(f"{path}: field '{origin.get(key, key)}': {why}")

    missing = [k for k in own if k not in state]
    if missing:
        raise fail(missing[0], f"missing ({len(missing)} {name} key(s) missing; not {name} weights?)")
    unexpected = [k for k in state if k not in own]
    if unexpected:
        raise fail(unexpected[0], f"unexpected key ({len(unexpected)} not in {name})")
    for k, v in own.items():
        if state[k].shape != v.shape:
            raise fail(k, f"shape {tuple(state[k].shape)}, {name} has {tuple(v.shape)}")


@torch.no_grad()
def object_features(model: nn.Module, rgb: Tensor, boxes2d: Tensor, input_size: int = 224) -> Tensor:
    """``[B, M, C]``: the backbone's last-stage features average-pooled inside each box.

    Args:
        model: a backbone whose ``features(x)`` maps ``[B, 3, S, S]`` ImageNet-normalised RGB to ``[B, C, h, w]``.
        rgb: ``[B, 3, H, W]`` in [0, 1], resized (bilinear, antialiased) to ``input_size x input_size``.
        boxes2d: ``[B, M, 4]`` image-pixel boxes ``(u0, v0, u1, v1)`` of ``rgb`` (not of the resized image).
    """
    H, W = rgb.shape[-2:]
    x = F.interpolate(rgb, size=(input_size, input_size), mode="bilinear", align_corners=False, antialias=True)
    mean, std = x.new_tensor(IMAGENET_MEAN).view(1, 3, 1, 1), x.new_tensor(IMAGENET_STD).view(1, 3, 1, 1)
    feats = model.features((x - mean) / std)
    return roi_average_pool(feats, boxes2d, (H, W))
