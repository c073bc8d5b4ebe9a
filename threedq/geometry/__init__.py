"""Geometry core: voxel grids, cameras, unprojection, box crops, yaw rotation, the ground plane and
fused point clouds.

Convention:
    Metres; reference frame R right-handed with z up; yaw counter-clockwise about +z seen from above,
    radians. Cameras use OpenCV axes, ``a_T_b`` maps frame b to frame a. Volumes are ``[B, C, Z, Y, X]``
    on a cell-centred grid; every ``grid_sample`` uses ``align_corners=False``. Point transforms, rigid
    inversion and yaw matrices are kornia's (``kornia.geometry.linalg``, ``kornia.geometry.conversions``); the
    rest are local ops, each docstring says what kornia lacks (``benchmarks/bench_geometry_kornia.py``).
"""

from .boxes2d import *  # noqa: F403
from .boxes2d import __all__ as _boxes2d_all
from .camera import *  # noqa: F403
from .camera import __all__ as _camera_all
from .crop import *  # noqa: F403
from .crop import __all__ as _crop_all
from .frustum import *  # noqa: F403
from .frustum import __all__ as _frustum_all
from .grid import *  # noqa: F403
from .ground import *  # noqa: F403
from .ground import __all__ as _ground_all
from .grid import __all__ as _grid_all
from .point_cloud import *  # noqa: F403
from .point_cloud import __all__ as _point_cloud_all
from .rotate import *  # noqa: F403
from .rotate import __all__ as _rotate_all
from .unproject import *  # noqa: F403
from .unproject import __all__ as _unproject_all

__all__ = [*_grid_all, *_camera_all, *_unproject_all, *_crop_all, *_rotate_all, *_frustum_all, *_ground_all, *_boxes2d_all,
           *_point_cloud_all]
