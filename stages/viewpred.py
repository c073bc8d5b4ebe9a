"""View prediction (GIGN pre-training, paper Sec. 3.1): learn the 3D feature grid by predicting other views.

Input views are unprojected into the grid in R and encoded by the 3D U-Net; the feature grid is resampled into a
held-out target camera's frustum and decoded to the target's RGB (L1 over the target pixels whose surface lies inside
the grid; ``rgb_loss: balanced`` balances the pixels above the label-free ground plane against the rest), and an
occupancy head predicts occupied vs free voxels (labels from the depth of every view of the sample) with a
class-balanced logistic loss. Metrics: the plain L1, the L1 above the ground (``l1_fg``) and the mean-colour
baseline's.
"""

from __future__ import annotations

from typing import Any, Literal

import torch
import torch.nn.functional as F
from jsonargparse.typing import NonNegativeFloat
from torch import Tensor

from threedq.geometry import (above_ground_mask, depth_to_points, free_space_from_depth, frustum_depth_max,
                              occupancy_from_depth, scale_intrinsics)
from threedq.nets import (OccupancyHead, ViewDecoder, balanced_l1, balanced_occupancy_loss, masked_l1,
                          occupancy_balanced_accuracy)
from threedq.stages.base import EncoderStage, SplitEvaluation
from threedq.viz.features import view_prediction_figure
from threedq.viz.png import write_png

__all__ = ["ViewPrediction"]


class ViewPrediction(SplitEvaluation, EncoderStage):
    """The view-prediction stage.

    Args:
        **kwargs: the encoder's arguments, by keyword (:class:`~threedq.stages.base.EncoderStage`).
        num_planes: depth planes of the target frustum.
        depth_range: ``(near, far)`` camera depth of the frustum, metres.
        pool: max-pool of the frustum along depth in the decoder.
        free_samples_per_ray: points sampled along each camera ray for free-space labels.
        free_pixel_stride: cast free-space rays through every n-th pixel in x and y.
        rgb_weight: weight of the RGB L1 loss.
        occ_weight: weight of the occupancy loss.
        rgb_loss: ``"balanced"`` (:func:`~threedq.nets.balanced_l1`, above vs below the ground) or ``"plain"``.
        ground_margin: a target pixel is foreground when its surface lies this many metres above the ground plane.
        lr: Adam learning rate.
        image_every_n_steps: write a PNG of input, prediction, target and occupancy this often (0: never).

    Convention: frame R metres, z up; RGB in [0, 1] (the decoder predicts ``rgb - 0.5``); images at half
    the input resolution.
    """

    def __init__(
        self, *, num_planes: int = 32, depth_range: tuple[float, float] = (1.2, 5.2), pool: int = 8,
        free_samples_per_ray: int = 32, free_pixel_stride: int = 2, rgb_weight: float = 30.0, occ_weight: float = 1.0,
        lr: float = 1e-3, image_every_n_steps: int = 200, rgb_loss: Literal["balanced", "plain"] = "balanced",
        ground_margin: NonNegativeFloat = 0.02, **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        self.save_hyperparameters()
        self.decoder = ViewDecoder(in_channels=self.feature_dim, num_planes=num_planes, pool=pool)
        self.occ_head = OccupancyHead(in_channels=self.feature_dim)

    def occupancy_labels(self, depth: Tensor, K: Tensor, R_T_cam: Tensor) -> tuple[Tensor, Tensor]:
        """Occupied and free voxels ``[B, 1, Z', Y', X']`` (float 0/1, disjoint) of the feature grid from depth
        ``[B, S, H, W]``, K ``[B, S, 3, 3]``, R_T_cam ``[B, S, 4, 4]``, aggregated in R."""
        B, S = depth.shape[:2]
        d, k, p = depth.flatten(0, 1), K.flatten(0, 1), R_T_cam.flatten(0, 1)
        occ = occupancy_from_depth(d, k, p, self.feature_grid).view(B, S, 1, *self.feature_grid.volume_shape)
        s = self.hparams.free_pixel_stride
        # pixel (s*i, s*j) of the full image is pixel (i, j) of the strided one
        k_strided = k * torch.tensor([1.0 / s, 1.0 / s, 1.0], dtype=k.dtype, device=k.device)[:, None]
        free = free_space_from_depth(d[:, ::s, ::s], k_strided, p, self.feature_grid,
                                     samples_per_ray=self.hparams.free_samples_per_ray)
        free = free.view(B, S, 1, *self.feature_grid.volume_shape)
        occ = occ.amax(1)
        return occ, free.amax(1) * (1 - occ)

    def target_valid(self, depth: Tensor, K: Tensor, R_T_cam: Tensor) -> Tensor:
        """Target pixels whose observed surface lies inside the grid (the only predictable ones), at half resolution
        ``[B, 1, H/2, W/2]``."""
        B, H, W = depth.shape
        points, ok = depth_to_points(depth, K, R_T_cam)
        inside = (ok & self.grid.contains(points)).view(B, 1, H, W).to(depth.dtype)
        return (F.avg_pool2d(inside, 2) > 0.5).to(depth.dtype)

    def target_foreground(self, batch: dict[str, Tensor], n_in: int) -> Tensor:
        """Target pixels (views ``n_in..S-1``) whose surface lies above the ground plane fitted to every view
        (:func:`~threedq.geometry.above_ground_mask`), at half resolution ``[B*T, 1, H/2, W/2]``."""
        fg = above_ground_mask(batch["depth"], batch["K"], batch["R_T_cam"], margin=self.hparams.ground_margin,
                               views=slice(n_in, None))
        fg = fg.flatten(0, 1)[:, None].to(batch["depth"].dtype)  # [B*T, 1, H, W]
        return (F.avg_pool2d(fg, 2) > 0.5).to(fg.dtype)

    def predict_view(self, feats: Tensor, K: Tensor, R_T_cam: Tensor, image_size: tuple[int, int]) -> Tensor:
        """Decode the feature grid ``[B, C, Z', Y', X']`` to the RGB of a camera ``[B, 3, H/2, W/2]`` in [-0.5, 0.5]."""
        H, W = image_size
        k_half = scale_intrinsics(K, 0.5, 0.5)
        pooled = frustum_depth_max(feats, self.feature_grid, k_half, R_T_cam, (H // 2, W // 2),
                                   tuple(self.hparams.depth_range), self.hparams.num_planes, self.decoder.pool)
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
        feats = self.encode_views(*(batch[k][:, :n_in] for k in ("rgb", "depth", "K", "R_T_cam")))
        return {"features": feats, "occ_logits": self.occ_head(feats)}

    @staticmethod
    def _num_inputs(batch: dict[str, Tensor]) -> int:
        """Input views of a batch: ``batch["num_input_views"]`` (set by SceneDataset), else all views but the last."""
        S = batch["rgb"].shape[1]
        n_in = int(batch["num_input_views"].reshape(-1)[0]) if "num_input_views" in batch else S - 1
        if n_in < 1 or S - n_in < 1:
            raise ValueError(f"rgb: view prediction needs >= 1 input and >= 1 target view per sample, got {S} views "
                             f"with num_input_views={n_in}")
        return n_in

    def _step(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        out = self(batch)
        n_in = self._num_inputs(batch)
        T = batch["rgb"].shape[1] - n_in
        r = self.view_prediction_loss(out["features"], out["occ_logits"], batch, n_in, foreground=not self.training)
        pred, target, valid, fg, occ, free = r["pred"], r["target"], r["valid"], r["fg"], r["occ"], r["free"]
        rgb_t = batch["rgb"][:, n_in:].flatten(0, 1)
        # baseline: every valid target pixel predicted as the mean colour of the input views' valid pixels
        in_valid = (batch["depth"][:, :n_in] > 0).to(rgb_t.dtype)[:, :, None]
        mean_col = (batch["rgb"][:, :n_in] * in_valid).sum((1, 3, 4)) / in_valid.sum((1, 3, 4)).clamp_min(1)
        mean_col = mean_col.repeat_interleave(T, dim=0) if T > 1 else mean_col
        mean_img = mean_col[:, :, None, None].expand_as(pred) - 0.5
        out = {
            "loss": r["loss"], "l1": r["l1"], "l1_mean_colour": masked_l1(mean_img, target, valid),
            "rgb_loss": r["rgb_loss"], "occ_loss": r["occ_loss"],
            "occ_bacc": occupancy_balanced_accuracy(out["occ_logits"], occ, free),
            "pred": pred, "target": target, "occ": occ, "occ_logits": out["occ_logits"],
        }
        if fg is not None:  # the same two numbers on the objects alone (pixels above the ground)
            out["l1_fg"] = masked_l1(pred, target, valid * fg)
            out["l1_fg_mean_colour"] = masked_l1(mean_img, target, valid * fg)
        return out

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        r = self._step(batch)
        self.log_dict({f"train/{k}": r[k] for k in ("loss", "l1", "occ_loss", "occ_bacc")}, prog_bar=True,
                      batch_size=batch["rgb"].shape[0])
        every = self.hparams.image_every_n_steps
        if every and self.global_step % every == 0:
            self._write_image(batch, r, "train")
        return r["loss"]

    def _eval_step(self, batch: dict[str, Tensor], split: str, batch_idx: int) -> None:
        r = self._step(batch)
        keys = ("loss",) * (split == "val") + ("l1", "l1_mean_colour", "l1_fg", "l1_fg_mean_colour", "occ_bacc")
        self.log_dict({f"{split}/{k}": r[k] for k in keys}, prog_bar=split == "val", batch_size=batch["rgb"].shape[0],
                      sync_dist=True)
        if split == "val" and batch_idx == 0 and self.hparams.image_every_n_steps:
            self._write_image(batch, r, "val")

    def _write_image(self, batch: dict[str, Tensor], r: dict[str, Tensor], tag: str) -> None:
        if self.trainer is None or not self.trainer.is_global_zero or self.trainer.sanity_checking:
            return
        img = view_prediction_figure(batch["rgb"][0, 0], r["pred"][0] + 0.5, r["target"][0] + 0.5,
                                     torch.sigmoid(r["occ_logits"][0, 0]), r["occ"][0, 0])
        write_png(self.run_dir / "images" / f"{tag}_step{self.global_step:06d}.png", img)
        experiment = getattr(self.logger, "experiment", None)
        if hasattr(experiment, "add_image"):
            experiment.add_image(f"{tag}/view_prediction", img, self.global_step, dataformats="HWC")
