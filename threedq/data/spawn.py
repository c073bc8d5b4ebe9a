"""What a "spawn" process pool needs of this process (the dataset generator's and the pseudo-boxes' pools)."""

from __future__ import annotations

import os
import sys

__all__ = ["unspawnable_main"]


def unspawnable_main() -> str | None:
    """The main script's path when a "spawn" worker could not re-run it (read from stdin, ``<stdin>``), else None.

    "spawn" starts each worker by re-running the main script as ``__mp_main__``; a script that is not a file cannot
    be re-run and the pool would restart its crashing workers forever. No main script (``python -c``, a notebook)
    is fine: there is nothing to re-run.
    """
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    return main_file if main_file is not None and not os.path.isfile(main_file) else None
