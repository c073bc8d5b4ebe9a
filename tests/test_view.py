"""threedq view: the fused point cloud, members turned into their prototype's pose, and the recording read back
with Rerun's own reader against the run files it came from."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from threedq.boxes import boxes_to_aabb
from threedq.errors import InputError
from threedq.geometry.point_cloud import fuse_views, points_in_aabb, voxel_downsample
from threedq.pipeline.view import aligned_member_points, read_run, run_view, template_voxels
from threedq.scene import load_index, load_scene


class TestVoxelDownsample:
    def test_smoke(self):
        p, c = voxel_downsample(np.zeros((3, 3)), np.zeros((3, 3), np.uint8), 0.1)
        assert p.shape == (1, 3) and c.shape == (1, 3) and c.dtype == np.uint8

    def test_exception(self):
        with pytest.raises(ValueError, match="voxel_size"):
            voxel_downsample(np.zeros((3, 3)), np.zeros((3, 3), np.uint8), 0.0)
        with pytest.raises(ValueError, match="colours"):
            voxel_downsample(np.zeros((3, 3)), np.zeros((2, 3), np.uint8), 0.1)

    def test_empty(self):
        p, c = voxel_downsample(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), 0.1)
        assert p.shape == (0, 3) and c.shape == (0, 3)

    def test_against_naive_loop(self):
        rng = np.random.default_rng(0)
        pts = rng.uniform(-1, 1, (500, 3))
        cols = rng.integers(0, 256, (500, 3)).astype(np.uint8)
        cells: dict[tuple[int, ...], list[int]] = {}
        for i, q in enumerate(pts):
            cells.setdefault(tuple(math.floor(x / 0.25) for x in q), []).append(i)
        want = {k: (pts[v].mean(0), cols[v].astype(float).mean(0)) for k, v in cells.items()}
        p, c = voxel_downsample(pts, cols, 0.25)
        assert len(p) == len(want)
        for q, col in zip(p, c):
            k = tuple(math.floor(x / 0.25) for x in q)
            np.testing.assert_allclose(q, want[k][0], atol=1e-5)
            np.testing.assert_allclose(col, np.rint(want[k][1]), atol=0)


    def test_far_apart_points(self):
        """Points too far apart for one integer key per cell take the row-wise path, with the same result."""
        pts = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [1e7, 1e7, 1e7], [-1e7, 0.0, 5.0]])
        p, c = voxel_downsample(pts, np.array([[0, 0, 0], [10, 10, 10], [1, 2, 3], [4, 5, 6]], np.uint8), 0.02)
        np.testing.assert_allclose(p, [[-1e7, 0.0, 5.0], [0.005, 0.0, 0.0], [1e7, 1e7, 1e7]], rtol=1e-6)
        assert c.tolist() == [[4, 5, 6], [5, 5, 5], [1, 2, 3]]


class TestFuseViews:
    def _plane(self, depth_value: float = 2.0):
        h, w = 8, 10
        K = np.array([[[10.0, 0, 4.5], [0, 10.0, 3.5], [0, 0, 1]]], np.float32)
        depth = np.full((1, h, w), depth_value, np.float32)
        rgb = np.full((1, h, w, 3), 200, np.uint8)
        return rgb, depth, K, np.eye(4, dtype=np.float32)[None]

    def test_hand_computed_plane(self):
        rgb, depth, K, T = self._plane()
        p, c = fuse_views(rgb, depth, K, T, voxel_size=0.001)
        assert p.shape == (80, 3)  # every pixel its own voxel (0.2 m apart at 2 m)
        np.testing.assert_allclose(p[:, 2], 2.0, atol=1e-6)
        np.testing.assert_allclose(sorted(set(np.round(p[:, 0], 4))), (np.arange(10) - 4.5) * 0.2, atol=1e-4)
        assert (c == 200).all()

    def test_invalid_depth_left_out(self):
        rgb, depth, K, T = self._plane()
        depth[0, 0, :] = 0
        depth[0, 1, :] = np.nan
        depth[0, 2, :3] = np.inf
        assert fuse_views(rgb, depth, K, T, voxel_size=0.001)[0].shape == (80 - 23, 3)

    def test_pose_moves_points(self):
        rgb, depth, K, T = self._plane()
        T2 = T.copy()
        T2[0, :3, 3] = [1.0, -2.0, 0.5]
        a, _ = fuse_views(rgb, depth, K, T, voxel_size=0.001)
        b, _ = fuse_views(rgb, depth, K, T2, voxel_size=0.001)
        np.testing.assert_allclose(np.sort(b - [1.0, -2.0, 0.5], 0), np.sort(a, 0), atol=1e-5)

    def test_max_points_seeded(self):
        rgb, depth, K, T = self._plane()
        a = fuse_views(rgb, depth, K, T, voxel_size=0.001, max_points=20, seed=3)[0]
        b = fuse_views(rgb, depth, K, T, voxel_size=0.001, max_points=20, seed=3)[0]
        assert a.shape == (20, 3) and np.array_equal(a, b)
        with pytest.raises(ValueError, match="max_points"):
            fuse_views(rgb, depth, K, T, max_points=0)


class TestMembers:
    def test_points_in_aabb(self):
        pts = np.array([[0, 0, 0], [1, 1, 1], [2, 0, 0]], float)
        assert points_in_aabb(pts, [0, 0, 0, 1, 1, 1]).tolist() == [True, True, False]

    def test_rotated_copy_aligns(self):
        """An L-shaped object and a copy turned by -70 deg: turning the copy by 7 yaw steps (70 deg) counter-
        clockwise puts it onto the original."""
        rng = np.random.default_rng(1)
        arm1 = np.c_[rng.uniform(0, 0.3, 200), rng.uniform(0, 0.05, 200), rng.uniform(0.02, 0.2, 200)]
        arm2 = np.c_[rng.uniform(0, 0.05, 100), rng.uniform(0, 0.15, 100), rng.uniform(0.02, 0.2, 100)]
        obj = np.r_[arm1, arm2] - [0.15, 0.07, 0]
        t = math.radians(-70)
        rot = np.array([[math.cos(t), -math.sin(t), 0], [math.sin(t), math.cos(t), 0], [0, 0, 1]])
        copy = obj @ rot.T + [2.0, 1.0, 0.0]
        box_a = np.r_[obj.min(0) - 0.001, obj.max(0) + 0.001]
        box_a[2] = 0.0
        box_b = np.r_[copy.min(0) - 0.001, copy.max(0) + 0.001]
        box_b[2] = 0.0
        a = aligned_member_points(obj, box_a, 0, 36)
        b = aligned_member_points(copy, box_b, 7, 36)
        centre_a = np.array([(box_a[0] + box_a[3]) / 2, (box_a[1] + box_a[4]) / 2, 0])
        centre_b = np.array([(box_b[0] + box_b[3]) / 2, (box_b[1] + box_b[4]) / 2, 0])
        # the same points up to the two boxes' centres (each box is the hull of its own, turned, points)
        shift = (centre_b - [2.0, 1.0, 0.0]) @ np.linalg.inv(rot).T - centre_a
        np.testing.assert_allclose(b, a - shift * [1, 1, 0], atol=1e-5)
        wrong = aligned_member_points(copy, box_b, 3, 36)
        assert np.abs(wrong - (a - shift * [1, 1, 0])).max() > 0.05

    def test_template_is_the_majority(self):
        one = np.array([[0.01, 0.01, 0.01], [0.04, 0.01, 0.01]])
        two = np.array([[0.01, 0.01, 0.01]])
        three = np.array([[0.10, 0.10, 0.10]])
        t = template_voxels([one, two, three], voxel=0.03)
        np.testing.assert_allclose(t, [[0.015, 0.015, 0.015]], atol=1e-6)  # 2 of 3 members; the others 1 of 3
        assert len(template_voxels([one], voxel=0.03)) == 2


# ---------------------------------------------------------------------------------------------- the recording
rr = pytest.importorskip("rerun")


def _fake_run(tmp: Path, data: Path) -> tuple[Path, dict]:
    """A run folder with rounds 0 and 1 as ``threedq em`` writes them (evaluations, boxes files, metrics), its
    boxes the test scenes' GT boxes with made-up scores, prototypes and yaw indices."""
    run = tmp / "run"
    index = load_index(data)
    files = index.files("test")
    truth: dict = {}
    for r, det in ((0, "03_detector_eval"), (1, "r01_detector_eval")):
        (run / det).mkdir(parents=True)
        aabbs, counts, scores, objects = [], [], [], []
        truth[r] = {}
        for i, f in enumerate(files):
            aabb = boxes_to_aabb(load_scene(data / f).boxes).astype(np.float32)
            sc = np.linspace(0.99, 0.9, len(aabb)).astype(np.float32)
            aabbs.append(aabb), counts.append(len(aabb)), scores.append(sc)
            rows = []
            for n, b in enumerate(aabb[:-1] if len(aabb) > 1 else aabb):  # the last box of a scene goes unassigned
                k, a = (3 * i + n + r) % 5, (5 * n + 11 * r + i) % 36
                objects.append({"scene": f, "box": [round(float(x), 6) for x in b], "prototype": k,
                                "angle_index": a, "similarity": 0.9})
                rows.append((k, a))
            truth[r][f] = {"boxes": len(aabb), "assigned": rows, "scores": sc}
        np.savez(run / det / "detections_test.npz", format="threedq-boxes", params="x", scenes=np.array(files),
                 counts=np.array(counts), aabb=np.concatenate(aabbs), scores=np.concatenate(scores))
        ev = run / f"r{r:02d}_eval"
        ev.mkdir()
        (ev / "config.yaml").write_text(yaml.safe_dump({"data": {"init_args": {
            "data_dir": str(data), "boxes": f"runs/em/{det}/detections_{{split}}.npz"}}}))
        (ev / "objects_test.json").write_text(json.dumps({"num_angles": 36, "objects": objects}))
    table3 = [{"round": r, "k": 10, "pool": 9, "map_50": 0.5 + r / 10, "hungarian_acc": 0.4 + r / 20} for r in (0, 1)]
    (run / "metrics.json").write_text(json.dumps({"table3": table3}))
    return run, truth


def _read_back(path: Path) -> dict[str, list[tuple[int | None, dict]]]:
    """Entity path -> (round or None for static, {column: value}) rows, through Rerun's own reader."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream():
        table = chunk.to_record_batch().to_pydict()
        for i in range(chunk.num_rows):
            row = {k: v[i] for k, v in table.items()}
            out.setdefault(chunk.entity_path, []).append((row.get("round"), row))
    return out


class TestRecording:
    def test_run_read_back(self, tiny_dataset, tmp_path):
        run, truth = _fake_run(tmp_path, tiny_dataset)
        counts = run_view(str(run), save=str(tmp_path / "run.rrd"), progress=False)
        assert (tmp_path / "run.rrd").is_file() and not (tmp_path / "run.rrd.partial").exists()
        got = _read_back(tmp_path / "run.rrd")
        files = load_index(tiny_dataset).files("test")
        assert counts["scenes"] == len(files)
        for f in files:
            name = Path(f).stem
            assert f"/scenes/{name}/points" in got and f"/scenes/{name}/cameras" in got
            gt = got[f"/scenes/{name}/ground_truth"]
            assert len(gt[0][1]["Boxes3D:centers"]) == len(load_scene(tiny_dataset / f).boxes)
            dets = {r: row for r, row in got[f"/scenes/{name}/detections"]}
            arrows = {r: row for r, row in got[f"/scenes/{name}/yaw"]}
            for r in (0, 1):
                want = truth[r][f]
                labels = dets[r]["Boxes3D:labels"]
                assert len(labels) == want["boxes"]
                for n, (k, a) in enumerate(want["assigned"]):
                    assert labels[n] == f"p{k:02d} {want['scores'][n]:.2f}"
                    v = arrows[r]["Arrows3D:vectors"][n]
                    assert math.isclose(math.degrees(math.atan2(v[1], v[0])) % 360, (-10 * a) % 360, abs_tol=1e-3)
                assert len(arrows[r]["Arrows3D:vectors"]) == len(want["assigned"])
                if want["boxes"] > len(want["assigned"]):
                    assert labels[-1] == f"{want['scores'][-1]:.2f}"  # no prototype: the score alone
        for r in (0, 1):
            members = {(k) for f in files for k, _ in truth[r][f]["assigned"]}
            for k in members:
                rows = [row for rr_, row in got[f"/prototypes/p{k:02d}/template"] if rr_ == r]
                assert rows and rows[0]["Points3D:labels"][0].startswith(f"p{k:02d}: ")
        metric = {r: row["Scalars:scalars"][0] for r, row in got["/metrics/map_50"]}
        assert metric == pytest.approx({0: 0.5, 1: 0.6})
        assert "/metrics/round" not in got and "/metrics/k" not in got

    def test_max_scenes_and_points(self, tiny_dataset, tmp_path):
        run, _ = _fake_run(tmp_path, tiny_dataset)
        counts = run_view(str(run), save=str(tmp_path / "a.rrd"), max_scenes=1, points_per_scene=50, progress=False)
        got = _read_back(tmp_path / "a.rrd")
        pts = [row["Points3D:positions"] for e, rows in got.items() if e.endswith("/points") for _, row in rows]
        assert counts["scenes"] == 1 and len(pts) == 1 and len(pts[0]) <= 50

    def test_parse_folder(self, tiny_dataset, tmp_path):
        f = load_index(tiny_dataset).files("test")[0]
        aabb = boxes_to_aabb(load_scene(tiny_dataset / f).boxes)
        objs = [{"box": b.tolist(), "score": 0.95, "prototype": 2, "angle_index": 9, "name": "mug"} for b in aabb]
        out = tmp_path / "parse"
        out.mkdir()
        (out / "scene.json").write_text(json.dumps({"scene": str(tiny_dataset / f), "objects": objs}))
        (out / "summary.json").write_text(json.dumps({"files": [{"json": "scene.json"}]}))
        run_view(str(out), save=str(tmp_path / "p.rrd"), progress=False)
        got = _read_back(tmp_path / "p.rrd")
        (r, row), = got[f"/scenes/{Path(f).stem}/detections"]
        assert r == 0 and row["Boxes3D:labels"] == ["mug (p02) 0.95"] * len(aabb)

    def test_bad_inputs(self, tiny_dataset, tmp_path):
        with pytest.raises(InputError, match="is not a folder"):
            run_view(str(tmp_path / "nothing"), save=str(tmp_path / "x.rrd"))
        (tmp_path / "empty_run" / "00_viewpred").mkdir(parents=True)
        with pytest.raises(InputError, match="no finished round"):
            run_view(str(tmp_path / "empty_run"), save=str(tmp_path / "x.rrd"))
        run, _ = _fake_run(tmp_path, tiny_dataset)
        with pytest.raises(InputError, match="give one of them"):
            run_view(str(run), save=str(tmp_path / "x.rrd"), serve=True)
        with pytest.raises(InputError, match="holds no index.json"):
            read_run(run, data_dir=tmp_path)
        (run / "r01_eval" / "objects_test.json").write_text("{not json")
        with pytest.raises(InputError, match="r01_eval/objects_test.json: not valid JSON"):
            run_view(str(run), save=str(tmp_path / "x.rrd"))
        assert not (tmp_path / "x.rrd").exists()

    def test_no_display(self, tiny_dataset, tmp_path, monkeypatch):
        """Without a display the native viewer cannot start: one line naming the alternatives, nothing spawned."""
        run, _ = _fake_run(tmp_path, tiny_dataset)
        monkeypatch.delenv("DISPLAY", raising=False)
        monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
        monkeypatch.setattr("sys.platform", "linux")
        with pytest.raises(InputError, match="no display .* --save run.rrd, or serve the web viewer with --serve true"):
            run_view(str(run))

    def test_command_line(self, tiny_dataset, tmp_path, capsys):
        from threedq.cli import main

        run, _ = _fake_run(tmp_path, tiny_dataset)
        assert main(["view", "--run", str(run), "--save", str(tmp_path / "c.rrd"), "--progress", "false"]) == 0
        assert "threedq view: 2 scene(s)" in capsys.readouterr().out
        assert main(["view", "--run", str(tmp_path / "missing"), "--save", str(tmp_path / "d.rrd")]) == 2
        assert "is not a folder" in capsys.readouterr().err
