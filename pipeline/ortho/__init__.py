"""``seqat dsm`` / ``ortho`` / ``run --ortho``: DSM, orthorectifier, mosaic, rasters, GIS export.

The orthorectifier (:mod:`pipeline.ortho.orthorectifier`) is built from its footprint,
projection and occlusion parts; :mod:`pipeline.ortho.live` runs it while a flight is
georeferenced.
"""
