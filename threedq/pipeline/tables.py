"""Every markdown table threedq writes: the ``threedq em`` report (``report.md``), the ``threedq eval`` report
(``results.md``), paper Table 2 (retrieval), the feature-set table (``table2.md``), and the cells and labels they share.
"""

from __future__ import annotations

import math
from typing import Any

from threedq.metrics.retrieval import PROTOCOL_LABELS
from threedq.pipeline.baselines2d import Q25D_HOWTO, RESNET_HOWTO
from threedq.pipeline.evaluation import DESCRIPTOR, SEARCH_LABELS

__all__ = ["METHOD_LABELS", "RETRIEVAL_ROWS", "cluster_search_label", "em_markdown", "eval_markdown",
           "feature_cells", "feature_sets_markdown", "fewshot_cell", "fmt", "method_rows", "precision_label",
           "retrieval_markdown", "size_band_lines"]


METHOD_LABELS = {"threedq": "threedq (rotation-aware 3D prototypes)", "no_rot": "no-rot-3DQ (no rotation search)",
                 "pointcloud": "point-cloud registration",
                 "q25d": "2.5DQ-Nets (2D prototypes, in-plane rotation search)"}


def method_rows(quantization: dict[str, Any]) -> list[tuple[str, Any]]:
    """``quantization``'s (method, result) pairs in the tables' order (:data:`METHOD_LABELS`, then by name)."""
    order = list(METHOD_LABELS)
    return sorted(quantization.items(), key=lambda kv: (order.index(kv[0]) if kv[0] in order else len(order), kv[0]))


def cluster_search_label(method: str = "fast", occupancy_floor: float | None = None) -> str:
    """How each clustering row searches rotations: the stage's bank (threedq) with ``method``, on crops weighted by
    ``occupancy_floor`` (None: plain crops); the banks fitted here with the fast search."""
    own = ("exact search over 36 yaw steps (cosine over the full cube)" if method == "exact"
           else "fast search over 36 yaw steps (cosine over the inscribed cylinder)")
    if occupancy_floor is not None:
        own += (f", of crops weighted by their input occupancy (empty space {occupancy_floor:g}, voxels at or next to "
                f"observed surface {1 + occupancy_floor:g}; not the paper's plain crops)")
    return (f"Prototype assignment: threedq by the {own}; no-rot-3DQ by the same bank EM with 1 yaw step (no search); "
            "2.5DQ-Nets by the fast search on one-slice crops, i.e. over 36 in-plane angles (cosine over the inscribed "
            "disc); point-cloud registration by its occupancy-only similarity over 36 yaw steps.")


def precision_label(retrieval: dict[str, Any]) -> str:
    """``precision@k`` of a :func:`~threedq.pipeline.evaluation.retrieval_table`, saying so when k was lowered."""
    k, asked = retrieval["k"], retrieval.get("k_requested", retrieval["k"])
    if k < asked:
        return f"precision@{k} (k lowered from {asked}: {retrieval['num_objects']} test objects)"
    return f"precision@{k}"


def fewshot_cell(value: float | None, shots: int = 2) -> str:
    """A few-shot accuracy for a table: ``n/a`` with the reason when it is undefined (NaN or None)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return f"n/a (no category has more than {shots} objects: all are labelled shots)"
    return f"{value:.3f}"


def yaw_cell(v: dict[str, Any]) -> str:
    """A median relative yaw error for a table, with the number of pairs it is the median of when known."""
    pairs = v.get("yaw_pairs")
    return f"{v['yaw_median_deg']:.1f}" + (f" ({int(pairs)} pairs)" if pairs is not None else "")


#: Row names of the retrieval table.
RETRIEVAL_ROWS = {
    "learned": "threedq learned features",
    "raw_rgb_occupancy": "(a) raw RGB + occupancy crops, no learning",
    "random_encoder": "(b) randomly initialised encoder",
    DESCRIPTOR: "(c) six numbers: mean colour of the occupied voxels + sorted box extents (no learning)",
}


def retrieval_markdown(r: dict[str, Any], probe: dict[str, Any] | None = None, learned: str | None = None,
                       extra_rows: list[str] | None = None) -> list[str]:
    """Paper Table 2 as markdown lines: each feature set under both protocols, the same-object top-1 rate and the
    linear probe, with each column's protocol, pool, search and perfect-feature ceiling."""
    pk = precision_label(r)
    prot = r.get("protocols") or {"strict": {"pool": r["num_objects"], "precision_at_k": r["precision_at_k"]}}
    st, pa = prot.get("strict", {}), prot.get("paper")
    lines = [f"Rotation-max {pk}, {r['num_angles']} yaw steps, macro over categories; {SEARCH_LABELS[r['search']]}.",
             ""]
    for name in ("strict", "paper"):
        if name in prot:
            c = prot[name]
            ceiling = f"; perfect features would score {c['ceiling']:.3f} on this pool" if "ceiling" in c else ""
            gallery = f" (gallery: {c['gallery']})" if c.get("gallery") else ""
            lines.append(f"- **{name}**: {PROTOCOL_LABELS[name]}{gallery}; pool {c['pool']} objects{ceiling}.")
    if probe:
        lines.append(f"- **linear probe**: a logistic regression on the voxel-averaged frozen crops, trained with the "
                     f"labels of {probe['train_objects']} training objects (the labels train the probe only), "
                     f"accuracy on the {probe['test_objects']} test objects.")
    lines.append("")
    head = f"| features | {pk}, strict |"
    sep = "|---|---|"
    if pa:
        head += f" {pk}, paper | same object nearest (paper, top-1) |"
        sep += "---|---|"
    if probe:
        head += " linear probe acc. |"
        sep += "---|"
    lines += [head, sep]
    names = dict(RETRIEVAL_ROWS)
    if learned:
        names["learned"] = learned
    for key, label in names.items():
        if key not in st.get("precision_at_k", {}):
            continue
        row = f"| {label} | {st['precision_at_k'][key]:.3f} |"
        if pa:
            p = pa["precision_at_k"].get(key)
            t = pa.get("same_object_top1", {}).get(key)
            row += f" {'-' if p is None else f'{p:.3f}'} | {'-' if t is None else f'{t:.3f}'} |"
        if probe:
            a = probe["accuracy"].get(key)
            row += f" {'-' if a is None else f'{a:.3f}'} |"
        lines.append(row)
    if pa and pa.get("coarse"):
        c = pa["coarse"]
        row = (f"| *coarse labels, not the headline*: learned, {c['num_classes']} classes (CLEVR primitives by shape "
               f"only; ceiling {c['ceiling']:.3f}) | - | {c['precision_at_k']['learned']:.3f} | - |")
        lines.append(row + (" - |" if probe else ""))
    lines += extra_rows or []
    return lines


def eval_markdown(res: dict[str, Any]) -> str:
    r = res["retrieval"]
    lines = ["# threedq evaluation", "",
             f"Held-out split `{res['split']}`: {res['num_test_objects']} objects in {res['num_test_categories']} "
             f"categories ({res.get('box_source', 'GT boxes')}, {res['num_input_views']} input view(s) per scene); "
             f"K = {res['num_prototypes']}"
             + (f"; baseline banks fitted on {res['num_train_objects']} training objects."
                if res["num_train_objects"] else "."), "", "## Retrieval (paper Table 2)", ""]
    rn = res.get("resnet")
    rn_name = (rn or {}).get("backbone_label", "ImageNet ResNet-18")
    rn_stage = "layer4" if rn is None else f"{rn.get('feature_stage', 'layer4')}"
    if rn is not None and rn.get("backbone", "resnet18") != "resnet18":
        rn_stage += f", {rn['feature_dim']} channels,"
    rn_label = f"{rn_name} ({rn_stage} pooled in the projected GT box; cosine, no rotation search)"
    pad = (" - | - |" if "paper" in r.get("protocols", {}) else "") + (" - |" if res.get("probe") else "")
    if rn is None:
        rn_row = f"| {rn_label} | {RESNET_HOWTO} |" + pad
    else:
        at = f" (at k = {rn['k']})" if rn["k"] != r["k"] else ""
        rn_row = f"| {rn_label} | {rn['precision_at_k']:.3f}{at} |" + pad
        if "paper_precision_at_k" in rn and "paper" in r.get("protocols", {}):
            rn_row = (f"| {rn_label} | {rn['precision_at_k']:.3f}{at} | {rn['paper_precision_at_k']:.3f} | "
                      f"{rn['same_object_top1']:.3f} |" + (" - |" if res.get("probe") else ""))
    lines += retrieval_markdown(r, res.get("probe"), learned="threedq learned features (the evaluated encoder)",
                                extra_rows=[rn_row])
    if res.get("paper_protocol_not_run"):
        lines += ["", f"Not run: {res['paper_protocol_not_run']}."]
    if res.get("baselines_not_run"):
        lines += ["", f"Not run: {res['baselines_not_run']}."]
    if res.get("confused_pairs"):
        lines += ["", "Most confused category pairs (learned features, strict protocol; top-k slots of one category's "
                  "queries held by the other's objects, both directions): " + "; ".join(
                      f"{p['a']} / {p['b']} ({p['slots']})" for p in res["confused_pairs"][:8])
                  + ". Per category: `per_category_retrieval.png`."]
    lines += ["", f"## Clustering into K = {res['num_prototypes']} prototypes (paper Tables 1 and 4), and pose", "",
              res.get("cluster_search", cluster_search_label()), "",
              "| method | Hungarian acc. | few-shot acc. (2 shots) | yaw median err. (deg) | yaw acc. @10 deg | "
              "@20 deg |", "|---|---|---|---|---|---|"]
    for m, v in method_rows(res["quantization"]):
        yaw = ("n/a (in-plane angle, not a yaw) | n/a | n/a" if m == "q25d"
               else f"{yaw_cell(v)} | {v['yaw_acc_10']:.3f} | {v['yaw_acc_20']:.3f}")
        lines.append(f"| {METHOD_LABELS.get(m, m)} | {v['hungarian_acc']:.3f} | {fewshot_cell(v['fewshot_acc'])} | "
                     f"{yaw} |")
    if "q25d" not in res["quantization"]:
        lines.append(f"| {METHOD_LABELS['q25d']} | {Q25D_HOWTO} | | | | |")
    lines += ["", "## Few-shot labelling, 2 labelled objects per category (paper Table 1)", "",
              "Prototype rows: labels propagated through the prototypes above (same search); ResNetRet: label of the "
              "nearest labelled object (cosine, no rotation); ResNetClass: a linear classifier (logistic regression) "
              f"trained on the labelled objects' {rn_name.removeprefix('ImageNet ')} features. The same labelled "
              "draw (seed) for every row.", "",
              "| method | few-shot acc. |", "|---|---|"]
    for m, v in method_rows(res["quantization"]):
        lines.append(f"| {METHOD_LABELS.get(m, m)} | {fewshot_cell(v['fewshot_acc'])} |")
    if "q25d" not in res["quantization"]:
        lines.append(f"| {METHOD_LABELS['q25d']} | {Q25D_HOWTO} |")
    for key, label in (("ret_acc", f"ResNetRet ({rn_name}, nearest labelled object)"),
                       ("class_acc", f"ResNetClass ({rn_name} + linear classifier on the shots)")):
        lines.append(f"| {label} | {RESNET_HOWTO if rn is None else fewshot_cell(rn[key])} |")
    if res.get("curve"):
        ks = sorted({int(k) for v in res["curve"].values() for k in v})
        lines += ["", "## Hungarian accuracy vs K (paper Fig. 3a)", "",
                  res.get("cluster_search", cluster_search_label()), "",
                  "| method | " + " | ".join(f"K={k}" for k in ks) + " |", "|---|" + "---|" * len(ks)]
        for m, v in method_rows(res["curve"]):
            lines.append(f"| {METHOD_LABELS.get(m, m)} | " + " | ".join(
                f"{v[str(k)]:.3f}" if str(k) in v else "-" for k in ks) + " |")
        if "q25d" not in res["curve"]:
            lines.append(f"| {METHOD_LABELS['q25d']} | {Q25D_HOWTO} |" + " |" * (len(ks) - 1))
    lines += ["", "Yaw error: pairs of objects of one asymmetric category assigned to one prototype; the estimated "
              "relative yaw (from the rotation search) against the true one. A method that groups more of a category "
              "into one prototype is scored on more, and other, pairs: compare two runs on the pairs both group with "
              "`benchmarks/yaw_common_pairs.py`.", ""]
    return "\n".join(lines)


def feature_cells(retrieval: dict[str, Any] | None) -> dict[str, Any]:
    """The learned features' Table 3 cells of a round's retrieval table: precision@k under both protocols (with their
    ceilings), the pool and the same-object top-1 rate."""
    if not retrieval:
        return {"precision_at_10": None, "precision_at_10_paper": None, "same_object_top1": None}
    paper = retrieval.get("protocols", {}).get("paper", {})
    return {"precision_at_10": retrieval["precision_at_k"]["learned"], "k": retrieval["k"],
            "precision_at_10_paper": paper.get("precision_at_k", {}).get("learned"),
            "same_object_top1": paper.get("same_object_top1", {}).get("learned"), "pool": retrieval["num_objects"],
            "ceiling_strict": retrieval.get("protocols", {}).get("strict", {}).get("ceiling"),
            "ceiling_paper": paper.get("ceiling")}


def fmt(v: float | None, digits: int = 3) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def size_band_cells(rows: list[dict[str, Any]]) -> list[str]:
    """The cells of one box set's row of a size-band table: share found at IoU 0.25 / 0.5; median centre errors."""
    return ["-" if not r["objects"] else f"{r['found_25']:.2f} / {r['found_50']:.2f}"
            + ("" if r["median_centre_error_xy"] != r["median_centre_error_xy"]  # NaN: no box overlaps any
               else f"; {r['median_centre_error_xy']:.3f} / {r['median_centre_error_z']:+.3f}") for r in rows]


def size_band_lines(det: dict[str, Any], work_dir: str) -> list[str]:
    """Objects found per size band by each box set of a detector evaluation (``by_size``), as a markdown table."""
    if not det.get("by_size"):
        return []
    tables = {t["boxes"]: t["rows"] for t in det["by_size"]}
    names = list(tables)
    bands = [r["band"] for r in tables[names[0]]]
    lines = ["### Objects found per size (largest extent of the GT box; share found at IoU 0.25 / 0.5; median "
             "centre error of the best box in the plane / in height, metres)", "",
             "| boxes | " + " | ".join(f"{b} ({r['objects']})" for b, r in zip(bands, tables[names[0]])) + " |",
             "|---|" + "---|" * len(bands)]
    for name in names:
        lines.append(f"| {name} | " + " | ".join(size_band_cells(tables[name])) + " |")
    lines += ["", f"Picture: `{work_dir}/03_detector_eval/detection_by_size.png`.", ""]
    flat = det.get("flat_objects")
    if flat and flat["of"]:
        how = ("`flat_boxes` adds the input view's observed boxes of such objects to the ranked boxes of the mAP, "
               "below the boxes handed on" if flat["flat_boxes"] else "`flat_boxes` is off: they are not detected")
        lines += [f"{flat['objects']} of {flat['of']} test objects ({flat['objects'] / flat['of']:.0%}) are less tall "
                  f"than {flat['min_box_height']:.3f} m, the detector's `min_box_height` (half a voxel of the feature "
                  "grid, which cannot tell them from the floor): the detector is not trained on them and does not "
                  f"hand them on (row \"flat\" above); {how}. A finer `grid_resolution` (view prediction retrained) "
                  "is what would let it learn them.", ""]
    return lines


def _em_header_lines(summary: dict[str, Any]) -> list[str]:
    """The report's title, the run's facts and the view-prediction table."""
    vp = summary["viewpred_eval"]["view_prediction"]
    return ["# threedq em report", "",
            f"- work dir: `{summary['work_dir']}`; rounds: {summary['rounds']}"
            + (f"; data: `{summary['data_config']}`" if summary.get("data_config") else ""),
            f"- machine: {summary['machine']}; torch {summary['torch']}; frozen-encoder stages in "
            f"{summary.get('frozen_precision', '32-true')}"
            + (f"; mining in {summary['mining_precision']}" if summary.get("mining_precision") else ""),
            f"- view prediction checkpoint: `{summary['viewpred']['checkpoint']}` "
            + ("(given with --viewpred_ckpt, not trained here)" if summary["viewpred"].get("given")
               else f"({summary['viewpred'].get('seconds', '?')} s)"),
            "", f"## View prediction on held-out scenes ({vp['num_scenes']} scenes)", "", *viewpred_lines(vp), ""]


def viewpred_lines(vp: dict[str, Any]) -> list[str]:
    """The view-prediction table of an evaluation's ``view_prediction`` metrics."""
    lines = ["| metric | value |", "|---|---|",
             f"| RGB L1 (target pixels inside the grid, half resolution) | {vp['l1']:.4f} |",
             f"| RGB L1 of the mean-colour baseline | {vp['l1_mean_colour']:.4f} |"]
    if "l1_fg" in vp:
        lines += [f"| RGB L1 on the objects (target pixels above the ground plane) | {vp['l1_fg']:.4f} |",
                  f"| the same for the mean-colour baseline | {vp['l1_fg_mean_colour']:.4f} |"]
    lines.append(f"| occupancy balanced accuracy | {vp['occ_bacc']:.3f} |")
    return lines


def _em_detector_lines(summary: dict[str, Any]) -> list[str]:
    """The 3D detection section (pseudo-boxes, the warm-start detector, size bands); empty without a detector."""
    det = summary.get("detector_eval")
    if not det:
        return []
    pb, dd = det["pseudo_boxes"], det["detector"]
    sv = det.get("pseudo_boxes_single_view")
    return [f"## 3D detection on held-out scenes ({dd['num_gt']} GT objects; dataset-level mAP, axis-aligned IoU)", "",
            "| boxes | mAP@0.25 | mAP@0.5 |", "|---|---|---|",
            f"| label-free pseudo-boxes (depth, ground plane, 3D components; every view) | {pb['map_25']:.3f} | "
            f"{pb['map_50']:.3f} |",
            *([f"| the same from only the view(s) the detector sees (its fair reference) | {sv['map_25']:.3f} | "
               f"{sv['map_50']:.3f} |"] if sv else []),
            f"| detector trained on the pseudo-boxes | {dd['map_25']:.3f} | {dd['map_50']:.3f} |", "",
            f"Detections beside GT: `{summary['work_dir']}/03_detector_eval/detections.png`. "
            f"Rounds use {_boxes_word(summary)} boxes.", "", *size_band_lines(det, summary["work_dir"])]


def _boxes_word(summary: dict[str, Any]) -> str:
    return "detected" if summary.get("boxes") == "detections" else "GT"


def _em_round_lines(summary: dict[str, Any]) -> list[str]:
    """The per-EM-round table (round 0 first, when measured) and the final round's tables; empty without rounds."""
    rounds = summary.get("round_results", [])
    r0 = summary.get("round0_result")
    if not rounds:
        return []
    pk = precision_label(rounds[0]["retrieval"])
    lines = [f"## Per EM round (threedq, {_boxes_word(summary)} boxes, held-out objects)", "",
             f"{pk}: {SEARCH_LABELS[rounds[0]['retrieval']['search']]}; strict: "
             f"{PROTOCOL_LABELS['strict']}; paper: {PROTOCOL_LABELS['paper']}. Round 0 is the view-prediction encoder "
             "and a bank fitted on it, on round 1's boxes (the paper's iteration 0).", "",
             f"| round | {pk}, strict | {pk}, paper | same object nearest (paper) | pool (ceiling strict / paper) | "
             "Hungarian acc. | few-shot acc. | yaw median err. (deg) | yaw acc. @10 deg |",
             "|---|---|---|---|---|---|---|---|---|"]
    for i, r in ([(0, r0)] if r0 else []) + list(enumerate(rounds, 1)):
        q = r["quantization"]["threedq"]
        c = feature_cells(r["retrieval"])
        ceil = f"{c['pool']} ({fmt(c['ceiling_strict'])} / {fmt(c['ceiling_paper'])})"
        lines.append(f"| {i} | {fmt(c['precision_at_10'])} | {fmt(c['precision_at_10_paper'])} | "
                     f"{fmt(c['same_object_top1'])} | {ceil} | {q['hungarian_acc']:.3f} | "
                     f"{fewshot_cell(q['fewshot_acc'])} | {yaw_cell(q)} | {q['yaw_acc_10']:.3f} |")
    last = rounds[-1]
    lines += ["", f"## Final round in detail ({last['num_test_objects']} test objects, {last['num_test_categories']} "
              f"categories, K = {last['num_prototypes']})", "", "Retrieval (paper Table 2):", "",
              *retrieval_markdown(last["retrieval"], last.get("probe"),
                                  learned="threedq features of the final round (learned)"),
              "", "Clustering and pose (paper Tables 1 and 4; yaw error beyond the paper):", "",
              "| method | Hungarian acc. | few-shot acc. | yaw median err. (deg) | yaw acc. @10 | @20 |",
              "|---|---|---|---|---|---|"]
    for m, v in method_rows(last["quantization"]):
        lines.append(f"| {METHOD_LABELS.get(m, m)} | {v['hungarian_acc']:.3f} | {fewshot_cell(v['fewshot_acc'])} | "
                     f"{yaw_cell(v)} | {v['yaw_acc_10']:.3f} | {v['yaw_acc_20']:.3f} |")
    lines += ["", f"Pictures in `{summary['final_eval_dir']}/`: `prototype_alignment.png`, `retrieval.png`, "
              "`per_category_retrieval.png` (per-category precision@10 under both protocols, the most confused pairs). "
              "Accuracy against K (Fig. 3a): `threedq eval --ckpt <round>/checkpoints/last.ckpt`."]
    return lines


def _mining_row(i: int, f: dict[str, Any]) -> str:
    """One row of the mining table: round ``i``'s refresh ``f`` (the miner's logged counts; absent ones ``-``)."""
    yaw = f"{f['yaw_median_err_deg']:.1f} ({f['yaw_pairs']} pairs)" if "yaw_median_err_deg" in f else "-"
    yaw_sym = (f"{f['yaw_sym_median_err_deg']:.1f} ({f['yaw_sym_pairs']} pairs)"
               if "yaw_sym_median_err_deg" in f else "-")
    pool = f"{f['pool_on_objects']:.2f}" if "pool_on_objects" in f else "-"
    if "pool_vouched" in f:
        pool += f" ({f['pool_vouched']} of {f['pool_boxes_seen']} vouched"
        pool += f", {f['pool_scene_vouched']} by the scene too)" if "pool_scene_vouched" in f else ")"
    pairs = f"{f['pairs']}"
    src = f.get("candidates_from", "features")
    if src != "features":
        inputs = {"occupancy": "occupancy", "input": "crops, occupancy and colour"}.get(src, src)
        pairs += f" (from the input {inputs}: mutual {f['occupancy_mutual_k']}-NN)"
    context = f"{f['min_cosine']:.3f}" if src == "features" else "- (no patch check)"
    on = f"{f.get('labelled_pairs', '-')}" + (f" ({f['pairs_on_objects_iou25']} at IoU 0.25)"
                                              if "pairs_on_objects_iou25" in f else "")
    spread = f"{f['distinct_queries']} / {f['distinct_boxes']}" if "distinct_boxes" in f else "-"
    return (f"| {i} | {f['refresh']} | {pool} | {pairs} | {spread} | {on} | {f['same_category']:.3f} | {yaw} | "
            f"{yaw_sym} | {context} | {f['seconds']} |")


def _em_mining_lines(summary: dict[str, Any]) -> list[str]:
    """The correspondence-mining table (one row per round and refresh); empty when mining is off."""
    mining = summary.get("mining_results") or []
    if not mining:
        return []
    return ["", f"## Correspondence mining per round (`{summary.get('mining_config')}`; categories and yaws used for "
            "measuring only)", "",
            "| round | refresh | pool boxes on GT objects | pairs | queries / boxes they use | of them on two GT "
            "objects | same category (of those) | yaw median err., same-category asymmetric pairs (deg) | the same "
            "over every finite symmetry, modulo its period (deg) | context cosine threshold | seconds |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
            *(_mining_row(i, f) for i, m in enumerate(mining, 1) for f in m["refreshes"]),
            "", "Pictures of the best pairs of each refresh: `r<round>_mining/mining/refresh_<step>.png`."]


def _em_table3_lines(summary: dict[str, Any]) -> list[str]:
    """Table 3: every module (features, quantization, detection) per round; empty without it."""
    rounds = summary.get("round_results", [])
    table3 = summary.get("table3") or []
    if not table3:
        return []
    lines = ["", f"## Table 3: every module per round (held-out split; rounds on {_boxes_word(summary)} boxes)", "",
             "Round 0 is the state before the rounds (the paper's iteration 0): the warm-start detector, and the "
             "view-prediction encoder's features and prototypes on the boxes round 1 takes. "
             f"{precision_label(rounds[0]['retrieval']) if rounds else 'precision@10'}: "
             f"{SEARCH_LABELS[rounds[0]['retrieval']['search']] if rounds else '-'}; strict and paper protocol as "
             "above (pool and ceilings in the per-round table); detection: the round's detector "
             "(after its self-labelling), dataset-level mAP@0.5; precision / recall: its boxes above the 0.9 "
             "objectness threshold, the ones handed on, at IoU 0.5 (a box nested in a matched one is a false "
             "positive). "
             + ("Prototypes: from round 2 on, each round's quantizer refines the previous round's bank."
                if summary.get("bank_warm_start", True)
                else "Prototypes: every round's quantizer fits an empty bank on its encoder "
                "(`--bank_warm_start false`)."),
             "", f"| round | features: precision@{rounds[0]['retrieval']['k'] if rounds else 10}, strict | paper "
             "protocol | same object nearest | quantization: Hungarian acc. | detection: mAP@0.5 | mAP@0.25 | "
             "handed-on precision | recall |", "|---|---|---|---|---|---|---|---|---|"]
    for t in table3:
        h = t["handed_on_test"] or {}
        lines.append(f"| {t['round']} | {fmt(t['precision_at_10'])} | {fmt(t.get('precision_at_10_paper'))} | "
                     f"{fmt(t.get('same_object_top1'))} | {fmt(t['hungarian_acc'])} | {fmt(t['map_50'])} | "
                     f"{fmt(t['map_25'])} | {fmt(h.get('precision'))} | {fmt(h.get('recall'))} |")
    lines += ["", f"Curves: `{summary['work_dir']}/table3.png`."]
    return lines


def _em_self_label_lines(summary: dict[str, Any]) -> list[str]:
    """The detector self-labelling table (one row per round); empty when self-labelling is off."""
    sl = summary.get("self_label_results") or []
    if not sl:
        return []
    lines = ["", f"## Detector self-labelling per round (`{summary.get('self_labelling_config')}`; GT used for "
             "measuring only)", "",
             "| round | pool scenes | candidates | positives | of them true (IoU 0.5) | negatives | of them background "
             "(no object at IoU 0.25) | mAP@0.5 before | after |", "|---|---|---|---|---|---|---|---|---|"]
    before = summary["detector_eval"]["detector"]["map_50"] if summary.get("detector_eval") else None
    for i, r in enumerate(sl, 1):
        lab = r["labels"] or {}
        after = r["detector_eval"]["detector"]["map_50"]
        pos = f"{lab.get('positives', '-')}"
        if lab.get("positive_boxes", lab.get("positives")) != lab.get("positives"):  # pseudo-boxes are positives too
            pos += f" (boxes trained as positives: {lab['positive_boxes']}, the pseudo-boxes)"
        lines.append(f"| {i} | {lab.get('scenes', '-')} | {lab.get('candidates', '-')} | {pos} | "
                     f"{fmt(lab.get('positives_true_at_50'))} | {lab.get('negatives', '-')} | "
                     f"{fmt(lab.get('negatives_false_at_25'))} | {fmt(before)} | {fmt(after)} |")
        before = after
    return lines + ["", "Pictures: the labels on training scenes `r<round>_self_labelling/self_labels/labels.png` "
                    "(kept green, pruned red); the round's detections on test scenes "
                    "`r<round>_detector_eval/detections.png`."]


def em_markdown(summary: dict[str, Any]) -> str:
    """The ``threedq em`` report (``report.md``) of a run's summary, as markdown."""
    mining = summary.get("mining_results") or []
    sl = summary.get("self_label_results") or []
    lines = [*_em_header_lines(summary), *_em_detector_lines(summary), *_em_round_lines(summary),
             *_em_mining_lines(summary), *_em_table3_lines(summary), *_em_self_label_lines(summary)]
    if not mining or not sl:
        lines += ["", "## Left out of these rounds", ""]
        if not mining:
            lines.append("The encoder is not fine-tuned between rounds (mining is off).")
        if not sl:
            lines.append("The detector is not self-labelled (self-labelling is off): it stays the warm start.")
    lines.append("")
    return "\n".join(lines)


def _cell(v: float | None, digits: int = 3) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def _yaw_or_dash(r: dict[str, Any]) -> str:
    v = r.get("yaw_median_deg")
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else yaw_cell(r)


def feature_sets_markdown(table: dict[str, Any]) -> str:
    """The table as markdown, naming the search, the protocols, their pool and ceilings."""
    ceil = table.get("ceilings", {})
    banks = (f"banks of K = {table['K']} fitted on {table['num_train_objects']} training objects"
             if table["num_train_objects"] else "no training split: retrieval only (no probe, no banks)")
    lines = [f"## Feature sets (paper Table 2, with clustering): {table['num_test_objects']} test objects, {banks}", "",
             f"precision@10: {SEARCH_LABELS[table['search']]}.",
             *(f"- {p}: {PROTOCOL_LABELS[p]}; pool {table['num_test_objects']} objects; perfect features would score "
               f"{c:.3f}." for p, c in ceil.items()),
             "- linear probe: a logistic regression on the voxel-averaged frozen crops (the descriptor's six numbers), "
             "trained with the training objects' labels (they train the probe only), accuracy on the test objects.", "",
             "| features | precision@10, strict | precision@10, paper | same object nearest (paper) | linear probe "
             "acc. | Hungarian acc. | few-shot acc. | yaw median err. (deg) | yaw acc. @10 deg |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, r in table["rows"].items():
        lines.append(f"| {name} | {_cell(r['precision_at_10'])} | {_cell(r.get('precision_at_10_paper'))} | "
                     f"{_cell(r.get('same_object_top1'))} | {_cell(r.get('probe_acc'))} | "
                     f"{_cell(r['hungarian_acc'])} | {_cell(r['fewshot_acc'])} | {_yaw_or_dash(r)} | "
                     f"{_cell(r['yaw_acc_10'])} |")
    return "\n".join(lines) + "\n"
