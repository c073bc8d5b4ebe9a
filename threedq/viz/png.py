"""PNG bytes of pictures: RGB arrays (OpenCV's encoder) and matplotlib figures (its object API on an Agg canvas).

No function here touches pyplot or the global matplotlib backend, so importing or running threedq never changes a
user's (a notebook's) backend, and figures are freed with their last reference (no pyplot figure registry).

Convention: images are ``[H, W, 3]`` uint8 RGB (not OpenCV's BGR).
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from threedq.atomic_io import atomic_write_bytes

__all__ = ["figure_png", "new_figure", "rgb_png", "write_png"]


def new_figure(**kwargs: Any) -> Any:
    """A matplotlib ``Figure`` on its own Agg canvas (``kwargs``: ``Figure``'s, e.g. ``figsize``, ``dpi``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def figure_png(fig: Any, dpi: float | None = None) -> bytes:
    """PNG bytes of a figure from :func:`new_figure`, laid out tightly."""
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", **({} if dpi is None else {"dpi": dpi}))
    return buf.getvalue()


def rgb_png(img: np.ndarray) -> bytes:
    """PNG bytes of an ``[H, W, 3]`` uint8 RGB image.

    Raises:
        ValueError: for another shape or dtype. RuntimeError: when the encoder fails.
    """
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"img: expected [H, W, 3] uint8 RGB, got {list(img.shape)} {img.dtype}")
    ok, png = cv2.imencode(".png", np.ascontiguousarray(img[:, :, ::-1]))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return png.tobytes()


def write_png(path: str | Path, picture: Any) -> Path:
    """Write an RGB image or a :func:`new_figure` figure (or PNG bytes) as a PNG, atomically; returns the path."""
    if isinstance(picture, (bytes, bytearray)):
        data = bytes(picture)
    elif isinstance(picture, np.ndarray):
        data = rgb_png(picture)
    else:
        data = figure_png(picture)
    atomic_write_bytes(Path(path), data)
    return Path(path)
