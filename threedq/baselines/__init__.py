"""Non-learned baselines of the paper's experiments.

- :mod:`threedq.baselines.pointcloud`: the "point cloud registration" baseline of section 4.2 (objects
  clustered into registered point-set prototypes with a rotation-aware, occupancy-only similarity).
"""

from threedq.baselines.pointcloud import PointCloudPrototypes, occupied_points, rotation_aware_similarity

__all__ = ["PointCloudPrototypes", "occupied_points", "rotation_aware_similarity"]
