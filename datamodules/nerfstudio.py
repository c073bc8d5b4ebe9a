"""nerfstudio transforms.json captures with depth: imported into canonical records on first use, then read as a scene folder.

Expected tree of each capture: the module docstring of ``threedq/data/formats/nerfstudio.py``; see
:class:`~threedq.datamodules.capture_folder.CaptureDataModule` for the arguments.
"""

from __future__ import annotations

from threedq.datamodules.capture_folder import CaptureDataModule

__all__ = ["NerfstudioDataModule"]


class NerfstudioDataModule(CaptureDataModule):
    """nerfstudio transforms.json captures with depth; arguments as :class:`~threedq.datamodules.capture_folder.CaptureDataModule`."""

    FORMAT = "nerfstudio"
