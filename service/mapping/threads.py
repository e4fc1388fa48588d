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
The end-of-run outputs, with no worker left to wait for, go back to Python's 5 ms
(:data:`OUTPUTS_SWITCH_INTERVAL_S`): there half a dozen threads (the map's PNG bands and their
encoder, the GeoTIFF, the tile writers) each hold the GIL briefly, and at 0.2 ms their hand-overs
cost more CPU than they save (measured on the 57-still survey of ``tools/bench_survey.py``).
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from typing import Callable, Iterable, Iterator, TypeVar

__all__ = ["SWITCH_INTERVAL_S", "OUTPUTS_SWITCH_INTERVAL_S", "BACKGROUND_NICE", "WorkerFirst", "lower_priority", "switch_interval"]

T = TypeVar("T")

SWITCH_INTERVAL_S = 0.0002  # seconds, while the worker maps
OUTPUTS_SWITCH_INTERVAL_S = 0.005  # Python's default, for the end-of-run outputs (see below)
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


class WorkerFirst:
    """The worker's frames before the background threads' Python code.

    The worker maps each frame inside ``with first.frame():``. A background thread calls
    :meth:`wait` between the steps of its work (a kept frame of a re-render strip, a loop
    registration, an iteration of a pose-graph solve, a few hundred trajectory rows): it returns
    at once while the worker is between frames (reading the camera), else when the worker's
    frame is done, or after ``max_wait_s`` (a worker that is never between frames cannot starve
    the background; its work then goes on slowly). The background's C calls (warps, FFTs, PNG
    encoding, sparse solves) run on regardless; what waits is its Python code, which holds the
    interpreter between them: each time the worker takes the GIL back from a thread running
    Python, it waits up to a switch interval, and a frame does hundreds of such take-backs
    (300 small OpenCV calls: 0.7 ms alone, 14 ms beside one Python-busy thread, 80-110 ms beside
    two at a 1 ms interval). With ``enabled=False`` (a replay: no frame deadline, throughput
    first) :meth:`wait` returns at once; so does a wait in the worker's own thread (background
    work it does itself when a background thread is behind). The worker must not block on a
    background job inside :meth:`frame` (the job would wait at each pause point): it waits for
    them at the end of the run, or in a replay, whose gate is disabled.
    """

    def __init__(self, enabled: bool = True, max_wait_s: float = 0.1) -> None:
        self.enabled = enabled
        self.max_wait_s = max_wait_s
        self._between = threading.Event()  # set while the worker is between frames
        self._between.set()
        self._worker: int | None = None  # thread id of the worker (the last to enter frame())

    @contextlib.contextmanager
    def frame(self) -> Iterator[None]:
        """The worker maps a frame inside this block."""
        self._worker = threading.get_ident()
        self._between.clear()
        try:
            yield
        finally:
            self._between.set()

    def wait(self) -> None:
        """A background thread's pause point (see the class docstring); no wait when disabled."""
        if self.enabled and not self._between.is_set() and threading.get_ident() != self._worker:
            self._between.wait(self.max_wait_s)

    def paced(self, items: Iterable[T], every: int = 256) -> Iterable[T]:
        """A view of ``items`` that calls :meth:`wait` before each ``every`` of them, each time it is
        iterated (as often as ``items`` can be)."""
        return _Paced(items, self.wait, every)


class _Paced(Iterable[T]):
    """See :meth:`WorkerFirst.paced`."""

    def __init__(self, items: Iterable[T], wait: Callable[[], None], every: int) -> None:
        self._items, self._wait, self._every = items, wait, max(1, int(every))

    def __iter__(self) -> Iterator[T]:
        for i, item in enumerate(self._items):
            if i % self._every == 0:
                self._wait()
            yield item
