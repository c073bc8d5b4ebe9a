"""Metrics of the paper's evaluation (torchmetrics ``Metric``s with DDP-correct states, plus functional forms)."""

from threedq.metrics.clustering import HungarianAccuracy, cluster_confusion, hungarian_accuracy, matching
from threedq.metrics.detection import DetectionMAP, assign_detections, average_precision, match_detections
from threedq.metrics.fewshot import (
    FewShotAccuracy,
    few_shot_accuracy,
    linear_probe,
    linear_probe_accuracy,
    nearest_shot_accuracy,
    select_labelled,
)
from threedq.metrics.pose import RelativeYawError, relative_yaw_error, relative_yaw_errors
from threedq.metrics.retrieval import (
    PROTOCOLS,
    RetrievalPrecisionAtK,
    per_class_precision_at_k,
    precision_ceiling,
    retrieval_confusion,
    retrieval_precision_at_k,
    same_object_top1,
)

__all__ = [
    "PROTOCOLS", "DetectionMAP", "FewShotAccuracy", "HungarianAccuracy", "RelativeYawError", "RetrievalPrecisionAtK",
    "assign_detections", "average_precision", "cluster_confusion", "few_shot_accuracy", "hungarian_accuracy",
    "linear_probe", "linear_probe_accuracy", "match_detections", "matching", "nearest_shot_accuracy",
    "per_class_precision_at_k", "precision_ceiling", "relative_yaw_error", "relative_yaw_errors",
    "retrieval_confusion", "retrieval_precision_at_k", "same_object_top1", "select_labelled",
]  # fmt: skip
