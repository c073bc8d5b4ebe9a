"""``threedq em``: run the stages of 3DQ-Nets in order, each as its own LightningCLI run.

The paper's loop (Sec. 3.4): view-prediction pre-training; the detector warm-started from label-free pseudo-boxes;
then each round: mine correspondences on the boxes the current detector hands on and fine-tune the encoder ->
quantize the objects into prototypes -> evaluate the round (the last one with the baselines) -> self-label the
detector, whose detections are the next round's boxes. ``--boxes gt`` runs the rounds on GT boxes (the oracle
protocol). Folder names: :class:`~threedq.pipeline.run_layout.RunLayout`; the stages after view prediction share one
:class:`~threedq.stages.crop_cache.CropCache`.

A finished stage (``stage.json``) or evaluation (``metrics.json`` / ``results.json``) is never re-run; ``--resume
true`` restarts the interrupted stage from its beginning in a cleared folder, so the resumed run writes the
``metrics.json`` of an uninterrupted one. Each stage saves its resolved ``config.yaml``.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import inspect
import json
import platform
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from jsonargparse.typing import NonNegativeInt

from threedq.atomic_io import atomic_write_json, atomic_write_text
from threedq.data.box_files import load_boxes_file
from threedq.errors import InputError
from threedq.locks import hold_folder
from threedq.pipeline.data_commands import output_folder
from threedq.pipeline.detection_eval import evaluate_detection
from threedq.pipeline.lightning_cli import (
    DEFAULT_DATA_CONFIG,
    ThreeDQCLI,
    packaged_configs_dir,
    resolve_config,
    test_checkpoint,
)
from threedq.pipeline.overrides import stage_overrides
from threedq.pipeline.precision import bf16_is_native as _bf16_is_native
from threedq.pipeline.presets import stage_presets
from threedq.pipeline.report import evaluate_quantizer
from threedq.pipeline.results import MiningResult, SelfLabellingResult, StageRecord
from threedq.pipeline.run_layout import RunLayout
from threedq.pipeline.tables import em_markdown, feature_cells, fewshot_cell, fmt, precision_label
from threedq.stages.checkpoint import require_stage
from threedq.stages.crop_cache import CropCache
from threedq.viz.curves import table3_figure
from threedq.viz.png import write_png

__all__ = ["evaluate_run_on", "run_em"]

ROUND_STAGES: tuple[str, ...] = ("mining", "quantizer", "self_labelling")
#: How a round fits its quantizer: one epoch over the training boxes, no validation pass.
_QUANTIZER_FIT = {"max_steps": -1, "max_epochs": 1, "limit_val_batches": 0}


def _config_label(path: Path, work: Path) -> str:
    """How the report names a config file: relative to the packaged configs, else to the work folder's parent."""
    path = Path(path)
    for base in (packaged_configs_dir(), work.resolve().parent):
        try:
            return str(path.resolve().relative_to(Path(base).resolve()))
        except ValueError:
            continue
    return str(path)


def _stage_done(run_dir: Path) -> StageRecord | None:
    marker = RunLayout.stage_marker(run_dir)
    return StageRecord.from_json(json.loads(marker.read_text())) if marker.is_file() else None


def _remove_torn_writes(work: Path) -> None:
    """Delete the temporary files of atomic writes that a kill cut short (``.<name>.<random>.tmp``)."""
    for tmp in work.rglob(".*.tmp"):
        if tmp.is_file():
            tmp.unlink()
            print(f"[em] removed {tmp} (a write cut short by the interruption)")


def _frees_its_stage(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Run ``fn`` (one stage or evaluation through a ``ThreeDQCLI``), then collect the cycles it built."""

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        finally:
            gc.collect()

    return run


@contextlib.contextmanager
def _old_objects_frozen() -> Iterator[None]:
    """Leave the objects that exist before the run out of the collector's work (``gc.freeze``) until it ends."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def _crop_cache_setup(cache: CropCache | None) -> Callable[[Any], None] | None:
    """The ``model_setup`` that hands a stage the run's shared crop cache (None: no cache)."""
    return None if cache is None else (lambda model: model.use_crop_cache(cache))


def _cli_args(configs: list[Path], run_dir: Path, overrides: list[str]) -> list[str]:
    args = [a for c in configs for a in ("--config", str(c))]
    return [*args, f"--trainer.default_root_dir={run_dir}", *overrides]


@_frees_its_stage
def _fit_stage(name: str, configs: list[Path], run_dir: Path, overrides: list[str], resume: bool,
               crop_cache: CropCache | None = None) -> StageRecord:
    done = _stage_done(run_dir)
    if done is not None:
        print(f"[em] {name}: finished earlier ({RunLayout.stage_marker(run_dir)}), not re-run")
        return done
    last = RunLayout.checkpoint(run_dir)
    if run_dir.exists() and any(run_dir.iterdir()):
        if not resume:
            raise RuntimeError(f"{run_dir} holds an unfinished '{name}' run: pass --resume to continue it, or delete "
                               "the folder")
        print(f"[em] {name}: unfinished (interrupted): restarting it from its beginning in a cleared {run_dir}")
        shutil.rmtree(run_dir)
    print(f"[em] {name}: training in {run_dir}")
    t0 = time.time()
    ThreeDQCLI(args=["fit", *_cli_args(configs, run_dir, overrides)], model_setup=_crop_cache_setup(crop_cache))
    if not last.is_file():
        raise RuntimeError(f"{name}: training finished without writing {last}")
    info = StageRecord(stage=name, checkpoint=str(last), seconds=round(time.time() - t0, 1))
    atomic_write_json(RunLayout.stage_marker(run_dir), info.to_json())
    return info


def _given_viewpred(path: str | Path) -> StageRecord:
    """The stage record of a view-prediction checkpoint given with ``--viewpred_ckpt``.

    Raises:
        InputError: no such file, not a checkpoint that loads safely, or another stage's.
    """
    ckpt = Path(path)
    require_stage(ckpt, "viewpred", "--viewpred_ckpt")
    print(f"[em] viewpred: given ({ckpt}), not trained here")
    return StageRecord(stage="viewpred", checkpoint=str(ckpt.resolve()), seconds=0.0, given=True)


def _mining_diagnostics(run_dir: Path) -> list[dict[str, Any]]:
    """The per-refresh diagnostics a mining run wrote (``mining/refresh_*.json``), in order."""
    return [json.loads(p.read_text()) for p in sorted((run_dir / "mining").glob("refresh_*.json"))]


@_frees_its_stage
def _evaluate_viewpred(configs: list[Path], ckpt: Path, run_dir: Path) -> dict[str, Any]:
    cached = run_dir / "metrics.json"
    if cached.is_file():
        print(f"[em] viewpred_eval: finished earlier ({cached}), not re-run")
        return json.loads(cached.read_text())
    t0 = time.time()
    cli, res = test_checkpoint(configs, ckpt, run_dir)
    vp = {k.removeprefix("test/"): v for k, v in res.items()}
    vp["num_scenes"] = len(cli.datamodule.index.files("test"))
    metrics = {"view_prediction": vp, "split": "test", "seconds": round(time.time() - t0, 1)}
    atomic_write_json(cached, metrics)
    return metrics


@_frees_its_stage
def _evaluate_detector(configs: list[Path], ckpt: Path, run_dir: Path, splits: tuple[str, ...],
                       overrides: list[str] | None = None, crop_cache: CropCache | None = None) -> dict[str, Any]:
    cached = run_dir / "results.json"
    if cached.is_file():
        done = json.loads(cached.read_text())
        if all(s in done.get("detections", {}) for s in splits):
            print(f"[em] detector_eval: finished earlier ({cached}), not re-run")
            return done
        print(f"[em] detector_eval: {cached} lacks detections of {', '.join(splits)}: evaluating again")
    cli, res = test_checkpoint(configs, ckpt, run_dir, overrides or [], model_setup=_crop_cache_setup(crop_cache))
    test_map = {k.removeprefix("test/"): (int(v) if k.startswith("test/num_") else v) for k, v in res.items()}
    return evaluate_detection(cli.model, cli.datamodule, run_dir, test_map, splits=splits)


@_frees_its_stage
def _evaluate_round(configs: list[Path], ckpt: Path, run_dir: Path, final: bool, overrides: list[str] | None = None,
                    crop_cache: CropCache | None = None) -> dict[str, Any]:
    cached = run_dir / "results.json"
    if cached.is_file():
        print(f"[em] {run_dir.name}: finished earlier ({cached}), not re-run")
        return json.loads(cached.read_text())
    cli, res = test_checkpoint(configs, ckpt, run_dir, overrides or [], model_setup=_crop_cache_setup(crop_cache))
    return evaluate_quantizer(cli.model, cli.datamodule, run_dir, res, baselines=final, curve_k=[],
                              random_encoder=final, per_category=final)


def _check_handed_on(eval_dir: Path, splits: tuple[str, ...]) -> None:
    """Refuse to start a round on handed-on detections (``eval_dir/detections_<split>.npz``) of fewer than 2 boxes."""
    for split in splits:
        path = RunLayout.detections(eval_dir, split)
        if not path.is_file():
            continue
        n = sum(len(aabb) for aabb, _ in load_boxes_file(path).values())
        if n < 2:
            raise RuntimeError(f"{path}: field 'boxes': the detector hands on {n} box(es) of the {split} split, the "
                               "rounds need at least 2; train the detector longer or run the rounds on GT boxes "
                               "(--boxes gt)")


def _table3(det_eval: dict[str, Any] | None, rounds: list[dict[str, Any]],
            self_labels: list[SelfLabellingResult], round0: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Paper Table 3 rows: per round 0..R, feature precision@10 (strict and paper protocol, same-object top-1),
    Hungarian accuracy and detection mAP@0.5 (test). Round 0: the warm-start detector and ``round0`` (a quantizer on
    the view-prediction encoder); a round's detection is its self-labelled detector's (else the warm start's).
    """
    def det_row(d: dict[str, Any] | None) -> dict[str, Any]:
        if not d:
            return {"map_50": None, "map_25": None, "handed_on_test": None}
        return {"map_50": d["detector"]["map_50"], "map_25": d["detector"]["map_25"],
                "handed_on_test": d.get("handed_on", {}).get("test")}
    rows = [{"round": 0, **feature_cells(round0["retrieval"] if round0 else None),
             "hungarian_acc": round0["quantization"]["threedq"]["hungarian_acc"] if round0 else None,
             **det_row(det_eval)}]
    for i, r in enumerate(rounds):
        d = self_labels[i].detector_eval if i < len(self_labels) else det_eval
        rows.append({"round": i + 1, **feature_cells(r["retrieval"]),
                     "hungarian_acc": r["quantization"]["threedq"]["hungarian_acc"], **det_row(d)})
    return rows


def _precisions(frozen_precision: str) -> tuple[str, dict[str, Any]]:
    """The precision of the stages reading a frozen encoder (``auto`` resolved: bf16 where it is native) and the
    trainer overrides of mining (none, or fp32 where bf16 would be emulated)."""
    mining_trainer: dict[str, Any] = {}
    if frozen_precision == "auto":
        native = _bf16_is_native()
        frozen_precision = "bf16-mixed" if native else "32-true"
        if not native:
            mining_trainer = {"precision": "32-true"}
    return frozen_precision, mining_trainer


@dataclass(frozen=True)
class _RunConfigs:
    """The resolved configs of every stage, each stage's own then the data and extra configs (empty: stage off)."""

    vp: list[Path]
    q: list[Path]
    m: list[Path]
    sl: list[Path]
    d: list[Path]
    vp_overrides: list[str]
    mine: bool
    relabel: bool


#: ``threedq em --preset paper``: the configs that replace each default (configs/paper/, the 256 px embedded data).
PAPER_PRESET = {"config": "paper/viewpred.yaml", "quantizer_config": "paper/quantizer.yaml",
                "detector_config": "paper/detector.yaml", "mining_config": "paper/mining.yaml",
                "self_labelling_config": "paper/self_labelling.yaml", "data_config": "data/clevr_veggie_256.yaml"}


def _preset(preset: str, *given: str | None) -> tuple[str | None, ...]:
    """The stage and data configs of ``preset`` in :data:`PAPER_PRESET`'s order (``paper`` replaces the defaults)."""
    if preset == "default":
        return given
    if preset != "paper":
        raise InputError(f"--preset: expected 'default' or 'paper', got {preset!r}")
    return tuple(PAPER_PRESET[k] if g == _DEFAULT_CONFIGS[k] else g for k, g in zip(PAPER_PRESET, given))


def _resolve_configs(config: str, quantizer_config: str | None, detector_config: str | None,
                     mining_config: str | None, self_labelling_config: str | None, data_config: str | None,
                     extra_configs: list[str] | str | None, detection: bool, max_steps: int | None) -> _RunConfigs:
    """Resolve the configs of every stage (:func:`run_em`'s arguments) and check the arguments the rounds hand each."""
    if isinstance(extra_configs, (str, Path)):
        extra_configs = [str(extra_configs)]
    extra = [resolve_config(c) for c in ([data_config] if data_config else []) + list(extra_configs or [])]
    vp_configs = [resolve_config(config), *extra]
    presets = stage_presets(extra)
    if quantizer_config is None:
        quantizer_config = presets.get("quantizer", "stages/quantizer.yaml")
    q_configs = [resolve_config(quantizer_config), *extra]
    if mining_config is None:
        mining_config = presets.get("mining", "stages/mining.yaml")
    if detector_config is None:
        detector_config = presets.get("detector", "stages/detector.yaml")
    mine = mining_config not in ("", "none")
    m_configs = [resolve_config(mining_config), *extra] if mine else []
    relabel = detection and self_labelling_config not in (None, "", "none")
    sl_configs = [resolve_config(self_labelling_config), *extra] if relabel else []
    overrides = stage_overrides(vp_configs, trainer={"max_steps": max_steps} if max_steps is not None else None)
    d_configs = [resolve_config(detector_config), *extra] if detection else []
    for cfgs, model_args, data_args in ((d_configs, ("encoder_ckpt",), ()),
                                        (q_configs, ("encoder_ckpt", "init_bank_ckpt"), ("boxes",)),
                                        (m_configs, ("encoder_ckpt", "em_round"), ("boxes",)),
                                        (sl_configs, ("encoder_ckpt", "bank_ckpt", "detector_ckpt"), ())):
        if cfgs:
            stage_overrides(cfgs, model=dict.fromkeys(model_args), data=dict.fromkeys(data_args))
    return _RunConfigs(vp_configs, q_configs, m_configs, sl_configs, d_configs, overrides, mine, relabel)


def _warm_start_detector(
    cfg: _RunConfigs, layout: RunLayout, vp_ckpt: Path, prec: dict[str, Any], resume: bool, crop_cache: CropCache,
    boxes: str, rounds: int) -> tuple[StageRecord, dict[str, Any], tuple[str, ...], dict[str, Any]]:
    """Train the detector on label-free pseudo-boxes and evaluate it.

    Returns:
        Its stage record, its evaluation, the splits whose detections the rounds read, and round 1's DataModule
        boxes (the detections handed on with ``boxes="detections"``, else empty: GT).
    """
    det = _fit_stage("detector", cfg.d, layout.detector,
                     stage_overrides(cfg.d, model={"encoder_ckpt": vp_ckpt}, trainer=prec), resume, crop_cache)
    det_splits = ("train", "val", "test") if boxes == "detections" else ("test",)
    det_eval = _evaluate_detector(cfg.d, det.path, layout.detector_eval, det_splits,
                                  stage_overrides(cfg.d, trainer=prec), crop_cache=crop_cache)
    print(f"[em] detection mAP@0.5: pseudo-boxes {det_eval['pseudo_boxes']['map_50']:.3f}, "
          f"detector {det_eval['detector']['map_50']:.3f}")
    boxes_of_round: dict[str, Any] = {}
    if boxes == "detections" and rounds:
        _check_handed_on(layout.detector_eval, ("train", "test"))
        boxes_of_round = {"boxes": layout.detections(layout.detector_eval)}
    return det, det_eval, det_splits, boxes_of_round


def _round0(cfg: _RunConfigs, layout: RunLayout, vp_ckpt: Path, boxes_of_round: dict[str, Any], prec: dict[str, Any],
            resume: bool, crop_cache: CropCache) -> dict[str, Any]:
    """The paper's iteration 0: the view-prediction encoder's features and prototypes on round 1's boxes, evaluated."""
    q0 = _fit_stage("round 0 quantizer (view-prediction encoder)", cfg.q, layout.round(0, "quantizer"),
                    stage_overrides(cfg.q, model={"encoder_ckpt": vp_ckpt}, data=boxes_of_round,
                                    trainer={**_QUANTIZER_FIT, **prec}), resume, crop_cache)
    return _evaluate_round(cfg.q, q0.path, layout.round(0, "eval"), final=False,
                           overrides=stage_overrides(cfg.q, data=boxes_of_round, trainer=prec), crop_cache=crop_cache)


@dataclass
class _Rounds:
    """What the EM rounds produced: per round its evaluation, mining result and self-labelling result."""

    results: list[dict[str, Any]] = field(default_factory=list)
    mining: list[MiningResult] = field(default_factory=list)
    self_labels: list[SelfLabellingResult] = field(default_factory=list)


def _run_rounds(rounds: int, cfg: _RunConfigs, layout: RunLayout, vp_ckpt: Path, det_ckpt: Path | None,
                det_eval: dict[str, Any] | None, det_splits: tuple[str, ...], boxes_of_round: dict[str, Any],
                boxes: str, bank_warm_start: bool, prec: dict[str, Any], mining_trainer: dict[str, Any], resume: bool,
                crop_cache: CropCache) -> _Rounds:
    """Rounds 1..``rounds``: mining (fine-tunes the encoder), quantizer, its evaluation (the last round's with the
    baselines), self-labelling of the detector and its evaluation (the next round's boxes)."""
    out = _Rounds()
    prev_bank: Path | None = None
    encoder = vp_ckpt
    for r in range(1, rounds + 1):
        if cfg.mine:
            m = _fit_stage(f"round {r} mining", cfg.m, layout.round(r, "mining"),
                           stage_overrides(cfg.m, model={"encoder_ckpt": encoder, "em_round": r},
                                           data=boxes_of_round, trainer=mining_trainer), resume, crop_cache)
            encoder = m.path
            out.mining.append(MiningResult(m, _mining_diagnostics(layout.round(r, "mining"))))
            crop_cache.drop("features")
            crop_cache.drop("grid")
        q_model: dict[str, Any] = {"encoder_ckpt": encoder}
        if prev_bank is not None and bank_warm_start:
            q_model["init_bank_ckpt"] = prev_bank
        q_over = stage_overrides(cfg.q, model=q_model, data=boxes_of_round, trainer={**_QUANTIZER_FIT, **prec})
        q = _fit_stage(f"round {r} quantizer", cfg.q, layout.round(r, "quantizer"), q_over, resume, crop_cache)
        prev_bank = q.path
        out.results.append(_evaluate_round(cfg.q, prev_bank, layout.round(r, "eval"), final=r == rounds,
                                           overrides=stage_overrides(cfg.q, data=boxes_of_round, trainer=prec),
                                           crop_cache=crop_cache))
        if cfg.relabel:
            assert det_ckpt is not None and det_eval is not None
            det_ckpt = _self_label_round(r, rounds, cfg, layout, encoder, prev_bank, det_ckpt, det_eval, det_splits,
                                         prec, resume, crop_cache, out.self_labels)
            if boxes == "detections" and r < rounds:
                _check_handed_on(layout.round(r, "detector_eval"), ("train", "test"))
                boxes_of_round = {"boxes": layout.detections(layout.round(r, "detector_eval"))}
        q_res, ret = out.results[-1]["quantization"]["threedq"], out.results[-1]["retrieval"]
        c = feature_cells(ret)
        print(f"[em] round {r}: Hungarian acc {q_res['hungarian_acc']:.3f}, few-shot "
              f"{fewshot_cell(q_res['fewshot_acc'])}, {precision_label(ret)} {c['precision_at_10']:.3f} (strict), "
              f"{fmt(c['precision_at_10_paper'])} (paper protocol)")
    if rounds:
        print(f"[em] crop cache: {crop_cache.hits} reused, {crop_cache.misses} computed (per scene: learned, raw "
              f"and random-encoder crops; {crop_cache.nbytes / 2**30:.2f} GiB held)")
    return out


def _self_label_round(r: int, rounds: int, cfg: _RunConfigs, layout: RunLayout, encoder: Path, bank: Path,
                     det_ckpt: Path, det_eval: dict[str, Any], det_splits: tuple[str, ...], prec: dict[str, Any],
                     resume: bool, crop_cache: CropCache, self_label_results: list[SelfLabellingResult]) -> Path:
    """Round ``r``'s self-labelling of the detector and its evaluation; appends the result to ``self_label_results``
    and returns the new detector checkpoint."""
    run = layout.round(r, "self_labelling")
    sl_model = {"encoder_ckpt": encoder, "bank_ckpt": bank}
    sl = _fit_stage(f"round {r} self-labelling", cfg.sl, run,
                    stage_overrides(cfg.sl, model={**sl_model, "detector_ckpt": det_ckpt}, trainer=prec),
                    resume, crop_cache)
    det_ckpt = sl.path
    splits = det_splits if r < rounds else ("test",)
    sl_eval = _evaluate_detector(cfg.sl, det_ckpt, layout.round(r, "detector_eval"), splits,
                                 stage_overrides(cfg.sl, model={**sl_model, "detector_ckpt": None}, trainer=prec),
                                 crop_cache)
    labels = run / "self_labels" / "labels.json"
    self_label_results.append(SelfLabellingResult(sl, json.loads(labels.read_text()) if labels.is_file() else None,
                                                  sl_eval))
    before = self_label_results[-2].map_50 if r > 1 else float(det_eval["detector"]["map_50"])
    print(f"[em] round {r} self-labelling: detection mAP@0.5 {self_label_results[-1].map_50:.3f} "
          f"(before: {before:.3f})")
    return det_ckpt


def _summary(work: Path, layout: RunLayout, rounds: int, cfg: _RunConfigs, data_config: str | None, vp: StageRecord,
             vp_eval: dict[str, Any], det: StageRecord | None, det_eval: dict[str, Any] | None, boxes: str,
             bank_warm_start: bool, frozen_precision: str, mining_trainer: dict[str, Any],
             round0: dict[str, Any] | None, rounds_run: _Rounds, crop_cache: CropCache) -> dict[str, Any]:
    """The run's ``metrics.json``: every stage's and round's results, Table 3, the configs and the machine."""
    mine, relabel = cfg.mine, cfg.relabel
    round_results, self_label_results = rounds_run.results, rounds_run.self_labels
    return {
        "work_dir": str(work), "rounds": rounds,
        "round_stages_run": [st for st in ROUND_STAGES if (st != "mining" or mine)
                             and (st != "self_labelling" or relabel)] if rounds else [],
        "self_labelling_config": _config_label(cfg.sl[0], work) if relabel else None,
        "self_label_results": [x.to_json() for x in self_label_results],
        "table3": _table3(det_eval, round_results, self_label_results, round0) if rounds else [],
        "round0_result": round0, "mining_config": _config_label(cfg.m[0], work) if mine else None,
        "quantizer_config": _config_label(cfg.q[0], work),
        "detector_config": _config_label(cfg.d[0], work) if cfg.d else None,
        "data_config": _config_label(resolve_config(data_config or DEFAULT_DATA_CONFIG), work),
        "mining_results": [x.to_json() for x in rounds_run.mining], "viewpred": vp.to_json(), "viewpred_eval": vp_eval,
        "detector": det.to_json() if det else None, "detector_eval": det_eval, "boxes": boxes,
        "bank_warm_start": bank_warm_start, "frozen_precision": frozen_precision,
        "mining_precision": mining_trainer.get("precision", "its config's"), "round_results": round_results,
        "final_eval_dir": str(layout.round(rounds, "eval")) if rounds else None,
        "crop_cache": {"reused": crop_cache.hits, "computed": crop_cache.misses,
                       "gib": round(crop_cache.nbytes / 2**30, 3)},
        "machine": f"{platform.machine()} {platform.processor() or ''} {torch.get_num_threads()} threads".strip(),
        "torch": torch.__version__,
    }


def _write_report(work: Path, summary: dict[str, Any]) -> None:
    """Write ``metrics.json``, ``table3.png`` and ``report.md`` to ``work``; print the final precision@k."""
    round_results = summary["round_results"]
    atomic_write_json(work / "metrics.json", summary)
    if summary["table3"]:
        write_png(work / "table3.png", table3_figure(summary["table3"]))
    atomic_write_text(work / "report.md", em_markdown(summary))
    if round_results:
        r = round_results[-1]["retrieval"]
        print(f"[em] precision@{r['k']}: " + ", ".join(f"{name} {v:.3f}" for name, v in r["precision_at_k"].items()))
    print(f"[em] wrote {work / 'report.md'} and {work / 'metrics.json'}")


def run_em(rounds: NonNegativeInt = 4, work_dir: str = "runs/em", resume: bool = False,
           config: str = "stages/viewpred.yaml", quantizer_config: str | None = None,
           detector_config: str | None = None, detection: bool = True,
           boxes: Literal["detections", "gt"] = "detections", data_config: str | None = None,
           extra_configs: list[str] | str | None = None, max_steps: int | None = None, mining_config: str | None = None,
           self_labelling_config: str | None = "stages/self_labelling.yaml", viewpred_ckpt: str | None = None,
           frozen_precision: Literal["auto", "bf16-mixed", "32-true"] = "auto", bank_warm_start: bool = False,
           preset: Literal["default", "paper"] = "default") -> dict[str, Any]:
    """Run view prediction, then ``rounds`` EM rounds, then the evaluation; write report.md + metrics.json.

    Args:
        rounds: EM rounds (detection -> mining -> quantization -> self-labelling) after pre-training.
        work_dir: folder of all runs of this experiment.
        resume: continue a killed run: finished stages and evaluations are kept, the interrupted stage restarts from
            its beginning (the numbers are those of an uninterrupted run).
        config: the view-prediction stage config (a path, or one inside the packaged configs/).
        quantizer_config: the quantizer stage config (default: the data's preset,
            :func:`~threedq.pipeline.presets.stage_presets`: ``stages/quantizer.yaml`` on the embedded data,
            ``stages/quantizer_multiview.yaml`` on the shape-only data and users' scene folders and captures).
        detector_config: the detector stage config, trained from label-free pseudo-boxes (default: the data's preset,
            :func:`~threedq.pipeline.presets.stage_presets`: ``stages/detector.yaml`` on the embedded and shape-only
            data, ``stages/detector_scene.yaml`` on users' scene folders and captures).
        detection: train and evaluate the detector before the rounds.
        boxes: object boxes of the rounds: ``detections`` (the paper's protocol: the boxes the current detector
            hands on, above its score threshold; needs ``detection``; GT is used only to score, over the detections
            matched to GT at IoU 0.5) or ``gt`` (the oracle boxes, for comparison).
        data_config: the dataset of every stage (a data config, ``configs/data/*.yaml`` or a file of your own naming
            the DataModule ``class_path`` and its ``data_dir``), composed after each stage's config; default: the
            embedded data (``data/clevr_veggie.yaml``, the CLI's default dataset).
        extra_configs: more configs composed after each stage's and the data config (e.g. ``trainer/gpu.yaml``); one
            path or a list (``--extra_configs my.yaml``, ``--extra_configs '[a.yaml, b.yaml]'``, ``--extra_configs+ x``).
        max_steps: override the training steps of the view-prediction stage.
        mining_config: the correspondence-learning stage config run at the start of every round, fine-tuning
            the encoder that the round's quantizer then uses; default: the data's preset
            (:func:`~threedq.pipeline.presets.stage_presets`: ``stages/mining.yaml`` on the embedded data,
            ``stages/mining_occupancy_pairs.yaml`` on the shape-only data and scene folders);
            ``stages/vc_moco.yaml`` or ``stages/vc.yaml``: the view-contrastive baselines; ``none``: no fine-tuning,
            every round quantizes the view-prediction features.
        self_labelling_config: the detector self-labelling stage config run at the end of every round (with the
            round's encoder and prototypes; the next round takes its boxes from the self-labelled detector);
            ``none``: the detector stays the warm start. Needs ``detection``.
        viewpred_ckpt: a view-prediction checkpoint to start from instead of training one (e.g. the embedded data's
            encoder on a dataset of your own: the detector is still warm-started from this dataset's own label-free
            pseudo-boxes and self-labelled on it). It is evaluated on this dataset's test split and copied nowhere.
        frozen_precision: Lightning precision of the stages that read a frozen encoder (the detector, the quantizer,
            self-labelling and every evaluation after view prediction): ``bf16-mixed``, ``32-true``, or ``auto``
            (bf16 where the CPU has bf16 instructions or the GPU supports it, else fp32, mining included). View
            prediction keeps its config's precision; a CPU without bf16 instructions runs bf16 as fp32
            (:func:`~threedq.pipeline.precision.cpu_precision`).
        bank_warm_start: from round 2 on, each round's quantizer refines the previous round's prototype bank (true,
            the paper's loop) or fits an empty bank on the round's encoder, as rounds 0 and 1 do (false;
            docs/studies/quantizer.md, "A fresh bank every round").
        preset: ``paper``: every stage config and the data config left at its default become the paper's sizes
            (:data:`PAPER_PRESET`: 144^3 grid, 256 px views, pools of 1000; docs/paper-scale.md).
    """
    if boxes == "detections" and not detection:
        raise InputError("--boxes: 'detections' needs --detection true")
    config, quantizer_config, detector_config, mining_config, self_labelling_config, data_config = _preset(
        preset, config, quantizer_config, detector_config, mining_config, self_labelling_config, data_config)
    frozen_precision, mining_trainer = _precisions(frozen_precision)
    prec = {"precision": frozen_precision}
    work = output_folder("--work_dir", work_dir)
    layout = RunLayout(work)
    with hold_folder(work, check_below=True), _old_objects_frozen():
        if resume:
            _remove_torn_writes(work)
        cfg = _resolve_configs(config, quantizer_config, detector_config, mining_config, self_labelling_config,
                               data_config, extra_configs, detection, max_steps)
        vp = (_given_viewpred(viewpred_ckpt) if viewpred_ckpt is not None
              else _fit_stage("viewpred", cfg.vp, layout.viewpred, cfg.vp_overrides, resume))
        vp_eval = _evaluate_viewpred(cfg.vp, vp.path, layout.viewpred_eval)
        crop_cache = CropCache()
        det, det_eval, det_splits, boxes_of_round = (
            _warm_start_detector(cfg, layout, vp.path, prec, resume, crop_cache, boxes, rounds) if detection
            else (None, None, ("test",), {}))
        round0 = _round0(cfg, layout, vp.path, boxes_of_round, prec, resume, crop_cache) if rounds else None
        rounds_run = _run_rounds(rounds, cfg, layout, vp.path, det.path if det else None, det_eval, det_splits,
                                 boxes_of_round, boxes, bank_warm_start, prec, mining_trainer, resume, crop_cache)
        summary = _summary(work, layout, rounds, cfg, data_config, vp, vp_eval, det, det_eval, boxes, bank_warm_start,
                           frozen_precision, mining_trainer, round0, rounds_run, crop_cache)
        _write_report(work, summary)
        return summary


#: run_em's default of each config :data:`PAPER_PRESET` replaces.
_DEFAULT_CONFIGS = {k: inspect.signature(run_em).parameters[k].default for k in PAPER_PRESET}


def evaluate_run_on(run: str | Path, out: str | Path, data_config: str | None = None,
                    detector_config: str | None = None, quantizer_config: str | None = None,
                    self_labelling_config: str = "stages/self_labelling.yaml",
                    frozen_precision: Literal["auto", "bf16-mixed", "32-true"] = "auto") -> dict[str, Any]:
    """Evaluate a finished run's last detector and last quantizer (encoder and prototype bank) on a dataset, training
    nothing, as a round's detector evaluation and round evaluation do (e.g. on a noisy copy, ``threedq data degrade``).

    Args:
        run: a ``threedq em`` work folder with at least one finished round.
        out: the folder written: ``detector_eval/`` and ``eval/`` (each kept once finished, as in a run).
        data_config: the dataset (default: the embedded data); detector_config, quantizer_config (default: the
            data's preset), self_labelling_config: the stage configs the run used.
        frozen_precision: as :func:`run_em`'s.

    Returns:
        ``{"detector_eval": ..., "round_eval": ...}``, the two evaluations' results.

    Raises:
        InputError: ``run`` has no finished detector or quantizer.
    """
    layout = RunLayout(Path(run))
    det_ckpt, q_ckpt = layout.final_detector(), layout.final_quantizer()
    if det_ckpt is None or q_ckpt is None:
        raise InputError(f"{run}: no finished {'detector' if det_ckpt is None else 'quantizer'} (stage.json and "
                         "checkpoints/last.ckpt); evaluate a threedq em run with at least one finished round")
    prec = {"precision": _precisions(frozen_precision)[0]}
    cfg = _resolve_configs("stages/viewpred.yaml", quantizer_config, detector_config, "none", self_labelling_config,
                           data_config, None, True, None)
    out = output_folder("--out", out)
    det_dir, eval_dir = out / "detector_eval", out / "eval"
    crop_cache = CropCache()
    relabelled = layout.rounds("self_labelling")
    det_cfg, model = cfg.d, None
    if relabelled and det_ckpt.parent.parent == layout.round(relabelled[-1], "self_labelling"):
        r = relabelled[-1]
        encoder = layout.finished(layout.round(r, "mining")) or layout.checkpoint(layout.viewpred)
        det_cfg, model = cfg.sl, {"encoder_ckpt": encoder, "bank_ckpt": layout.finished(layout.round(r, "quantizer")),
                                  "detector_ckpt": None}
    det_eval = _evaluate_detector(det_cfg, det_ckpt, det_dir, ("train", "val", "test"),
                                  stage_overrides(det_cfg, model=model, trainer=prec), crop_cache=crop_cache)
    boxes = {"boxes": RunLayout.detections(det_dir)}
    round_eval = _evaluate_round(cfg.q, q_ckpt, eval_dir, final=False,
                                 overrides=stage_overrides(cfg.q, data=boxes, trainer=prec), crop_cache=crop_cache)
    return {"detector_eval": det_eval, "round_eval": round_eval}
