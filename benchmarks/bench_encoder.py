"""Step time and achieved GFLOP/s of the 3D lifting U-Net (``threedq.nets.UNet3D``).

Prints a markdown table: per input grid, batch size, precision (fp32 / bf16 autocast), memory layout and pass
(inference forward / training forward + backward), the median wall time and the achieved GFLOP/s. FLOPs are counted
from the convolution shapes of one forward pass (2 x MACs; forward + backward = 3 x forward).

    python benchmarks/bench_encoder.py            # CPU, all configs (a few minutes on 2 cores)
    python benchmarks/bench_encoder.py --quick    # fewer configs
    python benchmarks/bench_encoder.py --device cuda

Convention:
    Grids are written ``X x Y x Z``; the input is ``[B, 4, Z, Y, X]``, the features ``[B, 32, Z/2, Y/2, X/2]``.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import math
import os
import statistics
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch
from _common import sync, table
from torch import Tensor, nn

from threedq.machine import cpu_name
from threedq.nets import UNet3D

#: Full sweep: (nx, ny, nz) input grids.
GRIDS: tuple[tuple[int, int, int], ...] = ((64, 64, 32), (64, 64, 64), (72, 72, 72))
QUICK_GRIDS: tuple[tuple[int, int, int], ...] = ((64, 64, 32), (72, 72, 72))
#: The paper's input grid (144^3 in -> 72^3 x 32 features).
PAPER_GRID = (144, 144, 144)


@dataclass(frozen=True)
class Config:
    grid: tuple[int, int, int]  # (nx, ny, nz)
    batch: int
    bf16: bool
    channels_last: bool
    backward: bool


@dataclass
class Result:
    config: Config
    median_s: float
    min_s: float
    gflop: float
    peak_mib: float | None


def conv_macs(model: nn.Module, x: Tensor) -> int:
    """Multiply-accumulates of all (transposed) 3D convolutions in one forward pass of ``model`` on ``x``
    (``[B, C, Z, Y, X]``), from the layer shapes: Conv3d ``B * C_out * prod(out) * C_in / groups * prod(k)``,
    ConvTranspose3d ``B * C_in * prod(in) * C_out / groups * prod(k)``."""
    total = 0

    def hook(module: nn.Module, inputs: tuple[Tensor, ...], output: Tensor) -> None:
        nonlocal total
        kernel, groups = math.prod(module.kernel_size), module.groups  # type: ignore[union-attr]
        if isinstance(module, nn.ConvTranspose3d):
            total += inputs[0].numel() * (module.out_channels // groups) * kernel
        else:
            total += output.numel() * (module.in_channels // groups) * kernel  # type: ignore[union-attr]

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, (nn.Conv3d, nn.ConvTranspose3d))]
    try:
        with torch.no_grad():
            was_training = model.training
            model.eval()
            model(x)
            model.train(was_training)
    finally:
        for h in handles:
            h.remove()
    return total


def bf16_supported(device: torch.device) -> bool:
    """Whether bf16 autocast is worth benchmarking on ``device``."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def make_step(model: nn.Module, x: Tensor, config: Config, device: torch.device) -> Callable[[], None]:
    """A closure running one forward (inference) or forward+backward (training) pass."""
    def autocast() -> contextlib.AbstractContextManager[None]:
        return torch.autocast(device.type, dtype=torch.bfloat16) if config.bf16 else contextlib.nullcontext()

    if config.backward:
        model.train()

        def step() -> None:
            for p in model.parameters():
                p.grad = None
            with autocast():
                out = model(x)
            out.float().mean().backward()
    else:
        model.eval()

        def step() -> None:
            with torch.inference_mode(), autocast():
                model(x)

    return step


def time_step(step: Callable[[], None], device: torch.device, warmup: int, repeats: int) -> list[float]:
    """Wall times (s) of ``repeats`` calls after ``warmup`` untimed calls."""
    for _ in range(warmup):
        step()
    sync(device)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        step()
        sync(device)
        times.append(time.perf_counter() - start)
    return times


def run_config(config: Config, device: torch.device, warmup: int, repeats: int) -> Result:
    """Build the model and input for ``config`` and time it."""
    torch.manual_seed(0)
    nx, ny, nz = config.grid
    model = UNet3D().to(device)
    x = torch.rand(config.batch, 4, nz, ny, nx, device=device)
    if config.channels_last:
        model = model.to(memory_format=torch.channels_last_3d)
        x = x.contiguous(memory_format=torch.channels_last_3d)
    gflop = 2 * conv_macs(model, x) * (3 if config.backward else 1) / 1e9
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    times = time_step(make_step(model, x, config, device), device, warmup, repeats)
    peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else None
    return Result(config, statistics.median(times), min(times), gflop, peak)


def configs(grids: tuple[tuple[int, int, int], ...], batches: tuple[int, ...], bf16: bool) -> Iterator[Config]:
    """All combinations, grouped by grid and batch."""
    for grid, batch, backward, use_bf16, channels_last in itertools.product(
            grids, batches, (False, True), (False, True) if bf16 else (False,), (False, True)):
        yield Config(grid, batch, use_bf16, channels_last, backward)


def format_row(r: Result, show_peak: bool) -> str:
    """One markdown table row."""
    c = r.config
    nx, ny, nz = c.grid
    cells = [f"{nx}x{ny}x{nz}", f"{nx // 2}x{ny // 2}x{nz // 2}", str(c.batch), "bf16 autocast" if c.bf16 else "fp32",
             "channels_last_3d" if c.channels_last else "contiguous", "fwd+bwd" if c.backward else "fwd",
             f"{r.median_s * 1e3:.1f}", f"{r.min_s * 1e3:.1f}", f"{r.gflop:.1f}", f"{r.gflop / r.median_s:.0f}"]
    if show_peak:
        cells.append(f"{r.peak_mib:.0f}" if r.peak_mib is not None else "-")
    return "| " + " | ".join(cells) + " |"


def load_average() -> str:
    """1/5/15-minute load averages, or "n/a" where the OS does not report them."""
    try:
        return "/".join(f"{v:.2f}" for v in os.getloadavg())
    except (AttributeError, OSError):
        return "n/a"


def main(argv: list[str] | None = None) -> None:
    """Parse arguments, run the sweep and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="device to benchmark on")
    parser.add_argument("--quick", action="store_true", help="batch 1, two grids, fewer repeats, no 144^3")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: CPUs available)")
    parser.add_argument("--warmup", type=int, default=None, help="untimed calls per config (default 2, quick 1)")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per config (default 5, quick 3)")
    parser.add_argument("--budget-s", type=float, default=240.0,
                        help="skip the 144^3 runs if they would push the total past this")
    args = parser.parse_args(argv)

    device = torch.device(args.device)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise SystemExit("--device cuda requested but CUDA is not available")
        torch.backends.cudnn.benchmark = True
    threads = args.threads or len(os.sched_getaffinity(0))
    torch.set_num_threads(threads)
    warmup = args.warmup if args.warmup is not None else (1 if args.quick else 2)
    repeats = args.repeats if args.repeats is not None else (3 if args.quick else 5)
    use_bf16 = bf16_supported(device)
    grids = QUICK_GRIDS if args.quick else GRIDS
    batches = (1,) if args.quick else (1, 2)
    show_peak = device.type == "cuda"
    hw = torch.cuda.get_device_name(device) if device.type == "cuda" else f"{cpu_name()}, {threads} threads"

    print(f"# UNet3D (paper widths 64/128/256 -> 32, {sum(p.numel() for p in UNet3D().parameters()):,} params)")
    print(f"torch {torch.__version__}, {hw}; median (and min) of {repeats} runs after {warmup} warm-up")
    print(f"load average at start: {load_average()} (other processes on a shared machine inflate the times)")
    print("fwd = eval + inference_mode; fwd+bwd = train mode, grads of mean(output), no optimizer step.")
    print("GFLOP: analytic from conv shapes, 2*MACs forward, fwd+bwd counted as 3x forward; BN/LReLU/norm ignored.")
    print("\n" + table(["input XxYxZ", "features", "B", "precision", "layout", "pass", "median ms", "min ms", "GFLOP",
                        "GFLOP/s"] + ["peak MiB"] * show_peak), flush=True)

    start = time.perf_counter()
    fwd_b1: dict[tuple[bool, bool], float] = {}
    for config in configs(grids, batches, use_bf16):
        result = run_config(config, device, warmup, repeats)
        if config.grid == (72, 72, 72) and config.batch == 1 and not config.backward:
            fwd_b1[(config.bf16, config.channels_last)] = result.median_s
        print(format_row(result, show_peak), flush=True)

    notes = []
    if not use_bf16:
        notes.append(f"bf16 skipped: not supported on this {device.type} device.")
    if not args.quick:
        precisions = (False, True) if use_bf16 else (False,)
        paper = [Config(PAPER_GRID, 1, bf16, cl, False) for bf16 in precisions for cl in (False, True)]
        if device.type == "cuda":
            paper += [Config(PAPER_GRID, 1, c.bf16, c.channels_last, True) for c in paper]
        for config in paper:
            # 144^3 costs ~8x the 72^3 forward; skip what would exceed the time budget.
            per_call = 8 * fwd_b1.get((config.bf16, config.channels_last), 0.0) * (3 if config.backward else 1)
            estimate = per_call * (warmup + repeats + 1)
            elapsed = time.perf_counter() - start
            if elapsed + estimate > args.budget_s:
                layout, kind = " channels_last_3d" if config.channels_last else "", "fwd+bwd" if config.backward else "fwd"
                notes.append(f"skipped 144^3 {'bf16' if config.bf16 else 'fp32'}{layout} {kind}: ~{estimate:.0f} s "
                             f"estimated, {elapsed:.0f} s of the {args.budget_s:.0f} s budget used")
                continue
            print(format_row(run_config(config, device, warmup, repeats), show_peak), flush=True)
        if device.type == "cpu":
            notes.append("144^3 (the paper's grid) is run forward-only at batch 1 on CPU.")
    print(f"\ntotal benchmark time: {time.perf_counter() - start:.0f} s; load average at end: {load_average()}")
    for note in notes:
        print(f"note: {note}")


if __name__ == "__main__":
    main()
