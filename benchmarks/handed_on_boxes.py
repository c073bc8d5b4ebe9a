"""What the boxes a ``threedq em`` round hands on to mining are, measured against GT (for measuring only).

Reads a detections file (``<work_dir>/03_detector_eval/detections_train.npz`` for round 1, ``rNN_detector_eval/`` for
later rounds) and the dataset, takes each scene's ``max_boxes`` boxes of highest score as the rounds do, matches them to
the GT objects by the rule of the mAP at IoU 0.5 (``assign_detections``), and sorts the unmatched ones:

* ``duplicate``: IoU >= 0.5 with a GT object another box already took;
* ``partial``: best IoU in [0.1, 0.5): on an object, but cut smaller or larger than it (with their volume against
  that object's GT box, and whether they touch two objects);
* ``off``: IoU < 0.1 with every GT object.

Also, per class: the fraction of boxes whose input view sees more than 10% of the pixels of their projection at a
depth 5 cm nearer than the box's nearest corner (something in front: occluded).

    python benchmarks/handed_on_boxes.py runs/em/03_detector_eval/detections_train.npz --data_dir data/clevr_veggie
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from threedq.machine import cpu_name


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("detections", type=Path, help="a detections_<split>.npz a round hands on")
    ap.add_argument("--data_dir", type=Path, required=True, help="the dataset folder (holds index.json)")
    ap.add_argument("--split", default="train")
    ap.add_argument("--max_boxes", type=int, default=8, help="boxes per scene the rounds take (highest scores)")
    args = ap.parse_args()

    from threedq.boxes import aabb_iou_3d

    kinds: dict[str, list[tuple[float, float, int]]] = {k: [] for k in ("matched", "duplicate", "partial", "off")}
    scenes = 0
    for _, s, m, aabb in handed_on_samples(args.detections, args.data_dir, args.split, args.max_boxes):
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
            kinds[kind].append((float(occl[j]), ratio, int((iou[j] > 0.05).sum())))
    n = sum(len(v) for v in kinds.values())
    print(f"machine: {cpu_name()}  date: {time.strftime('%Y-%m-%d')}  {args.detections}: {n} boxes, {scenes} scenes with boxes")
    print("| boxes | count | share | occluded > 10% | volume / GT's < 0.7 | 0.7-1.4 | >= 1.4 | "
          "touching 2+ GT objects |")
    print("|---|---|---|---|---|---|---|---|")
    for kind, rows in kinds.items():
        if not rows:
            print(f"| {kind} | 0 | 0.00 | - | - | - | - | - |")
            continue
        o, r, t = (np.array(c) for c in zip(*rows))
        print(f"| {kind} | {len(rows)} | {len(rows) / n:.2f} | {np.mean(o > 0.1):.2f} | {np.mean(r < 0.7):.2f} | "
              f"{np.mean((r >= 0.7) & (r < 1.4)):.2f} | {np.mean(r >= 1.4):.2f} | {np.mean(t >= 2):.2f} |")


if __name__ == "__main__":
    main()
