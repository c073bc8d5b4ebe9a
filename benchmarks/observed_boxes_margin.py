"""The single-view pseudo-boxes a detector is refined against, at several ground margins.

Per ``--margin MARGIN:MIN_HEIGHT`` (metres; ``measured``: the packaged :data:`threedq.box_refinement.OBSERVED_PARAMS`),
:func:`threedq.box_refinement.observed_boxes` of each test scene's input view: their mAP@0.25 / @0.5 against the GT
boxes, and the share of GT objects less tall than ``--flat`` found at IoU 0.25 / 0.5.

    python benchmarks/observed_boxes_margin.py --data_dir data/shifted
    python benchmarks/observed_boxes_margin.py --data_dir data/clevr_veggie --scenes 120
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from threedq.box_refinement import OBSERVED_PARAMS, observed_boxes
from threedq.boxes import aabb_iou_3d
from threedq.datamodules.scene_folder import SceneDataset
from threedq.machine import cpu_name
from threedq.pipeline.detection_eval import box_sets_map, gt_hulls
from threedq.scene import load_index, load_scene


def _params(spec: str):
    if spec == "measured":
        return dataclasses.replace(OBSERVED_PARAMS, ground_margin=None, min_height=None)
    margin, height = (float(x) for x in spec.split(":"))
    return dataclasses.replace(OBSERVED_PARAMS, ground_margin=margin, min_height=height)


def _found(gt: dict[str, np.ndarray], boxes: dict[str, tuple[np.ndarray, np.ndarray]], thr: float) -> float:
    """Share of the GT boxes some box overlaps at IoU >= ``thr`` (best box per object, no one-to-one matching)."""
    hit = total = 0
    for f, g in gt.items():
        total += len(g)
        if len(g) and len(boxes[f][0]):
            iou = aabb_iou_3d(torch.from_numpy(g).double(), torch.as_tensor(boxes[f][0]).double().reshape(-1, 6))
            hit += int((iou.max(1).values >= thr).sum())
    return hit / total if total else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data_dir", required=True)
    ap.add_argument("--scenes", type=int, default=None, help="only the first N test scenes")
    ap.add_argument("--margin", nargs="*", default=["0.015:0.02", "0.01:0.015", "measured", "0.005:0.02"])
    ap.add_argument("--flat", type=float, default=0.04, help="objects less tall than this (metres) are 'flat'")
    ap.add_argument("--num_input_views", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    data = Path(args.data_dir)
    index = load_index(data)
    files = index.files("test")[: args.scenes]
    ds = SceneDataset(data, index, "test", num_input_views=args.num_input_views, num_target_views=0, seed=args.seed)
    views = {f: np.asarray(ds[i]["view_ids"][: args.num_input_views].tolist()) for i, f in enumerate(files)}
    gt = gt_hulls(data, files)
    flat = {f: g[(g[:, 5] - g[:, 2]) < args.flat] for f, g in gt.items()}
    records = {f: load_scene(data / f, validate=False) for f in tqdm(files, desc="scenes", leave=False)}
    print(f"# single-view observed boxes, test split of {data} ({len(files)} scenes, {sum(map(len, gt.values()))} "
          f"objects, {sum(map(len, flat.values()))} under {args.flat:g} m tall); {cpu_name()}, torch "
          f"{torch.__version__}, {time.strftime('%Y-%m-%d')}")
    print("| ground margin : min height | mAP@0.25 | mAP@0.5 | flat objects found @0.25 / @0.5 |")
    print("|---|---|---|---|")
    for spec in args.margin:
        p = _params(spec)
        boxes = {}
        for f in tqdm(files, desc=spec, leave=False):
            r, v = records[f], views[f]
            boxes[f] = observed_boxes(r.depth[v], r.K[v], r.world_T_cam[v], index.scene_bounds, params=p)
        m = box_sets_map(gt, boxes, progress=False)
        found = [_found(flat, boxes, t) for t in (0.25, 0.5)]
        cell = " / ".join("-" if np.isnan(x) else f"{x:.2f}" for x in found)  # "-": no flat object
        print(f"| {spec} | {m['map_25']:.3f} | {m['map_50']:.3f} | {cell} |", flush=True)


if __name__ == "__main__":
    main()
