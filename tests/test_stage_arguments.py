"""Stage constructors: keyword-only, parents' arguments by keyword, every argument in the checkpoint, class defaults
equal to the packaged (tuned) configs, and a self-labelled detector decoding as the detector it fine-tunes."""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path

import pytest
import torch
import yaml
from threedq.stages.base import stage_arguments
from threedq.stages.detector import Detector
from threedq.stages.mining import Mining
from threedq.stages.quantizer import Quantizer
from threedq.stages.self_labelling import INHERITED_FROM_DETECTOR, SelfLabelling
from threedq.stages.supervised import SupervisedCeiling
from threedq.stages.viewpred import ViewPrediction

from threedq.pipeline.lightning_cli import load_config, packaged_configs_dir

STAGES = [ViewPrediction, Quantizer, Mining, SupervisedCeiling, Detector, SelfLabelling]
SMALL = {"grid_resolution": (16, 16, 8), "feature_dim": 8}


def _declared_defaults(cls: type) -> dict:
    """Every constructor argument along the class's bases, at the default of the most derived class declaring it
    (written out here with ``__init__.__code__``, independently of ``stage_arguments``)."""
    out: dict = {}
    for c in cls.__mro__:
        if c.__module__.startswith("lightning"):
            break
        init = c.__dict__.get("__init__")
        if init is None:
            continue
        code, defaults, kwdefaults = init.__code__, init.__defaults__ or (), init.__kwdefaults__ or {}
        positional = code.co_varnames[: code.co_argcount]
        for name, value in zip(positional[len(positional) - len(defaults):], defaults):
            out.setdefault(name, value)
        for name in code.co_varnames[code.co_argcount: code.co_argcount + code.co_kwonlyargcount]:
            if name in kwdefaults:
                out.setdefault(name, kwdefaults[name])
    return out


@pytest.mark.parametrize("cls", STAGES, ids=lambda c: c.__name__)
class TestStageArguments:
    def test_keyword_only(self, cls: type) -> None:
        params = inspect.signature(cls.__init__).parameters.values()
        assert all(p.kind in (p.KEYWORD_ONLY, p.VAR_KEYWORD) for p in params if p.name != "self")
        with pytest.raises(TypeError):
            cls((-1.0, -1.0, -0.5))

    def test_stage_arguments_against_the_code_objects(self, cls: type) -> None:
        assert stage_arguments(cls) == _declared_defaults(cls)

    def test_every_argument_in_hparams(self, cls: type) -> None:
        stage = cls(**SMALL)
        expected = _declared_defaults(cls)
        assert set(stage.hparams) == set(expected), set(stage.hparams) ^ set(expected)
        if cls is SelfLabelling:  # None = the detector's; without a detector checkpoint the Detector's defaults
            detector = _declared_defaults(Detector)
            expected.update({n: detector[n] for n in INHERITED_FROM_DETECTOR})
        for name, default in expected.items():
            if name in ("grid_min", "grid_max", "grid_resolution", "feature_dim", "encoder_channels", "feature_stride"):
                continue  # the resolved grid and widths (checked below)
            got = stage.hparams[name]
            assert (list(got) if isinstance(got, tuple) else got) == \
                (list(default) if isinstance(default, tuple) else default), name
        assert stage.hparams["grid_resolution"] == [16, 16, 8] and stage.hparams["feature_dim"] == 8
        assert stage.hparams["encoder_channels"] == [64, 128, 256]  # none given, no checkpoint: the paper's
        assert stage.hparams["feature_stride"] == 2  # likewise
        assert stage.hparams["grid_min"] == list(stage.grid.bounds_min)

    def test_a_parents_argument_by_keyword_reaches_the_parent(self, cls: type) -> None:
        stage = cls(channels_last=False, **SMALL)
        assert stage.channels_last is False and stage.hparams["channels_last"] is False

    def test_misspelt_argument_refused(self, cls: type) -> None:
        with pytest.raises(TypeError, match="grid_resolutoin"):
            cls(grid_resolutoin=(16, 16, 8))


def _stage_configs() -> list[str]:
    return sorted(str(p.relative_to(packaged_configs_dir())) for p in (packaged_configs_dir() / "stages").glob("*.yaml"))


#: What a stage config sets on purpose to other than its class's default: the grid and the encoder's widths view
#: prediction trains (the other stages take them from their encoder) and which correspondence source a mining config
#: runs.
CONFIG_CHOICES = {"grid_min", "grid_max", "grid_resolution", "feature_dim", "encoder_channels", "source"}
#: A variant config (one with ``base:``) holds only what it exists to set on top of its base; its own choices.
VARIANT_CHOICES = {"stages/detector_gt.yaml": set(), "stages/detector_scene.yaml": {"refine_to"},
                   "stages/quantizer_multiview.yaml": set(),
                   "stages/mining_occupancy_pairs.yaml": {"candidates_from"},
                   "stages/mining_paper.yaml": {"candidates_from", "candidates_per_query", "positives", "query_pool",
                                                "target_pool", "yaw_window", "rank_by"}}

#: the data arguments a variant sets (the detector's GT variant: ``boxes: gt``)
VARIANT_DATA = {"stages/quantizer_multiview.yaml": {"num_input_views": 3}, "stages/detector_scene.yaml": {}}


@pytest.mark.parametrize("config", _stage_configs())
def test_class_defaults_equal_the_tuned_config(config: str) -> None:
    model = load_config(config)["model"]
    module, name = model["class_path"].rsplit(".", 1)
    defaults = _declared_defaults(getattr(importlib.import_module(module), name))
    differ = {k: (defaults.get(k, "<not an argument>"), v) for k, v in (model.get("init_args") or {}).items()
              if not k.endswith("_ckpt") and k not in CONFIG_CHOICES | VARIANT_CHOICES.get(config, set())
              and (list(d) if isinstance(d := defaults.get(k, "<not an argument>"), tuple) else d) != v}
    assert not differ, f"{config}: class default vs config value: {differ}"


def test_a_variant_config_holds_only_its_choices() -> None:
    """Each variant names its stage's config as its base and sets its own choices and run folder, nothing else (of the
    data, the detector's GT variant its boxes, the quantizer's multi-view variant its input views)."""
    variants = sorted(str(p.relative_to(packaged_configs_dir())) for p in (packaged_configs_dir() / "stages").glob(
        "*.yaml") if "base" in (yaml.safe_load(p.read_text()) or {}))
    assert variants == sorted(VARIANT_CHOICES)
    for variant, own in VARIANT_CHOICES.items():
        cfg = yaml.safe_load((packaged_configs_dir() / variant).read_text())
        assert cfg["base"] == Path(variant).stem.split("_")[0] + ".yaml"
        assert set(cfg) <= {"base", "model", "data", "trainer"} and set(cfg["trainer"]) == {"default_root_dir"}
        assert set((cfg.get("model") or {}).get("init_args") or {}) == own
        data = VARIANT_DATA.get(variant, {"boxes": "gt"})
        assert (cfg.get("data") or {"init_args": data}) == {"init_args": data}


class TestSelfLabellingInheritsTheDetector:
    def _detector_ckpt(self, tmp_path: Path) -> Path:
        det = Detector(anchor_size=(0.4, 0.3, 0.2), channels=16, num_blocks=2, score_threshold=0.7,
                       eval_score_threshold=0.1, nms_iou=0.2, nms_iomin=0.5, max_detections=5, refine_iou=0.3,
                       flat_boxes=False, refine_to="scene", **SMALL)
        path = tmp_path / "det.ckpt"
        torch.save({"state_dict": det.state_dict(), "hyper_parameters": dict(det.hparams)}, path)
        return path

    def test_decoding_from_the_checkpoint(self, tmp_path: Path) -> None:
        ckpt = self._detector_ckpt(tmp_path)
        sl = SelfLabelling(detector_ckpt=str(ckpt), **SMALL)
        want = {"anchor_size": [0.4, 0.3, 0.2], "channels": 16, "num_blocks": 2, "score_threshold": 0.7,
                "eval_score_threshold": 0.1, "nms_iou": 0.2, "nms_iomin": 0.5, "max_detections": 5,
                "refine_iou": 0.3, "flat_boxes": False, "refine_to": "scene"}
        assert set(want) == set(INHERITED_FROM_DETECTOR)
        for k, v in want.items():
            got = sl.hparams[k]
            assert (list(got) if isinstance(got, tuple) else got) == pytest.approx(v), k
        assert torch.allclose(sl.anchor, torch.tensor([0.4, 0.3, 0.2]))
        # and the head loaded: same weights as the detector's
        state = torch.load(ckpt, weights_only=True)["state_dict"]
        assert all(torch.equal(sl.state_dict()[k], v) for k, v in state.items() if k.startswith("head."))

    def test_given_values_win(self, tmp_path: Path) -> None:
        sl = SelfLabelling(detector_ckpt=str(self._detector_ckpt(tmp_path)), score_threshold=0.95, nms_iou=0.05,
                           **SMALL)
        assert sl.hparams["score_threshold"] == 0.95 and sl.hparams["nms_iou"] == 0.05
        assert sl.hparams["max_detections"] == 5

    def test_without_a_checkpoint_the_detectors_defaults(self) -> None:
        sl = SelfLabelling(**SMALL)
        det = Detector(**SMALL)
        for k in INHERITED_FROM_DETECTOR:
            assert sl.hparams[k] == det.hparams[k], k
