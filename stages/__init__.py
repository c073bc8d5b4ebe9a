"""The stages of 3DQ-Nets, one LightningModule each, all sharing the encoder of :mod:`threedq.stages.base`.

Installed as ``threedq.stages`` (the folder sits at the top of the repository).
"""
