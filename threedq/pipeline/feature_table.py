"""Paper Table 2 with clustering beside it: one row per feature set, all measured on the same test crops.

Rows: raw ``cat[occ, occ * rgb]`` crops, a randomly initialised encoder, the colour + size descriptor (retrieval and
probe only), and every named encoder checkpoint. For each: retrieval precision@10 under the strict protocol and, when
the test loader holds a gallery view, the paper protocol (:func:`~threedq.pipeline.evaluation.retrieval_table`); a
linear probe; and a K-prototype bank fitted on the training crops, scored by Hungarian accuracy, few-shot accuracy and
relative yaw error (:func:`~threedq.pipeline.evaluation.quantization_metrics`).
"""

from __future__ import annotations

import time
from typing import Any

import torch

from threedq.pipeline.evaluation import (
    DESCRIPTOR,
    FEATURE_SETS,
    RETRIEVAL_SEARCH,
    collect_object_crops,
    probe_table,
    quantization_metrics,
    retrieval_table,
)
from threedq.quantization.prototypes import fit_prototype_bank
from threedq.stages.base import EncoderStage
from threedq.stages.checkpoint import load_encoder_state

__all__ = ["feature_sets_table"]

#: crop set -> its row name in a retrieval table
_ROW_KEYS = {key: name for name, key in FEATURE_SETS}


def _retrieval_cells(test: dict[str, torch.Tensor], key: str, name: str, num_angles: int,
                     search: str) -> dict[str, Any]:
    """Strict and (with a gallery) paper-protocol precision@10 and same-object top-1 of one feature set."""
    crops = {k: test[k] for k in ("labels", key, f"gallery_{key}", "aabb") if k in test}
    if name == DESCRIPTOR:
        crops = {k: test[k] for k in ("labels", "raw", "gallery_raw", "aabb") if k in test}
    table, _ = retrieval_table(crops, k=10, num_angles=num_angles, search=search)
    row_key = DESCRIPTOR if name == DESCRIPTOR else _ROW_KEYS[key]
    prot = table["protocols"]
    paper = prot.get("paper")
    return {"precision_at_10": prot["strict"]["precision_at_k"][row_key], "k": table["k"],
            "precision_at_10_paper": paper["precision_at_k"][row_key] if paper else None,
            "same_object_top1": paper["same_object_top1"][row_key] if paper else None,
            "ceilings": {p: v["ceiling"] for p, v in prot.items()}, "pool": table["num_objects"]}


_NO_TRAIN = {**dict.fromkeys(("probe_acc", "hungarian_acc", "fewshot_acc", "yaw_median_deg", "yaw_acc_10",
                               "yaw_acc_20"), float("nan")), "yaw_pairs": 0}


def _row(train: dict[str, torch.Tensor] | None, test: dict[str, torch.Tensor], key: str, K: int, num_angles: int,
         em_iterations: int, seed: int, search: str, num_classes: int, symmetry: list[int]) -> dict[str, Any]:
    cells = _retrieval_cells(test, key, key, num_angles, search)
    if train is None:
        return {**cells, **_NO_TRAIN}
    probe = probe_table({"labels": train["labels"], key: train[key]}, {"labels": test["labels"], key: test[key]})
    bank = fit_prototype_bank(train[key], min(K, train[key].shape[0]), iterations=em_iterations, num_angles=num_angles,
                              seed=seed)
    res = bank.assign(test[key])
    q = quantization_metrics(res.prototype, res.angle, num_angles, bank.active.numel(), test["labels"],
                             test["boxes"][:, 6], num_classes, symmetry, seed=seed)
    return {**cells, "probe_acc": probe["accuracy"][_ROW_KEYS[key]], **q}


def _descriptor_row(train: dict[str, torch.Tensor] | None, test: dict[str, torch.Tensor], num_angles: int,
                    search: str) -> dict[str, Any]:
    """The colour + size descriptor: retrieval and probe (no prototypes: it is six numbers, not a crop)."""
    cells = _retrieval_cells(test, "raw", DESCRIPTOR, num_angles, search)
    if train is None:
        return {**cells, **_NO_TRAIN}
    keys = ("labels", "raw", "aabb")
    probe = probe_table({k: train[k] for k in keys}, {k: test[k] for k in keys})
    return {**cells, **_NO_TRAIN, "probe_acc": probe["accuracy"][DESCRIPTOR]}


@torch.no_grad()
def feature_sets_table(stage: EncoderStage, train_loader: torch.utils.data.DataLoader,
                       test_loader: torch.utils.data.DataLoader, encoders: dict[str, str], num_classes: int,
                       symmetry_order: list[int], num_input_views: int = 1, K: int = 50, num_angles: int = 36,
                       em_iterations: int = 10, seed: int = 0, search: str = RETRIEVAL_SEARCH,
                       progress: bool = True) -> dict[str, Any]:
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
            gallery = test_loader.dataset.num_target_views > 0
            test = collect_object_crops(stage, test_loader, num_input_views,
                                        random_encoder_seed=seed if first else None, progress=progress, gallery=gallery)
            train = None
            if len(train_loader.dataset):
                train = collect_object_crops(stage, train_loader, num_input_views,
                                             random_encoder_seed=seed if first else None, progress=progress)
                n_train = int(train["labels"].shape[0])
            if first:
                base = test
                rows["raw crops"] = {**_row(train, test, "raw", **kw), "checkpoint": None}
                rows["random encoder"] = {**_row(train, test, "random", **kw), "checkpoint": None}
                rows["colour + size descriptor"] = {**_descriptor_row(train, test, num_angles, search),
                                                    "checkpoint": None}
            elif base is not None and not torch.equal(base["labels"], test["labels"]):
                raise RuntimeError(f"{ckpt}: the test crops differ from the first checkpoint's (other data?)")
            rows[name] = {**_row(train, test, "learned", **kw), "checkpoint": str(ckpt),
                          "seconds": round(time.time() - t0, 1)}
            if progress:
                r = rows[name]
                paper = "-" if r["precision_at_10_paper"] is None else f"{r['precision_at_10_paper']:.3f}"
                print(f"[table 2] {name}: precision@10 {r['precision_at_10']:.3f} (strict), {paper} (paper protocol), "
                      f"probe {r['probe_acc']:.3f}, Hungarian {r['hungarian_acc']:.3f}, "
                      f"few-shot {r['fewshot_acc']:.3f}")
    finally:
        stage.encoder.load_state_dict(own)
    first_row = next(iter(rows.values()), {})
    return {"search": search, "num_test_objects": int(base["labels"].shape[0]) if base is not None else 0,
            "num_train_objects": n_train, "K": K, "ceilings": first_row.get("ceilings", {}), "rows": rows}

