"""Evaluation of learned 3D features on held-out scenes (paper Table 2, GT or detected boxes).

Each object's box is cropped out of the scene's feature grid (16^3) and crops are compared at their best relative yaw
(36 steps); :func:`retrieval_table` scores rotation-max precision@10, macro over categories, under both protocols of
:mod:`threedq.metrics.retrieval` with each pool's perfect-feature ceiling, beside raw ``cat[occ, occ * rgb]`` crops, a
random encoder and a colour + size descriptor; :func:`probe_table` adds a linear probe on the frozen features.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm import tqdm

from threedq.baselines.descriptor import colour_size_descriptor, descriptor_similarity
from threedq.geometry import crop_boxes, yaw_angles
from threedq.metrics import cluster_confusion, few_shot_accuracy, hungarian_accuracy, linear_probe, relative_yaw_error
from threedq.metrics.retrieval import precision_ceiling, retrieval_precision_at_k, same_object_top1
from threedq.nets import UNet3D
from threedq.quantization.rotation_search import SEARCH_METHODS, all_pairs_rotation_max
from threedq.stages.base import EncoderStage
from threedq.stages.crop_cache import CropCache, sample_key

__all__ = ["RETRIEVAL_SEARCH", "SEARCH_LABELS", "collect_object_crops", "probe_table", "quantization_metrics",
           "retrieval_table"]

#: The rotation search every retrieval table of threedq uses unless told otherwise.
RETRIEVAL_SEARCH = "fast"
#: How a table header names each search.
SEARCH_LABELS = {"fast": "fast search (cylindrical resampling + FFT over yaw; cosine over the inscribed cylinder)",
                 "exact": "exact search (every crop rotated by every yaw; cosine over the full cube)"}
#: Crop sets of :func:`collect_object_crops` and their names in result tables.
FEATURE_SETS = (("learned", "learned"), ("raw_rgb_occupancy", "raw"), ("random_encoder", "random"))
#: The hand-made reference's name in result tables (computed from the ``raw`` crops and the boxes).
DESCRIPTOR = "colour_size_descriptor"
#: What the paper protocol's gallery is, as tables say it.
GALLERY_VIEW = "each scene's second fixed view (the first view after the input views)"


def _random_encoder_crops(stage: EncoderStage, random_enc: UNet3D, batch: dict[str, Tensor], v: int, crop_size: int,
                          cache: CropCache | None) -> Tensor:
    """Crops of ``batch``'s valid boxes from ``random_enc``'s features (view mean, L2-normalised), on the CPU."""
    mask = batch["box_mask"]
    B = mask.shape[0]
    if cache is not None:
        prefix, fp = stage.crop_cache_prefix(), cache.fingerprint(random_enc)
        keys = [("random", prefix, fp, sample_key(batch, b, v, crop_size)) for b in range(B)]
        hit = cache.get_many(keys)
        if hit is not None:
            return torch.cat(hit)
    x, _ = stage.views_input(*(batch[k][:, :v] for k in ("rgb", "depth", "K", "R_T_cam")))
    rf = random_enc(x).view(B, v, -1, *stage.feature_grid.volume_shape).mean(1)
    rand = crop_boxes(F.normalize(rf, dim=1), batch["aabb"], stage.feature_grid, crop_size, mask=mask)
    if cache is not None:
        for b, r in enumerate(rand.split(mask.sum(1).tolist())):
            cache.put(keys[b], r)
    return rand.cpu()


def _descriptor(crops: dict[str, Tensor], prefix: str = "") -> Tensor:
    """The colour + size descriptor of ``crops``' objects (of ``gallery_`` ones with that ``prefix``)."""
    return colour_size_descriptor(crops[f"{prefix}raw"], crops["aabb"])


def _single_view(batch: dict[str, Tensor], view: int) -> dict[str, Tensor]:
    """``batch`` with view ``view`` of every sample as its only view (the boxes, in frame R, are the same)."""
    out = dict(batch)
    for k in ("rgb", "depth", "K", "R_T_cam", "view_ids", "instance"):
        if k in batch and isinstance(batch[k], Tensor):
            out[k] = batch[k][:, view : view + 1]
    return out


@torch.no_grad()
def collect_object_crops(stage: EncoderStage, loader: torch.utils.data.DataLoader, num_input_views: int = 1,
                         crop_size: int = 16, random_encoder_seed: int | None = 0, progress: bool = True,
                         gallery: bool = False) -> dict[str, Tensor]:
    """Crop every GT object of every scene of ``loader`` out of three volumes.

    Args:
        stage: a stage with a (trained) encoder.
        loader: yields SceneDataset batches; the first ``num_input_views`` views are encoded.
        num_input_views: views aggregated per scene (the paper tests with one).
        crop_size: crops are ``crop_size^3``.
        random_encoder_seed: seed of the randomly initialised reference encoder (None: skip it).
        gallery: also crop the same boxes out of the grid of each scene's view ``num_input_views`` alone (the paper
            protocol's gallery, row ``i`` the twin of query ``i``).

    Returns:
        ``learned`` ``[N, C, s, s, s]``, ``raw`` ``[N, 4, s, s, s]``, ``random`` ``[N, C, s, s, s]`` (if
        requested), ``labels`` ``[N]``, ``boxes`` ``[N, 7]`` oriented GT boxes, ``aabb`` ``[N, 6]`` the cropped
        boxes (GT hulls, or the given boxes), ``scene`` ``[N]`` (index in the split); with ``gallery`` also
        ``gallery_learned``, ``gallery_raw`` and ``gallery_random`` (if requested) of the second view.

    Convention: boxes axis-aligned in R (z up), cropped as their tight hull.
    """
    was_training = stage.training
    stage.eval()
    random_enc = None
    if random_encoder_seed is not None:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(random_encoder_seed)
            random_enc = UNet3D(in_channels=4, out_channels=stage.encoder.out_channels, channels=stage.encoder.channels,
                                output_stride=stage.encoder.output_stride).to(stage.device).eval()
    keys = ("learned", "raw", "random", "labels", "boxes", "aabb", "scene", "gallery_learned", "gallery_raw",
            "gallery_random")
    out: dict[str, list[Tensor]] = {k: [] for k in keys}
    cache = stage.crop_cache if random_enc is not None and stage.crops_cacheable() else None
    v = num_input_views
    for batch in tqdm(loader, desc="object crops", disable=not progress, leave=False):
        batch = {k: t.to(stage.device) if isinstance(t, Tensor) else t for k, t in batch.items()}
        with stage.precision_context():
            crops = stage.object_crops(batch, v, crop_size)
            if gallery:
                if batch["rgb"].shape[1] <= v:
                    raise ValueError(f"gallery: the loader's samples hold {batch['rgb'].shape[1]} view(s), the paper "
                                     f"protocol needs a view after the {v} input view(s) (split_loader(gallery=True))")
                other = _single_view(batch, v)
                g = stage.object_crops(other, 1, crop_size)
                out["gallery_learned"].append(g["features"].float().cpu())
                out["gallery_raw"].append(g["raw"].cpu())
        out["learned"].append(crops["features"].float().cpu())
        out["raw"].append(crops["raw"].cpu())
        for k in ("labels", "boxes", "aabb", "scene"):
            out[k].append(crops[k].cpu())
        if random_enc is not None:
            out["random"].append(_random_encoder_crops(stage, random_enc, batch, v, crop_size, cache))
            if gallery:
                out["gallery_random"].append(_random_encoder_crops(stage, random_enc, other, 1, crop_size, cache))
    stage.train(was_training)
    return {k: torch.cat(v) for k, v in out.items() if v}


def _scores(sim: Tensor, labels: Tensor, k: int, protocol: str) -> float:
    return float(retrieval_precision_at_k(sim, labels, labels, k, exclude_diagonal=protocol == "strict"))


def retrieval_table(crops: dict[str, Tensor], k: int = 10, num_angles: int = 36, search: str = RETRIEVAL_SEARCH,
                    coarse_labels: Tensor | None = None) -> tuple[dict[str, Any], dict[str, Tensor]]:
    """Rotation-max retrieval precision@k of every crop set in ``crops`` under both protocols (paper Table 2).

    Args:
        crops: :func:`collect_object_crops` output (``labels`` and any of ``learned``, ``raw``, ``random``; with
            ``gallery_<set>`` the paper protocol is scored too; with ``raw`` and ``aabb`` the colour + size
            descriptor row).
        k: neighbours per query (at most N - 1 are used, under both protocols).
        num_angles: yaw steps of the search.
        search: ``"fast"`` or ``"exact"`` (:func:`~threedq.quantization.rotation_search.all_pairs_rotation_max`).
        coarse_labels: ``[N]`` coarser category ids (:func:`threedq.data.catalog.coarse_category`) for an extra,
            marked paper-protocol row of the learned features; None: no such row.

    Returns:
        The table: ``{"k", "k_requested", "num_angles", "search", "num_objects", "num_categories",
        "precision_at_k": {name: p} (strict), "protocols": {protocol: {"pool", "ceiling", "precision_at_k":
        {name: p}, ["same_object_top1": {name: rate}, "gallery", "coarse"]}}}`` (``k`` is ``min(k_requested, N - 1)``);
        and the similarity matrices, ``{name: [N, N]}`` of the strict protocol and ``{"paper/<name>": [N, N]}``
        (query x gallery).
    """
    if search not in SEARCH_METHODS:
        raise ValueError(f"search: expected one of {SEARCH_METHODS}, got {search!r}")
    labels = crops["labels"]
    n = labels.shape[0]
    if n < 2:
        raise ValueError(f"need at least 2 objects to evaluate retrieval, got {n}")
    kk = min(k, n - 1)
    protocols: dict[str, dict[str, Any]] = {
        "strict": {"pool": n, "precision_at_k": {}, "ceiling": float(precision_ceiling(labels, labels, kk, True))}}
    paper = any(f"gallery_{key}" in crops for _, key in FEATURE_SETS)
    if paper:
        protocols["paper"] = {"pool": n, "gallery": GALLERY_VIEW, "precision_at_k": {}, "same_object_top1": {},
                              "ceiling": float(precision_ceiling(labels, labels, kk, False))}
    sims: dict[str, Tensor] = {}

    def score(name: str, protocol: str, sim: Tensor) -> None:
        protocols[protocol]["precision_at_k"][name] = _scores(sim, labels, kk, protocol)
        if protocol == "paper":
            protocols[protocol]["same_object_top1"][name] = float(same_object_top1(sim))
        sims[name if protocol == "strict" else f"paper/{name}"] = sim

    for name, key in FEATURE_SETS:
        if key in crops:
            score(name, "strict", all_pairs_rotation_max(crops[key], crops[key], num_angles, method=search)[0])
        if f"gallery_{key}" in crops:
            score(name, "paper", all_pairs_rotation_max(crops[key], crops[f"gallery_{key}"], num_angles,
                                                        method=search)[0])
    if "raw" in crops and "aabb" in crops:
        d = _descriptor(crops)
        score(DESCRIPTOR, "strict", descriptor_similarity(d, d))
        if "gallery_raw" in crops:
            score(DESCRIPTOR, "paper", descriptor_similarity(d, _descriptor(crops, "gallery_")))
    if paper and coarse_labels is not None and "paper/learned" in sims:
        if coarse_labels.shape != labels.shape:
            raise ValueError(f"coarse_labels: expected [{n}], got {tuple(coarse_labels.shape)}")
        protocols["paper"]["coarse"] = {
            "num_classes": int(coarse_labels.unique().numel()),
            "ceiling": float(precision_ceiling(coarse_labels, coarse_labels, kk, False)),
            "precision_at_k": {"learned": float(retrieval_precision_at_k(sims["paper/learned"], coarse_labels,
                                                                         coarse_labels, kk))}}
    table: dict[str, Any] = {"k": kk, "k_requested": k, "num_angles": num_angles, "search": search, "num_objects": n,
                             "num_categories": int(labels.unique().numel()),
                             "precision_at_k": dict(protocols["strict"]["precision_at_k"]), "protocols": protocols}
    return table, sims


def pooled_features(crops: dict[str, Tensor]) -> dict[str, Tensor]:
    """``{name: [N, D]}`` what the linear probe reads: each crop set averaged over its voxels, and the descriptor."""
    out = {name: crops[key].flatten(2).mean(2) for name, key in FEATURE_SETS if key in crops}
    if "raw" in crops and "aabb" in crops:
        out[DESCRIPTOR] = _descriptor(crops)
    return out


def probe_table(train: dict[str, Tensor], test: dict[str, Tensor]) -> dict[str, Any]:
    """Linear-probe accuracy (:func:`threedq.metrics.linear_probe`) of every feature set both splits hold, trained on
    the labelled training objects: ``{"train_objects", "test_objects", "accuracy": {name: acc}}``."""
    keep = train["labels"] >= 0
    tr = {name: f[keep] for name, f in pooled_features(train).items()}
    te = pooled_features(test)
    acc = {name: float(linear_probe(tr[name], train["labels"][keep], te[name], test["labels"])["accuracy"])
           for name in te if name in tr}
    return {"train_objects": int(keep.sum()), "test_objects": int(test["labels"].shape[0]), "accuracy": acc}


def quantization_metrics(clusters: Tensor, angles: Tensor, num_angles: int, num_clusters: int, labels: Tensor,
                         gt_yaw: Tensor | None, num_classes: int, symmetry_order: list[int], shots: int = 2,
                         seed: int = 0) -> dict[str, float]:
    """Hungarian accuracy, few-shot accuracy and relative yaw error of one assignment.

    ``gt_yaw`` None (angles that are not yaws): the yaw fields are NaN and ``yaw_pairs`` 0.
    """
    conf = cluster_confusion(clusters, labels, num_clusters, num_classes)
    fs = few_shot_accuracy(clusters, labels, shots=shots, seed=seed, num_clusters=num_clusters)
    if gt_yaw is None:
        nan = float("nan")
        return {"hungarian_acc": float(hungarian_accuracy(conf)), "fewshot_acc": float(fs["accuracy"]),
                "yaw_median_deg": nan, "yaw_acc_10": nan, "yaw_acc_20": nan, "yaw_pairs": 0}
    est = yaw_angles(num_angles, dtype=torch.float64)[angles]
    yaw = relative_yaw_error(est, gt_yaw.double(), labels, clusters, symmetry_order)
    return {"hungarian_acc": float(hungarian_accuracy(conf)), "fewshot_acc": float(fs["accuracy"]),
            "yaw_median_deg": float(yaw["median_deg"]), "yaw_acc_10": float(yaw["acc_10"]),
            "yaw_acc_20": float(yaw["acc_20"]), "yaw_pairs": int(yaw["num_pairs"])}
