"""Time the miner's patch search (:func:`threedq.contrastive.miner.match_patch`) with and without a yaw window.

Prints median milliseconds per query (30 random 32 x 16^3 targets) for all 36 yaws and for windows of 1, 3 and 5
yaws, and checks that the window search equals the masked full search.

    python benchmarks/bench_match_patch.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import statistics
import time
from datetime import date

import torch
import torch.nn.functional as F

from threedq.contrastive.miner import _rotated_grid_patches, match_patch, patch_grid, yaw_angles
from threedq.machine import cpu_name


def _masked_full_search(q: torch.Tensor, pos: tuple[int, int, int], t: torch.Tensor, allowed: torch.Tensor):
    """The former computation: every target at all yaws, disallowed yaws masked before the argmax."""
    starts = [patch_grid(n, 4, 2) for n in t.shape[2:]]
    z, y, x = pos
    qv = F.normalize(q[:, z:z + 2, y:y + 2, x:x + 2].reshape(-1), dim=0)
    feats = F.normalize(_rotated_grid_patches(t, yaw_angles(36), starts, 2), dim=-1)
    cos = (feats @ qv).masked_fill(~allowed[:, :, None], float("-inf")).flatten(1)
    best, flat = cos.max(dim=1)
    return flat // feats.shape[2], best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    g = torch.Generator().manual_seed(0)
    q = F.normalize(torch.randn(32, 16, 16, 16, generator=g), dim=0)
    t = F.normalize(torch.randn(30, 32, 16, 16, 16, generator=g), dim=1)
    pos = (5, 9, 5)
    print(f"{cpu_name()}, {torch.get_num_threads()} threads, torch {torch.__version__}, {date.today()}\n")
    print("| yaws searched per target | masked full search ms | window search ms | speed-up | same yaw / cosine |")
    print("|---|---|---|---|---|")
    for width in (1, 3, 5, 36):
        allowed = torch.zeros(30, 36, dtype=torch.bool)
        for k in range(30):
            allowed[k, [(k + d) % 36 for d in range(-(width // 2), width - width // 2)]] = True
        times = {}
        for name, fn in (("full", lambda: _masked_full_search(q, pos, t, allowed)),
                         ("window", lambda: match_patch(q, pos, t, allowed_yaws=allowed))):
            fn()
            ts = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                fn()
                ts.append((time.perf_counter() - t0) * 1e3)
            times[name] = statistics.median(ts)
        yaw_a, cos_a = _masked_full_search(q, pos, t, allowed)
        yaw_b, _, cos_b = match_patch(q, pos, t, allowed_yaws=allowed)
        same = bool(torch.equal(yaw_a, yaw_b)) and bool(torch.allclose(cos_a, cos_b, atol=1e-6))
        print(f"| {width} of 36 | {times['full']:.1f} | {times['window']:.1f} | {times['full'] / times['window']:.1f}x | "
              f"{'yes' if same else 'NO'} |")


if __name__ == "__main__":
    main()
