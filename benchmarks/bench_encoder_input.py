"""Per-scene cost of the encoder's unprojected input (``EncoderStage.encoder_input``: occupancy and colour of one view
on the input grid) computed, and read back from the run's :class:`~threedq.stages.crop_cache.CropCache`
(``EncoderStage.views_input``), with the bytes the cache keeps for it.

Every stage after view prediction encodes the scenes again with its own encoder; the input they start from depends on
the views and the grid alone, so ``threedq em`` unprojects each scene once and later stages read it from the cache.
Rows (median milliseconds per scene, one view each, after one warm-up scene):

* ``encoder_input``: the unprojection itself;
* a cache miss: the unprojection, the views' hash, the packing (``pack_sparse``, ``pack_bits``) and the store;
* a cache hit: the views' hash and the unpacking.

Grid: the main job's input grid (``configs/stages/viewpred.yaml``: 64 x 64 x 32 voxels of 4 cm). Scenes: ``--data_dir``
(a dataset folder; its first ``--scenes`` test scenes, view 0), else that many scenes generated into a temporary
folder with the embedded generator's defaults (seed 0).

    python benchmarks/bench_encoder_input.py [--data_dir data/clevr_veggie] [--scenes 30]
"""

from __future__ import annotations

import datetime

import torch
from _scenes import bench_scenes, median_ms, scene_arguments

from threedq.machine import cpu_name


def main() -> None:
    args = scene_arguments(__doc__)

    from threedq.stages.base import EncoderStage
    from threedq.stages.crop_cache import CropCache

    data, _, records = bench_scenes(args.data_dir, args.scenes, "test")
    stage = EncoderStage(grid_min=(-1.28, -1.28, -0.32), grid_max=(1.28, 1.28, 0.96), grid_resolution=(64, 64, 32),
                         feature_dim=32, encoder_channels=(32, 64, 128)).eval()
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
    print(f"# encoder input, {len(views) - 1} scenes ({data}), view 0, grid {stage.grid.resolution}; "
          f"{cpu_name()}, {torch.get_num_threads()} threads, torch {torch.__version__}, {datetime.date.today()}")
    print("| what | ms / scene (median) |")
    print("|---|---|")
    print(f"| `encoder_input` (unprojection) | {compute:.1f} |")
    print(f"| `views_input`, cache miss (unprojection, hash, packing, store) | {miss:.1f} |")
    print(f"| `views_input`, cache hit (hash, unpacking) | {hit:.1f} |")
    print(f"\nbytes a view: dense `x` + `seen` {dense / 1e3:.0f} KB, kept in the cache {kept / 1e3:.0f} KB")


if __name__ == "__main__":
    main()
