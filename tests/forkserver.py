"""Run many ``threedq`` commands as real processes without paying Python's imports for each (test-only).

A ``threedq`` process spends 5-9 s importing torch, Lightning (which imports ``torch._dynamo``) and threedq before it
reads its first argument; the end-to-end test modules start dozens of them (``tests/test_bad_inputs.py``,
``tests/test_resume.py``). :class:`ForkServer` starts ONE Python process that imports those modules, then forks a
child per command. Each child is a process of its own, as with ``python -m threedq``: its own working directory,
environment, stdout and stderr (files, read back afterwards), exit status (a ``kill -9`` shows as ``-9``, as
:mod:`subprocess` reports it) and ``tests/fault_shim`` when ``PYTHONPATH`` names it; it runs ``threedq/__main__.py``
through :func:`runpy.run_module`, the way ``python -m`` does, and an uncaught exception prints its traceback and exits
1, as the interpreter does.

What a fork shares with the server, and so with its siblings: the state of the imports (nothing of threedq's
runs at import), Python's hash seed, and whatever the interpreter read from the environment at start-up. So a
command may only change the variables that nothing reads at start-up or import: :meth:`ForkServer.run` refuses an
environment whose ``PYTHON*``, ``OMP_*``, ``MKL_*``, ``KMP_*``, ``TQDM_*`` or ``TORCH*`` variables differ from the
server's (``PYTHONPATH`` may add ``tests/fault_shim``). Tests that are about a process's start-up (the imports a
subcommand makes, the installed wheel, a seed reproducing a run across processes) keep real subprocesses.

Protocol (JSON lines): the client writes ``{"id", "argv", "cwd", "env", "out", "err"}`` or ``{"kill": id}`` to the
server's stdin; the server answers ``{"id", "returncode"}`` on its stdout once the child has exited.
"""

from __future__ import annotations

import json
import os
import runpy
import select
import signal
import subprocess
import sys
import tempfile
import threading
from collections.abc import Mapping, Sequence
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from pathlib import Path

SHIM = Path(__file__).resolve().parent / "fault_shim"
PRELOAD = ("threedq.cli", "threedq.pipeline.lightning_cli", "threedq.pipeline.em", "threedq.pipeline.data_commands")
_STARTUP_PREFIXES = ("PYTHON", "OMP_", "MKL_", "KMP_", "TQDM_", "TORCH")


def startup_variables(env: Mapping[str, str]) -> dict[str, str]:
    """The variables of ``env`` that the interpreter or an import may read once, at start-up (PYTHONPATH aside)."""
    return {k: v for k, v in env.items() if k.startswith(_STARTUP_PREFIXES) and k != "PYTHONPATH"}


def _take(path: Path) -> str:
    """A child's captured stream, removed once read ('' when the child was killed before it opened the file)."""
    try:
        text = path.read_text(errors="replace")
    except FileNotFoundError:
        return ""
    path.unlink()
    return text


class ForkServer:
    """A server process with threedq imported; :meth:`run` is :func:`subprocess.run` for ``python -m threedq``.

    Thread-safe: several commands may run at once (each is a child of the server). Use as a context manager, or
    call :meth:`close`.

    Args:
        env: the server's environment (default: this process's); every command's environment must agree with it on
            the start-up variables (:func:`startup_variables`).
    """

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        self.env = dict(os.environ if env is None else env)
        self._tmp = tempfile.TemporaryDirectory(prefix="forkserver.")
        self._proc = subprocess.Popen([sys.executable, __file__, *PRELOAD], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, env=self.env, text=True, bufsize=1)
        self._lock = threading.Lock()
        self._pending: dict[int, Future] = {}
        self._next = 0
        self._ready: Future = Future()  # the server's imports run while the caller goes on (e.g. builds inputs)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self._proc.stdout is not None
        ready = self._proc.stdout.readline()
        if ready.strip() != "ready":
            self._ready.set_exception(RuntimeError(f"the fork server did not start (it said {ready!r})"))
            return
        self._ready.set_result(None)
        for line in self._proc.stdout:
            msg = json.loads(line)
            with self._lock:
                fut = self._pending.pop(msg["id"])
            fut.set_result(msg["returncode"])
        with self._lock:  # the server is gone: nothing pending will be answered
            for fut in self._pending.values():
                fut.set_exception(RuntimeError("the fork server exited"))
            self._pending.clear()

    def _send(self, msg: dict) -> None:
        assert self._proc.stdin is not None
        with self._lock:
            self._proc.stdin.write(json.dumps(msg) + "\n")
            self._proc.stdin.flush()

    def run(self, argv: Sequence[str], *, cwd: str | os.PathLike | None = None, env: Mapping[str, str] | None = None,
            timeout: float | None = None) -> subprocess.CompletedProcess:
        """Run ``python -m threedq *argv`` in a child of the server; stdout and stderr are captured as text.

        Raises:
            ValueError: ``env`` differs from the server's in a start-up variable.
            subprocess.TimeoutExpired: the command ran past ``timeout`` seconds (the child is killed).
        """
        self._ready.result(timeout=600)
        env = dict(self.env if env is None else env)
        if startup_variables(env) != startup_variables(self.env):
            mine, theirs = startup_variables(self.env), startup_variables(env)
            diff = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
            raise ValueError(f"env: start-up variables differ from the fork server's: {diff}; use a subprocess")
        with self._lock:
            cid = self._next
            self._next += 1
            fut: Future = Future()
            self._pending[cid] = fut
        out, err = Path(self._tmp.name) / f"{cid}.out", Path(self._tmp.name) / f"{cid}.err"
        self._send({"id": cid, "argv": list(map(str, argv)), "cwd": str(cwd or os.getcwd()), "env": env,
                    "out": str(out), "err": str(err)})
        args = [sys.executable, "-m", "threedq", *map(str, argv)]
        try:
            returncode = fut.result(timeout)
        except FutureTimeout:  # the builtin TimeoutError from Python 3.11 on, its own class in 3.10
            self._send({"kill": cid})
            fut.result()
            raise subprocess.TimeoutExpired(args, timeout or 0.0, _take(out), _take(err))
        return subprocess.CompletedProcess(args, returncode, _take(out), _take(err))

    def close(self) -> None:
        if self._proc.poll() is None:
            assert self._proc.stdin is not None
            self._proc.stdin.close()
            try:
                self._proc.wait(60)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        self._reader.join(10)
        self._tmp.cleanup()

    def __enter__(self) -> ForkServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------------------------------------------------
# The server (runs as ``python tests/forkserver.py <module to import>...``)
# ---------------------------------------------------------------------------------------------------------------


def _child(req: dict) -> None:
    """In the forked child: become ``python -m threedq <argv>`` and exit with its status. Never returns."""
    code = 1
    try:
        os.chdir(req["cwd"])
        os.environ.clear()
        os.environ.update(req["env"])
        for fd, path, flags in ((0, os.devnull, os.O_RDONLY), (1, req["out"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC),
                                (2, req["err"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC)):
            f = os.open(path, flags, 0o644)
            os.dup2(f, fd)
            os.close(f)
        sys.path[0] = os.getcwd()  # ``python -m`` puts the working directory first, not this file's folder
        if str(SHIM) in req["env"].get("PYTHONPATH", "").split(os.pathsep):  # what sitecustomize would do
            runpy.run_path(str(SHIM / "sitecustomize.py"), run_name="sitecustomize")
        sys.argv = ["threedq", *req["argv"]]
        runpy.run_module("threedq", run_name="__main__", alter_sys=True)
        code = 0
    except SystemExit as e:  # as the interpreter ends on SystemExit
        if e.code is None:
            code = 0
        elif isinstance(e.code, int):
            code = e.code
        else:
            print(e.code, file=sys.stderr)
            code = 1
    except BaseException:  # noqa: BLE001 - as the interpreter ends on an uncaught exception
        sys.excepthook(*sys.exc_info())
        code = 1
    finally:
        try:
            import atexit
            import threading

            threading._shutdown()  # as the interpreter ends: wait for non-daemon threads, then the atexit functions
            atexit._run_exitfuncs()
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)


def _serve(preload: Sequence[str]) -> None:
    import importlib

    for name in preload:
        importlib.import_module(name)
    out = sys.stdout
    out.write("ready\n")
    out.flush()
    children: dict[int, int] = {}  # pid -> request id
    by_id: dict[int, int] = {}  # request id -> pid
    buf = b""
    open_stdin = True
    while open_stdin or children:
        if open_stdin and select.select([0], [], [], 0.05)[0]:
            chunk = os.read(0, 65536)
            if not chunk:
                open_stdin = False
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                req = json.loads(line)
                if "kill" in req:
                    if req["kill"] in by_id:
                        os.kill(by_id[req["kill"]], signal.SIGKILL)
                    continue
                out.flush()
                sys.stderr.flush()
                pid = os.fork()
                if pid == 0:
                    _child(req)
                children[pid], by_id[req["id"]] = req["id"], pid
        elif not open_stdin:
            select.select([], [], [], 0.05)
        while children:
            pid, status = os.waitpid(-1, os.WNOHANG)
            if pid == 0:
                break
            cid = children.pop(pid)
            by_id.pop(cid, None)
            out.write(json.dumps({"id": cid, "returncode": os.waitstatus_to_exitcode(status)}) + "\n")
            out.flush()


if __name__ == "__main__":
    _serve(sys.argv[1:])
