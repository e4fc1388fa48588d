"""Where the pipeline's time goes: per-stage times recorded by the pipeline itself.

:class:`StageTimes` keeps, per stage, the count, the total, the largest time and a histogram of
log-spaced bins (24 per decade from 1 us to 1000 s), so that a run of any length takes the same
small memory and still gives medians and 95th percentiles (to within 5 %). ``run.json``
``timing_ms`` holds :meth:`StageTimes.summary`.

Stages of the pipeline (each time is per frame that went through the stage, in milliseconds):
``decode`` (reading and decoding a frame, in the decode thread of a replay), ``resize`` (telemetry
rectification and the downscale to the working size), ``register`` (tracking: registration and
pose), ``paint`` (the map update), ``loop_closure`` (keyframe bookkeeping, loop detection,
applying corrections and joins), ``map_upkeep`` (swapping re-rendered tiles in, refreshing
preview thumbnails: a few ms at most), ``sinks`` (viewer, status), ``outputs`` (checkpoints:
trajectory, run.json, preview), ``frame`` (the worker's whole time for the frame, checkpoints
included: its maximum is the largest stall of the worker); after the last frame
``final_rerender`` (the last corrections' re-renders, waited for) and ``final_outputs`` (the
whole end of the run: those re-renders and writing every output).
"""

from __future__ import annotations

import math
import threading

import numpy as np

_PER_DECADE = 24
_LO = 1e-6  # seconds
_BINS = 9 * _PER_DECADE + 1  # up to 1000 s


class _Stage:
    __slots__ = ("count", "total", "max", "hist")

    def __init__(self) -> None:
        self.count = 0
        self.total = 0.0
        self.max = 0.0
        self.hist = np.zeros(_BINS, np.int64)


class StageTimes:
    """Times of named stages (seconds in, milliseconds out). Thread-safe."""

    def __init__(self) -> None:
        self._stages: dict[str, _Stage] = {}
        self._lock = threading.Lock()

    def add(self, stage: str, seconds: float) -> None:
        """Record one pass through ``stage`` that took ``seconds``."""
        seconds = max(0.0, float(seconds))
        b = 0 if seconds <= _LO else min(_BINS - 1, int(math.log10(seconds / _LO) * _PER_DECADE) + 1)
        with self._lock:
            s = self._stages.get(stage)
            if s is None:
                s = self._stages[stage] = _Stage()
            s.count += 1
            s.total += seconds
            s.max = max(s.max, seconds)
            s.hist[b] += 1

    def count(self, stage: str) -> int:
        s = self._stages.get(stage)
        return s.count if s is not None else 0

    def max_ms(self, stage: str) -> float:
        s = self._stages.get(stage)
        return 1000.0 * s.max if s is not None else 0.0

    @staticmethod
    def _quantile(hist: np.ndarray, q: float) -> float:
        """Seconds at quantile ``q`` (the geometric centre of the bin it falls in)."""
        cum = np.cumsum(hist)
        b = int(np.searchsorted(cum, q * cum[-1], side="left"))
        if b == 0:
            return _LO / 2
        return _LO * 10 ** ((b - 0.5) / _PER_DECADE)

    def summary(self) -> dict[str, dict[str, float | int]]:
        """Per stage: ``count``, ``total_s``, ``mean``, ``median``, ``p95``, ``max`` (ms)."""
        out = {}
        with self._lock:
            for name, s in self._stages.items():
                if s.count == 0:
                    continue
                out[name] = {"count": s.count, "total_s": round(s.total, 3),
                             "mean": round(1000.0 * s.total / s.count, 3),
                             "median": round(1000.0 * self._quantile(s.hist, 0.5), 3),
                             "p95": round(1000.0 * self._quantile(s.hist, 0.95), 3),
                             "max": round(1000.0 * s.max, 3)}
        return out
