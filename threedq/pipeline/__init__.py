"""The pipeline layer: the LightningCLI subclass, ``threedq em``, evaluations, reports and caches.

It imports the stages and DataModules; nothing below it (core, stages, datamodules) imports it.
"""
