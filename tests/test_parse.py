"""Tests of scene parsing for users: ``threedq parse``, ``threedq label`` and the prototype renders."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import tiny_mining_config
from test_em import _em_config

from threedq.cli import main
from threedq.data.box_files import save_boxes_file
from threedq.geometry import rotate_yaw, yaw_angles
from threedq.pipeline.naming import load_labels, propagate_names
from threedq.pipeline.parse import (
    SceneParser,
    find_scenes,
    load_names,
    names_path,
    parse_records,
    resolve_run,
    scene_targets,
)
from threedq.pipeline.parse_command import run_parse
from threedq.pipeline.renders import load_view_decoder, orbit_poses, replaced_render
from threedq.scene import load_index, load_scene, save_scene


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory, tiny_dataset: Path) -> Path:
    """One EM round (mining, quantizer on GT boxes, self-labelling) on the tiny dataset."""
    from threedq.pipeline.em import run_em

    tmp = tmp_path_factory.mktemp("tiny_run")
    work = tmp / "em"
    # fp32 evaluation: the parse (fp32 by default) must reproduce it exactly
    run_em(rounds=1, work_dir=str(work), extra_configs=[_em_config(tmp, tiny_dataset)], boxes="gt",
           frozen_precision="32-true", mining_config=str(tiny_mining_config(tmp)))
    return work


@pytest.fixture(scope="module")
def tiny_run_plain(tmp_path_factory: pytest.TempPathFactory, tiny_dataset: Path) -> Path:
    """One EM round whose prototype bank compares plain crops (``occupancy_floor: null``, the paper's); no mining."""
    from threedq.pipeline.em import run_em
    from threedq.pipeline.lightning_cli import resolve_config

    tmp = tmp_path_factory.mktemp("tiny_run_plain")
    q = tmp / "quantizer.yaml"
    text = resolve_config("stages/quantizer.yaml").read_text()
    q.write_text(text.replace("    occupancy_floor: 0.2\n", "    occupancy_floor: null\n"))
    assert "occupancy_floor: null" in q.read_text()
    work = tmp / "em"
    run_em(rounds=1, work_dir=str(work), extra_configs=[_em_config(tmp, tiny_dataset)], boxes="gt",
           frozen_precision="32-true", quantizer_config=str(q), mining_config="none")
    return work


def _dataset_views(data_dir: Path, split: str, seed: int = 0, n: int = 1) -> list[list[int]]:
    """The views the DataModule's deterministic loader picks (SceneDataset, random_views=False)."""
    files = load_index(data_dir).files(split)
    out = []
    for i, f in enumerate(files):
        nv = load_scene(data_dir / f, validate=False).num_views
        out.append(np.random.default_rng([seed, i]).permutation(nv)[:n].tolist())
    return out


class TestResolveRun:
    def test_finds_the_final_parts(self, tiny_run: Path) -> None:
        a = resolve_run(tiny_run)
        assert a.prototypes == tiny_run / "r01_quantizer" / "checkpoints" / "last.ckpt"
        assert a.detector == tiny_run / "r01_self_labelling" / "checkpoints" / "last.ckpt"
        assert a.encoder == a.prototypes and a.viewpred == tiny_run / "00_viewpred" / "checkpoints" / "last.ckpt"
        warm = tiny_run / "02_detector" / "checkpoints" / "last.ckpt"
        assert resolve_run(tiny_run, detector=warm).detector == warm

    def test_exception(self, tmp_path: Path, tiny_run: Path) -> None:
        with pytest.raises(FileNotFoundError, match="run: no such folder"):
            resolve_run(tmp_path / "nope")
        with pytest.raises(FileNotFoundError, match="prototypes: run .*: no finished quantizer"):
            resolve_run(tmp_path)
        with pytest.raises(FileNotFoundError, match="detector: no such file"):
            resolve_run(tiny_run, detector=tmp_path / "x.ckpt")
        # a view-prediction checkpoint is not a detector
        vp = tiny_run / "00_viewpred" / "checkpoints" / "last.ckpt"
        with pytest.raises(ValueError, match=r"last\.ckpt: field 'state_dict': no 'head\.\*' weights"):
            SceneParser(resolve_run(tiny_run, detector=vp))


class TestParse:
    @pytest.mark.parametrize("run, floor", [("tiny_run", 0.2), ("tiny_run_plain", None)])
    def test_matches_the_evaluation(self, run: str, floor: float | None, tiny_dataset: Path,
                                    request: pytest.FixtureRequest) -> None:
        """Given the evaluation's boxes and views, the parse's prototype ids and yaw indices are the evaluation's, with
        the default bank of occupancy-weighted crops and with plain crops (the parse reads the weighting from the
        quantizer checkpoint)."""
        tiny_run = request.getfixturevalue(run)
        parser = SceneParser(resolve_run(tiny_run))
        assert parser.occupancy_floor == floor
        evaluated = json.loads((tiny_run / "r01_eval" / "objects_test.json").read_text())["objects"]
        files = load_index(tiny_dataset).files("test")
        recs = [load_scene(tiny_dataset / f) for f in files]
        boxes = []
        for f in files:
            b = np.array([o["box"] for o in evaluated if o["scene"] == f], np.float32).reshape(-1, 6)
            boxes.append((b, np.ones(len(b), np.float32)))
        parsed = parse_records(parser, recs, _dataset_views(tiny_dataset, "test"), batch_size=4, boxes=boxes)
        got = [(f, o) for f, p in zip(files, parsed) for o in p["objects"]]
        assert len(got) == len(evaluated) >= 2
        for (f, o), e in zip(got, evaluated):
            assert f == e["scene"] and np.allclose(o["box"], e["box"], atol=1e-5)
            assert (o["prototype"], o["angle_index"]) == (e["prototype"], e["angle_index"])
            assert o["similarity"] == pytest.approx(e["similarity"], abs=1e-4)
            assert o["yaw_deg"] == pytest.approx((-10.0 * e["angle_index"]) % 360)

    def test_refined_against_the_whole_scene(self, tiny_run: Path) -> None:
        """A ``refine_to: scene`` detector's parse refines its detections against the scene's pseudo-boxes fused over
        all its views (the renders' parameters here; two boxes on a flat floor, seen from 8 views), while an input-view
        detector gets no targets."""
        from dataclasses import asdict

        from analytic_scenes import render

        from threedq.boxes import aabb_iou_3d
        from threedq.datamodules.scene_folder import RENDER_PROPOSALS
        from threedq.proposals import propose_boxes

        parser = SceneParser(resolve_run(tiny_run), score_threshold=0.0)
        boxes = np.array([[-0.55, -0.35, 0.0, -0.15, 0.05, 0.3], [0.2, 0.1, 0.0, 0.5, 0.6, 0.2]])
        recs = [render(boxes, num_views=8)]
        assert scene_targets(parser, recs, sensor_captures=False) is None
        parser.detector.hparams.refine_to = "scene"
        targets = scene_targets(parser, recs, sensor_captures=False)
        fg = parser.detector.feature_grid
        want = propose_boxes(recs[0], bounds=(fg.bounds_min, fg.bounds_max), **asdict(RENDER_PROPOSALS))
        np.testing.assert_array_equal(targets[0][0], want[0])
        assert len(want[0]) == 2 and float(aabb_iou_3d(torch.from_numpy(want[0]).double(),
                                                       torch.from_numpy(boxes)).diagonal().min()) > 0.5
        seen = []
        detect = parser.detector.detect

        def recording(*args, **kwargs):  # the snapping itself: tests/test_box_refinement.py::TestSceneTargets
            seen.append(kwargs.get("targets"))
            return detect(*args, **kwargs)

        parser.detector.detect = recording
        parse_records(parser, recs, [[0]], targets=targets)
        parse_records(parser, recs, [[0]])
        assert len(seen) == 2 and seen[1] is None
        np.testing.assert_array_equal(seen[0][0][0], want[0])

    def test_yaw_convention(self, tiny_run: Path) -> None:
        """A prototype turned by -yaw[a] (the object the parse describes as 'R = 10 a') is found at index a."""
        parser = SceneParser(resolve_run(tiny_run))
        k = int(parser.bank.active.nonzero()[0])
        yaw = yaw_angles(parser.num_angles)
        for a in (0, 9, 18, 27):  # quarter turns are exact on the voxel grid
            turned = rotate_yaw(parser.bank.prototypes[k][None], -yaw[a][None])
            res = parser.bank.assign(turned)
            assert (int(res.prototype), int(res.angle)) == (k, a)

    def test_folder_with_bad_scenes(self, tmp_path: Path, tiny_run: Path, tiny_dataset: Path, capsys) -> None:
        scenes = tmp_path / "scenes"
        scenes.mkdir()
        files = load_index(tiny_dataset).files("test")
        for f in files:
            shutil.copy(tiny_dataset / f, scenes / Path(f).name)
        rec = load_scene(tiny_dataset / files[0])
        rec.depth[0, 3, 3] = np.nan
        save_scene(scenes / "nan_depth.npz", rec, validate=False)
        (scenes / "not_a_zip.npz").write_bytes(b"hello")
        out = tmp_path / "parsed"
        rc = main(["parse", "--run", str(tiny_run), "--scenes", str(scenes), "--out", str(out), "--score_threshold", "0",
                   "--progress", "false"])  # fmt: skip
        err = capsys.readouterr().err
        assert rc == 0
        summary = json.loads((out / "summary.json").read_text())
        assert (summary["scenes"], summary["parsed"], len(summary["failed"])) == (len(files) + 2, len(files), 2)
        bad = [line for line in err.splitlines() if line.startswith("threedq parse: skipped")]
        assert len(bad) == 2
        assert any("nan_depth.npz: field 'depth'" in line for line in bad)
        assert any("not_a_zip.npz: field" in line for line in bad)
        for f in files:
            doc = json.loads((out / f"{Path(f).stem}.json").read_text())
            assert (out / f"{Path(f).stem}.png").is_file() and doc["input_views"] == [0]
            assert doc["objects"], "threshold 0 keeps the top boxes"
            for o in doc["objects"]:
                assert set(o) >= {"box", "score", "prototype", "angle_index", "yaw_deg", "similarity", "name"}
                assert bool(parser_active(tiny_run)[o["prototype"]])

    def test_exception(self, tmp_path: Path, tiny_run: Path, tiny_dataset: Path) -> None:
        with pytest.raises(FileNotFoundError, match="scenes: no such file or folder"):
            run_parse(str(tmp_path / "none"), str(tmp_path / "o"), run=str(tiny_run))
        (tmp_path / "file").write_text("x")
        with pytest.raises(ValueError, match="out: .* not a folder"):
            run_parse(str(tiny_dataset), str(tmp_path / "file"), run=str(tiny_run))
        f = load_index(tiny_dataset).files("test")[0]
        summary = run_parse(str(tiny_dataset / f), str(tmp_path / "o"), run=str(tiny_run), views=[99], progress=False)
        assert summary["parsed"] == 0 and "field 'views'" in summary["failed"][0]
        assert find_scenes(tiny_dataset, "test")[1] == load_index(tiny_dataset).files("test")


    def test_default_views_are_the_banks(self, tmp_path: Path, tiny_run: Path, tiny_dataset: Path,
                                         monkeypatch: pytest.MonkeyPatch) -> None:
        """Without ``views``, a scene is read from as many views as the run's bank was fitted on, spread over its
        views: view 0 alone for the tiny run's one, 3 of the 4 views where the run's data read 3."""
        import json

        from threedq.pipeline import parse_command

        f = load_index(tiny_dataset).files("test")[0]
        def views(out: str) -> list[int]:
            run_parse(str(tiny_dataset / f), str(tmp_path / out), run=str(tiny_run), pictures=False, progress=False)
            doc = next(p for p in (tmp_path / out).glob("*.json") if p.name != "summary.json")
            return json.loads(doc.read_text())["input_views"]

        assert views("one") == [0]
        monkeypatch.setattr(parse_command, "_run_data_args", lambda run: {"num_input_views": 3})
        assert views("three") == [0, 2, 3]


def parser_active(run: Path) -> torch.Tensor:
    return SceneParser(resolve_run(run)).bank.active


class TestLabel:
    def test_propagate_names(self) -> None:
        # prototype 0: a x2, b x1 -> a (a conflict); 1: b; 2: a x1, c x1 -> a (tie: alphabetically first); 3: none
        out = propagate_names([0, 0, 0, 1, 2, 2], ["a", "a", "b", "b", "c", "a"], 4)
        assert out["names"] == {0: "a", 1: "b", 2: "a"}
        assert out["conflicts"] == {0: {"a": 2, "b": 1}, 2: {"c": 1, "a": 1}}

    def test_bad_labels(self, tmp_path: Path) -> None:
        p = tmp_path / "labels.yaml"
        for doc, field in ((["x"], "labels"), ({"labels": [{"scene": "a.npz", "name": "x"}]}, r"labels\[0\]"),
                           ({"labels": [{"scene": "a.npz", "name": "x", "box": [0, 0, 0, 1, 1]}]}, r"labels\[0\]"),
                           ({"labels": [{"scene": "a.npz", "name": "x", "box": [0, 0, 0, 1, 1, -1]}]}, r"labels\[0\]\.box"),
                           ({"labels": [{"scene": "a.npz", "name": "x", "object": -1}]}, r"labels\[0\]\.object")):  # fmt: skip
            p.write_text(yaml.safe_dump(doc))
            with pytest.raises(ValueError, match=rf"labels\.yaml: field '{field}"):
                load_labels(p)

    def test_label_then_parse_prints_names(self, tmp_path: Path, tiny_run: Path, tiny_dataset: Path, capsys) -> None:
        files = load_index(tiny_dataset).files("test")
        recs = {f: load_scene(tiny_dataset / f) for f in files}
        hull = lambda b: [b[0] - b[3] / 2, b[1] - b[4] / 2, b[2] - b[5] / 2, b[0] + b[3] / 2, b[1] + b[4] / 2,  # noqa: E731
                          b[2] + b[5] / 2]  # fmt: skip  (boxes are axis-aligned enough: the hull is only a label key)
        cats = load_index(tiny_dataset).categories
        items = [{"scene": f, "box": [float(x) for x in hull(b)], "name": cats[int(c)]}
                 for f in files for b, c in zip(recs[f].boxes, recs[f].categories)]  # fmt: skip
        labels = tmp_path / "labels.yaml"
        labels.write_text(yaml.safe_dump({"scenes": str(tiny_dataset), "labels": items}))
        assert main(["label", "--run", str(tiny_run), "--labels", str(labels)]) == 0
        out = capsys.readouterr().out
        assert f"{len(items)} object(s) named" in out and "unnamed" in out
        a = resolve_run(tiny_run)
        stored = json.loads(names_path(a.prototypes).read_text())
        assert stored["names"] and len(stored["objects"]) == len(items)
        names = load_names(a.prototypes, SceneParser(a).bank)
        # parse on the same boxes: every object named, with the name its prototype took
        box_file = tmp_path / "boxes.npz"
        save_boxes_file(box_file, {f: (np.array([it["box"] for it in items if it["scene"] == f], np.float32),
                                       np.ones(sum(it["scene"] == f for it in items), np.float32)) for f in files})  # fmt: skip
        summary = run_parse(str(tiny_dataset), str(tmp_path / "p"), run=str(tiny_run), split="test", boxes=str(box_file),
                            pictures=False, progress=False)  # fmt: skip
        assert summary["named_prototypes"] == len(names)
        for f in files:
            doc = json.loads((tmp_path / "p" / f"{Path(f).with_suffix('').as_posix().replace('/', '_')}.json").read_text())
            assert doc["objects"] and all(o["name"] == names[o["prototype"]] for o in doc["objects"])
        # names of another bank are refused
        other = json.loads(names_path(a.prototypes).read_text())
        other["bank"] = "0" * 16
        names_path(a.prototypes).write_text(json.dumps(other))
        with pytest.raises(ValueError, match="another prototype bank"):
            load_names(a.prototypes, SceneParser(a).bank)
        names_path(a.prototypes).unlink()


class TestRenders:
    def test_orbit_poses(self) -> None:
        pose = np.eye(4)
        pose[:3, 3] = [2.0, 0.0, 1.0]
        out = orbit_poses(pose, (0.0, 0.0), [0.0, 90.0, 180.0])
        np.testing.assert_allclose(out[:, :3, 3], [[2, 0, 1], [0, 2, 1], [-2, 0, 1]], atol=1e-6)
        np.testing.assert_allclose(out[1, :3, :3] @ out[1, :3, :3].T, np.eye(3), atol=1e-6)
        # about another centre: the centre stays where it is
        np.testing.assert_allclose(orbit_poses(pose, (2.0, 0.0), [90.0])[0, :3, 3], [2, 0, 1], atol=1e-6)

    def test_gallery_and_replaced(self, tmp_path: Path, tiny_run: Path, tiny_dataset: Path) -> None:
        f = load_index(tiny_dataset).files("test")[0]
        out = tmp_path / "r"
        s = run_parse(str(tiny_dataset / f), str(out), run=str(tiny_run), renders=True, score_threshold=0.0,
                      progress=False)  # fmt: skip
        assert s["parsed"] == 1
        import cv2

        g = cv2.imread(str(out / "gallery.png"))
        r = cv2.imread(str(out / f"{Path(f).stem}_replaced.png"))
        assert g is not None and g.shape[0] > 100 and r is not None and r.shape[1] > 3 * r.shape[0] - 10

    def test_no_objects_changes_nothing(self, tiny_run: Path, tiny_dataset: Path) -> None:
        a = resolve_run(tiny_run)
        parser, decoder = SceneParser(a), load_view_decoder(a.viewpred)
        rec = load_scene(tiny_dataset / load_index(tiny_dataset).files("test")[0])
        res = parse_records(parser, [rec], [[0]])[0]
        empty = replaced_render(parser, decoder, rec, {"objects": []}, res["_features"], 1)
        w = (empty.shape[1] - 6) // 3
        # decoded == replaced (below the panels' captions)
        assert np.array_equal(empty[16:, w + 3 : 2 * w + 3], empty[16:, 2 * w + 6 :])
        assert math.isfinite(float(empty.mean()))


class TestImportThenParse:
    def test_tum_folder_end_to_end(self, tmp_path: Path, tiny_run: Path, tiny_dataset: Path, capsys) -> None:
        """A tilted, shifted TUM capture: ``threedq data import`` then ``threedq parse``; boxes map back to the capture."""
        from capture_writers import write_objects, write_tum
        from test_formats_import import tilt

        from threedq.boxes import boxes_to_aabb

        f = load_index(tiny_dataset).files("test")[0]
        rec = load_scene(tiny_dataset / f)
        c_T_w = tilt()
        src = tmp_path / "rgbd_dataset_desk"
        write_tum(src, rec, capture_T_world=c_T_w)
        write_objects(src, rec, c_T_w)
        K = rec.K[0]
        data = tmp_path / "desk"
        assert main(["data", "import", "--format", "tum", str(src), "--out", str(data), "--split", "test",
                     "--intrinsics", str([float(x) for x in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])])]) == 0  # fmt: skip
        imported = load_scene(data / "test" / "rgbd_dataset_desk.npz")
        out = tmp_path / "parsed"
        assert main(["parse", "--run", str(tiny_run), "--scenes", str(data), "--out", str(out), "--score_threshold", "0",
                     "--progress", "false"]) == 0  # fmt: skip
        doc = json.loads((out / "test_rgbd_dataset_desk.json").read_text())
        assert doc["objects"] and all("capture_T_box" in o for o in doc["objects"])
        # on the imported GT boxes: each object's box centre, mapped to the capture frame, is where it was captured
        boxes = tmp_path / "gt.npz"
        save_boxes_file(boxes, {"test/rgbd_dataset_desk.npz": (boxes_to_aabb(imported.boxes.astype(np.float64)).astype(np.float32),
                                                               np.ones(imported.num_objects, np.float32))})  # fmt: skip
        assert main(["parse", "--run", str(tiny_run), "--scenes", str(data), "--out", str(tmp_path / "gt"), "--boxes",
                     str(boxes), "--progress", "false"]) == 0  # fmt: skip
        doc = json.loads((tmp_path / "gt" / "test_rgbd_dataset_desk.json").read_text())
        got = np.array([np.array(o["capture_T_box"])[:3, 3] for o in doc["objects"]])
        want = (c_T_w[:3, :3] @ rec.boxes[:, :3].astype(np.float64).T).T + c_T_w[:3, 3]
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, atol=0.02)


def test_parse_reads_captures_as_the_run_read_its_data(tmp_path: Path) -> None:
    """``threedq parse`` reads scenes as the run's data was read (its final quantizer's saved config): the poses
    corrected by the floor where they were sensor captures, and as many input views as its bank was fitted on."""
    from threedq.pipeline.parse_command import _run_data_args

    run = tmp_path / "run"
    assert _run_data_args(None) == {} and _run_data_args(run) == {}
    for r, sensor in ((1, "false"), (2, "true")):
        (run / f"r0{r}_quantizer").mkdir(parents=True)
        (run / f"r0{r}_quantizer" / "config.yaml").write_text(
            f"data:\n  class_path: x\n  init_args:\n    sensor_captures: {sensor}\n    num_input_views: {r + 1}\n")
    assert _run_data_args(run) == {"sensor_captures": True, "num_input_views": 3}  # the last round's
    (run / "r02_quantizer" / "config.yaml").write_text("data:\n  init_args:\n    data_dir: d\n")
    assert _run_data_args(run) == {"data_dir": "d"}


class TestSpreadViews:
    def test_hand_computed(self) -> None:
        from threedq.pipeline.parse_command import spread_views

        assert spread_views(28, 1) == [0]
        assert spread_views(28, 3) == [0, 14, 27]  # 13.5 rounds to 14 (half to even)
        assert spread_views(9, 3) == [0, 4, 8]
        assert spread_views(10, 4) == [0, 3, 6, 9]
        assert spread_views(2, 3) == [0, 1]  # a scene with fewer views gives all of them

    def test_distinct_and_in_range(self) -> None:
        from threedq.pipeline.parse_command import spread_views

        for v in range(1, 40):
            for n in range(1, 6):
                got = spread_views(v, n)
                assert len(got) == min(v, n) and len(set(got)) == len(got) and 0 <= min(got) and max(got) < v


class TestView:
    """``threedq view`` of a run ``threedq em`` wrote, and ``threedq parse --view``."""

    def test_recording_of_the_run(self, tmp_path: Path, tiny_run: Path, tiny_dataset: Path) -> None:
        pytest.importorskip("rerun")
        from test_view import _read_back

        from threedq.pipeline.view import run_view

        counts = run_view(str(tiny_run), save=str(tmp_path / "run.rrd"), progress=False)
        got = _read_back(tmp_path / "run.rrd")
        for r in (0, 1):
            objects = json.loads((tiny_run / f"r{r:02d}_eval" / "objects_test.json").read_text())["objects"]
            assert counts["boxes"][r] == len(objects)
            for f in load_index(tiny_dataset).files("test"):
                mine = [o for o in objects if o["scene"] == f]
                rows = [row for rr_, row in got.get(f"/scenes/{Path(f).stem}/detections", []) if rr_ == r]
                labels = rows[0]["Boxes3D:labels"] if rows and "Boxes3D:labels" in rows[0] else []
                assert sorted(labels) == sorted(f"p{o['prototype']:02d} 1.00" for o in mine)

    def test_parse_then_view(self, tmp_path: Path, tiny_run: Path, tiny_dataset: Path, monkeypatch) -> None:
        from threedq.pipeline import view

        calls = []
        monkeypatch.setattr(view, "run_view", lambda run, **kw: calls.append(run))
        f = load_index(tiny_dataset).files("test")[0]
        run_parse(str(tiny_dataset / f), str(tmp_path / "p"), run=str(tiny_run), pictures=False, view=True,
                  progress=False)
        assert calls == [str(tmp_path / "p")]


def test_yaw_confidence(tmp_path: Path, tiny_run: Path, tiny_dataset: Path) -> None:
    """Each parsed object carries a yaw_confidence, >= 0 (its yaw is the argmax of the search at its prototype);
    the margin excludes the yaws within 30 degrees (3 steps of 36) of the chosen one."""
    from threedq.pipeline.parse import yaw_margin_steps
    from threedq.quantization import yaw_margin

    f = load_index(tiny_dataset).files("test")[0]
    summary = run_parse(str(tiny_dataset / f), str(tmp_path / "p"), run=str(tiny_run), pictures=False,
                        score_threshold=0.0, progress=False)
    doc = json.loads((tmp_path / "p" / summary["files"][0]["json"]).read_text())
    conf = [o["yaw_confidence"] for o in doc["objects"]]
    assert conf and all(c >= 0 for c in conf)
    assert yaw_margin_steps(36) == 3 and yaw_margin_steps(12) == 1
    scores = torch.tensor([[0.2] * 36])
    scores[0, 5], scores[0, 20] = 0.9, 0.5
    assert math.isclose(float(yaw_margin(scores, torch.tensor([5]), yaw_margin_steps(36))[0]), 0.4, abs_tol=1e-6)
