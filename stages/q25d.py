"""2.5DQ-Nets (the paper's supplement, "2.5DQ-Nets"): 3DQ-Nets with 2D CNNs and an in-plane rotation search.

A 2D U-Net (:class:`~threedq.nets.UNet2D`) encodes ``cat[rgb, depth]`` of one view into per-pixel L2-normalised
features at half resolution, trained by autoencoding that view (:class:`~threedq.nets.RGBDDecoder2D`; L1 on RGB plus
L1 on normalised depth over valid pixels). Objects are their projected GT 3D boxes' regions of the feature map
(:meth:`Q25D.object_crops`); ``threedq eval --q25d`` fits their 2D prototypes with the prototype EM on one-slice crops
``[N, F, 1, s, s]`` (an in-plane rotation search) and scores them.
"""

from __future__ import annotations

import lightning as L
import torch
from torch import Tensor

from threedq.geometry import crop_boxes_2d, project_boxes_2d
from threedq.nets import RGBDDecoder2D, UNet2D
from threedq.stages.base import SplitEvaluation

__all__ = ["Q25D"]


class Q25D(SplitEvaluation, L.LightningModule):
    """The 2.5DQ-Nets stage: a 2D RGB-D autoencoder whose features are cropped at projected object boxes.

    Args:
        feature_dim: channels ``F`` of the per-pixel features.
        depth_range: ``(near, far)`` metres mapped to normalised depth ``[-0.5, 0.5]`` (invalid depth: 0).
        depth_weight: weight of the depth L1 against the RGB L1.
        crop_size: object crops are ``crop_size x crop_size`` feature pixels.
        lr: Adam learning rate.

    Convention: images ``[B, C, H, W]`` (row y down); RGB in [0, 1] from the DataModule, fed as ``rgb - 0.5``;
    boxes in frame R projected with the view's ``K`` and ``R_T_cam`` (view 0 of each sample).
    """

    def __init__(self, feature_dim: int = 32, depth_range: tuple[float, float] = (1.2, 5.2), depth_weight: float = 1.0,
                 crop_size: int = 16, lr: float = 1e-3) -> None:
        super().__init__()
        near, far = depth_range
        if not far > near > 0:
            raise ValueError(f"depth_range: expected 0 < near < far metres, got {tuple(depth_range)!r}")
        if crop_size < 1:
            raise ValueError(f"crop_size: expected >= 1, got {crop_size}")
        self.save_hyperparameters()
        self.encoder = UNet2D(in_channels=4, out_channels=feature_dim)
        self.decoder = RGBDDecoder2D(in_channels=feature_dim)

    def rgbd_input(self, rgb: Tensor, depth: Tensor) -> tuple[Tensor, Tensor]:
        """``[N, 3, H, W]`` RGB in [0, 1] and ``[N, H, W]`` depth (m, 0 invalid) -> ``x`` ``[N, 4, H, W]`` =
        ``cat[rgb - 0.5, depth_n]`` and ``valid`` ``[N, 1, H, W]`` (depth > 0)."""
        near, far = self.hparams.depth_range
        valid = (depth > 0).unsqueeze(1)
        d = ((depth.unsqueeze(1) - near) / (far - near)).clamp(0.0, 1.0) - 0.5
        d = torch.where(valid, d, torch.zeros_like(d))
        return torch.cat([rgb - 0.5, d], dim=1), valid.to(rgb.dtype)

    def encode(self, rgb: Tensor, depth: Tensor) -> Tensor:
        """``[N, F, H/2, W/2]`` L2-normalised features of ``[N, 3, H, W]`` RGB and ``[N, H, W]`` depth."""
        x, _ = self.rgbd_input(rgb, depth)
        return self.encoder(x)

    def _step(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        rgb, depth = batch["rgb"][:, 0], batch["depth"][:, 0]
        x, valid = self.rgbd_input(rgb, depth)
        rgb_hat, depth_hat = self.decoder(self.encoder(x))
        l1_rgb = (rgb_hat - x[:, :3]).abs().mean()
        l1_depth = ((depth_hat - x[:, 3:]).abs() * valid).sum() / valid.sum().clamp_min(1.0)
        return {"loss": l1_rgb + self.hparams.depth_weight * l1_depth, "l1_rgb": l1_rgb, "l1_depth": l1_depth,
                "l1_rgb_mean_colour": (x[:, :3] - x[:, :3].mean(dim=(2, 3), keepdim=True)).abs().mean()}

    @torch.no_grad()
    def object_crops(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """Crop every valid object of a SceneDataset batch out of view 0's feature map.

        Returns:
            ``features`` ``[N, F, s, s]`` (``s = crop_size``), ``labels`` ``[N]``, ``boxes2d`` ``[N, 4]`` (image
            pixels), ``visible`` ``[N]`` bool (box in front of the camera and inside the image), ``scene``
            ``[N]``; N = ``batch["box_mask"].sum()``, in the order of the 3D stages' ``object_crops``.
        """
        rgb, depth = batch["rgb"][:, 0], batch["depth"][:, 0]
        H, W = rgb.shape[-2:]
        feats = self.encode(rgb, depth)  # [B, F, H/2, W/2]
        boxes2d, visible = project_boxes_2d(batch["boxes"], batch["K"][:, 0], batch["R_T_cam"][:, 0], (H, W))
        h, w = feats.shape[-2:]
        scale = boxes2d.new_tensor([w / W, h / H, w / W, h / H])
        crops = crop_boxes_2d(feats, (boxes2d + 0.5) * scale - 0.5, self.hparams.crop_size)  # [B, M, F, s, s]
        mask = batch["box_mask"]
        return {"features": crops[mask], "labels": batch["categories"][mask], "boxes2d": boxes2d[mask],
                "visible": visible[mask], "scene": batch["scene_index"][:, None].expand_as(mask)[mask]}

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        r = self._step(batch)
        self.log_dict({"train/loss": r["loss"], "train/l1_rgb": r["l1_rgb"], "train/l1_depth": r["l1_depth"]},
                      prog_bar=True, batch_size=batch["rgb"].shape[0])
        return r["loss"]

    def _eval_step(self, batch: dict[str, Tensor], split: str, batch_idx: int) -> None:
        r = self._step(batch)
        self.log_dict({f"{split}/{k}": v for k, v in r.items()}, prog_bar=split == "val",
                      batch_size=batch["rgb"].shape[0], sync_dist=True)

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.parameters(), lr=self.hparams.lr)
