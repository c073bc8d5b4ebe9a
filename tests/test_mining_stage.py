"""The correspondence-learning stage (stages/mining.py, its pair sources and positives): the pieces against
hand-computed cases and naive loops, and a short fit of each source (vc, vc_moco, mined) and pair source."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from conftest import refused as refused_by
from conftest import tiny_data_yaml
from threedq.geometry import rotate_yaw
from threedq.stages.mining import Mining, gt_box_iou, implied_yaw_error_deg
from threedq.stages.pair_sources import input_pairs, mutual_pool_neighbours, pool_shape_agreement, spread_candidates
from threedq.stages.positives import (
    corner_keys,
    corner_offsets,
    crop_voxels,
    occupancy_positives,
    shape_agreement,
    shape_cells,
)
from threedq.viz.features import mined_pairs_figure


class TestCornerOffsets:
    def test_hand_computed(self) -> None:
        off = corner_offsets(4, 2)
        assert off.shape == (8, 3)
        assert set(off.flatten().tolist()) == {-3, 4}
        # centred on the patch centre (start + 0.5): corners at -3.5 and +3.5
        assert torch.allclose(off.float().mean(0), torch.full((3,), 0.5))
        assert len({tuple(r) for r in off.tolist()}) == 8

    def test_patch_of_four(self) -> None:
        assert set(corner_offsets(3, 4).flatten().tolist()) == {-1, 4}


class TestCornerKeys:
    def test_planted_shift_and_jitter(self) -> None:
        torch.manual_seed(0)
        q = F.normalize(torch.randn(8, 16, 16, 16), dim=0)
        shift = torch.tensor([1, -2, 2])
        t = torch.roll(q, shifts=tuple(shift.tolist()), dims=(1, 2, 3))  # target = query moved by +shift
        qpos = torch.tensor([6, 7, 5])
        off = corner_offsets(4, 2)
        voxels, keys = corner_keys(q, qpos, t, qpos + shift, off, search=0)
        assert torch.equal(voxels, qpos + off)
        expect = F.normalize(q[:, voxels[:, 0], voxels[:, 1], voxels[:, 2]].T, dim=1)
        assert torch.allclose(keys, expect, atol=1e-6)
        # the match is off by one voxel: the 3^3 search finds the true corners again, no search does not
        _, found = corner_keys(q, qpos, t, qpos + shift + torch.tensor([0, 1, 0]), off, search=1)
        assert torch.allclose(found, expect, atol=1e-6)
        _, missed = corner_keys(q, qpos, t, qpos + shift + torch.tensor([0, 1, 0]), off, search=0)
        assert not torch.allclose(missed, expect, atol=1e-3)

    def test_clamped_into_the_crop(self) -> None:
        q = torch.randn(4, 8, 8, 8)
        voxels, keys = corner_keys(q, torch.tensor([0, 0, 6]), q, torch.tensor([0, 0, 6]), corner_offsets(4, 2), 1)
        assert voxels.min() >= 0 and voxels.max() <= 7 and keys.shape == (8, 4)


class TestImpliedYawError:
    def test_hand_computed(self) -> None:
        A = 36
        # query at 50 deg, target at 20 deg: rotating the target by 30 deg (b = 3) aligns it
        err = implied_yaw_error_deg(torch.tensor([3, 4, 33]), A, torch.full((3,), math.radians(50)),
                                    torch.full((3,), math.radians(20)), torch.ones(3, dtype=torch.long))
        assert torch.allclose(err, torch.tensor([0.0, 10.0, 60.0], dtype=torch.float64), atol=1e-5)

    def test_symmetry(self) -> None:
        # a 2-fold symmetric object: 180 deg off is no error
        err = implied_yaw_error_deg(torch.tensor([18]), 36, torch.zeros(1), torch.zeros(1), torch.tensor([2]))
        assert float(err) == pytest.approx(0.0, abs=1e-9)


def test_mined_pairs_figure() -> None:
    raw = torch.zeros(2, 4, 8, 8, 8)
    raw[:, 0, :3] = 1.0
    raw[:, 1:, :3] = 0.3
    img = mined_pairs_figure(raw, raw, torch.tensor([[0, 1, 2], [2, 2, 2]]), torch.tensor([[0, 3, 3], [1, 1, 1]]),
                             ["a", "b"], scale=4)
    assert img.dtype.name == "uint8" and img.shape[2] == 3
    assert img.shape[0] == 2 * (18 + 32) + 4 and img.shape[1] == 2 * 32 + 4
    assert (img[..., 0] == 255).any() and ((img[..., 0] == 255) & (img[..., 1] == 0)).any()  # red patch boxes


def refused(**init_args: object) -> str:
    """The parser's error for the mining stage's ``init_args`` on the tiny grid."""
    return refused_by(Mining, grid_resolution=[32, 32, 16], **init_args)


class TestMiningArguments:
    def test_each_argument_is_checked_by_its_type(self) -> None:
        for name, bad in (("source", "views"), ("keep", 0), ("queue_size", -1), ("query_pool", 1.5),
                          ("context_quantile", 1.0), ("momentum", 1.5), ("positives", "corners"),
                          ("yaw_window", -1), ("corner_search", -1), ("rank_by", "cosine")):
            assert name in refused(**{name: bad}), name

    def test_good_arguments_parse_to_plain_numbers(self) -> None:
        from jsonargparse import ArgumentParser

        parser = ArgumentParser(exit_on_error=False)
        parser.add_class_arguments(Mining, "model")
        cfg = parser.parse_object({"model": {"grid_resolution": [32, 32, 16], "queue_size": 64, "keep": 7,
                                             "pool_min_scene_iou": 1.0}})
        m = parser.instantiate(cfg).model
        assert m.hparams.keep == 7 and type(m.hparams.keep) is int  # a checkpoint loads with weights_only
        assert type(m.hparams.pool_min_scene_iou) is float and type(m.hparams.queue_size) is int

    def test_settings_that_join_two_arguments(self) -> None:
        kw = {"grid_resolution": (32, 32, 16), "queue_size": 64}
        with pytest.raises(ValueError, match="freeze_encoder"):
            Mining(freeze_encoder=True, **kw)
        with pytest.raises(ValueError, match="query_pool"):
            Mining(query_pool=20, target_pool=10, **kw)
        with pytest.raises(ValueError, match="corner_offset"):
            Mining(crop_size=8, corner_offset=5, **kw)

    def test_vc_needs_two_view_sets(self) -> None:
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, source="vc")
        batch = {"rgb": torch.rand(1, 1, 3, 32, 32), "num_input_views": torch.tensor([1])}
        with pytest.raises(ValueError, match="two disjoint sets"):
            m._two_view_sets(batch)

    def test_the_pair_source_follows_candidates_from(self) -> None:
        from threedq.stages.pair_sources import FeaturePairs, InputPairs

        kw = {"grid_resolution": (32, 32, 16), "queue_size": 64}
        src = Mining(**kw).pair_source
        assert isinstance(src, InputPairs) and src.colour and (src.mutual_k, src.per_query) == (10, 2)
        assert not Mining(candidates_from="occupancy", **kw).pair_source.colour
        feat = Mining(candidates_from="features", candidates_per_query=None, top_k=5, **kw).pair_source
        assert isinstance(feat, FeaturePairs) and feat.top_k == 5 and feat.per_query is None
        assert feat.miner["yaw_window"] == 1 and feat.miner["rank_by"] == "retrieval"


class TestPairSourceCandidates:
    """:meth:`PairSource.candidates`: the source's pairs spread over the queries, or the best ``count``."""

    def test_input_pairs_spread_and_cut(self) -> None:
        from threedq.stages.pair_sources import InputPairs, input_occupancy

        g = torch.Generator().manual_seed(0)
        raw = (torch.rand(8, 4, 6, 6, 6, generator=g) > 0.5).float()
        pool = {"raw": raw, "scene": torch.tensor([0, 0, 1, 1, 2, 2, 3, 3]), "features": torch.randn(8, 4, 6, 6, 6)}
        every = input_pairs(input_occupancy(raw), pool["scene"], 4, 3, 8)
        best = InputPairs(3, False, None, 8).candidates(pool, 4, 2, 0.5)
        assert best["query_index"].tolist() == every["query_index"][:2].tolist()
        spread = InputPairs(3, False, 1, 8).candidates(pool, 4, 100, 0.5)
        order = spread_candidates(every["query_index"], 1, 100)
        assert spread["target_index"].tolist() == every["target_index"][order].tolist()
        assert len(set(spread["query_index"].tolist())) == spread["query_index"].numel()  # one pair per query
        colour = InputPairs(3, True, None, 8).candidates(pool, 4, 100, 0.5)
        want = input_pairs(input_occupancy(raw, colour=True), pool["scene"], 4, 3, 8)
        assert torch.equal(colour["score"], want["score"])

    def test_feature_pairs_are_the_miners(self) -> None:
        from threedq.contrastive import mine_correspondences
        from threedq.stages.pair_sources import FeaturePairs

        torch.manual_seed(0)
        feats = torch.randn(6, 8, 8, 8, 8)
        scene = torch.tensor([0, 0, 1, 1, 2, 2])
        pool = {"features": feats, "scene": scene, "raw": torch.zeros(6, 4, 8, 8, 8)}
        miner = {"patch": 2, "grid": 2, "context_distance": 2, "min_score": 0.0, "yaw_window": None, "rank_by": "score"}
        got = FeaturePairs(3, None, 8, **miner).candidates(pool, 3, 4, 0.3)
        want = mine_correspondences(feats[:3], feats, top_k=3, keep=4, exclude=scene[:3, None] == scene[None, :],
                                    min_cosine=0.3, num_angles=8, **miner)
        for k in ("query_index", "target_index", "yaw"):
            assert torch.equal(got[k], want[k]), k


class TestCropVoxels:
    """``crop_voxels``: the features at flat cell indices of each crop (the multi-view positives' keys and queries)."""

    def test_against_a_naive_loop(self) -> None:
        torch.manual_seed(0)
        crops = torch.randn(3, 5, 4, 4, 4)
        idx = torch.randint(0, 64, (3, 7))
        got = crop_voxels(crops, idx)
        assert got.shape == (3, 7, 5)
        for n in range(3):
            for v in range(7):
                z, y, x = int(idx[n, v]) // 16, int(idx[n, v]) // 4 % 4, int(idx[n, v]) % 4
                ref = crops[n, :, z, y, x]
                assert torch.allclose(got[n, v], ref / ref.norm(), atol=1e-6)

    def test_gradcheck(self) -> None:
        crops = torch.randn(2, 3, 2, 2, 2, dtype=torch.float64, requires_grad=True)
        idx = torch.tensor([[0, 7], [3, 3]])
        assert torch.autograd.gradcheck(lambda c: crop_voxels(c, idx), (crops,))


class TestOccupancyPositives:
    """``positives: occupancy``: pairs re-posed and ranked by their objects' occupancy, positives where both are occupied."""

    @staticmethod
    def _shape(seed: int, s: int = 8) -> torch.Tensor:
        g = torch.Generator().manual_seed(seed)
        return (torch.rand(1, s, s, s, generator=g) > 0.6).float()  # asymmetric under yaw, almost surely

    def test_smoke_and_a_known_quarter_turn(self) -> None:
        q = self._shape(0)[None]
        t = rotate_yaw(q, torch.tensor([-math.pi / 2]))  # the target is the query turned back a quarter
        cos, yaw = shape_agreement(q, t, num_angles=8)
        assert yaw.tolist() == [2] and torch.allclose(cos, torch.ones(1), atol=1e-5)  # 2 steps of 45 deg turn it on

    def test_against_a_naive_float64_loop(self) -> None:
        q = torch.stack([self._shape(i) for i in range(5)])
        t = torch.stack([self._shape(10 + i) for i in range(5)])
        cos, yaw = shape_agreement(q, t, num_angles=12, chunk=2)
        for p in range(5):
            best, arg = -2.0, -1
            for a in range(12):
                r = rotate_yaw(t[p:p + 1].double(), torch.tensor([2 * math.pi * a / 12], dtype=torch.float64))
                c = float(F.cosine_similarity(q[p].double().flatten(), r.flatten(), dim=0))
                if c > best + 1e-9:
                    best, arg = c, a
            assert abs(float(cos[p]) - best) < 1e-5 and int(yaw[p]) == arg

    def test_cells_lie_where_both_are_occupied(self) -> None:
        s = 8
        q = torch.stack([self._shape(1), self._shape(2), torch.zeros(1, s, s, s)])
        t = torch.stack([self._shape(3), self._shape(4), self._shape(5)])
        cells, valid = shape_cells(q, t, 8, torch.Generator().manual_seed(0))
        assert valid.tolist() == [True, True, False] and cells.shape == (2, 8) and cells.dtype == torch.long
        for p in range(2):
            assert len(set(cells[p].tolist())) == 8  # without replacement
            for c in cells[p].tolist():
                z, y, x = c // (s * s), (c // s) % s, c % s
                assert q[p, 0, z, y, x] > 0 and t[p, 0, z, y, x] > 0
        again = shape_cells(q, t, 8, torch.Generator().manual_seed(0))
        assert torch.equal(again[0], cells)  # the generator reproduces the draw
        few = torch.zeros(1, 1, s, s, s)
        few[0, 0, 0, 0, :5] = 1
        assert not shape_cells(few, few, 8)[1].any()  # fewer shared cells than positives: dropped

    def test_the_stage_keeps_the_pairs_that_agree_best_at_their_own_yaw(self) -> None:
        s = 8
        a, b = torch.zeros(1, s, s, s), torch.zeros(1, s, s, s)  # sparse, so the 3^3 dilation keeps them apart
        a[0, 1:3, 1, 1:7] = 1  # an L on the floor with a post at one end
        a[0, 1:3, 1:5, 1] = 1
        a[0, 1:6, 1, 6] = 1
        b[0, 1:6, 4, 3:5] = 1  # a wall across the middle
        raw = torch.zeros(4, 4, s, s, s)
        raw[0, :1], raw[1, :1], raw[2, :1] = a, rotate_yaw(a[None], torch.tensor([-math.pi / 2]))[0], b
        pool = {"raw": raw, "features": torch.randn(4, 32, s, s, s)}
        # pair 0: query 0 with an unrelated shape; pair 1: with its own quarter-turned copy; pair 2: an empty target
        mined = {"query_index": torch.tensor([0, 0, 0]), "target_index": torch.tensor([2, 1, 3]),
                 "yaw": torch.tensor([5, 5, 5]), "score": torch.tensor([0.9, 0.8, 0.7]),
                 "query_pos": torch.zeros(3, 3, dtype=torch.long), "target_pos_aligned": torch.zeros(3, 3, dtype=torch.long)}
        out, vox, keys = occupancy_positives(pool["features"], F.max_pool3d(raw[:, :1], 3, 1, 1), mined, 8, 2, 8,
                                             torch.Generator().manual_seed(0))
        assert out["target_index"].tolist() == [1, 2] and out["yaw"][0] == 2  # the copy first, turned by 90 deg
        assert out["score"].tolist() == pytest.approx([0.8, 0.9]) and out["shape_cosine"][0] > out["shape_cosine"][1]
        assert vox.shape == (2, 8, 3) and keys.shape == (2, 8, 32) and torch.equal(out["query_pos"], vox[:, 0])
        for p, (t, b_) in enumerate(zip(out["target_index"].tolist(), out["yaw"].tolist())):  # keys: the turned target
            turned = rotate_yaw(pool["features"][t:t + 1], torch.tensor([2 * math.pi * b_ / 8]))[0]
            for n, (z, y, x) in enumerate(vox[p].tolist()):
                assert F.max_pool3d(raw[:1, :1], 3, 1, 1)[0, 0, z, y, x] > 0  # on the query's dilated occupancy
                assert torch.allclose(keys[p, n], F.normalize(turned[:, z, y, x], dim=0), atol=1e-5)

    def test_no_candidates_or_no_shared_cells_leave_no_pairs(self) -> None:
        pool = {"raw": torch.zeros(3, 4, 8, 8, 8), "features": torch.randn(3, 32, 8, 8, 8)}  # empty crops

        def mined(q: list[int], t: list[int]) -> dict[str, torch.Tensor]:
            n = len(q)
            return {"query_index": torch.tensor(q, dtype=torch.long), "target_index": torch.tensor(t, dtype=torch.long),
                    "yaw": torch.zeros(n, dtype=torch.long), "score": torch.zeros(n),
                    "query_pos": torch.zeros(n, 3, dtype=torch.long),
                    "target_pos_aligned": torch.zeros(n, 3, dtype=torch.long)}

        for q, t in (([], []), ([0, 1], [1, 2])):
            out, vox, keys = occupancy_positives(pool["features"], pool["raw"][:, :1], mined(q, t), 8, 2, 8,
                                                 torch.Generator().manual_seed(0))
            assert out["query_index"].numel() == 0 and vox.shape == (0, 8, 3) and keys.shape == (0, 8, 32)


#: Per short-fit arm: the pair source's settings.
ARMS = {
    "mined": {"candidates_from": "features", "candidates_per_query": "null", "positives": "patches"},  # the paper's
    "mined_shape": {"candidates_from": "features", "candidates_per_query": "null", "positives": "occupancy"},
    "mined_input": {"candidates_from": "input", "candidates_per_query": 2, "positives": "occupancy"},
    "mined_occupancy": {"candidates_from": "occupancy", "candidates_per_query": 2, "positives": "occupancy"},
    "mined_scene": {"candidates_from": "features", "candidates_per_query": "null", "positives": "patches"},
}


def _config(tmp_path: Path, data_dir: Path, encoder_ckpt: Path, source: str) -> Path:
    arm = ARMS.get(source, ARMS["mined"])
    cfg = tmp_path / f"tiny_{source}.yaml"
    cfg.write_text(
        f"""
model:
  init_args:
    grid_resolution: [32, 32, 16]
    encoder_ckpt: {encoder_ckpt}
    crop_size: 8
    queue_size: 256
    voxels_per_object: 16
    query_pool: 6
    target_pool: 12
    top_k: 3
    keep: 5
    num_angles: 8
    search_grid: 2
    context_distance: 2
    min_score: 0.0
    corner_offset: 2
    refresh_every: 2
    pairs_per_step: 2
    pool_batch_size: 2
    retrieval_k: 1
    occupancy_mutual_k: 3
    candidates_from: {arm["candidates_from"]}
    candidates_per_query: {arm["candidates_per_query"]}
    positives: {arm["positives"]}
    pool_min_scene_iou: {0.3 if source == "mined_scene" else "null"}
{tiny_data_yaml(data_dir, batch_size=2, **({"num_target_views": 1} if source.startswith("vc") else {}))}
trainer:
  max_steps: 3
  precision: 32-true
  limit_val_batches: 1
  val_check_interval: 3
  enable_progress_bar: false
  enable_model_summary: false
  log_every_n_steps: 1
"""
    )
    return cfg


@pytest.mark.parametrize("source", ["vc", "vc_moco", "mined", "mined_shape", "mined_input", "mined_occupancy",
                                    "mined_scene"])
def test_short_fit_of_each_config(source: str, tmp_path: Path, tiny_dataset: Path,
                                  monkeypatch: pytest.MonkeyPatch) -> None:
    from threedq.pipeline.lightning_cli import ThreeDQCLI, resolve_config
    from threedq.stages.base import EncoderStage, encoder_state_from_checkpoint

    torch.manual_seed(0)
    enc = tmp_path / "enc.pt"
    start = EncoderStage(grid_resolution=(32, 32, 16)).encoder.state_dict()
    torch.save(start, enc)
    asked = []  # the splits the stage asked the DataModule's fused pseudo-boxes of
    if source == "mined_scene":  # the tiny scenes' 32x32 views are too coarse for pseudo-boxes: their GT boxes stand in
        from threedq.datamodules.scene_folder import SceneFolderDataModule

        def gt_as_fused(dm: SceneFolderDataModule, split: str, progress: bool = False) -> dict:
            asked.append(split)
            ds = dm.fixed_view_dataset(split, with_boxes=False)
            return {f: (ds[i]["aabb"][ds[i]["box_mask"]].numpy(), np.ones(int(ds[i]["box_mask"].sum()), np.float32))
                    for i, f in enumerate(ds.files)}

        monkeypatch.setattr(SceneFolderDataModule, "pseudo_boxes", gt_as_fused)
    run = tmp_path / source
    name = "mining" if source.startswith("mined") else source
    cli = ThreeDQCLI(args=["fit", "--config", str(resolve_config(f"stages/{name}.yaml")),
                           "--config", str(_config(tmp_path, tiny_dataset, enc, source)),
                           f"--trainer.default_root_dir={run}"])
    model = cli.model
    assert isinstance(model, Mining)
    assert model.hparams.source == ("mined" if source.startswith("mined") else source)
    assert model.trainer.global_step == 3
    logged = cli.trainer.logged_metrics
    assert "train/loss" in logged and torch.isfinite(logged["train/loss"])
    assert "val/precision_at_1" in logged
    ckpt = run / "checkpoints" / "last.ckpt"
    saved = torch.load(ckpt, weights_only=True, map_location="cpu")
    state = saved["state_dict"]
    assert state["moco.queue"].shape == (256, 32) and "moco.queue_ptr" in state
    assert all(type(v) in (int, float, str, bool, list, type(None)) for v in saved["hyper_parameters"].values())
    tuned = encoder_state_from_checkpoint(ckpt)
    assert any(not torch.equal(tuned[k], start[k]) for k in start if start[k].is_floating_point())
    if source == "vc":
        assert int(state["moco.queue_ptr"]) == 0  # in-batch negatives: the queue is not used
    else:
        assert int(state["moco.queue_ptr"]) > 0
        # the key encoder moved towards the query encoder but lags it (momentum 0.999)
        k0 = next(k for k in start if k.endswith("weight"))
        assert not torch.equal(state[f"moco.encoder_k.{k0}"], tuned[k0])
    if not source.startswith("mined"):
        return
    assert bool(state["queue_primed"]) and int(state["refreshes"]) == 2  # steps 0 and 2
    logs = sorted((run / "mining").glob("refresh_*.json"))
    assert [p.name for p in logs] == ["refresh_000000.json", "refresh_000002.json"]
    info = json.loads(logs[0].read_text())
    assert info["pairs"] >= 1 and 0.0 <= info["same_category"] <= 1.0 and info["queries"] == 6
    # a box matched at IoU 0.5 overlaps its object at >= 0.25: the looser count holds the stricter one
    assert info["labelled_pairs"] <= info["pairs_on_objects_iou25"] <= info["pairs"]
    assert 1 <= info["distinct_queries"] <= min(info["pairs"], info["queries"])
    assert max(info["distinct_queries"], info["distinct_targets"]) <= info["distinct_boxes"] <= 2 * info["pairs"]
    assert (run / "mining" / "refresh_000000.png").is_file()
    arm = ARMS[source]
    if arm["candidates_from"] != "features":  # the source and its k are recorded; each query in at most 2 pairs
        assert (info["candidates_from"], info["occupancy_mutual_k"]) == (arm["candidates_from"], 3)
        assert info["distinct_queries"] >= info["pairs"] / 2
    else:
        assert "candidates_from" not in info
    if arm["positives"] == "occupancy":  # ranked by their objects' occupancy agreement
        assert info["pairs"] <= min(5, info["shape_candidates"]) and 0.0 < info["shape_cosine_mean"] <= 1.0 + 1e-6
    else:
        assert "shape_candidates" not in info
    # the scene check: of the boxes the input views vouched for, those the DataModule's fused pseudo-boxes vouch for
    assert ("pool_scene_vouched" in info) == (source == "mined_scene")
    if source == "mined_scene":  # asked once (then kept), and every input-vouched GT box passes
        assert asked == ["train"] and info["pool_scene_vouched"] == info["pool_vouched"] >= 1


def test_the_queue_is_primed_once_then_takes_every_steps_keys(tmp_path: Path, tiny_dataset: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """MoCo's queue: primed with unit pool voxels at the first refresh, then every step's keys are enqueued, in order,
    and the second refresh does not prime it again."""
    from threedq.pipeline.lightning_cli import ThreeDQCLI, resolve_config
    from threedq.stages.base import EncoderStage

    torch.manual_seed(0)
    enc = tmp_path / "enc.pt"
    torch.save(EncoderStage(grid_resolution=(32, 32, 16)).encoder.state_dict(), enc)
    after_refresh, after_step, keys = [], [], []
    real_refresh, real_step, real_enqueue = Mining.refresh_pairs, Mining._mined_step, Mining._enqueue

    def refresh(self: Mining) -> dict:
        out = real_refresh(self)
        after_refresh.append(self.moco.queue.clone())
        return out

    def step(self: Mining) -> dict:
        out = real_step(self)
        after_step.append((len(after_refresh), self.moco.queue.clone()))
        return out

    def enqueue(self: Mining, k: torch.Tensor) -> None:
        keys.append(k.detach().clone())
        real_enqueue(self, k)

    monkeypatch.setattr(Mining, "refresh_pairs", refresh)
    monkeypatch.setattr(Mining, "_mined_step", step)
    monkeypatch.setattr(Mining, "_enqueue", enqueue)
    ThreeDQCLI(args=["fit", "--config", str(resolve_config("stages/mining.yaml")),
                     "--config", str(_config(tmp_path, tiny_dataset, enc, "mined")),
                     f"--trainer.default_root_dir={tmp_path / 'run'}"])
    assert len(after_refresh) == 2 and len(after_step) == 3  # refreshes at steps 0 and 2
    norms = after_refresh[0].norm(dim=1)
    assert torch.allclose(norms, torch.ones_like(norms), atol=1e-5)  # unit rows
    k = torch.cat(keys)
    assert k.shape[0] > 0 and torch.equal(after_step[-1][1][: k.shape[0]], k.float())  # the keys, in order
    # not re-primed at the second refresh: the rows no key has reached are the first refresh's pool voxels
    assert torch.equal(after_refresh[1][k.shape[0]:], after_refresh[0][k.shape[0]:])


class TestMiningConfigs:
    """The shipped mining configs: each variant is its base plus the keys it changes."""

    @staticmethod
    def _model_args(config: str) -> dict:
        from threedq.pipeline.lightning_cli import ThreeDQCLI

        cli = ThreeDQCLI(args=["--config", config, "--model.init_args.encoder_ckpt=null",
                               "--model.init_args.grid_resolution=[32, 32, 16]"], run=False)
        return dict(cli.config["model"]["init_args"])

    def test_variants_change_only_their_keys(self) -> None:
        base = self._model_args("stages/mining.yaml")
        for variant, changed in (("stages/mining_occupancy_pairs.yaml", {"candidates_from": "occupancy"}),
                                 ("stages/mining_paper.yaml", {"candidates_from": "features",
                                                               "candidates_per_query": None, "positives": "patches",
                                                               "query_pool": 1000, "target_pool": 1000,
                                                               "yaw_window": None, "rank_by": "score"})):
            got = self._model_args(variant)
            assert {k: v for k, v in got.items() if base.get(k) != v} == changed, variant


class TestSpreadCandidates:
    """:func:`spread_candidates`: each query's best pairs, round-robin over the queries."""

    def test_hand_computed(self) -> None:

        q = torch.tensor([5, 5, 2, 5, 2, 7, 2, 7])  # ranks: 5 -> pairs 0, 1, 3; 2 -> 2, 4, 6; 7 -> 5, 7
        assert spread_candidates(q, 2, 10).tolist() == [0, 2, 5, 1, 4, 7]
        assert spread_candidates(q, 1, 10).tolist() == [0, 2, 5]
        assert spread_candidates(q, 3, 4).tolist() == [0, 2, 5, 1]
        assert spread_candidates(q[:0], 2, 4).numel() == 0

    def test_against_a_naive_loop(self) -> None:

        g = torch.Generator().manual_seed(0)
        q = torch.randint(0, 15, (200,), generator=g)
        for per_query, count in ((1, 100), (3, 30), (4, 500)):
            seen: dict[int, int] = {}
            rank = []
            for v in q.tolist():  # each pair's rank among its query's pairs, walking in rank order
                rank.append(seen.get(v, 0))
                seen[v] = seen.get(v, 0) + 1
            want = sorted((r, n) for n, r in enumerate(rank) if r < per_query)[:count]
            assert spread_candidates(q, per_query, count).tolist() == [n for _, n in want]

    def test_exceptions(self) -> None:
        for bad in (0, -1, 1.5):
            assert "candidates_per_query" in refused(candidates_per_query=bad)


class TestPoolShapeAgreement:
    """:func:`pool_shape_agreement`: :func:`shape_agreement` of every pair of a pool at once."""

    @staticmethod
    def _crops(n: int, s: int = 8, seed: int = 0) -> torch.Tensor:
        g = torch.Generator().manual_seed(seed)
        return (torch.rand(n, 1, s, s, s, generator=g) > 0.7).float()

    def test_smoke_and_shapes(self) -> None:

        out = pool_shape_agreement(self._crops(5), 12)
        assert out.shape == (5, 5) and out.dtype == torch.float32
        assert torch.allclose(out.diagonal(), torch.ones(5), atol=1e-5)  # yaw 0: each crop on itself

    def test_against_pairwise_shape_agreement(self) -> None:
        """The naive reference: :func:`shape_agreement` pair by pair; chunking changes nothing."""

        for channels in (1, 4):  # occupancy, and occupancy with colour (one cosine over all channels)
            occ = torch.cat([self._crops(7, seed=c) for c in range(channels)], dim=1)
            occ[3] = 0  # an empty crop agrees with nothing
            want = torch.stack([torch.stack([shape_agreement(occ[n:n + 1], occ[m:m + 1], 12)[0][0]
                                             for m in range(7)]) for n in range(7)])
            for chunk in (1, 3, 128):
                assert torch.allclose(pool_shape_agreement(occ, 12, chunk=chunk), want, atol=1e-5)
            assert float(want[3].abs().max()) == 0.0

    def test_rotated_copy(self) -> None:
        """A crop and its copy turned by a known quarter turn agree fully (grid-exact rotation)."""

        occ = self._crops(2, seed=1)
        turned = torch.rot90(occ[0], 1, dims=(2, 3))  # 90 deg about the vertical (Z) axis of a [1, Z, Y, X] crop
        out = pool_shape_agreement(torch.stack([occ[0], turned, occ[1]]), 36)
        assert float(out[0, 1]) == pytest.approx(1.0, abs=1e-5) and float(out[1, 0]) == pytest.approx(1.0, abs=1e-5)
        assert float(out[0, 2]) < 0.9

    def test_gradcheck(self) -> None:

        occ = (torch.rand(3, 1, 4, 4, 4, dtype=torch.float64) + 0.1).requires_grad_(True)
        assert torch.autograd.gradcheck(lambda x: pool_shape_agreement(x, 4), (occ,))


class TestMutualPoolNeighbours:
    """:func:`mutual_pool_neighbours`: pairs each among the other's k most similar."""

    def test_hand_computed(self) -> None:

        sim = torch.tensor([[0.0, 0.9, 0.1, 0.5],
                            [0.9, 0.0, 0.8, 0.2],
                            [0.1, 0.8, 0.0, 0.7],
                            [0.5, 0.2, 0.7, 0.0]])
        eye = torch.eye(4, dtype=torch.bool)
        # 1-NN: 0 -> 1, 1 -> 0, 2 -> 1, 3 -> 2: only 0 - 1 is mutual
        assert mutual_pool_neighbours(sim, eye, 1).nonzero().tolist() == [[0, 1], [1, 0]]
        # 2-NN: 0 -> {1, 3}, 1 -> {0, 2}, 2 -> {1, 3}, 3 -> {2, 0}
        assert mutual_pool_neighbours(sim, eye, 2).nonzero().tolist() == [[0, 1], [0, 3], [1, 0], [1, 2], [2, 1],
                                                                          [2, 3], [3, 0], [3, 2]]
        # excluding 0 - 1 (the same scene, say): 0 -> 3, 1 -> 2, 2 -> 1, 3 -> 2
        ex = eye.clone()
        ex[0, 1] = ex[1, 0] = True
        assert mutual_pool_neighbours(sim, ex, 1).nonzero().tolist() == [[1, 2], [2, 1]]

    def test_against_a_naive_loop(self) -> None:

        g = torch.Generator().manual_seed(0)
        N = 30
        sim = torch.rand(N, N, generator=g)
        scene = torch.randint(0, 6, (N,), generator=g)
        ex = scene[:, None] == scene[None, :]
        for k in (1, 3, 8, 40):
            near = [set(sorted((m for m in range(N) if not ex[n, m]), key=lambda m: -float(sim[n, m]))[:k])
                    for n in range(N)]
            want = [[n, m] for n in range(N) for m in range(N) if m in near[n] and n in near[m]]
            assert mutual_pool_neighbours(sim, ex, k).nonzero().tolist() == want

    def test_exceptions(self) -> None:
        for bad in (0, -1, 1.5):
            assert "occupancy_mutual_k" in refused(occupancy_mutual_k=bad)


class TestInputPairs:
    """:func:`input_pairs`: candidate pairs from the input crops alone."""

    @staticmethod
    def _pool() -> tuple[torch.Tensor, torch.Tensor]:
        g = torch.Generator().manual_seed(3)
        a, b = ((torch.rand(2, 1, 8, 8, 8, generator=g) > 0.7).float()).unbind(0)
        # scene 0: a, b; scene 1: a and b turned by a quarter turn about the vertical axis (grid-exact)
        occ = torch.stack([a, b, torch.rot90(a, 1, dims=(2, 3)), torch.rot90(b, -1, dims=(2, 3))])
        return occ, torch.tensor([0, 0, 1, 1])

    def test_hand_computed(self) -> None:
        from threedq.geometry.rotate import rotate_yaw

        occ, scene = self._pool()
        out = input_pairs(occ, scene, 2, 1, 36)
        assert sorted(zip(out["query_index"].tolist(), out["target_index"].tolist())) == [(0, 2), (1, 3)]
        for q, t, y, sc in zip(out["query_index"], out["target_index"], out["yaw"], out["score"]):
            assert float(sc) == pytest.approx(1.0, abs=1e-5)
            turned = rotate_yaw(occ[t][None], torch.tensor([2 * math.pi * float(y) / 36]))[0]  # the miner's yaw
            assert torch.allclose(turned, occ[q], atol=1e-4)  # convention: turns the target onto the query
        assert {int(y) for y in out["yaw"]} == {9, 27}  # a quarter turn back, either way
        assert out["query_pos"].shape == (2, 3) and out["score"][0] >= out["score"][1]

    def test_against_the_mutual_matrix(self) -> None:
        """Every mutual pair with a query among the first n_q, best agreement first, and nothing else."""

        g = torch.Generator().manual_seed(0)
        occ = (torch.rand(12, 1, 6, 6, 6, generator=g) > 0.6).float()
        scene = torch.arange(12) // 3
        out = input_pairs(occ, scene, 7, 3, 12)
        sim = pool_shape_agreement(occ, 12)
        mut = mutual_pool_neighbours(sim, scene[:, None] == scene[None, :], 3)
        want = {(n, m) for n in range(7) for m in range(12) if mut[n, m]}
        got = list(zip(out["query_index"].tolist(), out["target_index"].tolist()))
        assert set(got) == want and len(got) == len(want)
        assert bool((out["score"][1:] <= out["score"][:-1]).all())

    def test_exceptions(self) -> None:
        assert "candidates_from" in refused(candidates_from="geometry")
        for source in ("occupancy", "input"):  # the patch positives need the miner's patch matches
            with pytest.raises(ValueError, match=f"positives: 'patches' .*candidates_from '{source}'"):
                Mining(grid_resolution=(32, 32, 16), queue_size=64, candidates_from=source, positives="patches")


def test_pool_reads_the_grids_other_stages_cached(tiny_dataset: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The pool is cut from each scene's fixed views in float32 (even under bf16 autocast), so under ``threedq em``
    it reads the grids a stage with the same weights left in the crop cache: no encoder pass, equal crops."""
    from threedq.datamodules.scene_folder import SceneDataset, SceneFolderDataModule
    from threedq.stages.crop_cache import CropCache
    from threedq.pipeline.report import split_loader
    from threedq.scene import load_index

    torch.manual_seed(0)
    m = Mining(grid_resolution=(32, 32, 16), target_pool=4, query_pool=2, crop_size=8, queue_size=64,
               pool_min_scene_iou=None)  # the scene's check asks a DataModule (its own tests below)
    index = load_index(tiny_dataset)
    train = SceneDataset(tiny_dataset, index, "train", num_input_views=1, num_target_views=0, random_views=True)
    monkeypatch.setattr(m, "_train_dataset", lambda: train)
    pool_ds = m._pool_dataset()
    assert pool_ds.random_views is False and train.random_views is True  # a copy: the training data is unchanged
    ref = m._cut_pool(pool_ds, torch.Generator().manual_seed(3))
    # another stage (same weights) encodes the training split from the fixed views, as split_loader gives them
    m.use_crop_cache(CropCache())
    dm = SceneFolderDataModule(str(tiny_dataset), num_input_views=1, num_target_views=0, max_objects=3, seed=0)
    m.eval()
    with torch.no_grad():
        for batch in split_loader(dm, "train", batch_size=2):
            m.encode_views(*(batch[k][:, :1] for k in ("rgb", "depth", "K", "R_T_cam")))
    calls = []
    m.encoder.register_forward_hook(lambda *a: calls.append(1))
    m.train()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = m._cut_pool(m._pool_dataset(), torch.Generator().manual_seed(3))
    assert not calls and m.crop_cache.hits > 0
    assert got["features"].dtype == torch.float32
    for k in ref:
        assert torch.equal(got[k], ref[k]), k


class TestPoolObjectCheck:
    """``pool_min_observed_iou``: the pool keeps the boxes the input views' label-free pseudo-boxes vouch for."""

    def _stage_and_batch(self, data_dir: Path, **kw: object) -> tuple[Mining, dict[str, torch.Tensor]]:
        from threedq.datamodules.scene_folder import SceneDataset
        from threedq.scene import load_index

        torch.manual_seed(0)
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, crop_size=8, **kw).eval()
        ds = SceneDataset(data_dir, load_index(data_dir), "train", num_input_views=1, num_target_views=0,
                          random_views=False)
        j = next(i for i in range(len(ds)) if int(ds[i]["box_mask"].sum()) >= 2)
        return m, {k: v[None] if isinstance(v, torch.Tensor) else v for k, v in ds[j].items()}

    def test_against_a_naive_loop_and_a_box_on_the_floor(self, tiny_dataset: Path) -> None:
        from threedq.box_refinement import observed_boxes
        from threedq.boxes import aabb_iou_3d

        m, batch = self._stage_and_batch(tiny_dataset)
        fg = m.feature_grid
        # a 20 cm box standing on the floor in the grid corner farthest from every object
        lo, hi = torch.tensor(fg.bounds_min), torch.tensor(fg.bounds_max)
        objs = batch["aabb"][0][batch["box_mask"][0]]
        corners = [(lo[0] + 0.05, lo[1] + 0.05), (hi[0] - 0.25, lo[1] + 0.05), (lo[0] + 0.05, hi[1] - 0.25),
                   (hi[0] - 0.25, hi[1] - 0.25)]
        cands = [torch.tensor([x, y, float(objs[:, 2].min()), x + 0.2, y + 0.2, float(objs[:, 2].min()) + 0.2])
                 for x, y in corners]
        floor = max(cands, key=lambda b: -float(aabb_iou_3d(b[None], objs).max()))
        assert float(aabb_iou_3d(floor[None], objs).max()) == 0.0
        batch["aabb"] = torch.cat([batch["aabb"], floor[None, None].to(batch["aabb"].dtype)], dim=1)  # a new last slot
        batch["box_mask"] = torch.cat([batch["box_mask"], torch.ones(1, 1, dtype=torch.bool)], dim=1)
        got = m._observed_iou(batch)
        obs, _ = observed_boxes(batch["depth"][0, :1], batch["K"][0, :1], batch["R_T_cam"][0, :1],
                                (fg.bounds_min, fg.bounds_max))
        boxes = batch["aabb"][0][batch["box_mask"][0]]
        assert got.shape == (boxes.shape[0],)
        for n, b in enumerate(boxes):  # naive: one box at a time, every observed box
            best = max((float(aabb_iou_3d(b[None].float(), torch.from_numpy(o)[None])[0, 0]) for o in obs), default=0.0)
            assert abs(float(got[n]) - best) < 1e-6
        assert float(got[-1]) < 0.1  # the floor box: nothing observed there
        assert float(got.max()) > 0.5  # some object is seen

    def test_the_pool_keeps_only_vouched_boxes(self, tiny_dataset: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        from threedq.datamodules.scene_folder import SceneDataset
        from threedq.scene import load_index

        index = load_index(tiny_dataset)
        train = SceneDataset(tiny_dataset, index, "train", num_input_views=1, num_target_views=0, random_views=False)
        pools = {}
        for thr in (None, 0.5):
            torch.manual_seed(0)  # the same encoder
            m = Mining(grid_resolution=(32, 32, 16), target_pool=1000, query_pool=2, crop_size=8, queue_size=64,
                       pool_min_observed_iou=thr, pool_min_scene_iou=None).eval()
            monkeypatch.setattr(m, "_train_dataset", lambda: train)
            m._pool_stats = {"boxes": 0, "vouched": 0}
            pools[thr] = (m._cut_pool(m._pool_dataset(), torch.Generator().manual_seed(3)), dict(m._pool_stats))
        (every, _), (vouched, stats) = pools[None], pools[0.5]
        assert stats["boxes"] == every["scene"].numel() and stats["vouched"] == vouched["scene"].numel()
        assert 0 < vouched["scene"].numel() <= every["scene"].numel()
        # the kept boxes are the same boxes with the same crops (keyed by scene and slot)
        ref = {(int(s), int(t)): n for n, (s, t) in enumerate(zip(every["scene"], every["slot"]))}
        for n, (s, t) in enumerate(zip(vouched["scene"], vouched["slot"])):
            assert torch.equal(vouched["features"][n], every["features"][ref[(int(s), int(t))]])

    def test_bad_threshold(self) -> None:
        for bad in (0.0, 1.5, -0.5, "x"):
            assert "pool_min_observed_iou" in refused(pool_min_observed_iou=bad)


class TestPoolSceneCheck:
    """``pool_min_scene_iou``: the pool keeps the boxes the pseudo-boxes fused over their scene's views vouch for."""

    def test_against_a_naive_loop_and_a_box_cut_short(self, tiny_dataset: Path) -> None:
        from threedq.boxes import aabb_iou_3d
        from threedq.datamodules.scene_folder import SceneDataset
        from threedq.scene import load_index

        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, crop_size=8, pool_min_scene_iou=0.7).eval()
        ds = SceneDataset(tiny_dataset, load_index(tiny_dataset), "train", num_input_views=1, num_target_views=0,
                          random_views=False)
        j = next(i for i in range(len(ds)) if int(ds[i]["box_mask"].sum()) >= 2)
        batch = {k: v[None] if isinstance(v, torch.Tensor) else v for k, v in ds[j].items()}
        gt = batch["aabb"][0][batch["box_mask"][0]].float()
        # the scene's fused pseudo-boxes: its GT boxes (the fused views see each object whole)
        m._scene_pseudo_boxes = lambda: {ds.files[j]: (gt.numpy(), np.ones(len(gt), np.float32))}
        half = gt[0].clone()
        half[3] = (half[0] + half[3]) / 2  # cut short to half its x extent: IoU 0.5 with its object's box, by hand
        batch["aabb"] = torch.cat([batch["aabb"], half[None, None].to(batch["aabb"].dtype)], dim=1)
        batch["box_mask"] = torch.cat([batch["box_mask"], torch.ones(1, 1, dtype=torch.bool)], dim=1)
        got = m._scene_iou(batch, ds)
        boxes = batch["aabb"][0][batch["box_mask"][0]].float()
        assert got.shape == (boxes.shape[0],)
        for n, b in enumerate(boxes):  # naive: one box at a time, every fused box
            best = max(float(aabb_iou_3d(b[None], g[None])[0, 0]) for g in gt)
            assert abs(float(got[n]) - best) < 1e-6
        assert torch.allclose(got[:-1], torch.ones(len(gt)))  # the objects' own boxes
        assert abs(float(got[-1]) - 0.5) < 1e-5  # the cut-short box: dropped at 0.7

    def test_the_pool_keeps_only_boxes_both_checks_vouch_for(self, tiny_dataset: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
        from threedq.datamodules.scene_folder import SceneDataset
        from threedq.scene import load_index

        train = SceneDataset(tiny_dataset, load_index(tiny_dataset), "train", num_input_views=1, num_target_views=0,
                             random_views=False)
        fused = {}  # each scene's GT boxes, but the first object of every second scene cut to half its height
        for i in range(len(train)):
            s = train[i]
            gt = s["aabb"][s["box_mask"]].float().clone()
            if i % 2 == 0 and len(gt):
                gt[0, 5] = (gt[0, 2] + gt[0, 5]) / 2
            fused[train.files[i]] = (gt.numpy(), np.ones(len(gt), np.float32))
        pools = {}
        for thr in (None, 0.7):
            torch.manual_seed(0)  # the same encoder
            m = Mining(grid_resolution=(32, 32, 16), target_pool=1000, query_pool=2, crop_size=8, queue_size=64,
                       pool_min_scene_iou=thr).eval()
            monkeypatch.setattr(m, "_train_dataset", lambda: train)
            monkeypatch.setattr(m, "_scene_pseudo_boxes", lambda: fused)
            m._pool_stats = {"boxes": 0, "vouched": 0, "scene_vouched": 0}
            pools[thr] = (m._cut_pool(m._pool_dataset(), torch.Generator().manual_seed(3)), dict(m._pool_stats))
        (every, before), (kept, stats) = pools[None], pools[0.7]
        assert before["scene_vouched"] == 0 and stats["vouched"] == every["scene"].numel()
        assert stats["scene_vouched"] == kept["scene"].numel()
        # dropped: exactly the input-vouched boxes whose slot-0 object was cut, in the even scenes
        dropped = {(int(s), int(t)) for s, t in zip(every["scene"], every["slot"])} - \
            {(int(s), int(t)) for s, t in zip(kept["scene"], kept["slot"])}
        assert dropped and all(s % 2 == 0 and t == 0 for s, t in dropped)
        assert len(dropped) == sum(1 for s, t in zip(every["scene"], every["slot"]) if int(s) % 2 == 0 and int(t) == 0)
        ref = {(int(s), int(t)): n for n, (s, t) in enumerate(zip(every["scene"], every["slot"]))}
        for n, (s, t) in enumerate(zip(kept["scene"], kept["slot"])):  # the same boxes with the same crops
            assert torch.equal(kept["features"][n], every["features"][ref[(int(s), int(t))]])

    def test_exceptions(self, tiny_dataset: Path) -> None:
        for bad in (0.0, 1.5, -0.5, "x"):
            assert "pool_min_scene_iou" in refused(pool_min_scene_iou=bad)
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, pool_min_scene_iou=0.7)
        with pytest.raises(ValueError, match="pool_min_scene_iou.*pseudo_boxes"):  # no DataModule to ask
            m._scene_pseudo_boxes()
        from threedq.datamodules.scene_folder import SceneDataset
        from threedq.scene import load_index

        ds = SceneDataset(tiny_dataset, load_index(tiny_dataset), "train", num_input_views=1, num_target_views=0,
                          random_views=False)
        batch = {k: v[None] if isinstance(v, torch.Tensor) else v for k, v in ds[0].items()}
        m._scene_pseudo_boxes = dict
        with pytest.raises(ValueError, match=f"pool_min_scene_iou.*no entry for {ds.files[0]}"):
            m._scene_iou(batch, ds)


class TestRoundLearningRate:
    """``round_lr``: the optimiser's learning rate per EM round, against the hand-computed lr / r."""

    kw = {"grid_resolution": (32, 32, 16), "queue_size": 64, "lr": 3e-4}

    @pytest.mark.parametrize("em_round", [1, 2, 3, 4])
    def test_harmonic_and_constant(self, em_round: int) -> None:
        harmonic = Mining(round_lr="harmonic", em_round=em_round, **self.kw)
        assert harmonic.configure_optimizers().param_groups[0]["lr"] == pytest.approx(3e-4 / em_round)
        constant = Mining(round_lr="constant", em_round=em_round, **self.kw)  # the paper's: one rate in every round
        assert constant.configure_optimizers().param_groups[0]["lr"] == pytest.approx(3e-4)

    def test_the_default_falls_and_is_lr_outside_the_loop(self) -> None:
        assert Mining(em_round=4, **self.kw).configure_optimizers().param_groups[0]["lr"] == pytest.approx(3e-4 / 4)
        assert Mining(**self.kw).configure_optimizers().param_groups[0]["lr"] == 3e-4  # em_round 1: lr itself

    def test_recorded_in_the_hyperparameters(self) -> None:
        m = Mining(round_lr="harmonic", em_round=3, **self.kw)
        assert (m.hparams.round_lr, m.hparams.em_round) == ("harmonic", 3)

    def test_errors(self) -> None:
        assert "round_lr" in refused(round_lr="cosine")
        for bad in (0, -1, 1.5):
            assert "em_round" in refused(em_round=bad)


class TestPairMeasures:
    """``Mining.pair_measures`` on a hand-computed case: categories of yaw symmetry order 1, 2 and 0 (any yaw),
    36 yaw steps of 10 deg."""

    def _case(self) -> tuple[dict, dict]:
        deg = [50.0, 10.0, 105.0, 0.0, 30.0, 70.0, 0.0]
        pool = {"labels": torch.tensor([0, 0, 1, 1, 2, 2, -1]), "yaw": torch.tensor([math.radians(d) for d in deg])}
        # (query, target, mined yaw step): 50 - 10 = 40 = step 4 (0 deg off); 10 - 50 = -40 = step 32 (30: 20 off,
        # 33: 10 off); order 2: 105 - 0 = 105 mod 180 against step 28 = 280 (5 off); order 0, another category and a
        # box on no object have no yaw error
        rows = [(0, 1, 4), (1, 0, 30), (1, 0, 33), (2, 3, 28), (4, 5, 9), (0, 2, 0), (6, 0, 0)]
        q, t, y = (torch.tensor(c) for c in zip(*rows))
        return pool, {"query_index": q, "target_index": t, "yaw": y}

    def test_hand_computed(self) -> None:
        pool, mined = self._case()
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, num_angles=36, symmetry_order=[1, 2, 0])
        out = m.pair_measures(pool, mined)
        assert out["labelled_pairs"] == 6 and out["same_category"] == pytest.approx(5 / 6)
        # of 0, 20 and 10 deg (float32 yaws)
        assert out["yaw_pairs"] == 3 and out["yaw_median_err_deg"] == pytest.approx(10.0, abs=1e-4)
        assert out["yaw_sym_pairs"] == 4 and out["yaw_sym_median_err_deg"] == pytest.approx(5.0, abs=1e-4)

    def test_pairs_on_objects_at_iou_025(self) -> None:
        pool, mined = self._case()
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64)
        assert "pairs_on_objects_iou25" not in m.pair_measures(pool, mined)  # no GT IoUs: not measured
        # boxes 1 and 6 overlap no object at 0.25: pairs (0,1), (1,0), (1,0), (6,0) fall out, 3 of 7 remain
        pool["gt_iou"] = torch.tensor([0.9, 0.2, 0.25, 0.6, 0.3, 0.5, 0.0])
        assert m.pair_measures(pool, mined)["pairs_on_objects_iou25"] == 3
        pool["gt_iou"] = torch.full((7,), float("nan"))  # a batch without GT boxes
        assert "pairs_on_objects_iou25" not in m.pair_measures(pool, mined)

    def test_gt_box_iou_hand_computed(self) -> None:

        unit = [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]
        batch = {"aabb": torch.tensor([[unit, [0, 0, 0, 0.5, 1, 1], [5, 5, 5, 6, 6, 6]],
                                       [unit, [0, 0, 0, 2, 1, 1], unit]]),
                 "box_mask": torch.tensor([[True, True, True], [True, True, False]]),
                 "gt_aabb": torch.tensor([[unit, [4, 4, 4, 5.5, 6, 6]], [[0, 0, 0, 0.0, 0, 0], unit]]),
                 "gt_mask": torch.tensor([[True, True], [False, False]])}
        # scene 0: the box itself 1; half its x extent 0.5; [5,6]^3 against [4,5.5]x[4,6]x[4,6]: 0.5 / (1 + 6 - 0.5)
        got = gt_box_iou(batch)
        assert torch.allclose(got, torch.tensor([1.0, 0.5, 0.5 / 6.5, 0.0, 0.0]))  # scene 1 has no GT box
        del batch["gt_aabb"]
        assert torch.isnan(gt_box_iou(batch)).all() and gt_box_iou(batch).shape == (5,)

    def test_without_symmetry_or_pairs(self) -> None:
        pool, mined = self._case()
        out = Mining(grid_resolution=(32, 32, 16), queue_size=64).pair_measures(pool, mined)
        assert not any(k.startswith("yaw") for k in out)
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, symmetry_order=[0, 0, 0])
        out = m.pair_measures(pool, mined)  # every category symmetric under any yaw: no yaw error to measure
        assert not any(k.startswith("yaw") for k in out) and out["labelled_pairs"] == 6
