"""The result pages of the main job, generated from one committed ``metrics.json``: never hand-copied numbers.

``docs/results/metrics.json`` (``runs/em/metrics.json`` of ``threedq em --rounds 4``) and ``run.json`` beside it
(command, commit, date, duration, machine) are the only source of ``docs/results.md``, the README's results table
and picture, and the tables of ``docs/fidelity.md``, each between ``<!-- generated:NAME begin ... -->`` and
``<!-- generated:NAME end -->`` markers::

    python -m threedq.pipeline.results_pages --run runs/em --time_log time.log   # record runs/em, then write
    python -m threedq.pipeline.results_pages                                     # rewrite from the committed files
    python -m threedq.pipeline.results_pages --check                             # exit 1 if a page is stale
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import yaml

from threedq.machine import cpu_capabilities, cpu_name
from threedq.pipeline.presets import preset_results_markdown
from threedq.pipeline.tables import METHOD_LABELS as METHODS
from threedq.pipeline.tables import _cell as _f
from threedq.pipeline.tables import method_rows as _methods
from threedq.pipeline.tables import size_band_cells, viewpred_lines

__all__ = ["PAPER", "fidelity_blocks", "load_results", "main", "overview_figure", "readme_table", "record_run",
           "replace_block", "results_page", "write_pages"]

ROOT = Path(__file__).resolve().parents[2]
RESULTS_DIR = Path("docs/results")
OVERVIEW = "docs/img/overview.png"
MAIN_JOB = "pip install torch==2.13.0 -e . && threedq em --rounds 4"
GENERATOR = "python -m threedq.pipeline.results_pages"

#: The paper's CLEVR-veggie numbers (3DQ-Nets, AAAI 2021, main text and supplement; the Table 3 rows are its
#: iterations 0-3).
PAPER: dict[str, Any] = {
    "table1": {"3DQ-Nets": 0.75, "ResNetRet": 0.80, "ResNetClass": 0.72},
    "table2": {"ResNet": 0.87, "rgbocc": 0.74, "rgbocc+VC": 0.71, "rgbocc+VC*": 0.74, "ours": 0.81},
    "table3": {"features": [0.72, 0.76, 0.79, 0.79], "quantization": [0.51, 0.63, 0.65, 0.66],
               "detection": [0.43, 0.48, 0.51, 0.52]},
    "table4": {"2.5DQ-Nets": 0.23, "no-rot-3DQ": 0.73, "point-cloud registration": 0.51, "3DQ-Nets": 0.77},
    "table5": {"3D pretrain": (0.42, 0.61), "2D triang-pretrain": (0.37, 0.52)},
}


def _paper(values: list[float], i: int) -> str:
    return f"{values[i]:.2f}" if i < len(values) else "-"


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f} min"


def _short(commit: str) -> str:
    return commit[:7]


def _cells(retrieval: dict[str, Any], key: str = "learned") -> dict[str, Any]:
    """precision@k of feature set ``key`` under both protocols, the same-object top-1, pool and ceilings."""
    prot = retrieval.get("protocols", {})
    st, pa = prot.get("strict", {}), prot.get("paper", {})
    return {"strict": st.get("precision_at_k", retrieval["precision_at_k"]).get(key),
            "paper": pa.get("precision_at_k", {}).get(key), "top1": pa.get("same_object_top1", {}).get(key),
            "pool": retrieval["num_objects"], "ceil_strict": st.get("ceiling"), "ceil_paper": pa.get("ceiling")}


def _detector_evals(m: dict[str, Any]) -> list[dict[str, Any]]:
    """The detector evaluations of the run: the warm start's, then each round's after its self-labelling."""
    return [m["detector_eval"], *(s["detector_eval"] for s in m.get("self_label_results") or [])]


def _final(m: dict[str, Any]) -> dict[str, Any]:
    return m["round_results"][-1]


def _run_line(info: dict[str, Any]) -> str:
    peak = f", peak resident memory {info['peak_rss_gib']:.1f} GiB" if info.get("peak_rss_gib") else ""
    return (f"`{info['command']}` at commit `{_short(info['commit'])}`, {info['date']}, on {info['machine']}: "
            f"**{_minutes(info['wall_seconds'])}** for `{info['timed']}`{peak}. {_provenance(info)}")


#: the instruction sets that change which kernels (and so which float and bf16 numbers) torch runs, named on the page
NUMERIC_FLAGS = ("amx_bf16", "avx512_bf16", "avx512_fp16", "avx512_vnni", "avx512_f", "avx2", "fma3")


def _provenance(info: dict[str, Any]) -> str:
    """What a reader on another CPU type compares: the dataset's bytes and the CPU's instruction sets."""
    data = (f"dataset fingerprint `{info['data_sha256'][:12]}`" if info.get("data_sha256")
            else "dataset fingerprint not recorded")
    shown = [f for f in info.get("cpu_flags") or () if f in NUMERIC_FLAGS]
    flags = (f"CPU flags {', '.join(shown) or 'none of ' + ', '.join(NUMERIC_FLAGS)} (all in run.json)"
             if info.get("cpu_flags") else "CPU flags not recorded")
    return (f"Its {data}, {flags}: the generator's scenes and bf16 arithmetic differ by CPU type, so another CPU "
            "gives other numbers for one seed")


def data_fingerprint(data_dir: str | Path) -> str | None:
    """SHA-256 over the relative path and bytes of every file of a dataset folder (its index and scenes; caches
    such as ``proposals/`` left out), in path order; None where the folder is missing."""
    root = Path(data_dir)
    if not root.is_dir():
        return None
    digest = hashlib.sha256()
    for f in sorted(p for p in root.rglob("*") if p.is_file() and "proposals" not in p.relative_to(root).parts):
        digest.update(str(f.relative_to(root)).encode() + b"\0")
        with f.open("rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def cpu_flags() -> list[str]:
    """The instruction sets torch reports for this CPU (:func:`~threedq.machine.cpu_capabilities`), sorted."""
    return sorted(k for k, v in cpu_capabilities().items() if v is True)


def _run_data_dir(run: Path) -> Path | None:
    """The dataset folder the run's view-prediction stage read (its saved config), or None."""
    cfg = run / "00_viewpred" / "config.yaml"
    try:
        return Path(yaml.safe_load(cfg.read_text())["data"]["init_args"]["data_dir"])
    except (OSError, KeyError, TypeError, yaml.YAMLError):
        return None


def readme_table(m: dict[str, Any], info: dict[str, Any]) -> str:
    """The README's short table: the main job beside the paper, both retrieval protocols named."""
    r0, rl = m["round0_result"], _final(m)
    c0, cl = _cells(r0["retrieval"]), _cells(rl["retrieval"])
    q, dets, n = rl["quantization"], _detector_evals(m), len(m["round_results"])
    lines = [
        f"The main job at commit `{_short(info['commit'])}` ({info['date']}, {info['machine']}, "
        f"{_minutes(info['wall_seconds'])}"
        + ("; how it ran: [docs/results.md](docs/results.md)" if info.get("note") else "")
        + "), held-out test split, detected boxes, beside the paper's CLEVR-veggie "
        "numbers. Retrieval is precision@10 under two protocols: **strict** = leave-one-out over one view of each "
        "test scene; **paper** = the gallery holds the same objects seen from a second view (the query's own object "
        "counts as a hit). Our pool is the test objects the detections matched (paper: about 1000).", "",
        "| measure (paper table) | paper | threedq |", "|---|---|---|",
        f"| retrieval precision@10, view-prediction features (Table 2, rgbocc) | {PAPER['table2']['rgbocc']:.2f} | "
        f"{_f(c0['strict'])} strict, {_f(c0['paper'])} paper protocol |",
        f"| retrieval precision@10 after {n} mining rounds (Table 2, ours) | {PAPER['table2']['ours']:.2f} | "
        f"{_f(cl['strict'])} strict, {_f(cl['paper'])} paper protocol (perfect features: {_f(cl['ceil_strict'])}, "
        f"{_f(cl['ceil_paper'])}) |",
        f"| unsupervised classification, K = 50 prototypes (Table 4, Hungarian accuracy) | "
        f"{PAPER['table4']['3DQ-Nets']:.2f} | {_f(q['threedq']['hungarian_acc'])} |",
        f"| few-shot labelling, 2 labelled objects per category (Table 1) | {PAPER['table1']['3DQ-Nets']:.2f} | "
        f"{_f(q['threedq']['fewshot_acc'])} |",
        f"| 3D detection mAP@0.5, warm start -> after the rounds (Table 5) | "
        f"{PAPER['table5']['2D triang-pretrain'][0]:.2f} -> {PAPER['table5']['2D triang-pretrain'][1]:.2f} | "
        f"{_f(dets[0]['detector']['map_50'])} -> {_f(dets[-1]['detector']['map_50'])} |", "",
        f"Every table, round by round: [docs/results.md](docs/results.md) (generated from "
        f"[docs/results/metrics.json](docs/results/metrics.json) by `{GENERATOR}`).",
    ]
    return "\n".join(lines)


def _table3_lines(m: dict[str, Any]) -> list[str]:
    p = PAPER["table3"]
    lines = ["| round | paper: features / quantization / detection | threedq: precision@10 strict / **paper** / "
             "same-object top-1 | pool (ceiling strict / paper) | threedq: Hungarian (K = 50) | threedq: mAP@0.5 |",
             "|---|---|---|---|---|---|"]
    for t in m["table3"]:
        i = t["round"]
        lines.append(f"| {i} | {_paper(p['features'], i)} / {_paper(p['quantization'], i)} / "
                     f"{_paper(p['detection'], i)} | {_f(t['precision_at_10'])} / "
                     f"**{_f(t.get('precision_at_10_paper'))}**"
                     f" / {_f(t.get('same_object_top1'))} | {t.get('pool', '-')} ({_f(t.get('ceiling_strict'))} / "
                     f"{_f(t.get('ceiling_paper'))}) | {_f(t['hungarian_acc'])} | {_f(t['map_50'])} |")
    return lines


def _per_round_lines(m: dict[str, Any]) -> list[str]:
    """Per round: features, clustering, pose, detection, and what its mining and self-labelling stages did."""
    rounds = [(0, m["round0_result"])] + list(enumerate(m["round_results"], 1))
    mining, sl = m.get("mining_results") or [], m.get("self_label_results") or []
    t3 = {t["round"]: t for t in m["table3"]}
    lines = ["| round | precision@10 strict | paper | same-object top-1 | Hungarian | few-shot | yaw median err. "
             "(deg) | mAP@0.5 | handed-on precision / recall | mined pairs (on two GT objects) | same category | mined "
             "yaw err. (deg) | self-label positives (true at IoU 0.5) | negatives (background) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for i, r in rounds:
        c = _cells(r["retrieval"])
        q = r["quantization"]["threedq"]
        t = t3.get(i, {})
        h = t.get("handed_on_test") or {}
        pairs = same = yaw = "-"
        if 1 <= i <= len(mining) and mining[i - 1]["refreshes"]:
            refs = mining[i - 1]["refreshes"]
            pairs = " + ".join(f"{f['pairs']} ({f['labelled_pairs']})" if "labelled_pairs" in f else str(f["pairs"])
                               for f in refs)
            same = " / ".join(_f(f["same_category"], 2) for f in refs)
            yaw = " / ".join(_f(f.get("yaw_median_err_deg"), 0) for f in refs)
        pos = neg = "-"
        if 1 <= i <= len(sl) and sl[i - 1].get("labels"):
            lab = sl[i - 1]["labels"]
            pos = f"{lab['positives']} ({_f(lab.get('positives_true_at_50'), 2)})"
            neg = f"{lab['negatives']} ({_f(lab.get('negatives_false_at_25'), 2)})"
        lines.append(f"| {i} | {_f(c['strict'])} | {_f(c['paper'])} | {_f(c['top1'])} | {_f(q['hungarian_acc'])} | "
                     f"{_f(q['fewshot_acc'])} | {_f(q['yaw_median_deg'], 1)} | {_f(t.get('map_50'))} | "
                     f"{_f(h.get('precision'))} / {_f(h.get('recall'))} | {pairs} | {same} | {yaw} | {pos} | {neg} |")
    return lines


#: The paper's name of each method in its Table 4.
PAPER_METHODS = {"threedq": "3DQ-Nets", "no_rot": "no-rot-3DQ", "pointcloud": "point-cloud registration",
                 "q25d": "2.5DQ-Nets"}
#: How the pages name the feature sets of a retrieval table (their order in Table 2).
FEATURES = {"learned": None, "raw_rgb_occupancy": "raw `cat[occ, occ * rgb]` crops, no learning",
            "random_encoder": "a randomly initialised encoder",
            "colour_size_descriptor": "six numbers: mean colour of the occupied voxels + sorted box extents "
                                      "(no learning)"}
NOT_IN_MAIN_JOB = "not in the main job: `threedq eval --weights` (an ImageNet weights file)"


def _table1_lines(m: dict[str, Any]) -> list[str]:
    q = _final(m)["quantization"]
    lines = ["| method | paper (CLEVR) | threedq |", "|---|---|---|"]
    for name, v in _methods(q):
        paper = PAPER["table1"]["3DQ-Nets"] if name == "threedq" else None
        lines.append(f"| {METHODS.get(name, name)} | {_f(paper, 2)} | {_f(v['fewshot_acc'])} |")
    lines += [f"| ResNetRet (ImageNet ResNet-18, nearest labelled object) | {PAPER['table1']['ResNetRet']:.2f} | "
              f"{NOT_IN_MAIN_JOB} |",
              f"| ResNetClass (ImageNet ResNet-18 + linear classifier) | {PAPER['table1']['ResNetClass']:.2f} | "
              f"{NOT_IN_MAIN_JOB} |"]
    return lines


def _table2_lines(m: dict[str, Any]) -> list[str]:
    r0, rl = m["round0_result"], _final(m)
    r = rl["retrieval"]
    prot = r.get("protocols", {})
    probe = (rl.get("probe") or {}).get("accuracy", {})
    lines = [f"Rotation-max precision@{r['k']}, {r['num_angles']} yaw steps, macro over categories, "
             f"{r.get('search', 'fast')} search. Pools and the precision perfect features would reach on them:"]
    for name, label in (("strict", "strict"), ("paper", "paper protocol")):
        if name in prot:
            lines.append(f"- {label}: {prot[name]['pool']} objects, ceiling {_f(prot[name].get('ceiling'))}.")
    if rl.get("probe"):
        lines.append("- linear probe: a logistic regression on the voxel-averaged frozen crops, trained with the "
                     f"labels of {rl['probe']['train_objects']} training objects (they train the probe only), "
                     f"accuracy on the {rl['probe']['test_objects']} test objects.")
    lines += ["", "| features | strict | paper protocol | same-object top-1 | linear probe |", "|---|---|---|---|---|"]
    c0 = _cells(r0["retrieval"])
    lines.append(f"| rgbocc: the view-prediction encoder, round 0 ({c0['pool']} objects, ceilings "
                 f"{_f(c0['ceil_strict'])} / {_f(c0['ceil_paper'])}) | {_f(c0['strict'])} | {_f(c0['paper'])} | "
                 f"{_f(c0['top1'])} | - |")
    for key, label in FEATURES.items():
        if key not in r["precision_at_k"]:
            continue
        c = _cells(r, key)
        label = label or f"ours: the encoder after {len(m['round_results'])} mining rounds"
        lines.append(f"| {label} | {_f(c['strict'])} | {_f(c['paper'])} | {_f(c['top1'])} | {_f(probe.get(key))} |")
    coarse = prot.get("paper", {}).get("coarse")
    if coarse:
        lines.append(f"| *coarse labels, not the headline*: ours, {coarse['num_classes']} classes (CLEVR primitives by "
                     f"shape only; ceiling {_f(coarse['ceiling'])}) | - | {_f(coarse['precision_at_k']['learned'])} | "
                     "- | - |")
    p = PAPER["table2"]
    lines += ["", f"Paper (CLEVR, its protocol, about 1000 objects): ResNet {p['ResNet']:.2f}, "
              f"rgbocc {p['rgbocc']:.2f}, rgbocc+VC {p['rgbocc+VC']:.2f}, rgbocc+VC* {p['rgbocc+VC*']:.2f}, "
              f"ours {p['ours']:.2f}. The ImageNet row "
              "needs its weights (`threedq eval --weights`); rgbocc+VC and rgbocc+VC* are `threedq eval --encoders` "
              "runs, not part of the main job."]
    return lines


def _table4_lines(m: dict[str, Any]) -> list[str]:
    q = _final(m)["quantization"]
    lines = ["| method | paper (CLEVR) | threedq: Hungarian acc. | yaw median err. (deg) | yaw acc. @10 deg |",
             "|---|---|---|---|---|"]
    for name, v in _methods(q):
        pv = PAPER["table4"].get(PAPER_METHODS.get(name, ""))
        lines.append(f"| {METHODS.get(name, name)} | {_f(pv, 2)} | {_f(v['hungarian_acc'])} | "
                     f"{_f(v.get('yaw_median_deg'), 1)} ({v.get('yaw_pairs', '-')} pairs) | "
                     f"{_f(v.get('yaw_acc_10'))} |")
    if "q25d" not in q:
        lines.append(f"| {METHODS['q25d']} | {PAPER['table4']['2.5DQ-Nets']:.2f} | not in the main job "
                     "(`threedq eval --q25d`) | | |")
    return lines


def _table5_lines(m: dict[str, Any]) -> list[str]:
    dets = _detector_evals(m)
    d0 = dets[0]
    p3, p2 = PAPER["table5"]["3D pretrain"], PAPER["table5"]["2D triang-pretrain"]
    lines = ["| boxes | paper (CLEVR): initial / final | threedq: mAP@0.25 | mAP@0.5 |", "|---|---|---|---|",
             f"| label-free pseudo-boxes (depth, ground plane, 3D components; every view) | - | "
             f"{_f(d0['pseudo_boxes']['map_25'])} | {_f(d0['pseudo_boxes']['map_50'])} |"]
    if d0.get("pseudo_boxes_single_view"):
        sv = d0["pseudo_boxes_single_view"]
        lines.append(f"| the same from only the view the detector sees (its fair reference) | - | {_f(sv['map_25'])} | "
                     f"{_f(sv['map_50'])} |")
    lines.append(f"| detector warm-started from the pseudo-boxes (paper: triangulated 2D proposals) | "
                 f"{p2[0]:.2f} / {p2[1]:.2f} | {_f(d0['detector']['map_25'])} | {_f(d0['detector']['map_50'])} |")
    for i, d in enumerate(dets[1:], 1):
        lines.append(f"| after round {i}'s self-labelling | | {_f(d['detector']['map_25'])} | "
                     f"{_f(d['detector']['map_50'])} |")
    lines += ["", f"The paper's other warm start, from GT 3D boxes of the training set: {p3[0]:.2f} / {p3[1]:.2f} "
              "(threedq: `threedq em --boxes gt` and `stages/detector_gt.yaml`, not part of the main job)."]
    return lines


def _by_size_lines(m: dict[str, Any]) -> list[str]:
    """Objects found per size band: the pseudo-boxes and the warm-start detector, then the last round's detector."""
    dets = _detector_evals(m)
    tables = [(t["boxes"], t["rows"]) for t in dets[0].get("by_size") or []]
    if len(dets) > 1:
        tables += [(f"{t['boxes']}, after round {len(dets) - 1}", t["rows"]) for t in dets[-1].get("by_size") or []
                   if t["boxes"].startswith("detector")]
    if not tables:
        return ["Not in this run's metrics.json."]
    first = tables[0][1]
    lines = ["| boxes | " + " | ".join(f"{r['band']} ({r['objects']})" for r in first) + " |",
             "|---|" + "---|" * len(first)]
    for name, rows in tables:
        lines.append(f"| {name} | " + " | ".join(size_band_cells(rows)) + " |")
    flat = dets[0].get("flat_objects")
    if flat and flat["of"]:
        lines += ["", f"{flat['objects']} of {flat['of']} test objects are less tall than "
                  f"{flat['min_box_height']:.3f} m "
                  "(the \"flat\" band), the detector's `min_box_height`: it is not trained on them; "
                  + ("the input view's observed boxes stand in for them in the mAP (`flat_boxes`)."
                     if flat["flat_boxes"] else "they are not detected (`flat_boxes` off).")]
    return lines


def _timing_lines(m: dict[str, Any], info: dict[str, Any]) -> list[str]:
    rows: list[tuple[str, float]] = [("view prediction (training)", m["viewpred"]["seconds"]),
                                     ("view prediction evaluation", m["viewpred_eval"]["seconds"])]
    if m.get("detector"):
        rows += [("detector warm start (training)", m["detector"]["seconds"]),
                 ("detector evaluation", m["detector_eval"]["seconds"])]
    if m.get("round0_result"):
        rows.append(("round 0 evaluation", m["round0_result"]["seconds"]))
    mining, sl = m.get("mining_results") or [], m.get("self_label_results") or []
    for i, r in enumerate(m["round_results"], 1):
        if i <= len(mining):
            rows.append((f"round {i} mining", mining[i - 1]["seconds"]))
        rows.append((f"round {i} evaluation", r["seconds"]))
        if i <= len(sl):
            rows += [(f"round {i} self-labelling", sl[i - 1]["seconds"]),
                     (f"round {i} detector evaluation", sl[i - 1]["detector_eval"]["seconds"])]
    total = sum(s for _, s in rows)
    lines = ["| stage | seconds |", "|---|---|", *(f"| {name} | {s:.0f} |" for name, s in rows)]
    lines.append(f"| the rest: the quantizers of rounds 0-{len(m['round_results'])}, start-up, data generation on "
                 f"a first run, loading | {info['wall_seconds'] - total:.0f} |")
    lines.append(f"| **the whole job** | **{info['wall_seconds']:.0f}** |")
    return lines


def results_page(m: dict[str, Any], info: dict[str, Any], root: str | Path = ROOT) -> str:
    """``docs/results.md``: today's numbers of the main job, whole (the presets' table from the rows under ``root``)."""
    rl, n = _final(m), len(m["round_results"])
    lines = [
        "# Results of the main job", "",
        f"<!-- generated by `{GENERATOR}` from docs/results/metrics.json and docs/results/run.json: do not edit by "
        "hand -->", "",
        f"Today's numbers, all from one run: {_run_line(info)}."
        + (f" {info['note']}" if info.get("note") else "")
        + " The run's `metrics.json` is committed as "
        "[results/metrics.json](results/metrics.json), when and where it ran as [results/run.json](results/run.json); "
        "after a rerun of the main job `python -m threedq.pipeline.results_pages --run runs/em` records it and "
        "rewrites this page, the README's table and the generated tables of [fidelity.md](fidelity.md).", "",
        f"Data: the embedded CLEVR-veggie-like set (`{m.get('data_config', 'data/clevr_veggie.yaml')}`), held-out test "
        f"split, one input view per scene, {rl['num_test_categories']} categories; the rounds run on the boxes the "
        f"detector hands on ({'detected' if m.get('boxes') == 'detections' else 'GT'} boxes), and the label-based "
        f"metrics score the test objects those boxes matched at IoU 0.5 ({rl['num_test_objects']} in round {n}). "
        f"K = {rl['num_prototypes']} prototypes, 36 yaw steps. Machine: {info['machine']}; "
        f"frozen-encoder stages in {m.get('frozen_precision')}, mining in {m.get('mining_precision')}.", "",
        "Retrieval protocols: **strict** = leave-one-out over one view of each test scene (a query never retrieves "
        "itself); **paper** = the queries are the objects seen from one view, the gallery the same objects from a "
        "second view of their scene, and the query's own object there counts as a hit. Each comes with its pool and "
        "the precision@10 perfect features would reach on it (the ceiling): numbers of different pools are not "
        "comparable. [fidelity.md](fidelity.md) sets these numbers beside the paper's and lists every departure; "
        "[studies/README.md](studies/README.md) holds the studies that chose today's defaults.", "",
        "## Table 3: every module per EM round", "",
        "Round 0 is the paper's iteration 0: the warm-start detector, and the view-prediction encoder's features and a "
        "bank fitted on them, on the boxes round 1 takes. A round's detection is its detector after its "
        "self-labelling. The paper's columns are its iterations 0-3.", "", *_table3_lines(m), "",
        "### Per round: features, clusters, pose, detection, and what mining and self-labelling did", "",
        "Mining: pairs of each pool refresh (in brackets those on two GT objects), the share of those of one "
        "category and the median yaw error of their implied relative pose (labels measure, never train). "
        "Self-labelling: the boxes the prototypes made positives (share true at IoU 0.5; the label-free pseudo-boxes "
        "are trained as positives too) and the negatives (share on no object at IoU 0.25). Handed-on boxes: the "
        "detector's boxes above 0.9 objectness, the next round's boxes, against the test objects at IoU 0.5.", "",
        *_per_round_lines(m), "",
        f"## Table 1: few-shot labelling, 2 labelled objects per category (round {n})", "", *_table1_lines(m), "",
        f"## Table 2: retrieval (round {n})", "", *_table2_lines(m), "",
        f"## Table 4: unsupervised classification, K = {rl['num_prototypes']} prototypes, and pose (round {n})", "",
        rl.get("cluster_search", ""), "", *_table4_lines(m), "",
        "## Table 5: 3D detection (dataset-level mAP, axis-aligned IoU, "
        f"{m['detector_eval']['detector']['num_gt']} test objects)", "", *_table5_lines(m), "",
        "## Detection by object size", "",
        "Largest extent of each GT box; share found at IoU 0.25 / 0.5; median centre error of the best box in the "
        "plane / in height (metres).", "", *_by_size_lines(m), "",
        f"## View prediction on held-out scenes ({m['viewpred_eval']['view_prediction']['num_scenes']} scenes)", "",
        *viewpred_lines(m["viewpred_eval"]["view_prediction"]), "", *_preset_lines(root), "## Time of each stage", "",
        f"From the run's records (`stage.json`, each evaluation's `seconds`); the whole job ran from "
        f"{info['started']} to {info['ended']}.", "", *_timing_lines(m, info), ""]
    return "\n".join(lines)


def _preset_lines(root: str | Path) -> list[str]:
    """The section on the data configs' stage presets (:mod:`threedq.pipeline.presets`), where the rows are here."""
    table = preset_results_markdown(root)
    if not table:
        return []
    return ["## Stage presets: which miner serves which kind of data", "",
            "`threedq em --data_config X` mines with X's preset: the embedded data (shape and colour name its "
            "categories) `stages/mining.yaml`, the shape-only data and scene folders of one's own "
            "`stages/mining_occupancy_pairs.yaml` (objects of one kind come in many colours). Round 4 of `threedq em "
            "--rounds 4` from each data set's round 0, mean (range) over 2 seeds: retrieval comes from the encoders, "
            "the clustering from the bank each round fits (the warm-started rows are the only embedded run of the "
            "occupancy preset). How they ran: [studies/mined-pairs.md](studies/mined-pairs.md).", "", table, ""]


def fidelity_blocks(m: dict[str, Any], info: dict[str, Any]) -> dict[str, str]:
    """The generated blocks of ``docs/fidelity.md``: the run it is measured on, Table 3, Tables 1/2/4, Table 5."""
    rl, n, t3 = _final(m), len(m["round_results"]), m["table3"]
    q, r = rl["quantization"], rl["retrieval"]
    cl = _cells(r)
    rows = {k: _cells(r, k) for k in r["precision_at_k"]}
    probe = (rl.get("probe") or {}).get("accuracy", {})
    coarse = r.get("protocols", {}).get("paper", {}).get("coarse")
    dets = _detector_evals(m)
    per_round = ", ".join(f"round {t['round']} {t['pool']}" for t in t3)
    run = _run_line(info) + "." + (f" {info['note']}" if info.get("note") else "")
    gt = max(d["detector"]["num_gt"] for d in dets)
    pool_sizes = sorted({t["pool"] for t in t3})
    pools = (f"Today's main job scores the objects of the embedded test split ({gt} GT objects, "
             f"{rl['num_test_categories']} categories) that the round's detections match at IoU 0.5: "
             f"{pool_sizes[0]}-{pool_sizes[-1]} objects per round; perfect features would reach "
             f"{_f(min(t['ceiling_strict'] for t in t3))}-{_f(max(t['ceiling_strict'] for t in t3))} strict and "
             f"{_f(min(t['ceiling_paper'] for t in t3))}-{_f(max(t['ceiling_paper'] for t in t3))} paper protocol "
             "on those pools.")
    table3 = "\n".join([
        f"Features: precision@10 over the test objects the round's boxes matched ({per_round}), fast search.", "",
        *_table3_lines(m), "",
        f"Over the rounds: features {_f(t3[0]['precision_at_10_paper'])} -> {_f(t3[-1]['precision_at_10_paper'])} "
        f"(paper protocol; paper {PAPER['table3']['features'][0]:.2f} -> {PAPER['table3']['features'][-1]:.2f}), "
        f"same-object top-1 {_f(t3[0]['same_object_top1'])} -> {_f(t3[-1]['same_object_top1'])}, Hungarian "
        f"{_f(t3[0]['hungarian_acc'])} -> {_f(t3[-1]['hungarian_acc'])} (paper {PAPER['table3']['quantization'][0]:.2f}"
        f" -> {PAPER['table3']['quantization'][-1]:.2f}), detection {_f(t3[0]['map_50'])} -> {_f(t3[-1]['map_50'])} "
        f"(paper {PAPER['table3']['detection'][0]:.2f} -> {PAPER['table3']['detection'][-1]:.2f}).",
    ])
    p1, p2, p4 = PAPER["table1"], PAPER["table2"], PAPER["table4"]
    c0 = _cells(m["round0_result"]["retrieval"])
    tables124 = "\n".join([
        f"| table | paper (CLEVR) | threedq, round {n} ({rl['num_test_objects']} matched test objects) |",
        "|---|---|---|",
        f"| 1: few-shot accuracy, 2 labelled objects per category | 3DQ-Nets {p1['3DQ-Nets']:.2f}, ResNetRet "
        f"{p1['ResNetRet']:.2f}, ResNetClass {p1['ResNetClass']:.2f} | {_f(q['threedq']['fewshot_acc'])} (ResNet rows "
        "need ImageNet weights: `threedq eval --weights`) |",
        f"| 2: retrieval precision@10, ours | {p2['ours']:.2f} | {_f(cl['strict'])} strict, {_f(cl['paper'])} paper "
        f"protocol (ceilings {_f(cl['ceil_strict'])} / {_f(cl['ceil_paper'])}) |",
        f"| 2: rgbocc (view prediction) | {p2['rgbocc']:.2f} | round 0: {_f(c0['strict'])} / {_f(c0['paper'])} (on "
        f"{c0['pool']} objects, ceilings {_f(c0['ceil_strict'])} / {_f(c0['ceil_paper'])}) |",
        f"| 4: Hungarian accuracy, K = 50: 3DQ-Nets | {p4['3DQ-Nets']:.2f} | {_f(q['threedq']['hungarian_acc'])} |",
        *([f"| 4: no-rot-3DQ | {p4['no-rot-3DQ']:.2f} | {_f(q['no_rot']['hungarian_acc'])} |"]
          if "no_rot" in q else []),
        *([f"| 4: point-cloud registration | {p4['point-cloud registration']:.2f} | "
           f"{_f(q['pointcloud']['hungarian_acc'])} |"] if "pointcloud" in q else []),
        f"| 4: 2.5DQ-Nets | {p4['2.5DQ-Nets']:.2f} | opt-in (`threedq eval --q25d`), measured in "
        "[studies/baselines-2d.md](studies/baselines-2d.md) |", "",
        "References of the final round's Table 2 (same pool; strict / paper protocol, same-object top-1, linear "
        "probe): " + "; ".join(
            f"{label} {_f(rows[k]['strict'])} / {_f(rows[k]['paper'])}, {_f(rows[k]['top1'])}"
            + (f", probe {_f(probe[k])}" if k in probe else "")
            for k, label in (("raw_rgb_occupancy", "raw `cat[occ, occ * rgb]` crops"),
                             ("random_encoder", "random encoder"),
                             ("colour_size_descriptor", "the six-number colour + size descriptor")) if k in rows)
        + (f"; the learned features' linear probe {_f(probe['learned'])}" if "learned" in probe else "") + "."
        + (f" Coarse labels (marked, not the headline: CLEVR primitives by shape, {coarse['num_classes']} classes "
           f"present): {_f(coarse['precision_at_k']['learned'])}, ceiling {_f(coarse['ceiling'])}." if coarse else ""),
    ])
    pt = PAPER["table5"]
    table5 = "\n".join([
        "| | paper (CLEVR) | threedq (the main job) |", "|---|---|---|",
        f"| detector warm-started from GT 3D boxes of the training set: initial / final | {pt['3D pretrain'][0]:.2f} / "
        f"{pt['3D pretrain'][1]:.2f} | not in the main job (`threedq em --boxes gt`, `stages/detector_gt.yaml`; "
        "measured in [studies/detector.md](studies/detector.md)) |",
        "| warm-started from label-free proposals (paper: triangulated 2D detections; threedq: depth + ground plane + "
        f"3D components): initial / final | {pt['2D triang-pretrain'][0]:.2f} / {pt['2D triang-pretrain'][1]:.2f} | "
        f"{_f(dets[0]['detector']['map_50'])} / {_f(dets[-1]['detector']['map_50'])} |",
    ])
    return {"fidelity-run": run, "fidelity-pools": pools, "fidelity-table3": table3, "fidelity-tables124": tables124,
            "fidelity-table5": table5}


def fidelity_gt_block(doc: dict[str, Any]) -> str:
    """fidelity.md's Table 2 on GT boxes, from ``docs/results/fidelity_gt.json``: the ``table2.json`` of
    ``threedq eval --encoders`` on the test split (``gt``) and on the paper-size pool (``pool``), with how they ran."""
    gt, pool = doc["gt"], doc.get("pool")
    n, m = gt["num_test_objects"], (pool or {}).get("num_test_objects")
    head = (f"| features | {n}: strict | {n}: **paper** | {n}: same-object top-1 | {n}: linear probe | "
            f"{n}: Hungarian, K = {gt['K']} |")
    sep = "|---|---|---|---|---|---|"
    if pool:
        head += f" {m}: strict | {m}: **paper** | {m}: same-object top-1 |"
        sep += "---|---|---|"
    lines = [f"Measured {doc['date']} at commit `{_short(doc['commit'])}` on {doc['machine']}, on the encoders of the "
             f"main job recorded in [results/run.json](results/run.json); commands: "
             + "; ".join(f"`{c}`" for c in doc["commands"]) + ".", "", head, sep]
    for name, r in gt["rows"].items():
        q = (pool or {}).get("rows", {}).get(name, {})
        row = (f"| {name} | {_f(r.get('precision_at_10'))} | {_f(r.get('precision_at_10_paper'))} | "
               f"{_f(r.get('same_object_top1'))} | {_f(r.get('probe_acc'))} | {_f(r.get('hungarian_acc'))} |")
        if pool:
            row += (f" {_f(q.get('precision_at_10'))} | {_f(q.get('precision_at_10_paper'))} | "
                    f"{_f(q.get('same_object_top1'))} |")
        lines.append(row)
    p2, p4 = PAPER["table2"], PAPER["table4"]
    paper = f"{p2['rgbocc']:.2f} / {p2['ours']:.2f}"
    lines.append(f"| **paper** (CLEVR, its protocol and pool): rgbocc / ours | | {paper} | | | "
                 f"3DQ-Nets {p4['3DQ-Nets']:.2f} (Table 4) |" + (f" | {paper} | |" if pool else ""))
    ceil = "; ".join(f"{d['num_test_objects']} objects: " + " / ".join(
        f"{_f(v)} {k}" for k, v in d.get("ceilings", {}).items()) for d in (gt, pool) if d)
    lines += ["", f"Perfect features would score {ceil}."]
    if doc.get("not_run"):
        lines += ["", f"Not re-run with these encoders: {doc['not_run']}."]
    return "\n".join(lines)


def _markers(name: str) -> tuple[str, str]:
    return (f"<!-- generated:{name} begin ({GENERATOR}; do not edit by hand) -->", f"<!-- generated:{name} end -->")


def replace_block(text: str, name: str, content: str) -> str:
    """``text`` with what lies between the markers of block ``name`` replaced by ``content``.

    Raises:
        ValueError: the markers are missing or out of order.
    """
    begin, end = _markers(name)
    pattern = re.compile(re.escape(begin) + r"\n.*?" + re.escape(end), flags=re.S)
    if len(pattern.findall(text)) != 1:
        raise ValueError(f"block '{name}': expected one '{begin}' ... '{end}' pair")
    return pattern.sub(lambda _: f"{begin}\n{content}\n{end}", text)


def load_results(folder: str | Path = ROOT / RESULTS_DIR) -> tuple[dict[str, Any], dict[str, Any]]:
    """The committed ``metrics.json`` and ``run.json`` of the main job."""
    folder = Path(folder)
    return (json.loads((folder / "metrics.json").read_text()), json.loads((folder / "run.json").read_text()))


NOT_RECORDED = (f"No run of the main job is recorded yet: run `{MAIN_JOB}`, then `{GENERATOR} --run runs/em`, which "
                "commits its numbers here. No number is shown until then.")


def readme_picture(info: dict[str, Any]) -> str:
    """The README's picture (``docs/img/overview.png``, drawn by :func:`overview_figure` from the recorded run)."""
    return "\n".join([
        f"![A test scene, its detections and the prototypes they fall into]({OVERVIEW})", "",
        f"*From the main job's own outputs (commit `{_short(info['commit'])}`): a held-out scene with the boxes of the "
        "last round, each labelled with the prototype it falls into; on the right, other test objects the same "
        f"prototype holds. No label was used to make them; `{GENERATOR} --run runs/em` draws it from a run folder.*"])


def empty_pages() -> tuple[str, dict[str, str], dict[str, str]]:
    """The pages when no main job is recorded: ``docs/results.md``, the README's block, the fidelity blocks. They say
    so, and how to record one; they show no number."""
    page = "\n".join(["# Results of the main job", "",
                      f"<!-- generated by `{GENERATOR}` from docs/results/: do not edit by hand -->", "",
                      NOT_RECORDED, "", "Earlier measurements, each with its commit and date: "
                      "[studies/README.md](studies/README.md).", ""])
    readme = {"readme-results": NOT_RECORDED, "readme-picture": ""}
    fidelity = {name: NOT_RECORDED for name in ("fidelity-run", "fidelity-pools", "fidelity-table3",
                                                  "fidelity-tables124", "fidelity-table5")}
    return page, readme, fidelity


def expected_pages(root: str | Path = ROOT) -> dict[Path, str]:
    """Every generated page, as this module writes it from the committed files: ``{path: text}``."""
    root = Path(root)
    if (root / RESULTS_DIR / "metrics.json").is_file():
        m, info = load_results(root / RESULTS_DIR)
        page, fidelity = results_page(m, info, root), fidelity_blocks(m, info)
        if (root / RESULTS_DIR / "fidelity_gt.json").is_file():
            gt_doc = json.loads((root / RESULTS_DIR / "fidelity_gt.json").read_text())
            fidelity["fidelity-gt"] = fidelity_gt_block(gt_doc)
        readme = {"readme-results": readme_table(m, info),
                  "readme-picture": readme_picture(info) if (root / OVERVIEW).is_file() else ""}
    else:
        page, readme, fidelity = empty_pages()
    pages = {root / "docs/results.md": page}
    blocks: dict[Path, dict[str, str]] = {root / "README.md": readme, root / "docs/fidelity.md": fidelity}
    for path, named in blocks.items():
        text = path.read_text(encoding="utf-8")
        for name, content in named.items():
            text = replace_block(text, name, content)
        pages[path] = text
    return pages


def write_pages(root: str | Path = ROOT) -> list[Path]:
    """Write every generated page; returns those that changed."""
    changed = []
    for path, text in expected_pages(root).items():
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            path.write_text(text, encoding="utf-8")
            changed.append(path)
    return changed


def parse_time_log(path: str | Path) -> dict[str, float]:
    """Wall-clock seconds and peak resident memory (GiB) from the output of ``/usr/bin/time -v``."""
    out: dict[str, float] = {}
    for line in Path(path).read_text().splitlines():
        line = line.strip()
        if line.startswith("Elapsed (wall clock) time"):
            parts = [float(p) for p in line.rsplit(": ", 1)[1].split(":")]
            out["wall_seconds"] = sum(p * 60 ** i for i, p in enumerate(reversed(parts)))
        elif line.startswith("Maximum resident set size (kbytes)"):
            out["peak_rss_gib"] = int(line.rsplit(": ", 1)[1]) / 2**20
    return out


def _iso(t: str) -> dt.datetime:
    return dt.datetime.fromisoformat(t.replace("Z", "+00:00"))


def record_run(run: str | Path, root: str | Path = ROOT, commit: str | None = None, started: str | None = None,
               ended: str | None = None, time_log: str | list[str] | None = None,
               timed: str = "threedq em --rounds 4", note: str | None = None) -> dict[str, Any]:
    """Copy ``run/metrics.json`` to ``docs/results/`` and write ``run.json`` beside it; returns the latter.

    ``commit``: default the checkout's ``HEAD``; ``started``: default the run's lock file's time; ``ended``: default
    when ``metrics.json`` was written; ``time_log``: ``/usr/bin/time -v`` output(s) (wall times added, the largest
    peak memory; else ``ended - started``); ``note``: how the run was made, if not by the plain command (shown).
    """
    run, root = Path(run), Path(root)
    metrics = json.loads((run / "metrics.json").read_text())
    if not metrics.get("round_results"):
        raise ValueError(f"{run / 'metrics.json'}: field 'round_results': no EM round, not a main job's run")
    if commit is None:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                                check=True).stdout.strip()
    if started is None:
        started = json.loads((run / ".threedq-run.lock").read_text())["since"]
    if ended is None:
        ended = dt.datetime.fromtimestamp((run / "metrics.json").stat().st_mtime, dt.timezone.utc).isoformat()
    started_t, ended_t = _iso(started), _iso(ended)
    logs = [parse_time_log(t) for t in ([time_log] if isinstance(time_log, (str, Path)) else time_log or [])]
    timing = {k: (sum if k == "wall_seconds" else max)(t[k] for t in logs if k in t)
              for k in ("wall_seconds", "peak_rss_gib") if any(k in t for t in logs)}
    threads = re.search(r"(\d+) threads", metrics.get("machine", ""))
    info = {"command": MAIN_JOB, "timed": timed, "commit": commit, "date": started_t.date().isoformat(),
            "started": started_t.strftime("%Y-%m-%dT%H:%M:%SZ"), "ended": ended_t.strftime("%Y-%m-%dT%H:%M:%SZ"),
            "wall_seconds": round(timing.get("wall_seconds", (ended_t - started_t).total_seconds()), 1),
            "peak_rss_gib": round(timing["peak_rss_gib"], 2) if "peak_rss_gib" in timing else None,
            "machine": f"{cpu_name()}, {threads.group(1) if threads else '?'} threads, torch {metrics.get('torch')}",
            "cpu_flags": cpu_flags(),
            "data_sha256": data_fingerprint(d) if (d := _run_data_dir(run)) is not None else None}
    if note:
        info["note"] = note
    dest = root / RESULTS_DIR
    dest.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(run / "metrics.json", dest / "metrics.json")
    (dest / "run.json").write_text(json.dumps(info, indent=1) + "\n")
    return info


def overview_figure(run: str | Path, out: str | Path, data_dir: str | Path | None = None, members: int = 5) -> Path:
    """The README's picture from a finished ``threedq em`` run: one test scene's input view with the final round's
    boxes, each labelled with its prototype, and beside each box other test objects of that prototype (read from
    ``<run>/rNN_eval/objects_test.json`` and the scenes; drawn by :mod:`threedq.viz.overview`)."""
    from threedq.datamodules.scene_folder import fixed_views
    from threedq.scene import load_index, load_scene
    from threedq.viz.overview import box_tile, prototype_overview
    from threedq.viz.png import rgb_png, write_png

    run = Path(run)
    evals = sorted(p for p in run.glob("r[0-9][0-9]_eval") if (p / "objects_test.json").is_file())
    if not evals:
        raise FileNotFoundError(f"{run}: no finished round evaluation (rNN_eval/objects_test.json)")
    ev = evals[-1]
    objects = json.loads((ev / "objects_test.json").read_text())["objects"]
    cfg = yaml.safe_load((ev / "config.yaml").read_text()) if (ev / "config.yaml").is_file() else {}
    init = ((cfg or {}).get("data") or {}).get("init_args") or {}
    data = Path(data_dir or init.get("data_dir") or "data/clevr_veggie")
    if not data.is_absolute() and not (data / "index.json").is_file():
        data = run.resolve().parents[1] / data  # relative to where the run was started (runs/em -> .)
    seed, need = int(init.get("seed", 0) or 0), int(init.get("num_input_views", 1) or 1)
    files = load_index(data).files("test")
    by_proto: dict[int, list[dict[str, Any]]] = {}
    by_scene: dict[str, list[dict[str, Any]]] = {}
    for o in objects:
        by_proto.setdefault(o["prototype"], []).append(o)
        by_scene.setdefault(o["scene"], []).append(o)

    def score(scene: str) -> tuple[int, int]:  # most objects in distinct prototypes, then most other members to show
        objs = by_scene.get(scene, [])
        protos = {o["prototype"] for o in objs}
        return (len(protos) if len(protos) == len(objs) else 0, sum(min(members, len(by_proto[k]) - 1) for k in protos))

    scene = max(files, key=score)  # the first such scene in test order

    def view(file: str) -> tuple[Any, Any, Any]:
        rec = load_scene(data / file)
        v = int(fixed_views(seed, files.index(file), rec.rgb.shape[0], need)[0])  # the evaluation's input view
        return rec.rgb[v], rec.K[v], rec.world_T_cam[v]

    objs = sorted(by_scene[scene], key=lambda o: o["prototype"])
    rows = []
    for o in objs:
        others = [x for x in by_proto[o["prototype"]] if not (x["scene"] == o["scene"] and x["box"] == o["box"])]
        others = sorted(others, key=lambda x: -x["similarity"])[:members]
        tiles = [box_tile(*view(x["scene"]), x["box"]) for x in others]
        rows.append((o["prototype"], len(by_proto[o["prototype"]]), tiles))
    rnd = int(ev.name[1:3])
    img = prototype_overview(*view(scene), [o["box"] for o in objs], rows,
                             title=f"A test scene ({Path(scene).stem}), the boxes of round {rnd} and the prototypes "
                                   "they fall into (no label used)")
    return write_png(out, rgb_png(img))


def main(argv: list[str] | None = None) -> int:
    """``python -m threedq.pipeline.results_pages``: record a run (``--run``), then write the pages."""
    ap = argparse.ArgumentParser(prog=GENERATOR, description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", help="a finished main job's folder (runs/em): copy its metrics.json to docs/results/, "
                                  "write docs/results/run.json and draw docs/img/overview.png, then the pages")
    ap.add_argument("--commit", help="the commit the run ran (default: HEAD)")
    ap.add_argument("--started", help="ISO time the run started (default: its lock file's)")
    ap.add_argument("--ended", help="ISO time the run ended (default: when metrics.json was written)")
    ap.add_argument("--time_log", action="append", help="the run's /usr/bin/time -v output (wall time, peak "
                    "memory); once per part of a resumed run")
    ap.add_argument("--note", help="how the run was made, if not by the plain command in this checkout")
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 if a generated page is stale")
    args = ap.parse_args(argv)
    if args.run and args.check:
        ap.error("--check writes nothing: give it without --run")
    if args.run:
        info = record_run(args.run, commit=args.commit, started=args.started, ended=args.ended, time_log=args.time_log,
                          note=args.note)
        print(f"recorded {args.run}: commit {_short(info['commit'])}, {_minutes(info['wall_seconds'])}")
        print(f"wrote {overview_figure(args.run, ROOT / OVERVIEW)}")
    if args.check:
        stale = [p for p, text in expected_pages().items() if p.read_text(encoding="utf-8") != text]
        for p in stale:
            print(f"{p.relative_to(ROOT)}: stale; run {GENERATOR}", file=sys.stderr)
        return 1 if stale else 0
    for p in write_pages():
        print(f"wrote {p.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
