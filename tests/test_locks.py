"""``threedq.locks``: one run per work folder, one writer per shared file, between real processes.

The other process is always a real one (a ``python`` subprocess holding a lock until told to let go, or killed with
``SIGKILL``): locks between processes are what is tested, and ``flock`` within one process behaves otherwise.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from threedq.locks import (
    FOLDER_LOCK_NAME,
    FolderInUseError,
    exclusive,
    held_by,
    hold_folder,
    is_first_process,
    lock_file_for,
)

TESTS = Path(__file__).resolve().parent


class Holder:
    """A subprocess that takes a lock, says so on stdout, and keeps it until :meth:`release` (or a kill)."""

    def __init__(self, code: str, env: dict[str, str] | None = None) -> None:
        script = textwrap.dedent(f"""
            import sys
            from threedq.locks import exclusive, hold_folder
            with {code}:
                print("held", flush=True)
                sys.stdin.readline()
        """)
        self.proc = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, env={**os.environ, **(env or {})})
        line = self.proc.stdout.readline()
        assert line.strip() == "held", self.proc.stderr.read()

    def release(self) -> None:
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()
        assert self.proc.wait(timeout=60) == 0, self.proc.stderr.read()

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=60)

    def __enter__(self) -> Holder:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=60)


class TestHoldFolder:
    def test_smoke(self, tmp_path: Path) -> None:
        work = tmp_path / "a" / "work"
        with hold_folder(work, command="threedq em --work_dir x") as held:
            assert held == work.resolve() and work.is_dir()
            info = json.loads((work / FOLDER_LOCK_NAME).read_text())
            assert info["pid"] == os.getpid() and info["command"] == "threedq em --work_dir x"
        with Holder(f"hold_folder({str(work)!r})") as other:  # released: another process takes it at once
            other.release()

    def test_second_process_refused_with_the_holder(self, tmp_path: Path) -> None:
        work = tmp_path / "work"
        with Holder(f"hold_folder({str(work)!r}, command='threedq em --rounds 4')") as other:
            with pytest.raises(FolderInUseError) as e, hold_folder(work):
                pass
            line = str(e.value)
            assert "\n" not in line
            assert str(work.resolve()) in line and f"pid {other.proc.pid}" in line and "'threedq em --rounds 4'" in line
            other.release()
        with hold_folder(work):  # free again
            pass

    def test_inside_a_held_folder_refused(self, tmp_path: Path) -> None:
        work = tmp_path / "work"
        with Holder(f"hold_folder({str(work)!r})") as other:
            with pytest.raises(FolderInUseError, match=f"inside {work.resolve()}.*pid {other.proc.pid}"), \
                    hold_folder(work / "00_viewpred"):
                pass
            with hold_folder(tmp_path / "elsewhere"):  # a sibling folder is free
                pass
            other.release()

    def test_above_a_held_folder_refused_with_check_below(self, tmp_path: Path) -> None:
        inner = tmp_path / "work" / "00_viewpred"
        with Holder(f"hold_folder({str(inner)!r})") as other:
            with pytest.raises(FolderInUseError, match=f"{inner.resolve()} inside it is held.*pid {other.proc.pid}"), \
                    hold_folder(tmp_path / "work", check_below=True):
                pass
            with hold_folder(tmp_path / "work"):  # without check_below, only this folder and those above count
                pass
            other.release()

    def test_reentrant_in_one_process(self, tmp_path: Path) -> None:
        work = tmp_path / "work"
        with hold_folder(work, check_below=True), hold_folder(work / "00_viewpred"), hold_folder(work):
            assert not (work / "00_viewpred" / FOLDER_LOCK_NAME).exists()  # held through the folder above
        with Holder(f"hold_folder({str(work)!r})") as other:  # all released
            other.release()

    def test_holder_killed_does_not_block(self, tmp_path: Path) -> None:
        work = tmp_path / "work"
        with Holder(f"hold_folder({str(work)!r})") as other:
            pid = other.proc.pid
            other.kill()
        assert f"pid {pid}" in held_by(work / FOLDER_LOCK_NAME)  # the stale file still names the dead holder ...
        with hold_folder(work):  # ... and does not block
            assert json.loads((work / FOLDER_LOCK_NAME).read_text())["pid"] == os.getpid()

    def test_other_ranks_of_a_distributed_launch_hold_nothing(self, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
        work = tmp_path / "work"
        with Holder(f"hold_folder({str(work)!r})") as rank0:
            monkeypatch.setenv("LOCAL_RANK", "1")
            assert not is_first_process()
            with hold_folder(work):  # rank 1 runs the same command in rank 0's folder
                pass
            monkeypatch.setenv("LOCAL_RANK", "0")
            monkeypatch.setenv("SLURM_PROCID", "0")
            assert is_first_process()
            rank0.release()

    def test_a_file_in_the_way_is_left_to_the_run(self, tmp_path: Path) -> None:
        f = tmp_path / "a_file"
        f.write_text("x")
        with hold_folder(f):  # not a folder: nothing is locked, the command's own check refuses it
            pass
        assert f.read_text() == "x"


class TestExclusive:
    def test_smoke(self, tmp_path: Path) -> None:
        target = tmp_path / "cache.npz"
        with exclusive(target, what="computing"):
            assert lock_file_for(target) == tmp_path / ".cache.npz.lock"
            assert "computing" in held_by(lock_file_for(target))
        with exclusive(target, what="computing"), exclusive(target, what="computing"):  # re-entrant
            pass

    def test_waits_for_the_writer_then_reads_its_file(self, tmp_path: Path) -> None:
        """The holder writes the file only after the waiter says it waits, then lets go: the waiter finds it whole."""
        target = tmp_path / "shared.txt"
        waiter_code = textwrap.dedent(f"""
            from pathlib import Path
            from threedq.locks import exclusive
            with exclusive({str(target)!r}, what="reading"):
                print(Path({str(target)!r}).read_text(), flush=True)
        """)
        with Holder(f"exclusive({str(target)!r}, what='writing')") as first:
            waiter = _start(waiter_code)
            line = _wait_for_line(waiter, "waiting for")
            assert f"waiting for pid {first.proc.pid}" in line and "writing" in line and str(target) in line
            target.write_text("made by the first process")  # what the holder makes while the waiter waits
            first.release()
            out, err = waiter.communicate(timeout=60)
        assert waiter.returncode == 0, err
        assert out.strip() == "made by the first process"

    def test_before_wait_runs_only_when_another_process_holds_it_and_may_refuse(self, tmp_path: Path) -> None:
        target = tmp_path / "shared.txt"
        called: list[str] = []
        with exclusive(target, what="writing", before_wait=lambda: called.append("free")):
            pass
        assert called == []  # nobody held it: nothing to wait for

        def refuse() -> None:
            called.append("held")
            raise RuntimeError("would wait forever")

        with Holder(f"exclusive({str(target)!r}, what='writing')"):
            with pytest.raises(RuntimeError, match="would wait forever"):
                with exclusive(target, what="reading", before_wait=refuse):
                    pass
        assert called == ["held"]
        with exclusive(target, what="writing"):  # the refused attempt left nothing held
            pass

    def test_holder_killed_does_not_block(self, tmp_path: Path) -> None:
        target = tmp_path / "data"
        with Holder(f"exclusive({str(target)!r}, what='generating')") as other:
            other.kill()
        with exclusive(target, what="generating"):
            pass

    def test_unwritable_place_is_left_to_the_writes(self, tmp_path: Path) -> None:
        blocker = tmp_path / "file"
        blocker.write_text("x")
        with exclusive(blocker / "sub" / "cache.npz", what="computing"):  # its folder cannot be made: no lock
            pass


# ---------------------------------------------------------------------------------------------------------------
# Shared data made on first use by two processes at once: the first is paused while it holds the lock, until the
# second says it waits for it (so they do meet, whatever the machine's speed)
# ---------------------------------------------------------------------------------------------------------------


def _start(code: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _wait_for_line(proc: subprocess.Popen, text: str, stream: str = "stderr") -> str:
    """Read ``proc``'s stream until a line holding ``text`` (the process must not end before it)."""
    seen = []
    for line in getattr(proc, stream):
        seen.append(line)
        if text in line:
            return line
    raise AssertionError(f"{text!r} never came (exit {proc.wait()}):\n{''.join(seen)[-3000:]}")


_PAUSE = """
import sys
def _gate(pause):
    if not pause:  # the second process: its imports overlap the first's; it goes on once told to
        print("ready", file=sys.stderr, flush=True)
        sys.stdin.readline()
def _pause_once(fn, said=[]):
    def run(*a, **k):
        if not said:
            said.append(1)
            print("paused", file=sys.stderr, flush=True)
            sys.stdin.readline()
        return fn(*a, **k)
    return run
"""

_FIRST_USE = _PAUSE + """
import hashlib
from pathlib import Path
sys.path.insert(0, {tests!r})
from conftest import TINY
import threedq.data.generate as generate
from threedq.datamodules.clevr_veggie import ClevrVeggieDataModule
from threedq.scene import load_index, load_scene
if {pause}:
    generate._run_task = _pause_once(generate._run_task)
dm = ClevrVeggieDataModule(data_dir={data!r}, num_scenes=6, image_size=TINY["image_size"], num_views=TINY["num_views"],
                           max_objects=TINY["max_objects"], generator_workers=1)
_gate({pause})
dm.prepare_data()
index = load_index({data!r})
digest = hashlib.sha256()
for f in index.files("train") + index.files("val") + index.files("test"):
    load_scene(Path({data!r}) / f)  # validated: whole
    digest.update((Path({data!r}) / f).read_bytes())
print("digest", digest.hexdigest(), len(index.scenes), flush=True)
"""


def _meet(first_code: str, second_code: str) -> tuple[subprocess.Popen, str, str, subprocess.Popen, str, str]:
    """Start both (their imports overlap); wait until the first is paused holding the lock, let the second go on,
    wait until it says it waits for the first, let the first go on; both run to their end."""
    first = _start(first_code)
    second = None
    try:
        second = _start(second_code)
        _wait_for_line(first, "paused")
        _wait_for_line(second, "ready")
        second.stdin.write("\n")
        second.stdin.flush()
        waited = _wait_for_line(second, "waiting for")
        assert f"pid {first.pid}" in waited, waited
        first.stdin.write("\n")
        first.stdin.flush()
        out1, err1 = first.communicate(timeout=600)
        out2, err2 = second.communicate(timeout=600)
    finally:
        for p in (first, second):
            if p is not None and p.poll() is None:
                p.kill()
    assert first.returncode == 0, err1[-3000:]
    assert second.returncode == 0, err2[-3000:]
    return first, out1, err1, second, out2, waited


def test_first_use_generation_by_two_processes(tmp_path: Path) -> None:
    """Two runs on a fresh clone reach the embedded dataset together: one generates, the other waits, then reads
    the same whole files (it generates nothing)."""
    data = tmp_path / "clevr_veggie"
    _, out1, _, _, out2, waited = _meet(
        _FIRST_USE.format(tests=str(TESTS), data=str(data), pause=True),
        _FIRST_USE.format(tests=str(TESTS), data=str(data), pause=False))
    assert "generating" in waited and str(data) in waited
    d1 = next(ln for ln in out1.splitlines() if ln.startswith("digest"))
    d2 = next(ln for ln in out2.splitlines() if ln.startswith("digest"))
    assert d1 == d2 and d1.endswith(" 6")
    assert not [p for p in data.rglob("*") if p.name.endswith(".tmp")]


_PROPOSALS = _PAUSE + """
import threedq.data.proposal_cache as pc
from threedq.data.proposal_cache import propose_dataset
calls = []
real = pc.propose_boxes
def counted(*a, **k):
    calls.append(1)
    return real(*a, **k)
pc.propose_boxes = counted
if {pause}:
    pc._complete = _pause_once(pc._complete)
_gate({pause})
out = propose_dataset({data!r}, "train", {cache!r}, progress=False)
print("computed", len(calls), "of", len(out), flush=True)
"""


def test_proposal_cache_computed_once_by_two_processes(tiny_dataset: Path, tmp_path: Path) -> None:
    """The second process waits for the first one's proposal cache and reads it: it computes no scene itself."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data, ignore=shutil.ignore_patterns("proposals", ".*"))
    cache = data / "proposals" / "train.npz"
    fmt = {"data": str(data), "cache": str(cache)}
    _, out1, _, _, out2, waited = _meet(_PROPOSALS.format(pause=True, **fmt), _PROPOSALS.format(pause=False, **fmt))
    assert "computing proposals" in waited and str(cache) in waited
    n = int(out1.split()[-1])
    assert n > 0 and out1.strip() == f"computed {n} of {n}" and out2.strip() == f"computed 0 of {n}"
