"""One exception tree for seqat and the pipeline built on it (STYLE.md §6)."""

from __future__ import annotations


class SeqatError(Exception):
    """Base class of every error seqat raises on purpose."""


class ConfigError(SeqatError):
    """A configuration file or option is invalid (names the file, key and value)."""


class InputDataError(SeqatError, OSError):
    """An input data file is unreadable or malformed (names the file, line and field)."""


class EstimationError(SeqatError):
    """An adjustment cannot be computed (singular system, degenerate geometry).

    The message carries the numbers (matrix order, eigenvalues, iteration).
    """
