"""Detection evaluation: dataset-level 3D mAP of pseudo-boxes and of a trained detector, and detection files.

:func:`evaluate_detection` is the ``detector_eval`` step of ``threedq em``: on the held-out split it scores
(a) the label-free pseudo-boxes of :mod:`threedq.proposals` and (b) the detector, at IoU 0.25 and 0.5
(:class:`~threedq.metrics.DetectionMAP`, accumulated over the whole split); it draws detections beside GT
on held-out scenes and writes the detector's boxes of the requested splits as ``detections_<split>.npz``
(``threedq em``: the test split, or every split with ``--boxes detections``; the
layout of :func:`threedq.data.box_files.save_boxes_file`), which later stages read through the DataModule's
``boxes`` option.

Convention: frame R (the record's world frame), metres, z up; boxes axis-aligned
``(xmin, ymin, zmin, xmax, ymax, zmax)``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from threedq.atomic_io import atomic_write_bytes, atomic_write_json
from threedq.boxes import boxes_to_aabb
from threedq.data.box_files import save_boxes_file
from threedq.data.proposal_cache import propose_dataset
from threedq.datamodules.scene_folder import SceneDataset
from threedq.metrics import DetectionMAP
from threedq.metrics.detection import assign_detections
from threedq.proposals import ProposalParams
from threedq.scene import load_scene
from threedq.stages.detector import detection_figure

__all__ = ["box_sets_map", "detect_split", "evaluate_detection", "precision_recall"]


def box_sets_map(
    data_dir: str | Path, files: list[str], box_sets: dict[str, tuple[np.ndarray, np.ndarray]],
    iou_thresholds: tuple[float, ...] = (0.25, 0.5), progress: bool = True,
) -> dict[str, float]:
    """Dataset-level mAP of per-scene boxes against the GT boxes' axis-aligned hulls.

    Args:
        data_dir: dataset folder; files: scene files (as in ``index.json``) to score;
        box_sets: ``{file -> (aabb [P,6], scores [P])}``.

    Returns:
        ``{"map_25", "map_50", "num_gt", "num_det"}`` (keys follow ``iou_thresholds``).
    """
    metric = DetectionMAP(iou_thresholds=iou_thresholds)
    for f in tqdm(files, desc="box mAP", disable=not progress, leave=False):
        if f not in box_sets:
            raise ValueError(f"box_sets: no boxes for scene {f}")
        rec = load_scene(Path(data_dir) / f, validate=False)
        gt = torch.from_numpy(boxes_to_aabb(rec.boxes.astype(np.float64)).astype(np.float32)).reshape(-1, 6)
        aabb, scores = box_sets[f]
        metric.update([{"boxes": torch.as_tensor(aabb).reshape(-1, 6), "scores": torch.as_tensor(scores).reshape(-1)}],
                      [{"boxes": gt}])  # fmt: skip
    return {k: (float(v) if v.is_floating_point() else int(v)) for k, v in metric.compute().items()}


@torch.no_grad()
def detect_split(
    stage: torch.nn.Module, loader: torch.utils.data.DataLoader, score_threshold: float | None = None,
    progress: bool = True,
) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], list[tuple[dict[str, Tensor], list[dict[str, Tensor]]]]]:
    """Run a :class:`~threedq.stages.detector.Detector` over a deterministic loader.

    Returns:
        ``{scene file -> (aabb [P,6], scores [P])}`` at ``score_threshold`` (default: the stage's) and the
        first batch with its detections (for pictures). The mAP is the stage's own (``trainer.test``).
    """
    was_training = stage.training
    stage.eval()
    files = loader.dataset.files
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    first: list = []
    for batch in tqdm(loader, desc="detect", disable=not progress, leave=False):
        batch = {k: v.to(stage.device) if isinstance(v, Tensor) else v for k, v in batch.items()}
        with stage.precision_context():  # as the stage's test_step runs (and keys the crop cache)
            logits, box = stage(batch)
        dets = stage.detect(logits, box, score_threshold)
        for i, d in zip(batch["scene_index"].tolist(), dets):
            out[files[i]] = (d["boxes"].cpu().numpy(), d["scores"].cpu().numpy())
        if not first:
            first.append((batch, dets))
    stage.train(was_training)
    return out, first


def precision_recall(
    data_dir: str | Path, box_sets: dict[str, tuple[np.ndarray, np.ndarray]], iou_threshold: float = 0.5
) -> dict[str, float | int]:
    """Precision and recall of a set of kept boxes against the GT boxes' axis-aligned hulls.

    Matching is :func:`~threedq.metrics.detection.assign_detections` (greedy by score, one GT per box): a second
    box on an already matched object, e.g. a box nested in it, is a false positive.

    Returns:
        ``{"precision", "recall", "boxes", "matched", "gt"}`` (precision is NaN with no boxes).
    """
    boxes = matched = gt_total = 0
    for f, (aabb, scores) in box_sets.items():
        rec = load_scene(Path(data_dir) / f, validate=False)
        gt = torch.from_numpy(boxes_to_aabb(rec.boxes.astype(np.float64)).astype(np.float32)).reshape(-1, 6)
        a = torch.as_tensor(aabb, dtype=torch.float32).reshape(-1, 6)
        gt_total += gt.shape[0]
        boxes += a.shape[0]
        if a.shape[0] and gt.shape[0]:
            matched += int((assign_detections(a, torch.as_tensor(scores).reshape(-1), gt, iou_threshold) >= 0).sum())
    return {"precision": matched / boxes if boxes else float("nan"), "recall": matched / max(gt_total, 1),
            "boxes": boxes, "matched": matched, "gt": gt_total}  # fmt: skip


def evaluate_detection(stage: Any, dm: Any, out_dir: str | Path, test_map: dict[str, float],
                       splits: tuple[str, ...] = ("train", "val", "test"), progress: bool = True) -> dict[str, Any]:  # fmt: skip
    """mAP of the pseudo-boxes on the test split beside the detector's, a detections picture, and detection files.

    Args:
        stage: a trained :class:`~threedq.stages.detector.Detector`; dm: its scene DataModule (set up).
        out_dir: receives ``results.json``, ``detections.png`` and ``detections_<split>.npz``.
        test_map: the detector's test metrics as its own ``test_step`` measured them (``trainer.test``:
            ``map_25``, ``map_50``, ``num_gt``, ``num_det``); the pseudo-boxes are scored here by the same
            :class:`~threedq.metrics.DetectionMAP`.

    Returns:
        ``{"pseudo_boxes": {...}, "detector": {...}, "detections": {split: path}, "handed_on": {split: precision,
        recall and counts of the boxes above the stage's score threshold at IoU 0.5}, "seconds"}``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    test_files = dm.index.files("test")
    pseudo = propose_dataset(dm.data_dir, "test", dm.data_dir / "proposals" / "test.npz",
                             params=ProposalParams(view_stride=2), progress=progress)  # fmt: skip
    result: dict[str, Any] = {
        "split": "test",
        "pseudo_boxes": box_sets_map(dm.data_dir, test_files, pseudo, progress=progress),
        "detector": dict(test_map),
    }
    files: dict[str, str] = {}
    handed_on: dict[str, dict[str, Any]] = {}
    for split in splits:
        if not dm.index.files(split):
            continue
        ds = SceneDataset(dm.data_dir, dm.index, split, num_input_views=dm.num_input_views,
                          num_target_views=0, max_objects=dm.max_objects, random_views=False, seed=dm.seed)  # fmt: skip
        loader = torch.utils.data.DataLoader(ds, batch_size=4, shuffle=False, num_workers=0)
        dets, first = detect_split(stage, loader, progress=progress)
        path = out / f"detections_{split}.npz"
        save_boxes_file(path, dets, json.dumps({"score_threshold": stage.hparams.score_threshold}))
        files[split] = str(path)
        # the boxes handed on to mining and quantization (GT used for measuring only)
        handed_on[split] = {"score_threshold": stage.hparams.score_threshold, **precision_recall(dm.data_dir, dets)}
        if split == "test":
            kept = sum(len(s) for _, s in dets.values())
            result["detector"]["boxes_kept_at_score_threshold"] = kept
            batch, d = first[0]
            img = detection_figure(batch, d, max_scenes=4)
            ok, png = cv2.imencode(".png", img[:, :, ::-1])
            if ok:
                atomic_write_bytes(out / "detections.png", png.tobytes())
    result["detections"] = files
    result["handed_on"] = handed_on
    result["seconds"] = round(time.time() - t0, 1)
    atomic_write_json(out / "results.json", result)
    return result
