"""``kill -9`` a running ``threedq em`` at several points, resume it, and get the uninterrupted run's numbers.

The uninterrupted run is a new ``python -m threedq em --rounds 2`` process on the tiny fixture; the killed and resumed
runs are processes forked from one that imported threedq once (``tests/forkserver.py``: each new interpreter spends
5-9 s on imports), each a process of its own. A run is killed with ``SIGKILL`` by ``tests/fault_shim`` when an atomic
write reaches a chosen file, before or after the rename:

1. during view prediction (its first training picture half-written: a torn temporary file is left behind);
2. between stages (right after the detector's ``stage.json``);
3. during a round's evaluation write (round 1's ``results.json``, after its figures);
4. during round 2's self-labelling (its labels file half-written).

Each time ``--resume true`` goes on. The finished run equals an uninterrupted run of the same seed: the same
``metrics.json`` (timings, the work folder's own path and the last bits of evaluation losses aside), bit-identical
checkpoints of every stage (encoder, detector, prototype bank), the same files, no temporary file left. The uninterrupted run is itself a separate
process from each part of the resumed one, so this also shows that a seed reproduces a CPU run bit for bit.

While the uninterrupted run holds its work folder, a second ``threedq em`` on the same folder is refused with one line
naming the folder and the first run (:mod:`threedq.locks`). And a full disk: one kind of write after another fails
(``ENOSPC``, once ``EACCES``: a checkpoint, a stage marker, the detections handed on, a prototype bank, a round's
results, self-labels, ``metrics.json``, ``report.md``), each run stops with one line naming the file, and the run
resumed once the space is back equals the uninterrupted one; a failed rewrite of ``metrics.json`` keeps the old file.

The full-disk chain runs in a thread beside the uninterrupted run and the kill chain (separate processes and work
folders, each mostly on one core): on two cores the module takes about the longer chain's time, not the sum.
"""

from __future__ import annotations

import concurrent.futures
import fnmatch
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import torch
from conftest import tiny_data_yaml, tiny_quantizer_config
from forkserver import ForkServer

from threedq.locks import FOLDER_LOCK_NAME

pytestmark = pytest.mark.slow

TESTS = Path(__file__).resolve().parent


def _config(tmp: Path, data_dir: Path) -> Path:
    cfg = tmp / "tiny.yaml"
    cfg.write_text(
        "model:\n  init_args:\n    grid_resolution: [32, 32, 16]\n"
        f"{tiny_data_yaml(data_dir)}\n"
        "trainer:\n  max_steps: 2\n  log_every_n_steps: 1\n  limit_val_batches: 1\n  check_val_every_n_epoch: 1\n"
        "  enable_progress_bar: false\n  enable_model_summary: false\n"
    )
    return cfg


def _em_command(work: Path, cfg: Path, *extra: str, kill_at: str | None = None,
                fault: tuple[str, str, str] | None = None, pause_at: str | None = None) -> tuple[list[str], dict]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS / "fault_shim"), env.get("PYTHONPATH", "")])
    env["OMP_NUM_THREADS"] = "2"
    for name in ("THREEDQ_KILL_AT", "THREEDQ_FAULT", "THREEDQ_FAULT_MATCH", "THREEDQ_PAUSE_AT"):
        env.pop(name, None)
    if kill_at is not None:
        env["THREEDQ_KILL_AT"] = kill_at
    if fault is not None:  # (errno name, folder, glob of the files whose writes fail)
        env["THREEDQ_FAULT"], env["THREEDQ_FAULT_MATCH"] = f"{fault[0]}:{fault[1]}", fault[2]
    if pause_at is not None:
        env["THREEDQ_PAUSE_AT"] = pause_at
    cmd = [sys.executable, "-m", "threedq", "em", "--rounds", "2", "--work_dir", str(work), "--extra_configs",
           str(cfg), "--quantizer_config", str(cfg.parent / "tiny_quantizer.yaml"), "--mining_config", "none",
           "--boxes", "gt", *extra]
    return cmd, env


def _em(work: Path, cfg: Path, *extra: str, server: ForkServer | None = None,
        **faults: Any) -> subprocess.CompletedProcess:
    """One ``threedq em`` run: forked by ``server``, or (None) a new ``python -m threedq`` process."""
    cmd, env = _em_command(work, cfg, *extra, **faults)
    if server is not None:
        return server.run(cmd[3:], env=env, timeout=600)
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)


def _normalised(path: Path, work: Path) -> object:
    """metrics.json without timings and crop-cache counts (what one process saved), with the run folder's own path
    replaced by a placeholder, and evaluation losses to 6 significant digits: a resumed run encodes again the grids an
    uninterrupted run took from its crop cache, and the two computations can differ in the last bits (seen with the
    half-width encoder: the detector evaluation's mean loss 2.4925165 against 2.4925163; every checkpoint stays
    bit-identical and every other number equal)."""
    def walk(o: object) -> object:
        if isinstance(o, dict):
            return {k: float(f"{v:.6g}") if k == "loss" and isinstance(v, float) else walk(v)
                    for k, v in o.items() if k not in ("seconds", "crop_cache")}
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
def workspace(tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(folder of this module's runs, their tiny config)."""
    tmp = tmp_path_factory.mktemp("resume")
    tiny_quantizer_config(tmp)  # beside the config: _em_command passes it
    return tmp, _config(tmp, tiny_dataset)


@pytest.fixture(scope="module")
def server(workspace: tuple[Path, Path]):
    """The fork server of the killed and resumed runs, in the environment of :func:`_em_command`."""
    with ForkServer(_em_command(*workspace)[1]) as s:
        yield s


@pytest.fixture(scope="module")
def background(request: pytest.FixtureRequest, workspace: tuple[Path, Path], server: ForkServer):
    """The full-disk chain (:data:`FULL_DISK`), started in a thread before the uninterrupted run when a test of
    :class:`TestFullDisk` is selected: its runs are separate processes in their own work folder, each mostly on one
    core, so on two cores it overlaps the uninterrupted run and the kill chain (running the kill chain in a third
    thread made the module slower: 132 s against 106 s). Yields ``{"full_disk": future}`` (empty when not
    selected)."""
    wanted = any(item.module is request.module and item.cls is TestFullDisk for item in request.session.items)
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        futures = {"full_disk": pool.submit(_full_disk_chain, *workspace, server)} if wanted else {}
        yield futures  # leaving the pool waits for the chain, whatever happened meanwhile


@pytest.fixture(scope="module")
def reference(workspace: tuple[Path, Path], background: dict, server: ForkServer) -> dict:
    """The uninterrupted run; while it runs (paused once the detector has finished), a second ``threedq em`` on the
    same work folder is started and must be refused."""
    tmp, cfg = workspace
    ref = tmp / "uninterrupted"
    cmd, env = _em_command(ref, cfg, pause_at="*/02_detector/stage.json")
    first = subprocess.Popen(cmd, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    try:
        seen = []
        for line in first.stderr:  # until it pauses, holding the work folder
            seen.append(line)
            if "[fault_shim] paused" in line:
                break
        else:
            raise AssertionError(f"the first run never paused (exit {first.wait()}):\n{''.join(seen)[-3000:]}")
        second = _em(ref, cfg, server=server)
        first.stdin.write("\n")
        first.stdin.flush()
        out, err = first.communicate(timeout=600)
    finally:
        if first.poll() is None:
            first.kill()
    assert first.returncode == 0, err[-3000:]
    return {"ref": ref, "cfg": cfg, "tmp": tmp, "first_pid": first.pid, "second": second}


def _kill_chain(tmp: Path, cfg: Path, server: ForkServer) -> dict:
    killed = tmp / "killed"
    log = []
    for what, at in KILLS:
        res = _em(killed, cfg, "--resume", "true", kill_at=at, server=server)
        log.append((what, res))
    final = _em(killed, cfg, "--resume", "true", server=server)
    assert final.returncode == 0, final.stderr[-3000:]
    return {"killed": killed, "log": log, "final": final}


@pytest.fixture(scope="module")
def runs(reference: dict, workspace: tuple[Path, Path], server: ForkServer) -> dict:
    return {"ref": reference["ref"], **_kill_chain(*workspace, server)}


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
        # each killed run left its lock file behind, naming it; the next run took the folder at once
        assert (runs["killed"] / FOLDER_LOCK_NAME).is_file()

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


class TestSecondRunRefused:
    def test_second_em_on_a_held_work_folder_stops_with_one_line(self, reference: dict) -> None:
        second, ref = reference["second"], reference["ref"]
        assert second.returncode == 2, second.stderr[-3000:]
        lines = [ln for ln in second.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1, second.stderr[-3000:]
        assert lines[0].startswith("threedq: error: ") and f"{ref} is in use by another threedq run" in lines[0]
        assert f"pid {reference['first_pid']}" in lines[0] and "threedq em --rounds 2" in lines[0]
        assert "[em]" not in second.stdout  # refused before it did anything

    def test_the_first_run_is_untouched(self, reference: dict, runs: dict) -> None:
        # it finished (the fixture checks) and equals the killed-and-resumed run (TestKillAndResume): the second
        # run wrote nothing into it
        assert _normalised(reference["ref"] / "metrics.json", reference["ref"]) == \
            _normalised(runs["killed"] / "metrics.json", runs["killed"])


# One kind of write after another fails for lack of space (or permission), each in a run resumed from the one before;
# the order is the order in which a run writes them.
FULL_DISK = [
    ("ENOSPC", "a checkpoint", "*/00_viewpred/checkpoints/last.ckpt"),
    ("ENOSPC", "a stage marker", "*/02_detector/stage.json"),
    ("ENOSPC", "the detections handed on", "*/03_detector_eval/detections_test.npz"),
    ("ENOSPC", "a prototype bank (the quantizer's checkpoint)", "*/r01_quantizer/checkpoints/last.ckpt"),
    ("ENOSPC", "a round's results", "*/r01_eval/results.json"),
    ("ENOSPC", "self-labels", "*/r01_self_labelling/self_labels/labels.json"),
    ("EACCES", "a read-only folder", "*/r02_eval/results.json"),
    ("ENOSPC", "metrics.json", "*/full_disk/metrics.json"),
    ("ENOSPC", "report.md", "*/full_disk/report.md"),
]


def _full_disk_chain(tmp: Path, cfg: Path, server: ForkServer) -> dict:
    work = tmp / "full_disk"
    log = []
    for errno_name, what, glob in FULL_DISK:
        log.append((errno_name, what, glob, _em(work, cfg, "--resume", "true", fault=(errno_name, str(work), glob),
                                               server=server)))
    final = _em(work, cfg, "--resume", "true", server=server)
    assert final.returncode == 0, final.stderr[-3000:]
    before = (work / "metrics.json").read_bytes()
    rewrite = _em(work, cfg, "--resume", "true", fault=("ENOSPC", str(work), "*/full_disk/metrics.json"),
                  server=server)
    return {"work": work, "log": log, "before": before, "rewrite": rewrite}


@pytest.fixture(scope="module")
def full_disk(reference: dict, background: dict, workspace: tuple[Path, Path], server: ForkServer) -> dict:
    chain = background["full_disk"].result() if "full_disk" in background else _full_disk_chain(*workspace, server)
    return {"ref": reference["ref"], **chain}


class TestFullDisk:
    def test_each_failed_write_stops_with_one_line_naming_the_file(self, full_disk: dict) -> None:
        for errno_name, what, glob, res in full_disk["log"]:
            assert res.returncode == 2, f"{what}: exit {res.returncode}\n{res.stderr[-3000:]}"
            last = [ln for ln in res.stderr.splitlines() if ln.strip()][-1]
            cause = "no space left on device" if errno_name == "ENOSPC" else "permission denied"
            assert last.startswith("threedq: error: "), f"{what}: {last}"
            assert fnmatch.fnmatch(last.split("threedq: error: ")[1].split(": ")[0], glob), f"{what}: {last}"
            assert cause in last.lower(), f"{what}: {last}"
            assert "Traceback" not in res.stderr, f"{what}: {res.stderr[-3000:]}"

    def test_resumed_after_space_is_freed_equals_uninterrupted(self, full_disk: dict) -> None:
        ref, work = full_disk["ref"], full_disk["work"]
        assert _normalised(ref / "metrics.json", ref) == _normalised(work / "metrics.json", work)
        for rel in sorted(p.relative_to(ref) for p in ref.rglob("last.ckpt")):
            sa = torch.load(ref / rel, weights_only=True, map_location="cpu")["state_dict"]
            sb = torch.load(work / rel, weights_only=True, map_location="cpu")["state_dict"]
            assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa), rel
        assert _files(ref) == _files(work)
        assert not [p for p in work.rglob("*.tmp")]

    def test_a_failed_rewrite_keeps_the_previous_file(self, full_disk: dict) -> None:
        res, work = full_disk["rewrite"], full_disk["work"]
        assert res.returncode == 2 and f"{work / 'metrics.json'}: no space left on device" in res.stderr
        assert (work / "metrics.json").read_bytes() == full_disk["before"]
