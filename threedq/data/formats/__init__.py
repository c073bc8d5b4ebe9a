"""Readers of on-disk RGB-D capture formats (:data:`~threedq.data.formats.registry.FORMATS`), one module per format.

Each ``read_<format>(folder, ...) -> Capture`` (its expected directory tree in its module docstring) reads one capture
in its own frame; :func:`~threedq.data.formats.importer.import_captures` normalises and writes them as a dataset.
"""

from threedq.data.formats.capture import Capture, CaptureObjects, FrameSkip
from threedq.data.formats.importer import ImportSummary, find_captures, import_captures
from threedq.data.formats.normalise import boxes_to_capture_frame, normalise_capture
from threedq.data.formats.registry import FORMATS

__all__ = ["FORMATS", "Capture", "CaptureObjects", "FrameSkip", "ImportSummary", "boxes_to_capture_frame",
           "find_captures", "import_captures", "normalise_capture"]
