"""Per-scene cost of the label-free box proposals (:func:`threedq.proposals.propose_boxes`) and of their two largest
parts, with the parameters of the detector stage's pseudo-boxes (``view_stride=2``: 14 of 28 views).

Rows (median milliseconds per scene over the scenes, after one warm-up scene):

* back-projection of the valid depth pixels into the world (``threedq.proposals._world_points``);
* the ground plane's RANSAC fit and least-squares refinement (:func:`threedq.geometry.ground.fit_ground_plane`);
* the whole ``propose_boxes`` (the two above included).

Scenes: ``--data_dir`` (a dataset folder; its first ``--scenes`` training scenes), else that many scenes generated
into a temporary folder with the embedded generator's defaults (seed 0). The script runs on older commits too (copy
it and `_scenes.py` into a worktree, run it there with ``PYTHONPATH=.`` so that the worktree's threedq is imported) to
price a change there.

    python benchmarks/bench_proposals.py [--data_dir data/clevr_veggie] [--scenes 30]
"""

from __future__ import annotations

import datetime
import statistics

import numpy as np
from _scenes import bench_scenes, median_ms, scene_arguments

from threedq.machine import cpu_name


def main() -> None:
    args = scene_arguments(__doc__)

    from threedq.geometry.ground import fit_ground_plane
    from threedq.proposals import ProposalParams, _world_points, propose_boxes

    data, index, records = bench_scenes(args.data_dir, args.scenes, "train")
    params = ProposalParams(view_stride=2)  # the pseudo-boxes' (datamodules/scene_folder.py)
    bounds = index.scene_bounds
    views = slice(0, None, params.view_stride)

    def back_project(r):
        return _world_points(r.depth[views], r.K[views], r.world_T_cam[views], params.pixel_stride)

    pts = {id(r): back_project(r)[0] for r in records}

    def ground(r):
        return fit_ground_plane(pts[id(r)], camera_centres=r.world_T_cam[views, :3, 3].astype(np.float64),
                                iters=params.ransac_iters, threshold=params.ransac_threshold,
                                max_tilt_deg=params.max_ground_tilt_deg, sample=params.ransac_sample, seed=params.seed)

    def whole(r):
        return propose_boxes(r, bounds=bounds, view_stride=params.view_stride)

    n_pts = statistics.median(len(p) for p in pts.values())
    print(f"# label-free proposals, {len(records) - 1} scenes ({data}), {n_pts:.0f} points a scene (median); "
          f"{cpu_name()}, {datetime.date.today()}")
    print("| part | ms / scene (median) |")
    print("|---|---|")
    for name, fn in (("back-projection (`_world_points`)", back_project), ("ground plane (`fit_ground_plane`)", ground),
                     ("whole `propose_boxes`", whole)):
        print(f"| {name} | {median_ms(fn, records):.1f} |")


if __name__ == "__main__":
    main()
