"""Real DDP on CPU: two gloo processes run the stages to the end and measure what one process measures.

Two launch paths, as users launch them:

- Lightning's own launcher: ``threedq fit ... --config trainer/ddp_cpu.yaml`` (``devices: 2``) starts the second
  process itself;
- ``torchrun --standalone --nproc_per_node 2`` (what a SLURM ``srun`` or a multi-node launch does per node):
  ``tests/ddp_driver.py`` runs several ``threedq`` commands one after the other in the same two processes.

Each torchmetrics metric gathered over the 2 processes (Hungarian accuracy, few-shot accuracy, relative yaw,
3D mAP, retrieval precision@K) equals the value of one process on the same checkpoint and data; the prototype
bank fitted under DDP equals the one fitted in one process with the same seed. The test split holds an odd
number of scenes (5), so the processes evaluate unequal shares.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

pytestmark = pytest.mark.slow

HERE = Path(__file__).resolve().parent


@pytest.fixture(scope="module")
def ddp_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """15 scenes (train 8 / val 2 / test 5) of 2 asymmetric categories (mug, banana: relative yaw is defined)."""
    from threedq.data.generate import generate_dataset
    from threedq.data.generator_config import GeneratorConfig

    out = tmp_path_factory.mktemp("ddp_data")
    config = GeneratorConfig(image_size=(32, 32), num_views=4, min_objects=2, max_objects=3,
                             categories=("mug", "banana"))
    generate_dataset(out, num_scenes=15, seed=3, config=config, split_fractions=(0.5, 0.15, 0.35), workers=1,
                     progress=False)
    return out


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(HERE.parent), env.get("PYTHONPATH", "")])
    env["OMP_NUM_THREADS"] = "1"
    return env


def _run(cmd: list[str], cwd: Path, timeout: int = 300) -> subprocess.CompletedProcess:
    res = subprocess.run(cmd, cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, f"{' '.join(cmd)} failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    return res


def _same(a: float, b: float, tol: float = 1e-5) -> bool:
    return (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=tol, abs_tol=tol)


@pytest.fixture(scope="module")
def runs(ddp_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    from threedq.pipeline.lightning_cli import ThreeDQCLI

    work = tmp_path_factory.mktemp("ddp_runs")
    data = work / "data.yaml"
    data.write_text(
        "data:\n  class_path: threedq.datamodules.scene_folder.SceneFolderDataModule\n"
        f"  init_args:\n    data_dir: {ddp_data}\n    batch_size: 2\n"
        "trainer:\n  enable_progress_bar: false\n  enable_model_summary: false\n  log_every_n_steps: 1\n"
    )
    vp = work / "vp.yaml"
    vp.write_text("model:\n  init_args:\n    grid_resolution: [32, 32, 16]\n"
                  "trainer:\n  max_steps: 2\n  limit_val_batches: 1\n")
    # the encoder every later stage uses: one process
    ThreeDQCLI(args=["fit", "--config", "stages/viewpred.yaml", "--config", str(data), "--config", str(vp),
                     f"--trainer.default_root_dir={work / 'vp_1p'}"])
    encoder = work / "vp_1p" / "checkpoints" / "last.ckpt"
    enc = f"--model.init_args.encoder_ckpt={encoder}"
    # 1. Lightning's launcher: view prediction fit on 2 processes, from the command line a user types
    _run([sys.executable, "-m", "threedq", "fit", "--config", "stages/viewpred.yaml", "--config", str(data),
          "--config", str(vp), "--config", "trainer/ddp_cpu.yaml", f"--trainer.default_root_dir={work / 'vp_ddp'}"],
         cwd=work)
    q = ["--config", "stages/quantizer.yaml", "--config", str(data), enc,
         "--model.init_args.num_prototypes=2"]
    # GT boxes: the tiny scenes' pseudo-boxes are too few and too flat for the detector's anchor and positives
    det = ["--config", "stages/detector.yaml", "--config", str(data), enc, "--data.init_args.boxes=gt", "--trainer.max_steps=2",
           "--trainer.limit_val_batches=1", "--model.init_args.eval_score_threshold=0.0"]
    mine = ["--config", "stages/mining.yaml", "--config", str(data), enc, "--model.init_args.retrieval_k=3",
            "--trainer.precision=32-true"]
    ddp = ["--config", "trainer/ddp_cpu.yaml"]
    q_ckpt, det_ckpt = work / "q_ddp" / "checkpoints" / "last.ckpt", work / "det_ddp" / "checkpoints" / "last.ckpt"
    commands = [
        ["test", "--config", "stages/viewpred.yaml", "--config", str(data), "--config", str(vp), *ddp,
         f"--ckpt_path={work / 'vp_ddp' / 'checkpoints' / 'last.ckpt'}", f"--trainer.default_root_dir={work / 'vpt'}"],
        ["fit", *q, *ddp, f"--trainer.default_root_dir={work / 'q_ddp'}"],
        ["test", *q, *ddp, f"--ckpt_path={q_ckpt}", f"--trainer.default_root_dir={work / 'qt_ddp'}"],
        ["fit", *det, *ddp, f"--trainer.default_root_dir={work / 'det_ddp'}"],
        ["test", *det, *ddp, f"--ckpt_path={det_ckpt}", f"--trainer.default_root_dir={work / 'dett_ddp'}"],
        ["test", *mine, *ddp, f"--trainer.default_root_dir={work / 'mt_ddp'}"],
    ]
    plan = work / "plan.json"
    plan.write_text(json.dumps({"out": str(work / "ddp.json"), "commands": commands}))
    # 2. torchrun: the same two processes run every command above
    _run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
          str(HERE / "ddp_driver.py"), str(plan)], cwd=work)
    results = json.loads((work / "ddp.json").read_text())

    def one(args: list[str]) -> dict[str, float]:
        cli = ThreeDQCLI(args=args)
        return {k: float(v) for k, v in cli.trainer.callback_metrics.items()}

    single = {
        "q_fit": one(["fit", *q, f"--trainer.default_root_dir={work / 'q_1p'}"]),
        "q_test": one(["test", *q, f"--ckpt_path={q_ckpt}", f"--trainer.default_root_dir={work / 'qt_1p'}"]),
        "det_test": one(["test", *det, f"--ckpt_path={det_ckpt}", f"--trainer.default_root_dir={work / 'dett_1p'}"]),
        "mine_test": one(["test", *mine, f"--trainer.default_root_dir={work / 'mt_1p'}"]),
    }
    return {"work": work, "q_args": q, "ddp": dict(zip(["vp_test", "q_fit", "q_test", "det_fit", "det_test", "mine_test"], results)),
            "single": single}


class TestDDP:
    def test_stages_run_to_the_end(self, runs: dict) -> None:
        work = runs["work"]
        for stage in ("vp_ddp", "q_ddp", "det_ddp"):
            assert (work / stage / "checkpoints" / "last.ckpt").is_file(), stage
        assert runs["ddp"]["vp_test"]["test/l1"] > 0 and 0 <= runs["ddp"]["vp_test"]["test/occ_bacc"] <= 1
        # the rank-0 pictures are written (asking the logger's folder on rank 0 alone used to hang the run)
        assert list((work / "vp_ddp" / "images").glob("train_step*.png"))

    def test_quantizer_metrics_equal_one_process(self, runs: dict) -> None:
        ddp, one = runs["ddp"]["q_test"], runs["single"]["q_test"]
        assert ddp["test/objects"] == one["test/objects"] > 5  # every test object once: none dropped, none doubled
        for key in ("test/hungarian_acc", "test/fewshot_acc", "test/yaw_median_deg", "test/yaw_acc10",
                    "test/yaw_acc20", "test/yaw_pairs"):
            assert _same(ddp[key], one[key]), (key, ddp[key], one[key])
        assert one["test/yaw_pairs"] > 0 and not math.isnan(one["test/fewshot_acc"])

    def test_detection_map_equal_one_process(self, runs: dict) -> None:
        ddp, one = runs["ddp"]["det_test"], runs["single"]["det_test"]
        keys = [k for k in one if k.startswith("test/map") or k.startswith("test/num_")]
        assert {"test/map_25", "test/map_50"} <= set(keys)
        for key in keys:
            assert _same(ddp[key], one[key]), (key, ddp[key], one[key])

    def test_retrieval_precision_equal_one_process(self, runs: dict) -> None:
        ddp, one = runs["ddp"]["mine_test"], runs["single"]["mine_test"]
        keys = [k for k in one if "precision" in k]
        assert keys
        for key in keys:
            assert _same(ddp[key], one[key]), (key, ddp[key], one[key])

    def test_bank_equal_one_process(self, runs: dict) -> None:
        work = runs["work"]
        a = torch.load(work / "q_1p" / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")["state_dict"]
        b = torch.load(work / "q_ddp" / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")["state_dict"]
        assert int(a["bank.active"].sum()) >= 2
        assert torch.equal(a["bank.active"], b["bank.active"])
        assert torch.equal(a["bank.member_count"], b["bank.member_count"])
        torch.testing.assert_close(a["bank.prototypes"], b["bank.prototypes"], atol=1e-5, rtol=1e-5)
        # each training object once in the EM: the padding of the distributed sampler is not counted twice
        assert runs["ddp"]["q_fit"]["train/objects"] >= runs["single"]["q_fit"]["train/objects"]


class TestSlurm:
    def test_srun_style_launch(self, runs: dict) -> None:
        """Two processes started as ``srun --ntasks-per-node 2`` starts them (SLURM's variables set by hand, no
        scheduler here): Lightning's SLURM environment forms the group; the metrics equal one process's."""
        import csv
        import socket

        work = runs["work"]
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
        args = [sys.executable, "-m", "threedq", "test", *runs["q_args"], "--config", "trainer/ddp_cpu.yaml",
                f"--ckpt_path={work / 'q_ddp' / 'checkpoints' / 'last.ckpt'}", f"--trainer.default_root_dir={work / 'q_slurm'}"]
        procs = []
        for rank in range(2):
            env = _env() | {"SLURM_JOB_ID": "1", "SLURM_JOB_NAME": "threedq", "SLURM_NTASKS": "2",
                            "SLURM_NTASKS_PER_NODE": "2", "SLURM_PROCID": str(rank), "SLURM_LOCALID": str(rank),
                            "SLURM_NODEID": "0", "SLURM_NODELIST": "localhost", "MASTER_PORT": str(port)}
            procs.append(subprocess.Popen(args, cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                          text=True))
        outs = [p.communicate(timeout=300)[0] for p in procs]
        failed = [r for r, p in enumerate(procs) if p.returncode != 0]  # the output of the rank that failed
        assert not failed, "\n".join(f"rank {r} (exit {procs[r].returncode}): {outs[r][-3000:]}" for r in failed)
        assert "MEMBER: 2/2" in outs[1]
        rows = list(csv.DictReader((work / "q_slurm" / "metrics.csv").open()))
        got = {k: float(v) for r in rows for k, v in r.items() if k.startswith("test/") and v != ""}
        one = runs["single"]["q_test"]
        assert got["test/objects"] == one["test/objects"]
        for key in ("test/hungarian_acc", "test/fewshot_acc", "test/yaw_median_deg"):
            assert _same(got[key], one[key]), (key, got[key], one[key])


class TestSamplers:
    def test_contiguous_blocks_cover_once_in_order(self) -> None:
        from threedq.data.samplers import contiguous_block

        for n in (0, 1, 5, 8, 11):
            for w in (1, 2, 3, 4):
                blocks = [list(contiguous_block(n, w, r)) for r in range(w)]
                assert sum(blocks, []) == list(range(n))
                assert max(map(len, blocks)) - min(map(len, blocks)) <= 1
        with pytest.raises(ValueError, match="rank"):
            contiguous_block(5, 2, 2)

    def test_epoch_sampler_same_samples_any_world_size(self) -> None:
        from threedq.data.samplers import EpochShuffleSampler

        data = list(range(7))
        one = EpochShuffleSampler(data, seed=3)
        one.set_epoch(2)
        two = [EpochShuffleSampler(data, seed=3, num_replicas=2, rank=r) for r in range(2)]
        for s in two:
            s.set_epoch(2)
        got = [x for s in two for x in s]
        assert all(e == 2 for _, e in got) and sorted({i for i, _ in got}) == data  # 8 drawn: one padded repeat
        assert sorted(i for i, _ in one) == data
        one.set_epoch(3)
        assert [i for i, _ in one] != [i for i, _ in EpochShuffleSampler(data, seed=3)]  # epoch 0 differs
