"""``threedq em``: run the stages of 3DQ-Nets in order, each as its own LightningCLI run.

Layout of ``work_dir``::

    work_dir/
      00_viewpred/            # LightningCLI run: config.yaml, checkpoints/last.ckpt, metrics.csv,
        stage.json            #   TensorBoard events, images/*.png; stage.json once it has finished
      01_eval_features/
        metrics.json          # held-out evaluation of the learned features
      metrics.json            # everything measured, per stage and round
      report.md               # the same as tables

A finished stage (its ``stage.json`` exists) is never re-run; ``--resume`` continues an interrupted
one from its ``checkpoints/last.ckpt``. Every stage saves its resolved ``config.yaml``, so each can be
re-run or inspected on its own with ``threedq fit --config <run>/config.yaml``.

Stages implemented so far: view-prediction pre-training, then the evaluation of the learned features
(rotation-max retrieval precision@10 on GT boxes against two references). The per-round stages of the
paper (detection, correspondence mining, quantization, self-labelling) are not implemented yet, so
``rounds`` has no stage to run and is recorded in the report as such.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path
from typing import Any

import torch

from threedq.atomic_io import atomic_write_json, atomic_write_text
from threedq.cli import ThreeDQCLI, resolve_config

__all__ = ["run_em"]

ROUND_STAGES: tuple[str, ...] = ()  # detection, mining, quantization, self-labelling: not implemented yet


def _stage_done(run_dir: Path) -> dict[str, Any] | None:
    marker = run_dir / "stage.json"
    return json.loads(marker.read_text()) if marker.is_file() else None


def _cli_args(configs: list[Path], run_dir: Path, overrides: list[str]) -> list[str]:
    args: list[str] = []
    for c in configs:
        args += ["--config", str(c)]
    return [*args, f"--trainer.default_root_dir={run_dir}", *overrides]


def _fit_stage(
    name: str, configs: list[Path], run_dir: Path, overrides: list[str], resume: bool
) -> dict[str, Any]:
    done = _stage_done(run_dir)
    if done is not None:
        print(f"[em] {name}: finished earlier ({run_dir / 'stage.json'}), not re-run")
        return done
    last = run_dir / "checkpoints" / "last.ckpt"
    ckpt_args: list[str] = []
    if run_dir.exists() and any(run_dir.iterdir()):
        if not resume:
            raise RuntimeError(
                f"{run_dir} holds an unfinished '{name}' run: pass --resume to continue it, or delete the folder"
            )
        if last.is_file():
            ckpt_args = ["--ckpt_path", str(last)]
            print(f"[em] {name}: resuming from {last}")
    print(f"[em] {name}: training in {run_dir}")
    t0 = time.time()
    ThreeDQCLI(args=["fit", *_cli_args(configs, run_dir, overrides), *ckpt_args])
    if not last.is_file():
        raise RuntimeError(f"{name}: training finished without writing {last}")
    info = {"stage": name, "checkpoint": str(last), "seconds": round(time.time() - t0, 1)}
    atomic_write_json(run_dir / "stage.json", info)
    return info


def _evaluate(configs: list[Path], ckpt: Path, run_dir: Path, overrides: list[str], eval_views: int) -> dict[str, Any]:
    from threedq.evaluation import evaluate_features, evaluate_view_prediction

    cached = run_dir / "metrics.json"
    if cached.is_file():
        print(f"[em] eval_features: finished earlier ({cached}), not re-run")
        return json.loads(cached.read_text())
    cli = ThreeDQCLI(args=[*_cli_args(configs, run_dir, overrides), "--trainer.logger=false"], run=False)
    model, dm = cli.model, cli.datamodule
    state = torch.load(ckpt, map_location="cpu", weights_only=True)["state_dict"]
    model.load_state_dict(state)
    dm.prepare_data()
    dm.setup("test")
    t0 = time.time()
    metrics = {
        "retrieval": evaluate_features(model, dm.test_dataloader(), num_input_views=eval_views),
        "view_prediction": evaluate_view_prediction(model, dm.test_dataloader()),
        "split": "test",
    }
    metrics["seconds"] = round(time.time() - t0, 1)
    atomic_write_json(cached, metrics)
    return metrics


def _report(summary: dict[str, Any]) -> str:
    ev = summary["eval_features"]
    r, vp = ev["retrieval"], ev["view_prediction"]
    p = r["precision_at_k"]
    lines = [
        "# threedq em report",
        "",
        f"- work dir: `{summary['work_dir']}`; rounds asked: {summary['rounds']}",
        f"- machine: {summary['machine']}; torch {summary['torch']}",
        f"- view prediction: {summary['viewpred']['checkpoint']}",
        "",
        f"## Retrieval on held-out scenes (GT boxes, {r['num_objects']} objects, {r['num_categories']} categories)",
        "",
        f"Rotation-max precision@{r['k']} over {r['num_angles']} yaw steps, macro-averaged over categories, "
        f"{r['num_input_views']} input view(s) per scene.",
        "",
        "| features | precision@%d |" % r["k"],
        "|---|---|",
    ]
    names = {
        "learned": "threedq view prediction (learned)",
        "raw_rgb_occupancy": "(a) raw RGB + occupancy crops, no learning",
        "random_encoder": "(b) randomly initialised encoder",
    }
    for key, label in names.items():
        if key in p:
            lines.append(f"| {label} | {p[key]:.3f} |")
    lines += [
        "",
        "## View prediction on held-out scenes",
        "",
        "| metric | value |",
        "|---|---|",
        f"| RGB L1 (valid pixels, half resolution) | {vp['l1']:.4f} |",
        f"| RGB L1 of the mean-colour baseline | {vp['l1_mean_colour']:.4f} |",
        f"| occupancy balanced accuracy | {vp['occ_bacc']:.3f} |",
        "",
        "## EM rounds",
        "",
        "The per-round stages (3D detection, cross-scene correspondence mining, prototype quantization, "
        "detector self-labelling) are not implemented yet, so no round stage ran.",
        "",
    ]
    return "\n".join(lines)


def run_em(
    rounds: int = 4,
    work_dir: str = "runs/em",
    resume: bool = False,
    config: str = "stages/viewpred.yaml",
    extra_configs: list[str] | None = None,
    max_steps: int | None = None,
    eval_views: int = 1,
) -> dict[str, Any]:
    """Run view prediction, then ``rounds`` EM rounds, then the evaluation; write report.md + metrics.json.

    Args:
        rounds: EM rounds (detection -> mining -> quantization -> self-labelling) after pre-training.
        work_dir: folder of all runs of this experiment.
        resume: continue an interrupted stage from its last checkpoint (finished stages are never re-run).
        config: the view-prediction stage config (a path, or one inside the packaged configs/).
        extra_configs: more configs composed after it (e.g. ``trainer/gpu.yaml``, a data config).
        max_steps: override the training steps of the view-prediction stage.
        eval_views: input views per held-out scene for the evaluation (the paper tests with 1).
    """
    if rounds < 0:
        raise ValueError(f"rounds: expected >= 0, got {rounds}")
    work = Path(work_dir)
    configs = [resolve_config(config), *(resolve_config(c) for c in (extra_configs or []))]
    overrides = [f"--trainer.max_steps={max_steps}"] if max_steps is not None else []
    vp = _fit_stage("viewpred", configs, work / "00_viewpred", overrides, resume)
    ev = _evaluate(configs, Path(vp["checkpoint"]), work / "01_eval_features", [], eval_views)
    summary = {
        "work_dir": str(work),
        "rounds": rounds,
        "round_stages_run": list(ROUND_STAGES),
        "viewpred": vp,
        "eval_features": ev,
        "machine": f"{platform.machine()} {platform.processor() or ''} {torch.get_num_threads()} threads".strip(),
        "torch": torch.__version__,
    }
    atomic_write_json(work / "metrics.json", summary)
    atomic_write_text(work / "report.md", _report(summary))
    p = ev["retrieval"]["precision_at_k"]
    k = ev["retrieval"]["k"]
    print(f"[em] precision@{k}: " + ", ".join(f"{name} {v:.3f}" for name, v in p.items()))
    print(f"[em] wrote {work / 'report.md'} and {work / 'metrics.json'}")
    return summary
