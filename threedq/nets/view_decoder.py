"""View prediction and occupancy heads of GIGNs, with their losses and metric.

Convention:
    Feature volumes are ``[B, C, Z, Y, X]`` in the reference frame R; frustum tensors are ``[B, C, D, h, w]``
    (``D`` depth planes near to far, ``h x w`` pixels, from :func:`threedq.geometry.frustum.resample_to_frustum`);
    images are ``[B, 3, h, w]`` with RGB in ``[0, 1]``, and the decoder predicts ``rgb - 0.5`` in ``[-0.5, 0.5]``.
    Occupancy logits are positive for "occupied".
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["OccupancyHead", "ViewDecoder", "balanced_l1", "balanced_occupancy_loss", "depth_max_pool", "masked_l1",
           "occupancy_balanced_accuracy"]


def depth_max_pool(frustum: Tensor, pool: int) -> Tensor:
    """Max of a frustum tensor over each group of ``pool`` consecutive depth planes.

    Forward and gradient are those of ``F.max_pool3d(frustum, (pool, 1, 1), (pool, 1, 1))`` bit for bit (the first
    maximum of a group takes its gradient; NaN counts as the maximum, and of a group with several NaN another one may
    take it), as a reduction over a view of the planes.

    Args:
        frustum: ``[B, C, D, h, w]``, any memory format.
        pool: planes a group; must divide ``D``.

    Returns:
        ``[B, C, D / pool, h, w]``.

    Raises:
        ValueError: if ``frustum`` is not 5-D or ``pool`` does not divide its depth.

    Convention:
        Planes ordered near to far; group ``g`` covers planes ``g * pool .. (g + 1) * pool - 1``.
    """
    if frustum.ndim != 5 or pool < 1 or frustum.shape[2] % pool:
        raise ValueError(f"frustum must be [B, C, D, h, w] with D divisible by pool={pool}, got {tuple(frustum.shape)}")
    return frustum.unflatten(2, (frustum.shape[2] // pool, pool)).max(dim=3).values


class ViewDecoder(nn.Module):
    """2D RGB estimation from a frustum-aligned feature tensor (the GIGN view-prediction CNN).

    Max-pool along depth by ``pool`` (coarse aggregation along each camera ray), Conv3d 3x3x3 ``C -> hidden`` +
    LeakyReLU, fold the remaining ``D / pool`` depth cells into channels, Conv2d 3x3 ``-> hidden`` + LeakyReLU,
    Conv2d 1x1 ``-> out_channels``, then ``0.5 * tanh``.

    Args:
        in_channels: feature channels ``C`` of the frustum tensor.
        num_planes: number ``D`` of depth planes; must be divisible by ``pool``.
        pool: max-pool kernel and stride along depth.
        hidden: width of the hidden 3D and 2D convolutions.
        out_channels: output channels ``E`` (3 for RGB).

    Shape:
        - Input: ``[B, in_channels, num_planes, h, w]``.
        - Output: ``[B, out_channels, h, w]`` in ``[-0.5, 0.5]``.

    Convention:
        Depth planes ordered near to far; the output is compared with ``rgb - 0.5`` (RGB in ``[0, 1]``).
    """

    def __init__(self, in_channels: int = 32, num_planes: int = 32, pool: int = 8, hidden: int = 32,
                 out_channels: int = 3) -> None:
        super().__init__()
        if min(in_channels, num_planes, pool, hidden, out_channels) < 1:
            raise ValueError("all ViewDecoder sizes must be positive ints")
        if num_planes % pool:
            raise ValueError(f"num_planes ({num_planes}) must be divisible by pool ({pool})")
        self.in_channels, self.num_planes, self.pool, self.hidden = in_channels, num_planes, pool, hidden
        self.conv3d = nn.Conv3d(in_channels, hidden, kernel_size=3, padding=1)
        self.conv2d = nn.Conv2d(hidden * (num_planes // pool), hidden, kernel_size=3, padding=1)
        self.to_rgb = nn.Conv2d(hidden, out_channels, kernel_size=1)
        self.act = nn.LeakyReLU(0.01, inplace=True)

    def forward(self, frustum: Tensor) -> Tensor:
        """Decode ``[B, in_channels, num_planes, h, w]`` frustum features to ``[B, out_channels, h, w]``.

        Convention: depth planes near to far; output is ``rgb - 0.5``.
        """
        if frustum.ndim != 5 or frustum.shape[1:3] != (self.in_channels, self.num_planes):
            raise ValueError(f"frustum must have shape [B, {self.in_channels}, {self.num_planes}, h, w], got "
                             f"{tuple(frustum.shape)}")
        return self.decode_pooled(depth_max_pool(frustum, self.pool))

    def decode_pooled(self, pooled: Tensor) -> Tensor:
        """:meth:`forward` after its pooling: ``pooled`` ``[B, in_channels, num_planes / pool, h, w]`` is
        :func:`depth_max_pool` of a frustum, or :func:`threedq.geometry.frustum_depth_max` from the feature grid.

        Convention: depth groups near to far; output is ``rgb - 0.5``.
        """
        groups = self.num_planes // self.pool
        if pooled.ndim != 5 or pooled.shape[1:3] != (self.in_channels, groups):
            raise ValueError(f"pooled frustum must have shape [B, {self.in_channels}, {groups}, h, w], got "
                             f"{tuple(pooled.shape)}")
        # the first 3D conv in float32 even under autocast: its bf16 weight gradient comes out NaN on oneDNN CPU
        with torch.autocast(pooled.device.type, enabled=False):
            x = self.act(self.conv3d(pooled.float()))  # [B, hidden, D / pool, h, w]
        x = x.reshape(x.shape[0], -1, x.shape[-2], x.shape[-1])  # [B, hidden * D / pool, h, w], channel-major
        x = self.act(self.conv2d(x))
        return 0.5 * torch.tanh(self.to_rgb(x))


class OccupancyHead(nn.Module):
    """Per-voxel occupancy logits from a feature volume (a 1x1x1 Conv3d).

    Args:
        in_channels: feature channels ``C``.

    Shape:
        - Input: ``[B, C, Z, Y, X]``.
        - Output: ``[B, 1, Z, Y, X]`` logits (sigmoid gives the probability of "occupied").

    Convention:
        ``[B, C, Z, Y, X]`` volumes in R; positive logit = occupied.
    """

    def __init__(self, in_channels: int = 32) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.conv = nn.Conv3d(in_channels, 1, kernel_size=1)

    def forward(self, features: Tensor) -> Tensor:
        """Occupancy logits ``[B, 1, Z, Y, X]`` of a ``[B, in_channels, Z, Y, X]`` feature volume.

        Convention: positive logit = occupied.
        """
        if features.ndim != 5 or features.shape[1] != self.in_channels:
            raise ValueError(f"features must have shape [B, {self.in_channels}, Z, Y, X], got {tuple(features.shape)}")
        return self.conv(features)


def _check_same_spatial(name: str, a: Tensor, ref: Tensor) -> None:
    if a.ndim != ref.ndim or a.shape[0] != ref.shape[0] or a.shape[1] != 1 or a.shape[2:] != ref.shape[2:]:
        expected = (ref.shape[0], 1, *ref.shape[2:])
        raise ValueError(f"{name} must have shape {expected}, got {tuple(a.shape)}")


def masked_l1(pred: Tensor, target: Tensor, valid: Tensor) -> Tensor:
    """Mean absolute error over valid pixels.

    Args:
        pred: ``[B, E, h, w]`` prediction.
        target: ``[B, E, h, w]`` target (same space as ``pred``, e.g. ``rgb - 0.5``).
        valid: ``[B, 1, h, w]`` 0/1 (bool or float) mask of pixels to use.

    Returns:
        Scalar (float32 at least): ``sum(|pred - target| * valid) / (E * sum(valid))``; 0 (with zero gradient) if no
        pixel is valid.

    Raises:
        ValueError: on shape mismatch.

    Convention: images ``[B, E, h, w]``; the mask broadcasts over channels.
    """
    if pred.shape != target.shape or pred.ndim != 4:
        raise ValueError(f"pred and target must have the same shape [B, E, h, w], got {tuple(pred.shape)} and "
                         f"{tuple(target.shape)}")
    _check_same_spatial("valid", valid, pred)
    dtype = torch.promote_types(pred.dtype, torch.float32)
    weight = valid.to(dtype)
    err = (pred.to(dtype) - target.to(dtype)).abs() * weight
    count = weight.sum() * pred.shape[1]
    return err.sum() / count.clamp_min(1.0)


def balanced_l1(pred: Tensor, target: Tensor, valid: Tensor, foreground: Tensor) -> Tensor:
    """Foreground/background-balanced L1: the mean over valid foreground pixels plus the mean over the rest.

    Args:
        pred: ``[B, E, h, w]`` prediction.
        target: ``[B, E, h, w]`` target.
        valid: ``[B, 1, h, w]`` 0/1 mask of pixels to use.
        foreground: ``[B, 1, h, w]`` 0/1 mask of foreground pixels (only its valid part counts).

    Returns:
        Scalar: ``masked_l1(pred, target, valid * fg) + masked_l1(pred, target, valid * (1 - fg))`` (an empty set
        contributes 0).

    Raises:
        ValueError: on shape mismatch.

    Convention: images ``[B, E, h, w]``; masks broadcast over channels; the means pool the whole minibatch.
    """
    _check_same_spatial("foreground", foreground, pred)
    _check_same_spatial("valid", valid, pred)
    fg = valid.to(pred.dtype) * foreground.to(pred.dtype)
    return masked_l1(pred, target, fg) + masked_l1(pred, target, valid.to(pred.dtype) - fg)


def balanced_occupancy_loss(logits: Tensor, occupied: Tensor, free: Tensor) -> Tensor:
    """Class-balanced logistic loss for occupancy.

    Args:
        logits: ``[B, 1, ...]`` occupancy logits.
        occupied: ``[B, 1, ...]`` 0/1 (bool or float) mask of voxels labelled occupied.
        free: ``[B, 1, ...]`` 0/1 mask of voxels labelled free (disjoint from ``occupied``).

    Returns:
        Scalar (float32 at least): ``mean_{occupied} softplus(-logit) + mean_{free} softplus(logit)``; each term is
        0 when its set is empty.

    Raises:
        ValueError: on shape mismatch.

    Convention:
        Positive logit = occupied; the means are over the whole minibatch (as in the paper).
    """
    _check_same_spatial("occupied", occupied, logits)
    _check_same_spatial("free", free, logits)
    if logits.shape[1] != 1:
        raise ValueError(f"logits must have shape [B, 1, ...], got {tuple(logits.shape)}")
    dtype = torch.promote_types(logits.dtype, torch.float32)
    x, occ, fre = logits.to(dtype), occupied.to(dtype), free.to(dtype)
    pos = (F.softplus(-x) * occ).sum() / occ.sum().clamp_min(1.0)
    neg = (F.softplus(x) * fre).sum() / fre.sum().clamp_min(1.0)
    return pos + neg


@torch.no_grad()
def occupancy_balanced_accuracy(logits: Tensor, occupied: Tensor, free: Tensor) -> Tensor:
    """Balanced accuracy of occupancy predictions.

    Args:
        logits: ``[B, 1, ...]`` occupancy logits; ``logit > 0`` predicts occupied.
        occupied: ``[B, 1, ...]`` 0/1 (bool or float) mask of voxels labelled occupied.
        free: ``[B, 1, ...]`` 0/1 mask of voxels labelled free.

    Returns:
        Scalar float32 ``(TPR + TNR) / 2`` with TPR over occupied and TNR over free voxels. If one set is empty
        the other's rate is returned; if both are empty, NaN.

    Raises:
        ValueError: on shape mismatch.

    Convention:
        Positive logit = occupied; rates pooled over the whole minibatch.
    """
    _check_same_spatial("occupied", occupied, logits)
    _check_same_spatial("free", free, logits)
    pred, occ, fre = logits > 0, occupied.bool(), free.bool()
    rates = []
    if occ.any():
        rates.append((pred & occ).sum().float() / occ.sum().float())
    if fre.any():
        rates.append((~pred & fre).sum().float() / fre.sum().float())
    if not rates:
        return torch.tensor(float("nan"), device=logits.device)
    return torch.stack(rates).mean()
