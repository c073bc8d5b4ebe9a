"""The markdown tables module: cells, labels and orders written the same wherever a table uses them."""

from __future__ import annotations

import json

from threedq.pipeline.tables import (
    METHOD_LABELS,
    cluster_search_label,
    feature_cells,
    fewshot_cell,
    fmt,
    method_rows,
    precision_label,
    size_band_lines,
    yaw_cell,
)


def test_cells() -> None:
    assert fmt(None) == "-" and fmt(0.12345) == "0.123" and fmt(2.0, 1) == "2.0"
    assert fewshot_cell(0.5) == "0.500"
    assert fewshot_cell(float("nan")).startswith("n/a (no category has more than 2 objects")
    assert yaw_cell({"yaw_median_deg": 10.06, "yaw_pairs": 449}) == "10.1 (449 pairs)"
    assert yaw_cell({"yaw_median_deg": 7.0}) == "7.0"  # a result written before the pair count was kept
    assert precision_label({"k": 10, "k_requested": 10, "num_objects": 50}) == "precision@10"
    assert precision_label({"k": 5, "k_requested": 10, "num_objects": 6}) == "precision@5 (k lowered from 10: 6 test objects)"


def test_method_rows_keep_the_table_order_after_a_json_round_trip() -> None:
    q = {"pointcloud": 1, "zeta": 4, "threedq": 2, "alpha": 5, "no_rot": 3}
    again = json.loads(json.dumps(q, sort_keys=True))
    order = [m for m, _ in method_rows(q)]
    assert order == [m for m, _ in method_rows(again)]
    known = [m for m in METHOD_LABELS if m in q]
    assert order == known + ["alpha", "zeta"]


def test_feature_cells() -> None:
    assert feature_cells(None) == {"precision_at_10": None, "precision_at_10_paper": None, "same_object_top1": None}
    r = {"precision_at_k": {"learned": 0.4}, "k": 10, "num_objects": 30,
         "protocols": {"strict": {"ceiling": 0.9}, "paper": {"precision_at_k": {"learned": 0.5}, "ceiling": 1.0,
                                                             "same_object_top1": {"learned": 0.7}}}}
    c = feature_cells(r)
    assert (c["precision_at_10"], c["precision_at_10_paper"], c["same_object_top1"]) == (0.4, 0.5, 0.7)
    assert (c["pool"], c["ceiling_strict"], c["ceiling_paper"]) == (30, 0.9, 1.0)


def test_size_band_lines_hand_case() -> None:
    row = {"band": "0.10-0.20 m", "objects": 4, "found_25": 0.75, "found_50": 0.5,
           "median_centre_error_xy": 0.0123, "median_centre_error_z": -0.002}
    empty = {"band": ">= 0.40 m", "objects": 0, "found_25": 0.0, "found_50": 0.0,
             "median_centre_error_xy": float("nan"), "median_centre_error_z": float("nan")}
    det = {"by_size": [{"boxes": "detector", "rows": [row, empty]}]}
    lines = size_band_lines(det, "runs/em")
    assert lines[2] == "| boxes | 0.10-0.20 m (4) | >= 0.40 m (0) |"
    assert lines[3] == "|---|---|---|"
    assert lines[4] == "| detector | 0.75 / 0.50; 0.012 / -0.002 | - |"
    assert lines[-2] == "Picture: `runs/em/03_detector_eval/detection_by_size.png`."
    assert size_band_lines({}, "runs/em") == []


def test_size_band_lines_say_which_objects_the_grid_cannot_resolve() -> None:
    row = {"band": "all", "objects": 4, "found_25": 0.75, "found_50": 0.5,
           "median_centre_error_xy": 0.0123, "median_centre_error_z": -0.002}
    det = {"by_size": [{"boxes": "detector", "rows": [row]}],
           "flat_objects": {"min_box_height": 0.04, "objects": 1, "of": 4, "flat_boxes": True}}
    last = size_band_lines(det, "runs/em")[-2]
    assert last.startswith("1 of 4 test objects (25%) are less tall than 0.040 m, the detector's `min_box_height`")
    assert "`flat_boxes` adds the input view's observed boxes" in last
    det["flat_objects"]["flat_boxes"] = False
    assert "`flat_boxes` is off: they are not detected" in size_band_lines(det, "runs/em")[-2]


def test_cluster_search_label_names_the_similarity() -> None:
    plain, weighted = cluster_search_label("fast"), cluster_search_label("fast", 0.2)
    assert "weighted" not in plain and "inscribed cylinder" in plain
    assert "weighted by their input occupancy (empty space 0.2, voxels at or next to observed surface 1.2" in weighted
    assert "cosine over the full cube" in cluster_search_label("exact", 0.0)


def test_em_report_names_where_the_pairs_came_from() -> None:
    """The mining table names the queries and boxes each refresh's pairs use and the pair source; the context
    threshold only where the miner's patch check read it."""
    import json
    from pathlib import Path

    from threedq.pipeline.tables import em_markdown

    summary = json.loads((Path(__file__).resolve().parents[1] / "docs/results/metrics.json").read_text())
    f = summary["mining_results"][0]["refreshes"][0]  # the pairs' spread over the pool, a column of its own

    def row() -> list[str]:
        return next(line for line in em_markdown(summary).splitlines() if line.startswith("| 1 | 1 | ")).split(" | ")

    assert row()[4] == f"{f['distinct_queries']} / {f['distinct_boxes']}"
    f["candidates_from"], f["occupancy_mutual_k"] = "input", 10
    assert row()[3] == f"{f['pairs']} (from the input crops, occupancy and colour: mutual 10-NN)"
    assert row()[9] == "- (no patch check)"  # the context threshold reads nothing then
    f["candidates_from"] = "occupancy"
    assert row()[3] == f"{f['pairs']} (from the input occupancy: mutual 10-NN)"
    del f["candidates_from"], f["occupancy_mutual_k"]  # the paper's miner on the learned features
    assert row()[3] == f"{f['pairs']}" and row()[9] == f"{f['min_cosine']:.3f}"
    del f["distinct_boxes"]  # a run from before the field
    assert row()[4] == "-"
