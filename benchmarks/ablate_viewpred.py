"""View-prediction training variants vs. retrieval precision@10 of the learned crops (docs/results.md).

Each variant trains ``configs/stages/viewpred.yaml`` from scratch (seed 0) for ``--steps`` steps with extra
LightningCLI overrides, then scores it on the test split with :func:`threedq.pipeline.evaluation.evaluate_features`
(``--search``: the fast rotation-max search by default, as every threedq table; 36 yaw steps) and the stage's own
``test_step`` (``trainer.test``).
Run it from a folder holding the embedded data (``data/clevr_veggie``, made by ``threedq em`` or
``threedq fit``); one row per variant, appended to ``--out`` as JSON lines as soon as it is done, so a
killed run keeps the finished rows.

    python benchmarks/ablate_viewpred.py --steps 600 \\
        --variant default= --variant rgb100=--model.init_args.rgb_weight=100
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import cpu_name  # noqa: E402

DEFAULT_VARIANTS = [
    "default=",
    "plain L1=--model.init_args.rgb_loss=plain",
    "bf16=--trainer.precision=bf16-mixed",
    "3 targets=--data.init_args.num_target_views=3",
    "rgb100=--model.init_args.rgb_weight=100",
]


def run_variant(name: str, overrides: list[str], steps: int, root: Path, search: str) -> dict:
    from threedq.pipeline.lightning_cli import ThreeDQCLI
    from threedq.pipeline.evaluation import evaluate_features
    from threedq.pipeline.report import split_loader

    config = Path(__file__).resolve().parents[1] / "configs" / "stages" / "viewpred.yaml"
    t0 = time.perf_counter()
    cli = ThreeDQCLI(
        args=[
            "--config", str(config), f"--trainer.max_steps={steps}", f"--trainer.default_root_dir={root / name}",
            "--model.init_args.image_every_n_steps=0", "--trainer.check_val_every_n_epoch=1000", *overrides,
        ],
        run=False,
    )
    cli.trainer.fit(cli.model, cli.datamodule)
    train_s = time.perf_counter() - t0
    vp = {k.removeprefix("test/"): v for k, v in cli.trainer.test(cli.model, datamodule=cli.datamodule, verbose=False)[0].items()}
    ret = evaluate_features(cli.model, split_loader(cli.datamodule, "test"), search=search)
    return {"variant": name, "overrides": overrides, "steps": steps, "train_s": round(train_s, 1), "search": search,
            "view_pred_l1": vp["l1"], "l1_mean_colour": vp["l1_mean_colour"], "l1_fg": vp["l1_fg"],
            "l1_fg_mean_colour": vp["l1_fg_mean_colour"], **ret["precision_at_k"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--variant", action="append", help="NAME=OVERRIDE[ OVERRIDE...] (repeatable)")
    ap.add_argument("--root", type=Path, default=Path("runs/ablate_viewpred"))
    ap.add_argument("--out", type=Path, default=Path("runs/ablate_viewpred/results.jsonl"))
    ap.add_argument("--search", choices=("fast", "exact"), default="fast", help="rotation search of precision@10")
    args = ap.parse_args()
    rows = []
    for spec in args.variant or DEFAULT_VARIANTS:
        name, _, rest = spec.partition("=")
        row = run_variant(name, rest.split(), args.steps, args.root, args.search)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with args.out.open("a") as f:
            f.write(json.dumps(row) + "\n")
        rows.append(row)
    print(f"\nmachine: {cpu_name()}  date: {time.strftime('%Y-%m-%d')}  steps: {args.steps}  precision@10: {args.search} search\n")
    print("| variant | train s | view-pred L1 (mean colour) | object L1 (mean colour) | learned p@10 | raw p@10 | "
          "random p@10 |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['variant']} | {r['train_s']:.0f} | {r['view_pred_l1']:.4f} ({r['l1_mean_colour']:.4f}) | "
              f"{r['l1_fg']:.4f} ({r['l1_fg_mean_colour']:.4f}) | "
              f"{r['learned']:.3f} | {r['raw_rgb_occupancy']:.3f} | {r.get('random_encoder', float('nan')):.3f} |")


if __name__ == "__main__":
    main()
