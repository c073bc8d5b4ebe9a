"""Scene normalisation (z up, centred), ``threedq data import``, the format DataModules and ``threedq data index``."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from capture_writers import (
    write_objects,
    write_open3d,
    write_replica,
    write_tum,
)
from scipy.spatial.transform import Rotation
from threedq.datamodules.bigbird import BigBirdDataModule
from threedq.datamodules.rig import CameraRigDataModule
from threedq.datamodules.capture_folder import CaptureDataModule
from threedq.datamodules.open3d import KinectOpen3dDataModule
from threedq.datamodules.nerfstudio import NerfstudioDataModule
from threedq.datamodules.replica import ReplicaDataModule
from threedq.datamodules.scannet import ScanNetDataModule
from threedq.datamodules.scene_folder import SceneFolderDataModule
from threedq.datamodules.tum import TumRGBDDataModule

from threedq.cli import main
from threedq.data.folder_index import index_folder
from threedq.data.formats import FORMATS, Capture, import_captures
from threedq.data.formats.normalise import (
    boxes_to_capture_frame,
    farthest_views,
    normalise_capture,
    rotation_between,
)
from threedq.scene import SceneValidationError, load_index, load_scene, save_scene

ROOT = Path(__file__).resolve().parents[1]


def tilt() -> np.ndarray:
    """capture_T_world: the scene tilted ~19 deg, turned 40 deg and shifted by (2.5, -1.2, 0.8) m."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [40, 15, -12], degrees=True).as_matrix()
    T[:3, 3] = [2.5, -1.2, 0.8]
    return T


class TestNormalise:
    def test_smoke(self, turntable) -> None:
        cap = Capture(
            turntable.rgb,
            turntable.depth,
            turntable.K.astype(np.float64),
            turntable.world_T_cam.astype(np.float64),
            [str(i) for i in range(6)],
            "mem",
            "test",
        )
        rec = normalise_capture(cap, max_views=4)
        assert rec.num_views == 4 and rec.num_objects == 0 and rec.meta["unannotated"]
        assert np.asarray(rec.meta["canonical_T_capture"]).shape == (4, 4)

    def test_exception(self, turntable) -> None:
        cap = Capture(
            turntable.rgb,
            np.zeros_like(turntable.depth),
            turntable.K.astype(np.float64),
            turntable.world_T_cam.astype(np.float64),
            [str(i) for i in range(6)],
            "somewhere",
            "test",
        )
        with pytest.raises(SceneValidationError, match="somewhere: field 'depth': no support plane"):
            normalise_capture(cap)

    def test_farthest_views_hand_computed(self) -> None:
        c = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [10, 0, 0]], float)
        assert farthest_views(c, 2).tolist() == [0, 3]
        assert farthest_views(c, 3).tolist() == [0, 2, 3]
        assert farthest_views(c, 9).tolist() == [0, 1, 2, 3]

    def test_rotation_between(self) -> None:
        for a in ([0.2, -0.5, 0.8], [0, 0, -1.0], [1.0, 0, 0]):
            R = rotation_between(np.array(a), np.array([0, 0, 1.0]))
            np.testing.assert_allclose(R @ (np.array(a) / np.linalg.norm(a)), [0, 0, 1], atol=1e-12)
            np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
            assert np.linalg.det(R) == pytest.approx(1.0)

    def test_depth_beyond_max_range_becomes_zero(self, turntable) -> None:
        cap = Capture(
            turntable.rgb,
            turntable.depth,
            turntable.K.astype(np.float64),
            turntable.world_T_cam.astype(np.float64),
            [str(i) for i in range(6)],
            "mem",
            "test",
        )
        rec = normalise_capture(cap, max_depth=5.0)
        far = turntable.depth > 5.0
        assert far.any() and np.all(rec.depth[far] == 0)
        np.testing.assert_array_equal(rec.depth[~far], turntable.depth[~far])

    @pytest.mark.parametrize("fmt", ["open3d", "tum"])
    def test_feature_tilted_off_centre_capture(self, turntable, tmp_path, fmt) -> None:
        c_T_w = tilt()
        src = tmp_path / "desk"
        K = turntable.K[0]
        if fmt == "open3d":
            write_open3d(src, turntable, capture_T_world=c_T_w)
            options = {}
        else:
            write_tum(src, turntable, capture_T_world=c_T_w)
            options = {"intrinsics": (K[0, 0], K[1, 1], K[0, 2], K[1, 2])}
        write_objects(src, turntable, c_T_w)
        summary = import_captures(fmt, src, tmp_path / "out", reader_options=options, progress=False)
        assert summary.scenes == [("train/desk.npz", 6, 6)] and not summary.skipped
        rec = load_scene(tmp_path / "out" / "train" / "desk.npz")
        n_T_c = np.asarray(rec.meta["canonical_T_capture"])
        n_T_w = n_T_c @ c_T_w  # original world -> canonical: must be a yaw + a horizontal shift
        assert math.degrees(math.acos(min(1.0, n_T_w[2, 2]))) < 1.0  # z up
        assert abs(n_T_w[2, 3]) < 0.01  # the original ground z = 0 is the canonical z = 0
        yaw = math.atan2(n_T_w[1, 0], n_T_w[0, 0])
        orig = turntable.boxes.astype(np.float64)
        centres = (n_T_w[:3, :3] @ orig[:, :3].T).T + n_T_w[:3, 3]
        np.testing.assert_allclose(rec.boxes[:, :3], centres, atol=0.02)
        np.testing.assert_allclose(rec.boxes[:, 3:6], orig[:, 3:6], atol=1e-6)
        dyaw = (rec.boxes[:, 6] - orig[:, 6] - yaw + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(np.degrees(dyaw)).max() < 1.0
        np.testing.assert_allclose(rec.boxes[:, 2] - rec.boxes[:, 5] / 2, 0.0, atol=0.02)  # they stand on z = 0
        lo, hi = rec.boxes[:, :2].min(0), rec.boxes[:, :2].max(0)
        assert np.abs((lo + hi) / 2).max() < 0.2  # centred on what stands on the plane
        # the boxes sit on the objects in every image: projected centres agree with the original views
        for v in range(rec.num_views):

            def proj(pose, K, p):
                q = np.linalg.inv(pose.astype(np.float64)) @ np.append(p, 1.0)
                return (K.astype(np.float64) @ q[:3])[:2] / q[2]

            for m in range(rec.num_objects):
                np.testing.assert_allclose(
                    proj(rec.world_T_cam[v], rec.K[v], rec.boxes[m, :3].astype(np.float64)),
                    proj(turntable.world_T_cam[v], turntable.K[v], orig[m, :3]),
                    atol=0.05,
                )
        # and they map back to the capture's own frame
        capture_T_box, size = boxes_to_capture_frame(rec.boxes, n_T_c)
        np.testing.assert_allclose(capture_T_box[:, :3, 3], (c_T_w[:3, :3] @ orig[:, :3].T).T + c_T_w[:3, 3], atol=1e-4)
        np.testing.assert_allclose(size, orig[:, 3:6], atol=1e-6)
        index = load_index(tmp_path / "out")
        assert index.categories == sorted(index.categories, key=lambda c: index.categories.index(c))
        assert sorted(index.categories) == sorted({f"cat{int(c)}" for c in turntable.categories})
        assert main(["data", "check", str(tmp_path / "out")]) == 0  # boxes inside the chosen bounds


class TestImport:
    def test_smoke_cli(self, turntable, tmp_path, capsys) -> None:
        src = tmp_path / "Replica"
        for name in ("room0", "room1"):
            write_replica(src / name, turntable, drop_last_line=name == "room1")
            write_objects(src / name, turntable, np.eye(4))
        out = tmp_path / "out"
        assert (
            main(
                [
                    "data",
                    "import",
                    "--format",
                    "replica",
                    str(src),
                    "--out",
                    str(out),
                    "--max_views",
                    "4",
                    "--progress",
                    "false",
                ]
            )
            == 0
        )
        text = capsys.readouterr().out
        assert re.search(r"skipped: .*room1/traj.txt:6: field 'pose'", text)
        assert "imported 2 scene(s), 8 views; 1 frame(s) skipped (pose 1)" in text
        assert "train/room1.npz: 4 views kept of 5 posed frames" in text
        assert main(["data", "check", str(out)]) == 0
        dm = SceneFolderDataModule(str(out), batch_size=2, num_input_views=2, num_target_views=1)
        batch = next(iter(dm.train_dataloader()))
        assert batch["rgb"].shape == (2, 3, 3, 36, 48) and batch["box_mask"].sum() == 2 * turntable.num_objects

    def test_exception(self, turntable, tmp_path, capsys) -> None:
        with pytest.raises(SceneValidationError, match="no replica capture: expected traj.txt"):
            import_captures("replica", tmp_path, tmp_path / "out", progress=False)
        with pytest.raises(ValueError, match="'max_dt' does not apply to format 'replica'"):
            write_replica(tmp_path / "room0", turntable)
            import_captures("replica", tmp_path / "room0", tmp_path / "out", reader_options={"max_dt": 0.1})
        assert (
            main(
                [
                    "data",
                    "import",
                    "--format",
                    "replica",
                    str(tmp_path / "room0"),
                    "--out",
                    str(tmp_path / "o"),
                    "--max_dt",
                    "0.1",
                    "--progress",
                    "false",
                ]
            )
            == 2
        )
        # a capture with no usable frame fails alone; the others are imported
        write_replica(tmp_path / "all" / "good", turntable)
        write_replica(tmp_path / "all" / "bad", turntable)
        (tmp_path / "all" / "bad" / "traj.txt").write_text("")
        summary = import_captures("replica", tmp_path / "all", tmp_path / "out2", progress=False)
        assert [s[0] for s in summary.scenes] == ["train/good.npz"]
        assert len(summary.failed) == 1 and "bad" in summary.failed[0] and "no usable frame" in summary.failed[0]

    def test_feature_unannotated_capture_trains(self, turntable, tmp_path) -> None:
        # no threedq_objects.json: a scene without boxes, usable for view prediction
        write_replica(tmp_path / "room0", turntable)
        dm = ReplicaDataModule(
            capture_dirs={"train": str(tmp_path / "room0")},
            data_dir=str(tmp_path / "out"),
            max_views=5,
            num_input_views=2,
            num_target_views=2,
            batch_size=1,
        )
        dm.setup("fit")
        batch = next(iter(dm.train_dataloader()))
        assert batch["rgb"].shape == (1, 4, 3, 36, 48) and not batch["box_mask"].any()
        rec = load_scene(tmp_path / "out" / "train" / "room0.npz")
        assert rec.num_views == 5 and rec.meta["unannotated"] and rec.meta["source_format"] == "replica"

    @pytest.mark.parametrize(
        "cls",
        [
            TumRGBDDataModule,
            ScanNetDataModule,
            NerfstudioDataModule,
            ReplicaDataModule,
            BigBirdDataModule,
            KinectOpen3dDataModule,
            CameraRigDataModule,
        ],
    )
    def test_one_datamodule_per_format(self, cls) -> None:
        assert issubclass(cls, CaptureDataModule) and cls.FORMAT in FORMATS


class TestFolderIndex:
    def test_feature_index_of_a_folder(self, turntable, tmp_path, capsys) -> None:
        save_scene(tmp_path / "train" / "a.npz", turntable)
        save_scene(tmp_path / "test" / "b.npz", turntable)
        (tmp_path / "train" / "broken.npz").write_bytes(b"PK\x03\x04 not really")
        assert main(["data", "index", str(tmp_path)]) == 0
        out = capsys.readouterr().out
        assert "broken.npz: field '<file>'" in out and "2 scenes (train 1, val 0, test 1)" in out
        index = load_index(tmp_path)
        assert index.files("train") == ["train/a.npz"] and index.files("test") == ["test/b.npz"]
        n = int(turntable.categories.max()) + 1
        assert index.categories == [f"category_{i}" for i in range(n)] and index.symmetry_order == [1] * n
        assert "broken" not in json.dumps(index.scenes)  # left out of the index
        assert main(["data", "check", str(tmp_path)]) == 0  # bounds from the data hold every box

    def test_exception(self, turntable, tmp_path) -> None:
        save_scene(tmp_path / "a.npz", turntable)
        with pytest.raises(SceneValidationError, match="'categories'"):
            index_folder(tmp_path, categories=["only_one"] if turntable.categories.max() > 0 else [])
        with pytest.raises(SceneValidationError, match="no valid scene"):
            index_folder(tmp_path / "empty")

    def test_readme_example_index_loads(self, turntable, tmp_path) -> None:
        # the index.json example of the "Real captures" section (docs/data.md) is a valid hand-written index
        readme = (ROOT / "docs" / "data.md").read_text(encoding="utf-8")
        section = readme.split("## Real captures", 1)[1].split("\n## ", 1)[0]
        example = json.loads(re.search(r"```json\n(.*?)```", section, re.DOTALL).group(1))
        (tmp_path / "index.json").write_text(json.dumps(example))
        index = load_index(tmp_path)
        assert index.files() and len(index.symmetry_order) == len(index.categories)
        documented = set(re.findall(r"^\| `(\w+)` \|", section, re.MULTILINE))
        assert set(example) <= documented and {"format", "version", "scene_bounds", "symmetry_order"} <= documented
