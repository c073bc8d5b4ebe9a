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

from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from threedq.errors import InputError
from threedq.stages.base import EncoderStage, stage_arguments
from threedq.stages.checkpoint import load_checkpoint
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

__all__ = ["VIEW_PREDICTION_SETTINGS", "ViewPrediction", "ViewPredictionObjective", "view_prediction_checkpoint"]


#: the view-prediction settings the objective reads (:attr:`ViewPredictionObjective.vp_settings`); a stage that keeps
#: the objective as a regulariser (the mining stage's ``view_prediction_weight``) takes them from the checkpoint it
#: loads the decoder from
VIEW_PREDICTION_SETTINGS = ("num_planes", "depth_range", "pool", "free_samples_per_ray", "free_pixel_stride",
                            "rgb_weight", "occ_weight", "rgb_loss", "ground_margin", "shape_channels",
                            "occupancy_views")


def view_prediction_checkpoint(path: str | Path) -> tuple[dict[str, Any], dict[str, Tensor], dict[str, Tensor]]:
    """The view-prediction objective a checkpoint carries: its settings (:data:`VIEW_PREDICTION_SETTINGS`), the
    decoder's and the occupancy head's weights.

    A view-prediction checkpoint has them (its hyperparameters; a setting it predates at :class:`ViewPrediction`'s
    default), and so has a mining checkpoint trained with ``view_prediction_weight > 0`` (the settings under
    ``view_prediction_settings``).

    Raises:
        InputError: the file carries no decoder (one line naming the file and the field).
    """
    ck = load_checkpoint(path)
    settings = ck.content.get("view_prediction_settings") if ck.is_lightning else None
    if settings is None and ck.stage == "viewpred":
        defaults = stage_arguments(ViewPrediction)
        hp = ck.hparams or {}
        settings = {k: hp.get(k, defaults[k]) for k in VIEW_PREDICTION_SETTINGS}
    decoder, occ_head = (ck.prefixed("decoder."), ck.prefixed("occ_head.")) if ck.is_lightning else ({}, {})
    if settings is None or not decoder or not occ_head:
        raise InputError(
            f"{path}: field 'state_dict': no view-prediction decoder ('decoder.*', 'occ_head.*'): keeping view "
            f"prediction as a regulariser needs a view-prediction checkpoint, or a mining one trained with "
            f"view_prediction_weight > 0"
        )
    settings = dict(settings)
    settings.setdefault("shape_channels", 0)  # a mining checkpoint from before the setting: the paper's, none
    settings.setdefault("occupancy_views", 0)  # likewise: every target view decoded, the paper's
    missing = [k for k in VIEW_PREDICTION_SETTINGS if k not in settings]
    if missing:
        raise InputError(f"{path}: field 'view_prediction_settings': missing {missing}")
    return dict(settings), decoder, occ_head


class ViewPredictionObjective:
    """The view-prediction loss, for an :class:`~threedq.stages.base.EncoderStage` with a ``decoder``
    (:class:`~threedq.nets.ViewDecoder`), an ``occ_head`` (:class:`~threedq.nets.OccupancyHead`) and
    :attr:`vp_settings`: :class:`ViewPrediction` trains with it, the mining stage keeps it as a regulariser.

    Convention: see :class:`ViewPrediction`.
    """

    @property
    def vp_settings(self) -> Mapping[str, Any]:
        """The :data:`VIEW_PREDICTION_SETTINGS` of the objective, by name."""
        raise NotImplementedError

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
        s = self.vp_settings["free_pixel_stride"]
        # Pixel (s*i, s*j) of the full image is pixel (i, j) of the strided one: u' = u / s.
        k_strided = k * torch.tensor([1.0 / s, 1.0 / s, 1.0], dtype=k.dtype, device=k.device)[:, None]
        free = free_space_from_depth(
            d[:, ::s, ::s], k_strided, p, self.feature_grid, samples_per_ray=self.vp_settings["free_samples_per_ray"]
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

    def num_decoded_targets(self, batch: dict[str, Tensor], n_in: int) -> int:
        """``T``: the target views of ``batch`` the decoder predicts, views ``n_in .. n_in + T - 1``; the last
        ``occupancy_views`` of the sample's views add only to the occupancy labels.

        Raises:
            ValueError: fewer than one decoded target would be left (naming the fields).
        """
        S, k = batch["rgb"].shape[1], int(self.vp_settings.get("occupancy_views", 0) or 0)
        T = S - n_in - k
        if T < 1:
            raise ValueError(
                f"occupancy_views: {k} of the sample's {S} views feed only the occupancy labels and {n_in} are inputs, "
                f"so no target view is left to decode; set data num_target_views >= 1 + occupancy_views"
            )
        return T

    def target_foreground(self, batch: dict[str, Tensor], n_in: int, T: int | None = None) -> Tensor:
        """Target pixels whose surface lies above the ground plane, at half resolution ``[B*T, 1, H/2, W/2]``.

        The plane is fitted label-free to the depth of every view of the sample
        (:func:`~threedq.geometry.above_ground_mask`); a half-resolution pixel is foreground when most of its
        four full-resolution pixels are. ``T``: the decoded targets (views ``n_in .. n_in + T - 1``; default: every
        view after the inputs).
        """
        views = slice(n_in, None if T is None else n_in + T)
        fg = above_ground_mask(batch["depth"], batch["K"], batch["R_T_cam"], margin=self.vp_settings["ground_margin"],
                               views=views)  # the plane from every view, the mask of the targets
        fg = fg.flatten(0, 1)[:, None].to(batch["depth"].dtype)  # [B*T, 1, H, W]
        return (F.avg_pool2d(fg, 2) > 0.5).to(fg.dtype)

    def predict_view(self, feats: Tensor, K: Tensor, R_T_cam: Tensor, image_size: tuple[int, int]) -> Tensor:
        """Decode the feature grid ``[B, C, Z', Y', X']`` to the RGB of a camera ``[B, 3, H/2, W/2]`` in [-0.5, 0.5]."""
        H, W = image_size
        k_half = scale_intrinsics(K, 0.5, 0.5)
        pooled = frustum_depth_max(  # the decoder's depth max-pool of the frustum, without the frustum (bitwise)
            feats, self.feature_grid, k_half, R_T_cam, (H // 2, W // 2), tuple(self.vp_settings["depth_range"]),
            self.vp_settings["num_planes"], self.decoder.pool,
        )
        return self.decoder.decode_pooled(pooled)

    def view_prediction_loss(self, feats: Tensor, occ_logits: Tensor, batch: dict[str, Tensor], n_in: int,
                             foreground: bool = False) -> dict[str, Tensor]:
        """The loss of predicting the target views of ``batch`` from the feature grid of its input views.

        Args:
            feats: ``[B, C, Z', Y', X']`` the grid encoded from the first ``n_in`` views of each sample;
                occ_logits: ``[B, 1, Z', Y', X']`` the occupancy head's output on it.
            batch: ``rgb [B, S, 3, H, W]``, ``depth [B, S, H, W]``, ``K``, ``R_T_cam``; views ``n_in..S-1`` are the
                targets.
            foreground: compute the above-ground mask even when the RGB loss does not need it (for ``l1_fg``).

        Returns:
            ``loss`` (``rgb_weight`` x the RGB loss + ``occ_weight`` x the balanced occupancy loss), ``l1`` (the plain
            masked L1), ``rgb_loss`` (the RGB loss, unweighted), ``occ_loss``, ``pred`` / ``target``
            ``[B*T, 3, H/2, W/2]`` in [-0.5, 0.5], ``valid``, ``fg`` (or None) ``[B*T, 1, H/2, W/2]``, ``occ`` /
            ``free`` ``[B, 1, Z', Y', X']``.
        """
        st = self.vp_settings
        T = self.num_decoded_targets(batch, n_in)
        tv = slice(n_in, n_in + T)  # the decoded targets; the views after them feed the occupancy labels alone
        rgb_t, depth_t = batch["rgb"][:, tv].flatten(0, 1), batch["depth"][:, tv].flatten(0, 1)
        K_t, pose_t = batch["K"][:, tv].flatten(0, 1), batch["R_T_cam"][:, tv].flatten(0, 1)
        H, W = rgb_t.shape[-2:]
        k = int(st.get("shape_channels", 0) or 0)  # shape channels: the decoder reads them, the RGB loss does not train them
        feats_rgb = torch.cat([feats[:, :k].detach(), feats[:, k:]], 1) if k else feats
        feats_t = feats_rgb.repeat_interleave(T, dim=0) if T > 1 else feats_rgb
        pred = self.predict_view(feats_t, K_t, pose_t, (H, W))  # [B*T, 3, H/2, W/2]
        target = F.avg_pool2d(rgb_t, 2) - 0.5
        valid = self.target_valid(depth_t, K_t, pose_t)
        occ, free = self.occupancy_labels(batch["depth"], batch["K"], batch["R_T_cam"])
        l1 = masked_l1(pred, target, valid)
        balanced = st["rgb_loss"] == "balanced"
        fg = self.target_foreground(batch, n_in, T) if balanced or foreground else None
        rgb_loss = balanced_l1(pred, target, valid, fg) if balanced else l1
        occ_loss = balanced_occupancy_loss(occ_logits, occ, free)
        loss = st["rgb_weight"] * rgb_loss + st["occ_weight"] * occ_loss
        return {"loss": loss, "l1": l1, "rgb_loss": rgb_loss, "occ_loss": occ_loss, "pred": pred, "target": target,
                "valid": valid, "fg": fg, "occ": occ, "free": free}


class ViewPrediction(ViewPredictionObjective, EncoderStage):
    """The view-prediction stage.

    Args:
        **kwargs: the encoder's arguments (``grid_min``, ``grid_max``, ``grid_resolution``, ``feature_dim``,
            ``encoder_channels``, ``feature_stride``, ``encoder_ckpt``, ``freeze_encoder``, ``channels_last``), by keyword: see
            :class:`~threedq.stages.base.EncoderStage`.
        num_planes: depth planes of the target frustum.
        depth_range: ``(near, far)`` camera depth of the frustum, metres.
        pool: max-pool of the frustum along depth in the decoder.
        free_samples_per_ray: points sampled along each camera ray for free-space labels.
        free_pixel_stride: cast free-space rays through every n-th pixel in x and y (the feature voxels
            are several pixels wide, so 2 loses nothing and is 4x cheaper).
        rgb_weight: weight of the RGB L1 loss. With equal weights the occupancy loss dominates the shared
            encoder and the RGB branch barely learns: after 200 steps on the embedded data (32x32x16 grid)
            the held-out in-grid L1 was 0.101 at weight 1, 0.069 at 10, 0.058 at 30 and 0.052 with no
            occupancy loss at all (mean-colour baseline 0.046), while occupancy accuracy stays > 0.98.
        occ_weight: weight of the occupancy loss.
        rgb_warmup_steps: the RGB loss's weight rises linearly from 0 at step 0 to ``rgb_weight`` at this step, so that
            the first steps train the encoder on occupancy alone (the shape study found the first 100 steps are where
            the RGB term costs shape; docs/studies/shape.md). 0 (the paper's): ``rgb_weight`` from the first step.
            Training only: validation reports the full-weight loss.
        shape_channels: the first this many of the ``feature_dim`` channels are trained by the occupancy loss
            alone: the view decoder reads them detached, so the RGB loss's gradient reaches only the other channels
            (and, through them, the shared U-Net). 0 (the paper's): every channel serves both losses. A departure
            from the paper, for features that keep 3D shape where the RGB loss would spend them on colour
            (docs/studies/shape.md, "Shape channels").
        occupancy_views: the last this many views of each sample are not decoded: their depth only adds to the
            occupancy labels (occupied and free voxels fused over every view of the sample), so the occupancy head
            must predict the sides of the objects no input view sees, an amodal target. The data's
            ``num_target_views`` must leave at least one decoded target (``num_target_views >= 1 +
            occupancy_views``). 0 (the paper's): every target view is decoded and labels occupancy.
        rgb_loss: ``"balanced"`` (default): :func:`~threedq.nets.balanced_l1`, the mean L1 over target pixels
            above the ground plus the mean over the rest, the RGB counterpart of the balanced occupancy loss;
            ``"plain"``: the mean over all valid pixels (the paper's Eq. 1). Objects cover about 9% of the
            valid pixels of the embedded scenes, so with the plain loss the features learn the ground's colour
            and the objects' silhouettes but hardly their colours: after 600 steps, retrieval precision@10 of
            the learned crops is 0.240 with the plain loss and 0.325 with the balanced one (raw input crops
            0.333; docs/studies/main-job-runs.md).
        ground_margin: a target pixel is foreground when its surface lies more than this many metres above
            the ground plane fitted (RANSAC, label-free) to the depth of the sample's views.
        lr: Adam learning rate (paper: 1e-3).
        lr_schedule: ``"constant"`` (the paper's): ``lr`` throughout; ``"cosine"``: ``lr`` annealed to 0 along a
            half cosine over the run's optimizer steps (``trainer.max_steps``, else its epochs), stepped every
            optimizer step (``torch.optim.lr_scheduler.CosineAnnealingLR``; the trainer's checkpoints carry its
            state, so a resumed fit goes on along the same curve). A departure from the paper: at the main job's
            budget it lost 0.05 same-object top-1 and gained 0.01 linear probe (2 seeds, docs/studies/viewpred-recipe.md).
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
        rgb_warmup_steps: int = 0,
        lr: float = 1e-3,
        lr_schedule: Literal["constant", "cosine"] = "constant",
        image_every_n_steps: int = 200,
        rgb_loss: Literal["balanced", "plain"] = "balanced",
        ground_margin: float = 0.02,
        shape_channels: int = 0,
        occupancy_views: int = 0,
        **kwargs: Any,
    ) -> None:
        if rgb_loss not in ("balanced", "plain"):
            raise ValueError(f"rgb_loss: expected 'balanced' or 'plain', got {rgb_loss!r}")
        if lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"lr_schedule: expected 'constant' or 'cosine', got {lr_schedule!r}")
        if not ground_margin >= 0:
            raise ValueError(f"ground_margin: expected >= 0 metres, got {ground_margin!r}")
        super().__init__(**kwargs)
        if isinstance(rgb_warmup_steps, bool) or not isinstance(rgb_warmup_steps, int) or rgb_warmup_steps < 0:
            raise ValueError(f"rgb_warmup_steps: expected an int >= 0, got {rgb_warmup_steps!r}")
        if isinstance(occupancy_views, bool) or int(occupancy_views) != occupancy_views or occupancy_views < 0:
            raise ValueError(f"occupancy_views: expected an int >= 0, got {occupancy_views!r}")
        if not 0 <= shape_channels <= self.feature_dim:
            raise ValueError(f"shape_channels: expected 0..feature_dim ({self.feature_dim}), got {shape_channels!r}")
        self.save_hyperparameters()
        self.decoder = ViewDecoder(in_channels=self.feature_dim, num_planes=num_planes, pool=pool)
        self.occ_head = OccupancyHead(in_channels=self.feature_dim)

    @property
    def vp_settings(self) -> Mapping[str, Any]:
        return self.hparams

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
        T = self.num_decoded_targets(batch, n_in)
        r = self.view_prediction_loss(out["features"], out["occ_logits"], batch, n_in, foreground=not self.training)
        pred, target, valid, fg, occ, free = r["pred"], r["target"], r["valid"], r["fg"], r["occ"], r["free"]
        rgb_t = batch["rgb"][:, n_in:n_in + T].flatten(0, 1)
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

    def training_loss(self, r: dict[str, Tensor]) -> Tensor:
        """``r["loss"]`` of :meth:`_step` with the RGB term scaled by ``min(1, global_step / rgb_warmup_steps)``."""
        w = self.hparams.get("rgb_warmup_steps", 0)
        if not w or self.global_step >= w:
            return r["loss"]
        return r["loss"] - (1.0 - self.global_step / w) * self.hparams.rgb_weight * r["rgb_loss"]

    # ------------------------------------------------------------------ Lightning hooks
    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        r = self._step(batch)
        r["loss"] = self.training_loss(r)
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

    def configure_optimizers(self) -> torch.optim.Optimizer | dict[str, Any]:
        params = [p for p in self.parameters() if p.requires_grad]
        opt = torch.optim.Adam(params, lr=self.hparams.lr, betas=(0.9, 0.999))
        if self.hparams.lr_schedule == "constant":
            return opt
        total = self.trainer.estimated_stepping_batches  # float("inf") for a run without max_steps or max_epochs
        if not 0 < total < float("inf"):
            raise ValueError(f"lr_schedule: 'cosine' needs a finite run (trainer.max_steps or max_epochs), got {total} steps")
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=int(total), eta_min=0.0)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step", "frequency": 1}}

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


