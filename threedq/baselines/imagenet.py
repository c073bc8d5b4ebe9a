"""What the ImageNet backbones of the 2D baselines share: the weight-file reader, ImageNet's normalisation and the
features of objects pooled in their image boxes.

The paper's "ResNet", "ResNetRet" and "ResNetClass" rows (Tables 1 and 2) read ImageNet features of each object:
"average-pool features within the projected (ground-truth) 2D object boxes". :func:`object_features` does that for
any backbone whose ``features`` maps a normalised image to its last feature stage
(:class:`~threedq.baselines.resnet.ResNet18`'s ``layer4``, 512 channels; :class:`~threedq.baselines.mobilenet.MobileNetV2`'s ``features``, 1280 channels; both
stride 32). :func:`read_state_dict` and :func:`check_state_dict` read a user-supplied weight file
(``torch.load(weights_only=True)``, nothing downloaded) and turn every way it can be wrong into one
:class:`~threedq.errors.InputError` line naming the file and the offending key.

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
    """The state dict of tensors stored in ``path`` (``torch.load(weights_only=True)``, on the CPU).

    A checkpoint dict with a ``state_dict`` entry is accepted too (its ``state_dict`` is returned).

    Args:
        path: the weight file.
        expected: what the file should hold, for the messages (e.g. ``"torchvision resnet18 weights"``).

    Returns:
        ``{key: tensor}`` in the file's order.

    Raises:
        InputError: one line naming the file: no such file, not a file ``torch.load(weights_only=True)`` reads, or not
            a non-empty dict of tensors.

    Convention: the error lines read ``<path>: field '<key>': <what is wrong>`` (``'<file>'`` for the whole file).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"--weights {path}: no such file")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises several types for corrupt or unsafe files
        first = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), type(e).__name__)
        raise InputError(f"{path}: field '<file>': not a tensor file torch.load(weights_only=True) reads "
                         f"({first[:160]})") from e
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or not obj:
        raise InputError(f"{path}: field '<file>': expected a non-empty state dict of tensors ({expected})")
    bad = next((k for k, v in obj.items() if not isinstance(v, Tensor)), None)
    if bad is not None:
        raise InputError(f"{path}: field '{bad}': not a tensor ({type(obj[bad]).__name__}); expected a state dict of "
                         f"tensors ({expected})")
    return dict(obj)


def check_state_dict(path: str | Path, state: Mapping[str, Tensor], own: Mapping[str, Tensor], name: str,
                     origin: Mapping[str, str] | None = None) -> None:
    """Raise unless ``state`` has exactly the keys and shapes of ``own`` (what a strict ``load_state_dict`` needs).

    Args:
        path: the file ``state`` was read from (named in the message).
        state: the file's tensors (keys already in the model's layout).
        own: the model's ``state_dict()``.
        name: the model, for the messages (e.g. ``"ResNet-18"``).
        origin: ``{model key: key in the file}`` where the file's keys were renamed (the message names the file's).

    Raises:
        InputError: one line naming the file and the first missing, unexpected or mis-shaped key.

    Convention: keys are checked in ``own``'s order (missing, then unexpected in ``state``'s order, then shapes).
    """
    origin = origin or {}
    missing = [k for k in own if k not in state]
    if missing:
        raise InputError(f"{path}: field '{origin.get(missing[0], missing[0])}': missing ({len(missing)} {name} "
                         f"key(s) missing; not {name} weights?)")
    unexpected = [k for k in state if k not in own]
    if unexpected:
        raise InputError(f"{path}: field '{origin.get(unexpected[0], unexpected[0])}': unexpected key "
                         f"({len(unexpected)} not in {name})")
    for k, v in own.items():
        if state[k].shape != v.shape:
            raise InputError(f"{path}: field '{origin.get(k, k)}': shape {tuple(state[k].shape)}, {name} has "
                             f"{tuple(v.shape)}")


@torch.no_grad()
def object_features(model: nn.Module, rgb: Tensor, boxes2d: Tensor, input_size: int = 224) -> Tensor:
    """The backbone's last-stage features average-pooled inside each box.

    Args:
        model: a backbone whose ``features(x)`` maps ``[B, 3, S, S]`` ImageNet-normalised RGB to ``[B, C, h, w]``
            (used in its current mode; the loaders return it in eval mode).
        rgb: ``[B, 3, H, W]`` in [0, 1].
        boxes2d: ``[B, M, 4]`` image-pixel boxes of ``rgb`` (``(u0, v0, u1, v1)``).
        input_size: the image is resized (bilinear, antialiased) to ``input_size x input_size`` before the network.

    Returns:
        ``[B, M, C]`` features (C = 512 for ResNet-18, 1280 for MobileNetV2).

    Convention: boxes stay in the original image's pixels; the resize is accounted for by
    :func:`~threedq.geometry.boxes2d.roi_average_pool` (both cover the same continuous image extent). A box given with
    its corners swapped (``u0 > u1`` or ``v0 > v1``) pools the same samples, so the same features.
    """
    H, W = rgb.shape[-2:]
    x = F.interpolate(rgb, size=(input_size, input_size), mode="bilinear", align_corners=False, antialias=True)
    mean, std = x.new_tensor(IMAGENET_MEAN).view(1, 3, 1, 1), x.new_tensor(IMAGENET_STD).view(1, 3, 1, 1)
    feats = model.features((x - mean) / std)
    return roi_average_pool(feats, boxes2d, (H, W))
