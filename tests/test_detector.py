"""Detector stage: target assignment, box coding round trip, head shapes, a one-batch overfit, figures, and
the DataModule's proposed/detected boxes (matching to GT)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from threedq.datamodules.scene_folder import SceneFolderDataModule, detections_as_objects
from threedq.stages.detector import Detector, DetectorHead, cell_centres, decode_boxes, detection_targets
from threedq.viz.detection import detection_figure
from threedq.boxes import aabb_iou_3d
from threedq.data.box_files import load_boxes_file, save_boxes_file

SMALL = dict(grid_resolution=(32, 32, 16), image_every_n_steps=0)


def _grid() -> tuple[torch.Tensor, torch.Tensor]:
    # 8 x 8 x 4 cells of 0.25 m from (-1, -1, 0).
    centres = cell_centres(torch.tensor([-1.0, -1.0, 0.0]), torch.tensor([0.25, 0.25, 0.25]), (4, 8, 8))
    return centres, torch.tensor([0.5, 0.5, 0.5])


class TestCellCentres:
    def test_hand_computed(self) -> None:
        c, _ = _grid()
        assert c.shape == (4, 8, 8, 3)
        assert torch.allclose(c[0, 0, 0], torch.tensor([-0.875, -0.875, 0.125]))
        assert torch.allclose(c[3, 7, 1], torch.tensor([-0.625, 0.875, 0.875]))  # x index 1, y 7, z 3


class TestDetectionTargets:
    def test_hand_built_box(self) -> None:
        centres, anchor = _grid()
        box = torch.tensor([[[-0.5, -0.5, 0.0, 0.5, 0.5, 0.5]]])  # 1 m x 1 m x 0.5 m at the origin
        label, target, assigned = detection_targets(centres, box, torch.tensor([[True]]), anchor, 0.5, 0.1)
        assert label.shape == (1, 4, 8, 8) and target.shape == (1, 6, 4, 8, 8)
        # Naive reference, cell by cell.
        for z in range(4):
            for y in range(8):
                for x in range(8):
                    p = centres[z, y, x]
                    inner = bool(((p - torch.tensor([0.0, 0.0, 0.25])).abs() <= torch.tensor([0.25, 0.25, 0.125])).all())
                    near = bool(((p >= torch.tensor([-0.6, -0.6, -0.1])) & (p <= torch.tensor([0.6, 0.6, 0.6]))).all())
                    if inner:
                        assert label[0, z, y, x] == 1
                    elif z == 0 and y == 3 and x == 3:
                        assert label[0, z, y, x] == 1  # nearest cell to the centre (ties: first index)
                    elif near:
                        assert label[0, z, y, x] == -1
                    else:
                        assert label[0, z, y, x] == 0
        assert int((label == 1).sum()) == 8  # x, y centres +-0.125 and z centres 0.125, 0.375 (inclusive)
        assert int(assigned.max()) == 0 and int(assigned.min()) == -1

    def test_round_trip_decodes_the_box(self) -> None:
        centres, anchor = _grid()
        boxes = torch.tensor([[[-0.9, -0.8, 0.0, -0.3, -0.1, 0.7], [0.2, 0.1, 0.0, 0.8, 0.5, 0.4]]])
        label, target, assigned = detection_targets(centres, boxes, torch.tensor([[True, True]]), anchor)
        decoded = decode_boxes(centres, target, anchor)  # [1, Z, Y, X, 6]
        pos = label[0] == 1
        assert pos.any()
        expect = boxes[0][assigned[0][pos]]
        assert torch.allclose(decoded[0][pos], expect, atol=1e-5)
        # Both boxes own some positive cell.
        assert set(assigned[0][pos].tolist()) == {0, 1}

    def test_thin_box_gives_no_positive_and_its_region_is_ignored(self) -> None:
        centres, anchor = _grid()
        thin = torch.tensor([[[-0.5, -0.5, 0.0, 0.5, 0.5, 0.03]]])  # 3 cm tall: below a 4 cm min_height
        one = torch.tensor([[True]])
        counted, _, _ = detection_targets(centres, thin, one, anchor, 0.5, 0.1, min_height=0.0)
        label, _, assigned = detection_targets(centres, thin, one, anchor, 0.5, 0.1, min_height=0.04)
        assert int((counted == 1).sum()) == 1  # no cell centre is within the inner 1.5 cm: only the nearest cell
        assert int((label == 1).sum()) == 0 and int(assigned.max()) == -1
        # Naive reference: cells within 0.1 m of the box are ignored, the rest negative.
        for z in range(4):
            for y in range(8):
                for x in range(8):
                    p = centres[z, y, x]
                    near = bool(((p >= torch.tensor([-0.6, -0.6, -0.1])) & (p <= torch.tensor([0.6, 0.6, 0.13]))).all())
                    assert label[0, z, y, x] == (-1 if near else 0)
        # a box exactly min_height tall still counts
        edge = torch.tensor([[[-0.5, -0.5, 0.0, 0.5, 0.5, 0.25]]])
        label, _, _ = detection_targets(centres, edge, one, anchor, 0.5, 0.1, min_height=0.25)
        assert int((label == 1).sum()) > 0

    def test_masked_box_is_ignored(self) -> None:
        centres, anchor = _grid()
        box = torch.tensor([[[-0.5, -0.5, 0.0, 0.5, 0.5, 0.5]]])
        label, _, _ = detection_targets(centres, box, torch.tensor([[False]]), anchor)
        assert (label == 0).all()


class TestAnchorFromBoxes:
    def test_median_of_the_boxes_tall_enough(self) -> None:
        m = Detector(**SMALL)
        assert m.anchor_size is None
        ext = np.array([[0.2, 0.3, 0.4], [0.4, 0.5, 0.6], [0.6, 0.7, 0.8], [1.0, 1.0, 0.01], [0.9, 0.9, np.nan]])
        m.set_anchor_from_boxes(ext, "test boxes")
        assert m.anchor_size == pytest.approx((0.4, 0.5, 0.6))  # the thin and the non-finite box are left out
        assert m.hparams.anchor_size is None  # the hyperparameters stay as given: the anchor is a buffer
        assert torch.allclose(m.anchor, torch.tensor([0.4, 0.5, 0.6]))

    def test_default_min_height_is_half_a_feature_voxel(self) -> None:
        m = Detector(**SMALL)
        assert m.min_box_height == pytest.approx(m.feature_grid.voxel_size[2] / 2)
        assert Detector(min_box_height=0.0, **SMALL).min_box_height == 0.0

    def test_exceptions(self) -> None:
        m = Detector(**SMALL)
        with pytest.raises(ValueError, match=r"my boxes: anchor_size: null .* min_box_height=0\.04 m tall"):
            Detector(min_box_height=0.04, **SMALL).set_anchor_from_boxes(np.array([[0.3, 0.3, 0.02]]), "my boxes")
        z = torch.zeros(1, 4, 8, 8)
        with pytest.raises(RuntimeError, match="anchor_size is null"):
            m.loss(z, torch.zeros(1, 6, 4, 8, 8), torch.zeros(1, 1, 6), torch.ones(1, 1, dtype=torch.bool))
        with pytest.raises(RuntimeError, match="anchor_size is null"):
            m.detect(z, torch.zeros(1, 6, 4, 8, 8))
        with pytest.raises(ValueError, match="min_box_height"):
            Detector(min_box_height=-0.1, **SMALL)
        with pytest.raises(ValueError, match="anchor_size"):
            Detector(anchor_size=(0.5, float("inf"), 0.5), **SMALL)

    def test_box_extents_of_the_gt_boxes(self, tiny_dataset: Path) -> None:
        from threedq.boxes import box_corners
        from threedq.scene import load_scene

        dm = SceneFolderDataModule(str(tiny_dataset))
        ext = dm.box_extents("train")
        ref = []  # independent: the extent of each box's 8 corners
        for f in dm.index.files("train"):
            for c in box_corners(load_scene(tiny_dataset / f).boxes.astype(np.float64)):
                ref.append(c.max(0) - c.min(0))
        assert ext.shape == (len(ref), 3)
        assert np.allclose(ext, np.array(ref), atol=1e-6)

    def test_box_extents_of_a_box_file_keep_the_best_max_boxes(self, tiny_dataset: Path, tmp_path: Path) -> None:
        dm0 = SceneFolderDataModule(str(tiny_dataset))
        sets = {}
        for split in ("train", "val", "test"):
            for f in dm0.index.files(split):
                a = np.array([[0, 0, 0, 0.1, 0.1, 0.1], [0, 0, 0, 0.2, 0.3, 0.4], [0, 0, 0, 0.5, 0.5, 0.5]], np.float32)
                sets[f] = (a, np.array([0.1, 0.9, 0.5], np.float32))
        for split in ("train", "val", "test"):
            save_boxes_file(tmp_path / f"b_{split}.npz", {f: sets[f] for f in dm0.index.files(split)})
        dm = SceneFolderDataModule(str(tiny_dataset), boxes=str(tmp_path / "b_{split}.npz"), max_boxes=2)
        ext = dm.box_extents("train")
        n = len(dm0.index.files("train"))
        assert ext.shape == (2 * n, 3)
        assert np.allclose(ext[:2], [[0.2, 0.3, 0.4], [0.5, 0.5, 0.5]], atol=1e-6)  # scores 0.9, 0.5; 0.1 dropped

    def test_fit_takes_it_and_a_loaded_checkpoint_keeps_it(self, tiny_dataset: Path, tmp_path: Path) -> None:
        import lightning as L

        from threedq.errors import InputError

        torch.manual_seed(0)
        kw = dict(batch_size=2, num_target_views=0)
        dm = SceneFolderDataModule(str(tiny_dataset), boxes="gt", **kw)
        m = Detector(**SMALL)
        trainer = L.Trainer(max_steps=2, limit_val_batches=0, num_sanity_val_steps=0, logger=False,
                            enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)  # fmt: skip
        trainer.fit(m, datamodule=dm)
        ext = dm.box_extents("train")
        expect = tuple(round(float(v), 4) for v in np.median(ext[ext[:, 2] >= m.min_box_height], axis=0))
        assert m.anchor_size == pytest.approx(expect)
        ckpt = tmp_path / "det.ckpt"
        trainer.save_checkpoint(ckpt)
        saved = torch.load(ckpt, weights_only=True)
        assert saved["state_dict"]["anchor"].tolist() == pytest.approx(expect)  # the checkpoint carries it as a buffer
        assert saved["hyper_parameters"]["anchor_size"] is None
        # tested on data whose boxes have another median: the checkpoint's anchor, not the data's
        other = SceneFolderDataModule(str(tiny_dataset), boxes="gt", max_boxes=1, **kw)
        other.box_extents = lambda split: np.array([[0.9, 0.9, 0.9]])  # type: ignore[method-assign]
        m2 = Detector(**SMALL)
        tester = L.Trainer(logger=False, enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)
        tester.test(m2, datamodule=other, ckpt_path=str(ckpt), verbose=False, weights_only=True)
        assert m2.anchor_size == pytest.approx(expect) and torch.allclose(m2.anchor, torch.tensor(expect))
        # a checkpoint written before the anchor was a buffer (only its hyperparameters held it) still decodes with it
        saved["state_dict"].pop("anchor")
        saved["hyper_parameters"]["anchor_size"] = list(expect)
        old = tmp_path / "det_old.ckpt"
        torch.save(saved, old)
        m3 = Detector(**SMALL)
        tester.test(m3, datamodule=other, ckpt_path=str(old), verbose=False, weights_only=True)
        assert m3.anchor_size == pytest.approx(expect)
        # an explicit, different anchor is refused by name
        with pytest.raises(InputError, match=r"anchor_size.*trained with anchor_size=.*asks for \[0\.9, 0\.9, 0\.9\]"):
            tester.test(Detector(anchor_size=(0.9, 0.9, 0.9), **SMALL), datamodule=other, ckpt_path=str(ckpt),
                        verbose=False, weights_only=True)  # fmt: skip


class TestDetectorHead:
    def test_shapes(self) -> None:
        head = DetectorHead(32, 32, 3)
        obj, box = head(torch.randn(2, 32, 8, 16, 16))
        assert obj.shape == (2, 4, 8, 8) and box.shape == (2, 6, 4, 8, 8)

    def test_bad_config(self) -> None:
        from conftest import refused

        with pytest.raises(ValueError, match="anchor_size"):
            Detector(anchor_size=(0.5, 0.0, 0.5), **SMALL)
        for name, bad in (("score_threshold", 1.5), ("nms_iomin", -0.5), ("inner_fraction", 0.0), ("channels", 0)):
            assert name in refused(Detector, feature_dim=8, **{name: bad})


@pytest.fixture(scope="module")
def train_batch(tiny_dataset: Path) -> dict[str, torch.Tensor]:
    from threedq.datamodules.scene_folder import SceneDataset

    dm = SceneFolderDataModule(str(tiny_dataset))
    ds = SceneDataset(tiny_dataset, dm.index, "train", num_target_views=0, random_views=False)
    return torch.utils.data.default_collate([ds[i] for i in range(4)])


class TestDetectorStage:
    def test_overfit_one_batch(self, train_batch: dict[str, torch.Tensor]) -> None:
        torch.manual_seed(0)
        m = Detector(anchor_size=(0.5, 0.5, 0.5), score_threshold=0.5, **SMALL)
        opt = torch.optim.Adam(m.head.parameters(), lr=3e-3)
        m.train()
        with torch.no_grad():  # the frozen encoder (in eval mode) gives the same grid every step: encode it once
            v = m.input_views(train_batch)
            feats = m.encode_views(*(train_batch[k][:, :v] for k in ("rgb", "depth", "K", "R_T_cam")))
            torch.testing.assert_close(m.head(feats)[0], m(train_batch)[0])  # what the stage's forward computes
        losses = []
        for _ in range(150):
            logits, box = m.head(feats)
            r = m.loss(logits, box, train_batch["aabb"], train_batch["box_mask"])
            opt.zero_grad()
            r["loss"].backward()
            opt.step()
            losses.append(float(r["loss"].detach()))
        assert losses[-1] < losses[0] / 4
        with torch.no_grad():  # settle the BatchNorm running statistics on the final weights
            for _ in range(10):
                m(train_batch)
        m.eval()
        logits, box = m(train_batch)
        dets = m.detect(logits, box)
        hits = 0
        for d, a, k in zip(dets, train_batch["aabb"], train_batch["box_mask"]):
            if len(d["boxes"]) and k.any():
                hits += int((aabb_iou_3d(d["boxes"], a[k]).amax(0) >= 0.25).sum())
        assert hits >= int(train_batch["box_mask"].sum()) // 2
        img = detection_figure({**train_batch, "gt_aabb": train_batch["aabb"], "gt_mask": train_batch["box_mask"]}, dets, 2)
        assert img.dtype == np.uint8 and img.ndim == 3

    def test_frozen_encoder_gets_no_gradient(self, train_batch: dict[str, torch.Tensor]) -> None:
        m = Detector(anchor_size=(0.5, 0.5, 0.5), **SMALL)
        logits, box = m(train_batch)
        m.loss(logits, box, train_batch["aabb"], train_batch["box_mask"])["loss"].backward()
        assert all(p.grad is None for p in m.encoder.parameters())
        assert any(p.grad is not None for p in m.head.parameters())


class TestDetectionsAsObjects:
    def test_greedy_matching(self) -> None:
        gt = np.array([[0, 0, 0.25, 0.5, 0.5, 0.5, 0], [2, 2, 0.25, 0.5, 0.5, 0.5, 0]], np.float32)
        cats = np.array([7, 3])
        aabb = np.array(
            [[-0.25, -0.25, 0, 0.25, 0.25, 0.5],      # exact match of GT 0
             [-0.2, -0.25, 0, 0.3, 0.25, 0.5],        # duplicate of GT 0 (lower score)
             [5, 5, 0, 6, 6, 1]], np.float32)          # matches nothing  # fmt: skip
        scores = np.array([0.9, 0.8, 0.95], np.float32)
        out = detections_as_objects(aabb, scores, gt, cats, 0.5, keep_unmatched=True, max_boxes=4)
        # Ordered by score: unmatched (0.95), GT0 (0.9), duplicate (0.8, GT0 taken -> unmatched).
        assert out["categories"].tolist() == [-1, 7, -1, -1]
        assert out["box_mask"].tolist() == [True, True, True, False]
        assert out["box_matched"].tolist() == [False, True, False, False]
        assert torch.allclose(out["boxes"][1], torch.from_numpy(gt[0]))
        only = detections_as_objects(aabb, scores, gt, cats, 0.5, keep_unmatched=False, max_boxes=4)
        assert only["box_mask"].tolist() == [True, False, False, False]
        assert only["categories"][0] == 7

    def test_max_boxes_keeps_best(self) -> None:
        aabb = np.array([[0, 0, 0, 1, 1, 1], [2, 2, 0, 3, 3, 1]], np.float32)
        out = detections_as_objects(aabb, np.array([0.1, 0.7]), np.zeros((0, 7)), np.zeros(0, int), max_boxes=1)
        assert torch.allclose(out["aabb"][0], torch.from_numpy(aabb[1]))


class TestBoxesOption:
    def test_box_file_round_trip_and_datamodule(self, tiny_dataset: Path, tmp_path: Path) -> None:
        dm = SceneFolderDataModule(str(tiny_dataset), batch_size=2, num_target_views=0)
        files = dm.index.files("val")
        # "Detections" = the GT hulls themselves, shifted slightly: every one matches its GT object.
        from threedq.boxes import boxes_to_aabb
        from threedq.scene import load_scene

        boxes = {}
        for f in files:
            rec = load_scene(tiny_dataset / f, validate=False)
            a = boxes_to_aabb(rec.boxes.astype(np.float64)).astype(np.float32) + 0.01
            boxes[f] = (a, np.linspace(0.9, 0.5, len(a)).astype(np.float32))
        path = tmp_path / "det_val.npz"
        save_boxes_file(path, boxes)
        back = load_boxes_file(path)
        for f in files:
            np.testing.assert_array_equal(back[f][0], boxes[f][0])
        dm2 = SceneFolderDataModule(str(tiny_dataset), batch_size=2, num_target_views=0,
                                    boxes=str(tmp_path / "det_{split}.npz"))  # fmt: skip
        from threedq.datamodules.scene_folder import SceneDataset

        ds = SceneDataset(tiny_dataset, dm2.index, "val", num_target_views=0, box_sets=dm2.box_sets("val"),
                          keep_unmatched=False, max_boxes=5)  # fmt: skip
        item = ds[0]
        n = int(item["gt_mask"].sum())
        assert int(item["box_mask"].sum()) == n
        gt_cats = load_scene(tiny_dataset / files[0], validate=False).categories
        assert sorted(item["categories"][:n].tolist()) == sorted(gt_cats.tolist())
        assert torch.allclose(item["aabb"][:n].sort(0).values, item["gt_aabb"][:n].sort(0).values + 0.01, atol=1e-5)

    def test_bad_boxes_option(self, tiny_dataset: Path, tmp_path: Path) -> None:
        with pytest.raises(ValueError, match="boxes"):
            SceneFolderDataModule(str(tiny_dataset), boxes="detections.npz")
        dm = SceneFolderDataModule(str(tiny_dataset), boxes=str(tmp_path / "missing_{split}.npz"))
        with pytest.raises(FileNotFoundError, match="missing_train.npz"):
            dm.setup()


class TestPreNmsCap:
    def test_nms_sees_only_the_highest_scores(self, monkeypatch: pytest.MonkeyPatch) -> None:
        """With more boxes above the threshold than the cap, detect() equals NMS over the cap's highest-scoring
        cells (naive reference: sort, cut, NMS); under the cap it is NMS over all of them."""
        import threedq.stages.detector as det_module
        from threedq.boxes import nms_3d

        m = Detector(anchor_size=(0.5, 0.5, 0.5), **SMALL)
        shape = m.centres.shape[:3]
        g = torch.Generator().manual_seed(0)
        logits = torch.randn(1, 1, *shape, generator=g) * 3
        box = torch.randn(1, 6, *shape, generator=g) * 0.3
        full = m.detect(logits, box, 0.05)[0]
        scores = torch.sigmoid(logits).flatten()
        boxes = decode_boxes(m.centres, box, m.anchor).flatten(1, 3)[0]
        above = scores >= 0.05
        cap = int(above.sum()) // 3
        monkeypatch.setattr(det_module, "PRE_NMS_TOP_K", cap)
        capped = m.detect(logits, box, 0.05)[0]
        s, b = scores[above], boxes[above]
        top = torch.sort(torch.topk(s, cap).indices).values
        k = nms_3d(b[top], s[top], m.hparams.nms_iou, m.hparams.nms_iomin)[: m.hparams.max_detections]
        torch.testing.assert_close(capped["scores"], s[top][k])
        torch.testing.assert_close(capped["boxes"], b[top][k])
        monkeypatch.setattr(det_module, "PRE_NMS_TOP_K", 10**9)
        torch.testing.assert_close(m.detect(logits, box, 0.05)[0]["scores"], full["scores"])
