"""TUM RGB-D sequences (Sturm et al. 2012): colour, depth and motion-capture poses associated by timestamp.

Expected tree::

    rgbd_dataset_freiburg1_xyz/        # any name; "freiburg1|2|3" in it selects the intrinsics
      rgb.txt                          # "timestamp rgb/<timestamp>.png" lines, '#' comments
      depth.txt                        # "timestamp depth/<timestamp>.png"
      groundtruth.txt                  # "timestamp tx ty tz qx qy qz qw" (camera-to-world, quaternion scalar-last)
      rgb/<timestamp>.png              # 8-bit colour, 640x480
      depth/<timestamp>.png            # 16-bit, depth / 5000 = metres, 0 = missing; registered to colour
      threedq_objects.json             # optional: annotated boxes in the mocap frame

Each colour frame takes the nearest depth frame and the nearest pose (not interpolated), each within ``max_dt``
seconds, or is skipped and counted. Intrinsics are TUM's published per-sensor constants (``fr1``, ``fr2``, ``fr3``,
chosen from the folder name) unless given; TUM's lens distortion for fr1/fr2 is not applied.

Convention: mocap world frame, metres; the pose is the colour camera's optical centre, OpenCV camera axes.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from threedq.data.formats.capture import Capture, FrameSkip, load_frames, png_frame, skipping
from threedq.scene import SceneValidationError

__all__ = ["MARKER", "TUM_INTRINSICS", "read_tum"]

MARKER = "rgb.txt"
DEPTH_UNITS_PER_METRE = 5000.0
#: (fx, fy, cx, cy) per sensor, from the TUM RGB-D "file formats" page (640x480)
TUM_INTRINSICS = {"fr1": (517.3, 516.5, 318.6, 255.3), "fr2": (520.9, 521.0, 325.1, 249.7),
                  "fr3": (535.4, 539.2, 320.1, 247.6)}
_QUAT_TOL = 1e-3


def _read_list(path: Path, ncols: int, field_name: str, skipped: list[FrameSkip]) -> list[tuple[float, list[str]]]:
    """``(timestamp, other columns)`` of a TUM list file; malformed lines are skipped and counted."""
    if not path.is_file():
        raise SceneValidationError(str(path), field_name, "no such file")
    out = []
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            if len(parts) != ncols:
                raise ValueError(f"expected {ncols} columns, got {len(parts)}")
            out.append((float(parts[0]), parts[1:]))
        except ValueError as e:
            skipped.append(FrameSkip(f"{path}:{n}", field_name, f"malformed line ({e})"))
    out.sort(key=lambda x: x[0])
    return out


def _nearest(times: np.ndarray, t: float) -> tuple[int, float]:
    """Index of the nearest timestamp and its distance (``inf`` when empty)."""
    if times.size == 0:
        return -1, float("inf")
    i = int(np.searchsorted(times, t))
    j = min((j for j in (i - 1, i) if 0 <= j < times.size), key=lambda k: abs(times[k] - t))
    return j, abs(float(times[j]) - t)


def _intrinsics(folder: Path, intrinsics: tuple[float, float, float, float] | None) -> np.ndarray:
    if intrinsics is None:
        m = re.search(r"freiburg([123])", folder.resolve().name)
        if not m:
            why = "no 'freiburg1|2|3' in the folder name: give the intrinsics (fx, fy, cx, cy)"
            raise SceneValidationError(str(folder), "intrinsics", why)
        intrinsics = TUM_INTRINSICS[f"fr{m.group(1)}"]
    fx, fy, cx, cy = (float(x) for x in intrinsics)
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])


def read_tum(folder: str | Path, intrinsics: tuple[float, float, float, float] | None = None, max_dt: float = 0.02,
             depth_units_per_metre: float | None = None, max_views: int | None = None) -> Capture:
    """Read a TUM RGB-D sequence (tree in the module docstring); frame ids are the colour timestamps (``%.6f``).

    ``intrinsics`` ``(fx, fy, cx, cy)`` (``None`` = TUM's constants of the sensor in the folder name); ``max_dt``: the
    association tolerance in seconds; ``depth_units_per_metre`` ``None`` = 5000; at most ``max_views`` frames are read.
    """
    folder = Path(folder)
    K = _intrinsics(folder, intrinsics)
    scale = DEPTH_UNITS_PER_METRE if depth_units_per_metre is None else float(depth_units_per_metre)
    skipped: list[FrameSkip] = []
    rgbs = _read_list(folder / "rgb.txt", 2, "rgb", skipped)
    depths = _read_list(folder / "depth.txt", 2, "depth", skipped)
    gt = _read_list(folder / "groundtruth.txt", 8, "pose", skipped)
    d_times, p_times = np.array([t for t, _ in depths]), np.array([t for t, _ in gt])
    gt_file = str(folder / "groundtruth.txt")
    frames = []
    for t, (rgb_name,) in rgbs:
        stamp = f"{t:.6f}"
        (jd, dt_d), (jp, dt_p) = _nearest(d_times, t), _nearest(p_times, t)
        late = [(src, what) for dt, src, what in ((dt_d, folder / "depth.txt", "depth"), (dt_p, gt_file, "pose"))
                if dt > max_dt]
        if late:
            src, what = late[0]
            skipped.append(FrameSkip(str(src), what, f"no {what} within {max_dt} s of rgb {stamp}"))
            continue
        with skipping(skipped):
            q = np.array([float(x) for x in gt[jp][1][3:7]])
            if not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1) > _QUAT_TOL:
                why = f"pose at {p_times[jp]:.6f}: quaternion norm {np.linalg.norm(q):.4g} is not 1 (not a rotation)"
                raise SceneValidationError(gt_file, "pose", why)
            pose = np.eye(4)
            pose[:3, :3] = Rotation.from_quat(q).as_matrix()  # scipy: scalar-last, like TUM
            pose[:3, 3] = [float(x) for x in gt[jp][1][:3]]
            if not np.all(np.isfinite(pose)):
                raise SceneValidationError(gt_file, "pose", f"pose at {p_times[jp]:.6f} is not finite")
            frames.append(png_frame(stamp, pose, folder / rgb_name, folder / depths[jd][1][0], scale, K))
    return load_frames(frames, str(folder), "tum", skipped, folder, max_views)
