"""M-step of the prototype EM: closed-form mean of the aligned members vs gradient descent on the paper's loss.

At a fixed assignment (prototype + yaw per object, from one E-step), the quantization loss
``mean_o ||M_k(o) - Rotate(e_o, -R_o)||^2`` is minimised by the mean of each prototype's aligned members.
This script measures it: loss and time of the closed form vs Adam (the paper's gradient update) after
several numbers of steps, on random crops or on saved object crops (``torch.save`` of a dict with a
``learned`` ``[N, C, 16, 16, 16]`` tensor, e.g. from :func:`threedq.pipeline.evaluation.collect_object_crops`).

    python benchmarks/bench_mstep.py                      # 1000 random 32 x 16^3 crops, K = 50
    python benchmarks/bench_mstep.py --crops crops.pt     # real crops
"""

from __future__ import annotations

import argparse
import datetime
import time

import torch

from threedq.machine import cpu_name
from threedq.quantization.prototypes import fit_prototype_bank, normalized, quantization_loss


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--crops", default=None, help="a torch file with a 'learned' [N, C, S, S, S] tensor")
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--k", type=int, default=50)
    ap.add_argument("--steps", type=int, nargs="+", default=[10, 50, 200, 1000])
    ap.add_argument("--lr", type=float, nargs="+", default=[1e-2, 1e-1])
    args = ap.parse_args()
    torch.manual_seed(0)
    if args.crops:
        crops = torch.load(args.crops, weights_only=True)["learned"].float()
        source = f"{args.crops} ({crops.shape[0]} crops)"
    else:
        crops = torch.randn(args.n, 32, 16, 16, 16)
        source = f"random ({args.n} crops)"
    crops = normalized(crops)
    bank = fit_prototype_bank(crops, num_prototypes=args.k, iterations=1, num_angles=36)
    res = bank.assign(crops)
    aligned = bank.canonical_rotation(crops, res)
    start = bank.prototypes.clone()
    before = float(quantization_loss(bank, crops, res))
    rows = [("E-step result (before the M-step)", before, 0.0)]
    t0 = time.perf_counter()
    bank.accumulate(crops, res)
    bank.update()
    rows.append(("closed form (mean of aligned members)", float(quantization_loss(bank, crops, res)), time.perf_counter() - t0))
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
    print(f"# M-step: closed form vs gradient descent, {source}, K = {args.k}; {cpu_name()}, "
          f"{torch.get_num_threads()} threads, torch {torch.__version__}, {datetime.date.today()}")
    print()
    print("| M-step | quantization loss | seconds |")
    print("|---|---|---|")
    for name, loss, sec in rows:
        print(f"| {name} | {loss:.4f} | {sec:.3f} |")


if __name__ == "__main__":
    main()
