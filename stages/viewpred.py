"""View prediction (GIGN pre-training, paper Sec. 3.1): learn the 3D feature grid by predicting other views.

Input views are unprojected into the grid in R and encoded by the 3D U-Net; the aggregated feature grid
is resampled into a held-out target camera's frustum and decoded to the target's RGB (L1 over valid
pixels), and an occupancy head predicts, per voxel, occupied vs free space with a class-balanced
logistic loss. Occupancy labels come from the depth of every view of the sample (input and target):
occupied where depth points fall, free along each camera ray in front of the observed surface.
RGB is scored on the target pixels whose surface lies inside the grid (nothing else can be predicted
from it), for the model and for the mean-colour baseline alike. By default the RGB loss is balanced
between the pixels above the scene's ground plane (fitted to the depth, no labels) and the rest, as the
occupancy loss is balanced between occupied and free voxels; metrics report both the plain L1 and the
L1 on the above-ground pixels (``l1_fg``).
"""

from __future__ import annotations

from typing import Any, Literal

import torch
import torch.nn.functional as F
from jsonargparse.typing import NonNegativeFloat
from torch import Tensor

from threedq.stages.base import EncoderStage
from threedq.viz.features import view_prediction_figure
from threedq.viz.png import write_png
from threedq.geometry import (
    above_ground_mask,
    depth_to_points,
    free_space_from_depth,
    frustum_depth_max,
    occupancy_from_depth,
    scale_intrinsics,
)
from threedq.nets import (
    OccupancyHead,
    ViewDecoder,
    balanced_l1,
    balanced_occupancy_loss,
    masked_l1,
    occupancy_balanced_accuracy,
)

__all__ = ["ViewPrediction"]


class ViewPrediction(EncoderStage):
    """The view-prediction stage.

    Args:
        **kwargs: the encoder's arguments (``grid_min``, ``grid_max``, ``grid_resolution``, ``feature_dim``,
            ``encoder_channels``, ``feature_stride``, ``encoder_ckpt``, ``freeze_encoder``, ``channels_last``), by
            keyword: see :class:`~threedq.stages.base.EncoderStage`.
        num_planes: depth planes of the target frustum.
        depth_range: ``(near, far)`` camera depth of the frustum, metres.
        pool: max-pool of the frustum along depth in the decoder.
        free_samples_per_ray: points sampled along each camera ray for free-space labels.
        free_pixel_stride: cast free-space rays through every n-th pixel in x and y (the feature voxels
            are several pixels wide, so 2 loses nothing and is 4x cheaper).
        rgb_weight: weight of the RGB L1 loss (with equal weights the occupancy loss dominates the shared encoder
            and the RGB branch barely learns).
        occ_weight: weight of the occupancy loss.
        rgb_loss: ``"balanced"`` (default): :func:`~threedq.nets.balanced_l1`, the mean L1 over target pixels
            above the ground plus the mean over the rest, the RGB counterpart of the balanced occupancy loss;
            ``"plain"``: the mean over all valid pixels (the paper's Eq. 1). Objects cover a small part of the valid
            pixels of a tabletop scene, so with the plain loss the features learn the ground's colour and the
            objects' silhouettes but hardly their colours (docs/studies/viewpred-recipe.md).
        ground_margin: a target pixel is foreground when its surface lies more than this many metres above
            the ground plane fitted (RANSAC, label-free) to the depth of the sample's views.
        lr: Adam learning rate (paper: 1e-3).
        image_every_n_steps: write a PNG of (input, predicted, true target, occupancy slices) this often;
            0 disables.

    Convention: frame R metres, z up; RGB in [0, 1] (the decoder predicts ``rgb - 0.5``); images at half
    the input resolution.
    """

    def __init__(
        self,
        *,
        num_planes: int = 32,
        depth_range: tuple[float, float] = (1.2, 5.2),
        pool: int = 8,
        free_samples_per_ray: int = 32,
        free_pixel_stride: int = 2,
        rgb_weight: float = 30.0,
        occ_weight: float = 1.0,
        lr: float = 1e-3,
        image_every_n_steps: int = 200,
        rgb_loss: Literal["balanced", "plain"] = "balanced",
        ground_margin: NonNegativeFloat = 0.02,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        self.save_hyperparameters()
        self.decoder = ViewDecoder(in_channels=self.feature_dim, num_planes=num_planes, pool=pool)
        self.occ_head = OccupancyHead(in_channels=self.feature_dim)

    def occupancy_labels(self, depth: Tensor, K: Tensor, R_T_cam: Tensor) -> tuple[Tensor, Tensor]:
        """Occupied and free voxels of the feature grid from ``S`` views per scene, aggregated in R.

        Args:
            depth ``[B, S, H, W]``, K ``[B, S, 3, 3]``, R_T_cam ``[B, S, 4, 4]``.

        Returns:
            ``occupied``, ``free``: ``[B, 1, Z', Y', X']`` float 0/1, disjoint (occupied wins).
        """
        B, S = depth.shape[:2]
        d, k, p = depth.flatten(0, 1), K.flatten(0, 1), R_T_cam.flatten(0, 1)
        occ = occupancy_from_depth(d, k, p, self.feature_grid).view(B, S, 1, *self.feature_grid.volume_shape)
        s = self.hparams.free_pixel_stride
        # Pixel (s*i, s*j) of the full image is pixel (i, j) of the strided one: u' = u / s.
        k_strided = k * torch.tensor([1.0 / s, 1.0 / s, 1.0], dtype=k.dtype, device=k.device)[:, None]
        free = free_space_from_depth(
            d[:, ::s, ::s], k_strided, p, self.feature_grid, samples_per_ray=self.hparams.free_samples_per_ray
        )
        free = free.view(B, S, 1, *self.feature_grid.volume_shape)
        occ = occ.amax(1)
        return occ, free.amax(1) * (1 - occ)

    def target_valid(self, depth: Tensor, K: Tensor, R_T_cam: Tensor) -> Tensor:
        """Target pixels whose observed surface lies inside the grid, at half resolution ``[B, 1, H/2, W/2]``.

        Only those can be predicted from the grid: a ray that leaves the grid before it hits anything (far
        ground, sky) carries no information, so it is left out of the loss and of every RGB metric.
        """
        B, H, W = depth.shape
        points, ok = depth_to_points(depth, K, R_T_cam)
        inside = (ok & self.grid.contains(points)).view(B, 1, H, W).to(depth.dtype)
        return (F.avg_pool2d(inside, 2) > 0.5).to(depth.dtype)

    def target_foreground(self, batch: dict[str, Tensor], n_in: int) -> Tensor:
        """Target pixels (views ``n_in..S-1``) whose surface lies above the ground plane, at half resolution
        ``[B*T, 1, H/2, W/2]``.

        The plane is fitted label-free to the depth of every view of the sample
        (:func:`~threedq.geometry.above_ground_mask`); a half-resolution pixel is foreground when most of its
        four full-resolution pixels are.
        """
        fg = above_ground_mask(batch["depth"], batch["K"], batch["R_T_cam"], margin=self.hparams.ground_margin,
                               views=slice(n_in, None))  # the plane from every view, the mask of the targets
        fg = fg.flatten(0, 1)[:, None].to(batch["depth"].dtype)  # [B*T, 1, H, W]
        return (F.avg_pool2d(fg, 2) > 0.5).to(fg.dtype)

    def predict_view(self, feats: Tensor, K: Tensor, R_T_cam: Tensor, image_size: tuple[int, int]) -> Tensor:
        """Decode the feature grid ``[B, C, Z', Y', X']`` to the RGB of a camera ``[B, 3, H/2, W/2]`` in [-0.5, 0.5]."""
        H, W = image_size
        k_half = scale_intrinsics(K, 0.5, 0.5)
        pooled = frustum_depth_max(  # the decoder's depth max-pool of the frustum, without the frustum (bitwise)
            feats, self.feature_grid, k_half, R_T_cam, (H // 2, W // 2), tuple(self.hparams.depth_range),
            self.hparams.num_planes, self.decoder.pool,
        )
        return self.decoder.decode_pooled(pooled)

    def view_prediction_loss(self, feats: Tensor, occ_logits: Tensor, batch: dict[str, Tensor], n_in: int,
                             foreground: bool = False) -> dict[str, Tensor]:
        """The loss of predicting the target views of ``batch`` from the feature grid of its input views.

        Args:
            feats: ``[B, C, Z', Y', X']`` the grid encoded from the first ``n_in`` views of each sample;
                occ_logits: ``[B, 1, Z', Y', X']`` the occupancy head's output on it.
            batch: ``rgb [B, S, 3, H, W]``, ``depth [B, S, H, W]``, ``K``, ``R_T_cam``; views ``n_in..S-1`` are the
                ``T`` targets.
            foreground: compute the above-ground mask even when the RGB loss does not need it (for ``l1_fg``).

        Returns:
            ``loss`` (``rgb_weight`` x the RGB loss + ``occ_weight`` x the balanced occupancy loss), ``l1`` (the plain
            masked L1), ``rgb_loss`` (the RGB loss, unweighted), ``occ_loss``, ``pred`` / ``target``
            ``[B*T, 3, H/2, W/2]`` in [-0.5, 0.5], ``valid``, ``fg`` (or None) ``[B*T, 1, H/2, W/2]``, ``occ`` /
            ``free`` ``[B, 1, Z', Y', X']``.
        """
        hp = self.hparams
        T = batch["rgb"].shape[1] - n_in
        rgb_t, depth_t = batch["rgb"][:, n_in:].flatten(0, 1), batch["depth"][:, n_in:].flatten(0, 1)
        K_t, pose_t = batch["K"][:, n_in:].flatten(0, 1), batch["R_T_cam"][:, n_in:].flatten(0, 1)
        H, W = rgb_t.shape[-2:]
        feats_t = feats.repeat_interleave(T, dim=0) if T > 1 else feats
        pred = self.predict_view(feats_t, K_t, pose_t, (H, W))  # [B*T, 3, H/2, W/2]
        target = F.avg_pool2d(rgb_t, 2) - 0.5
        valid = self.target_valid(depth_t, K_t, pose_t)
        occ, free = self.occupancy_labels(batch["depth"], batch["K"], batch["R_T_cam"])
        l1 = masked_l1(pred, target, valid)
        balanced = hp.rgb_loss == "balanced"
        fg = self.target_foreground(batch, n_in) if balanced or foreground else None
        rgb_loss = balanced_l1(pred, target, valid, fg) if balanced else l1
        occ_loss = balanced_occupancy_loss(occ_logits, occ, free)
        loss = hp.rgb_weight * rgb_loss + hp.occ_weight * occ_loss
        return {"loss": loss, "l1": l1, "rgb_loss": rgb_loss, "occ_loss": occ_loss, "pred": pred, "target": target,
                "valid": valid, "fg": fg, "occ": occ, "free": free}

    def forward(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        n_in = self._num_inputs(batch)
        feats = self.encode_views(
            batch["rgb"][:, :n_in], batch["depth"][:, :n_in], batch["K"][:, :n_in], batch["R_T_cam"][:, :n_in]
        )
        return {"features": feats, "occ_logits": self.occ_head(feats)}

    @staticmethod
    def _num_inputs(batch: dict[str, Tensor]) -> int:
        """Input views of a batch: ``batch["num_input_views"]`` (set by SceneDataset), else all views but the last."""
        S = batch["rgb"].shape[1]
        n_in = int(batch["num_input_views"].reshape(-1)[0]) if "num_input_views" in batch else S - 1
        if n_in < 1 or S - n_in < 1:
            raise ValueError(
                f"rgb: view prediction needs >= 1 input and >= 1 target view per sample, got {S} views with "
                f"num_input_views={n_in}"
            )
        return n_in

    def _step(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        out = self(batch)
        n_in = self._num_inputs(batch)
        T = batch["rgb"].shape[1] - n_in
        r = self.view_prediction_loss(out["features"], out["occ_logits"], batch, n_in, foreground=not self.training)
        pred, target, valid, fg, occ, free = r["pred"], r["target"], r["valid"], r["fg"], r["occ"], r["free"]
        rgb_t = batch["rgb"][:, n_in:].flatten(0, 1)
        # Baseline: every valid target pixel predicted as the mean colour of the input views' valid pixels.
        in_valid = (batch["depth"][:, :n_in] > 0).to(rgb_t.dtype)[:, :, None]
        mean_col = (batch["rgb"][:, :n_in] * in_valid).sum((1, 3, 4)) / in_valid.sum((1, 3, 4)).clamp_min(1)
        mean_col = mean_col.repeat_interleave(T, dim=0) if T > 1 else mean_col
        mean_img = mean_col[:, :, None, None].expand_as(pred) - 0.5
        out = {
            "loss": r["loss"],
            "l1": r["l1"],
            "l1_mean_colour": masked_l1(mean_img, target, valid),
            "rgb_loss": r["rgb_loss"],
            "occ_loss": r["occ_loss"],
            "occ_bacc": occupancy_balanced_accuracy(out["occ_logits"], occ, free),
            "pred": pred,
            "target": target,
            "occ": occ,
            "occ_logits": out["occ_logits"],
        }
        if fg is not None:  # the same two numbers on the objects alone (pixels above the ground)
            out["l1_fg"] = masked_l1(pred, target, valid * fg)
            out["l1_fg_mean_colour"] = masked_l1(mean_img, target, valid * fg)
        return out

    # ------------------------------------------------------------------ Lightning hooks
    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        r = self._step(batch)
        B = batch["rgb"].shape[0]
        self.log_dict(
            {"train/loss": r["loss"], "train/l1": r["l1"], "train/occ_loss": r["occ_loss"], "train/occ_bacc": r["occ_bacc"]},
            prog_bar=True,
            batch_size=B,
        )
        every = self.hparams.image_every_n_steps
        if every and self.global_step % every == 0:
            self._write_image(batch, r, "train")
        return r["loss"]

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        r = self._step(batch)
        B = batch["rgb"].shape[0]
        self.log_dict(
            {
                "val/loss": r["loss"],
                "val/l1": r["l1"],
                "val/l1_mean_colour": r["l1_mean_colour"],
                "val/l1_fg": r["l1_fg"],
                "val/l1_fg_mean_colour": r["l1_fg_mean_colour"],
                "val/occ_bacc": r["occ_bacc"],
            },
            prog_bar=True,
            batch_size=B,
            sync_dist=True,
        )
        if batch_idx == 0 and self.hparams.image_every_n_steps:
            self._write_image(batch, r, "val")

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        r = self._step(batch)
        self.log_dict(
            {
                "test/l1": r["l1"],
                "test/l1_mean_colour": r["l1_mean_colour"],
                "test/l1_fg": r["l1_fg"],
                "test/l1_fg_mean_colour": r["l1_fg_mean_colour"],
                "test/occ_bacc": r["occ_bacc"],
            },
            batch_size=batch["rgb"].shape[0],
            sync_dist=True,
        )

    def configure_optimizers(self) -> torch.optim.Optimizer:
        params = [p for p in self.parameters() if p.requires_grad]
        return torch.optim.Adam(params, lr=self.hparams.lr, betas=(0.9, 0.999))

    # ------------------------------------------------------------------ pictures
    def _write_image(self, batch: dict[str, Tensor], r: dict[str, Tensor], tag: str) -> None:
        if self.trainer is None or not self.trainer.is_global_zero or self.trainer.sanity_checking:
            return
        img = view_prediction_figure(
            batch["rgb"][0, 0], r["pred"][0] + 0.5, r["target"][0] + 0.5, torch.sigmoid(r["occ_logits"][0, 0]), r["occ"][0, 0]
        )
        write_png(self.run_dir / "images" / f"{tag}_step{self.global_step:06d}.png", img)
        experiment = getattr(self.logger, "experiment", None)
        if hasattr(experiment, "add_image"):
            experiment.add_image(f"{tag}/view_prediction", img, self.global_step, dataformats="HWC")


