"""How much of a round's Hungarian accuracy is the bank's fit, and how much the encoder?

For each ``threedq em`` run folder given, takes one round's encoder and prototype bank, crops the training split's
boxes and the test split's boxes matched to GT objects once, and scores the loop's bank as fitted and fresh banks
fitted on the same training crops from the initialisation orders of ``--seeds`` (the round's quantizer settings),
each with its quantization loss. GT labels are used for scoring only. Prints a markdown table (one row per run) and
appends one JSON line per run to ``--out``.

    python benchmarks/bank_fit_spread.py runs/em runs/em_s1 --round 4 --seeds 0,1,2,3 --out runs/bank_fit_spread.jsonl
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch

from threedq.machine import cpu_name


def round_crops(run: Path, rnd: int) -> tuple[object, torch.Tensor, torch.Tensor, torch.Tensor, int]:
    """(the round's quantizer stage with its bank loaded, training crops, matched test crops, their labels, number
    of categories); crops weighted as the quantizer's similarity weighs them."""
    from threedq.pipeline.evaluation import collect_object_crops
    from threedq.pipeline.lightning_cli import test_checkpoint
    from threedq.pipeline.report import split_loader
    from threedq.quantization.prototypes import prototype_crops

    cfg = run / f"r{rnd:02d}_eval" / "config.yaml"
    ckpt = run / f"r{rnd:02d}_quantizer" / "checkpoints" / "last.ckpt"
    for p in (cfg, ckpt):
        if not p.is_file():
            raise FileNotFoundError(f"{run}: round {rnd} has no {p.relative_to(run)} (a finished `threedq em` round?)")
    with tempfile.TemporaryDirectory() as tmp:
        cli, _ = test_checkpoint([cfg], ckpt, tmp)
    model, dm = cli.model, cli.datamodule
    hp = model.hparams
    with torch.no_grad():
        tr = collect_object_crops(model, split_loader(dm, "train"), dm.num_input_views, hp.crop_size,
                                  random_encoder_seed=None)
        te = collect_object_crops(model, split_loader(dm, "test"), dm.num_input_views, hp.crop_size,
                                  random_encoder_seed=None)
    x_tr = prototype_crops(tr["learned"], tr["raw"], hp.occupancy_floor).float().contiguous()
    matched = te["labels"] >= 0
    x_te = prototype_crops(te["learned"], te["raw"], hp.occupancy_floor).float()[matched].contiguous()
    return model, x_tr, x_te, te["labels"][matched], len(dm.index.categories)


def score(bank: object, x_tr: torch.Tensor, x_te: torch.Tensor, labels: torch.Tensor, categories: int) -> dict:
    """Quantization loss on the training crops and Hungarian accuracy on the matched test crops."""
    from threedq.metrics import HungarianAccuracy
    from threedq.quantization.prototypes import assign_chunked, quantization_loss

    fit = assign_chunked(bank, x_tr)
    acc = HungarianAccuracy(bank.active.numel(), categories)
    acc.update(assign_chunked(bank, x_te).prototype, labels)
    return {"loss": round(float(quantization_loss(bank, x_tr, fit)), 3), "hungarian": round(float(acc.compute()), 4)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="threedq em work folders")
    ap.add_argument("--round", type=int, default=4, help="the round whose encoder and bank are scored")
    ap.add_argument("--seeds", default="0,1,2,3", help="initialisation orders of the fresh banks")
    ap.add_argument("--out", type=Path, default=Path("runs/bank_fit_spread.jsonl"))
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    if not seeds:
        ap.error("--seeds: at least one seed")

    from threedq.quantization.prototypes import PrototypeBank, run_prototype_em

    args.out.parent.mkdir(parents=True, exist_ok=True)
    lines = [f"# fresh-bank fits of round {args.round}'s encoder; {cpu_name()}, {time.strftime('%Y-%m-%d')}",
             "| run | loop's bank (Table 3) | fresh fits: mean (min-max) | each fit: Hungarian (loss) |",
             "|---|---|---|---|"]
    for run in args.runs:
        t0 = time.time()
        model, x_tr, x_te, labels, categories = round_crops(run, args.round)
        hp, loop = model.hparams, model.bank
        row = {"run": str(run), "round": args.round, "train_crops": int(x_tr.shape[0]),
               "test_objects": int(x_te.shape[0]), "loop": score(loop, x_tr, x_te, labels, categories), "fits": []}
        for s in seeds:
            bank = PrototypeBank(hp.num_prototypes, loop.prototypes.shape[1], loop.prototypes.shape[-1],
                                 loop.num_angles, loop.init_threshold, loop.method)
            run_prototype_em(bank, x_tr, hp.em_iterations, seed=s, fill_free=hp.fill_free_slots)
            row["fits"].append({"seed": s, **score(bank, x_tr, x_te, labels, categories)})
            print(json.dumps(row["fits"][-1]), flush=True)
        h = [f["hungarian"] for f in row["fits"]]
        row.update(fresh_mean=round(sum(h) / len(h), 4), fresh_min=min(h), fresh_max=max(h),
                   seconds=round(time.time() - t0, 1), cpu=cpu_name(), date=time.strftime("%Y-%m-%d"))
        with args.out.open("a") as f:
            f.write(json.dumps(row) + "\n")
        each = ", ".join(f"{f['hungarian']:.3f} ({f['loss']:.1f})" for f in row["fits"])
        lines.append(f"| {run} | {row['loop']['hungarian']:.3f} | {row['fresh_mean']:.3f} "
                     f"({row['fresh_min']:.3f}-{row['fresh_max']:.3f}) | {each} |")
        print(lines[-1], flush=True)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
