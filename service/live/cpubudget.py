"""A CPU budget shared by threads: at most ``share`` of one core, on average.

The map server's answering threads spend it (:class:`photomap.live.mapserver.MapServer`): however
many clients ask, and however much (a QGIS canvas asking a hundred tiles at a time, a page left
open on every zoom, a hostile client asking for tiles it will never show), the server's answers
take no more of the mapping's cores than the budget. Beyond it an answer waits its turn: it
comes later, it is not refused.

A token bucket in CPU seconds: it holds ``share * burst_s`` when full (a burst of answers, such
as a page's first screen of tiles, goes at once), each answer takes the CPU its thread spent on
it (the thread's own clock), and it fills again at ``share`` CPU seconds per wall second.
"""

from __future__ import annotations

import threading
import time
from typing import Callable

__all__ = ["BURST_S", "MIN_WAIT_S", "CpuBudget"]

BURST_S = 2.0  # wall seconds' worth of the share a full budget holds
MIN_WAIT_S = 0.001  # an answer owing less than this much wall time goes on


class CpuBudget:
    """``share`` of one core for the threads that :meth:`spend` it, with bursts of ``burst_s``
    wall seconds' worth. ``share`` 0: no limit. ``clock``: wall seconds; ``sleep(seconds)``:
    waits (returns True to stop waiting, as ``threading.Event.wait`` does once the server closes).
    """

    def __init__(self, share: float, burst_s: float = BURST_S, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], object] = time.sleep) -> None:
        self.share = float(share)
        self._capacity = self.share * float(burst_s)
        self._tokens = self._capacity
        self._clock, self._sleep = clock, sleep
        self._at = clock()
        self._lock = threading.Lock()
        self.waits = 0  # answers that waited for the budget
        self.spent_s = 0.0  # CPU seconds spent in all

    def _fill(self) -> float:  # under the lock: the tokens now
        now = self._clock()
        self._tokens = min(self._capacity, self._tokens + (now - self._at) * self.share)
        self._at = now
        return self._tokens

    def wait(self) -> None:
        """Return once the budget is not overspent: at once within it, else after the wall time
        it takes to refill what was overspent, and what others overspent meanwhile (``sleep``
        returning True ends the wait early)."""
        if self.share <= 0:
            return
        waited = False
        while True:
            with self._lock:
                owed = -self._fill() / self.share
                if owed < MIN_WAIT_S:  # (a shorter wait would be lost in the clocks' steps)
                    return
                if not waited:
                    self.waits += 1
                waited = True
            if self._sleep(owed):
                return

    def spend(self, cpu_s: float) -> None:
        """Take ``cpu_s`` CPU seconds (what an answer cost its thread) from the budget."""
        if self.share <= 0:
            return
        cpu_s = max(0.0, float(cpu_s))
        with self._lock:
            self._fill()
            self._tokens -= cpu_s
            self.spent_s += cpu_s
