"""Many small files written side by side: a few threads, a bounded queue, errors re-raised.

An output of many small files (the full-resolution map tiles, their world files, web tiles)
encodes each one (PNG encoding releases the GIL) and waits on the file system for each (an fsync
before the rename where the file must be durable on its own; the end-of-run outputs skip it and
sync once, :func:`photomap.io.trajectory_files.sync_filesystem`). :class:`ParallelWrites` runs
such jobs on ``workers`` threads, so that encoding uses every core and the waits overlap
(concurrent fsyncs share a journal commit). At most ``2 * workers`` jobs wait, so memory stays a few
files whatever their number. The first job's error is raised from :meth:`submit` or at the end of
the ``with`` block; after one the remaining jobs are dropped.
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

WORKERS = 4


class ParallelWrites:
    """``with ParallelWrites() as w: w.submit(job, *args)``: ``job(*args)`` on a worker thread."""

    def __init__(self, workers: int = WORKERS) -> None:
        self._workers = max(1, int(workers))
        self._pool = ThreadPoolExecutor(self._workers, "photomap-files")
        self._pending: deque[Future] = deque()

    def submit(self, job: Callable[..., object], *args) -> None:
        """Queue ``job(*args)``; waits while ``2 * workers`` jobs are queued (and raises a finished one's error)."""
        self._pending.append(self._pool.submit(job, *args))
        while len(self._pending) > 2 * self._workers or (self._pending and self._pending[0].done()):
            self._pending.popleft().result()

    def __enter__(self) -> ParallelWrites:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            while self._pending and exc_type is None:
                self._pending.popleft().result()
        finally:
            for f in self._pending:
                f.cancel()
            self._pool.shutdown(wait=True)
