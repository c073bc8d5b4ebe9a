"""``threedq em``: the loop end to end on the tiny dataset (stages in order, finished ones skipped, an interrupted one
restarted, the crop cache shared, a given view-prediction checkpoint); killed runs, a second run and full disks are in
``tests/test_resume.py``."""

from __future__ import annotations

import gc
import json
import shutil
import weakref
from pathlib import Path
from typing import Any

import pytest
import torch
import yaml
from conftest import tiny_data_yaml, tiny_mining_config, tiny_quantizer_config
from threedq.pipeline.lightning_cli import packaged_configs_dir
from lightning.pytorch import LightningModule

from threedq.scene import load_index


def _em_config(tmp_path: Path, data_dir: Path) -> str:
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(
        f"""
model:
  init_args:
    grid_resolution: [32, 32, 16]
{tiny_data_yaml(data_dir)}
trainer:
  max_steps: 2
  log_every_n_steps: 1
  limit_val_batches: 1
  check_val_every_n_epoch: 1
  enable_progress_bar: false
  enable_model_summary: false
"""
    )
    return str(cfg)


def run_em(**kwargs: Any) -> dict:
    """:func:`threedq.pipeline.em.run_em` with the tests' quantizer config (:func:`conftest.tiny_quantizer_config`,
    written beside the work folder) unless the test gives one."""
    from threedq.pipeline import em

    if "quantizer_config" not in kwargs:
        q = Path(kwargs["work_dir"]).parent / "tiny_quantizer.yaml"
        kwargs["quantizer_config"] = str(q if q.is_file() else tiny_quantizer_config(q.parent))
    return em.run_em(**kwargs)


class TestEm:
    def test_runs_then_skips_finished_stages(self, tmp_path: Path, tiny_dataset: Path, capsys) -> None:

        cfg = _em_config(tmp_path, tiny_dataset)
        work = tmp_path / "em"
        def modules() -> list[LightningModule]:
            return [o for o in gc.get_objects() if isinstance(o, LightningModule) and not isinstance(o, weakref.ProxyTypes)]

        gc.collect()
        before = modules()  # what earlier tests keep alive is not the run's (held here, so no new module takes an id)
        ids = {id(o) for o in before}
        gc.disable()  # only em's own collections run: a stage's module must not wait for the next automatic one
        try:
            summary = run_em(rounds=2, work_dir=str(work), extra_configs=[cfg], mining_config="none", boxes="gt")
            # 12 stages and evaluations ran; their modules (a stage's module, trainer and datamodule reference one
            # another) are freed as each ends. jsonargparse keeps the last parser in a context variable, and through
            # it the last CLI and its module: at most one stays
            alive = [type(o).__name__ for o in modules() if id(o) not in ids]
        finally:
            gc.enable()
        assert len(alive) <= 1, alive
        cache = summary["crop_cache"]
        # round 2 and its evaluation encode nothing new: the same encoder, views and boxes as round 1
        assert cache["reused"] > 0 and cache["reused"] >= cache["computed"] // 2
        assert json.loads((work / "metrics.json").read_text())["crop_cache"] == cache
        final = summary["round_results"][-1]
        assert set(final["retrieval"]["precision_at_k"]) == {"learned", "raw_rgb_occupancy", "random_encoder",
                                                             "colour_size_descriptor"}
        paper = final["retrieval"]["protocols"]["paper"]
        assert set(paper["precision_at_k"]) == set(final["retrieval"]["precision_at_k"]) == set(paper["same_object_top1"])
        assert paper["pool"] == final["num_test_objects"] and 0 < paper["ceiling"] <= 1
        assert set(final["quantization"]) == {"threedq", "no_rot", "pointcloud"}
        assert 0 <= final["quantization"]["threedq"]["hungarian_acc"] <= 1
        assert summary["viewpred_eval"]["view_prediction"]["num_scenes"] == 2
        report = (work / "report.md").read_text()
        assert "Hungarian" in report and "precision@" in report
        assert json.loads((work / "metrics.json").read_text())["rounds"] == 2
        for png in ("prototype_alignment.png", "retrieval.png"):
            assert (work / "r02_eval" / png).is_file()
        det = summary["detector_eval"]
        assert 0 <= det["pseudo_boxes"]["map_50"] <= det["pseudo_boxes"]["map_25"] <= 1
        assert 0 <= det["detector"]["map_50"] <= 1 and det["detector"]["num_gt"] > 0
        assert (work / "03_detector_eval" / "detections.png").is_file()
        # the fair reference (pseudo-boxes from the detector's own input view) and the objects found per size band
        single = det["pseudo_boxes_single_view"]
        assert 0 <= single["map_50"] <= single["map_25"] <= 1 and single["num_gt"] == det["detector"]["num_gt"]
        assert [t["boxes"] for t in det["by_size"]][:2] == ["pseudo-boxes (all views)", "pseudo-boxes (input view)"]
        for rows in (t["rows"] for t in det["by_size"]):
            assert rows[-1]["band"] == "all" and rows[-1]["objects"] == det["detector"]["num_gt"]
            assert sum(r["objects"] for r in rows[:-2]) == rows[-1]["objects"]  # the size bands; then "flat", "all"
            assert rows[-2]["band"].startswith("flat: < ") and rows[-2]["objects"] <= rows[-1]["objects"]
        assert (work / "03_detector_eval" / "detection_by_size.png").is_file() and "Objects found per size" in report
        assert "3D detection" in report
        run = work / "00_viewpred"
        assert (run / "config.yaml").is_file() and (run / "checkpoints" / "last.ckpt").is_file()
        assert list((run / "images").glob("*.png")) and (run / "metrics.csv").is_file()
        stamp = (run / "checkpoints" / "last.ckpt").stat().st_mtime_ns
        # the detector is self-labelled every round; Table 3 has rounds 0..2
        assert summary["round_stages_run"] == ["quantizer", "self_labelling"]
        sl = summary["self_label_results"]
        assert len(sl) == 2 and sl[1]["checkpoint"] == str(work / "r02_self_labelling" / "checkpoints" / "last.ckpt")
        assert sl[0]["labels"]["scenes"] == len(load_index(tiny_dataset).files("train"))
        assert [t["round"] for t in summary["table3"]] == [0, 1, 2]
        # round 0 (the paper's iteration 0) is the view-prediction encoder on round 1's boxes: without mining and on
        # GT boxes, round 1 quantizes exactly that, so the two rows' features and clustering agree
        t0, t1 = summary["table3"][0], summary["table3"][1]
        for key in ("precision_at_10", "precision_at_10_paper", "same_object_top1", "hungarian_acc"):
            assert t0[key] is not None and t0[key] == pytest.approx(t1[key]), key
        assert (work / "r00_eval" / "results.json").is_file()
        assert summary["table3"][2]["map_50"] == sl[1]["detector_eval"]["detector"]["map_50"]
        assert "handed_on" in sl[1]["detector_eval"] and (work / "table3.png").is_file()
        assert "Table 3" in report and "self-labelling per round" in report
        # round 2's prototypes: an empty bank fitted afresh (--bank_warm_start, default false); on
        # GT boxes without mining round 2 quantizes round 1's crops with round 1's seeds, so its fit is round 1's
        q2 = yaml.safe_load((work / "r02_quantizer" / "config.yaml").read_text())["model"]["init_args"]
        assert q2.get("init_bank_ckpt") is None
        banks = [torch.load(work / f"r0{r}_quantizer" / "checkpoints" / "last.ckpt", weights_only=True,
                            map_location="cpu")["state_dict"] for r in (1, 2)]
        keys = [k for k in banks[0] if k.startswith("bank.")]
        assert keys and all(torch.equal(banks[0][k], banks[1][k]) for k in keys)
        assert summary["bank_warm_start"] is False and "`--bank_warm_start false`" in report
        # round 2's detector is round 1's, fine-tuned again
        r1 = torch.load(work / "r01_self_labelling" / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
        cfg2 = yaml.safe_load((work / "r02_self_labelling" / "config.yaml").read_text())
        assert cfg2["model"]["init_args"]["detector_ckpt"] == str(work / "r01_self_labelling" / "checkpoints" / "last.ckpt")
        assert "head.out.weight" in r1["state_dict"]
        capsys.readouterr()
        run_em(rounds=2, work_dir=str(work), extra_configs=[cfg], mining_config="none", boxes="gt")
        assert "finished earlier" in capsys.readouterr().out
        assert (run / "checkpoints" / "last.ckpt").stat().st_mtime_ns == stamp
        # killed during round 2's self-labelling: a resumed run redoes only that stage
        (work / "r02_self_labelling" / "stage.json").unlink()
        shutil.rmtree(work / "r02_detector_eval")
        q_stamp = (work / "r02_quantizer" / "checkpoints" / "last.ckpt").stat().st_mtime_ns
        with pytest.raises(RuntimeError, match="--resume"):
            run_em(rounds=2, work_dir=str(work), extra_configs=[cfg], mining_config="none", boxes="gt")
        capsys.readouterr()
        again = run_em(rounds=2, work_dir=str(work), extra_configs=[cfg], mining_config="none", boxes="gt", resume=True)
        out = capsys.readouterr().out
        assert "round 2 self-labelling: unfinished (interrupted): restarting" in out
        assert "round 2 quantizer: finished earlier" in out
        assert (work / "r02_quantizer" / "checkpoints" / "last.ckpt").stat().st_mtime_ns == q_stamp
        assert (run / "checkpoints" / "last.ckpt").stat().st_mtime_ns == stamp
        assert again["table3"][2]["map_50"] is not None

    def test_round_with_mining(self, tmp_path: Path, tiny_dataset: Path, capsys, monkeypatch: pytest.MonkeyPatch) -> None:
        """A round fine-tunes the encoder by mining first; its quantizer runs on that encoder, not view prediction's.
        On a CPU without bf16 instructions (here pretended) mining and the frozen stages run in float32."""
        from threedq.stages.base import encoder_state_from_checkpoint

        from threedq.pipeline import em

        monkeypatch.setattr(em, "_bf16_is_native", lambda cpu=None: False)

        cfg = _em_config(tmp_path, tiny_dataset)
        work = tmp_path / "em"
        # the paper's pool: on the tiny scenes the object check (pool_min_observed_iou, on in mining.yaml) vouches for
        # 7 of the 16 GT boxes, too few for the 2-step encoder to mine a pair from; the check has its own tests
        mining = yaml.safe_load((packaged_configs_dir() / "stages/mining.yaml").read_text())
        assert mining["model"]["init_args"]["pool_min_observed_iou"] == 0.5
        mining["model"]["init_args"]["pool_min_observed_iou"] = None
        assert mining["model"]["init_args"]["pool_min_scene_iou"] == 0.7  # likewise the scene's check
        mining["model"]["init_args"]["pool_min_scene_iou"] = None
        (tmp_path / "mining_paper_pool.yaml").write_text(yaml.safe_dump(mining))
        summary = run_em(rounds=1, work_dir=str(work), extra_configs=[cfg], detection=False, boxes="gt",
                         mining_config=str(tmp_path / "mining_paper_pool.yaml"))
        assert summary["round_stages_run"] == ["mining", "quantizer"]
        assert summary["frozen_precision"] == summary["mining_precision"] == "32-true"
        for stage in ("r01_mining", "r01_quantizer"):  # the mining config asks for bf16-mixed
            assert yaml.safe_load((work / stage / "config.yaml").read_text())["trainer"]["precision"] == "32-true"
        mined = work / "r01_mining" / "checkpoints" / "last.ckpt"
        assert summary["mining_results"][0]["checkpoint"] == str(mined)
        mining_args = yaml.safe_load((work / "r01_mining" / "config.yaml").read_text())["model"]["init_args"]
        assert mining_args["em_round"] == 1  # em tells each round's mining stage its round (round_lr)
        refreshes = summary["mining_results"][0]["refreshes"]
        assert refreshes and refreshes[0]["pairs"] >= 1 and 0 <= refreshes[0]["same_category"] <= 1
        assert 1 <= refreshes[0]["labelled_pairs"] <= refreshes[0]["pairs"]  # GT boxes: every box is on an object
        vp = encoder_state_from_checkpoint(work / "00_viewpred" / "checkpoints" / "last.ckpt")
        tuned = encoder_state_from_checkpoint(mined)
        used = encoder_state_from_checkpoint(work / "r01_quantizer" / "checkpoints" / "last.ckpt")
        assert all(torch.equal(used[k], tuned[k]) for k in tuned)
        assert any(not torch.equal(vp[k], tuned[k]) for k in tuned if tuned[k].is_floating_point())
        report = (work / "report.md").read_text()
        assert "Correspondence mining per round" in report and "same category" in report
        assert (work / "r01_mining" / "mining" / "refresh_000000.png").is_file()

    def test_rounds_on_detected_boxes(self, tmp_path: Path, tiny_dataset: Path) -> None:
        import numpy as np

        from threedq.boxes import boxes_to_aabb
        from threedq.data.box_files import load_boxes_file, save_boxes_file
        from threedq.scene import load_index, load_scene

        cfg = _em_config(tmp_path, tiny_dataset)
        work = tmp_path / "em"
        run_em(rounds=0, work_dir=str(work), extra_configs=[cfg], boxes="gt")
        det_dir = work / "03_detector_eval"
        assert sorted(p.name for p in det_dir.glob("detections_*.npz")) == ["detections_test.npz"]  # GT rounds
        run_em(rounds=0, work_dir=str(work), extra_configs=[cfg], boxes="detections")  # fills in the others
        index = load_index(tiny_dataset)
        for split in ("train", "val", "test"):
            dets = load_boxes_file(det_dir / f"detections_{split}.npz")
            assert set(dets) == set(index.files(split))
            # A 2-step detector finds nothing useful: stand in a perfect one (GT hulls, shifted 1 cm), so
            # that the rounds' plumbing of detected boxes is what is tested.
            perfect = {}
            for f in index.files(split):
                a = boxes_to_aabb(load_scene(tiny_dataset / f, validate=False).boxes.astype(np.float64)) + 0.01
                perfect[f] = (a.astype(np.float32), np.full(len(a), 0.95, np.float32))
            save_boxes_file(det_dir / f"detections_{split}.npz", perfect)
        # the tiny scenes' 32x32 views give no pseudo-boxes to fuse: mining's scene check finds an empty pool and
        # says so; without it the rounds run
        with pytest.raises(ValueError, match="pool of the training split's boxes is empty.*pool_min_scene_iou"):
            run_em(rounds=1, work_dir=str(work), extra_configs=[cfg], boxes="detections")
        summary = run_em(rounds=1, work_dir=str(work), extra_configs=[cfg], boxes="detections",
                         mining_config=str(tiny_mining_config(tmp_path)), resume=True)
        assert summary["boxes"] == "detections"
        q = yaml.safe_load((work / "r01_quantizer" / "config.yaml").read_text())
        assert q["data"]["init_args"]["boxes"].endswith("detections_{split}.npz")
        final = summary["round_results"][-1]
        assert final["num_test_objects"] == sum(len(load_scene(tiny_dataset / f, validate=False).boxes)
                                                for f in index.files("test"))  # fmt: skip
        with pytest.raises(ValueError, match="boxes"):
            run_em(rounds=1, work_dir=str(work), extra_configs=[cfg], boxes="detections", detection=False)

    def test_resume_an_interrupted_stage(self, tmp_path: Path, tiny_dataset: Path, capsys) -> None:

        cfg = _em_config(tmp_path, tiny_dataset)
        work = tmp_path / "em"
        run_em(rounds=0, work_dir=str(work), extra_configs=[cfg], max_steps=1)
        run = work / "00_viewpred"
        (run / "stage.json").unlink()  # as if killed after its last checkpoint
        (run / "images" / ".train_step000000.png.x1y2.tmp").write_bytes(b"torn")  # a write cut short
        (work / "01_viewpred_eval" / "metrics.json").unlink()
        with pytest.raises(RuntimeError, match="--resume"):
            run_em(rounds=0, work_dir=str(work), extra_configs=[cfg], max_steps=3)
        capsys.readouterr()
        run_em(rounds=0, work_dir=str(work), extra_configs=[cfg], max_steps=3, resume=True)
        out = capsys.readouterr().out
        assert "restarting it from its beginning" in out and "a write cut short" in out
        state = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
        assert state["global_step"] == 3
        assert not list(work.rglob("*.tmp")) and (work / "01_viewpred_eval" / "metrics.json").is_file()



def test_em_given_viewpred_checkpoint(tmp_path: Path, tiny_dataset: Path, capsys) -> None:
    """``--viewpred_ckpt``: no view prediction is trained; the detector and the rounds run on the given encoder."""
    from threedq.stages.base import encoder_state_from_checkpoint

    from threedq.errors import InputError

    cfg = _em_config(tmp_path, tiny_dataset)
    first = tmp_path / "first"
    run_em(rounds=0, work_dir=str(first), extra_configs=[cfg], detection=False, boxes="gt", max_steps=2)
    given = first / "00_viewpred" / "checkpoints" / "last.ckpt"
    work = tmp_path / "em"
    capsys.readouterr()
    summary = run_em(rounds=1, work_dir=str(work), extra_configs=[cfg], mining_config="none", boxes="gt",
                     viewpred_ckpt=str(given))
    assert "viewpred: given" in capsys.readouterr().out
    assert not (work / "00_viewpred").exists() and summary["viewpred"]["given"]
    enc = encoder_state_from_checkpoint(given)
    for stage in ("02_detector", "r01_quantizer", "r01_self_labelling"):
        used = encoder_state_from_checkpoint(work / stage / "checkpoints" / "last.ckpt")
        assert all(torch.equal(used[k], enc[k]) for k in enc), stage
    assert summary["viewpred_eval"]["view_prediction"]["num_scenes"] == 2
    assert "given with --viewpred_ckpt" in (work / "report.md").read_text()
    with pytest.raises(InputError, match="this is a detector checkpoint; --viewpred_ckpt needs a viewpred"):
        run_em(rounds=0, work_dir=str(tmp_path / "x"), extra_configs=[cfg],
               viewpred_ckpt=str(work / "02_detector" / "checkpoints" / "last.ckpt"))
    with pytest.raises(InputError, match="--viewpred_ckpt .*nope.ckpt: no such file"):
        run_em(rounds=0, work_dir=str(tmp_path / "x"), extra_configs=[cfg], viewpred_ckpt=str(tmp_path / "nope.ckpt"))


def test_em_data_config(tmp_path: Path, tiny_dataset: Path) -> None:
    """``--data_config``: a user's dataset is one file (a DataModule class and its folder), composed into every stage;
    the stage configs keep how they load it, and the report names the file."""

    mine = tmp_path / "my_data.yaml"
    mine.write_text(yaml.safe_dump({"data": {"class_path": "threedq.datamodules.scene_folder.SceneFolderDataModule",
                                             "init_args": {"data_dir": str(tiny_dataset)}}}))
    rest = tmp_path / "tiny_model.yaml"
    rest.write_text(yaml.safe_dump({"model": {"init_args": {"grid_resolution": [32, 32, 16]}},
                                    "trainer": {"max_steps": 1, "limit_val_batches": 1, "enable_progress_bar": False,
                                                "enable_model_summary": False}}))
    work = tmp_path / "em"
    summary = run_em(rounds=0, work_dir=str(work), data_config=str(mine), extra_configs=[str(rest)], detection=False,
                     boxes="gt")
    used = yaml.safe_load((work / "00_viewpred" / "config.yaml").read_text())["data"]
    assert used["class_path"] == "threedq.datamodules.scene_folder.SceneFolderDataModule"
    assert used["init_args"]["data_dir"] == str(tiny_dataset)
    assert used["init_args"]["num_target_views"] == 1  # stages/viewpred.yaml's loading argument, kept
    assert summary["viewpred_eval"]["view_prediction"]["num_scenes"] == 2
    # named as the report names configs: relative to the work folder's parent, where threedq em usually runs
    assert summary["data_config"] == "my_data.yaml" and "data: `my_data.yaml`" in (work / "report.md").read_text()


def test_em_bank_warm_start(tmp_path: Path, tiny_dataset: Path) -> None:
    """``--bank_warm_start true``: from round 2 on each round's quantizer refines the previous round's bank, once
    (no restarts). Without mining and on GT boxes round 2 refines round 1's fit on the same crops: its assignments,
    so its Hungarian accuracy, stay round 1's."""
    cfg = _em_config(tmp_path, tiny_dataset)
    work = tmp_path / "em"
    summary = run_em(rounds=2, work_dir=str(work), extra_configs=[cfg], mining_config="none", boxes="gt",
                     detection=False, bank_warm_start=True)
    q2 = yaml.safe_load((work / "r02_quantizer" / "config.yaml").read_text())["model"]["init_args"]
    assert q2["init_bank_ckpt"] == str(work / "r01_quantizer" / "checkpoints" / "last.ckpt")
    t1, t2 = summary["table3"][1], summary["table3"][2]
    assert t1["hungarian_acc"] == t2["hungarian_acc"]
    assert summary["bank_warm_start"] is True
    assert "refines the previous round's bank" in (work / "report.md").read_text()
