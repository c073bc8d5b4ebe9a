"""The checkpoint contract (stages/checkpoint.py): one object per file, read once, refused in one line when unsafe."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from threedq.errors import InputError
from threedq.stages import checkpoint as ck
from threedq.stages.base import EncoderStage


@pytest.fixture()
def count_loads(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    """Every ``torch.load`` the contract makes, by path (the cache starts empty)."""
    monkeypatch.setattr(ck, "_CACHE", type(ck._CACHE)())
    calls: list[Path] = []
    real = torch.load

    def load(path, *args, **kwargs):
        calls.append(Path(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(ck.torch, "load", load)
    return calls


def _lightning_file(path: Path, hparams: dict | None, state: dict) -> Path:
    obj = {"state_dict": state, **({"hyper_parameters": hparams} if hparams is not None else {})}
    torch.save(obj, path)
    return path


class TestLoadCheckpoint:
    def test_every_helper_reads_the_file_once(self, tmp_path: Path, count_loads: list[Path]) -> None:
        p = _lightning_file(tmp_path / "q.ckpt", {"_class_path": "threedq.stages.quantizer.Quantizer", "feature_dim": 8},
                            {"encoder.w": torch.ones(2), "bank.prototypes": torch.zeros(3, 8)})
        assert ck.checkpoint_stage(p) == "quantizer"
        assert ck.checkpoint_hparams(p)["feature_dim"] == 8
        assert ck.encoder_grid_from_checkpoint(p) == {"feature_dim": 8}
        assert set(ck.checkpoint_state(p)) == {"encoder.w", "bank.prototypes"}
        assert torch.equal(ck.encoder_state_from_checkpoint(p)["w"], torch.ones(2))
        ck.require_stage(p, "quantizer", "--ckpt")
        assert count_loads == [p]

    def test_a_stage_reads_its_encoder_file_once(self, tmp_path: Path, count_loads: list[Path]) -> None:
        torch.manual_seed(0)
        src = EncoderStage(grid_resolution=(16, 16, 8), feature_dim=8)
        p = _lightning_file(tmp_path / "vp.ckpt", {"grid_resolution": [16, 16, 8], "feature_dim": 8},
                            {f"encoder.{k}": v for k, v in src.encoder.state_dict().items()})
        stage = EncoderStage(encoder_ckpt=str(p))  # the grid and the weights, from one read
        assert stage.grid_fields["grid_resolution"] == (16, 16, 8) and count_loads == [p]
        for k, v in src.encoder.state_dict().items():
            assert torch.equal(stage.encoder.state_dict()[k], v)

    def test_rewritten_file_is_read_again(self, tmp_path: Path, count_loads: list[Path]) -> None:
        p = _lightning_file(tmp_path / "a.ckpt", {"x": 1}, {"head.w": torch.zeros(1)})
        assert ck.checkpoint_hparams(p)["x"] == 1
        _lightning_file(p, {"x": 2, "y": [1, 2, 3]}, {"head.w": torch.zeros(1)})
        os.utime(p, ns=(p.stat().st_atime_ns, p.stat().st_mtime_ns + 10**9))  # a later mtime, whatever the clock
        assert ck.checkpoint_hparams(p)["x"] == 2
        assert count_loads == [p, p]

    def test_returned_mappings_do_not_change_the_cache(self, tmp_path: Path, count_loads: list[Path]) -> None:
        p = _lightning_file(tmp_path / "a.ckpt", {"x": 1}, {"head.w": torch.zeros(1)})
        ck.checkpoint_hparams(p)["x"] = 99
        ck.checkpoint_state(p).pop("head.w")
        assert ck.checkpoint_hparams(p)["x"] == 1 and "head.w" in ck.checkpoint_state(p)

    def test_prefixed_and_stage_by_weights(self, tmp_path: Path) -> None:
        p = _lightning_file(tmp_path / "d.ckpt", None, {"head.a.w": torch.ones(1), "encoder.b": torch.zeros(1)})
        c = ck.load_checkpoint(p)
        assert set(c.prefixed("head.")) == {"a.w"} and c.prefixed("bank.") == {}
        assert c.stage == "detector" and c.hparams is None and c.grid == {}
        assert ck.checkpoint_hparams(p, missing_ok=True) == {}
        with pytest.raises(InputError, match="hyper_parameters"):
            ck.checkpoint_hparams(p)

    def test_bare_encoder_state_dict(self, tmp_path: Path) -> None:
        p = tmp_path / "enc.pt"
        torch.save({"conv.weight": torch.ones(2)}, p)
        c = ck.load_checkpoint(p)
        assert not c.is_lightning and c.stage is None
        assert set(ck.encoder_state_from_checkpoint(p)) == {"conv.weight"}
        with pytest.raises(InputError, match="not a Lightning checkpoint"):
            ck.checkpoint_state(p)

    @pytest.mark.parametrize("content", [b"not a checkpoint", b"PK\x03\x04 truncated"])
    def test_unreadable_file_is_one_line_naming_it(self, tmp_path: Path, content: bytes) -> None:
        p = tmp_path / "bad.ckpt"
        p.write_bytes(content)
        with pytest.raises(InputError) as e:
            ck.load_checkpoint(p)
        assert str(p) in str(e.value) and "\n" not in str(e.value)

    def test_python_objects_are_refused(self, tmp_path: Path) -> None:
        p = tmp_path / "pickle.ckpt"
        torch.save({"state_dict": {}, "hyper_parameters": {"f": Path("x")}}, p)
        with pytest.raises(InputError, match="weights_only"):
            ck.load_checkpoint(p)

    def test_missing_file(self, tmp_path: Path) -> None:
        with pytest.raises(FileNotFoundError, match="no such file"):
            ck.load_checkpoint(tmp_path / "nope.ckpt")


class TestAtomicCheckpointIO:
    def test_smoke_round_trip(self, tmp_path: Path) -> None:
        io = ck.AtomicCheckpointIO()
        state = {"state_dict": {"w": torch.arange(6.0).reshape(2, 3)}, "hyper_parameters": {"a": 1}}
        io.save_checkpoint(state, tmp_path / "sub" / "last.ckpt")
        back = torch.load(tmp_path / "sub" / "last.ckpt", weights_only=True)
        assert torch.equal(back["state_dict"]["w"], state["state_dict"]["w"]) and back["hyper_parameters"] == {"a": 1}

    def test_exception(self, tmp_path: Path) -> None:
        with pytest.raises(TypeError, match="storage_options"):
            ck.AtomicCheckpointIO().save_checkpoint({}, tmp_path / "x.ckpt", storage_options={"x": 1})

    def test_full_disk_keeps_the_previous_checkpoint(self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        import errno

        path = tmp_path / "last.ckpt"
        io = ck.AtomicCheckpointIO()
        io.save_checkpoint({"step": torch.tensor(1)}, path)
        before = path.read_bytes()

        def full(fd: int) -> None:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        monkeypatch.setattr(os, "fsync", full)
        with pytest.raises(OSError) as e:
            io.save_checkpoint({"step": torch.tensor(2)}, path)
        assert e.value.errno == errno.ENOSPC and e.value.filename == str(path)
        assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["last.ckpt"]

    def test_every_cli_run_writes_through_it(self, tiny_dataset: Path, tmp_path: Path) -> None:
        from threedq.pipeline.lightning_cli import ThreeDQCLI

        cli = ThreeDQCLI(args=["--config", "stages/viewpred.yaml", f"--data.init_args.data_dir={tiny_dataset}",
                               f"--trainer.default_root_dir={tmp_path}"], run=False)
        assert isinstance(cli.trainer.strategy.checkpoint_io, ck.AtomicCheckpointIO)


class TestLastStepCheckpoint:
    """``last.ckpt`` after a fit stopped by ``max_steps`` between two step saves, mid-epoch, with validation every
    2nd epoch (so no epoch-end save): the shape of ``threedq fit --trainer.max_steps=850`` on 200-step epochs."""

    @staticmethod
    def _fit(callback_cls: type, tmp_path: Path, max_steps: int) -> int:
        import lightning as L
        from lightning.pytorch.demos.boring_classes import BoringModel

        L.seed_everything(0, verbose=False)
        ckpt = callback_cls(dirpath=tmp_path / "checkpoints", save_last=True, every_n_train_steps=10)
        trainer = L.Trainer(max_steps=max_steps, check_val_every_n_epoch=2, callbacks=[ckpt], logger=False,
                            enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)
        trainer.fit(BoringModel())  # 32 training batches an epoch
        assert trainer.global_step == max_steps
        return torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)["global_step"]

    def test_lightnings_own_keeps_the_last_multiple(self, tmp_path: Path) -> None:
        from lightning.pytorch.callbacks import ModelCheckpoint

        assert self._fit(ModelCheckpoint, tmp_path, 25) == 20  # the defect this class exists for

    @pytest.mark.parametrize("max_steps", [25, 20, 45])
    def test_holds_the_final_step(self, tmp_path: Path, max_steps: int) -> None:
        assert self._fit(ck.LastStepCheckpoint, tmp_path, max_steps) == max_steps

    def test_the_cli_uses_it(self, tiny_dataset: Path, tmp_path: Path) -> None:
        from threedq.pipeline.lightning_cli import ThreeDQCLI

        cli = ThreeDQCLI(args=["--config", "stages/viewpred.yaml", f"--data.init_args.data_dir={tiny_dataset}",
                               f"--trainer.default_root_dir={tmp_path}"], run=False)
        assert [type(c) for c in cli.trainer.callbacks if isinstance(c, ck.ModelCheckpoint)] == [ck.LastStepCheckpoint]
