"""Short lists in one-line messages: the first few items, then how many more."""

from __future__ import annotations

from collections.abc import Sequence

#: Items a one-line message names before it counts the rest.
MAX_NAMED = 5


def first_few(items: Sequence[str], limit: int = MAX_NAMED, sep: str = ", ") -> str:
    """The first ``limit`` of ``items`` joined by ``sep``, then ``and N more``.

    A comma list reads ``a, b and 3 more``; a list of sentences (``sep="; "``, each may hold
    commas) reads ``a: why; b: why; and 3 more``.
    """
    shown = sep.join(items[:limit])
    rest = len(items) - limit
    if rest <= 0:
        return shown
    return f"{shown}{' ' if sep == ', ' else sep}and {rest} more"
