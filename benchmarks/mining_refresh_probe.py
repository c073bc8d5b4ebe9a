"""Replay the first pool refresh of a ``threedq em`` round's mining stage under several retrieval settings.

The mining stage of round r writes its full configuration to ``<work_dir>/rNN_mining/config.yaml``. This script
builds that stage from it (same encoder, boxes, data, seed), cuts the pool as the stage's first refresh does
(:meth:`~threedq.stages.mining.Mining.refresh_pairs`: same generator, same object check, same candidates by
:meth:`~threedq.stages.mining.Mining.candidate_pairs`; outside ``threedq em``, so without its crop cache: on the main
job's runs its measures came within 0.03 of the run's own refresh, not bit for bit), and mines it once per setting
given in ``--settings`` (keyword arguments of :func:`~threedq.contrastive.mine_correspondences`, on top of
the stage's own; and the stage's ``retrieval_occupancy_floor``). For each it prints, with GT used for measuring only,
the columns of the round's report: pairs on two GT objects, one category among those, the implied yaw error on
asymmetric categories and over every category of finite symmetry order; and whether the pairs (query, target, yaw)
are the same as the first setting's, and the seconds the mining took. ``--seed`` draws another pool of the same
boxes. With the stage's ``positives: occupancy`` each setting's candidates (``shape_oversample`` x ``keep``) go
through the stage's shape ranking (:meth:`~threedq.stages.mining.Mining._shape_positives`) as in a refresh; the
stage settings ``retrieval_occupancy_floor``, ``max_pairs_per_box``, ``candidates_per_query`` and
``occupancy_mutual_k``, ``candidates_from`` may be set per setting too. Run it from the
folder the run was made in (the config's paths are relative to it):

    python benchmarks/mining_refresh_probe.py runs/em/r01_mining/config.yaml \\
        --settings '{"plain": {"csls_k": null}, "csls": {"csls_k": 10}, "csls+mutual": {"csls_k": 10, "mutual_k": 10}}'

Rows are appended to ``--out`` as JSON lines.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import torch  # noqa: E402
import yaml  # noqa: E402

from _machine import cpu_name  # noqa: E402


# settings of the stage (not keywords of mine_correspondences) a probe setting may change
STAGE_SETTINGS = ("retrieval_occupancy_floor", "max_pairs_per_box", "candidates_per_query", "occupancy_mutual_k",
                  "candidates_from")


def stage_from_run_config(path: Path) -> tuple[object, object]:
    """(Mining stage, DataModule set up for fit) from a run's saved ``config.yaml`` (its run-only keys dropped)."""
    from threedq.pipeline.lightning_cli import ThreeDQCLI

    cfg = yaml.safe_load(path.read_text())
    for key in ("ckpt_path", "weights_only"):  # keys of `threedq fit`'s saved config that are not configuration
        cfg.pop(key, None)
    with tempfile.TemporaryDirectory() as tmp:
        clean = Path(tmp) / "config.yaml"
        clean.write_text(yaml.safe_dump(cfg))
        cli = ThreeDQCLI(args=["--config", str(clean), "--trainer.logger=false"], run=False)
    cli.datamodule.setup("fit")
    return cli.model, cli.datamodule


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("config", type=Path, help="a round's rNN_mining/config.yaml")
    ap.add_argument("--settings", required=True,
                    help='JSON {"name": {keyword: value}}: mine_correspondences keywords per setting')
    ap.add_argument("--out", type=Path, default=Path("runs/mining_refresh_probe.jsonl"))
    ap.add_argument("--seed", type=int, default=None,
                    help="draw the pool with this seed instead of the stage's (another pool of the same boxes)")
    args = ap.parse_args()
    settings = json.loads(args.settings)
    if not isinstance(settings, dict) or not all(isinstance(v, dict) for v in settings.values()):
        ap.error('--settings: expected a JSON object {"name": {keyword: value}}')

    from threedq.contrastive import calibrate_context_cosine

    model, dm = stage_from_run_config(args.config)
    hp = model.hparams
    ds = copy.copy(dm.train_dataloader().dataset)
    if getattr(ds, "random_views", False):
        ds.random_views = False  # the pool's views, as Mining._pool_dataset
    seed = hp.seed if args.seed is None else args.seed
    g = torch.Generator().manual_seed(seed + 1009 * 0)  # the first refresh of the stage, rank 0
    model._pool_stats = {"boxes": 0, "vouched": 0, "scene_vouched": 0}
    model._scene_pseudo_boxes = lambda: dm.pseudo_boxes("train")  # the scene's check asks the DataModule
    t0 = time.time()
    pool = model._cut_pool(ds, g)
    feats = pool["features"]
    n_t = feats.shape[0]
    n_q = min(hp.query_pool, n_t)
    on_objects = float((pool["labels"] >= 0).float().mean())
    print(f"machine: {cpu_name()}  date: {time.strftime('%Y-%m-%d')}  {args.config}: pool of {n_t} boxes, "
          f"{on_objects:.3f} on GT objects ({time.time() - t0:.0f} s)", flush=True)
    min_cos = hp.min_cosine if hp.min_cosine is not None else calibrate_context_cosine(
        feats, pool["scene"], hp.context_quantile, hp.patch, generator=g)
    exclude = pool["scene"][:n_q, None] == pool["scene"][None, :]
    first = None
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for name, kw in settings.items():
        t1 = time.time()
        mine_kw = {k: v for k, v in kw.items() if k not in STAGE_SETTINGS}  # mine_correspondences' keywords
        saved = {k: hp[k] for k in STAGE_SETTINGS}
        hp.update({k: v for k, v in kw.items() if k in STAGE_SETTINGS})  # this setting's stage settings
        mined = model.candidate_pairs(pool, n_q, min_cos, exclude, model.candidate_count(), g, **mine_kw)
        if hp.positives == "occupancy":  # the stage's shape ranking (and cap), as its refresh
            mined = model._shape_positives(pool, mined, 8, torch.Generator().manual_seed(seed))[0]
        hp.update(saved)
        seconds = time.time() - t1
        qi, ti = mined["query_index"], mined["target_index"]
        m = model.pair_measures(pool, mined)  # the measures of the round's report
        row = {"config": str(args.config), "seed": seed, "setting": name, **kw, "pool_on_objects": round(on_objects, 3),
               "pairs": int(qi.numel()),
               "on_two_objects": round(m["labelled_pairs"] / qi.numel(), 3) if qi.numel() else None,
               "same_category": round(m["same_category"], 3) if m["labelled_pairs"] else None,
               "yaw_median_deg": round(m["yaw_median_err_deg"], 1) if "yaw_median_err_deg" in m else None,
               "yaw_pairs": m.get("yaw_pairs", 0),
               # every category of finite symmetry order, modulo its period (more pairs than the report's column)
               "yaw_sym_median_deg": round(m["yaw_sym_median_err_deg"], 1) if "yaw_sym_median_err_deg" in m else None,
               "yaw_sym_pairs": m.get("yaw_sym_pairs", 0),
               # both boxes on a GT object at IoU 0.25 (the report's looser count), and the boxes the pairs use
               "on_two_objects_iou25": (round(m["pairs_on_objects_iou25"] / qi.numel(), 3)
                                        if qi.numel() and "pairs_on_objects_iou25" in m else None),
               "distinct_boxes": int(torch.cat([qi, ti]).unique().numel())}
        key = torch.stack([qi, ti, mined["yaw"]], dim=1)
        first = key if first is None else first
        row.update(same_pairs_as_first=bool(key.shape == first.shape and torch.equal(key, first)),
                   seconds=round(seconds, 1), cpu=cpu_name(), date=time.strftime("%Y-%m-%d"))
        print(json.dumps(row), flush=True)
        with args.out.open("a") as f:
            f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
