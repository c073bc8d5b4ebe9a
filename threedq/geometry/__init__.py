"""Geometry core: voxel grids, cameras, unprojection, box crops, yaw rotation, the ground plane and
fused point clouds.

Convention:
    Metres; reference frame R right-handed with z up; yaw counter-clockwise about +z seen from above,
    radians. Cameras use OpenCV axes, ``a_T_b`` maps frame b to frame a. Volumes are ``[B, C, Z, Y, X]``
    on a cell-centred grid; every ``grid_sample`` uses ``align_corners=False``. Point transforms, rigid
    inversion and yaw matrices are kornia's (``kornia.geometry.linalg``, ``kornia.geometry.conversions``); the
    rest are local ops.
"""

from . import boxes2d, camera, crop, frustum, grid, ground, point_cloud, rotate, unproject
from .boxes2d import *  # noqa: F403
from .camera import *  # noqa: F403
from .crop import *  # noqa: F403
from .frustum import *  # noqa: F403
from .grid import *  # noqa: F403
from .ground import *  # noqa: F403
from .point_cloud import *  # noqa: F403
from .rotate import *  # noqa: F403
from .unproject import *  # noqa: F403

_MODULES = (grid, camera, unproject, crop, rotate, frustum, ground, boxes2d, point_cloud)
__all__ = [name for module in _MODULES for name in module.__all__]
