"""nerfstudio transforms.json captures with depth, imported into canonical records on first use (capture layout: the
module docstring of ``threedq/data/formats/nerfstudio.py``)."""

from threedq.datamodules.capture_folder import CaptureDataModule

__all__ = ["NerfstudioDataModule"]


class NerfstudioDataModule(CaptureDataModule):
    """nerfstudio transforms.json captures with depth; arguments as :class:`CaptureDataModule`."""

    FORMAT = "nerfstudio"
