"""Detection evaluation: dataset-level 3D mAP of pseudo-boxes and of a trained detector, and detection files.

:func:`evaluate_detection` is the ``detector_eval`` step of ``threedq em``: it scores the label-free pseudo-boxes
and the detector on the test split at IoU 0.25 and 0.5, measures what each box set finds per object size band, draws
detections beside GT and writes the detector's boxes of each split as ``detections_<split>.npz``
(:func:`threedq.data.box_files.save_boxes_file`), which later stages read through the DataModule's ``boxes`` option.

Convention: frame R (the record's world frame), metres, z up; boxes axis-aligned
``(xmin, ymin, zmin, xmax, ymax, zmax)``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from threedq.atomic_io import atomic_write_json
from threedq.box_refinement import observed_boxes
from threedq.boxes import boxes_to_aabb
from threedq.data.box_files import save_boxes_file
from threedq.metrics import DetectionMAP
from threedq.metrics.detection import assign_detections
from threedq.metrics.localisation import by_size_band, localisation_errors
from threedq.scene import load_scene, load_scene_boxes
from threedq.stages.detector import boxes_of_batch
from threedq.viz.detection import detection_figure, size_band_figure
from threedq.viz.png import write_png

__all__ = ["box_sets_map", "detect_split", "evaluate_detection", "gt_hulls", "precision_recall",
           "single_view_pseudo_boxes", "size_band_table"]


def gt_hulls(data_dir: str | Path, files: list[str]) -> dict[str, np.ndarray]:
    """``{file -> [G, 6]}`` the axis-aligned hulls of each scene's GT boxes (float64)."""
    return {f: boxes_to_aabb(load_scene_boxes(Path(data_dir) / f).astype(np.float64)).reshape(-1, 6) for f in files}


def box_sets_map(gt: dict[str, np.ndarray], box_sets: dict[str, tuple[np.ndarray, np.ndarray]],
                 iou_thresholds: tuple[float, ...] = (0.25, 0.5), progress: bool = True) -> dict[str, float]:
    """Dataset-level mAP of per-scene boxes against the GT boxes' axis-aligned hulls.

    Args:
        gt: ``{file -> [G, 6]}`` GT hulls of the scenes to score (:func:`gt_hulls`), in order;
        box_sets: ``{file -> (aabb [P,6], scores [P])}``.

    Returns:
        ``{"map_25", "map_50", "num_gt", "num_det"}`` (keys follow ``iou_thresholds``).
    """
    metric = DetectionMAP(iou_thresholds=iou_thresholds)
    for f, hulls in tqdm(gt.items(), desc="box mAP", disable=not progress, leave=False):
        if f not in box_sets:
            raise ValueError(f"box_sets: no boxes for scene {f}")
        aabb, scores = box_sets[f]
        metric.update([{"boxes": torch.as_tensor(aabb).reshape(-1, 6), "scores": torch.as_tensor(scores).reshape(-1)}],
                      [{"boxes": torch.from_numpy(hulls.astype(np.float32))}])
    return {k: (float(v) if v.is_floating_point() else int(v)) for k, v in metric.compute().items()}


@torch.no_grad()
def detect_split(
    stage: torch.nn.Module, loader: torch.utils.data.DataLoader, score_threshold: float | None = None,
    progress: bool = True, input_views: dict[str, list[int]] | None = None,
    targets: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], list[tuple[dict[str, Tensor], list[dict[str, Tensor]]]]]:
    """Run a :class:`~threedq.stages.detector.Detector` over a deterministic loader.

    Args:
        input_views: when given, filled with ``{scene file -> the view indices the detector saw}``.
        targets: ``{scene file -> (aabb [Q, 6], scores [Q])}`` to refine against instead of the input views'
            pseudo-boxes (a ``refine_to: scene`` detector's, :meth:`~threedq.stages.detector.Detector.scene_targets`).

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
        with stage.precision_context():
            logits, box = stage(batch)
        scene = None if targets is None else boxes_of_batch(targets, files, batch["scene_index"],
                                                           "targets: no pseudo-boxes for ")
        dets = stage.detect(logits, box, score_threshold, views=stage.input_of(batch), targets=scene)
        for j, (i, d) in enumerate(zip(batch["scene_index"].tolist(), dets)):
            out[files[i]] = (d["boxes"].cpu().numpy(), d["scores"].cpu().numpy())
            if input_views is not None:
                input_views[files[i]] = batch["view_ids"][j, : int(batch["num_input_views"][j])].tolist()
        if not first:
            first.append((batch, dets))
    stage.train(was_training)
    return out, first


def precision_recall(gt: dict[str, np.ndarray], box_sets: dict[str, tuple[np.ndarray, np.ndarray]],
                     iou_threshold: float = 0.5) -> dict[str, float | int]:
    """Precision and recall of a set of kept boxes against the GT hulls (:func:`gt_hulls`) of their scenes, matched by
    :func:`~threedq.metrics.detection.assign_detections` (a second box on a matched object is a false positive).

    Returns:
        ``{"precision", "recall", "boxes", "matched", "gt"}`` (precision is NaN with no boxes).
    """
    boxes = matched = gt_total = 0
    for f, (aabb, scores) in box_sets.items():
        g = torch.from_numpy(gt[f].astype(np.float32))
        a = torch.as_tensor(aabb, dtype=torch.float32).reshape(-1, 6)
        gt_total += g.shape[0]
        boxes += a.shape[0]
        if a.shape[0] and g.shape[0]:
            matched += int((assign_detections(a, torch.as_tensor(scores).reshape(-1), g, iou_threshold) >= 0).sum())
    return {"precision": matched / boxes if boxes else float("nan"), "recall": matched / max(gt_total, 1),
            "boxes": boxes, "matched": matched, "gt": gt_total}


def single_view_pseudo_boxes(data_dir: str | Path, views: dict[str, list[int]], bounds: Any = None,
                             progress: bool = True, align_floor: bool = False,
                             ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The label-free pseudo-boxes (:func:`~threedq.box_refinement.observed_boxes`) of each scene from only the views
    a detector sees (``{file -> view indices}``); ``align_floor``: poses corrected by the floor (sensor captures).
    """
    from threedq.datamodules.scene_folder import sensor_corrections

    out = {}
    for f, v in tqdm(sorted(views.items()), desc="single-view pseudo-boxes", disable=not progress, leave=False):
        path = Path(data_dir) / f
        rec = load_scene(path, validate=False)
        idx = np.asarray(v, dtype=np.int64)
        poses = sensor_corrections(path, rec)[0] if align_floor else rec.world_T_cam
        out[f] = observed_boxes(rec.depth[idx], rec.K[idx], poses[idx], bounds)
    return out


def size_band_table(gt: dict[str, np.ndarray], box_sets: dict[str, tuple[np.ndarray, np.ndarray]],
                    flat_height: float | None = None) -> list[dict[str, Any]]:
    """:func:`~threedq.metrics.localisation.by_size_band` of per-scene boxes against the GT hulls (:func:`gt_hulls`);
    ``flat_height``: also the row of the objects less tall than this."""
    per_scene = []
    for f, (aabb, scores) in box_sets.items():
        per_scene.append(localisation_errors(torch.as_tensor(aabb, dtype=torch.float64).reshape(-1, 6),
                                             torch.as_tensor(scores, dtype=torch.float64).reshape(-1),
                                             torch.from_numpy(gt[f])))
    return by_size_band(per_scene, flat_height=flat_height)


def evaluate_detection(stage: Any, dm: Any, out_dir: str | Path, test_map: dict[str, float],
                       splits: tuple[str, ...] = ("train", "val", "test"), progress: bool = True,
                       ) -> dict[str, Any]:
    """mAP of the pseudo-boxes on the test split beside the detector's, a detections picture, and detection files.

    Args:
        stage: a trained :class:`~threedq.stages.detector.Detector`; dm: its scene DataModule (set up).
        out_dir: receives ``results.json``, ``detections.png`` and ``detections_<split>.npz``.
        test_map: the detector's test metrics as its own ``test_step`` measured them (``map_25``, ``map_50``,
            ``num_gt``, ``num_det``).

    Returns:
        ``{"pseudo_boxes", "pseudo_boxes_single_view", "detector": {...}, "by_size": [{"boxes", "rows"}],
        "flat_objects", "detections": {split: path}, "handed_on": {split: precision, recall and counts}, "seconds"}``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    gt_test = gt_hulls(dm.data_dir, dm.index.files("test"))
    pseudo = dm.pseudo_boxes("test", progress=progress)
    result: dict[str, Any] = {"split": "test", "pseudo_boxes": box_sets_map(gt_test, pseudo, progress=progress),
                              "detector": dict(test_map)}
    files: dict[str, str] = {}
    handed_on: dict[str, dict[str, Any]] = {}
    for split in splits:
        if not dm.index.files(split):
            continue
        ds = dm.fixed_view_dataset(split, with_boxes=False)
        loader = torch.utils.data.DataLoader(ds, batch_size=4, shuffle=False, num_workers=0)
        views: dict[str, list[int]] = {}
        targets = dm.pseudo_boxes(split, progress=progress) if stage.hparams.get("refine_to") == "scene" else None
        dets, first = detect_split(stage, loader, progress=progress, input_views=views, targets=targets)
        path = out / f"detections_{split}.npz"
        save_boxes_file(path, dets, json.dumps({"score_threshold": stage.hparams.score_threshold}))
        files[split] = str(path)
        gt = gt_test if split == "test" else gt_hulls(dm.data_dir, ds.files)
        handed_on[split] = {"score_threshold": stage.hparams.score_threshold, **precision_recall(gt, dets)}
        if split == "test":
            result["detector"]["boxes_kept_at_score_threshold"] = sum(len(s) for _, s in dets.values())
            fg = stage.feature_grid
            single = single_view_pseudo_boxes(dm.data_dir, views, (fg.bounds_min, fg.bounds_max), progress=progress,
                                              align_floor=getattr(dm, "sensor_captures", False))
            result["pseudo_boxes_single_view"] = box_sets_map(gt, single, progress=progress)
            flat = float(stage.min_box_height) if stage.min_box_height > 0 else None
            tables = {"pseudo-boxes (all views)": size_band_table(gt, pseudo, flat),
                      "pseudo-boxes (input view)": size_band_table(gt, single, flat),
                      f"detector (score >= {stage.hparams.score_threshold:g})": size_band_table(gt, dets, flat)}
            result["by_size"] = [{"boxes": name, "rows": rows} for name, rows in tables.items()]
            rows = tables["pseudo-boxes (all views)"]
            result["flat_objects"] = {"min_box_height": stage.min_box_height,
                                      "objects": rows[-2]["objects"] if flat else 0, "of": rows[-1]["objects"],
                                      "flat_boxes": bool(stage.hparams.flat_boxes)}
            write_png(out / "detection_by_size.png", size_band_figure(tables))
            batch, d = first[0]
            write_png(out / "detections.png", detection_figure(batch, d, max_scenes=4))
    result.update(detections=files, handed_on=handed_on, seconds=round(time.time() - t0, 1))
    atomic_write_json(out / "results.json", result)
    return result
