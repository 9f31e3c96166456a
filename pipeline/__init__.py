"""seqat pipeline: flight folders, result files, simulation I/O and the ``seqat`` command line.

Laid out by stage, one subpackage each (docs/architecture.md, *Packages*):
:mod:`pipeline.flight` reads a flight folder into :class:`seqat.types.Frame` objects,
:mod:`pipeline.run` streams them through an estimator and writes the results atomically
(:mod:`pipeline.run.store`), then :mod:`pipeline.reference`, :mod:`pipeline.ortho` and
:mod:`pipeline.report` work on the run folder; :mod:`pipeline.simulate` makes flights,
:mod:`pipeline.bench` measures, :mod:`pipeline.cli` is the command line, and
:mod:`pipeline.tracking` and :mod:`pipeline.common` are shared below them. The numerics live
in :mod:`seqat`, which never imports this package.
"""
