"""``threedq em --preset paper``: which configs it runs, and that they are the paper's sizes."""

from __future__ import annotations

import pytest

from threedq.errors import InputError
from threedq.pipeline.em import _DEFAULT_CONFIGS, PAPER_PRESET, _preset
from threedq.pipeline.lightning_cli import load_config

DEFAULTS = tuple(_DEFAULT_CONFIGS.values())


class TestPreset:
    def test_default_changes_nothing(self) -> None:
        assert _preset("default", *DEFAULTS) == DEFAULTS
        assert _preset("default", "a.yaml", None, None, None, None, None) == ("a.yaml", None, None, None, None, None)

    def test_paper_replaces_every_default(self) -> None:
        assert _preset("paper", *DEFAULTS) == tuple(PAPER_PRESET.values())

    def test_a_config_given_stays(self) -> None:
        given = ("mine.yaml", *DEFAULTS[1:4], "none", "data/shapes.yaml")
        out = _preset("paper", *given)
        assert out[0] == "mine.yaml" and out[4] == "none" and out[5] == "data/shapes.yaml"
        assert out[1:4] == (PAPER_PRESET["quantizer_config"], PAPER_PRESET["detector_config"],
                            PAPER_PRESET["mining_config"])

    def test_exception(self) -> None:
        with pytest.raises(InputError, match="--preset: expected 'default' or 'paper'"):
            _preset("huge", *DEFAULTS)


class TestPaperSizes:
    """The preset's configs, their bases composed, hold the paper's sizes."""

    def test_sizes(self) -> None:
        vp = load_config(PAPER_PRESET["config"])
        assert vp["model"]["init_args"]["grid_resolution"] == [144, 144, 144]
        assert vp["model"]["init_args"]["encoder_channels"] == [64, 128, 256]
        assert vp["trainer"]["max_steps"] == 100_000 and vp["data"]["init_args"]["batch_size"] == 2
        assert load_config(PAPER_PRESET["data_config"])["data"]["init_args"]["image_size"] == [256, 256]
        mining = load_config(PAPER_PRESET["mining_config"])["model"]["init_args"]
        assert (mining["query_pool"], mining["target_pool"], mining["queue_size"]) == (1000, 1000, 100_000)
        assert mining["candidates_from"] == "features" and mining["positives"] == "patches"
        q = load_config(PAPER_PRESET["quantizer_config"])["model"]["init_args"]
        assert (q["num_prototypes"], q["num_angles"]) == (50, 36)
        sl = load_config(PAPER_PRESET["self_labelling_config"])["model"]["init_args"]
        assert (sl["positive_threshold"], sl["negative_threshold"], sl["pool_scenes"]) == (0.8, 0.65, 1000)
