"""Bad inputs through the real ``threedq`` command (issue #17, item 1): one table of cases, each a subprocess.

Every case builds its bad input in its own folder, runs ``python -m threedq ...`` and expects:

* a non-zero exit status and no Python traceback;
* exactly ONE error line, naming the file (or the option) and the field. The error line is the line of stderr
  that starts with ``threedq: error:`` (and it is stderr's last line: no usage, no nested details after it), or,
  for the two commands whose job is to report bad files (``threedq data check``, ``threedq data import``), the
  one line of their report that names a ``field '...'``. No parse error prints the usage: every error is one line;
* no file that existed before the run changed (path -> mtime_ns, size, sha1 of its content), neither in the
  case's folder nor in the inputs shared by all cases (dataset, checkpoints).

A full disk and a folder without write permission are simulated in the subprocess by ``tests/fault_shim`` (a
``sitecustomize`` on ``PYTHONPATH``, see its docstring); without root, the permission case uses a real
read-only folder instead.

The commands of the selected cases run two at a time, each a process of its own forked from one that has imported
threedq once (``tests/forkserver.py``: a new ``python -m threedq`` spends 5-9 s importing torch and Lightning before it
reads its arguments); a case's test then checks its own outcome. A few cases (:data:`REAL_TOO`) also run as a new
``python -m threedq`` subprocess, and the two outcomes must agree. A few cases whose code path another case already
takes run in this process through ``threedq.cli.main`` instead (:data:`IN_PROCESS`), with the same checks.
"""

from __future__ import annotations

import concurrent.futures
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from forkserver import ForkServer

pytestmark = pytest.mark.slow

TESTS = Path(__file__).resolve().parent
SHIM = TESTS / "fault_shim"
PARALLEL = 2
TIMEOUT_S = 240


# ---------------------------------------------------------------------------------------------------------------
# Shared inputs (read by many cases, never written)
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class Shared:
    root: Path
    data: Path  # the tiny dataset (12 scenes: train 8 / val 2 / test 2)
    config: Path  # its stage config: grid 32 x 32 x 16, 4 views of 32 x 32
    viewpred_ckpt: Path
    quantizer_ckpt: Path
    turntable: object  # SceneRecord of tests/capture_writers.py


def _tiny_config(path: Path, data_dir: Path) -> Path:
    path.write_text(
        yaml.safe_dump(
            {
                "model": {"init_args": {"grid_resolution": [32, 32, 16]}},
                "data": {"init_args": {"data_dir": str(data_dir), "num_scenes": 12, "image_size": [32, 32],
                                       "num_views": 4, "generator_workers": 1}},
                "trainer": {"max_steps": 1, "log_every_n_steps": 1, "limit_val_batches": 1,
                            "enable_progress_bar": False, "enable_model_summary": False},
            }
        )
    )
    return path


@pytest.fixture(scope="module")
def shared(tmp_path_factory: pytest.TempPathFactory, tiny_dataset: Path, turntable) -> Shared:
    """The tiny dataset, its config and two real checkpoints (view prediction, quantizer) made in this process."""
    from threedq.pipeline.lightning_cli import ThreeDQCLI, resolve_config

    root = tmp_path_factory.mktemp("bad_inputs_shared")
    data = root / "data"
    shutil.copytree(tiny_dataset, data, ignore=shutil.ignore_patterns("proposals"))
    config = _tiny_config(root / "tiny.yaml", data)
    runs = root / "runs"
    common = ["--config", str(config), "--trainer.logger=false", "--trainer.enable_checkpointing=false"]
    cli = ThreeDQCLI(args=["--config", str(resolve_config("stages/viewpred.yaml")), *common,
                           f"--trainer.default_root_dir={runs / 'vp'}"], run=False)
    cli.trainer.fit(cli.model, datamodule=cli.datamodule)
    vp = root / "viewpred.ckpt"
    cli.trainer.save_checkpoint(vp, weights_only=True)
    cli = ThreeDQCLI(args=["--config", str(resolve_config("stages/quantizer.yaml")), *common,
                           f"--model.init_args.encoder_ckpt={vp}", "--trainer.max_steps=-1", "--trainer.max_epochs=1",
                           f"--trainer.default_root_dir={runs / 'q'}"], run=False)
    cli.trainer.fit(cli.model, datamodule=cli.datamodule)
    q = root / "quantizer.ckpt"
    cli.trainer.save_checkpoint(q, weights_only=True)
    shutil.rmtree(runs)
    return Shared(root, data, config, vp, q, turntable)


def snapshot(folder: Path) -> dict[str, tuple[int, int, str]]:
    """path -> (mtime_ns, size, sha1 of the content) of every file under ``folder``."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file() and not p.is_symlink():
            st = p.stat()
            out[str(p)] = (st.st_mtime_ns, st.st_size, hashlib.sha1(p.read_bytes()).hexdigest())
    return out


# ---------------------------------------------------------------------------------------------------------------
# The table
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class Ctx:
    """What a case's builder gets: its own folder and the shared inputs."""

    dir: Path
    shared: Shared

    def dataset(self) -> Path:
        """A private copy of the tiny dataset."""
        d = self.dir / "data"
        if not d.exists():
            shutil.copytree(self.shared.data, d)
        return d

    def file(self, name: str, text: str | bytes) -> Path:
        p = self.dir / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(text.encode() if isinstance(text, str) else text)
        return p


@dataclass
class Run:
    argv: list[str]  # after "threedq"
    expect: list[str]  # substrings of the one error line
    after: Callable[[], None] | None = None  # more checks once the command has run
    fault: str | None = None  # THREEDQ_FAULT for tests/fault_shim ("ENOSPC:<folder>")


@dataclass
class Case:
    name: str
    build: Callable[[Ctx], Run]  # makes the bad input in the case's folder; returns the command and expectations


SCENE = "train/scene_000001.npz"


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An .npz archive of ``arrays`` as given: unvalidated, object arrays pickled (numpy.savez)."""
    import io

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _scene_case(mutate: Callable[[dict[str, np.ndarray]], None], field_name: str, *more: str) -> Callable[[Ctx], Run]:
    """``threedq data check`` of a dataset copy with one scene's arrays changed by ``mutate`` (written unvalidated)."""

    def build(ctx: Ctx) -> Run:
        d = ctx.dataset()
        path = d / SCENE
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        mutate(arrays)
        path.write_bytes(npz_bytes(arrays))
        return Run(["data", "check", str(d)], [str(path), f"field '{field_name}'", *more])

    return build


def _scene_bytes_case(make: Callable[[bytes], bytes], *expect: str) -> Callable[[Ctx], Run]:
    def build(ctx: Ctx) -> Run:
        d = ctx.dataset()
        path = d / SCENE
        path.write_bytes(make(path.read_bytes()))
        return Run(["data", "check", str(d)], [str(path), *expect])

    return build


def _set(key: str, fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[dict[str, np.ndarray]], None]:
    def mutate(a: dict[str, np.ndarray]) -> None:
        a[key] = fn(a[key].copy())

    return mutate


def _put(arr: np.ndarray, index: tuple, value: float) -> np.ndarray:
    arr[index] = value
    return arr


def _drop(key: str) -> Callable[[dict[str, np.ndarray]], None]:
    return lambda a: a.pop(key)


def _empty_scene(a: dict[str, np.ndarray]) -> None:
    a["boxes"], a["categories"] = np.zeros((0, 7), np.float32), np.zeros((0,), np.int64)
    a.pop("instance", None)


def _index_case(change: Callable[[Path], None], *expect: str) -> Callable[[Ctx], Run]:
    def build(ctx: Ctx) -> Run:
        d = ctx.dataset()
        change(d)
        return Run(["data", "check", str(d)], [*(e.format(d=d) for e in expect)])

    return build


def _edit_index(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    def change(d: Path) -> None:
        idx = json.loads((d / "index.json").read_text())
        fn(idx)
        (d / "index.json").write_text(json.dumps(idx))

    return change


def _unknown_split(idx: dict) -> None:
    idx["scenes"][3]["split"] = "holdout"


def _missing_scene(idx: dict) -> None:
    idx["scenes"].append({"file": "train/scene_000099.npz", "split": "train"})


def _config_case(text: str, *expect: str, stage: str = "stages/viewpred.yaml") -> Callable[[Ctx], Run]:
    """``threedq fit`` of a stage config composed with a bad one (``{cfg}`` in ``expect``: the bad file)."""

    def build(ctx: Ctx) -> Run:
        cfg = ctx.file("bad.yaml", text)
        argv = ["fit", "--config", stage, "--config", str(ctx.shared.config), "--config", str(cfg),
                f"--trainer.default_root_dir={ctx.dir / 'run'}"]
        return Run(argv, [e.format(cfg=cfg) for e in expect])

    return build


def _eval_case(make_ckpt: Callable[[Ctx], Path], *expect: str) -> Callable[[Ctx], Run]:
    """``threedq eval`` of a bad checkpoint (``{ckpt}`` in ``expect``: its path)."""

    def build(ctx: Ctx) -> Run:
        ckpt = make_ckpt(ctx)
        argv = ["eval", "--ckpt", str(ckpt), "--extra_configs", str(ctx.shared.config), "--out", str(ctx.dir / "out"),
                "--curve_k", "[]"]
        return Run(argv, [e.format(ckpt=ckpt) for e in expect])

    return build


def _truncated_ckpt(ctx: Ctx) -> Path:
    return ctx.file("truncated.ckpt", ctx.shared.quantizer_ckpt.read_bytes()[:100_000])


def _other_grid_ckpt(ctx: Ctx) -> Path:
    obj = torch.load(ctx.shared.quantizer_ckpt, map_location="cpu", weights_only=True)
    obj["hyper_parameters"]["grid_resolution"] = [16, 16, 8]
    p = ctx.dir / "other_grid.ckpt"
    torch.save(obj, p)
    return p


def _unsafe_ckpt(ctx: Ctx) -> Path:
    import argparse

    p = ctx.dir / "unsafe.ckpt"
    torch.save({"state_dict": {}, "hyper_parameters": {"args": argparse.Namespace(lr=0.1)}}, p)
    return p


def _list_ckpt(ctx: Ctx) -> Path:
    p = ctx.dir / "list.ckpt"
    torch.save([torch.zeros(3)], p)
    return p


def _em(ctx: Ctx, *more: str) -> list[str]:
    return ["em", "--work_dir", str(ctx.dir / "em"), "--extra_configs", str(ctx.shared.config), *more]


def _generate(out: Path, *more: str) -> list[str]:
    return ["data", "generate", "--out", str(out), "--scenes", "2", "--image_size", "[32, 32]", "--views", "2",
            "--workers", "1", "--progress", "false", *more]


def _out_is_file(argv: Callable[[Ctx, Path], list[str]], option: str) -> Callable[[Ctx], Run]:
    def build(ctx: Ctx) -> Run:
        f = ctx.file("a_file", "I am a file\n")
        return Run(argv(ctx, f), [option, str(f), "not a folder"])

    return build


def _no_write_permission(ctx: Ctx) -> Run:
    ro = ctx.dir / "read_only"
    ro.mkdir()
    if os.geteuid() == 0:  # root writes through chmod: simulate the refusal in the subprocess
        return Run(_generate(ro / "d"), [str(ro / "d"), "permission denied"], fault=f"EACCES:{ro}")
    ro.chmod(0o555)
    return Run(_generate(ro / "d"), [str(ro / "d"), "permission denied"])


def _disk_full_generate(ctx: Ctx) -> Run:
    out = ctx.dir / "d"

    def nothing_partial() -> None:  # the folders may exist; no file, whole or partial, nor a temporary one
        assert [p for p in out.rglob("*") if not p.is_dir()] == []

    return Run(_generate(out), [str(out / "train" / "scene_000000.npz"), "no space left on device"],
               after=nothing_partial, fault=f"ENOSPC:{ctx.dir}")


def _disk_full_index(ctx: Ctx) -> Run:
    d = ctx.dataset()

    def no_temporary() -> None:  # index.json itself is covered by the snapshot
        assert not list(d.glob(".index.json.*")), list(d.iterdir())

    return Run(["data", "index", str(d)], [str(d / "index.json"), "no space left on device"], after=no_temporary,
               fault=f"ENOSPC:{d}")


def _nan_depth_in_fit(ctx: Ctx) -> Run:
    """Every training scene has a NaN depth: the DataLoader worker's error reaches the user as one line."""
    d = ctx.dataset()
    for path in sorted((d / "train").glob("*.npz")):
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["depth"][0, 0, 0] = np.nan
        path.write_bytes(npz_bytes(arrays))
    cfg = ctx.file("data.yaml", yaml.safe_dump({"data": {"init_args": {"data_dir": str(d), "num_workers": 1}}}))
    argv = ["fit", "--config", "stages/viewpred.yaml", "--config", str(ctx.shared.config), "--config", str(cfg),
            f"--trainer.default_root_dir={ctx.dir / 'run'}", "--trainer.limit_val_batches=0"]
    return Run(argv, [str(d / "train"), "field 'depth'", "non-finite"])


def _one_object_test_split(ctx: Ctx) -> Run:
    """A dataset whose test split holds one object: the evaluation says so instead of failing in a metric."""
    from threedq.scene import load_scene, save_scene

    d = ctx.dataset()
    idx = json.loads((d / "index.json").read_text())
    tests = [s for s in idx["scenes"] if s["split"] == "test"]
    for s in tests[1:]:
        s["split"] = "val"
    path = d / tests[0]["file"]
    rec = load_scene(path)
    rec.boxes, rec.categories = rec.boxes[:1], rec.categories[:1]
    if rec.instance is not None:
        rec.instance = np.where(rec.instance == 1, 1, 0).astype(np.int32)
    save_scene(path, rec)
    (d / "index.json").write_text(json.dumps(idx))
    cfg = ctx.file("data.yaml", yaml.safe_dump({"data": {"init_args": {"data_dir": str(d)}}}))
    argv = ["eval", "--ckpt", str(ctx.shared.quantizer_ckpt), "--extra_configs", f"[{ctx.shared.config}, {cfg}]",
            "--out", str(ctx.dir / "out"), "--baselines", "false", "--curve_k", "[]"]
    return Run(argv, [str(d / "index.json"), "field 'scenes'", "1 object"])


# --- real-data formats: a valid capture (tests/capture_writers.py), then one fault that fails the whole capture


def _import_case(fmt: str, write: str, corrupt: Callable[[Path], Path], field_name: str) -> Callable[[Ctx], Run]:
    def build(ctx: Ctx) -> Run:
        import capture_writers

        name = "rgbd_dataset_freiburg1_xyz" if fmt == "tum" else "room0" if fmt == "replica" else "capture"
        folder = ctx.dir / "src" / name
        getattr(capture_writers, write)(folder, ctx.shared.turntable)
        bad = corrupt(folder)
        argv = ["data", "import", str(folder), "--format", fmt, "--out", str(ctx.dir / "out"), "--progress", "false"]
        return Run(argv, [str(bad), f"field '{field_name}'"])

    return build


def _write(rel: str, text: str) -> Callable[[Path], Path]:
    def corrupt(folder: Path) -> Path:
        p = folder / rel
        p.write_text(text)
        return p

    return corrupt


def _truncate(rel: str, keep: int) -> Callable[[Path], Path]:
    def corrupt(folder: Path) -> Path:
        p = folder / rel
        p.write_bytes(p.read_bytes()[:keep])
        return p

    return corrupt


def _replica_params(folder: Path) -> Path:
    p = folder.parent / "cam_params.json"
    p.write_text(json.dumps({"camera": {"w": 48, "h": 36}}))
    return p


CASES: list[Case] = [
    # --- scene files (threedq data check names each bad file on one line)
    Case("scene_truncated", _scene_bytes_case(lambda b: b[:300], "field '<file>'", "truncated")),
    Case("scene_not_a_zip", _scene_bytes_case(lambda b: b"just some text, not a zip archive\n", "field '<file>'")),
    Case("scene_nan_depth", _scene_case(_set("depth", lambda a: _put(a, (0, 5, 5), np.nan)), "depth", "non-finite")),
    Case("scene_inf_depth", _scene_case(_set("depth", lambda a: _put(a, (1, 2, 3), np.inf)), "depth", "non-finite")),
    Case("scene_negative_depth", _scene_case(_set("depth", lambda a: _put(a, (0, 1, 1), -0.5)), "depth", "negative")),
    Case("scene_inf_pose", _scene_case(_set("world_T_cam", lambda a: _put(a, (2, 0, 3), np.inf)), "world_T_cam",
                                       "non-finite")),
    Case("scene_non_rigid_pose", _scene_case(_set("world_T_cam", lambda a: _put(a, (1, 0, 0), 1.5)), "world_T_cam",
                                             "not rigid")),
    Case("scene_depth_size_mismatch", _scene_case(_set("depth", lambda a: a[:, :, :-1]), "depth", "to match rgb")),
    Case("scene_views_mismatch", _scene_case(_set("K", lambda a: a[:-1]), "K", "expected shape")),
    Case("scene_empty", _scene_case(_empty_scene, "boxes", "empty scene")),
    Case("scene_box_outside_bounds", _scene_case(_set("boxes", lambda a: _put(a, (0, 0), 50.0)), "boxes",
                                                 "outside the scene bounds")),
    Case("scene_rgb_float", _scene_case(_set("rgb", lambda a: a.astype(np.float32)), "rgb", "uint8")),
    Case("scene_depth_int", _scene_case(_set("depth", lambda a: a.astype(np.int32)), "depth", "float")),
    Case("scene_missing_key", _scene_case(_drop("world_T_cam"), "world_T_cam", "missing key")),
    Case("scene_category_out_of_range", _scene_case(_set("categories", lambda a: a + 1000), "categories", ">=")),
    Case("scene_object_array", _scene_case(lambda a: a.update(boxes=np.array([{"x": 1}], dtype=object)), "boxes",
                                           "cannot be read")),
    # --- index.json
    Case("index_missing", _index_case(lambda d: (d / "index.json").unlink(), "{d}/index.json", "no such file")),
    Case("index_bad_json", _index_case(lambda d: (d / "index.json").write_text('{"format": "threedq-scenes",'),
                                       "{d}/index.json", "field '<file>'", "not valid JSON")),
    Case("index_unknown_split", _index_case(_edit_index(_unknown_split), "{d}/index.json", "field 'scenes'",
                                            "unknown split 'holdout'")),
    Case("index_missing_scene_file", _index_case(_edit_index(_missing_scene), "{d}/train/scene_000099.npz",
                                                 "no such file")),
    Case("index_wrong_format", _index_case(_edit_index(lambda i: i.update(format="something-else")),
                                           "{d}/index.json", "field 'format'")),
    Case("index_bad_bounds", _index_case(_edit_index(lambda i: i.update(scene_bounds={"min": [0, 0]})),
                                         "{d}/index.json", "field 'scene_bounds'")),
    # --- configs
    Case("config_unknown_key", _config_case("model:\n  init_args:\n    bogus_key: 1\n", "{cfg}",
                                            "field 'model.init_args.bogus_key'", "not accepted")),
    Case("config_unknown_section", _config_case("bogus_section: 1\n", "{cfg}", "field 'bogus_section'")),
    Case("config_wrong_type", _config_case("trainer:\n  max_steps: many\n", "{cfg}", "field 'trainer.max_steps'",
                                           "many")),
    Case("config_bad_yaml", _config_case("model: [\n", "{cfg}", "field '<file>'", "not valid YAML")),
    Case("config_not_a_mapping", _config_case("- 1\n- 2\n", "{cfg}", "field '<file>'", "expected a mapping")),
    Case("config_old_class_path", _config_case("model:\n  class_path: stages.viewpred.ViewPrediction\n", "{cfg}",
                                               "field 'class_path'", "threedq.stages.viewpred.ViewPrediction")),
    Case("config_syncbn_on_cpu", lambda ctx: Run(
        ["fit", "--config", "stages/viewpred.yaml", "--config", str(ctx.shared.config), "--config", "trainer/ddp.yaml",
         "--trainer.accelerator=cpu", "--trainer.devices=2", f"--trainer.default_root_dir={ctx.dir / 'run'}"],
        ["--trainer.sync_batchnorm", "trainer/ddp_cpu.yaml"])),
    Case("config_missing_file", lambda ctx: Run(["fit", "--config", str(ctx.dir / "nope.yaml")],
                                                [str(ctx.dir / "nope.yaml"), "not found"])),
    Case("option_wrong_type", lambda ctx: Run(["fit", "--config", "stages/viewpred.yaml", "--trainer.max_steps=abc"],
                                              ["--trainer.max_steps", "abc"])),
    Case("em_extra_config_unknown_key", lambda ctx: Run(
        [*_em(ctx), "--extra_configs+", str(ctx.file("bad.yaml", "model:\n  init_args:\n    bogus_key: 1\n"))],
        [str(ctx.dir / "bad.yaml"), "field 'model.init_args.bogus_key'"])),
    # --- checkpoints
    Case("ckpt_truncated", _eval_case(_truncated_ckpt, "{ckpt}", "field '<file>'", "truncated")),
    Case("ckpt_other_stage", _eval_case(lambda ctx: ctx.shared.viewpred_ckpt,
                                        "{ckpt}: this is a viewpred checkpoint; eval needs a quantizer checkpoint")),
    Case("ckpt_other_grid", _eval_case(_other_grid_ckpt, "{ckpt}", "field 'grid_resolution'")),
    Case("ckpt_unsafe_pickle", _eval_case(_unsafe_ckpt, "{ckpt}", "field '<file>'", "weights_only=True",
                                          "argparse.Namespace")),
    Case("ckpt_not_a_checkpoint", _eval_case(_list_ckpt, "{ckpt}", "not a stage checkpoint")),
    Case("ckpt_missing", _eval_case(lambda ctx: ctx.dir / "nope.ckpt", "--ckpt {ckpt}", "no such file")),
    Case("encoder_ckpt_truncated", lambda ctx: Run(
        ["fit", "--config", "stages/quantizer.yaml", "--config", str(ctx.shared.config),
         f"--model.init_args.encoder_ckpt={_truncated_ckpt(ctx)}", f"--trainer.default_root_dir={ctx.dir / 'run'}"],
        [str(ctx.dir / "truncated.ckpt"), "field '<file>'"])),
    Case("resume_other_stage", lambda ctx: Run(
        ["fit", "--config", "stages/viewpred.yaml", "--config", str(ctx.shared.config),
         "--ckpt_path", str(ctx.shared.quantizer_ckpt), f"--trainer.default_root_dir={ctx.dir / 'run'}"],
        [str(ctx.shared.quantizer_ckpt), "this is a quantizer checkpoint"])),
    Case("resume_truncated", lambda ctx: Run(
        ["fit", "--config", "stages/viewpred.yaml", "--config", str(ctx.shared.config),
         "--ckpt_path", str(_truncated_ckpt(ctx)), f"--trainer.default_root_dir={ctx.dir / 'run'}"],
        [str(ctx.dir / "truncated.ckpt"), "field '<file>'"])),
    # --- command-line options
    Case("em_negative_rounds", lambda ctx: Run(_em(ctx, "--rounds", "-1"), ["--rounds", "-1"])),
    Case("em_rounds_not_int", lambda ctx: Run(_em(ctx, "--rounds", "four"), ["--rounds", "four"])),
    Case("em_unknown_boxes", lambda ctx: Run(_em(ctx, "--boxes", "bogus"), ["--boxes", "bogus"])),
    Case("em_missing_extra_config", lambda ctx: Run(_em(ctx, "--extra_configs+", str(ctx.dir / "nope.yaml")),
                                                    [str(ctx.dir / "nope.yaml"), "not found"])),
    Case("unknown_option", lambda ctx: Run(["data", "check", str(ctx.shared.data), "--nope", "1"], ["--nope"])),
    Case("import_unknown_format", lambda ctx: Run(
        ["data", "import", str(ctx.dir), "--format", "bogus", "--out", str(ctx.dir / "o")], ["--format", "bogus"])),
    Case("generate_zero_scenes", lambda ctx: Run(_generate(ctx.dir / "d", "--scenes", "0"), ["--scenes", "0"])),
    Case("generate_out_is_file", _out_is_file(lambda ctx, f: _generate(f), "--out")),
    Case("eval_out_is_file", _out_is_file(lambda ctx, f: ["eval", "--ckpt", str(ctx.shared.quantizer_ckpt),
                                                         "--extra_configs", str(ctx.shared.config), "--out", str(f)],
                                          "--out")),
    Case("em_work_dir_is_file", _out_is_file(lambda ctx, f: ["em", "--work_dir", str(f)], "--work_dir")),
    Case("no_write_permission", _no_write_permission),
    # --- real-data formats (threedq data import names the failed capture's file and field)
    Case("import_tum", _import_case("tum", "write_tum", _write("groundtruth.txt", "1305031102.1 nan 0 0 0 0 0 1\n"),
                                    "frames")),
    Case("import_scannet", _import_case("scannet", "write_scannet", _write("intrinsic/intrinsic_depth.txt", "1 2\n"),
                                        "intrinsic_depth")),
    Case("import_nerfstudio", _import_case("nerfstudio", "write_nerfstudio", _truncate("transforms.json", 500),
                                           "frames")),
    Case("import_replica", _import_case("replica", "write_replica", _replica_params, "camera")),
    Case("import_bigbird", _import_case("bigbird", "write_bigbird", _truncate("calibration.h5", 200), "NP1_rgb_K")),
    Case("import_open3d", _import_case("open3d", "write_open3d", _write("camera_intrinsic.json", '{"width": 48}'),
                                       "intrinsic_matrix")),
    Case("import_rig", _import_case("rig", "write_rig", _write("rig.yaml", "cameras: [\n"), "<file>")),
    # --- a full disk (simulated: writes fail with ENOSPC); atomic writes leave nothing partial
    Case("disk_full_generate", _disk_full_generate),
    Case("disk_full_index", _disk_full_index),
    # --- through the loaders of a training run and an evaluation
    Case("fit_worker_nan_depth", _nan_depth_in_fit),
    Case("eval_one_test_object", _one_object_test_split),
]


# ---------------------------------------------------------------------------------------------------------------
# Running them
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class Outcome:
    run: Run
    returncode: int
    stdout: str
    stderr: str
    before: dict[str, tuple[int, int, str]]
    after: dict[str, tuple[int, int, str]]
    seconds: float
    folder: Path | None = None  # the case's folder (None: a case run in this process)


#: The environment of every command (and of the fork server).
ENV = {**os.environ, "PYTHONWARNINGS": "ignore", "TQDM_DISABLE": "1"}
#: Cases that also run as a new ``python -m threedq`` process: the forked command must give the same outcome.
#: A data command under the fault shim, and a parse error of a Lightning subcommand.
REAL_TOO = ("disk_full_index", "config_unknown_key")
REAL_SUFFIX = "@subprocess"


def _execute(folder: Path, run: Run, server: ForkServer | None) -> tuple[int, str, str, float]:
    """Run the case's command in ``folder``: forked by ``server``, or (None) as a new ``python -m threedq``."""
    env = dict(ENV)
    if run.fault:
        env["PYTHONPATH"] = os.pathsep.join([str(SHIM), *filter(None, [env.get("PYTHONPATH")])])
        env["THREEDQ_FAULT"] = run.fault
    t0 = time.perf_counter()
    if server is None:
        p = subprocess.run([sys.executable, "-m", "threedq", *run.argv], cwd=folder, env=env, capture_output=True,
                           text=True, timeout=TIMEOUT_S)
    else:
        p = server.run(run.argv, cwd=folder, env=env, timeout=TIMEOUT_S)
    return p.returncode, p.stdout, p.stderr, time.perf_counter() - t0


@pytest.fixture(scope="module")
def server():
    """The fork server of the cases' commands (its imports run while the shared inputs and the cases are built)."""
    with ForkServer(ENV) as s:
        yield s


@pytest.fixture(scope="module")
def outcomes(request: pytest.FixtureRequest, server: ForkServer, shared: Shared,
             tmp_path_factory: pytest.TempPathFactory):
    """Build the selected cases' inputs, run their commands two at a time; name -> Outcome, plus the shared
    inputs' snapshots before and after all runs under the key ``None``."""
    selected: dict[str, Case] = {}
    for item in request.session.items:
        if item.module is not request.module or not hasattr(item, "callspec"):
            continue
        if getattr(item, "originalname", None) == "test_bad_input":
            selected[item.callspec.params["case"].name] = item.callspec.params["case"]
        elif getattr(item, "originalname", None) == "test_a_forked_command_is_the_real_process":
            case = BY_NAME[item.callspec.params["name"]]
            selected[case.name] = case
            selected[case.name + REAL_SUFFIX] = case
    base = tmp_path_factory.mktemp("bad_inputs")
    built: dict[str, tuple[Path, Run, dict]] = {}
    out: dict = {}
    for name, case in selected.items():
        folder = base / name
        folder.mkdir()
        try:
            run = case.build(Ctx(folder, shared))
        except Exception as e:  # noqa: BLE001 - reported by the case's own test
            out[name] = e
            continue
        built[name] = (folder, run, snapshot(folder))
    shared_before = snapshot(shared.root)
    with concurrent.futures.ThreadPoolExecutor(PARALLEL) as pool:
        futures = {name: pool.submit(_execute, folder, run, None if name.endswith(REAL_SUFFIX) else server)
                   for name, (folder, run, _) in built.items()}
        results = {name: f.result() for name, f in futures.items()}
    out[None] = (shared_before, snapshot(shared.root))
    for name, (folder, run, before) in built.items():
        rc, so, se, seconds = results[name]
        for p in folder.rglob("*"):  # undo a read-only folder so that tmp_path can be cleaned
            if p.is_dir():
                p.chmod(0o755)
        after = {k: v for k, v in snapshot(folder).items() if k in before}
        out[name] = Outcome(run, rc, so, se, before, after, seconds, folder)
    for name, o in out.items():
        if isinstance(o, Outcome):
            _log(name, o)
    return out


ERROR_PREFIX = "threedq: error: "


def _log(name: str, o: Outcome) -> None:
    """With THREEDQ_BAD_INPUTS_LOG=<file>: append what the case printed (for reading the corpus at a glance)."""
    log = os.environ.get("THREEDQ_BAD_INPUTS_LOG")
    if log:
        with open(log, "a", encoding="utf-8") as f:
            lines = " | ".join(error_lines(o)) or o.stderr.strip()[-300:]
            f.write(f"{name}\t{o.returncode}\t{o.seconds:.1f}\t{lines}\n")


def error_lines(o: Outcome) -> list[str]:
    """The lines that report an error: ``threedq: error:`` lines of stderr, and report lines naming a field."""
    lines = [ln for ln in o.stderr.splitlines() if ln.startswith(ERROR_PREFIX)]
    lines += [ln for ln in o.stdout.splitlines() if "field '" in ln]
    return lines


#: Cases whose path another case already takes through a subprocess: run in this process through
#: ``threedq.cli.main`` (same checks), which keeps the file's run time down (~3 s of imports per subprocess).
IN_PROCESS = {
    "scene_views_mismatch", "scene_depth_int", "scene_category_out_of_range", "index_wrong_format", "index_bad_bounds",
    "config_unknown_section", "config_not_a_mapping", "em_rounds_not_int", "em_missing_extra_config", "unknown_option",
    "import_unknown_format", "ckpt_not_a_checkpoint", "ckpt_missing", "resume_truncated",
    # the scene validator's other fields, an em option, a config's class path, two more importers: the same paths as
    # scene_nan_depth, em_negative_rounds, config_unknown_key and import_tum take through a subprocess
    "scene_inf_depth", "scene_negative_depth", "scene_inf_pose", "scene_rgb_float", "scene_box_outside_bounds",
    "em_unknown_boxes", "config_old_class_path", "import_scannet", "import_open3d",
}
BY_NAME = {c.name: c for c in CASES}
SUBPROCESS_CASES = [c for c in CASES if c.name not in IN_PROCESS]
IN_PROCESS_CASES = [c for c in CASES if c.name in IN_PROCESS]


@pytest.mark.parametrize("case", SUBPROCESS_CASES, ids=[c.name for c in SUBPROCESS_CASES])
def test_bad_input(case: Case, outcomes) -> None:
    o: Outcome = outcomes[case.name]
    if isinstance(o, Exception):
        raise o
    check(o)
    before, after = outcomes[None]
    assert before == after, "a shared input changed"


@pytest.mark.parametrize("name", REAL_TOO)
def test_a_forked_command_is_the_real_process(name: str, outcomes) -> None:
    """The same case through the fork server and as a new ``python -m threedq``: one exit status, one output."""
    forked, real = outcomes[name], outcomes[name + REAL_SUFFIX]
    for o in (forked, real):
        if isinstance(o, Exception):
            raise o

    def text(o: Outcome, stream: str) -> str:
        return getattr(o, stream).replace(str(o.folder), "<case>")

    assert forked.returncode == real.returncode
    assert text(forked, "stderr") == text(real, "stderr")
    assert text(forked, "stdout") == text(real, "stdout")
    assert error_lines(real), "the real process printed no error line"


def test_the_fork_server_refuses_a_start_up_variable_it_did_not_start_with(server: ForkServer) -> None:
    with pytest.raises(ValueError, match="OMP_NUM_THREADS"):
        server.run(["--help"], env={**ENV, "OMP_NUM_THREADS": str(int(ENV.get("OMP_NUM_THREADS", "1")) + 1)})
    assert server.run(["--help"], env={**ENV, "THREEDQ_FAULT_MATCH": "x"}).returncode == 0  # not read at start-up


def test_the_fork_server_kills_a_command_past_its_timeout(server: ForkServer) -> None:
    with pytest.raises(subprocess.TimeoutExpired):
        server.run(["em", "--help"], env=ENV, timeout=0.01)  # about 0.3 s forked
    assert server.run(["--help"], env=ENV).returncode == 0  # the server goes on


@pytest.mark.parametrize("case", IN_PROCESS_CASES, ids=[c.name for c in IN_PROCESS_CASES])
def test_bad_input_in_process(case: Case, shared: Shared, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                              capsys: pytest.CaptureFixture[str]) -> None:
    from threedq.cli import main

    run = case.build(Ctx(tmp_path, shared))
    assert run.fault is None
    before, shared_before = snapshot(tmp_path), snapshot(shared.root)
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    t0 = time.perf_counter()
    try:
        rc = main(run.argv)
    except SystemExit as e:
        rc = e.code if isinstance(e.code, int) else 1
    out, err = capsys.readouterr()
    after = {k: v for k, v in snapshot(tmp_path).items() if k in before}
    outcome = Outcome(run, rc, out, err, before, after, time.perf_counter() - t0)
    _log(case.name, outcome)
    check(outcome)
    assert snapshot(shared.root) == shared_before, "a shared input changed"


def check(o: Outcome) -> None:
    """The expectations every case shares (module docstring)."""
    report = (f"\n--- threedq {' '.join(o.run.argv)} ({o.seconds:.1f} s)\n--- stdout:\n{o.stdout[-3000:]}\n"
              f"--- stderr:\n{o.stderr[-3000:]}")
    assert o.returncode != 0, report
    assert "Traceback" not in o.stderr and "Traceback" not in o.stdout, report
    assert "usage:" not in o.stderr, report
    lines = error_lines(o)
    assert len(lines) == 1, f"expected one error line, got {lines}{report}"
    line = lines[0]
    if line.startswith(ERROR_PREFIX):  # nothing follows it (no nested details, no second traceback)
        assert o.stderr.rstrip().splitlines()[-1] == line, report
    for want in o.run.expect:
        assert want in line, f"{want!r} not in the error line {line!r}"
    assert o.after == o.before, "a file that existed before the run changed"
    if o.run.after is not None:
        o.run.after()


def test_table_is_large_enough() -> None:
    assert len(SUBPROCESS_CASES) >= 40 and len({c.name for c in CASES}) == len(CASES) and IN_PROCESS <= {
        c.name for c in CASES}


# ---------------------------------------------------------------------------------------------------------------
# What the fixes promise beyond one line of error
# ---------------------------------------------------------------------------------------------------------------


def test_small_test_split_is_scored_at_a_lower_k_and_says_so(shared: Shared, tmp_path: Path) -> None:
    """3 test objects: precision@10 is scored at k = 2 and every table says so; few-shot is n/a, with the reason."""
    from threedq.pipeline.report import run_eval

    d = tmp_path / "data"
    shutil.copytree(shared.data, d)
    idx = json.loads((d / "index.json").read_text())
    tests = [s for s in idx["scenes"] if s["split"] == "test"]
    tests[1]["split"] = "val"  # one test scene left: 3 objects of 3 categories
    (d / "index.json").write_text(json.dumps(idx))
    cfg = tmp_path / "data.yaml"
    cfg.write_text(yaml.safe_dump({"data": {"init_args": {"data_dir": str(d)}}}))
    res = run_eval(str(shared.quantizer_ckpt), extra_configs=[str(shared.config), str(cfg)], out=str(tmp_path / "out"),
                   baselines=False, curve_k=[])
    n = res["num_test_objects"]
    assert res["retrieval"]["k"] == n - 1 < 10 and res["retrieval"]["k_requested"] == 10
    md = (tmp_path / "out" / "results.md").read_text()
    assert f"precision@{n - 1} (k lowered from 10: {n} test objects)" in md
    assert np.isnan(res["quantization"]["threedq"]["fewshot_acc"])
    assert "| n/a (no category has more than 2 objects: all are labelled shots) |" in md
    assert (tmp_path / "out" / "retrieval.png").is_file()


def test_extra_configs_takes_one_path_like_config() -> None:
    from threedq.cli import build_parser

    em, ev = build_parser("em"), build_parser("eval")
    assert em.parse_args(["em", "--extra_configs", "my.yaml"]).em.extra_configs == "my.yaml"
    assert ev.parse_args(["eval", "--ckpt", "q.ckpt", "--extra_configs", "my.yaml"]).eval.extra_configs == "my.yaml"
    assert em.parse_args(["em", "--extra_configs", "[a.yaml, b.yaml]"]).em.extra_configs == ["a.yaml", "b.yaml"]
    two = ["em", "--extra_configs", "a.yaml", "--extra_configs+", "b.yaml"]
    assert em.parse_args(two).em.extra_configs == ["a.yaml", "b.yaml"]


def test_a_failed_atomic_write_names_the_file_and_keeps_the_old_one(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    import errno

    from threedq.atomic_io import atomic_write_text
    from threedq.errors import error_line

    target = tmp_path / "index.json"
    target.write_text("old\n")

    def full(*args: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(OSError) as e:
        atomic_write_text(target, "new\n")
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(target)
    assert error_line(e.value).startswith(f"{target}: no space left on device")
    assert target.read_text() == "old\n" and [p.name for p in tmp_path.iterdir()] == ["index.json"]


def test_error_line_of_a_dataloader_worker() -> None:
    from threedq.errors import error_line

    msg = ("Caught SceneValidationError in DataLoader worker process 0.\nOriginal Traceback (most recent call last):\n"
           '  File "x.py", line 1, in f\n'
           "threedq.scene.SceneValidationError: d/s.npz: field 'depth': 1 non-finite value(s)\n")
    assert error_line(RuntimeError(msg)) == "d/s.npz: field 'depth': 1 non-finite value(s)"


def test_rounds_refuse_detections_with_too_few_boxes(tmp_path: Path) -> None:
    from threedq.data.box_files import save_boxes_file
    from threedq.pipeline.em import _check_handed_on

    box = np.array([[0, 0, 0, 0.1, 0.1, 0.1]], np.float32)
    save_boxes_file(tmp_path / "detections_train.npz", {"train/a.npz": (box, np.ones(1, np.float32)),
                                                        "train/b.npz": (box, np.ones(1, np.float32))})
    save_boxes_file(tmp_path / "detections_test.npz", {"test/a.npz": (box[:0], np.ones(0, np.float32))})
    _check_handed_on(tmp_path, ("train",))
    with pytest.raises(RuntimeError, match=r"detections_test.npz: field 'boxes': the detector hands on 0 box\(es\)"):
        _check_handed_on(tmp_path, ("train", "test"))


def test_too_few_detected_objects_are_the_boxes_fault_with_their_numbers(tmp_path: Path) -> None:
    """Too few test objects to evaluate: with GT boxes the index holds too few; with handed-on boxes the message
    names the boxes file and what they found (count, median extent), not the index."""
    from types import SimpleNamespace

    from threedq.data.box_files import load_boxes_file, save_boxes_file
    from threedq.pipeline.report import _too_few_objects

    big = np.array([[0, 0, 0, 1.3, 1.4, 0.3]], np.float32)  # one box the size of the object area
    save_boxes_file(tmp_path / "detections_test.npz", {"test/a.npz": (big, np.ones(1, np.float32)),
                                                       "test/b.npz": (big[:0], np.ones(0, np.float32))})
    boxes = str(tmp_path / "detections_{split}.npz")
    dm = SimpleNamespace(data_dir=tmp_path / "data", boxes=boxes,
                         box_sets=lambda split: load_boxes_file(boxes.format(split=split)))
    msg = _too_few_objects(dm, 1)
    assert msg.startswith(f"{tmp_path / 'detections_test.npz'}: field 'boxes': 1 box(es) in 2 test scene(s), "
                          "median extent 1.30 x 1.40 x 0.30 m, of which 1 match")
    assert "index.json" not in msg
    gt = SimpleNamespace(data_dir=tmp_path / "data", boxes="gt")
    assert _too_few_objects(gt, 1).startswith(f"{tmp_path / 'data' / 'index.json'}: field 'scenes': the test split "
                                              "holds 1 object(s)")


def test_data_config_is_composed_after_the_stage_config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``threedq eval --data_config d.yaml --extra_configs x.yaml``: the stage config, then the data, then the extras."""
    from threedq.cli import build_parser
    from threedq.pipeline import report

    assert build_parser("em").parse_args(["em", "--data_config", "d.yaml"]).em.data_config == "d.yaml"
    assert build_parser("eval").parse_args(["eval", "--ckpt", "q.ckpt", "--data_config", "d.yaml"]).eval.data_config \
        == "d.yaml"
    seen: list[list[Path]] = []

    class Stop(Exception):
        pass

    def fake_test_checkpoint(configs, *args, **kwargs):
        seen.append([Path(c) for c in configs])
        raise Stop

    d, x = tmp_path / "d.yaml", tmp_path / "x.yaml"
    for f in (d, x):
        f.write_text("{}\n")
    monkeypatch.setattr(report, "require_stage", lambda *a, **k: None)
    monkeypatch.setattr(report, "test_checkpoint", fake_test_checkpoint)
    with pytest.raises(Stop):
        report.run_eval("q.ckpt", data_config=str(d), extra_configs=str(x), out=str(tmp_path / "out"))
    assert [c.name for c in seen[0]] == ["quantizer.yaml", "d.yaml", "x.yaml"]
