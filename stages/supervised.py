"""The supervised ceiling of the retrieval table: threedq's encoder, grid and crop trained **with category labels**.

A reference, not a method: the shared encoder (trained from scratch on its config's grid), each GT box cropped to
``crop_size^3`` (:meth:`EncoderStage.object_crops`) and a cosine classifier on the voxel-averaged crop (logits scaled
by ``logit_scale``) trained with cross-entropy on the training scenes. Its checkpoint is scored like any encoder
(``threedq eval --encoders``); validation logs strict precision@K. Labels are used here and nowhere else in training.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from threedq.metrics import RetrievalPrecisionAtK
from threedq.stages.base import EncoderStage, RetrievalEvaluation

__all__ = ["SupervisedCeiling"]


class SupervisedCeiling(RetrievalEvaluation, EncoderStage):
    """Encoder + crop + linear classifier trained with category labels (a Table 2 reference row).

    Args:
        **kwargs: the encoder's arguments, by keyword (:class:`~threedq.stages.base.EncoderStage`).
        num_classes: categories of the dataset (the CLI links it from ``index.json``); needed to train.
        crop_size: object crops are ``crop_size^3``.
        lr: Adam learning rate of encoder and classifier.
        logit_scale: the cosine classifier's logits are ``logit_scale * cos(pooled crop, class weight)``.
        retrieval_k: K of the validation precision@K (strict protocol).
        num_angles: yaw steps of the validation retrieval's rotation search.

    Convention: crops in frame R, z up; boxes axis-aligned hulls of the GT boxes.
    """

    def __init__(
        self, *, num_classes: int | None = None, crop_size: int = 16, lr: float = 1e-3, logit_scale: float = 16.0,
        retrieval_k: int = 10, num_angles: int = 36, **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        if num_classes is not None and num_classes < 2:
            raise ValueError(f"num_classes: expected >= 2 (or null: the dataset's count), got {num_classes}")
        self.save_hyperparameters()
        self.classifier: torch.nn.Linear | None = None
        if num_classes is not None:
            self.classifier = torch.nn.Linear(self.feature_dim, num_classes, bias=False)
        self.metrics = torch.nn.ModuleDict(
            {split: RetrievalPrecisionAtK(k=retrieval_k, num_angles=num_angles) for split in ("val", "test")})

    def setup(self, stage: str) -> None:
        super().setup(stage)
        if self.classifier is None:
            raise ValueError("num_classes: null: give the dataset's category count (the threedq CLI takes it from "
                             "the dataset's index.json)")

    def logits(self, features: Tensor) -> Tensor:
        """``[N, num_classes]`` class scores of ``[N, C, s, s, s]`` crops (the cosine classifier on the voxel mean)."""
        assert self.classifier is not None
        pooled = torch.nn.functional.normalize(features.flatten(2).mean(2).float(), dim=1)
        weight = torch.nn.functional.normalize(self.classifier.weight, dim=1)
        return self.hparams.logit_scale * pooled @ weight.T

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor | None:
        crops = self.object_crops(batch, self.input_views(batch), self.hparams.crop_size)
        keep = crops["labels"] >= 0
        if not keep.any():
            return None
        logits = self.logits(crops["features"][keep])
        labels = crops["labels"][keep]
        loss = torch.nn.functional.cross_entropy(logits, labels)
        self.log("train/loss", loss, prog_bar=True, batch_size=int(keep.sum()))
        self.log("train/acc", (logits.argmax(1) == labels).float().mean(), prog_bar=True, batch_size=int(keep.sum()))
        return loss
