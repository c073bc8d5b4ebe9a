"""The capture formats by name: ``FORMATS[name] = (parse function, marker file that identifies a capture)``."""

from __future__ import annotations

from collections.abc import Callable

from threedq.data.formats import bigbird, nerfstudio, open3d, replica, rig, scannet, tum
from threedq.data.formats.capture import Capture

__all__ = ["FORMATS"]

FORMATS: dict[str, tuple[Callable[..., Capture], str]] = {
    "tum": (tum.parse_tum, tum.MARKER),
    "scannet": (scannet.parse_scannet, scannet.MARKER),
    "nerfstudio": (nerfstudio.parse_nerfstudio, nerfstudio.MARKER),
    "replica": (replica.parse_replica, replica.MARKER),
    "bigbird": (bigbird.parse_bigbird, bigbird.MARKER),
    "open3d": (open3d.parse_open3d, open3d.MARKER),
    "rig": (rig.parse_rig, rig.MARKER),
}
