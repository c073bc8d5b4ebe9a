"""The 2D encoder-decoder of 2.5DQ-Nets: UNet3D's layer list with 2D convolutions, and its autoencoding head.

The supplement's 2.5DQ-Nets has "the exact architecture as our 3DQ-Nets model, except it uses 2D CNNs
instead of 3D", trained by "autoencoding the same RGB-D view". :class:`UNet2D` is :class:`~threedq.nets.UNet3D`
with ``Conv2d`` / ``ConvTranspose2d`` (4-2-64, 4-2-128, 4-2-256, 4-0.5-128, 4-0.5-64, 1-1-F, skip
concatenations, per-pixel L2-normalised output at half resolution); :class:`RGBDDecoder2D` maps those features
back to the full-resolution RGB-D view.

Convention:
    Images ``[B, C, H, W]`` (row y down, column x right); the feature map at half resolution covers the same
    image extent: feature pixel ``(i, j)`` covers image pixels ``2i..2i+1``, ``2j..2j+1``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["RGBDDecoder2D", "UNet2D"]

#: Spatial sizes of the input must be divisible by this (three stride-2 convolutions).
DOWNSAMPLE = 8


def _down(in_channels: int, out_channels: int, negative_slope: float) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, 4, 2, 1, bias=False), nn.BatchNorm2d(out_channels),
                         nn.LeakyReLU(negative_slope, inplace=True))


def _up(in_channels: int, out_channels: int, negative_slope: float) -> nn.Sequential:
    return nn.Sequential(nn.ConvTranspose2d(in_channels, out_channels, 4, 2, 1, bias=False),
                         nn.BatchNorm2d(out_channels), nn.LeakyReLU(negative_slope, inplace=True))


class UNet2D(nn.Module):
    """2D encoder-decoder over ``cat[rgb, depth]`` producing a per-pixel feature map at half resolution.

    Args:
        in_channels: input channels (4 for RGB-D).
        out_channels: feature dimension ``F`` (32, as the 3D encoder's).
        channels: widths of the three encoder levels.
        negative_slope: LeakyReLU slope.
        normalize: L2-normalise the output per pixel.

    Shape:
        - Input: ``[B, in_channels, H, W]``, ``H, W`` divisible by 8.
        - Output: ``[B, out_channels, H/2, W/2]``.

    Convention: see the module docstring.
    """

    def __init__(self, in_channels: int = 4, out_channels: int = 32, channels: tuple[int, int, int] = (64, 128, 256),
                 negative_slope: float = 0.01, normalize: bool = True) -> None:
        super().__init__()
        if len(channels) != 3 or any(int(c) < 1 for c in channels):
            raise ValueError(f"channels must be 3 positive ints, got {channels!r}")
        if in_channels < 1 or out_channels < 1:
            raise ValueError(f"in_channels and out_channels must be positive, got {in_channels}, {out_channels}")
        c1, c2, c3 = (int(c) for c in channels)
        self.in_channels, self.out_channels, self.normalize = in_channels, out_channels, normalize
        self.enc1 = _down(in_channels, c1, negative_slope)
        self.enc2 = _down(c1, c2, negative_slope)
        self.enc3 = _down(c2, c3, negative_slope)
        self.dec1 = _up(c3, c2, negative_slope)
        self.dec2 = _up(2 * c2, c1, negative_slope)
        self.head = nn.Conv2d(2 * c1, out_channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        """``[B, in_channels, H, W]`` -> ``[B, out_channels, H/2, W/2]`` (unit norm per pixel when ``normalize``)."""
        if x.ndim != 4 or x.shape[1] != self.in_channels:
            raise ValueError(f"x must have shape [B, {self.in_channels}, H, W], got {tuple(x.shape)}")
        if any(s <= 0 or s % DOWNSAMPLE for s in x.shape[2:]):
            raise ValueError(f"the spatial size (H, W) = {tuple(x.shape[2:])} of x must be positive and divisible by "
                             f"{DOWNSAMPLE}")
        e1 = self.enc1(x)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        d1 = torch.cat((self.dec1(e3), e2), dim=1)
        d2 = torch.cat((self.dec2(d1), e1), dim=1)
        out = self.head(d2)
        if self.normalize:
            out = F.normalize(out.float(), p=2.0, dim=1, eps=1e-12).to(out.dtype)
        return out


class RGBDDecoder2D(nn.Module):
    """Half-resolution features -> the full-resolution RGB-D view (the autoencoding target).

    ConvTranspose2d k4 s2 (F -> hidden) + BatchNorm + LeakyReLU, a 3x3 conv block, and a 1x1 conv to 4
    channels: RGB as ``0.5 tanh`` (RGB in [-0.5, 0.5], as the view decoder) and normalised depth (linear).

    Shape: ``[B, F, h, w]`` -> ``rgb`` ``[B, 3, 2h, 2w]``, ``depth`` ``[B, 1, 2h, 2w]``.
    """

    def __init__(self, in_channels: int = 32, hidden: int = 64, negative_slope: float = 0.01) -> None:
        super().__init__()
        self.up = _up(in_channels, hidden, negative_slope)
        self.conv = nn.Sequential(nn.Conv2d(hidden, hidden, 3, 1, 1, bias=False), nn.BatchNorm2d(hidden),
                                  nn.LeakyReLU(negative_slope, inplace=True))
        self.out = nn.Conv2d(hidden, 4, 1)

    def forward(self, feats: Tensor) -> tuple[Tensor, Tensor]:
        y = self.out(self.conv(self.up(feats)))
        return 0.5 * torch.tanh(y[:, :3]), y[:, 3:]
