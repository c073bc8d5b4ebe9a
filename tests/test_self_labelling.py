"""Detector self-labelling: center-surround similarity, the confined loss mask, the labelling rule, a short fit."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import torch
import torch.nn.functional as F

from threedq.geometry import VoxelGridSpec
from threedq.stages.detector import Detector, cell_centres, detection_targets
from threedq.stages.self_labelling import SelfLabelling, center_surround_similarity, self_label_targets

# a 2 m x 2 m x 1 m grid of 10 cm cells: [Z, Y, X] = [10, 20, 20]
SPEC = VoxelGridSpec((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0), (20, 20, 10))


def _floor_grid(channels: int = 8, seed: int = 0) -> torch.Tensor:
    """Every voxel the same unit 'floor' feature plus a little noise: ``[1, C, Z, Y, X]``."""
    g = torch.Generator().manual_seed(seed)
    floor = F.normalize(torch.ones(channels), dim=0)
    vol = floor.view(1, channels, 1, 1, 1).expand(1, channels, *SPEC.volume_shape).clone()
    return F.normalize(vol + 0.05 * torch.randn(vol.shape, generator=g), dim=1)


def _plant_blob(vol: torch.Tensor, lo: tuple[float, float, float], hi: tuple[float, float, float], feature: torch.Tensor) -> None:
    idx = [((torch.arange(n) + 0.5) * v + b) for n, v, b in zip(SPEC.resolution, SPEC.voxel_size, SPEC.bounds_min)]
    inx = [(c >= a) & (c <= b) for c, a, b in zip(idx, lo, hi)]  # x, y, z
    m = inx[2][:, None, None] & inx[1][None, :, None] & inx[0][None, None, :]
    vol[0][:, m] = feature[:, None]


class TestCenterSurroundSimilarity:
    def test_blob_low_floor_high(self) -> None:
        vol = _floor_grid()
        blob = F.normalize(torch.tensor([1.0, -1, 1, -1, 1, -1, 1, -1]), dim=0)
        _plant_blob(vol, (-0.3, -0.3, 0.2), (0.1, 0.1, 0.6), blob)
        boxes = torch.tensor([[[-0.3, -0.3, 0.2, 0.1, 0.1, 0.6],    # the isolated blob
                               [0.4, 0.4, 0.2, 0.7, 0.7, 0.5]]])    # plain floor  # fmt: skip
        s = center_surround_similarity(vol, boxes, SPEC, size=4)
        assert s.shape == (1, 2)
        assert s[0, 0] < 0.2 and s[0, 1] > 0.9

    def test_hand_computed_half_and_half(self) -> None:
        # the centre box holds feature a; of its six neighbours, the three on +x, +y, +z hold a, the others b
        # (orthogonal to a): mean cosine 3/6 = 0.5 (noise-free volume)
        a, b = torch.eye(4)[0], torch.eye(4)[1]
        vol = b.view(1, 4, 1, 1, 1).expand(1, 4, *SPEC.volume_shape).clone()
        box = (-0.2, -0.2, 0.4, 0.0, 0.0, 0.6)
        _plant_blob(vol, box[:3], box[3:], a)
        for ax in range(3):
            lo, hi = list(box[:3]), list(box[3:])
            lo[ax] += 0.2
            hi[ax] += 0.2
            _plant_blob(vol, tuple(lo), tuple(hi), a)
        s = center_surround_similarity(vol, torch.tensor([[box]]), SPEC, size=2)
        assert s[0, 0] == pytest.approx(0.5, abs=1e-5)

    def test_neighbours_outside_the_grid_are_left_out(self) -> None:
        vol = _floor_grid()
        # a box whose -x neighbour lies wholly outside: the mean is over the five inside, still floor-like
        s = center_surround_similarity(vol, torch.tensor([[[-1.0, -0.2, 0.3, -0.7, 0.1, 0.6]]]), SPEC, size=4)
        assert s[0, 0] > 0.9
        # the whole grid as a box: every neighbour outside -> NaN
        assert torch.isnan(center_surround_similarity(vol, torch.tensor([[[-1.0, -1, 0, 1, 1, 1]]]), SPEC, 4)).all()

    def test_shapes_and_errors(self) -> None:
        vol = _floor_grid().expand(2, -1, -1, -1, -1)
        assert center_surround_similarity(vol, torch.zeros(2, 0, 6), SPEC).shape == (2, 0)
        with pytest.raises(ValueError, match="aabb"):
            center_surround_similarity(vol, torch.zeros(3, 1, 6), SPEC)

    def test_gradcheck(self) -> None:
        vol = _floor_grid(channels=2).double().requires_grad_(True)
        boxes = torch.tensor([[[-0.3, -0.3, 0.2, 0.1, 0.1, 0.6]]], dtype=torch.float64)
        # fast mode: a random vector-Jacobian product against finite differences (the full Jacobian took 10 s)
        assert torch.autograd.gradcheck(lambda v: center_surround_similarity(v, boxes, SPEC, size=2), (vol,),
                                        fast_mode=True)


class TestSelfLabelTargets:
    def test_loss_confined_to_the_two_regions(self) -> None:
        cell = torch.tensor(SPEC.voxel_size) * 2
        centres = cell_centres(torch.tensor(SPEC.bounds_min), cell, tuple(n // 2 for n in SPEC.volume_shape))
        anchor = torch.tensor([0.4, 0.4, 0.4])
        pos = torch.tensor([[[-0.6, -0.6, 0.0, -0.2, -0.2, 0.4]]])
        neg = torch.tensor([[[0.2, 0.2, 0.0, 0.8, 0.6, 0.4], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]]])
        neg_mask = torch.tensor([[True, False]])
        label, target = self_label_targets(centres, pos, torch.ones(1, 1, dtype=torch.bool), neg, neg_mask, anchor)
        full, full_target, _ = detection_targets(centres, pos, torch.ones(1, 1, dtype=torch.bool), anchor)
        # positives and their targets exactly as in the warm start
        assert torch.equal(label == 1, full == 1)
        assert torch.equal(full_target[:, :, label[0] == 1], target[:, :, label[0] == 1])
        # negatives: exactly the cells whose centre lies inside the (valid) negative box
        p = centres
        inside = ((p >= neg[0, 0, :3]) & (p <= neg[0, 0, 3:])).all(-1)
        assert torch.equal(label[0] == 0, inside) and inside.any()
        # everything else ignored
        assert torch.equal(label[0] == -1, ~inside & ~(full[0] == 1))

    def test_surround_shell_is_negative(self) -> None:
        cell = torch.tensor(SPEC.voxel_size) * 2
        centres = cell_centres(torch.tensor(SPEC.bounds_min), cell, tuple(n // 2 for n in SPEC.volume_shape))
        anchor = torch.tensor([0.4, 0.4, 0.4])
        pos = torch.tensor([[[-0.4, -0.4, 0.2, 0.0, 0.0, 0.6]]])
        one = torch.ones(1, 1, dtype=torch.bool)
        none = torch.zeros(1, 1, 6), torch.zeros(1, 1, dtype=torch.bool)
        label, _ = self_label_targets(centres, pos, one, *none, anchor, negative_margin=0.1, surround=0.5)
        plain, _ = self_label_targets(centres, pos, one, *none, anchor, negative_margin=0.1)
        p = centres
        grown = ((p >= pos[0, 0, :3] - 0.2) & (p <= pos[0, 0, 3:] + 0.2)).all(-1)
        near = ((p >= pos[0, 0, :3] - 0.1) & (p <= pos[0, 0, 3:] + 0.1)).all(-1)
        # negatives: the grown box minus the box and its margin; positives unchanged; the rest ignored
        assert torch.equal(label[0] == 0, grown & ~near) and (grown & ~near).any()
        assert torch.equal(label == 1, plain == 1)
        assert torch.equal(label[0] == -1, ~(grown & ~near) & ~(plain[0] == 1))

    def test_spared_cells_are_never_negative(self) -> None:
        cell = torch.tensor(SPEC.voxel_size) * 2
        centres = cell_centres(torch.tensor(SPEC.bounds_min), cell, tuple(n // 2 for n in SPEC.volume_shape))
        anchor = torch.tensor([0.4, 0.4, 0.4])
        pos = torch.tensor([[[-0.4, -0.4, 0.2, 0.0, 0.0, 0.6]]])
        neg = torch.tensor([[[0.2, 0.2, 0.0, 0.8, 0.6, 0.4]]])
        spare = torch.tensor([[[0.5, 0.1, 0.0, 0.9, 0.5, 0.4],       # cuts into the negative box
                               [-0.6, -0.6, 0.0, 0.2, 0.2, 0.8]]])   # covers the positive box and its shell  # fmt: skip
        one = torch.ones(1, 1, dtype=torch.bool)
        args = (centres, pos, one, neg, one, anchor, 0.5, 0.1, 0.5)
        plain, plain_target = self_label_targets(*args)
        label, target = self_label_targets(*args, spare_aabb=spare, spare_mask=torch.ones(1, 2, dtype=torch.bool))
        p = centres
        spared = ((p >= spare[0, :, None, None, None, :3]) & (p <= spare[0, :, None, None, None, 3:])).all(-1).any(0)
        # a negative survives exactly where it is not spared; positives and their targets untouched
        assert torch.equal(label[0] == 0, (plain[0] == 0) & ~spared)
        assert ((plain[0] == 0) & spared).any() and (label[0] == 0).any()
        assert torch.equal(label == 1, plain == 1) and torch.equal(target, plain_target)
        # a masked-out spared box spares nothing
        none, _ = self_label_targets(*args, spare_aabb=spare, spare_mask=torch.zeros(1, 2, dtype=torch.bool))
        assert torch.equal(none, plain)

    def test_no_labels_no_loss(self) -> None:
        det = Detector(grid_min=SPEC.bounds_min, grid_max=SPEC.bounds_max, grid_resolution=SPEC.resolution, feature_dim=8)
        z = torch.zeros(1, 0, 6)
        m = torch.zeros(1, 0, dtype=torch.bool)
        label, target = self_label_targets(det.centres, z, m, z, m, det.anchor)
        assert (label == -1).all()
        logits, box = det.head(torch.randn(1, 8, *det.feature_grid.volume_shape))
        r = det.loss_from_targets(logits, box, label, target)
        assert float(r["loss"]) == 0.0 and int(r["num_pos"]) == 0 and int(r["num_neg"]) == 0


class TestLabellingRule:
    """A planted case: the bank holds the crop of an object; a detection on it is positive, one on the floor
    negative, and one on an object that is also like its surroundings is vetoed (negative)."""

    def _stage(self, **kwargs: Any) -> SelfLabelling:
        from threedq.quantization.prototypes import PrototypeBank

        kwargs = {"proposal_positives": False, "spare_proposals": False, **kwargs}  # each switch tested alone
        st = SelfLabelling(grid_min=(-1.28, -1.28, -0.32), grid_max=(1.28, 1.28, 0.96), grid_resolution=(32, 32, 16),
                           feature_dim=8, crop_size=4, num_angles=4, **kwargs)  # fmt: skip
        st.bank = PrototypeBank(2, 8, 4, num_angles=4, method="exact")
        return st

    def _scene(self) -> tuple[torch.Tensor, torch.Tensor]:
        fg = VoxelGridSpec((-1.28, -1.28, -0.32), (1.28, 1.28, 0.96), (16, 16, 8))
        floor = F.normalize(torch.ones(8), dim=0)
        vol = floor.view(1, 8, 1, 1, 1).expand(1, 8, *fg.volume_shape).clone()
        obj = F.normalize(torch.tensor([1.0, -1, 1, -1, 1, -1, 1, -1]), dim=0)
        idx = [((torch.arange(n) + 0.5) * v + b) for n, v, b in zip(fg.resolution, fg.voxel_size, fg.bounds_min)]
        m = ((idx[2] >= 0) & (idx[2] <= 0.48))[:, None, None] & ((idx[1] >= -0.8) & (idx[1] <= -0.32))[None, :, None] \
            & ((idx[0] >= -0.8) & (idx[0] <= -0.32))[None, None, :]
        vol[0][:, m] = obj[:, None]
        boxes = torch.tensor([[-0.8, -0.8, 0.0, -0.32, -0.32, 0.48],   # the object
                              [0.4, 0.4, 0.0, 0.88, 0.88, 0.48]])      # plain floor  # fmt: skip
        return vol, boxes

    def _label(self, st: SelfLabelling, vol: torch.Tensor, boxes: torch.Tensor, detected: torch.Tensor | None = None,
               proposals: torch.Tensor | None = None) -> torch.Tensor:
        from threedq.geometry import crop_boxes

        st.bank.add(crop_boxes(vol, boxes[:1][None], st.feature_grid, 4)[0], threshold=2.0)  # the object's crop
        det = boxes if detected is None else detected
        st.detect = lambda logits, box, thr=None: [{"boxes": det.clone(), "scores": torch.ones(len(det))}]  # type: ignore
        gt_batch = {"aabb": boxes[None], "box_mask": torch.ones(1, 2, dtype=torch.bool)}
        rows, _ = st._label_batch(vol, gt_batch, None if proposals is None else [proposals])[0]
        return rows

    def test_object_positive_floor_negative(self) -> None:
        vol, boxes = self._scene()
        rows = self._label(self._stage(), vol, boxes)
        assert rows.shape == (2, 7)
        assert rows[0, 0] == 1 and torch.allclose(rows[0, 1:], boxes[0])
        assert rows[1, 0] == 0 and torch.allclose(rows[1, 1:], boxes[1])

    def test_veto(self) -> None:
        from threedq.geometry import crop_boxes

        vol, boxes = self._scene()
        # the bank also holds the floor's crop: the floor box is above both thresholds, and negative
        st = self._stage()
        st.bank.add(crop_boxes(vol, boxes[1:][None], st.feature_grid, 4)[0], threshold=2.0)
        rows = self._label(st, vol, boxes)
        assert rows[1, 0] == 0

    def test_spare_proposals_rows(self) -> None:
        vol, boxes = self._scene()
        rows = self._label(self._stage(spare_proposals=True), vol, boxes, boxes, boxes[:1])
        assert rows.shape == (3, 7)
        assert rows[:2, 0].tolist() == [1.0, 0.0]
        assert rows[2, 0] == 2 and torch.allclose(rows[2, 1:], boxes[0])

    def test_proposal_positives(self) -> None:
        vol, boxes = self._scene()
        other = torch.tensor([[0.0, -0.8, 0.0, 0.3, -0.5, 0.3]])  # a pseudo-box nothing detected, unlike a prototype
        props = torch.cat([boxes[:1], other])
        loose = torch.cat([boxes[:1] + torch.tensor([0.08, 0.0, 0.0, 0.08, 0.0, 0.0]), boxes[1:]])
        rows = self._label(self._stage(proposal_positives=True), vol, boxes, loose, props)
        # every pseudo-box is a positive once (the snapped detection is not a second one); the floor stays negative
        assert rows.shape == (3, 7)
        assert rows[:2, 0].tolist() == [1.0, 1.0] and torch.allclose(rows[:2, 1:], props)
        assert rows[2, 0] == 0 and torch.allclose(rows[2, 1:], boxes[1])
        plain = self._label(self._stage(), vol, boxes, loose, props)
        assert (plain[:, 0] == 1).sum() == 1  # without the switch only the vouched-for object

    def test_occupancy_weighted_bank(self) -> None:
        # a bank fitted on occupancy-weighted crops scores the candidates' weighted crops (the quantizer's
        # occupancy_floor, read from its checkpoint): the object is positive at cosine 1, and every score is the
        # bank's own assignment of the weighted crop
        from threedq.geometry import crop_boxes
        from threedq.quantization.prototypes import prototype_crops

        vol, boxes = self._scene()
        st = self._stage()
        st.occupancy_floor = 0.2
        occ = torch.zeros(1, 1, *st.grid.volume_shape)
        occ[..., 4:10, 6:10, 6:10] = 1.0  # input-grid cells of the object (z 0-0.48, x and y -0.8..-0.32)
        weighted = lambda b: prototype_crops(crop_boxes(vol, b[None], st.feature_grid, 4)[0],  # noqa: E731
                                             crop_boxes(occ, b[None], st.grid, 4)[0], 0.2)
        st.bank.add(weighted(boxes[:1]), threshold=2.0)
        det = boxes.clone()
        st.detect = lambda logits, box, thr=None: [{"boxes": det.clone(), "scores": torch.ones(len(det))}]  # type: ignore
        gt_batch = {"aabb": boxes[None], "box_mask": torch.ones(1, 2, dtype=torch.bool)}
        rows, diag = st._label_batch(vol, gt_batch, None, occ)[0]
        assert rows[0, 0] == 1 and rows[1, 0] == 0
        torch.testing.assert_close(diag["proto"], st.bank.assign(weighted(boxes)).score)
        assert diag["proto"][0] > 0.999
        with pytest.raises(ValueError, match="occupancy"):
            st._label_batch(vol, gt_batch, None)

    def test_bad_arguments(self) -> None:
        from conftest import refused

        for name, bad in (("positive_threshold", 1.5), ("negative_threshold", -2.0), ("candidate_threshold", 1.5),
                          ("pool_scenes", 0), ("batch_size", 0), ("score_threshold", -0.1)):
            assert name in refused(SelfLabelling, feature_dim=8, **{name: bad})
        with pytest.raises(ValueError, match="freeze_encoder"):
            SelfLabelling(feature_dim=8, freeze_encoder=False)


def test_short_fit_and_resume(tmp_path: Path, tiny_dataset: Path) -> None:
    """Detector -> quantizer -> self-labelling on the tiny fixture; the labels travel in the checkpoint."""
    from threedq.pipeline.lightning_cli import ThreeDQCLI, resolve_config
    from threedq.stages.base import EncoderStage

    torch.manual_seed(0)
    enc = tmp_path / "enc.pt"
    torch.save(EncoderStage(grid_resolution=(32, 32, 16)).encoder.state_dict(), enc)
    data = (f"--data.init_args.data_dir={tiny_dataset}", "--data.init_args.num_scenes=12",
            "--data.init_args.image_size=[32, 32]", "--data.init_args.num_views=4",
            "--data.init_args.generator_workers=1", "--trainer.enable_progress_bar=false",
            "--trainer.enable_model_summary=false", "--trainer.limit_val_batches=0", "--trainer.num_sanity_val_steps=0")
    common = (f"--model.init_args.encoder_ckpt={enc}", "--model.init_args.grid_resolution=[32, 32, 16]")
    det = tmp_path / "det"
    ThreeDQCLI(args=["fit", "--config", str(resolve_config("stages/detector.yaml")), *common, *data,
                     "--data.init_args.boxes=gt", "--trainer.max_steps=2", f"--trainer.default_root_dir={det}",
                     "--model.init_args.anchor_size=[0.21, 0.22, 0.23]", "--model.init_args.nms_iou=0.35"])
    q = tmp_path / "q"
    ThreeDQCLI(args=["fit", "--config", str(resolve_config("stages/quantizer.yaml")), *common, *data,
                     "--model.init_args.num_prototypes=4", "--model.init_args.crop_size=8",
                     "--model.init_args.num_angles=8", "--trainer.max_steps=-1", f"--trainer.default_root_dir={q}"])
    run = tmp_path / "sl"
    args = ["--config", str(resolve_config("stages/self_labelling.yaml")), *common, *data,
            f"--model.init_args.detector_ckpt={det / 'checkpoints' / 'last.ckpt'}",
            f"--model.init_args.bank_ckpt={q / 'checkpoints' / 'last.ckpt'}", "--model.init_args.crop_size=8",
            "--model.init_args.num_angles=8", "--model.init_args.candidate_threshold=0.0",
            "--model.init_args.positive_threshold=0.0", "--model.init_args.batch_size=2",
            f"--trainer.default_root_dir={run}"]
    # what the config leaves null or at the class default is the detector's, in the hyperparameters the stage reads
    # and saves (LightningCLI records the parsed config: the stage puts the detector's values back over it)
    parsed = ThreeDQCLI(args=args, run=False).model
    assert parsed.hparams.anchor_size == (0.21, 0.22, 0.23) and parsed.hparams.nms_iou == 0.35
    cli = ThreeDQCLI(args=["fit", *args, "--trainer.max_steps=2"])
    model = cli.model
    assert isinstance(model, SelfLabelling) and model.trainer.global_step == 2
    assert bool(model.labelled) and model.labels.shape[1] == 8 and len(model.labels) > 0
    info = json.loads((run / "self_labels" / "labels.json").read_text())
    kinds = model.labels[:, 1]
    assert info["scenes"] == len(model._pool_files)
    assert info["positive_boxes"] == int((kinds == 1).sum()) and info["negative_boxes"] == int((kinds == 0).sum())
    # the packaged config: every pseudo-box a positive (at least the vouched-for ones), every one also spared
    assert info["negatives"] == info["negative_boxes"] and info["positive_boxes"] >= info["positives"]
    assert int((kinds == 2).sum()) == info["positive_boxes"] > 0  # positives and spared boxes: the pseudo-boxes
    assert torch.isfinite(cli.trainer.logged_metrics["train/loss"])
    ckpt = run / "checkpoints" / "last.ckpt"
    state = torch.load(ckpt, weights_only=True, map_location="cpu")["state_dict"]
    assert torch.equal(state["labels"], model.labels.cpu())
    # resumed with other thresholds: the labels come from the checkpoint, not from a new labelling pass
    cli2 = ThreeDQCLI(args=["fit", *args, "--trainer.max_steps=4", "--model.init_args.positive_threshold=0.99",
                            "--ckpt_path", str(ckpt)])  # fmt: skip
    assert cli2.model.trainer.global_step == 4
    assert torch.equal(cli2.model.labels.cpu(), state["labels"])
    # the packaged config's anchor_size: null takes the anchor the detector was trained with (the median extent of
    # its training boxes, saved in its hyperparameters)
    from threedq.errors import InputError
    from threedq.stages.base import checkpoint_hparams

    trained = checkpoint_hparams(det / "checkpoints" / "last.ckpt")["anchor_size"]
    assert trained is not None and model.hparams.anchor_size == tuple(trained) == (0.21, 0.22, 0.23)
    assert torch.allclose(model.anchor.cpu(), torch.tensor(trained, dtype=torch.float32))
    assert tuple(checkpoint_hparams(ckpt)["anchor_size"]) == (0.21, 0.22, 0.23)  # what the test step decodes with
    # a detector trained with another anchor is refused by name (its boxes would decode at the wrong size)
    with pytest.raises(InputError, match=r"det.*last\.ckpt: field 'anchor_size': the detector was trained with "
                                         r"anchor_size=\[.*\], this stage asks for \[0\.3, 0\.3, 0\.3\]"):
        SelfLabelling(encoder_ckpt=str(enc), grid_resolution=(32, 32, 16), anchor_size=(0.3, 0.3, 0.3),
                      detector_ckpt=str(det / "checkpoints" / "last.ckpt"))


def test_test_a_checkpoint_from_another_folder(tmp_path: Path, tiny_dataset: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Stages run with relative paths save them in their hyperparameters, which Lightning puts over the config of a
    later ``threedq test --ckpt_path``; from another folder those files are not there, and the checkpoint's own
    weights (encoder, head, bank) are used instead of failing."""
    from threedq.pipeline.lightning_cli import ThreeDQCLI, resolve_config
    from threedq.stages.base import EncoderStage

    run_dir = tmp_path / "project"
    run_dir.mkdir()
    monkeypatch.chdir(run_dir)
    torch.manual_seed(0)
    torch.save(EncoderStage(grid_resolution=(32, 32, 16)).encoder.state_dict(), "enc.pt")
    data = (f"--data.init_args.data_dir={tiny_dataset}", "--data.init_args.num_scenes=12",
            "--data.init_args.image_size=[32, 32]", "--data.init_args.num_views=4",
            "--data.init_args.generator_workers=1", "--trainer.enable_progress_bar=false",
            "--trainer.enable_model_summary=false", "--trainer.limit_val_batches=0", "--trainer.num_sanity_val_steps=0")
    common = ("--model.init_args.encoder_ckpt=enc.pt", "--model.init_args.grid_resolution=[32, 32, 16]")
    ThreeDQCLI(args=["fit", "--config", str(resolve_config("stages/detector.yaml")), *common, *data,
                     "--data.init_args.boxes=gt", "--trainer.max_steps=2", "--trainer.default_root_dir=det"])
    ThreeDQCLI(args=["fit", "--config", str(resolve_config("stages/quantizer.yaml")), *common, *data,
                     "--model.init_args.num_prototypes=4", "--model.init_args.crop_size=8",
                     "--model.init_args.num_angles=8", "--trainer.max_steps=-1", "--trainer.default_root_dir=q"])
    sl_args = ["--config", str(resolve_config("stages/self_labelling.yaml")), *data, "--model.init_args.crop_size=8",
               "--model.init_args.num_angles=8", "--model.init_args.candidate_threshold=0.0",
               "--model.init_args.batch_size=2"]
    ThreeDQCLI(args=["fit", *sl_args, *common, "--model.init_args.detector_ckpt=det/checkpoints/last.ckpt",
                     "--model.init_args.bank_ckpt=q/checkpoints/last.ckpt", "--trainer.max_steps=2",
                     "--trainer.default_root_dir=sl"])
    ckpt = (run_dir / "sl" / "checkpoints" / "last.ckpt").resolve()
    saved = torch.load(ckpt, weights_only=True, map_location="cpu")
    assert saved["hyper_parameters"]["detector_ckpt"] == "det/checkpoints/last.ckpt"  # relative: the bug's setting
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    cli = ThreeDQCLI(args=["test", *sl_args, "--ckpt_path", str(ckpt), "--trainer.logger=false",
                           "--trainer.default_root_dir=t"])
    assert cli.model.hparams.encoder_ckpt == str(ckpt) and cli.model.hparams.detector_ckpt is None
    assert "test/map_50" in cli.trainer.logged_metrics
    head = {k: v for k, v in saved["state_dict"].items() if k.startswith("head.")}
    assert all(torch.equal(cli.model.state_dict()[k].cpu(), v) for k, v in head.items())


def test_a_checkpoint_tested_without_its_detector_decodes_as_written(tmp_path: Path) -> None:
    """``threedq em`` tests a self-labelled checkpoint without its ``detector_ckpt``: the decoding it was written
    with (anchor, thresholds, NMS, refinement) comes back from the checkpoint, unless given."""
    st = SelfLabelling(grid_min=(-1.28, -1.28, -0.32), grid_max=(1.28, 1.28, 0.96), grid_resolution=(32, 32, 16),
                       feature_dim=8, anchor_size=(0.2, 0.3, 0.4), nms_iou=0.42, refine_iou=0.0, max_detections=5)
    ckpt = {"hyper_parameters": dict(st.hparams), "state_dict": st.state_dict()}
    fresh = SelfLabelling(grid_min=(-1.28, -1.28, -0.32), grid_max=(1.28, 1.28, 0.96), grid_resolution=(32, 32, 16),
                          feature_dim=8)
    assert fresh.hparams.nms_iou == Detector(feature_dim=8).hparams.nms_iou != 0.42
    fresh.on_load_checkpoint(ckpt)
    assert (fresh.hparams.nms_iou, fresh.hparams.refine_iou, fresh.hparams.max_detections) == (0.42, 0.0, 5)
    assert fresh.anchor_size == (0.2, 0.3, 0.4)  # from the checkpoint's anchor buffer
    assert torch.allclose(fresh.anchor, torch.tensor([0.2, 0.3, 0.4]))
    given = SelfLabelling(grid_min=(-1.28, -1.28, -0.32), grid_max=(1.28, 1.28, 0.96), grid_resolution=(32, 32, 16),
                          feature_dim=8, nms_iou=0.2)
    given.on_load_checkpoint(ckpt)
    assert given.hparams.nms_iou == 0.2 and given.hparams.refine_iou == 0.0
