"""Tests of threedq.data.draw and threedq.data.contact_sheet: projection, wireframes, colourisation, contact sheet.

Scenes are built by hand (a tiny numpy ray caster of boxes on a ground plane); no rendering engine.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from analytic_scenes import look_at
from threedq.boxes import box_corners
from threedq.data.contact_sheet import CAPTION_HEIGHT, PAD, TILES_PER_VIEW, TITLE_HEIGHT, contact_sheet
from threedq.data.draw import colorize_depth, colorize_instances, distinct_colour, draw_boxes, project_points
from threedq.scene import DatasetIndex, SceneRecord, save_index, save_scene

CATEGORIES = ["chair", "table", "mug"]


# ----------------------------------------------------------------------------- helpers


def make_K(f: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]], dtype=np.float64)


def render(boxes: np.ndarray, categories: np.ndarray, K: np.ndarray, pose: np.ndarray, H: int, W: int):
    """Ray-cast boxes on the ground plane z = 0: (rgb [H,W,3] u8, depth [H,W] f32, instance [H,W] i32)."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pix = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3)
    d_cam = pix @ np.linalg.inv(K).T  # z = 1, so the ray parameter t is the z-depth
    d = d_cam @ pose[:3, :3].T
    o = pose[:3, 3]
    n = d.shape[0]
    depth = np.full(n, np.inf)
    inst = np.zeros(n, np.int32)
    shade = np.ones(n)
    base = np.zeros((n, 3))
    # ground plane, checkerboard
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(d[:, 2] < 0, -o[2] / d[:, 2], np.inf)
    gp_all = o + np.where(np.isfinite(tg), tg, 0)[:, None] * d
    hit = np.isfinite(tg) & np.all(np.abs(gp_all[:, :2]) <= 2.5, axis=1)  # a 5 m x 5 m floor; beyond: no depth
    gp = gp_all[hit]
    checker = (np.floor(gp[:, 0] * 2) + np.floor(gp[:, 1] * 2)) % 2
    depth[hit] = tg[hit]
    base[hit] = np.where(checker[:, None] > 0, 150.0, 110.0)
    for m, (b, c) in enumerate(zip(boxes, categories), start=1):
        cy_, sy_ = np.cos(-b[6]), np.sin(-b[6])
        Rinv = np.array([[cy_, -sy_, 0], [sy_, cy_, 0], [0, 0, 1]])
        ol = Rinv @ (o - b[:3])
        dl = d @ Rinv.T
        half = b[3:6] / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half - ol) / dl, (half - ol) / dl
        tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
        tmin = np.nan_to_num(tmin, nan=-np.inf)
        tmax = np.nan_to_num(tmax, nan=np.inf)
        tnear, tfar = tmin.max(axis=1), tmax.min(axis=1)
        ok = (tnear <= tfar) & (tnear > 0) & (tnear < depth)
        depth[ok] = tnear[ok]
        inst[ok] = m
        base[ok] = distinct_colour(CATEGORIES[int(c)])
        shade[ok] = np.array([0.75, 0.6, 1.0])[tmin.argmax(axis=1)[ok]]
    rgb = np.clip(base * shade[:, None], 0, 255).astype(np.uint8).reshape(H, W, 3)
    depth = np.where(np.isfinite(depth), depth, 0).astype(np.float32).reshape(H, W)
    return rgb, depth, inst.reshape(H, W)


def make_scene(seed: int, V: int = 4, H: int = 32, W: int = 40) -> SceneRecord:
    rng = np.random.default_rng(seed)
    boxes = np.array(
        [
            [-0.6, 0.3, 0.4, 0.5, 0.5, 0.8, rng.uniform(-np.pi, np.pi)],
            [0.5, -0.2, 0.25, 0.9, 0.6, 0.5, rng.uniform(-np.pi, np.pi)],
            [0.2, 0.7, 0.1, 0.15, 0.15, 0.2, 0.0],
        ]
    )
    cats = np.array([0, 1, 2])
    K = make_K(0.9 * W, (W - 1) / 2, (H - 1) / 2)
    rgbs, depths, insts, Ks, poses = [], [], [], [], []
    for k in range(V):
        a = 2 * np.pi * k / V + 0.3 * seed
        pose = look_at((3 * np.cos(a), 3 * np.sin(a), 1.8), (0, 0, 0.3))
        rgb, depth, inst = render(boxes, cats, K, pose, H, W)
        rgbs.append(rgb), depths.append(depth), insts.append(inst), Ks.append(K), poses.append(pose)
    return SceneRecord(
        rgb=np.stack(rgbs),
        depth=np.stack(depths),
        K=np.stack(Ks).astype(np.float32),
        world_T_cam=np.stack(poses).astype(np.float32),
        boxes=boxes.astype(np.float32),
        categories=cats,
        instance=np.stack(insts),
    )


def write_dataset(folder: Path, n: int = 2, **scene_kw) -> list[SceneRecord]:
    records = [make_scene(i, **scene_kw) for i in range(n)]
    scenes = []
    for i, r in enumerate(records):
        name = f"scene_{i:04d}.npz"
        save_scene(folder / name, r)
        scenes.append({"file": name, "split": "train" if i == 0 else "val"})
    save_index(
        folder,
        DatasetIndex(
            categories=CATEGORIES,
            symmetry_order=[1, 1, 0],
            scenes=scenes,
            scene_bounds=((-2.0, -2.0, 0.0), (2.0, 2.0, 2.0)),
            seed=0,
        ),
    )
    return records


def changed_mask(before_small: np.ndarray, after: np.ndarray, s: int) -> np.ndarray:
    size = (before_small.shape[1] * s, before_small.shape[0] * s)
    up = cv2.resize(before_small, size, interpolation=cv2.INTER_NEAREST)
    return np.any(up != after, axis=-1)


# ----------------------------------------------------------------------------- project_points


def test_project_points_hand_case():
    K = make_K(100.0, 31.5, 31.5)
    # camera at (0, 0, 5) looking down world -z: x_cam = +x_world, y_cam = -y_world, z_cam = -z_world
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]], dtype=np.float64)
    pose[:3, 3] = (0, 0, 5)
    assert np.isclose(np.linalg.det(pose[:3, :3]), 1.0)
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.5, -0.5, 1]])
    uv, z = project_points(pts, K, pose)
    # origin -> principal point; (1,0,0): x=1, z=5 -> u = 100/5 + 31.5; (0,1,0): y_cam = -1 -> v = 31.5 - 20
    # (0.5,-0.5,1): cam (0.5, 0.5, 4) -> u = v = 31.5 + 12.5
    np.testing.assert_allclose(uv, [[31.5, 31.5], [51.5, 31.5], [31.5, 11.5], [44.0, 44.0]], atol=1e-9)
    np.testing.assert_allclose(z, [5, 5, 5, 4], atol=1e-9)
    # the look_at helper gives the same pose (up = +y_world so that image "up" is +y)
    np.testing.assert_allclose(look_at((0, 0, 5), (0, 0, 0), up=(0, 1, 0)), pose, atol=1e-12)


def test_project_points_round_trip():
    rng = np.random.default_rng(0)
    K = make_K(120.0, 40.0, 30.0)
    K[0, 1] = 0.5  # a little skew, to exercise the full matrix
    pose = look_at((2.0, -3.0, 1.5), (0.1, 0.2, 0.3))
    uv = rng.uniform([0, 0], [80, 60], size=(50, 2))
    z = rng.uniform(0.5, 6.0, size=50)
    cam = np.concatenate([uv, np.ones((50, 1))], axis=1) @ np.linalg.inv(K).T * z[:, None]
    world = cam @ pose[:3, :3].T + pose[:3, 3]
    uv2, z2 = project_points(world, K, pose)
    np.testing.assert_allclose(uv2, uv, atol=1e-8)
    np.testing.assert_allclose(z2, z, atol=1e-10)


def test_project_points_behind_camera_is_nan():
    uv, z = project_points(np.array([[0.0, 0, -1], [0, 0, 2]]), make_K(50, 10, 10), np.eye(4))
    assert z[0] < 0 and np.all(np.isnan(uv[0]))
    np.testing.assert_allclose(uv[1], [10, 10])
    with pytest.raises(ValueError, match="points_world"):
        project_points(np.zeros((3, 2)), make_K(50, 10, 10), np.eye(4))


# ----------------------------------------------------------------------------- draw_boxes


def _front_setup():
    H = W = 64
    K = make_K(110.0, 31.5, 31.5)
    pose = look_at((2.5, -2.5, 2.0), (0, 0, 0.3))
    img = np.full((H, W, 3), 40, np.uint8)
    box = np.array([[0.0, 0.0, 0.3, 0.8, 0.5, 0.6, 0.4]])
    return img, box, K, pose


@pytest.mark.parametrize("s", [1, 3])
def test_draw_boxes_in_front_draws_only_near_its_hull(s):
    img, box, K, pose = _front_setup()
    out = draw_boxes(img, box, [""], K, pose, upscale=s, thickness=2)
    assert out.shape == (64 * s, 64 * s, 3) and out.dtype == np.uint8
    assert np.array_equal(img, np.full_like(img, 40)), "input must not be modified"
    changed = changed_mask(img, out, s)
    assert changed.any()
    uv, z = project_points(box_corners(box)[0], K, pose)
    assert np.all(z > 0)
    uv_out = uv * s + (s - 1) / 2  # pixel-centre convention of the nearest-neighbour upscale
    assert np.all((uv_out > 3) & (uv_out < 64 * s - 4)), "test box must project inside the image"
    # every projected corner has drawn pixels right next to it
    ys, xs = np.nonzero(changed)
    for u, v in uv_out:
        assert np.min(np.hypot(xs - u, ys - v)) <= 2.0, (u, v)
    # ... and nothing is drawn away from the projected hull (margin = line thickness + anti-aliasing)
    hull = np.zeros(changed.shape, np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(np.round(uv_out).astype(np.int32)), 1)
    near_hull = cv2.dilate(hull, np.ones((7, 7), np.uint8)) > 0
    assert not np.any(changed & ~near_hull)
    assert np.any((hull > 0) & ~changed), "the wireframe must not fill the box"


def test_draw_boxes_label_score_and_colour():
    img, box, K, pose = _front_setup()
    plain = draw_boxes(img, box, [""], K, pose, colour=(0, 255, 0))
    labelled = draw_boxes(img, box, ["chair"], K, pose, colour=(0, 255, 0))
    scored = draw_boxes(img, box, ["chair"], K, pose, scores=[0.87], colour=(0, 255, 0))
    assert changed_mask(img, labelled, 3).sum() > changed_mask(img, plain, 3).sum() + 50
    assert not np.array_equal(labelled, scored)
    # a single colour is used as given (RGB order): pure green wireframe pixels exist, no red ones
    assert np.any(np.all(plain == (0, 255, 0), axis=-1))
    assert not np.any(plain[..., 0] > 40)
    # the label tag sits near the top of the box: above its centre in the image
    uv, _ = project_points(box_corners(box)[0], K, pose)
    tag_rows = np.nonzero(np.any(changed_mask(img, labelled, 3) & ~changed_mask(img, plain, 3), axis=1))[0]
    assert tag_rows.mean() < uv[:, 1].mean() * 3
    with pytest.raises(ValueError, match="labels"):
        draw_boxes(img, box, ["a", "b"], K, pose)


def test_draw_boxes_behind_camera_draws_nothing():
    img, box, K, pose = _front_setup()
    # mirror the box through the camera centre: entirely behind the camera
    eye = pose[:3, 3]
    behind = box.copy()
    behind[0, :3] = eye - (box[0, :3] - eye)
    _, z = project_points(box_corners(behind)[0], K, pose)
    assert np.all(z < 0)
    out = draw_boxes(img, behind, ["chair"], K, pose, scores=[0.5])
    assert not changed_mask(img, out, 3).any()


def test_draw_boxes_straddling_camera_plane_draws_only_visible_part():
    H = W = 64
    K = make_K(100.0, 31.5, 31.5)
    pose = np.eye(4)  # camera frame = world frame, looking along +z
    img = np.zeros((H, W, 3), np.uint8)
    # x in [0.5, 1.5], y in [-0.5, 0.5], z in [-1, 2]: the part in front (z > 0) has x / z >= 0.25, so it
    # projects right of u = cx + 25; the corners behind (z = -1) would land at u < cx - 50 if projected naively
    box = np.array([[1.0, 0.0, 0.5, 1.0, 1.0, 3.0, 0.0]])
    _, z = project_points(box_corners(box)[0], K, pose)
    assert np.any(z < 0) and np.any(z > 0)
    for s in (1, 3):
        out = draw_boxes(img, box, ["straddle"], K, pose, upscale=s)
        changed = changed_mask(img, out, s)
        assert changed.any(), "the visible part must be drawn, not the whole box dropped"
        ys, xs = np.nonzero(changed)
        wire = xs[ys > 20 * s]  # below the label tag, which may sit anywhere along the top
        assert wire.size and wire.min() >= (31.5 + 25) * s - 4
    # a box around the camera (every edge crosses the camera plane or lies behind it) does not crash
    around = np.array([[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.3]])
    out = draw_boxes(img, around, ["around"], K, pose)
    assert out.shape == (H * 3, W * 3, 3)
    # a corner exactly on the camera plane
    draw_boxes(img, np.array([[0.5, 0.5, 0.5, 1.0, 1.0, 1.0, 0.0]]), ["on"], K, pose)


def test_draw_boxes_no_boxes():
    img, _, K, pose = _front_setup()
    out = draw_boxes(img, np.zeros((0, 7)), [], K, pose, upscale=2)
    assert out.shape == (128, 128, 3) and not changed_mask(img, out, 2).any()


# ----------------------------------------------------------------------------- colourisation


def test_colorize_depth():
    depth = np.zeros((8, 10), np.float32)
    depth[:, 5:] = np.linspace(1.0, 4.0, 5)[None]
    out = colorize_depth(depth)
    assert out.shape == (8, 10, 3) and out.dtype == np.uint8
    assert np.all(out[:, :5] == 0), "invalid depth is black"
    assert np.all(out[:, 5:].sum(-1) > 0)
    lum = out[0, 5:].astype(float) @ [0.299, 0.587, 0.114]
    assert np.all(np.diff(lum) > 0), "viridis: brighter with depth"
    # normalised per image: a scaled copy gives the same picture
    np.testing.assert_array_equal(colorize_depth(depth * 3), out)
    assert np.all(colorize_depth(np.zeros((4, 4))) == 0)


def test_colorize_instances():
    inst = np.array([[0, 1, 2], [3, 1, 0]], np.int32)
    out = colorize_instances(inst)
    assert out.shape == (2, 3, 3) and out.dtype == np.uint8
    assert np.all(out[inst == 0] == 0)
    np.testing.assert_array_equal(out[0, 1], out[1, 1])
    colours = {tuple(out[0, 1]), tuple(out[0, 2]), tuple(out[1, 0])}
    assert len(colours) == 3 and (0, 0, 0) not in colours
    # fixed per id: the same id gets the same colour in another image
    np.testing.assert_array_equal(colorize_instances(np.array([[2]]))[0, 0], out[0, 2])
    palette = np.array([distinct_colour(i) for i in range(1, 21)])
    assert len({tuple(c) for c in palette}) == 20


# ----------------------------------------------------------------------------- contact_sheet


def test_contact_sheet(tmp_path):
    H, W, s = 32, 40, 3
    records = write_dataset(tmp_path / "ds", n=2, H=H, W=W)
    out = contact_sheet(tmp_path / "ds", tmp_path / "sheets" / "sheet.png", num_scenes=4, upscale=s)
    assert out == tmp_path / "sheets" / "sheet.png" and out.is_file()
    assert not [p for p in out.parent.iterdir() if p.name != "sheet.png"], "no temporary files left"
    bgr = cv2.imread(str(out), cv2.IMREAD_COLOR)
    assert bgr is not None
    sheet = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    n_rows, n_views = 2, 2
    row_h = TITLE_HEIGHT + CAPTION_HEIGHT + H * s
    assert sheet.shape == (PAD + n_rows * (row_h + PAD), PAD + TILES_PER_VIEW * n_views * (W * s + PAD), 3)
    assert sheet.std() > 20, "sheet is blank"
    # the first tile of each row is that scene's view-0 RGB, nearest-neighbour upscaled, in true colour
    for r, rec in enumerate(records):
        y0, x0 = PAD + r * (row_h + PAD) + TITLE_HEIGHT + CAPTION_HEIGHT, PAD
        tile = sheet[y0:y0 + H * s, x0:x0 + W * s]
        np.testing.assert_array_equal(tile[1::s, 1::s], rec.rgb[0])
        # second view group starts with view V // 2 = 2
        x1 = PAD + TILES_PER_VIEW * (W * s + PAD)
        np.testing.assert_array_equal(sheet[y0:y0 + H * s, x1:x1 + W * s][1::s, 1::s], rec.rgb[2])
        # the GT-box tile differs from the plain RGB (boxes drawn) and the title strip has text
        x3 = PAD + 3 * (W * s + PAD)
        assert np.any(sheet[y0:y0 + H * s, x3:x3 + W * s] != tile)
        assert sheet[y0 - TITLE_HEIGHT - CAPTION_HEIGHT:y0 - CAPTION_HEIGHT].max() > 150


def test_contact_sheet_split_views_and_errors(tmp_path):
    H, W = 24, 24
    write_dataset(tmp_path, n=2, H=H, W=W)
    out = contact_sheet(tmp_path, tmp_path / "val.png", split="val", views=[3], upscale=2)
    sheet = cv2.imread(str(out))
    assert sheet.shape == (PAD + TITLE_HEIGHT + CAPTION_HEIGHT + 2 * H + PAD, PAD + TILES_PER_VIEW * (2 * W + PAD), 3)
    out = contact_sheet(tmp_path, tmp_path / "one.png", num_scenes=1, views=[0, 1, 2])
    assert cv2.imread(str(out)).shape[1] == PAD + 3 * TILES_PER_VIEW * (3 * W + PAD)
    with pytest.raises(ValueError, match="no scenes"):
        contact_sheet(tmp_path, tmp_path / "x.png", split="test")
    with pytest.raises(ValueError, match="out of range"):
        contact_sheet(tmp_path, tmp_path / "x.png", views=[7])
    assert not (tmp_path / "x.png").exists()


def test_crop_birds_eye_hand_computed() -> None:
    import torch

    from threedq.data.draw import crop_birds_eye

    raw = torch.zeros(4, 3, 2, 2)  # [occ, r, g, b] x Z x Y x X
    raw[0, 0, 0, 0], raw[1:, 0, 0, 0] = 1.0, torch.tensor([1.0, 0.0, 0.0])  # red at z 0, (y 0, x 0)
    raw[0, 2, 0, 0], raw[1:, 2, 0, 0] = 1.0, torch.tensor([0.0, 1.0, 0.0])  # green above it: the top wins
    raw[0, 1, 1, 1], raw[1:, 1, 1, 1] = 0.4, torch.tensor([0.0, 0.0, 1.0])  # occupancy <= 0.5: not drawn
    img = crop_birds_eye(raw, background=0.25)
    assert img.shape == (2, 2, 3)
    assert img[1, 0].tolist() == [0.0, 1.0, 0.0]  # y 0 is the bottom row (y up)
    assert img[0, 1].tolist() == [0.25, 0.25, 0.25] and img[1, 1].tolist() == [0.25, 0.25, 0.25]
