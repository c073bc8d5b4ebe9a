"""What a "spawn" process pool needs of this process (the dataset generator's and the pseudo-boxes' pools)."""

from __future__ import annotations

import multiprocessing
import os
import sys

__all__ = ["refuse_in_spawned_main", "unspawnable_main"]


def unspawnable_main() -> str | None:
    """The main script's path when a "spawn" worker could not re-run it (not a file, e.g. ``<stdin>``), else None."""
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    return main_file if main_file is not None and not os.path.isfile(main_file) else None


def refuse_in_spawned_main(path: str | os.PathLike[str], what: str) -> None:
    """Raise ``RuntimeError`` when this "spawn" worker, re-running the main script from its top, would wait to do
    ``what`` to ``path`` (a lock its own parent holds): :func:`threedq.locks.exclusive`'s ``before_wait``."""
    # "spawn" sets this flag while a new process imports the parent's main script
    if not getattr(multiprocessing.current_process(), "_inheriting", False):
        return
    script = getattr(sys.modules.get("__mp_main__"), "__file__", None) or "the main script"
    raise RuntimeError(
        f"{os.fspath(path)}: a worker process of threedq's pool is re-running {script} from its top and reached "
        f'{what} again, which its parent is doing: start that script\'s work under `if __name__ == "__main__":` '
        '(Python\'s "spawn" workers import the main script); stop this run (Ctrl-C) and rerun')
