"""Diagnostic (#63): round 4's quantizer refitted from an empty bank (no init_bank_ckpt) on the same encoder and boxes,
and Table 3's round-4 measures of it, beside the loop's warm-started bank."""
import json, subprocess, sys
from pathlib import Path
from threedq.pipeline.em import _evaluate_round

for run in sys.argv[1:]:
    run = Path(run)
    out = Path("runs/diag_fresh") / run.name
    cfg = run / "r04_quantizer" / "config.yaml"
    ck = out / "q" / "checkpoints" / "last.ckpt"
    if not ck.is_file():
        subprocess.run(["threedq", "fit", "--config", str(cfg), "--model.init_args.init_bank_ckpt=null",
                        f"--trainer.default_root_dir={out / 'q'}", "--trainer.logger=false",
                        "--trainer.enable_progress_bar=false"], check=True)
    res = _evaluate_round([run / "r04_eval" / "config.yaml"], ck, out / "eval", final=False, overrides=[])
    warm = json.loads((run / "r04_eval" / "results.json").read_text())
    def pick(r):
        q = r["quantization"]["threedq"]
        return {k: round(float(q[k]), 4) for k in ("hungarian_acc", "fewshot_acc") if k in q}
    print(run.name, "warm:", pick(warm), "fresh:", pick(res), flush=True)
