"""The package as a user installs it: a wheel, not the editable checkout.

``pip install -e .`` serves every module from the checkout, so a package that ``pyproject.toml``/``setup.py`` leaves
out of the wheel goes unnoticed until someone runs ``pip install .`` or the Docker image. Here the wheel is built
from a copy of the tree's package folders, its file list is compared with the tree (every ``.py`` of ``threedq/``,
``stages/``, ``datamodules/`` and every YAML of ``configs/``, at the path the package layout maps it to), and it is
installed into a fresh virtual environment where the ``threedq`` command runs from a folder away from the checkout.

The fresh environment installs the wheel with ``--no-deps`` and sees this interpreter's site-packages through a
plain path line (a ``.pth`` file whose line is a folder), so the dependencies (torch, Lightning, ...) are not
installed a second time and none of that folder's own ``.pth`` files runs: the editable install's import hook stays
out, and ``threedq`` can only come from the wheel (checked through ``threedq.__file__``).
"""

from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
import sysconfig
import zipfile
from importlib import metadata
from pathlib import Path

import pytest

from conftest import tiny_data_yaml

ROOT = Path(__file__).resolve().parents[1]
pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not (ROOT / "setup.py").is_file(),
                                 reason="builds the wheel from the source tree, which this install does not hold")]
# top-level folder of the repository -> where its files land inside the wheel
LAYOUT = {"threedq": "threedq", "stages": "threedq/stages", "datamodules": "threedq/datamodules",
          "configs": "threedq/configs"}
BUILD_FILES = ("pyproject.toml", "setup.py", "README.md")


def tree_files(root: Path = ROOT) -> set[str]:
    """Every file the wheel must hold, at its path inside the wheel: ``.py`` of the code folders, ``.yaml`` of
    ``configs/``."""
    out: set[str] = set()
    for folder, target in LAYOUT.items():
        pattern = "*.yaml" if folder == "configs" else "*.py"
        for p in (root / folder).rglob(pattern):
            if "__pycache__" not in p.parts:
                out.add(f"{target}/{p.relative_to(root / folder).as_posix()}")
    return out


def _setuptools_can_build_here() -> bool:
    try:
        major, minor = (int(x) for x in metadata.version("setuptools").split(".")[:2])
    except metadata.PackageNotFoundError:
        return False
    return (major, minor) >= (70, 1)  # bdist_wheel inside setuptools: no `wheel` package needed


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The wheel built from a copy of the files a source distribution of threedq holds."""
    src = tmp_path_factory.mktemp("wheel_src")
    for name in BUILD_FILES:
        shutil.copy2(ROOT / name, src / name)
    for folder in LAYOUT:
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    dist = tmp_path_factory.mktemp("dist")
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist), str(src)]
    if _setuptools_can_build_here():
        cmd.insert(4, "--no-build-isolation")  # no download of the build backend when this one will do
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    wheels = sorted(dist.glob("threedq-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


@pytest.fixture(scope="module")
def venv(wheel: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh virtual environment holding the wheel (its ``bin`` folder is returned)."""
    env_dir = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env_dir)], check=True)
    py = env_dir / "bin" / "python"
    purelib = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  capture_output=True, text=True, check=True).stdout.strip())
    # this interpreter's site-packages as plain path lines: the dependencies, without running their .pth files
    host = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"], *site.getsitepackages()}
    (purelib / "zz_host_dependencies.pth").write_text("\n".join(sorted(host)) + "\n")
    done = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index", "-q",
                           str(wheel)], capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    return env_dir / "bin"


def _run(argv: list[str], cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


class TestWheel:
    def test_tree_files_sees_every_package(self) -> None:
        files = tree_files()
        for must in ("threedq/__init__.py", "threedq/viz/__init__.py", "threedq/stages/viewpred.py",
                     "threedq/datamodules/__init__.py", "threedq/configs/stages/viewpred.yaml"):
            assert must in files

    def test_every_module_and_config_is_in_the_wheel(self, wheel: Path) -> None:
        names = set(zipfile.ZipFile(wheel).namelist())
        missing = sorted(tree_files() - names)
        assert not missing, f"left out of {wheel.name}: {missing}"

    def test_nothing_at_the_top_level_but_threedq(self, wheel: Path) -> None:
        tops = {n.split("/")[0] for n in zipfile.ZipFile(wheel).namelist()}
        assert {t for t in tops if not t.endswith(".dist-info")} == {"threedq"}

    def test_a_new_package_is_found_without_listing_it(self, tmp_path: Path) -> None:
        """The discovery itself (``setup.py``'s, what the wheel above was built with): a sub-package added to a copy
        of the tree, under ``threedq/`` and under ``stages/``, is found though no file names it, at its installed
        name."""
        import importlib.util

        spec = importlib.util.spec_from_file_location("threedq_setup", ROOT / "setup.py")
        setup_py = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(setup_py)  # defines discover(); setup() runs only as __main__
        src = tmp_path / "src"
        for folder in LAYOUT:
            shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        before, package_dir = setup_py.discover(str(src))
        assert {"threedq.viz", "threedq.stages", "threedq.datamodules", "threedq.configs.stages"} <= set(before)
        assert package_dir == {"threedq.stages": "stages", "threedq.datamodules": "datamodules",
                               "threedq.configs": "configs"}
        for pkg in (src / "threedq" / "brand_new", src / "stages" / "brand_new_stage"):
            pkg.mkdir()
            (pkg / "__init__.py").write_text("VALUE = 1\n")
        after, _ = setup_py.discover(str(src))
        assert set(after) - set(before) == {"threedq.brand_new", "threedq.stages.brand_new_stage"}


class TestInstalledWheel:
    def test_imports_from_the_wheel_not_the_checkout(self, venv: Path, tmp_path: Path) -> None:
        done = _run([str(venv / "python"), "-c", "import threedq, threedq.viz, threedq.stages.viewpred, "
                     "threedq.datamodules; print(threedq.__file__)"], cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        where = Path(done.stdout.strip()).resolve()
        assert venv.parent.resolve() in where.parents and ROOT not in where.parents, where

    def test_help(self, venv: Path, tmp_path: Path) -> None:
        for argv in (["--help"], ["fit", "--help"]):
            done = _run([str(venv / "threedq"), *argv], cwd=tmp_path)
            assert done.returncode == 0, f"threedq {' '.join(argv)}:\n{done.stderr[-3000:]}"
            assert "usage" in done.stdout.lower()

    def test_two_step_fit_on_the_tiny_data(self, venv: Path, tmp_path: Path, tiny_dataset: Path) -> None:
        """``threedq fit`` with the packaged view-prediction config (found from a folder that has no ``configs/``)
        trains 2 steps and writes its checkpoint."""
        cfg = tmp_path / "tiny.yaml"
        cfg.write_text("model:\n  init_args:\n    grid_resolution: [32, 32, 16]\n" + tiny_data_yaml(tiny_dataset) + "\n")
        done = _run([str(venv / "threedq"), "fit", "--config", "stages/viewpred.yaml", "--config", str(cfg),
                     "--trainer.max_steps=2", "--trainer.limit_val_batches=1", "--trainer.logger=false",
                     "--trainer.enable_progress_bar=false", f"--trainer.default_root_dir={tmp_path / 'run'}"],
                    cwd=tmp_path)
        assert done.returncode == 0, done.stderr[-4000:]
        ckpts = list((tmp_path / "run").rglob("*.ckpt"))
        assert ckpts, f"no checkpoint under {tmp_path / 'run'}:\n{done.stderr[-2000:]}"
