"""Cross-view consistency of generated scenes through the geometry core.

The depth of view A, back-projected with A's K and pose, reprojected into view B, must land where B saw
the same surface: sampling B's depth there and back-projecting returns to A's pixel (round trip
A -> B -> A) with a mean error well under half a pixel, on object pixels that B sees unoccluded.
"""

from __future__ import annotations


import pytest
import torch
import torch.nn.functional as F

from threedq.data.generate import generate_dataset
from threedq.data.generator_config import GeneratorConfig
from threedq.geometry import depth_to_points, invert_rigid, project, transform_points
from threedq.scene import load_index, load_scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("mv")
    cfg = GeneratorConfig(image_size=(96, 128), num_views=6, min_objects=2, max_objects=3)
    generate_dataset(out, num_scenes=2, seed=3, config=cfg, splits=("train",), workers=1, progress=False)
    return load_scene(out / load_index(out).files("train")[0])


def _bilinear(img: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Sample ``img`` [H, W] at pixel coordinates ``uv`` [N, 2] (integer pixel centres)."""
    H, W = img.shape
    grid = torch.stack(((2 * uv[:, 0] + 1) / W - 1, (2 * uv[:, 1] + 1) / H - 1), dim=-1)
    return F.grid_sample(img[None, None], grid[None, None], mode="bilinear", align_corners=False)[0, 0, 0]


def round_trip_error(rec, a: int, b: int, K_b_override: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel A -> B -> A reprojection error (px) and depth discrepancy (m) on A's object pixels seen by B."""
    depth = torch.from_numpy(rec.depth).double()
    K = torch.from_numpy(rec.K).double()
    pose = torch.from_numpy(rec.world_T_cam).double()
    inst = torch.from_numpy(rec.instance)
    K_b = K[b] if K_b_override is None else K_b_override
    H, W = depth.shape[1:]
    pts, valid = depth_to_points(depth[a : a + 1], K[a : a + 1], pose[a : a + 1])  # [1, H*W, 3]
    ids_a = inst[a].flatten()
    keep = valid[0] & (ids_a > 0)
    X = pts[0, keep]
    vv, uu = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    pix_a = torch.stack((uu.flatten(), vv.flatten()), -1)[keep].double()
    uv_b, z_b = project(transform_points(invert_rigid(pose[b : b + 1]), X[None]), K_b[None])
    uv_b, z_b = uv_b[0], z_b[0]
    # B must see the same object at all four bilinear neighbours, in front of the camera and unoccluded.
    inside = (uv_b[:, 0] >= 0) & (uv_b[:, 0] <= W - 1) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] <= H - 1) & (z_b > 0)
    u0 = uv_b[:, 0].floor().long().clamp(0, W - 2)
    v0 = uv_b[:, 1].floor().long().clamp(0, H - 2)
    same = torch.ones_like(inside)
    for du in (0, 1):
        for dv in (0, 1):
            same &= inst[b][v0 + dv, u0 + du] == ids_a[keep]
    d_b = _bilinear(depth[b], uv_b)
    visible = inside & same & ((d_b - z_b).abs() < 0.02)
    # back to A through B's depth
    uv_h = torch.cat([uv_b[visible], torch.ones_like(uv_b[visible, :1])], -1)
    X_b = (torch.linalg.solve(K_b, uv_h.T).T) * d_b[visible, None]
    X_w = transform_points(pose[b : b + 1], X_b[None])
    uv_a, _ = project(transform_points(invert_rigid(pose[a : a + 1]), X_w), K[a : a + 1])
    err = (uv_a[0] - pix_a[visible]).norm(dim=-1)
    return err, (d_b - z_b)[visible]


def test_depth_reprojects_across_views(scene) -> None:
    errors, depth_gaps = [], []
    for a, b in [(0, 1), (1, 3), (2, 5), (4, 0)]:
        err, gap = round_trip_error(scene, a, b)
        if err.numel() > 20:
            errors.append(err)
            depth_gaps.append(gap)
    assert errors, "no view pair saw an object in common"
    err = torch.cat(errors)
    gap = torch.cat(depth_gaps)
    assert err.mean() < 0.5, f"mean A->B->A reprojection error {err.mean():.3f} px"
    assert gap.abs().median() < 0.005, f"median depth discrepancy {gap.abs().median():.4f} m"


def test_a_one_pixel_calibration_error_is_detected(scene) -> None:
    """The check is sensitive: shifting B's principal point by one pixel breaks it."""
    base, shifted = [], []
    for a, b in [(0, 1), (1, 3), (2, 5), (4, 0)]:
        e0, _ = round_trip_error(scene, a, b)
        K_b = torch.from_numpy(scene.K[b]).double().clone()
        K_b[0, 2] += 1.0
        e1, _ = round_trip_error(scene, a, b, K_b_override=K_b)
        if e0.numel() > 20 and e1.numel() > 20:
            base.append(e0)
            shifted.append(e1)
    assert base
    assert torch.cat(shifted).mean() > 2 * torch.cat(base).mean()
