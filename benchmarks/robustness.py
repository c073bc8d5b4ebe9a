"""Robustness to capture conditions: the main job's model, and one adaptation round, on noisy copies of the embedded data.

Per condition (``threedq.data.sensor``): ``frozen``, the main job's last detector and quantizer on a copy whose test
split is degraded; ``adapted`` (``--adapt``), ``threedq em --rounds 1 --viewpred_ckpt <main job's>`` on a copy whose
every split is degraded, its quantizer ``--quantizer_config`` and detector ``--detector_config`` (default the capture
DataModules' presets: 3 input views; detections refined against the scene's pseudo-boxes); with ``--viewpred copy``
the round trains its own view prediction on the copy (``threedq em --rounds 1``, a user's whole first run) instead of
reusing the main job's. Rows go to ``--rows`` (a row already there is not measured again: keep one file per CPU type);
the table (``--md``) and the picture (``--png``) are drawn from every row of the file::

    python benchmarks/robustness.py --main_run runs/em --work runs/robustness \\
        --rows benchmarks/results/robustness/rows.jsonl --md docs/robustness_table.md --png docs/img/robustness.png
    python benchmarks/robustness.py --rows benchmarks/results/robustness/rows.jsonl --png docs/img/robustness.png \\
        --conditions   # no condition: redraw the table and picture from the rows

Convention: a condition is ``level<L>`` (every effect at level L; ``level0`` is the clean data) or an effect's name
(that effect alone at level 1); metrics on the test split, mAP at IoU 0.5 against the GT boxes' hulls, yaw error the
median relative yaw error on asymmetric categories in degrees.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from _common import append_row, read_rows

from threedq.data.sensor import EFFECTS, degrade_dataset
from threedq.machine import cpu_name

LEVELS = ("level0", "level0.5", "level1", "level2")
#: (row key, table heading)
METRICS = (("pseudo_map_50", "pseudo-boxes mAP@0.5"), ("detector_map_50", "detector mAP@0.5"),
           ("precision_at_10", "p@10 strict"), ("precision_at_10_paper", "p@10 paper"),
           ("hungarian_acc", "Hungarian K=50"), ("fewshot_acc", "few-shot"), ("yaw_median_deg", "yaw error (deg)"))
DATA_CONFIG = """data:
  class_path: threedq.datamodules.clevr_veggie.ClevrVeggieDataModule
  init_args:
    data_dir: {data_dir}
    sensor_captures: {sensor}
"""
#: the adaptation rounds' quantizer: the capture DataModules' preset; rows without ``quantizer_config`` used ONE_VIEW
QUANTIZER, ONE_VIEW = "stages/quantizer_multiview.yaml", "stages/quantizer.yaml"
#: the adaptation rounds' detector: the capture DataModules' preset; rows without ``detector_config`` used PLAIN
DETECTOR, PLAIN = "stages/detector_scene.yaml", "stages/detector.yaml"


def _quantizer(r: dict[str, Any]) -> str:
    return r.get("quantizer_config", ONE_VIEW)


def _detector(r: dict[str, Any]) -> str:
    return r.get("detector_config", PLAIN)


def _viewpred(r: dict[str, Any]) -> str:
    return r.get("viewpred", "main")


def _configs(r: dict[str, Any]) -> str:
    """The table's name of a row's stage configs: the quantizer's, the detector's where it is not the default, and
    the view prediction's where the round trained its own."""
    q, d = Path(_quantizer(r)).stem, _detector(r)
    name = q if d == PLAIN else f"{q} + {Path(d).stem}"
    return name + (" + view prediction on the copy" if _viewpred(r) == "copy" else "")


def condition(name: str) -> tuple[float, list[str] | None]:
    """``(level, effects)`` of a condition name (see the module's convention)."""
    if name.startswith("level"):
        return float(name.removeprefix("level")), None
    if name not in EFFECTS:
        raise SystemExit(f"robustness: condition {name!r}: expected level<L> or one of {', '.join(EFFECTS)}")
    return 1.0, [name]


def noisy_copy(clean: Path, work: Path, name: str, splits: list[str] | None, sensor: bool) -> Path:
    """The dataset folder of a condition (the clean one for level 0) and a data config naming it, read as sensor
    captures or not (``sensor_captures``)."""
    level, effects = condition(name)
    if level == 0:  # the clean scenes, linked: the copy's own proposal caches leave the clean folder's alone
        data = work / "data_level0"
        for f in [clean / "index.json", *clean.glob("*/*.npz")]:
            dst = data / f.relative_to(clean)
            if not dst.exists():
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.link(f, dst)
    else:
        data = work / f"data_{name}_{'all' if splits is None else '_'.join(splits)}"
        t0 = time.time()
        n = degrade_dataset(clean, data, level, effects, splits=splits)
        if n:
            print(f"[robustness] {data}: {n} scenes written in {time.time() - t0:.0f} s", flush=True)
    cfg = work / f"{data.name}_{'sensor' if sensor else 'render'}.yaml"
    cfg.write_text(DATA_CONFIG.format(data_dir=data.resolve(), sensor=str(sensor).lower()))
    return cfg


def bank_cells(q: dict[str, Any]) -> dict[str, Any]:
    """The bank's numbers of a row, from an evaluation's ``quantization["threedq"]``."""
    return {k: q[k] for k in ("hungarian_acc", "fewshot_acc", "yaw_median_deg")}


def frozen_row(main_run: Path, work: Path, clean: Path, name: str, sensor: bool) -> dict[str, Any]:
    """The main job's model on the condition's noisy test split."""
    from threedq.pipeline.em import evaluate_run_on
    from threedq.pipeline.tables import feature_cells

    cfg = noisy_copy(clean, work, name, ["test"], sensor)
    t0 = time.time()
    r = evaluate_run_on(main_run, work / f"frozen_{name}_{cfg.stem.rsplit('_', 1)[1]}", data_config=str(cfg))
    q = r["round_eval"]["quantization"]["threedq"]
    cells = feature_cells(r["round_eval"]["retrieval"])
    return {"pseudo_map_50": r["detector_eval"]["pseudo_boxes"]["map_50"],
            "detector_map_50": r["detector_eval"]["detector"]["map_50"],
            **{k: cells[k] for k in ("precision_at_10", "precision_at_10_paper")}, **bank_cells(q),
            "seconds": round(time.time() - t0, 1)}


def adapted_row(main_run: Path, work: Path, clean: Path, name: str, seed: int, sensor: bool,
                quantizer: str = QUANTIZER, detector: str = DETECTOR, viewpred: str = "main") -> dict[str, Any]:
    """``threedq em --rounds 1 --viewpred_ckpt`` on the condition's noisy copy (every split), one seed, with the
    quantizer config ``quantizer`` and the detector config ``detector``; ``viewpred="copy"``: without
    ``--viewpred_ckpt`` (the round trains its view prediction on the copy)."""
    cfg = noisy_copy(clean, work, name, None, sensor)
    seed_cfg = work / f"seed{seed}.yaml"
    seed_cfg.write_text(f"seed_everything: {seed}\n")
    tag = ("" if quantizer == ONE_VIEW else f"_{Path(quantizer).stem}") + (
        "" if detector == PLAIN else f"_{Path(detector).stem}") + ("_vpcopy" if viewpred == "copy" else "")
    run = work / f"adapted_{name}_{cfg.stem.rsplit('_', 1)[1]}{tag}_s{seed}"
    t0 = time.time()
    cmd = ["threedq", "em", "--rounds", "1", "--work_dir", str(run), "--resume", "true",
           *([] if viewpred == "copy" else ["--viewpred_ckpt", str(main_run / "00_viewpred/checkpoints/last.ckpt")]),
           "--data_config", str(cfg), "--extra_configs", str(seed_cfg), "--quantizer_config", quantizer,
           "--detector_config", detector]
    print("[robustness] " + " ".join(cmd), flush=True)
    proc = subprocess.run(cmd, capture_output=True, text=True)
    (run.parent / f"{run.name}.log").write_text(proc.stdout + proc.stderr)
    if proc.returncode:  # a stage that finds too few objects stops the run with one line: the row's result
        return {"failed": (proc.stderr.strip().splitlines() or ["(no output)"])[-1],
                "seconds": round(time.time() - t0, 1)}
    m = json.loads((run / "metrics.json").read_text())
    last_round, q = m["table3"][-1], m["round_results"][-1]["quantization"]["threedq"]
    return {"pseudo_map_50": m["detector_eval"]["pseudo_boxes"]["map_50"],
            "warm_start_map_50": m["detector_eval"]["detector"]["map_50"],
            "detector_map_50": last_round["map_50"],
            **{k: last_round[k] for k in ("precision_at_10", "precision_at_10_paper")}, **bank_cells(q),
            "seconds": round(time.time() - t0, 1)}


def pseudo_box_rows(clean: Path, conditions: list[str], scenes: int) -> list[dict[str, Any]]:
    """The first stage alone, fast: the pseudo-boxes of ``scenes`` test scenes degraded in memory (the draws of
    ``threedq data degrade --seed 0``), with the renders' and the sensor captures' parameters, against the GT hulls."""
    import zlib

    import numpy as np

    from threedq.data.sensor import apply_capture
    from threedq.datamodules.scene_folder import RENDER_PROPOSALS, SENSOR_PROPOSALS
    from threedq.pipeline.detection_eval import box_sets_map, gt_hulls
    from threedq.proposals import propose_boxes
    from threedq.scene import load_index, load_scene

    index = load_index(clean)
    files = index.files("test")[:scenes]
    gt, rows = gt_hulls(clean, files), []
    for name in conditions:
        level, effects = condition(name)
        recs = {f: apply_capture(load_scene(clean / f), np.random.default_rng([0, zlib.crc32(f.encode())]), level,
                                 effects) for f in files}
        for read_as, params in (("renders", RENDER_PROPOSALS), ("sensor captures", SENSOR_PROPOSALS)):
            kw = {k: getattr(params, k) for k in params.__dataclass_fields__}
            sets = {f: propose_boxes(r, bounds=index.scene_bounds, **kw) for f, r in recs.items()}
            m = box_sets_map(gt, sets, progress=False)
            rows.append({"condition": name, "read_as": read_as, "map_50": m["map_50"], "map_25": m["map_25"],
                         "boxes_per_scene": sum(len(a) for a, _ in sets.values()) / len(files)})
            print(f"[robustness] pseudo-boxes {name} read as {read_as}: " + json.dumps(rows[-1]), flush=True)
    return rows


def pseudo_box_table(rows: list[dict[str, Any]], scenes: int) -> str:
    out = [f"| condition ({scenes} test scenes) | read as renders: mAP@0.5 / @0.25 / boxes per scene | "
           "read as sensor captures |", "|---|---|---|"]
    for name in dict.fromkeys(r["condition"] for r in rows):
        cells = [next(r for r in rows if r["condition"] == name and r["read_as"] == a) for a in
                 ("renders", "sensor captures")]
        out.append(f"| {name} | " + " | ".join(f"{c['map_50']:.3f} / {c['map_25']:.3f} / {c['boxes_per_scene']:.2f}"
                                                for c in cells) + " |")
    return "\n".join(out) + "\n"


def _fmt(v: Any) -> str:
    return "–" if v is None else (f"{v:.1f}" if isinstance(v, float) and v > 1.5 else f"{v:.3f}")


def _read_as(sensor: bool) -> str:
    return "sensor captures" if sensor else "renders"


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown: one line per condition and mode, the mean over seeds (and their range where there are several)."""
    order = {n: i for i, n in enumerate((*LEVELS, *EFFECTS))}
    def key(r: dict[str, Any]) -> tuple[str, bool, str, str]:
        return r["mode"], r["sensor_captures"], _configs(r), r["condition"]

    keys = sorted({key(r) for r in rows}, key=lambda k: (k[0] != "frozen", k[1], k[2], order.get(k[3], 99)))
    out = ["| mode | read as | stage configs | condition | seeds | " + " | ".join(h for _, h in METRICS) + " |",
           "|---|---|---|---|---|" + "---|" * len(METRICS)]
    for mode, sensor, q, cond in keys:
        group = [r for r in rows if key(r) == (mode, sensor, q, cond)]
        ok = [r for r in group if "failed" not in r]
        seeds = ", ".join(str(r["seed"]) for r in group)
        if not ok:
            out.append(f"| {mode} | {_read_as(sensor)} | {q} | {cond} | {seeds} | stopped: {group[0]['failed']} |"
                       + " |" * (len(METRICS) - 1))
            continue
        cells = []
        for vals in ([r[k] for r in ok if r.get(k) is not None] for k, _ in METRICS):
            cells.append(_fmt(sum(vals) / len(vals)) + (f" ({_fmt(min(vals))}-{_fmt(max(vals))})" if len(vals) > 1
                                                          else "") if vals else "–")
        out.append(f"| {mode} | {_read_as(sensor)} | {q} | {cond} | {seeds} | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def curve_png(rows: list[dict[str, Any]], path: Path) -> None:
    """Each metric against the capture level (every effect), as a share of its clean value: the main job's model, one
    adaptation round with the one-view quantizer and the input view's detector, and one with the capture DataModules'
    presets; solid read as sensor captures, dashed read as renders."""
    from threedq.viz.png import figure_png, new_figure, write_png

    fig = new_figure(figsize=(17, 4.5))
    colours = dict(zip([k for k, _ in METRICS], ["C0", "C1", "C2", "C3", "C4", "C5", "C6"]))
    panels = (("frozen", ONE_VIEW, PLAIN, "the main job's model"),
              ("adapted", ONE_VIEW, PLAIN, "one adaptation round: one view, the input view's boxes"),
              ("adapted", QUANTIZER, DETECTOR, "one adaptation round: the capture presets"))
    for ax_i, (mode, quantizer, detector, title) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), ax_i + 1)
        kept = [r for r in rows if r["mode"] == mode and _quantizer(r) == quantizer and _detector(r) == detector
                and _viewpred(r) == "main" and "failed" not in r]
        for sensor in (False, True):
            level_rows = [r for r in kept if r["sensor_captures"] == sensor and r["condition"] in LEVELS]
            clean = [r for r in kept if r["condition"] == "level0"]
            if not level_rows or not clean:
                continue
            for k, label in METRICS:
                if k == "yaw_median_deg":
                    continue
                base = sum(r[k] for r in clean) / len(clean)
                xs = sorted({condition(r["condition"])[0] for r in level_rows})
                ys = [sum(v) / len(v) / base for v in ([r[k] for r in level_rows if condition(r["condition"])[0] == x]
                                                       for x in xs)]
                ax.plot(xs, ys, marker="o", color=colours[k], ls="-" if sensor else "--",
                        label=f"{label} ({_read_as(sensor)})")
        ax.axhline(0.9, color="grey", lw=0.8, ls=":")
        ax.set_xlabel("capture level (1 = a Kinect-class sensor and a good SLAM run)")
        ax.set_ylabel("share of the clean value")
        ax.set_title(title, fontsize=9)
        ax.set_ylim(0, 1.25)
        ax.legend(fontsize=6, ncol=2)
    write_png(path, figure_png(fig))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--main_run", type=Path, default=Path("runs/em"), help="the main job's work dir")
    ap.add_argument("--clean", type=Path, default=Path("data/clevr_veggie"), help="the embedded data's folder")
    ap.add_argument("--work", type=Path, default=Path("runs/robustness"))
    ap.add_argument("--conditions", nargs="*", default=[*LEVELS, *EFFECTS])
    ap.add_argument("--adapt", nargs="*", default=["level0", "level1", "level2"],
                    help="conditions also run with one adaptation round")
    ap.add_argument("--seeds", nargs="*", type=int, default=[0], help="seeds of the adaptation rounds")
    ap.add_argument("--sensor_captures", nargs="*", default=["true"], choices=["true", "false"],
                    help="read the copies as sensor captures (the DataModule's sensor_captures), or not, or both")
    ap.add_argument("--quantizer_config", default=QUANTIZER, help="the adaptation rounds' quantizer config")
    ap.add_argument("--detector_config", default=DETECTOR, help="the adaptation rounds' detector config")
    ap.add_argument("--viewpred", default="main", choices=["main", "copy"],
                    help="the adaptation rounds' view prediction: the main job's, or trained on the copy")
    ap.add_argument("--rows", type=Path, default=Path("benchmarks/results/robustness/rows.jsonl"))
    ap.add_argument("--pseudo_boxes", type=int, default=0, metavar="N",
                    help="only the pseudo-boxes of N test scenes per condition (degraded in memory), renders' against "
                    "sensor captures' parameters: a table in a minute")
    ap.add_argument("--md", type=Path, default=None, help="write the table here too")
    ap.add_argument("--png", type=Path, default=None, help="draw the curves here")
    args = ap.parse_args(argv)
    for name in args.conditions + args.adapt:
        condition(name)
    if args.pseudo_boxes:
        text = pseudo_box_table(pseudo_box_rows(args.clean, args.conditions, args.pseudo_boxes), args.pseudo_boxes)
        print(text)
        if args.md:
            args.md.write_text(text)
        return 0
    args.work.mkdir(parents=True, exist_ok=True)
    args.rows.parent.mkdir(parents=True, exist_ok=True)
    rows = read_rows(args.rows) if args.rows.is_file() else []
    done = {(r["mode"], r["condition"], r["seed"], r["sensor_captures"], _quantizer(r), _detector(r),
             _viewpred(r)) for r in rows}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    todo = []
    for sensor in [s == "true" for s in args.sensor_captures]:
        todo += [("frozen", c, 0, sensor, ONE_VIEW, PLAIN, "main") for c in args.conditions]
        todo += [("adapted", c, s, sensor, args.quantizer_config, args.detector_config, args.viewpred)
                 for c in args.conditions if c in args.adapt for s in args.seeds]
    for mode, name, seed, sensor, quantizer, detector, viewpred in todo:
        if (mode, name, seed, sensor, quantizer, detector, viewpred) in done:
            continue
        row = {"mode": mode, "condition": name, "seed": seed, "sensor_captures": sensor, "quantizer_config": quantizer,
               "detector_config": detector, **({"viewpred": viewpred} if viewpred != "main" else {}),
               **(frozen_row(args.main_run, args.work, args.clean, name, sensor) if mode == "frozen"
                  else adapted_row(args.main_run, args.work, args.clean, name, seed, sensor, quantizer, detector,
                                   viewpred)),
               "machine": cpu_name(), "commit": commit, "date": time.strftime("%Y-%m-%d")}
        append_row(args.rows, row)
        rows.append(row)
        print(f"[robustness] {mode} {name} seed {seed}: " + json.dumps(row), flush=True)
    text = table(rows)
    print(text)
    if args.md:
        args.md.write_text(text)
    if args.png:
        curve_png(rows, args.png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
