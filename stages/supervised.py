"""The supervised ceiling of the retrieval table: threedq's encoder, grid and crop trained **with category labels**.

A reference, not a method: it answers "what do this encoder, this grid and this 16^3 object crop allow when labels
say what an object is?", so that the gap between threedq's label-free features and the paper's numbers can be split
into what the self-supervision misses and what the crop and the similarity cannot express. The encoder is the one
every stage shares (a :class:`~threedq.stages.base.EncoderStage`, trained from scratch, the grid of its config), an
object is its GT box cropped out of the feature grid to ``crop_size^3`` (:meth:`EncoderStage.object_crops`, as in
every evaluation), and a cosine classifier on the voxel-averaged crop (both L2-normalised, logits scaled by
``logit_scale``: the pooled unit-length features vary little in length, so a plain linear layer learns slowly) is
trained with cross-entropy against the object's category; training scenes only, one random input view per sample. Its checkpoint is scored like any
encoder: ``threedq eval --encoders '{"rgbocc": <view prediction>, "supervised (labels)": <this>}'`` (Table 2 with
both retrieval protocols; docs/fidelity.md). Validation logs strict precision@10 of the val crops.

Labels are used here and nowhere else in threedq's training.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from threedq.metrics import RetrievalPrecisionAtK
from threedq.stages.base import EncoderStage, SplitEvaluation

__all__ = ["SupervisedCeiling"]


class SupervisedCeiling(SplitEvaluation, EncoderStage):
    """Encoder + crop + linear classifier trained with category labels (a Table 2 reference row).

    Args:
        **kwargs: the encoder's arguments (``grid_min``, ``grid_max``, ``grid_resolution``, ``feature_dim``,
            ``encoder_channels``, ``feature_stride``, ``encoder_ckpt``, ``freeze_encoder``, ``channels_last``), by keyword: see
            :class:`~threedq.stages.base.EncoderStage` (from scratch by default, the view-prediction grid).
        num_classes: categories of the dataset (the threedq CLI links it from the dataset's ``index.json``:
            ``ThreeDQCLI``'s ``link_arguments``); needed to train.
        crop_size: object crops are ``crop_size^3`` (as the evaluations crop).
        lr: Adam learning rate of encoder and classifier.
        logit_scale: the cosine classifier's logits are ``logit_scale * cos(pooled crop, class weight)``.
        retrieval_k, num_angles: validation retrieval (strict protocol, fast search).

    Convention: crops in frame R, z up; boxes axis-aligned hulls of the GT boxes.
    """

    def __init__(
        self,
        *,
        num_classes: int | None = None,
        crop_size: int = 16,
        lr: float = 1e-3,
        logit_scale: float = 16.0,
        retrieval_k: int = 10,
        num_angles: int = 36,
        **kwargs: Any,
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
            raise ValueError("num_classes: null: give the dataset's category count (the threedq CLI takes it from the "
                             "dataset's index.json)")

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

    def _eval_step(self, batch: dict[str, Tensor], split: str) -> None:
        crops = self.object_crops(batch, self.input_views(batch), self.hparams.crop_size)
        keep = crops["labels"] >= 0
        if keep.any():
            self.metrics[split].update(crops["features"][keep], crops["labels"][keep])

    def _eval_epoch_end(self, split: str) -> None:
        m = self.metrics[split]
        n = sum(c.shape[0] for c in m.crops) if isinstance(m.crops, list) else m.crops.shape[0]
        if n > self.hparams.retrieval_k:
            self.log(f"{split}/precision_at_{self.hparams.retrieval_k}", m.compute(), prog_bar=True)
        m.reset()

    def configure_optimizers(self) -> torch.optim.Optimizer:
        params = [p for p in self.parameters() if p.requires_grad]
        return torch.optim.Adam(params, lr=self.hparams.lr)
