"""The 2.5DQ-Nets stage and the 2D baseline rows of ``threedq eval``, end to end on the tiny dataset.

One module fixture trains (1-2 steps each) view prediction, the quantizer and 2.5DQ-Nets through the real
CLI config path, and saves a randomly initialised ResNet-18 in torchvision's layout as the ``--weights`` file.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
import yaml

from threedq.baselines.resnet import ResNet18
from threedq.errors import InputError


@dataclass
class Run:
    root: Path
    config: Path
    viewpred: Path
    quantizer: Path
    q25d: Path
    weights: Path


def _tiny_config(path: Path, data_dir: Path, model: dict | None = None) -> Path:
    path.write_text(yaml.safe_dump({
        "model": {"init_args": model or {"grid_resolution": [32, 32, 16]}},
        "data": {"init_args": {"data_dir": str(data_dir), "num_scenes": 12, "image_size": [32, 32], "num_views": 4,
                               "generator_workers": 1}},
        "trainer": {"max_steps": 1, "log_every_n_steps": 1, "limit_val_batches": 1, "enable_progress_bar": False,
                    "enable_model_summary": False},
    }))
    return path


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory, tiny_dataset: Path) -> Run:
    from threedq.pipeline.lightning_cli import ThreeDQCLI, resolve_config

    root = tmp_path_factory.mktemp("q25d")
    data = root / "data"
    shutil.copytree(tiny_dataset, data, ignore=shutil.ignore_patterns("proposals"))
    config = _tiny_config(root / "tiny.yaml", data)
    common = ["--trainer.logger=false", "--trainer.enable_checkpointing=false"]
    cli = ThreeDQCLI(args=["--config", str(resolve_config("stages/viewpred.yaml")), "--config", str(config), *common,
                           f"--trainer.default_root_dir={root / 'runs'}"], run=False)
    cli.trainer.fit(cli.model, datamodule=cli.datamodule)
    vp = root / "viewpred.ckpt"
    cli.trainer.save_checkpoint(vp, weights_only=True)
    cli = ThreeDQCLI(args=["--config", str(resolve_config("stages/quantizer.yaml")), "--config", str(config), *common,
                           f"--model.init_args.encoder_ckpt={vp}", "--trainer.max_steps=-1", "--trainer.max_epochs=1",
                           f"--trainer.default_root_dir={root / 'runs'}"], run=False)
    cli.trainer.fit(cli.model, datamodule=cli.datamodule)
    q = root / "quantizer.ckpt"
    cli.trainer.save_checkpoint(q, weights_only=True)
    q25d_cfg = _tiny_config(root / "tiny_q25d.yaml", data, {"crop_size": 8})
    cli = ThreeDQCLI(args=["--config", str(resolve_config("stages/q25d.yaml")), "--config", str(q25d_cfg), *common,
                           "--trainer.max_steps=2", f"--trainer.default_root_dir={root / 'runs'}"], run=False)
    cli.trainer.fit(cli.model, datamodule=cli.datamodule)
    q25d = root / "q25d.ckpt"
    cli.trainer.save_checkpoint(q25d, weights_only=True)
    torch.manual_seed(0)
    weights = root / "resnet18.pth"
    torch.save(ResNet18().state_dict(), weights)
    shutil.rmtree(root / "runs", ignore_errors=True)
    return Run(root, config, vp, q, q25d, weights)


def test_stage_learns_and_crops_in_threedq_order(run: Run, tiny_dataset: Path) -> None:
    """Autoencoding loss drops on a fixed batch; object crops come in the 3D stages' order with their labels."""
    from threedq.pipeline.baselines2d import load_q25d
    from threedq.scene import load_index
    from threedq.datamodules.scene_folder import SceneDataset

    model = load_q25d(run.q25d)
    assert model.hparams.crop_size == 8
    ds = SceneDataset(tiny_dataset, load_index(tiny_dataset), "train", num_target_views=0)
    batch = torch.utils.data.default_collate([ds[0], ds[1]])
    crops = model.object_crops(batch)
    n = int(batch["box_mask"].sum())
    assert crops["features"].shape == (n, 32, 8, 8)
    assert torch.equal(crops["labels"], batch["categories"][batch["box_mask"]])
    assert bool(crops["visible"].all())  # generated scenes keep their objects in view
    torch.manual_seed(0)
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    losses = []
    for _ in range(8):
        loss = model._step(batch)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.8 * losses[0]


def test_eval_rows_with_and_without_baselines(run: Run, tmp_path: Path) -> None:
    from threedq.pipeline.report import run_eval

    out = tmp_path / "with"
    res = run_eval(str(run.quantizer), extra_configs=[str(run.config)], out=str(out), baselines=True, curve_k=[2, 3],
                   q25d=str(run.q25d), weights=str(run.weights), em_iterations=2)
    q = res["quantization"]["q25d"]
    assert 0.0 <= q["hungarian_acc"] <= 1.0 and q["yaw_pairs"] == 0
    assert set(res["curve"]["q25d"]) == {"2", "3"}
    rn = res["resnet"]
    assert rn["num_objects"] == res["num_test_objects"] and 0.0 <= rn["precision_at_k"] <= 1.0
    assert res["not_run"] == {}
    md = (out / "results.md").read_text()
    assert "| 2.5DQ-Nets (2D prototypes, in-plane rotation search) | " in md
    assert "n/a (in-plane angle, not a yaw)" in md
    assert "| ResNetRet (ImageNet ResNet-18, nearest labelled object) |" in md
    assert "needs --weights" not in md and "not run" not in md
    assert "in-plane angles" in md and "fast search" in md  # the tables name their searches
    assert json.loads((out / "results.json").read_text())["resnet"]["k"] == rn["k"]
    assert rn["backbone"] == "resnet18" and rn["feature_dim"] == 512
    # the MobileNetV2 stand-in is named in every row it fills (tables from the same numbers, its backbone fields)
    from threedq.baselines.backbone import backbone_fields
    from threedq.baselines.mobilenet import MobileNetV2
    from threedq.pipeline.tables import eval_markdown

    md2 = eval_markdown({**res, "resnet": {**rn, **backbone_fields(MobileNetV2())}})
    stand_in = "ImageNet MobileNetV2 (stand-in for the paper's ResNet-18)"
    assert (f"| {stand_in} (features.18, 1280 channels, pooled in the projected GT box; cosine, no rotation search) | "
            in md2)
    assert f"| ResNetRet ({stand_in}, nearest labelled object) |" in md2
    assert f"| ResNetClass ({stand_in} + linear classifier on the shots) |" in md2
    assert "ResNet-18 (layer4" not in md2 and "ImageNet ResNet-18," not in md2
    if "paper_precision_at_k" in rn:  # the paper protocol's columns filled from the gallery view's features
        assert f"| {rn['precision_at_k']:.3f} | {rn['paper_precision_at_k']:.3f} | {rn['same_object_top1']:.3f} |" in md

    out = tmp_path / "without"
    res = run_eval(str(run.quantizer), extra_configs=[str(run.config)], out=str(out), baselines=False, curve_k=[2])
    md = (out / "results.md").read_text()
    assert "q25d" not in res["quantization"] and res["resnet"] is None
    assert set(res["not_run"]) == {"q25d", "resnet"}
    for table_row in ("| ImageNet ResNet-18 (layer4 pooled in the projected GT box; cosine, no rotation search) | needs --weights",
                      "| ResNetClass (ImageNet ResNet-18 + linear classifier on the shots) | needs --weights",
                      "| 2.5DQ-Nets (2D prototypes, in-plane rotation search) | not run: train it with `threedq fit --config "
                      "stages/q25d.yaml`"):
        assert table_row in md
    assert md.count("2.5DQ-Nets (2D prototypes, in-plane rotation search) | not run") == 3  # Tables 4, 1 and Fig. 3a


def test_bad_baseline_files_are_one_line_input_errors(run: Run, tmp_path: Path) -> None:
    from threedq.pipeline.report import run_eval

    with pytest.raises(InputError, match="this is a quantizer checkpoint; --q25d needs a 2.5DQ-Nets"):
        run_eval(str(run.quantizer), extra_configs=[str(run.config)], out=str(tmp_path / "a"), q25d=str(run.quantizer))
    bad = tmp_path / "bad.pth"
    torch.save({"conv1.weight": torch.zeros(64, 3, 7, 7)}, bad)
    with pytest.raises(InputError, match=r"bad.pth: field 'bn1.weight': missing"):
        run_eval(str(run.quantizer), extra_configs=[str(run.config)], out=str(tmp_path / "b"), weights=str(bad))
    torch.save({"features.0.0.weight": torch.zeros(32, 3, 3, 3)}, bad)  # looks like MobileNetV2, is not
    with pytest.raises(InputError, match=r"bad.pth: field 'features.0.1.weight': missing \(311 MobileNetV2"):
        run_eval(str(run.quantizer), extra_configs=[str(run.config)], out=str(tmp_path / "c"), weights=str(bad))


def test_imagenet_features_of_the_gallery_view(run: Run) -> None:
    """``collect_resnet_features`` on the MobileNetV2 stand-in: one 1280-vector per GT object in loader order, for the
    input view or the paper protocol's gallery view (other pixels, so other features); a view the loader lacks is an
    error."""
    from threedq.baselines.mobilenet import MobileNetV2
    from threedq.datamodules.scene_folder import SceneDataset
    from threedq.pipeline.baselines2d import collect_resnet_features
    from threedq.scene import load_index

    ds = SceneDataset(run.root / "data", load_index(run.root / "data"), "test", num_target_views=1, random_views=False)
    loader = torch.utils.data.DataLoader(ds, batch_size=2)
    torch.manual_seed(0)
    net = MobileNetV2().eval()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny depthwise convolutions: as fast on one thread, not slowed by other jobs' load
    try:
        a = collect_resnet_features(net, loader, progress=False)
        b = collect_resnet_features(net, loader, progress=False, view=1)
    finally:
        torch.set_num_threads(threads)
    n = sum(int(s["box_mask"].sum()) for s in ds)
    assert a["features"].shape == b["features"].shape == (n, 1280)
    assert torch.equal(a["labels"], b["labels"])
    assert (a["features"] - b["features"]).abs().max() > 1e-2 * a["features"].abs().max()  # (untrained: tiny values)
    with pytest.raises(ValueError, match="view 2: the loader's samples hold 2 view"):
        collect_resnet_features(net, loader, progress=False, view=2)


def _eval_test_folder(run: Run, tmp_path: Path, folder: Path, *options: str) -> Path:
    """Index ``folder`` (only a ``test/`` split) with ``threedq data index`` and run ``threedq eval`` of the run's
    quantizer on it, with ``--encoders`` for Table 2 per feature set; returns the output folder."""
    from threedq.cli import main
    from threedq.scene import load_index

    cats = load_index(run.root / "data").categories
    assert main(["data", "index", str(folder), "--categories", json.dumps(list(cats))]) == 0
    assert load_index(folder).files("train") == []
    cfg = tmp_path / "folder.yaml"
    cfg.write_text(yaml.safe_dump({"data": {
        "class_path": "threedq.datamodules.scene_folder.SceneFolderDataModule",
        "init_args": {"data_dir": str(folder), "num_target_views": 0, "train_random_views": False}}}))
    out = tmp_path / "eval"
    assert main(["eval", "--ckpt", str(run.quantizer), "--extra_configs", f"[{run.config}, {cfg}]", "--out", str(out),
                 *options, "--encoders", json.dumps({"vp": str(run.viewpred)})]) == 0
    return out


def test_eval_on_a_folder_with_only_a_test_split(run: Run, tmp_path: Path, capsys) -> None:
    """``threedq eval --baselines true`` on a folder indexed by ``threedq data index`` with only a test split: the
    retrieval table and its references are scored, the banks fitted on training objects are said not to run (one
    line), no traceback."""
    folder = tmp_path / "test_only"
    shutil.copytree(run.root / "data" / "test", folder / "test")
    capsys.readouterr()
    out = _eval_test_folder(run, tmp_path, folder, "--baselines", "true", "--curve_k", "[2]")
    printed = capsys.readouterr().out
    assert "no training split" in printed and "Traceback" not in printed
    res = json.loads((out / "results.json").read_text())
    assert set(res["quantization"]) == {"threedq"} and res["curve"] == {} and res["probe"] is None
    assert "no training split" in res["baselines_not_run"]
    assert set(res["retrieval"]["protocols"]) == {"strict", "paper"}
    md = (out / "results.md").read_text()
    assert "Not run:" in md and "paper protocol" in md and (out / "per_category_retrieval.png").is_file()
    # Table 2 per feature set: retrieval under both protocols, no probe or banks without training objects
    t2 = json.loads((out / "table2.json").read_text())
    assert t2["num_train_objects"] == 0 and "retrieval only" in (out / "table2.md").read_text()
    vp = t2["rows"]["vp"]
    assert 0 <= vp["precision_at_10_paper"] <= 1 and vp["hungarian_acc"] != vp["hungarian_acc"]  # NaN


def test_eval_on_single_view_scenes_scores_the_strict_protocol(run: Run, tmp_path: Path, capsys) -> None:
    """Scenes with one view have no second view for the paper protocol's gallery: the evaluation says so in one line
    naming a scene file and scores the strict protocol."""
    from dataclasses import replace

    from threedq.scene import load_scene, save_scene

    folder = tmp_path / "one_view"
    for f in sorted((run.root / "data" / "test").glob("*.npz")):
        rec = load_scene(f)
        one = replace(rec, rgb=rec.rgb[:1], depth=rec.depth[:1], K=rec.K[:1], world_T_cam=rec.world_T_cam[:1],
                      instance=None if rec.instance is None else rec.instance[:1])
        save_scene(folder / "test" / f.name, one)
    capsys.readouterr()
    out = _eval_test_folder(run, tmp_path, folder, "--baselines", "false", "--curve_k", "[]")
    res = json.loads((out / "results.json").read_text())
    assert set(res["retrieval"]["protocols"]) == {"strict"}
    assert "paper protocol needs a view" in res["paper_protocol_not_run"] and ".npz" in res["paper_protocol_not_run"]
    assert "paper protocol needs a view" in capsys.readouterr().out
    t2 = json.loads((out / "table2.json").read_text())
    assert t2["rows"]["vp"]["precision_at_10_paper"] is None and 0 <= t2["rows"]["vp"]["precision_at_10"] <= 1
