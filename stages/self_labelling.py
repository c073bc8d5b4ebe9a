"""Detector self-labelling (paper Sec. 3.4; supplement "3D object detection supervised by prototypes distance and
center-surround score").

The detector of the previous round runs over a pool of ``pool_scenes`` training scenes on the round's (frozen)
encoder; each of its boxes above ``candidate_threshold`` is cut to a ``crop_size^3`` crop of the feature grid
and labelled without annotations:

* **positive** when its best cosine over all prototypes x ``num_angles`` yaws (the round's prototype bank,
  :meth:`~threedq.quantization.PrototypeBank.assign`) exceeds ``positive_threshold`` (paper: 0.8): it looks like
  an object the quantizer knows;
* **negative** when its center-surround similarity (:func:`center_surround_similarity`: the mean cosine of the
  crop with its six face-adjacent, equal-size neighbour crops) exceeds ``negative_threshold`` (paper: 0.65): a
  box that looks like its surroundings is not salient (floor, background);
* neither otherwise (ignored). A box above both thresholds is negative: the center-surround score vetoes
  background that happens to resemble a prototype (``docs/studies/detector.md``).

The detector head (encoder frozen) is then fine-tuned on these labels with the loss confined to the union of
the positive and negative regions (:func:`self_label_targets`): cells of a positive box are positives as in
the warm start (:func:`~threedq.stages.detector.detection_targets`), cells inside a negative box are negatives,
every other cell is ignored. Departures from the paper, each a switch (off = the paper; ``docs/studies/detector.md``):
positives must overlap a label-free pseudo-box and take its box (``snap_to_proposals``); the shell around each
positive box is negative (``surround_negatives``); every pseudo-box of a pool scene stays a positive, as in the warm
start, so the labels the prototypes and the center-surround score add are negatives and the positives they vouch for
(``proposal_positives``); no cell inside a pseudo-box is a negative, so a negative box or shell cutting into an
object is ignored there, not taught as background (``spare_proposals``). The labels are registered buffers
(``labels``, ``labelled``), so a resumed run trains on the same labels; the pool's feature grids are computed once
(the encoder is frozen) and every step draws ``batch_size`` of them, so a step costs a head pass, not an encoding
(the loader's batch is not used).

Diagnostics (GT boxes used for measuring only): ``self_labels/labels.json`` (counts; the share of positives
that match a GT object at IoU 0.5 and of negatives that match none at IoU 0.25) and
``self_labels/labels.png`` (the labelled boxes on a few pool scenes: positives green, negatives red).

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

__all__ = ["INHERITED_FROM_DETECTOR", "SelfLabelling", "center_surround_similarity", "load_head_state", "self_label_targets"]


#: face-adjacent neighbour directions (x, y, z order), in units of the box's extent
_FACES = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=torch.float32)


def center_surround_similarity(grid: Tensor, aabb: Tensor, spec: VoxelGridSpec, size: int = 16) -> Tensor:
    """Mean cosine between each box's crop and the crops of its six face-adjacent neighbours of equal size.

    A neighbour is the box shifted by its own extent along +-x, +-y or +-z. Each crop (``size^3`` cells,
    trilinear, :func:`~threedq.geometry.crop_boxes`) is flattened over channels and cells and L2-normalised;
    the score is the mean of the cosines with the neighbours whose centre lies inside the grid (a neighbour
    wholly outside carries no features). A box with no neighbour inside the grid scores NaN.

    Args:
        grid: ``[B, C, Z, Y, X]`` feature volume on ``spec``.
        aabb: ``[B, N, 6]`` boxes ``(xmin, ymin, zmin, xmax, ymax, zmax)``.
        spec: the grid of ``grid``.
        size: crop size.

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
    lo = torch.tensor(spec.bounds_min, dtype=ctr.dtype, device=ctr.device)
    hi = torch.tensor(spec.bounds_max, dtype=ctr.dtype, device=ctr.device)
    inside = ((ctr >= lo) & (ctr <= hi)).all(-1)  # [B, 6, N]
    n = inside.sum(1)
    mean = (cos * inside).sum(1) / n.clamp_min(1)
    return torch.where(n > 0, mean, torch.full_like(mean, float("nan")))


def self_label_targets(
    centres: Tensor, pos_aabb: Tensor, pos_mask: Tensor, neg_aabb: Tensor, neg_mask: Tensor, anchor: Tensor,
    inner_fraction: float = 0.5, negative_margin: float = 0.1, surround: float = 0.0, min_height: float = 0.0,
    spare_aabb: Tensor | None = None, spare_mask: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Objectness labels and box targets confined to the union of the positive and negative regions.

    Positive boxes label cells exactly as :func:`~threedq.stages.detector.detection_targets` does (inner cells
    positive with box targets, cells within ``negative_margin`` of a positive box ignored); a cell whose centre
    lies inside a negative box and near no positive box is negative, and so is one in the shell around a positive
    box (the box grown by ``surround`` times its extent on each side, minus the box and its ``negative_margin``);
    a cell inside a spared box is never negative (something geometric stands there that is not labelled
    positive); every other cell is ignored (-1).

    Args:
        centres: ``[Z, Y, X, 3]`` cell centres (x, y, z), metres.
        pos_aabb: ``[B, P, 6]`` positive boxes, pos_mask ``[B, P]``; neg_aabb ``[B, Q, 6]``, neg_mask ``[B, Q]``.
        anchor, inner_fraction, negative_margin: as in :func:`~threedq.stages.detector.detection_targets`.
        surround: width of the negative shell around each positive box, in units of its extent (0: none).
        min_height: positive boxes less tall than this give no positives (their region is ignored), as in
            :func:`~threedq.stages.detector.detection_targets`.
        spare_aabb: ``[B, S, 6]`` spared boxes, spare_mask ``[B, S]`` (None: none).

    Returns:
        ``label`` ``[B, Z, Y, X]`` (1 positive, 0 negative, -1 ignored) and ``target`` ``[B, 6, Z, Y, X]``.

    Convention: frame R metres; x, y, z order inside the last dimensions.
    """
    label, target, _ = detection_targets(centres, pos_aabb, pos_mask, anchor, inner_fraction, negative_margin, min_height)
    B = label.shape[0]
    p = centres.reshape(1, 1, -1, 3)
    in_neg = ((p >= neg_aabb[..., None, :3]) & (p <= neg_aabb[..., None, 3:])).all(-1) & neg_mask[..., None]
    in_neg = in_neg.any(1).view(B, *label.shape[1:])  # [B, Z, Y, X]
    if surround > 0:  # the shell around each positive box: what the objects stand out from
        ext = (pos_aabb[..., 3:] - pos_aabb[..., :3]) * surround
        lo, hi = pos_aabb[..., None, :3] - ext[..., None, :], pos_aabb[..., None, 3:] + ext[..., None, :]
        shell = ((p >= lo) & (p <= hi)).all(-1) & pos_mask[..., None]
        in_neg = in_neg | shell.any(1).view(B, *label.shape[1:])
    if spare_aabb is not None and spare_mask is not None and spare_aabb.shape[1]:
        spared = ((p >= spare_aabb[..., None, :3]) & (p <= spare_aabb[..., None, 3:])).all(-1) & spare_mask[..., None]
        in_neg = in_neg & ~spared.any(1).view(B, *label.shape[1:])
    label = torch.where((label == 0) & ~in_neg, torch.full_like(label, -1.0), label)
    return label, target


def load_head_state(head: torch.nn.Module, path: str | Path, anchor_size: Any = None) -> None:
    """Load the ``head.*`` weights of a detector (or self-labelling) checkpoint into ``head``.

    With ``anchor_size``, refuse a detector trained with another anchor (its boxes would decode at the wrong size),
    naming the checkpoint and the field; a checkpoint that holds no anchor (a bare state dict) is not checked.
    """
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
                                            "refine_iou", "flat_boxes")


class SelfLabelling(Detector):
    """Fine-tune a detector on labels from the prototypes and the center-surround score (see module docstring).

    Args:
        detector_ckpt: the detector to start from (its head; the warm start or the previous round's). What is not
            given of :data:`INHERITED_FROM_DETECTOR` (its anchor, head width and depth, score thresholds, NMS,
            detections per scene, box refinement) is taken from this checkpoint, so a self-labelled detector decodes
            as the detector it fine-tunes.
        bank_ckpt: the quantizer checkpoint whose prototype bank scores the candidates (the round's); its crops are
            weighted as that bank's were (the quantizer's ``occupancy_floor``).
        positive_threshold: best prototype cosine (over all prototypes and yaws) above which a box is positive
            (paper: 0.8).
        negative_threshold: center-surround similarity above which a box is negative (paper: 0.65).
        candidate_threshold: objectness of the detections that are labelled.
        pool_scenes: training scenes labelled (paper: 1000; all of a smaller split).
        crop_size: crops are ``crop_size^3`` (the bank's).
        num_angles: yaw steps of the prototype search (paper: 36).
        search_method: ``"fast"`` or ``"exact"`` rotation search.
        batch_size: pool scenes per training step.
        seed: seed of the pool draw and of the step's scene draws.
        surround_crop_size: crop size of the center-surround score (coarser than ``crop_size``: 7 crops per box).
        snap_to_proposals: when > 0, a positive must overlap a label-free pseudo-box (:mod:`threedq.proposals`,
            the warm start's labels: something standing on the ground plane) at IoU at least this, and takes that
            box; one that overlaps none is left unlabelled. 0 (the paper): positives keep the detector's own box.
        surround_negatives: cells in a shell this many box extents wide around each positive box are negatives
            (see :func:`self_label_targets`; 0, the paper: only the negative boxes' cells).
        spare_proposals: no cell inside a label-free pseudo-box is a negative (False, the paper: negative boxes label
            all their cells).
        proposal_positives: every label-free pseudo-box of a pool scene is a positive (the warm start's targets
            kept), beside the positives the prototypes vouch for; the detections then add negatives (False, the paper:
            only the detections the prototypes vouch for are positives).
        freeze_encoder: must stay True (the encoder is the round's, frozen).
        lr: Adam learning rate of the head (lower than the warm start's; docs/studies/detector.md).
        image_every_n_steps: as the detector's (0: no pictures).
        anchor_size, channels, num_blocks, score_threshold, eval_score_threshold, nms_iou, nms_iomin, max_detections,
            refine_iou, flat_boxes: as the :class:`~threedq.stages.detector.Detector`'s; None (the default): the value
            ``detector_ckpt`` was trained with (the Detector's default without a checkpoint). Given, they override
            it (an anchor other than the detector's is refused: the head's boxes would decode at another size).
        **kwargs: the :class:`~threedq.stages.detector.Detector`'s other arguments, by keyword, and the encoder's.
    """

    def __init__(
        self,
        *,
        detector_ckpt: str | None = None,
        bank_ckpt: str | None = None,
        positive_threshold: Cosine = 0.8,
        negative_threshold: Cosine = 0.65,
        candidate_threshold: ClosedUnitInterval = 0.5,
        pool_scenes: PositiveInt = 1000,
        crop_size: PositiveInt = 16,
        num_angles: PositiveInt = 36,
        search_method: Literal["fast", "exact"] = "fast",
        batch_size: PositiveInt = 8,
        seed: int = 0,
        surround_crop_size: PositiveInt = 8,
        snap_to_proposals: ClosedUnitInterval = 0.3,
        surround_negatives: NonNegativeFloat = 0.5,
        spare_proposals: bool = True,
        proposal_positives: bool = True,
        freeze_encoder: bool = True,
        lr: float = 1e-4,
        image_every_n_steps: int = 0,
        anchor_size: tuple[float, float, float] | None = None,
        channels: int | None = None,
        num_blocks: int | None = None,
        score_threshold: ClosedUnitInterval | None = None,
        eval_score_threshold: ClosedUnitInterval | None = None,
        nms_iou: ClosedUnitInterval | None = None,
        nms_iomin: ClosedUnitInterval | None = None,
        max_detections: PositiveInt | None = None,
        refine_iou: ClosedUnitInterval | None = None,
        flat_boxes: bool | None = None,
        **kwargs: Any,
    ) -> None:
        given = {"anchor_size": anchor_size, "channels": channels, "num_blocks": num_blocks,
                 "score_threshold": score_threshold, "eval_score_threshold": eval_score_threshold, "nms_iou": nms_iou,
                 "nms_iomin": nms_iomin, "max_detections": max_detections, "refine_iou": refine_iou,
                 "flat_boxes": flat_boxes}
        assert set(given) == set(INHERITED_FROM_DETECTOR)
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
        # save_hyperparameters records the arguments as given (under LightningCLI: the parsed config, where these
        # are null): record what this detector decodes with, or a fit would take a new anchor from its own training
        # boxes and decode the fine-tuned head at another size than it was trained for
        defaults = inspect.signature(Detector.__init__).parameters
        self.hparams.update({n: builtin_number(kwargs[n]) if n in kwargs else defaults[n].default
                             for n in INHERITED_FROM_DETECTOR})
        if detector_ckpt:
            load_head_state(self.head, detector_ckpt, asked_anchor)
        self.bank: PrototypeBank | None = None
        #: the bank's crop weighting (:func:`~threedq.quantization.prototypes.prototype_crops`), from its checkpoint
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

    # ------------------------------------------------------------------ checkpoint
    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """The labels' size, and what was not given of the decoding (thresholds, NMS, detections per scene,
        refinement) from the checkpoint's hyperparameters (the anchor: :meth:`Detector.on_load_checkpoint`), so a
        self-labelled checkpoint tested without its ``detector_ckpt`` decodes as it did when it was written."""
        super().on_load_checkpoint(checkpoint)
        saved = checkpoint.get("hyper_parameters") or {}
        for name in INHERITED_FROM_DETECTOR[3:]:  # the decoding (the anchor: Detector.on_load_checkpoint)
            if name not in self._given_decoding and saved.get(name) is not None:
                self.hparams[name] = saved[name]
        labels = checkpoint.get("state_dict", {}).get("labels")
        if labels is not None:
            self.labels = torch.zeros_like(labels)

    # ------------------------------------------------------------------ the pool
    @property
    def _uses_proposals(self) -> bool:
        h = self.hparams
        return h.snap_to_proposals > 0 or bool(h.spare_proposals) or bool(h.proposal_positives)

    def _pool_dataset(self) -> Any:
        dm = getattr(self.trainer, "datamodule", None)
        if dm is None or not hasattr(dm, "fixed_view_dataset"):
            raise RuntimeError("self-labelling: needs a scene-folder DataModule (its train split is the pool)")
        return dm.fixed_view_dataset("train", with_boxes=False)

    def _pool_order(self, n: int) -> list[int]:
        g = torch.Generator().manual_seed(self.hparams.seed)
        return torch.randperm(n, generator=g)[: self.hparams.pool_scenes].tolist()

    @torch.no_grad()
    def _encode_pool(self) -> None:
        """Feature grids of the pool scenes (frozen encoder), and the labels if there are none yet."""
        ds = self._pool_dataset()
        order = self._pool_order(len(ds))
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
            batch = {k: v.to(self.device) if isinstance(v, Tensor) else v for k, v in default_collate([ds[j] for j in idx]).items()}
            v = self.input_views(batch)
            # encoded under the trainer's precision, as training_step would (Lightning's autocast covers the steps, not
            # this hook): the grids then come from the crop cache the round's quantizer filled; labelled in fp32
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
            # the boxes the head trains on: with proposal_positives every pseudo-box is a positive
            info["positive_boxes"], info["negative_boxes"] = int((kinds == 1).sum()), int((kinds == 0).sum())
            self.log_dict({f"self_labels/{k}": float(v) for k, v in info.items() if isinstance(v, (int, float))},
                          rank_zero_only=True)
            if self.trainer.is_global_zero:
                self._write_diagnostics(info, first)

    @torch.no_grad()
    def _label_batch(self, grid: Tensor, batch: dict[str, Tensor], proposals: list[Any] | None = None,
                     occupancy: Tensor | None = None) -> list[tuple[Tensor, dict[str, Tensor]]]:
        """Per scene: label rows ``[L, 7]`` (kind, aabb) and the candidates' measurements (for the diagnostics).

        ``proposals``: per scene the label-free pseudo-boxes ``[P, 6]`` that positives snap to (``snap_to_proposals``),
        that are positives (``proposal_positives``) and whose cells are spared (``spare_proposals``).
        ``occupancy``: ``[B, 1, Z, Y, X]`` the input occupancy on the input grid (union over the input views); needed
        when the bank weights its crops by it (:attr:`occupancy_floor`).
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
            # each scene's boxes cropped on their own: a padded [B, most boxes] batch would crop the padding too
            # (the crops of the padding are work thrown away); every crop is the same either way
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
            # a box both like a prototype and like its surroundings is negative: the center-surround score decides
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
                pos = snap  # a positive nothing geometric supports (a shadow, a patch of floor) is left unlabelled
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
        cat = {k: torch.cat([r[k] for r in rows]) if rows else torch.zeros(0)
               for k in ("pos", "neg", "tp50", "tp25")}
        pos, neg = cat["pos"].bool(), cat["neg"].bool()
        tp50, tp25 = cat["tp50"].bool(), cat["tp25"].bool()
        n_gt = int(sum(int(r["num_gt"]) for r in rows))
        info: dict[str, Any] = {
            "scenes": len(rows),
            "candidates": int(pos.numel()),
            "candidate_threshold": self.hparams.candidate_threshold,
            "positives": int(pos.sum()),
            "negatives": int(neg.sum()),
            "ignored": int((~pos & ~neg).sum()),
            "gt_objects": n_gt,
            # GT used for measuring only
            "candidates_true_at_50": int(tp50.sum()),
            "positives_true_at_50": float(tp50[pos].float().mean()) if pos.any() else float("nan"),
            "negatives_false_at_25": float((~tp25[neg]).float().mean()) if neg.any() else float("nan"),
            "gt_recall_of_positives_at_50": float(tp50[pos].sum()) / max(n_gt, 1),
            "seconds": round(seconds, 1),
        }
        return info

    def _write_diagnostics(self, info: dict[str, Any], first: list[tuple[dict[str, Tensor], Tensor]]) -> None:
        out = self.run_dir / "self_labels"
        atomic_write_text(out / "labels.json", json.dumps(info, indent=1) + "\n")
        if first:
            write_png(out / "labels.png", self_labels_figure(first))

    # ------------------------------------------------------------------ training
    def on_train_start(self) -> None:
        if self._pool_grids is None:
            self._encode_pool()

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        assert self._pool_grids is not None, "on_train_start encodes the pool"
        n = self._pool_grids.shape[0]
        g = torch.Generator().manual_seed(self.hparams.seed * 1_000_003 + int(self.global_step))
        pick = torch.randint(n, (self.hparams.batch_size,), generator=g)
        grids = self._pool_grids[pick].to(self.device)
        pos_aabb, pos_mask, neg_aabb, neg_mask, spare_aabb, spare_mask = self._batch_labels(pick)
        logits, box = self.head(grids)
        label, target = self_label_targets(self.centres, pos_aabb, pos_mask, neg_aabb, neg_mask, self.anchor,
                                           self.hparams.inner_fraction, self.hparams.negative_margin,
                                           self.hparams.surround_negatives, self.min_box_height,
                                           spare_aabb, spare_mask)  # fmt: skip
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


