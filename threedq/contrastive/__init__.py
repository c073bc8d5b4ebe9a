"""Momentum contrast (MoCo, He et al. 2020) for correspondence mining (paper Sec. 3.3): streamed InfoNCE, the
key encoder / negative queue module, and the 3D correspondence miner (retrieval, patch matching, verification)."""

from . import infonce, miner, moco
from .infonce import *  # noqa: F403
from .miner import *  # noqa: F403
from .moco import *  # noqa: F403

__all__ = [name for module in (infonce, miner, moco) for name in module.__all__]
