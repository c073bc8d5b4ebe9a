"""``crop_boxes`` two ways, bitwise the same crops: ``grid_sample`` (one call, its points spread over the threads)
and the row gather (``threedq.geometry.crop._gather_crops``: ``grid_sample``'s
arithmetic with each of the eight corners a gather of whole channel rows), and ``crop_boxes`` as it now chooses,
with the padding slots skipped (``mask=``).

Each row: median milliseconds per batch of 4 scenes, the ways interleaved on the same batches after one warm-up
batch, every batch's crops checked bit for bit against ``grid_sample``'s. Boxes: the GT boxes (axis-aligned hulls)
of consecutive test scenes of ``--data_dir`` (a dataset folder), else of ``--scenes`` scenes generated with the
embedded generator's defaults (seed 0), padded to 3 slots as the data loader pads them (``max_objects``); volumes
random on the main job's grids: features ``[4, 32, 16, 32, 32]`` (float32, and bf16), the unprojected input
``[4, 4, 32, 64, 64]``; crops 16^3.

    python benchmarks/bench_crop_boxes.py [--data_dir data/clevr_veggie] [--scenes 30]
"""

from __future__ import annotations

import datetime
import statistics
import time

import torch
from _scenes import bench_scenes, scene_arguments

from threedq.machine import cpu_name


def main() -> None:
    args = scene_arguments(__doc__)

    from threedq.boxes import boxes_to_aabb
    from threedq.geometry import VoxelGridSpec, crop_boxes
    from threedq.geometry.crop import _gather_crops, _sampled_crops

    data, _, records = bench_scenes(args.data_dir, 4 * args.scenes + 3, "test")
    grid = VoxelGridSpec((-1.28, -1.28, -0.32), (1.28, 1.28, 0.96), (64, 64, 32))
    fgrid = grid.half()
    slots = 3
    batches = []
    for i in range(0, len(records) - 3, 4):
        aabb = torch.zeros(4, slots, 6)
        mask = torch.zeros(4, slots, dtype=torch.bool)
        for b, r in enumerate(records[i : i + 4]):
            hull = torch.as_tensor(boxes_to_aabb(r.boxes), dtype=torch.float32)[:slots]
            aabb[b, : len(hull)], mask[b, : len(hull)] = hull, True
        batches.append((aabb, mask))
    size = (16, 16, 16)

    def gather(v, aabb, mask):
        out = _gather_crops(v, aabb.reshape(-1, 6).to(v.dtype), torch.arange(4).repeat_interleave(slots), fgrid_of(v),
                            size)
        return out.view(4, slots, *out.shape[1:])

    def fgrid_of(v):
        return fgrid if v.shape[2:] == fgrid.volume_shape else grid

    cases = [("features [4, 32, 16, 32, 32] float32", torch.float32, fgrid, 32),
             ("features [4, 32, 16, 32, 32] bf16", torch.bfloat16, fgrid, 32),
             ("input [4, 4, 32, 64, 64] float32", torch.float32, grid, 4)]
    ways = {
        "`grid_sample`, every slot": lambda v, a, m: _sampled_crops(v, a.to(v.dtype), fgrid_of(v), size)[m],
        "row gather, every slot": lambda v, a, m: gather(v, a, m)[m],
        "`crop_boxes(..., mask=)` (its choice, valid boxes only)": lambda v, a, m: crop_boxes(v, a, fgrid_of(v), size, mask=m),
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
        rows.append((label, {w: statistics.median(t) for w, t in times.items()}))
    print(f"# crop_boxes, 16^3 crops, {len(batches) - 1} batches of 4 scenes x {slots} slots ({valid} valid boxes) "
          f"({data}); {cpu_name()}, {torch.get_num_threads()} threads, torch {torch.__version__}, {datetime.date.today()}")
    print("# crops of every way bitwise equal to grid_sample's on every batch")
    print("| volume | " + " | ".join(ways) + " |")
    print("|---|" + "---|" * len(ways))
    for label, t in rows:
        print(f"| {label} | " + " | ".join(f"{t[w]:.2f} ms" for w in ways) + " |")


if __name__ == "__main__":
    main()
