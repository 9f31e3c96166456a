"""A live watch reads and detects the next images while the current one is adjusted.

At 2 Hz a watch's serial work per image is reading, tracking, the AT update and the
publication of the live estimates; on the 196-image rendered block it exceeded the 500 ms
period and the latency grew along the flight (docs/benchmarks.md). Reading an image and
detecting its features need nothing of the tracker's or the estimator's state
(:meth:`pipeline.run.sources.ImageSource.read_ahead`), so :class:`ReadAhead` does them for
the next images in one thread, with its own detector: OpenCV's JPEG decode and SIFT release
the GIL and run on the second core. Matching, resection and the update stay in turn, so the
result is the same as without it.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

from pipeline.run.sources import ImageSource, ReadImage

#: Images read ahead of the one being adjusted (each holds its gray image until its turn).
READ_AHEAD_IMAGES = 2


class ReadAhead:
    """Reads and detects images of ``source`` ahead, in the order :meth:`schedule` gives."""

    def __init__(self, source: ImageSource, depth: int = READ_AHEAD_IMAGES) -> None:
        self._source = source
        self._depth = depth
        self._detector = source.detector()  # used by the worker thread only
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="seqat-read-ahead")
        self._pending: dict[Path, Future[ReadImage]] = {}

    def schedule(self, paths: Sequence[Path]) -> None:
        """Start reading the first ``depth`` of ``paths`` (the next images, in order) that
        are not read or being read yet."""
        for path in paths[: self._depth]:
            if path not in self._pending:
                self._pending[path] = self._pool.submit(self._source.read_ahead, path,
                                                        self._detector)

    def take(self, path: Path) -> ReadImage | None:
        """The image read ahead (waiting for it), or None if it was not scheduled."""
        future = self._pending.pop(path, None)
        return None if future is None else future.result()

    def close(self) -> None:
        """Drop what was read ahead and not taken; stop the thread."""
        for future in self._pending.values():
            future.cancel()
        self._pending.clear()
        self._pool.shutdown(wait=True)
