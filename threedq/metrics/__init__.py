"""Metrics of the paper's evaluation (torchmetrics ``Metric``s with DDP-correct states, plus functional forms)."""

from threedq.metrics.clustering import (
    ClusterPurity,
    HungarianAccuracy,
    cluster_confusion,
    hungarian_accuracy,
    matching,
    purity,
)
from threedq.metrics.fewshot import FewShotAccuracy, few_shot_accuracy, select_labelled
from threedq.metrics.pose import RelativeYawError, relative_yaw_error, relative_yaw_errors
from threedq.metrics.retrieval import RetrievalPrecisionAtK, retrieval_precision_at_k, rotation_max_similarity

__all__ = [
    "ClusterPurity",
    "FewShotAccuracy",
    "HungarianAccuracy",
    "RelativeYawError",
    "RetrievalPrecisionAtK",
    "cluster_confusion",
    "few_shot_accuracy",
    "hungarian_accuracy",
    "matching",
    "purity",
    "relative_yaw_error",
    "relative_yaw_errors",
    "retrieval_precision_at_k",
    "rotation_max_similarity",
    "select_labelled",
]
