"""Correspondence learning (paper Sec. 3.3, Table 2): fine-tune the shared encoder by InfoNCE metric learning.

Three sources of positive pairs (``source``):

* ``vc`` (rgbocc+VC): the same point inside an object box seen through two disjoint view sets of one scene (the first
  ``num_input_views`` views and the next as many); in-batch negatives.
* ``vc_moco`` (rgbocc+VC*): the same pairs; the second view set goes through the momentum key encoder
  (``moco.encoder_k``), negatives from the queue (``moco.queue``, ``[Q, D]``).
* ``mined`` (supplement "3D correspondence mining"): every ``refresh_every`` steps a pool of ``target_pool`` object
  crops (``crop_size^3``, encoder in eval mode, float32, fixed input views, boxes vouched for by label-free
  pseudo-boxes) is cut; a pair source (:mod:`threedq.stages.pair_sources`) proposes pairs whose queries are the first
  ``query_pool`` crops; the ``keep`` best become positives (:mod:`threedq.stages.positives`). A training step draws
  ``pairs_per_step`` pairs, re-encodes their query scenes and takes InfoNCE of the query cells against their keys,
  with the queue (primed with pool voxels at the first refresh) as negatives.

Each refresh logs its diagnostics (GT categories and yaws used for measuring only) and writes
``mining/refresh_<step>.json`` and ``mining/refresh_<step>.png`` under the run's log folder.

Convention: frame R metres, z up; crops ``[N, C, Z, Y, X]``; yaw counter-clockwise seen from above, index ``b``
meaning ``2 pi b / num_angles``; the mined yaw rotates the TARGET crop onto the query.
"""

from __future__ import annotations

import copy
import json
import math
import time
from typing import Any, Literal

import torch
import torch.nn.functional as F
from jsonargparse.typing import ClosedUnitInterval, NonNegativeInt, OpenUnitInterval, PositiveInt
from torch import Tensor
from torch.utils.data import default_collate

from threedq.argtypes import UnitIoU
from threedq.atomic_io import atomic_write_text
from threedq.box_refinement import observed_boxes
from threedq.boxes import best_aabb_iou
from threedq.contrastive import MomentumContrast, calibrate_context_cosine
from threedq.geometry import crop_boxes, rotate_yaw
from threedq.metrics import RetrievalPrecisionAtK
from threedq.stages.base import EncoderStage, RetrievalEvaluation
from threedq.stages.pair_sources import FeaturePairs, InputPairs, PairSource, input_occupancy
from threedq.stages.positives import corner_offsets, crop_voxels, occupancy_positives, patch_positives
from threedq.viz.features import mined_pairs_figure
from threedq.viz.png import write_png

__all__ = ["Mining", "gt_box_iou", "implied_yaw_error_deg"]


def gt_box_iou(batch: dict[str, Any]) -> Tensor:
    """``[N]`` for the batch's valid boxes (``box_mask`` order): the highest 3D IoU with a GT box of its scene
    (``gt_aabb``/``gt_mask``; measuring only); NaN where the batch carries no GT boxes, 0 where the scene has none."""
    mask = batch["box_mask"]
    if "gt_aabb" not in batch or "gt_mask" not in batch:
        return torch.full((int(mask.sum()),), float("nan"), device=mask.device)
    gt, gt_mask = batch["gt_aabb"], batch["gt_mask"]
    return torch.cat([best_aabb_iou(batch["aabb"][i][mask[i]].float(), gt[i][gt_mask[i]].float())
                      for i in range(mask.shape[0])])


def implied_yaw_error_deg(yaw_index: Tensor, num_angles: int, query_yaw: Tensor, target_yaw: Tensor,
                          symmetry: Tensor) -> Tensor:
    """Error (degrees) of a mined yaw against GT: rotating the target by ``2 pi b / A`` should equal
    ``query_yaw - target_yaw``, modulo the category's symmetry ``2 pi / symmetry``.

    Args:
        yaw_index: ``[P]`` long mined yaw steps; query_yaw, target_yaw: ``[P]`` GT yaws (radians);
        symmetry: ``[P]`` long yaw symmetry order of the category (1 = asymmetric).

    Returns:
        ``[P]`` errors in ``[0, 180 / symmetry]`` degrees.
    """
    period = 2 * math.pi / symmetry.to(torch.float64)
    d = yaw_index.to(torch.float64) * (2 * math.pi / num_angles) - (query_yaw - target_yaw).to(torch.float64)
    d = torch.remainder(d, period)
    return torch.rad2deg(torch.minimum(d, period - d))


class Mining(RetrievalEvaluation, EncoderStage):
    """The correspondence-learning stage (``vc``, ``vc_moco`` or ``mined``; see the module docstring).

    Args:
        **kwargs: the encoder's arguments, by keyword (:class:`~threedq.stages.base.EncoderStage`; cannot be frozen).
        source: ``"vc"``, ``"vc_moco"`` or ``"mined"``.
        queue_size: MoCo negatives Q.
        momentum: MoCo key-encoder momentum.
        temperature: InfoNCE temperature.
        lr: Adam learning rate.
        crop_size: object crops are ``crop_size^3`` voxels.
        voxels_per_object: ``vc``/``vc_moco``: points sampled per object box.
        query_pool: ``mined``: query crops per refresh, the first of the pool; ``<= target_pool``.
        target_pool: ``mined``: crops cut per refresh; the targets are those of other scenes.
        keep: pairs kept per refresh.
        num_angles: yaw steps of every rotation search.
        candidates_from: the pair source: ``"input"`` (input occupancy and colour), ``"occupancy"`` or ``"features"``.
        occupancy_mutual_k: ``input``/``occupancy``: pairs are mutual ``k`` nearest neighbours of the pool.
        candidates_per_query: each query's best pairs (``None``: the ``keep`` best pairs overall).
        positives: ``"occupancy"`` (cells both objects occupy at the pair's yaw) or ``"patches"`` (``features`` only).
        top_k: ``features``: targets retrieved per query (:func:`~threedq.contrastive.mine_correspondences`).
        patch: ``features``: patch edge, voxels.
        search_grid: ``features``: grid positions per axis of the patch search (the miner's ``grid``).
        context_distance: ``features``: Manhattan distance of the context patches, voxels.
        min_score: ``features``: verification score a pair needs to be kept.
        yaw_window: ``features``: search the patch within this many yaw steps of the retrieval's (``None``: all).
        rank_by: ``features``: order of the verified pairs, ``"score"`` or ``"retrieval"``.
        min_cosine: the miner's context threshold (``None``: calibrated per refresh, see ``context_quantile``).
        context_quantile: quantile of random patch pairs' best cosine that calibrates ``min_cosine``.
        corner_offset: ``patches``: the corners of a ``2 * corner_offset`` cube around the match.
        corner_search: ``patches``: each corner's key is its best match within ``+-corner_search`` voxels.
        refresh_every: steps between pool refreshes (the first at step 0).
        pairs_per_step: mined pairs (query scenes encoded) per training step.
        pool_batch_size: scenes encoded at once while cutting the pool.
        pool_min_observed_iou: least 3D IoU of a pool box with a pseudo-box of its input views (``None``: off).
        pool_min_scene_iou: least 3D IoU with a pseudo-box fused over its training scene's views (``None``: off).
        round_lr: ``"constant"`` (``lr`` in every EM round) or ``"harmonic"`` (``lr / em_round``).
        em_round: the EM round this stage runs in (1 outside ``threedq em``).
        seed: seed of the pool draws (offset by the refresh count and the process rank).
        retrieval_k: K of the validation/test precision@K.
        symmetry_order: per category, its yaw symmetry order (diagnostics only; ``None``: not scored by symmetry).
    """

    def __init__(
        self, *, source: Literal["vc", "vc_moco", "mined"] = "mined", queue_size: PositiveInt = 100_000,
        momentum: ClosedUnitInterval = 0.999, temperature: float = 0.07, lr: float = 1e-4, crop_size: PositiveInt = 16,
        voxels_per_object: PositiveInt = 256, query_pool: PositiveInt = 256, target_pool: PositiveInt = 512,
        keep: PositiveInt = 200, num_angles: PositiveInt = 36,
        candidates_from: Literal["input", "occupancy", "features"] = "input", occupancy_mutual_k: PositiveInt = 10,
        candidates_per_query: PositiveInt | None = 2, positives: Literal["occupancy", "patches"] = "occupancy",
        top_k: PositiveInt = 30, patch: PositiveInt = 2, search_grid: PositiveInt = 4,
        context_distance: PositiveInt = 6, min_cosine: float | None = None, context_quantile: OpenUnitInterval = 0.95,
        min_score: ClosedUnitInterval = 0.5, yaw_window: NonNegativeInt | None = 1,
        rank_by: Literal["score", "retrieval"] = "retrieval", corner_offset: PositiveInt = 4,
        corner_search: NonNegativeInt = 1, refresh_every: PositiveInt = 100, pairs_per_step: PositiveInt = 4,
        pool_batch_size: PositiveInt = 4, pool_min_observed_iou: UnitIoU | None = 0.5,
        pool_min_scene_iou: UnitIoU | None = 0.7,
        round_lr: Literal["constant", "harmonic"] = "harmonic", em_round: PositiveInt = 1, seed: int = 0,
        retrieval_k: PositiveInt = 10, symmetry_order: list[int] | None = None, **kwargs: Any,
    ) -> None:
        if kwargs.get("freeze_encoder"):
            raise ValueError("freeze_encoder: the mining stage fine-tunes the encoder; it cannot be frozen")
        if query_pool > target_pool:
            raise ValueError(f"query_pool: the queries are the first query_pool of the target_pool crops, so "
                             f"query_pool ({query_pool}) must be <= target_pool ({target_pool})")
        if 2 * corner_offset > crop_size:
            raise ValueError(f"corner_offset: a cube of 2 * {corner_offset} voxels does not fit a crop of {crop_size}")
        if positives == "patches" and candidates_from != "features":
            raise ValueError(f"positives: 'patches' are the corners around the miner's patch matches; candidates_from "
                             f"{candidates_from!r} proposes pairs without them: use candidates_from: features or "
                             f"positives: occupancy")
        super().__init__(**kwargs)
        self.save_hyperparameters()
        self.moco = MomentumContrast(self.encoder, dim=self.feature_dim, queue_size=queue_size, momentum=momentum,
                                     temperature=temperature)
        self.register_buffer("queue_primed", torch.zeros((), dtype=torch.bool))
        self.register_buffer("refreshes", torch.zeros((), dtype=torch.long))
        self.metrics = torch.nn.ModuleDict({s: RetrievalPrecisionAtK(k=retrieval_k, num_angles=num_angles)
                                            for s in ("val", "test")})
        self.pair_source: PairSource = (
            FeaturePairs(top_k, candidates_per_query, num_angles, patch=patch, grid=search_grid, min_score=min_score,
                         context_distance=context_distance, yaw_window=yaw_window, rank_by=rank_by)
            if candidates_from == "features" else
            InputPairs(occupancy_mutual_k, candidates_from == "input", candidates_per_query, num_angles))
        self._pairs: dict[str, Tensor] | None = None
        self._pool_stats = {"boxes": 0, "vouched": 0, "scene_vouched": 0}
        self._scene_boxes: dict[str, Any] | None = None  # the training split's fused pseudo-boxes
        self._candidates = 0
        self._refreshed_at = -1
        self.mining_history: list[dict[str, Any]] = []  # per refresh, its diagnostics

    def _two_view_sets(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        n = self.input_views(batch)
        S = batch["rgb"].shape[1]
        if S < 2 * n:
            raise ValueError(f"rgb: source {self.hparams.source!r} needs two disjoint sets of {n} views per sample, "
                             f"got {S} views (set the data's num_target_views >= num_input_views)")
        return tuple(tuple(batch[k][:, lo:lo + n] for k in ("rgb", "depth", "K", "R_T_cam")) for lo in (0, n))

    def _object_points(self, feats: Tensor, aabb: Tensor, mask: Tensor, idx: Tensor) -> Tensor:
        """Features ``[P, C]`` at the sampled cells ``idx`` ``[N, V]`` of every valid box's ``crop_size^3`` crop."""
        crops = crop_boxes(feats, aabb, self.feature_grid, self.hparams.crop_size, mask=mask)  # [N, C, s, s, s]
        return crop_voxels(crops, idx).flatten(0, 1)

    def _vc_step(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        a, b = self._two_view_sets(batch)
        mask, aabb = batch["box_mask"], batch["aabb"]
        n_obj = int(mask.sum())
        if n_obj == 0:
            return {"loss": None}
        s, V = self.hparams.crop_size, self.hparams.voxels_per_object
        if self.hparams.source == "vc":
            idx = torch.randint(0, s ** 3, (n_obj, min(V, s ** 3)), device=self.device)
            q = self._object_points(self.encode_views(*a), aabb, mask, idx)
            k = self._object_points(self.encode_views(*b), aabb, mask, idx)
            logits_neg = q @ k.T  # in-batch: the other points' keys are the negatives
            pos = (q * k).sum(1, keepdim=True)
            off = ~torch.eye(q.shape[0], dtype=torch.bool, device=q.device)
            logits = torch.cat([pos, logits_neg[off].view(q.shape[0], -1)], dim=1) / self.hparams.temperature
            loss = F.cross_entropy(logits, torch.zeros(q.shape[0], dtype=torch.long, device=q.device))
            return {"loss": loss, "positives": q.shape[0], "pos_cos": pos.mean()}
        with torch.no_grad():
            self.moco._momentum_update_key_encoder()
        feats = self.encode_views(*a)
        idx = torch.randint(0, s ** 3, (n_obj, min(V, s ** 3)), device=self.device)
        q = self._object_points(feats, aabb, mask, idx)
        with torch.no_grad():  # keys: the second view set through the momentum encoder (eval mode), same points
            x, seen = self.encoder_input(*(t.flatten(0, 1) for t in b))
            self.moco.encoder_k.eval()
            k = self._object_points(self.encode_input(x, seen, b[0].shape[1], encoder=self.moco.encoder_k), aabb,
                                    mask, idx)
        return self._moco_loss(q, k)

    def _moco_loss(self, q: Tensor, k: Tensor) -> dict[str, Any]:
        """InfoNCE of queries ``q`` ``[P, C]`` against keys ``k`` ``[P, C]`` and the queue; ``k`` is then enqueued."""
        loss = self.moco.loss(q, k)
        self._enqueue(k)
        return {"loss": loss, "positives": q.shape[0], "pos_cos": (q * k).sum(1).mean()}

    def _enqueue(self, k: Tensor) -> None:
        keys = self.all_gather(k.detach())
        self.moco._dequeue_and_enqueue(keys.reshape(-1, k.shape[-1]))

    def _train_dataset(self) -> Any:
        ds = getattr(self.trainer.train_dataloader, "dataset", None)
        if ds is None:
            raise RuntimeError("mining: the training dataloader has no .dataset to draw the pools from")
        return ds

    def _pool_dataset(self) -> Any:
        """The training split with each scene's fixed input views instead of random ones (so the crop cache serves)."""
        ds = copy.copy(self._train_dataset())
        if getattr(ds, "random_views", False):
            ds.random_views = False
        return ds

    @torch.no_grad()
    def _cut_pool(self, ds: Any, generator: torch.Generator) -> dict[str, Tensor]:
        """Crops of at most ``target_pool`` objects from random training scenes, encoder in eval mode, float32."""
        hp = self.hparams
        was_training = self.encoder.training
        self.encoder.eval()
        order = torch.randperm(len(ds), generator=generator).tolist()
        parts: dict[str, list[Tensor]] = {k: [] for k in ("features", "raw", "labels", "yaw", "scene", "slot",
                                                          "gt_iou")}
        got, i = 0, 0
        with torch.autocast(self.device.type, enabled=False):
            try:
                while got < hp.target_pool and i < len(order):
                    idx = order[i:i + hp.pool_batch_size]
                    i += len(idx)
                    batch = self._to_device(default_collate([ds[j] for j in idx]))
                    c = self.object_crops(batch, self.input_views(batch), hp.crop_size)
                    keep = torch.ones_like(c["slot"], dtype=torch.bool)
                    if hp.pool_min_observed_iou is not None:
                        keep = self._observed_iou(batch) >= hp.pool_min_observed_iou
                        self._pool_stats["boxes"] += int(keep.numel())
                        self._pool_stats["vouched"] += int(keep.sum())
                    if hp.pool_min_scene_iou is not None:
                        keep &= self._scene_iou(batch, ds) >= hp.pool_min_scene_iou
                        self._pool_stats["scene_vouched"] += int(keep.sum())
                    c.update(yaw=c["boxes"][:, 6], gt_iou=gt_box_iou(batch))
                    for k, v in parts.items():
                        v.append(c[k][keep])
                    got += int(keep.sum())
            finally:
                self.encoder.train(was_training)
        return {k: torch.cat(v)[:hp.target_pool] for k, v in parts.items()}

    def _observed_iou(self, batch: dict[str, Any]) -> Tensor:
        """``[N]`` for the batch's valid boxes: the highest 3D IoU with a label-free pseudo-box of its scene's input
        views (:func:`~threedq.box_refinement.observed_boxes` in the feature grid's bounds); 0 where there is none."""
        v = self.input_views(batch)
        fg = self.feature_grid
        out = []
        for i in range(batch["box_mask"].shape[0]):
            boxes = batch["aabb"][i][batch["box_mask"][i]].float().cpu()
            obs, _ = observed_boxes(batch["depth"][i, :v], batch["K"][i, :v], batch["R_T_cam"][i, :v],
                                    (fg.bounds_min, fg.bounds_max))
            out.append(best_aabb_iou(boxes, torch.from_numpy(obs).reshape(-1, 6)))
        return torch.cat(out).to(self.device)

    def _scene_iou(self, batch: dict[str, Any], ds: Any) -> Tensor:
        """``[N]`` for the batch's valid boxes: the highest 3D IoU with a label-free pseudo-box fused over the views of
        its training scene (the DataModule's ``pseudo_boxes("train")``); 0 where the scene has none."""
        if self._scene_boxes is None:
            self._scene_boxes = self._scene_pseudo_boxes()
        if not hasattr(ds, "files"):
            raise ValueError(f"pool_min_scene_iou: the pool's dataset ({type(ds).__name__}) names no scene files "
                             f"(.files); set pool_min_scene_iou: null")
        out = []
        for i in range(batch["box_mask"].shape[0]):
            boxes = batch["aabb"][i][batch["box_mask"][i]].float().cpu()
            name = ds.files[int(batch["scene_index"][i])]
            if name not in self._scene_boxes:
                raise ValueError(f"pool_min_scene_iou: the training split's pseudo-boxes have no entry for {name}")
            fused = torch.as_tensor(self._scene_boxes[name][0], dtype=torch.float32).reshape(-1, 6)
            out.append(best_aabb_iou(boxes, fused))
        return torch.cat(out).to(self.device)

    def _scene_pseudo_boxes(self) -> dict[str, Any]:
        """The DataModule's ``pseudo_boxes("train")``: label-free pseudo-boxes per scene file, fused over its views."""
        dm = getattr(self._trainer, "datamodule", None)
        if dm is None or not callable(getattr(dm, "pseudo_boxes", None)):
            raise ValueError(f"pool_min_scene_iou: the check needs a DataModule with pseudo_boxes(split) (threedq's "
                             f"scene-folder DataModules); got {type(dm).__name__}; set pool_min_scene_iou: null")
        return dm.pseudo_boxes("train")

    @torch.no_grad()
    def refresh_pairs(self) -> dict[str, Any]:
        """Cut a new pool, take the pair source's candidates and their positives; log, write and return the
        diagnostics."""
        hp = self.hparams
        t0 = time.time()
        rank = self.trainer.global_rank if self.trainer is not None else 0
        g = torch.Generator().manual_seed(hp.seed + 1009 * int(self.refreshes) + 7919 * rank)
        self._pool_stats = {"boxes": 0, "vouched": 0, "scene_vouched": 0}
        pool = self._cut_pool(self._pool_dataset(), g)
        feats = pool["features"]
        if feats.shape[0] == 0:
            raise ValueError(self._empty_pool_message())
        n_q = min(hp.query_pool, feats.shape[0])
        if not bool(self.queue_primed):
            flat = feats.permute(0, 2, 3, 4, 1).reshape(-1, feats.shape[1])
            pick = torch.randint(0, flat.shape[0], (self.moco.queue.shape[0],), generator=g).to(flat.device)
            self.moco.queue.copy_(F.normalize(flat[pick], dim=1))
            self.queue_primed.fill_(True)
        min_cos = hp.min_cosine if hp.min_cosine is not None else calibrate_context_cosine(
            feats, pool["scene"], hp.context_quantile, hp.patch, generator=g)
        mined = self.pair_source.candidates(pool, n_q, hp.keep, min_cos)
        self._candidates = int(mined["query_index"].numel())
        offsets = corner_offsets(hp.corner_offset, hp.patch, device=feats.device)
        if hp.positives == "occupancy":
            mined, q_voxels, keys = occupancy_positives(feats, input_occupancy(pool["raw"]), mined, offsets.shape[0],
                                                        hp.keep, hp.num_angles, g)
        else:
            q_voxels, keys = patch_positives(feats, mined, offsets, hp.corner_search, hp.num_angles)
        qi = mined["query_index"]
        self._pairs = {"scene": pool["scene"][qi], "slot": pool["slot"][qi], "query_voxels": q_voxels, "keys": keys}
        self._refreshed_at = self.global_step
        self.refreshes += 1
        return self._diagnostics(pool, mined, min_cos, n_q, time.time() - t0)

    def _empty_pool_message(self) -> str:
        hp, st = self.hparams, self._pool_stats
        checks = ", ".join(f"{k}={hp[k]}" for k in ("pool_min_observed_iou", "pool_min_scene_iou") if hp[k] is not None)
        seen = "" if hp.pool_min_observed_iou is None else (
            f" (of {st['boxes']} boxes seen, {st['vouched']} vouched for by the input views, "
            f"{st['scene_vouched']} by the scenes' fused views too)")
        strict = f"; the pool's checks ({checks}) may be too strict for this data: set them to null" if checks else ""
        return f"mining: the pool of the training split's boxes is empty{seen}: no box to mine pairs from" + strict

    def pair_measures(self, pool: dict[str, Tensor], mined: dict[str, Tensor]) -> dict[str, Any]:
        """GT measures of mined pairs (measuring only): ``same_category`` among the ``labelled_pairs`` (both boxes
        match a GT object), ``pairs_on_objects_iou25``, and, where the data names symmetries, the median implied yaw
        error ``yaw_median_err_deg`` over the ``yaw_pairs`` same-category pairs of asymmetric categories and
        ``yaw_sym_median_err_deg`` over the ``yaw_sym_pairs`` of every finite symmetry order (modulo its period). A
        key is absent where it has no pair."""
        qi, ti = mined["query_index"], mined["target_index"]
        lq, lt = pool["labels"][qi], pool["labels"][ti]
        labelled = (lq >= 0) & (lt >= 0)
        same = (lq == lt) & labelled
        out: dict[str, Any] = {"same_category": float(same.sum() / labelled.sum()) if labelled.any() else float("nan"),
                               "labelled_pairs": int(labelled.sum())}
        iou = pool.get("gt_iou")
        if iou is not None and iou.numel() and not bool(torch.isnan(iou).any()):
            # both boxes overlap a GT object at IoU >= 0.25
            out["pairs_on_objects_iou25"] = int(((iou[qi] >= 0.25) & (iou[ti] >= 0.25)).sum())
        sym = self.hparams.symmetry_order
        if sym is not None and same.any():
            s = torch.tensor(list(sym), dtype=torch.long).to(qi.device)[lq.clamp_min(0)]
            for key, use in (("yaw", same & (s == 1)), ("yaw_sym", same & (s >= 1))):
                if use.any():
                    err = implied_yaw_error_deg(mined["yaw"][use], self.hparams.num_angles, pool["yaw"][qi][use],
                                                pool["yaw"][ti][use], s[use])
                    out[f"{key}_median_err_deg"] = float(err.median())
                    out[f"{key}_pairs"] = int(use.sum())
        return out

    def _diagnostics(self, pool: dict[str, Tensor], mined: dict[str, Tensor], min_cos: float, n_q: int,
                     seconds: float) -> dict[str, Any]:
        hp = self.hparams
        qi = mined["query_index"]
        measures = self.pair_measures(pool, mined)
        info: dict[str, Any] = {
            "step": int(self.global_step), "refresh": int(self.refreshes),
            "pool_objects": int(pool["features"].shape[0]),
            "queries": n_q, "pairs": int(qi.numel()), "min_cosine": round(min_cos, 4),
            "score_mean": float(mined["score"].mean()) if qi.numel() else float("nan"),
            "distinct_queries": int(qi.unique().numel()),
            "distinct_targets": int(mined["target_index"].unique().numel()),
            "distinct_boxes": int(torch.cat([qi, mined["target_index"]]).unique().numel()),
            **{k: v for k, v in measures.items() if not k.startswith("yaw")},  # same_category, labelled_pairs, ...
            "pool_on_objects": float((pool["labels"] >= 0).float().mean()) if pool["labels"].numel() else float("nan"),
            "seconds": round(seconds, 1),
            **self.pair_source.describe(),
        }
        if hp.positives == "occupancy":
            info["shape_candidates"] = self._candidates
            info["shape_cosine_mean"] = float(mined["shape_cosine"].mean()) if qi.numel() else float("nan")
        if hp.pool_min_observed_iou is not None:
            info.update(pool_boxes_seen=self._pool_stats["boxes"], pool_vouched=self._pool_stats["vouched"])
        if hp.pool_min_scene_iou is not None:
            info["pool_scene_vouched"] = self._pool_stats["scene_vouched"]
        info.update({k: v for k, v in measures.items() if k.startswith("yaw")})
        self.mining_history.append(info)
        if self.trainer is not None:
            self.log_dict({f"mining/{k}": float(v) for k, v in info.items()
                           if k in ("pairs", "same_category", "yaw_median_err_deg", "min_cosine", "seconds")},
                          rank_zero_only=True)
            if self.trainer.is_global_zero:
                self._write_diagnostics(info, pool, mined)
        return info

    def _write_diagnostics(self, info: dict[str, Any], pool: dict[str, Tensor], mined: dict[str, Tensor]) -> None:
        out = self.run_dir / "mining"
        name = f"refresh_{info['step']:06d}"
        atomic_write_text(out / f"{name}.json", json.dumps(info, indent=1) + "\n")
        P = mined["query_index"].numel()
        if P == 0:
            return
        # the best 6 pairs and the worst 4 (the kept pairs are in rank order)
        pick = torch.cat([torch.arange(min(6, P)), torch.arange(min(max(6, P - 4), P), P)])
        pick = pick.to(mined["query_index"].device)
        qi, ti, yaw = mined["query_index"][pick], mined["target_index"][pick], mined["yaw"][pick]
        angle = yaw.to(pool["raw"].dtype) * (2 * math.pi / self.hparams.num_angles)
        aligned = rotate_yaw(pool["raw"][ti], angle)
        lab = pool["labels"]

        def verdict(q: int, t: int) -> str:  # GT, for measuring only
            if q < 0 or t < 0:
                return "off an object" if (q < 0) != (t < 0) else "off objects"
            return "same category" if q == t else "other category"

        score = mined.get("shape_cosine", mined["score"])  # what ranked the kept pairs
        captions = [f"{'best' if int(j) < 6 else 'worst'} {int(j) + 1}: {float(score[j]):.2f}, "
                    f"{int(yaw[n]) * 360 // self.hparams.num_angles} deg, {verdict(int(lab[qi[n]]), int(lab[ti[n]]))}"
                    for n, j in enumerate(pick.tolist())]  # at most 40 characters (the figure's caption bar)
        img = mined_pairs_figure(pool["raw"][qi], aligned, mined["query_pos"][pick], mined["target_pos_aligned"][pick],
                                 captions, self.hparams.patch)
        write_png(out / f"{name}.png", img)

    def _mined_step(self) -> dict[str, Any]:
        hp = self.hparams
        if self._pairs is None or (self.global_step % hp.refresh_every == 0 and self.global_step != self._refreshed_at):
            self.refresh_pairs()
        pairs = self._pairs
        P = pairs["scene"].numel()
        if P == 0:
            return {"loss": None}
        pick = torch.randperm(P)[: hp.pairs_per_step].to(pairs["scene"].device)
        scenes = pairs["scene"][pick]
        uniq, inv = scenes.unique(return_inverse=True)
        ds = self._train_dataset()
        batch = self._to_device(default_collate([ds[int(s)] for s in uniq.tolist()]))
        v = self.input_views(batch)
        feats = self.encode_views(*(batch[k][:, :v] for k in ("rgb", "depth", "K", "R_T_cam")))
        crops = crop_boxes(feats, batch["aabb"], self.feature_grid, hp.crop_size)  # [B, M, C, s, s, s]
        qv = pairs["query_voxels"][pick]  # [n, 8, 3]
        sel = crops[inv, pairs["slot"][pick]]  # [n, C, s, s, s]
        n = sel.shape[0]
        q = sel[torch.arange(n, device=sel.device)[:, None], :, qv[..., 0], qv[..., 1], qv[..., 2]]  # [n, 8, C]
        q = F.normalize(q.reshape(-1, q.shape[-1]), dim=1)
        k = pairs["keys"][pick].reshape(-1, q.shape[-1]).to(q.dtype)
        with torch.no_grad():
            self.moco._momentum_update_key_encoder()
        return self._moco_loss(q, k)

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor | None:
        r = self._mined_step() if self.hparams.source == "mined" else self._vc_step(batch)
        if r["loss"] is None:
            return None  # no objects / no pairs: skip the step
        self.log_dict({"train/loss": r["loss"], "train/pos_cos": r["pos_cos"],
                       "train/positives": float(r["positives"])}, prog_bar=True, batch_size=1)
        return r["loss"]

    def configure_optimizers(self) -> torch.optim.Optimizer:
        params = [p for p in self.encoder.parameters() if p.requires_grad]
        return torch.optim.Adam([{"params": params}], lr=self.round_learning_rate)

    @property
    def round_learning_rate(self) -> float:
        """The learning rate of this round: ``lr``, or ``lr / em_round`` under ``round_lr: harmonic``."""
        hp = self.hparams
        return hp.lr / hp.em_round if hp.round_lr == "harmonic" else hp.lr
