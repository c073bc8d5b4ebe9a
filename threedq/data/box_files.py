"""Box files: per-scene axis-aligned 3D boxes with scores in one ``.npz`` (proposal caches, detections).

Layout: ``format`` (:data:`BOX_FILE_FORMAT`), ``params`` (a JSON string: whatever made the boxes), ``scenes`` ``[S]``
str (scene files as listed in ``index.json``), ``counts`` ``[S]`` i64, ``aabb`` ``[sum P, 6]`` f32 ``(xmin, ymin, zmin,
xmax, ymax, zmax)`` in the world frame (metres, z up), ``scores`` ``[sum P]`` f32. Files are written atomically.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from threedq.atomic_io import atomic_write_bytes, npz_bytes

__all__ = ["BOX_FILE_FORMAT", "load_boxes_file", "load_boxes_file_with_params", "save_boxes_file"]

#: The ``format`` field of every box file.
BOX_FILE_FORMAT = "threedq-proposals"


def _read(path: Path) -> tuple[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """``(params json, {scene -> (aabb, scores)})``; raises ``ValueError`` naming the file when unreadable."""
    try:
        with np.load(path, allow_pickle=False) as z:
            fmt = str(z["format"])
            if fmt != BOX_FILE_FORMAT:
                raise ValueError(f"{path}: field 'format': expected {BOX_FILE_FORMAT!r}, got {fmt!r}")
            params = str(z["params"])
            names = [str(s) for s in z["scenes"]]
            counts, aabb, scores = z["counts"], z["aabb"], z["scores"]
    except ValueError as e:
        if str(e).startswith(str(path)):
            raise
        raise ValueError(f"{path}: not a readable proposal cache (truncated or corrupt: {e})") from e
    except (KeyError, zipfile.BadZipFile, OSError, EOFError) as e:
        raise ValueError(f"{path}: not a readable proposal cache (missing key or corrupt: {e})") from e
    ok = counts.shape == (len(names),) and aabb.ndim == 2 and aabb.shape[1] == 6 and scores.shape == (aabb.shape[0],)
    if not ok or int(counts.sum()) != aabb.shape[0] or np.any(counts < 0):
        raise ValueError(f"{path}: field 'counts': inconsistent proposal cache (array shapes do not agree)")
    ends = np.cumsum(counts)
    return params, {name: (aabb[e - c : e].astype(np.float32), scores[e - c : e].astype(np.float32))
                    for name, c, e in zip(names, counts.tolist(), ends.tolist())}


def load_boxes_file(path: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Read a per-scene box file: ``{scene file as listed in index.json -> (aabb [P,6] float32, scores [P] float32)}``;
    ``FileNotFoundError`` / ``ValueError`` naming the file when it is missing or unreadable."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: box file not found")
    return _read(path)[1]


def load_boxes_file_with_params(path: str | Path) -> tuple[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Like :func:`load_boxes_file`, but also returns the file's ``params`` string: ``(params, boxes)``."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: box file not found")
    return _read(path)


def save_boxes_file(path: str | Path, boxes: dict[str, tuple[np.ndarray, np.ndarray]], params: str = "{}") -> None:
    """Write ``{scene -> (aabb [P,6], scores [P])}`` and the ``params`` string atomically, scenes in dict order."""
    for name, (aabb, scores) in boxes.items():
        if np.asarray(aabb).reshape(-1, 6).shape[0] != np.asarray(scores).reshape(-1).shape[0]:
            raise ValueError(f"{path}: field 'scores': scene {name}: {len(scores)} scores for {len(aabb)} boxes")
    names = list(boxes)
    aabb = [np.asarray(boxes[k][0], np.float32).reshape(-1, 6) for k in names]
    scores = [np.asarray(boxes[k][1], np.float32).reshape(-1) for k in names]
    arrays = {"format": np.array(BOX_FILE_FORMAT), "params": np.array(params),
              "scenes": np.array(names, dtype=np.str_) if names else np.zeros((0,), dtype="<U1"),
              "counts": np.array([a.shape[0] for a in aabb], dtype=np.int64),
              "aabb": np.concatenate(aabb).astype(np.float32) if aabb else np.zeros((0, 6), np.float32),
              "scores": np.concatenate(scores).astype(np.float32) if scores else np.zeros((0,), np.float32)}
    atomic_write_bytes(Path(path), npz_bytes(arrays))
