"""The boxes a ``threedq em`` round hands on to mining, measured against GT (for measuring only), one question a run:

Reads detections files (``03_detector_eval/detections_train.npz`` for round 1, ``rNN_detector_eval/`` later) and the
dataset and takes each scene's ``max_boxes`` highest boxes.

* ``--op kinds`` (default): matches them to GT at IoU 0.5 (``assign_detections``) and sorts the unmatched:
  ``duplicate`` (IoU >= 0.5 with a GT object already taken), ``partial`` (best IoU in [0.1, 0.5)) and ``off``
  (IoU < 0.1); per class also the fraction of occluded boxes (something in front in the input view).
* ``--op pool_check``: scores each by the mining pool's two label-free checks, its best 3D IoU with the input view's
  pseudo-boxes (``pool_min_observed_iou``) and with the scene's fused pseudo-boxes (``pool_min_scene_iou``); per
  threshold the boxes kept and the share on a GT object at IoU 0.5. Rows go to ``--out`` as JSON lines.

    python benchmarks/handed_on_boxes.py runs/em/03_detector_eval/detections_train.npz --data_dir data/clevr_veggie
    python benchmarks/handed_on_boxes.py --op pool_check runs/em/03_detector_eval/detections_train.npz \\
        --data_dir data/clevr_veggie
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from _common import append_row, machine, table

from threedq.machine import cpu_name

#: the feature grid's bounds of ``configs/stages/viewpred.yaml`` (what the detector and the pool's input check use)
GRID_BOUNDS = ((-1.28, -1.28, -0.32), (1.28, 1.28, 0.96))


def occluded_fraction(aabb: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, pose: torch.Tensor,
                      margin: float = 0.05) -> torch.Tensor:
    """``[M]``: of the valid depth pixels inside each box's projected rectangle, the fraction nearer than the box's
    nearest corner by more than ``margin`` metres. aabb ``[M, 6]`` in R; depth ``[H, W]``; K ``[3, 3]``; pose
    ``[4, 4]`` camera-to-R."""
    from threedq.boxes import box_corners
    from threedq.geometry import invert_rigid, transform_points
    from threedq.geometry.camera import project

    centre, extent = (aabb[:, :3] + aabb[:, 3:]) / 2, aabb[:, 3:] - aabb[:, :3]
    corners = box_corners(torch.cat([centre, extent, torch.zeros(len(aabb), 1)], dim=1)[None])[0].reshape(-1, 3)
    cam = transform_points(invert_rigid(pose[None]), corners[None])[0]
    uv, z = project(cam[None], K[None])
    uv, z = uv[0].view(-1, 8, 2), z[0].view(-1, 8)
    H, W = depth.shape
    out = torch.zeros(len(aabb))
    for j in range(len(aabb)):
        u0, v0 = (int(max(0, x)) for x in uv[j].amin(0).floor().tolist())
        u1, v1 = (int(min(m, x)) for m, x in zip((W - 1, H - 1), uv[j].amax(0).ceil().tolist()))
        patch = depth[v0:v1 + 1, u0:u1 + 1]
        valid = patch > 0
        if valid.any():
            out[j] = ((patch < z[j].min() - margin) & valid).float().sum() / valid.float().sum()
    return out


def handed_on_samples(detections: Path, data_dir: Path, split: str = "train", max_boxes: int = 8
                      ) -> Iterator[tuple[str, dict, torch.Tensor, torch.Tensor]]:
    """The scenes of ``split`` with the boxes a round hands on (each scene's ``max_boxes`` of highest score, its fixed
    input view), as ``(scene file, sample, box_mask, aabb [M, 6] of the valid boxes)``; scenes without a box are
    skipped. Each sample also carries the scene's GT boxes (``gt_aabb``, ``gt_mask``) and the boxes' GT match
    (``categories``, -1 where unmatched)."""
    from threedq.data.box_files import load_boxes_file
    from threedq.datamodules.scene_folder import SceneDataset
    from threedq.scene import load_index

    ds = SceneDataset(data_dir, load_index(data_dir), split, num_input_views=1, num_target_views=0,
                      max_objects=max_boxes, box_sets=load_boxes_file(detections), random_views=False,
                      max_boxes=max_boxes)
    for i in range(len(ds)):
        s = ds[i]
        m = s["box_mask"]
        aabb = s["aabb"][m].float()
        if aabb.shape[0]:
            yield ds.files[i], s, m, aabb


def box_scores(detections: Path, data_dir: Path, split: str = "train", max_boxes: int = 8,
               bounds: tuple = GRID_BOUNDS) -> dict[str, np.ndarray]:
    """Per handed-on box (scenes in index order, each scene's boxes by decreasing score): ``on_object`` (matches a
    GT object; measuring only), ``input_iou`` and ``scene_iou`` (the two checks' best IoUs, 0 where there is no
    pseudo-box)."""
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


def kinds(detections: Path, args: argparse.Namespace) -> None:
    """The table of ``--op kinds`` for one detections file."""
    from threedq.boxes import aabb_iou_3d

    found: dict[str, list[tuple[float, float, int]]] = {k: [] for k in ("matched", "duplicate", "partial", "off")}
    scenes = 0
    for _, s, m, aabb in handed_on_samples(detections, args.data_dir, args.split, args.max_boxes):
        scenes += 1
        gt = s["gt_aabb"][s["gt_mask"]].float()  # the scene's GT boxes, which every sample carries beside its own
        iou = aabb_iou_3d(aabb, gt) if gt.shape[0] else torch.zeros(len(aabb), 1)
        occl = occluded_fraction(aabb, s["depth"][0], s["K"][0], s["R_T_cam"][0])
        vol = (aabb[:, 3:] - aabb[:, :3]).clamp_min(0).prod(1)
        gvol = (gt[:, 3:] - gt[:, :3]).clamp_min(0).prod(1) if gt.shape[0] else torch.ones(1)
        for j in range(len(aabb)):
            best = float(iou[j].max())
            kind = ("matched" if s["categories"][m][j] >= 0 else "duplicate" if best >= 0.5 else
                    "partial" if best >= 0.1 else "off")
            ratio = float(vol[j] / gvol[iou[j].argmax()]) if gt.shape[0] else float("nan")
            found[kind].append((float(occl[j]), ratio, int((iou[j] > 0.05).sum())))
    n = sum(len(v) for v in found.values())
    print(f"{detections}: {n} boxes, {scenes} scenes with boxes")
    rows = []
    for kind, rs in found.items():
        if not rs:
            rows.append((kind, 0, "0.00", *["-"] * 5))
            continue
        o, r, t = (np.array(c) for c in zip(*rs))
        rows.append((kind, len(rs), f"{len(rs) / n:.2f}", *(f"{np.mean(x):.2f}" for x in (
            o > 0.1, r < 0.7, (r >= 0.7) & (r < 1.4), r >= 1.4, t >= 2))))
    print(table(["boxes", "count", "share", "occluded > 10%", "volume / GT's < 0.7", "0.7-1.4", ">= 1.4",
                 "touching 2+ GT objects"], rows))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("detections", type=Path, nargs="+", help="detections_<split>.npz files rounds hand on")
    ap.add_argument("--op", choices=["kinds", "pool_check"], default="kinds")
    ap.add_argument("--data_dir", type=Path, required=True, help="the dataset folder (holds index.json, proposals/)")
    ap.add_argument("--split", default="train")
    ap.add_argument("--max_boxes", type=int, default=8, help="boxes per scene the rounds take (highest scores)")
    ap.add_argument("--scene_thresholds", type=float, nargs="+", default=[0.5, 0.6, 0.7, 0.8], help="pool_check")
    ap.add_argument("--out", type=Path, default=None, help="pool_check: append the rows as JSON lines")
    args = ap.parse_args()
    print(f"{machine()}; data: {args.data_dir}")
    if args.op == "kinds":
        for det in args.detections:
            kinds(det, args)
        return
    rows = []
    for det in args.detections:
        for r in check_table(box_scores(det, args.data_dir, args.split, args.max_boxes),
                             scene_thresholds=tuple(args.scene_thresholds)):
            rows.append((det, r["check"], r["kept"], f"{r['kept_share']:.2f}", f"{r['on_objects']:.3f}"))
            if args.out is not None:
                append_row(args.out, {"detections": str(det), "data_dir": str(args.data_dir), **r,
                                      "machine": cpu_name(), "date": time.strftime("%Y-%m-%d")})
    print(table(["boxes handed on", "check", "kept", "kept share", "on GT objects"], rows))


if __name__ == "__main__":
    main()
