"""Per-scene costs of the main job's hot ops on real scenes, one op a run (``--op``):

* ``proposals``: the label-free box proposals (:func:`threedq.proposals.propose_boxes`, the detector stage's
  ``view_stride=2``), their back-projection and ground-plane fit; median ms per training scene;
* ``encoder_input``: the encoder's unprojected input of view 0 (``EncoderStage.encoder_input``) computed, and read
  back from the run's :class:`~threedq.stages.crop_cache.CropCache` (``views_input``, a miss and a hit), with the
  bytes the cache keeps; median ms per test scene, the main job's 64 x 64 x 32 input grid;
* ``frustum_max``: the view decoder's input, the depth max of the target frustum, as ``grid_sample`` +
  ``F.max_pool3d``, ``grid_sample`` + ``depth_max_pool`` and ``frustum_depth_max``; median ms per batch of 2 target
  views (view 1 of the test scenes), forward and forward + backward, random ``channels_last_3d`` features
  ``[2, 32, 16, 32, 32]``, 32 planes over 1.2-5.2 m pooled by 8, 64 x 64 px;
* ``crop_boxes``: ``crop_boxes`` as ``grid_sample``, as the row gather (``threedq.geometry.crop._gather_crops``) and
  as it chooses with the padding slots skipped (``mask=``); median ms per batch of 4 test scenes' GT boxes padded to
  3 slots, random volumes (features ``[4, 32, 16, 32, 32]`` float32 and bf16, input ``[4, 4, 32, 64, 64]``), 16^3.

The ways of one op run interleaved on the same batches after a warm-up batch, and their outputs (and gradients) are
checked bit for bit against the first way's. Scenes: ``--data_dir`` (a dataset folder), else scenes generated with
the embedded generator's defaults (seed 0) into a temporary folder.

    python benchmarks/bench_scene_ops.py --op proposals [--data_dir data/clevr_veggie] [--scenes 30]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from _common import machine, table

GRID = ((-1.28, -1.28, -0.32), (1.28, 1.28, 0.96), (64, 64, 32))  # the main job's input grid


def bench_scenes(data_dir: Path | None, count: int, split: str) -> tuple[Path, Any, list[Any]]:
    """``count + 1`` scene records of ``split`` (the first is a warm-up): the first of ``data_dir`` (a dataset
    folder), else that many scenes generated with the embedded generator's defaults (seed 0) into a temporary folder.

    Returns:
        the folder the scenes came from (a temporary one is gone when this returns), its ``DatasetIndex`` and the
        records (read without validation).
    """
    from threedq.scene import load_index, load_scene

    with tempfile.TemporaryDirectory() as tmp:
        data = data_dir
        if data is None:
            from threedq.data.generate import generate_dataset

            data = Path(tmp) / "scenes"
            fractions = {"train": (1.0, 0.0, 0.0), "val": (0.0, 1.0, 0.0), "test": (0.0, 0.0, 1.0)}[split]
            generate_dataset(data, num_scenes=count + 1, seed=0, split_fractions=fractions, progress=False)
        index = load_index(data)
        records = [load_scene(data / f, validate=False) for f in index.files(split)[: count + 1]]
    return data, index, records


def median_ms(fn: Callable[[Any], Any], items: Sequence[Any]) -> float:
    """Median milliseconds of ``fn(item)`` over ``items[1:]``, after ``fn(items[0])`` as a warm-up."""
    fn(items[0])
    times = []
    for item in items[1:]:
        t0 = time.perf_counter()
        fn(item)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def proposals(data_dir: Path | None, scenes: int) -> None:
    from threedq.geometry.ground import fit_ground_plane
    from threedq.proposals import ProposalParams, _world_points, propose_boxes

    data, index, records = bench_scenes(data_dir, scenes, "train")
    params = ProposalParams(view_stride=2)  # the pseudo-boxes' (datamodules/scene_folder.py)
    views = slice(0, None, params.view_stride)

    def back_project(r):
        return _world_points(r.depth[views], r.K[views], r.world_T_cam[views], params.pixel_stride)

    pts = {id(r): back_project(r)[0] for r in records}

    def ground(r):
        return fit_ground_plane(pts[id(r)], camera_centres=r.world_T_cam[views, :3, 3].astype(np.float64),
                                iters=params.ransac_iters, threshold=params.ransac_threshold,
                                max_tilt_deg=params.max_ground_tilt_deg, sample=params.ransac_sample, seed=params.seed)

    def whole(r):
        return propose_boxes(r, bounds=index.scene_bounds, view_stride=params.view_stride)

    n_pts = statistics.median(len(p) for p in pts.values())
    print(f"# label-free proposals, {len(records) - 1} scenes ({data}), {n_pts:.0f} points a scene (median); "
          f"{machine()}")
    parts = (("back-projection (`_world_points`)", back_project), ("ground plane (`fit_ground_plane`)", ground),
             ("whole `propose_boxes`", whole))
    print(table(["part", "ms / scene (median)"], [(name, f"{median_ms(fn, records):.1f}") for name, fn in parts]))


def encoder_input(data_dir: Path | None, scenes: int) -> None:
    from threedq.stages.base import EncoderStage
    from threedq.stages.crop_cache import CropCache

    data, _, records = bench_scenes(data_dir, scenes, "test")
    stage = EncoderStage(grid_min=GRID[0], grid_max=GRID[1], grid_resolution=GRID[2], feature_dim=32,
                         encoder_channels=(32, 64, 128)).eval()
    views = [(torch.from_numpy(r.rgb[:1]).permute(0, 3, 1, 2).float().div(255)[None],
              torch.from_numpy(r.depth[:1]).float()[None], torch.from_numpy(r.K[:1]).float()[None],
              torch.from_numpy(r.world_T_cam[:1]).float()[None]) for r in records]
    with torch.no_grad():
        compute = median_ms(lambda v: stage.encoder_input(*(t.flatten(0, 1) for t in v)), views)
        stage.use_crop_cache(CropCache())
        miss = median_ms(lambda v: stage.views_input(*v), views)
        hit = median_ms(lambda v: stage.views_input(*v), views)
        kept = stage.crop_cache.nbytes / len(views)
        dense = sum(t.numel() * t.element_size() for t in stage.encoder_input(*(t.flatten(0, 1) for t in views[0])))
    print(f"# encoder input, {len(views) - 1} scenes ({data}), view 0, grid {stage.grid.resolution}; {machine()}")
    print(table(["what", "ms / scene (median)"], [("`encoder_input` (unprojection)", f"{compute:.1f}"),
                ("`views_input`, cache miss (unprojection, hash, packing, store)", f"{miss:.1f}"),
                ("`views_input`, cache hit (hash, unpacking)", f"{hit:.1f}")]))
    print(f"\nbytes a view: dense `x` + `seen` {dense / 1e3:.0f} KB, kept in the cache {kept / 1e3:.0f} KB")


def frustum_max(data_dir: Path | None, scenes: int) -> None:
    from threedq.geometry import VoxelGridSpec, frustum_depth_max, frustum_points, resample_to_frustum, scale_intrinsics
    from threedq.nets import depth_max_pool

    data, _, records = bench_scenes(data_dir, 2 * scenes + 1, "test")
    grid = VoxelGridSpec(*GRID).half()
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
          f"{hw[0]} x {hw[1]} px; {machine()}")
    print(f"# samples within half a voxel of the grid: {100 * statistics.mean(near):.0f}% (mean); outputs and "
          "gradients of every way bitwise equal on every batch")
    print(table(["way", "forward ms (median)", "forward + backward ms (median)"],
                [(n, f"{statistics.median(fwd[n]):.1f}", f"{statistics.median(both[n]):.1f}") for n in ways]))


def crop_boxes(data_dir: Path | None, scenes: int) -> None:
    from threedq.boxes import boxes_to_aabb
    from threedq.geometry import VoxelGridSpec, crop_boxes
    from threedq.geometry.crop import _gather_crops, _sampled_crops

    data, _, records = bench_scenes(data_dir, 4 * scenes + 3, "test")
    grid = VoxelGridSpec(*GRID)
    fgrid = grid.half()
    slots, size = 3, (16, 16, 16)
    batches = []
    for i in range(0, len(records) - 3, 4):
        aabb = torch.zeros(4, slots, 6)
        mask = torch.zeros(4, slots, dtype=torch.bool)
        for b, r in enumerate(records[i : i + 4]):
            hull = torch.as_tensor(boxes_to_aabb(r.boxes), dtype=torch.float32)[:slots]
            aabb[b, : len(hull)], mask[b, : len(hull)] = hull, True
        batches.append((aabb, mask))

    def grid_of(v):
        return fgrid if v.shape[2:] == fgrid.volume_shape else grid

    def gather(v, aabb, mask):
        out = _gather_crops(v, aabb.reshape(-1, 6).to(v.dtype), torch.arange(4).repeat_interleave(slots), grid_of(v),
                            size)
        return out.view(4, slots, *out.shape[1:])

    cases = [("features [4, 32, 16, 32, 32] float32", torch.float32, fgrid, 32),
             ("features [4, 32, 16, 32, 32] bf16", torch.bfloat16, fgrid, 32),
             ("input [4, 4, 32, 64, 64] float32", torch.float32, grid, 4)]
    ways = {
        "`grid_sample`, every slot": lambda v, a, m: _sampled_crops(v, a.to(v.dtype), grid_of(v), size)[m],
        "row gather, every slot": lambda v, a, m: gather(v, a, m)[m],
        "`crop_boxes(..., mask=)` (its choice, valid boxes only)": lambda v, a, m: crop_boxes(v, a, grid_of(v), size,
                                                                                             mask=m),
    }
    torch.manual_seed(0)
    rows = []
    valid = sum(int(m.sum()) for _, m in batches[1:])
    for label, dtype, g, channels in cases:
        times: dict[str, list[float]] = {w: [] for w in ways}
        for i, (aabb, mask) in enumerate(batches):
            volume = torch.randn(4, channels, *g.volume_shape).to(dtype)
            ref = None
            for name, way in ways.items():
                with torch.no_grad():
                    t0 = time.perf_counter()
                    out = way(volume, aabb, mask)
                    dt = time.perf_counter() - t0
                if ref is None:
                    ref = out
                elif not torch.equal(out, ref):
                    raise SystemExit(f"{label}, {name}: not bitwise grid_sample's crops on batch {i}")
                if i:
                    times[name].append(dt * 1e3)
        rows.append((label, *(f"{statistics.median(times[w]):.2f} ms" for w in ways)))
    print(f"# crop_boxes, 16^3 crops, {len(batches) - 1} batches of 4 scenes x {slots} slots ({valid} valid boxes) "
          f"({data}); {machine()}")
    print("# crops of every way bitwise equal to grid_sample's on every batch")
    print(table(["volume", *ways], rows))


OPS = {"proposals": proposals, "encoder_input": encoder_input, "frustum_max": frustum_max, "crop_boxes": crop_boxes}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--op", required=True, choices=list(OPS))
    ap.add_argument("--data_dir", type=Path, default=None)
    ap.add_argument("--scenes", type=int, default=30)
    args = ap.parse_args()
    OPS[args.op](args.data_dir, args.scenes)


if __name__ == "__main__":
    main()
