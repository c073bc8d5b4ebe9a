"""Non-learned baselines: the point cloud registration baseline of section 4.2 (:mod:`threedq.baselines.pointcloud`)
and a colour + size descriptor (:mod:`threedq.baselines.descriptor`)."""

from threedq.baselines.descriptor import colour_size_descriptor, descriptor_similarity
from threedq.baselines.pointcloud import PointCloudPrototypes

__all__ = ["PointCloudPrototypes", "colour_size_descriptor", "descriptor_similarity"]
