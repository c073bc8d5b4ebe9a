"""The prototype EM (what every quantizer stage and every bank of ``threedq eval`` runs) with each chunk's polar
spectrum computed once vs recomputed at every comparison, and with each object's rotation into its prototype's pose
kept between M-steps (redone when its yaw changes) vs redone at every M-step: seconds, and whether the banks are
bit-identical.

The crops are clustered smooth volumes (60 base shapes, noise added, L2-normalised over channels), 32 x 16^3 like the
learned crops; K = 50, 36 yaw steps, 10 E/M iterations, fast search; optionally under bf16 autocast, as
``threedq em`` runs its frozen-encoder stages.

    python benchmarks/bench_prototype_em.py                  # N = 1121 (the main job's round-4 training objects)
    python benchmarks/bench_prototype_em.py --n 2000 --bf16
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import time

import torch

from threedq.machine import cpu_name
from threedq.quantization.prototypes import PrototypeBank, run_prototype_em


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=1121)
    ap.add_argument("--k", type=int, default=50)
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--bf16", action="store_true", help="under bf16 autocast (threedq em's frozen stages)")
    args = ap.parse_args()
    g = torch.Generator().manual_seed(0)
    base = torch.nn.functional.avg_pool3d(torch.randn(60, 32, 16, 16, 16, generator=g), 5, 1, 2)
    crops = base[torch.randint(0, 60, (args.n,), generator=g)] + 0.3 * torch.randn(args.n, 32, 16, 16, 16, generator=g)
    crops = torch.nn.functional.normalize(crops, dim=1)
    ctx = torch.autocast("cpu", dtype=torch.bfloat16) if args.bf16 else contextlib.nullcontext()
    rows, banks = [], []
    ways = [("spectra recomputed at every comparison, every object rotated at every M-step",
             {"reuse_spectra": False, "reuse_aligned": False}),
            ("spectra computed once per chunk, every object rotated at every M-step",
             {"reuse_spectra": True, "reuse_aligned": False}),
            ("spectra once, rotations kept until an object's yaw changes (`reuse_aligned`, default)",
             {"reuse_spectra": True, "reuse_aligned": True})]
    for _, kw in ways:
        bank = PrototypeBank(args.k, 32, 16, 36, 0.8)
        with ctx:
            t0 = time.perf_counter()
            run_prototype_em(bank, crops, args.iterations, seed=0, **kw)
            rows.append(time.perf_counter() - t0)
        banks.append(bank)
    same = all(torch.equal(banks[0].prototypes, b.prototypes) and torch.equal(banks[0].active, b.active)
               for b in banks[1:])
    print(f"# prototype EM, {args.n} crops 32 x 16^3, K = {args.k}, {args.iterations} iterations, fast search"
          f"{', bf16 autocast' if args.bf16 else ''}; {cpu_name()}, {torch.get_num_threads()} threads, torch "
          f"{torch.__version__}, {datetime.date.today()}")
    print("| way | seconds |")
    print("|---|---|")
    for (name, _), t in zip(ways, rows, strict=True):
        print(f"| {name} | {t:.1f} |")
    print(f"banks bit-identical: {same}")


if __name__ == "__main__":
    main()
