"""benchmarks/device_copy.py: the cut copy of a scene folder reads back as the views it keeps, in their roles."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import device_copy
from threedq.datamodules.scene_folder import SceneFolderDataModule, fixed_views

from threedq.scene import SceneValidationError, load_index, load_scene, save_scene


@pytest.fixture(scope="module")
def copied(tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    tmp = tmp_path_factory.mktemp("device_copy")
    device_copy.pack(tiny_dataset, tmp / "packed", train_views=3, workers=1)
    device_copy.unpack(tmp / "packed", tmp / "copy", workers=1)
    return tiny_dataset, tmp / "copy"


class TestDeviceCopy:
    def test_fixed_views_keep_their_roles(self, copied: tuple[Path, Path]) -> None:
        """The copy's query and gallery views are the original's, pixel for pixel (depth to the millimetre)."""
        src, dst = copied
        a, b = (SceneFolderDataModule(d, seed=0) for d in (src, dst))
        for dm in (a, b):
            dm.setup("test")
        for split in ("val", "test"):
            da, db = a.fixed_view_dataset(split, gallery=True), b.fixed_view_dataset(split, gallery=True)
            assert len(da) == len(db) > 0
            for i in range(len(da)):
                x, y = da[i], db[i]
                assert x["rgb"].shape[0] == y["rgb"].shape[0] == 2
                assert np.array_equal(x["rgb"].numpy(), y["rgb"].numpy())
                assert np.abs(x["depth"].numpy() - y["depth"].numpy()).max() <= 0.0005 + 1e-6
                assert np.array_equal(x["R_T_cam"].numpy(), y["R_T_cam"].numpy())
                assert np.array_equal(x["boxes"].numpy(), y["boxes"].numpy())

    def test_training_scenes_keep_seeded_views(self, copied: tuple[Path, Path]) -> None:
        src, dst = copied
        index = load_index(src)
        for k, s in enumerate(index.scenes):
            if s["split"] != "train":
                continue
            a, b = load_scene(src / s["file"]), load_scene(dst / s["file"])
            views = device_copy.copy_views("train", 0, k, a.rgb.shape[0], 3, 12345, 0)
            assert len(set(views.tolist())) == b.rgb.shape[0] == 3
            assert np.array_equal(a.rgb[views], b.rgb) and np.array_equal(a.K[views], b.K)
            assert b.instance is None and b.meta == a.meta

    def test_copy_order_is_the_inverse_of_the_copys_view_rule(self) -> None:
        for pos in range(40):
            stored = device_copy.copy_views("test", pos, 999, 28, 6, 1, 7)
            read = stored[fixed_views(7, pos, 2, 2)]
            assert np.array_equal(read, fixed_views(7, pos, 28, 2))

    def test_depth_beyond_the_format_is_refused(self, tiny_dataset: Path, tmp_path: Path) -> None:
        src = tmp_path / "far"
        shutil.copytree(tiny_dataset, src)
        f = load_index(src).files("test")[0]
        rec = load_scene(src / f)
        rec.depth[:] = np.where(rec.depth > 0, 70.0, 0.0)
        save_scene(src / f, rec, validate=False)
        with pytest.raises(SceneValidationError, match=r"far/test/.*depth.*65\.535 m"):
            device_copy.pack(src, tmp_path / "out", workers=1)

    def test_corrupt_packed_scene_names_the_file(self, copied: tuple[Path, Path], tmp_path: Path) -> None:
        packed = copied[1].parent / "packed"
        bad = tmp_path / "bad"
        shutil.copytree(packed, bad)
        f = load_index(bad).files("train")[0]
        (bad / f).write_bytes(b"not a zip")
        with pytest.raises(SceneValidationError, match=rf"{Path(f).name}"):
            device_copy.unpack(bad, tmp_path / "copy", workers=1)

    def test_too_few_training_views(self, tiny_dataset: Path, tmp_path: Path) -> None:
        with pytest.raises(ValueError, match="train_views"):
            device_copy.pack(tiny_dataset, tmp_path / "x", train_views=1)
