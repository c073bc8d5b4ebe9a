"""Neural networks of threedq: the 3D lifting U-Net, its 2D twin (2.5DQ-Nets), the view-prediction decoder and the occupancy head.

Convention:
    Volumes are ``[B, C, Z, Y, X]`` in the reference frame R (metres, z up, cell-centred voxels); frustum tensors
    ``[B, C, D, h, w]``; images ``[B, C, h, w]``.
"""

from .unet3d import *  # noqa: F403
from .unet3d import __all__ as _unet3d_all
from .unet2d import *  # noqa: F403
from .unet2d import __all__ as _unet2d_all
from .view_decoder import *  # noqa: F403
from .view_decoder import __all__ as _view_decoder_all

__all__ = [*_unet3d_all, *_unet2d_all, *_view_decoder_all]
