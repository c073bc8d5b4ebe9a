"""Pose benchmark: how well does the prototype match give each object's yaw, on categories seen and unseen?

Per dataset, each ``--encoder NAME=CKPT`` (a repeated NAME is another seed) is scored by a K = 50 rotation-aware bank
fitted label-free on the test objects themselves, per number of ``--input_views`` and box source (GT; with ``--run``
that run's detections, found from the same input views): median relative yaw errors, accuracy within 10 / 20 deg,
the confident half, the yaw found directly between two objects (``pairs``) and Hungarian accuracy, with references
(random yaws, the raw crops' bank, point-cloud registration). One JSON line per (dataset, row, seed) goes to
``--rows``; the table is printed.

    python benchmarks/pose.py --encoder "main job=runs/em/r04_quantizer/checkpoints/last.ckpt" \\
        --encoder "main job=runs/em_s1/r04_quantizer/checkpoints/last.ckpt" --rows pose_rows.jsonl
    python benchmarks/pose.py --encoder "main job=runs/em/r04_quantizer/checkpoints/last.ckpt" --input_views 1 3 \
        --run runs/em --rows pose_rows.jsonl
    python benchmarks/pose.py --table_only --rows benchmarks/results/pose/rows.jsonl
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Any

import torch
from _common import append_row, mean_range, read_rows

from threedq.machine import cpu_name

DATASETS = {"embedded": "data/clevr_veggie.yaml", "shapes": "data/shapes.yaml", "unseen": "data/shapes_unseen.yaml"}
K, NUM_ANGLES, EM_ITERATIONS, BANK_SEEDS, OCCUPANCY_FLOOR = 50, 36, 10, (0, 1), 0.2
PAIRS = 800  # same-category pairs drawn for the direct search (seeded)


def yaw_summary(angles: torch.Tensor, clusters: torch.Tensor, test: dict, sym: list[int]) -> dict[str, float]:
    """Median relative yaw error (asymmetric, and 2- and 4-fold modulo the period) and accuracy within 10 / 20 deg."""
    from threedq.geometry import yaw_angles
    from threedq.metrics.pose import relative_yaw_error

    est = yaw_angles(NUM_ANGLES, dtype=torch.float64)[angles]
    gt = test["boxes"][:, 6].double()
    out: dict[str, float] = {}
    for order, name in ((1, "asym"), (2, "2fold"), (4, "4fold")):
        r = relative_yaw_error(est, gt, test["labels"], clusters, sym, order=order)
        out[f"{name}_median_deg"] = float(r["median_deg"])
        if order == 1:
            out["asym_acc_10"], out["asym_acc_20"] = float(r["acc_10"]), float(r["acc_20"])
            out["asym_pairs"] = int(r["num_pairs"])
    out["asym_objects"] = int((torch.tensor(sym)[test["labels"]] == 1).sum())
    return out


def pair_yaw_error(crops: torch.Tensor, test: dict, sym: list[int], seed: int = 0) -> float:
    """Median error of the yaw the rotation search finds directly between two objects of one asymmetric category."""
    from threedq.geometry import yaw_angles
    from threedq.quantization.rotation_search import best_prototype_and_yaw

    labels, gt = test["labels"], test["boxes"][:, 6].double()
    asym = [i for i in range(labels.shape[0]) if sym[int(labels[i])] == 1]
    pairs = [(i, j) for a, i in enumerate(asym) for j in asym[a + 1 :] if labels[i] == labels[j]]
    if not pairs:
        return float("nan")
    pick = torch.randperm(len(pairs), generator=torch.Generator().manual_seed(seed))[:PAIRS].tolist()
    yaw, errs = yaw_angles(NUM_ANGLES, dtype=torch.float64), []
    for a, b in (pairs[p] for p in pick):
        step = best_prototype_and_yaw(crops[a : a + 1], crops[b : b + 1], NUM_ANGLES).angle[0]
        # turning a by yaw[step] aligns it with b: the estimate of g_a - g_b is -yaw[step]
        e = (-yaw[step] - (gt[a] - gt[b]) + math.pi) % (2 * math.pi) - math.pi
        errs.append(abs(float(e)))
    return math.degrees(float(torch.tensor(errs).median()))


def bank_rows(crops: torch.Tensor, test: dict, sym: list[int], num_classes: int) -> tuple[dict[str, float], Any]:
    """Mean over the bank seeds of a K = 50 bank fitted on the test crops themselves (labels unused)."""
    from threedq.metrics import cluster_confusion, hungarian_accuracy
    from threedq.pipeline.parse import yaw_margin_steps
    from threedq.quantization import fit_prototype_bank, yaw_confidence

    acc: dict[str, list[float]] = {}
    first = None
    for seed in BANK_SEEDS:
        bank = fit_prototype_bank(crops, min(K, crops.shape[0]), iterations=EM_ITERATIONS, num_angles=NUM_ANGLES,
                                  seed=seed)
        res = bank.assign(crops)
        first = res if first is None else first
        m = yaw_summary(res.angle, res.prototype, test, sym)
        margin = yaw_confidence(res, yaw_margin_steps(NUM_ANGLES))
        sure = margin >= margin.median()
        sub = {k: v[sure] for k, v in test.items() if torch.is_tensor(v) and v.shape[:1] == margin.shape}
        m["confident_asym_median_deg"] = yaw_summary(res.angle[sure], res.prototype[sure], sub, sym)["asym_median_deg"]
        conf = cluster_confusion(res.prototype, test["labels"], min(K, crops.shape[0]), num_classes)
        m["hungarian_acc"] = float(hungarian_accuracy(conf))
        for k, v in m.items():
            acc.setdefault(k, []).append(v)
    return {k: sum(v) / len(v) for k, v in acc.items()}, first


def detected_boxes(run: Path, dm: Any, out: Path, views: int) -> str:
    """Write the boxes the detector of ``run`` finds on the test split (from each scene's first ``views`` fixed views,
    as ``threedq parse`` detects on the views it reads; the run's hand-on threshold) to the boxes file ``out``;
    returns its path."""
    from threedq.data.box_files import save_boxes_file
    from threedq.pipeline.parse import SceneParser, resolve_run
    from threedq.pipeline.report import split_loader

    parser = SceneParser(resolve_run(str(run), None, None, None))
    old, dm.num_input_views = dm.num_input_views, views
    loader = split_loader(dm, "test")
    dm.num_input_views = old
    boxes: dict[str, tuple[Any, Any]] = {}
    files = loader.dataset.files
    with torch.no_grad():
        for batch in loader:
            res = parser(batch)
            for i, a, sc in zip(batch["scene_index"].tolist(), res["aabb"], res["score"]):
                boxes[files[i]] = (a.numpy(), sc.numpy())
    save_boxes_file(out, boxes)
    return str(out)


def object_crops(stage: Any, dm: Any, views: int, boxes: str) -> dict[str, torch.Tensor]:
    """The test objects' crops from ``views`` fixed input views, at the GT boxes or a boxes file's matched boxes."""
    from threedq.pipeline.evaluation import collect_object_crops
    from threedq.pipeline.report import split_loader

    dm.num_input_views, dm.boxes = views, boxes
    with torch.no_grad():
        return collect_object_crops(stage, split_loader(dm, "test"), views, random_encoder_seed=None, progress=False)


def measure(datasets: list[str], encoders: list[str], rows_path: Path, input_views: list[int],
            run: Path | None) -> list[dict[str, Any]]:
    import tempfile

    from shape_benchmark import load_datamodule
    from threedq.stages.viewpred import ViewPrediction

    from threedq.quantization.prototypes import prototype_crops

    machine = {"cpu": cpu_name(), "torch": torch.__version__, "date": time.strftime("%Y-%m-%d")}
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="pose_boxes_"))
    for ds in datasets:
        dm = load_datamodule(DATASETS[ds])
        sym, num_classes = list(dm.index.symmetry_order), len(dm.index.categories)
        sources = {(v, "GT"): "gt" for v in input_views}
        if run is not None:  # boxes found from the views the crops are read from
            sources.update({(v, "detected"): detected_boxes(run, dm, tmp / f"{ds}_{v}.npz", v) for v in input_views})
        seen: dict[tuple[str, int, str], int] = {}
        first_clusters = None
        for spec, ((views, box_name), boxes) in ((e, b) for e in encoders for b in sources.items()):
            name, _, ckpt = spec.partition("=")
            key = (name, views, box_name)
            seen[key] = seen.get(key, -1) + 1
            t0 = time.perf_counter()
            test = object_crops(ViewPrediction(encoder_ckpt=ckpt).eval(), dm, views, boxes)
            crops = prototype_crops(test["learned"], test["raw"], OCCUPANCY_FLOOR)
            row, res = bank_rows(crops, test, sym, num_classes)
            row["pairs_asym_median_deg"] = pair_yaw_error(crops, test, sym)
            where = {"input_views": views, "boxes": box_name}
            new = [{"dataset": ds, "row": name, **where, "seed": seen[key], "objects": int(test["labels"].shape[0]),
                    **row, "seconds": round(time.perf_counter() - t0, 1), **machine}]
            if first_clusters is None:  # the references, once per dataset (the first encoder's crops)
                first_clusters = res.prototype
                refs = {"raw crops (bank)": bank_rows(test["raw"], test, sym, num_classes)[0]}
                refs["raw crops (bank)"]["pairs_asym_median_deg"] = pair_yaw_error(test["raw"], test, sym)
                refs["input occupancy (pairs)"] = {"pairs_asym_median_deg": pair_yaw_error(test["raw"][:, :1],
                                                                                           test, sym)}
                rand = torch.randint(0, NUM_ANGLES, res.angle.shape, generator=torch.Generator().manual_seed(0))
                refs["random yaw"] = yaw_summary(rand, first_clusters, test, sym)
                refs["point-cloud registration"] = _pointcloud(test, sym)
                new += [{"dataset": ds, "row": ref, **where, "seed": 0, "objects": int(test["labels"].shape[0]), **r,
                         **machine} for ref, r in refs.items()]
            for r in new:
                append_row(rows_path, r)
            rows += new
            print(f"{ds}: {name} seed {seen[key]}, {views} view(s), {box_name} boxes: yaw {row['asym_median_deg']:.1f} deg, pairs "
                  f"{row['pairs_asym_median_deg']:.1f}, confident half {row['confident_asym_median_deg']:.1f}",
                  flush=True)
    return rows


def _pointcloud(test: dict, sym: list[int]) -> dict[str, float]:
    from threedq.baselines.pointcloud import PointCloudPrototypes

    acc: dict[str, list[float]] = {}
    for seed in BANK_SEEDS:
        pc = PointCloudPrototypes(num_angles=NUM_ANGLES, threshold=0.25)
        occ = test["raw"][:, :1]
        pc.fit(occ, K=min(K, occ.shape[0]), iterations=EM_ITERATIONS, seed=seed)
        proto, angle, _ = pc.assign(occ)
        for k, v in yaw_summary(angle, proto, test, sym).items():
            acc.setdefault(k, []).append(v)
    return {k: sum(v) / len(v) for k, v in acc.items()}


COLUMNS = (("asym_median_deg", "yaw, asymmetric (median deg)"), ("asym_acc_10", "within 10 deg"),
           ("asym_acc_20", "within 20 deg"), ("confident_asym_median_deg", "confident half (deg)"),
           ("pairs_asym_median_deg", "pairs, direct search (deg)"), ("2fold_median_deg", "2-fold mod 180 (deg)"),
           ("4fold_median_deg", "4-fold mod 90 (deg)"), ("hungarian_acc", "Hungarian"))


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown: one line per (dataset, boxes, input views, row), the mean (and range) over its seeds."""
    out = ["| dataset | boxes | input views | row | seeds | objects | asymmetric objects | "
           + " | ".join(h for _, h in COLUMNS) + " |", "|" + "---|" * (7 + len(COLUMNS))]
    groups: dict[tuple[str, str, int, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["dataset"], r.get("boxes", "GT"), r.get("input_views", 1), r["row"]), []).append(r)
    for (ds, boxes, views, name), rs in sorted(groups.items(), key=lambda g: g[0][:3]):
        cells = []
        for key, _ in COLUMNS:
            v = [r[key] for r in rs if key in r and r[key] == r[key]]
            cells.append(mean_range(v, 2 if "acc" in key else (1 if "deg" in key else 3)) if v else "")
        asym = int(rs[0]["asym_objects"]) if "asym_objects" in rs[0] else ""
        head = f"| {ds} | {boxes} | {views} | {name} | {len(rs)} | {rs[0]['objects']} | {asym} | "
        out.append(head + " | ".join(cells) + " |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--encoder", action="append", default=[], help="NAME=CKPT (a repeated NAME: another seed)")
    ap.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=list(DATASETS))
    ap.add_argument("--input_views", type=int, nargs="+", default=[1], help="a row per number of input views")
    ap.add_argument("--run", type=Path, help="also score on the boxes this threedq em run's detector finds")
    ap.add_argument("--rows", type=Path, default=Path("pose_rows.jsonl"))
    ap.add_argument("--table_only", action="store_true", help="print the table of --rows, measure nothing")
    args = ap.parse_args()
    if not args.table_only:
        if not args.encoder:
            ap.error("--encoder: give at least one NAME=CKPT")
        measure(args.datasets, args.encoder, args.rows, args.input_views, args.run)
    rows = read_rows(args.rows)
    print(f"\n{rows[0]['date']}, {rows[0]['cpu']}, torch {rows[0]['torch']}; K = {K}, "
          f"{NUM_ANGLES} yaws, banks fitted on the test objects (labels unused), {len(BANK_SEEDS)} bank seeds\n")
    print(table(rows))


if __name__ == "__main__":
    main()
