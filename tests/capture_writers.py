"""Write a generated scene out in each capture format's on-disk layout (the test side of the parsers).

The writers are independent of the parsers: they follow each format's published layout (``docs`` of the
format, ``/work/shared/reference/data-formats.md``) with numpy, OpenCV, h5py and json only.

The scene is rendered by the project's generator from a turntable camera set: cameras ``c`` (elevations)
times yaws ``t``, ``world_T_cam[c, t] = Rz(yaw_t) @ P_c`` - so it is also a BigBIRD turntable and a fixed rig.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import h5py
import numpy as np
from scipy.spatial.transform import Rotation

from threedq.scene import SceneRecord

ELEVATIONS_DEG = (35.0, 60.0)
YAWS_DEG = (0.0, 120.0, 240.0)
OPENGL_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def rz(deg: float) -> np.ndarray:
    T = np.eye(4)
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def rig_cameras(distance: float = 3.2) -> np.ndarray:
    """``P_c`` ``[C,4,4]``: camera-to-rig poses looking at the origin (OpenCV axes)."""
    out = []
    for e in ELEVATIONS_DEG:
        eye = distance * np.array([math.cos(math.radians(e)), 0.0, math.sin(math.radians(e))])
        z = -eye / np.linalg.norm(eye)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, eye
        out.append(T)
    return np.array(out)


def turntable_scene(image_size: tuple[int, int] = (24, 32), seed: int = 7) -> SceneRecord:
    """A generated scene (objects, light) rendered from the turntable cameras; views ordered camera-major."""
    from threedq.data.generator_config import GeneratorConfig
    from threedq.data.layout import sample_scene
    from threedq.data.render_scene import make_renderer, render_scene

    config = GeneratorConfig(image_size=image_size, num_views=6, max_objects=3, min_objects=2)
    layout = sample_scene(config, np.random.SeedSequence(seed))
    P = rig_cameras()
    poses = np.array([rz(t) @ P[c] for c in range(len(P)) for t in YAWS_DEG])
    poses = poses.astype(np.float32).astype(np.float64)
    layout = dataclasses.replace(layout, world_T_cam=poses, K=np.repeat(layout.K[:1], len(poses), axis=0))
    renderer = make_renderer(config)
    try:
        return render_scene(layout, renderer)
    finally:
        renderer.release()


def write_objects(folder: Path, rec: SceneRecord, capture_T_world: np.ndarray) -> None:
    """``threedq_objects.json`` with the record's boxes in the capture frame."""
    objs = []
    for b, c in zip(rec.boxes.astype(np.float64), rec.categories):
        w_T_box = rz(math.degrees(b[6]))
        w_T_box[:3, 3] = b[:3]
        objs.append(
            {"category": f"cat{int(c)}", "capture_T_box": (capture_T_world @ w_T_box).tolist(), "size": b[3:6].tolist()}
        )
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "threedq_objects.json").write_text(json.dumps({"objects": objs}))


def _bgr(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)


def _png16(path: Path, depth: np.ndarray, units_per_metre: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.clip(np.rint(depth.astype(np.float64) * units_per_metre), 0, 65535).astype(np.uint16))


def _img(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    params = [cv2.IMWRITE_JPEG_QUALITY, 100] if path.suffix == ".jpg" else []
    cv2.imwrite(str(path), _bgr(rgb), params)


def upsample2(rgb: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Colour at twice the size (nearest: an area downsampling gives the original back) and its intrinsics."""
    big = np.repeat(np.repeat(rgb, 2, axis=0), 2, axis=1)
    S = np.array([[2.0, 0, 0.5], [0, 2.0, 0.5], [0, 0, 1]])  # u' = 2 (u + 0.5) - 0.5
    return big, S @ K.astype(np.float64)


def write_tum(
    folder: Path, rec: SceneRecord, capture_T_world: np.ndarray | None = None, drop_pose: int | None = None
) -> None:
    """TUM layout with timestamp jitter: depth 10 ms after colour, mocap 5 ms before, extra mocap lines between."""
    capture_T_world = np.eye(4) if capture_T_world is None else capture_T_world
    rgb_lines, depth_lines, gt_lines = ["# color images"], ["# depth maps"], ["# timestamp tx ty tz qx qy qz qw"]
    for v in range(rec.num_views):
        t = 1305031102.175304 + 0.5 * v
        td = t + (0.01 if v % 2 == 0 else -0.012)
        _img(folder / "rgb" / f"{t:.6f}.png", rec.rgb[v])
        _png16(folder / "depth" / f"{td:.6f}.png", rec.depth[v], 5000.0)
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
        pose = capture_T_world @ rec.world_T_cam[v].astype(np.float64)
        q = Rotation.from_matrix(pose[:3, :3]).as_quat()  # x y z w
        if v != drop_pose:
            gt_lines.append(f"{t - 0.005:.6f} " + " ".join(f"{x:.9f}" for x in [*pose[:3, 3], *q]))
        gt_lines.append(f"{t + 0.25:.6f} 9 9 9 0 0 0 1")  # another pose, far from every colour frame
    for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", depth_lines), ("groundtruth.txt", gt_lines)):
        (folder / name).write_text("\n".join(lines) + "\n")


def write_scannet(folder: Path, rec: SceneRecord, bad_pose: int | None = None) -> list[int]:
    """SensReader export: colour at twice the depth size (JPEG), depth in millimetres, numbered 0, 5, 10, ..."""
    ids = [5 * v for v in range(rec.num_views)]
    K = rec.K[0].astype(np.float64)
    _, Kc = upsample2(rec.rgb[0], K)
    (folder / "intrinsic").mkdir(parents=True, exist_ok=True)
    for name, k in (("intrinsic_color", Kc), ("intrinsic_depth", K)):
        K4 = np.eye(4)
        K4[:3, :3] = k
        np.savetxt(folder / "intrinsic" / f"{name}.txt", K4, fmt="%.17g")
    for name in ("extrinsic_color", "extrinsic_depth"):
        np.savetxt(folder / "intrinsic" / f"{name}.txt", np.eye(4), fmt="%.6f")
    (folder / "pose").mkdir(parents=True, exist_ok=True)
    for v, i in enumerate(ids):
        _img(folder / "color" / f"{i}.jpg", upsample2(rec.rgb[v], K)[0])
        _png16(folder / "depth" / f"{i}.png", rec.depth[v], 1000.0)
        pose = rec.world_T_cam[v].astype(np.float64)
        if v == bad_pose:
            pose = np.full((4, 4), -np.inf)
        np.savetxt(folder / "pose" / f"{i}.txt", pose, fmt="%.9f")
    return ids


def write_nerfstudio(folder: Path, rec: SceneRecord, scale: float = 2e-4, non_rigid: int | None = None) -> None:
    """transforms.json with OpenGL poses, COLMAP pixel centres, global intrinsics but per-frame ones on odd frames,
    depth in units of ``scale`` metres (``depth_unit_scale_factor``)."""
    K = rec.K[0].astype(np.float64)
    H, W = rec.image_size
    top = {
        "camera_model": "OPENCV",
        "fl_x": K[0, 0],
        "fl_y": K[1, 1],
        "cx": K[0, 2] + 0.5,
        "cy": K[1, 2] + 0.5,
        "w": W,
        "h": H,
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "depth_unit_scale_factor": scale,
        "frames": [],
    }
    for v in range(rec.num_views):
        pose = rec.world_T_cam[v].astype(np.float64) @ OPENGL_FLIP
        if v == non_rigid:
            pose[:3, :3] *= 1.1
        fr = {
            "file_path": f"images/frame_{v + 1:05d}.png",
            "depth_file_path": f"depth/frame_{v + 1:05d}.png",
            "transform_matrix": pose.tolist(),
        }
        if v % 2:
            Kv = rec.K[v].astype(np.float64)
            fr.update({"fl_x": Kv[0, 0], "fl_y": Kv[1, 1], "cx": Kv[0, 2] + 0.5, "cy": Kv[1, 2] + 0.5})
        top["frames"].append(fr)
        _img(folder / fr["file_path"], rec.rgb[v])
        _png16(folder / fr["depth_file_path"], rec.depth[v], 1.0 / scale)
    (folder / "transforms.json").write_text(json.dumps(top, indent=2))


def write_replica(folder: Path, rec: SceneRecord, drop_last_line: bool = False) -> None:
    """NICE-SLAM Replica export: results/frame*.jpg, depth*.png / 6553.5, traj.txt; cam_params.json one level up."""
    K = rec.K[0].astype(np.float64)
    H, W = rec.image_size
    folder.mkdir(parents=True, exist_ok=True)
    (folder.parent / "cam_params.json").write_text(
        json.dumps(
            {"camera": {"w": W, "h": H, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "scale": 6553.5}}
        )
    )
    lines = []
    for v in range(rec.num_views):
        _img(folder / "results" / f"frame{v:06d}.jpg", rec.rgb[v])
        _png16(folder / "results" / f"depth{v:06d}.png", rec.depth[v], 6553.5)
        lines.append(" ".join(f"{x:.9f}" for x in rec.world_T_cam[v].astype(np.float64).reshape(-1)))
    if drop_last_line:
        lines = lines[:-1]
    (folder / "traj.txt").write_text("\n".join(lines) + "\n")


def write_open3d(
    folder: Path, rec: SceneRecord, capture_T_world: np.ndarray | None = None, bad_depth_size: int | None = None
) -> None:
    """Open3D reconstruction folder: color/*.png, depth/*.png (mm), camera_intrinsic.json (column-major), .log."""
    capture_T_world = np.eye(4) if capture_T_world is None else capture_T_world
    K = rec.K[0].astype(np.float64)
    H, W = rec.image_size
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "camera_intrinsic.json").write_text(
        json.dumps({"width": W, "height": H, "intrinsic_matrix": K.T.reshape(-1).tolist()})
    )
    log = []
    for v in range(rec.num_views):
        _img(folder / "color" / f"{v:06d}.png", rec.rgb[v])
        d = rec.depth[v]
        if v == bad_depth_size:
            d = d[:-2]
        _png16(folder / "depth" / f"{v:06d}.png", d, 1000.0)
        pose = capture_T_world @ rec.world_T_cam[v].astype(np.float64)
        log.append(f"{v} {v} {v + 1}")
        log.extend(" ".join(f"{x:.9f}" for x in row) for row in pose)
    (folder / "trajectory.log").write_text("\n".join(log) + "\n")


def write_bigbird(folder: Path, rec: SceneRecord, corrupt_h5: str | None = None) -> None:
    """BigBIRD object folder for the turntable scene: cameras NP1 (lower) and NP5 (upper, the reference), colour
    at twice the depth size, depth in 100 um units in h5, calibration.h5, poses/NP5_{deg}_pose.h5."""
    P = rig_cameras()
    cams = {1: P[0], 5: P[1]}  # camera id -> P_c (rig = table frame at yaw 0)
    K = rec.K[0].astype(np.float64)
    _, Kc = upsample2(rec.rgb[0], K)
    folder.mkdir(parents=True, exist_ok=True)
    with h5py.File(folder / "calibration.h5", "w") as f:
        for c, Pc in cams.items():
            c_T_5 = np.linalg.inv(Pc) @ cams[5]
            f[f"NP{c}_rgb_K"], f[f"NP{c}_depth_K"] = Kc, K
            f[f"H_NP{c}_from_NP5"], f[f"H_NP{c}_ir_from_NP5"] = c_T_5, c_T_5  # IR camera at the colour camera
    (folder / "poses").mkdir(exist_ok=True)
    for ci, c in enumerate(cams):
        for ti, yaw in enumerate(YAWS_DEG):
            deg = int(yaw)
            v = ci * len(YAWS_DEG) + ti
            if c == 5:
                with h5py.File(folder / "poses" / f"NP5_{deg}_pose.h5", "w") as f:
                    f["H_table_from_reference_camera"] = rz(yaw) @ cams[5]
            _img(folder / f"NP{c}_{deg}.jpg", upsample2(rec.rgb[v], K)[0])
            with h5py.File(folder / f"NP{c}_{deg}.h5", "w") as f:
                f["depth"] = np.rint(rec.depth[v].astype(np.float64) * 10000).clip(0, 65535).astype(np.uint16)
    if corrupt_h5 is not None:
        p = folder / corrupt_h5
        p.write_bytes(p.read_bytes()[:200])


def carla_encode(depth: np.ndarray) -> np.ndarray:
    """CARLA's RGB depth encoding ``[H,W,3]`` uint8 (R least significant, far plane 1000 m)."""
    n = np.rint(depth.astype(np.float64) / 1000.0 * (256**3 - 1)).astype(np.int64)
    return np.stack([n & 255, (n >> 8) & 255, n >> 16], axis=-1).astype(np.uint8)


def write_rig(folder: Path, rec: SceneRecord, drop_capture: int | None = None) -> None:
    """A recorded rig: the turntable's cameras are the rig's cameras, its yaws the captures; CARLA depth."""
    P = rig_cameras()
    K = rec.K[0].astype(np.float64)
    spec = {"depth": {"encoding": "carla"}, "cameras": {}, "captures": {}}
    for ci in range(len(P)):
        spec["cameras"][f"cam_{ci:02d}"] = {"K": K.tolist(), "rig_T_cam": P[ci].tolist()}
        for ti in range(len(YAWS_DEG)):
            v = ci * len(YAWS_DEG) + ti
            _img(folder / f"cam_{ci:02d}" / f"rgb_{ti:06d}.png", rec.rgb[v])
            _img(folder / f"cam_{ci:02d}" / f"depth_{ti:06d}.png", carla_encode(rec.depth[v]))
    for ti, yaw in enumerate(YAWS_DEG):
        if ti != drop_capture:
            spec["captures"][ti] = rz(yaw).tolist()
    import yaml

    (folder / "rig.yaml").write_text(yaml.safe_dump(spec))
