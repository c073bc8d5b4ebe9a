"""The capture conditions of :mod:`threedq.data.sensor`: one class per function (smoke, bad arguments, shapes, a
feature checked against a hand-computed reference, determinism, level 0 = identity), then the generator's use."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from threedq.data import GeneratorConfig, generate_dataset
from threedq.data.sensor import (
    EFFECTS,
    apply_capture,
    axial_noise,
    drop_depth,
    exposure,
    pose_drift,
    quantise_disparity,
    tilt_gravity,
)
from threedq.scene import SceneRecord, load_scene, validate_scene

BAD_LEVELS = [-0.1, math.nan, math.inf, True, "1"]


def rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def ring_poses(n: int = 40, radius: float = 3.0, height: float = 1.5) -> np.ndarray:
    """``[n, 4, 4]`` camera-to-world poses on a circle, looking at the origin (OpenCV axes, world z up)."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i, a in enumerate(np.linspace(0, 2 * math.pi, n, endpoint=False)):
        centre = np.array([radius * math.cos(a), radius * math.sin(a), height])
        z = -centre / np.linalg.norm(centre)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        poses[i, :3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
        poses[i, :3, 3] = centre
    return poses


def angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angles ``[...]`` of rotation matrices ``[..., 3, 3]``, degrees."""
    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


def assert_rigid(poses: np.ndarray) -> None:
    R = poses[:, :3, :3].astype(np.float64)
    np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(R), 1, atol=1e-6)
    np.testing.assert_array_equal(poses[:, 3], np.tile([0, 0, 0, 1], (len(poses), 1)))


def sigma(z: float) -> float:
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


class TestAxialNoise:
    def test_smoke(self):
        out = axial_noise(np.full((2, 8, 8), 1.0, np.float32), rng(), 1.0)
        assert out.dtype == np.float32 and np.all(out > 0)

    @pytest.mark.parametrize("level", BAD_LEVELS)
    def test_bad_level(self, level):
        with pytest.raises(ValueError, match="level"):
            axial_noise(np.ones((4, 4)), rng(), level)

    @pytest.mark.parametrize("depth", [np.ones(5), np.ones((4, 4), np.int32)])
    def test_bad_depth(self, depth):
        with pytest.raises(ValueError, match="depth"):
            axial_noise(depth, rng(), 1.0)

    @pytest.mark.parametrize("shape", [(7, 9), (3, 7, 9)])
    def test_shapes(self, shape):
        assert axial_noise(np.ones(shape), rng(), 1.0).shape == shape

    @pytest.mark.parametrize("level", [1.0, 2.0])
    def test_std_on_a_flat_plane_and_zero_stays_zero(self, level):
        depth = np.full((400, 400), 1.5)
        depth[:10] = 0
        out = axial_noise(depth, rng(), level)
        assert np.all(out[:10] == 0)
        assert np.std(out[10:] - 1.5) == pytest.approx(level * sigma(1.5), rel=0.1)
        assert abs(np.mean(out[10:] - 1.5)) < 0.1 * sigma(1.5)

    def test_deterministic_identity_and_input_kept(self):
        depth = np.linspace(0.5, 4, 64).reshape(8, 8)
        before = depth.copy()
        np.testing.assert_array_equal(axial_noise(depth, rng(3), 1), axial_noise(depth, rng(3), 1))
        np.testing.assert_array_equal(axial_noise(depth, rng(3), 0), depth)
        np.testing.assert_array_equal(depth, before)


class TestQuantiseDisparity:
    def test_smoke(self):
        assert quantise_disparity(np.full((4, 4), 2.0, np.float32), 1.0).dtype == np.float32

    @pytest.mark.parametrize("level", BAD_LEVELS)
    def test_bad_level(self, level):
        with pytest.raises(ValueError, match="level"):
            quantise_disparity(np.ones((4, 4)), level)

    def test_bad_depth(self):
        with pytest.raises(ValueError, match="depth"):
            quantise_disparity(np.ones((2, 2, 2), np.uint16), 1.0)

    @pytest.mark.parametrize("shape", [(7, 9), (2, 3, 7, 9)])
    def test_shapes(self, shape):
        assert quantise_disparity(np.ones(shape), 1.0).shape == shape

    @pytest.mark.parametrize("level", [1.0, 2.0])
    @pytest.mark.parametrize("z0", [1.0, 3.0])
    def test_step_is_the_formula(self, z0, level):
        step = level * 2.85e-3 * z0**2
        depth = np.linspace(z0 - 6 * step, z0 + 6 * step, 40001).reshape(1, -1)
        values = np.unique(quantise_disparity(depth, level))
        values = values[np.abs(values - z0) < 4 * step]
        steps, mid = np.diff(values), (values[1:] + values[:-1]) / 2
        assert len(steps) >= 6
        np.testing.assert_allclose(steps, level * 2.85e-3 * mid**2, rtol=0.01)  # the step at the depth it is at
        assert np.median(steps) == pytest.approx(step, rel=0.05)
        out = quantise_disparity(depth, level)  # disparity off by at most half a step: |1/out - 1/z| <= q / 2
        assert np.all(np.abs(out - depth) <= 0.5 * level * 2.85e-3 * out * depth * (1 + 1e-9))

    def test_zero_stays_zero_deterministic_identity(self):
        depth = np.array([[0.0, 1.2], [2.5, 0.0]])
        out = quantise_disparity(depth, 1.0)
        assert out[0, 0] == 0 and out[1, 1] == 0 and out[0, 1] > 0
        np.testing.assert_array_equal(out, quantise_disparity(depth, 1.0))
        np.testing.assert_array_equal(quantise_disparity(depth, 0), depth)


def step_image(views: int = 8, size: int = 256) -> np.ndarray:
    """``[views, size, size]``: 1 m on the left half, 2 m on the right half, no depth in the top 16 rows."""
    depth = np.ones((views, size, size))
    depth[:, :, size // 2:] = 2.0
    depth[:, :16] = 0
    return depth


class TestDropDepth:
    def test_smoke(self):
        out = drop_depth(np.full((2, 16, 16), 1.0, np.float32), rng(), 1.0)
        assert out.dtype == np.float32 and set(np.unique(out)) <= {0.0, 1.0}

    @pytest.mark.parametrize("level", BAD_LEVELS)
    def test_bad_level(self, level):
        with pytest.raises(ValueError, match="level"):
            drop_depth(np.ones((4, 4)), rng(), level)

    def test_bad_depth(self):
        with pytest.raises(ValueError, match="depth"):
            drop_depth(np.ones(4), rng(), 1.0)

    @pytest.mark.parametrize("shape", [(7, 9), (3, 7, 9)])
    def test_shapes(self, shape):
        assert drop_depth(np.ones(shape), rng(), 1.0).shape == shape

    @pytest.mark.parametrize("level", [1.0, 1.5])
    def test_half_of_the_edge_and_two_percent_elsewhere_in_clusters(self, level):
        depth = step_image()
        out = drop_depth(depth, rng(1), level)
        dropped = (out == 0) & (depth > 0)
        assert np.all(out[depth == 0] == 0)
        np.testing.assert_array_equal(out[~dropped], depth[~dropped])
        edge = np.zeros(depth.shape, bool)
        edge[:, 16:, 127:129] = True
        assert dropped[edge].mean() == pytest.approx(0.5 * level, abs=0.08)
        other = ~edge & (depth > 0)
        other[:, 16] = other[:, -1] = other[:, :, 0] = other[:, :, -1] = False  # no jump test at the border
        assert dropped[other].mean() == pytest.approx(0.02 * level, rel=0.25)
        # clusters, not salt: a dropped pixel's right neighbour is dropped far more often than 2%
        assert dropped[:, 20:, 1:120][dropped[:, 20:, :119]].mean() > 0.3

    def test_a_slanted_plane_has_no_edge(self):
        u = np.arange(256)
        depth = np.tile(1 / (0.2 + 0.004 * u), (8, 256, 1))  # a plane: disparity linear in u, 5 m .. 0.8 m
        assert np.abs(np.diff(depth, axis=-1)).max() > 0.05
        assert (drop_depth(depth, rng(2), 1.0) == 0).mean() == pytest.approx(0.02, rel=0.25)

    def test_deterministic_and_identity(self):
        depth = step_image(2, 32)
        np.testing.assert_array_equal(drop_depth(depth, rng(5), 1), drop_depth(depth, rng(5), 1))
        np.testing.assert_array_equal(drop_depth(depth, rng(5), 0), depth)


class TestExposure:
    def test_smoke(self):
        out = exposure(np.full((2, 8, 8, 3), 100, np.uint8), rng(), 1.0)
        assert out.dtype == np.uint8

    @pytest.mark.parametrize("level", BAD_LEVELS)
    def test_bad_level(self, level):
        with pytest.raises(ValueError, match="level"):
            exposure(np.zeros((1, 4, 4, 3), np.uint8), rng(), level)

    @pytest.mark.parametrize("rgb", [np.zeros((4, 4, 3), np.uint8), np.zeros((1, 4, 4, 4), np.uint8),
                                     np.zeros((1, 4, 4, 3), np.int32)])
    def test_bad_rgb(self, rgb):
        with pytest.raises(ValueError, match="rgb"):
            exposure(rgb, rng(), 1.0)

    @pytest.mark.parametrize("dtype", [np.uint8, np.float32])
    def test_shapes_dtype_and_range(self, dtype):
        rgb = np.full((3, 5, 7, 3), 250 if dtype == np.uint8 else 0.98, dtype)
        out = exposure(rgb, rng(), 2.0)
        assert out.shape == rgb.shape and out.dtype == dtype
        assert out.min() >= 0 and out.max() <= (255 if dtype == np.uint8 else 1.0)

    @pytest.mark.parametrize("level", [1.0, 2.0])
    def test_gains_within_the_bounds(self, level):
        rgb = np.full((50, 32, 32, 3), 0.4)
        gains = exposure(rgb, rng(4), level).mean(axis=(1, 2)) / 0.4  # [V, 3]
        low, high = (1 - 0.2 * level) * (1 - 0.15 * level), (1 + 0.2 * level) * (1 + 0.15 * level)
        assert gains.min() >= low - 0.01 and gains.max() <= high + 0.01
        assert gains.std() > 0.05 * level  # they do vary, per view and per channel
        assert np.std(gains[:, 0] / gains[:, 1]) > 0.03 * level  # white balance: the channels differ

    def test_deterministic_and_identity(self):
        rgb = rng(0).integers(0, 256, (2, 6, 6, 3), dtype=np.uint8)
        np.testing.assert_array_equal(exposure(rgb, rng(7), 1), exposure(rgb, rng(7), 1))
        np.testing.assert_array_equal(exposure(rgb, rng(7), 0), rgb)


def rotation_errors(poses: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``[V, 3, 3]``: each camera's rotation error ``R^T R'``."""
    return np.swapaxes(poses[:, :3, :3], 1, 2) @ out[:, :3, :3]


class TestPoseDrift:
    def test_smoke(self):
        assert pose_drift(ring_poses(5).astype(np.float32), rng(), 1.0).dtype == np.float32

    @pytest.mark.parametrize("level", BAD_LEVELS)
    def test_bad_level(self, level):
        with pytest.raises(ValueError, match="level"):
            pose_drift(ring_poses(3), rng(), level)

    @pytest.mark.parametrize("poses", [np.eye(4), np.zeros((2, 3, 4)), np.zeros((2, 4, 4), np.int64)])
    def test_bad_poses(self, poses):
        with pytest.raises(ValueError, match="poses"):
            pose_drift(poses, rng(), 1.0)

    @pytest.mark.parametrize("n", [1, 2, 40])
    def test_shapes_and_rigid(self, n):
        out = pose_drift(ring_poses(n), rng(), 2.0)
        assert out.shape == (n, 4, 4)
        assert_rigid(out)

    @pytest.mark.parametrize("level", [1.0, 2.0])
    def test_size_of_the_errors(self, level):
        poses = ring_poses(40)
        outs = [pose_drift(poses, rng(s), level) for s in range(50)]
        angles = np.concatenate([angle_deg(rotation_errors(poses, o)) for o in outs])
        shifts = np.concatenate([np.linalg.norm(o[:, :3, 3] - poses[:, :3, 3], axis=1) for o in outs])
        assert np.sqrt(np.mean(angles**2)) == pytest.approx(level, rel=0.2)
        assert np.sqrt(np.mean(shifts**2)) == pytest.approx(0.01 * level, rel=0.2)

    def test_neighbouring_views_more_alike_than_distant_ones(self):
        poses = ring_poses(40)
        near, far = [], []
        for s in range(30):
            E = rotation_errors(poses, pose_drift(poses, rng(s), 1.0))
            near.append(angle_deg(np.swapaxes(E[:-1], 1, 2) @ E[1:]).mean())
            far.append(angle_deg(np.swapaxes(E[:-20], 1, 2) @ E[20:]).mean())
        assert np.mean(near) < 0.5 * np.mean(far)

    def test_deterministic_and_identity(self):
        poses = ring_poses(6)
        np.testing.assert_array_equal(pose_drift(poses, rng(1), 1), pose_drift(poses, rng(1), 1))
        np.testing.assert_array_equal(pose_drift(poses, rng(1), 0), poses)


class TestTiltGravity:
    def test_smoke(self):
        assert tilt_gravity(ring_poses(3), rng(), 1.0).shape == (3, 4, 4)

    @pytest.mark.parametrize("level", BAD_LEVELS)
    def test_bad_level(self, level):
        with pytest.raises(ValueError, match="level"):
            tilt_gravity(ring_poses(3), rng(), level)

    def test_bad_poses(self):
        with pytest.raises(ValueError, match="poses"):
            tilt_gravity(np.zeros((3, 4)), rng(), 1.0)

    @pytest.mark.parametrize("n", [1, 7])
    def test_shapes_and_rigid(self, n):
        out = tilt_gravity(ring_poses(n), rng(), 3.0)
        assert out.shape == (n, 4, 4)
        assert_rigid(out)

    @pytest.mark.parametrize("level", [0.5, 1.0, 2.0])
    @pytest.mark.parametrize("seed", [0, 1])
    def test_a_horizontal_plane_tilts_by_the_angle(self, level, seed):
        poses = ring_poses(5)
        out = tilt_gravity(poses, rng(seed), level)
        floor = np.c_[rng(9).uniform(-2, 2, (100, 2)), np.zeros(100), np.ones(100)]  # world points, z = 0
        for v in range(5):  # seen by camera v, unprojected with the tilted pose
            seen = (out[v] @ np.linalg.inv(poses[v]) @ floor.T).T[:, :3]
            normal = np.linalg.svd(seen - seen.mean(0))[2][2]
            assert math.degrees(math.acos(abs(normal[2]))) == pytest.approx(2.0 * level, abs=1e-6)
        # one rotation for the whole scene, about a horizontal axis through the origin
        G = out @ np.linalg.inv(poses)
        np.testing.assert_allclose(G, np.broadcast_to(G[0], G.shape), atol=1e-9)
        axis = np.cross([0, 0, 1], G[0, :3, 2])
        np.testing.assert_allclose(G[0, :3, :3] @ axis, axis, atol=1e-9)
        np.testing.assert_allclose(G[0, :3, 3], 0, atol=1e-12)

    def test_deterministic_and_identity(self):
        poses = ring_poses(4)
        np.testing.assert_array_equal(tilt_gravity(poses, rng(2), 1), tilt_gravity(poses, rng(2), 1))
        np.testing.assert_array_equal(tilt_gravity(poses, rng(2), 0), poses)


def small_record() -> SceneRecord:
    V, H, W = 6, 24, 32
    depth = np.ones((V, H, W), np.float32)
    depth[:, :, W // 2:] = 2.0
    K = np.tile(np.array([[30, 0, W / 2], [0, 30, H / 2], [0, 0, 1]], np.float32), (V, 1, 1))
    return SceneRecord(rgb=np.full((V, H, W, 3), 120, np.uint8), depth=depth, K=K,
                       world_T_cam=ring_poses(V).astype(np.float32),
                       boxes=np.array([[0, 0, 0.2, 0.4, 0.4, 0.4, 0]], np.float32), categories=np.array([0]),
                       instance=np.zeros((V, H, W), np.int32), meta={"seed": 1})


class TestApplyCapture:
    def test_smoke_valid_record_and_input_kept(self):
        rec = small_record()
        before = {k: np.copy(v) for k, v in rec.arrays().items() if k != "meta"}
        out = apply_capture(rec, rng(), 1.0)
        validate_scene(out)
        assert out.meta == {"seed": 1, "capture": {"level": 1.0, "effects": list(EFFECTS)}} and rec.meta == {"seed": 1}
        for k, v in before.items():
            np.testing.assert_array_equal(getattr(rec, k), v)
        for k in ("K", "boxes", "categories", "instance"):
            np.testing.assert_array_equal(getattr(out, k), getattr(rec, k))
            assert getattr(out, k) is not getattr(rec, k)
        for k in ("rgb", "depth", "world_T_cam"):
            assert not np.array_equal(getattr(out, k), getattr(rec, k))

    @pytest.mark.parametrize("level", BAD_LEVELS)
    def test_bad_level(self, level):
        with pytest.raises(ValueError, match="level"):
            apply_capture(small_record(), rng(), level)

    @pytest.mark.parametrize("effects", ["exposure", ["exposure", "blur"], [1]])
    def test_bad_effects(self, effects):
        with pytest.raises(ValueError, match="effects"):
            apply_capture(small_record(), rng(), 1.0, effects)

    def test_missing_array(self):
        with pytest.raises(ValueError, match="world_T_cam"):
            apply_capture({"rgb": small_record().rgb, "depth": small_record().depth}, rng(), 1.0)

    def test_dict_in_dict_out(self):
        rec = small_record()
        arrays = {"rgb": rec.rgb, "depth": rec.depth, "world_T_cam": rec.world_T_cam, "extra": 3}
        out = apply_capture(arrays, rng(), 2.0)
        assert set(out) == set(arrays) and out["extra"] == 3 and out["depth"].shape == rec.depth.shape

    def test_only_the_chosen_effects_and_each_its_own_stream(self):
        rec = small_record()
        only_pose = apply_capture(rec, rng(3), 1.0, {"pose_drift"})
        np.testing.assert_array_equal(only_pose.rgb, rec.rgb)
        np.testing.assert_array_equal(only_pose.depth, rec.depth)
        with_more = apply_capture(rec, rng(3), 1.0, ["exposure", "pose_drift", "drop_depth"])
        np.testing.assert_array_equal(with_more.world_T_cam, only_pose.world_T_cam)

    def test_deterministic_and_identity(self):
        rec = small_record()
        a, b = apply_capture(rec, rng(8), 1.0), apply_capture(rec, rng(8), 1.0)
        for k in ("rgb", "depth", "world_T_cam"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
        same = apply_capture(rec, rng(8), 0)
        for k, v in rec.arrays().items():
            np.testing.assert_array_equal(same.arrays()[k], v)


# -- the generator --------------------------------------------------------------------------------------------
TINY = {"image_size": (48, 48), "num_views": 4}


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_generator_config_capture_fields():
    assert GeneratorConfig(capture_level=0).hash() == GeneratorConfig().hash()
    assert "capture_level" not in GeneratorConfig().to_dict() and "capture_effects" not in GeneratorConfig().to_dict()
    noisy = GeneratorConfig(capture_level=1, capture_effects=["pose_drift", "axial_noise"])
    assert noisy.capture_effects == ("axial_noise", "pose_drift") and noisy.hash() != GeneratorConfig().hash()
    assert GeneratorConfig.from_dict(noisy.to_dict()).hash() == noisy.hash()
    for kwargs, name in [({"capture_level": -1}, "capture_level"), ({"capture_effects": ["x"]}, "capture_effects"),
                         ({"capture_effects": []}, "capture_effects")]:
        with pytest.raises(ValueError, match=name):
            GeneratorConfig(**kwargs)


def test_generator_at_level_0_writes_the_same_bytes(tmp_path):
    generate_dataset(tmp_path / "a", 2, seed=4, config=GeneratorConfig(**TINY), split_fractions=(1, 0, 0),
                     workers=1, progress=False)
    generate_dataset(tmp_path / "b", 2, seed=4, config=GeneratorConfig(**TINY, capture_level=0.0),
                     split_fractions=(1, 0, 0), workers=1, progress=False)
    assert _files(tmp_path / "a") == _files(tmp_path / "b")


def test_generator_at_level_1_keeps_the_layout(tmp_path):
    for name, level in (("clean", 0.0), ("noisy", 1.0)):
        generate_dataset(tmp_path / name, 2, seed=4, config=GeneratorConfig(**TINY, capture_level=level),
                         split_fractions=(1, 0, 0), workers=1, progress=False)
    for i in range(2):
        clean = load_scene(tmp_path / "clean" / f"train/scene_{i:06d}.npz")
        noisy = load_scene(tmp_path / "noisy" / f"train/scene_{i:06d}.npz", validate=True)
        for k in ("boxes", "categories", "instance", "K"):
            np.testing.assert_array_equal(getattr(noisy, k), getattr(clean, k))
        assert not np.array_equal(noisy.depth, clean.depth) and not np.array_equal(noisy.rgb, clean.rgb)
        assert not np.array_equal(noisy.world_T_cam, clean.world_T_cam)
        assert noisy.meta["capture"]["level"] == 1.0 and "capture" not in clean.meta
        assert noisy.meta["object_names"] == clean.meta["object_names"]


class TestDegradeDataset:
    """``threedq data degrade``: a copy of a dataset folder with capture conditions, its layouts kept."""

    def test_copy_keeps_layouts_and_resumes(self, tiny_dataset: Path, tmp_path: Path) -> None:
        from threedq.data.sensor import degrade_dataset
        from threedq.scene import load_index, load_scene

        out = tmp_path / "noisy"
        files = load_index(tiny_dataset).files()
        assert degrade_dataset(tiny_dataset, out, 1.0, seed=3) == len(files)
        assert load_index(out).files() == files
        for rel in files[:3]:
            clean, noisy = load_scene(tiny_dataset / rel), load_scene(out / rel)
            assert np.array_equal(clean.boxes, noisy.boxes) and np.array_equal(clean.K, noisy.K)
            assert not np.array_equal(clean.depth, noisy.depth) and not np.array_equal(clean.world_T_cam,
                                                                                       noisy.world_T_cam)
        first = (out / files[0]).read_bytes()
        (out / files[0]).unlink()  # a killed run: the missing scene is written again, the same bytes
        assert degrade_dataset(tiny_dataset, out, 1.0, seed=3) == 1
        assert (out / files[0]).read_bytes() == first
        again = tmp_path / "again"  # one scene's draws depend on its seed and path alone
        degrade_dataset(tiny_dataset, again, 1.0, seed=3)
        assert (again / files[1]).read_bytes() == (out / files[1]).read_bytes()

    def test_some_splits(self, tiny_dataset: Path, tmp_path: Path) -> None:
        from threedq.data.sensor import degrade_dataset
        from threedq.scene import load_index

        out = tmp_path / "noisy_test"
        index = load_index(tiny_dataset)
        assert degrade_dataset(tiny_dataset, out, 1.0, splits=["test"]) == len(index.files())
        assert load_index(out).files() == index.files()
        for rel in index.files("train") + index.files("val"):  # copied as they are
            assert (out / rel).read_bytes() == (tiny_dataset / rel).read_bytes()
        everything = tmp_path / "noisy_all"  # the degraded split's scenes as a copy of every split has them
        degrade_dataset(tiny_dataset, everything, 1.0)
        for rel in index.files("test"):
            assert (out / rel).read_bytes() == (everything / rel).read_bytes() != (tiny_dataset / rel).read_bytes()

    def test_bad_input(self, tiny_dataset: Path, tmp_path: Path) -> None:
        from threedq.data.sensor import degrade_dataset
        from threedq.scene import SceneValidationError

        with pytest.raises(ValueError, match="splits: .*'tset'.* not among the splits of .*index.json"):
            degrade_dataset(tiny_dataset, tmp_path / "s", 1.0, splits=["tset"])
        with pytest.raises(ValueError, match="out: .* is the source folder"):
            degrade_dataset(tiny_dataset, tiny_dataset, 1.0)
        with pytest.raises(ValueError, match="level"):
            degrade_dataset(tiny_dataset, tmp_path / "x", -1.0)
        with pytest.raises(SceneValidationError, match="index.json"):
            degrade_dataset(tmp_path / "none", tmp_path / "y", 1.0)

    def test_the_command(self, tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
        from threedq.cli import main

        out = tmp_path / "noisy"
        assert main(["data", "degrade", str(tiny_dataset), "--out", str(out), "--progress", "false"]) == 0
        assert "capture level 1" in capsys.readouterr().out and (out / "index.json").is_file()
        assert main(["data", "degrade", str(tiny_dataset), "--out", str(tmp_path / "z"),
                     "--capture_effects", "[blur]", "--progress", "false"]) == 2
        assert "--capture_effects: unknown effect" in capsys.readouterr().err
