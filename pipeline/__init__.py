"""seqat pipeline: flight folders, result files, simulation I/O and the ``seqat`` command line.

One module per stage (DESIGN.md): :mod:`pipeline.flight.folder` reads a flight folder into
:class:`seqat.types.Frame` objects, :mod:`pipeline.run.runner` streams them through an estimator,
:mod:`pipeline.run.store` writes the results atomically, :mod:`pipeline.cli` is the command line.
The numerics live in :mod:`seqat`, which never imports this package.
"""
