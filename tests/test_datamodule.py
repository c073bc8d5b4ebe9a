"""The scene-folder and embedded-data DataModules: sample layout, determinism, generation on first use."""

from __future__ import annotations

import shutil
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch

from threedq.datamodules.clevr_veggie import ClevrVeggieDataModule
from threedq.datamodules.scene_folder import SENSOR_PROPOSALS, SceneDataset, SceneFolderDataModule
from threedq.boxes import boxes_to_aabb
from threedq.scene import SceneValidationError, load_index, load_scene


class TestSceneFolderDataModule:
    def test_sample_layout(self, tiny_dataset: Path) -> None:
        dm = SceneFolderDataModule(str(tiny_dataset), batch_size=2, num_input_views=2, num_target_views=1)
        dm.setup("fit")
        batch = next(iter(dm.train_dataloader()))
        assert batch["rgb"].shape == (2, 3, 3, 32, 32) and batch["rgb"].dtype == torch.float32
        assert 0 <= batch["rgb"].min() and batch["rgb"].max() <= 1
        assert batch["depth"].shape == (2, 3, 32, 32)
        assert batch["K"].shape == (2, 3, 3, 3) and batch["R_T_cam"].shape == (2, 3, 4, 4)
        assert batch["instance"].shape == (2, 3, 32, 32)
        assert batch["boxes"].shape == (2, 3, 7) and batch["aabb"].shape == (2, 3, 6)
        assert batch["box_mask"].dtype == torch.bool
        # views of one sample are distinct
        for ids in batch["view_ids"]:
            assert len(set(ids.tolist())) == 3
        # padding: categories -1 and zero boxes exactly where the mask is off
        assert torch.all((batch["categories"] >= 0) == batch["box_mask"])
        assert torch.all(batch["boxes"][~batch["box_mask"]] == 0)

    def test_sensor_captures_level_the_floor(self, tiny_dataset: Path, tmp_path: Path) -> None:
        """A copy whose every pose is tilted by 3 degrees (a tracker's gravity): with ``sensor_captures`` the samples'
        floor is level at z = 0 again; without, the tilt stays. The embedded data's DataModule leaves it off."""
        import math

        from scipy.spatial.transform import Rotation

        from threedq.geometry.camera import depth_to_points
        from threedq.geometry.ground import fit_ground_plane
        from threedq.scene import save_scene

        data = tmp_path / "tilted"
        shutil.copytree(tiny_dataset, data)
        G = np.eye(4)
        G[:3, :3] = Rotation.from_rotvec([math.radians(3.0), 0.0, 0.0]).as_matrix()
        for f in load_index(data).files("test"):
            rec = load_scene(data / f)
            rec.world_T_cam = (G @ rec.world_T_cam.astype(np.float64)).astype(np.float32)
            save_scene(data / f, rec)

        def floor_tilt(sensor: bool) -> float:
            dm = SceneFolderDataModule(str(data), num_input_views=4, num_target_views=0, sensor_captures=sensor)
            sample = dm.fixed_view_dataset("test", with_boxes=False)[0]
            pts, valid = depth_to_points(sample["depth"], sample["K"], sample["R_T_cam"])
            n, _, _ = fit_ground_plane(pts[valid].double().numpy(), camera_centres=sample["R_T_cam"][:, :3, 3].numpy())
            return math.degrees(math.acos(min(1.0, n[2])))

        assert abs(floor_tilt(False) - 3.0) < 0.3 and floor_tilt(True) < 0.3
        assert not ClevrVeggieDataModule(str(data)).sensor_captures and SceneFolderDataModule(str(data)).sensor_captures

    def test_sensor_captures_even_out_exposure(self, tiny_dataset: Path, tmp_path: Path) -> None:
        """A copy whose views were given other exposure and white-balance gains: with ``sensor_captures`` the floor
        takes one colour in every view of a sample again; without, the gains stay."""
        from threedq.geometry.camera import depth_to_points
        from threedq.scene import save_scene

        data = tmp_path / "exposed"
        shutil.copytree(tiny_dataset, data)
        for f in load_index(data).files("test"):
            rec = load_scene(data / f)
            gains = np.random.default_rng(0).uniform(0.7, 1.3, (rec.num_views, 1, 1, 3))
            rec.rgb = np.clip(np.round(rec.rgb * gains), 0, 255).astype(np.uint8)
            save_scene(data / f, rec)

        def floor_spread(sensor: bool) -> float:
            dm = SceneFolderDataModule(str(data), num_input_views=4, num_target_views=0, sensor_captures=sensor)
            sample = dm.fixed_view_dataset("test", with_boxes=False)[0]
            pts, valid = depth_to_points(sample["depth"], sample["K"], sample["R_T_cam"])
            floor = valid & (pts[..., 2].abs() < 0.01)
            rgb = sample["rgb"].permute(0, 2, 3, 1).reshape(4, -1, 3)
            med = torch.stack([rgb[i][floor[i].reshape(-1)].median(0).values for i in range(4)])
            return float((med / med.median(0).values).log().std())

        assert floor_spread(False) > 0.05 and floor_spread(True) < 0.02

    def test_matches_record(self, tiny_dataset: Path) -> None:
        index = load_index(tiny_dataset)
        ds = SceneDataset(tiny_dataset, index, "val", num_input_views=1, num_target_views=1, seed=3)
        item = ds[0]
        rec = load_scene(tiny_dataset / index.files("val")[0])
        v = item["view_ids"].numpy()
        np.testing.assert_array_equal((item["rgb"].permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8), rec.rgb[v])
        np.testing.assert_array_equal(item["R_T_cam"].numpy(), rec.world_T_cam[v])
        M = rec.num_objects
        np.testing.assert_allclose(item["aabb"][:M].numpy(), boxes_to_aabb(rec.boxes.astype(np.float64)), atol=1e-5)
        assert item["categories"][:M].tolist() == rec.categories.tolist()

    def test_fixed_views_are_deterministic(self, tiny_dataset: Path) -> None:
        index = load_index(tiny_dataset)
        a = SceneDataset(tiny_dataset, index, "test", seed=1)[1]["view_ids"]
        b = SceneDataset(tiny_dataset, index, "test", seed=1)[1]["view_ids"]
        assert torch.equal(a, b)

    def test_fixed_view_dataset_and_pseudo_boxes(self, tiny_dataset: Path, tmp_path: Path) -> None:
        from threedq.data.proposal_cache import propose_dataset

        data = tmp_path / "data"
        shutil.copytree(tiny_dataset, data)
        dm = SceneFolderDataModule(str(data), num_input_views=2, num_target_views=1)
        dm.setup("test")
        # the fixed-view dataset of a held-out split is the loader's own (held-out splits draw no random views)
        ref, got = dm.datasets["test"], dm.fixed_view_dataset("test")
        assert len(ref) == len(got) > 0
        for i in range(len(ref)):
            a, b = ref[i], got[i]
            assert torch.equal(a["rgb"][:2], b["rgb"]) and torch.equal(a["aabb"], b["aabb"])
            assert b["rgb"].shape[0] == 2  # no target view unless the gallery is asked for
        gal = dm.fixed_view_dataset("test", gallery=True)[0]
        assert gal["rgb"].shape[0] == 3 and torch.equal(gal["rgb"][:2], got[0]["rgb"])
        # the pseudo-boxes: the proposals of every second view, written once to the split's cache
        boxes = dm.pseudo_boxes("test")
        assert (data / "proposals" / "test.npz").is_file()
        direct = propose_dataset(data, "test", tmp_path / "ref.npz", params=SENSOR_PROPOSALS, progress=False)
        assert sorted(boxes) == sorted(direct) == sorted(dm.index.files("test"))
        for f in boxes:
            assert np.allclose(boxes[f][0], direct[f][0]) and np.allclose(boxes[f][1], direct[f][1])
        # boxes="proposals": the samples carry those boxes (a training split keeps the ones matching no object)
        # (read as renders: at 32 x 32 px the sensor preset's measured ground margin leaves these tiny scenes no box)
        dp = SceneFolderDataModule(str(data), num_input_views=2, boxes="proposals", sensor_captures=False)
        train = dp.pseudo_boxes("train")
        s0 = dp.fixed_view_dataset("train")[0]
        n = len(train[dp.index.files("train")[0]][0])
        assert n > 0 and int(s0["box_mask"].sum()) == min(n, dp.max_boxes)
        assert torch.equal(dp.fixed_view_dataset("test", with_boxes=False)[0]["aabb"], got[0]["aabb"])

    def test_fixed_views_are_read_once_and_again_after_a_rewrite(self, tiny_dataset: Path, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
        """The fixed views of a scene come from the process-wide view cache the second time (equal samples, no
        read), and a rewritten file is read again; random views are never cached."""
        import threedq.datamodules.scene_folder as sf

        data = tmp_path / "d"
        shutil.copytree(tiny_dataset, data)
        index = load_index(data)
        reads: list[str] = []
        real = sf.load_scene
        monkeypatch.setattr(sf, "load_scene", lambda path, **kw: reads.append(str(path)) or real(path, **kw))
        ds = SceneDataset(data, index, "val", num_input_views=1, num_target_views=1, seed=3)
        first = ds[0]
        again = SceneDataset(data, index, "val", num_input_views=1, num_target_views=1, seed=3)[0]
        assert len(reads) == 1
        for k, v in first.items():
            assert torch.equal(v, again[k]), k
        again["rgb"].mul_(0)  # a consumer writing into its sample does not reach the cache
        assert torch.equal(ds[0]["rgb"], first["rgb"]) and len(reads) == 1
        path = data / index.files("val")[0]
        rec = load_scene(path)
        rec.rgb[:] = 255 - rec.rgb
        from threedq.scene import save_scene

        save_scene(path, rec)
        changed = ds[0]
        assert len(reads) == 2 and torch.allclose(changed["rgb"], 1 - first["rgb"])
        rnd = SceneDataset(data, index, "train", num_input_views=1, num_target_views=0, random_views=True)
        n = len(reads)
        rnd[0], rnd[0]
        assert len(reads) == n + 2

    def test_random_views_follow_the_seed(self, tiny_dataset: Path) -> None:
        index = load_index(tiny_dataset)
        ds = SceneDataset(tiny_dataset, index, "train", num_input_views=2, random_views=True)
        L.seed_everything(11, verbose=False)
        a = [ds[i]["view_ids"] for i in range(4)]
        L.seed_everything(11, verbose=False)
        b = [ds[i]["view_ids"] for i in range(4)]
        assert all(torch.equal(x, y) for x, y in zip(a, b))

    def test_errors(self, tiny_dataset: Path, tmp_path: Path) -> None:
        index = load_index(tiny_dataset)
        with pytest.raises(ValueError, match="split"):
            SceneDataset(tiny_dataset, index, "nope")
        with pytest.raises(SceneValidationError, match="needs 5 distinct views but the scene has 4"):
            SceneDataset(tiny_dataset, index, "train", num_input_views=4, num_target_views=1)[0]
        with pytest.raises(SceneValidationError, match="max_objects"):
            # a scene with more objects than the padding size is an error, not a silent truncation
            big = next(i for i, f in enumerate(index.files("train")) if load_scene(tiny_dataset / f).num_objects > 1)
            SceneDataset(tiny_dataset, index, "train", max_objects=1)[big]
        with pytest.raises(SceneValidationError, match="index.json"):
            SceneFolderDataModule(str(tmp_path)).setup()
        # a corrupt scene file is named in the error
        copy = tmp_path / "copy"
        shutil.copytree(tiny_dataset, copy)
        f = copy / index.files("train")[0]
        f.write_bytes(f.read_bytes()[:100])
        with pytest.raises(SceneValidationError, match=str(f.name)):
            SceneDataset(copy, load_index(copy), "train")[0]


class TestClevrVeggieDataModule:
    def test_generates_on_first_use_then_reuses(self, tmp_path: Path) -> None:
        kwargs = dict(num_scenes=3, image_size=(32, 32), num_views=3, generator_workers=1, batch_size=1)
        dm = ClevrVeggieDataModule(data_dir=str(tmp_path / "d"), **kwargs)
        dm.prepare_data()
        index = load_index(tmp_path / "d")
        assert len(index.scenes) == 3 and len(index.categories) == 41
        before = {p: p.stat().st_mtime_ns for p in (tmp_path / "d").rglob("*.npz")}
        dm2 = ClevrVeggieDataModule(data_dir=str(tmp_path / "d"), **kwargs)
        dm2.prepare_data()  # cached: nothing rewritten
        assert before == {p: p.stat().st_mtime_ns for p in (tmp_path / "d").rglob("*.npz")}
        dm2.setup("fit")
        assert next(iter(dm2.train_dataloader()))["rgb"].shape == (1, 2, 3, 32, 32)

    def test_config_mismatch_is_an_error(self, tiny_dataset: Path) -> None:
        dm = ClevrVeggieDataModule(data_dir=str(tiny_dataset), image_size=(64, 64), num_views=4)
        with pytest.raises(SceneValidationError, match="different generator config"):
            dm.prepare_data()
