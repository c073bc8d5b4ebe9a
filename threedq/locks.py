"""Locks between processes on POSIX advisory locks (:func:`fcntl.flock`) of a small lock file.

* :func:`hold_folder`: a run's own output folder. Another process asking for it, for a folder inside it, or (with
  ``check_below``) for a folder above a held one is refused at once with :class:`FolderInUseError`.
* :func:`exclusive`: a file several runs share and the first one to need it writes; the others wait, then read it.

The kernel releases a lock when its process ends, however it ends; the lock file stays behind (it records who held it
last). Locks are re-entrant within a process. On a platform without :mod:`fcntl` runs are not guarded.
"""

from __future__ import annotations

import datetime
import errno
import json
import os
import socket
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

from threedq.errors import InputError

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "FOLDER_LOCK_NAME", "FolderInUseError", "exclusive", "held_by", "hold_folder", "is_first_process", "lock_file_for"
]  # fmt: skip

#: The lock file of a held folder (inside it).
FOLDER_LOCK_NAME = ".threedq-run.lock"

# lock file (absolute, normalised) -> [fd, depth]: the locks this process holds
_HELD: dict[Path, list[int]] = {}
_GUARD = threading.RLock()
#: The variables a distributed launch (torchrun, Lightning's own launcher, SLURM's srun) sets to a process's rank.
_RANK_VARIABLES = ("RANK", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK", "SLURM_PROCID")


def is_first_process() -> bool:
    """Whether this is the first process of a distributed launch (or not in one): the one that holds run folders."""
    for name in _RANK_VARIABLES:
        try:
            if int(os.environ.get(name, "0")) != 0:
                return False
        except ValueError:
            continue
    return True


class FolderInUseError(InputError):
    """A folder another process holds (one line: the folder and the holder)."""


def _abs(path: str | os.PathLike[str]) -> Path:
    return Path(os.path.abspath(os.path.realpath(os.fspath(path))))


def lock_file_for(path: str | os.PathLike[str]) -> Path:
    """The lock file :func:`exclusive` uses for ``path``: a hidden file beside it (``.<name>.lock``)."""
    p = _abs(path)
    return p.with_name(f".{p.name}.lock")


def held_by(lock_file: str | os.PathLike[str]) -> str:
    """Who holds (or last held) ``lock_file``, as the refusal line says it: ``pid 123, 'threedq em ...', since ...``."""
    try:
        info = json.loads(Path(lock_file).read_text() or "{}")
    except (OSError, ValueError):
        return "another process"
    if not isinstance(info, dict) or not info:
        return "another process"
    where = f" on {info['host']}" if info.get("host") and info["host"] != socket.gethostname() else ""
    command, since = info.get("command"), info.get("since")
    parts = [f"pid {info.get('pid', '?')}{where}", f"'{command}'" if command else "", f"since {since}" if since else ""]
    return ", ".join(part for part in parts if part)


def _hold(lock_file: Path, fd: int, what: str) -> None:
    """Register the lock this process now holds and write who holds it into the lock file (best effort)."""
    since = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
    info = {"pid": os.getpid(), "host": socket.gethostname(), "command": what, "since": since}
    with suppress(OSError):  # a full disk: the kernel's lock is what counts
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(info) + "\n").encode(), 0)
    with _GUARD:
        _HELD[lock_file] = [fd, 1]


def _open_lock(lock_file: Path) -> int:
    lock_file.parent.mkdir(parents=True, exist_ok=True)
    return os.open(lock_file, os.O_RDWR | os.O_CREAT, 0o644)


def _busy(lock_file: Path) -> bool:
    """Whether another process holds ``lock_file`` (a shared probe, released at once; ours count as free)."""
    if fcntl is None or lock_file in _HELD or not lock_file.is_file():
        return False
    try:
        fd = os.open(lock_file, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)  # closing releases the probe
    return False


def _command_line() -> str:
    argv = [Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python", *sys.argv[1:]]
    if argv[0] in ("__main__.py", "-m"):
        argv[0] = "threedq"
    return " ".join(argv)


def _release(lock_file: Path) -> None:
    with _GUARD:
        entry = _HELD[lock_file]
        entry[1] -= 1
        if entry[1] == 0:
            del _HELD[lock_file]
            os.close(entry[0])  # releases the lock; the file stays (removing it would race with another process)


def _reenter(lock_file: Path) -> bool:
    """Count one more use of a lock this process holds; False if it does not hold it."""
    with _GUARD:
        if lock_file not in _HELD:
            return False
        _HELD[lock_file][1] += 1
        return True


@contextmanager
def hold_folder(folder: str | os.PathLike[str], *, command: str | None = None,
                check_below: bool = False) -> Iterator[Path]:  # fmt: skip
    """Hold ``folder`` (created if needed) for this process until the block ends, or refuse at once.

    ``command``: how the refusal line of another process names this run (default: this process's command line);
    ``check_below``: also refuse when a folder inside ``folder`` is held by another process. Yields ``folder`` as an
    absolute path.

    Re-entrant (a folder inside one this process holds is held already); only the first process of a distributed
    launch (:func:`is_first_process`) holds folders.

    Raises:
        FolderInUseError: ``folder``, a folder above it, or (``check_below``) one inside it is held by another
            process; the line names the held folder and its holder (pid, command line, start time).
    """
    folder = _abs(folder)
    with _GUARD:
        held = (f for f in _HELD if f.name == FOLDER_LOCK_NAME and (folder == f.parent or f.parent in folder.parents))
        mine = next(held, None)
        if mine is not None:
            _reenter(mine)
    if mine is None and fcntl is not None and is_first_process():
        mine = _lock_folder(folder, command or _command_line(), check_below)
    try:
        yield folder
    finally:
        if mine is not None:
            _release(mine)


def _lock_folder(folder: Path, command: str, check_below: bool) -> Path | None:
    lock_file = folder / FOLDER_LOCK_NAME
    hint = "wait for it to end or use another folder"
    for above in folder.parents:
        if _busy(above / FOLDER_LOCK_NAME):
            holder = held_by(above / FOLDER_LOCK_NAME)
            raise FolderInUseError(f"{folder}: inside {above}, which another threedq run holds ({holder}); {hint}")
    if check_below and folder.is_dir():
        for below in folder.rglob(FOLDER_LOCK_NAME):
            if below != lock_file and _busy(below):
                where = f"{folder}: {below.parent} inside it"
                raise FolderInUseError(f"{where} is held by another threedq run ({held_by(below)}); {hint}")
    try:
        fd = _open_lock(lock_file)
    except OSError:
        return None  # the folder cannot be made or written: the run's own first write says so, naming its file
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise FolderInUseError(f"{folder} is in use by another threedq run ({held_by(lock_file)}); {hint}") from None
    except OSError as e:  # pragma: no cover - a file system without locks: run unguarded
        os.close(fd)
        if e.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
            raise
        return None
    _hold(lock_file, fd, command)
    return lock_file


@contextmanager
def exclusive(path: str | os.PathLike[str], *, what: str, quiet: bool = False,
              before_wait: Callable[[], None] | None = None) -> Iterator[None]:  # fmt: skip
    """Be the only process writing ``path`` until the block ends; wait while another process is (re-entrant). Use it
    around "if ``path`` is not complete, make it"; the lock is :func:`lock_file_for` ``(path)``.

    ``what``: what this process does to ``path``, for the waiting line of another process (``"generating"``); ``quiet``:
    do not print (to stderr) whom this process waits for; ``before_wait``: called before waiting (it may raise instead).
    """
    lock_file = lock_file_for(path)
    if fcntl is None:  # pragma: no cover - Windows
        yield
        return
    if not _reenter(lock_file):
        try:
            fd = _open_lock(lock_file)
        except OSError:  # its folder cannot be made or written: the writes themselves fail, naming their files
            yield
            return
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if before_wait is not None:
                    before_wait()
                if not quiet:
                    print(f"[threedq] waiting for {held_by(lock_file)} ({_abs(path)})", file=sys.stderr, flush=True)
                fcntl.flock(fd, fcntl.LOCK_EX)
        except BaseException:
            os.close(fd)
            raise
        _hold(lock_file, fd, f"{what} {_abs(path)}")
    try:
        yield
    finally:
        _release(lock_file)
