"""The correspondence-learning stage (stages/mining.py): its pieces against hand-computed cases, and a short fit
of each of the three sources (vc, vc_moco, mined) on the tiny fixture."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from conftest import tiny_data_yaml
from threedq.errors import InputError
from threedq.stages.mining import (
    Mining,
    corner_keys,
    corner_offsets,
    crop_voxels,
    implied_yaw_error_deg,
    prototype_keys,
    prototype_purity,
    recolour_scenes,
    shape_agreement,
    shape_cells,
)
from threedq.geometry import rotate_yaw
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


class TestMiningStageErrors:
    def test_bad_arguments(self) -> None:
        kw = {"grid_resolution": (32, 32, 16), "queue_size": 64}
        with pytest.raises(ValueError, match="source"):
            Mining(source="views", **kw)
        with pytest.raises(ValueError, match="freeze_encoder"):
            Mining(freeze_encoder=True, **kw)
        with pytest.raises(ValueError, match="query_pool"):
            Mining(query_pool=20, target_pool=10, **kw)
        with pytest.raises(ValueError, match="corner_offset"):
            Mining(crop_size=8, corner_offset=5, **kw)
        with pytest.raises(ValueError, match="min_cosine"):
            Mining(min_cosine=2.0, **kw)
        with pytest.raises(ValueError, match="view_positives"):
            Mining(view_positives=-1, **kw)
        with pytest.raises(ValueError, match="view_positives"):
            Mining(source="vc_moco", view_positives=4, **kw)
        with pytest.raises(ValueError, match="view_weight"):
            Mining(view_positives=4, view_weight=0.0, **kw)
        with pytest.raises(ValueError, match="negatives: expected 'queue' or 'pool', got 'batch'"):
            Mining(negatives="batch", **kw)
        with pytest.raises(ValueError, match="negatives: 'pool' .* source 'vc_moco' has no pool"):
            Mining(source="vc_moco", negatives="pool", **kw)
        for bad in (-0.1, 1.5, True, "1", None):
            with pytest.raises(ValueError, match="colour_jitter: expected a number in"):
                Mining(colour_jitter=bad, **kw)
        with pytest.raises(ValueError, match="colour_jitter: .* source 'vc' has none"):
            Mining(source="vc", colour_jitter=0.5, **kw)

    def test_vc_needs_two_view_sets(self) -> None:
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, source="vc")
        batch = {"rgb": torch.rand(1, 1, 3, 32, 32), "num_input_views": torch.tensor([1])}
        with pytest.raises(ValueError, match="two disjoint sets"):
            m._two_view_sets(batch)


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


class TestViewPositives:
    """The mined source's multi-view term: the same voxels of the same boxes from a second view set."""

    def _stage_and_batch(self, data_dir: Path) -> tuple[Mining, dict[str, torch.Tensor]]:
        from threedq.datamodules.scene_folder import SceneDataset
        from threedq.scene import load_index

        torch.manual_seed(0)
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, crop_size=8, view_positives=5).eval()
        ds = SceneDataset(data_dir, load_index(data_dir), "train", num_input_views=1, num_target_views=1,
                          random_views=False)
        j = next(i for i in range(len(ds)) if int(ds[i]["box_mask"].sum()) >= 2)
        return m, {k: v[None] if isinstance(v, torch.Tensor) else v for k, v in ds[j].items()}

    def test_shapes_and_identical_views(self, tiny_dataset: Path) -> None:
        m, batch = self._stage_and_batch(tiny_dataset)
        n = int(batch["box_mask"].sum())
        a, b = m._two_view_sets(batch)
        q, k = m._view_positives(m.encode_views(*a), b, batch, 5)
        assert q.shape == k.shape == (n * 5, 32)
        assert torch.allclose(q.norm(dim=1), torch.ones(n * 5), atol=1e-5) and not k.requires_grad
        # a round trip: the second "view set" = the input one, and the key encoder still a copy of the query
        # encoder (no momentum step yet): every key is its query
        q, k = m._view_positives(m.encode_views(*a), a, batch, 5)
        assert torch.allclose((q * k).sum(1), torch.ones(n * 5), atol=1e-5)
        # from the other view the same voxels differ
        q, k = m._view_positives(m.encode_views(*a), b, batch, 5)
        assert (q * k).sum(1).min() < 0.999

    def test_gradient_reaches_the_encoder_only_through_the_queries(self, tiny_dataset: Path) -> None:
        m, batch = self._stage_and_batch(tiny_dataset)
        m.train()
        a, b = m._two_view_sets(batch)
        q, k = m._view_positives(m.encode_views(*a), b, batch, 5)
        m.moco.loss(q, k).backward()
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in m.encoder.parameters())
        assert all(p.grad is None for p in m.moco.encoder_k.parameters())

    def test_no_boxes(self, tiny_dataset: Path) -> None:
        m, batch = self._stage_and_batch(tiny_dataset)
        batch["box_mask"][:] = False
        a, b = m._two_view_sets(batch)
        q, k = m._view_positives(m.encode_views(*a), b, batch, 5)
        assert q.shape == k.shape == (0, 32)

    def test_needs_a_second_view_set(self) -> None:
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, view_positives=4)
        with pytest.raises(ValueError, match="two disjoint sets"):
            m._two_view_sets({"rgb": torch.rand(1, 1, 3, 32, 32), "num_input_views": torch.tensor([1])})


class TestViewPredictionRegulariser:
    """``view_prediction_weight``: the view-prediction loss, with the decoder and settings of the checkpoint."""

    SETTINGS = dict(num_planes=16, pool=4, rgb_weight=7.0, occ_weight=0.5, free_samples_per_ray=8)

    def _vp_checkpoint(self, tmp_path: Path) -> tuple[Path, "ViewPrediction"]:
        from threedq.stages.viewpred import ViewPrediction

        torch.manual_seed(4)
        vp = ViewPrediction(grid_resolution=(32, 32, 16), image_every_n_steps=0, **self.SETTINGS)
        with torch.no_grad():  # not the decoder's initial weights, so that loading them is seen
            for prm in vp.decoder.parameters():
                prm.add_(0.01 * torch.randn_like(prm))
        ckpt = tmp_path / "vp.ckpt"
        torch.save({"state_dict": vp.state_dict(), "hyper_parameters": dict(vp.hparams)}, ckpt)
        return ckpt, vp

    def _batch(self, data_dir: Path, targets: int = 1) -> dict[str, torch.Tensor]:
        from threedq.datamodules.scene_folder import SceneFolderDataModule

        dm = SceneFolderDataModule(str(data_dir), batch_size=1, num_input_views=1, num_target_views=targets)
        dm.setup()
        return next(iter(dm.val_dataloader()))

    def test_equals_the_view_prediction_stages_loss(self, tmp_path: Path, tiny_dataset: Path) -> None:
        ckpt, vp = self._vp_checkpoint(tmp_path)
        m = Mining(encoder_ckpt=str(ckpt), queue_size=64, view_prediction_weight=2.0).eval()
        assert m.vp_settings["rgb_weight"] == 7.0 and m.vp_settings["num_planes"] == 16
        for a, b in zip(vp.decoder.state_dict().values(), m.decoder.state_dict().values()):
            assert torch.equal(a, b)
        batch = self._batch(tiny_dataset)
        with torch.no_grad():
            want = vp.eval()._step(batch)
            feats = m.encode_views(*(batch[k][:, :1] for k in ("rgb", "depth", "K", "R_T_cam")))
            got = m._view_prediction_term(feats, batch, 1)
        assert torch.allclose(got["loss"], want["loss"], rtol=1e-5) and torch.allclose(got["l1"], want["l1"])
        # the settings weigh the two terms: 7 x the balanced RGB L1 + 0.5 x the occupancy loss
        from threedq.nets import balanced_l1

        rgb = balanced_l1(got["pred"], got["target"], got["valid"], got["fg"])
        assert torch.allclose(got["loss"], 7.0 * rgb + 0.5 * got["occ_loss"], rtol=1e-5)

    def test_only_the_first_scene(self, tmp_path: Path, tiny_dataset: Path) -> None:
        ckpt, _ = self._vp_checkpoint(tmp_path)
        m = Mining(encoder_ckpt=str(ckpt), queue_size=64, view_prediction_weight=1.0).eval()
        one = self._batch(tiny_dataset)
        two = {k: torch.cat([v, v.flip(0) if k == "rgb" else v]) if isinstance(v, torch.Tensor) else v
               for k, v in one.items()}
        two["rgb"][1] = torch.rand_like(two["rgb"][1])  # another second scene changes nothing
        with torch.no_grad():
            f1 = m.encode_views(*(one[k][:, :1] for k in ("rgb", "depth", "K", "R_T_cam")))
            f2 = m.encode_views(*(two[k][:, :1] for k in ("rgb", "depth", "K", "R_T_cam")))
            a, b = m._view_prediction_term(f1, one, 1)["loss"], m._view_prediction_term(f2, two, 1)["loss"]
        assert torch.allclose(a, b, rtol=1e-5)

    def test_occupancy_term_alone(self, tmp_path: Path, tiny_dataset: Path) -> None:
        """``view_prediction_rgb: false``: the whole loss less its RGB term, and only the occupancy head trains."""
        from threedq.nets import balanced_l1

        ckpt, _ = self._vp_checkpoint(tmp_path)
        full = Mining(encoder_ckpt=str(ckpt), queue_size=64, view_prediction_weight=1.0).eval()
        occ = Mining(encoder_ckpt=str(ckpt), queue_size=64, view_prediction_weight=1.0,
                     view_prediction_rgb=False).eval()
        batch = self._batch(tiny_dataset)
        views = [batch[k][:, :1] for k in ("rgb", "depth", "K", "R_T_cam")]
        with torch.no_grad():
            want = full._view_prediction_term(full.encode_views(*views), batch, 1)
        feats = occ.encode_views(*views)
        got = occ._view_prediction_term(feats, batch, 1)
        assert "l1" not in got and "pred" not in got  # the decoder did not run
        rgb = balanced_l1(want["pred"], want["target"], want["valid"], want["fg"])
        assert torch.allclose(got["loss"], want["loss"] - 7.0 * rgb, rtol=1e-5, atol=1e-7)
        assert torch.allclose(got["loss"], 0.5 * got["occ_loss"]) and float(got["occ_loss"]) > 0
        got["loss"].backward()
        assert all(p.grad is None and not p.requires_grad for p in occ.decoder.parameters())
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in occ.occ_head.parameters())
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in occ.encoder.parameters())
        trained = {id(p) for g in occ.configure_optimizers().param_groups for p in g["params"]}
        assert not any(id(p) in trained for p in occ.decoder.parameters())
        assert all(id(p) in trained for p in occ.occ_head.parameters())
        with pytest.raises(ValueError, match=r"view_prediction_rgb: false .*\(view_prediction_weight 0\)"):
            Mining(encoder_ckpt=str(ckpt), queue_size=64, view_prediction_rgb=False)
        with pytest.raises(ValueError, match="view_prediction_rgb: expected true or false"):
            Mining(encoder_ckpt=str(ckpt), queue_size=64, view_prediction_weight=1.0, view_prediction_rgb="no")

    def test_errors(self, tmp_path: Path, tiny_dataset: Path) -> None:
        from threedq.errors import InputError
        from threedq.stages.base import EncoderStage

        kw = {"grid_resolution": (32, 32, 16), "queue_size": 64}
        with pytest.raises(ValueError, match="view_prediction_weight"):
            Mining(view_prediction_weight=-1.0, **kw)
        with pytest.raises(ValueError, match="view_prediction_weight.*encoder_ckpt"):
            Mining(view_prediction_weight=1.0, **kw)
        with pytest.raises(ValueError, match="correspondence_weight: expected a number >= 0"):
            Mining(correspondence_weight=-0.5, **kw)
        with pytest.raises(ValueError, match="correspondence_weight: 0 leaves the mined source no loss"):
            Mining(correspondence_weight=0.0, **kw)
        ckpt, _ = self._vp_checkpoint(tmp_path)
        with pytest.raises(ValueError, match="view_prediction_weight.*source 'vc'"):
            Mining(source="vc", encoder_ckpt=str(ckpt), view_prediction_weight=1.0, queue_size=64)
        enc = tmp_path / "enc.ckpt"  # a checkpoint with an encoder and no decoder
        torch.save({"state_dict": {f"encoder.{k}": v for k, v in
                                   EncoderStage(grid_resolution=(32, 32, 16)).encoder.state_dict().items()},
                    "hyper_parameters": {"grid_resolution": [32, 32, 16]}}, enc)
        with pytest.raises(InputError, match=r"enc\.ckpt.*'state_dict'.*no view-prediction decoder"):
            Mining(encoder_ckpt=str(enc), view_prediction_weight=1.0, queue_size=64)
        m = Mining(encoder_ckpt=str(ckpt), view_prediction_weight=1.0, queue_size=64)
        batch = self._batch(tiny_dataset, targets=0)
        feats = m.encode_views(*(batch[k][:, :1] for k in ("rgb", "depth", "K", "R_T_cam")))
        with pytest.raises(ValueError, match="num_target_views"):
            m._view_prediction_term(feats, batch, 1)
        # off (the default): no decoder, and nothing asks for its settings
        plain = Mining(encoder_ckpt=str(ckpt), queue_size=64)
        assert not hasattr(plain, "decoder") and not any(k.startswith("decoder.") for k in plain.state_dict())
        with pytest.raises(RuntimeError, match="view_prediction_weight is 0"):
            plain.vp_settings


def _bank_file(path: Path, protos: torch.Tensor, num_angles: int) -> Path:
    """A quantizer checkpoint holding ``protos`` ``[k, C, S, S, S]`` as its active prototypes (one slot free)."""
    from threedq.quantization.prototypes import PrototypeBank

    k = protos.shape[0]
    bank = PrototypeBank(k + 1, protos.shape[1], protos.shape[-1], num_angles)
    bank.prototypes[:k] = protos
    bank.active[:k] = True
    torch.save({"state_dict": {f"bank.{n}": v for n, v in bank.state_dict().items()},
                "hyper_parameters": {"_class_path": "threedq.stages.quantizer.Quantizer", "num_prototypes": k + 1,
                                     "crop_size": protos.shape[-1], "num_angles": num_angles,
                                     "occupancy_floor": None}}, path)
    return path


class TestProjectionHead:
    """``projection_dim``: the queue's InfoNCE on the head's outputs (MoCo v2), the grid's features left as they are."""

    def _moco_state(self, m: Mining) -> None:
        torch.manual_seed(1)
        m.moco.queue.copy_(F.normalize(torch.randn(64, 32), dim=1))

    def test_loss_against_a_hand_built_reference(self) -> None:
        from threedq.contrastive import info_nce_plain

        torch.manual_seed(0)
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, projection_dim=8)
        self._moco_state(m)
        head = m.projection
        q = F.normalize(torch.randn(6, 32, dtype=torch.float64), dim=1).float().requires_grad_(True)
        k = F.normalize(torch.randn(6, 32), dim=1)
        got = m._contrast(q, k)
        # the reference: every row through the head by hand (float64), normalised, then the plain InfoNCE
        w1, b1, w2, b2 = (t.detach().double() for t in (head[0].weight, head[0].bias, head[2].weight, head[2].bias))

        def proj(x: torch.Tensor) -> torch.Tensor:
            return F.normalize(torch.clamp(x.double() @ w1.T + b1, min=0) @ w2.T + b2, dim=1)

        want = info_nce_plain(proj(q.detach()), proj(k), proj(m.moco.queue), 0.07)
        assert got.dtype == torch.float32 and torch.allclose(got.double(), want, atol=1e-5)
        got.backward()
        assert q.grad is not None and q.grad.abs().sum() > 0  # the encoder side learns through the head
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in head.parameters())
        assert not m.moco.queue.requires_grad  # keys and queue: no gradient (MoCo)

    def test_queue_keeps_features_and_is_projected_afresh_after_each_enqueue(self) -> None:
        torch.manual_seed(0)
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, projection_dim=8)
        self._moco_state(m)
        m.all_gather = lambda t: t  # no trainer: one process
        q, k = F.normalize(torch.randn(4, 32), dim=1), F.normalize(torch.randn(4, 32), dim=1)
        first = m._contrast(q, k)
        m._enqueue(k)
        assert torch.equal(m.moco.queue[:4], k)  # the queue holds the unit features, not the head's outputs
        second = m._contrast(q, k)
        assert not torch.allclose(first, second)  # the new negatives were projected
        m._projected_queue = None
        assert torch.allclose(second, m._contrast(q, k))

    def test_without_a_head_the_paper_loss(self) -> None:
        torch.manual_seed(0)
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64)
        self._moco_state(m)
        q, k = F.normalize(torch.randn(4, 32), dim=1), F.normalize(torch.randn(4, 32), dim=1)
        assert m.projection is None and torch.equal(m._contrast(q, k), m.moco.loss(q, k))

    def test_bad_arguments(self) -> None:
        kw = {"grid_resolution": (32, 32, 16), "queue_size": 64}
        for bad in (0, -3, 2.5, True, "32"):
            with pytest.raises(ValueError, match="projection_dim"):
                Mining(projection_dim=bad, **kw)
        with pytest.raises(ValueError, match="projection_dim.*in-batch"):
            Mining(projection_dim=8, source="vc", **kw)
        for bad in (0.0, -1e-3, True):
            with pytest.raises(ValueError, match="projection_lr"):
                Mining(projection_lr=bad, projection_dim=8, **kw)


class TestShapePositives:
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
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, crop_size=s, corner_offset=2, num_angles=8, keep=2,
                   positives="occupancy")
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
        out, vox, keys = m._shape_positives(pool, mined, 8, torch.Generator().manual_seed(0))
        assert out["target_index"].tolist() == [1, 2] and out["yaw"][0] == 2  # the copy first, turned by 90 deg
        assert out["score"].tolist() == pytest.approx([0.8, 0.9]) and out["shape_cosine"][0] > out["shape_cosine"][1]
        assert vox.shape == (2, 8, 3) and keys.shape == (2, 8, 32) and torch.equal(out["query_pos"], vox[:, 0])
        for p, (t, b_) in enumerate(zip(out["target_index"].tolist(), out["yaw"].tolist())):  # keys: the turned target
            turned = rotate_yaw(pool["features"][t:t + 1], torch.tensor([2 * math.pi * b_ / 8]))[0]
            for n, (z, y, x) in enumerate(vox[p].tolist()):
                assert F.max_pool3d(raw[:1, :1], 3, 1, 1)[0, 0, z, y, x] > 0  # on the query's dilated occupancy
                assert torch.allclose(keys[p, n], F.normalize(turned[:, z, y, x], dim=0), atol=1e-5)

    def test_no_candidates_or_no_shared_cells_leave_no_pairs(self) -> None:
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, crop_size=8, corner_offset=2, num_angles=8, keep=2,
                   positives="occupancy")
        pool = {"raw": torch.zeros(3, 4, 8, 8, 8), "features": torch.randn(3, 32, 8, 8, 8)}  # empty crops

        def mined(q: list[int], t: list[int]) -> dict[str, torch.Tensor]:
            n = len(q)
            return {"query_index": torch.tensor(q, dtype=torch.long), "target_index": torch.tensor(t, dtype=torch.long),
                    "yaw": torch.zeros(n, dtype=torch.long), "score": torch.zeros(n),
                    "query_pos": torch.zeros(n, 3, dtype=torch.long),
                    "target_pos_aligned": torch.zeros(n, 3, dtype=torch.long)}

        for q, t in (([], []), ([0, 1], [1, 2])):
            out, vox, keys = m._shape_positives(pool, mined(q, t), 8, torch.Generator().manual_seed(0))
            assert out["query_index"].numel() == 0 and vox.shape == (0, 8, 3) and keys.shape == (0, 8, 32)

    def test_exceptions(self) -> None:
        kw = {"grid_resolution": (32, 32, 16), "queue_size": 64}
        with pytest.raises(ValueError, match="positives"):
            Mining(positives="corners", **kw)
        for bad in (0, 1.5, True):
            with pytest.raises(ValueError, match="shape_oversample"):
                Mining(shape_oversample=bad, **kw)
        with pytest.raises(ValueError, match="positives.*verify_by_prototypes"):
            Mining(positives="occupancy", verify_by_prototypes=True, bank_ckpt="x.ckpt", **kw)


#: The miner's own candidates (the paper's; ``stages/mining.yaml`` takes the input crops' mutual neighbours): what
#: the patch positives need and what the short fits below exercise, unless a test replaces these lines.
FEATURE_CANDIDATES = "    candidates_from: features\n    occupancy_mutual_k: null\n    candidates_per_query: null\n"
#: The same as keyword arguments of :class:`Mining`.
PAPER_MINER = {"candidates_from": "features", "occupancy_mutual_k": None, "candidates_per_query": None}


def _config(tmp_path: Path, data_dir: Path, encoder_ckpt: Path, source: str) -> Path:
    views = source == "mined_views"
    proto = source == "mined_proto"
    bank = _bank_file(tmp_path / "bank.ckpt", torch.randn(3, 32, 8, 8, 8), 8) if proto else None
    vp = source in ("mined_vp", "mined_vp_only", "mined_vp_occ")
    csls = source == "mined_csls"
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
    view_positives: {4 if views else 0}
    view_prediction_weight: {1.0 if vp else 0.0}
    view_prediction_rgb: {"false" if source == "mined_vp_occ" else "true"}
    projection_dim: {16 if source == "mined_proj" else "null"}
    projection_lr: {0.01 if source == "mined_proj" else 0.001}
    positives: {"occupancy" if source == "mined_shape" else "patches"}
{FEATURE_CANDIDATES}    negatives: {"pool" if source == "mined_pool" else "queue"}
    colour_jitter: {1.0 if source == "mined_jitter" else 0.0}
    correspondence_weight: {0.0 if source == "mined_vp_only" else 1.0}
    csls_k: {2 if csls else "null"}
    mutual_k: {3 if csls else "null"}
    retrieval_occupancy_floor: {0.2 if csls else "null"}
    prototype_weight: {1.0 if proto else 0.0}
    bank_ckpt: {bank if proto else "null"}
    pool_min_scene_iou: {0.3 if source == "mined_scene" else "null"}
    max_pairs_per_box: {2 if source == "mined_shape" else "null"}
{tiny_data_yaml(data_dir, batch_size=2, **({"num_target_views": 1} if views or vp else {}))}
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


@pytest.mark.parametrize("source", ["vc", "vc_moco", "mined", "mined_views", "mined_vp", "mined_vp_only",
                                    "mined_vp_occ", "mined_csls", "mined_proto", "mined_proj", "mined_shape",
                                    "mined_pool", "mined_jitter", "mined_scene"])
def test_short_fit_of_each_config(source: str, tmp_path: Path, tiny_dataset: Path,
                                  monkeypatch: pytest.MonkeyPatch) -> None:
    from threedq.stages.base import EncoderStage, encoder_state_from_checkpoint

    from threedq.pipeline.lightning_cli import ThreeDQCLI, resolve_config

    torch.manual_seed(0)
    enc = tmp_path / "enc.pt"
    start = EncoderStage(grid_resolution=(32, 32, 16)).encoder.state_dict()
    torch.save(start, enc)
    if source in ("mined_vp", "mined_vp_only", "mined_vp_occ"):  # the regulariser's decoder: a view-prediction ckpt
        from threedq.stages.viewpred import ViewPrediction

        vp = ViewPrediction(grid_resolution=(32, 32, 16), image_every_n_steps=0)
        vp.encoder.load_state_dict(start)
        enc = tmp_path / "vp.ckpt"
        torch.save({"state_dict": vp.state_dict(), "hyper_parameters": dict(vp.hparams)}, enc)
    import threedq.stages.mining as stage_mining

    miner_csls_k = []
    real_miner = stage_mining.mine_correspondences
    monkeypatch.setattr(stage_mining, "mine_correspondences",
                        lambda *a, **k: miner_csls_k.append((k.get("csls_k"), k.get("mutual_k"),
                                                             k.get("retrieval_crops") is not None))
                        or real_miner(*a, **k))
    recoloured = []  # (input, output) of each recolouring
    real_recolour = stage_mining.recolour_scenes
    monkeypatch.setattr(stage_mining, "recolour_scenes",
                        lambda rgb, s: recoloured.append((rgb.clone(), out := real_recolour(rgb, s))) or out)
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
    if source.startswith("mined"):  # each refresh mined with the config's csls_k, mutual_k and retrieval crops
        want = {(2, 3, True)} if source == "mined_csls" else {(None, None, False)}
        assert miner_csls_k and set(miner_csls_k) == want
    assert model.trainer.global_step == 3
    logged = cli.trainer.logged_metrics
    assert "train/loss" in logged and torch.isfinite(logged["train/loss"])
    assert "val/precision_at_1" in logged
    ckpt = run / "checkpoints" / "last.ckpt"
    state = torch.load(ckpt, weights_only=True, map_location="cpu")["state_dict"]
    assert state["moco.queue"].shape == (256, 32) and "moco.queue_ptr" in state
    tuned = encoder_state_from_checkpoint(ckpt)
    assert any(not torch.equal(tuned[k], start[k]) for k in start if start[k].is_floating_point())
    if source == "mined_jitter":  # each step's query scenes, and nothing else (the pool keeps its colours)
        assert model.hparams.colour_jitter == 1.0 and len(recoloured) == 3
        for rgb, out in recoloured:
            assert rgb.ndim == 5 and out.shape == rgb.shape and not torch.equal(out, rgb)
    else:
        assert not recoloured
    if source == "vc":
        assert int(state["moco.queue_ptr"]) == 0  # in-batch negatives: the queue is not used
    elif source == "mined_pool":
        assert int(state["moco.queue_ptr"]) == 0  # the pool's voxels are the negatives: no key was enqueued
    else:
        assert int(state["moco.queue_ptr"]) > 0
        # the key encoder moved towards the query encoder but lags it (momentum 0.999)
        k0 = next(k for k in start if k.endswith("weight"))
        assert not torch.equal(state[f"moco.encoder_k.{k0}"], tuned[k0])
    if source == "mined_views":
        # every step enqueues its 2 pairs' 8 mined keys each and 4 view keys per box of its query scenes
        assert float(logged["train/view_positives"]) % 4 == 0 and float(logged["train/view_positives"]) >= 4
        assert -1.0 <= float(logged["train/view_pos_cos"]) <= 1.0
        assert int(state["moco.queue_ptr"]) > 3 * 2 * 8
    if source == "mined_vp_only":  # correspondence_weight 0: the step's loss is the view-prediction term alone
        assert torch.allclose(logged["train/loss"], logged["train/vp_loss"])
        assert int(state["moco.queue_ptr"]) > 0  # the pairs were still mined and their keys enqueued
    if source == "mined_vp":  # with the pairs' InfoNCE (> 0) on top of the view-prediction term
        assert float(logged["train/loss"]) > float(logged["train/vp_loss"]) + 1e-3
    if source in ("mined_vp", "mined_vp_only"):
        assert float(logged["train/vp_l1"]) > 0 and torch.isfinite(logged["train/vp_loss"])
        # the decoder trained along, and the checkpoint carries it and its settings on to the next round's mining
        before = vp.decoder.state_dict()
        assert any(not torch.equal(state[f"decoder.{k}"], v) for k, v in before.items() if v.is_floating_point())
        saved = torch.load(ckpt, weights_only=True, map_location="cpu")
        assert saved["view_prediction_settings"]["rgb_weight"] == 30.0
        nxt = Mining(encoder_ckpt=str(ckpt), queue_size=64, view_prediction_weight=1.0)
        assert all(torch.equal(state[f"decoder.{k}"], v) for k, v in nxt.decoder.state_dict().items())
    elif source == "mined_vp_occ":  # the occupancy term alone: the head trained, the decoder carried on untouched
        assert "train/vp_l1" not in logged and float(logged["train/vp_occ"]) > 0
        assert torch.allclose(logged["train/vp_loss"], logged["train/vp_occ"])  # occ_weight 1
        assert all(torch.equal(state[f"decoder.{k}"], v) for k, v in vp.decoder.state_dict().items())
        assert any(not torch.equal(state[f"occ_head.{k}"], v) for k, v in vp.occ_head.state_dict().items()
                   if v.is_floating_point())
        nxt = Mining(encoder_ckpt=str(ckpt), queue_size=64, view_prediction_weight=1.0, view_prediction_rgb=False)
        assert all(torch.equal(state[f"occ_head.{k}"], v) for k, v in nxt.occ_head.state_dict().items())
    elif source.startswith("mined"):
        assert not any(k.startswith("decoder.") for k in state)
    if source == "mined_proj":  # the head trains at its own rate and goes on to the next round's mining
        assert state["projection.2.weight"].shape == (16, 32) and state["moco.queue"].shape == (256, 32)
        groups = torch.load(ckpt, weights_only=True, map_location="cpu")["optimizer_states"][0]["param_groups"]
        assert [g["lr"] for g in groups] == [pytest.approx(1e-4), pytest.approx(0.01)] and len(groups[1]["params"]) == 4
        nxt = Mining(encoder_ckpt=str(ckpt), queue_size=64, projection_dim=16)
        assert all(torch.equal(state[f"projection.{k}"], v) for k, v in nxt.projection.state_dict().items())
        with pytest.raises(InputError, match=r"last\.ckpt: field 'projection\.\*': does not fit"):
            Mining(encoder_ckpt=str(ckpt), queue_size=64, projection_dim=8)
    else:
        assert not any(k.startswith("projection.") for k in state)
    if source == "mined_shape":  # each refresh ranked the miner's pairs by their objects' occupancy agreement
        for f in sorted((run / "mining").glob("refresh_*.json")):
            info = json.loads(f.read_text())
            assert info["pairs"] <= min(5, info["shape_candidates"]) and 0.0 < info["shape_cosine_mean"] <= 1.0 + 1e-6
            assert info["distinct_boxes"] >= info["pairs"]  # each box in at most 2 pairs: 2 P slots over >= P boxes
    if source == "mined_proto":  # a prototype positive for every query voxel the turned prototype covers
        assert 1 <= float(logged["train/prototype_positives"]) <= 2 * 8
        assert -1.0 <= float(logged["train/prototype_pos_cos"]) <= 1.0
        assert not any(k.startswith("bank.") for k in state)  # the bank is bank_ckpt's, not this stage's state
    else:
        assert "train/prototype_pos_cos" not in logged
    if source.startswith("mined"):
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
        assert ("prototype_positive_purity" in info) == (source == "mined_proto")
        # the scene check: of the boxes the input views vouched for, those the DataModule's fused pseudo-boxes vouch
        # for too
        assert ("pool_scene_vouched" in info) == (source == "mined_scene")
        if source == "mined_scene":  # asked once (then kept), and every input-vouched GT box passes
            assert asked == ["train"] and info["pool_scene_vouched"] == info["pool_vouched"] >= 1


class TestCapPairsPerBox:
    """:func:`cap_pairs_per_box`: in rank order, each box in at most ``cap`` kept pairs."""

    def test_hand_computed(self) -> None:
        from threedq.stages.mining import cap_pairs_per_box

        q, t = torch.tensor([0, 0, 1, 0, 2, 3]), torch.tensor([1, 2, 2, 3, 3, 0])
        # cap 2: (0,1) keep [0:1, 1:1]; (0,2) keep [0:2, 2:1]; (1,2) keep [1:2, 2:2]; (0,3) box 0 full; (2,3) box 2
        # full; (3,0) box 0 full
        assert cap_pairs_per_box(q, t, 2).tolist() == [True, True, True, False, False, False]
        assert cap_pairs_per_box(q, t, 1).tolist() == [True, False, False, False, True, False]
        assert cap_pairs_per_box(q, t, 6).all() and cap_pairs_per_box(q[:0], t[:0], 1).shape == (0,)

    def test_against_a_naive_count(self) -> None:
        from threedq.stages.mining import cap_pairs_per_box

        g = torch.Generator().manual_seed(0)
        q, t = torch.randint(0, 12, (300,), generator=g), torch.randint(0, 12, (300,), generator=g)
        for cap in (1, 3, 7):
            keep = cap_pairs_per_box(q, t, cap)
            for n in range(q.numel()):  # a pair is dropped exactly when one of its boxes is already full before it
                before = torch.cat([q[:n][keep[:n]], t[:n][keep[:n]]])
                full = int((before == q[n]).sum()) >= cap or int((before == t[n]).sum()) >= cap
                assert bool(keep[n]) == (not full)

    def test_the_stage_spreads_its_pairs(self) -> None:
        s = 8
        kw: dict = {"grid_resolution": (32, 32, 16), "queue_size": 64, "crop_size": s, "corner_offset": 2,
                    "num_angles": 8, "keep": 3, "positives": "occupancy"}
        raw = torch.zeros(4, 4, s, s, s)
        raw[:, 0, 1:6, 2:5, 2:5] = 1  # four equal boxes: every pair agrees fully
        pool = {"raw": raw, "features": torch.randn(4, 32, s, s, s)}
        n = 3
        mined = {"query_index": torch.tensor([0, 0, 2]), "target_index": torch.tensor([1, 2, 3]),
                 "yaw": torch.zeros(n, dtype=torch.long), "score": torch.tensor([0.9, 0.8, 0.7]),
                 "query_pos": torch.zeros(n, 3, dtype=torch.long), "target_pos_aligned": torch.zeros(n, 3, dtype=torch.long)}
        out, _, _ = Mining(**kw)._shape_positives(pool, mined, 8, torch.Generator().manual_seed(0))
        assert out["query_index"].numel() == 3  # no cap: box 0 in two pairs
        out, vox, keys = Mining(**kw, max_pairs_per_box=1)._shape_positives(pool, mined, 8,
                                                                            torch.Generator().manual_seed(0))
        pairs = sorted(zip(out["query_index"].tolist(), out["target_index"].tolist()))  # equal agreement: rank order
        assert pairs == [(0, 1), (2, 3)] and vox.shape[0] == keys.shape[0] == 2  # (0, 2): box 0 is taken

    def test_exceptions(self) -> None:
        for bad in (0, True, 2.0, "4"):
            with pytest.raises(ValueError, match="max_pairs_per_box"):
                Mining(grid_resolution=(32, 32, 16), queue_size=64, max_pairs_per_box=bad)
        with pytest.raises(ValueError, match="max_pairs_per_box.*positives"):
            Mining(grid_resolution=(32, 32, 16), queue_size=64, positives="patches", max_pairs_per_box=4,
                   **PAPER_MINER)


class TestOraclePairs:
    """:func:`oracle_pairs` (a diagnostic with labels): same category, other scene, the GT relative yaw."""

    def test_hand_computed(self) -> None:
        from threedq.stages.mining import oracle_pairs

        labels = torch.tensor([0, 1, 0, -1, 0, 1])
        scene = torch.tensor([0, 0, 1, 1, 0, 2])
        yaw = torch.tensor([math.radians(50), 0.0, math.radians(20), 0.0, 0.0, math.radians(-30)])
        out = oracle_pairs(labels, scene, yaw, n_q=2, per_query=5, count=10, num_angles=36)
        # query 0 (category 0, scene 0): only box 2 (box 4 shares its scene); query 1: only box 5
        assert out["query_index"].tolist() == [0, 1] and out["target_index"].tolist() == [2, 5]
        assert out["yaw"].tolist() == [3, 3]  # 50 - 20 = 30 deg; 0 - (-30) = 30 deg
        err = implied_yaw_error_deg(out["yaw"], 36, yaw[out["query_index"]], yaw[out["target_index"]],
                                    torch.ones(2, dtype=torch.long))
        assert float(err.max()) == pytest.approx(0.0, abs=1e-6)
        assert out["query_pos"].shape == out["target_pos_aligned"].shape == (2, 3)

    def test_against_a_naive_check(self) -> None:
        from threedq.stages.mining import oracle_pairs

        g = torch.Generator().manual_seed(0)
        N, A = 60, 36
        labels = torch.randint(-1, 4, (N,), generator=g)
        scene = torch.randint(0, 10, (N,), generator=g)
        yaw = torch.rand(N, generator=g) * 2 * math.pi - math.pi
        out = oracle_pairs(labels, scene, yaw, n_q=20, per_query=3, count=40, num_angles=A,
                           generator=torch.Generator().manual_seed(1))
        qi, ti = out["query_index"], out["target_index"]
        assert 0 < qi.numel() <= 40 and bool((qi < 20).all())
        assert bool((labels[qi] == labels[ti]).all() & (labels[qi] >= 0).all() & (scene[qi] != scene[ti]).all())
        err = implied_yaw_error_deg(out["yaw"], A, yaw[qi], yaw[ti], torch.ones_like(qi))
        assert float(err.max()) <= 180 / A + 1e-6  # the nearest step: within half a step
        first = [int(qi[n]) for n in range(qi.numel()) if int(qi[n]) not in qi[:n].tolist()]
        assert qi[: len(first)].tolist() == sorted(first)  # every query's first target before any second one
        counts = torch.bincount(qi, minlength=20)
        assert int(counts.max()) <= 3
        empty = oracle_pairs(torch.full((5,), -1), scene[:5], yaw[:5], 5, 3, 10, A)
        assert empty["query_index"].numel() == 0 and empty["yaw"].numel() == 0

    def test_the_stage_poses_them_at_the_gt_yaw(self) -> None:
        s = 8
        kw: dict = {"grid_resolution": (32, 32, 16), "queue_size": 64, "crop_size": s, "corner_offset": 2,
                    "num_angles": 8, "keep": 2, "positives": "occupancy"}
        raw = torch.zeros(3, 4, s, s, s)
        raw[:, 0, 1:7, 1:7, 1:7] = 1  # a cube: it agrees with itself at every quarter turn
        pool = {"raw": raw, "features": torch.randn(3, 32, s, s, s)}
        z = torch.zeros(2, 3, dtype=torch.long)
        mined = {"query_index": torch.tensor([0, 1]), "target_index": torch.tensor([1, 2]),
                 "yaw": torch.tensor([2, 6]), "score": torch.ones(2), "query_pos": z, "target_pos_aligned": z}
        out, _, _ = Mining(**kw)._shape_positives(pool, mined, 8, torch.Generator().manual_seed(0))
        assert out["yaw"].tolist() == [0, 0]  # the miner's own pose: the shape's best yaw, ties to the lowest step
        out, vox, keys = Mining(**kw, oracle_pairs="gt")._shape_positives(pool, mined, 8,
                                                                          torch.Generator().manual_seed(0))
        assert sorted(out["yaw"].tolist()) == [2, 6] and vox.shape == (2, 8, 3) and keys.shape == (2, 8, 32)
        out, _, _ = Mining(**kw, oracle_pairs="gt_category")._shape_positives(pool, mined, 8,
                                                                              torch.Generator().manual_seed(0))
        assert out["yaw"].tolist() == [0, 0]  # the GT pairs at the stage's own posing
        # the keys are the target's features turned by the GT yaw, at the query's cells
        j = out["query_index"].tolist().index(0)
        turned = rotate_yaw(pool["features"][1:2], torch.tensor([2 * 2 * math.pi / 8]))[0]
        z, y, x = vox[j].unbind(-1)
        assert torch.allclose(keys[j], F.normalize(turned[:, z, y, x].T, dim=1), atol=1e-5)

    def test_exceptions(self) -> None:
        kw = {"grid_resolution": (32, 32, 16), "queue_size": 64}
        for bad in (True, 1, "GT"):
            with pytest.raises(ValueError, match="oracle_pairs: expected null or one of"):
                Mining(oracle_pairs=bad, **kw)
        with pytest.raises(ValueError, match="oracle_pairs: .*positives 'patches'"):
            Mining(oracle_pairs="gt", positives="patches", **kw, **PAPER_MINER)


@pytest.mark.parametrize("oracle", ["gt", "mined_gt_filtered", "spread", "occupancy", "occupancy_only", "input_only"])
def test_oracle_pairs_in_a_short_fit(oracle: str, tmp_path: Path, tiny_dataset: Path,
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The diagnostic's pairs reach the stage's refresh: every kept pair on two GT objects of one category; ``gt``
    does not call the miner, ``mined_gt_filtered`` does. ``spread`` (``candidates_per_query: 1``, label-free): the
    miner returns every verified pair and the ranking gets at most one per query. ``occupancy``
    (``occupancy_mutual_k: 3`` with ``candidates_per_query: 1``, label-free): every pair the ranking gets is a pair
    of mutual neighbours by a naive loop over :func:`shape_agreement`, at most one per query, ``keep`` at most.
    ``occupancy_only`` (the same with ``candidates_from: occupancy``): the same, and the miner is never called;
    ``input_only`` (``candidates_from: input``): the same on the whole input crops, occupancy and colour."""
    import threedq.stages.mining as stage_mining
    from threedq.pipeline.lightning_cli import ThreeDQCLI, resolve_config
    from threedq.stages.base import EncoderStage

    torch.manual_seed(0)
    enc = tmp_path / "enc.pt"
    torch.save(EncoderStage(grid_resolution=(32, 32, 16)).encoder.state_dict(), enc)
    calls, handed = [], []
    real_miner, real_shape = stage_mining.mine_correspondences, Mining._shape_positives
    monkeypatch.setattr(stage_mining, "mine_correspondences",
                        lambda *a, **k: calls.append(k["keep"]) or real_miner(*a, **k))

    def shape(self: Mining, pool: dict, mined: dict, *a: object) -> tuple:
        handed.append((mined["query_index"].clone(), mined["target_index"].clone(), pool))
        return real_shape(self, pool, mined, *a)

    monkeypatch.setattr(Mining, "_shape_positives", shape)
    real_cut = Mining._cut_pool

    def two_categories(self: Mining, ds: object, generator: torch.Generator) -> dict:  # the tiny data's: all distinct
        pool = real_cut(self, ds, generator)
        pool["labels"] = torch.where(pool["labels"] >= 0, pool["labels"] % 2, pool["labels"])
        return pool

    monkeypatch.setattr(Mining, "_cut_pool", two_categories)
    cfg = _config(tmp_path, tiny_dataset, enc, "mined_shape")
    paper = "candidates_from: features\n    occupancy_mutual_k: null\n    candidates_per_query: null"
    setting = {"spread": "candidates_per_query: 1\n    occupancy_mutual_k: null\n    candidates_from: features",
               "occupancy": "candidates_per_query: 1\n    occupancy_mutual_k: 3\n    candidates_from: features",
               "occupancy_only": "candidates_per_query: 1\n    occupancy_mutual_k: 3\n    candidates_from: occupancy",
               "input_only": "candidates_per_query: 1\n    occupancy_mutual_k: 3\n    candidates_from: input",
               }.get(oracle, f"oracle_pairs: {oracle}\n    {paper}")
    extra = f"    max_pairs_per_box: 2\n    {setting}\n    pool_min_observed_iou: null\n"
    cfg.write_text(cfg.read_text().replace(FEATURE_CANDIDATES, "").replace("    max_pairs_per_box: 2\n", extra))
    run = tmp_path / "run"
    cli = ThreeDQCLI(args=["fit", "--config", str(resolve_config("stages/mining.yaml")), "--config", str(cfg),
                           f"--trainer.default_root_dir={run}"])
    history = cli.model.mining_history
    assert history and sum(h["pairs"] for h in history) > 0
    if oracle == "spread":
        assert cli.model.hparams.candidates_per_query == 1 and cli.model.hparams.oracle_pairs is None
        assert calls and set(calls) == {6 * 3}  # every query's top_k verified pairs
        for q, _, _ in handed:
            assert q.numel() and q.unique().numel() == q.numel()  # one candidate per query
        return
    if oracle.startswith(("occupancy", "input")):
        from threedq.stages.mining import shape_agreement

        hp = cli.model.hparams
        assert hp.occupancy_mutual_k == 3 and cli.model.candidate_count() == hp.keep
        assert all(h["occupancy_mutual_k"] == 3 for h in history)
        if oracle == "occupancy":
            assert calls and set(calls) == {6 * 3} and hp.candidates_from == "features"
        else:
            assert not calls and all(h["candidates_from"] == oracle[:-5] for h in history)
        for q, t, pool in handed:
            assert q.numel() <= hp.keep and q.unique().numel() == q.numel()
            occ = Mining._input_occupancy(pool) if oracle != "input_only" else \
                F.max_pool3d(pool["raw"].float(), kernel_size=3, stride=1, padding=1)  # occupancy and colour
            N = occ.shape[0]
            a, b = torch.meshgrid(torch.arange(N), torch.arange(N), indexing="ij")
            sim = shape_agreement(occ[a.flatten()], occ[b.flatten()], hp.num_angles)[0].view(N, N)
            sim = sim.masked_fill(pool["scene"][:, None] == pool["scene"][None, :], float("-inf"))
            third = [sorted(row.tolist(), reverse=True)[2] for row in sim]  # each box's 3rd best in other scenes
            for i, j in zip(q.tolist(), t.tolist()):  # within float rounding of the batched agreement
                assert sim[i, j] >= third[i] - 1e-5 and sim[j, i] >= third[j] - 1e-5
        return
    assert cli.model.hparams.oracle_pairs == oracle
    assert bool(calls) == (oracle == "mined_gt_filtered")
    for h in history:
        if h["pairs"]:
            assert h["same_category"] == 1.0 and h["labelled_pairs"] == h["pairs"]


class TestSpreadCandidates:
    """:func:`spread_candidates`: each query's best pairs, round-robin over the queries."""

    def test_hand_computed(self) -> None:
        from threedq.stages.mining import spread_candidates

        q = torch.tensor([5, 5, 2, 5, 2, 7, 2, 7])  # ranks: 5 -> pairs 0, 1, 3; 2 -> 2, 4, 6; 7 -> 5, 7
        assert spread_candidates(q, 2, 10).tolist() == [0, 2, 5, 1, 4, 7]
        assert spread_candidates(q, 1, 10).tolist() == [0, 2, 5]
        assert spread_candidates(q, 3, 4).tolist() == [0, 2, 5, 1]
        assert spread_candidates(q[:0], 2, 4).numel() == 0

    def test_against_a_naive_loop(self) -> None:
        from threedq.stages.mining import spread_candidates

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
        for bad in (0, True, 2.0, "3"):
            with pytest.raises(ValueError, match="candidates_per_query"):
                Mining(grid_resolution=(32, 32, 16), queue_size=64, candidates_per_query=bad)


class TestPoolShapeAgreement:
    """:func:`pool_shape_agreement`: :func:`shape_agreement` of every pair of a pool at once."""

    @staticmethod
    def _crops(n: int, s: int = 8, seed: int = 0) -> torch.Tensor:
        g = torch.Generator().manual_seed(seed)
        return (torch.rand(n, 1, s, s, s, generator=g) > 0.7).float()

    def test_smoke_and_shapes(self) -> None:
        from threedq.stages.mining import pool_shape_agreement

        out = pool_shape_agreement(self._crops(5), 12)
        assert out.shape == (5, 5) and out.dtype == torch.float32
        assert torch.allclose(out.diagonal(), torch.ones(5), atol=1e-5)  # yaw 0: each crop on itself

    def test_against_pairwise_shape_agreement(self) -> None:
        """The naive reference: :func:`shape_agreement` pair by pair; chunking changes nothing."""
        from threedq.stages.mining import pool_shape_agreement, shape_agreement

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
        from threedq.stages.mining import pool_shape_agreement

        occ = self._crops(2, seed=1)
        turned = torch.rot90(occ[0], 1, dims=(2, 3))  # 90 deg about the vertical (Z) axis of a [1, Z, Y, X] crop
        out = pool_shape_agreement(torch.stack([occ[0], turned, occ[1]]), 36)
        assert float(out[0, 1]) == pytest.approx(1.0, abs=1e-5) and float(out[1, 0]) == pytest.approx(1.0, abs=1e-5)
        assert float(out[0, 2]) < 0.9

    def test_gradcheck(self) -> None:
        from threedq.stages.mining import pool_shape_agreement

        occ = (torch.rand(3, 1, 4, 4, 4, dtype=torch.float64) + 0.1).requires_grad_(True)
        assert torch.autograd.gradcheck(lambda x: pool_shape_agreement(x, 4), (occ,))


class TestMutualPoolNeighbours:
    """:func:`mutual_pool_neighbours`: pairs each among the other's k most similar."""

    def test_hand_computed(self) -> None:
        from threedq.stages.mining import mutual_pool_neighbours

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
        from threedq.stages.mining import mutual_pool_neighbours

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
        kw = {"grid_resolution": (32, 32, 16), "queue_size": 64}
        for bad in (0, True, 2.0, "3"):
            with pytest.raises(ValueError, match="occupancy_mutual_k: expected"):
                Mining(occupancy_mutual_k=bad, **kw)
        with pytest.raises(ValueError, match="occupancy_mutual_k: .*positives 'patches'"):
            Mining(occupancy_mutual_k=5, positives="patches", **kw)


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
        from threedq.stages.mining import input_pairs

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
        from threedq.stages.mining import input_pairs, mutual_pool_neighbours, pool_shape_agreement

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
        kw = {"grid_resolution": (32, 32, 16), "queue_size": 64}
        with pytest.raises(ValueError, match="candidates_from: expected"):
            Mining(candidates_from="geometry", **kw)
        for source in ("occupancy", "input"):
            with pytest.raises(ValueError, match=f"candidates_from: '{source}' .*occupancy_mutual_k"):
                Mining(candidates_from=source, occupancy_mutual_k=None, **kw)


class TestRecolourScenes:
    """:func:`recolour_scenes`: one random colour transform per scene, shared by its views."""

    def test_smoke_and_shapes(self) -> None:
        torch.manual_seed(0)
        rgb = torch.rand(2, 3, 3, 12, 16)
        out = recolour_scenes(rgb, 1.0)
        assert out.shape == rgb.shape and out.dtype == rgb.dtype
        assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0
        assert recolour_scenes(rgb, 0.0) is rgb  # off: the input itself

    def test_one_transform_per_scene(self) -> None:
        torch.manual_seed(1)
        view = torch.rand(3, 12, 16)
        rgb = view.expand(2, 3, 3, 12, 16).clone()  # 2 scenes of 3 identical views
        out = recolour_scenes(rgb, 1.0)
        assert torch.allclose(out[:, 0], out[:, 1]) and torch.allclose(out[:, 0], out[:, 2])  # views alike
        assert (out[0] - out[1]).abs().max() > 0.05  # scenes not

    def test_grey_stays_grey(self) -> None:
        """Hue and saturation leave a grey pixel grey, brightness and contrast act on all channels alike
        (hand-derived: R = G = B in, R = G = B out)."""
        torch.manual_seed(2)
        grey = torch.rand(4, 1, 1, 8, 8).expand(4, 2, 3, 8, 8).clone()
        out = recolour_scenes(grey, 1.0)
        assert torch.allclose(out[:, :, 0], out[:, :, 1], atol=1e-5)
        assert torch.allclose(out[:, :, 1], out[:, :, 2], atol=1e-5)

    def test_strength_scales_the_change(self) -> None:
        """Near 0 the colours barely move; at 1 a saturated colour's hue moves (red no longer the largest channel in
        some scene)."""
        torch.manual_seed(3)
        rgb = torch.rand(4, 1, 3, 8, 8)
        assert (recolour_scenes(rgb, 1e-6) - rgb).abs().max() < 1e-3
        red = torch.zeros(16, 1, 3, 4, 4)
        red[:, :, 0] = 0.9
        out = recolour_scenes(red, 1.0)
        assert (out[:, 0, 0].mean((1, 2)) < out[:, 0, 1:].mean((2, 3)).max(1).values).any()

    def test_a_seed_reproduces_it(self) -> None:
        rgb = torch.rand(2, 2, 3, 8, 8)
        torch.manual_seed(4)
        a = recolour_scenes(rgb, 0.5)
        torch.manual_seed(4)
        assert torch.equal(a, recolour_scenes(rgb, 0.5))


@pytest.mark.parametrize("negatives", ["queue", "pool"])
def test_negatives_from_the_queue_or_the_pool(negatives: str, tmp_path: Path, tiny_dataset: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """``negatives: queue`` (MoCo's): primed once with pool voxels, then every step's keys are enqueued. ``pool``:
    the queue is drawn afresh from each refresh's pool and no step writes to it."""
    from threedq.pipeline.lightning_cli import ThreeDQCLI, resolve_config
    from threedq.stages.base import EncoderStage

    torch.manual_seed(0)
    enc = tmp_path / "enc.pt"
    torch.save(EncoderStage(grid_resolution=(32, 32, 16)).encoder.state_dict(), enc)
    source = "mined_pool" if negatives == "pool" else "mined"
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
    cli = ThreeDQCLI(args=["fit", "--config", str(resolve_config("stages/mining.yaml")),
                           "--config", str(_config(tmp_path, tiny_dataset, enc, source)),
                           f"--trainer.default_root_dir={tmp_path / 'run'}"])
    assert cli.model.hparams.negatives == negatives
    assert len(after_refresh) == 2 and len(after_step) == 3  # refreshes at steps 0 and 2
    norms = after_refresh[0].norm(dim=1)
    assert torch.allclose(norms, torch.ones_like(norms), atol=1e-5)  # unit rows
    if negatives == "pool":
        assert not keys
        assert not torch.equal(after_refresh[0], after_refresh[1])  # drawn afresh from the second pool
        for n, queue in after_step:  # no step writes to it
            assert torch.equal(queue, after_refresh[n - 1])
    else:
        k = torch.cat(keys)
        assert k.shape[0] > 0 and torch.equal(after_step[-1][1][: k.shape[0]], k.float())  # the keys, in order
        # not re-primed at the second refresh: the rows no key has reached are the first refresh's pool voxels
        assert torch.equal(after_refresh[1][k.shape[0]:], after_refresh[0][k.shape[0]:])


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
        for bad in (0.0, 1.5, True, "0.5"):
            with pytest.raises(ValueError, match="pool_min_observed_iou"):
                Mining(grid_resolution=(32, 32, 16), queue_size=64, pool_min_observed_iou=bad)


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
        for bad in (0.0, 1.5, True, "0.7"):
            with pytest.raises(ValueError, match="pool_min_scene_iou"):
                Mining(grid_resolution=(32, 32, 16), queue_size=64, pool_min_scene_iou=bad)
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


class TestCslsSetting:
    def test_bad_value(self) -> None:
        for bad in (0, -1, True, 2.0, "5"):
            with pytest.raises(ValueError, match="csls_k"):
                Mining(grid_resolution=(32, 32, 16), queue_size=64, csls_k=bad)
            with pytest.raises(ValueError, match="mutual_k"):
                Mining(grid_resolution=(32, 32, 16), queue_size=64, mutual_k=bad)


class TestRetrievalOccupancyFloor:
    def test_bad_value(self) -> None:
        for bad in (-0.1, True, "0.2", float("nan"), float("inf")):
            with pytest.raises(ValueError, match="retrieval_occupancy_floor"):
                Mining(grid_resolution=(32, 32, 16), queue_size=64, retrieval_occupancy_floor=bad)

    def test_crops(self) -> None:
        """None without a floor; with one, the quantizer's occupancy-weighted crops (hand-computed: the 3^3 dilated
        occupancy times 1, plus the floor), queries first."""
        g = torch.Generator().manual_seed(0)
        feats = torch.randn(5, 3, 4, 4, 4, generator=g)
        raw = torch.zeros(5, 4, 4, 4, 4)
        raw[:, 0, 0, 0, 0] = 1.0  # one occupied corner voxel: its 2^3 corner block is near surface
        pool = {"features": feats, "raw": raw}
        plain = Mining(grid_resolution=(32, 32, 16), queue_size=64, retrieval_occupancy_floor=None)
        assert plain.retrieval_crops(pool, 2) is None
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64)  # the default floor, 0.2
        q, t = m.retrieval_crops(pool, 2)
        w = torch.full((4, 4, 4), 0.2)
        w[:2, :2, :2] = 1.2
        torch.testing.assert_close(t, feats * w)
        torch.testing.assert_close(q, t[:2])
        assert m.retrieval_crops(pool, 2, None) is None  # a probe's override


class TestPrototypeAgreement:
    """``verify_by_prototypes``: a mined pair passes when the bank puts both objects in one prototype at yaws that
    imply the pair's mined yaw (rotated copies of two prototypes by known quarter turns)."""

    A = 4  # quarter turns: exact rotations of a cube crop

    def _bank_file(self, tmp_path: Path, protos: torch.Tensor) -> Path:
        from threedq.quantization.prototypes import PrototypeBank

        bank = PrototypeBank(3, protos.shape[1], protos.shape[-1], self.A)
        bank.prototypes[:2] = protos
        bank.active[:2] = True
        path = tmp_path / "quantizer.ckpt"
        torch.save({"state_dict": {f"bank.{k}": v for k, v in bank.state_dict().items()},
                    "hyper_parameters": {"_class_path": "threedq.stages.quantizer.Quantizer", "num_prototypes": 3,
                                         "crop_size": protos.shape[-1], "num_angles": self.A,
                                         "occupancy_floor": None}}, path)
        return path

    def test_rotated_copies_with_known_angles(self, tmp_path: Path) -> None:
        from threedq.geometry import rotate_yaw

        torch.manual_seed(0)
        S, C = 8, 32
        protos = torch.randn(2, C, S, S, S)
        path = self._bank_file(tmp_path, protos)
        m = Mining(grid_resolution=(32, 32, 16), queue_size=64, crop_size=S, num_angles=self.A, bank_ckpt=str(path),
                   verify_by_prototypes=True, prototype_yaw_window=0, positives="patches", **PAPER_MINER)
        # pool object n = prototype k_n rotated by -a_n quarter turns, so that rotating it by a_n gives the prototype
        k = torch.tensor([0, 0, 1, 1, 0])
        a = torch.tensor([0, 1, 3, 2, 2])
        feats = torch.stack([rotate_yaw(protos[kk][None], torch.tensor([-2 * math.pi * int(aa) / self.A]))[0]
                             for kk, aa in zip(k, a)])
        pool = {"features": feats, "raw": torch.ones(5, 4, S, S, S)}
        qi = torch.tensor([0, 0, 1, 2, 0, 4])
        ti = torch.tensor([1, 1, 4, 3, 2, 0])
        # naive: same prototype, and the target rotated by b lands on the query: b = a_t - a_q (mod A)
        b = torch.tensor([1, 2, 1, 3, 0, 0])
        want = [bool(k[q] == k[t]) and int(bb) % self.A == (int(a[t]) - int(a[q])) % self.A for q, t, bb in zip(qi, ti, b)]
        assert want == [True, False, True, True, False, False]
        got = m.prototype_agreement(pool, {"query_index": qi, "target_index": ti, "yaw": b})
        assert got.tolist() == want
        # a window of one step lets the off-by-one yaw through, never another prototype
        m.hparams.prototype_yaw_window = 1
        got = m.prototype_agreement(pool, {"query_index": qi, "target_index": ti, "yaw": b})
        assert got.tolist() == [True, True, True, True, False, False]

    def test_errors(self, tmp_path: Path) -> None:
        kw = {"grid_resolution": (32, 32, 16), "queue_size": 64, "crop_size": 8, "num_angles": self.A,
              "positives": "patches", **PAPER_MINER}
        with pytest.raises(ValueError, match="bank_ckpt"):
            Mining(verify_by_prototypes=True, **kw)
        with pytest.raises(InputError, match="no such file"):
            Mining(verify_by_prototypes=True, bank_ckpt=str(tmp_path / "none.ckpt"), **kw)
        path = self._bank_file(tmp_path, torch.randn(2, 32, 8, 8, 8))
        with pytest.raises(InputError, match="num_angles"):
            Mining(verify_by_prototypes=True, bank_ckpt=str(path), **{**kw, "num_angles": 36})
        with pytest.raises(ValueError, match="prototype_yaw_window"):
            Mining(verify_by_prototypes=True, bank_ckpt=str(path), prototype_yaw_window=-1, **kw)
        # not asked to verify: the bank is not read
        Mining(bank_ckpt=str(tmp_path / "none.ckpt"), **kw)


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
        with pytest.raises(ValueError, match="round_lr"):
            Mining(round_lr="cosine", **self.kw)
        for bad in (0, -1, 1.5, True):
            with pytest.raises(ValueError, match="em_round"):
                Mining(em_round=bad, **self.kw)


class TestPrototypeKeys:
    """``prototype_weight``: each query voxel's second positive is its prototype's feature at the same cell, the
    prototype turned by the object's assigned yaw onto the object."""

    def test_rotated_copies_with_known_angles(self) -> None:
        from threedq.geometry import rotate_yaw

        torch.manual_seed(0)
        S, C, A = 8, 16, 4  # quarter turns: exact on a cube crop
        protos = torch.randn(5, C, S, S, S)
        a = torch.tensor([0, 1, 2, 3, 1])
        # object n = its prototype turned by -a_n (so that turning the object by a_n gives the prototype)
        objects = rotate_yaw(protos, -a.float() * (2 * math.pi / A))
        vox = torch.randint(0, S, (5, 8, 3))
        keys, valid = prototype_keys(protos, a, vox, A)
        assert keys.shape == (5, 8, C) and valid.shape == (5, 8) and bool(valid.all())
        want = torch.stack([F.normalize(objects[n][:, vox[n, :, 0], vox[n, :, 1], vox[n, :, 2]].T, dim=1)
                            for n in range(5)])
        torch.testing.assert_close(keys, want, atol=1e-5, rtol=0)
        # the wrong yaw gives other cells: not the object's features
        wrong, _ = prototype_keys(protos, (a + 1) % A, vox, A)
        assert (wrong * want).sum(2).mean() < 0.5

    def test_against_a_naive_loop(self) -> None:
        from threedq.geometry import rotate_yaw

        torch.manual_seed(1)
        S, C, A = 8, 4, 36
        protos = torch.randn(3, C, S, S, S, dtype=torch.float64)
        a = torch.tensor([5, 0, 31])
        vox = torch.randint(0, S, (3, 6, 3))
        keys, valid = prototype_keys(protos, a, vox, A)
        for n in range(3):
            turned = rotate_yaw(protos[n : n + 1], torch.tensor([-2 * math.pi * int(a[n]) / A], dtype=torch.float64))[0]
            for v in range(6):
                f = turned[:, int(vox[n, v, 0]), int(vox[n, v, 1]), int(vox[n, v, 2])]
                assert bool(valid[n, v]) == bool(f.norm() > 1e-6)
                if valid[n, v]:
                    torch.testing.assert_close(keys[n, v], f / f.norm())

    def test_cells_turned_in_from_outside_are_not_positives(self) -> None:
        S, C, A = 8, 2, 8
        protos = torch.ones(1, C, S, S, S)
        corner = torch.tensor([[[0, 0, 0], [0, 4, 4]]])  # a corner cell comes from outside the crop at 45 deg
        keys, valid = prototype_keys(protos, torch.tensor([1]), corner, A)
        assert valid.tolist() == [[False, True]] and float(keys[0, 0].abs().sum()) == 0.0

    def test_no_pairs(self) -> None:
        keys, valid = prototype_keys(torch.zeros(0, 4, 8, 8, 8), torch.zeros(0, dtype=torch.long),
                                     torch.zeros(0, 8, 3, dtype=torch.long), 36)
        assert keys.shape == (0, 8, 4) and valid.shape == (0, 8) and valid.dtype == torch.bool

    def test_gradcheck(self) -> None:
        protos = torch.randn(2, 3, 4, 4, 4, dtype=torch.float64, requires_grad=True)
        vox = torch.tensor([[[1, 1, 2], [2, 2, 1]], [[0, 1, 1], [3, 2, 2]]])
        assert torch.autograd.gradcheck(lambda p: prototype_keys(p, torch.tensor([3, 7]), vox, 36)[0], (protos,))


class TestPrototypePurity:
    def test_hand_computed(self) -> None:
        prototype = torch.tensor([0, 0, 0, 1, 1, 2])
        labels = torch.tensor([4, 4, 7, 5, -1, 9])
        # query 0: mates 1 (4), 2 (7) -> 1/2; query 3: its only mate is unlabelled -> no share; query 4: unlabelled;
        # query 2: mates 0, 1 (both 4) -> 0
        assert prototype_purity(prototype, labels, torch.tensor([0, 3, 4, 2])) == pytest.approx(0.25)
        assert math.isnan(prototype_purity(prototype, labels, torch.tensor([3, 5])))


class TestPrototypeWeightErrors:
    def test_errors(self, tmp_path: Path) -> None:
        kw = {"grid_resolution": (32, 32, 16), "queue_size": 64, "crop_size": 8, "num_angles": 4}
        with pytest.raises(ValueError, match="prototype_weight.*bank_ckpt"):
            Mining(prototype_weight=1.0, **kw)
        path = _bank_file(tmp_path / "bank.ckpt", torch.randn(2, 32, 8, 8, 8), 4)
        for bad in (-1.0, True, "1"):
            with pytest.raises(ValueError, match="prototype_weight"):
                Mining(prototype_weight=bad, bank_ckpt=str(path), **kw)
        with pytest.raises(ValueError, match="prototype_weight.*source"):
            Mining(source="vc", prototype_weight=1.0, bank_ckpt=str(path), **kw)
        with pytest.raises(InputError, match="no such file"):
            Mining(prototype_weight=1.0, bank_ckpt=str(tmp_path / "none.ckpt"), **kw)
        with pytest.raises(InputError, match="num_angles"):
            Mining(prototype_weight=1.0, bank_ckpt=str(path), **{**kw, "num_angles": 36})
        m = Mining(prototype_weight=1.0, bank_ckpt=str(path), **kw)
        assert m.verify_bank is not None and m.verify_bank.num_active == 2


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
        from threedq.stages.mining import gt_box_iou

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
