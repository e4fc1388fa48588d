"""Keep the process's resident memory flat over a long run (glibc's allocator, Linux).

A run allocates and frees large arrays all the time (frames, warped footprints, tiles, checkpoint
copies) from several threads. glibc's malloc raises its mmap threshold each time such an array
is freed, so later ones come from the heap arenas, where freed memory stays resident and
fragments: a 2500-frame flight measured (tools/bench_memory.py) RSS growing ~17-20 KB a frame
with only ~0.5 KB/frame of live Python objects and a fixed number of map tiles in memory. At most
two arenas, and ``malloc_trim`` every second (:func:`trimmed_heap`: free pages go back to the
system), keep it flat: on the 10,000-frame 1080p flight of ``tools/bench_pipeline.py`` RSS right
after a trim stayed at 270-290 MB from 10 % of the flight on, while with a trim only at each
checkpoint (5 s or more apart) it swung between 300 and 380 MB (the heap's free pages left
resident since the last trim); a trim takes 2-14 ms, in its own thread, between the worker's
frames. Elsewhere (another libc, another OS) these are no-ops.

Python's cyclic garbage collector: a full collection walks every tracked object, ~60,000 of
them after the imports (NumPy, OpenCV, pymavlink, ...), and a run adds few (a row per frame).
Collections while mapping would cost the worker 40-57 ms each (10,000-frame 1080p flight of
``tools/bench_pipeline.py``, 2 cores); :func:`frozen_heap` moves the objects that exist when a
run starts out of the collector's sight for its duration (``gc.freeze``).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import gc
import logging
import sys
import threading
from typing import Callable, Iterator

log = logging.getLogger(__name__)

__all__ = ["TRIM_INTERVAL_S", "frozen_heap", "limit_heap_growth", "release_free_memory", "trimmed_heap"]

TRIM_INTERVAL_S = 1.0  # seconds between two trims of the heap during a run

_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
_libc = None
_applied = False


def _glibc():
    global _libc
    if _libc is None:
        _libc = False
        if sys.platform.startswith("linux"):
            try:
                lib = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
                lib.mallopt  # noqa: B018 (glibc only)
                lib.malloc_trim
                _libc = lib
            except (OSError, AttributeError):
                pass
    return _libc or None


def limit_heap_growth(arenas: int = 2, mmap_threshold: int | None = None) -> bool:
    """At most ``arenas`` malloc arenas and, when given, a fixed mmap threshold (bytes: larger
    arrays are mapped and unmapped; 128 KiB measured twice the worker's time per frame, so it is
    off by default); once per process. Returns whether it applied."""
    global _applied
    libc = _glibc()
    if libc is None or _applied:
        return _applied
    ok = bool(libc.mallopt(_M_ARENA_MAX, int(arenas)))
    if mmap_threshold is not None:
        ok = ok and bool(libc.mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold)))
    _applied = ok
    log.debug("malloc: %d arenas, mmap threshold %s: %s", arenas,
              "malloc's own" if mmap_threshold is None else f"{int(mmap_threshold)} B", "set" if ok else "refused")
    return ok


def release_free_memory() -> None:
    """Give the heap's free memory back to the system (``malloc_trim``); a few milliseconds."""
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)


@contextlib.contextmanager
def trimmed_heap(interval: float = TRIM_INTERVAL_S, wait: Callable[[], None] | None = None) -> Iterator[None]:
    """Inside the block, a thread (``photomap-heap``) gives the heap's free memory back to the
    system every ``interval`` seconds (:func:`release_free_memory`), each time after ``wait()``
    (e.g. :meth:`photomap.mapping.threads.WorkerFirst.wait`: between the worker's frames, whose
    allocations would wait for the trim). No thread without glibc."""
    if _glibc() is None or interval <= 0:
        yield
        return
    stop = threading.Event()

    def trim() -> None:
        while not stop.wait(interval):
            if wait is not None:
                wait()
            release_free_memory()

    thread = threading.Thread(target=trim, name="photomap-heap", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


@contextlib.contextmanager
def frozen_heap() -> Iterator[None]:
    """Inside the block, the garbage collector leaves alone the objects that existed before it
    (collected once first; ``gc.freeze``, undone after)."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()
