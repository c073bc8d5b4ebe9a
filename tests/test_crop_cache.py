"""The content-keyed crop cache: fingerprints, lookups, eviction, and crops identical to uncached ones."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from threedq.datamodules.scene_folder import SceneFolderDataModule
from threedq.stages.base import EncoderStage
from threedq.stages.crop_cache import (
    CropCache, module_fingerprint, pack_bits, pack_sparse, sample_key, unpack_bits, unpack_sparse,
)
from threedq.pipeline.evaluation import collect_object_crops
from threedq.nets import UNet3D
from threedq.pipeline.report import split_loader


@pytest.fixture(scope="module")
def dm(tiny_dataset: Path) -> SceneFolderDataModule:
    d = SceneFolderDataModule(str(tiny_dataset), batch_size=2, num_input_views=1, num_target_views=0)
    d.setup()
    return d


@pytest.fixture(scope="module")
def batch(dm: SceneFolderDataModule) -> dict[str, torch.Tensor]:
    return next(iter(split_loader(dm, "train", batch_size=2)))


def _stage(seed: int = 0) -> EncoderStage:
    torch.manual_seed(seed)
    return EncoderStage(grid_resolution=(32, 32, 16), feature_dim=8).eval()


class TestModuleFingerprint:
    def test_same_weights_same_print(self) -> None:
        a, b = UNet3D(4, 8), UNet3D(4, 8)
        assert module_fingerprint(a) != module_fingerprint(b)  # different random init
        b.load_state_dict(a.state_dict())
        assert module_fingerprint(a) == module_fingerprint(b)

    def test_one_changed_value_changes_it(self) -> None:
        a = UNet3D(4, 8)
        before = module_fingerprint(a)
        with torch.no_grad():
            next(a.parameters()).view(-1)[0] += 1e-6
        assert module_fingerprint(a) != before

    def test_memo_follows_in_place_writes(self) -> None:
        a, b = UNet3D(4, 8), UNet3D(4, 8)
        cache = CropCache()
        first = cache.fingerprint(a)
        assert cache.fingerprint(a) == first
        a.load_state_dict(b.state_dict())  # copy_ into the same tensors bumps their version counters
        assert cache.fingerprint(a) == module_fingerprint(b) != first


class TestPackSparse:
    """The compact form of the cached encoder inputs: a round trip must be bitwise, signed zeros and NaN included."""

    def test_round_trip_is_bitwise(self) -> None:
        t = torch.zeros(2, 4, 3, 5)
        t[0, 1, 2, 3], t[1, 0, 0, 0], t[1, 3, 2, 4] = 0.25, -0.0, float("nan")
        t[0, 2] = torch.rand(3, 5)
        index, values = pack_sparse(t)
        assert index.dtype == torch.int32 and values.dtype == t.dtype
        # a naive loop: every flat position whose value is not +0.0 (the non-zeros, the NaN, the -0.0), in order
        naive = [i for i, v in enumerate(t.reshape(-1).tolist()) if not (v == 0 and math.copysign(1.0, v) > 0)]
        assert index.tolist() == naive
        back = unpack_sparse(index, values, tuple(t.shape))
        assert back.view(torch.int32).equal(t.view(torch.int32))  # bit for bit: -0.0 and NaN come back as they were

    def test_other_dtypes_and_empty(self) -> None:
        for t in (torch.tensor([[True, False], [False, True]]), torch.tensor([0, 3, 0, -2]),
                  torch.zeros(3, 3, dtype=torch.bfloat16).index_fill_(0, torch.tensor([1]), 1.5), torch.zeros(0, 4)):
            index, values = pack_sparse(t)
            back = unpack_sparse(index, values, tuple(t.shape))
            assert back.dtype == t.dtype and torch.equal(back, t)
        index, values = pack_sparse(torch.zeros(6))
        assert index.numel() == 0 and torch.equal(unpack_sparse(index, values, (2, 3)), torch.zeros(2, 3))

    def test_a_hand_made_case(self) -> None:
        index, values = pack_sparse(torch.tensor([[0.0, 2.0], [0.0, -1.0]]))
        assert index.tolist() == [1, 3] and values.tolist() == [2.0, -1.0]


class TestPackBits:
    def test_round_trip(self) -> None:
        g = torch.Generator().manual_seed(0)
        for shape in ((2, 1, 4, 8, 8), (3, 5), (7,), (0, 3)):
            mask = torch.rand(shape, generator=g) > 0.5
            bits = pack_bits(mask)
            assert bits.dtype == torch.uint8 and bits.numel() == -(-mask.numel() // 8)
            assert torch.equal(unpack_bits(bits, shape), mask)

    def test_a_hand_made_case(self) -> None:
        bits = pack_bits(torch.tensor([True, False, False, False, False, False, False, True, True]))
        assert bits.tolist() == [0b10000001, 0b10000000]  # first entry in the highest bit


class TestInputWithCache:
    """The unprojected input (``views_input``), kept per scene under the ``input`` kind: it depends on the views and
    the grid, not on the encoder, so a new encoder reads the inputs an earlier one's stage computed."""

    def _views(self, batch: dict[str, torch.Tensor], n: int = 1) -> tuple[torch.Tensor, ...]:
        return tuple(batch[k][:, :n] for k in ("rgb", "depth", "K", "R_T_cam"))

    def test_hit_is_bitwise_encoder_input_and_survives_new_weights(self, batch: dict[str, torch.Tensor]) -> None:
        stage = _stage(0)
        views = self._views(batch, 2)  # two views per scene: scene-major like encoder_input's flattening
        ref_x, ref_seen = stage.encoder_input(*(v.flatten(0, 1) for v in views))
        stage.use_crop_cache(CropCache())
        with torch.no_grad():
            first = stage.views_input(*views)
            stage.encoder.load_state_dict(_stage(1).encoder.state_dict())  # another encoder: same inputs
            stage.crop_cache.drop("grid")
            second = stage.views_input(*views)
        B = batch["rgb"].shape[0]
        assert stage.crop_cache.hits == 3 * B and stage.crop_cache.misses == 3 * B
        for x, seen in (first, second):
            assert x.dtype == ref_x.dtype and seen.dtype == ref_seen.dtype
            assert x.view(torch.int32).equal(ref_x.view(torch.int32)) and torch.equal(seen, ref_seen)
        # kept compact: fewer bytes than the dense input
        stored = sum(v.numel() * v.element_size() for k, v in stage.crop_cache._store.items() if k[0] == "input")
        assert stored < (ref_x.numel() * ref_x.element_size()) / 2

    def test_other_views_miss(self, batch: dict[str, torch.Tensor]) -> None:
        stage = _stage()
        stage.use_crop_cache(CropCache())
        rgb, depth, K, pose = self._views(batch)
        with torch.no_grad():
            stage.views_input(rgb, depth, K, pose)
            x, _ = stage.views_input(rgb, depth * 1.01, K, pose)
        assert stage.crop_cache.hits == 0
        assert torch.equal(x, stage.encoder_input(rgb.flatten(0, 1), (depth * 1.01).flatten(0, 1), K.flatten(0, 1),
                                                  pose.flatten(0, 1))[0])

    def test_not_used_with_gradient_or_training_encoder(self, batch: dict[str, torch.Tensor]) -> None:
        """A training step's views may be drawn at random: its inputs are not kept."""
        stage = _stage()
        stage.use_crop_cache(CropCache())
        stage.views_input(*self._views(batch))
        stage.train()
        with torch.no_grad():
            stage.views_input(*self._views(batch))
        assert len(stage.crop_cache) == 0


class TestEncoderInput:
    """``encoder_input``: the paper's ``cat[occ, occ * rgb]`` of the unprojected views."""

    def test_against_independent_references(self, batch: dict[str, torch.Tensor]) -> None:
        from threedq.geometry import occupancy_from_depth, unproject_rgb

        rgb, depth, K, pose = (batch[k][:, 0] for k in ("rgb", "depth", "K", "R_T_cam"))
        stage = EncoderStage(grid_resolution=(32, 32, 16), feature_dim=8)
        x, _ = stage.encoder_input(rgb, depth, K, pose)
        occ = occupancy_from_depth(depth, K, pose, stage.grid)
        ray_rgb = unproject_rgb(rgb, K, pose, stage.grid)
        assert torch.equal(x, torch.cat([occ, occ * ray_rgb], dim=1)) and occ.sum() > 0


class TestSampleKey:
    def test_depends_on_views_boxes_and_size(self, batch: dict[str, torch.Tensor]) -> None:
        k = sample_key(batch, 0, 1, 8)
        assert k == sample_key({key: v.clone() for key, v in batch.items() if torch.is_tensor(v)}, 0, 1, 8)
        assert k != sample_key(batch, 1, 1, 8)
        assert k != sample_key(batch, 0, 1, 16)
        moved = dict(batch, aabb=batch["aabb"] + 0.01)
        assert k != sample_key(moved, 0, 1, 8)
        darker = dict(batch, rgb=batch["rgb"] * 0.5)
        assert k != sample_key(darker, 0, 1, 8)


class TestCropCache:
    def test_all_or_nothing_and_counts(self) -> None:
        cache = CropCache()
        cache.put(("a",), torch.ones(2, 3))
        assert cache.get_many([("a",), ("b",)]) is None
        assert (cache.misses, cache.hits) == (2, 0)
        got = cache.get_many([("a",)])
        assert got is not None and torch.equal(got[0], torch.ones(2, 3))
        assert cache.hits == 1 and len(cache) == 1 and cache.nbytes == 6 * 4

    def test_stores_a_copy(self) -> None:
        cache, t = CropCache(), torch.zeros(3)
        cache.put(("t",), t)
        t += 1
        assert torch.equal(cache.get_many([("t",)])[0], torch.zeros(3))

    def test_evicts_oldest_beyond_max_bytes(self) -> None:
        cache = CropCache(max_bytes=100)
        for i in range(5):
            cache.put((str(i),), torch.zeros(10))  # 40 bytes each
        assert cache.nbytes <= 100 and len(cache) == 2
        assert cache.get_many([("0",)]) is None and cache.get_many([("3",), ("4",)]) is not None
        cache.put(("4",), torch.zeros(5))  # replacing an entry accounts for the old one
        assert cache.nbytes == 40 + 20

    def test_drop_one_kind(self) -> None:
        cache = CropCache()
        cache.put(("features", "enc1", "s0"), torch.zeros(4))
        cache.put(("features", "enc1", "s1"), torch.zeros(2))
        cache.put(("raw", "s0"), torch.zeros(3))
        assert cache.drop("features") == 2
        assert len(cache) == 1 and cache.nbytes == 3 * 4 and cache.get_many([("raw", "s0")]) is not None
        assert cache.drop("random") == 0

    def test_entries_made_in_inference_mode_are_plain(self) -> None:
        cache = CropCache()
        with torch.inference_mode():
            cache.put(("i",), torch.ones(3))
        got = cache.get_many([("i",)])[0]
        assert not got.is_inference()
        got.add_(1)  # in-place use outside inference mode is allowed

    def test_bad_size(self) -> None:
        with pytest.raises(ValueError, match="max_bytes"):
            CropCache(max_bytes=0)


class TestGridsWithCache:
    """Whole feature grids (``encode_views``) kept under the ``grid`` kind, keyed by the views alone."""

    def _views(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:
        return tuple(batch[k][:, :1] for k in ("rgb", "depth", "K", "R_T_cam"))

    def test_hit_equals_uncached_and_ignores_boxes(self, batch: dict[str, torch.Tensor]) -> None:
        stage = _stage()
        with torch.no_grad():
            ref = stage.encode_views(*self._views(batch))
            stage.use_crop_cache(CropCache())
            first = stage.encode_views(*self._views(batch))
            other_boxes = {**batch, "aabb": batch["aabb"] + 0.1}
            second = stage.encode_views(*self._views(other_boxes))
        # 2 scenes: grid misses, then the 3 parts of each scene's unprojected input; then 2 grid hits
        assert stage.crop_cache.misses == 2 + 2 * 3 and stage.crop_cache.hits == 2
        assert torch.equal(first, ref) and torch.equal(second, ref)
        assert {k[0] for k in stage.crop_cache._store} == {"grid", "input"}
        assert stage.crop_cache.drop("grid") == 2 and stage.crop_cache.drop("input") == 2 * 3
        assert len(stage.crop_cache) == 0

    def test_other_views_or_weights_miss(self, batch: dict[str, torch.Tensor]) -> None:
        stage = _stage(0)
        stage.use_crop_cache(CropCache())
        with torch.no_grad():
            stage.encode_views(*self._views(batch))
            rgb, depth, K, pose = self._views(batch)
            stage.encode_views(rgb.flip(-1), depth, K, pose)
            assert stage.crop_cache.hits == 0
            stage.encoder.load_state_dict(_stage(1).encoder.state_dict())
            fresh = stage.encode_views(rgb, depth, K, pose)
            assert stage.crop_cache.hits == 3 * rgb.shape[0]  # the grids of new weights miss; the inputs are the same
            stage.use_crop_cache(None)
            assert torch.equal(fresh, stage.encode_views(rgb, depth, K, pose))

    def test_not_used_with_gradient(self, batch: dict[str, torch.Tensor]) -> None:
        stage = _stage()
        stage.use_crop_cache(CropCache())
        stage.encode_views(*self._views(batch))
        assert len(stage.crop_cache) == 0


class TestObjectCropsWithCache:
    def test_hit_equals_uncached(self, batch: dict[str, torch.Tensor]) -> None:
        stage = _stage()
        with torch.no_grad():
            ref = stage.object_crops(batch, 1, 8)
            stage.use_crop_cache(CropCache())
            first = stage.object_crops(batch, 1, 8)
            assert stage.crop_cache.misses > 0 and stage.crop_cache.hits == 0
            second = stage.object_crops(batch, 1, 8)
        assert stage.crop_cache.hits == 2 * batch["rgb"].shape[0]  # features + raw per sample (no input asked)
        for k in ref:
            assert torch.equal(first[k], ref[k]) and torch.equal(second[k], ref[k]), k

    def test_grids_shared_with_encode_views(self, batch: dict[str, torch.Tensor]) -> None:
        """object_crops keeps the whole grid: encode_views of the same views is then a hit equal to an uncached
        encoding, and crops of other boxes (the next round's detections) are cut from it without encoding again."""
        stage = _stage()
        views = tuple(batch[k][:, :1] for k in ("rgb", "depth", "K", "R_T_cam"))
        with torch.no_grad():
            ref_grid = stage.encode_views(*views)
            other = {**batch, "aabb": batch["aabb"] + 0.05}
            ref_other = stage.object_crops(other, 1, 8)
            stage.use_crop_cache(CropCache())
            stage.object_crops(batch, 1, 8)
            B = batch["rgb"].shape[0]
            assert {k[0] for k in stage.crop_cache._store} == {"features", "raw", "grid", "input"}
            hits = stage.crop_cache.hits
            grid = stage.encode_views(*views)
            assert stage.crop_cache.hits == hits + B
            calls = []
            stage.encoder.register_forward_hook(lambda *a: calls.append(1))
            got = stage.object_crops(other, 1, 8)
        assert torch.equal(grid, ref_grid)
        assert not calls  # new boxes, same views and weights: no encoder pass
        for k in ref_other:
            assert torch.equal(got[k], ref_other[k]), k

    def test_new_weights_are_a_miss(self, batch: dict[str, torch.Tensor]) -> None:
        stage = _stage(0)
        stage.use_crop_cache(CropCache())
        with torch.no_grad():
            stage.object_crops(batch, 1, 8)
            stage.encoder.load_state_dict(_stage(1).encoder.state_dict())
            fresh = stage.object_crops(batch, 1, 8)
            stage.use_crop_cache(None)
            ref = stage.object_crops(batch, 1, 8)
        assert torch.equal(fresh["features"], ref["features"])

    def test_not_used_with_gradient_or_training_encoder(self, batch: dict[str, torch.Tensor]) -> None:
        stage = _stage()
        stage.use_crop_cache(CropCache())
        stage.object_crops(batch, 1, 8)  # grad enabled
        assert len(stage.crop_cache) == 0
        stage.train()
        with torch.no_grad():
            stage.object_crops(batch, 1, 8)  # BatchNorm in training mode
        assert len(stage.crop_cache) == 0

    def test_collect_with_cache_equals_without(self, dm: SceneFolderDataModule) -> None:
        stage = _stage()
        ref = collect_object_crops(stage, split_loader(dm, "test", batch_size=1), crop_size=8, progress=False)
        stage.use_crop_cache(CropCache())
        for _ in range(2):  # fill, then hit
            got = collect_object_crops(stage, split_loader(dm, "test", batch_size=1), crop_size=8, progress=False)
            for k in ref:
                assert torch.equal(got[k], ref[k]), k
        assert stage.crop_cache.hits > 0

