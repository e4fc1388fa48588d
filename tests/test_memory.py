"""The heap keeper: free memory goes back to the system during a run (glibc, Linux)."""

from __future__ import annotations

import os
import sys
import threading

import pytest

import logging

from photomap.mapping import memory
from photomap.mapping.memory import _glibc, limit_heap_growth, trimmed_heap
from photomap.mapping.threads import WorkerFirst

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux") or _glibc() is None,
                                reason="malloc_trim is glibc's (Linux)")


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def test_freed_heap_memory_goes_back_between_the_workers_frames():
    # 160 MB in 64 KB blocks (below malloc's mmap threshold: from the heap), a block kept every
    # 1000 so that freeing the rest leaves free memory inside the heap, resident until trimmed
    blocks = [bytearray(b"x" * 65536) for _ in range(2560)]
    kept = blocks[::1000]
    high = rss_mb()
    del blocks
    freed = rss_mb()
    assert freed > high - 40, "the allocator gave the blocks back by itself: nothing to test"
    first = WorkerFirst(enabled=True, max_wait_s=60.0)
    waited = threading.Event()

    def wait() -> None:
        waited.set()
        first.wait()

    frame = first.frame()
    frame.__enter__()  # the worker maps a frame: the keeper waits for its end to trim
    with trimmed_heap(interval=0.02, wait=wait):
        assert waited.wait(10.0)
        assert rss_mb() > high - 40
        frame.__exit__(None, None, None)
        for _ in range(500):  # the frame is done: trimmed within the next interval
            if rss_mb() < freed - 100:
                break
            threading.Event().wait(0.01)
        assert rss_mb() < freed - 100
    assert len(kept) == 3


def test_the_heap_limit_is_said_in_one_debug_line(monkeypatch, caplog):
    """``-v`` logs the malloc settings as a run applies them (no mmap threshold): the line
    formats (a None given to ``%d`` was a logging traceback on stderr)."""
    monkeypatch.setattr(memory, "_applied", False)  # once per process: as if not applied yet
    with caplog.at_level(logging.DEBUG, logger="photomap.mapping.memory"):
        assert limit_heap_growth()
    lines = [r.getMessage() for r in caplog.records if r.name == "photomap.mapping.memory"]
    assert lines == ["malloc: 2 arenas, mmap threshold malloc's own: set"]
