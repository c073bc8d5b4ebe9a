"""Stage presets (threedq.pipeline.presets) and configs that change another (``base:``,
threedq.pipeline.lightning_cli.config_chain)."""

from __future__ import annotations

from pathlib import Path

import pytest

from threedq.pipeline.lightning_cli import ConfigError, config_chain, resolve_config, resolve_config_args
from threedq.pipeline.presets import stage_presets


class TestStagePresets:
    EMBEDDED = {"mining": "stages/mining.yaml", "quantizer": "stages/quantizer.yaml"}
    SHAPES = {"mining": "stages/mining_occupancy_pairs.yaml", "quantizer": "stages/quantizer_multiview.yaml"}
    CAPTURES = {**SHAPES, "detector": "stages/detector_scene.yaml"}

    def test_the_shipped_data_configs(self) -> None:
        assert stage_presets([]) == self.EMBEDDED  # the default data: the embedded scenes
        assert stage_presets(["data/clevr_veggie.yaml"]) == self.EMBEDDED
        for shapes in ("data/shapes.yaml", "data/shapes_unseen.yaml"):
            assert stage_presets([shapes]) == self.SHAPES

    def test_a_scene_folder_of_ones_own_takes_its_class_preset(self, tmp_path: Path) -> None:
        own = tmp_path / "desk.yaml"
        own.write_text("data:\n  class_path: threedq.datamodules.scene_folder.SceneFolderDataModule\n"
                       "  init_args:\n    data_dir: data/desk\n")
        assert stage_presets([own]) == self.CAPTURES
        own.write_text(own.read_text() + "presets:\n  mining: stages/mining.yaml\n")  # the config's own wins
        assert stage_presets([own]) == {**self.CAPTURES, "mining": "stages/mining.yaml"}
        own.write_text(own.read_text().replace("scene_folder.SceneFolderDataModule", "tum.TumRGBDDataModule"))
        assert stage_presets([own]) == {**self.CAPTURES, "mining": "stages/mining.yaml"}  # a capture DataModule

    def test_the_multiview_quantizer_is_its_base_with_three_views(self) -> None:
        from threedq.pipeline.lightning_cli import load_config

        base, multi = load_config("stages/quantizer.yaml"), load_config("stages/quantizer_multiview.yaml")
        assert multi["data"]["init_args"]["num_input_views"] == 3
        multi["data"]["init_args"]["num_input_views"] = 1
        multi["trainer"]["default_root_dir"] = base["trainer"]["default_root_dir"]
        assert multi == base

    def test_the_scene_detector_is_its_base_refined_against_the_scene(self) -> None:
        from threedq.pipeline.lightning_cli import load_config

        base, scene = load_config("stages/detector.yaml"), load_config("stages/detector_scene.yaml")
        assert scene["model"]["init_args"].pop("refine_to") == "scene"
        scene["trainer"]["default_root_dir"] = base["trainer"].get("default_root_dir")
        assert scene == base

    @pytest.mark.parametrize("presets, field", [("[a, b]", "presets"), ("{viewpred: x.yaml}", "presets.viewpred"),
                                                ("{mining: 3}", "presets.mining")])
    def test_bad_presets_name_file_and_field(self, presets: str, field: str, tmp_path: Path) -> None:
        bad = tmp_path / "bad.yaml"
        bad.write_text(f"presets: {presets}\n")
        with pytest.raises(ConfigError, match=rf"bad\.yaml: field '{field}'"):
            stage_presets([bad])

    def test_em_runs_the_data_configs_preset(self) -> None:
        """``threedq em --data_config X`` without ``--mining_config`` mines with X's preset; ``--mining_config`` and
        ``none`` win."""
        from threedq.pipeline.em import _resolve_configs

        def mining(data_config: str | None, mining_config: str | None = None) -> list[str]:
            cfg = _resolve_configs("stages/viewpred.yaml", "stages/quantizer.yaml", "stages/detector.yaml",
                                   mining_config, "stages/self_labelling.yaml", data_config, None, True, None)
            return [p.name for p in cfg.m]

        assert mining(None) == ["mining.yaml"]
        assert mining("data/shapes.yaml") == ["mining_occupancy_pairs.yaml", "shapes.yaml"]
        assert mining("data/shapes.yaml", "stages/mining.yaml") == ["mining.yaml", "shapes.yaml"]
        assert mining("data/shapes.yaml", "none") == []

    def test_em_quantizes_with_the_data_configs_preset(self) -> None:
        from threedq.pipeline.em import _resolve_configs

        def quantizer(data_config: str | None, quantizer_config: str | None = None) -> list[str]:
            cfg = _resolve_configs("stages/viewpred.yaml", quantizer_config, "stages/detector.yaml", "none",
                                   "stages/self_labelling.yaml", data_config, None, True, None)
            return [p.name for p in cfg.q]

        assert quantizer(None) == ["quantizer.yaml"]
        assert quantizer("data/shapes.yaml") == ["quantizer_multiview.yaml", "shapes.yaml"]
        assert quantizer("data/shapes.yaml", "stages/quantizer.yaml") == ["quantizer.yaml", "shapes.yaml"]

    def test_em_detects_with_the_data_configs_preset(self, tmp_path: Path) -> None:
        from threedq.pipeline.em import _resolve_configs

        def detector(data_config: str | None, detector_config: str | None = None) -> list[str]:
            cfg = _resolve_configs("stages/viewpred.yaml", None, detector_config, "none",
                                   "stages/self_labelling.yaml", data_config, None, True, None)
            return [p.name for p in cfg.d]

        own = tmp_path / "desk.yaml"
        own.write_text("data:\n  class_path: threedq.datamodules.scene_folder.SceneFolderDataModule\n"
                       "  init_args:\n    data_dir: data/desk\n")
        assert detector(None) == ["detector.yaml"]
        assert detector("data/shapes.yaml") == ["detector.yaml", "shapes.yaml"]
        assert detector(str(own)) == ["detector_scene.yaml", "desk.yaml"]
        assert detector(str(own), "stages/detector.yaml") == ["detector.yaml", "desk.yaml"]


class TestConfigChain:
    def test_a_variant_and_its_base(self, tmp_path: Path) -> None:
        chain = config_chain("stages/mining_occupancy_pairs.yaml")
        assert [p.name for p in chain] == ["mining.yaml", "mining_occupancy_pairs.yaml"]
        assert chain[0] == resolve_config("stages/mining.yaml")
        args = resolve_config_args(["fit", "--config", "stages/mining_paper.yaml"])
        assert args == ["fit", "--config", str(chain[0]), "--config", str(resolve_config("stages/mining_paper.yaml"))]

    def test_a_base_beside_the_variant_and_a_loop(self, tmp_path: Path) -> None:
        (tmp_path / "a.yaml").write_text("base: b.yaml\n")
        (tmp_path / "b.yaml").write_text("trainer:\n  max_steps: 3\n")
        assert config_chain(tmp_path / "a.yaml") == [tmp_path / "b.yaml", tmp_path / "a.yaml"]
        (tmp_path / "b.yaml").write_text("base: a.yaml\n")
        with pytest.raises(ConfigError, match="field 'base': the configs' bases form a loop"):
            config_chain(tmp_path / "a.yaml")
        (tmp_path / "c.yaml").write_text("base: [x]\n")
        with pytest.raises(ConfigError, match=r"c\.yaml: field 'base'"):
            config_chain(tmp_path / "c.yaml")
        (tmp_path / "d.yaml").write_text("base: nowhere.yaml\n")
        with pytest.raises(FileNotFoundError, match="nowhere.yaml"):
            config_chain(tmp_path / "d.yaml")
