"""What a ``threedq em`` run costs besides its training: stage start-up and pictures, on the test suite's tiny data.

Prints a markdown table: the median seconds of

* a whole ``run_em(rounds=2)`` on 12 generated scenes of 4 views at 32x32 (the tests' tiny dataset; GT boxes, no
  mining; 2 steps per stage): almost all of it is fixed cost, which every end-to-end test pays;
* one stage's start-up through ``ThreeDQCLI`` (``fit --print_config``: parsers built, the config parsed, nothing
  trained), with the parser of the named subcommand only (what ``ThreeDQCLI`` builds) and with all four of
  Lightning's (what ``LightningCLI`` builds);
* the retrieval and prototype-alignment pictures of an evaluation, drawn and encoded as PNG (60 crops of 16^3; the
  script runs on older commits too, where they were matplotlib figures written at 150 dpi).

    python benchmarks/bench_em_overhead.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from threedq.machine import cpu_name


def _median_s(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(min(2, os.cpu_count() or 1))

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
        rows.append(("`run_em(rounds=2)`, tiny data (7 stages, 7 evaluations)", _median_s(em, args.repeats)))
        start(ThreeDQCLI)
        rows.append(("one stage's start-up, the named subcommand's parser (ThreeDQCLI)",
                     _median_s(lambda: start(ThreeDQCLI), args.repeats)))
        rows.append(("one stage's start-up, all four subcommands' parsers (LightningCLI's way)",
                     _median_s(lambda: start(AllSubcommands), args.repeats)))
    g = torch.Generator().manual_seed(0)
    test = {"raw": torch.rand(60, 4, 16, 16, 16, generator=g), "labels": torch.randint(0, 5, (60,), generator=g)}
    cats = [f"category {i}" for i in range(5)]
    sim = torch.rand(60, 60, generator=g)
    clusters, angles = torch.randint(0, 4, (60,), generator=g), torch.randint(0, 36, (60,), generator=g)
    rows.append(("retrieval + prototype-alignment pictures, 60 crops", _median_s(
        lambda: (png(retrieval_figure(test, sim, cats)), png(alignment_figure(test, clusters, angles, 36, cats))),
        args.repeats)))
    print(f"# threedq em overhead, {torch.get_num_threads()} threads, cpu ({cpu_name()}), torch {torch.__version__}, "
          f"median of {args.repeats}\n")
    print("| what | seconds |\n|---|---|")
    for what, s in rows:
        print(f"| {what} | {s:.2f} |")


if __name__ == "__main__":
    main()
