"""Detections refined against their own input views (``threedq.box_refinement``): analytic ray-cast scenes, hand
cases, a naive loop, the detector's decoding path."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from threedq.box_refinement import OBSERVED_PARAMS, _CACHE, add_flat_boxes, observed_boxes, refine_boxes
from threedq.boxes import aabb_iou_3d, nms_3d
from threedq.proposals import propose_boxes

from analytic_scenes import render  # noqa: E402  (tests/ is on sys.path under pytest)

BOUNDS = ((-1.0, -1.0, -0.5), (1.0, 1.0, 1.0))
BOXES = np.array([[-0.55, -0.35, 0.0, -0.15, 0.05, 0.3], [0.2, 0.1, 0.0, 0.5, 0.6, 0.2]])  # aabb, on z = 0


def _iou(b: np.ndarray, o: np.ndarray) -> float:
    """IoU of two axis-aligned boxes, written out."""
    lo, hi = np.maximum(b[:3], o[:3]), np.minimum(b[3:], o[3:])
    inter = np.prod(np.clip(hi - lo, 0, None))
    return float(inter / (np.prod(b[3:] - b[:3]) + np.prod(o[3:] - o[:3]) - inter))


def _random_boxes(g: np.random.Generator, n: int, smallest: float, largest: float) -> np.ndarray:
    lo = g.uniform(-1, 1, (n, 3))
    return np.concatenate([lo, lo + g.uniform(smallest, largest, (n, 3))], 1)


def _naive_refine(boxes: np.ndarray, scores: np.ndarray, observed: np.ndarray, min_iou: float, nms_iou: float):
    """Per detection, a loop over the observed boxes for the best IoU (first of equal ones), then greedy NMS."""
    out = boxes.copy()
    for i, b in enumerate(boxes):
        best, arg = -1.0, -1
        for j, o in enumerate(observed):
            iou = _iou(b, o)
            if iou > best:
                best, arg = iou, j
        if arg >= 0 and best >= min_iou:
            out[i] = observed[arg]
    kept: list[int] = []
    for i in np.argsort(-scores, kind="stable"):
        ok = True
        for k in kept:
            ok &= _iou(out[i], out[k]) <= nms_iou
        if ok:
            kept.append(int(i))
    return out[kept], scores[kept]


class TestObservedBoxes:
    def test_smoke_one_view_finds_both_boxes(self) -> None:
        scene = render(BOXES, num_views=1)
        aabb, scores = observed_boxes(scene.depth, scene.K, scene.world_T_cam, BOUNDS)
        assert aabb.dtype == np.float32 and aabb.shape == (2, 6) and scores.shape == (2,)
        iou = aabb_iou_3d(torch.from_numpy(aabb).double(), torch.from_numpy(BOXES)).numpy()
        # one view sees two faces of each box: its box reaches the ground and spans most of each object
        assert (iou.max(0) > 0.5).all(), iou

    def test_equals_the_proposals_of_the_same_views(self) -> None:
        scene = render(BOXES, num_views=2)
        got = observed_boxes(scene.depth, scene.K, scene.world_T_cam, BOUNDS)
        want = propose_boxes(scene, bounds=BOUNDS, view_stride=1, min_views=1, ground_margin=None, min_height=None)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        assert OBSERVED_PARAMS.min_views == 1 and OBSERVED_PARAMS.view_stride == 1
        assert OBSERVED_PARAMS.ground_margin is None and OBSERVED_PARAMS.min_height is None  # measured per scene

    def test_tensors_and_the_cache(self) -> None:
        scene = render(BOXES, num_views=1)
        a = observed_boxes(torch.from_numpy(scene.depth), torch.from_numpy(scene.K), torch.from_numpy(scene.world_T_cam),
                           BOUNDS)  # fmt: skip
        n = len(_CACHE)
        b = observed_boxes(scene.depth, scene.K, scene.world_T_cam, BOUNDS)
        assert b is a and len(_CACHE) == n  # same bytes: the cached result
        c = observed_boxes(scene.depth, scene.K, scene.world_T_cam, ((-1.0, -1.0, -0.5), (0.0, 1.0, 1.0)))
        assert c is not a and len(c[0]) == 1  # other bounds: computed (the box at x > 0 is cut away)

    def test_exceptions(self) -> None:
        scene = render(BOXES, num_views=1)
        depth = scene.depth.copy()
        depth[0, 3, 3] = np.nan
        with pytest.raises(ValueError, match="depth"):
            observed_boxes(depth, scene.K, scene.world_T_cam, BOUNDS)
        with pytest.raises(ValueError, match="world_T_cam"):
            observed_boxes(scene.depth, scene.K, scene.world_T_cam[:, :3], BOUNDS)


class TestRefineBoxes:
    def test_hand_case(self) -> None:
        det = torch.tensor([[0.0, 0.0, 0.1, 1.0, 1.0, 1.1],   # IoU 0.82 with observed 0: snapped
                            [0.1, 0.0, 0.0, 1.1, 1.0, 1.0],   # also observed 0: after snapping a duplicate
                            [5.0, 5.0, 0.0, 5.5, 5.5, 0.5]])  # nothing observed near: kept as regressed
        scores = torch.tensor([0.7, 0.9, 0.8])
        obs = torch.tensor([[0.05, 0.0, 0.0, 1.05, 1.0, 1.0], [3.0, 3.0, 0.0, 3.2, 3.2, 0.2]])
        boxes, s, snapped = refine_boxes(det, scores, obs, 0.1, 0.1)
        torch.testing.assert_close(boxes, torch.stack([obs[0], det[2]]))
        torch.testing.assert_close(s, torch.tensor([0.9, 0.8]))  # the higher-scoring of the two snapped stays
        assert snapped.tolist() == [True, False]

    def test_min_iou_and_no_observed_box(self) -> None:
        det = torch.tensor([[0.0, 0.0, 0.0, 1.0, 1.0, 1.0]])
        obs = torch.tensor([[0.5, 0.0, 0.0, 1.5, 1.0, 1.0]])  # IoU 1/3
        assert refine_boxes(det, torch.ones(1), obs, 0.3, 0.1)[2].tolist() == [True]
        boxes, _, snapped = refine_boxes(det, torch.ones(1), obs, 0.4, 0.1)
        assert snapped.tolist() == [False] and torch.equal(boxes, det)
        boxes, s, snapped = refine_boxes(det, torch.ones(1), torch.zeros(0, 6), 0.1, 0.1)
        assert torch.equal(boxes, det) and snapped.tolist() == [False]
        boxes, s, snapped = refine_boxes(torch.zeros(0, 6), torch.zeros(0), obs, 0.1, 0.1)
        assert boxes.shape == (0, 6) and s.shape == (0,) and snapped.shape == (0,)

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_against_a_naive_loop(self, seed: int) -> None:
        g = np.random.default_rng(seed)
        boxes, observed = _random_boxes(g, 12, 0.1, 0.6), _random_boxes(g, 5, 0.1, 0.6)
        scores = g.permutation(12) / 12.0
        want = _naive_refine(boxes, scores, observed, 0.1, 0.2)
        got = refine_boxes(torch.from_numpy(boxes), torch.from_numpy(scores), torch.from_numpy(observed), 0.1, 0.2)
        np.testing.assert_allclose(got[0].numpy(), want[0])
        np.testing.assert_allclose(got[1].numpy(), want[1])

    def test_exceptions(self) -> None:
        det = torch.zeros(1, 6)
        with pytest.raises(ValueError, match="min_iou"):
            refine_boxes(det, torch.ones(1), det, 0.0, 0.1)
        with pytest.raises(ValueError, match="boxes/scores"):
            refine_boxes(det, torch.ones(2), det, 0.1, 0.1)


def _naive_add_flat(boxes, scores, observed, observed_scores, max_height, scale, min_score, overlap):
    """A loop over the observed boxes: flat, scored high enough, overlapping no detection at ``overlap``."""
    out_b, out_s = list(boxes), list(scores)
    for o, os_ in zip(observed, observed_scores):
        if o[5] - o[2] >= max_height or os_ * scale < min_score:
            continue
        ious = [_iou(b, o) for b in boxes]
        if not ious or max(ious) < overlap:
            out_b.append(o)
            out_s.append(os_ * scale)
    order = np.argsort(-np.asarray(out_s), kind="stable")
    return np.asarray(out_b).reshape(-1, 6)[order], np.asarray(out_s)[order]


class TestAddFlatBoxes:
    def test_hand_case(self) -> None:
        det = torch.tensor([[0.0, 0.0, 0.0, 1.0, 1.0, 0.5]])
        obs = torch.tensor([[0.0, 0.0, 0.0, 1.0, 1.0, 0.03],    # flat but under the detection (IoU 0.06 >= 0.05)
                            [2.0, 2.0, 0.0, 2.5, 2.2, 0.03],    # flat, alone: added at 0.9 * 0.5
                            [3.0, 3.0, 0.0, 3.5, 3.5, 0.3],     # tall: the detector's business
                            [4.0, 4.0, 0.0, 4.2, 4.2, 0.02]])   # flat, alone, scored too low: 0.9 * 0.04 < 0.05
        boxes, s = add_flat_boxes(det, torch.tensor([0.95]), obs, torch.tensor([1.0, 0.5, 1.0, 0.04]), 0.04, 0.9,
                                  0.05, 0.05)  # fmt: skip
        torch.testing.assert_close(boxes, torch.stack([det[0], obs[1]]))
        torch.testing.assert_close(s, torch.tensor([0.95, 0.45]))
        # no detections: every flat box scored high enough; none observed: the detections as they are
        boxes, s = add_flat_boxes(torch.zeros(0, 6), torch.zeros(0), obs, torch.tensor([1.0, 0.5, 1.0, 0.04]), 0.04,
                                  0.9, 0.05, 0.05)  # fmt: skip
        torch.testing.assert_close(boxes, obs[:2])
        boxes, s = add_flat_boxes(det, torch.tensor([0.95]), torch.zeros(0, 6), torch.zeros(0), 0.04, 0.9, 0.05, 0.05)
        assert torch.equal(boxes, det) and s.tolist() == [pytest.approx(0.95)]

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_against_a_naive_loop(self, seed: int) -> None:
        g = np.random.default_rng(seed)
        boxes, observed = _random_boxes(g, 6, 0.1, 0.6), _random_boxes(g, 10, 0.02, 0.3)
        scores, obs_scores = g.uniform(0.5, 1.0, 6), g.uniform(0.0, 1.0, 10)
        want = _naive_add_flat(boxes, scores, observed, obs_scores, 0.15, 0.9, 0.2, 0.1)
        got = add_flat_boxes(*(torch.from_numpy(a) for a in (boxes, scores, observed, obs_scores)), 0.15, 0.9, 0.2, 0.1)
        np.testing.assert_allclose(got[0].numpy(), want[0])
        np.testing.assert_allclose(got[1].numpy(), want[1])

    def test_exceptions(self) -> None:
        det = torch.zeros(1, 6)
        with pytest.raises(ValueError, match="boxes/scores"):
            add_flat_boxes(det, torch.ones(2), det, torch.ones(1), 0.04, 0.9, 0.05, 0.1)
        with pytest.raises(ValueError, match="observed_scores"):
            add_flat_boxes(det, torch.ones(1), det, torch.ones(3), 0.04, 0.9, 0.05, 0.1)
        with pytest.raises(ValueError, match="score_scale"):
            add_flat_boxes(det, torch.ones(1), det, torch.ones(1), 0.04, 1.5, 0.05, 0.1)


class TestDetectorRefinement:
    """The detector's decoding: with its input views, a loose detection is moved onto the observed box."""

    def _stage(self, refine_iou: float, flat_boxes: bool = True):
        from threedq.stages.detector import Detector

        return Detector(grid_min=(-1.0, -1.0, -0.5), grid_max=(1.0, 1.0, 1.0), grid_resolution=(16, 16, 12),
                        feature_dim=8, anchor_size=(0.4, 0.4, 0.3), score_threshold=0.5, refine_iou=refine_iou,
                        flat_boxes=flat_boxes)  # fmt: skip

    def _logits_for(self, stage, target: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Objectness and regression that decode to one box ``target`` (plus nothing else above 0.5)."""
        centres = stage.centres  # [Z, Y, X, 3]
        c = torch.tensor((target[:3] + target[3:]) / 2, dtype=torch.float32)
        idx = int(((centres.reshape(-1, 3) - c) ** 2).sum(1).argmin())
        Z, Y, X = centres.shape[:3]
        logits = torch.full((1, Z, Y, X), -10.0)
        logits.view(1, -1)[0, idx] = 10.0
        box = torch.zeros(1, 6, Z, Y, X)
        cell = centres.reshape(-1, 3)[idx]
        size = torch.tensor(target[3:] - target[:3], dtype=torch.float32)
        box.view(1, 6, -1)[0, :3, idx] = (c - cell) / stage.anchor
        box.view(1, 6, -1)[0, 3:, idx] = torch.log(size / stage.anchor)
        return logits, box

    def test_detection_snaps_onto_its_view_and_off_keeps_the_regression(self) -> None:
        scene = render(BOXES, num_views=1)
        views = tuple(torch.from_numpy(a)[None] for a in (scene.depth, scene.K, scene.world_T_cam))
        loose = BOXES[0] + np.array([0.06, -0.05, 0.08, 0.06, -0.05, 0.0])  # off in the plane, floating
        on = self._stage(0.1)
        logits, box = self._logits_for(on, loose)
        plain = on.detect(logits, box)[0]["boxes"]
        torch.testing.assert_close(plain[0].double(), torch.from_numpy(loose), atol=1e-5, rtol=0)
        refined = on.detect(logits, box, views=views)[0]["boxes"]
        obs, _ = observed_boxes(scene.depth, scene.K, scene.world_T_cam, ((-1.0, -1.0, -0.5), (1.0, 1.0, 1.0)))
        assert refined.shape == (1, 6)
        j = int(aabb_iou_3d(refined.double(), torch.from_numpy(obs).double()).argmax())
        torch.testing.assert_close(refined[0], torch.from_numpy(obs[j]))
        truth = torch.from_numpy(BOXES[:1])
        assert float(aabb_iou_3d(refined.double(), truth)) > float(aabb_iou_3d(plain.double(), truth))
        off = self._stage(0.0)
        torch.testing.assert_close(off.detect(logits, box, views=views)[0]["boxes"], plain)

    def test_nms_after_snapping(self) -> None:
        # the refinement's own suppression equals nms_3d on the snapped boxes
        det = torch.tensor([[0.0, 0.0, 0.0, 1.0, 1.0, 1.0], [0.05, 0.0, 0.0, 1.05, 1.0, 1.0]])
        obs = torch.tensor([[0.0, 0.0, 0.0, 1.0, 1.0, 0.9]])
        boxes, s, _ = refine_boxes(det, torch.tensor([0.6, 0.8]), obs, 0.5, 0.5)
        keep = nms_3d(obs.repeat(2, 1), torch.tensor([0.6, 0.8]), 0.5)
        assert boxes.shape[0] == keep.numel() == 1 and float(s[0]) == pytest.approx(0.8)

    def test_flat_objects_come_from_the_view_below_the_hand_on_threshold(self) -> None:
        # a 5 cm tall box (under min_box_height: half the 12.5 cm voxel) beside a tall one the detector finds
        flat = np.array([0.1, -0.7, 0.0, 0.6, -0.3, 0.05])
        scene = render(np.stack([BOXES[0], flat]), num_views=1)
        views = tuple(torch.from_numpy(a)[None] for a in (scene.depth, scene.K, scene.world_T_cam))
        obs, obs_s = observed_boxes(scene.depth, scene.K, scene.world_T_cam, BOUNDS)
        j = int(aabb_iou_3d(torch.from_numpy(flat[None]), torch.from_numpy(obs).double()).argmax())
        assert obs[j, 5] - obs[j, 2] < 0.0625 and float(aabb_iou_3d(torch.from_numpy(flat[None]), torch.from_numpy(obs[j:j + 1]).double())) > 0.5
        on = self._stage(0.1)
        logits, box = self._logits_for(on, BOXES[0])
        handed_on = on.detect(logits, box, views=views)[0]  # at the stage's score threshold (0.5): the tall one only
        assert handed_on["boxes"].shape == (1, 6)
        ranked = on.detect(logits, box, 0.01, views=views)[0]
        assert ranked["boxes"].shape == (2, 6)
        torch.testing.assert_close(ranked["boxes"][1], torch.from_numpy(obs[j]))
        assert float(ranked["scores"][1]) == pytest.approx(0.5 * float(obs_s[j]))
        off = self._stage(0.1, flat_boxes=False).detect(logits, box, 0.01, views=views)[0]
        assert off["boxes"].shape == (1, 6)


class TestSceneTargets:
    """``refine_to: scene``: detections are refined against given per-scene pseudo-boxes instead of the input
    views' own, and the stage takes them from its DataModule's ``pseudo_boxes(split)`` by scene file."""

    def _stage(self, refine_to: str = "scene"):
        from threedq.stages.detector import Detector

        return Detector(grid_min=(-1.0, -1.0, -0.5), grid_max=(1.0, 1.0, 1.5), grid_resolution=(16, 16, 16),
                        feature_dim=8, anchor_size=(0.4, 0.4, 0.3), score_threshold=0.5, refine_to=refine_to)

    def test_targets_replace_the_input_views(self) -> None:
        stage = self._stage()
        loose = BOXES[0] + np.array([0.06, -0.05, 0.08, 0.06, -0.05, 0.0])
        logits, box = TestDetectorRefinement._logits_for(None, stage, loose)
        scene = render(BOXES, num_views=1)
        views = tuple(torch.from_numpy(a)[None] for a in (scene.depth, scene.K, scene.world_T_cam))
        target = (BOXES[:1].astype(np.float32) + np.float32(0.01), np.ones(1, np.float32))  # by hand: one box near it
        got = stage.detect(logits, box, views=views, targets=[target])[0]["boxes"]
        torch.testing.assert_close(got, torch.from_numpy(target[0]))
        alone = stage.detect(logits, box, targets=[target])[0]["boxes"]  # no views needed
        torch.testing.assert_close(alone, got)
        far = (BOXES[1:2].astype(np.float32), np.ones(1, np.float32))  # overlaps nothing: the regression stays
        kept = stage.detect(logits, box, targets=[far])[0]["boxes"]
        torch.testing.assert_close(kept[0].double(), torch.from_numpy(loose), atol=1e-5, rtol=0)

    def test_scene_targets_by_file(self) -> None:
        from types import SimpleNamespace

        boxes = {"a.npz": (np.zeros((1, 6), np.float32), np.ones(1, np.float32)),
                 "b.npz": (np.ones((2, 6), np.float32), np.ones(2, np.float32))}
        asked = []

        def pseudo_boxes(split):
            asked.append(split)
            return boxes

        stage = self._stage()
        stage._trainer = SimpleNamespace(datamodule=SimpleNamespace(pseudo_boxes=pseudo_boxes))
        batch = {"scene_index": torch.tensor([1, 0, 1])}
        got = stage.scene_targets(batch, "test", files=["a.npz", "b.npz"])
        assert [g[0].shape[0] for g in got] == [2, 1, 2] and asked == ["test"]
        stage.scene_targets(batch, "test", files=["a.npz", "b.npz"])
        assert asked == ["test"]  # read once per split
        with pytest.raises(ValueError, match="no entry for c.npz"):
            stage.scene_targets({"scene_index": torch.tensor([0])}, "test", files=["c.npz"])
        assert self._stage("input").scene_targets(batch, "test", files=["a.npz", "b.npz"]) is None

    def test_exception_without_a_scene_datamodule(self) -> None:
        from types import SimpleNamespace

        stage = self._stage()
        stage._trainer = SimpleNamespace(datamodule=object())
        with pytest.raises(ValueError, match="refine_to: 'scene'.*set refine_to: input"):
            stage.scene_targets({"scene_index": torch.tensor([0])}, "val", files=["a.npz"])

    def test_detect_split_takes_the_targets(self) -> None:
        from threedq.pipeline.detection_eval import detect_split

        stage = self._stage().eval()
        scene = render(BOXES, num_views=1)
        rgb = torch.from_numpy(scene.rgb).permute(0, 3, 1, 2).float() / 255
        sample = {"rgb": rgb, "depth": torch.from_numpy(scene.depth),
                  "K": torch.from_numpy(scene.K), "R_T_cam": torch.from_numpy(scene.world_T_cam),
                  "scene_index": torch.tensor(0), "view_ids": torch.tensor([0]), "num_input_views": torch.tensor(1)}

        class Data(torch.utils.data.Dataset):
            files = ["s.npz"]

            def __len__(self):
                return 1

            def __getitem__(self, i):
                return sample

        loader = torch.utils.data.DataLoader(Data(), batch_size=1)
        with torch.no_grad():
            plain, _ = detect_split(stage, loader, 0.0, progress=False)
            shifted = plain["s.npz"][0][:3] + np.float32(0.02)  # by hand: a target beside three of the detections
            target = {"s.npz": (shifted, np.ones(3, np.float32))}
            logits, box = stage({k: v[None] for k, v in sample.items()})
            want = stage.detect(logits, box, 0.0, targets=[target["s.npz"]])[0]["boxes"].numpy()
            got, _ = detect_split(stage, loader, 0.0, progress=False, targets=target)
        np.testing.assert_array_equal(got["s.npz"][0], want)
        snapped = (want[:, None] == shifted[None]).all(-1).any(-1)
        assert snapped.sum() >= 1 and not np.array_equal(plain["s.npz"][0], want)
        with pytest.raises(ValueError, match="no pseudo-boxes for s.npz"):
            detect_split(stage, loader, progress=False, targets={})

    def test_validation_step_refines_against_the_scene(self) -> None:
        """The stage's own validation step (metric and picture) refines against the scene's pseudo-boxes: each
        detection's box is then one of them or its regression."""
        from types import SimpleNamespace

        stage = self._stage().eval()
        scene = render(BOXES, num_views=1)
        rgb = torch.from_numpy(scene.rgb).permute(0, 3, 1, 2).float() / 255
        batch = {"rgb": rgb[None], "depth": torch.from_numpy(scene.depth)[None], "K": torch.from_numpy(scene.K)[None],
                 "R_T_cam": torch.from_numpy(scene.world_T_cam)[None], "scene_index": torch.tensor([0]),
                 "num_input_views": torch.tensor([1]), "gt_aabb": torch.from_numpy(BOXES).float()[None],
                 "gt_mask": torch.ones(1, 2, dtype=torch.bool)}
        shifted = BOXES.astype(np.float32) + np.float32(0.01)
        asked = []

        def pseudo_boxes(split):
            asked.append(split)
            return {"s.npz": (shifted, np.ones(2, np.float32))}

        stage._trainer = SimpleNamespace(datamodule=SimpleNamespace(pseudo_boxes=pseudo_boxes), global_step=1000,
                                         val_dataloaders=SimpleNamespace(dataset=SimpleNamespace(files=["s.npz"])),
                                         is_global_zero=False, sanity_checking=False)
        stage.log = lambda *args, **kwargs: None
        with torch.no_grad():
            stage._eval_step(batch, "val", 0)  # with the picture's detection too (image_every_n_steps)
        assert asked == ["val"] and stage.val_map.compute()["num_det"] > 0
