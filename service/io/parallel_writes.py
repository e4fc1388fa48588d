"""Many small files written side by side: a few threads, a bounded queue, errors re-raised.

An end-of-run output of many small files (the full-resolution map tiles and their world files)
spends most of its time waiting: each file is fsync-ed before its rename (durable after a power
loss), one journal commit each, and PNG encoding releases the GIL. :class:`ParallelWrites` runs
such jobs on ``workers`` threads, so that the waits overlap (concurrent fsyncs share a journal
commit) and encoding uses every core. At most ``2 * workers`` jobs wait, so memory stays a few
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
