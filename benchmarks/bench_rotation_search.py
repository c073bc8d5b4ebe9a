"""Rotation search: naive vs prototypes-prerotated vs cylindrical + rFFT (``threedq.quantization.rotation_search``).

Markdown tables measured in one process (compare ratios, not absolute times): (a) prototype assignment, 1000 objects x
50 prototypes x 36 yaws on 32 x 16^3 crops (naive on a subset, scaled linearly; prerotated prototypes + one GEMM;
``method="fast"`` in fp32 and bf16, with and without the band limit), agreement with naive; (b) retrieval 1000 x 1000
x 36 yaws, exact ``rotation_max_similarity`` (a subset, scaled) vs ``all_pairs_rotation_max(method="fast")``, top-1
agreement. Data: "random" (Gaussian, L2-normalised per voxel) and "structured" (smooth asymmetric blobs, objects
rotated by a known multiple of 10 deg plus 5% noise).

Usage::

    python benchmarks/bench_rotation_search.py            # a few minutes on 2 cores
    python benchmarks/bench_rotation_search.py --quick    # smaller subsets, one repeat
    python benchmarks/bench_rotation_search.py --device cuda

Convention:
    Crops ``[N, C, Z, Y, X]``, z up; angle ``a`` = ``2 pi a / 36`` counter-clockwise seen from above, rotating the
    object (query) by ``a`` aligns it with the prototype (gallery crop).
"""

from __future__ import annotations

import argparse
import datetime
import math
import statistics
import time
from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from _common import sync, table
from torch import Tensor

from threedq.geometry import rotate_yaw, yaw_angles
from threedq.machine import cpu_name
from threedq.quantization.rotation_search import all_pairs_rotation_max, best_prototype_and_yaw, rotation_max_similarity

A = 36
C = 32
S = 16


def interleaved(methods: dict[str, Callable[[], Any]], device: torch.device, repeats: int,
                warmups: dict[str, Callable[[], Any]]) -> dict[str, tuple[float, float, Any]]:
    """Round-robin timing: after one warm-up each (``warmups[label]`` where given), ``repeats`` rounds that run every
    method once. Returns ``label -> (min s, median s, last result)``."""
    for label, fn in methods.items():
        warmups.get(label, fn)()
    sync(device)
    times: dict[str, list[float]] = {label: [] for label in methods}
    results: dict[str, Any] = {}
    for _ in range(repeats):
        for label, fn in methods.items():
            t0 = time.perf_counter()
            results[label] = fn()
            sync(device)
            times[label].append(time.perf_counter() - t0)
    return {label: (min(t), statistics.median(t), results[label]) for label, t in times.items()}


def random_crops(n: int, device: torch.device, seed: int) -> Tensor:
    """i.i.d. Gaussian features, L2-normalised per voxel (like the encoder's output)."""
    gen = torch.Generator(device="cpu").manual_seed(seed)
    return F.normalize(torch.randn(n, C, S, S, S, generator=gen), dim=1).to(device)


def blob_crops(n: int, device: torch.device, seed: int, gaussians: int = 4) -> Tensor:
    """Distinct smooth asymmetric crops: a few anisotropic Gaussians near the axis, each with a random channel
    signature (random positive offset), built in chunks of fp32."""
    gen = torch.Generator(device="cpu").manual_seed(seed)
    coords = torch.arange(S, dtype=torch.float32) - (S - 1) / 2
    zz, yy, xx = (t[None, None] for t in torch.meshgrid(coords, coords, coords, indexing="ij"))
    out = torch.empty(n, C, S, S, S)
    for start in range(0, n, 128):
        m = min(128, n - start)
        rad = 0.28 * S * torch.rand(m, gaussians, generator=gen).sqrt()
        ang = 2 * math.pi * torch.rand(m, gaussians, generator=gen)
        cx, cy = (rad * torch.cos(ang))[..., None, None, None], (rad * torch.sin(ang))[..., None, None, None]
        cz = ((torch.rand(m, gaussians, generator=gen) * 2 - 1) * 0.25 * S)[..., None, None, None]
        sig = (S / 16) * (1.2 + 1.5 * torch.rand(m, gaussians, 3, generator=gen))
        sx, sy, sz = (sig[..., i, None, None, None] for i in range(3))
        g = torch.exp(-((xx - cx) ** 2 / (2 * sx**2) + (yy - cy) ** 2 / (2 * sy**2) + (zz - cz) ** 2 / (2 * sz**2)))
        w = torch.randn(m, gaussians, C, generator=gen) + 0.5
        out[start : start + m] = torch.einsum("ngzyx,ngc->nczyx", g, w)
    return out.to(device)


def rotated_copies(bank: Tensor, index: Tensor, seed: int, noise: float = 0.05) -> tuple[Tensor, Tensor]:
    """Crops ``bank[index]`` rotated by ``-a`` steps (+ noise), and ``a`` (rotating back by ``a`` aligns them)."""
    gen = torch.Generator(device="cpu").manual_seed(seed)
    a = torch.randint(A, (index.shape[0],), generator=gen).to(bank.device)
    out = torch.empty(index.shape[0], *bank.shape[1:], device=bank.device)
    for start in range(0, index.shape[0], 128):
        sl = slice(start, start + 128)
        out[sl] = rotate_yaw(bank[index[sl]], -yaw_angles(A, device=bank.device)[a[sl]])
    scale = noise * out.std()
    out += scale * torch.randn(out.shape, generator=gen).to(bank.device)
    return out, a


def prerotated_search(objects: Tensor, prototypes: Tensor) -> tuple[Tensor, Tensor]:
    """Prototypes rotated by every ``-yaw`` (K * A copies) + one GEMM: cos(object, rotate(prototype, -a))."""
    k = prototypes.shape[0]
    angles = -yaw_angles(A, device=prototypes.device, dtype=prototypes.dtype)
    rotated = F.normalize(rotate_yaw(prototypes, angles.expand(k, A)).flatten(2), dim=2)  # [K, A, D]
    obj = F.normalize(objects.flatten(1), dim=1)
    scores = obj @ rotated.reshape(k * A, -1).T  # [N, K*A]
    flat = scores.argmax(dim=1)
    return flat // A, flat % A


def step_distance(a: Tensor, b: Tensor) -> Tensor:
    d = (a - b).abs() % A
    return torch.minimum(d, A - d)


def agreement(proto: Tensor, angle: Tensor, ref_proto: Tensor, ref_angle: Tensor) -> str:
    same = (proto == ref_proto) & (angle == ref_angle)
    near = (proto == ref_proto) & (step_distance(angle, ref_angle) <= 1)
    return f"{same.float().mean().item():.3f} ({near.float().mean().item():.3f})"


def fmt_t(t_min: float, t_med: float) -> str:
    t_min, t_med = (f"{t * 1000:.0f} ms" if t < 1 else f"{t:.2f} s" for t in (t_min, t_med))
    return f"{t_min} ({t_med})"


def prototype_table(device: torch.device, args: argparse.Namespace) -> list[str]:
    n, k, sub = args.objects, args.prototypes, args.naive_objects
    scale = n / sub
    rows = [table(["method", "random: time min (median)", "x naive (min)", "agrees w/ naive (+-1 step)",
                   "structured: agrees w/ naive", "structured: = truth"])]
    rnd_p, rnd_o = random_crops(k, device, 1), random_crops(n, device, 2)
    st_p = blob_crops(k, device, 3)
    idx = torch.randint(k, (n,), generator=torch.Generator().manual_seed(4)).to(device)
    st_o, st_a = rotated_copies(st_p, idx, seed=5)

    def fast(o: Tensor, p: Tensor, dtype: torch.dtype | None, band: bool) -> tuple[Tensor, Tensor]:
        r = best_prototype_and_yaw(o, p, A, "fast", compute_dtype=dtype, bandlimit=band)
        return r.prototype, r.angle

    def naive(o: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        r = best_prototype_and_yaw(o, p, A, "exact")
        return r.prototype, r.angle

    naive_label = f"naive: rotate every object x36 + GEMM (measured on {sub} objects, x{scale:g} scaled)"
    fns: dict[str, Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]] = {
        naive_label: lambda o, p: naive(o[:sub], p),
        "prototypes prerotated x36 (1800 copies) + one GEMM": prerotated_search,
    }
    for dtype, name in ((None, "fp32"), (torch.bfloat16, "bf16")):
        for band in (True, False):
            label = f"fast: cylindrical + rFFT, {name}" + ("" if band else ", no band limit")
            fns[label] = lambda o, p, dtype=dtype, band=band: fast(o, p, dtype, band)
    timing = interleaved({label: (lambda fn=fn: fn(rnd_o, rnd_p)) for label, fn in fns.items()}, device,
                         args.repeats, warmups={naive_label: lambda: naive(rnd_o[:2], rnd_p)})
    t_naive, ref_r, ref_s = timing[naive_label][0] * scale, timing[naive_label][2], naive(st_o[:sub], st_p)
    for label, fn in fns.items():
        t_min, t_med, (p_r, a_r) = timing[label]
        if label == naive_label:
            t_min, t_med = t_min * scale, t_med * scale
            p_s, a_s = ref_s
            truth_cell = agreement(p_s, a_s, idx[:sub], st_a[:sub])
        else:
            p_s, a_s = fn(st_o, st_p)
            truth_cell = agreement(p_s, a_s, idx, st_a)
        agree = f"{agreement(p_r[:sub], a_r[:sub], *ref_r)} | {agreement(p_s[:sub], a_s[:sub], *ref_s)}"
        rows.append(f"| {label} | {fmt_t(t_min, t_med)} | {t_naive / t_min:.0f}x | {agree} | {truth_cell} |")
    return rows


def retrieval_table(device: torch.device, args: argparse.Namespace) -> list[str]:
    n = m = args.gallery
    sub, scale = args.exact_queries, n / args.exact_queries
    rows = [table(["method", "random: time min (median)", "x exact (min)", "top-1 = exact", "structured: top-1 = exact",
                   "structured: top-1 = truth", "structured: angle at top-1 = exact"])]
    rnd_q, rnd_g = random_crops(n, device, 6), random_crops(m, device, 7)
    st_g = blob_crops(m, device, 8)
    perm = torch.randperm(m, generator=torch.Generator().manual_seed(9)).to(device)
    st_q, _ = rotated_copies(st_g, perm, seed=10)

    exact_label = f"exact: rotation_max_similarity fp32, chunk 16 (measured on {sub} queries, x{scale:g} scaled)"
    fns: dict[str, Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]] = {
        exact_label: lambda q, g: rotation_max_similarity(q[:sub], g, A, chunk=16),
    }
    for dtype, name in ((None, "fp32"), (torch.bfloat16, "bf16")):
        for band in (True, False):
            label = f"fast: all_pairs_rotation_max, {name}" + ("" if band else ", no band limit")
            fns[label] = lambda q, g, dtype=dtype, band=band: all_pairs_rotation_max(q, g, A, "fast",
                                                                                    compute_dtype=dtype, bandlimit=band)
    warm = {exact_label: lambda: rotation_max_similarity(rnd_q[:2], rnd_g, A, chunk=16)}
    timing = interleaved({label: (lambda fn=fn: fn(rnd_q, rnd_g)) for label, fn in fns.items()}, device, args.repeats,
                         warmups=warm)
    t_exact = timing[exact_label][0] * scale
    top_r = timing[exact_label][2][0].argmax(dim=1)
    sim_s, ang_s = rotation_max_similarity(st_q[:sub], st_g, A, chunk=16)
    top_s = sim_s.argmax(dim=1)
    rows_sub = torch.arange(sub, device=device)
    for label, fn in fns.items():
        t_min, t_med, (fs_r, _) = timing[label]
        if label == exact_label:
            t_min, t_med = t_min * scale, t_med * scale
            fs_s, fa_s, ft_all = sim_s, ang_s, None
        else:
            fs_s, fa_s = fn(st_q, st_g)
            ft_all = fs_s.argmax(dim=1)
        ft_r, ft_s = fs_r.argmax(dim=1), fs_s[:sub].argmax(dim=1)
        angle_ok = (fa_s[rows_sub, ft_s] == ang_s[rows_sub, top_s]) & (ft_s == top_s)
        truth = (ft_s == perm[:sub]) if ft_all is None else (ft_all == perm)
        rate = lambda x: f"{x.float().mean().item():.3f}"
        rows.append(f"| {label} | {fmt_t(t_min, t_med)} | {t_exact / t_min:.0f}x | {rate(ft_r[:sub] == top_r)} | "
                    f"{rate(ft_s == top_s)} | {rate(truth)} | {rate(angle_ok)} |")
    return rows


def matmul_gflops(device: torch.device) -> str:
    """Achieved fp32 / bf16 GEMM GFLOP/s right now (2048^3): how loaded the machine is."""
    out = []
    for dtype in (torch.float32, torch.bfloat16):
        a = torch.randn(2048, 2048, device=device).to(dtype)
        t = interleaved({"": lambda a=a: a @ a}, device, 3, {})[""][1]
        out.append(f"{str(dtype).removeprefix('torch.')} {2 * 2048**3 / t / 1e9:.0f}")
    return ", ".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--quick", action="store_true", help="smaller naive/exact subsets, one repeat")
    parser.add_argument("--objects", type=int, default=1000, help="objects in (a)")
    parser.add_argument("--prototypes", type=int, default=50, help="prototypes in (a)")
    parser.add_argument("--gallery", type=int, default=1000, help="queries = gallery crops in (b)")
    args = parser.parse_args()
    device = torch.device(args.device)
    args.repeats = 1 if args.quick else 5
    args.naive_objects = min(args.objects, 20 if args.quick else 50)
    args.exact_queries = min(args.gallery, 20 if args.quick else 50)
    torch.manual_seed(0)

    print("# Rotation search benchmark\n")
    dev = torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_name()
    print(f"- machine: {dev}; torch threads: {torch.get_num_threads()}; torch {torch.__version__}; "
          f"device {device}")
    print(f"- date: {datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}")
    print(f"- crops {C} x {S}^3 fp32, {A} yaw steps; every method warmed up once (the cached interpolation matrix is "
          f"built then), then {args.repeats} interleaved rounds (each method once per round): min and median; "
          "naive/exact are run on a subset of objects/queries each round and scaled linearly (their cost is linear "
          "in the number of objects/queries)\n")
    print(f"- GEMM GFLOP/s at start (load probe; idle roofs here ~210 fp32, ~900 bf16): {matmul_gflops(device)}\n")
    print(f"## (a) {args.objects} objects x {args.prototypes} prototypes x {A} yaw\n")
    print("\n".join(prototype_table(device, args)))
    print("\nAgreement: same prototype and same angle as naive on the naive-measured objects (in brackets: angle "
          f"within one step). '= truth': the known prototype and angle of the rotated copies, all {args.objects} "
          "objects (naive: its measured subset).\n")
    print(f"## (b) retrieval {args.gallery} x {args.gallery} x {A}\n")
    print("\n".join(retrieval_table(device, args)))
    print(f"\n- GEMM GFLOP/s at end: {matmul_gflops(device)}")
    print("\nTop-1 agreement on the exact-measured queries; structured queries are rotated noisy copies of distinct "
          "gallery crops (truth = their source).")


if __name__ == "__main__":
    main()
