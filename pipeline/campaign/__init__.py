"""Many flights and large mosaics on Dask (``seqat process FLIGHT... --out OUT``, issue 18)."""
