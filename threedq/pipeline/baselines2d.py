"""The 2D baselines of the paper's tables, measured on the same test objects as threedq (``threedq eval``).

* 2.5DQ-Nets (Tables 1 and 4, Fig. 3a): a :class:`~threedq.stages.q25d.Q25D` checkpoint (``--q25d``) crops every
  object out of its 2D feature map; a bank fitted on the training crops (one-slice crops: an in-plane search) scores
  the test crops (:func:`~threedq.pipeline.evaluation.quantization_metrics`).
* ImageNet ResNet-18 (Tables 1 and 2; ``--weights``) or the MobileNetV2 stand-in: features pooled in each projected
  GT box; retrieval precision@10 by cosine without rotation, few-shot "ResNetRet" and "ResNetClass".

Objects come in the order of the same deterministic loaders as the 3D crops (the caller checks the labels agree).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm import tqdm

from threedq.baselines.backbone import backbone_fields, load_backbone
from threedq.baselines.imagenet import object_features
from threedq.errors import InputError
from threedq.geometry import project_boxes_2d
from threedq.metrics import cluster_confusion, hungarian_accuracy, linear_probe_accuracy, nearest_shot_accuracy
from threedq.metrics.retrieval import retrieval_precision_at_k, same_object_top1
from threedq.pipeline.evaluation import quantization_metrics
from threedq.quantization.prototypes import fit_prototype_bank
from threedq.stages.checkpoint import checkpoint_hparams, checkpoint_stage, checkpoint_state
from threedq.stages.q25d import Q25D

__all__ = ["Q25D_HOWTO", "RESNET_HOWTO", "collect_q25d_crops", "backbone_fields", "collect_resnet_features",
           "load_q25d", "q25d_results", "resnet_paper_results", "resnet_results"]

#: What the tables say when the 2.5DQ-Nets rows were not computed.
Q25D_HOWTO = ("not run: train it with `threedq fit --config stages/q25d.yaml` (same data), then add "
              "`--q25d runs/q25d/checkpoints/last.ckpt` to `threedq eval`")
#: What the tables say when the ResNet-18 rows were not computed.
RESNET_HOWTO = ("needs --weights (a torchvision resnet18 ImageNet file, e.g. resnet18-f37072fd.pth, or the ImageNet "
                "MobileNetV2 stand-in: docs/studies/imagenet.md)")


def load_q25d(path: str | Path) -> Q25D:
    """A :class:`Q25D` with the weights and hyperparameters of a ``threedq fit --config stages/q25d.yaml`` checkpoint.

    Raises:
        InputError: no such file, not loadable with ``weights_only=True``, or another stage's checkpoint.
    """
    if not Path(path).is_file():
        raise InputError(f"--q25d {path}: no such file")
    stage = checkpoint_stage(path)
    if stage != "q25d":
        kind = f"a {stage}" if stage else "not a stage"
        raise InputError(f"{path}: this is {kind} checkpoint; --q25d needs a 2.5DQ-Nets (stages/q25d.yaml) checkpoint")
    hp = checkpoint_hparams(path)
    keys = ("feature_dim", "depth_range", "depth_weight", "crop_size", "lr")
    model = Q25D(**{k: (tuple(hp[k]) if k == "depth_range" else hp[k]) for k in keys if k in hp})
    state = checkpoint_state(path)
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as e:
        raise InputError(f"{path}: field 'state_dict': does not fit a Q25D ({str(e).splitlines()[0][:200]})") from e
    return model.eval()


@torch.no_grad()
def collect_q25d_crops(model: Q25D, loader: torch.utils.data.DataLoader, progress: bool = True) -> dict[str, Tensor]:
    """Every GT object of ``loader`` as a 2.5DQ crop: ``features`` ``[N, F, 1, s, s]`` (one-slice volumes, the
    prototype bank's layout), ``labels`` ``[N]``, ``visible`` ``[N]`` bool."""
    model.eval()
    out: dict[str, list[Tensor]] = {"features": [], "labels": [], "visible": []}
    for batch in tqdm(loader, desc="2.5DQ crops", disable=not progress, leave=False):
        c = model.object_crops({k: v.to(model.device) if isinstance(v, Tensor) else v for k, v in batch.items()})
        out["features"].append(c["features"].unsqueeze(2).cpu())
        for k in ("labels", "visible"):
            out[k].append(c[k].cpu())
    return {k: torch.cat(v) for k, v in out.items()}


@torch.no_grad()
def collect_resnet_features(net: torch.nn.Module, loader: torch.utils.data.DataLoader, progress: bool = True,
                            view: int = 0) -> dict[str, Tensor]:
    """ImageNet box-pooled features of every GT object of ``loader`` in one view.

    Args:
        net: :class:`~threedq.baselines.resnet.ResNet18` or :class:`~threedq.baselines.mobilenet.MobileNetV2`
            (:func:`~threedq.baselines.backbone.load_backbone`).
        loader: SceneDataset batches (``rgb`` ``[B, V, 3, H, W]``, ``boxes`` ``[B, M, 7]``, ``K``, ``R_T_cam``,
            ``box_mask``, ``categories``).
        view: which view's image (0: the input view; ``num_input_views``: the paper protocol's gallery view).

    Returns:
        ``features`` ``[N, C]`` (C = 512 ResNet-18, 1280 MobileNetV2), ``labels`` ``[N]``, ``visible`` ``[N]`` bool,
        ``boxes`` ``[N, 7]`` (the 3D boxes) and ``scene`` ``[N]`` (index in the split), objects in loader order.

    Convention: each object's oriented GT box projected into the view (:func:`~threedq.geometry.project_boxes_2d`).
    """
    net.eval()
    device = next(net.parameters()).device
    out: dict[str, list[Tensor]] = {"features": [], "labels": [], "visible": [], "boxes": [], "scene": []}
    for batch in tqdm(loader, desc=f"{getattr(net, 'label', 'ImageNet')} features", disable=not progress, leave=False):
        rgb, boxes, K, pose = (batch[k].to(device) for k in ("rgb", "boxes", "K", "R_T_cam"))
        if rgb.shape[1] <= view:
            raise ValueError(f"view {view}: the loader's samples hold {rgb.shape[1]} view(s)")
        rgb = rgb[:, view]
        boxes2d, visible = project_boxes_2d(boxes, K[:, view], pose[:, view], rgb.shape[-2:])
        f = object_features(net, rgb, boxes2d)
        mask = batch["box_mask"].to(device)
        out["features"].append(f[mask].cpu())
        out["labels"].append(batch["categories"][batch["box_mask"]])
        out["visible"].append(visible[mask].cpu())
        out["boxes"].append(batch["boxes"][batch["box_mask"]])
        out["scene"].append(batch["scene_index"][:, None].expand_as(batch["box_mask"])[batch["box_mask"]])
    return {k: torch.cat(v) for k, v in out.items()}


def q25d_results(train: dict[str, Tensor], test: dict[str, Tensor], K: int, num_angles: int, num_classes: int,
                 curve_k: list[int] | None = None, em_iterations: int = 10, seed: int = 0,
                 shots: int = 2) -> tuple[dict[str, Any], dict[str, float]]:
    """Fit 2D banks on ``train`` crops (K, and each K of ``curve_k``), score ``test`` crops.

    Returns:
        The Table 4 / Table 1 row (:func:`quantization_metrics`, yaw fields NaN: an in-plane angle is not a yaw)
        and ``{str(k): Hungarian accuracy}`` for the curve.
    """
    labels = test["labels"]
    bank = fit_prototype_bank(train["features"], min(K, train["features"].shape[0]), iterations=em_iterations,
                              num_angles=num_angles, seed=seed)
    res = bank.assign(test["features"])
    row = quantization_metrics(res.prototype, res.angle, num_angles, bank.active.numel(), labels, None, num_classes,
                               [], shots=shots, seed=seed)
    row["not_visible"] = int((~test["visible"]).sum())
    curve: dict[str, float] = {}
    for k in [k for k in (curve_k or []) if k <= train["features"].shape[0]]:
        b = fit_prototype_bank(train["features"], k, iterations=em_iterations, num_angles=num_angles, seed=seed)
        curve[str(k)] = float(hungarian_accuracy(cluster_confusion(b.assign(test["features"]).prototype, labels, k,
                                                                   num_classes)))
    return row, curve


def resnet_results(test: dict[str, Tensor], k: int = 10, shots: int = 2, seed: int = 0) -> dict[str, Any]:
    """Retrieval precision@k (cosine, no rotation, leave-one-out) and few-shot Ret / Class accuracy of the
    test objects' ImageNet features (``test``: :func:`collect_resnet_features`, ``features`` ``[N, C]``)."""
    feats, labels = test["features"].double(), test["labels"]
    n = labels.shape[0]
    if n < 2:
        raise ValueError(f"need at least 2 objects to evaluate retrieval, got {n}")
    f = torch.nn.functional.normalize(feats, dim=1)
    kk = min(k, n - 1)
    return {"precision_at_k": float(retrieval_precision_at_k(f @ f.T, labels, labels, kk, exclude_diagonal=True)),
            "k": kk, "k_requested": k, "num_objects": n,
            "ret_acc": float(nearest_shot_accuracy(feats, labels, shots, seed)["accuracy"]),
            "class_acc": float(linear_probe_accuracy(feats, labels, shots, seed)["accuracy"]),
            "not_visible": int((~test["visible"]).sum())}


def resnet_paper_results(query: dict[str, Tensor], gallery: dict[str, Tensor], k: int = 10) -> dict[str, float]:
    """The paper retrieval protocol on ImageNet features: the gallery the same objects from the second view.

    Args:
        query, gallery: ``features`` ``[N, C]`` and ``labels`` ``[N]``, row ``i`` of both the same object.
        k: neighbours per query (at most N - 1, as the strict protocol).

    Returns:
        ``paper_precision_at_k`` (cosine, no rotation search) and ``same_object_top1`` (the twin is the nearest).

    Raises:
        ValueError: the two hold other objects (labels differ) or fewer than 2.
    """
    labels = query["labels"]
    if not torch.equal(labels, gallery["labels"]):
        raise ValueError("the gallery view's objects differ from the query view's")
    n = labels.shape[0]
    if n < 2:
        raise ValueError(f"need at least 2 objects to evaluate retrieval, got {n}")
    fq, fg = (torch.nn.functional.normalize(d["features"].double(), dim=1) for d in (query, gallery))
    sim = fq @ fg.T
    return {"paper_precision_at_k": float(retrieval_precision_at_k(sim, labels, labels, min(k, n - 1))),
            "same_object_top1": float(same_object_top1(sim))}


def load_resnet(weights: str | Path) -> torch.nn.Module:
    """The ImageNet backbone of a ``--weights`` file (:func:`~threedq.baselines.backbone.load_backbone`)."""
    return load_backbone(weights)
