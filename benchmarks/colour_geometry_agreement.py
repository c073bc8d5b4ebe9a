"""Can unlabelled data say whether colour is part of what makes a category? A label-free test, against GT.

Issue #63's colour jitter (``colour_jitter`` of the mining stage) raises the shape-only data's features and lowers
the embedded data's, because on the one colour is noise and on the other half of a category. A miner that chose
the jitter by itself would need a label-free signal telling the two apart. The natural one: do objects of the same
shape share a colour more often than chance? This script measures it on the training split's GT boxes (one input
view per scene, the raw ``cat[occ, occ * rgb]`` crops every stage starts from), and, for reference only, what the
labels say.

Per object ``i``: its colour ``c_i``, the mean sRGB of its input-occupied cells (the colour half of
:func:`threedq.baselines.descriptor.colour_size_descriptor`); its geometric nearest neighbour
``nn(i)``, the object of another scene whose 3^3-dilated input occupancy agrees best at the best of 36 yaws (the
cosine of :func:`threedq.stages.mining.shape_agreement`, the miner's shape ranking), searched among ``--pool``
objects for ``--queries`` of them, as a refresh of the miner does (256 of 512 by default).

* ``label-free agreement``: mean ``|c_i - c_nn(i)|`` over the queries divided by mean ``|c_i - c_j|`` over all
  pairs from different scenes. 1: colour says nothing about shape; 0: shape neighbours share their colour.
* ``nn same category`` (GT, measuring only): how often ``nn(i)`` is of ``i``'s category.
* ``colour within category`` (GT, measuring only): the same ratio with ``nn(i)`` replaced by every object of ``i``'s
  category in another scene: 0 where a category has one colour, 1 where colour is drawn apart from the category.

Subsets (GT picks the objects, to show a kind of data; the statistic itself never reads labels): the embedded data's
CLEVR primitives, whose 24 categories are 3 shapes x 8 colours (colour drawn apart from shape, yet half of the
category), and its 17 meshes of one colour each.

    D=benchmarks/results/colour_geometry_amd_2026-12-05
    python benchmarks/colour_geometry_agreement.py --seeds 0 1 --out $D/agreement.jsonl --md $D/agreement.md \\
        --png docs/img/colour_geometry_agreement.png

One pool per (dataset, subset, seed) from a random draw of the training objects; about 3 min a dataset on 2 cores
(most of it cutting the crops).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import cpu_name

from threedq.atomic_io import atomic_write_text

DATASETS = {"shapes": "data/shapes.yaml", "embedded": "data/clevr_veggie.yaml"}
NUM_ANGLES = 36


def shape_similarity(raw_q: Any, raw_t: Any, num_angles: int = NUM_ANGLES) -> Any:
    """``[Q, T]``: the best cosine over ``num_angles`` yaws of each query's 3^3-dilated input occupancy with each
    target's turned by that yaw (the all-pairs form of :func:`threedq.stages.mining.shape_agreement`).

    Convention: crops ``[N, C, Z, Y, X]``, Z vertical; yaws ``2 pi k / num_angles`` about Z
    (:func:`threedq.geometry.rotate_yaw`)."""
    import torch
    import torch.nn.functional as F

    from threedq.geometry import rotate_yaw

    def dilated(raw: Any) -> Any:
        return F.max_pool3d(raw[:, :1].float(), kernel_size=3, stride=1, padding=1)

    q = F.normalize(dilated(raw_q).flatten(1), dim=1)
    t = dilated(raw_t)
    best = torch.full((q.shape[0], t.shape[0]), -2.0)
    for k in range(num_angles):
        yaw = torch.full((t.shape[0],), 2 * math.pi * k / num_angles)
        best = torch.maximum(best, q @ F.normalize(rotate_yaw(t, yaw).flatten(1), dim=1).T)
    return best


def agreement(colours: Any, sim: Any, scene: Any, labels: Any) -> dict[str, float]:
    """The three measures of the module docstring for ``Q = sim.shape[0]`` queries (the first ``Q`` objects) against
    all ``T`` objects.

    Args:
        colours: ``[T, 3]``; sim: ``[Q, T]`` shape similarity; scene: ``[T]`` scene ids; labels: ``[T]`` categories
            (GT, for the two reference measures only).

    Returns:
        ``label_free_agreement``, ``nn_same_category``, ``colour_within_category`` (NaN where no query has a
        same-category object in another scene).
    """
    import torch

    n_q = sim.shape[0]
    other = scene[:n_q, None] != scene[None, :]  # [Q, T]
    nn = sim.masked_fill(~other, -math.inf).argmax(dim=1)
    d = torch.cdist(colours[:n_q].double(), colours.double())  # [Q, T]
    chance = d[other].mean()
    same = other & (labels[:n_q, None] == labels[None, :])
    return {
        "label_free_agreement": float(d[torch.arange(n_q), nn].mean() / chance),
        "nn_same_category": float((labels[nn] == labels[:n_q]).double().mean()),
        "colour_within_category": float(d[same].mean() / chance) if same.any() else float("nan"),
    }


def subsets(dataset: str, labels: Any) -> dict[str, Any]:
    """The object subsets scored per dataset: ``all``, and on the embedded data ``primitives`` (the 24 CLEVR
    categories, ids 0-23) and ``meshes`` (the rest). GT picks them; the measures never read labels."""
    from threedq.data.catalog import CLEVR_COLORS, CLEVR_SHAPES

    out = {"all": labels >= 0}
    if dataset == "embedded":
        n = len(CLEVR_COLORS) * len(CLEVR_SHAPES)
        out["primitives (3 shapes x 8 colours)"] = (labels >= 0) & (labels < n)
        out["meshes (one colour each)"] = labels >= n
    return out


def run(datasets: list[str], seeds: list[int], queries: int, pool: int) -> list[dict[str, Any]]:
    import torch
    from shape_benchmark import load_datamodule, random_stage
    from tqdm import tqdm

    from threedq.baselines.descriptor import colour_size_descriptor
    from threedq.pipeline.evaluation import collect_object_crops
    from threedq.pipeline.report import split_loader

    rows = []
    for name in datasets:
        t0 = time.time()
        dm = load_datamodule(DATASETS[name])
        with torch.no_grad():  # the raw crops do not depend on the encoder; the stage only cuts them
            crops = collect_object_crops(random_stage(0), split_loader(dm, "train"), random_encoder_seed=None,
                                         progress=True)
        raw, scene, labels = crops["raw"], crops["scene"], crops["labels"]
        for subset, keep in subsets(name, labels).items():
            idx = keep.nonzero().flatten()
            for seed in tqdm(seeds, desc=f"{name}: {subset}", leave=False):
                g = torch.Generator().manual_seed(seed)
                pick = idx[torch.randperm(idx.numel(), generator=g)[:pool]]
                n_q = min(queries, pick.numel())
                sim = shape_similarity(raw[pick[:n_q]], raw[pick])
                colours = colour_size_descriptor(raw[pick], crops["aabb"][pick])[:, :3]  # the descriptor's colour
                m = agreement(colours, sim, scene[pick], labels[pick])
                rows.append({"dataset": name, "subset": subset, "seed": seed, "queries": n_q,
                             "pool": int(pick.numel()), **m})
        print(f"{name}: {raw.shape[0]} training objects, {time.time() - t0:.0f} s", file=sys.stderr)
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown: one row per (dataset, subset), mean and range over seeds."""
    head = ("| data (training split, GT boxes) | objects searched | label-free agreement | nn same category (GT) "
            "| colour within category (GT) |\n|---|---|---|---|---|")
    note = (f"{cpu_name()}, torch {__import__('torch').__version__}, 2 threads. Search: rotation-max cosine over "
            f"{NUM_ANGLES} yaws of the 3^3-dilated input occupancy (the miner's shape ranking); colour: mean sRGB "
            "of the occupied cells. Mean (range) over the seeds' random pools.")
    lines = [note, "", head]
    keys = list(dict.fromkeys((r["dataset"], r["subset"]) for r in rows))
    for dataset, subset in keys:
        rs = [r for r in rows if (r["dataset"], r["subset"]) == (dataset, subset)]

        def cell(key: str, rs: list[dict[str, Any]] = rs) -> str:
            v = [r[key] for r in rs]
            return f"{sum(v) / len(v):.3f} ({min(v):.3f}-{max(v):.3f})" if len(v) > 1 else f"{v[0]:.3f}"

        lines.append(f"| {dataset}, {subset} | {rs[0]['queries']} of {rs[0]['pool']} | {cell('label_free_agreement')}"
                     f" | {cell('nn_same_category')} | {cell('colour_within_category')} |")
    return "\n".join(lines)


def figure(rows: list[dict[str, Any]]) -> Any:
    """A scatter, one point per (dataset, subset) and seed: the label-free agreement (x) against the colour within
    category (y, GT). A signal able to choose the jitter would put the data whose colour names the category (low y)
    at low x only."""
    from threedq.viz.png import new_figure

    fig = new_figure(figsize=(6.4, 4.4), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    keys = list(dict.fromkeys((r["dataset"], r["subset"]) for r in rows))
    for i, (dataset, subset) in enumerate(keys):
        rs = [r for r in rows if (r["dataset"], r["subset"]) == (dataset, subset)]
        ax.scatter([r["label_free_agreement"] for r in rs], [r["colour_within_category"] for r in rs],
                   color=f"C{i}", label=f"{dataset}, {subset}", s=36)
    ax.plot([0, 1.1], [0, 1.1], color="0.7", lw=0.8, ls="--")
    ax.set_xlim(0, 1.1)
    ax.set_ylim(0, 1.1)
    ax.set_xlabel("label-free: colour distance to the shape neighbour / chance")
    ax.set_ylabel("GT: colour distance within a category / chance")
    ax.set_title("Does colour follow shape? (1 = no)", fontsize=10)
    ax.legend(fontsize=7, loc="lower left")
    return fig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=list(DATASETS))
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="one random pool of objects per seed")
    ap.add_argument("--queries", type=int, default=256, help="queries per pool (the miner's query_pool)")
    ap.add_argument("--pool", type=int, default=512, help="objects per pool (the miner's target_pool)")
    ap.add_argument("--out", type=Path, default=Path("runs/colour_geometry_agreement.jsonl"),
                    help="the rows, one JSON line per (dataset, subset, seed); rewritten by a run")
    ap.add_argument("--md", type=Path, default=None, help="also write the table here")
    ap.add_argument("--png", type=Path, default=None, help="also draw the scatter (figure) here")
    ap.add_argument("--table_only", action="store_true", help="table (and picture) from --out, nothing measured")
    args = ap.parse_args()
    if args.table_only:
        rows = [json.loads(line) for line in args.out.read_text().splitlines() if line.strip()]
    else:
        rows = run(args.datasets, args.seeds, args.queries, args.pool)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out, "".join(json.dumps(r) + "\n" for r in rows))
    md = table(rows)
    print(md)
    if args.md:
        args.md.parent.mkdir(parents=True, exist_ok=True)
        args.md.write_text(md + "\n")
    if args.png:
        from threedq.viz.png import write_png

        write_png(args.png, figure(rows))


if __name__ == "__main__":
    main()
