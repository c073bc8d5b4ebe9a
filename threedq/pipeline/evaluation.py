"""Evaluation of learned 3D features on held-out scenes (paper Table 2 protocol, GT boxes).

For every object of the evaluated split, its axis-aligned GT box is cropped out of the scene's feature
grid and resized to 16^3; crops are compared at their best relative yaw over 36 steps of 10 deg and
rotation-max retrieval precision@10 is macro-averaged over categories. :func:`retrieval_table` is the one
implementation of that measurement (``threedq em``, ``threedq eval`` and the benchmarks all call it); it
uses one declared search (:data:`RETRIEVAL_SEARCH`, ``"fast"`` unless asked otherwise) and records it, so
every table can name it. Two references are computed
side by side: (a) raw ``cat[occ, occ * rgb]`` crops of the input grid (no learning) and (b) the same
encoder with random weights.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm import tqdm

from threedq.stages.base import EncoderStage
from threedq.pipeline.crop_cache import CropCache, sample_key
from threedq.geometry import crop_boxes, yaw_angles
from threedq.metrics import cluster_confusion, few_shot_accuracy, hungarian_accuracy, relative_yaw_error
from threedq.metrics.retrieval import retrieval_precision_at_k
from threedq.quantization.rotation_search import SEARCH_METHODS, all_pairs_rotation_max
from threedq.nets import UNet3D

__all__ = [
    "RETRIEVAL_SEARCH",
    "SEARCH_LABELS",
    "collect_object_crops",
    "evaluate_features",
    "quantization_metrics",
    "retrieval_table",
]

#: The rotation search every retrieval table of threedq uses unless told otherwise.
RETRIEVAL_SEARCH = "fast"
#: How a table header names each search.
SEARCH_LABELS = {
    "fast": "fast search (cylindrical resampling + FFT over yaw; cosine over the inscribed cylinder)",
    "exact": "exact search (every crop rotated by every yaw; cosine over the full cube)",
}
#: Crop sets of :func:`collect_object_crops` and their names in result tables.
FEATURE_SETS = (("learned", "learned"), ("raw_rgb_occupancy", "raw"), ("random_encoder", "random"))


def _random_encoder_crops(
    stage: EncoderStage, random_enc: UNet3D, batch: dict[str, Tensor], v: int, crop_size: int, cache: CropCache | None
) -> Tensor:
    """Crops of ``batch``'s valid boxes from ``random_enc``'s features (view mean, L2-normalised), on the CPU."""
    mask = batch["box_mask"]
    B = mask.shape[0]
    if cache is not None:
        prefix, fp = stage.crop_cache_prefix(), cache.fingerprint(random_enc)
        keys = [("random", prefix, fp, sample_key(batch, b, v, crop_size)) for b in range(B)]
        hit = cache.get_many(keys)
        if hit is not None:
            return torch.cat(hit)
    rgb, depth, K, pose = (batch[k][:, :v].flatten(0, 1) for k in ("rgb", "depth", "K", "R_T_cam"))
    x, _ = stage.encoder_input(rgb, depth, K, pose)
    rf = random_enc(x).view(B, v, -1, *stage.feature_grid.volume_shape).mean(1)
    rand = crop_boxes(F.normalize(rf, dim=1), batch["aabb"], stage.feature_grid, crop_size)
    if cache is not None:
        for b in range(B):
            cache.put(keys[b], rand[b][mask[b]])
    return rand[mask].cpu()


@torch.no_grad()
def collect_object_crops(
    stage: EncoderStage,
    loader: torch.utils.data.DataLoader,
    num_input_views: int = 1,
    crop_size: int = 16,
    random_encoder_seed: int | None = 0,
    progress: bool = True,
) -> dict[str, Tensor]:
    """Crop every GT object of every scene of ``loader`` out of three volumes.

    Args:
        stage: a stage with a (trained) encoder.
        loader: yields SceneDataset batches; the first ``num_input_views`` views are encoded.
        num_input_views: views aggregated per scene (the paper tests with one).
        crop_size: crops are ``crop_size^3``.
        random_encoder_seed: seed of the randomly initialised reference encoder (None: skip it).

    Returns:
        ``learned`` ``[N, C, s, s, s]``, ``raw`` ``[N, 4, s, s, s]``, ``random`` ``[N, C, s, s, s]`` (if
        requested), ``labels`` ``[N]``, ``boxes`` ``[N, 7]`` oriented GT boxes, ``aabb`` ``[N, 6]`` the cropped
        boxes (GT hulls, or the given boxes), ``scene`` ``[N]`` (index in the split).

    Convention: boxes axis-aligned in R (z up), cropped as their tight hull.
    """
    was_training = stage.training
    stage.eval()
    random_enc = None
    if random_encoder_seed is not None:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(random_encoder_seed)
            random_enc = UNet3D(in_channels=4, out_channels=stage.encoder.out_channels).to(stage.device).eval()
    out: dict[str, list[Tensor]] = {k: [] for k in ("learned", "raw", "random", "labels", "boxes", "aabb", "scene")}
    cache = stage.crop_cache if random_enc is not None and stage.crops_cacheable() else None
    for batch in tqdm(loader, desc="object crops", disable=not progress, leave=False):
        batch = {k: v.to(stage.device) if isinstance(v, Tensor) else v for k, v in batch.items()}
        with stage.precision_context():  # as the stage's test_step encodes (and keys the crop cache)
            crops = stage.object_crops(batch, num_input_views, crop_size)
        out["learned"].append(crops["features"].float().cpu())
        out["raw"].append(crops["raw"].cpu())
        for k in ("labels", "boxes", "aabb", "scene"):
            out[k].append(crops[k].cpu())
        if random_enc is not None:
            out["random"].append(_random_encoder_crops(stage, random_enc, batch, num_input_views, crop_size, cache))
    stage.train(was_training)
    return {k: torch.cat(v) for k, v in out.items() if v}


def retrieval_table(
    crops: dict[str, Tensor], k: int = 10, num_angles: int = 36, search: str = RETRIEVAL_SEARCH
) -> tuple[dict[str, Any], dict[str, Tensor]]:
    """Leave-one-out rotation-max retrieval precision@k of every crop set in ``crops`` (paper Table 2).

    Args:
        crops: :func:`collect_object_crops` output (``labels`` and any of ``learned``, ``raw``, ``random``).
        k: neighbours per query (at most N - 1 are used).
        num_angles: yaw steps of the search.
        search: ``"fast"`` or ``"exact"`` (:func:`~threedq.quantization.rotation_search.all_pairs_rotation_max`).

    Returns:
        ``{"k", "k_requested", "num_angles", "search", "num_objects", "num_categories", "precision_at_k": {name: p}}``
        (``k`` is ``min(k_requested, N - 1)``: tables name it with :func:`threedq.pipeline.report.precision_label`) and the
        ``[N, N]`` similarity matrix of each crop set (for pictures). Categories with a single object still
        count as queries (they can only score 0), as in the paper's per-class average.
    """
    if search not in SEARCH_METHODS:
        raise ValueError(f"search: expected one of {SEARCH_METHODS}, got {search!r}")
    labels = crops["labels"]
    n = labels.shape[0]
    if n < 2:
        raise ValueError(f"need at least 2 objects to evaluate retrieval, got {n}")
    kk = min(k, n - 1)  # a split of N <= k objects is scored at k = N - 1; "k_requested" keeps what was asked
    table: dict[str, Any] = {
        "k": kk, "k_requested": k, "num_angles": num_angles, "search": search, "num_objects": n,
        "num_categories": int(labels.unique().numel()), "precision_at_k": {},
    }
    sims: dict[str, Tensor] = {}
    for name, key in FEATURE_SETS:
        if key in crops:
            sim, _ = all_pairs_rotation_max(crops[key], crops[key], num_angles, method=search)
            sims[name] = sim
            table["precision_at_k"][name] = float(retrieval_precision_at_k(sim, labels, labels, kk, exclude_diagonal=True))
    return table, sims


def evaluate_features(
    stage: EncoderStage,
    loader: torch.utils.data.DataLoader,
    num_input_views: int = 1,
    k: int = 10,
    num_angles: int = 36,
    search: str = RETRIEVAL_SEARCH,
    progress: bool = True,
) -> dict[str, Any]:
    """Crop every object of ``loader`` and score learned, raw and random-encoder crops with :func:`retrieval_table`."""
    crops = collect_object_crops(stage, loader, num_input_views=num_input_views, progress=progress)
    table, _ = retrieval_table(crops, k, num_angles, search)
    return {**table, "num_input_views": num_input_views}


def quantization_metrics(
    clusters: Tensor, angles: Tensor, num_angles: int, num_clusters: int, labels: Tensor, gt_yaw: Tensor | None,
    num_classes: int, symmetry_order: list[int], shots: int = 2, seed: int = 0,
) -> dict[str, float]:
    """Hungarian accuracy, few-shot accuracy and relative yaw error of one assignment.

    ``gt_yaw`` None (an assignment whose angles are not yaws, e.g. 2.5DQ-Nets' in-plane angles): the yaw fields
    are NaN and ``yaw_pairs`` 0.
    """
    conf = cluster_confusion(clusters, labels, num_clusters, num_classes)
    fs = few_shot_accuracy(clusters, labels, shots=shots, seed=seed, num_clusters=num_clusters)
    if gt_yaw is None:
        nan = float("nan")
        return {"hungarian_acc": float(hungarian_accuracy(conf)), "fewshot_acc": float(fs["accuracy"]),
                "yaw_median_deg": nan, "yaw_acc_10": nan, "yaw_acc_20": nan, "yaw_pairs": 0}
    est = yaw_angles(num_angles, dtype=torch.float64)[angles]
    yaw = relative_yaw_error(est, gt_yaw.double(), labels, clusters, symmetry_order)
    return {
        "hungarian_acc": float(hungarian_accuracy(conf)),
        "fewshot_acc": float(fs["accuracy"]),
        "yaw_median_deg": float(yaw["median_deg"]),
        "yaw_acc_10": float(yaw["acc_10"]),
        "yaw_acc_20": float(yaw["acc_20"]),
        "yaw_pairs": int(yaw["num_pairs"]),
    }
