"""Readers of on-disk RGB-D capture formats, one module per format, each producing the canonical scene record.

A reader (``read_<format>(folder, ...) -> Capture``, the expected directory tree in its module docstring)
reads one capture in its own frame; :func:`~threedq.data.formats.normalise.normalise_capture` makes it a
canonical :class:`~threedq.scene.SceneRecord` (z up, centred, subsampled views, ``canonical_T_capture`` in
``meta``); :func:`~threedq.data.formats.importer.import_captures` writes a dataset folder of them.

Formats (:data:`~threedq.data.formats.registry.FORMATS`): ``tum`` (TUM RGB-D), ``scannet`` (SensReader
export), ``nerfstudio`` (``transforms.json`` with depth), ``replica`` (NICE-SLAM export), ``bigbird`` (raw
turntable captures), ``open3d`` (Kinect / Open3D reconstruction folders), ``rig`` (a recorded multi-camera
rig with a YAML spec, e.g. CARLA).
"""

from threedq.data.formats.capture import Capture, CaptureObjects, FrameSkip
from threedq.data.formats.importer import ImportSummary, find_captures, import_captures
from threedq.data.formats.normalise import boxes_to_capture_frame, normalise_capture
from threedq.data.formats.registry import FORMATS

__all__ = [
    "FORMATS",
    "Capture",
    "CaptureObjects",
    "FrameSkip",
    "ImportSummary",
    "boxes_to_capture_frame",
    "find_captures",
    "import_captures",
    "normalise_capture",
]
