"""Label-free 3D box proposals: analytic ray-cast scenes, ground-plane robustness, errors and the dataset cache."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from threedq.boxes import boxes_to_aabb
from threedq.data import proposal_cache
from threedq.data.box_files import load_boxes_file_with_params
from threedq.data.proposal_cache import propose_dataset
from threedq.proposals import PROPOSALS_VERSION, ProposalParams, fit_ground_plane, propose_boxes
from threedq.scene import SceneValidationError, load_index, load_scene

from analytic_scenes import render  # noqa: E402  (tests/ is on sys.path under pytest)

VOXEL = ProposalParams.voxel_size
BOUNDS = ((-1.0, -1.0, -0.5), (1.0, 1.0, 1.0))
BOXES = np.array([[-0.55, -0.35, 0.0, -0.15, 0.05, 0.3], [0.2, 0.1, 0.0, 0.5, 0.6, 0.2]])  # aabb, on z = 0


def _match(pred: np.ndarray, true: np.ndarray, tol: float) -> None:
    assert pred.shape == true.shape, (pred, true)
    for b in true:
        err = np.abs(pred - b).max(axis=1)
        assert err.min() <= tol, f"no proposal within {tol} of {b}: {pred}"


def test_two_boxes_on_flat_ground() -> None:
    aabb, scores = propose_boxes(render(BOXES), bounds=BOUNDS)
    assert aabb.dtype == np.float32 and scores.dtype == np.float32
    assert aabb.shape == (2, 6) and scores.shape == (2,)
    _match(aabb.astype(np.float64), BOXES, tol=VOXEL)
    assert np.all((scores > 0) & (scores <= 1)) and np.all(np.diff(scores) <= 0)


def test_views_turned_by_a_tracker_are_aligned_on_the_floor() -> None:
    """Each view's pose turned by 1.5 degrees about its own camera (a tracker's error): the floors of the views
    disagree by centimetres and the fixed-margin proposals take floor for objects; with ``align_floor`` the two
    boxes come back as with the exact poses."""
    from scipy.spatial.transform import Rotation

    rec = render(BOXES)
    rng = np.random.default_rng(0)
    turned = rec.world_T_cam.astype(np.float64).copy()
    for v in range(len(turned)):
        E = np.eye(4)
        axis = rng.normal(size=3)
        E[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.radians(1.5)).as_matrix()
        turned[v] = turned[v] @ E
    rec.world_T_cam = turned.astype(np.float32)
    wrong, _ = propose_boxes(rec, bounds=BOUNDS)
    assert wrong.shape != (2, 6) or np.abs(wrong - BOXES[np.argsort(-BOXES[:, 5])]).max() > 3 * VOXEL
    aabb, _ = propose_boxes(rec, bounds=BOUNDS, align_floor=True)
    _match(aabb.astype(np.float64), BOXES, tol=3 * VOXEL)  # the turn about the vertical stays: a few cm in x, y


def test_tilted_offset_ground_plane() -> None:
    normal = np.array([math.sin(math.radians(10)), 0.0, math.cos(math.radians(10))])
    offset = 0.15
    # boxes sink into the tilted ground; their visible top and xy extents are what counts
    boxes = BOXES + np.array([0, 0, -0.2, 0, 0, 0.2])
    rec = render(boxes, normal=normal, offset=offset)
    pts_plane = fit_ground_plane(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]))
    assert pts_plane is not None and np.allclose(pts_plane[0], [0, 0, 1])
    aabb, _ = propose_boxes(rec, bounds=BOUNDS)
    assert aabb.shape == (2, 6)
    for b in boxes:
        i = int(np.argmin(np.abs(aabb[:, :2] - b[:2]).sum(1)))
        assert np.abs(aabb[i, [0, 1, 3, 4, 5]] - b[[0, 1, 3, 4, 5]]).max() <= VOXEL
        # extended down to the (tilted) ground: at least to the plane under the centre, not below the
        # plane's lowest point under the footprint (where the box's downhill side meets the ground)
        xs, ys = np.array([aabb[i, 0], aabb[i, 3]]), np.array([aabb[i, 1], aabb[i, 4]])
        plane_z = (offset - normal[0] * xs[:, None] - normal[1] * ys[None, :]) / normal[2]
        centre_z = (offset - normal[0] * xs.mean() - normal[1] * ys.mean()) / normal[2]
        assert plane_z.min() - VOXEL <= aabb[i, 2] <= centre_z + 1e-3
    # the plane itself is found, not assumed at z = 0
    from threedq.proposals import _world_points

    pts, _, _ = _world_points(rec.depth, rec.K, rec.world_T_cam, 1)
    n, d, _ = fit_ground_plane(pts)
    assert np.degrees(np.arccos(np.clip(n @ normal, -1, 1))) < 0.5 and abs(-d - offset) < 5e-3


class TestWorldPoints:
    """``_world_points``: the valid pixels of every view back-projected into the world, one view at a time."""

    @staticmethod
    def naive(depth: np.ndarray, K: np.ndarray, T: np.ndarray, stride: int) -> tuple[np.ndarray, ...]:
        """One pixel at a time, in float64 (view-major, then row, then column)."""
        world, view, foot = [], [], []
        for i in range(depth.shape[0]):
            k = K[i].astype(np.float64)
            for v in range(0, depth.shape[1], stride):
                for u in range(0, depth.shape[2], stride):
                    z = float(depth[i, v, u])
                    if z > 0:
                        y = (v - k[1, 2]) / k[1, 1]
                        x = (u - k[0, 2] - k[0, 1] * y) / k[0, 0]
                        world.append(T[i].astype(np.float64) @ np.array([x * z, y * z, z, 1.0]))
                        view.append(i)
                        foot.append(z / math.sqrt(k[0, 0] * k[1, 1]))
        return np.array(world)[:, :3], np.array(view), np.array(foot)

    @pytest.mark.parametrize("stride", [1, 2])
    def test_feature_against_a_pixel_loop(self, stride: int) -> None:
        from threedq.proposals import _world_points

        rng = np.random.default_rng(3)
        depth = rng.uniform(0.5, 3.0, size=(3, 7, 9)).astype(np.float32)
        depth[rng.random(depth.shape) < 0.3] = 0  # invalid pixels
        depth[1] = 0  # a view without one valid pixel
        K = np.tile(np.array([[8.0, 0.3, 4.2], [0.0, 7.5, 3.1], [0.0, 0.0, 1.0]], np.float32), (3, 1, 1))
        K[2, 0, 0] = 11.0
        T = np.tile(np.eye(4, dtype=np.float32), (3, 1, 1))
        for i, a in enumerate((0.3, -1.1, 2.0)):  # yaw about z, then a pitch about x, and a translation
            c, s = math.cos(a), math.sin(a)
            rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
            rx = np.array([[1, 0, 0], [0, math.cos(0.7), -math.sin(0.7)], [0, math.sin(0.7), math.cos(0.7)]])
            T[i, :3, :3], T[i, :3, 3] = rz @ rx, (0.5 * i, -0.2, 1.0 + i)
        got, ref = _world_points(depth, K, T, stride), self.naive(depth, K, T, stride)
        assert got[0].dtype == np.float64 and got[0].shape == ref[0].shape and got[0].shape[0] > 10
        np.testing.assert_allclose(got[0], ref[0], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(got[1], ref[1])
        np.testing.assert_allclose(got[2], ref[2], rtol=1e-14, atol=0)

    def test_no_valid_pixel(self) -> None:
        from threedq.proposals import _world_points

        pts, view, foot = _world_points(np.zeros((2, 4, 4), np.float32), np.tile(np.eye(3), (2, 1, 1)),
                                        np.tile(np.eye(4), (2, 1, 1)), 1)
        assert pts.shape == (0, 3) and view.shape == (0,) and foot.shape == (0,)


class TestFitGroundPlaneRefinement:
    """The least-squares refinement of the RANSAC plane against the last right singular vector of the inliers."""

    def test_feature_against_svd(self) -> None:
        rng = np.random.default_rng(0)
        normal = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
        xy = rng.uniform(-2, 2, size=(5000, 2)) + 7.0  # far from the origin: the centring matters
        z = (0.3 - normal[0] * xy[:, 0] - normal[1] * xy[:, 1]) / normal[2] + rng.normal(0, 2e-3, 5000)
        pts = np.column_stack([xy, z])
        n, d, _ = fit_ground_plane(pts, threshold=0.01)
        # the reference: two rounds of SVD refinement from the same RANSAC start, done here
        inl = pts[np.abs(pts @ n + d) <= 0.01]
        vt = np.linalg.svd(inl - inl.mean(axis=0), full_matrices=False)[2]
        ref = vt[-1] if vt[-1][2] > 0 else -vt[-1]
        assert np.abs(n - ref).max() < 1e-12 and abs(d + ref @ inl.mean(axis=0)) < 1e-12
        assert np.degrees(np.arccos(min(1.0, n @ normal))) < 0.1


class TestGroundMargin:
    """The ground margin measured from the ground's own spread (``ground_margin=None``, the observed boxes')."""

    FLAT = np.array([[-0.2, -0.8, 0.0, 0.3, -0.5, 0.014]])  # 50 x 30 cm, 1.4 cm tall: under the old fixed 1.5 cm

    def test_exact_depth_keeps_a_flat_object(self) -> None:
        rec = render(np.concatenate([BOXES, self.FLAT]))
        aabb, _ = propose_boxes(rec, bounds=BOUNDS, ground_margin=None, min_height=None)
        assert aabb.shape == (3, 6)
        j = int(np.argmin(np.abs(aabb - self.FLAT[0]).sum(1)))
        assert np.abs(aabb[j] - self.FLAT[0]).max() <= VOXEL and aabb[j, 5] == pytest.approx(0.014, abs=1e-3)
        fixed = propose_boxes(rec, bounds=BOUNDS)[0]  # the fixed 1.5 cm (the training pseudo-boxes')
        assert fixed.shape == (2, 6)

    def test_noisy_depth_keeps_its_floor_as_ground(self) -> None:
        rec = render(BOXES)
        g = np.random.default_rng(0)
        noisy = rec.depth * (1 + g.normal(0, 0.002, rec.depth.shape)).astype(np.float32)  # ~4 mm at 2 m
        rec = type(rec)(**{**rec.__dict__, "depth": np.where(rec.depth > 0, noisy, 0).astype(np.float32)})
        fixed = propose_boxes(rec, bounds=BOUNDS, ground_margin=0.005, min_height=0.01)[0]
        measured = propose_boxes(rec, bounds=BOUNDS, ground_margin=None, min_height=None)[0]
        assert measured.shape == (2, 6)  # the two boxes, no floor speckle
        _match(measured.astype(np.float64), BOXES, tol=2 * VOXEL)
        assert fixed.shape[0] > 2  # the same floor under a fixed 5 mm margin: speckle proposed as objects

    def test_ground_spread_against_numpy(self) -> None:
        from threedq.geometry.ground import ground_spread

        g = np.random.default_rng(1)
        h = np.concatenate([g.normal(0, 0.003, 20000), g.uniform(0.05, 0.3, 5000)])  # ground + objects
        assert ground_spread(h, 0.01) == pytest.approx(0.003, rel=0.1)  # truncation at 3.3 sigma moves it little
        inl = h[np.abs(h) <= 0.01]
        assert ground_spread(h, 0.01) == pytest.approx(1.4826 * np.median(np.abs(inl - np.median(inl))))
        assert ground_spread(np.zeros(10), 0.01) == 0.0 and ground_spread(np.array([1.0]), 0.01) == 0.0

    def test_explicit_values_and_bad_ones(self) -> None:
        assert ProposalParams(ground_margin=0.01, min_height=0.02).ground_margin == 0.01
        with pytest.raises(ValueError, match="min_ground_margin"):
            ProposalParams(min_ground_margin=-1.0)
        with pytest.raises(ValueError, match="ground_margin"):
            ProposalParams(ground_margin=float("nan"))


def test_empty_scene_and_no_depth_give_no_proposals() -> None:
    rec = render(np.zeros((0, 6)), num_views=4)
    aabb, scores = propose_boxes(rec, bounds=BOUNDS)
    assert aabb.shape == (0, 6) and scores.shape == (0,) and aabb.dtype == np.float32
    rec.depth[:] = 0
    aabb, scores = propose_boxes(rec, bounds=BOUNDS)
    assert aabb.shape == (0, 6) and scores.shape == (0,)


def test_bad_input_names_the_field() -> None:
    rec = render(BOXES[:1], num_views=2)
    rec.depth[0, 3, 3] = np.nan
    with pytest.raises(ValueError, match="depth"):
        propose_boxes(rec)
    rec = render(BOXES[:1], num_views=2)
    rec.K = rec.K[:1]
    with pytest.raises(ValueError, match="K"):
        propose_boxes(rec)
    rec = render(BOXES[:1], num_views=2)
    with pytest.raises(ValueError, match="voxel_size"):
        propose_boxes(rec, voxel_size=0)
    with pytest.raises(ValueError, match="footprint"):
        propose_boxes(rec, footprint="sphere")
    with pytest.raises(ValueError, match="bounds"):
        propose_boxes(rec, bounds=((0, 0, 0), (0, 1, 1)))


def test_tiny_dataset_end_to_end_and_cache(tiny_dataset: Path, tmp_path: Path, monkeypatch) -> None:
    index = load_index(tiny_dataset)
    cache = tmp_path / "props.npz"
    out = propose_dataset(tiny_dataset, "train", cache, progress=False)
    files = index.files("train")
    assert list(out) == files and cache.is_file()
    lo, hi = np.array(index.scene_bounds[0]), np.array(index.scene_bounds[1])
    hits = 0
    for f, (aabb, scores) in out.items():
        assert aabb.dtype == np.float32 and aabb.shape == (len(scores), 6) and scores.dtype == np.float32
        assert np.all(np.isfinite(aabb)) and np.all((scores > 0) & (scores <= 1))
        assert np.all(aabb[:, 3:] > aabb[:, :3])
        assert np.all(aabb[:, :3] >= lo - 1e-3) and np.all(aabb[:, 3:] <= hi + 1e-3)
        gt = boxes_to_aabb(load_scene(tiny_dataset / f).boxes.astype(np.float64))
        for g in gt:  # crude overlap check: 32x32 images, 4 views are very coarse
            inter = np.clip(np.minimum(aabb[:, 3:], g[3:]) - np.maximum(aabb[:, :3], g[:3]), 0, None).prod(1)
            hits += int(np.any(inter > 0))
    assert hits > 0

    params, stored = load_boxes_file_with_params(cache)  # a box file whose params name the algorithm version
    assert json.loads(params)["version"] == PROPOSALS_VERSION and list(stored) == files

    # reuse: nothing is recomputed, identical results
    calls = []
    real = proposal_cache.propose_boxes
    monkeypatch.setattr(proposal_cache, "propose_boxes", lambda *a, **k: calls.append(1) or real(*a, **k))
    again = propose_dataset(tiny_dataset, "train", cache, progress=False)
    assert not calls
    for f in files:
        np.testing.assert_array_equal(again[f][0], out[f][0])
        np.testing.assert_array_equal(again[f][1], out[f][1])

    # resume: a cache of the first scenes is completed, not recomputed
    part = tmp_path / "part.npz"
    propose_dataset(tiny_dataset, "train", part, max_scenes=3, progress=False)
    calls.clear()
    full = propose_dataset(tiny_dataset, "train", part, progress=False)
    assert len(calls) == len(files) - 3 and list(full) == files

    # other parameters: recomputed with a warning
    calls.clear()
    with pytest.warns(UserWarning, match="other parameters"):
        propose_dataset(tiny_dataset, "train", cache, params=ProposalParams(voxel_size=0.05), progress=False)
    assert len(calls) == len(files)

    # corrupt cache: a clear error naming the file
    cache.write_bytes(b"not an npz")
    with pytest.raises(ValueError, match="props.npz"):
        propose_dataset(tiny_dataset, "train", cache, progress=False)

    with pytest.raises(ValueError, match="split"):
        propose_dataset(tiny_dataset, "nope", tmp_path / "x.npz", progress=False)


def test_full_disk_while_caching_keeps_the_cache_and_resumes_equal(tiny_dataset: Path, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """A write of the cache that fails for lack of space names the cache and leaves the previous one whole; run again
    once there is space, it completes to what an uninterrupted computation gives."""
    import errno
    import os

    clean = propose_dataset(tiny_dataset, "train", tmp_path / "clean.npz", progress=False)
    cache = tmp_path / "cache.npz"
    propose_dataset(tiny_dataset, "train", cache, max_scenes=2, progress=False)
    before = cache.read_bytes()

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError) as e:
        propose_dataset(tiny_dataset, "train", cache, save_every=1, progress=False)
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(cache)
    assert cache.read_bytes() == before and not list(tmp_path.glob(".*.tmp"))
    monkeypatch.undo()
    resumed = propose_dataset(tiny_dataset, "train", cache, progress=False)
    assert list(resumed) == list(clean)
    for f in clean:
        np.testing.assert_array_equal(resumed[f][0], clean[f][0])
        np.testing.assert_array_equal(resumed[f][1], clean[f][1])


def test_pool_of_workers_gives_the_same_boxes_and_cache(tiny_dataset: Path, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(proposal_cache, "MIN_POOL_SCENES", 1)  # the tiny split is below the real threshold
    serial = propose_dataset(tiny_dataset, "train", tmp_path / "one.npz", progress=False, save_every=3)
    pooled = propose_dataset(tiny_dataset, "train", tmp_path / "two.npz", progress=False, save_every=3, workers=2)
    assert list(pooled) == list(serial)
    for f in serial:
        np.testing.assert_array_equal(pooled[f][0], serial[f][0])
        np.testing.assert_array_equal(pooled[f][1], serial[f][1])
    assert (tmp_path / "one.npz").read_bytes() == (tmp_path / "two.npz").read_bytes()
    with pytest.raises(ValueError, match="workers"):
        propose_dataset(tiny_dataset, "train", tmp_path / "x.npz", progress=False, workers=0)


def test_pool_worker_error_is_the_scenes_own(tiny_dataset: Path, tmp_path: Path, monkeypatch) -> None:
    # a corrupt scene among the pool's: the parent raises the error computing it in-process gives, naming the file
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    bad = data / load_index(data).files("train")[2]
    bad.write_bytes(bad.read_bytes()[:100])
    monkeypatch.setattr(proposal_cache, "MIN_POOL_SCENES", 1)
    with pytest.raises(SceneValidationError, match=bad.name) as serial:
        propose_dataset(data, "train", tmp_path / "one.npz", progress=False)
    with pytest.raises(SceneValidationError, match=bad.name) as pooled:
        propose_dataset(data, "train", tmp_path / "two.npz", progress=False, workers=2)
    assert str(pooled.value) == str(serial.value)


def test_no_pool_when_the_main_script_cannot_be_rerun(monkeypatch) -> None:
    import sys
    import types

    main = types.ModuleType("__main__")
    monkeypatch.setitem(sys.modules, "__main__", main)
    assert proposal_cache._pool_size(2, 100) == 2  # no main script (python -c, a notebook): spawn is fine
    main.__file__ = "<stdin>"
    assert proposal_cache._pool_size(2, 100) == 1
    main.__file__ = __file__
    assert proposal_cache._pool_size(2, 100) == 2 and proposal_cache._pool_size(2, 5) == 1
    assert proposal_cache._pool_size(1, 100) == 1
