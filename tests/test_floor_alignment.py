"""threedq.geometry.floor_alignment: poses corrected by the floor the views see, against analytic scenes with known
pose errors (a view turned about its camera centre, the whole world tilted by a known angle)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from analytic_scenes import render
from threedq.geometry.floor_alignment import align_to_floor

BOXES = np.array([[-0.3, -0.2, 0.0, -0.05, 0.1, 0.25], [0.15, -0.1, 0.0, 0.4, 0.2, 0.15]])


def _floor_of_view(depth: np.ndarray, K: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane ``z = a x + b y + c`` of a view's points below 1 cm (its floor) -> (unit normal, height at
    the view's floor centroid)."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
    p = cam @ T[:3, :3].T + T[:3, 3]
    p = p[np.abs(p[:, 2] - np.median(p[:, 2])) < 0.03] if p.size else p
    A = np.c_[p[:, 0], p[:, 1], np.ones(len(p))]
    a, b, c = np.linalg.lstsq(A, p[:, 2], rcond=None)[0]
    n = np.array([-a, -b, 1.0]) / math.hypot(a, b, 1.0)
    return n, float(A.mean(0) @ [a, b, c])


def _turn_about_camera(T: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """A tracker's orientation error: the camera turned about its own centre (in the camera frame)."""
    E = np.eye(4)
    E[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    return T @ E


@pytest.fixture(scope="module")
def scene():
    return render(BOXES, num_views=8)


class TestAlignToFloor:
    def test_smoke(self, scene) -> None:
        out = align_to_floor(scene.depth, scene.K, scene.world_T_cam)
        assert out.world_T_cam.shape == (8, 4, 4) and out.world_T_cam.dtype == scene.world_T_cam.dtype

    def test_exception(self, scene) -> None:
        with pytest.raises(ValueError, match="world_T_cam"):
            align_to_floor(scene.depth, scene.K, scene.world_T_cam[:3])
        with pytest.raises(ValueError, match="depth"):
            align_to_floor(scene.depth[0], scene.K, scene.world_T_cam)

    def test_exact_poses_are_left_bit_for_bit(self, scene) -> None:
        out = align_to_floor(scene.depth, scene.K, scene.world_T_cam)
        assert not out.applied and np.array_equal(out.world_T_cam, scene.world_T_cam)

    def test_no_depth_no_change(self, scene) -> None:
        out = align_to_floor(np.zeros_like(scene.depth), scene.K, scene.world_T_cam)
        assert not out.applied and np.array_equal(out.world_T_cam, scene.world_T_cam)

    @pytest.mark.parametrize("deg", [0.7, 1.5, -2.5])
    def test_a_turned_view_gets_its_floor_back(self, scene, deg: float) -> None:
        """View 3 turned by a known angle about its camera's x axis: its floor leaves z = 0 by centimetres; after the
        alignment it is level and at z = 0 again (the other views untouched), and the view's pose is the true one up
        to a turn about the vertical, which the floor cannot see."""
        poses = scene.world_T_cam.astype(np.float64).copy()
        poses[3] = _turn_about_camera(poses[3], np.array([math.radians(deg), 0.0, 0.0]))
        n0, h0 = _floor_of_view(scene.depth[3], scene.K[3], poses[3])
        assert math.degrees(math.acos(n0[2])) > 0.5 * abs(deg) and abs(h0) > 0.01  # the error is visible
        out = align_to_floor(scene.depth, scene.K, poses)
        n1, h1 = _floor_of_view(scene.depth[3], scene.K[3], out.world_T_cam[3])
        assert math.degrees(math.acos(n1[2])) < 0.05 and abs(h1) < 0.002
        assert out.applied and abs(out.view_angle_deg[3] - abs(deg)) < 0.2 * abs(deg)
        others = [i for i in range(8) if i != 3]
        assert np.allclose(out.world_T_cam[others], poses[others], atol=1e-6)
        # the corrected camera: the true camera up to a rotation about the world vertical through its centre
        true, fixed = scene.world_T_cam[3].astype(np.float64), out.world_T_cam[3]
        assert np.linalg.norm(fixed[:3, 3] - true[:3, 3]) < 0.002
        rel = Rotation.from_matrix(fixed[:3, :3] @ true[:3, :3].T).as_rotvec()
        assert np.linalg.norm(rel[:2]) < math.radians(0.05)

    def test_a_tilted_world_is_levelled(self, scene) -> None:
        """Every pose tilted by 2 degrees about a horizontal axis through the origin (a tracker's gravity error): the
        floor comes back level at z = 0 in every view, the views stay consistent (one rigid motion for all)."""
        G = np.eye(4)
        G[:3, :3] = Rotation.from_rotvec(np.array([math.cos(1.0), math.sin(1.0), 0.0]) * math.radians(2.0)).as_matrix()
        poses = G @ scene.world_T_cam.astype(np.float64)
        out = align_to_floor(scene.depth, scene.K, poses)
        assert out.applied and abs(out.scene_tilt_deg - 2.0) < 0.05
        for v in range(8):
            n, h = _floor_of_view(scene.depth[v], scene.K[v], out.world_T_cam[v])
            assert math.degrees(math.acos(n[2])) < 0.05 and abs(h) < 0.002
        motion = out.world_T_cam @ np.linalg.inv(poses)  # one rigid motion for every view
        assert np.allclose(motion, motion[0], atol=1e-6)
        assert np.abs(out.view_angle_deg).max() < 0.05 or not np.any(out.view_angle_deg)
