"""The supervised ceiling (a Table 2 reference row): encoder + crop + linear classifier trained with labels."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
import yaml

from threedq.datamodules.scene_folder import SceneFolderDataModule
from threedq.stages.supervised import SupervisedCeiling

GRID = {"grid_min": (-1.28, -1.28, -0.32), "grid_max": (1.28, 1.28, 0.96), "grid_resolution": (32, 32, 16),
        "feature_dim": 8}


def _batch(data: Path) -> dict[str, torch.Tensor]:
    dm = SceneFolderDataModule(data_dir=str(data), batch_size=4, num_target_views=0)
    dm.setup("fit")
    return next(iter(dm.train_dataloader()))


class TestSupervisedCeiling:
    def test_overfits_one_batch(self, tiny_dataset: Path) -> None:
        torch.manual_seed(0)
        batch = _batch(tiny_dataset)
        n = int(batch["box_mask"].sum())
        assert n >= 2
        stage = SupervisedCeiling(**GRID, num_classes=41, channels_last=False)
        opt = stage.configure_optimizers()
        losses = []
        for _ in range(40):
            opt.zero_grad()
            loss = stage.training_step(batch, 0)
            loss.backward()
            opt.step()
            losses.append(loss.item())
        assert losses[-1] < 0.2 * losses[0]
        stage.eval()
        with torch.no_grad():
            crops = stage.object_crops(batch, 1, 16)
            assert torch.equal(stage.logits(crops["features"]).argmax(1), crops["labels"])

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="num_classes"):
            SupervisedCeiling(**GRID, num_classes=1)

    def test_packaged_config_trains_and_its_encoder_is_a_table2_row(self, tmp_path: Path, tiny_dataset: Path) -> None:
        """``threedq fit --config stages/supervised.yaml`` on the tiny data: num_classes from index.json, the
        checkpoint carries it and its encoder loads where ``threedq eval --encoders`` loads one."""
        from threedq.pipeline.lightning_cli import ThreeDQCLI, resolve_config
        from threedq.scene import load_index
        from threedq.stages.base import load_encoder_state
        from threedq.nets import UNet3D

        data = tmp_path / "data"
        shutil.copytree(tiny_dataset, data, ignore=shutil.ignore_patterns("proposals"))
        cfg = tmp_path / "tiny.yaml"
        cfg.write_text(yaml.safe_dump({
            "model": {"init_args": {"grid_resolution": [32, 32, 16]}},
            "data": {"init_args": {"data_dir": str(data), "num_scenes": 12, "image_size": [32, 32], "num_views": 4,
                                   "generator_workers": 1}},
            "trainer": {"max_steps": 2, "log_every_n_steps": 1, "limit_val_batches": 1, "enable_progress_bar": False,
                        "enable_model_summary": False, "logger": False},
        }))
        cli = ThreeDQCLI(args=["fit", "--config", str(resolve_config("stages/supervised.yaml")), "--config", str(cfg),
                               f"--trainer.default_root_dir={tmp_path / 'run'}"])
        ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
        if not ckpt.is_file():  # no logger: Lightning names the checkpoint after the step
            ckpt = next((tmp_path / "run" / "checkpoints").glob("*.ckpt"))
        hp = torch.load(ckpt, weights_only=True, map_location="cpu")["hyper_parameters"]
        assert hp["num_classes"] == len(load_index(data).categories) == cli.model.classifier.out_features
        enc = UNet3D(in_channels=4, out_channels=32)
        load_encoder_state(enc, ckpt)
        trained = cli.model.encoder.state_dict()
        assert all(torch.equal(v, trained[k]) for k, v in enc.state_dict().items())
