"""Detector self-labelling (paper Sec. 3.4; supplement "3D object detection supervised by prototypes distance and
center-surround score").

The previous round's detector runs over ``pool_scenes`` training scenes on the round's frozen encoder; each box above
``candidate_threshold`` is cut to a ``crop_size^3`` feature crop and labelled without annotations: **positive** when
its best cosine over the round's prototypes x ``num_angles`` yaws exceeds ``positive_threshold``; **negative** when
its center-surround similarity (:func:`center_surround_similarity`) exceeds ``negative_threshold`` (this wins over
positive); ignored otherwise. The head (encoder frozen) is then fine-tuned with the loss confined to the labelled
regions (:func:`self_label_targets`). Switches beyond the paper (off = the paper): ``snap_to_proposals``,
``surround_negatives``, ``proposal_positives``, ``spare_proposals``. The labels are buffers (``labels``,
``labelled``), so a resumed run trains on the same labels; the pool's feature grids are computed once and each step
draws ``batch_size`` of them (the loader's batch is not used).

Diagnostics (GT used for measuring only): ``self_labels/labels.json`` and ``self_labels/labels.png``.

Convention: frame R metres, z up; boxes axis-aligned ``(xmin, ymin, zmin, xmax, ymax, zmax)``; volumes
``[B, C, Z, Y, X]``.
"""

from __future__ import annotations

import inspect
import json
import time
from pathlib import Path
from typing import Any, Literal

import torch
import torch.nn.functional as F
from jsonargparse.typing import ClosedUnitInterval, NonNegativeFloat, PositiveInt

from threedq.argtypes import Cosine
from torch import Tensor
from torch.utils.data import default_collate
from tqdm import tqdm

from threedq.atomic_io import atomic_write_text
from threedq.boxes import aabb_iou_3d
from threedq.geometry import VoxelGridSpec, crop_boxes
from threedq.metrics.detection import assign_detections
from threedq.quantization.prototypes import PrototypeBank, prototype_crops
from threedq.stages.checkpoint import checkpoint_hparams, load_checkpoint
from threedq.stages.base import builtin_number
from threedq.stages.detector import Detector, check_same_anchor, detection_targets
from threedq.stages.quantizer import bank_occupancy_floor, load_bank_state
from threedq.viz.detection import self_labels_figure
from threedq.viz.png import write_png

__all__ = ["INHERITED_FROM_DETECTOR", "SelfLabelling", "center_surround_similarity", "load_head_state",
           "self_label_targets"]


#: face-adjacent neighbour directions (x, y, z order), in units of the box's extent
_FACES = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=torch.float32)


def center_surround_similarity(grid: Tensor, aabb: Tensor, spec: VoxelGridSpec, size: int = 16) -> Tensor:
    """Mean cosine between each box's crop and those of its six face-adjacent neighbours (the box shifted by its own
    extent along +-x, +-y, +-z) whose centre lies inside the grid; crops flattened and L2-normalised.

    Args:
        grid: ``[B, C, Z, Y, X]`` feature volume on ``spec``.
        aabb: ``[B, N, 6]`` boxes ``(xmin, ymin, zmin, xmax, ymax, zmax)``.
        spec: the grid of ``grid``.
        size: crops are ``size^3``.

    Returns:
        ``[B, N]`` similarity in [-1, 1] (NaN where no neighbour is inside the grid).

    Convention: frame R metres; boxes axis-aligned.
    """
    if aabb.ndim != 3 or aabb.shape[-1] != 6 or aabb.shape[0] != grid.shape[0]:
        raise ValueError(f"aabb: expected [B, N, 6] with B = {grid.shape[0]}, got {tuple(aabb.shape)}")
    B, N = aabb.shape[:2]
    if N == 0:
        return aabb.new_zeros(B, 0)
    ext = aabb[..., 3:] - aabb[..., :3]  # [B, N, 3]
    shift = _FACES.to(aabb)[None, :, None] * ext[:, None]  # [B, 6, N, 3]
    moved = aabb[:, None] + shift.repeat(1, 1, 1, 2)  # [B, 6, N, 6]
    boxes = torch.cat([aabb, moved.reshape(B, 6 * N, 6)], dim=1)  # [B, 7N, 6]
    crops = crop_boxes(grid, boxes.to(grid.dtype), spec, size).flatten(2)
    crops = F.normalize(crops.to(torch.promote_types(crops.dtype, torch.float32)), dim=-1, eps=1e-8)
    centre, around = crops[:, :N], crops[:, N:].view(B, 6, N, -1)
    cos = (around * centre[:, None]).sum(-1)  # [B, 6, N]
    ctr = (moved[..., :3] + moved[..., 3:]) / 2
    lo, hi = (torch.tensor(b, dtype=ctr.dtype, device=ctr.device) for b in (spec.bounds_min, spec.bounds_max))
    inside = ((ctr >= lo) & (ctr <= hi)).all(-1)  # [B, 6, N]
    n = inside.sum(1)
    mean = (cos * inside).sum(1) / n.clamp_min(1)
    return torch.where(n > 0, mean, torch.full_like(mean, float("nan")))


def self_label_targets(
    centres: Tensor, pos_aabb: Tensor, pos_mask: Tensor, neg_aabb: Tensor, neg_mask: Tensor, anchor: Tensor,
    inner_fraction: float = 0.5, negative_margin: float = 0.1, surround: float = 0.0, min_height: float = 0.0,
    spare_aabb: Tensor | None = None, spare_mask: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Objectness labels and box targets confined to the union of the positive and negative regions: positive boxes
    label cells as :func:`~threedq.stages.detector.detection_targets` does; a cell inside a negative box (or the
    ``surround`` shell of a positive box) and near no positive box is negative, unless inside a spared box; every
    other cell is ignored (-1).

    Args:
        centres: ``[Z, Y, X, 3]`` cell centres (x, y, z), metres.
        pos_aabb: ``[B, P, 6]`` positive boxes, pos_mask ``[B, P]``; neg_aabb ``[B, Q, 6]``, neg_mask ``[B, Q]``.
        anchor, inner_fraction, negative_margin: as in :func:`~threedq.stages.detector.detection_targets`.
        surround: width of the negative shell around each positive box, in units of its extent (0: none).
        min_height: positive boxes less tall than this give no positives (as in ``detection_targets``).
        spare_aabb: ``[B, S, 6]`` spared boxes, spare_mask ``[B, S]`` (None: none).

    Returns:
        ``label`` ``[B, Z, Y, X]`` (1 positive, 0 negative, -1 ignored) and ``target`` ``[B, 6, Z, Y, X]``.

    Convention: frame R metres; x, y, z order inside the last dimensions.
    """
    label, target, _ = detection_targets(centres, pos_aabb, pos_mask, anchor, inner_fraction, negative_margin,
                                         min_height)
    B = label.shape[0]
    p = centres.reshape(1, 1, -1, 3)

    def inside(aabb: Tensor, mask: Tensor, pad: Tensor | float = 0.0) -> Tensor:  # [B, Z, Y, X]: inside any box
        lo, hi = aabb[..., None, :3] - pad, aabb[..., None, 3:] + pad
        return (((p >= lo) & (p <= hi)).all(-1) & mask[..., None]).any(1).view(B, *label.shape[1:])

    in_neg = inside(neg_aabb, neg_mask)
    if surround > 0:  # the shell around each positive box
        in_neg = in_neg | inside(pos_aabb, pos_mask, ((pos_aabb[..., 3:] - pos_aabb[..., :3]) * surround)[..., None, :])
    if spare_aabb is not None and spare_mask is not None and spare_aabb.shape[1]:
        in_neg = in_neg & ~inside(spare_aabb, spare_mask)
    label = torch.where((label == 0) & ~in_neg, torch.full_like(label, -1.0), label)
    return label, target


def load_head_state(head: torch.nn.Module, path: str | Path, anchor_size: Any = None) -> None:
    """Load the ``head.*`` weights of a detector (or self-labelling) checkpoint into ``head``; with ``anchor_size``,
    refuse a checkpoint whose anchor differs (one that holds none is not checked)."""
    if anchor_size is not None:
        trained = load_checkpoint(path).anchor
        if trained is not None:
            check_same_anchor(trained, anchor_size, str(path))
    state = load_checkpoint(path).prefixed("head.")
    if not state:
        raise ValueError(f"{path}: field 'state_dict': no 'head.*' weights (not a detector checkpoint?)")
    try:
        head.load_state_dict(state)
    except RuntimeError as e:
        raise ValueError(f"{path}: field 'state_dict': the detector head does not fit this stage: {e}") from None


#: What a self-labelled detector takes from the detector checkpoint it fine-tunes unless given.
INHERITED_FROM_DETECTOR: tuple[str, ...] = ("anchor_size", "channels", "num_blocks", "score_threshold",
                                            "eval_score_threshold", "nms_iou", "nms_iomin", "max_detections",
                                            "refine_iou", "flat_boxes", "refine_to")


class SelfLabelling(Detector):
    """Fine-tune a detector on labels from the prototypes and the center-surround score (see module docstring).

    Args:
        detector_ckpt: the detector to start from (its head; what is not given of :data:`INHERITED_FROM_DETECTOR`).
        bank_ckpt: the quantizer checkpoint whose prototype bank scores the candidates (and its ``occupancy_floor``).
        positive_threshold: best prototype cosine (over all prototypes and yaws) above which a box is positive.
        negative_threshold: center-surround similarity above which a box is negative.
        candidate_threshold: objectness of the detections that are labelled.
        pool_scenes: training scenes labelled (all of a smaller split).
        crop_size: crops are ``crop_size^3`` (the bank's).
        num_angles: yaw steps of the prototype search.
        search_method: ``"fast"`` or ``"exact"`` rotation search.
        batch_size: pool scenes per training step.
        seed: seed of the pool draw and of the step's scene draws.
        surround_crop_size: crop size of the center-surround score.
        snap_to_proposals: > 0: a positive must overlap a label-free pseudo-box at this IoU and takes its box.
        surround_negatives: width of the negative shell around each positive box, in box extents (0: none).
        spare_proposals: no cell inside a label-free pseudo-box is a negative.
        proposal_positives: every label-free pseudo-box of a pool scene is a positive too.
        freeze_encoder: must stay True.
        lr: Adam learning rate of the head.
        image_every_n_steps: as the detector's (0: no pictures).
        anchor_size: as the :class:`~threedq.stages.detector.Detector`'s (None: ``detector_ckpt``'s; another: refused).
        channels: as the Detector's (None: ``detector_ckpt``'s).
        num_blocks: as the Detector's (None: ``detector_ckpt``'s).
        score_threshold: as the Detector's (None: ``detector_ckpt``'s).
        eval_score_threshold: as the Detector's (None: ``detector_ckpt``'s).
        nms_iou: as the Detector's (None: ``detector_ckpt``'s).
        nms_iomin: as the Detector's (None: ``detector_ckpt``'s).
        max_detections: as the Detector's (None: ``detector_ckpt``'s).
        refine_iou: as the Detector's (None: ``detector_ckpt``'s).
        flat_boxes: as the Detector's (None: ``detector_ckpt``'s).
        refine_to: as the Detector's (None: ``detector_ckpt``'s).
        **kwargs: the :class:`~threedq.stages.detector.Detector`'s other arguments and the encoder's, by keyword.
    """

    def __init__(
        self, *, detector_ckpt: str | None = None, bank_ckpt: str | None = None, positive_threshold: Cosine = 0.8,
        negative_threshold: Cosine = 0.65, candidate_threshold: ClosedUnitInterval = 0.5,
        pool_scenes: PositiveInt = 1000, crop_size: PositiveInt = 16, num_angles: PositiveInt = 36,
        search_method: Literal["fast", "exact"] = "fast", batch_size: PositiveInt = 8, seed: int = 0,
        surround_crop_size: PositiveInt = 8, snap_to_proposals: ClosedUnitInterval = 0.3,
        surround_negatives: NonNegativeFloat = 0.5, spare_proposals: bool = True, proposal_positives: bool = True,
        freeze_encoder: bool = True, lr: float = 1e-4, image_every_n_steps: int = 0,
        anchor_size: tuple[float, float, float] | None = None, channels: int | None = None,
        num_blocks: int | None = None, score_threshold: ClosedUnitInterval | None = None,
        eval_score_threshold: ClosedUnitInterval | None = None, nms_iou: ClosedUnitInterval | None = None,
        nms_iomin: ClosedUnitInterval | None = None, max_detections: PositiveInt | None = None,
        refine_iou: ClosedUnitInterval | None = None, flat_boxes: bool | None = None,
        refine_to: Literal["input", "scene"] | None = None, **kwargs: Any,
    ) -> None:
        args = locals()
        given = {name: args[name] for name in INHERITED_FROM_DETECTOR}
        kwargs.update({k: v for k, v in given.items() if v is not None})
        given_decoding = {k for k, v in given.items() if v is not None}
        if not freeze_encoder:
            raise ValueError("freeze_encoder: self-labelling trains the detector head on a frozen encoder")
        asked_anchor = kwargs.get("anchor_size")  # an explicit anchor is checked against the detector's below
        if detector_ckpt:  # what is not given is the detector's: its anchor, head and decoding
            trained = {**checkpoint_hparams(detector_ckpt, missing_ok=True),
                       "anchor_size": load_checkpoint(detector_ckpt).anchor}  # its buffer (older files: hparams)
            for name in INHERITED_FROM_DETECTOR:
                if kwargs.get(name) is None and trained.get(name) is not None:
                    v = tuple(float(a) for a in trained[name]) if name == "anchor_size" else trained[name]
                    kwargs[name] = v
        super().__init__(freeze_encoder=freeze_encoder, lr=lr, image_every_n_steps=image_every_n_steps, **kwargs)
        self._given_decoding = given_decoding
        self.save_hyperparameters()
        # record what this detector decodes with (the arguments as given may be null)
        defaults = inspect.signature(Detector.__init__).parameters
        self.hparams.update({n: builtin_number(kwargs[n]) if n in kwargs else defaults[n].default
                             for n in INHERITED_FROM_DETECTOR})
        if detector_ckpt:
            load_head_state(self.head, detector_ckpt, asked_anchor)
        self.bank: PrototypeBank | None = None
        #: the bank's crop weighting (:func:`~threedq.quantization.prototypes.prototype_crops`)
        self.occupancy_floor: float | None = None
        if bank_ckpt:
            self.occupancy_floor = bank_occupancy_floor(bank_ckpt)
            num = load_checkpoint(bank_ckpt).prefixed("bank.").get("prototypes")
            if num is None:
                raise ValueError(f"{bank_ckpt}: field 'state_dict': no 'bank.prototypes' (not a quantizer checkpoint?)")
            self.bank = PrototypeBank(num.shape[0], self.feature_dim, crop_size, num_angles, method=search_method)
            load_bank_state(self.bank, bank_ckpt)
        # the labels: rows (pool position, kind 1 positive / 0 negative / 2 spared, aabb[6]); resized on load
        self.register_buffer("labels", torch.zeros(0, 8))
        self.register_buffer("labelled", torch.zeros((), dtype=torch.bool))
        self._pool_grids: Tensor | None = None
        self._pool_files: list[str] = []

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """The labels' size, and what was not given of the decoding from the checkpoint's hyperparameters (the anchor:
        :meth:`Detector.on_load_checkpoint`)."""
        super().on_load_checkpoint(checkpoint)
        saved = checkpoint.get("hyper_parameters") or {}
        for name in INHERITED_FROM_DETECTOR[3:]:  # the decoding (the anchor: Detector.on_load_checkpoint)
            if name not in self._given_decoding and saved.get(name) is not None:
                self.hparams[name] = saved[name]
        labels = checkpoint.get("state_dict", {}).get("labels")
        if labels is not None:
            self.labels = torch.zeros_like(labels)

    @property
    def _uses_proposals(self) -> bool:
        h = self.hparams
        return h.snap_to_proposals > 0 or bool(h.spare_proposals) or bool(h.proposal_positives)

    def _pool_dataset(self) -> Any:
        dm = getattr(self.trainer, "datamodule", None)
        if dm is None or not hasattr(dm, "fixed_view_dataset"):
            raise RuntimeError("self-labelling: needs a scene-folder DataModule (its train split is the pool)")
        return dm.fixed_view_dataset("train", with_boxes=False)

    @torch.no_grad()
    def _encode_pool(self) -> None:
        """Feature grids of the pool scenes (frozen encoder), and the labels if there are none yet."""
        ds = self._pool_dataset()
        g = torch.Generator().manual_seed(self.hparams.seed)
        order = torch.randperm(len(ds), generator=g)[: self.hparams.pool_scenes].tolist()
        label_now = not bool(self.labelled)
        t0 = time.time()
        grids, rows, diag_rows = [], [], []
        first: list[tuple[dict[str, Tensor], list[Tensor]]] = []
        was = self.head.training
        self.head.eval()
        bar = self.trainer.progress_bar_callback is not None
        proposals = None
        if self._uses_proposals:
            proposals = self.trainer.datamodule.pseudo_boxes("train", progress=bar)
        for start in tqdm(range(0, len(order), 8), desc="self-labelling pool", disable=not bar, leave=False):
            idx = order[start:start + 8]
            batch = self._to_device(default_collate([ds[j] for j in idx]))
            v = self.input_views(batch)
            # encoded under the trainer's precision (the crop cache's grids), labelled in fp32
            weighted = label_now and self.occupancy_floor is not None
            with self.precision_context():
                g, x = self._encode_views(*(batch[k][:, :v] for k in ("rgb", "depth", "K", "R_T_cam")),
                                          need_input=weighted)
            g = g.float()
            occ = x.view(g.shape[0], v, *x.shape[1:])[:, :, :1].amax(1).float() if weighted else None
            grids.append(g.to("cpu"))
            if label_now:
                props = None if proposals is None else [proposals[ds.files[j]][0] for j in idx]
                for b, (r, d) in enumerate(self._label_batch(g, batch, props, occ)):
                    rows.append(torch.cat([torch.full((len(r), 1), float(start + b)), r], dim=1))
                    diag_rows.append(d)
                    if len(first) < 4 and len(r):  # the picture shows positives and negatives
                        first.append(({k: batch[k][b] for k in ("rgb", "K", "R_T_cam")}, r[r[:, 0] < 2]))
        self.head.train(was)
        self._pool_grids = torch.cat(grids)
        self._pool_files = [ds.files[j] for j in order]
        if label_now:
            self.labels = torch.cat(rows).to(self.device) if rows else torch.zeros(0, 8, device=self.device)
            self.labelled.fill_(True)
            info = self._diagnostics(diag_rows, time.time() - t0)
            kinds = self.labels[:, 1]
            info["positive_boxes"], info["negative_boxes"] = int((kinds == 1).sum()), int((kinds == 0).sum())
            self.log_dict({f"self_labels/{k}": float(v) for k, v in info.items() if isinstance(v, (int, float))},
                          rank_zero_only=True)
            if self.trainer.is_global_zero:
                self._write_diagnostics(info, first)

    @torch.no_grad()
    def _label_batch(self, grid: Tensor, batch: dict[str, Tensor], proposals: list[Any] | None = None,
                     occupancy: Tensor | None = None) -> list[tuple[Tensor, dict[str, Tensor]]]:
        """Per scene: label rows ``[L, 7]`` (kind, aabb) and the candidates' measurements (for the diagnostics).

        ``proposals``: per scene the label-free pseudo-boxes ``[P, 6]``; ``occupancy``: ``[B, 1, Z, Y, X]`` the input
        occupancy (union over the input views), needed with an :attr:`occupancy_floor`.
        """
        if self.bank is None:
            raise RuntimeError("bank_ckpt: self-labelling needs the round's prototype bank")
        if self.occupancy_floor is not None and occupancy is None:
            raise ValueError("occupancy: the bank weights its crops by the input occupancy (occupancy_floor="
                             f"{self.occupancy_floor}) and none was given")
        logits, box = self.head(grid)
        dets = self.detect(logits, box, self.hparams.candidate_threshold)
        props = [None] * len(dets) if proposals is None else [
            torch.as_tensor(p, dtype=grid.dtype, device=grid.device).reshape(-1, 6) for p in proposals]
        counts = [d["boxes"].shape[0] for d in dets]
        proto_all: list[Tensor] = [grid.new_zeros(n) for n in counts]
        cs_all: list[Tensor] = [grid.new_zeros(n) for n in counts]
        if sum(counts):
            # each scene's boxes cropped on their own (no padding cropped)
            crops: list[Tensor] = []
            for b, d in enumerate(dets):
                if not counts[b]:
                    continue
                aabb = d["boxes"].to(grid.dtype)[None]
                c = crop_boxes(grid[b : b + 1], aabb, self.feature_grid, self.hparams.crop_size)[0]
                if self.occupancy_floor is not None:
                    occ = crop_boxes(occupancy[b : b + 1], aabb.to(occupancy.dtype), self.grid,
                                     self.hparams.crop_size)[0]
                    c = prototype_crops(c, occ, self.occupancy_floor)
                crops.append(c)
                cs_all[b] = center_surround_similarity(grid[b : b + 1], aabb, self.feature_grid,
                                                       self.hparams.surround_crop_size)[0]
            scores = self.bank.assign(torch.cat(crops).float()).score.to(torch.float32)
            proto_all = list(torch.split(scores, counts))
        out = []
        for b, d in enumerate(dets):
            aabb, n = d["boxes"], counts[b]
            proto, cs = proto_all[b], cs_all[b]
            neg = cs > self.hparams.negative_threshold  # NaN compares False: never negative
            pos = proto > self.hparams.positive_threshold
            pos &= ~neg
            if proposals is not None and self.hparams.snap_to_proposals > 0 and pos.any():
                pr = props[b].to(aabb.dtype)
                if len(pr):
                    best, j = aabb_iou_3d(aabb, pr).max(1)
                    snap = pos & (best >= self.hparams.snap_to_proposals)
                    aabb = torch.where(snap[:, None], pr[j], aabb)
                else:
                    snap = torch.zeros_like(pos)
                pos = snap  # a positive no pseudo-box supports is left unlabelled
            keep = pos | neg
            if self.hparams.proposal_positives and self.hparams.snap_to_proposals > 0 and proposals is not None:
                keep &= ~pos  # the positives are the pseudo-boxes (a snapped positive is one of them), added below
            rows = torch.cat([pos[keep, None].to(aabb.dtype), aabb[keep]], dim=1).cpu()
            if self.hparams.proposal_positives and proposals is not None and len(props[b]):
                pp = props[b].to(aabb.dtype)
                rows = torch.cat([torch.cat([pp.new_ones((len(pp), 1)), pp], dim=1).cpu(), rows])
            if self.hparams.spare_proposals and proposals is not None and len(props[b]):
                spare = props[b].to(aabb.dtype)
                rows = torch.cat([rows, torch.cat([spare.new_full((len(spare), 1), 2.0), spare], dim=1).cpu()])
            gt = batch["aabb"][b][batch["box_mask"][b]]
            m50 = assign_detections(aabb, d["scores"], gt, 0.5) >= 0 if n else torch.zeros(0, dtype=torch.bool)
            m25 = assign_detections(aabb, d["scores"], gt, 0.25) >= 0 if n else torch.zeros(0, dtype=torch.bool)
            out.append((rows, {"pos": pos.cpu(), "neg": neg.cpu(), "tp50": m50.cpu(), "tp25": m25.cpu(),
                               "proto": proto.cpu(), "cs": cs.cpu(), "num_gt": torch.tensor(gt.shape[0])}))
        return out

    def _diagnostics(self, rows: list[dict[str, Tensor]], seconds: float) -> dict[str, Any]:
        pos, neg, tp50, tp25 = (torch.cat([r[k] for r in rows]).bool() if rows else torch.zeros(0, dtype=torch.bool)
                                for k in ("pos", "neg", "tp50", "tp25"))
        n_gt = int(sum(int(r["num_gt"]) for r in rows))
        return {
            "scenes": len(rows), "candidates": int(pos.numel()),
            "candidate_threshold": self.hparams.candidate_threshold, "positives": int(pos.sum()),
            "negatives": int(neg.sum()), "ignored": int((~pos & ~neg).sum()), "gt_objects": n_gt,
            # GT used for measuring only
            "candidates_true_at_50": int(tp50.sum()),
            "positives_true_at_50": float(tp50[pos].float().mean()) if pos.any() else float("nan"),
            "negatives_false_at_25": float((~tp25[neg]).float().mean()) if neg.any() else float("nan"),
            "gt_recall_of_positives_at_50": float(tp50[pos].sum()) / max(n_gt, 1),
            "seconds": round(seconds, 1),
        }

    def _write_diagnostics(self, info: dict[str, Any], first: list[tuple[dict[str, Tensor], Tensor]]) -> None:
        out = self.run_dir / "self_labels"
        atomic_write_text(out / "labels.json", json.dumps(info, indent=1) + "\n")
        if first:
            write_png(out / "labels.png", self_labels_figure(first))

    def on_train_start(self) -> None:
        if self._pool_grids is None:
            self._encode_pool()

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        assert self._pool_grids is not None, "on_train_start encodes the pool"
        n = self._pool_grids.shape[0]
        g = torch.Generator().manual_seed(self.hparams.seed * 1_000_003 + int(self.global_step))
        pick = torch.randint(n, (self.hparams.batch_size,), generator=g)
        grids = self._pool_grids[pick].to(self.device)
        lab = self._batch_labels(pick)  # positive, negative and spared boxes, each with its mask
        logits, box = self.head(grids)
        hp = self.hparams
        label, target = self_label_targets(self.centres, *lab[:4], self.anchor, hp.inner_fraction, hp.negative_margin,
                                           hp.surround_negatives, self.min_box_height, *lab[4:])
        r = self.loss_from_targets(logits, box, label, target)
        self.log_dict({"train/loss": r["loss"], "train/obj_loss": r["obj_loss"], "train/box_loss": r["box_loss"],
                       "train/num_pos": r["num_pos"].float(), "train/num_neg": r["num_neg"].float()},
                      prog_bar=True, batch_size=len(pick))  # fmt: skip
        return r["loss"]

    def _batch_labels(self, pick: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Positive, negative and spared boxes (each ``[B, M, 6]`` and mask ``[B, M]``) of the picked pool scenes."""
        lab = self.labels
        out = []
        for kind in (1.0, 0.0, 2.0):
            per = [lab[(lab[:, 0] == float(i)) & (lab[:, 1] == kind), 2:] for i in pick.tolist()]
            m = max(1, max(len(p) for p in per))
            aabb = lab.new_zeros(len(per), m, 6)
            mask = torch.zeros(len(per), m, dtype=torch.bool, device=lab.device)
            for j, p in enumerate(per):
                aabb[j, : len(p)] = p
                mask[j, : len(p)] = True
            out += [aabb, mask]
        return out[0], out[1], out[2], out[3], out[4], out[5]


