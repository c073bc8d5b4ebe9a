"""Paper Table 2 with clustering beside it: one row per feature set, all measured on the same test crops.

Rows: raw ``cat[occ, occ * rgb]`` crops, a randomly initialised encoder, and every named encoder checkpoint
(e.g. ``rgbocc`` = view prediction, ``rgbocc+VC``, ``rgbocc+VC*``, ``ours`` = cross-scene mining). For each:
rotation-max retrieval precision@10 (:func:`~threedq.pipeline.evaluation.retrieval_table`, one declared
search), and a K-prototype bank fitted on the training split's crops of that feature set
(:func:`~threedq.quantization.prototypes.fit_prototype_bank`, the same EM as the quantizer stage) scored on
the test crops by Hungarian accuracy, few-shot accuracy and relative yaw error
(:func:`~threedq.pipeline.evaluation.quantization_metrics`).
"""

from __future__ import annotations

import time
from typing import Any

import torch

from threedq.pipeline.evaluation import (
    RETRIEVAL_SEARCH,
    SEARCH_LABELS,
    collect_object_crops,
    quantization_metrics,
    retrieval_table,
)
from threedq.quantization.prototypes import fit_prototype_bank
from threedq.stages.base import EncoderStage, load_encoder_state

__all__ = ["feature_sets_table", "feature_sets_markdown"]


def _row(train: torch.Tensor, test: dict[str, torch.Tensor], key: str, K: int, num_angles: int, em_iterations: int,
         seed: int, search: str, num_classes: int, symmetry: list[int]) -> dict[str, Any]:
    table, _ = retrieval_table({"labels": test["labels"], key: test[key]}, k=10, num_angles=num_angles, search=search)
    bank = fit_prototype_bank(train, min(K, train.shape[0]), iterations=em_iterations, num_angles=num_angles, seed=seed)
    res = bank.assign(test[key])
    q = quantization_metrics(res.prototype, res.angle, num_angles, bank.active.numel(), test["labels"],
                             test["boxes"][:, 6], num_classes, symmetry, seed=seed)
    return {"precision_at_10": next(iter(table["precision_at_k"].values())), "k": table["k"], **q}


@torch.no_grad()
def feature_sets_table(
    stage: EncoderStage,
    train_loader: torch.utils.data.DataLoader,
    test_loader: torch.utils.data.DataLoader,
    encoders: dict[str, str],
    num_classes: int,
    symmetry_order: list[int],
    num_input_views: int = 1,
    K: int = 50,
    num_angles: int = 36,
    em_iterations: int = 10,
    seed: int = 0,
    search: str = RETRIEVAL_SEARCH,
    progress: bool = True,
) -> dict[str, Any]:
    """Score raw crops, a random encoder and each named encoder checkpoint on one set of test crops.

    Args:
        stage: a stage whose grid the checkpoints share; its encoder weights are replaced in turn (and restored).
        train_loader, test_loader: deterministic loaders of the two splits (GT boxes).
        encoders: ``{row name: checkpoint}`` in row order (any checkpoint with ``encoder.*`` weights).
        num_classes, symmetry_order: of the dataset (metrics only).

    Returns:
        ``{"search", "num_test_objects", "num_train_objects", "K", "rows": {name: {precision_at_10,
        hungarian_acc, fewshot_acc, yaw_median_deg, yaw_acc_10, yaw_acc_20, yaw_pairs, checkpoint}}}``.
    """
    own = {k: v.clone() for k, v in stage.encoder.state_dict().items()}
    rows: dict[str, dict[str, Any]] = {}
    kw = {"K": K, "num_angles": num_angles, "em_iterations": em_iterations, "seed": seed, "search": search,
          "num_classes": num_classes, "symmetry": symmetry_order}
    base: dict[str, torch.Tensor] | None = None
    n_train = 0
    try:
        for i, (name, ckpt) in enumerate(encoders.items()):
            t0 = time.time()
            load_encoder_state(stage.encoder, ckpt)
            first = i == 0
            test = collect_object_crops(stage, test_loader, num_input_views, random_encoder_seed=seed if first else None,
                                        progress=progress)
            train = collect_object_crops(stage, train_loader, num_input_views, random_encoder_seed=seed if first else None,
                                         progress=progress)
            n_train = int(train["labels"].shape[0])
            if first:
                base = test
                rows["raw crops"] = {**_row(train["raw"], test, "raw", **kw), "checkpoint": None}
                rows["random encoder"] = {**_row(train["random"], test, "random", **kw), "checkpoint": None}
            elif base is not None and not torch.equal(base["labels"], test["labels"]):
                raise RuntimeError(f"{ckpt}: the test crops differ from the first checkpoint's (other data?)")
            rows[name] = {**_row(train["learned"], test, "learned", **kw), "checkpoint": str(ckpt),
                          "seconds": round(time.time() - t0, 1)}
            if progress:
                r = rows[name]
                print(f"[table 2] {name}: precision@10 {r['precision_at_10']:.3f}, Hungarian {r['hungarian_acc']:.3f}, "
                      f"few-shot {r['fewshot_acc']:.3f}")
    finally:
        stage.encoder.load_state_dict(own)
    return {"search": search, "num_test_objects": int(base["labels"].shape[0]) if base is not None else 0,
            "num_train_objects": n_train, "K": K, "rows": rows}


def feature_sets_markdown(table: dict[str, Any]) -> str:
    """The table as markdown, naming the search."""
    lines = [
        f"## Feature sets (paper Table 2, with clustering): {table['num_test_objects']} test objects, banks of "
        f"K = {table['K']} fitted on {table['num_train_objects']} training objects",
        "",
        f"precision@10: {SEARCH_LABELS[table['search']]}.",
        "",
        "| features | precision@10 | Hungarian acc. | few-shot acc. | yaw median err. (deg) | yaw acc. @10 deg |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in table["rows"].items():
        lines.append(f"| {name} | {r['precision_at_10']:.3f} | {r['hungarian_acc']:.3f} | {r['fewshot_acc']:.3f} | "
                     f"{r['yaw_median_deg']:.1f} | {r['yaw_acc_10']:.3f} |")
    return "\n".join(lines) + "\n"
