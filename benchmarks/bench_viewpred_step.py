"""Time one view-prediction training step (forward, backward, Adam) and its parts.

Prints a markdown table: for fp32 and bf16 autocast, with and without channels_last_3d, the median time of a whole
step and of its parts on scenes rendered by the embedded generator (batch 2, 1 input + 1 target view, 128x128).

    python benchmarks/bench_viewpred_step.py [--repeats 5] [--grid 64 64 32] [--device cpu] [--channels 64 128 256]
        [--fp32_only] [--decoder 32 8] [--channels_last_only] [--compile] [--feature_stride 2 1]

``--decoder PLANES POOL`` (repeatable): the frustum's depth planes and the decoder's depth max-pool. ``--compile``
adds a row per configuration with the encoder under ``torch.compile``. ``--feature_stride`` (a row each): the
encoder's output stride.
"""

from __future__ import annotations

import argparse
import itertools
import os
import statistics
import tempfile
import time
from contextlib import nullcontext

import torch
from _common import sync, table

from threedq.data.generate import generate_dataset
from threedq.data.generator_config import GeneratorConfig
from threedq.datamodules.scene_folder import SceneFolderDataModule
from threedq.machine import cpu_name
from threedq.stages.viewpred import ViewPrediction


def time_step(model: ViewPrediction, batch: dict, opt: torch.optim.Optimizer, bf16: bool,
              device: str) -> dict[str, float]:
    ctx = torch.autocast(device_type=device.split(":")[0], dtype=torch.bfloat16) if bf16 else nullcontext()
    t: dict[str, float] = {}

    def mark(name: str, t0: float) -> float:
        sync(device)
        now = time.perf_counter()
        t[name] = now - t0
        return now

    sync(device)
    t_start = t0 = time.perf_counter()
    with ctx:
        n_in = batch["rgb"].shape[1] - 1
        rgb, depth, K, pose = (batch[k][:, :n_in].flatten(0, 1) for k in ("rgb", "depth", "K", "R_T_cam"))
        x, _ = model.encoder_input(rgb, depth, K, pose)
        if model.channels_last:
            x = x.contiguous(memory_format=torch.channels_last_3d)
        t0 = mark("unproject", t0)
        feats = model.encoder(x)
        logits = model.occ_head(feats)
        t0 = mark("encoder", t0)
        occ, free = model.occupancy_labels(batch["depth"], batch["K"], batch["R_T_cam"])
        t0 = mark("occ/free labels", t0)
        H, W = batch["rgb"].shape[-2:]
        pred = model.predict_view(feats, batch["K"][:, -1], batch["R_T_cam"][:, -1], (H, W))
        t0 = mark("frustum+decoder", t0)
        from threedq.nets import balanced_occupancy_loss, masked_l1

        target = torch.nn.functional.avg_pool2d(batch["rgb"][:, -1], 2) - 0.5
        loss = masked_l1(pred.float(), target, torch.ones_like(target[:, :1])) + balanced_occupancy_loss(
            logits.float(), occ, free
        )
    opt.zero_grad()
    loss.backward()
    opt.step()
    mark("backward+adam", t0)
    sync(device)
    t["step"] = time.perf_counter() - t_start
    return t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--grid", type=int, nargs=3, default=(64, 64, 32), help="nx ny nz of the input grid")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--channels", type=int, nargs=3, action="append",
                    help="the encoder's widths (repeatable: one row each; default the paper's 64 128 256)")
    ap.add_argument("--decoder", type=int, nargs=2, action="append", metavar=("PLANES", "POOL"),
                    help="the frustum's depth planes and the decoder's depth pool (repeatable; default 32 8)")
    ap.add_argument("--channels_last_only", action="store_true", help="only the channels_last_3d layout")
    ap.add_argument("--feature_stride", type=int, nargs="+", default=[2], choices=(1, 2),
                    help="the encoder's output stride(s): 2 (the paper's) and/or 1 (features on the input grid)")
    ap.add_argument("--compile", action="store_true", help="also each configuration with a torch.compile'd encoder")
    ap.add_argument("--fp32_only", action="store_true", help="skip bf16 autocast (emulated, very slow, on CPUs without "
                    "bf16 instructions)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        generate_dataset(tmp, num_scenes=2, seed=0, config=GeneratorConfig(), splits=("train",), workers=1,
                         progress=False)
        dm = SceneFolderDataModule(tmp, batch_size=2)
        dm.setup()
        batch = next(iter(dm.train_dataloader()))
    batch = {k: v.to(args.device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
    print(f"# view-prediction step, batch 2, 128x128, grid {tuple(args.grid)}, {args.threads} threads, {args.device} "
          f"({cpu_name() if args.device == 'cpu' else torch.cuda.get_device_name()}), "
          f"torch {torch.__version__}, median of {args.repeats} after 2 warm-ups\n")
    cols = ["unproject", "encoder", "occ/free labels", "frustum+decoder", "backward+adam", "step"]
    print(table(["encoder widths", "feature stride", "planes / pool", "precision", "layout", "encoder",
                 *(f"{c} ms" for c in cols)]))
    for channels, stride, (planes, pool), bf16, cl, compiled in itertools.product(
            args.channels or [(64, 128, 256)], args.feature_stride, args.decoder or [(32, 8)],
            (False,) if args.fp32_only else (False, True), (True,) if args.channels_last_only else (False, True),
            (False, True) if args.compile else (False,)):
        torch.manual_seed(0)
        model = ViewPrediction(grid_resolution=tuple(args.grid), encoder_channels=tuple(channels), channels_last=cl,
                               feature_stride=stride, num_planes=planes, pool=pool, image_every_n_steps=0)
        model = model.to(args.device)
        if compiled:
            model.encoder = torch.compile(model.encoder, dynamic=False)
        opt = torch.optim.Adam(model.parameters(), 1e-3)
        t0 = time.perf_counter()
        for _ in range(2):
            time_step(model, batch, opt, bf16, args.device)
        warm_s = time.perf_counter() - t0
        runs = [time_step(model, batch, opt, bf16, args.device) for _ in range(args.repeats)]
        med = {c: 1000 * statistics.median(r[c] for r in runs) for c in cols}
        enc = f"torch.compile (warm-ups {warm_s:.0f} s)" if compiled else "eager"
        print(f"| {'-'.join(map(str, channels))} | {stride} | {planes} / {pool} | "
              f"{'bf16 autocast' if bf16 else 'fp32'} | {'channels_last_3d' if cl else 'contiguous'} | "
              f"{enc} | " + " | ".join(f"{med[c]:.0f}" for c in cols) + " |")


if __name__ == "__main__":
    main()
