"""Table 2 with clustering (threedq/pipeline/feature_table.py) on the tiny fixture."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from threedq.datamodules.scene_folder import SceneFolderDataModule
from threedq.pipeline.evaluation import collect_object_crops, retrieval_table
from threedq.pipeline.feature_table import feature_sets_table
from threedq.pipeline.tables import feature_sets_markdown
from threedq.pipeline.report import split_loader
from threedq.stages.base import EncoderStage


def test_rows_against_direct_measurement(tmp_path: Path, tiny_dataset: Path) -> None:
    torch.manual_seed(0)
    a, b = EncoderStage(grid_resolution=(32, 32, 16)), EncoderStage(grid_resolution=(32, 32, 16))
    pa, pb = tmp_path / "a.pt", tmp_path / "b.pt"
    torch.save(a.encoder.state_dict(), pa)
    torch.save(b.encoder.state_dict(), pb)
    stage = EncoderStage(grid_resolution=(32, 32, 16)).eval()
    own = {k: v.clone() for k, v in stage.encoder.state_dict().items()}
    dm = SceneFolderDataModule(str(tiny_dataset), batch_size=2, num_input_views=1, num_target_views=0)
    cats = len(dm.index.categories)
    sym = list(dm.index.symmetry_order)
    table = feature_sets_table(stage, split_loader(dm, "train"), split_loader(dm, "test", gallery=True),
                               {"a": str(pa), "a again": str(pa), "b": str(pb)}, cats, sym, K=3, num_angles=8,
                               em_iterations=2, progress=False)
    rows = table["rows"]
    assert list(rows) == ["raw crops", "random encoder", "colour + size descriptor", "a", "a again", "b"]
    for name in ("precision_at_10", "precision_at_10_paper", "same_object_top1", "probe_acc", "hungarian_acc",
                 "fewshot_acc", "yaw_acc_10"):
        x, y = rows["a"][name], rows["a again"][name]
        assert x == y or (math.isnan(x) and math.isnan(y))  # the same weights give the same row
        assert all(0.0 <= r[name] <= 1.0 for r in rows.values() if not math.isnan(r[name]))
    assert not math.isnan(rows["a"]["hungarian_acc"])
    # the stage's own weights are back
    for k, v in stage.encoder.state_dict().items():
        assert torch.equal(v, own[k]), k
    # precision@10 of row "b" equals the retrieval table computed directly from b's crops
    test = collect_object_crops(b.eval(), split_loader(dm, "test", gallery=True), 1, random_encoder_seed=None,
                                progress=False, gallery=True)
    direct, _ = retrieval_table({"labels": test["labels"], "learned": test["learned"],
                                 "gallery_learned": test["gallery_learned"]}, k=10, num_angles=8)
    assert rows["b"]["precision_at_10"] == pytest.approx(direct["precision_at_k"]["learned"])
    paper = direct["protocols"]["paper"]
    assert rows["b"]["precision_at_10_paper"] == pytest.approx(paper["precision_at_k"]["learned"])
    assert rows["b"]["same_object_top1"] == pytest.approx(paper["same_object_top1"]["learned"])
    # the descriptor row is the descriptor's retrieval, not the raw crops' (it is computed from them)
    refs, _ = retrieval_table({k: test[k] for k in ("labels", "raw", "gallery_raw", "aabb")}, k=10, num_angles=8)
    d = rows["colour + size descriptor"]
    assert d["precision_at_10"] == pytest.approx(refs["protocols"]["strict"]["precision_at_k"]["colour_size_descriptor"])
    assert d["same_object_top1"] == pytest.approx(refs["protocols"]["paper"]["same_object_top1"]["colour_size_descriptor"])
    assert rows["raw crops"]["precision_at_10"] == pytest.approx(refs["precision_at_k"]["raw_rgb_occupancy"])
    # the gallery is another view: its crops differ from the queries' (the input view's crops are unchanged)
    assert not torch.equal(test["gallery_learned"], test["learned"])
    plain = collect_object_crops(b.eval(), split_loader(dm, "test"), 1, random_encoder_seed=None, progress=False)
    assert torch.equal(plain["learned"], test["learned"])
    md = feature_sets_markdown(table)
    assert "| b |" in md and "fast search" in md and "paper protocol" in md


def test_missing_checkpoint(tmp_path: Path, tiny_dataset: Path) -> None:
    stage = EncoderStage(grid_resolution=(32, 32, 16))
    dm = SceneFolderDataModule(str(tiny_dataset), batch_size=2, num_input_views=1, num_target_views=0)
    with pytest.raises(FileNotFoundError, match="missing.ckpt"):
        feature_sets_table(stage, split_loader(dm, "train"), split_loader(dm, "test"),
                           {"x": str(tmp_path / "missing.ckpt")}, 3, [1, 1, 1], progress=False)
