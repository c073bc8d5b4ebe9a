"""The relative yaw error of two ``threedq em`` runs on the object pairs both of them put in one prototype.

Reads each run's per-object assignments (``rNN_eval/objects_test.json``: box, prototype, yaw index) and the scenes'
GT boxes, and per round prints each run's yaw error on all its pairs (checked against its ``results.json``), on the
pairs common to both runs (each run's own yaws), and on the pairs only one run has. Reruns no evaluation.

    python benchmarks/yaw_common_pairs.py --data_dir data/clevr_veggie --run hull=runs/em --run cube=runs/em_cube \\
        [--rounds 0 4] [--out table.md]

Convention: the evaluation's: yaws counter-clockwise about +z, frame R; errors in degrees in ``[0, 180]``; only
categories of symmetry order 1 give pairs; a detected box is the GT object of highest axis-aligned IoU.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _common import table as md_table

from threedq.boxes import aabb_iou_3d, boxes_to_aabb
from threedq.metrics import relative_yaw_error
from threedq.scene import load_scene_gt


def read_objects(path: Path, data_dir: Path, min_iou: float = 0.5) -> dict[tuple[str, int], dict[str, Any]]:
    """``{(scene, GT index): {prototype, est (rad), gt (rad), category}}`` of one evaluation's ``objects_test.json``."""
    try:
        d = json.loads(path.read_text())
        objects, num_angles = d["objects"], int(d["num_angles"])
    except (OSError, json.JSONDecodeError, KeyError) as e:
        raise SystemExit(f"yaw_common_pairs: {path}: not an evaluation's objects file ({type(e).__name__}: {e})") from e
    out: dict[tuple[str, int], dict[str, Any]] = {}
    scenes: dict[str, tuple[np.ndarray, np.ndarray, torch.Tensor]] = {}  # each scene's GT, read once
    for o in objects:
        if o["scene"] not in scenes:
            boxes, cats = load_scene_gt(data_dir / o["scene"])
            boxes, cats = np.asarray(boxes, np.float64), np.asarray(cats, np.int64)
            scenes[o["scene"]] = (boxes, cats, torch.from_numpy(boxes_to_aabb(boxes)))
        boxes, cats, gt_aabb = scenes[o["scene"]]
        iou = aabb_iou_3d(torch.tensor([o["box"]], dtype=torch.float64), gt_aabb)[0].numpy()
        j = int(iou.argmax())
        if iou[j] < min_iou:
            raise SystemExit(f"yaw_common_pairs: {path}: a box of {o['scene']} overlaps no GT object at IoU >= "
                             f"{min_iou} (best {iou[j]:.2f}): is --data_dir the run's data?")
        out[(o["scene"], j)] = {"prototype": int(o["prototype"]), "gt": float(boxes[j, 6]), "category": int(cats[j]),
                                "est": 2 * math.pi * int(o["angle_index"]) / num_angles}
    return out


def _median(x: list[float] | np.ndarray) -> float:
    return float(np.median(x)) if len(x) else float("nan")


def pair_errors(objs: dict, symmetry_order: list[int]) -> dict[tuple, float]:
    """Every same-prototype pair of one asymmetric category and its error in degrees: a naive loop over the pairs."""
    groups: dict[tuple[int, int], list] = {}
    for k, o in objs.items():
        if symmetry_order[o["category"]] == 1:
            groups.setdefault((o["prototype"], o["category"]), []).append(k)
    out = {}
    for members in groups.values():
        for a, b in itertools.combinations(sorted(members), 2):
            # alignment convention: y_o + g_o is the same for every object of one prototype when posed perfectly
            d = (objs[a]["est"] + objs[a]["gt"]) - (objs[b]["est"] + objs[b]["gt"])
            out[(a, b)] = math.degrees(abs((d + math.pi) % (2 * math.pi) - math.pi))
    return out


def _library_median(objs: dict, keys: list, clusters: list[int], symmetry_order: list[int]) -> tuple[float, int]:
    t = lambda f, dt: torch.tensor([f(objs[k]) for k in keys], dtype=dt)  # noqa: E731
    r = relative_yaw_error(t(lambda o: o["est"], torch.float64), t(lambda o: o["gt"], torch.float64),
                           t(lambda o: o["category"], torch.long), torch.tensor(clusters), symmetry_order,
                           max_pairs_per_group=10**9)
    return float(r["median_deg"]), int(r["num_pairs"])


def compare(a: dict, b: dict, symmetry_order: list[int]) -> dict[str, Any]:
    """The yaw error of runs ``a`` and ``b`` (objects of :func:`read_objects`) on all, common and own pairs."""
    pa, pb = pair_errors(a, symmetry_order), pair_errors(b, symmetry_order)
    common = sorted(set(pa) & set(pb))
    shared = sorted(set(a) & set(b))  # objects both runs matched
    # the library on the common pairs: one cluster per (prototype in a, prototype in b)
    ids = {k: i for i, k in enumerate(sorted({(a[o]["prototype"], b[o]["prototype"]) for o in shared}))}
    both = [ids[(a[o]["prototype"], b[o]["prototype"])] for o in shared]
    row = {"pairs_a": len(pa), "pairs_b": len(pb), "common": len(common),
           "all_a": _median(list(pa.values())), "all_b": _median(list(pb.values())),
           "common_a": _median([pa[k] for k in common]), "common_b": _median([pb[k] for k in common])}
    for name, own, other in (("a", pa, pb), ("b", pb, pa)):
        only = sorted(set(own) - set(other))
        row[f"only_{name}"], row[f"only_{name}_median"] = len(only), _median([own[k] for k in only])
    for name, objs, own in (("a", a, pa), ("b", b, pb)):
        keys = sorted(objs)
        lib, n = _library_median(objs, keys, [objs[k]["prototype"] for k in keys], symmetry_order)
        if n != len(own) or not math.isclose(lib, row[f"all_{name}"], abs_tol=1e-6):
            raise RuntimeError(f"run {name}: the naive pairs ({len(own)}, median {row[f'all_{name}']:.3f}) differ from "
                               f"the library's ({n}, {lib:.3f})")
        if common:
            lib, n = _library_median(objs, shared, both, symmetry_order)
            if n != len(common) or not math.isclose(lib, row[f"common_{name}"], abs_tol=1e-6):
                raise RuntimeError(f"run {name}: common pairs differ from the library's ({n}, {lib:.3f})")
    return row


def _reported(run: Path, r: int) -> float | None:
    p = run / f"r{r:02d}_eval" / "results.json"
    try:
        return float(json.loads(p.read_text())["quantization"]["threedq"]["yaw_median_deg"])
    except (OSError, KeyError, ValueError):
        return None


def main(argv: list[str] | None = None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data_dir", required=True, type=Path, help="the runs' data (index.json and the scene files)")
    ap.add_argument("--run", action="append", required=True, help="NAME=WORK_DIR of a threedq em run (twice)")
    ap.add_argument("--rounds", type=int, nargs="+", help="rounds to compare (default: every round both runs have)")
    ap.add_argument("--out", type=Path, help="also write the table to this markdown file")
    args = ap.parse_args(argv)
    if len(args.run) != 2 or any("=" not in r for r in args.run):
        ap.error("--run NAME=WORK_DIR, exactly twice")
    (na, ra), (nb, rb) = (r.split("=", 1) for r in args.run)
    ra, rb = Path(ra), Path(rb)
    try:
        sym = list(json.loads((args.data_dir / "index.json").read_text())["symmetry_order"])
    except (OSError, json.JSONDecodeError, KeyError) as e:
        raise SystemExit(f"yaw_common_pairs: {args.data_dir / 'index.json'}: no symmetry_order ({e})") from e
    rounds = args.rounds or [r for r in range(100) if (ra / f"r{r:02d}_eval/objects_test.json").is_file()
                             and (rb / f"r{r:02d}_eval/objects_test.json").is_file()]
    if not rounds:
        raise SystemExit(f"yaw_common_pairs: no round with rNN_eval/objects_test.json in both {ra} and {rb}")
    cells = []
    for r in rounds:
        a = read_objects(ra / f"r{r:02d}_eval" / "objects_test.json", args.data_dir)
        b = read_objects(rb / f"r{r:02d}_eval" / "objects_test.json", args.data_dir)
        row = compare(a, b, sym)
        for name, run in (("a", ra), ("b", rb)):
            rep = _reported(run, r)
            if rep is not None and not math.isclose(rep, row[f"all_{name}"], abs_tol=1e-3):
                print(f"yaw_common_pairs: note: {run}, round {r}: results.json reports {rep:.3f} deg, the objects give "
                      f"{row[f'all_{name}']:.3f} (pairs capped per group there?)", file=sys.stderr)
        cells.append([r, f"{row['all_a']:.1f} ({row['pairs_a']})", f"{row['all_b']:.1f} ({row['pairs_b']})",
                      row["common"], f"{row['common_a']:.1f}", f"{row['common_b']:.1f}",
                      f"{row['only_a']}, {row['only_a_median']:.1f}", f"{row['only_b']}, {row['only_b_median']:.1f}"])
    table = (f"Relative yaw error (median, deg), same-prototype pairs of asymmetric categories: {na} ({ra}) vs {nb} "
             f"({rb})\n\n" + md_table(["round", f"{na}: all pairs", f"{nb}: all pairs", "common pairs",
                                      f"{na} on them", f"{nb} on them", f"only {na}: pairs, median",
                                      f"only {nb}: pairs, median"], cells))
    print(table)
    if args.out:
        args.out.write_text(table + "\n")
    return table


if __name__ == "__main__":
    main()
