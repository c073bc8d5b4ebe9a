"""Metrics of the paper's evaluation (torchmetrics ``Metric``s with DDP-correct states, plus functional forms)."""

from threedq.metrics.retrieval import RetrievalPrecisionAtK, retrieval_precision_at_k, rotation_max_similarity

__all__ = ["RetrievalPrecisionAtK", "retrieval_precision_at_k", "rotation_max_similarity"]
