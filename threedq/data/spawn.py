"""What a "spawn" process pool needs of this process (the dataset generator's and the pseudo-boxes' pools)."""

from __future__ import annotations

import multiprocessing
import os
import sys

__all__ = ["refuse_in_spawned_main", "unspawnable_main"]


def unspawnable_main() -> str | None:
    """The main script's path when a "spawn" worker could not re-run it (read from stdin, ``<stdin>``), else None.

    "spawn" starts each worker by re-running the main script as ``__mp_main__``; a script that is not a file cannot
    be re-run and the pool would restart its crashing workers forever. No main script (``python -c``, a notebook)
    is fine: there is nothing to re-run.
    """
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    return main_file if main_file is not None and not os.path.isfile(main_file) else None


def refuse_in_spawned_main(path: str | os.PathLike[str], what: str) -> None:
    """Raise when a "spawn" worker re-running the main script from its top would wait to do ``what`` to ``path``.

    Called before waiting for ``path``'s lock (:func:`threedq.locks.exclusive`'s ``before_wait``). A script that
    makes data at its top level (no ``if __name__ == "__main__":`` guard) is re-run by each worker of the
    generator's or the pseudo-boxes' pool; the worker would wait for the lock its own parent holds, forever, while
    the parent waits for the worker. Raised instead, naming the script and the fix (the pool starts another
    worker, which says the same, until the run is stopped).

    Raises:
        RuntimeError: this process is a "spawn" worker still importing the main script.
    """
    # The flag "spawn" sets while a new process imports the parent's main script (what the standard library's own
    # "An attempt has been made to start a new process before ... bootstrapping" check reads).
    if not getattr(multiprocessing.current_process(), "_inheriting", False):
        return
    script = getattr(sys.modules.get("__mp_main__"), "__file__", None) or "the main script"
    raise RuntimeError(
        f"{os.fspath(path)}: a worker process of threedq's pool is re-running {script} from its top and reached "
        f"{what} again, which its parent is doing: start that script's work under `if __name__ == \"__main__\":` "
        "(Python's \"spawn\" workers import the main script); stop this run (Ctrl-C) and rerun"
    )
