"""Per-scene latency of ``threedq parse`` by part, at the default scale and at the paper's, and bf16's agreement.

Parts (:meth:`threedq.pipeline.parse.SceneParser.forward`, one scene, one input view): unproject, encode, detect,
crop, rotation search against K = 50 prototypes x 36 yaws. Scales: default (128 px view, 64 x 64 x 32 grid) and paper
(256 px, 144^3). Random weights, 3 objects per scene; modes fp32, fp32 under ``torch.inference_mode`` and bf16
autocast, each with ``channels_last_3d``. With ``--run`` and ``--scenes`` it also parses the test split in fp32 and
bf16 on the same boxes and prints how often prototype id and yaw agree.

    python benchmarks/bench_parse.py                                  # both scales, ~2 min on 2 cores
    python benchmarks/bench_parse.py --run runs/em --scenes data/clevr_veggie
    python benchmarks/bench_parse.py --device cuda
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _common import machine, table

from threedq.pipeline.parse import RunArtifacts, SceneParser, find_scenes, parse_records, resolve_run
from threedq.quantization.prototypes import PrototypeBank
from threedq.scene import load_scene
from threedq.stages.detector import Detector

SCALES = {
    "default (128^2 view, 64x64x32 grid)": ((128, 128), (-1.28, -1.28, -0.32), (1.28, 1.28, 0.96), (64, 64, 32)),
    "paper (256^2 view, 144^3 grid)": ((256, 256), (-1.44, -1.44, -0.32), (1.44, 1.44, 2.56), (144, 144, 144)),
}
PARTS = ("unproject", "encode", "detect", "crop", "search")


def random_parser(tmp: Path, grid_min, grid_max, res, precision: str, device: str) -> SceneParser:
    """A :class:`SceneParser` over random weights: a detector checkpoint and a quantizer-like one with 50 prototypes."""
    torch.manual_seed(0)
    det = Detector(grid_min=grid_min, grid_max=grid_max, grid_resolution=res, feature_dim=32)
    hp = {"grid_min": list(grid_min), "grid_max": list(grid_max), "grid_resolution": list(res), "feature_dim": 32}
    torch.save({"state_dict": det.state_dict(), "hyper_parameters": {**hp, "score_threshold": 0.5}}, tmp / "det.ckpt")
    bank = PrototypeBank(50, 32, 16, 36)
    bank.prototypes.copy_(torch.nn.functional.normalize(torch.randn_like(bank.prototypes), dim=1))
    bank.active.fill_(True)
    state = {**{f"bank.{k}": v for k, v in bank.state_dict().items()},
             **{f"encoder.{k}": v for k, v in det.encoder.state_dict().items()}}  # fmt: skip
    hq = {**hp, "num_prototypes": 50, "crop_size": 16, "num_angles": 36}
    torch.save({"state_dict": state, "hyper_parameters": hq}, tmp / "q.ckpt")
    art = RunArtifacts(encoder=tmp / "q.ckpt", detector=tmp / "det.ckpt", prototypes=tmp / "q.ckpt")
    return SceneParser(art, score_threshold=0.5, precision=precision).to(device)


def scene(image: tuple[int, int], grid_min, grid_max, device: str) -> dict[str, torch.Tensor]:
    """One synthetic view looking down at the grid centre from 2.5 m (a plane and a box of depth)."""
    H, W = image
    f = 1.1 * W
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    c = np.array([(a + b) / 2 for a, b in zip(grid_min, grid_max)])
    eye = c + np.array([0.0, -2.2, 1.4])
    fwd = (c - eye) / np.linalg.norm(c - eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, fwd], 1)
    pose[:3, 3] = eye
    g = torch.Generator().manual_seed(0)
    depth = 2.0 + 0.8 * torch.rand(H, W, generator=g)
    return {"rgb": torch.rand(1, 1, 3, H, W, generator=g).to(device), "depth": depth[None, None].to(device),
            "K": K[None, None].to(device), "R_T_cam": torch.tensor(pose, dtype=torch.float32)[None, None].to(device)}


def three_boxes(grid_min, grid_max) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """3 boxes of 0.5 m standing on z = 0 around the grid centre (a typical embedded scene's objects)."""
    cx, cy = ((a + b) / 2 for a, b in zip(grid_min[:2], grid_max[:2]))
    rows = [[cx + dx - 0.25, cy + dy - 0.25, 0.0, cx + dx + 0.25, cy + dy + 0.25, 0.5]
            for dx, dy in ((-0.5, 0.0), (0.4, 0.3), (0.1, -0.5))]  # fmt: skip
    return [(torch.tensor(rows), torch.ones(3))]


def time_parts(parser: SceneParser, batch, boxes, repeats: int, inference: bool) -> dict[str, float]:
    """Median seconds of each part over ``repeats`` parses (after one warm-up), 3 objects per scene."""
    ctx = torch.inference_mode if inference else contextlib.nullcontext
    samples: dict[str, list[float]] = {p: [] for p in (*PARTS, "total")}
    with ctx():
        for r in range(repeats + 1):
            res = parser(batch)  # detection at 0.5 on random weights: NMS over many candidates
            res3 = parser(batch, boxes)  # 3 boxes matched (crop + search on 3 objects)
            if r == 0:
                continue
            t = {**{k: res["timings"][k] for k in ("unproject", "encode", "detect")},
                 **{k: res3["timings"][k] for k in ("crop", "search")}}  # fmt: skip
            for k, v in t.items():
                samples[k].append(v)
            samples["total"].append(sum(t.values()))
    return {k: statistics.median(v) for k, v in samples.items()}


def agreement(run: str, scenes: str, limit: int) -> list[str]:
    """fp32 vs bf16 parses of the run's test split: prototype+yaw agreement on fp32's boxes, and box agreement."""
    art = resolve_run(run)
    root, files = find_scenes(scenes, "test")
    files = files[:limit]
    recs = [load_scene(root / f) for f in files]
    views = [[0]] * len(recs)
    p32, p16 = SceneParser(art), SceneParser(art, precision="bf16")
    t0 = time.perf_counter()
    a = parse_records(p32, recs, views)
    t32 = time.perf_counter() - t0
    boxes = [(np.array([o["box"] for o in s["objects"]], np.float32).reshape(-1, 6),
              np.array([o["score"] for o in s["objects"]], np.float32)) for s in a]  # fmt: skip
    t0 = time.perf_counter()
    b = parse_records(p16, recs, views, boxes=boxes)
    t16 = time.perf_counter() - t0
    own = parse_records(p16, recs, views)
    pairs = [(x, y) for sa, sb in zip(a, b) for x, y in zip(sa["objects"], sb["objects"])]
    same = sum(x["prototype"] == y["prototype"] and x["angle_index"] == y["angle_index"] for x, y in pairs)
    same_k = sum(x["prototype"] == y["prototype"] for x, y in pairs)
    same_boxes = sum(len(sa["objects"]) == len(sb["objects"]) and all(np.allclose(x["box"], y["box"], atol=0.02)
                     for x, y in zip(sa["objects"], sb["objects"])) for sa, sb in zip(a, own))
    n = max(len(pairs), 1)
    return [f"Agreement on {run} ({len(files)} test scenes, {len(pairs)} objects, view 0; bf16 matched on fp32's "
            "boxes):", "", table(["measure", "value"], [
                ("same prototype and yaw index", f"{same}/{len(pairs)} = {same / n:.1%}"),
                ("same prototype", f"{same_k}/{len(pairs)} = {same_k / n:.1%}"),
                ("scenes whose bf16 detections equal fp32's (count, boxes within 2 cm)", f"{same_boxes}/{len(files)}"),
                ("whole parse of the split (batches of 4), fp32 / bf16", f"{t32:.1f} s / {t16:.1f} s")])]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--run", default=None, help="a threedq em folder (for the bf16 agreement table)")
    ap.add_argument("--scenes", default=None, help="its dataset folder")
    ap.add_argument("--limit", type=int, default=250, help="test scenes of the agreement table")
    args = ap.parse_args()
    print(f"# bench_parse — {machine()}, device {args.device}\n")
    print("Per-scene latency (median of", args.repeats, "after a warm-up; 1 view, 3 objects, K = 50 x 36 yaws), ms:\n")
    print(table(["scale", "mode", *PARTS, "total"]))
    with tempfile.TemporaryDirectory() as tmp:
        for name, (image, lo, hi, res) in SCALES.items():
            batch = scene(image, lo, hi, args.device)
            for mode, precision, inference in (("fp32", "fp32", False), ("fp32 inference_mode", "fp32", True),
                                               ("bf16 autocast + inference_mode", "bf16", True)):  # fmt: skip
                parser = random_parser(Path(tmp), lo, hi, res, precision, args.device)
                t = time_parts(parser, batch, three_boxes(lo, hi), args.repeats, inference)
                cells = " | ".join(f"{1000 * t[p]:.1f}" for p in PARTS)
                print(f"| {name} | {mode} | {cells} | **{1000 * t['total']:.0f}** |", flush=True)
                del parser
    if args.run and args.scenes:
        print()
        print("\n".join(agreement(args.run, args.scenes, args.limit)))


if __name__ == "__main__":
    main()
