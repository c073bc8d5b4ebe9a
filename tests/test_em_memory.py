"""``benchmarks/em_memory.py``: a run's memory samples given to its stages, and the process tree's resident memory."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import load_benchmark

em_memory = load_benchmark("em_memory")


class TestStages:
    def test_stage_ends_from_markers(self, tmp_path: Path) -> None:
        marks = {"00_viewpred": ("stage.json", 110.0), "01_viewpred_eval": ("metrics.json", 130.0),
                 "02_detector": ("stage.json", 190.0), "03_detector_eval": ("results.json", 260.0)}
        for name, (marker, t) in marks.items():
            (tmp_path / name).mkdir()
            (tmp_path / name / marker).write_text("{}")
            os.utime(tmp_path / name / marker, (t, t))
        (tmp_path / "r01_mining").mkdir()  # unfinished: no marker, no end
        (tmp_path / "02_detector" / "checkpoints").mkdir()
        assert em_memory.stage_ends(tmp_path) == [(110.0, "00_viewpred"), (130.0, "01_viewpred_eval"),
                                                  (190.0, "02_detector"), (260.0, "03_detector_eval")]

    def test_peaks_hand_computed(self) -> None:
        ends = [(110.0, "a"), (130.0, "b"), (190.0, "c")]
        g = 2**30
        samples = [(101.0, 1 * g), (109.0, 3 * g), (110.0, 2 * g),  # a: up to and including its end
                   (120.0, 5 * g),  # b
                   # c: no sample
                   (200.0, 4 * g), (201.0, 1 * g)]  # after the last stage
        rows = em_memory.per_stage_peaks(samples, ends, start=100.0)
        assert rows == [{"stage": "a", "ended_s": 10, "peak_gib": 3.0}, {"stage": "b", "ended_s": 30, "peak_gib": 5.0},
                        {"stage": "c", "ended_s": 90, "peak_gib": 0.0},
                        {"stage": "after the last stage (report)", "ended_s": None, "peak_gib": 4.0}]

    def test_no_tail_row_without_samples(self) -> None:
        rows = em_memory.per_stage_peaks([(105.0, 2**30)], [(110.0, "a")], start=100.0)
        assert [r["stage"] for r in rows] == ["a"]


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="reads /proc (Linux)")
def test_tree_rss_counts_a_grandchild() -> None:
    """A shell whose child holds 256 MiB of touched memory: the tree's RSS includes it, the shell's own does not."""
    code = "x = b'\\x01' * (256 << 20); import time; time.sleep(30)"
    shell = subprocess.Popen(["sh", "-c", f'"{sys.executable}" -c "{code}"; true'])
    try:
        deadline = time.time() + 20
        while time.time() < deadline and em_memory.tree_rss_bytes(shell.pid) < 256 << 20:
            time.sleep(0.1)
        own = int(next(line for line in Path(f"/proc/{shell.pid}/status").read_text().splitlines()
                       if line.startswith("VmRSS:")).split()[1]) * 1024
        assert em_memory.tree_rss_bytes(shell.pid) >= 256 << 20 > own
    finally:
        for child in em_memory._children().get(shell.pid, []):
            os.kill(child, 9)
        shell.kill()
        shell.wait()
