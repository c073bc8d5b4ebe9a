"""Feature recipe study: view-prediction recipes vs what the learned 3D features retrieve.

Each recipe (``--variant NAME=OVERRIDES`` of ``configs/stages/viewpred.yaml``; a leading ``--config stages/X.yaml``
trains that stage; ``{seed}`` becomes the seed) is trained per seed up to the largest ``--eval_steps`` and scored at
each on the test split's GT boxes: retrieval (cosine and occupancy-weighted), ``--probe``, ``--cluster`` (K = 50
banks), the references and seconds per step. One JSON line per (recipe, seed, step) is appended to ``--out``; the
table is printed (``--png``: curves drawn). ``--score NAME=CKPT`` scores checkpoints instead of training.

    python benchmarks/feature_recipes.py --seeds 0 1 --eval_steps 500 1000 2000 \\
        --variant default= --variant "3 targets=--data.init_args.num_target_views=3"
"""

from __future__ import annotations

import argparse
import gc
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from _common import append_row, read_rows
from _common import table as md_table

from threedq.machine import cpu_name

DEFAULT_VARIANTS = ["default=", "3 targets=--data.init_args.num_target_views=3",
                    "batch 4=--data.init_args.batch_size=4"]
#: (name in the rows, similarity applied to the learned crops before the rotation search)
SIMILARITIES = ("cosine", "occupancy")


def _score(crops: dict, similarity: str) -> dict[str, Any]:
    from threedq.geometry import occupancy_weighted
    from threedq.pipeline.evaluation import retrieval_table

    c = dict(crops)
    if similarity == "occupancy":
        for key, raw in (("learned", "raw"), ("gallery_learned", "gallery_raw")):
            c[key] = occupancy_weighted(c[key], c[raw][:, :1])
        c = {k: v for k, v in c.items() if k in ("learned", "gallery_learned", "labels")}
    table, _ = retrieval_table(c)
    p, out = table["protocols"], {}
    refs = (("learned", similarity),)
    if similarity == "cosine":
        refs += (("raw_rgb_occupancy", "raw"), ("colour_size_descriptor", "descriptor"))
    for name, key in refs:
        out.update({f"{key}/strict": p["strict"]["precision_at_k"][name],
                    f"{key}/paper": p["paper"]["precision_at_k"][name],
                    f"{key}/top1": p["paper"]["same_object_top1"][name]})
    if similarity == "cosine":
        out["pool"] = table["num_objects"]
        out["ceiling/strict"], out["ceiling/paper"] = p["strict"]["ceiling"], p["paper"]["ceiling"]
    return out


#: (name in the rows, the quantizer's ``occupancy_floor``) of the ``--cluster`` banks
CLUSTER_SIMILARITIES = (("cosine", None), ("occupancy", 0.2))


def _cluster(train: dict, test: dict, num_classes: int, em_seeds: tuple[int, ...] = (0, 1),
             symmetry_order: list[int] | None = None) -> dict[str, float]:
    """Hungarian and few-shot accuracy and the median relative yaw error of K = 50 banks fitted on ``train``'s learned
    crops, per similarity (mean over ``em_seeds``). ``symmetry_order``: per category (None: all asymmetric)."""
    from threedq.pipeline.evaluation import quantization_metrics
    from threedq.quantization.prototypes import fit_prototype_bank, prototype_crops

    out: dict[str, float] = {}
    K = min(50, int(train["labels"].shape[0]))
    sym = list(symmetry_order) if symmetry_order is not None else [1] * num_classes
    for name, floor in CLUSTER_SIMILARITIES:
        acc: dict[str, list[float]] = {"hungarian": [], "fewshot": [], "yaw_median_deg": []}
        for seed in em_seeds:
            bank = fit_prototype_bank(prototype_crops(train["learned"], train["raw"], floor), K, seed=seed)
            res = bank.assign(prototype_crops(test["learned"], test["raw"], floor))
            m = quantization_metrics(res.prototype, res.angle, 36, K, test["labels"], test["boxes"][:, 6], num_classes,
                                     sym, seed=seed)
            for k, v in acc.items():
                v.append(m[k if k == "yaw_median_deg" else f"{k}_acc"])
        out.update({f"{name}/{k}": sum(v) / len(v) for k, v in acc.items()})
    return out


def _channels(crops: dict, channels: slice | None) -> dict:
    """``crops`` with only ``channels`` of its learned crops (``learned``, ``gallery_learned``); all where None."""
    if channels is None:
        return crops
    out = dict(crops)
    for key in ("learned", "gallery_learned"):
        if key in crops:
            c = crops[key].shape[1]
            if not 0 <= (channels.start or 0) < (channels.stop or c) <= c:
                raise ValueError(f"--channels {channels.start}:{channels.stop}: the crops have {c} channels")
            out[key] = crops[key][:, channels]
    return out


def score_encoder(stage: Any, dm: Any, probe: bool, cluster: bool = False,
                  channels: slice | None = None) -> dict[str, Any]:
    """Every number of one row for ``stage``'s encoder on the test split's GT boxes, one input view per scene;
    ``channels``: those scored."""
    import copy

    import torch

    if getattr(dm, "num_input_views", 1) != 1:
        dm = copy.copy(dm)  # the loaders are built per call from these attributes (fixed_view_dataset)
        dm.num_input_views = 1

    from threedq.pipeline.evaluation import collect_object_crops, probe_table
    from threedq.pipeline.report import split_loader

    with torch.no_grad():
        crops = collect_object_crops(stage, split_loader(dm, "test", gallery=True), random_encoder_seed=None,
                                     progress=False, gallery=True)
        crops = _channels(crops, channels)
        row: dict[str, Any] = {}
        row.update({k: v for sim in SIMILARITIES for k, v in _score(crops, sim).items()})
        if probe or cluster:
            train = _channels(collect_object_crops(stage, split_loader(dm, "train"), random_encoder_seed=None,
                                                   progress=False), channels)
        if probe:
            acc = probe_table(train, crops)["accuracy"]
            row.update({"probe/learned": acc["learned"], "probe/raw": acc["raw_rgb_occupancy"],
                        "probe/descriptor": acc["colour_size_descriptor"]})
        if cluster:
            row.update(_cluster(train, crops, len(dm.index.categories), symmetry_order=list(dm.index.symmetry_order)))
    return row


def _device_name(device: Any) -> str:
    import torch

    return torch.cuda.get_device_name(device) if device.type == "cuda" else f"{device.type}, {cpu_name()}"


def run_one(name: str, overrides: list[str], seed: int, eval_steps: list[int], root: Path, out: Path, probe: bool,
            data_dir: str | None, cluster: bool = False, data_config: str | None = None) -> None:
    """Train one (recipe, seed) and append a row per evaluation step to ``out``."""
    import lightning as L

    from threedq.pipeline.lightning_cli import ThreeDQCLI

    configs = Path(__file__).resolve().parents[1] / "configs"
    config, quiet = configs / "stages" / "viewpred.yaml", ["--model.init_args.image_every_n_steps=0"]
    if overrides[:1] == ["--config"]:  # another stage's config (e.g. stages/supervised.yaml, the label ceiling)
        config, quiet, overrides = configs / overrides[1], [], overrides[2:]
    overrides = [o.replace("{seed}", str(seed)) for o in overrides]  # e.g. the mining stage's pool seed
    steps = sorted(set(eval_steps))
    extra = [f"--data.init_args.data_dir={data_dir}"] if data_dir else []
    config_args = ["--config", str(config)]
    if data_config:  # another dataset, composed after the stage config as `threedq fit --config` composes it
        from threedq.pipeline.lightning_cli import resolve_config

        config_args += ["--config", str(resolve_config(data_config))]
    cli = ThreeDQCLI(args=[*config_args, f"--seed_everything={seed}", f"--trainer.max_steps={steps[-1]}",
                           f"--trainer.default_root_dir={root / name.replace(' ', '_') / f'seed{seed}'}", *quiet,
                           "--trainer.check_val_every_n_epoch=100000", "--trainer.enable_progress_bar=false",
                           "--trainer.enable_checkpointing=false", *extra, *overrides], run=False)
    timer = {"train_s": 0.0, "t0": time.perf_counter()}

    class Evaluate(L.Callback):
        def on_train_batch_end(self, trainer: L.Trainer, stage: Any, *args: Any) -> None:
            if trainer.global_step not in steps:
                return
            timer["train_s"] += time.perf_counter() - timer["t0"]
            t = time.perf_counter()
            row = {"variant": name, "overrides": overrides, "seed": seed, "steps": trainer.global_step,
                   "s_per_step": timer["train_s"] / trainer.global_step,
                   **score_encoder(stage, cli.datamodule, probe, cluster),
                   "eval_s": round(time.perf_counter() - t, 1), "device": _device_name(stage.device)}
            append_row(out, row)
            print(f"{name} seed {seed} step {trainer.global_step}: paper {row['cosine/paper']:.3f} "
                  f"(occupancy {row['occupancy/paper']:.3f}) top-1 {row['cosine/top1']:.3f}", flush=True)
            timer["t0"] = time.perf_counter()

    cli.trainer.callbacks.append(Evaluate())
    cli.trainer.fit(cli.model, cli.datamodule)


def score_checkpoints(specs: list[str], data_dir: str | None, out: Path, probe: bool, cluster: bool = False,
                      channels: slice | None = None) -> None:
    """One row per ``NAME=CKPT``: the checkpoint's encoder scored as :func:`score_encoder` does (no training);
    ``channels``: one more row per checkpoint on these channels of the learned crops alone."""
    from threedq.datamodules.clevr_veggie import ClevrVeggieDataModule
    from threedq.datamodules.scene_folder import SceneFolderDataModule
    from threedq.stages.crop_cache import CropCache
    from threedq.stages.viewpred import ViewPrediction

    dm = SceneFolderDataModule(data_dir=data_dir) if data_dir else ClevrVeggieDataModule()
    dm.prepare_data()
    dm.setup("fit")
    dm.setup("test")
    for spec in specs:
        name, _, ckpt = spec.partition("=")
        stage = ViewPrediction(encoder_ckpt=ckpt).eval()
        if channels is not None:  # the second row reads the same encodings
            stage.use_crop_cache(CropCache())
        for sl in (None, channels) if channels is not None else (None,):
            variant = name + ("" if sl is None else f", channels {sl.start}:{sl.stop}")
            row = {"variant": variant, "overrides": [ckpt], "seed": None, "steps": 0, "s_per_step": float("nan"),
                   **score_encoder(stage, dm, probe, cluster, sl), "device": _device_name(stage.device),
                   "data_dir": data_dir}
            append_row(out, row)
            print(f"{row['variant']}: strict {row['cosine/strict']:.3f} paper {row['cosine/paper']:.3f} "
                  f"(occupancy {row['occupancy/paper']:.3f}) top-1 {row['cosine/top1']:.3f}", flush=True)
        stage.use_crop_cache(None)  # the next checkpoint's grids replace these (about 2 MiB a scene)
        del stage
        gc.collect()


COLUMNS = [("cosine/strict", "strict"), ("cosine/paper", "paper"), ("cosine/top1", "top-1"),
           ("occupancy/strict", "strict (occ.-weighted)"), ("occupancy/paper", "paper (occ.-weighted)"),
           ("occupancy/top1", "top-1 (occ.-weighted)"), ("probe/learned", "linear probe"),
           ("cosine/hungarian", "Hungarian K=50"), ("occupancy/hungarian", "Hungarian K=50 (occ.-weighted)"),
           ("cosine/fewshot", "few-shot"), ("occupancy/fewshot", "few-shot (occ.-weighted)"),
           ("cosine/yaw_median_deg", "yaw median err. (deg)"),
           ("occupancy/yaw_median_deg", "yaw median err. (deg, occ.-weighted)")]


def _cell(values: list[float]) -> str:
    if not values:
        return "-"
    m = sum(values) / len(values)
    return f"{m:.3f} ({min(values):.3f}-{max(values):.3f})" if len(values) > 1 else f"{m:.3f}"


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown: one line per (recipe, steps), mean (range) over seeds; the references from the same rows."""
    groups: dict[tuple[str, int], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["variant"], r["steps"]), []).append(r)
    body = [[name, steps or "-", len(rs), _cell([r["s_per_step"] for r in rs if r["s_per_step"] == r["s_per_step"]]),
             *(_cell([r[k] for r in rs if k in r]) for k, _ in COLUMNS)]  # NaN s/step: a scored checkpoint
            for (name, steps), rs in groups.items()]
    shapes = list(dict.fromkeys(r.get("crop", "hull") for r in rows)) or ["hull"]
    refs = [("raw", f"raw crops{'' if s == 'hull' else f', {s} crop'}", s) for s in shapes]
    refs.append(("descriptor", "colour + size descriptor (of the hull crops)", "hull"))
    ref_rows: list[list[Any]] = []
    for key, label, shape in refs:
        keys = [f"{key}/{m}" for m in ("strict", "paper", "top1")] + [f"probe/{key}"]
        # recipes on other data (e.g. another image size) have own references: equal ones, the recipes having them
        same: dict[tuple[str, ...], list[str]] = {}
        for name in dict.fromkeys(r["variant"] for r in rows):
            own = [r for r in rows if r.get("crop", "hull") == shape and r["variant"] == name]
            cells = tuple(_cell([r[k] for r in own if k in r][:1]) for k in keys)
            if cells != ("-",) * 4:
                same.setdefault(cells, []).append(name)
        if len(same) <= 1:
            ref_rows.append([label, *next(iter(same), ("-",) * 4)])
        else:
            ref_rows += [[f"{label}, rows of {', '.join(names)}", *c] for c, names in same.items()]
    if rows:
        ref_rows.append(["perfect features (ceiling)", f"{rows[0]['ceiling/strict']:.3f}",
                         f"{rows[0]['ceiling/paper']:.3f}", 1, 1])
    lines = [md_table(["recipe", "steps", "seeds", "s/step", *(c for _, c in COLUMNS)], body), "",
             md_table(["reference (same objects)", "strict", "paper", "top-1", "linear probe"], ref_rows)]
    if rows:
        lines.append(f"\npool: {rows[0]['pool']} test objects (GT boxes); fast rotation search, 36 yaws; k = 10")
    return "\n".join(lines)


CURVE_PANELS = [("cosine/paper", "precision@10, paper protocol"), ("cosine/strict", "precision@10, strict"),
                ("cosine/top1", "same-object top-1"), ("probe/learned", "linear probe")]


def curve_points(rows: list[dict[str, Any]], key: str) -> dict[str, dict[Any, list[tuple[int, float]]]]:
    """Per recipe and seed, ``(steps, value)`` of ``key`` sorted by steps (trained recipes only)."""
    out: dict[str, dict[Any, list[tuple[int, float]]]] = {}
    for r in rows:
        if r.get("steps") and key in r:
            out.setdefault(r["variant"], {}).setdefault(r["seed"], []).append((r["steps"], r[key]))
    return {v: {s: sorted(pts) for s, pts in seeds.items()} for v, seeds in out.items()}


def curves_figure(rows: list[dict[str, Any]]) -> Any:
    """Each recipe's numbers against its training steps, a line per seed, one colour a recipe, with the
    :func:`curve_references`."""
    from threedq.viz.curves import runs_figure

    panels = [(title, {v: list(seeds.values()) for v, seeds in curve_points(rows, key).items()},
               curve_references(rows, key)) for key, title in CURVE_PANELS if any(key in r for r in rows)]
    return runs_figure(panels, "view-prediction steps")


def curve_references(rows: list[dict[str, Any]], key: str) -> list[tuple[float, str, str, str | None]]:
    """The reference lines of ``key``'s panel, ``(y, linestyle, label, recipe)``: the raw crops (dashed) and the
    descriptor (dotted) on the same objects; one grey line (recipe None) where every recipe's rows share the value,
    else a line per value, in the recipe's colour where only one recipe has it."""
    metric = key.split("/", 1)[1] if key.startswith("cosine/") else None
    references: list[tuple[float, str, str, str | None]] = []
    for source, style, label in (("raw", "--", "raw crops"), ("descriptor", ":", "descriptor")):
        ref = f"{source}/{metric}" if metric else f"probe/{source}"
        first: dict[str, float] = {}
        for r in (r for r in rows if ref in r and r.get("crop", "hull") == "hull"):
            first.setdefault(r["variant"], r[ref])
        by_value: dict[float, list[str]] = {}
        for name, y in first.items():
            by_value.setdefault(y, []).append(name)
        for y, names in by_value.items():
            if len(by_value) == 1:
                references.append((y, style, label, None))
            else:  # a recipe's own value in its colour; one shared by several recipes grey, naming them
                references.append((y, style, f"{label} ({', '.join(names)})", names[0] if len(names) == 1 else None))
    return references


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variant", action="append", help="NAME=OVERRIDE[ OVERRIDE...] (repeatable)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--eval_steps", type=int, nargs="+", default=[500, 1000, 2000])
    ap.add_argument("--probe", action="store_true", help="also the linear probe (encodes the training split)")
    ap.add_argument("--cluster", action="store_true",
                    help="also the K = 50 prototype banks, plain and occupancy-weighted (encodes the training split)")
    ap.add_argument("--jobs", type=int, default=1, help="(recipe, seed) trainings at once, in subprocesses")
    ap.add_argument("--common", default="", help="overrides added to every recipe, e.g. '--trainer.accelerator=gpu'")
    ap.add_argument("--data_dir", default=None, help="default: the stage config's (data/clevr_veggie)")
    ap.add_argument("--data_config", default=None,
                    help="train on another dataset: a data config (a path, or one of the packaged configs/, e.g. "
                         "data/shapes.yaml), composed after the stage config")
    ap.add_argument("--root", type=Path, default=Path("runs/feature_recipes"))
    ap.add_argument("--out", type=Path, default=Path("runs/feature_recipes/results.jsonl"))
    ap.add_argument("--table_only", action="store_true", help="print the table of --out and stop")
    ap.add_argument("--png", type=Path, default=None,
                    help="also draw each recipe's numbers against its steps, a line per seed, into this PNG")
    ap.add_argument("--score", action="append", metavar="NAME=CKPT",
                    help="score an existing encoder checkpoint instead of training (repeatable; any stage's "
                         "checkpoint); with --data_dir any scene folder (threedq data generate / index)")
    ap.add_argument("--channels", default=None, metavar="START:STOP",
                    help="with --score: one more row per checkpoint on these channels of the learned crops alone "
                         "(e.g. 0:16, the view-prediction stage's shape_channels)")
    ap.add_argument("--one", nargs=2, metavar=("SPEC", "SEED"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.one:
        name, _, rest = args.one[0].partition("=")
        run_one(name, rest.split() + args.common.split(), int(args.one[1]), args.eval_steps, args.root, args.out,
                args.probe, args.data_dir, args.cluster, args.data_config)
        return
    if args.score:
        channels = None
        if args.channels:
            try:
                a, b = (int(v) for v in args.channels.split(":"))
            except ValueError:
                ap.error(f"--channels: expected START:STOP, e.g. 0:16, got {args.channels!r}")
            channels = slice(a, b)
        score_checkpoints(args.score, args.data_dir, args.out, args.probe, args.cluster, channels)
    elif not args.table_only:
        jobs = [(spec, seed) for spec in (args.variant or DEFAULT_VARIANTS) for seed in args.seeds]
        common = ["--eval_steps", *map(str, args.eval_steps), "--root", str(args.root), "--out", str(args.out)]
        common += ([f"--common={args.common}"] if args.common else []) + (["--probe"] if args.probe else [])
        common += (["--cluster"] if args.cluster else []) + (["--data_dir", args.data_dir] if args.data_dir else [])
        common += ["--data_config", args.data_config] if args.data_config else []
        running: list[subprocess.Popen] = []
        for spec, seed in jobs:
            while len(running) >= args.jobs:
                running = [p for p in running if p.poll() is None]
                time.sleep(1)
            env = dict(os.environ)
            if args.jobs > 1:
                env.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 2) // args.jobs)))
            running.append(subprocess.Popen([sys.executable, __file__, "--one", spec, str(seed), *common], env=env))
        failed = [p.args for p in running if p.wait() != 0]
        if failed:
            print(f"failed: {failed}", file=sys.stderr)
    rows = read_rows(args.out)
    print(f"\nmachine: {rows[0]['device'] if rows else cpu_name()}  date: {time.strftime('%Y-%m-%d')}  "
          f"precision@10 of the test split's GT boxes\n")
    print(table(rows))
    if args.png is not None:
        from threedq.viz.png import write_png

        write_png(args.png, curves_figure(rows))
        print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
