"""View-prediction stage: shapes, one-scene overfit, the shared-encoder contract, the grid travelling with it."""

from __future__ import annotations

import pickle
from pathlib import Path

import lightning as L
import pytest
import torch
import torch.nn.functional as F
from threedq.datamodules.scene_folder import SceneFolderDataModule
from threedq.stages.base import EncoderStage, load_encoder_state
from threedq.stages.viewpred import ViewPrediction
from threedq.viz.features import view_prediction_figure

SMALL = dict(grid_resolution=(32, 32, 16), image_every_n_steps=0)


def first_batch(root: Path, batch_size: int, num_target_views: int, split: str = "val") -> dict[str, torch.Tensor]:
    """The first batch of the tiny dataset's ``split`` loader, one input view and ``num_target_views`` targets."""
    dm = SceneFolderDataModule(str(root), batch_size=batch_size, num_input_views=1, num_target_views=num_target_views)
    dm.setup()
    return next(iter(dm.val_dataloader() if split == "val" else dm.train_dataloader()))


@pytest.fixture(scope="module")
def batch(tiny_dataset: Path) -> dict[str, torch.Tensor]:
    return first_batch(tiny_dataset, 1, 1)


class TestViewPrediction:
    def test_shapes(self, batch: dict[str, torch.Tensor]) -> None:
        m = ViewPrediction(**SMALL)
        out = m(batch)
        assert out["features"].shape == (1, 32, 8, 16, 16)  # (nz, ny, nx) / 2
        norms = out["features"].norm(dim=1)
        assert torch.allclose(norms, torch.ones_like(norms), atol=1e-4)
        r = m._step(batch)
        assert r["pred"].shape == (1, 3, 16, 16) and r["pred"].abs().max() <= 0.5
        occ, free = r["occ"], m.occupancy_labels(batch["depth"], batch["K"], batch["R_T_cam"])[1]
        assert occ.shape == free.shape == (1, 1, 8, 16, 16)
        assert occ.sum() > 0 and free.sum() > 0 and (occ * free).sum() == 0

    def test_needs_a_target_view(self, batch: dict[str, torch.Tensor]) -> None:
        one = {k: (v[:, :1] if k in ("rgb", "depth", "K", "R_T_cam") else v) for k, v in batch.items()}
        with pytest.raises(ValueError, match=">= 1 target view"):
            ViewPrediction(**SMALL)._step(one)

    def test_overfit_one_scene(self, batch: dict[str, torch.Tensor]) -> None:
        L.seed_everything(0, verbose=False)
        m = ViewPrediction(**SMALL)
        opt = torch.optim.Adam(m.parameters(), lr=3e-3)
        first = m._step(batch)
        for _ in range(60):
            r = m._step(batch)
            opt.zero_grad()
            r["loss"].backward()
            opt.step()
        last = m._step(batch)
        assert last["l1"] < first["l1"] / 5
        assert last["loss"] < first["loss"] / 2.5
        assert last["occ_bacc"] > 0.9

    def test_the_loss_weighs_its_terms(self, batch: dict[str, torch.Tensor]) -> None:
        """``view_prediction_loss`` reports the RGB loss it weighted: rgb_weight * rgb_loss + occ_weight * occ."""
        torch.manual_seed(0)
        stage = ViewPrediction(grid_resolution=(32, 32, 16), image_every_n_steps=0, rgb_weight=7.0, occ_weight=3.0)
        with torch.no_grad():
            out = stage(batch)
            r = stage.view_prediction_loss(out["features"], out["occ_logits"], batch, 1)
        assert torch.isfinite(r["rgb_loss"]) and torch.isfinite(r["occ_loss"]) and r["rgb_loss"] > 0
        torch.testing.assert_close(r["loss"], 7.0 * r["rgb_loss"] + 3.0 * r["occ_loss"])

    def test_figure(self, batch: dict[str, torch.Tensor]) -> None:
        m = ViewPrediction(**SMALL)
        r = m._step(batch)
        img = view_prediction_figure(batch["rgb"][0, 0], r["pred"][0] + 0.5, r["target"][0] + 0.5,
                                     torch.sigmoid(r["occ_logits"][0, 0]), r["occ"][0, 0])
        assert img.dtype.name == "uint8" and img.shape == (32, 5 * 32 + 4 * 2, 3)


class TestBalancedRgbLoss:
    """The default RGB loss balances the pixels above the ground (the objects) against the rest."""

    @pytest.fixture(scope="class")
    def many(self, tiny_dataset: Path) -> dict[str, torch.Tensor]:
        return first_batch(tiny_dataset, 4, 3, "train")

    def test_foreground_matches_the_instance_masks(self, many: dict[str, torch.Tensor]) -> None:
        b = many
        m = ViewPrediction(**SMALL)
        fg = m.target_foreground(b, 1)  # label-free: depth and poses only
        T = b["rgb"].shape[1] - 1
        objects = (F.avg_pool2d((b["instance"][:, 1:].flatten(0, 1)[:, None] > 0).float(), 2) > 0.5).float()
        valid = m.target_valid(*(b[k][:, 1:].flatten(0, 1) for k in ("depth", "K", "R_T_cam")))
        assert fg.shape == objects.shape == (4 * T, 1, 16, 16)
        agree = ((fg == objects).float() * valid).sum() / valid.sum()
        assert objects.sum() > 20 and agree > 0.97

    def test_plain_is_the_papers_loss_and_balanced_differs(self, many: dict[str, torch.Tensor]) -> None:
        batch = many
        torch.manual_seed(0)
        plain = ViewPrediction(**SMALL, rgb_loss="plain")
        balanced = ViewPrediction(**SMALL)
        balanced.load_state_dict(plain.state_dict())
        rp, rb = plain._step(batch), balanced._step(batch)  # training mode
        torch.testing.assert_close(rp["loss"], 30.0 * rp["l1"] + rp["occ_loss"])
        torch.testing.assert_close(rp["l1"], rb["l1"])
        assert "l1_fg" not in rp  # plain training skips the ground fit
        balanced.eval()
        re = balanced._step(batch)
        assert re["l1_fg"] > 0 and re["l1_fg_mean_colour"] > 0
        assert not torch.allclose(rb["loss"], rp["loss"])

    def test_bad_settings(self) -> None:
        from conftest import refused

        for name, bad in (("rgb_loss", "l2"), ("ground_margin", -0.01)):
            assert name in refused(ViewPrediction, **{name: bad})


class TestTargetViews:
    """Several target views per sample."""

    def test_num_input_views_is_read_from_the_batch(self, tiny_dataset: Path) -> None:
        dm = SceneFolderDataModule(str(tiny_dataset), batch_size=1, num_input_views=1, num_target_views=2)
        dm.setup()
        b = next(iter(dm.val_dataloader()))
        assert b["rgb"].shape[1] == 3 and int(b["num_input_views"][0]) == 1
        r = ViewPrediction(**SMALL)._step(b)
        assert r["pred"].shape == (2, 3, 16, 16)  # one prediction per target view

    def test_duplicated_target_gives_the_same_loss(self, batch: dict[str, torch.Tensor]) -> None:
        torch.manual_seed(3)
        m = ViewPrediction(**SMALL).eval()
        dup = {k: (torch.cat([v, v[:, -1:]], 1) if k in ("rgb", "depth", "K", "R_T_cam") else v) for k, v in batch.items()}
        with torch.no_grad():
            one, two = m._step(batch), m._step(dup)
        assert torch.allclose(one["l1"], two["l1"], atol=1e-6)
        assert torch.allclose(one["l1_mean_colour"], two["l1_mean_colour"], atol=1e-6)
        assert torch.equal(two["pred"][0], two["pred"][1])


class TestEncoderContract:
    def test_load_from_lightning_checkpoint(self, tmp_path: Path) -> None:
        torch.manual_seed(1)
        src = ViewPrediction(**SMALL)
        ckpt = tmp_path / "vp.ckpt"
        torch.save({"state_dict": src.state_dict(), "hyper_parameters": dict(src.hparams)}, ckpt)
        dst = EncoderStage(grid_resolution=(32, 32, 16), encoder_ckpt=str(ckpt))
        for (k, a), b in zip(src.encoder.state_dict().items(), dst.encoder.state_dict().values()):
            assert torch.equal(a, b), k

    def test_plain_state_dict_and_freezing(self, tmp_path: Path) -> None:
        torch.manual_seed(2)
        src = EncoderStage(grid_resolution=(32, 32, 16))
        path = tmp_path / "encoder.pt"
        torch.save(src.encoder.state_dict(), path)
        dst = EncoderStage(grid_resolution=(32, 32, 16), encoder_ckpt=str(path), freeze_encoder=True)
        dst.train()
        assert not any(p.requires_grad for p in dst.encoder.parameters())
        assert not dst.encoder.training  # frozen BatchNorm statistics
        tuned = EncoderStage(grid_resolution=(32, 32, 16), encoder_ckpt=str(path), freeze_encoder=False)
        assert all(p.requires_grad for p in tuned.encoder.parameters())

    @pytest.mark.parametrize("stage", ["detector", "quantizer"])
    def test_frozen_encoder_is_unchanged_by_fit(self, stage: str, tmp_path: Path, tiny_dataset: Path) -> None:
        """Lightning never calls train() at fit start: a frozen encoder must already be in eval mode."""
        from threedq.stages.detector import Detector
        from threedq.stages.quantizer import Quantizer

        torch.manual_seed(3)
        src = EncoderStage(grid_resolution=(32, 32, 16))
        with torch.no_grad():  # non-trivial running statistics, so that drifting them would show
            src.train()
            src.encode_views(*(torch.rand(2, 1, *s) for s in ((3, 32, 32), (32, 32))),
                             torch.tensor([[[[40.0, 0, 16], [0, 40, 16], [0, 0, 1]]]]).expand(2, 1, 3, 3),
                             torch.eye(4).expand(2, 1, 4, 4))
        path = tmp_path / "encoder.pt"
        torch.save(src.encoder.state_dict(), path)
        kind = Detector if stage == "detector" else Quantizer
        extra = {"num_prototypes": 2, "crop_size": 8, "em_iterations": 1} if stage == "quantizer" else {}
        m = kind(grid_resolution=(32, 32, 16), encoder_ckpt=str(path), freeze_encoder=True, **extra)
        dm = SceneFolderDataModule(str(tiny_dataset), batch_size=2, num_input_views=1, num_target_views=0)
        seen_modes = []
        m.on_train_batch_start = lambda *a: seen_modes.append(m.encoder.training)
        L.Trainer(max_steps=2, max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                  enable_model_summary=False, num_sanity_val_steps=0, limit_val_batches=0,
                  default_root_dir=tmp_path).fit(m, dm)
        assert seen_modes and not any(seen_modes)
        for (k, a), b in zip(src.encoder.state_dict().items(), m.encoder.state_dict().values()):
            assert torch.equal(a, b), k

    def test_errors(self, tmp_path: Path) -> None:
        with pytest.raises(FileNotFoundError, match="encoder_ckpt"):
            EncoderStage(encoder_ckpt=str(tmp_path / "missing.ckpt"))
        other = EncoderStage(grid_resolution=(32, 32, 16), feature_dim=16)
        path = tmp_path / "enc16.pt"
        torch.save({"state_dict": other.state_dict()}, path)
        with pytest.raises(ValueError, match=r"enc16\.pt: field 'encoder\.head\.weight'"):
            EncoderStage(grid_resolution=(32, 32, 16), encoder_ckpt=str(path))
        evil = tmp_path / "evil.ckpt"
        evil.write_bytes(pickle.dumps({"state_dict": {"encoder.x": object()}}))
        with pytest.raises(ValueError, match="cannot be loaded safely"):
            load_encoder_state(other.encoder, evil)
        no_enc = tmp_path / "noenc.ckpt"
        torch.save({"state_dict": {"decoder.w": torch.zeros(1)}, "epoch": 3}, no_enc)
        with pytest.raises(ValueError, match="no 'encoder"):
            load_encoder_state(other.encoder, no_enc)


class TestGridTravelsWithEncoder:
    """Later stages read the grid from the encoder checkpoint; a stage naming another grid is refused."""

    def _viewpred_ckpt(self, tmp_path: Path, **grid) -> Path:
        torch.manual_seed(4)
        src = ViewPrediction(image_every_n_steps=0, **grid)
        ckpt = tmp_path / "vp.ckpt"
        torch.save({"state_dict": src.state_dict(), "hyper_parameters": dict(src.hparams)}, ckpt)
        return ckpt

    def test_the_grid_comes_from_the_checkpoint(self, tmp_path: Path) -> None:
        from threedq.stages.detector import Detector
        from threedq.stages.quantizer import Quantizer

        grid = {"grid_min": (-1.0, -1.0, -0.5), "grid_max": (1.0, 1.0, 0.5), "grid_resolution": (32, 32, 16),
                "feature_dim": 16}
        ckpt = self._viewpred_ckpt(tmp_path, **grid)
        for stage in (Detector(encoder_ckpt=str(ckpt)), Quantizer(encoder_ckpt=str(ckpt), num_prototypes=2, crop_size=8)):
            assert stage.grid.resolution == (32, 32, 16) and stage.feature_dim == 16
            assert stage.grid.bounds_min == (-1.0, -1.0, -0.5) and stage.grid.bounds_max == (1.0, 1.0, 0.5)
            # and the stage's own checkpoint carries it on
            assert stage.hparams["grid_resolution"] == [32, 32, 16] and stage.hparams["feature_dim"] == 16
            assert stage.hparams["grid_min"] == [-1.0, -1.0, -0.5]

    def test_same_values_named_again_are_fine(self, tmp_path: Path) -> None:
        ckpt = self._viewpred_ckpt(tmp_path, grid_resolution=(32, 32, 16))
        assert EncoderStage(grid_resolution=[32, 32, 16], encoder_ckpt=str(ckpt)).grid.resolution == (32, 32, 16)

    @pytest.mark.parametrize(
        "field, value",
        [("grid_resolution", (64, 64, 32)), ("feature_dim", 8), ("grid_max", (1.28, 1.28, 1.0)),
         ("encoder_channels", (16, 32, 64)), ("feature_stride", 1)],
    )
    def test_another_grid_is_refused(self, tmp_path: Path, field: str, value) -> None:
        ckpt = self._viewpred_ckpt(tmp_path, grid_resolution=(32, 32, 16))
        with pytest.raises(ValueError, match=rf"vp\.ckpt: field '{field}': the encoder was trained with") as e:
            EncoderStage(encoder_ckpt=str(ckpt), **{field: value})
        assert "\n" not in str(e.value)

    def test_encoder_widths_come_from_the_checkpoint(self, tmp_path: Path) -> None:
        from threedq.stages.detector import Detector

        ckpt = self._viewpred_ckpt(tmp_path, grid_resolution=(32, 32, 16), encoder_channels=(8, 16, 32))
        src = torch.load(ckpt, weights_only=True)["state_dict"]
        assert src["encoder.enc1.0.weight"].shape[0] == 8 and src["encoder.enc3.0.weight"].shape[0] == 32
        det = Detector(encoder_ckpt=str(ckpt))
        assert det.encoder.channels == (8, 16, 32) and det.hparams["encoder_channels"] == [8, 16, 32]
        # the weights were loaded, not only the shapes matched
        assert torch.equal(det.encoder.state_dict()["enc2.0.weight"], src["encoder.enc2.0.weight"])

    def test_a_checkpoint_without_widths_has_the_papers(self, tmp_path: Path) -> None:
        """Checkpoints written before ``encoder_channels`` existed hold the paper's (64, 128, 256) encoder."""
        ckpt = self._viewpred_ckpt(tmp_path, grid_resolution=(32, 32, 16))
        obj = torch.load(ckpt, weights_only=True)
        del obj["hyper_parameters"]["encoder_channels"]
        torch.save(obj, ckpt)
        assert EncoderStage(encoder_ckpt=str(ckpt)).encoder.channels == (64, 128, 256)

    def test_feature_stride_comes_from_the_checkpoint(self, tmp_path: Path) -> None:
        """Features on the input grid (``feature_stride=1``): the stage's feature grid is the input grid, and a later
        stage takes the stride and the weights of the extra layer from the encoder checkpoint."""
        from threedq.stages.quantizer import Quantizer

        ckpt = self._viewpred_ckpt(tmp_path, grid_resolution=(32, 32, 16), encoder_channels=(8, 16, 32),
                                   feature_stride=1)
        src = torch.load(ckpt, weights_only=True)
        assert src["hyper_parameters"]["feature_stride"] == 1
        q = Quantizer(encoder_ckpt=str(ckpt), num_prototypes=2, crop_size=8)
        assert q.encoder.output_stride == 1 and q.hparams["feature_stride"] == 1
        assert q.feature_grid.resolution == q.grid.resolution == (32, 32, 16)
        assert torch.equal(q.encoder.state_dict()["dec3.0.weight"], src["state_dict"]["encoder.dec3.0.weight"])
        with torch.no_grad():
            assert q.encoder(torch.rand(1, 4, 16, 32, 32)).shape == (1, 32, 16, 32, 32)

    def test_a_checkpoint_without_a_stride_has_the_papers(self, tmp_path: Path) -> None:
        ckpt = self._viewpred_ckpt(tmp_path, grid_resolution=(32, 32, 16), encoder_channels=(8, 16, 32))
        obj = torch.load(ckpt, weights_only=True)
        del obj["hyper_parameters"]["feature_stride"]
        torch.save(obj, ckpt)
        s = EncoderStage(encoder_ckpt=str(ckpt))
        assert s.encoder.output_stride == 2 and s.feature_grid.resolution == (16, 16, 8)

    def test_a_stride_other_than_1_or_2_is_refused(self) -> None:
        with pytest.raises(ValueError, match="feature_stride: expected 1 or 2, got 4"):
            EncoderStage(feature_stride=4)

    def test_no_checkpoint_no_grid_gives_the_default(self) -> None:
        from threedq.stages.base import DEFAULT_GRID

        s = EncoderStage()
        assert s.grid.resolution == DEFAULT_GRID["grid_resolution"] and s.feature_dim == DEFAULT_GRID["feature_dim"]
