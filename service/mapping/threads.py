"""How the mapping's threads share the CPU and the interpreter (Linux per-thread nice values; the
GIL's switch interval).

The worker releases the GIL in every NumPy and OpenCV call and takes it back after. Beside threads
that run Python code (the pose-graph optimiser, the re-render and checkpoint threads), each
take-back waits until the holder lets go: after the interpreter's switch interval at worst, 5 ms
by default. A checkpoint does dozens of such calls; on the 10,000-frame 1080p flight of
``tools/bench_pipeline.py`` (2 cores) its worker time went from 71 / 183 ms (median / max) to
44 / 110 ms with the interval at 1 ms (and the checkpoint writer at low priority, since given
back its normal one: starved on a loaded computer it wrote no checkpoint before a small disk
filled, and the map was lost). Pure Python work of the worker is shared the same way: beside two
Python-busy threads a 5 ms loop over the rows takes 15 ms or more. With the interval at 0.2 ms
the same flight's worst frames went from 164 to 112 ms (99.9th percentile 98 -> 74 ms), the
median frame unchanged. A run sets :data:`SWITCH_INTERVAL_S` for its duration
(:func:`switch_interval`); the threads whose work can wait (trajectory writer, re-renders,
loop registrations, pose-graph solves) lower their own priority (:func:`lower_priority`).
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from typing import Iterator

__all__ = ["SWITCH_INTERVAL_S", "BACKGROUND_NICE", "lower_priority", "switch_interval"]

SWITCH_INTERVAL_S = 0.0002  # seconds (Python's default: 0.005)
BACKGROUND_NICE = 10  # added to the nice value of threads whose work can wait


def lower_priority(nice: int = BACKGROUND_NICE) -> None:
    """Raise the calling thread's nice value by ``nice`` (Linux: per thread); no error elsewhere."""
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))
    except (AttributeError, OSError):
        pass


@contextlib.contextmanager
def switch_interval(seconds: float = SWITCH_INTERVAL_S) -> Iterator[None]:
    """The interpreter's switch interval set to ``seconds`` inside the block (restored after)."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    try:
        yield
    finally:
        sys.setswitchinterval(old)
