"""The capture formats by name: ``FORMATS[name] = (parse function, marker file that identifies a capture)``."""

from __future__ import annotations

from collections.abc import Callable

from threedq.data.formats import bigbird, nerfstudio, open3d, replica, rig, scannet, tum
from threedq.data.formats.capture import Capture

__all__ = ["FORMATS"]

_MODULES = {"tum": tum, "scannet": scannet, "nerfstudio": nerfstudio, "replica": replica, "bigbird": bigbird,
            "open3d": open3d, "rig": rig}
FORMATS: dict[str, tuple[Callable[..., Capture], str]] = {
    name: (getattr(m, f"read_{name}"), m.MARKER) for name, m in _MODULES.items()}
