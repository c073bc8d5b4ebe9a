"""What a ``threedq`` run costs besides its training, one question a run (``--op``), median seconds:

* ``em`` (default): a whole ``run_em(rounds=2)`` on the tests' tiny dataset (12 scenes, 2 steps per stage); one
  stage's start-up through ``ThreeDQCLI`` (``fit --print_config``), with the named subcommand's parser only and with
  all four of Lightning's; and an evaluation's retrieval and prototype-alignment pictures (60 crops of 16^3);
* ``cli_start``: how long a command takes to reach its work, ``threedq --help``, ``threedq em --help``, ``threedq data
  check <missing folder>`` and ``threedq fit --config <missing file>``, each as a new interpreter (``python -m
  threedq ...``) and as a fork of one that has imported threedq (``tests/forkserver.py``).

    python benchmarks/bench_em_overhead.py [--repeats 3]
    python benchmarks/bench_em_overhead.py --op cli_start [--repeats 5]
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _common import machine, table

ROOT = Path(__file__).resolve().parent.parent


def _median_s(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def fork_server_class() -> type:
    """``tests/forkserver.py``'s ``ForkServer``, loaded from its file (the tests are no package)."""
    spec = importlib.util.spec_from_file_location("forkserver", ROOT / "tests" / "forkserver.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["forkserver"] = module
    spec.loader.exec_module(module)
    return module.ForkServer


def cli_start(repeats: int) -> None:
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
                for _ in range(repeats):  # interleaved
                    new.append(_median_s(lambda: subprocess.run([sys.executable, "-m", "threedq", *argv], cwd=tmp,
                                                                capture_output=True), 1))
                    forked.append(_median_s(lambda: server.run(argv, cwd=tmp), 1))
                rows.append((f"`{' '.join(['threedq', *argv]).replace(tmp, '<tmp>')}`",
                             f"{statistics.median(new):.2f}", f"{statistics.median(forked):.2f}"))
    print(f"# threedq command start-up, {machine()}, median of {repeats}\n")
    print(f"The fork server's own start (its imports, once): {start:.2f} s\n")
    print(table(["command", "new interpreter (s)", "forked (s)"], rows))


def em_overhead(repeats: int) -> None:
    from lightning.pytorch.cli import LightningCLI

    from threedq.data.generate import generate_dataset
    from threedq.data.generator_config import GeneratorConfig
    from threedq.pipeline.em import run_em
    from threedq.pipeline.lightning_cli import ThreeDQCLI
    from threedq.viz.features import alignment_figure, retrieval_figure
    from threedq.viz.png import figure_png, rgb_png

    def png(picture: object) -> bytes:
        return rgb_png(picture) if isinstance(picture, np.ndarray) else figure_png(picture, dpi=150)

    class AllSubcommands(ThreeDQCLI):
        def subcommands(self) -> dict[str, set[str]]:  # type: ignore[override]
            return LightningCLI.subcommands()

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data = tmp / "data"
        generate_dataset(data, num_scenes=12, seed=5, config=GeneratorConfig(image_size=(32, 32), num_views=4,
                         max_objects=3), split_fractions=(0.7, 0.15, 0.15), workers=1, progress=False)
        cfg = tmp / "tiny.yaml"
        cfg.write_text(
            "model:\n  init_args:\n    grid_resolution: [32, 32, 16]\n"
            f"data:\n  init_args:\n    data_dir: {data}\n    num_scenes: 12\n    image_size: [32, 32]\n"
            "    num_views: 4\n    generator_workers: 1\n"
            "trainer:\n  max_steps: 2\n  log_every_n_steps: 1\n  limit_val_batches: 1\n  check_val_every_n_epoch: 1\n"
            "  enable_progress_bar: false\n  enable_model_summary: false\n"
        )

        def em() -> None:
            shutil.rmtree(tmp / "em", ignore_errors=True)
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                run_em(rounds=2, work_dir=str(tmp / "em"), extra_configs=[str(cfg)], mining_config="none", boxes="gt")

        def start(cls: type) -> None:
            with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
                cls(args=["fit", "--config", "stages/viewpred.yaml", "--config", str(cfg), "--print_config"])

        em()  # warm-up: imports, first-use caches
        rows.append(("`run_em(rounds=2)`, tiny data (7 stages, 7 evaluations)", _median_s(em, repeats)))
        start(ThreeDQCLI)
        rows.append(("one stage's start-up, the named subcommand's parser (ThreeDQCLI)",
                     _median_s(lambda: start(ThreeDQCLI), repeats)))
        rows.append(("one stage's start-up, all four subcommands' parsers (LightningCLI's way)",
                     _median_s(lambda: start(AllSubcommands), repeats)))
    g = torch.Generator().manual_seed(0)
    test = {"raw": torch.rand(60, 4, 16, 16, 16, generator=g), "labels": torch.randint(0, 5, (60,), generator=g)}
    cats = [f"category {i}" for i in range(5)]
    sim = torch.rand(60, 60, generator=g)
    clusters, angles = torch.randint(0, 4, (60,), generator=g), torch.randint(0, 36, (60,), generator=g)
    rows.append(("retrieval + prototype-alignment pictures, 60 crops", _median_s(
        lambda: (png(retrieval_figure(test, sim, cats)), png(alignment_figure(test, clusters, angles, 36, cats))),
        repeats)))
    print(f"# threedq em overhead, {machine()}, median of {repeats}\n")
    print(table(["what", "seconds"], [(what, f"{s:.2f}") for what, s in rows]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--op", choices=["em", "cli_start"], default="em")
    ap.add_argument("--repeats", type=int, default=None, help="default: em 3, cli_start 5")
    args = ap.parse_args()
    if args.op == "cli_start":
        cli_start(args.repeats or 5)
    else:
        torch.set_num_threads(min(2, os.cpu_count() or 1))
        em_overhead(args.repeats or 3)


if __name__ == "__main__":
    main()
