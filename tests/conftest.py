"""Shared fixtures: a tiny dataset made by the real generator once per test session."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest
import torch

torch.set_num_threads(min(2, torch.get_num_threads()))

TINY = {"image_size": (32, 32), "num_views": 4, "max_objects": 3}


def tiny_data_yaml(data_dir: Path, **extra: object) -> str:
    """The ``data:`` block of a stage config on the tiny dataset (YAML text, top level), with ``extra`` init_args."""
    h, w = TINY["image_size"]
    lines = ["data:", "  init_args:", f"    data_dir: {data_dir}", "    num_scenes: 12", f"    image_size: [{h}, {w}]",
             f"    num_views: {TINY['num_views']}", "    generator_workers: 1", *(f"    {k}: {v}" for k, v in extra.items())]
    return "\n".join(lines)


def tiny_quantizer_config(folder: Path) -> Path:
    """``stages/quantizer.yaml`` with a coarser rotation search (12 yaws, not 36) and 3 EM iterations (not 10), written
    to ``folder``: what ``threedq em``'s tests check is the loop (stages, resume, files), and on the tiny dataset the
    packaged search was a third of a loop's time. The packaged config itself runs in ``tests/test_configs.py``."""
    import yaml

    from threedq.pipeline.lightning_cli import resolve_config

    config = yaml.safe_load(resolve_config("stages/quantizer.yaml").read_text())
    config["model"]["init_args"].update(num_angles=12, em_iterations=3)
    path = folder / "tiny_quantizer.yaml"
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def tiny_mining_config(folder: Path) -> Path:
    """``stages/mining.yaml`` without the scene's check of the pool (``pool_min_scene_iou: null``), written to
    ``folder``: the tiny scenes' 32x32 views give no pseudo-boxes to fuse, so the check would leave the pool empty
    (the check has its own tests in ``tests/test_mining_stage.py``)."""
    import yaml

    from threedq.pipeline.lightning_cli import resolve_config

    config = yaml.safe_load(resolve_config("stages/mining.yaml").read_text())
    config["model"]["init_args"]["pool_min_scene_iou"] = None
    path = folder / "tiny_mining.yaml"
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def load_benchmark(name: str) -> ModuleType:
    """``benchmarks/<name>.py`` imported as a module (the scripts are not a package; their folder on ``sys.path``, as
    when a script runs, for their shared helpers)."""
    path = Path(__file__).resolve().parent.parent / "benchmarks" / f"{name}.py"
    if str(path.parent) not in sys.path:
        sys.path.insert(0, str(path.parent))
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """12 scenes (train 8 / val 2 / test 2) of 4 views at 32x32, generated in-process."""
    from threedq.data.generate import generate_dataset
    from threedq.data.generator_config import GeneratorConfig

    out = tmp_path_factory.mktemp("tiny_dataset")
    generate_dataset(out, num_scenes=12, seed=5, config=GeneratorConfig(**TINY), split_fractions=(0.7, 0.15, 0.15),
                     workers=1, progress=False)
    return out


@pytest.fixture(scope="session")
def turntable():
    """A generated scene seen from a turntable (2 cameras x 3 yaws, 36x48): every capture format's test scene."""
    from capture_writers import turntable_scene

    return turntable_scene((36, 48))


def refused(cls: type, **init_args: object) -> str:
    """The one-line error the CLI's parser gives for the arguments ``init_args`` of the stage or DataModule ``cls``:
    the annotations (jsonargparse's restricted types, ``Literal``) validate each argument's range."""
    from jsonargparse import ArgumentError, ArgumentParser

    parser = ArgumentParser(exit_on_error=False)
    parser.add_class_arguments(cls, "model")
    with pytest.raises(ArgumentError) as e:
        parser.parse_object({"model": init_args})
    return str(e.value)
