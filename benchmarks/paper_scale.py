"""The paper's preset at full size on this machine: does every stage run at 144^3 / 256 px, how long, how much memory,
and what would the whole run cost on a GPU?

A smoke run (``threedq em --preset paper --rounds 1`` on ``--scenes`` scenes, every stage cut to ``--steps`` steps,
under ``/usr/bin/time -v``; ``--stage_memory``: each stage's peak memory on its own), the FLOPs and CPU seconds of one
view-prediction step, and the paper's 100,000 steps estimated at assumed shares of a V100's and an H100's peak.
``--minutes`` instead trains the preset's view prediction on ``--device`` and sets its step time beside the estimate.

    python benchmarks/paper_scale.py --work runs/paper_smoke      # about 5 min on 2 cores
    python benchmarks/paper_scale.py --work runs/paper_smoke --stage_memory     # about 10 min more
    python benchmarks/paper_scale.py --work runs/paper_smoke --flops_only
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch
from _common import append_row, machine, table
from torch.utils.flop_counter import FlopCounterMode

from threedq.machine import cpu_name

#: name -> (peak TFLOPS of the precision the preset would run in, what it is)
GPUS = {"V100": (15.7, "fp32 peak"), "H100 SXM": (989.0, "bf16 tensor-core peak, dense")}
EFFICIENCIES = (0.10, 0.35)  # shares of peak a 3D-convolution training step may sustain (assumed, in the table)
PAPER_STEPS, PAPER_HOURS = 100_000, 24.0


#: the smoke run's folders in the order the run makes them, with the file that marks each finished
STAGES = (("view prediction", "00_viewpred", "stage.json"), ("its evaluation", "01_viewpred_eval", "metrics.json"),
          ("detector warm start", "02_detector", "stage.json"),
          ("its evaluation (every split)", "03_detector_eval", "results.json"),
          ("round 0 quantizer", "r00_quantizer", "stage.json"), ("round 0 evaluation", "r00_eval", "results.json"),
          ("mining", "r01_mining", "stage.json"), ("round 1 quantizer", "r01_quantizer", "stage.json"),
          ("round 1 evaluation", "r01_eval", "results.json"), ("self-labelling", "r01_self_labelling", "stage.json"),
          ("its detector evaluation", "r01_detector_eval", "results.json"))


class StepProbe(pl.Callback):
    """Counts the FLOPs of a stage's second training step (forward and backward) and times its third; appends one JSON
    line per stage (its run folder's name) to ``out``."""

    def __init__(self, out: str) -> None:
        self.out, self.calls, self.t0 = out, 0, 0.0
        self.counter: FlopCounterMode | None = None
        self.rows: dict[str, float] = {}

    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any, idx: int) -> None:
        self.calls += 1
        if self.calls == 2:
            self.counter = FlopCounterMode(display=False)
            self.counter.__enter__()
        self.t0 = time.perf_counter()

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any,
                           idx: int) -> None:
        seconds = time.perf_counter() - self.t0
        if self.counter is not None:
            self.counter.__exit__(None, None, None)
            self.rows["tflop"] = self.counter.get_total_flops() / 1e12
            self.counter = None
        elif self.calls == 3:
            self.rows["s_per_step"] = seconds

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        append_row(Path(self.out), {"stage": Path(trainer.default_root_dir).name, **self.rows})


def _run_args(work: Path) -> list[str]:
    return ["threedq", "em", "--preset", "paper", "--rounds", "1", "--work_dir", str(work / "em"), "--data_config",
            str(work / "data.yaml"), "--extra_configs", str(work / "steps.yaml"), "--resume", "true",
            "--boxes", "gt"]  # a detector of a few steps hands on no box above 0.9: the round's stages take GT boxes


def _env() -> dict[str, str]:
    """The environment of a smoke run: this folder on the path, for :class:`StepProbe`'s class path."""
    here = str(Path(__file__).resolve().parent)
    return {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [here, os.environ.get("PYTHONPATH")]))}


def _peak_gib(stderr: str) -> float | None:
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", stderr)
    return round(int(rss.group(1)) / 2**20, 2) if rss else None


def _steps_yaml(steps: int, probe: Path | None) -> str:
    """The extra config that cuts every stage to ``steps`` steps (with :class:`StepProbe` writing to ``probe``)."""
    text = (f"trainer:\n  max_steps: {steps}\n  limit_val_batches: 1\n  check_val_every_n_epoch: 1\n"
            "  enable_progress_bar: false\n")
    if probe is not None:
        text += f"  callbacks:\n    - class_path: paper_scale.StepProbe\n      init_args:\n        out: {probe}\n"
    return text


def smoke(work: Path, scenes: int, steps: int) -> dict[str, Any]:
    """The preset's ``threedq em --rounds 1`` at full size with ``steps`` steps per stage: seconds per stage, peak
    resident memory of the run, exit status."""
    work.mkdir(parents=True, exist_ok=True)
    data = work / "data.yaml"
    data.write_text(f"base: data/clevr_veggie_256.yaml\ndata:\n  init_args:\n    data_dir: {(work / 'data').resolve()}\n"
                    f"    num_scenes: {scenes}\n    split_fractions: [0.5, 0.125, 0.375]\n")
    probe = work / "steps.jsonl"
    probe.unlink(missing_ok=True)
    (work / "steps.yaml").write_text(_steps_yaml(steps, probe))
    t0 = time.perf_counter()
    proc = subprocess.run(["/usr/bin/time", "-v", *_run_args(work)], capture_output=True, text=True, check=False,
                          env=_env())  # its exit status is reported
    out: dict[str, Any] = {"returncode": proc.returncode, "wall_s": round(time.perf_counter() - t0, 1),
                           "peak_gib": _peak_gib(proc.stderr)}
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
    out["steps"] = {r["stage"]: r for r in map(json.loads, probe.read_text().splitlines())} if probe.is_file() else {}
    return out


def stage_memory(work: Path, steps: int) -> dict[str, float | None]:
    """Each stage's peak resident memory (GiB): a copy of the finished smoke run without the stage and the ones after
    it, resumed until the stage's marker file appears."""
    import psutil

    peaks: dict[str, float | None] = {}
    for i, (name, folder, marker) in enumerate(STAGES):
        part = work / "stage_memory"
        shutil.rmtree(part, ignore_errors=True)
        part.mkdir(parents=True)
        for _, earlier, _ in STAGES[:i]:  # hard links: the resumed run replaces files atomically, never edits them
            shutil.copytree(work / "em" / earlier, part / "em" / earlier, copy_function=os.link)
        shutil.copy(work / "data.yaml", part / "data.yaml")
        (part / "steps.yaml").write_text(_steps_yaml(steps, None))
        proc = subprocess.Popen(["/usr/bin/time", "-v", *_run_args(part)], stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True, env=_env())
        done = part / "em" / folder / marker
        while proc.poll() is None and not done.is_file():
            time.sleep(0.2)
        if proc.poll() is None:  # the stage has finished: stop the run before the next one starts
            for child in psutil.Process(proc.pid).children():
                child.terminate()
        _, err = proc.communicate()
        peaks[name] = _peak_gib(err) if done.is_file() else None
        print(f"  {name}: {peaks[name]} GiB", flush=True)
    shutil.rmtree(work / "stage_memory", ignore_errors=True)
    return peaks


def _preset_viewpred_step() -> tuple[Any, dict[str, torch.Tensor]]:
    """The preset's view-prediction stage (untrained) and one batch of its data (2 scenes of 256 px views)."""
    import tempfile

    from threedq.datamodules.scene_folder import SceneFolderDataModule
    from threedq.stages.viewpred import ViewPrediction

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
    return model, batch


def viewpred_step_flops(repeats: int = 2) -> dict[str, float]:
    """FLOPs (forward + backward) and CPU seconds of one view-prediction training step of the preset."""
    model, batch = _preset_viewpred_step()
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    with FlopCounterMode(display=False) as counter:
        model._step(batch)["loss"].backward()
    flops = counter.get_total_flops()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        opt.zero_grad()
        model._step(batch)["loss"].backward()
        opt.step()
        times.append(time.perf_counter() - t0)
    return {"tflop_per_step": flops / 1e12, "cpu_s_per_step": min(times) if times else float("nan"),
            "batch": int(batch["rgb"].shape[0])}


def timed_steps(minutes: float, device: str, bf16: bool) -> dict[str, Any]:
    """Train the preset's view prediction on one batch for ``minutes`` on ``device`` (bf16 autocast or fp32): the
    median seconds of a step after the first, the steps done and the peak memory (allocator on a GPU, else RSS)."""
    import resource
    import statistics

    model, batch = _preset_viewpred_step()
    model.to(device)
    batch = {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    cuda = device.startswith("cuda")
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    times: list[float] = []
    end = time.perf_counter() + 60 * minutes
    while time.perf_counter() < end or len(times) < 3:
        t0 = time.perf_counter()
        opt.zero_grad()
        with torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=bf16):
            loss = model._step(batch)["loss"]
        loss.backward()
        opt.step()
        sync()
        times.append(time.perf_counter() - t0)
    peak = (torch.cuda.max_memory_allocated() if cuda else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
    name = torch.cuda.get_device_name() if cuda else cpu_name()
    return {"device": name, "steps": len(times), "s_per_step": statistics.median(times[1:]),
            "peak_gib": round(peak / 2**30, 2), "precision": "bf16-mixed" if bf16 else "fp32"}


def estimate_table(tflop: float) -> str:
    """Hours for the paper's 100k view-prediction steps at two sustained shares of each GPU's peak, and the share the
    paper's own 24 h on a V100 implies for this step's FLOPs."""
    implied = tflop * PAPER_STEPS / (PAPER_HOURS * 3600) / GPUS["V100"][0]
    rows = [(name, f"{peak:g} ({what})", f"{share:.0%}", f"{tflop / (peak * share):.3f}",
             f"{tflop / (peak * share) * PAPER_STEPS / 3600:.1f} h")
            for name, (peak, what) in GPUS.items() for share in EFFICIENCIES]
    head = ["GPU", "peak TFLOPS", "share of peak sustained (assumed)", "s per step", "100k steps"]
    return (f"The paper's 24 h for 100k steps on a V100 is {implied:.1%} of its fp32 peak for {tflop:.2f} TFLOP a step."
            "\n\n" + table(head, rows))


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("runs/paper_smoke"))
    ap.add_argument("--scenes", type=int, default=16)
    ap.add_argument("--steps", type=int, default=3, help="steps per stage (the probe times the third)")
    ap.add_argument("--flops_only", action="store_true", help="only the FLOPs and the estimate, no smoke run")
    ap.add_argument("--stage_memory", action="store_true", help="also each stage's peak memory, on its own")
    ap.add_argument("--minutes", type=float, help="only train the preset's view prediction for this long on --device "
                    "and set its step time beside the estimate (benchmarks/device_check/paper.sh on a GPU)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--bf16", action=argparse.BooleanOptionalAction, default=None,
                    help="bf16 autocast (default: on a GPU, as trainer/gpu.yaml)")
    args = ap.parse_args()
    print(machine())
    if args.minutes is not None:
        bf16 = args.device.startswith("cuda") if args.bf16 is None else args.bf16
        t = timed_steps(args.minutes, args.device, bf16)
        f = viewpred_step_flops(repeats=0)
        print(f"\nview prediction of the preset on {t['device']} ({t['precision']}, batch {f['batch']}, one batch "
              f"repeated): {t['steps']} steps in {args.minutes:g} min, median {t['s_per_step']:.3f} s a step, "
              f"peak {t['peak_gib']} GiB; {f['tflop_per_step'] / t['s_per_step']:.1f} TFLOPS sustained; the paper's "
              f"100k steps at this rate: {t['s_per_step'] * PAPER_STEPS / 3600:.1f} h\n")
        print(estimate_table(f["tflop_per_step"]))
        return
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
    print("\n" + table(["stage", "seconds (with set-up)"], [(n, f"{sec:.1f}") for n, sec in s["stages"].items()]))
    print("\nthe trained stages' steps (FLOPs of the second step, forward and backward; seconds of the third):\n")
    print(table(["stage", "TFLOP per step", "s per step"], [(f, f"{r.get('tflop', float('nan')):.3f}",
                f"{r.get('s_per_step', float('nan')):.2f}") for f, r in s["steps"].items()]))
    if args.stage_memory:
        print("\neach stage's peak resident memory, resumed on its own:\n")
        print(table(["stage", "peak GiB"], stage_memory(args.work, args.steps).items()))
    print(f"\nround 1 on the smoke data (no measure of quality at {args.steps} steps): {s['round1']}")


if __name__ == "__main__":
    main()
