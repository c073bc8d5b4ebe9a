"""Shape-only benchmark: do 3D features hold shape when colour says nothing about the category?

Datasets: ``shapes`` (20 categories told apart by shape alone), ``unseen`` (8 held-out meshes, test split only) and,
with ``--datasets embedded``, the embedded data as a guard. Each ``--encoder NAME=CKPT`` (a repeated NAME is another
seed) and a random encoder per ``--random_seeds`` is scored on GT boxes, one input view: retrieval, the linear shape
probe and K = 50 prototype banks; once per dataset the encoder-free references. One JSON line per (dataset, row, seed)
is appended to ``--out``; the markdown table is printed (``--md``: written; ``--table_only``: rebuilt from ``--out``).

    python benchmarks/shape_benchmark.py --random_seeds 0 1 \\
        --encoder "view prediction=runs/em/00_viewpred/checkpoints/last.ckpt" \\
        --encoder "round-4 mining=runs/em/r04_mining/checkpoints/last.ckpt"
"""

from __future__ import annotations

import argparse
import gc
import time
from pathlib import Path
from typing import Any

from _common import append_row, mean_range, read_rows
from _common import table as md_table

from threedq.machine import cpu_name

DATASETS = {"shapes": "data/shapes.yaml", "unseen": "data/shapes_unseen.yaml"}
#: the embedded data (a category is a shape and a colour), scored only with ``--datasets embedded``
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
    """A view-prediction stage of the main job's architecture (``configs/stages/viewpred.yaml``) seeded ``seed``."""
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
    """Mean over :data:`EM_SEEDS` of one K-prototype bank's Hungarian / few-shot accuracy and yaw error (``threedq``,
    ``no_rot`` on ``learned`` crops, ``pointcloud`` on ``raw``); with ``test["colours"]``, ``colour_hungarian_acc``."""
    from threedq.metrics import cluster_confusion, hungarian_accuracy
    from threedq.pipeline.evaluation import quantization_metrics
    from threedq.pipeline.report import _assign

    acc: dict[str, list[float]] = {}
    k = min(K, int(fit["labels"].shape[0]))
    for seed in EM_SEEDS:
        proto, angle, a = _assign(method, fit, test, k, 36, 10, seed, floor)
        m = quantization_metrics(proto, angle, a, k, test["labels"], test["boxes"][:, 6], num_classes, sym, seed=seed)
        if "colours" in test:
            conf = cluster_confusion(proto, test["colours"], k, int(test["colours"].max()) + 1)
            m["colour_hungarian_acc"] = float(hungarian_accuracy(conf))
        for key in ("hungarian_acc", "fewshot_acc", "yaw_median_deg", "colour_hungarian_acc"):
            if key in m:
                acc.setdefault(key, []).append(m[key])
    return {key: sum(v) / len(v) for key, v in acc.items()}


def instance_colours(dm: Any, split: str, crops: dict) -> Any:
    """``[N]`` long: each cropped object's index into :data:`threedq.data.catalog.RANDOM_COLOR_PALETTE` (matched to
    its scene's row by its box), or None where the scenes record no colours."""
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
        rec, colours = records[s], records[s].meta.get("object_colors")
        if colours is None:
            return None
        row = np.flatnonzero(np.all(np.abs(rec.boxes - box[None]) < 1e-4, axis=1))
        if len(row) != 1:
            raise RuntimeError(f"{files[s]}: object {i}'s box matches {len(row)} rows of the scene's boxes")
        out[i] = int(np.argmin(np.abs(palette - np.asarray(colours[row[0]])[None]).sum(1)))
    return out


def with_input_occupancy(crops: dict) -> dict:
    """The crops with ``learned`` ``[N, C, s, s, s]`` -> ``cat[f / |f|, o / |o|]`` ``[N, C + 1, s, s, s]`` (``o`` the
    input occupancy, channel 0 of ``raw``); likewise ``gallery_learned``."""
    import torch

    def unit(x: Any) -> Any:
        return x / x.flatten(1).norm(dim=1).clamp_min(1e-8).view(-1, *([1] * (x.dim() - 1)))

    out = dict(crops)
    for key, raw in (("learned", "raw"), ("gallery_learned", "gallery_raw")):
        if key in crops:
            out[key] = torch.cat([unit(crops[key].float()), unit(crops[raw][:, :1].float())], dim=1)
    return out


def score_features(test: dict, train: dict | None, num_classes: int, sym: list[int]) -> dict[str, Any]:
    """Every number of one row from the ``learned`` crops (and the references' from ``raw``)."""
    from feature_recipes import _score

    from threedq.pipeline.evaluation import probe_table

    row: dict[str, Any] = {**_score(test, "cosine"), **_score(test, "occupancy")}
    fit = train if train is not None else test  # the unseen set has no training split: the bank fits its objects
    if train is not None:
        acc = probe_table(train, test)["accuracy"]
        row["probe/learned"], row["probe/raw"] = acc["learned"], acc["raw_rgb_occupancy"]
    for method in ("threedq", "no_rot"):
        for k, v in _bank_metrics(method, fit, test, num_classes, sym, OCCUPANCY_FLOOR).items():
            row[f"{method}/{k}"] = v
    return row


def references(test: dict, train: dict | None, num_classes: int, sym: list[int]) -> dict[str, Any]:
    """The encoder-free rows: raw crops (retrieval and a K = 50 bank), point-cloud registration."""
    from threedq.pipeline.evaluation import retrieval_table

    fit = train if train is not None else test
    as_learned = lambda c: {**c, "learned": c["raw"]}  # noqa: E731 - the raw crops scored as features
    occ = {"learned": test["raw"][:, :1], "gallery_learned": test["gallery_raw"][:, :1], "labels": test["labels"]}
    p = retrieval_table(occ)[0]["protocols"]  # the input occupancy alone: the shape the encoder is given
    row: dict[str, Any] = {"raw_occupancy/strict": p["strict"]["precision_at_k"]["learned"],
                           "raw_occupancy/paper": p["paper"]["precision_at_k"]["learned"],
                           "raw_occupancy/top1": p["paper"]["same_object_top1"]["learned"]}
    for prefix, method, f, t in (("raw_bank", "threedq", as_learned(fit), as_learned(test)),
                                 ("pointcloud", "pointcloud", fit, test)):
        row.update({f"{prefix}/{k}": v for k, v in _bank_metrics(method, f, t, num_classes, sym, None).items()})
    return row


def imagenet_row(net: Any, dm: Any, num_classes: int, sym: list[int], labels: Any = None) -> dict[str, Any]:
    """Every number of the 2D ImageNet row (pooled ``[N, C]`` features of the input view, the gallery view's for
    the paper protocol, the training split's for the probe).

    Args:
        net: :func:`~threedq.pipeline.baselines2d.load_resnet` (ResNet-18 or the MobileNetV2 stand-in).
        dm: the dataset's DataModule; num_classes, sym: its category count and symmetry orders.
        labels: ``[N]`` the encoder rows' test labels, where they ran: the objects must be the same (loader order).

    Returns:
        ``cosine/strict``, ``cosine/paper``, ``cosine/top1``, ``probe/learned`` (with a training split), ``ret_acc``,
        ``class_acc`` (2 shots, seed 0), ``no_rot/*`` (K = 50 bank, no yaw), ``objects`` and the backbone's fields.
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
    rr, pp = resnet_results(q, k=10, shots=2, seed=0), resnet_paper_results(q, g, k=10)
    row: dict[str, Any] = {"objects": int(q["labels"].shape[0]), "cosine/strict": rr["precision_at_k"],
                           "cosine/paper": pp["paper_precision_at_k"], "cosine/top1": pp["same_object_top1"],
                           **{k: rr[k] for k in ("ret_acc", "class_acc", "not_visible")}}
    train = collect_resnet_features(net, split_loader(dm, "train"), progress=False) if dm.index.files("train") else None
    if train is not None:
        row["probe/learned"] = float(linear_probe(train["features"], train["labels"], q["features"],
                                                  q["labels"])["accuracy"])
    as_crops = lambda f: f[:, :, None, None, None]  # noqa: E731 - a [N, C] vector as a 1-voxel crop for the bank
    te = {"learned": as_crops(q["features"]), "labels": q["labels"], "boxes": q["boxes"]}
    if (colours := instance_colours(dm, "test", q)) is not None:
        te["colours"] = colours
    fit = {"learned": as_crops(train["features"]), "labels": train["labels"]} if train is not None else te
    row.update({f"no_rot/{k}": v for k, v in _bank_metrics("no_rot", fit, te, num_classes, sym, None).items()
                if k != "yaw_median_deg"})
    return {**row, **backbone_fields(net)}


def run(encoders: list[str], random_seeds: list[int], datasets: list[str], out: Path,
        input_occupancy: bool = False, weights: Path | None = None) -> None:
    import torch

    from threedq.pipeline.baselines2d import load_resnet
    from threedq.stages.viewpred import ViewPrediction

    net = load_resnet(weights) if weights is not None else None  # a bad file is refused before the long work

    machine = {"cpu": cpu_name(), "torch": torch.__version__, "threads": torch.get_num_threads(),
               "date": time.strftime("%Y-%m-%d")}

    def record(ds: str, name: str, seed: int | None, values: dict[str, Any], t0: float | None) -> dict[str, Any]:
        row = {"dataset": ds, "row": name, "seed": seed, **values, **machine}
        if t0 is not None:
            row["seconds"] = round(time.perf_counter() - t0, 1)
        append_row(out, row)
        return row

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
        refs_done, first_labels, colours = False, None, None  # colours: the same objects in every row, read once
        for name, seed, make in rows:
            t0 = time.perf_counter()
            stage = make()
            test, train = object_crops(stage, dm)
            colours = colours if colours is not None else instance_colours(dm, "test", test)
            if colours is not None:
                test["colours"] = colours
            objects = {"objects": int(test["labels"].shape[0])}
            row = record(ds, name, seed, {**objects, **score_features(test, train, num_classes, sym)}, t0)
            print(f"{ds} / {name} [{seed}]: strict {row['cosine/strict']:.3f} paper {row['cosine/paper']:.3f} "
                  f"top-1 {row['cosine/top1']:.3f} Hungarian {row['threedq/hungarian_acc']:.3f} "
                  f"yaw {row['threedq/yaw_median_deg']:.0f} deg ({row['seconds']:.0f} s)", flush=True)
            if input_occupancy:
                t1 = time.perf_counter()
                tr2 = with_input_occupancy(train) if train is not None else None
                values = {**objects, **score_features(with_input_occupancy(test), tr2, num_classes, sym)}
                row2 = record(ds, f"{name} + input occupancy", seed, values, t1)
                print(f"{ds} / {row2['row']} [{seed}]: strict {row2['cosine/strict']:.3f} paper "
                      f"{row2['cosine/paper']:.3f} Hungarian {row2['threedq/hungarian_acc']:.3f}", flush=True)
            if not refs_done and getattr(stage, "encoder_input_kind", "occupancy_colour") == "occupancy_colour":
                ref = record(ds, "references", None, {**objects, **references(test, train, num_classes, sym)}, None)
                print(f"{ds} / references: point-cloud Hungarian {ref['pointcloud/hungarian_acc']:.3f}, raw bank "
                      f"{ref['raw_bank/hungarian_acc']:.3f}", flush=True)
                refs_done, first_labels = True, test["labels"]
            del stage, test, train
            gc.collect()
        if net is not None:  # the 2D ImageNet row, once per dataset (checked against the encoder rows' objects)
            t2 = time.perf_counter()
            rn = record(ds, net.label, None, imagenet_row(net, dm, num_classes, sym, first_labels), t2)
            print(f"{ds} / {rn['row']}: strict {rn['cosine/strict']:.3f} paper {rn['cosine/paper']:.3f} "
                  f"top-1 {rn['cosine/top1']:.3f} ResNetRet {rn['ret_acc']:.3f} ResNetClass "
                  f"{rn['class_acc']:.3f} ({rn['seconds']:.0f} s)", flush=True)
            gc.collect()


COLUMNS = [("cosine/strict", "strict P@10"), ("cosine/paper", "paper P@10"), ("cosine/top1", "same-object top-1"),
           ("probe/learned", "shape probe"), ("threedq/hungarian_acc", "Hungarian K=50"),
           ("threedq/fewshot_acc", "few-shot"), ("threedq/yaw_median_deg", "yaw median (deg, asym.)"),
           ("no_rot/hungarian_acc", "no-rot Hungarian"), ("threedq/colour_hungarian_acc", "Hungarian vs colour")]


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown, one table per dataset: the reference rows, then each encoder row (mean and range over seeds)."""
    lines: list[str] = []
    digits = lambda k: 0 if "yaw" in k else 3  # noqa: E731
    head = ["features", *(c for _, c in COLUMNS)]
    for ds in dict.fromkeys(r["dataset"] for r in rows):
        rs = [r for r in rows if r["dataset"] == ds]
        feats = [r for r in rs if r["row"] != "references" and "backbone" not in r]
        imagenet = [r for r in rs if "backbone" in r]
        if not feats and not imagenet:
            continue
        m = (feats or imagenet)[0]
        lines += [f"### {ds} ({ALL_DATASETS.get(ds, ds)}; {m['objects']} test objects; GT boxes, one input view)", "",
                  f"{m['cpu']}, torch {m['torch']}, {m['threads']} threads, {m['date']}. Retrieval: rotation-max "
                  "search over 36 yaws, cosine; banks: K = 50, 36 yaws, occupancy-weighted crops (floor "
                  f"{OCCUPANCY_FLOOR}), mean of EM seeds {', '.join(map(str, EM_SEEDS))}.", ""]
        first = {"features": feats[:1], "references": [r for r in rs if r["row"] == "references"][:1]}
        retrieval, bank = [k for k, _ in COLUMNS[:3]], [k for k, _ in COLUMNS if k.startswith("threedq/")]
        cols = lambda source, prefix, keys: {k: (source, f"{prefix}/{k.split('/')[1]}") for k in keys}  # noqa: E731
        reference_rows = {
            "raw `cat[occ, occ * rgb]` crops": {**cols("features", "raw", retrieval),
                                                "probe/learned": ("features", "probe/raw"),
                                                **cols("references", "raw_bank", bank)},
            "raw occupancy channel alone": cols("references", "raw_occupancy", retrieval),
            "colour + size descriptor": cols("features", "descriptor", retrieval),
            "point-cloud registration": cols("references", "pointcloud", bank),
        }
        body = [[label, *(mean_range([r.get(w[k][1]) for r in first[w[k][0]]], digits(k)) if k in w else "-"
                          for k, _ in COLUMNS)] for label, w in reference_rows.items()]
        for name in dict.fromkeys(r["row"] for r in feats):
            group = [r for r in feats if r["row"] == name]
            body.append([f"{name} ({len(group)} seed{'s' if len(group) > 1 else ''})",
                         *(mean_range([r.get(k) for r in group], digits(k)) for k, _ in COLUMNS)])
        # the 2D rows: no rotation search, no yaw; their bank is the no-rot one
        inet = [(f"{r['backbone_label']}, {r['feature_stage']} pooled in the projected GT box (no rotation search)", r)
                for r in imagenet]
        body += [[label, *(mean_range([r.get(k)], digits(k)) for k, _ in COLUMNS)] for label, r in inet]
        lines.append(md_table(head, body))
        if imagenet:
            extra = ("ret_acc", "class_acc", "no_rot/hungarian_acc", "no_rot/colour_hungarian_acc")
            lines += ["", "ImageNet rows: few-shot as in paper Table 1 (2 labelled objects per category, seed 0) and "
                      "the colours of their no-rotation banks' clusters; the encoder rows' few-shot column above "
                      "propagates the labels through their prototypes instead.", "",
                      md_table(["features", "ResNetRet (nearest labelled object)", "ResNetClass (linear classifier "
                                "on the shots)", "no-rot Hungarian K=50", "no-rot Hungarian vs colour"],
                               [[label, *(mean_range([r.get(k)]) for k in extra)] for label, r in inet])]
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
    md = table(read_rows(args.out))
    print(md)
    if args.md:
        args.md.parent.mkdir(parents=True, exist_ok=True)
        args.md.write_text(md + "\n")


if __name__ == "__main__":
    main()
