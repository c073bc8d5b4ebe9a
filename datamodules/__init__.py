"""One LightningDataModule per dataset, all reading the canonical scene record (:mod:`threedq.scene`).

Installed as ``threedq.datamodules`` (the folder sits at the top of the repository).
"""
