"""Diagnostic (#63): the prototype EM's convergence and restarts. Crops of round R's encoder (train: all detected
boxes, what the quantizer fits; test: detected boxes matched to GT, what Table 3 scores) extracted once; banks fitted
fresh with several seeds, scored every 10 EM iterations (quantization loss, mean score, Hungarian); and the loop's
warm-started bank with more iterations."""
import copy, json, sys, time
from pathlib import Path
import torch
from threedq.pipeline.lightning_cli import test_checkpoint
from threedq.pipeline.evaluation import collect_object_crops
from threedq.pipeline.report import split_loader
from threedq.quantization.prototypes import (PrototypeBank, assign_chunked, prototype_crops, quantization_loss,
                                             run_prototype_em)
from threedq.metrics import HungarianAccuracy

# usage: python em_iterations_diag.py <run folder> <round, e.g. 04> <seeds, e.g. 0,1,2> [blocks of 10 iterations]
run, rnd = Path(sys.argv[1]), sys.argv[2]
seeds = [int(s) for s in sys.argv[3].split(",")]
blocks = int(sys.argv[4]) if len(sys.argv) > 4 else 4
out = Path("runs/diag_em_iter") / f"{run.name}_r{rnd}"
cli, _ = test_checkpoint([run / f"r{rnd}_eval" / "config.yaml"], run / f"r{rnd}_quantizer" / "checkpoints" / "last.ckpt",
                         out, [])
model, dm = cli.model, cli.datamodule
nv = dm.num_input_views
floor = model.hparams.occupancy_floor
with torch.no_grad():
    tr = collect_object_crops(model, split_loader(dm, "train"), nv, random_encoder_seed=None)
    te = collect_object_crops(model, split_loader(dm, "test"), nv, random_encoder_seed=None)
Xtr = prototype_crops(tr["learned"], tr["raw"], floor).float().contiguous()
Xte = prototype_crops(te["learned"], te["raw"], floor).float().contiguous()
lab = te["labels"]; keep = lab >= 0; Xte, lab = Xte[keep], lab[keep]
C = len(dm.index.categories)
print(f"train crops {Xtr.shape[0]}, test matched {Xte.shape[0]}, categories {C}", flush=True)

def score(bank):
    r = assign_chunked(bank, Xtr)
    h = HungarianAccuracy(bank.active.numel(), C); h.update(assign_chunked(bank, Xte).prototype, lab)
    return {"loss": round(float(quantization_loss(bank, Xtr, r)), 3), "mean_score": round(float(r.score.mean()), 5),
            "hungarian": round(float(h.compute()), 4)}

rows = []
loop = model.bank
rows.append({"bank": "loop (warm-started), as fitted", "iters": 0, **score(loop)}); print(rows[-1], flush=True)
b = copy.deepcopy(loop)
for k in range(1, blocks):
    run_prototype_em(b, Xtr, 10); rows.append({"bank": "loop + more", "iters": 10 * k, **score(b)}); print(rows[-1], flush=True)
for s in seeds:
    b = PrototypeBank(loop.active.numel(), loop.prototypes.shape[1], loop.prototypes.shape[-1], loop.num_angles,
                      loop.init_threshold, loop.method).to(Xtr.device)
    t = time.time()
    for k in range(1, blocks + 1):
        run_prototype_em(b, Xtr, 10, seed=s)
        rows.append({"bank": f"fresh seed {s}", "iters": 10 * k, "sec": round(time.time() - t, 1), **score(b)})
        print(rows[-1], flush=True)
Path(f"runs/diag_em_iter_{run.name}_r{rnd}.json").write_text(json.dumps(rows, indent=1))
