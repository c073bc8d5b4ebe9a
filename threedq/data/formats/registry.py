"""The capture formats by name: ``FORMATS[name] = (parse function, marker file that identifies a capture)``."""

from __future__ import annotations

from collections.abc import Callable

from threedq.data.formats import bigbird, nerfstudio, open3d, replica, rig, scannet, tum
from threedq.data.formats.capture import Capture

__all__ = ["FORMATS"]

FORMATS: dict[str, tuple[Callable[..., Capture], str]] = {
    "tum": (tum.read_tum, tum.MARKER),
    "scannet": (scannet.read_scannet, scannet.MARKER),
    "nerfstudio": (nerfstudio.read_nerfstudio, nerfstudio.MARKER),
    "replica": (replica.read_replica, replica.MARKER),
    "bigbird": (bigbird.read_bigbird, bigbird.MARKER),
    "open3d": (open3d.read_open3d, open3d.MARKER),
    "rig": (rig.read_rig, rig.MARKER),
}
