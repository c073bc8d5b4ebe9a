"""The prototype EM, one question a run (``--op``), on K = 50 banks of 32 x 16^3 crops:

* ``em`` (default): each chunk's polar spectrum computed once vs at every comparison, and each object's rotation into
  its prototype's pose kept between M-steps vs redone: seconds, and whether the banks are bit-identical; clustered
  smooth volumes (60 base shapes, noise added), 36 yaws, fast search, optionally under bf16 autocast;
* ``mstep``: at a fixed assignment, loss and time of the closed-form M-step (mean of the aligned members) vs Adam on
  the paper's loss after several numbers of steps, on random crops or on saved object crops (``--crops``: a
  ``torch.save`` of a dict with a ``learned`` ``[N, C, 16, 16, 16]`` tensor).

    python benchmarks/bench_prototype_em.py                  # N = 1121 (the main job's round-4 training objects)
    python benchmarks/bench_prototype_em.py --n 2000 --bf16
    python benchmarks/bench_prototype_em.py --op mstep       # 1000 random 32 x 16^3 crops
    python benchmarks/bench_prototype_em.py --op mstep --crops crops.pt
"""

from __future__ import annotations

import argparse
import contextlib
import time

import torch
from _common import machine, table

from threedq.quantization.prototypes import (PrototypeBank, fit_prototype_bank, normalized, quantization_loss,
                                             run_prototype_em)


def mstep(args: argparse.Namespace) -> None:
    torch.manual_seed(0)
    if args.crops:
        crops = torch.load(args.crops, weights_only=True)["learned"].float()
        source = f"{args.crops} ({crops.shape[0]} crops)"
    else:
        crops = torch.randn(args.n or 1000, 32, 16, 16, 16)
        source = f"random ({args.n or 1000} crops)"
    crops = normalized(crops)
    bank = fit_prototype_bank(crops, num_prototypes=args.k, iterations=1, num_angles=36)
    res = bank.assign(crops)
    aligned, start = bank.canonical_rotation(crops, res), bank.prototypes.clone()
    rows = [("E-step result (before the M-step)", float(quantization_loss(bank, crops, res)), 0.0)]
    t0 = time.perf_counter()
    bank.accumulate(crops, res)
    bank.update()
    rows.append(("closed form (mean of aligned members)", float(quantization_loss(bank, crops, res)),
                 time.perf_counter() - t0))
    for lr in args.lr:
        protos = start.clone().requires_grad_(True)
        opt = torch.optim.Adam([protos], lr=lr)
        done, t = 0, 0.0
        for steps in sorted(args.steps):
            t0 = time.perf_counter()
            for _ in range(steps - done):
                loss = (protos[res.prototype] - aligned).pow(2).flatten(1).sum(1).mean()
                opt.zero_grad()
                loss.backward()
                opt.step()
            t += time.perf_counter() - t0
            done = steps
            with torch.no_grad():
                final = float((protos[res.prototype] - aligned).pow(2).flatten(1).sum(1).mean())
            rows.append((f"Adam lr {lr:g}, {steps} steps", final, t))
    print(f"# M-step: closed form vs gradient descent, {source}, K = {args.k}; {machine()}\n")
    print(table(["M-step", "quantization loss", "seconds"],
                [(name, f"{loss:.4f}", f"{sec:.3f}") for name, loss, sec in rows]))


def em(args: argparse.Namespace) -> None:
    n = args.n or 1121
    g = torch.Generator().manual_seed(0)
    base = torch.nn.functional.avg_pool3d(torch.randn(60, 32, 16, 16, 16, generator=g), 5, 1, 2)
    crops = base[torch.randint(0, 60, (n,), generator=g)] + 0.3 * torch.randn(n, 32, 16, 16, 16, generator=g)
    crops = torch.nn.functional.normalize(crops, dim=1)
    ctx = torch.autocast("cpu", dtype=torch.bfloat16) if args.bf16 else contextlib.nullcontext()
    rows, banks = [], []
    ways = [("spectra recomputed at every comparison, every object rotated at every M-step", False, False),
            ("spectra computed once per chunk, every object rotated at every M-step", True, False),
            ("spectra once, rotations kept until an object's yaw changes (`reuse_aligned`, default)", True, True)]
    for _, spectra, aligned in ways:
        bank = PrototypeBank(args.k, 32, 16, 36, 0.8)
        with ctx:
            t0 = time.perf_counter()
            run_prototype_em(bank, crops, args.iterations, seed=0, reuse_spectra=spectra, reuse_aligned=aligned)
            rows.append(time.perf_counter() - t0)
        banks.append(bank)
    same = all(torch.equal(banks[0].prototypes, b.prototypes) and torch.equal(banks[0].active, b.active)
               for b in banks[1:])
    print(f"# prototype EM, {n} crops 32 x 16^3, K = {args.k}, {args.iterations} iterations, fast search"
          f"{', bf16 autocast' if args.bf16 else ''}; {machine()}")
    print(table(["way", "seconds"], [(w[0], f"{t:.1f}") for w, t in zip(ways, rows, strict=True)]))
    print(f"banks bit-identical: {same}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--op", choices=["em", "mstep"], default="em")
    ap.add_argument("--n", type=int, default=None, help="random crops (default: em 1121, mstep 1000)")
    ap.add_argument("--k", type=int, default=50)
    ap.add_argument("--iterations", type=int, default=10, help="em: EM iterations")
    ap.add_argument("--bf16", action="store_true", help="em: under bf16 autocast (threedq em's frozen stages)")
    ap.add_argument("--crops", default=None, help="mstep: a torch file with a 'learned' [N, C, S, S, S] tensor")
    ap.add_argument("--steps", type=int, nargs="+", default=[10, 50, 200, 1000], help="mstep: Adam steps")
    ap.add_argument("--lr", type=float, nargs="+", default=[1e-2, 1e-1], help="mstep: Adam rates")
    args = ap.parse_args()
    {"em": em, "mstep": mstep}[args.op](args)


if __name__ == "__main__":
    main()
