"""The capture parsers: each reads back a generated scene written in its format, with the format's quirks.

Per parser: a smoke test, a corrupt-input test (one bad file is skipped and named, the rest is read) and a
round trip against the original generated record (depth within the format's quantisation, poses within
1e-5, intrinsics exact after the documented resize).
"""

from __future__ import annotations

import numpy as np
import pytest
from capture_writers import (
    upsample2,
    write_bigbird,
    write_nerfstudio,
    write_open3d,
    write_replica,
    write_rig,
    write_scannet,
    write_tum,
)

from threedq.data.formats import FORMATS
from threedq.data.formats.bigbird import read_bigbird, register_depth
from threedq.data.formats.capture import Capture, resize_to
from threedq.data.formats.nerfstudio import read_nerfstudio
from threedq.data.formats.open3d import read_open3d
from threedq.data.formats.replica import read_replica
from threedq.data.formats.rig import decode_carla_depth, read_rig
from threedq.data.formats.scannet import read_scannet
from threedq.data.formats.tum import read_tum
from threedq.scene import SceneRecord, SceneValidationError


def assert_round_trip(
    cap: Capture,
    rec: SceneRecord,
    views: list[int],
    depth_step: float,
    rgb_tol: float = 0.0,
    K: np.ndarray | None = None,
    depth_range: float = np.inf,
) -> None:
    """The capture's views ``views`` of the record: depth within half a unit (where the format can hold it:
    below ``depth_range``), poses 1e-5, K exact, mean colour error at most ``rgb_tol`` (JPEG)."""
    assert cap.num_views == len(views)
    inside = rec.depth[views] < depth_range
    assert inside.mean() > 0.9
    np.testing.assert_allclose(cap.depth[inside], rec.depth[views][inside], atol=depth_step / 2 + 1e-6, rtol=0)
    np.testing.assert_allclose(cap.world_T_cam, rec.world_T_cam[views].astype(np.float64), atol=1e-5, rtol=0)
    np.testing.assert_array_equal(
        cap.K, (rec.K[views] if K is None else np.broadcast_to(K, cap.K.shape)).astype(np.float64)
    )
    diff = np.abs(cap.rgb.astype(np.int16) - rec.rgb[views].astype(np.int16))
    assert diff.mean() <= rgb_tol, diff.mean()


def test_every_format_is_registered() -> None:
    assert sorted(FORMATS) == ["bigbird", "nerfstudio", "open3d", "replica", "rig", "scannet", "tum"]


class TestTum:
    def test_smoke(self, turntable, tmp_path) -> None:
        write_tum(tmp_path, turntable)
        K = turntable.K[0]
        cap = read_tum(tmp_path, intrinsics=(K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        assert cap.rgb.shape == turntable.rgb.shape and cap.format == "tum" and not cap.skipped

    def test_exception(self, turntable, tmp_path) -> None:
        write_tum(tmp_path, turntable, drop_pose=2)  # a missing groundtruth line
        K = turntable.K[0]
        cap = read_tum(tmp_path, intrinsics=(K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        assert cap.num_views == 5 and len(cap.skipped) == 1
        assert "groundtruth.txt" in str(cap.skipped[0]) and "'pose'" in str(cap.skipped[0])
        with pytest.raises(SceneValidationError, match="intrinsics"):
            read_tum(tmp_path)  # no freiburg1|2|3 in the folder name and no intrinsics given

    def test_feature_round_trip(self, turntable, tmp_path) -> None:
        # depth 10 ms after colour, mocap 5 ms before, decoy mocap lines 250 ms away: nearest within 20 ms
        write_tum(tmp_path, turntable)
        K = turntable.K[0]
        cap = read_tum(tmp_path, intrinsics=(K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        assert_round_trip(cap, turntable, list(range(6)), 1 / 5000)
        with pytest.raises(SceneValidationError, match="no usable frame"):
            read_tum(tmp_path, intrinsics=(1, 1, 0, 0), max_dt=0.001)  # every association fails

    def test_sensor_intrinsics_from_the_folder_name(self, turntable, tmp_path) -> None:
        seq = tmp_path / "rgbd_dataset_freiburg2_desk"
        write_tum(seq, turntable)
        np.testing.assert_array_equal(read_tum(seq).K[0], [[520.9, 0, 325.1], [0, 521.0, 249.7], [0, 0, 1]])


class TestScanNet:
    def test_smoke(self, turntable, tmp_path) -> None:
        write_scannet(tmp_path, turntable)
        cap = read_scannet(tmp_path)
        assert cap.rgb.shape == turntable.rgb.shape and cap.frame_ids == ["0", "5", "10", "15", "20", "25"]

    def test_exception(self, turntable, tmp_path) -> None:
        ids = write_scannet(tmp_path, turntable, bad_pose=1)  # a -inf pose, as SensReader writes
        jpg = tmp_path / "color" / f"{ids[3]}.jpg"
        jpg.write_bytes(jpg.read_bytes()[: jpg.stat().st_size // 2])  # a truncated colour image
        cap = read_scannet(tmp_path)
        assert cap.num_views == 4 and len(cap.skipped) == 2
        lines = sorted(str(s) for s in cap.skipped)
        assert any(f"color/{ids[3]}.jpg" in ln and "'rgb'" in ln for ln in lines)
        assert any(f"pose/{ids[1]}.txt" in ln and "'pose'" in ln and "inf" in ln for ln in lines)
        assert_round_trip(cap, turntable, [0, 2, 4, 5], 1e-3, rgb_tol=2.0)

    def test_feature_round_trip(self, turntable, tmp_path) -> None:
        # colour at twice the depth size: views come out on the depth grid with K = intrinsic_depth exactly
        write_scannet(tmp_path, turntable)
        cap = read_scannet(tmp_path)
        assert_round_trip(cap, turntable, list(range(6)), 1e-3, rgb_tol=2.0)

    def test_resize_intrinsics(self) -> None:
        # hand-computed: halving a 4x4 image, pixel centres at integers: u' = (u + 0.5) / 2 - 0.5
        K = np.array([[10.0, 0, 1.5], [0, 20.0, 1.5], [0, 0, 1]])
        img, K2 = resize_to(np.zeros((4, 4, 3), np.uint8), K, (2, 2))
        assert img.shape == (2, 2, 3)
        np.testing.assert_allclose(K2, [[5.0, 0, 0.5], [0, 10.0, 0.5], [0, 0, 1]])
        big, Kb = upsample2(np.zeros((2, 2, 3), np.uint8), K2)
        np.testing.assert_allclose(resize_to(big, Kb, (2, 2))[1], K2)


class TestNerfstudio:
    def test_smoke(self, turntable, tmp_path) -> None:
        write_nerfstudio(tmp_path, turntable)
        cap = read_nerfstudio(tmp_path)
        assert cap.rgb.shape == turntable.rgb.shape and cap.frame_ids[0] == "images/frame_00001.png"

    def test_exception(self, turntable, tmp_path) -> None:
        write_nerfstudio(tmp_path, turntable, non_rigid=4)
        cap = read_nerfstudio(tmp_path)
        assert cap.num_views == 5 and len(cap.skipped) == 1
        line = str(cap.skipped[0])
        assert "transforms.json: frames[4]" in line and "'transform_matrix'" in line and "not rigid" in line
        with pytest.raises(SceneValidationError, match="transforms.json"):
            read_nerfstudio(tmp_path / "nowhere")

    def test_feature_round_trip(self, turntable, tmp_path) -> None:
        # OpenGL camera axes, COLMAP pixel centres, per-frame intrinsics on odd frames, depth in 0.2 mm units
        write_nerfstudio(tmp_path, turntable, scale=2e-4)
        cap = read_nerfstudio(tmp_path)
        assert_round_trip(cap, turntable, list(range(6)), 2e-4)


class TestReplica:
    def test_smoke(self, turntable, tmp_path) -> None:
        write_replica(tmp_path / "room0", turntable)
        cap = read_replica(tmp_path / "room0")
        assert cap.rgb.shape == turntable.rgb.shape and cap.frame_ids[-1] == "000005"

    def test_exception(self, turntable, tmp_path) -> None:
        write_replica(tmp_path / "room0", turntable, drop_last_line=True)  # traj.txt one line short
        cap = read_replica(tmp_path / "room0")
        assert cap.num_views == 5 and len(cap.skipped) == 1
        assert "traj.txt:6" in str(cap.skipped[0]) and "'pose'" in str(cap.skipped[0])

    def test_feature_round_trip(self, turntable, tmp_path) -> None:
        write_replica(tmp_path / "room0", turntable)
        cap = read_replica(tmp_path / "room0")
        assert_round_trip(cap, turntable, list(range(6)), 1 / 6553.5, rgb_tol=2.0)

    def test_nice_slam_constants_without_cam_params(self, turntable, tmp_path) -> None:
        write_replica(tmp_path / "room0", turntable)
        (tmp_path / "cam_params.json").unlink()
        np.testing.assert_array_equal(
            read_replica(tmp_path / "room0").K[0], [[600, 0, 599.5], [0, 600, 339.5], [0, 0, 1]]
        )


class TestBigBird:
    def test_smoke(self, turntable, tmp_path) -> None:
        write_bigbird(tmp_path, turntable)
        cap = read_bigbird(tmp_path)
        assert cap.rgb.shape == turntable.rgb.shape
        assert cap.frame_ids == ["NP1_0", "NP1_120", "NP1_240", "NP5_0", "NP5_120", "NP5_240"]

    def test_exception(self, turntable, tmp_path) -> None:
        write_bigbird(tmp_path, turntable, corrupt_h5="NP5_120.h5")  # a truncated depth file
        cap = read_bigbird(tmp_path)
        assert cap.num_views == 5 and len(cap.skipped) == 1
        assert "NP5_120.h5" in str(cap.skipped[0]) and "'depth'" in str(cap.skipped[0])

    def test_feature_round_trip(self, turntable, tmp_path) -> None:
        # poses composed from the turntable pose and the calibration; colour 2x the depth size, resized
        write_bigbird(tmp_path, turntable)
        cap = read_bigbird(tmp_path)
        # 16-bit depth in 100 um units holds at most 6.5535 m: farther floor pixels are saturated by the writer
        assert_round_trip(cap, turntable, list(range(6)), 1e-4, rgb_tol=2.0, depth_range=6.5)

    def test_register_depth_across_a_baseline(self) -> None:
        # hand-computed: a fronto-parallel plane at 2 m seen by an IR camera 0.1 m to the right of the colour
        # camera: the colour camera sees it at 2 m too, shifted by fx * b / z = 40 * 0.1 / 2 = 2 px
        K = np.array([[40.0, 0, 7.5], [0, 40.0, 5.5], [0, 0, 1]])
        rgb_T_ir = np.eye(4)
        rgb_T_ir[0, 3] = 0.1
        out = register_depth(np.full((12, 16), 2.0, np.float32), K, rgb_T_ir, K, (12, 16))
        np.testing.assert_array_equal(out[:, 2:], 2.0)
        np.testing.assert_array_equal(out[:, :2], 0.0)  # nothing lands on the 2 columns the IR camera cannot see


class TestOpen3d:
    def test_smoke(self, turntable, tmp_path) -> None:
        write_open3d(tmp_path, turntable)
        cap = read_open3d(tmp_path)
        assert cap.rgb.shape == turntable.rgb.shape and cap.frame_ids[0] == "000000"

    def test_exception(self, turntable, tmp_path) -> None:
        write_open3d(tmp_path, turntable, bad_depth_size=3)
        cap = read_open3d(tmp_path)
        assert cap.num_views == 5 and len(cap.skipped) == 1
        assert "depth/000003.png" in str(cap.skipped[0]) and "'depth'" in str(cap.skipped[0])
        png = tmp_path / "depth" / "000001.png"
        png.write_bytes(png.read_bytes()[: png.stat().st_size // 2])  # a truncated 16-bit PNG
        cap = read_open3d(tmp_path)
        assert cap.num_views == 4 and any("depth/000001.png: field 'depth': truncated" in str(s) for s in cap.skipped)

    def test_feature_round_trip(self, turntable, tmp_path) -> None:
        # the intrinsic matrix is stored column-major; depth in millimetres
        write_open3d(tmp_path, turntable)
        assert_round_trip(read_open3d(tmp_path), turntable, list(range(6)), 1e-3)

    def test_only_the_kept_views_are_read(self, turntable, tmp_path) -> None:
        # max_views=2 keeps view 0 and the camera farthest from it; the other images are never decoded
        write_open3d(tmp_path, turntable)
        centres = turntable.world_T_cam[:, :3, 3].astype(np.float64)
        far = int(np.argmax(np.linalg.norm(centres - centres[0], axis=1)))
        for v in set(range(6)) - {0, far}:
            (tmp_path / "color" / f"{v:06d}.png").write_bytes(b"not an image")
        cap = read_open3d(tmp_path, max_views=2)
        assert cap.frame_ids == [f"{v:06d}" for v in sorted({0, far})] and not cap.skipped and cap.num_frames == 6
        # a corrupt chosen image is skipped and counted, and the next farthest readable view is read instead
        write_open3d(tmp_path / "b", turntable)
        (tmp_path / "b" / "color" / f"{far:06d}.png").write_bytes(b"not an image")
        cap = read_open3d(tmp_path / "b", max_views=2)
        assert cap.num_views == 2 and f"{far:06d}" not in cap.frame_ids and len(cap.skipped) == 1


class TestRig:
    def test_smoke(self, turntable, tmp_path) -> None:
        write_rig(tmp_path, turntable)
        cap = read_rig(tmp_path)
        assert cap.rgb.shape == turntable.rgb.shape and cap.frame_ids[3] == "cam_01/000000"

    def test_exception(self, turntable, tmp_path) -> None:
        write_rig(tmp_path, turntable, drop_capture=1)  # no rig pose for capture 1
        cap = read_rig(tmp_path)
        assert cap.num_views == 4 and len(cap.skipped) == 2
        assert all("rig.yaml" in str(s) and "'captures.1'" in str(s) for s in cap.skipped)

    def test_feature_round_trip(self, turntable, tmp_path) -> None:
        # world_T_cam = world_T_rig @ rig_T_cam; CARLA's RGB-encoded depth (1000 m / (2^24 - 1) per step)
        write_rig(tmp_path, turntable)
        assert_round_trip(read_rig(tmp_path), turntable, list(range(6)), 1000 / (256**3 - 1))

    def test_carla_depth_hand_computed(self) -> None:
        px = np.array([[[255, 255, 255], [0, 0, 0], [1, 0, 0], [0, 1, 0]]], np.uint8)
        np.testing.assert_allclose(
            decode_carla_depth(px)[0], [1000.0, 0.0, 1000 / (2**24 - 1), 256000 / (2**24 - 1)], rtol=1e-6
        )
