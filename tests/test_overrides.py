"""``stage_overrides``: the LightningCLI overrides ``threedq em`` hands a stage, checked against what it takes."""

from __future__ import annotations

from pathlib import Path

import pytest
from threedq.datamodules.clevr_veggie import ClevrVeggieDataModule
from threedq.stages.quantizer import Quantizer
from threedq.stages.self_labelling import SelfLabelling

from threedq.errors import InputError
from threedq.pipeline.lightning_cli import resolve_config
from threedq.pipeline.overrides import class_of, stage_overrides

QUANTIZER = [resolve_config("stages/quantizer.yaml")]
SELF_LABELLING = [resolve_config("stages/self_labelling.yaml")]


class TestStageOverrides:
    def test_smoke_hand_written(self, tmp_path: Path) -> None:
        got = stage_overrides(QUANTIZER, model={"encoder_ckpt": tmp_path / "a.ckpt", "init_bank_ckpt": None},
                              data={"boxes": "d/detections_{split}.npz"},
                              trainer={"max_steps": -1, "precision": "bf16-mixed", "enable_checkpointing": False})
        assert got == [f"--model.init_args.encoder_ckpt={tmp_path / 'a.ckpt'}", "--model.init_args.init_bank_ckpt=null",
                       "--data.init_args.boxes=d/detections_{split}.npz", "--trainer.max_steps=-1",
                       "--trainer.precision=bf16-mixed", "--trainer.enable_checkpointing=false"]
        assert stage_overrides(QUANTIZER) == [] and stage_overrides(QUANTIZER, model={}, trainer=None) == []

    def test_parents_arguments_count(self) -> None:
        # SelfLabelling takes the detector's and the encoder's arguments by keyword
        assert stage_overrides(SELF_LABELLING, model={"nms_iou": 0.2, "grid_resolution": [8, 8, 4]}) == [
            "--model.init_args.nms_iou=0.2", "--model.init_args.grid_resolution=[8, 8, 4]"]

    @pytest.mark.parametrize("key, values, name", [
        ("model", {"encoder_checkpoint": "x"}, "Quantizer (model of quantizer.yaml): takes no argument 'encoder_checkpoint'"),
        ("data", {"boxs": "x"}, "ClevrVeggieDataModule (data of quantizer.yaml): takes no argument 'boxs'"),
        ("trainer", {"max_step": 3}, "lightning.Trainer: takes no argument 'max_step'"),
    ])
    def test_exception(self, key: str, values: dict, name: str) -> None:
        with pytest.raises(InputError) as e:
            stage_overrides(QUANTIZER, **{key: values})
        assert name in str(e.value) and "\n" not in str(e.value)

    def test_the_last_config_names_the_class(self, tmp_path: Path) -> None:
        other = tmp_path / "other.yaml"
        other.write_text("model:\n  class_path: threedq.stages.self_labelling.SelfLabelling\n")
        assert class_of(QUANTIZER, "model") is Quantizer and class_of([*QUANTIZER, other], "model") is SelfLabelling
        assert class_of(QUANTIZER, "data") is ClevrVeggieDataModule
        stage_overrides([*QUANTIZER, other], model={"detector_ckpt": None})  # SelfLabelling's argument now
        unknown = tmp_path / "unknown.yaml"
        unknown.write_text("model:\n  class_path: my_lab.MyStage\n")
        assert class_of([unknown], "model") is None
        assert stage_overrides([unknown], model={"anything": 1}) == ["--model.init_args.anything=1"]  # not checkable
