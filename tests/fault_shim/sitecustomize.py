"""Fault injection for the subprocesses of ``tests/test_bad_inputs.py`` and ``tests/test_resume.py`` (test-only).

Python imports ``sitecustomize`` at start-up from ``sys.path``; the tests put this folder first on ``PYTHONPATH``
and set ``THREEDQ_FAULT=<ERRNO>:<folder>``. Then, inside ``<folder>``:

* ``ENOSPC`` (a full disk): flushing a file to disk (``os.fsync``) and opening a file for writing with ``open``
  fail with ``OSError(ENOSPC)``; creating folders and the temporary files of :mod:`threedq.atomic_io` still
  works, as on a disk that is full but for its metadata.
* ``EACCES`` (no write permission, for a root user whom ``chmod`` does not stop): creating a folder or a file,
  or opening one for writing, fails with ``PermissionError``.

``THREEDQ_FAULT_MATCH=<glob>`` narrows the fault to the files whose absolute path matches ``<glob>`` (``fnmatch``;
the temporary file of an atomic write, ``.<name>.<random>.tmp``, counts as the ``<name>`` it is written for), so a
run fails at one kind of write (``*/checkpoints/last.ckpt``, ``*/r01_eval/results.json``) and nowhere else.

``THREEDQ_KILL_AT=<before|after>:<glob>`` (for ``tests/test_resume.py``): the process sends itself ``SIGKILL`` (a
``kill -9``: no handler, no clean-up runs) when an ``os.replace`` targets a path matching ``<glob>`` (``fnmatch`` on the
absolute path), just before or just after the rename: every atomic write of threedq ends in one.

``THREEDQ_PAUSE_AT=<glob>`` (for a second process to meet this one at a known point): after the first rename onto a
path matching ``<glob>`` the process prints ``[fault_shim] paused after writing <path>`` to stderr and waits for a line
on its stdin.

Monkeypatching cannot reach a subprocess; this can. Without these variables it does nothing.
"""

from __future__ import annotations

import builtins
import errno
import fnmatch
import io
import os
import re
import signal
import sys

_SPEC = os.environ.get("THREEDQ_FAULT", "")
if _SPEC:
    _code, _, _root = _SPEC.partition(":")
    _ERR = getattr(errno, _code)
    _ROOT = os.path.realpath(_root)
    _MATCH = os.environ.get("THREEDQ_FAULT_MATCH", "")
    _TEMPORARY = re.compile(r"^\.(.+)\.[A-Za-z0-9_]+\.tmp$")  # threedq.atomic_io's temporary file of <name>

    def _inside(path: object) -> bool:
        try:
            p = os.path.realpath(os.fsdecode(path))  # type: ignore[arg-type]
        except TypeError:
            return False
        if not (p == _ROOT or p.startswith(_ROOT + os.sep)):
            return False
        if not _MATCH:
            return True
        head, name = os.path.split(p)
        m = _TEMPORARY.match(name)
        return fnmatch.fnmatch(os.path.join(head, m.group(1)) if m else p, _MATCH)

    def _fail(path: object) -> None:
        raise OSError(_ERR, os.strerror(_ERR), os.fspath(path))  # type: ignore[arg-type]

    _open, _io_open, _os_open, _fsync, _mkdir = builtins.open, io.open, os.open, os.fsync, os.mkdir

    def _guarded_open(file, mode="r", *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        if isinstance(file, (str, bytes, os.PathLike)) and any(c in mode for c in "wax+") and _inside(file):
            _fail(file)
        return _io_open(file, mode, *args, **kwargs)

    def _guarded_fsync(fd):  # noqa: ANN001, ANN202
        try:
            path = os.readlink(f"/proc/self/fd/{int(fd if isinstance(fd, int) else fd.fileno())}")
        except OSError:
            path = None
        if path is not None and _inside(path):
            _fail(path)
        return _fsync(fd)

    builtins.open = io.open = _guarded_open
    os.fsync = _guarded_fsync
    if _ERR == errno.EACCES:

        def _guarded_os_open(path, flags, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
            if flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT) and _inside(path):
                _fail(path)
            return _os_open(path, flags, *args, **kwargs)

        def _guarded_mkdir(path, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
            if _inside(path) and os.path.realpath(os.fsdecode(path)) != _ROOT:
                _fail(path)
            return _mkdir(path, *args, **kwargs)

        os.open, os.mkdir = _guarded_os_open, _guarded_mkdir

_KILL = os.environ.get("THREEDQ_KILL_AT", "")
_PAUSE = os.environ.get("THREEDQ_PAUSE_AT", "")
if _KILL or _PAUSE:
    _when, _, _pattern = _KILL.partition(":")
    _replace = os.replace
    _paused: list[str] = []

    def _killing_replace(src, dst, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        target = os.path.abspath(os.fspath(dst))
        hit = bool(_KILL) and fnmatch.fnmatch(target, _pattern)
        if hit and _when == "before":
            os.kill(os.getpid(), signal.SIGKILL)
        result = _replace(src, dst, *args, **kwargs)
        if hit and _when == "after":
            os.kill(os.getpid(), signal.SIGKILL)
        if _PAUSE and not _paused and fnmatch.fnmatch(target, _PAUSE):
            _paused.append(target)  # once: say so, and wait for a line on stdin
            print(f"[fault_shim] paused after writing {target}", file=sys.stderr, flush=True)
            sys.stdin.readline()
        return result

    os.replace = _killing_replace
