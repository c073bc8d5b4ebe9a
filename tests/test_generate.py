"""The embedded dataset generator: determinism, splits and seeds, format, geometry, resuming, arguments.

Tiny configs (64x64 pixels, 4-6 views) keep the file fast. The geometric checks back-project every
pixel with the record's own ``K`` and ``world_T_cam``, exactly as :mod:`threedq.scene` documents them,
so any convention bug (pose direction, camera axes, half-pixel offset, row flip, depth definition)
fails them.
"""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from threedq.boxes import box_corners
from threedq.data import CATEGORIES, GeneratorConfig, generate_dataset
from threedq.data.catalog import (
    CATEGORY_NAMES,
    CLEVR_COLORS,
    HELD_OUT_CATEGORIES,
    HELD_OUT_NAMES,
    PRIMITIVE_SOURCES,
    RANDOM_COLOR_PALETTE,
    SHAPE_ONLY_NAMES,
    category_by_name,
)
from threedq.data.meshes import category_extents
from threedq.data.generator_config import GENERATOR_VERSION
from threedq.data.layout import intrinsics, sample_scene
from threedq.data.splits import derive_test_seed, scene_seed_sequence, split_sizes
from threedq.scene import load_index, load_scene

TINY = GeneratorConfig(image_size=(64, 64), num_views=4)
SINGLE = GeneratorConfig(image_size=(48, 80), num_views=6, min_objects=1, max_objects=1)  # non-square on purpose
N_SCENES = 6  # -> 4 train, 1 val, 1 test


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ds") / "a"
    generate_dataset(out, N_SCENES, seed=0, config=TINY, workers=1, progress=False)
    return out


# -- catalogue ------------------------------------------------------------------------------------
def test_catalogue():
    assert len(CATEGORIES) == 41 and len(set(CATEGORY_NAMES)) == 41
    assert CATEGORY_NAMES[0] == "cube_gray" and CATEGORY_NAMES[23] == "cylinder_yellow"
    assert CATEGORY_NAMES[24:27] == ("banana", "pear", "strawberry")
    for i, (colour, rgb) in enumerate(CLEVR_COLORS):
        assert category_by_name(f"sphere_{colour}").color == pytest.approx(tuple(c / 255 for c in rgb))
        assert CATEGORY_NAMES[8 + i] == f"sphere_{colour}"
    orders = {c.name: c.symmetry_order for c in CATEGORIES}
    assert {orders[f"cube_{c}"] for c, _ in CLEVR_COLORS} == {4}
    assert {orders[f"sphere_{c}"] for c, _ in CLEVR_COLORS} == {orders[f"cylinder_{c}"] for c, _ in CLEVR_COLORS} == {0}
    assert orders["cracker_box"] == orders["lego_duplo"] == orders["potted_meat_can"] == 2
    assert orders["apple"] == 0 and orders["banana"] == orders["mug"] == orders["power_drill"] == 1
    ycb = [c for c in CATEGORIES if c.source not in PRIMITIVE_SOURCES]
    assert len(ycb) == 17 and sum(c.symmetry_order == 1 for c in ycb) >= 12  # mostly asymmetric
    colours = np.array([c.color for c in ycb])
    dists = np.linalg.norm(colours[:, None] - colours[None], axis=-1) + np.eye(17)
    assert dists.min() > 0.1  # distinct colours


# -- sampling (numpy only) ------------------------------------------------------------------------
def test_held_out_categories(tmp_path):
    """8 categories the embedded set never draws: selectable by name, own symmetry orders, rendered with boxes of
    their mesh's proportions (a shifted dataset: smaller objects, closer cameras, a wider field of view)."""
    assert len(HELD_OUT_NAMES) == len(set(HELD_OUT_NAMES)) == 8
    assert not set(HELD_OUT_NAMES) & set(CATEGORY_NAMES)
    assert set(GeneratorConfig().category_names) == set(CATEGORY_NAMES)  # the default never draws them
    assert {c.source for c in HELD_OUT_CATEGORIES}.isdisjoint(c.source for c in CATEGORIES)
    orders = {c.name: c.symmetry_order for c in HELD_OUT_CATEGORIES}
    assert orders["bowl"] == orders["cups"] == 0 and orders["rubiks_cube"] == 4 and orders["sugar_box"] == 2
    assert orders["scissors"] == orders["spatula"] == orders["adjustable_wrench"] == 1
    with pytest.raises(ValueError, match="held out of the embedded set: sugar_box"):
        category_by_name("dragon")
    cfg = GeneratorConfig(image_size=(48, 48), num_views=6, max_objects=1, categories=("bowl", "scissors"),
                          object_size=0.3, distance_range=(1.8, 2.2), fov_deg=65.0)
    assert cfg.symmetry_order == (0, 1)
    generate_dataset(tmp_path, 4, seed=3, config=cfg, split_fractions=(1, 0, 0), workers=1, progress=False)
    index = load_index(tmp_path)
    assert index.categories == ["bowl", "scissors"] and index.symmetry_order == [0, 1]
    for f in index.files("train"):
        rec = load_scene(tmp_path / f)
        (box,), (cat,) = rec.boxes, rec.categories
        ext = category_extents(index.categories[int(cat)])
        assert np.allclose(np.sort(box[3:6]) / box[3:6].max(), np.sort(ext) / ext.max(), atol=1e-4)
        assert 0.3 * 0.75 - 1e-6 <= box[3:6].max() <= 0.3 * 1.25 + 1e-6
        assert (rec.instance == 1).sum() > 0  # the object is seen


def test_sample_scene_layout_invariants():
    cfg = GeneratorConfig()
    lo, hi = np.array(cfg.scene_bounds[0]), np.array(cfg.scene_bounds[1])
    K = intrinsics(cfg)
    assert K[0, 0] == K[1, 1] == pytest.approx(128 / (2 * math.tan(math.radians(55) / 2)))
    assert K[0, 2] == K[1, 2] == 63.5
    counts = set()
    for i in range(200):
        lay = sample_scene(cfg, scene_seed_sequence(7, "train", i))
        boxes = lay.boxes
        counts.add(len(boxes))
        corners = box_corners(boxes)
        assert np.all(corners >= lo) and np.all(corners <= hi)
        assert np.allclose(boxes[:, 2], boxes[:, 5] / 2)  # resting on the ground
        assert np.all((boxes[:, 6] >= 0) & (boxes[:, 6] < 2 * np.pi))
        assert np.all(np.hypot(boxes[:, 0], boxes[:, 1]) <= cfg.placement_radius + 1e-9)
        assert np.all((boxes[:, 3:6].max(1) >= 0.5 * 0.75 - 1e-9) & (boxes[:, 3:6].max(1) <= 0.5 * 1.25 + 1e-9))
        r = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])  # footprint circles do not overlap
        for a in range(len(boxes)):
            for b in range(a):
                assert np.hypot(*(boxes[a, :2] - boxes[b, :2])) >= r[a] + r[b]
        # cameras: rigid, above the ground, z axis towards the scene centre, image x horizontal
        R, t = lay.world_T_cam[:, :3, :3], lay.world_T_cam[:, :3, 3]
        assert np.allclose(R.transpose(0, 2, 1) @ R, np.eye(3), atol=1e-6)
        assert np.allclose(np.linalg.det(R), 1, atol=1e-6)
        assert np.allclose(R[:, 2, 0], 0, atol=1e-6)  # camera x has no world-z component
        dist = np.linalg.norm(t - [0, 0, 0.2], axis=1)
        assert np.all((dist > 2.8 - 0.2) & (dist < 3.6 + 0.2))
        elev = np.degrees(np.arcsin(-R[:, 2, 2]))
        assert np.all((elev >= 20 - 1e-4) & (elev <= 80 + 1e-4))
    assert counts == {1, 2, 3}
    a = sample_scene(cfg, scene_seed_sequence(7, "train", 3))
    b = sample_scene(cfg, scene_seed_sequence(7, "train", 3))
    assert np.array_equal(a.boxes, b.boxes) and np.array_equal(a.world_T_cam, b.world_T_cam)


class TestRandomColours:
    """``color_mode="random"``: the shape-only data (a category is a shape; each instance a random palette colour)."""

    def test_shape_only_names(self):
        assert len(SHAPE_ONLY_NAMES) == len(set(SHAPE_ONLY_NAMES)) == 20
        assert SHAPE_ONLY_NAMES[:3] == ("cube", "sphere", "cylinder")
        assert set(SHAPE_ONLY_NAMES[3:]) < set(CATEGORY_NAMES)  # the 17 meshes of the embedded data
        assert not set(SHAPE_ONLY_NAMES[:3]) & set(CATEGORY_NAMES)  # never drawn by the default
        assert category_by_name("cube").source == "cube" and category_by_name("cube").symmetry_order == 4
        assert GeneratorConfig(categories=SHAPE_ONLY_NAMES).symmetry_order[:3] == (4, 0, 0)

    def test_palette_is_not_the_catalogue_colours(self):
        pal = np.array(RANDOM_COLOR_PALETTE)
        cat = np.array([c.color for c in CATEGORIES + HELD_OUT_CATEGORIES])
        assert len(pal) >= 12 and np.all((pal >= 0) & (pal <= 1))
        assert np.linalg.norm(pal[:, None] - cat[None], axis=-1).min() > 0.05

    def test_same_layout_as_category_colours_and_colours_from_the_palette(self):
        cat_cfg = GeneratorConfig(categories=SHAPE_ONLY_NAMES)
        rnd_cfg = GeneratorConfig(categories=SHAPE_ONLY_NAMES, color_mode="random")
        per_category: dict[int, set] = {}
        for i in range(60):
            a = sample_scene(cat_cfg, scene_seed_sequence(3, "train", i))
            b = sample_scene(rnd_cfg, scene_seed_sequence(3, "train", i))
            assert np.array_equal(a.boxes, b.boxes) and np.array_equal(a.categories, b.categories)
            assert np.array_equal(a.world_T_cam, b.world_T_cam) and a.lighting == b.lighting
            assert all(o.color is None for o in a.objects)
            for o in b.objects:
                assert o.color in RANDOM_COLOR_PALETTE
                per_category.setdefault(o.category, set()).add(o.color)
            again = sample_scene(rnd_cfg, scene_seed_sequence(3, "train", i))
            assert [o.color for o in again.objects] == [o.color for o in b.objects]  # reproducible
        # colour says nothing about the category: each seen category in several colours
        assert sum(len(c) >= 3 for c in per_category.values()) >= 0.8 * len(per_category)

    def test_hash_of_the_default_is_that_of_datasets_made_before_the_option(self):
        # the literals: GeneratorConfig().hash() and one with categories/image size, at 0b31d44 (before color_mode)
        assert GeneratorConfig().hash() == "a7db700431f9dd2dee4fc362273da35fac382326"
        old = GeneratorConfig(categories=("bowl", "scissors"), image_size=(48, 48))
        assert old.hash() == "e691e0f4987fb6cc916a1fdcbfdf7061b3e09059"
        assert GeneratorConfig(color_mode="random").hash() != GeneratorConfig().hash()
        rnd = GeneratorConfig(categories=SHAPE_ONLY_NAMES, color_mode="random")
        assert GeneratorConfig.from_dict(rnd.to_dict()) == rnd

    def test_rendered_instances_take_their_own_colour(self, tmp_path):
        cfg = GeneratorConfig(image_size=(48, 48), num_views=3, min_objects=3, max_objects=3,
                              categories=("cube", "sphere"), color_mode="random", shadows=False)
        generate_dataset(tmp_path, 3, seed=1, config=cfg, split_fractions=(1, 0, 0), workers=1, progress=False)
        for f in load_index(tmp_path).files("train"):
            rec = load_scene(tmp_path / f)
            colours = rec.meta["object_colors"]
            assert len(colours) == len(rec.boxes)
            for i, c in enumerate(colours):
                pix = rec.rgb[rec.instance == i + 1].astype(np.float64) / 255.0
                if len(pix) < 20:
                    continue
                # shading scales the albedo: the brightest pixels' chromaticity is the instance's colour's
                top = pix[np.argsort(pix.sum(1))[-len(pix) // 4:]].mean(0)
                want = np.asarray(c)
                if want.sum() > 0.3:
                    assert np.allclose(top / top.sum(), want / want.sum(), atol=0.06), (f, i, top, want)

    def test_bad_mode_names_the_argument(self):
        with pytest.raises(ValueError, match="color_mode"):
            GeneratorConfig(color_mode="rainbow")


def test_split_sizes():
    assert split_sizes(1000, (0.8, 0.1, 0.1), ("train", "val", "test")) == {"train": 800, "val": 100, "test": 100}
    assert split_sizes(6, (0.8, 0.1, 0.1), ("train", "val", "test")) == {"train": 4, "val": 1, "test": 1}
    assert split_sizes(3, (0.8, 0.1, 0.1), ("train", "val", "test")) == {"train": 1, "val": 1, "test": 1}
    assert split_sizes(7, (0.8, 0.1, 0.1), ("train", "val")) == {"train": 6, "val": 1}
    assert split_sizes(5, (0.8, 0.1, 0.1), ("test",)) == {"test": 5}
    assert sum(split_sizes(997, (0.5, 0.3, 0.2), ("train", "val", "test")).values()) == 997


# -- the written dataset --------------------------------------------------------------------------
def test_index_and_records_are_valid(dataset):
    index = load_index(dataset)
    assert index.categories == list(CATEGORY_NAMES)
    assert index.symmetry_order == [c.symmetry_order for c in CATEGORIES]
    assert index.symmetric[CATEGORY_NAMES.index("sphere_red")] and not index.symmetric[CATEGORY_NAMES.index("mug")]
    assert index.scene_bounds == TINY.scene_bounds
    assert index.generator["version"] == GENERATOR_VERSION
    assert index.generator["config"] == TINY.to_dict() and index.generator["config_hash"] == TINY.hash()
    assert index.generator["test_seed"] == derive_test_seed(0) != 0
    assert [s["split"] for s in index.scenes] == ["train"] * 4 + ["val", "test"]
    assert index.files("val") == ["val/scene_000000.npz"]
    for i, entry in enumerate(index.scenes):
        rec = load_scene(dataset / entry["file"], bounds=index.scene_bounds, num_categories=len(index.categories))
        assert rec.rgb.shape == (4, 64, 64, 3) and rec.instance is not None
        assert set(np.unique(rec.instance)) <= set(range(rec.num_objects + 1))
        meta = rec.meta
        split = entry["split"]
        assert meta["split"] == split and meta["index"] == (i if split == "train" else 0)
        assert meta["seed"] == (index.generator["test_seed"] if split == "test" else 0)
        assert meta["config_hash"] == TINY.hash() and meta["generator_version"] == GENERATOR_VERSION
        names = [index.categories[c] for c in rec.categories]
        assert names == meta["object_names"]
        # boxes follow the normalised meshes: the largest extent is the object's size
        assert np.all((rec.boxes[:, 3:6].max(1) > 0.37) & (rec.boxes[:, 3:6].max(1) < 0.63))
        assert (rec.depth > 0).mean() > 0.5  # the ground fills most of every view


def _backproject(depth: np.ndarray, K: np.ndarray, world_T_cam: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """World points ``[N, 3]`` of the masked pixels: ``X_cam = depth * K^-1 [u, v, 1]``, ``X = R X_cam + t``."""
    v, u = np.nonzero(mask)
    z = depth[v, u].astype(np.float64)
    Kd = K.astype(np.float64)
    x = (u - Kd[0, 2]) / Kd[0, 0] * z
    y = (v - Kd[1, 2]) / Kd[1, 1] * z
    cam = np.stack([x, y, z], 1)
    T = world_T_cam.astype(np.float64)
    return cam @ T[:3, :3].T + T[:3, 3]


def _in_box(points: np.ndarray, box: np.ndarray, margin: float) -> np.ndarray:
    c, s = math.cos(box[6]), math.sin(box[6])
    d = points - box[:3]
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], 1)
    return np.all(np.abs(local) <= box[3:6] / 2 + margin, axis=1)


def _check_geometry(folder: Path, check_centres: bool) -> tuple[int, int]:
    """Check every view of every scene; return (object views checked, object centres checked)."""
    index = load_index(folder)
    checked = centres = 0
    for entry in index.scenes:
        rec = load_scene(folder / entry["file"])
        boxes = rec.boxes.astype(np.float64)
        for v in range(rec.num_views):
            depth, inst, K, T = rec.depth[v], rec.instance[v], rec.K[v], rec.world_T_cam[v]
            ground = (inst == 0) & (depth > 0)
            assert ground.sum() > 0
            zg = _backproject(depth, K, T, ground)[:, 2]
            assert np.abs(zg).max() < 1e-3, f"{entry['file']} view {v}: ground pixels back-project off z=0"
            for i in range(1, rec.num_objects + 1):
                mask = inst == i
                if not mask.any():
                    continue
                assert np.all(depth[mask] > 0)
                pts = _backproject(depth, K, T, mask)
                inside = _in_box(pts, boxes[i - 1], margin=0.01).mean()
                assert inside >= 0.99, f"{entry['file']} view {v} object {i}: {inside:.3f} of its pixels inside its box"
                checked += 1
                if check_centres:
                    # the projected box centre of a fully framed object lies in its mask's bounding rectangle
                    cam_T_world = np.linalg.inv(T.astype(np.float64))
                    corners = np.c_[box_corners(boxes[i - 1]), np.ones(8)] @ cam_T_world.T
                    uv = corners[:, :3] @ K.astype(np.float64).T
                    uv = uv[:, :2] / uv[:, 2:]
                    H, W = depth.shape
                    if mask.sum() < 10 or not np.all((uv >= 0) & (uv <= [W - 1, H - 1])):
                        continue
                    c = cam_T_world @ np.r_[boxes[i - 1, :3], 1.0]
                    cu, cv = (K.astype(np.float64) @ c[:3])[:2] / c[2]
                    rows, cols = np.nonzero(mask)
                    assert rows.min() <= cv <= rows.max() and cols.min() <= cu <= cols.max()
                    centres += 1
    return checked, centres


def test_geometric_consistency_multi_object(dataset):
    assert _check_geometry(dataset, check_centres=False)[0] >= 10


def test_geometric_consistency_single_object(tmp_path):
    generate_dataset(tmp_path, 4, seed=5, config=SINGLE, split_fractions=(1, 0, 0), workers=1, progress=False)
    checked, centres = _check_geometry(tmp_path, check_centres=True)
    assert checked >= 15 and centres >= 15


# -- determinism and seeds ------------------------------------------------------------------------
def test_same_seed_same_bytes_with_two_workers(dataset, tmp_path):
    generate_dataset(tmp_path, N_SCENES, seed=0, config=TINY, workers=2, progress=False)
    assert _files(tmp_path) == _files(dataset)


def test_other_seed_other_scenes_and_test_seed_only_changes_test(dataset, tmp_path):
    other = tmp_path / "other"
    generate_dataset(other, N_SCENES, seed=1, config=TINY, workers=1, progress=False)
    a, b = load_scene(dataset / "train/scene_000000.npz"), load_scene(other / "train/scene_000000.npz")
    assert not np.array_equal(a.world_T_cam, b.world_T_cam) and not np.array_equal(a.rgb, b.rgb)

    new_test = tmp_path / "new_test"
    generate_dataset(new_test, N_SCENES, seed=0, config=TINY, test_seed=123, workers=1, progress=False)
    fa, fb = _files(dataset), _files(new_test)
    for name in fa:
        if name.startswith(("train/", "val/")):
            assert fa[name] == fb[name], name
    assert fa["test/scene_000000.npz"] != fb["test/scene_000000.npz"]
    assert load_scene(new_test / "test/scene_000000.npz").meta["seed"] == 123


def test_only_some_splits(tmp_path):
    index = generate_dataset(tmp_path, 2, seed=0, config=TINY, splits=["test"], workers=1, progress=False)
    assert [s["file"] for s in index.scenes] == ["test/scene_000000.npz", "test/scene_000001.npz"]
    assert not (tmp_path / "train").exists()


# -- resuming -------------------------------------------------------------------------------------
def test_resume_regenerates_missing_corrupt_and_stale_files_only(dataset, tmp_path):
    work = tmp_path / "resume"
    shutil.copytree(dataset, work)
    (work / "train/scene_000001.npz").unlink()
    corrupt = work / "train/scene_000002.npz"
    corrupt.write_bytes(corrupt.read_bytes()[: corrupt.stat().st_size // 2])
    shutil.copyfile(work / "train/scene_000000.npz", work / "train/scene_000003.npz")  # wrong index in meta
    untouched = work / "val/scene_000000.npz"
    os.utime(untouched, ns=(1_000_000_000_000_000_000, 1_000_000_000_000_000_000))
    (work / "index.json").unlink()
    generate_dataset(work, N_SCENES, seed=0, config=TINY, workers=1, progress=False)
    assert untouched.stat().st_mtime_ns == 1_000_000_000_000_000_000
    assert _files(work) == _files(dataset)


def test_config_change_makes_files_stale(dataset, tmp_path):
    work = tmp_path / "stale"
    shutil.copytree(dataset, work)
    cfg = GeneratorConfig(image_size=(64, 64), num_views=4, shadows=False)
    index = generate_dataset(work, N_SCENES, seed=0, config=cfg, workers=1, progress=False)
    rec = load_scene(work / index.scenes[0]["file"])
    assert rec.meta["config_hash"] == cfg.hash() != TINY.hash()


# -- configuration and arguments ------------------------------------------------------------------
def test_config_hash_and_round_trip():
    cfg = GeneratorConfig(categories=["cube_red", "banana"], image_size=[32, 48])
    assert cfg.categories == ("cube_red", "banana") and cfg.image_size == (32, 48)
    assert GeneratorConfig.from_dict(cfg.to_dict()) == cfg
    assert cfg.hash() == GeneratorConfig.from_dict(cfg.to_dict()).hash()
    assert GeneratorConfig().hash() == GeneratorConfig(categories=CATEGORY_NAMES).hash()
    assert GeneratorConfig().hash() != GeneratorConfig(fov_deg=50).hash()
    assert cfg.symmetry_order == (4, 1)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"categories": ("cube_red", "dragon")}, "categories"),
        ({"categories": "cube_red"}, "categories"),
        ({"categories": ()}, "categories"),
        ({"image_size": (0, 64)}, "image_size"),
        ({"image_size": (64,)}, "image_size"),
        ({"num_views": 0}, "num_views"),
        ({"min_objects": 3, "max_objects": 2}, "min_objects"),
        ({"object_size": -1.0}, "object_size"),
        ({"fov_deg": 180.0}, "fov_deg"),
        ({"elevation_range_deg": (20.0, 95.0)}, "elevation_range_deg"),
        ({"distance_range": (3.0, 2.0)}, "distance_range"),
        ({"placement_radius": 2.0}, "scene_bounds"),
        ({"scene_bounds": ((1, 1, 1), (0, 0, 0))}, "scene_bounds"),
        ({"mesh_faces": -1}, "mesh_faces"),
    ],
)
def test_config_errors_name_the_argument(kwargs, name):
    with pytest.raises(ValueError, match=name):
        GeneratorConfig(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"num_scenes": 0}, "num_scenes"),
        ({"num_scenes": 2.5}, "num_scenes"),
        ({"workers": 0}, "workers"),
        ({"seed": -1}, "seed"),
        ({"test_seed": -3}, "test_seed"),
        ({"splits": ("train", "dev")}, "splits"),
        ({"splits": "train"}, "splits"),
        ({"split_fractions": (0.5, 0.5)}, "split_fractions"),
        ({"split_fractions": (0.0, 0.0, 1.0), "splits": ("train",)}, "split_fractions"),
        ({"config": {"num_views": 4}}, "config"),
    ],
)
def test_generate_errors_name_the_argument(kwargs, name, tmp_path):
    args = {"out": tmp_path, "num_scenes": 2, "progress": False, "workers": 1, **kwargs}
    with pytest.raises(ValueError, match=name):
        generate_dataset(**args)
    assert not (tmp_path / "index.json").exists()


def test_a_spawned_worker_rerunning_an_unguarded_script_says_so_instead_of_waiting(tmp_path):
    """A script generating at its top level (no ``if __name__ == "__main__":``) is re-run by each "spawn" worker;
    the worker used to wait forever for the folder lock its own parent holds. It now raises, naming the script."""
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "unguarded.py"
    script.write_text("from threedq.data import GeneratorConfig, generate_dataset\n"
                      "generate_dataset('d', 4, config=GeneratorConfig(image_size=(32, 32), num_views=2), workers=2,"
                      " progress=False)\n")
    proc = subprocess.Popen([sys.executable, str(script)], cwd=tmp_path, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    lines: list[str] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stderr.readline()
            if not line and proc.poll() is not None:
                break
            lines.append(line)
            if line.startswith("RuntimeError"):
                break
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the pool restarts its failing workers until the run is stopped
        proc.wait()
    said = [x for x in lines if x.startswith("RuntimeError")]
    assert said, "".join(lines[-20:])
    assert str(script) in said[0] and 'if __name__ == "__main__":' in said[0] and "d:" in said[0]


def test_refuse_in_spawned_main_only_while_a_worker_imports_the_main_script(monkeypatch):
    import multiprocessing

    from threedq.data.spawn import refuse_in_spawned_main

    refuse_in_spawned_main("data/x", "generating the dataset")  # the main process: nothing to refuse
    monkeypatch.setattr(multiprocessing.current_process(), "_inheriting", True, raising=False)
    with pytest.raises(RuntimeError, match=r"data/x: .*generating the dataset.*__main__"):
        refuse_in_spawned_main("data/x", "generating the dataset")
