"""``seqat reference``: the COLMAP bundle adjustment of a run (``OUT/reference/``)."""
