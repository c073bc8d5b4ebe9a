"""Every packaged config (``configs/``), each parsed as itself and run for one batch on the tiny dataset.

A stage config is the only ``--config`` of its run; a data or trainer config is composed with
``stages/viewpred.yaml`` (they hold no model) and its own values must reach the parsed result. Each runs with
``--trainer.fast_dev_run=true`` on the tiny fixture: the overrides below only point the data at the fixture, shrink
the grid to it and hand over the checkpoints a stage reads (made by the packaged configs of the stages that write
them); nothing else of the config is replaced. Trainer configs that need a GPU or several processes
(``gpu``, ``ddp``, ``ddp_cpu``) are parsed, not run: CI has neither (``tests/test_ddp.py`` runs real DDP).
A copy of a config with one key misspelt must fail the same check (``TestMutatedConfig``). Stage configs name no
dataset: ``TestDataComposition`` checks that a data config of one's own replaces the default one, before or after the
stage config, and that the stage's loading arguments survive the change of DataModule class.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
import yaml

from threedq.cli import main
from threedq.pipeline.lightning_cli import ThreeDQCLI, default_data, load_config, packaged_configs_dir

CONFIGS = sorted(str(p.relative_to(packaged_configs_dir())) for p in packaged_configs_dir().glob("*/*.yaml"))
#: Trainer configs parsed but not run here (a GPU, or several processes).
PARSE_ONLY = {"trainer/gpu.yaml", "trainer/ddp.yaml", "trainer/ddp_cpu.yaml"}
#: Stages whose config names its own grid (they train an encoder from scratch): shrunk to the tiny data.
OWN_GRID = {"stages/viewpred.yaml", "stages/supervised.yaml", "paper/viewpred.yaml"}
#: What each stage config reads from another stage's checkpoint (filled by the ``checkpoints`` fixture).
NEEDS = {
    "stages/detector.yaml": ("encoder_ckpt",),
    "stages/detector_gt.yaml": ("encoder_ckpt",),
    "stages/detector_scene.yaml": ("encoder_ckpt",),
    "stages/quantizer.yaml": ("encoder_ckpt",),
    "stages/quantizer_multiview.yaml": ("encoder_ckpt",),
    "stages/mining.yaml": ("encoder_ckpt",),
    "stages/mining_occupancy_pairs.yaml": ("encoder_ckpt",),
    "stages/mining_paper.yaml": ("encoder_ckpt",),
    "stages/vc.yaml": ("encoder_ckpt",),
    "stages/vc_moco.yaml": ("encoder_ckpt",),
    "stages/self_labelling.yaml": ("encoder_ckpt", "detector_ckpt", "bank_ckpt"),
    "paper/detector.yaml": ("encoder_ckpt",),
    "paper/quantizer.yaml": ("encoder_ckpt",),
    "paper/mining.yaml": ("encoder_ckpt",),
    "paper/self_labelling.yaml": ("encoder_ckpt", "detector_ckpt", "bank_ckpt"),
}
TINY_GRID = "--model.init_args.grid_resolution=[32, 32, 16]"


def _load(config: str) -> dict:
    """The config as it runs: its bases' keys with its own on top."""
    return load_config(config)


def _data_args(data_dir: Path) -> list[str]:
    return [f"--data.init_args.data_dir={data_dir}", "--data.init_args.num_scenes=12",
            "--data.init_args.image_size=[32, 32]", "--data.init_args.num_views=4",
            "--data.init_args.generator_workers=1"]


def _run_args(config: str, data_dir: Path, root: Path, ckpts: dict[str, Path]) -> list[str]:
    """``fit`` of ``config`` as itself, on the tiny data, for one batch."""
    args = ["fit"]
    if config.startswith(("data/", "trainer/")):
        args += ["--config", "stages/viewpred.yaml"]
    args += ["--config", config, *_data_args(data_dir), "--trainer.fast_dev_run=true",
             "--trainer.enable_progress_bar=false", "--trainer.enable_model_summary=false",
             f"--trainer.default_root_dir={root}"]
    if config.startswith(("data/", "trainer/")) or config in OWN_GRID:
        args.append(TINY_GRID)
    for key in NEEDS.get(config, ()):
        args.append(f"--model.init_args.{key}={ckpts[key]}")
    if "encoder_ckpt" in NEEDS.get(config, ()):
        args.append(TINY_GRID)  # a bare encoder state dict carries no grid
    if config in ("stages/self_labelling.yaml", "paper/self_labelling.yaml"):
        args += ["--model.init_args.crop_size=8", "--model.init_args.num_angles=8"]  # the tiny bank's
    if config.startswith(("stages/mining", "paper/mining")):  # the tiny 32x32 views give no pseudo-boxes to fuse
        args.append("--model.init_args.pool_min_scene_iou=null")
    return args


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory: pytest.TempPathFactory, tiny_dataset: Path) -> dict[str, Path]:
    """An encoder, a detector and a prototype bank for the stages that read them, each by its packaged config."""
    from threedq.stages.base import EncoderStage

    root = tmp_path_factory.mktemp("configs")
    torch.manual_seed(0)
    enc = root / "encoder.pt"
    torch.save(EncoderStage(grid_resolution=(32, 32, 16)).encoder.state_dict(), enc)
    out = {"encoder_ckpt": enc}
    for key, config, extra in (
        ("detector_ckpt", "stages/detector.yaml", ["--data.init_args.boxes=gt"]),
        ("bank_ckpt", "stages/quantizer.yaml", ["--model.init_args.crop_size=8", "--model.init_args.num_angles=8",
                                                 "--model.init_args.num_prototypes=4"]),
    ):
        cli = ThreeDQCLI(args=[*_run_args(config, tiny_dataset, root / key, out)[1:], *extra], run=False)
        cli.trainer.fit(cli.model, datamodule=cli.datamodule)
        out[key] = root / f"{key}.ckpt"
        cli.trainer.save_checkpoint(out[key], weights_only=True)
    return out


@pytest.fixture(scope="module")
def data_copy(tmp_path_factory: pytest.TempPathFactory, tiny_dataset: Path) -> Path:
    """The tiny dataset without its proposal cache (the detector config's warm start computes it)."""
    out = tmp_path_factory.mktemp("configs_data") / "data"
    shutil.copytree(tiny_dataset, out, ignore=shutil.ignore_patterns("proposals"))
    return out


def _exit_code(argv: list[str]) -> int:
    """What ``threedq <argv>`` exits with (``--print_config`` exits 0 through SystemExit; errors return 2)."""
    try:
        return main(argv)
    except SystemExit as e:
        return int(e.code or 0)


def _check_parse(config: str, capsys: pytest.CaptureFixture[str]) -> dict:
    """``--print_config`` of the config as it is run above; returns the printed config."""
    args = ["fit"] + (["--config", "stages/viewpred.yaml"] if config.startswith(("data/", "trainer/")) else [])
    code = _exit_code([*args, "--config", config, "--print_config"])
    out = capsys.readouterr()
    assert code == 0, out.err
    return yaml.safe_load(out.out)


@pytest.mark.parametrize("config", CONFIGS)
def test_parses_as_itself(config: str, capsys: pytest.CaptureFixture[str]) -> None:
    """The printed config holds this file's class paths and values (not another config's)."""
    own, printed = _load(config), _check_parse(config, capsys)
    for section in ("model", "data"):
        if section in own:
            # a stage config's data block says how it loads data (no class_path: the default dataset's class)
            want = own[section].get("class_path") or default_data()["class_path"]
            assert printed[section]["class_path"] == want
            for key, value in (own[section].get("init_args") or {}).items():
                got = printed[section]["init_args"][key]
                assert got == value or (isinstance(value, list) and list(got) == value), (section, key)
    for key, value in (own.get("trainer") or {}).items():
        assert printed["trainer"][key] == value, ("trainer", key)


@pytest.mark.slow
@pytest.mark.parametrize("config", [c for c in CONFIGS if c not in PARSE_ONLY])
def test_runs_one_batch(config: str, tmp_path: Path, data_copy: Path, checkpoints: dict[str, Path]) -> None:
    """``threedq fit --config <config>`` trains and validates one batch on the tiny data (a data config that names
    other generator settings, e.g. the shape-only data's categories and colours, on 12 tiny scenes of its own, made
    on first use as the config makes them)."""
    generator = {"categories", "color_mode"} & set((_load(config).get("data") or {}).get("init_args") or {})
    data_dir = tmp_path / "own_data" if config.startswith("data/") and generator else data_copy
    args = _run_args(config, data_dir, tmp_path, checkpoints)
    fractions = ((_load(config).get("data") or {}).get("init_args") or {}).get("split_fractions")
    if data_dir != data_copy and fractions and not fractions[0]:  # a test-only set: trained on splits of its own kind
        args.append("--data.init_args.split_fractions=[0.5, 0.25, 0.25]")
    cli = ThreeDQCLI(args=args)
    assert cli.trainer.state.finished, config
    assert cli.trainer.global_step <= 1


class TestMutatedConfig:
    """The checks above fail on a config with one key misspelt, in the model, the data or the trainer."""

    @pytest.mark.parametrize("section, key", [("model", "rgb_weight"), ("data", "batch_size"), ("trainer", "max_steps")])
    def test_misspelt_key_fails(self, section: str, key: str, tmp_path: Path,
                                capsys: pytest.CaptureFixture[str]) -> None:
        cfg = _load("stages/viewpred.yaml")
        block = cfg[section]["init_args"] if section != "trainer" else cfg[section]
        block[key[:-1] + "x"] = block.pop(key)
        bad = tmp_path / "viewpred_mutated.yaml"
        bad.write_text(yaml.safe_dump(cfg))
        assert _exit_code(["fit", "--config", str(bad), "--print_config"]) != 0
        assert key[:-1] + "x" in capsys.readouterr().err

    def test_changed_value_is_seen(self, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                   monkeypatch: pytest.MonkeyPatch) -> None:
        """A value changed in the file reaches the parsed config, so ``test_parses_as_itself`` reads the file."""
        cfg = _load("stages/viewpred.yaml")
        cfg["model"]["init_args"]["rgb_weight"] = 7.5
        (tmp_path / "stages").mkdir()
        (tmp_path / "stages" / "viewpred.yaml").write_text(yaml.safe_dump(cfg))
        monkeypatch.chdir(tmp_path)  # a local file wins over the packaged one (resolve_config)
        assert _check_parse("stages/viewpred.yaml", capsys)["model"]["init_args"]["rgb_weight"] == 7.5


class TestDataComposition:
    """Stage configs say how a stage loads data, data configs which dataset (``configs/data/*.yaml``)."""

    def test_stage_configs_name_no_dataset(self) -> None:
        for config in CONFIGS:
            if config.startswith(("stages/", "paper/")):
                data = _load(config).get("data") or {}
                assert "class_path" not in data, config
                assert not {"data_dir", "num_scenes", "split_fractions"} & set(data.get("init_args") or {}), config

    def test_default_dataset_is_the_data_config(self, capsys: pytest.CaptureFixture[str]) -> None:
        printed = _check_parse("stages/detector.yaml", capsys)["data"]
        own = _load("data/clevr_veggie.yaml")["data"]
        assert printed["class_path"] == own["class_path"]
        assert printed["init_args"]["data_dir"] == own["init_args"]["data_dir"]
        assert printed["init_args"]["batch_size"] == 4 and printed["init_args"]["boxes"] == "proposals"

    @pytest.mark.parametrize("own_first", [False, True])
    def test_own_dataset_is_one_file(self, own_first: bool, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
        mine = tmp_path / "my_data.yaml"
        mine.write_text(yaml.safe_dump({"data": {"class_path": "threedq.datamodules.scene_folder.SceneFolderDataModule",
                                                 "init_args": {"data_dir": "data/my_scenes"}}}))
        stage = ["--config", "stages/detector.yaml"]
        order = [*(["--config", str(mine)]), *stage] if own_first else [*stage, "--config", str(mine)]
        assert _exit_code(["fit", *order, "--print_config"]) == 0
        printed = yaml.safe_load(capsys.readouterr().out)["data"]
        assert printed["class_path"].endswith("SceneFolderDataModule")
        args = printed["init_args"]
        assert args["data_dir"] == "data/my_scenes" and "num_scenes" not in args  # the embedded generator's are gone
        assert args["batch_size"] == 4 and args["boxes"] == "proposals" and args["train_random_views"] is False


class TestLinkedFromData:
    """``num_classes`` and ``symmetry_order`` come from the dataset's ``index.json`` (``link_arguments``), to the
    stages that take them; the others are built as before."""

    @pytest.mark.parametrize("config, linked", [("stages/quantizer.yaml", ("num_classes", "symmetry_order")),
                                                ("stages/mining.yaml", ("symmetry_order",)),
                                                ("stages/detector.yaml", ())])
    def test_stage_gets_the_dataset_values(self, config: str, linked: tuple[str, ...], tmp_path: Path,
                                           tiny_dataset: Path, checkpoints: dict[str, Path]) -> None:
        from threedq.scene import load_index
        from threedq.stages.base import stage_arguments

        index = load_index(tiny_dataset)
        cli = ThreeDQCLI(args=_run_args(config, tiny_dataset, tmp_path, checkpoints)[1:], run=False)
        want = {"num_classes": len(index.categories), "symmetry_order": list(index.symmetry_order)}
        for key in linked:
            assert cli.model.hparams[key] == want[key], key
        assert not {"num_classes", "symmetry_order"} - set(linked) & set(stage_arguments(type(cli.model)))

    def test_checkpoint_rebuilds_through_lightning(self, checkpoints: dict[str, Path]) -> None:
        """A checkpoint names only its stage's arguments (not the linked values of another stage), so Lightning's
        ``load_from_checkpoint`` rebuilds the stage, with the detector's anchor from its buffer."""
        from threedq.stages.base import stage_arguments
        from threedq.stages.checkpoint import checkpoint_hparams, load_checkpoint
        from threedq.stages.detector import Detector

        path = checkpoints["detector_ckpt"]
        hp = checkpoint_hparams(path)
        assert {k for k in hp if not k.startswith("_")} <= set(stage_arguments(Detector))
        det = Detector.load_from_checkpoint(path, weights_only=True)
        assert det.anchor_size == load_checkpoint(path).anchor and det.anchor_size is not None

    def test_a_datamodule_of_ones_own_says_them_by_attribute(self) -> None:
        """Read from the DataModule's attributes; its data is made first (``prepare_data``) only when they cannot be
        read yet (no index.json), so building a run does not re-check data that exists."""
        import lightning as L

        from threedq.errors import InputError
        from threedq.pipeline.lightning_cli import dataset_num_classes, dataset_symmetry_order

        class Mine(L.LightningDataModule):
            def __init__(self, made: bool) -> None:
                super().__init__()
                self.made, self.prepared = made, 0

            def prepare_data(self) -> None:
                self.made, self.prepared = True, self.prepared + 1

            @property
            def num_classes(self) -> int:
                if not self.made:
                    raise InputError("index.json: field '<file>': no such file")
                return 3

        fresh, made = Mine(made=False), Mine(made=True)
        assert dataset_num_classes(fresh) == 3 and fresh.prepared == 1
        assert dataset_num_classes(made) == 3 and made.prepared == 0
        assert dataset_symmetry_order(made) is None and dataset_num_classes(L.LightningDataModule()) is None

    def test_a_config_cannot_set_them(self, capsys: pytest.CaptureFixture[str]) -> None:
        assert _exit_code(["fit", "--config", "stages/quantizer.yaml", "--model.init_args.num_classes=3",
                           "--print_config"]) != 0
        assert "num_classes" in capsys.readouterr().err
