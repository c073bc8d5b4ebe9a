"""Locks between processes: one run per work folder, one writer per shared file.

Two kinds, both on POSIX advisory locks (:func:`fcntl.flock`) of a small lock file:

* :func:`hold_folder` — a run's own output folder (``threedq em --work_dir``, the ``trainer.default_root_dir`` of
  ``threedq fit``, ``threedq eval --out``, ``threedq parse --out``). A second process asking for the same folder,
  for a folder inside it, or (with ``check_below``) for a folder above one that is held, is refused at once with
  :class:`FolderInUseError`: one line naming the folder and the process that holds it.
* :func:`exclusive` — a file several runs share and the first one to need it writes (the embedded dataset, the
  proposal caches): the second process waits (saying for whom) and then reads what the first wrote.

The kernel releases a lock when its process ends, however it ends (``kill -9`` included), so a holder that died
never blocks the next run or ``--resume``: the lock file stays behind (``.threedq-run.lock``; it only records who held
it last) and is taken again at once. Locks are re-entrant within a process (``threedq em`` holds its work folder
and runs each stage in-process in a folder inside it). They work on local disks and on NFS (Linux emulates
``flock`` there with byte-range locks); on a platform without :mod:`fcntl` (Windows) runs are not guarded.
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
from contextlib import contextmanager
from pathlib import Path

from threedq.errors import InputError

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "FOLDER_LOCK_NAME", "FolderInUseError", "exclusive", "held_by", "hold_folder", "is_first_process", "lock_file_for",
]

#: The lock file of a held folder (inside it).
FOLDER_LOCK_NAME = ".threedq-run.lock"

# lock file (absolute, normalised) -> [fd, depth]: the locks this process holds (re-entrancy; a second flock on
# another descriptor of the same file would conflict with our own).
_HELD: dict[Path, list[int]] = {}
_GUARD = threading.RLock()


#: The variables a distributed launch (torchrun, Lightning's own launcher, SLURM's srun) sets to a process's rank.
_RANK_VARIABLES = ("RANK", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK", "SLURM_PROCID")


def is_first_process() -> bool:
    """Whether this is the first process of a distributed launch (or not in one): the one that holds run folders.

    The other processes of a launch run the same command on the same folders on purpose; they hold nothing.
    """
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


def _describe(info: dict) -> str:
    parts = [f"pid {info.get('pid', '?')}"]
    if info.get("host") and info.get("host") != socket.gethostname():
        parts[0] += f" on {info['host']}"
    if info.get("command"):
        parts.append(f"'{info['command']}'")
    if info.get("since"):
        parts.append(f"since {info['since']}")
    return ", ".join(parts)


def held_by(lock_file: str | os.PathLike[str]) -> str:
    """Who holds (or last held) ``lock_file``, as the refusal line says it: ``pid 123, 'threedq em ...', since ...``."""
    try:
        info = json.loads(Path(lock_file).read_text() or "{}")
    except (OSError, ValueError):
        return "another process"
    return _describe(info) if isinstance(info, dict) and info else "another process"


def _record(fd: int, what: str) -> None:
    """Write who holds the lock into the lock file (best effort: the lock holds whether or not this is written)."""
    info = {"pid": os.getpid(), "host": socket.gethostname(), "command": what,
            "since": datetime.datetime.now().astimezone().isoformat(timespec="seconds")}
    data = (json.dumps(info) + "\n").encode()
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, data, 0)
    except OSError:
        pass  # a full disk: the kernel's lock is what counts


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
            os.close(entry[0])  # releases the lock; the file stays (removing it would race with a process about to lock it)


def _reenter(lock_file: Path) -> bool:
    """Count one more use of a lock this process holds; False if it does not hold it."""
    with _GUARD:
        if lock_file not in _HELD:
            return False
        _HELD[lock_file][1] += 1
        return True


@contextmanager
def hold_folder(folder: str | os.PathLike[str], *, command: str | None = None,
                check_below: bool = False) -> Iterator[Path]:
    """Hold ``folder`` (created if needed) for this process until the block ends, or refuse at once.

    Args:
        folder: the run's output folder.
        command: how the refusal line of another process names this run (default: this process's command line).
        check_below: also refuse when a folder inside ``folder`` is held by another process (a run over a whole
            work folder, like ``threedq em``).

    Yields:
        ``folder`` as an absolute path.

    Raises:
        FolderInUseError: ``folder``, a folder above it, or (``check_below``) one inside it is held by another
            process; the line names the held folder and its holder (pid, command line, start time).

    Re-entrant: a folder inside one this process holds is held already (nothing is locked again). Only the first
    process of a distributed launch holds folders (:func:`is_first_process`): the others share its folder.
    """
    folder = _abs(folder)
    with _GUARD:
        mine = next((f for f in _HELD if f.name == FOLDER_LOCK_NAME
                     and (folder == f.parent or f.parent in folder.parents)), None)
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
    for above in folder.parents:
        if _busy(above / FOLDER_LOCK_NAME):
            raise FolderInUseError(f"{folder}: inside {above}, which another threedq run holds "
                                   f"({held_by(above / FOLDER_LOCK_NAME)}); wait for it to end or use another folder")
    if check_below and folder.is_dir():
        for below in folder.rglob(FOLDER_LOCK_NAME):
            if below != lock_file and _busy(below):
                raise FolderInUseError(f"{folder}: {below.parent} inside it is held by another threedq run "
                                       f"({held_by(below)}); wait for it to end or use another folder")
    try:
        fd = _open_lock(lock_file)
    except OSError:
        return None  # the folder cannot be made or written (a file in its place, no permission): the run's own
        # first write says so, naming its file
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise FolderInUseError(f"{folder} is in use by another threedq run ({held_by(lock_file)}); "
                               "wait for it to end or use another folder") from None
    except OSError as e:  # pragma: no cover - a file system without locks: run unguarded
        os.close(fd)
        if e.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
            raise
        return None
    _record(fd, command)
    with _GUARD:
        _HELD[lock_file] = [fd, 1]
    return lock_file


@contextmanager
def exclusive(path: str | os.PathLike[str], *, what: str, quiet: bool = False,
              before_wait: Callable[[], None] | None = None) -> Iterator[None]:
    """Be the only process writing ``path`` until the block ends; wait while another process is.

    The lock is :func:`lock_file_for` ``(path)``. Use it around "if ``path`` is not complete, make it": the process
    that waited finds it made when its turn comes.

    Args:
        path: the shared file or folder.
        what: what this process does to it, for the waiting line of another process (``"generating"``).
        quiet: do not print the line saying whom this process waits for (it goes to stderr).
        before_wait: called when another process holds the lock, before waiting for it (it may raise instead).

    Re-entrant within a process.
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
        _record(fd, f"{what} {_abs(path)}")
        with _GUARD:
            _HELD[lock_file] = [fd, 1]
    try:
        yield
    finally:
        _release(lock_file)
