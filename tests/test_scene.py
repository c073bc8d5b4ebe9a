"""The canonical scene record: round trips, deterministic bytes, and one clear error per kind of bad input."""

from __future__ import annotations

import math
import zipfile
from pathlib import Path

import numpy as np
import pytest

from threedq.atomic_io import npz_bytes
from threedq.boxes import box_corners, boxes_to_aabb
from threedq.scene import (
    DatasetIndex,
    SceneRecord,
    SceneValidationError,
    load_index,
    load_scene,
    load_scene_boxes,
    load_scene_gt,
    save_index,
    save_scene,
    validate_scene,
)

BOUNDS = ((-1.0, -1.0, -0.5), (1.0, 1.0, 1.0))


def make_record(V: int = 3, H: int = 6, W: int = 8, M: int = 2, seed: int = 0) -> SceneRecord:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4, dtype=np.float32), (V, 1, 1))
    for v in range(V):
        a = 2 * math.pi * v / V
        c, s = math.cos(a), math.sin(a)
        poses[v, :3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32)
        poses[v, :3, 3] = [0.1 * v, 0.0, 2.0]
    K = np.tile(np.array([[10, 0, (W - 1) / 2], [0, 10, (H - 1) / 2], [0, 0, 1]], np.float32), (V, 1, 1))
    boxes = np.array([[0.2 * m, -0.1, 0.15, 0.2, 0.3, 0.3, 0.4 * m] for m in range(M)], np.float32)
    return SceneRecord(
        rgb=rng.integers(0, 256, (V, H, W, 3), dtype=np.uint8),
        depth=rng.uniform(0.5, 3.0, (V, H, W)).astype(np.float32),
        K=K,
        world_T_cam=poses,
        boxes=boxes,
        categories=np.arange(M, dtype=np.int64),
        instance=rng.integers(0, M + 1, (V, H, W)).astype(np.int32),
        meta={"seed": 3},
    )


class TestSaveLoad:
    def test_round_trip(self, tmp_path: Path) -> None:
        rec = make_record()
        path = save_scene(tmp_path / "a" / "s.npz", rec)
        back = load_scene(path, bounds=BOUNDS, num_categories=5)
        for k, v in rec.arrays().items():
            if k != "meta":
                np.testing.assert_array_equal(getattr(back, k), v)
        assert back.meta == {"seed": 3}
        assert back.num_views == 3 and back.num_objects == 2 and back.image_size == (6, 8)

    def test_deterministic_bytes_and_no_temp_files(self, tmp_path: Path) -> None:
        rec = make_record()
        a = save_scene(tmp_path / "a.npz", rec).read_bytes()
        b = save_scene(tmp_path / "b.npz", rec).read_bytes()
        assert a == b
        assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "b.npz"]

    def test_readable_by_numpy(self, tmp_path: Path) -> None:
        rec = make_record()
        path = save_scene(tmp_path / "s.npz", rec)
        with np.load(path) as npz:
            assert set(npz.files) >= {"rgb", "depth", "K", "world_T_cam", "instance", "boxes", "categories"}
            assert npz["depth"].dtype == np.float32 and npz["rgb"].dtype == np.uint8

    def test_optional_instance(self, tmp_path: Path) -> None:
        rec = make_record()
        rec.instance = None
        back = load_scene(save_scene(tmp_path / "s.npz", rec))
        assert back.instance is None


def _expect(rec: SceneRecord, field: str, match: str, bounds=None) -> None:
    with pytest.raises(SceneValidationError, match=match) as e:
        validate_scene(rec, source="scenes/x.npz", bounds=bounds)
    assert e.value.field == field
    msg = str(e.value)
    assert msg.startswith("scenes/x.npz: field '" + field + "'") and "\n" not in msg


class TestValidate:
    def test_good(self) -> None:
        assert validate_scene(make_record(), bounds=BOUNDS) is not None

    def test_nan_depth(self) -> None:
        rec = make_record()
        rec.depth[1, 2, 3] = np.nan
        _expect(rec, "depth", "non-finite")

    def test_inf_pose(self) -> None:
        rec = make_record()
        rec.world_T_cam[0, 0, 3] = np.inf
        _expect(rec, "world_T_cam", "non-finite")

    def test_non_rigid_pose(self) -> None:
        rec = make_record()
        rec.world_T_cam[2, :3, :3] *= 1.1  # a scale is not a rotation
        _expect(rec, "world_T_cam", "view 2: rotation is not rigid")

    def test_reflection_pose(self) -> None:
        rec = make_record()
        rec.world_T_cam[1, :3, 0] *= -1  # det = -1
        _expect(rec, "world_T_cam", "view 1")

    def test_negative_depth(self) -> None:
        rec = make_record()
        rec.depth[0, 0, 0] = -1
        _expect(rec, "depth", "negative")

    def test_a_view_without_depth(self) -> None:
        rec = make_record()
        rec.depth[1] = 0  # a sensor frame that returned nothing
        _expect(rec, "depth", "view 1 has no valid depth at all")
        rec.depth[1, 5, 5] = 2.0  # one valid pixel is a view
        validate_scene(rec)

    def test_shape_mismatch_between_views(self) -> None:
        rec = make_record()
        rec.depth = rec.depth[:2]
        _expect(rec, "depth", "to match rgb")
        rec = make_record()
        rec.K = rec.K[:2]
        _expect(rec, "K", "expected shape")

    def test_empty_scene(self) -> None:
        rec = make_record()
        rec.boxes = np.zeros((0, 7), np.float32)
        rec.categories = np.zeros((0,), np.int64)
        _expect(rec, "boxes", "empty scene")

    def test_box_outside_bounds(self) -> None:
        rec = make_record()
        rec.boxes[1, 0] = 0.95  # centre inside, half-extent sticks out
        _expect(rec, "boxes", "object 1 lies outside", bounds=BOUNDS)

    def test_categories_mismatch(self) -> None:
        rec = make_record()
        rec.categories = rec.categories[:1]
        _expect(rec, "categories", "to match boxes")
        with pytest.raises(SceneValidationError, match="id 1 >= number of categories 1"):
            validate_scene(make_record(), num_categories=1)


class TestLoadErrors:
    def test_missing_file(self, tmp_path: Path) -> None:
        with pytest.raises(SceneValidationError, match="no such file"):
            load_scene(tmp_path / "nope.npz")

    def test_truncated_file(self, tmp_path: Path) -> None:
        path = save_scene(tmp_path / "s.npz", make_record())
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
        with pytest.raises(SceneValidationError) as e:
            load_scene(path)
        assert str(path) in str(e.value)

    def test_missing_key(self, tmp_path: Path) -> None:
        arrays = make_record().arrays()
        del arrays["world_T_cam"]
        path = tmp_path / "s.npz"
        path.write_bytes(npz_bytes(arrays))
        with pytest.raises(SceneValidationError, match="field 'world_T_cam': missing key"):
            load_scene(path)

    def test_nan_on_disk(self, tmp_path: Path) -> None:
        rec = make_record()
        rec.depth[0, 1, 1] = np.nan
        path = tmp_path / "s.npz"
        path.write_bytes(npz_bytes(rec.arrays()))
        with pytest.raises(SceneValidationError, match=r"s\.npz: field 'depth': 1 non-finite"):
            load_scene(path)

    def test_corrupt_member(self, tmp_path: Path) -> None:
        path = save_scene(tmp_path / "s.npz", make_record())
        with zipfile.ZipFile(path) as zf:
            members = {n: zf.read(n) for n in zf.namelist()}
        members["depth.npy"] = members["depth.npy"][:200]  # header intact, data cut short
        with zipfile.ZipFile(path, "w") as zf:
            for n, b in members.items():
                zf.writestr(n, b)
        with pytest.raises(SceneValidationError, match="field 'depth'"):
            load_scene(path)


class TestLoadSceneGt:
    """The boxes and categories of a scene file alone, as :func:`load_scene` reads them."""

    def test_equals_load_scene(self, tmp_path: Path) -> None:
        path = save_scene(tmp_path / "s.npz", make_record(M=3))
        boxes, categories = load_scene_gt(path)
        rec = load_scene(path)
        np.testing.assert_array_equal(boxes, rec.boxes)
        np.testing.assert_array_equal(categories, rec.categories)

    def test_errors_name_file_and_field(self, tmp_path: Path) -> None:
        arrays = make_record().arrays()
        del arrays["categories"]
        path = tmp_path / "s.npz"
        path.write_bytes(npz_bytes(arrays))
        with pytest.raises(SceneValidationError, match=r"s\.npz: field 'categories': missing key"):
            load_scene_gt(path)


class TestLoadSceneBoxes:
    """The boxes of a scene file alone: what :func:`load_scene` reads, and its errors, without the views."""

    def test_equals_load_scene(self, tmp_path: Path) -> None:
        rec = make_record(M=3)
        path = save_scene(tmp_path / "s.npz", rec)
        boxes = load_scene_boxes(path)
        assert boxes.dtype == np.float32 and boxes.shape == (3, 7)
        np.testing.assert_array_equal(boxes, load_scene(path).boxes)

    def test_empty_scene(self, tmp_path: Path) -> None:
        path = tmp_path / "s.npz"
        path.write_bytes(npz_bytes({**make_record().arrays(), "boxes": np.zeros((0, 7), np.float32),
                                    "categories": np.zeros(0, np.int64)}))
        assert load_scene_boxes(path).shape == (0, 7)

    def test_reads_no_view(self, tmp_path: Path) -> None:
        """A cut-short depth member does not matter to the boxes (only the ``boxes`` member is decompressed)."""
        path = save_scene(tmp_path / "s.npz", make_record())
        with zipfile.ZipFile(path) as zf:
            members = {n: zf.read(n) for n in zf.namelist()}
        members["depth.npy"] = members["depth.npy"][:200]
        with zipfile.ZipFile(path, "w") as zf:
            for n, b in members.items():
                zf.writestr(n, b)
        np.testing.assert_array_equal(load_scene_boxes(path), make_record().arrays()["boxes"])

    def test_errors_name_file_and_field(self, tmp_path: Path) -> None:
        with pytest.raises(SceneValidationError, match=r"nope\.npz: field '<file>': no such file"):
            load_scene_boxes(tmp_path / "nope.npz")
        arrays = make_record().arrays()
        del arrays["boxes"]
        path = tmp_path / "s.npz"
        path.write_bytes(npz_bytes(arrays))
        with pytest.raises(SceneValidationError, match=r"s\.npz: field 'boxes': missing key"):
            load_scene_boxes(path)
        path.write_bytes(b"not a zip")
        with pytest.raises(SceneValidationError, match=r"s\.npz: field '<file>': not a \.npz"):
            load_scene_boxes(path)


class TestIndex:
    def test_round_trip(self, tmp_path: Path) -> None:
        idx = DatasetIndex(
            categories=["a", "b", "c"],
            symmetry_order=[1, 0, 4],
            scenes=[{"file": "train/s0.npz", "split": "train"}, {"file": "test/s0.npz", "split": "test"}],
            scene_bounds=BOUNDS,
            generator={"version": "x"},
            seed=7,
        )
        save_index(tmp_path, idx)
        back = load_index(tmp_path)
        assert back.categories == ["a", "b", "c"] and back.symmetric == [False, True, True]
        assert back.files("test") == ["test/s0.npz"] and back.scene_bounds == BOUNDS and back.seed == 7

    @pytest.mark.parametrize(
        "text, field",
        [("{not json", "<file>"), ('{"format": "other"}', "format"), ('{"format": "threedq-scenes"}', "categories")],
    )
    def test_bad_index(self, tmp_path: Path, text: str, field: str) -> None:
        (tmp_path / "index.json").write_text(text)
        with pytest.raises(SceneValidationError) as e:
            load_index(tmp_path)
        assert e.value.field == field and "index.json" in str(e.value)


class TestBoxes:
    def test_corners_hand_computed(self) -> None:
        # A 2 x 1 x 1 box yawed by +90 deg: its long side turns from x to y.
        c = box_corners(np.array([1.0, 2.0, 0.5, 2.0, 1.0, 1.0, math.pi / 2]))
        assert c.shape == (8, 3)
        np.testing.assert_allclose(c[0], [1.5, 1.0, 0.0], atol=1e-12)  # local (-1, -0.5, -0.5) -> (0.5, -1)
        np.testing.assert_allclose(c[7], [0.5, 3.0, 1.0], atol=1e-12)  # local (+1, +0.5, +0.5) -> (-0.5, +1)
        np.testing.assert_allclose(boxes_to_aabb(np.array([1.0, 2.0, 0.5, 2.0, 1.0, 1.0, math.pi / 2])),
                                   [0.5, 1.0, 0.0, 1.5, 3.0, 1.0], atol=1e-12)

    def test_aabb_of_rotated_square(self) -> None:
        # A unit square yawed by 45 deg has an axis-aligned hull of side sqrt(2).
        aabb = boxes_to_aabb(np.array([[0.0, 0.0, 0.0, 1.0, 1.0, 1.0, math.pi / 4]]))
        np.testing.assert_allclose(aabb[0, 3] - aabb[0, 0], math.sqrt(2), atol=1e-12)

    def test_aabb_of_an_unyawed_box_is_itself(self) -> None:
        aabb = np.array([[-1.0, 0.0, 2.0, 1.0, 3.0, 4.0]])
        np.testing.assert_allclose(boxes_to_aabb(np.concatenate(
            [(aabb[:, :3] + aabb[:, 3:]) / 2, aabb[:, 3:] - aabb[:, :3], np.zeros((1, 1))], axis=1)), aabb)

    def test_bad_shape(self) -> None:
        with pytest.raises(ValueError, match=r"boxes: expected shape \[\.\.\., 7\]"):
            box_corners(np.zeros((3, 6)))
