"""The result pages are what the generator writes from the committed main job (``docs/results/``), so they cannot
go stale: ``docs/results.md``, the README's results table and the generated tables of ``docs/fidelity.md``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from threedq.pipeline import results_pages as rp

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / "docs/results/metrics.json"
#: Another main job's metrics.json (same shape, earlier code, 2026-11-27): the pages must render from it too.
OLDER = Path(__file__).resolve().parent / "data" / "older_main_job_metrics.json"


def test_committed_pages_are_generated() -> None:
    stale = [str(p.relative_to(ROOT)) for p, text in rp.expected_pages(ROOT).items()
             if p.read_text(encoding="utf-8") != text]
    assert not stale, f"stale pages {stale}: run `python -m threedq.pipeline.results_pages`"


@pytest.mark.skipif(not (rp.ROOT / "README.md").is_file(),
                    reason="the generator's root holds no README (an installed package, e.g. the Docker image)")
def test_check_reports_no_stale_page() -> None:
    assert rp.main(["--check"]) == 0


def test_committed_run_is_described() -> None:
    if not COMMITTED.is_file():
        assert rp.NOT_RECORDED in (ROOT / "docs/results.md").read_text(encoding="utf-8")
        pytest.skip("no main job recorded: the pages say so and show no number")
    metrics, info = rp.load_results(ROOT / "docs/results")
    assert info["command"] == rp.MAIN_JOB
    assert len(info["commit"]) == 40 and info["wall_seconds"] > 0 and info["machine"]
    assert metrics["rounds"] == len(metrics["round_results"]) == len(metrics["table3"]) - 1
    assert rp.MAIN_JOB in (ROOT / "README.md").read_text(encoding="utf-8")  # the README runs what was recorded


def test_replace_block() -> None:
    begin, end = rp._markers("x")
    text = f"a\n{begin}\nold\n{end}\nb\n"
    assert rp.replace_block(text, "x", "new\nlines") == f"a\n{begin}\nnew\nlines\n{end}\nb\n"
    with pytest.raises(ValueError, match="block 'y'"):
        rp.replace_block(text, "y", "new")


def test_parse_time_log(tmp_path) -> None:
    log = tmp_path / "time.log"
    log.write_text("\tCommand being timed: \"threedq em --rounds 4\"\n"
                   "\tElapsed (wall clock) time (h:mm:ss or m:ss): 1:02:03\n"
                   "\tMaximum resident set size (kbytes): 12582912\n")
    assert rp.parse_time_log(log) == {"wall_seconds": 3723.0, "peak_rss_gib": 12.0}
    log.write_text("\tElapsed (wall clock) time (h:mm:ss or m:ss): 28:27.50\n")
    assert rp.parse_time_log(log) == {"wall_seconds": 1707.5}


@pytest.mark.skipif(not COMMITTED.is_file() and not OLDER, reason="no main job's metrics.json here")
def test_record_run_then_write(tmp_path) -> None:
    """``--run``'s record: metrics.json copied, run.json written; the pages are then generated from them, and a
    second write changes nothing."""
    run = tmp_path / "runs" / "em"
    run.mkdir(parents=True)
    shutil.copyfile(COMMITTED if COMMITTED.is_file() else OLDER[0], run / "metrics.json")
    (run / ".threedq-run.lock").write_text(json.dumps({"since": "2026-11-29T06:38:25+00:00"}))
    root = tmp_path / "repo"
    (root / "docs").mkdir(parents=True)
    for page in ("README.md", "docs/fidelity.md"):
        shutil.copyfile(ROOT / page, root / page)
    info = rp.record_run(run, root=root, commit="a" * 40, ended="2026-11-29T07:08:25Z", note="A test.")
    assert info["wall_seconds"] == 1800.0 and info["date"] == "2026-11-29" and info["peak_rss_gib"] is None
    assert (root / "docs/results/metrics.json").read_bytes() == (run / "metrics.json").read_bytes()
    changed = rp.write_pages(root)
    assert root / "docs/results.md" in changed and root / "README.md" in changed
    text = (root / "docs/results.md").read_text()
    assert "`aaaaaaa`" in text and "30.0 min" in text and "A test." in text
    for title in ("## Table 1", "## Table 2", "## Table 3", "## Table 4", "## Table 5", "## Detection by object size",
                  "## Time of each stage"):
        assert title in text
    assert "30.0 min" in (root / "README.md").read_text() and rp.NOT_RECORDED not in (root / "README.md").read_text()
    assert rp.write_pages(root) == []
    # a run stopped and resumed: the wall times of its parts add up, the larger peak memory counts
    logs = []
    for i, (wall, kb) in enumerate((("20:00.00", 6291456), ("5:00.50", 8388608))):
        logs.append(tmp_path / f"time{i}.log")
        logs[-1].write_text(f"\tElapsed (wall clock) time (h:mm:ss or m:ss): {wall}\n"
                            f"\tMaximum resident set size (kbytes): {kb}\n")
    info = rp.record_run(run, root=root, commit="a" * 40, started="2026-11-29T06:00:00Z",
                         ended="2026-11-29T07:00:00Z", time_log=[str(x) for x in logs])
    assert info["wall_seconds"] == 1500.5 and info["peak_rss_gib"] == 8.0


def test_older_metrics_render() -> None:
    """Every page renders from an older main job's metrics.json: the fields they read are the ones threedq em has
    written since then."""
    path = OLDER
    info = {"command": rp.MAIN_JOB, "timed": "threedq em --rounds 4", "commit": "b" * 40, "date": "2026-11-27",
            "started": "2026-11-27T10:00:00Z", "ended": "2026-11-27T10:40:00Z", "wall_seconds": 2400.0,
            "peak_rss_gib": None, "machine": "a test machine"}
    m = json.loads(path.read_text())
    assert "## Table 5" in rp.results_page(m, info)
    assert "| 3D detection mAP@0.5" in rp.readme_table(m, info)
    assert set(rp.fidelity_blocks(m, info)) == {"fidelity-run", "fidelity-pools", "fidelity-table3",
                                                "fidelity-tables124", "fidelity-table5"}


def test_fidelity_gt_block() -> None:
    """fidelity.md's Table 2 on GT boxes from two table2.json files (synthetic numbers, the shape threedq eval
    --encoders writes): one row per feature set, both pools side by side, the paper's row, the ceilings."""
    row = {"precision_at_10": 0.5, "precision_at_10_paper": 0.55, "same_object_top1": 0.6, "probe_acc": 0.7,
           "hungarian_acc": 0.4}
    gt = {"num_test_objects": 487, "K": 50, "ceilings": {"strict": 0.915, "paper": 0.956},
          "rows": {"raw crops": row, "ours (round 4 mining)": row}}
    pool = {"num_test_objects": 1003, "K": 50, "ceilings": {"strict": 1.0, "paper": 1.0},
            "rows": {"raw crops": {**row, "probe_acc": None}}}
    doc = {"date": "2026-11-29", "commit": "c" * 40, "machine": "a test machine", "commands": ["threedq eval ..."],
           "gt": gt, "pool": pool}
    text = rp.fidelity_gt_block(doc)
    assert "| 487: strict | 487: **paper** |" in text and "| 1003: strict |" in text
    assert "| raw crops | 0.500 | 0.550 | 0.600 | 0.700 | 0.400 | 0.500 | 0.550 | 0.600 |" in text
    assert "| ours (round 4 mining) | 0.500 | 0.550 | 0.600 | 0.700 | 0.400 | - | - | - |" in text
    assert "487 objects: 0.915 strict / 0.956 paper; 1003 objects: 1.000 strict / 1.000 paper" in text
    assert "| raw crops | 0.500 | 0.550 | 0.600 | 0.700 | 0.400 |\n" in rp.fidelity_gt_block({**doc, "pool": None}) + "\n"


def test_data_fingerprint(tmp_path: Path) -> None:
    """The dataset's fingerprint changes with one byte of a scene, not with a cache folder; a missing folder has none."""
    (tmp_path / "scenes").mkdir()
    (tmp_path / "index.json").write_text("{}")
    (tmp_path / "scenes" / "a.npz").write_bytes(b"abc")
    first = rp.data_fingerprint(tmp_path)
    assert first is not None and len(first) == 64
    (tmp_path / "proposals").mkdir()
    (tmp_path / "proposals" / "train.npz").write_bytes(b"cache")
    assert rp.data_fingerprint(tmp_path) == first
    (tmp_path / "scenes" / "a.npz").write_bytes(b"abd")
    assert rp.data_fingerprint(tmp_path) != first
    assert rp.data_fingerprint(tmp_path / "none") is None
    info = {"data_sha256": first, "cpu_flags": ["aes", "avx2", "avx512_bf16"]}
    assert first[:12] in rp._provenance(info) and "avx2, avx512_bf16 (all in run.json)" in rp._provenance(info)
    assert "not recorded" in rp._provenance({})
