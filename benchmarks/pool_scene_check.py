"""How many of the boxes a ``threedq em`` round hands on to mining lie on GT objects after each pool check.

Reads a detections file (``<work_dir>/03_detector_eval/detections_train.npz`` for round 1, ``rNN_detector_eval/`` for
later rounds) and the dataset, takes each scene's ``max_boxes`` boxes of highest score as the rounds do, and scores
each box by the two label-free checks of the mining stage's pool:

* the input view's (``pool_min_observed_iou``): its best 3D IoU with the pseudo-boxes of the scene's input view
  (:func:`~threedq.box_refinement.observed_boxes`, within the feature grid's bounds);
* the scene's (``pool_min_scene_iou``): its best 3D IoU with the pseudo-boxes fused over the scene's views, the
  DataModule's ``pseudo_boxes`` (``<data_dir>/proposals/<split>.npz``, every second view).

For each threshold it prints the boxes kept and the share of them that match a GT object at IoU 0.5 by the mAP's
rule (what the rounds' reports call "pool boxes on GT objects"; GT for measuring only). Rows go to ``--out`` as JSON
lines.

    python benchmarks/pool_scene_check.py runs/em/03_detector_eval/detections_train.npz --data_dir data/clevr_veggie
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from threedq.machine import cpu_name

#: the feature grid's bounds of ``configs/stages/viewpred.yaml`` (what the detector and the pool's input check use)
GRID_BOUNDS = ((-1.28, -1.28, -0.32), (1.28, 1.28, 0.96))


def box_scores(detections: Path, data_dir: Path, split: str = "train", max_boxes: int = 8,
               bounds: tuple = GRID_BOUNDS) -> dict[str, np.ndarray]:
    """Per handed-on box (scenes in index order, each scene's boxes by decreasing score): ``on_object`` (matches a
    GT object; measuring only), ``input_iou`` and ``scene_iou`` (the two checks' best IoUs, 0 where there is no
    pseudo-box)."""
    from handed_on_boxes import handed_on_samples

    from threedq.box_refinement import observed_boxes
    from threedq.boxes import best_aabb_iou
    from threedq.data.box_files import load_boxes_file

    fused = load_boxes_file(data_dir / "proposals" / f"{split}.npz")
    cols: dict[str, list[float]] = {"on_object": [], "input_iou": [], "scene_iou": []}

    def best(boxes: torch.Tensor, others: np.ndarray) -> torch.Tensor:
        return best_aabb_iou(boxes, torch.as_tensor(others, dtype=torch.float32).reshape(-1, 6))

    for name, s, m, aabb in handed_on_samples(detections, data_dir, split, max_boxes):
        obs, _ = observed_boxes(s["depth"][:1], s["K"][:1], s["R_T_cam"][:1], bounds)
        cols["on_object"] += (s["categories"][m] >= 0).float().tolist()
        cols["input_iou"] += best(aabb, obs).tolist()
        cols["scene_iou"] += best(aabb, fused[name][0]).tolist()
    return {k: np.asarray(v, np.float64) for k, v in cols.items()}


def check_table(scores: dict[str, np.ndarray], input_iou: float = 0.5,
                scene_thresholds: tuple[float, ...] = (0.5, 0.6, 0.7, 0.8)) -> list[dict]:
    """Rows (check, kept, kept share, on GT objects among the kept): every box, the input check alone, and the input
    check with each scene threshold."""
    on, inp, scn = scores["on_object"], scores["input_iou"], scores["scene_iou"]
    rows = []
    for name, keep in [("every box", np.ones_like(on, bool)), (f"input view >= {input_iou}", inp >= input_iou)] + [
            (f"input view >= {input_iou}, scene >= {t}", (inp >= input_iou) & (scn >= t)) for t in scene_thresholds]:
        rows.append({"check": name, "kept": int(keep.sum()), "kept_share": float(keep.mean()) if len(on) else 0.0,
                     "on_objects": float(on[keep].mean()) if keep.any() else float("nan")})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("detections", type=Path, nargs="+", help="detections_<split>.npz files rounds hand on")
    ap.add_argument("--data_dir", type=Path, required=True, help="the dataset folder (holds index.json, proposals/)")
    ap.add_argument("--split", default="train")
    ap.add_argument("--max_boxes", type=int, default=8, help="boxes per scene the rounds take (highest scores)")
    ap.add_argument("--scene_thresholds", type=float, nargs="+", default=[0.5, 0.6, 0.7, 0.8])
    ap.add_argument("--out", type=Path, default=None, help="append the rows as JSON lines")
    args = ap.parse_args()
    print(f"machine: {cpu_name()}  date: {time.strftime('%Y-%m-%d')}  data: {args.data_dir}")
    print("| boxes handed on | check | kept | kept share | on GT objects |")
    print("|---|---|---|---|---|")
    for det in args.detections:
        rows = check_table(box_scores(det, args.data_dir, args.split, args.max_boxes),
                           scene_thresholds=tuple(args.scene_thresholds))
        for r in rows:
            print(f"| {det} | {r['check']} | {r['kept']} | {r['kept_share']:.2f} | {r['on_objects']:.3f} |")
            if args.out is not None:
                with args.out.open("a") as f:
                    f.write(json.dumps({"detections": str(det), "data_dir": str(args.data_dir), **r,
                                        "machine": cpu_name(), "date": time.strftime("%Y-%m-%d")}) + "\n")


if __name__ == "__main__":
    main()
