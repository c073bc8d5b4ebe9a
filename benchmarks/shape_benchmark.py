"""Shape-only benchmark: do 3D features hold shape when colour says nothing about the category?

Two datasets of the embedded generator with a random palette colour per instance (``color_mode: random``), made on
first use (about a minute in all on 2 cores):

* ``configs/data/shapes.yaml``: 20 categories told apart by shape alone (CLEVR's cube, sphere, cylinder and the 17
  scanned meshes), 420 training / 150 test scenes;
* ``configs/data/shapes_unseen.yaml``: the 8 held-out meshes, shapes no encoder trained on either dataset has seen,
  200 test scenes (no training split: its banks are fitted on its own test objects, labels unused).

Each encoder (``--encoder NAME=CKPT``, repeatable; a repeated NAME is another seed of that row) and a randomly
initialised encoder of the main job's architecture per ``--random_seeds`` is scored on both, on GT boxes, one input
view per scene, with the measurements of ``threedq eval`` and ``benchmarks/feature_recipes.py``:

* retrieval precision@10 under both protocols (``strict``: leave-one-out over one view; ``paper``: the gallery holds
  the same objects from a second view, twin counted) and the same-object top-1, with the paper's cosine over the
  rotation-max search (and the occupancy-weighted cosine);
* the linear shape probe on voxel-averaged crops (labels train the probe only; shapes set only);
* the quantizer's rotation-aware K = 50 prototype EM (occupancy-weighted, the quantizer's default): Hungarian and
  few-shot accuracy, median relative yaw error on the asymmetric categories; and the no-rot-3DQ bank (no rotation
  search) on the same features; and the same clusters scored against the instances' colours ("Hungarian vs
  colour": a bank that groups objects by colour rather than shape scores high there);

and once per dataset, the references: the raw ``cat[occ, occ * rgb]`` input crops (retrieval, and a K = 50 bank on
them), their occupancy channel alone (retrieval), the colour + size descriptor, and point-cloud registration
(K = 50, rotation-aware, input occupancy). They are cut with the first row whose encoder sees the paper's input (not
an ``encoder_input`` ablation, whose raw crops are what it sees); a run of ablations alone adds ``--random_seeds 0``
for them.

``--datasets embedded`` scores the same rows on the embedded data (``configs/data/clevr_veggie.yaml``, whose
categories are a shape and a colour): the guard that a change made for shape must not lower.

``--input_occupancy`` adds a row per encoder row with the input occupancy skipped into its crops
(:func:`with_input_occupancy`: the learned crop and the occupancy crop at equal weight; a departure from the paper).

``--weights FILE`` adds the paper's 2D ImageNet row once per dataset (:func:`imagenet_row`): a torchvision ResNet-18
file, or the ImageNet MobileNetV2 stand-in (``docs/studies/imagenet.md``), its last stage average-pooled in each
projected GT box as ``threedq eval --weights`` does; cosine retrieval without rotation search under both protocols (the
gallery features from the second view's image), the shape probe on the pooled vectors, ResNetRet / ResNetClass
few-shot (paper Table 1) and a K = 50 bank without rotation search (no-rot columns; "Hungarian vs colour" of that
bank in the extra table). It may run alone (``--random_seeds`` with no seed and no ``--encoder``); beside encoder
rows its test objects are checked to be theirs.

One JSON line per (dataset, row, seed) is appended to ``--out`` as soon as it is measured; the markdown table (mean
and range over seeds) is printed and, with ``--md``, written; ``--table_only`` rebuilds it from ``--out``.

    python benchmarks/shape_benchmark.py --random_seeds 0 1 \\
        --encoder "view prediction=runs/em/00_viewpred/checkpoints/last.ckpt" \\
        --encoder "round-4 mining=runs/em/r04_mining/checkpoints/last.ckpt"

Training encoders on the shapes data itself, scored at several steps: ``benchmarks/feature_recipes.py
--data_config data/shapes.yaml --probe --cluster --eval_steps 100 500 1700``.
"""

from __future__ import annotations

import argparse
import gc
import json
import time
from pathlib import Path
from typing import Any

from threedq.machine import cpu_name

DATASETS = {"shapes": "data/shapes.yaml", "unseen": "data/shapes_unseen.yaml"}
# the embedded data, where a category is a shape and a colour: the shape study's guard ("nothing lower than today"),
# scored only when asked for (--datasets embedded); its banks are fitted on its training objects like the shapes set's
GUARD_DATASETS = {"embedded": "data/clevr_veggie.yaml"}
ALL_DATASETS = {**DATASETS, **GUARD_DATASETS}
K = 50
OCCUPANCY_FLOOR = 0.2  # the quantizer's default crop weighting (configs/stages/quantizer.yaml)
EM_SEEDS = (0, 1)


def load_datamodule(config: str) -> Any:
    """The DataModule a data config names (a path, or one inside the packaged ``configs/``), prepared and set up."""
    import importlib

    from threedq.pipeline.lightning_cli import load_config

    spec = load_config(config)["data"]  # with its base's keys (``base:``)
    module, _, cls = spec["class_path"].rpartition(".")
    dm = getattr(importlib.import_module(module), cls)(**spec.get("init_args", {}))
    dm.prepare_data()
    dm.setup("fit")
    dm.setup("test")
    return dm


def random_stage(seed: int) -> Any:
    """A view-prediction stage of the main job's architecture (``configs/stages/viewpred.yaml``), randomly
    initialised with ``seed``."""
    import torch
    import yaml

    from threedq.pipeline.lightning_cli import resolve_config
    from threedq.stages.viewpred import ViewPrediction

    args = yaml.safe_load(Path(resolve_config("stages/viewpred.yaml")).read_text())["model"]["init_args"]
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return ViewPrediction(**args).eval()


def object_crops(stage: Any, dm: Any) -> tuple[dict, dict | None]:
    """(test crops with the paper protocol's gallery, training crops or None) on GT boxes, one input view."""
    import torch

    from threedq.pipeline.evaluation import collect_object_crops
    from threedq.pipeline.report import split_loader

    with torch.no_grad():
        test = collect_object_crops(stage, split_loader(dm, "test", gallery=True), random_encoder_seed=None,
                                    progress=False, gallery=True)
        train = (collect_object_crops(stage, split_loader(dm, "train"), random_encoder_seed=None, progress=False)
                 if dm.index.files("train") else None)
    return test, train


def _bank_metrics(method: str, fit: dict, test: dict, num_classes: int, sym: list[int],
                  floor: float | None) -> dict[str, float]:
    """Mean over :data:`EM_SEEDS` of one K-prototype bank's Hungarian / few-shot accuracy and yaw error:
    ``threedq`` (rotation-aware, 36 yaws), ``no_rot`` (1 yaw) on ``learned`` crops, ``pointcloud`` on ``raw``.
    Where ``test`` holds ``colours`` (palette index per object), also ``colour_hungarian_acc``: the same clusters
    scored against the instances' colours instead of their shapes (a bank that groups by colour scores high)."""
    from threedq.metrics import cluster_confusion, hungarian_accuracy
    from threedq.pipeline.evaluation import quantization_metrics
    from threedq.pipeline.report import _assign

    acc: dict[str, list[float]] = {}
    k = min(K, int(fit["labels"].shape[0]))
    for seed in EM_SEEDS:
        proto, angle, a = _assign(method, fit, test, k, 36, 10, seed, floor)
        m = quantization_metrics(proto, angle, a, k, test["labels"], test["boxes"][:, 6], num_classes, sym, seed=seed)
        if "colours" in test:
            colours = test["colours"]
            conf = cluster_confusion(proto, colours, k, int(colours.max()) + 1)
            m["colour_hungarian_acc"] = float(hungarian_accuracy(conf))
        for key in ("hungarian_acc", "fewshot_acc", "yaw_median_deg", "colour_hungarian_acc"):
            if key in m:
                acc.setdefault(key, []).append(m[key])
    return {key: sum(v) / len(v) for key, v in acc.items()}


def instance_colours(dm: Any, split: str, crops: dict) -> Any:
    """``[N]`` long: each cropped object's colour as an index into
    :data:`threedq.data.catalog.RANDOM_COLOR_PALETTE` (``color_mode: random`` data), or None where the scenes record
    no colours. Objects are matched to their scene's rows by their box."""
    import numpy as np
    import torch

    from threedq.data.catalog import RANDOM_COLOR_PALETTE
    from threedq.scene import load_scene

    palette = np.asarray(RANDOM_COLOR_PALETTE)
    files = dm.index.files(split)
    out = torch.full((crops["labels"].shape[0],), -1, dtype=torch.long)
    records: dict[int, Any] = {}
    for i, (s, box) in enumerate(zip(crops["scene"].tolist(), crops["boxes"].numpy())):
        if s not in records:
            records[s] = load_scene(Path(dm.data_dir) / files[s], validate=False)
        rec = records[s]
        colours = rec.meta.get("object_colors")
        if colours is None:
            return None
        row = np.flatnonzero(np.all(np.abs(rec.boxes - box[None]) < 1e-4, axis=1))
        if len(row) != 1:
            raise RuntimeError(f"{files[s]}: object {i}'s box matches {len(row)} rows of the scene's boxes")
        out[i] = int(np.argmin(np.abs(palette - np.asarray(colours[row[0]])[None]).sum(1)))
    return out


def with_input_occupancy(crops: dict) -> dict:
    """The crops with the input occupancy skipped into the features (a lever of the shape study; a departure from the
    paper, whose crops hold the learned features alone): ``learned`` becomes ``cat[f / |f|, o / |o|]`` per object,
    ``f`` its learned crop and ``o`` its input-occupancy crop (channel 0 of ``raw``), each scaled to unit norm, so
    that their cosine is the mean of the two parts' cosines; likewise ``gallery_learned``.

    Shapes: ``learned`` ``[N, C, s, s, s]`` -> ``[N, C + 1, s, s, s]``."""
    import torch

    def unit(x: Any) -> Any:
        return x / x.flatten(1).norm(dim=1).clamp_min(1e-8).view(-1, *([1] * (x.dim() - 1)))

    out = dict(crops)
    for key, raw in (("learned", "raw"), ("gallery_learned", "gallery_raw")):
        if key in crops:
            out[key] = torch.cat([unit(crops[key].float()), unit(crops[raw][:, :1].float())], dim=1)
    return out


def _retrieval(test: dict) -> dict[str, float]:
    from feature_recipes import _score

    out = {}
    for sim in ("cosine", "occupancy"):
        out.update(_score(test, sim))
    return out


def score_features(test: dict, train: dict | None, num_classes: int, sym: list[int]) -> dict[str, Any]:
    """Every number of one row from the ``learned`` crops (and the references' from ``raw``)."""
    from threedq.pipeline.evaluation import probe_table

    row: dict[str, Any] = _retrieval(test)
    fit = train if train is not None else test  # the unseen set has no training split: the bank fits its objects
    if train is not None:
        acc = probe_table(train, test)["accuracy"]
        row["probe/learned"], row["probe/raw"] = acc["learned"], acc["raw_rgb_occupancy"]
    for method in ("threedq", "no_rot"):
        for k, v in _bank_metrics(method, fit, test, num_classes, sym, OCCUPANCY_FLOOR).items():
            row[f"{method}/{k}"] = v
    return row


def references(test: dict, train: dict | None, num_classes: int, sym: list[int]) -> dict[str, Any]:
    """The encoder-free rows: raw crops (retrieval and a K = 50 rotation-aware bank on them), point-cloud
    registration."""
    from threedq.pipeline.evaluation import retrieval_table

    fit = train if train is not None else test
    as_learned = lambda c: {**c, "learned": c["raw"]}  # noqa: E731 - the raw crops scored as features
    row: dict[str, Any] = {}
    # the input occupancy alone (channel 0 of the raw crops): what shape the encoder is given, without colour
    occ = {"learned": test["raw"][:, :1], "gallery_learned": test["gallery_raw"][:, :1], "labels": test["labels"]}
    p = retrieval_table(occ)[0]["protocols"]
    row["raw_occupancy/strict"] = p["strict"]["precision_at_k"]["learned"]
    row["raw_occupancy/paper"] = p["paper"]["precision_at_k"]["learned"]
    row["raw_occupancy/top1"] = p["paper"]["same_object_top1"]["learned"]
    for k, v in _bank_metrics("threedq", as_learned(fit), as_learned(test), num_classes, sym, None).items():
        row[f"raw_bank/{k}"] = v
    for k, v in _bank_metrics("pointcloud", fit, test, num_classes, sym, None).items():
        row[f"pointcloud/{k}"] = v
    return row


def imagenet_row(net: Any, dm: Any, num_classes: int, sym: list[int], labels: Any = None) -> dict[str, Any]:
    """Every number of the 2D ImageNet row (:func:`~threedq.pipeline.baselines2d.collect_resnet_features`: the input
    view's features ``[N, C]``, the gallery view's for the paper protocol, the training split's for the probe).

    Args:
        net: :func:`~threedq.pipeline.baselines2d.load_resnet` (ResNet-18 or the MobileNetV2 stand-in).
        dm: the dataset's DataModule.
        num_classes, sym: the dataset's category count and symmetry orders (for the bank's metrics).
        labels: ``[N]`` the encoder rows' test labels, where they ran: the objects must be the same (loader order).

    Returns:
        ``cosine/strict``, ``cosine/paper``, ``cosine/top1`` (cosine, no rotation search), ``probe/learned`` (where
        there is a training split),
        ``ret_acc`` / ``class_acc`` (2 shots, seed 0, as ``threedq eval``), ``no_rot/*`` (K = 50 bank on the
        features, no rotation search, with "Hungarian vs colour"; the yaw is meaningless there and dropped),
        ``objects`` and the backbone's fields.
    """
    import torch

    from threedq.metrics.fewshot import linear_probe
    from threedq.pipeline.baselines2d import (backbone_fields, collect_resnet_features, resnet_paper_results,
                                              resnet_results)
    from threedq.pipeline.report import split_loader

    loader = split_loader(dm, "test", gallery=True)
    q = collect_resnet_features(net, loader, progress=False)
    g = collect_resnet_features(net, loader, progress=False, view=dm.num_input_views)
    if labels is not None and not torch.equal(q["labels"], labels):
        raise RuntimeError("ImageNet row: the test objects differ from the encoder rows' (loader order?)")
    rr = resnet_results(q, k=10, shots=2, seed=0)  # strict protocol (leave-one-out), ResNetRet, ResNetClass
    pp = resnet_paper_results(q, g, k=10)  # the gallery view's features, twin counted
    row: dict[str, Any] = {"objects": int(q["labels"].shape[0]),
                           "cosine/strict": rr["precision_at_k"], "cosine/paper": pp["paper_precision_at_k"],
                           "cosine/top1": pp["same_object_top1"], "ret_acc": rr["ret_acc"],
                           "class_acc": rr["class_acc"], "not_visible": rr["not_visible"]}
    train = (collect_resnet_features(net, split_loader(dm, "train"), progress=False)
             if dm.index.files("train") else None)
    if train is not None:
        row["probe/learned"] = float(linear_probe(train["features"], train["labels"], q["features"],
                                                  q["labels"])["accuracy"])
    as_crops = lambda f: f[:, :, None, None, None]  # noqa: E731 - a [N, C] vector as a 1-voxel crop for the bank
    te = {"learned": as_crops(q["features"]), "labels": q["labels"], "boxes": q["boxes"]}
    colours = instance_colours(dm, "test", q)
    if colours is not None:
        te["colours"] = colours
    fit = {"learned": as_crops(train["features"]), "labels": train["labels"]} if train is not None else te
    for k, v in _bank_metrics("no_rot", fit, te, num_classes, sym, None).items():
        if k != "yaw_median_deg":
            row[f"no_rot/{k}"] = v
    return {**row, **backbone_fields(net)}


def _append(out: Path, row: dict[str, Any]) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("a") as f:
        f.write(json.dumps(row) + "\n")


def run(encoders: list[str], random_seeds: list[int], datasets: list[str], out: Path,
        input_occupancy: bool = False, weights: Path | None = None) -> None:
    import torch

    from threedq.pipeline.baselines2d import load_resnet
    from threedq.stages.viewpred import ViewPrediction

    net = load_resnet(weights) if weights is not None else None  # a bad file is refused before the long work

    machine = {"cpu": cpu_name(), "torch": torch.__version__, "threads": torch.get_num_threads(),
               "date": time.strftime("%Y-%m-%d")}
    for ds in datasets:
        dm = load_datamodule(ALL_DATASETS[ds])
        num_classes, sym = len(dm.index.categories), list(dm.index.symmetry_order)
        rows: list[tuple[str, int | None, Any]] = [("random encoder", s, lambda s=s: random_stage(s))
                                                   for s in random_seeds]
        seen: dict[str, int] = {}
        for spec in encoders:
            name, _, ckpt = spec.partition("=")
            seen[name] = seen.get(name, -1) + 1
            rows.append((name, seen[name], lambda ckpt=ckpt: ViewPrediction(encoder_ckpt=ckpt).eval()))
        refs_done = False
        first_labels = None  # the test objects' labels of the first encoder row (the ImageNet row is checked on them)
        colours = None  # the test objects are the same for every row: their colours are read once per dataset
        for name, seed, make in rows:
            t0 = time.perf_counter()
            stage = make()
            test, train = object_crops(stage, dm)
            if colours is None:
                colours = instance_colours(dm, "test", test)
            if colours is not None:
                test["colours"] = colours
            row = {"dataset": ds, "row": name, "seed": seed, "objects": int(test["labels"].shape[0]),
                   **score_features(test, train, num_classes, sym), **machine}
            row["seconds"] = round(time.perf_counter() - t0, 1)
            _append(out, row)
            print(f"{ds} / {name} [{seed}]: strict {row['cosine/strict']:.3f} paper {row['cosine/paper']:.3f} "
                  f"top-1 {row['cosine/top1']:.3f} Hungarian {row['threedq/hungarian_acc']:.3f} "
                  f"yaw {row['threedq/yaw_median_deg']:.0f} deg ({row['seconds']:.0f} s)", flush=True)
            if input_occupancy:
                t1 = time.perf_counter()
                tr2 = with_input_occupancy(train) if train is not None else None
                row2 = {"dataset": ds, "row": f"{name} + input occupancy", "seed": seed,
                        "objects": int(test["labels"].shape[0]),
                        **score_features(with_input_occupancy(test), tr2, num_classes, sym), **machine}
                row2["seconds"] = round(time.perf_counter() - t1, 1)
                _append(out, row2)
                print(f"{ds} / {row2['row']} [{seed}]: strict {row2['cosine/strict']:.3f} paper "
                      f"{row2['cosine/paper']:.3f} Hungarian {row2['threedq/hungarian_acc']:.3f}", flush=True)
            if not refs_done and getattr(stage, "encoder_input_kind", "occupancy_colour") == "occupancy_colour":
                # the references are the paper's input crops: never those of an encoder that sees an ablated input
                ref = {"dataset": ds, "row": "references", "seed": None, "objects": int(test["labels"].shape[0]),
                       **references(test, train, num_classes, sym), **machine}
                _append(out, ref)
                print(f"{ds} / references: point-cloud Hungarian {ref['pointcloud/hungarian_acc']:.3f}, raw bank "
                      f"{ref['raw_bank/hungarian_acc']:.3f}", flush=True)
                refs_done = True
                first_labels = test["labels"]
            del stage, test, train
            gc.collect()
        if net is not None:  # the 2D ImageNet row, once per dataset (checked against the encoder rows' objects)
            t2 = time.perf_counter()
            rn = {"dataset": ds, "row": net.label, "seed": None, **imagenet_row(net, dm, num_classes, sym, first_labels),
                  **machine}
            rn["seconds"] = round(time.perf_counter() - t2, 1)
            _append(out, rn)
            print(f"{ds} / {rn['row']}: strict {rn['cosine/strict']:.3f} paper {rn['cosine/paper']:.3f} "
                  f"top-1 {rn['cosine/top1']:.3f} ResNetRet {rn['ret_acc']:.3f} ResNetClass "
                  f"{rn['class_acc']:.3f} ({rn['seconds']:.0f} s)", flush=True)
            gc.collect()


# ---- the table ------------------------------------------------------------------------------------------------
COLUMNS = [("cosine/strict", "strict P@10"), ("cosine/paper", "paper P@10"), ("cosine/top1", "same-object top-1"),
           ("probe/learned", "shape probe"), ("threedq/hungarian_acc", "Hungarian K=50"),
           ("threedq/fewshot_acc", "few-shot"), ("threedq/yaw_median_deg", "yaw median (deg, asym.)"),
           ("no_rot/hungarian_acc", "no-rot Hungarian"), ("threedq/colour_hungarian_acc", "Hungarian vs colour")]


def _cell(values: list[float], digits: int = 3) -> str:
    values = [v for v in values if v is not None and v == v]
    if not values:
        return "-"
    m = sum(values) / len(values)
    f = f"{{:.{digits}f}}"
    return f.format(m) + (f" ({f.format(min(values))}-{f.format(max(values))})" if len(values) > 1 else "")


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown, one table per dataset: the reference rows, then each encoder row (mean and range over seeds)."""
    lines: list[str] = []
    for ds in dict.fromkeys(r["dataset"] for r in rows):
        rs = [r for r in rows if r["dataset"] == ds]
        feats = [r for r in rs if r["row"] != "references" and "backbone" not in r]
        imagenet = [r for r in rs if "backbone" in r]
        refs = [r for r in rs if r["row"] == "references"]
        if not feats and not imagenet:
            continue
        machine = (feats or imagenet)[0]
        lines += [f"### {ds} ({ALL_DATASETS.get(ds, ds)}; {machine['objects']} test objects; GT boxes, one input view)",
                  "", f"{machine['cpu']}, torch {machine['torch']}, {machine['threads']} threads, {machine['date']}. "
                  "Retrieval: rotation-max search over 36 yaws, cosine; banks: K = 50, 36 yaws, occupancy-weighted "
                  f"crops (floor {OCCUPANCY_FLOOR}), mean of EM seeds {', '.join(map(str, EM_SEEDS))}.", "",
                  "| features | " + " | ".join(c for _, c in COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
        digits = lambda k: 0 if "yaw" in k else 3  # noqa: E731
        first = {"features": feats[:1], "references": refs[:1]}  # the encoder-free numbers, equal in every row
        reference_rows = {
            "raw `cat[occ, occ * rgb]` crops": {
                "cosine/strict": ("features", "raw/strict"), "cosine/paper": ("features", "raw/paper"),
                "cosine/top1": ("features", "raw/top1"), "probe/learned": ("features", "probe/raw"),
                "threedq/hungarian_acc": ("references", "raw_bank/hungarian_acc"),
                "threedq/fewshot_acc": ("references", "raw_bank/fewshot_acc"),
                "threedq/yaw_median_deg": ("references", "raw_bank/yaw_median_deg"),
                "threedq/colour_hungarian_acc": ("references", "raw_bank/colour_hungarian_acc")},
            "raw occupancy channel alone": {
                "cosine/strict": ("references", "raw_occupancy/strict"),
                "cosine/paper": ("references", "raw_occupancy/paper"),
                "cosine/top1": ("references", "raw_occupancy/top1")},
            "colour + size descriptor": {
                "cosine/strict": ("features", "descriptor/strict"), "cosine/paper": ("features", "descriptor/paper"),
                "cosine/top1": ("features", "descriptor/top1")},
            "point-cloud registration": {
                "threedq/hungarian_acc": ("references", "pointcloud/hungarian_acc"),
                "threedq/fewshot_acc": ("references", "pointcloud/fewshot_acc"),
                "threedq/yaw_median_deg": ("references", "pointcloud/yaw_median_deg"),
                "threedq/colour_hungarian_acc": ("references", "pointcloud/colour_hungarian_acc")},
        }
        for label, where in reference_rows.items():
            cells = [_cell([r.get(where[k][1]) for r in first[where[k][0]]], digits(k)) if k in where else "-"
                     for k, _ in COLUMNS]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        for name in dict.fromkeys(r["row"] for r in feats):
            group = [r for r in feats if r["row"] == name]
            label = f"{name} ({len(group)} seed{'s' if len(group) > 1 else ''})"
            lines.append(f"| {label} | " + " | ".join(_cell([r.get(k) for r in group], digits(k)) for k, _ in COLUMNS)
                         + " |")
        def imagenet_label(r: dict[str, Any]) -> str:
            return f"{r['backbone_label']}, {r['feature_stage']} pooled in the projected GT box (no rotation search)"

        for r in imagenet:  # the 2D rows: no rotation search, no yaw; their bank is the no-rot one
            lines.append(f"| {imagenet_label(r)} | " + " | ".join(_cell([r.get(k)], digits(k)) for k, _ in COLUMNS)
                         + " |")
        if imagenet:
            lines += ["", "ImageNet rows: few-shot as in paper Table 1 (2 labelled objects per category, seed 0) and "
                      "the colours of their no-rotation banks' clusters; the encoder rows' few-shot column above "
                      "propagates the labels through their prototypes instead.", "",
                      "| features | ResNetRet (nearest labelled object) | ResNetClass (linear classifier on the shots) "
                      "| no-rot Hungarian K=50 | no-rot Hungarian vs colour |", "|---|---|---|---|---|"]
            lines += [f"| {imagenet_label(r)} | {_cell([r['ret_acc']])} | {_cell([r['class_acc']])} | "
                      f"{_cell([r.get('no_rot/hungarian_acc')])} | {_cell([r.get('no_rot/colour_hungarian_acc')])} |"
                      for r in imagenet]
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--encoder", action="append", default=[], metavar="NAME=CKPT",
                    help="a checkpoint to score (repeatable; a repeated NAME is another seed of that row)")
    ap.add_argument("--random_seeds", type=int, nargs="*", default=[0, 1],
                    help="randomly initialised encoders of the main job's architecture, one row seed each")
    ap.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=list(ALL_DATASETS),
                    help="the shape-only sets (default) and, when named, the embedded data as the guard "
                         "(%(choices)s)")
    ap.add_argument("--input_occupancy", action="store_true",
                    help="also score each row with the input occupancy skipped into its crops (with_input_occupancy)")
    ap.add_argument("--weights", type=Path, default=None,
                    help="an ImageNet file for the 2D row (torchvision resnet18, or the MobileNetV2 stand-in of "
                         "docs/studies/imagenet.md); needs an encoder row in the same run")
    ap.add_argument("--out", type=Path, default=Path("runs/shape_benchmark/results.jsonl"))
    ap.add_argument("--md", type=Path, default=None, help="also write the table here")
    ap.add_argument("--table_only", action="store_true", help="print the table of --out and stop")
    args = ap.parse_args()
    for spec in args.encoder:
        name, sep, ckpt = spec.partition("=")
        if not sep or not name or not Path(ckpt).is_file():
            ap.error(f"--encoder {spec!r}: expected NAME=CKPT with an existing checkpoint file")
    if not args.table_only:
        run(args.encoder, args.random_seeds, args.datasets, args.out, args.input_occupancy, args.weights)
    rows = [json.loads(line) for line in args.out.read_text().splitlines() if line.strip()]
    md = table(rows)
    print(md)
    if args.md:
        args.md.parent.mkdir(parents=True, exist_ok=True)
        args.md.write_text(md + "\n")


if __name__ == "__main__":
    main()
