"""``seqat bench``: every benchmark (docs/benchmarks.md), each reachable through ``seqat bench``.

strip (simulated strips, Seq-R / Seq-F / Sim), flight (an image flight), long (memory and
time along a long strip), rendered (products of a rendered flight against truth), ortho
(timing of the ortho stage), gtsam (GTSAM's fixed-lag smoother beside Seq-R; optional
package gtsam), faults/ (seeded blunders, GNSS jump, dropout); report and
common hold what they share.
"""
