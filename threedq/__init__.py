"""threedq: 3DQ-Nets — detect, cluster into pose-canonical 3D prototypes and pose objects in posed RGB-D scenes, without labels."""

__version__ = "0.2.0"
