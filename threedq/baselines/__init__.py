"""Non-learned baselines of the paper's experiments.

- :mod:`threedq.baselines.pointcloud`: the "point cloud registration" baseline of section 4.2 (objects
  clustered into registered point-set prototypes with a rotation-aware, occupancy-only similarity).
- :mod:`threedq.baselines.descriptor`: a six-number colour + size descriptor (a reference row of Table 2).
"""

from threedq.baselines.descriptor import colour_size_descriptor, descriptor_similarity
from threedq.baselines.pointcloud import PointCloudPrototypes

__all__ = [
    "PointCloudPrototypes",
    "colour_size_descriptor",
    "descriptor_similarity",
]
