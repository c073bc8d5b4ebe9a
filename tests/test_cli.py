"""The threedq command: subcommands, packaged configs, data generate / check / show."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from threedq.cli import main
from threedq.pipeline.lightning_cli import packaged_configs_dir, resolve_config


def test_help_lists_subcommands(capsys: pytest.CaptureFixture[str]) -> None:
    """In this process (``tests/test_packaging.py`` runs the installed command's ``--help``)."""
    with pytest.raises(SystemExit) as done:
        main(["--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    for sub in ("fit", "validate", "test", "predict", "data", "em"):
        assert sub in out
    for sub in ("eval", "parse", "label"):
        assert sub in out


@pytest.mark.parametrize("user_setting", [None, "2"])
def test_one_blas_thread(user_setting: str | None) -> None:
    """The command runs numpy's BLAS on one thread (already loaded or loaded later), unless the user set
    ``OPENBLAS_NUM_THREADS``; torch's threads are untouched. A fresh interpreter whose BLAS starts with 2 threads."""
    import os

    code = ("import numpy, torch; from threadpoolctl import threadpool_info, threadpool_limits; "
            "threadpool_limits(limits=2, user_api='blas'); torch.set_num_threads(2); "
            "from threedq.cli import one_blas_thread; one_blas_thread(); import scipy.linalg; "
            "print(sorted({i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'}), "
            "torch.get_num_threads())")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if user_setting is not None:
        env["OPENBLAS_NUM_THREADS"] = user_setting
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout
    assert out.split() == (["[1]", "2"] if user_setting is None else ["[2]", "2"])


class TestEndProcessGroup:
    def test_destroys_the_group_a_run_formed(self, tmp_path: Path) -> None:
        """A one-process gloo group, formed as Lightning forms it, is gone after the call; a second call is a no-op."""
        import torch.distributed as dist

        from threedq.cli import end_process_group

        dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'store'}", rank=0, world_size=1)
        try:
            assert dist.is_initialized()
            end_process_group()
            assert not dist.is_initialized()
            end_process_group()
        finally:
            if dist.is_initialized():
                dist.destroy_process_group()

    def test_main_ends_it_on_an_error_too(self, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
        """``main`` ends the group when the command stops on a bad input (one line, exit 2), not only on success."""
        import torch.distributed as dist

        from threedq.cli import main

        dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'store'}", rank=0, world_size=1)
        try:
            assert main(["data", "check", str(tmp_path / "missing")]) == 2
            assert "threedq: error:" in capsys.readouterr().err
            assert not dist.is_initialized()
        finally:
            if dist.is_initialized():
                dist.destroy_process_group()


def test_a_subcommand_imports_its_own_modules_only() -> None:
    """``threedq data ...`` parses without importing Lightning (a fresh interpreter: this one has imported it)."""
    code = ("import sys; from threedq.cli import build_parser; p = build_parser('data'); "
            "p.parse_args(['data', 'check', 'x']); "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'lightning', 'torchmetrics'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
    code = "import sys; from threedq.cli import build_parser; build_parser('em'); print('lightning' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "True"
    # the top-level help lists every subcommand without importing one
    code = ("import sys, contextlib, io; from threedq.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit): main(['--help'])\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('lightning', 'torch', 'threedq')\n"
            "             and not m.startswith(('threedq.cli', 'threedq.errors')) and m != 'threedq'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


class TestResolveConfig:
    def test_packaged_from_any_directory(self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        monkeypatch.chdir(tmp_path)
        p = resolve_config("stages/viewpred.yaml")
        assert p == packaged_configs_dir() / "stages" / "viewpred.yaml" and p.is_file()

    def test_local_file_wins(self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        monkeypatch.chdir(tmp_path)
        (tmp_path / "stages").mkdir()
        (tmp_path / "stages" / "viewpred.yaml").write_text("seed_everything: 3\n")
        assert resolve_config("stages/viewpred.yaml") == Path("stages/viewpred.yaml")

    def test_missing(self) -> None:
        with pytest.raises(FileNotFoundError, match="nope.yaml.*tried"):
            resolve_config("stages/nope.yaml")

    def test_fit_print_config_from_elsewhere(self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
        monkeypatch.chdir(tmp_path)
        with pytest.raises(SystemExit) as e:
            main(["fit", "--config", "stages/viewpred.yaml", "--print_config"])
        assert e.value.code == 0
        out = capsys.readouterr().out
        assert "threedq.stages.viewpred.ViewPrediction" in out and "ClevrVeggieDataModule" in out


class TestDataCommands:
    def test_generate_check_show(self, tmp_path: Path, capsys) -> None:
        d = tmp_path / "d"
        args = ["data", "generate", "--out", str(d), "--scenes", "3", "--seed", "1", "--image_size", "[32, 32]",
                "--views", "3", "--workers", "1", "--progress", "false"]
        assert main(args) == 0
        assert "wrote 3 scenes" in capsys.readouterr().out
        assert main(["data", "check", str(d)]) == 0
        assert "3/3 scenes valid" in capsys.readouterr().out
        png = tmp_path / "sheet.png"
        assert main(["data", "show", str(d), "--out", str(png), "--scenes", "2"]) == 0
        img = cv2.imread(str(png))
        assert img is not None and img.std() > 5
        # a corrupted scene is reported on one line naming the file and the field
        victim = sorted(d.rglob("*.npz"))[0]
        victim.write_bytes(victim.read_bytes()[:300])
        assert main(["data", "check", str(d)]) == 1
        out = capsys.readouterr().out.splitlines()
        bad = [line for line in out if str(victim) in line]
        assert len(bad) == 1 and "field '" in bad[0]
        assert "2/3 scenes valid" in out[-1]

    def test_generate_scene_knobs(self, tmp_path: Path, capsys) -> None:
        """The generator's scene knobs reach the scenes: smaller objects, closer cameras, a category subset."""
        from threedq.scene import load_index, load_scene

        d = tmp_path / "shifted"
        args = ["data", "generate", "--out", str(d), "--scenes", "3", "--image_size", "[32, 32]", "--views", "3",
                "--workers", "1", "--progress", "false", "--object_size", "0.2", "--scale_range", "[1.0, 1.0]",
                "--distance_range", "[1.5, 1.6]", "--fov_deg", "70", "--elevation_range_deg", "[30, 40]",
                "--categories", "[banana, mug]"]
        assert main(args) == 0
        index = load_index(d)
        cfg = index.generator["config"]
        assert (cfg["object_size"], cfg["distance_range"], cfg["fov_deg"]) == (0.2, [1.5, 1.6], 70.0)
        assert list(index.categories) == ["banana", "mug"]
        for f in index.files("train") + index.files("test"):
            rec = load_scene(d / f)
            assert float(rec.boxes[:, 3:6].max()) <= 0.2 + 1e-4  # largest extent = object_size at scale 1
            # cameras look at (0, 0, 0.2) +- (0.1, 0.1, 0.05) from 1.5-1.6 m
            dist = np.linalg.norm(rec.world_T_cam[:, :3, 3] - np.array([0.0, 0.0, 0.2]), axis=1)
            assert dist.min() > 1.5 - 0.16 and dist.max() < 1.6 + 0.16
            assert np.allclose(rec.K[:, 0, 0], 16 / np.tan(np.radians(35)), rtol=1e-3)  # 70 deg FOV at 32 px
        assert main([*args[:3], str(tmp_path / "bad"), *args[4:], "--fov_deg", "200"]) == 2
        assert "--fov_deg" in capsys.readouterr().err

    def test_bad_dataset_folder(self, tmp_path: Path, capsys) -> None:
        assert main(["data", "check", str(tmp_path)]) == 2
        assert "index.json" in capsys.readouterr().err


class TestOldClassPaths:
    """Configs and command lines naming the pre-0.2 top-level packages get one line naming the new path."""

    def test_config_file(self, tmp_path: Path, capsys) -> None:
        cfg = tmp_path / "old.yaml"
        cfg.write_text("model:\n  class_path: stages.viewpred.ViewPrediction  # saved by threedq 0.1\n")
        assert main(["fit", "--config", str(cfg)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1
        assert str(cfg) in err and "'stages.viewpred.ViewPrediction'" in err
        assert "threedq.stages.viewpred.ViewPrediction" in err

    @pytest.mark.parametrize(
        "args",
        [
            ["--model=datamodules.clevr_veggie.ClevrVeggieDataModule"],
            ["--data.class_path", "datamodules.scene_folder.SceneFolderDataModule"],
        ],
    )
    def test_command_line(self, args: list[str], capsys) -> None:
        assert main(["fit", "--config", "stages/viewpred.yaml", *args]) == 2
        err = capsys.readouterr().err
        assert "field 'class_path'" in err and "use 'threedq.datamodules." in err

    @pytest.mark.parametrize("old, new", [("tum_rgbd.TumRGBDDataModule", "tum.TumRGBDDataModule"),
                                          ("kinect_open3d.KinectOpen3dDataModule", "open3d.KinectOpen3dDataModule"),
                                          ("camera_rig.CameraRigDataModule", "rig.CameraRigDataModule")])
    def test_renamed_data_modules(self, old: str, new: str, tmp_path: Path, capsys) -> None:
        cfg = tmp_path / "capture.yaml"
        cfg.write_text(f"data:\n  class_path: threedq.datamodules.{old}\n")
        assert main(["fit", "--config", "stages/viewpred.yaml", "--config", str(cfg)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"was renamed; use 'threedq.datamodules.{new}'" in err

    def test_new_paths_and_other_values_pass(self) -> None:
        from threedq.pipeline.lightning_cli import check_class_paths, resolve_config_args

        check_class_paths("model:\n  class_path: threedq.stages.viewpred.ViewPrediction\n", "x.yaml")
        out = resolve_config_args(["--data.init_args.data_dir=stages.d", "--trainer.default_root_dir", "stages.x"])
        assert out[0] == "--data.init_args.data_dir=stages.d"

    def test_packaged_configs_use_new_paths(self) -> None:
        for f in packaged_configs_dir().rglob("*.yaml"):
            assert "class_path: stages." not in f.read_text() and "class_path: datamodules." not in f.read_text(), f


class TestSubcommandParsers:
    """``ThreeDQCLI`` builds the parser of the Lightning subcommand its command line names, not all four."""

    def test_the_named_one_or_all(self) -> None:
        from types import SimpleNamespace

        from lightning.pytorch.cli import LightningCLI

        from threedq.pipeline.lightning_cli import ThreeDQCLI

        every = LightningCLI.subcommands()
        for name in ("fit", "validate", "test", "predict"):
            assert ThreeDQCLI.subcommands(SimpleNamespace(_args=[name, "--config", "x.yaml"])) == {name: every[name]}
        for args in ([], ["--config", "x.yaml", "fit"], ["--help"]):  # no subcommand first: every parser, as Lightning
            assert ThreeDQCLI.subcommands(SimpleNamespace(_args=args)) == every

    @pytest.mark.parametrize("sub", ["fit", "test"])
    def test_help_of_a_subcommand(self, sub: str, capsys: pytest.CaptureFixture[str]) -> None:
        with pytest.raises(SystemExit) as e:
            main([sub, "--config", "stages/viewpred.yaml", "--help"])
        assert e.value.code == 0
        out = capsys.readouterr().out
        assert ("Runs the full optimization routine" if sub == "fit" else "Perform one evaluation epoch") in out
        assert "--ckpt_path" in out and "--trainer.max_steps" in out
