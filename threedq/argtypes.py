"""Number types of stage and DataModule arguments that jsonargparse validates (one type per restriction)."""

from __future__ import annotations

from jsonargparse.typing import restricted_number_type

__all__ = ["Cosine", "OccupancyFloor", "UnitIoU"]

#: an IoU or fraction threshold, a number in (0, 1]
UnitIoU = restricted_number_type("UnitIoU", float, [(">", 0), ("<=", 1)], docstring="a number in (0, 1]")
#: a cosine threshold, a number in [-1, 1]
Cosine = restricted_number_type("Cosine", float, [(">=", -1), ("<=", 1)], docstring="a number in [-1, 1]")
#: the weight of empty space in an occupancy-weighted crop, a number in [0, 1)
OccupancyFloor = restricted_number_type("OccupancyFloor", float, [(">=", 0), ("<", 1)], docstring="a number in [0, 1)")
