"""The paper's preset at full size on this machine: does every stage run at 144^3 / 256 px, how long, how much memory,
and what would the whole run cost on a GPU?

1. **Smoke run.** ``threedq em --preset paper --rounds 1`` on ``--scenes`` scenes of the 256 px embedded data (the
   preset's data config with fewer scenes), every stage's steps cut to ``--steps`` (only the step counts shrink: the
   grid, the image size, the widths, the pools, the queue, K and the yaws are the preset's), the round on GT boxes
   (``--boxes gt``: a detector of a few steps hands on no box above its 0.9 threshold). It runs under
   ``/usr/bin/time -v`` (the peak memory of the whole run) and reads each stage's seconds from the run's
   ``metrics.json``.
2. **FLOPs per step.** One view-prediction training step of the preset (batch 2, one input and one target view) is
   counted with ``torch.utils.flop_counter.FlopCounterMode`` (forward and backward), and timed on this CPU.
3. **Estimate.** The 100,000 view-prediction steps of the paper at 10% and 35% of a GPU's peak (a V100's fp32
   15.7 TFLOPS, as the paper trained; an H100 SXM's dense bf16 989 TFLOPS, as ``trainer/gpu.yaml``'s bf16-mixed
   would run), beside the share of the V100's peak that the paper's own 24 h implies. The shares are assumptions:
   no GPU has run the preset (``benchmarks/device_check/``).

Usage::

    python benchmarks/paper_scale.py --work runs/paper_smoke      # about 20 min on 2 cores
    python benchmarks/paper_scale.py --work runs/paper_smoke --flops_only
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

from threedq.machine import cpu_name

#: name -> (peak TFLOPS of the precision the preset would run in, what it is)
GPUS = {"V100": (15.7, "fp32 peak"), "H100 SXM": (989.0, "bf16 tensor-core peak, dense")}
EFFICIENCIES = (0.10, 0.35)  # shares of peak a 3D-convolution training step may sustain (assumed, in the table)
PAPER_STEPS, PAPER_HOURS = 100_000, 24.0


def smoke(work: Path, scenes: int, steps: int) -> dict[str, Any]:
    """The preset's ``threedq em --rounds 1`` at full size with ``steps`` steps per stage: seconds per stage, peak
    resident memory of the run, exit status."""
    work.mkdir(parents=True, exist_ok=True)
    data = work / "data.yaml"
    data.write_text(f"base: data/clevr_veggie_256.yaml\ndata:\n  init_args:\n    data_dir: {work / 'data'}\n"
                    f"    num_scenes: {scenes}\n    split_fractions: [0.5, 0.125, 0.375]\n")
    short = work / "steps.yaml"
    short.write_text(f"trainer:\n  max_steps: {steps}\n  limit_val_batches: 1\n  check_val_every_n_epoch: 1\n"
                     "  enable_progress_bar: false\n")
    cmd = ["/usr/bin/time", "-v", "threedq", "em", "--preset", "paper", "--rounds", "1", "--work_dir",
           str(work / "em"), "--data_config", str(data), "--extra_configs", str(short), "--resume", "true",
           "--boxes", "gt"]  # a detector of a few steps hands on no box above 0.9: the round's stages take GT boxes
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)  # its exit status is reported
    wall = time.perf_counter() - t0
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr)
    out: dict[str, Any] = {"returncode": proc.returncode, "wall_s": round(wall, 1),
                           "peak_gib": round(int(rss.group(1)) / 2**20, 2) if rss else None}
    metrics = work / "em" / "metrics.json"
    if proc.returncode != 0 or not metrics.is_file():
        out["error"] = proc.stderr[-3000:]
        return out
    m = json.loads(metrics.read_text())
    out["stages"] = {
        "view prediction": m["viewpred"]["seconds"], "its evaluation": m["viewpred_eval"]["seconds"],
        "detector warm start": m["detector"]["seconds"], "its evaluation (every split)": m["detector_eval"]["seconds"],
        "round 0 (quantizer + evaluation)": m["round0_result"]["seconds"],
        "mining": m["mining_results"][0]["seconds"], "round 1 (quantizer + evaluation)": m["round_results"][0]["seconds"],
        "self-labelling": m["self_label_results"][0]["seconds"],
    }  # fmt: skip
    out["round1"] = {k: m["table3"][-1][k] for k in ("map_50", "precision_at_10", "hungarian_acc")}
    return out


def viewpred_step_flops(repeats: int = 2) -> dict[str, float]:
    """FLOPs (forward + backward) and CPU seconds of one view-prediction training step of the preset."""
    import tempfile

    from threedq.datamodules.scene_folder import SceneFolderDataModule
    from threedq.stages.viewpred import ViewPrediction
    from torch.utils.flop_counter import FlopCounterMode

    from threedq.data.generate import generate_dataset
    from threedq.data.generator_config import GeneratorConfig
    from threedq.pipeline.lightning_cli import load_config

    args = load_config("paper/viewpred.yaml")["model"]["init_args"]
    model = ViewPrediction(**{**args, "image_every_n_steps": 0})
    with tempfile.TemporaryDirectory() as tmp:
        generate_dataset(tmp, num_scenes=2, seed=0, config=GeneratorConfig(image_size=(256, 256)), splits=("train",),
                         workers=1, progress=False)
        dm = SceneFolderDataModule(tmp, batch_size=2, num_target_views=1)
        dm.setup()
        batch = next(iter(dm.train_dataloader()))
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    counter = FlopCounterMode(display=False)
    with counter:
        loss = model._step(batch)["loss"]
        loss.backward()
    flops = counter.get_total_flops()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        opt.zero_grad()
        model._step(batch)["loss"].backward()
        opt.step()
        times.append(time.perf_counter() - t0)
    return {"tflop_per_step": flops / 1e12, "cpu_s_per_step": min(times), "batch": int(batch["rgb"].shape[0])}


def estimate_table(tflop: float) -> str:
    """Hours for the paper's 100k view-prediction steps at two sustained shares of each GPU's peak, and the share the
    paper's own 24 h on a V100 implies for this step's FLOPs."""
    implied = tflop * PAPER_STEPS / (PAPER_HOURS * 3600) / GPUS["V100"][0]
    rows = [f"The paper's 24 h for 100k steps on a V100 is {implied:.1%} of its fp32 peak for {tflop:.2f} TFLOP a step.",
            "", "| GPU | peak TFLOPS | share of peak sustained (assumed) | s per step | 100k steps |", "|---|---|---|---|---|"]
    for name, (peak, what) in GPUS.items():
        for share in EFFICIENCIES:
            s = tflop / (peak * share)
            rows.append(f"| {name} | {peak:g} ({what}) | {share:.0%} | {s:.3f} | {s * PAPER_STEPS / 3600:.1f} h |")
    return "\n".join(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("runs/paper_smoke"))
    ap.add_argument("--scenes", type=int, default=16)
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--flops_only", action="store_true", help="only the FLOPs and the estimate, no smoke run")
    args = ap.parse_args()
    print(f"{time.strftime('%Y-%m-%d')}, {cpu_name()}, {torch.get_num_threads()} threads, torch {torch.__version__}")
    f = viewpred_step_flops()
    print(f"\nview prediction, one training step of the preset (batch {f['batch']}, 144^3 grid, 256 px): "
          f"{f['tflop_per_step']:.2f} TFLOP forward + backward, {f['cpu_s_per_step']:.1f} s on this CPU\n")
    print(estimate_table(f["tflop_per_step"]))
    if args.flops_only:
        return
    s = smoke(args.work, args.scenes, args.steps)
    print(f"\nsmoke run (threedq em --preset paper --rounds 1, {args.scenes} scenes, {args.steps} steps per stage): "
          f"exit {s['returncode']}, {s['wall_s']:.0f} s, peak {s['peak_gib']} GiB")
    if "error" in s:
        print(s["error"], file=sys.stderr)
        sys.exit(1)
    print("\n| stage | seconds |\n|---|---|")
    for name, sec in s["stages"].items():
        print(f"| {name} | {sec:.1f} |")
    print(f"\nround 1 on the smoke data (no measure of quality at {args.steps} steps): {s['round1']}")


if __name__ == "__main__":
    main()
