"""The 3D object detector stage (paper Sec. 3.1 "3D object detection", supplement: detector architecture).

On the encoder's feature grid: a down-sampling Conv3d (stride 2), residual blocks, then a 1x1x1 head with one anchor
per cell: an objectness logit and a box regression ``(dx, dy, dz, log sx, log sy, log sz)`` relative to the cell
centre and the anchor size. Targets: :func:`detection_targets`; class-balanced logistic objectness loss and smooth L1
over positives; inference thresholds, decodes and runs greedy 3D NMS. Training boxes come from the DataModule's
``boxes`` (``gt`` or ``proposals``); validation and test score against the GT (``gt_aabb``) with
:class:`~threedq.metrics.DetectionMAP` at IoU 0.25 and 0.5.

Convention: frame R metres, z up; boxes axis-aligned ``(xmin, ymin, zmin, xmax, ymax, zmax)``; volumes
``[B, C, Z, Y, X]``.
"""

from __future__ import annotations

import contextlib
import math
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from jsonargparse.typing import ClosedUnitInterval, PositiveInt

from threedq.argtypes import UnitIoU as UnitFraction
from lightning.pytorch.utilities import rank_zero_info
from torch import Tensor, nn

from threedq.errors import InputError
from threedq.stages.base import EncoderStage, SplitEvaluation
from threedq.box_refinement import add_flat_boxes, observed_boxes, refine_boxes
from threedq.boxes import nms_3d
from threedq.metrics import DetectionMAP
from threedq.viz.detection import detection_figure
from threedq.viz.png import write_png

__all__ = ["Detector", "DetectorHead", "decode_boxes", "detection_targets"]

#: The most boxes of one scene that enter 3D NMS (the highest scores): NMS builds an N x N overlap matrix.
PRE_NMS_TOP_K = 16_384


class _ResBlock3d(nn.Module):
    def __init__(self, channels: int) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Conv3d(channels, channels, 3, padding=1, bias=False), nn.BatchNorm3d(channels),
                                  nn.LeakyReLU(0.2), nn.Conv3d(channels, channels, 3, padding=1, bias=False),
                                  nn.BatchNorm3d(channels))
        self.act = nn.LeakyReLU(0.2)

    def forward(self, x: Tensor) -> Tensor:
        return self.act(x + self.body(x))


class DetectorHead(nn.Module):
    """Down-sampling Conv3d (k4 s2) + three residual blocks + a 1x1x1 objectness/box head.

    Args:
        in_channels: feature-grid channels.
        channels: width of the residual blocks.
        num_blocks: residual blocks.

    Shapes: ``[B, C, Z, Y, X]`` -> objectness ``[B, Z/2, Y/2, X/2]`` logits and box ``[B, 6, Z/2, Y/2, X/2]``.
    """

    def __init__(self, in_channels: int = 32, channels: int = 32, num_blocks: int = 3) -> None:
        super().__init__()
        self.down = nn.Sequential(nn.Conv3d(in_channels, channels, 4, stride=2, padding=1, bias=False),
                                  nn.BatchNorm3d(channels), nn.LeakyReLU(0.2))
        self.blocks = nn.Sequential(*[_ResBlock3d(channels) for _ in range(num_blocks)])
        self.out = nn.Conv3d(channels, 7, 1)
        nn.init.constant_(self.out.bias[:1], -2.0)  # start with low objectness everywhere

    def forward(self, feats: Tensor) -> tuple[Tensor, Tensor]:
        y = self.out(self.blocks(self.down(feats)))
        return y[:, 0], y[:, 1:]


def cell_centres(origin: Tensor, cell: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """World coordinates ``[Z, Y, X, 3]`` (x, y, z order) of the cell centres of a grid with ``origin`` ``[3]``
    (xmin, ymin, zmin), ``cell`` ``[3]`` cell size (x, y, z) and ``shape`` ``(Z, Y, X)``."""
    Z, Y, X = shape
    zs, ys, xs = (torch.arange(n, dtype=origin.dtype, device=origin.device) + 0.5 for n in (Z, Y, X))
    gz, gy, gx = torch.meshgrid(zs, ys, xs, indexing="ij")
    return torch.stack([gx, gy, gz], dim=-1) * cell + origin


def detection_targets(
    centres: Tensor, aabb: Tensor, mask: Tensor, anchor: Tensor, inner_fraction: float = 0.5,
    negative_margin: float = 0.1, min_height: float = 0.0,
) -> tuple[Tensor, Tensor, Tensor]:
    """Objectness labels and box-regression targets of every cell.

    Args:
        centres: ``[Z, Y, X, 3]`` cell centres (x, y, z), metres.
        aabb: ``[B, M, 6]`` boxes; mask ``[B, M]`` valid boxes.
        anchor: ``[3]`` anchor size (sx, sy, sz).
        inner_fraction: a cell is positive when its centre is within this fraction of the box's half-extent
            of the box centre (per axis); the cell nearest to the centre is positive too.
        negative_margin: a cell is negative when its centre is more than this (metres) outside every box.
        min_height: boxes less tall than this (metres) give no positives; their cells (and margin) are ignored.

    Returns:
        ``label`` ``[B, Z, Y, X]`` (1 positive, 0 negative, -1 ignored) and ``target`` ``[B, 6, Z, Y, X]``
        ``((c - p) / anchor, log(size / anchor))`` of the box a positive cell belongs to (the smallest-volume
        one if several), ``assigned`` ``[B, Z, Y, X]`` index of that box (-1 none).

    Convention: frame R, metres; x, y, z order inside the last dimensions.
    """
    if mask.shape[1] == 0:  # no boxes at all: one masked-out box keeps the reductions defined
        aabb, mask = aabb.new_zeros(aabb.shape[0], 1, 6), mask.new_zeros(mask.shape[0], 1)
    B = mask.shape[0]
    Z, Y, X = centres.shape[:3]
    p = centres.view(1, 1, -1, 3)  # [1, 1, N, 3]
    lo, hi = aabb[..., None, :3], aabb[..., None, 3:]  # [B, M, 1, 3]
    ctr, half = (lo + hi) / 2, (hi - lo) / 2
    inner = ((p - ctr).abs() <= half * inner_fraction).all(-1)  # [B, M, N]
    # the cell holding the box centre is always positive
    nearest = ((p - ctr) ** 2).sum(-1).argmin(-1)  # [B, M]
    inner = inner.scatter(2, nearest[..., None], True)
    tall = (aabb[..., 5] - aabb[..., 2]) >= min_height  # [B, M]
    inner &= (mask & tall)[..., None]
    near = ((p >= lo - negative_margin) & (p <= hi + negative_margin)).all(-1) & mask[..., None]  # [B, M, N]
    vol = (hi - lo).prod(-1).squeeze(-1)  # [B, M]
    big = torch.finfo(vol.dtype).max
    cost = torch.where(inner, vol[..., None].expand_as(inner), torch.full_like(inner, big, dtype=vol.dtype))
    best_cost, best = cost.min(1)  # [B, N]
    pos = best_cost < big
    label = torch.where(near.any(1), -1.0, 0.0)
    label = torch.where(pos, 1.0, label)
    idx = best[..., None].expand(-1, -1, 3)
    c = torch.gather(ctr.squeeze(2), 1, idx)  # [B, N, 3]
    s = torch.gather((hi - lo).squeeze(2), 1, idx).clamp_min(1e-4)
    target = torch.cat([(c - p.view(1, -1, 3)) / anchor, torch.log(s / anchor)], dim=-1)  # [B, N, 6]
    target = target.permute(0, 2, 1).reshape(B, 6, Z, Y, X)
    assigned = torch.where(pos, best, torch.full_like(best, -1)).view(B, Z, Y, X)
    return label.view(B, Z, Y, X), target, assigned


def check_same_anchor(trained: Any, asked: Any, source: str) -> None:
    """Refuse to decode a detector's boxes with another anchor than it was trained with (``InputError`` naming
    ``source``, the field and both anchors)."""
    trained, asked = [round(float(a), 6) for a in trained], [round(float(a), 6) for a in asked]
    if trained != asked:
        raise InputError(f"{source}: field 'anchor_size': the detector was trained with anchor_size={trained}, "
                         f"this stage asks for {asked} (set model.init_args.anchor_size to null or to the "
                         "detector's)")  # fmt: skip


def decode_boxes(centres: Tensor, box: Tensor, anchor: Tensor) -> Tensor:
    """Boxes ``[B, Z, Y, X, 6]`` (xmin..zmax) from regressions ``[B, 6, Z, Y, X]`` at cell centres ``[Z, Y, X, 3]``."""
    r = box.permute(0, 2, 3, 4, 1)
    c = centres + r[..., :3] * anchor
    s = anchor * torch.exp(r[..., 3:].clamp(max=4.0))
    return torch.cat([c - s / 2, c + s / 2], dim=-1)


def boxes_of_batch(boxes: dict[str, tuple[np.ndarray, np.ndarray]], files: list[str], scene_index: Tensor,
                   missing_message: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """``boxes[files[i]]`` for each ``i`` of ``scene_index``; ``ValueError`` of ``missing_message`` followed by the
    first scene file it has no entry for."""
    names = [files[int(i)] for i in scene_index.reshape(-1)]
    missing = [n for n in names if n not in boxes]
    if missing:
        raise ValueError(f"{missing_message}{missing[0]}")
    return [boxes[n] for n in names]


class Detector(SplitEvaluation, EncoderStage):
    """3D detector on the shared encoder's feature grid.

    Args:
        freeze_encoder: keep the encoder fixed.
        **kwargs: the encoder's other arguments, by keyword (:class:`~threedq.stages.base.EncoderStage`).
        anchor_size: ``(sx, sy, sz)`` metres, every cell's anchor (``None``: a loaded checkpoint's, else the median
            extent of the training boxes at least ``min_box_height`` tall).
        min_box_height: metres; lower training boxes give no positives, their region ignored (None: half a voxel).
        channels: residual-block width.
        num_blocks: residual blocks.
        inner_fraction: target assignment's inner part of a box (see :func:`detection_targets`).
        negative_margin: target assignment's margin around a box, metres (see :func:`detection_targets`).
        box_weight: weight of the box-regression loss.
        score_threshold: objectness kept as detections handed on.
        eval_score_threshold: objectness kept for the mAP.
        nms_iou: 3D NMS IoU threshold.
        nms_iomin: 3D NMS threshold on intersection over the smaller box (1 = off).
        max_detections: detections per scene, after NMS.
        refine_iou: a detection takes the pseudo-box of ``refine_to`` it overlaps this much, then NMS again (0: off).
        flat_boxes: with ``refine_iou > 0``, add the pseudo-boxes of ``refine_to`` below ``min_box_height`` that no
            box hits.
        refine_to: the pseudo-boxes a detection is refined against: ``"input"``, those of the views the detector
            reads; ``"scene"``, the DataModule's ``pseudo_boxes(split)``, fused over every view of the scene (a
            departure from the paper's single-view detection: the boxes then use views the detector does not read).
        lr: Adam learning rate.
        image_every_n_steps: write a detections PNG at validation when this many steps have passed (0: never).

    Convention: frame R metres, z up; boxes axis-aligned ``(xmin, ymin, zmin, xmax, ymax, zmax)``.
    """

    def __init__(
        self, *, freeze_encoder: bool = True, anchor_size: tuple[float, float, float] | None = None,
        channels: PositiveInt = 32, num_blocks: PositiveInt = 3, inner_fraction: UnitFraction = 0.5,
        negative_margin: float = 0.1, box_weight: float = 1.0, score_threshold: ClosedUnitInterval = 0.9,
        eval_score_threshold: ClosedUnitInterval = 0.05, nms_iou: ClosedUnitInterval = 0.1,
        nms_iomin: ClosedUnitInterval = 0.3, max_detections: PositiveInt = 16, refine_iou: ClosedUnitInterval = 0.1,
        flat_boxes: bool = True, refine_to: Literal["input", "scene"] = "input", lr: float = 1e-3,
        image_every_n_steps: int = 200, min_box_height: float | None = None, **kwargs: Any,
    ) -> None:
        super().__init__(freeze_encoder=freeze_encoder, **kwargs)
        if anchor_size is not None and (len(anchor_size) != 3
                                        or not all(math.isfinite(a) and a > 0 for a in anchor_size)):
            raise ValueError(f"anchor_size: expected 3 positive sizes (metres) or null, got {anchor_size}")
        if min_box_height is not None and not (math.isfinite(min_box_height) and min_box_height >= 0):
            raise ValueError(f"min_box_height: expected a size >= 0 (metres) or null, got {min_box_height}")
        self.save_hyperparameters()
        self.head = DetectorHead(self.feature_dim, channels, num_blocks)
        fg = self.feature_grid
        self.min_box_height = fg.voxel_size[2] / 2 if min_box_height is None else float(min_box_height)
        # None: taken from a loaded checkpoint or the training boxes; a buffer, so the checkpoint carries it
        self._anchor_explicit = anchor_size is not None
        self._anchor_known = anchor_size is not None
        self.register_buffer("anchor", torch.tensor(anchor_size or (1.0, 1.0, 1.0), dtype=torch.float32))
        cell = torch.tensor(fg.voxel_size, dtype=torch.float32) * 2
        shape = tuple(n // 2 for n in fg.volume_shape)  # (Z, Y, X) after the stride-2 layer
        origin = torch.tensor(fg.bounds_min, dtype=torch.float32)
        self.register_buffer("centres", cell_centres(origin, cell, shape), persistent=False)
        self.val_map = DetectionMAP(iou_thresholds=(0.25, 0.5))
        self.test_map = DetectionMAP(iou_thresholds=(0.25, 0.5))
        self._last_image_step = -1
        self._scene_boxes: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}

    def on_fit_start(self) -> None:
        """Take a ``None`` ``anchor_size`` that no checkpoint gave from the DataModule's training boxes."""
        super().on_fit_start()
        if not self._anchor_known:
            dm = getattr(self.trainer, "datamodule", None)
            if dm is None or not hasattr(dm, "box_extents") or not hasattr(dm, "describe_boxes"):
                raise ValueError("anchor_size: null takes the median size of the training boxes, which needs a "
                                 "scene-folder DataModule; set model.init_args.anchor_size")  # fmt: skip
            self.set_anchor_from_boxes(dm.box_extents("train"), dm.describe_boxes("train"))

    def set_anchor_from_boxes(self, extents: np.ndarray, source: str) -> None:
        """Set the anchor to the per-axis median of the ``extents`` ``[N, 3]`` (x, y, z; metres) at least
        ``min_box_height`` tall; ``source`` is named in the error when none is."""
        ext = np.asarray(extents, dtype=np.float64).reshape(-1, 3)
        ext = ext[np.isfinite(ext).all(1) & (ext > 0).all(1) & (ext[:, 2] >= self.min_box_height)]
        if len(ext) == 0:
            raise ValueError(f"{source}: anchor_size: null takes the median size of the training boxes at least "
                             f"min_box_height={self.min_box_height:g} m tall, and there are none (of {len(extents)}); "
                             "set model.init_args.anchor_size, or lower model.init_args.min_box_height (the detector "
                             "learns no object from boxes below it)")  # fmt: skip
        anchor = tuple(round(float(a), 4) for a in np.median(ext, axis=0))
        self._set_anchor(anchor)
        rank_zero_info(f"anchor_size: {list(anchor)} m, the median of {len(ext)} training boxes of {source}")

    def _set_anchor(self, anchor: Any) -> None:
        self.anchor.copy_(torch.tensor([float(a) for a in anchor], dtype=torch.float32))  # saved with the checkpoint
        self._anchor_known = True

    @property
    def anchor_size(self) -> tuple[float, float, float] | None:
        """The anchor this detector decodes with, to the micrometre (``None`` until known)."""
        return tuple(round(float(a), 6) for a in self.anchor.tolist()) if self._anchor_known else None

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """A loaded detector decodes with the anchor it was trained with: adopt the checkpoint's when this stage's
        was ``None``; refuse a different explicit one."""
        super().on_load_checkpoint(checkpoint)
        state = checkpoint.get("state_dict")
        buf = state.get("anchor") if isinstance(state, dict) else None
        hparams = checkpoint.get("hyper_parameters") or {}
        trained = buf.tolist() if isinstance(buf, torch.Tensor) else hparams.get("anchor_size")
        if trained is None:
            return
        if self._anchor_explicit:
            check_same_anchor(trained, self.anchor_size, "checkpoint")
        self._set_anchor(trained)
        if isinstance(state, dict) and buf is None:  # written before the anchor was a buffer: its hparams held it
            state["anchor"] = self.anchor.detach().clone()

    def _check_anchor(self) -> None:
        if not self._anchor_known:
            raise RuntimeError("anchor_size is null and was never taken from training boxes: run the stage through "
                               "a Trainer with a scene-folder DataModule, or set anchor_size")  # fmt: skip

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        """Objectness logits ``[B, Z, Y, X]`` and box regressions ``[B, 6, Z, Y, X]`` of a batch."""
        v = self.input_views(batch)
        with torch.no_grad() if self.freeze_encoder else contextlib.nullcontext():
            feats = self.encode_views(*(batch[k][:, :v] for k in ("rgb", "depth", "K", "R_T_cam")))
        return self.head(feats)

    def loss(self, logits: Tensor, box: Tensor, aabb: Tensor, mask: Tensor) -> dict[str, Tensor]:
        self._check_anchor()
        label, target, _ = detection_targets(self.centres, aabb, mask, self.anchor, self.hparams.inner_fraction,
                                             self.hparams.negative_margin, self.min_box_height)
        return self.loss_from_targets(logits, box, label, target)

    def loss_from_targets(self, logits: Tensor, box: Tensor, label: Tensor, target: Tensor) -> dict[str, Tensor]:
        """Class-balanced objectness loss over the labelled cells (``label`` 1 / 0; -1 ignored) + smooth L1 of the
        positives' boxes. Shapes: logits and label ``[B, Z, Y, X]``, box and target ``[B, 6, Z, Y, X]``."""
        pos, neg = label == 1, label == 0
        bce = F.binary_cross_entropy_with_logits(logits, (label == 1).to(logits.dtype), reduction="none")
        obj = bce[neg].mean() if neg.any() else logits.sum() * 0
        if pos.any():
            obj = obj + bce[pos].mean()
            reg = F.smooth_l1_loss(box.permute(0, 2, 3, 4, 1)[pos], target.permute(0, 2, 3, 4, 1)[pos], beta=0.1)
        else:
            reg = box.sum() * 0
        return {"loss": obj + self.hparams.box_weight * reg, "obj_loss": obj, "box_loss": reg, "num_pos": pos.sum(),
                "num_neg": neg.sum()}

    def input_of(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """The input views of a batch: ``depth [B, V, H, W]``, ``K [B, V, 3, 3]``, ``R_T_cam [B, V, 4, 4]``."""
        v = self.input_views(batch)
        return batch["depth"][:, :v], batch["K"][:, :v], batch["R_T_cam"][:, :v]

    @torch.no_grad()
    def detect(self, logits: Tensor, box: Tensor, score_threshold: float | None = None,
               views: tuple[Tensor, Tensor, Tensor] | None = None,
               targets: list[tuple[np.ndarray, np.ndarray]] | None = None) -> list[dict[str, Tensor]]:
        """Per scene ``{"boxes": [P, 6], "scores": [P]}`` after thresholding and 3D NMS; with ``refine_iou > 0``,
        refined against the pseudo-boxes of the input ``views`` (:meth:`input_of`), or against per scene
        ``targets`` ``(aabb [Q, 6], scores [Q])`` when given (:meth:`scene_targets`)."""
        self._check_anchor()
        thr = self.hparams.score_threshold if score_threshold is None else score_threshold
        scores = torch.sigmoid(logits.float()).flatten(1)
        boxes = decode_boxes(self.centres, box.float(), self.anchor).flatten(1, 3)
        refine = (views is not None or targets is not None) and self.hparams.refine_iou > 0
        fg = self.feature_grid
        out = []
        for i, (s, b) in enumerate(zip(scores, boxes)):
            keep = s >= thr
            s, b = s[keep], b[keep]
            if s.shape[0] > PRE_NMS_TOP_K:  # the highest-scoring ones, in their cell order (NMS's order of ties)
                top = torch.topk(s, PRE_NMS_TOP_K).indices.sort().values
                s, b = s[top], b[top]
            k = nms_3d(b, s, self.hparams.nms_iou, self.hparams.nms_iomin)[: self.hparams.max_detections]
            b, s = b[k], s[k]
            if refine:
                if targets is None:
                    obs, obs_s = observed_boxes(views[0][i], views[1][i], views[2][i], (fg.bounds_min, fg.bounds_max))
                else:
                    obs, obs_s = targets[i]
                obs = torch.as_tensor(obs, dtype=torch.float32).reshape(-1, 6).to(b.device)
                obs_s = torch.as_tensor(obs_s, dtype=torch.float32).reshape(-1).to(b.device)
                if b.shape[0]:
                    b, s, _ = refine_boxes(b, s, obs, self.hparams.refine_iou, self.hparams.nms_iou,
                                           self.hparams.nms_iomin)  # fmt: skip
                if self.hparams.flat_boxes:
                    b, s = add_flat_boxes(b, s, obs, obs_s, self.min_box_height, self.hparams.score_threshold, thr,
                                          self.hparams.nms_iou)  # fmt: skip
                    b, s = b[: self.hparams.max_detections], s[: self.hparams.max_detections]
            out.append({"boxes": b, "scores": s})
        return out

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        logits, box = self(batch)
        r = self.loss(logits, box, batch["aabb"], batch["box_mask"])
        self.log_dict({"train/loss": r["loss"], "train/obj_loss": r["obj_loss"], "train/box_loss": r["box_loss"]},
                      prog_bar=True, batch_size=logits.shape[0])
        return r["loss"]

    def scene_targets(self, batch: dict[str, Tensor], split: str, files: list[str] | None = None,
                      ) -> list[tuple[np.ndarray, np.ndarray]] | None:  # fmt: skip
        """With ``refine_to: scene``, the batch's scenes' pseudo-boxes fused over all their views (the trainer's
        DataModule's ``pseudo_boxes(split)``; ``files``: the scene files ``batch["scene_index"]`` indexes, default the
        trainer's ``split`` loader's); else ``None``."""
        if self.hparams.refine_to != "scene":
            return None
        dm = getattr(self._trainer, "datamodule", None) if self._trainer is not None else None
        if split not in self._scene_boxes:
            if dm is None or not callable(getattr(dm, "pseudo_boxes", None)):
                raise ValueError(f"refine_to: 'scene' refines against the DataModule's pseudo_boxes(split), which "
                                 f"needs a scene-folder DataModule; got {type(dm).__name__}; set refine_to: input")
            self._scene_boxes[split] = dm.pseudo_boxes(split)
        if files is None:
            loader = self.trainer.test_dataloaders if split == "test" else self.trainer.val_dataloaders
            files = getattr(getattr(loader, "dataset", None), "files", None)
            if files is None:
                raise ValueError(f"refine_to: 'scene': the {split} loader's dataset names no scene files (.files)")
        return boxes_of_batch(self._scene_boxes[split], files, batch["scene_index"],
                              f"refine_to: 'scene': the {split} split's pseudo-boxes have no entry for ")

    def _eval_step(self, batch: dict[str, Tensor], split: str, batch_idx: int) -> None:
        logits, box = self(batch)
        r = self.loss(logits, box, batch["gt_aabb"], batch["gt_mask"])
        self.log(f"{split}/loss", r["loss"], batch_size=logits.shape[0], sync_dist=True)
        views = self.input_of(batch)
        snap = self.scene_targets(batch, split)
        dets = self.detect(logits, box, self.hparams.eval_score_threshold, views, snap)
        targets = [{"boxes": a[m]} for a, m in zip(batch["gt_aabb"], batch["gt_mask"])]
        getattr(self, f"{split}_map").update(dets, targets)
        every = self.hparams.image_every_n_steps
        if batch_idx == 0 and every and split == "val" and self.global_step - self._last_image_step >= every:
            self._last_image_step = self.global_step
            self._write_image(batch, self.detect(logits, box, views=views, targets=snap), "val")

    def _eval_epoch_end(self, split: str) -> None:
        metric = getattr(self, f"{split}_map")
        res = metric.compute()
        self.log_dict({f"{split}/map_25": res["map_25"], f"{split}/map_50": res["map_50"]}, prog_bar=True)
        self.log_dict({f"{split}/num_gt": float(res["num_gt"]), f"{split}/num_det": float(res["num_det"])})
        metric.reset()

    def predict_step(self, batch: dict[str, Tensor], batch_idx: int) -> list[dict[str, Tensor]]:
        logits, box = self(batch)
        return self.detect(logits, box, views=self.input_of(batch))

    def _write_image(self, batch: dict[str, Tensor], dets: list[dict[str, Tensor]], tag: str) -> None:
        if self.trainer is None or not self.trainer.is_global_zero or self.trainer.sanity_checking:
            return
        write_png(self.run_dir / "images" / f"{tag}_detections_step{self.global_step:06d}.png",
                  detection_figure(batch, dets, max_scenes=2))


