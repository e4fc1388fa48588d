"""Live camera (V4L2, or a network stream through :mod:`photomap.drivers.stream`): a capture thread, a
drop-oldest queue and reconnection with back-off."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import Any, Callable, Iterator

import cv2

from photomap.errors import InputError

from photomap.drivers.frames import CaptureStats, Frame, SourceBase

log = logging.getLogger(__name__)

# Pixel formats that OpenCV hands over as they are (CAP_PROP_CONVERT_RGB off): 16-bit and 8-bit gray.
RAW_FORMATS = {"Y16 ": "uint16 gray", "GREY": "uint8 gray"}


def normalize_fourcc(fourcc: str) -> str:
    """A V4L2 pixel format as its 4-character code: ``"Y16"`` -> ``"Y16 "``, ``"mjpg"`` -> ``"MJPG"``."""
    code = fourcc.strip().upper()
    if not 1 <= len(code) <= 4:
        raise InputError(f"camera fourcc must have 1 to 4 characters, got {fourcc!r}")
    return code.ljust(4)


def fourcc_text(value: float) -> str:
    """The 4-character code of a ``CAP_PROP_FOURCC`` value ("" when there is none)."""
    code = int(value) if value and value > 0 else 0
    text = "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))
    return text.strip() if code and text.isprintable() else ""


def open_v4l2(device: str | int) -> cv2.VideoCapture:
    """The default capture factory: ``cv2.VideoCapture(device, cv2.CAP_V4L2)``."""
    return cv2.VideoCapture(device, cv2.CAP_V4L2)


def backoff_delays(initial: float, maximum: float) -> Iterator[float]:
    """Exponential back-off: ``initial, 2*initial, 4*initial, ...`` capped at ``maximum`` (seconds)."""
    delay = initial
    while True:
        yield min(delay, maximum)
        delay = min(delay * 2.0, maximum)


class CameraSource(SourceBase):
    """Frames of a live camera, read by a background thread into a bounded queue.

    When the consumer falls behind, the oldest queued frame is discarded (counted in
    ``stats.dropped``), so what the consumer gets is never more than ``queue_size`` frames
    old. ``Frame.t`` is ``clock()`` (default ``time.monotonic``) right after the read returned.
    Every frame read gets the next ``index``, dropped ones included.

    When ``read_failures`` reads in a row fail (camera unplugged), the loss is logged once,
    the capture is released and reopened with exponential back-off between
    ``reconnect_initial`` and ``reconnect_max`` seconds until it works again or ``close()``
    is called; the first frame after that counts in ``stats.reconnects``. The back-off only
    resets once a frame arrives. The consumer just sees a gap in ``t`` (no frames meanwhile).

    Threads: the capture thread owns the capture (handed the first one, opening the later
    ones): it alone reads and releases it, when it ends. ``close()`` only signals and waits at
    most ``join_timeout`` s for the thread; a driver stuck in ``read()`` keeps its (daemon)
    thread and capture, never the process. Every wait is bounded.

    Parameters
    ----------
    device : str or int
        ``/dev/videoN`` or the index N.
    width, height : int, optional
        Requested frame size in pixels (None: the camera's default).
    fps : float, optional
        Requested frame rate (None: the camera's default).
    fourcc : str, optional
        Requested pixel format: ``"MJPG"`` or ``"YUYV"`` (decoded to uint8 BGR), ``"GREY"`` (uint8
        ``HxW``), ``"Y16"`` (uint16 ``HxW``, the raw values: thermal cores), or another code the
        driver offers (None: the camera's default). What was asked for and what the camera delivers
        (size, format, rate, frame type) is logged once, at the first frame.
    queue_size : int
        Frames held for the consumer before the oldest is dropped.
    read_failures : int
        Consecutive failed reads after which the camera counts as lost.
    reconnect_initial, reconnect_max : float
        First and largest delay (seconds) between reopening attempts.
    capture_factory : callable, optional
        ``factory(device)`` returning an object with ``isOpened()``, ``read()``, ``set()``,
        ``release()`` like ``cv2.VideoCapture`` (default :func:`open_v4l2`; tests pass a fake).
    clock : callable
        Time stamp source for ``Frame.t`` (seconds).
    join_timeout : float
        Seconds ``close()`` waits for the capture thread (a read blocked in the driver).
    loss : str, optional
        How a loss is told in the log (default: after ``read_failures`` failed reads).
    notes : callable, optional
        ``notes()`` returns a clause appended to the lines logged at the first frame, at each loss
        and recovery and at the end (a stream's decoder messages since the last line).
    unavailable : str
        Why the device may not open, for the error raised at start.

    Raises
    ------
    InputError
        The device cannot be opened at start.
    """

    live = True

    def __init__(
        self,
        device: str | int,
        *,
        width: int | None = None,
        height: int | None = None,
        fps: float | None = None,
        fourcc: str | None = None,
        queue_size: int = 4,
        read_failures: int = 5,
        reconnect_initial: float = 0.5,
        reconnect_max: float = 8.0,
        capture_factory: Callable[[str | int], Any] | None = None,
        clock: Callable[[], float] = time.monotonic,
        join_timeout: float = 2.0,
        loss: str | None = None,
        notes: Callable[[], str] | None = None,
        unavailable: str = "no such device, or it is busy",
    ) -> None:
        if queue_size < 1:
            raise InputError(f"camera queue size must be at least 1, got {queue_size}")
        fourcc = normalize_fourcc(fourcc) if fourcc else None
        self.device = device
        self.stats = CaptureStats()
        self._asked = (width, height, fourcc, fps)
        self._props = [
            (cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*fourcc) if fourcc else None),
            (cv2.CAP_PROP_FRAME_WIDTH, width),
            (cv2.CAP_PROP_FRAME_HEIGHT, height),
            (cv2.CAP_PROP_FPS, fps),
            (cv2.CAP_PROP_CONVERT_RGB, 0 if fourcc in RAW_FORMATS else None),
        ]
        self._loss = loss or f"after {max(1, read_failures)} failed reads"
        self._notes = notes or (lambda: "")
        self._read_failures = max(1, read_failures)
        self._reconnect = (reconnect_initial, reconnect_max)
        self._factory = capture_factory or open_v4l2
        self._clock = clock
        self._join_timeout = join_timeout
        self._name = str(device)
        self._queue: deque[Frame] = deque()
        self._queue_size = queue_size
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._error: Exception | None = None
        self._cap: Any | None = self._open()
        if self._cap is None:
            raise InputError(f"cannot open camera {device}: {unavailable}{self._notes()}")
        self._thread = threading.Thread(target=self._run, name=f"capture {device}", daemon=True)
        self._thread.start()

    @property
    def closed(self) -> bool:
        """True once ``close()`` was called (or the capture thread ended on an error)."""
        return self._stop.is_set()

    def _open(self) -> Any | None:
        """A new opened capture with the requested properties, or None."""
        cap = self._factory(self.device)
        if not cap.isOpened():
            cap.release()
            return None
        for prop, value in self._props:
            if value is not None and not cap.set(prop, value):
                log.warning("camera %s: could not set property %d to %s", self._name, prop, value)
        return cap

    def _run(self) -> None:
        index = 0
        failures = 0
        outage: Iterator[float] | None = None  # back-off delays while the camera is lost
        try:
            while not self._stop.is_set():
                if self._cap is None:  # stopped while reopening
                    break
                ok, image = self._cap.read()
                t = self._clock()
                if self._stop.is_set():
                    break
                if ok and image is not None:
                    if index == 0:
                        self._log_delivered(image)
                    if outage is not None:
                        outage = None
                        self.stats.reconnects += 1
                        log.warning("camera %s is back%s", self._name, self._notes())
                    failures = 0
                    self._push(Frame(index=index, t=t, image=image, source=self._name))
                    index += 1
                    continue
                failures += 1
                if failures >= self._read_failures:
                    failures = 0
                    if outage is None:
                        log.warning("camera %s lost %s: reconnecting%s", self._name, self._loss,
                                    self._notes())
                        outage = backoff_delays(*self._reconnect)
                    self._reopen(outage)
        except Exception as exc:  # surfaced to the consumer by __iter__
            self._error = exc
        finally:
            with self._cond:
                self._stop.set()
                self._cond.notify_all()
            self._release()  # the reading thread releases its capture, never another thread
            notes = self._notes()
            if notes:
                log.info("camera %s closed%s", self._name, notes)

    def _log_delivered(self, image: Any) -> None:
        """Log, once, what was asked for and what the camera delivers."""
        get = getattr(self._cap, "get", None)
        width, height, fourcc, fps = self._asked

        def prop(p: int) -> float:
            try:
                return float(get(p)) if get is not None else 0.0
            except Exception:  # a driver that cannot tell
                return 0.0

        got_fourcc = fourcc_text(prop(cv2.CAP_PROP_FOURCC))
        got_fps = prop(cv2.CAP_PROP_FPS)
        kind = f"{image.dtype} {'BGR' if image.ndim == 3 else 'gray'} {image.shape[1]}x{image.shape[0]}"
        delivered = " ".join(x for x in (got_fourcc, f"at {got_fps:g} fps" if got_fps > 0 else "") if x)
        asked = " ".join(x for x in (f"{width or '-'}x{height or '-'}" if width or height else "",
                                     (fourcc or "").strip(), f"at {fps:g} fps" if fps else "") if x)
        log.info("camera %s: %sdelivers %s%s%s", self._name, f"asked for {asked}, " if asked else "",
                 kind, f" ({delivered})" if delivered else "", self._notes())
        if fourcc and got_fourcc and got_fourcc != fourcc.strip():
            log.warning("camera %s delivers %s, not the %s asked for", self._name, got_fourcc, fourcc.strip())
        if (width and image.shape[1] != width) or (height and image.shape[0] != height):
            log.warning("camera %s delivers %dx%d, not the %sx%s asked for", self._name, image.shape[1],
                        image.shape[0], width or "-", height or "-")

    def _push(self, frame: Frame) -> None:
        with self._cond:
            self.stats.read += 1
            if len(self._queue) >= self._queue_size:
                self._queue.popleft()
                self.stats.dropped += 1
            self._queue.append(frame)
            self._cond.notify()

    def _reopen(self, delays: Iterator[float]) -> None:
        """Release the capture and reopen it after the next delays, until it opens or close().

        The back-off continues over ``delays`` (shared by the whole outage), so a camera that
        opens but still delivers nothing is retried less and less often.
        """
        self._release()
        for delay in delays:
            if self._stop.wait(delay):
                return
            cap = self._open()
            if cap is not None:
                self._cap = cap
                return
            log.debug("camera %s: reopening failed", self._name)

    def _release(self) -> None:
        """Release the current capture (capture thread only; idempotent)."""
        cap, self._cap = self._cap, None
        if cap is not None:
            try:
                cap.release()
            except Exception as exc:  # a failing driver must not stop the thread's cleanup
                log.warning("camera %s: release failed: %s", self._name, exc)

    def __iter__(self) -> Iterator[Frame]:
        while True:
            with self._cond:
                while not self._queue and not self._stop.is_set():
                    self._cond.wait(0.5)  # bounded: notify is the fast path, not the only one
                if not self._queue:
                    break
                frame = self._queue.popleft()
            yield frame
        if self._error is not None:
            raise self._error

    def close(self) -> None:
        """Stop the capture thread (it releases the camera); pending frames are discarded.

        Only signals and waits at most ``join_timeout`` s; safe from any thread.
        """
        with self._cond:
            self._stop.set()
            self._queue.clear()
            self._cond.notify_all()
        if self._thread is not threading.current_thread():
            self._thread.join(self._join_timeout)
        if self._thread.is_alive():
            log.warning("camera %s: capture thread did not stop within %.1f s; left to exit "
                        "with the process", self._name, self._join_timeout)
