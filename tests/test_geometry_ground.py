"""threedq.geometry.ground: which pixels lie above the ground plane, checked on exact ray-cast scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from threedq.geometry import above_ground_mask

from analytic_scenes import render  # noqa: E402  (tests/ is on sys.path under pytest)

BOXES = np.array([[-0.55, -0.35, 0.0, -0.15, 0.05, 0.3], [0.2, 0.1, 0.0, 0.5, 0.6, 0.2]])  # aabb, on z = 0


def _tensors(rec) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A scene record as one batch element: depth [1,V,H,W], K [1,V,3,3], R_T_cam [1,V,4,4]."""
    return (torch.from_numpy(rec.depth)[None], torch.from_numpy(rec.K)[None], torch.from_numpy(rec.world_T_cam)[None])


def _heights(rec, normal: np.ndarray, offset: float) -> np.ndarray:
    """Exact height above the plane ``n . p = offset`` of every pixel's surface point [V,H,W] (NaN where invalid)."""
    V, H, W = rec.depth.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    out = np.full((V, H, W), np.nan)
    for i in range(V):
        K, T, z = rec.K[i].astype(np.float64), rec.world_T_cam[i].astype(np.float64), rec.depth[i].astype(np.float64)
        cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
        world = cam @ T[:3, :3].T + T[:3, 3]
        out[i] = np.where(z > 0, world @ normal - offset, np.nan)
    return out


class TestAboveGroundMask:
    def test_smoke(self) -> None:
        depth, K, pose = _tensors(render(BOXES, num_views=2))
        mask = above_ground_mask(depth, K, pose)
        assert mask.shape == depth.shape and mask.dtype == torch.bool

    def test_exception(self) -> None:
        depth, K, pose = _tensors(render(BOXES, num_views=2))
        with pytest.raises(ValueError, match=r"\[B, S, H, W\]"):
            above_ground_mask(depth[0], K, pose)
        with pytest.raises(ValueError, match=r"\[B, S, 3, 3\]"):
            above_ground_mask(depth, K[:, :1], pose)
        with pytest.raises(ValueError, match="fit_stride"):
            above_ground_mask(depth, K, pose, fit_stride=0)

    @pytest.mark.parametrize("tilt_deg, offset", [(0.0, 0.0), (10.0, 0.15)])
    def test_feature_against_exact_heights(self, tilt_deg: float, offset: float) -> None:
        normal = np.array([math.sin(math.radians(tilt_deg)), 0.0, math.cos(math.radians(tilt_deg))])
        boxes = BOXES + np.array([0, 0, -0.2, 0, 0, 0.2])  # reach below a raised or tilted ground
        rec = render(boxes, normal=normal, offset=offset, num_views=4)
        margin = 0.02
        mask = above_ground_mask(*_tensors(rec), margin=margin)[0].numpy()
        h = _heights(rec, normal, offset)
        valid = np.isfinite(h)
        assert not mask[~valid].any()  # no depth, never foreground
        clear = valid & (np.abs(h - margin) > 0.01)  # away from the threshold, where the fitted plane decides
        assert clear.sum() > 1000 and (h[clear] > margin).sum() > 200  # both classes present
        np.testing.assert_array_equal(mask[clear], h[clear] > margin)

    def test_ground_only_and_batch_independence(self) -> None:
        ground = render(np.zeros((0, 6)), num_views=2)
        scene = render(BOXES, num_views=2)
        depth, K, pose = (torch.cat(t) for t in zip(_tensors(ground), _tensors(scene)))
        both = above_ground_mask(depth, K, pose)
        assert not both[0].any()  # an empty scene: nothing above the ground
        torch.testing.assert_close(both[1], above_ground_mask(*_tensors(scene))[0])

    @pytest.mark.parametrize("views", [slice(1, None), slice(2, 4), slice(0, 1), slice(3, None)])
    def test_views_are_the_slice_of_all(self, views: slice) -> None:
        # the plane is fitted to every view (and oriented by every camera) whichever views are tested
        ground = render(np.zeros((0, 6)), num_views=4)
        scene = render(BOXES, num_views=4)
        depth, K, pose = (torch.cat(t) for t in zip(_tensors(scene), _tensors(ground)))
        some = above_ground_mask(depth, K, pose, views=views)
        assert torch.equal(some, above_ground_mask(depth, K, pose)[:, views])
        assert some.shape == depth[:, views].shape and some[0].any()

    def test_no_plane_means_every_valid_pixel(self) -> None:
        depth, K, pose = _tensors(render(BOXES, num_views=2))
        sparse = torch.zeros_like(depth)
        sparse[0, 0, 40, 40:42] = depth[0, 0, 40, 40:42]  # two points cannot define a plane
        torch.testing.assert_close(above_ground_mask(sparse, K, pose), sparse > 0)
