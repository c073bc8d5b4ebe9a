"""``kill -9`` a running ``threedq em`` at several points, resume it, and get the uninterrupted run's numbers.

The run is a real subprocess (``python -m threedq em --rounds 2`` on the tiny fixture). It is killed with
``SIGKILL`` by ``tests/fault_shim`` when an atomic write reaches a chosen file, before or after the rename:

1. during view prediction (its first training picture half-written: a torn temporary file is left behind);
2. between stages (right after the detector's ``stage.json``);
3. during a round's evaluation write (round 1's ``results.json``, after its figures);
4. during round 2's self-labelling (its labels file half-written).

Each time ``--resume true`` goes on. The finished run equals an uninterrupted run of the same seed: the same
``metrics.json`` (timings and the work folder's own path aside), bit-identical checkpoints of every stage (encoder,
detector, prototype bank), the same files, no temporary file left. The uninterrupted run is itself a separate
process from each part of the resumed one, so this also shows that a seed reproduces a CPU run bit for bit.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

pytestmark = pytest.mark.slow

TESTS = Path(__file__).resolve().parent


def _config(tmp: Path, data_dir: Path) -> Path:
    cfg = tmp / "tiny.yaml"
    cfg.write_text(
        "model:\n  init_args:\n    grid_resolution: [32, 32, 16]\n"
        f"data:\n  init_args:\n    data_dir: {data_dir}\n    num_scenes: 12\n    image_size: [32, 32]\n"
        "    num_views: 4\n    generator_workers: 1\n"
        "trainer:\n  max_steps: 2\n  log_every_n_steps: 1\n  limit_val_batches: 1\n  check_val_every_n_epoch: 1\n"
        "  enable_progress_bar: false\n  enable_model_summary: false\n"
    )
    return cfg


def _em(work: Path, cfg: Path, *extra: str, kill_at: str | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS / "fault_shim"), env.get("PYTHONPATH", "")])
    env["OMP_NUM_THREADS"] = "2"
    env.pop("THREEDQ_KILL_AT", None)
    if kill_at is not None:
        env["THREEDQ_KILL_AT"] = kill_at
    cmd = [sys.executable, "-m", "threedq", "em", "--rounds", "2", "--work_dir", str(work), "--extra_configs",
           str(cfg), "--mining_config", "none", "--boxes", "gt", *extra]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)


def _normalised(path: Path, work: Path) -> object:
    """metrics.json without timings, with the run folder's own path replaced by a placeholder."""
    def walk(o: object) -> object:
        if isinstance(o, dict):
            return {k: walk(v) for k, v in o.items() if k != "seconds"}
        if isinstance(o, list):
            return [walk(v) for v in o]
        if isinstance(o, str):
            return o.replace(str(work), "<work>")
        return o
    return walk(json.loads(path.read_text()))


def _files(work: Path) -> set[str]:
    # TensorBoard names its event files by time and process id
    return {str(p.relative_to(work)) for p in work.rglob("*") if p.is_file() and "tfevents" not in p.name}


KILLS = [
    ("during view prediction", "before:*/00_viewpred/images/train_step000000.png"),
    ("between stages", "after:*/02_detector/stage.json"),
    ("during round 1's evaluation write", "before:*/r01_eval/results.json"),
    ("during round 2's self-labelling", "before:*/r02_self_labelling/self_labels/labels.json"),
]


@pytest.fixture(scope="module")
def runs(tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    tmp = tmp_path_factory.mktemp("resume")
    cfg = _config(tmp, tiny_dataset)
    ref, killed = tmp / "uninterrupted", tmp / "killed"
    res = _em(ref, cfg)
    assert res.returncode == 0, res.stderr[-3000:]
    log = []
    for what, at in KILLS:
        res = _em(killed, cfg, "--resume", "true", kill_at=at)
        log.append((what, res))
    final = _em(killed, cfg, "--resume", "true")
    assert final.returncode == 0, final.stderr[-3000:]
    return {"ref": ref, "killed": killed, "log": log, "final": final}


class TestKillAndResume:
    def test_each_kill_happened(self, runs: dict) -> None:
        for what, res in runs["log"]:
            assert res.returncode == -9, f"{what}: exit {res.returncode}, not killed:\n{res.stderr[-2000:]}"
        outs = [res.stdout for _, res in runs["log"][1:]] + [runs["final"].stdout]
        # after the kill during view prediction: the torn picture is removed and the stage restarts
        assert "a write cut short" in outs[0] and "viewpred: unfinished (interrupted): restarting" in outs[0]
        # after the kill between stages: the detector is kept
        assert "detector: finished earlier" in outs[1]
        # after the kill during round 2's self-labelling: rounds 1 and 2 up to it are kept
        assert "round 2 quantizer: finished earlier" in outs[3] and "round 2 self-labelling: unfinished" in outs[3]

    def test_metrics_equal_uninterrupted(self, runs: dict) -> None:
        ref, killed = runs["ref"], runs["killed"]
        a, b = _normalised(ref / "metrics.json", ref), _normalised(killed / "metrics.json", killed)
        assert a == b
        def report(work: Path) -> str:  # timings aside
            return re.sub(r"\d+(\.\d+)? s\b", "<t> s", (work / "report.md").read_text().replace(str(work), "<work>"))
        assert report(ref) == report(killed)

    def test_checkpoints_bit_identical(self, runs: dict) -> None:
        ref, killed = runs["ref"], runs["killed"]
        ckpts = sorted(p.relative_to(ref) for p in ref.rglob("last.ckpt"))
        assert len(ckpts) >= 6  # view prediction, detector, 2 x (quantizer, self-labelling)
        for rel in ckpts:
            sa = torch.load(ref / rel, weights_only=True, map_location="cpu")["state_dict"]
            sb = torch.load(killed / rel, weights_only=True, map_location="cpu")["state_dict"]
            assert sa.keys() == sb.keys(), rel
            for k in sa:
                assert torch.equal(sa[k], sb[k]), f"{rel}: {k}"

    def test_no_stale_or_torn_file(self, runs: dict) -> None:
        ref, killed = runs["ref"], runs["killed"]
        assert not [p for p in killed.rglob("*.tmp")]
        assert _files(ref) == _files(killed)
        for p in killed.rglob("*.json"):
            json.loads(p.read_text())  # every JSON whole
