"""How long a ``threedq`` command takes to reach its work: a new interpreter against a fork of one that has imported
threedq (``tests/forkserver.py``, what the end-to-end tests use).

Prints a markdown table, the median seconds (wall clock) of commands that end as soon as they have parsed their
arguments or found their first bad input:

* ``threedq --help`` (the subcommands listed; none of their modules is imported for it);
* ``threedq em --help`` (the em parser: imports Lightning and the pipeline);
* ``threedq data check <missing folder>`` (a data command's error: no Lightning);
* ``threedq fit --config <missing file>`` (a Lightning subcommand's error);

each as ``python -m threedq ...`` (a new interpreter, what a user runs) and through the fork server.

    python benchmarks/bench_cli_start.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from threedq.machine import cpu_name

ROOT = Path(__file__).resolve().parent.parent


def fork_server_class() -> type:
    """``tests/forkserver.py``'s ``ForkServer``, loaded from its file (the tests are no package)."""
    spec = importlib.util.spec_from_file_location("forkserver", ROOT / "tests" / "forkserver.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["forkserver"] = module
    spec.loader.exec_module(module)
    return module.ForkServer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    import torch

    with tempfile.TemporaryDirectory() as tmp:
        commands = [["--help"], ["em", "--help"], ["data", "check", str(Path(tmp) / "missing")],
                    ["fit", "--config", str(Path(tmp) / "missing.yaml")]]
        rows = []
        t0 = time.perf_counter()
        with fork_server_class()() as server:
            server.run(["--help"], cwd=tmp)  # waits for the server's imports
            start = time.perf_counter() - t0
            for argv in commands:
                new, forked = [], []
                for _ in range(args.repeats):
                    t = time.perf_counter()
                    subprocess.run([sys.executable, "-m", "threedq", *argv], cwd=tmp, capture_output=True)
                    new.append(time.perf_counter() - t)
                    t = time.perf_counter()
                    server.run(argv, cwd=tmp)
                    forked.append(time.perf_counter() - t)
                rows.append((" ".join(["threedq", *argv]).replace(tmp, "<tmp>"), statistics.median(new),
                             statistics.median(forked)))
    print(f"# threedq command start-up, cpu ({cpu_name()}), torch {torch.__version__}, median of {args.repeats}\n")
    print(f"The fork server's own start (its imports, once): {start:.2f} s\n")
    print("| command | new interpreter (s) | forked (s) |\n|---|---|---|")
    for what, a, b in rows:
        print(f"| `{what}` | {a:.2f} | {b:.2f} |")


if __name__ == "__main__":
    main()
