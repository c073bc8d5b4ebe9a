"""InfoNCE against a MoCo queue, forward + backward: plain (``[P, 1 + Q]`` logits) vs streamed over the queue.

``threedq.contrastive.info_nce_plain`` against ``info_nce_streamed`` (chunks with an online log-sum-exp; by default the
query gradient in the same pass, or ``recompute=True``). Each variant runs in a fresh subprocess: the median wall time
of forward + backward, and the extra memory (growth of the peak resident set, ``VmHWM``; on CUDA
``torch.cuda.max_memory_allocated`` minus the memory before the runs).

    python benchmarks/bench_infonce.py                    # CPU, and CUDA when there is one
    python benchmarks/bench_infonce.py --device cpu --chunks 256 1024

Convention:
    Rows are samples: queries and positive keys ``[P, D]``, the queue ``[Q, D]``, all L2-normalised.
"""

from __future__ import annotations

import argparse
import datetime
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from _common import sync, table

from threedq.contrastive import info_nce_plain, info_nce_streamed
from threedq.machine import cpu_name


def vm_mib(field: str) -> float:
    """``VmHWM`` (peak resident set size so far) or ``VmRSS`` of this process, in MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no {field} in /proc/self/status")


def reset_peak_rss() -> float:
    """Reset ``VmHWM`` to the current resident set (``clear_refs`` 5, Linux >= 4.0); return the baseline in MiB.

    Without the reset, the peak left by making the inputs (temporaries already freed) would hide what the
    runs add; where the reset is refused, the baseline is the old peak and the growth a lower bound.
    """
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass
    return vm_mib("VmHWM")


def variant_name(variant: str) -> str:
    if variant == "plain":
        return "plain (cat + cross_entropy)"
    kind, chunk = variant.split(":")
    extra = ", recompute in backward" if kind == "recompute" else ""
    return f"streamed, chunk {chunk}{extra}"


def child(args: argparse.Namespace) -> None:
    """Time one variant on one device; print one JSON line."""
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    g = torch.Generator().manual_seed(0)
    q0 = F.normalize(torch.randn(args.p, args.d, generator=g), dim=1).to(device)
    k = F.normalize(torch.randn(args.p, args.d, generator=g), dim=1).to(device)
    queue = F.normalize(torch.randn(args.q, args.d, generator=g), dim=1).to(device)
    q = q0.clone().requires_grad_(True)
    if args.variant == "plain":
        def fn() -> torch.Tensor:
            return info_nce_plain(q, k, queue, args.temperature)
    else:
        kind, chunk = args.variant.split(":")

        def fn() -> torch.Tensor:
            return info_nce_streamed(q, k, queue, args.temperature, chunk=int(chunk), recompute=kind == "recompute")

    def step() -> float:
        q.grad = None
        sync(device)
        t0 = time.perf_counter()
        fn().backward()
        sync(device)
        return time.perf_counter() - t0

    sync(device)
    if cuda:
        base = torch.cuda.memory_allocated()
        torch.cuda.reset_peak_memory_stats()
    else:
        base = reset_peak_rss()
    for _ in range(args.warmup):
        step()
    times = [step() for _ in range(args.repeats)]
    if cuda:
        extra = (torch.cuda.max_memory_allocated() - base) / 2**20
        name = torch.cuda.get_device_name(device)
    else:
        extra = vm_mib("VmHWM") - base
        name = "cpu"
    with torch.no_grad():
        loss = float(fn())
    print(json.dumps({"ms": 1000 * statistics.median(times), "mib": extra, "device": name, "loss": loss}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--p", type=int, default=1024, help="queries (positives)")
    ap.add_argument("--q", type=int, default=100_000, help="queue size")
    ap.add_argument("--d", type=int, default=32, help="feature size")
    ap.add_argument("--temperature", type=float, default=0.07)
    ap.add_argument("--chunks", type=int, nargs="+", default=[256, 1024, 4096, 16384])
    ap.add_argument("--recompute-chunks", type=int, nargs="*", default=[1024],
                    help="chunk sizes also timed with recompute=True")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    ap.add_argument("--child", dest="variant", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.variant is not None:
        child(args)
        return
    devices = ["cpu", "cuda"] if args.device == "auto" else [args.device]
    if "cuda" in devices and not torch.cuda.is_available():
        if args.device == "cuda":
            raise SystemExit("--device cuda: CUDA is not available")
        devices.remove("cuda")
    variants = ["plain", *[f"streamed:{c}" for c in args.chunks], *[f"recompute:{c}" for c in args.recompute_chunks]]
    common = ["--p", str(args.p), "--q", str(args.q), "--d", str(args.d), "--temperature", str(args.temperature),
              "--threads", str(args.threads), "--repeats", str(args.repeats), "--warmup", str(args.warmup)]
    rows = []
    for device in devices:
        for variant in variants:
            cmd = [sys.executable, str(Path(__file__).resolve()), *common, "--device", device, "--child", variant]
            out = subprocess.run(cmd, capture_output=True, text=True, check=True)
            rows.append((variant, json.loads(out.stdout.strip().splitlines()[-1])))
    print(f"# InfoNCE forward + backward, {args.p} queries vs a {args.q} x {args.d} queue, fp32, "
          f"T = {args.temperature}; {cpu_name()}, {args.threads} threads, torch {torch.__version__}, "
          f"{datetime.date.today()}")
    print(f"# median of {args.repeats} after {args.warmup} warm-ups, one subprocess per row; extra MiB: CPU "
          f"VmHWM growth, CUDA max_memory_allocated over the inputs")
    print("\n" + table(["variant", "device", "ms (median)", "extra MiB"],
                       [(variant_name(v), r["device"], f"{r['ms']:.1f}", f"{r['mib']:.1f}") for v, r in rows]))
    plain = {r["device"]: r["loss"] for v, r in rows if v == "plain"}
    diff = max(abs(r["loss"] - plain[r["device"]]) for v, r in rows if v != "plain")
    print(f"\nmax |loss(streamed) - loss(plain)| = {diff:.2e}")


if __name__ == "__main__":
    main()
