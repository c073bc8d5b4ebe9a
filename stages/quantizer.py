"""Rotation-aware quantization into 3D prototypes (paper Sec. 3.2) as a Lightning stage.

With the encoder frozen, one pass over the training scenes collects the object crops of the DataModule's boxes; at
the epoch's last batch the prototype bank is initialised incrementally and refined by ``em_iterations`` rounds of
E-step (best prototype and yaw per object) and closed-form M-step (under DDP on the crops of every process).
Validation and test measure Hungarian-matched accuracy, few-shot labelling accuracy and relative yaw error.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import torch
from jsonargparse.typing import NonNegativeInt, PositiveInt

from threedq.argtypes import OccupancyFloor
from torch import Tensor

from threedq.stages.base import EncoderStage, SplitEvaluation
from threedq.stages.checkpoint import checkpoint_hparams, load_checkpoint
from threedq.geometry import yaw_angles
from threedq.metrics import FewShotAccuracy, HungarianAccuracy, RelativeYawError
from threedq.quantization.prototypes import (PrototypeBank, assign_chunked, prototype_crops, quantization_loss,
                                              run_prototype_em)

__all__ = ["Quantizer", "bank_occupancy_floor", "load_bank_state"]


def load_bank_state(bank: PrototypeBank, path: str) -> None:
    """Load the ``bank.*`` buffers of a quantizer checkpoint into ``bank`` (shapes must match)."""
    state = load_checkpoint(path).prefixed("bank.")
    if not state:
        raise ValueError(f"{path}: field 'state_dict': no 'bank.*' buffers (not a quantizer checkpoint?)")
    own = bank.state_dict()
    for k, v in state.items():
        if k not in own or own[k].shape != v.shape:
            raise ValueError(f"{path}: field 'bank.{k}': shape {tuple(v.shape)} does not fit this bank")
    bank.load_state_dict(state)


def _saved_floor(hparams: dict[str, Any] | None) -> float | None:
    """``occupancy_floor`` of a quantizer checkpoint's hyperparameters (None where absent: the plain cosine)."""
    floor = (hparams or {}).get("occupancy_floor")
    return None if floor is None else float(floor)


def bank_occupancy_floor(path: str | Path) -> float | None:
    """The ``occupancy_floor`` a quantizer checkpoint's bank was fitted with (its crops must be weighted alike)."""
    return _saved_floor(checkpoint_hparams(path, missing_ok=True))


class Quantizer(SplitEvaluation, EncoderStage):
    """The quantizer stage.

    Args:
        freeze_encoder: keep the encoder fixed.
        **kwargs: the encoder's other arguments, by keyword (:class:`~threedq.stages.base.EncoderStage`).
        num_prototypes: K, the bank's prototypes.
        crop_size: object crops are ``crop_size^3``.
        num_angles: yaw steps of the rotation search (1: the no-rot-3DQ baseline).
        init_threshold: incremental initialisation threshold on rotation-max cosine.
        fill_free_slots: after the incremental pass, open the free slots from the objects farthest from the bank.
        em_iterations: E/M rounds at the end of each training epoch.
        em_restarts: fits of an empty bank (seeds ``seed, seed + 1, ...``); the lowest quantization loss is kept.
        search_method: ``"fast"`` (cylindrical FFT) or ``"exact"`` rotation search.
        num_classes: categories of the dataset, for the metrics only (``None``: no evaluation metrics).
        symmetry_order: per category, its yaw symmetry order, for the yaw-error metric (``None``: all asymmetric).
        shots: labelled examples per category of the few-shot metric.
        seed: seed of the incremental-initialisation order and of the few-shot draw.
        init_bank_ckpt: start from the prototype bank of an earlier quantizer checkpoint instead of an empty one.
        occupancy_floor: in [0, 1): crop voxels weighted by this plus their dilated input occupancy
            (:func:`~threedq.quantization.prototypes.prototype_crops`); ``None``: the plain cosine.

    Convention: crops in frame R, z up; yaw counter-clockwise seen from above.
    """

    def __init__(
        self, *, freeze_encoder: bool = True, num_prototypes: PositiveInt = 50, crop_size: PositiveInt = 16,
        num_angles: PositiveInt = 36, init_threshold: float = 0.8, fill_free_slots: bool = True,
        em_iterations: NonNegativeInt = 10, em_restarts: PositiveInt = 4,
        search_method: Literal["fast", "exact"] = "fast", num_classes: int | None = None,
        symmetry_order: list[int] | None = None, shots: PositiveInt = 2, seed: int = 0,
        init_bank_ckpt: str | None = None, occupancy_floor: OccupancyFloor | None = 0.2, **kwargs: Any,
    ) -> None:
        super().__init__(freeze_encoder=freeze_encoder, **kwargs)
        self.save_hyperparameters()
        self.automatic_optimization = False
        self.bank = PrototypeBank(num_prototypes, self.feature_dim, crop_size, num_angles, init_threshold,
                                  search_method)
        if init_bank_ckpt:
            load_bank_state(self.bank, init_bank_ckpt)
            fitted = bank_occupancy_floor(init_bank_ckpt)
            if fitted != occupancy_floor:
                raise ValueError(f"{init_bank_ckpt}: field 'hyper_parameters.occupancy_floor': the bank was fitted "
                                 f"with {fitted}, this stage has occupancy_floor={occupancy_floor}")
        self._train_crops: list[Tensor] = []
        self._train_keys: list[Tensor] = []
        self.metrics: torch.nn.ModuleDict | None = None
        if num_classes is not None:
            sym = list(symmetry_order) if symmetry_order is not None else [1] * num_classes
            if len(sym) != num_classes:
                raise ValueError(f"symmetry_order: {len(sym)} orders for num_classes={num_classes} categories")
            self.metrics = torch.nn.ModuleDict({split: torch.nn.ModuleDict({
                "hungarian": HungarianAccuracy(num_prototypes, num_classes),
                "fewshot": FewShotAccuracy(num_prototypes, num_classes, shots=shots, seed=seed),
                "yaw": RelativeYawError(sym),
            }) for split in ("val", "test")})

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Take the crop weighting of the checkpoint's bank, whatever this stage was built with."""
        self.hparams.occupancy_floor = _saved_floor(checkpoint.get("hyper_parameters"))

    def _split_metrics(self, split: str) -> torch.nn.ModuleDict:
        if self.metrics is None:
            raise ValueError("num_classes: null: the quantizer's evaluation needs the dataset's category count (the "
                             "threedq CLI takes it, and symmetry_order, from the dataset's index.json)")
        return self.metrics[split]

    def on_train_epoch_start(self) -> None:
        self._train_crops, self._train_keys = [], []

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        with torch.no_grad():
            out = self.object_crops(batch, self.input_views(batch), self.hparams.crop_size)
            crops = prototype_crops(out["features"], out["raw"], self.hparams.occupancy_floor)
        self._train_crops.append(crops.detach())
        self._train_keys.append(out["scene"] * batch["box_mask"].shape[1] + out["slot"])
        self.log("train/objects", float(crops.shape[0]), reduce_fx="sum", on_step=False, on_epoch=True, batch_size=1,
                 sync_dist=True)
        if batch_idx == self.trainer.num_training_batches - 1:
            # EM on the last batch of the epoch, so that this epoch's validation sees the updated bank
            self._run_em()

    def _gathered_crops(self) -> Tensor:
        """This epoch's training crops of every process, each object once, in the canonical order (scene index, then
        the box's row), so that the bank is the same in one process and in many."""
        crops = torch.cat(self._train_crops) if self._train_crops else self.bank.prototypes[:0]
        keys = torch.cat(self._train_keys) if self._train_keys else torch.zeros(0, dtype=torch.long,
                                                                               device=crops.device)
        if self.trainer is not None and self.trainer.world_size > 1:
            # pad to the largest count so all_gather sees equal shapes on every process
            n = torch.tensor([crops.shape[0]], device=crops.device)
            counts = self.all_gather(n).flatten()
            pad = int(counts.max()) - crops.shape[0]
            gathered = self.all_gather(torch.cat([crops, crops.new_zeros(pad, *crops.shape[1:])]))  # [W, Nmax, ...]
            gathered_keys = self.all_gather(torch.cat([keys, keys.new_zeros(pad)]))
            crops = torch.cat([gathered[r, : int(c)] for r, c in enumerate(counts)])
            keys = torch.cat([gathered_keys[r, : int(c)] for r, c in enumerate(counts)])
        keys, order = torch.sort(keys, stable=True)
        first = torch.ones_like(keys, dtype=torch.bool)
        first[1:] = keys[1:] != keys[:-1]
        return crops[order[first]]

    def on_train_epoch_end(self) -> None:
        if self._train_crops:  # the epoch stopped before its last batch (max_steps, limit_train_batches)
            self._run_em()

    def _run_em(self) -> None:
        crops = self._gathered_crops()
        self._train_crops, self._train_keys = [], []
        if crops.shape[0] == 0:
            raise RuntimeError("quantizer: no object crops in the training split")
        spectra: dict = {}  # each chunk's polar spectrum, computed once for the EM and the assignment below
        bank = run_prototype_em(self.bank, crops, self.hparams.em_iterations, seed=self.hparams.seed,
                                fill_free=self.hparams.fill_free_slots, spectra=spectra,
                                restarts=self.hparams.em_restarts)
        res = assign_chunked(bank, crops, spectra=spectra)
        self.log_dict({"train/prototypes_active": float(bank.num_active), "train/mean_score": res.score.mean(),
                       "train/quantization_loss": quantization_loss(bank, crops, res)}, prog_bar=True)

    def configure_optimizers(self) -> None:
        return None  # closed-form EM; no gradient step

    def _eval_step(self, batch: dict[str, Tensor], split: str, batch_idx: int = 0) -> None:
        if self.bank.num_active == 0:
            return  # sanity check before any training
        crops = self.object_crops(batch, self.input_views(batch), self.hparams.crop_size)
        if crops["features"].shape[0] == 0:
            return  # no (matched) boxes in this batch, e.g. detections that hit no GT object
        res = self.bank.assign(prototype_crops(crops["features"], crops["raw"], self.hparams.occupancy_floor))
        m = self._split_metrics(split)
        m["hungarian"].update(res.prototype, crops["labels"])
        m["fewshot"].update(res.prototype, crops["labels"])
        est_yaw = yaw_angles(self.hparams.num_angles, device=self.device)[res.angle]
        m["yaw"].update(est_yaw, crops["boxes"][:, 6], crops["labels"], res.prototype)

    def _eval_epoch_end(self, split: str) -> None:
        if self.bank.num_active == 0:
            return
        m = self._split_metrics(split)
        yaw = m["yaw"].compute()
        self.log_dict({
            f"{split}/hungarian_acc": m["hungarian"].compute(), f"{split}/fewshot_acc": m["fewshot"].compute(),
            f"{split}/yaw_median_deg": yaw["median_deg"], f"{split}/yaw_acc10": yaw["acc_10"],
            f"{split}/yaw_acc20": yaw["acc_20"], f"{split}/yaw_pairs": float(yaw["num_pairs"]),
        }, prog_bar=True)
        # the confusion matrix is this process's again after compute(): sum the counts over processes
        self.log(f"{split}/objects", m["hungarian"].confusion.sum().float(), reduce_fx="sum", sync_dist=True)
        for metric in m.values():
            metric.reset()

