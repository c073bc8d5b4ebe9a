"""The view decoder's input, the depth max of the target camera's frustum, three ways: ``grid_sample`` of the whole
frustum then ``F.max_pool3d``, the whole frustum then ``depth_max_pool`` (a reduction
over a view of the planes), and ``frustum_depth_max`` (only the windows with a sample near the grid).

Each row: median milliseconds per batch of 2 target views, forward alone and forward + backward (the volume's
gradient), the three run interleaved on the same batches after one warm-up batch; every batch's outputs and
gradients are checked bit for bit against the first way. Shapes: the main job's view-prediction stage
(``configs/stages/viewpred.yaml``): features ``[2, 32, 16, 32, 32]`` (``channels_last_3d``, as the encoder gives
them) on the half-resolution feature grid, 32 depth planes over 1.2-5.2 m pooled by 8, 64 x 64 pixels (the 128 px
views at half resolution). Cameras: view 1 of consecutive test scenes of ``--data_dir`` (a dataset folder), else of
``--scenes`` scenes generated with the embedded generator's defaults (seed 0); the features are random.

    python benchmarks/bench_frustum_max.py [--data_dir data/clevr_veggie] [--scenes 30]
"""

from __future__ import annotations

import datetime
import statistics
import time

import torch
import torch.nn.functional as F
from _scenes import bench_scenes, scene_arguments

from threedq.machine import cpu_name


def main() -> None:
    args = scene_arguments(__doc__)

    from threedq.geometry import (
        VoxelGridSpec, frustum_depth_max, frustum_points, resample_to_frustum, scale_intrinsics,
    )
    from threedq.nets import depth_max_pool

    data, _, records = bench_scenes(args.data_dir, 2 * args.scenes + 1, "test")
    grid = VoxelGridSpec((-1.28, -1.28, -0.32), (1.28, 1.28, 0.96), (64, 64, 32)).half()
    planes, pool, hw, depth_range = 32, 8, (64, 64), (1.2, 5.2)
    cams = [(scale_intrinsics(torch.from_numpy(r.K[1]).float(), 0.5, 0.5), torch.from_numpy(r.world_T_cam[1]).float())
            for r in records]
    batches = [(torch.stack([cams[i][0], cams[i + 1][0]]), torch.stack([cams[i][1], cams[i + 1][1]]))
               for i in range(0, len(cams) - 1, 2)]

    ways = {
        "`grid_sample` + `F.max_pool3d`": lambda v, K, T: F.max_pool3d(
            resample_to_frustum(v, grid, K, T, hw, depth_range, planes), (pool, 1, 1), (pool, 1, 1)),
        "`grid_sample` + `depth_max_pool`": lambda v, K, T: depth_max_pool(
            resample_to_frustum(v, grid, K, T, hw, depth_range, planes), pool),
        "`frustum_depth_max` (the decoder's input now)": lambda v, K, T: frustum_depth_max(
            v, grid, K, T, hw, depth_range, planes, pool),
    }
    fwd: dict[str, list[float]] = {w: [] for w in ways}
    both: dict[str, list[float]] = {w: [] for w in ways}
    torch.manual_seed(0)
    near = []
    for i, (K, T) in enumerate(batches):
        features = torch.randn(2, 32, *grid.volume_shape).contiguous(memory_format=torch.channels_last_3d)
        grad_out = torch.randn(2, 32, planes // pool, *hw)
        first = None
        for name, way in ways.items():
            with torch.no_grad():
                t0 = time.perf_counter()
                way(features, K, T)
                t_fwd = time.perf_counter() - t0
            v = features.clone().requires_grad_(True)
            t0 = time.perf_counter()
            out = way(v, K, T)
            out.backward(grad_out)
            t_both = time.perf_counter() - t0
            if first is None:
                first = (out.detach(), v.grad)
            elif not (torch.equal(out, first[0]) and torch.equal(v.grad, first[1])):
                raise SystemExit(f"{name}: not bitwise the first way's output and gradient on batch {i}")
            if i:  # batch 0 warms up
                fwd[name].append(t_fwd * 1e3)
                both[name].append(t_both * 1e3)
        coords = grid.world_to_normalized(frustum_points(K, T, hw, depth_range, planes))
        size = torch.tensor(grid.volume_shape[::-1], dtype=coords.dtype)
        near.append(float((~(coords.abs() > 1 + 2 / size).any(-1)).float().mean()))
    print(f"# depth max of the target frustum, {len(batches) - 1} batches of 2 views ({data}), features "
          f"[2, 32, {', '.join(map(str, grid.volume_shape))}] channels_last_3d, {planes} planes / pool {pool}, "
          f"{hw[0]} x {hw[1]} px; {cpu_name()}, {torch.get_num_threads()} threads, torch {torch.__version__}, "
          f"{datetime.date.today()}")
    print(f"# samples within half a voxel of the grid: {100 * statistics.mean(near):.0f}% (mean); outputs and "
          "gradients of every way bitwise equal on every batch")
    print("| way | forward ms (median) | forward + backward ms (median) |")
    print("|---|---|---|")
    for name in ways:
        print(f"| {name} | {statistics.median(fwd[name]):.1f} | {statistics.median(both[name]):.1f} |")


if __name__ == "__main__":
    main()
