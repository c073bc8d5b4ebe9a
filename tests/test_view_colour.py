"""threedq.data.view_colour: per-view colour gains from the floor, against analytic scenes whose views were given
known exposure and white-balance gains, and a naive per-pixel reference."""

from __future__ import annotations

import numpy as np
import pytest

from analytic_scenes import render
from threedq.data.sensor import exposure
from threedq.data.view_colour import apply_gains, floor_colour_gains

BOXES = np.array([[-0.3, -0.2, 0.0, -0.05, 0.1, 0.25], [0.15, -0.1, 0.0, 0.4, 0.2, 0.15]])
FLOOR, BOX = np.array([0.55, 0.45, 0.35]), np.array([0.2, 0.6, 0.3])


def _coloured(rec, gains: np.ndarray | None = None):
    """The scene with a floor of colour FLOOR and boxes of colour BOX (float RGB), each view times ``gains``."""
    V, H, W = rec.depth.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rgb = np.zeros((V, H, W, 3))
    for i in range(V):
        d = rec.depth[i].astype(np.float64)
        K, T = rec.K[i].astype(np.float64), rec.world_T_cam[i].astype(np.float64)
        cam = np.stack([(u - K[0, 2]) / K[0, 0] * d, (v - K[1, 2]) / K[1, 1] * d, d], -1)
        z = (cam @ T[:3, :3].T + T[:3, 3])[..., 2]
        rgb[i] = np.where((np.abs(z) < 1e-3)[..., None], FLOOR, BOX) * (d > 0)[..., None]
    if gains is not None:
        rgb = rgb * gains[:, None, None, :]
    rec.rgb = rgb.astype(np.float32)
    return rec


def naive_gains(rgb, depth, K, poses, band=0.03, stride=2, min_floor=0.05, min_change=0.06) -> np.ndarray:
    """Pixel by pixel: back-project with K's inverse, keep the points within ``band`` of z = 0, median per view."""
    V, H, W = depth.shape
    med = []
    for i in range(V):
        Kinv = np.linalg.inv(K[i].astype(np.float64))
        cols, total = [], 0
        for r in range(0, H, stride):
            for c in range(0, W, stride):
                d, total = float(depth[i, r, c]), total + 1
                if d > 0 and np.isfinite(d):
                    p = poses[i, :3, :3].astype(np.float64) @ (Kinv @ [c, r, 1.0] * d) + poses[i, :3, 3]
                    if abs(p[2]) <= band:
                        cols.append(rgb[i, r, c].astype(np.float64))
        med.append(np.median(cols, axis=0) if cols and len(cols) >= min_floor * total else None)
    seen = [m for m in med if m is not None]
    out = np.ones((V, 3))
    if len(seen) >= 2:
        ref = np.median(seen, axis=0)
        for i, m in enumerate(med):
            if m is not None and np.abs(ref / m - 1).max() > min_change:
                out[i] = ref / m
    return out


@pytest.fixture(scope="module")
def scene():
    return render(BOXES, num_views=8)


GAINS = np.array([[1.2, 1.0, 0.9], [0.8, 0.9, 1.1], [1.0, 1.0, 1.0], [1.3, 1.15, 1.0], [0.75, 0.85, 0.95],
                  [1.1, 1.25, 1.05], [0.9, 0.8, 0.7], [1.05, 1.1, 1.2]])


class TestFloorColourGains:
    def test_smoke(self, scene) -> None:
        rec = _coloured(scene)
        g = floor_colour_gains(rec.rgb, rec.depth, rec.K, rec.world_T_cam)
        assert g.shape == (8, 3) and g.dtype == np.float64

    def test_exception(self, scene) -> None:
        rec = _coloured(scene)
        shapes = r"got \[8, 96, 96, 3\], \[8, 96, 96\], \[8, 3, 3\], \[3, 4, 4\]"
        with pytest.raises(ValueError, match=r"rgb \[V,H,W,3\].*" + shapes):
            floor_colour_gains(rec.rgb, rec.depth, rec.K, rec.world_T_cam[:3])
        with pytest.raises(ValueError, match="rgb"):
            floor_colour_gains(rec.rgb[..., :2], rec.depth, rec.K, rec.world_T_cam)

    def test_same_colours_everywhere_are_left_bit_for_bit(self, scene) -> None:
        rec = _coloured(scene)
        g = floor_colour_gains(rec.rgb, rec.depth, rec.K, rec.world_T_cam)
        assert np.array_equal(g, np.ones((8, 3)))
        assert np.array_equal(apply_gains(rec.rgb, g), rec.rgb)

    def test_feature_known_gains_are_undone(self, scene) -> None:
        """Views given known gains: after the correction every view's floor and boxes have the colour they have
        under the scene's median gain (the reference is the scene's median, not a colour assumed)."""
        rec = _coloured(scene, GAINS)
        g = floor_colour_gains(rec.rgb, rec.depth, rec.K, rec.world_T_cam, min_change=0.0)
        np.testing.assert_allclose(g, np.median(GAINS, axis=0) / GAINS, rtol=1e-5)
        fixed = apply_gains(rec.rgb, g)
        want = _coloured(scene, np.repeat(np.median(GAINS, axis=0)[None], 8, 0)).rgb
        np.testing.assert_allclose(fixed, want, atol=1e-5)

    def test_feature_matches_naive(self, scene) -> None:
        rng = np.random.default_rng(0)
        rec = _coloured(scene, GAINS)
        rec.rgb = np.clip(rec.rgb + rng.normal(0, 0.02, rec.rgb.shape), 0, 1).astype(np.float32)
        got = floor_colour_gains(rec.rgb, rec.depth, rec.K, rec.world_T_cam)
        np.testing.assert_allclose(got, naive_gains(rec.rgb, rec.depth, rec.K, rec.world_T_cam), rtol=1e-10)

    def test_views_without_floor_keep_their_colours(self, scene) -> None:
        rec = _coloured(scene, GAINS)
        depth = rec.depth.copy()
        depth[1] = 0.0  # no depth at all
        g = floor_colour_gains(rec.rgb, depth, rec.K, rec.world_T_cam)
        assert np.array_equal(g[1], np.ones(3)) and not np.allclose(g[0], 1)
        only_one = np.zeros_like(depth)
        only_one[0] = rec.depth[0]
        assert np.array_equal(floor_colour_gains(rec.rgb, only_one, rec.K, rec.world_T_cam), np.ones((8, 3)))

    def test_small_gains_are_left_alone(self, scene) -> None:
        small = 1 + 0.5 * (GAINS - 1) / np.abs(GAINS - 1).max() * 0.1  # every gain within 5% of 1
        rec = _coloured(scene, small)
        assert np.array_equal(floor_colour_gains(rec.rgb, rec.depth, rec.K, rec.world_T_cam), np.ones((8, 3)))

    def test_round_trip_with_the_generators_exposure(self, scene) -> None:
        """threedq.data.sensor.exposure at level 1 (gains, white balance, pixel noise, uint8): the views' floor colours
        spread by about 15%; corrected, by under 2%."""
        rec = _coloured(scene)
        rgb = exposure(np.round(rec.rgb * 255).astype(np.uint8), np.random.default_rng(3), 1.0)
        floor = _coloured(scene).rgb[..., 0] == np.float32(FLOOR[0])

        def spread(x: np.ndarray) -> float:
            med = np.stack([np.median(x[i][floor[i]].astype(np.float64), axis=0) for i in range(8)])
            return float(np.log(med / np.median(med, axis=0)).std())

        g = floor_colour_gains(rgb, rec.depth, rec.K, rec.world_T_cam)
        fixed = apply_gains(rgb, g)
        assert fixed.dtype == np.uint8
        assert spread(rgb) > 0.05 and spread(fixed) < 0.02


class TestApplyGains:
    def test_uint8_rounds_and_clips(self) -> None:
        rgb = np.array([[[[100, 200, 10]]]], np.uint8)
        out = apply_gains(rgb, np.array([[1.5, 1.5, 0.55]]))
        assert out.dtype == np.uint8 and out.tolist() == [[[[150, 255, 6]]]]

    def test_float_keeps_dtype_and_range(self) -> None:
        rgb = np.full((2, 1, 1, 3), 0.8, np.float32)
        out = apply_gains(rgb, np.array([[1.5, 1.0, 0.5], [1.0, 1.0, 1.0]]))
        assert out.dtype == np.float32
        np.testing.assert_allclose(out[:, 0, 0], [[1.0, 0.8, 0.4], [0.8, 0.8, 0.8]])
