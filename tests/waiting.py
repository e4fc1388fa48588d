"""Waiting in tests for what other threads and processes do (a writer thread, a server, a link):
a deadline for the test, never an assertion on speed."""

from __future__ import annotations

import time
from typing import Callable, TypeVar

T = TypeVar("T")


def wait_until(predicate: Callable[[], T], timeout: float = 10.0, poll: float = 0.02) -> T:
    """Call ``predicate`` every ``poll`` s until it gives something truthy, and return that; at
    the deadline (``timeout`` s, generous: the suite runs on loaded 2-core machines) return what
    one last call gives."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got = predicate()
        if got:
            return got
        time.sleep(poll)
    return predicate()
