"""Per-thread CPU priority (Linux): background threads that must not slow the AT loop.

On Linux a thread id is a process id for ``setpriority``, so one thread can be made nicer
than the rest of its process; threads it starts inherit it. Elsewhere, or without
permission, nothing happens.
"""

from __future__ import annotations

import contextlib
import os
import threading

#: The largest niceness.
MAX_NICE = 19

_niced = threading.local()


def lower_thread_priority(nice: int) -> None:
    """Make the calling thread ``nice`` steps nicer (at most :data:`MAX_NICE`)."""
    if nice <= 0 or not hasattr(os, "setpriority"):
        return
    tid = threading.get_native_id()
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, tid, min(os.getpriority(os.PRIO_PROCESS, tid) + nice,
                                                 MAX_NICE))


def lower_thread_priority_once(nice: int) -> None:
    """:func:`lower_thread_priority` the first time a thread calls it (pool threads)."""
    if nice > 0 and not getattr(_niced, "done", False):
        _niced.done = True
        lower_thread_priority(nice)
