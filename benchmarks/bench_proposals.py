"""Per-scene cost of the label-free box proposals (:func:`threedq.proposals.propose_boxes`) and of their two largest
parts, with the parameters of the detector stage's pseudo-boxes (``view_stride=2``: 14 of 28 views).

Rows (median milliseconds per scene over the scenes, after one warm-up scene):

* back-projection of the valid depth pixels into the world (``threedq.proposals._world_points``);
* the ground plane's RANSAC fit and least-squares refinement (:func:`threedq.geometry.ground.fit_ground_plane`);
* the whole ``propose_boxes`` (the two above included).

Scenes: ``--data_dir`` (a dataset folder; its first ``--scenes`` training scenes), else that many scenes generated
into a temporary folder with the embedded generator's defaults (seed 0). The script runs on older commits too (copy
it into a worktree) to price a change there.

    python benchmarks/bench_proposals.py [--data_dir data/clevr_veggie] [--scenes 30]
"""

from __future__ import annotations

import argparse
import datetime
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import cpu_name


def _ms(fn, records: list) -> float:
    fn(records[0])  # warm-up
    times = []
    for r in records[1:]:
        t0 = time.perf_counter()
        fn(r)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data_dir", type=Path, default=None)
    ap.add_argument("--scenes", type=int, default=30)
    args = ap.parse_args()

    from threedq.geometry.ground import fit_ground_plane
    from threedq.proposals import ProposalParams, _world_points, propose_boxes
    from threedq.scene import load_index, load_scene

    with tempfile.TemporaryDirectory() as tmp:
        data = args.data_dir
        if data is None:
            from threedq.data.generate import generate_dataset

            data = Path(tmp) / "scenes"
            generate_dataset(data, num_scenes=args.scenes + 1, seed=0, split_fractions=(1.0, 0.0, 0.0), progress=False)
        index = load_index(data)
        files = index.files("train")[: args.scenes + 1]
        records = [load_scene(data / f, validate=False) for f in files]
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
        print(f"| {name} | {_ms(fn, records):.1f} |")


if __name__ == "__main__":
    main()
