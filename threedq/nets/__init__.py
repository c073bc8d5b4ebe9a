"""Neural networks of threedq: the 3D lifting U-Net, its 2D twin (2.5DQ-Nets), the view-prediction decoder and the
occupancy head.

Convention:
    Volumes are ``[B, C, Z, Y, X]`` in the reference frame R (metres, z up, cell-centred voxels); frustum tensors
    ``[B, C, D, h, w]``; images ``[B, C, h, w]``.
"""

from . import unet2d, unet3d, view_decoder
from .unet2d import *  # noqa: F403
from .unet3d import *  # noqa: F403
from .view_decoder import *  # noqa: F403

__all__ = [name for module in (unet3d, unet2d, view_decoder) for name in module.__all__]
