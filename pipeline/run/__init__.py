"""``seqat run`` / ``watch`` / ``feed``: frames through an estimator, results stored atomically.

Session, runner, watch, feed, journal (``--resume``), latency budget, frame sources, the
result files of a run (:mod:`pipeline.run.store`) and their accuracy and robustness records.
"""
