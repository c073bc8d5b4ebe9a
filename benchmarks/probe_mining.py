"""How well does the 3D patch miner pick same-category pairs on trained features?

Crops every test object of the embedded data (``data/clevr_veggie``) with a quantizer checkpoint's encoder, mines
correspondences from the first ``--queries`` objects against all of them (other scenes only), and prints (GT for
measuring only) the share of kept pairs of one category, the same for plain top-k retrieval and its top-1, and the
verification scores.

    python benchmarks/probe_mining.py --ckpt runs/em/r04_quantizer/checkpoints/last.ckpt --min_cosine 0.5
    python benchmarks/probe_mining.py --ckpt ... --min_cosine 0.95 --yaw_window 1 --rank_by retrieval
"""

from __future__ import annotations

import argparse
import time

import torch

from threedq.contrastive import mine_correspondences, retrieve_targets
from threedq.machine import cpu_name
from threedq.pipeline.evaluation import collect_object_crops
from threedq.pipeline.lightning_cli import resolve_config, test_checkpoint
from threedq.pipeline.report import split_loader
from threedq.stages.mining import implied_yaw_error_deg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", required=True, help="a quantizer (or any stage) checkpoint with the encoder")
    ap.add_argument("--config", default="stages/quantizer.yaml")
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--top_k", type=int, default=30)
    ap.add_argument("--keep", type=int, default=200)
    ap.add_argument("--min_cosine", type=float, default=0.5)
    ap.add_argument("--yaw_window", type=int, default=None, help="patch yaw within this many steps of the retrieval's")
    ap.add_argument("--rank_by", default="score", choices=["score", "retrieval"])
    args = ap.parse_args()
    torch.manual_seed(0)
    cli, _ = test_checkpoint([resolve_config(args.config)], args.ckpt, "runs/probe_mining")
    crops = collect_object_crops(cli.model, split_loader(cli.datamodule, "test"), 1, random_encoder_seed=None,
                                 progress=False)
    f, lab, scene = crops["learned"], crops["labels"], crops["scene"]
    n = min(args.queries, f.shape[0])
    exclude = scene[:n, None] == scene[None, :]
    t0 = time.time()
    out = mine_correspondences(f[:n], f, top_k=args.top_k, keep=args.keep, exclude=exclude, min_cosine=args.min_cosine,
                               yaw_window=args.yaw_window, rank_by=args.rank_by)
    seconds = time.time() - t0
    qi, ti = out["query_index"], out["target_index"]
    idx, _, _ = retrieve_targets(f[:n], f, top_k=args.top_k, exclude=exclude)
    print(f"machine: {cpu_name()}  date: {time.strftime('%Y-%m-%d')}  checkpoint: {args.ckpt}")
    sym = torch.tensor(list(cli.datamodule.index.symmetry_order))
    same = lab[qi] == lab[ti]
    use = same & (sym[lab[qi]] == 1)
    yaw_err = (implied_yaw_error_deg(out["yaw"][use], 36, crops["boxes"][qi[use], 6], crops["boxes"][ti[use], 6],
                                     sym[lab[qi[use]]]).median() if use.any() else float("nan"))
    print(f"options: min_cosine {args.min_cosine}, yaw_window {args.yaw_window}, rank_by {args.rank_by}; yaw median "
          f"error of same-category asymmetric pairs: {float(yaw_err):.1f} deg ({int(use.sum())} pairs)")
    print(f"| min_cosine | queries | pairs kept | mined pairs, same category | top-{args.top_k} retrieval, same "
          "category | top-1 retrieval, same category | score p10 / p50 / p90 | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    q = out["score"].quantile(torch.tensor([0.1, 0.5, 0.9])).tolist() if qi.numel() else [float("nan")] * 3
    print(f"| {args.min_cosine} | {n} | {qi.numel()} | {(lab[qi] == lab[ti]).float().mean():.3f} | "
          f"{(lab[idx] == lab[:n, None]).float().mean():.3f} | {(lab[idx[:, 0]] == lab[:n]).float().mean():.3f} | "
          f"{q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} | {seconds:.1f} |")


if __name__ == "__main__":
    main()
