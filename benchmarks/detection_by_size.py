"""Where a detector loses IoU: objects found per size band, from an existing run's detection files.

For each detector evaluation folder given (its ``detections_test.npz``), the dataset's label-free pseudo-boxes and the
pseudo-boxes of the view(s) the detector sees, prints per size band of the GT boxes: the share found at IoU 0.25 and
0.5, the median best IoU, centre errors and |log size ratio| per axis; and the single-view pseudo-boxes' mAP.
``--snap IOU ...`` adds rows with each detected box replaced by the single-view pseudo-box it overlaps most (at least
IOU). ``--num_input_views`` and ``--seed`` must be the DataModule's.

    python benchmarks/detection_by_size.py --data_dir data/shifted runs/shifted/03_detector_eval \\
        --out benchmarks/results/detection_by_size_shifted.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from threedq.datamodules.scene_folder import SceneDataset

from threedq.boxes import aabb_iou_3d
from threedq.data.box_files import load_boxes_file
from threedq.data.proposal_cache import propose_dataset
from threedq.machine import cpu_name
from threedq.pipeline.detection_eval import (
    box_sets_map,
    gt_hulls,
    single_view_pseudo_boxes,
    size_band_table,
)
from threedq.proposals import ProposalParams
from threedq.scene import load_index


def _fmt(x: float, spec: str = ".2f") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def _snapped(dets: dict, reference: dict, min_iou: float) -> dict:
    """Each box of ``dets`` replaced by the ``reference`` box it overlaps most, where that IoU is >= ``min_iou``."""
    out = {}
    for f, (aabb, scores) in dets.items():
        a = np.asarray(aabb, dtype=np.float64).reshape(-1, 6).copy()
        p = np.asarray(reference[f][0], dtype=np.float64).reshape(-1, 6)
        if len(a) and len(p):
            iou = aabb_iou_3d(torch.from_numpy(a), torch.from_numpy(p)).numpy()
            j = iou.argmax(1)
            ok = iou[np.arange(len(a)), j] >= min_iou
            a[ok] = p[j[ok]]
        out[f] = (a.astype(np.float32), np.asarray(scores))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("eval_dirs", nargs="*", help="detector evaluation folders holding detections_test.npz")
    ap.add_argument("--data_dir", required=True)
    ap.add_argument("--num_input_views", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="also write the tables as JSON here")
    ap.add_argument("--snap", type=float, nargs="*", default=[],
                    help="also score each detector with its boxes snapped to the single-view pseudo-box of IoU >= this")
    args = ap.parse_args()
    t0 = time.time()
    data = Path(args.data_dir)
    index = load_index(data)
    files = index.files("test")
    ds = SceneDataset(data, index, "test", num_input_views=args.num_input_views, num_target_views=0, seed=args.seed)
    views = {f: ds[i]["view_ids"][: args.num_input_views].tolist() for i, f in enumerate(files)}
    gt = gt_hulls(data, files)
    pseudo = propose_dataset(data, "test", data / "proposals" / "test.npz", params=ProposalParams(view_stride=2))
    single = single_view_pseudo_boxes(data, views, index.scene_bounds)
    sets = {"pseudo-boxes (all views)": pseudo, "pseudo-boxes (input view)": single}
    for d in args.eval_dirs:
        sets[f"detector {d}"] = load_boxes_file(Path(d) / "detections_test.npz")
        for thr in args.snap:
            sets[f"detector {d}, snapped at IoU >= {thr:g}"] = _snapped(sets[f"detector {d}"], single, thr)
    result = {"machine": f"{cpu_name()}, {torch.get_num_threads()} threads, torch {torch.__version__}", "date": time.strftime("%Y-%m-%d"), "data_dir": str(data),
              "command": " ".join(sys.argv), "single_view_map": box_sets_map(gt, single, progress=False),
              "by_size": [{"boxes": name, "rows": size_band_table(gt, boxes)} for name, boxes in sets.items()]}
    print(f"# objects found per size band, test split of {data} ({len(files)} scenes); {result['machine']}")
    print(f"single-view pseudo-boxes: mAP@0.25 {result['single_view_map']['map_25']:.3f}, "
          f"mAP@0.5 {result['single_view_map']['map_50']:.3f}\n")
    print("| boxes | band | objects | found@0.25 | found@0.5 | median best IoU | centre err xy (m) | centre err z (m) "
          "| median abs log size ratio x / y / z |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, rows in ((t["boxes"], t["rows"]) for t in result["by_size"]):
        for r in rows:
            if not r["objects"]:
                continue
            ls = " / ".join(_fmt(v) for v in r["median_abs_log_size_ratio"])
            print(f"| {name} | {r['band']} | {r['objects']} | {_fmt(r['found_25'])} | {_fmt(r['found_50'])} | "
                  f"{_fmt(r['median_best_iou'])} | {_fmt(r['median_centre_error_xy'], '.3f')} | "
                  f"{_fmt(r['median_centre_error_z'], '+.3f')} | {ls} |")
    print(f"\n({time.time() - t0:.0f} s)")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
