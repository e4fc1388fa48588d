"""Replay a video file (anything the installed OpenCV/FFmpeg decodes), frame by frame, no drops."""

from __future__ import annotations

import logging
import struct
import threading
from datetime import datetime
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
from photomap.errors import InputError

from photomap.drivers.frames import CaptureStats, Frame, SourceBase

log = logging.getLogger(__name__)

# Seconds from the QuickTime/MP4 epoch (1904-01-01 UTC) to the Unix epoch.
_MP4_EPOCH_OFFSET = int((datetime(1970, 1, 1) - datetime(1904, 1, 1)).total_seconds())


def mp4_creation_time(path: str | Path) -> float | None:
    """Creation time recorded in an MP4/MOV file's ``moov/mvhd`` box.

    Returns
    -------
    float or None
        Seconds since the Unix epoch (the box stores UTC by the standard; some cameras write
        local time), or None when the file is not MP4/MOV, has no ``mvhd`` or stores 0.
    """
    try:
        with open(path, "rb") as f:
            moov = _find_box(f, b"moov", 0, Path(path).stat().st_size)
            if moov is None:
                return None
            mvhd = _find_box(f, b"mvhd", *moov)
            if mvhd is None:
                return None
            f.seek(mvhd[0])
            head = f.read(12)
    except OSError:
        return None
    if len(head) < 8:
        return None
    version = head[0]
    if version == 1 and len(head) >= 12:
        created = struct.unpack(">Q", head[4:12])[0]
    else:
        created = struct.unpack(">I", head[4:8])[0]
    if created == 0:
        return None
    return float(created - _MP4_EPOCH_OFFSET)


def _find_box(f, kind: bytes, start: int, end: int) -> tuple[int, int] | None:
    """(payload start, payload end) of the first box ``kind`` between byte offsets start..end."""
    pos = start
    while pos + 8 <= end:
        f.seek(pos)
        header = f.read(16)
        if len(header) < 8:
            return None
        size, box = struct.unpack(">I4s", header[:8])
        payload = pos + 8
        if size == 1:  # 64-bit size follows
            if len(header) < 16:
                return None
            size = struct.unpack(">Q", header[8:16])[0]
            payload = pos + 16
        elif size == 0:  # box runs to the end of its parent
            size = end - pos
        if size < payload - pos:
            return None
        if box == kind:
            return payload, min(pos + size, end)
        pos += size
    return None


class VideoFileSource(SourceBase):
    """Frames of a video file in decoding order; never drops.

    ``Frame.t`` is the frame's presentation time in seconds from the start of the file
    (``CAP_PROP_POS_MSEC`` after the read). A frame that fails to decode mid-file is skipped
    and counted in ``stats.corrupt``; it still consumes its index.

    Threads: iterate from one thread at a time (the *reader*). The capture is never released
    while a ``read()`` runs (FFmpeg can deadlock in its slice-thread lock, or crash, when a
    capture is released under a running decode): ``close()`` from any thread (or a signal
    handler) only marks the source closed; the reader releases the capture when its read
    returns, or ``close()`` releases it at once when no read runs. ``close()`` waits at most
    ``close_timeout`` seconds for a running read and never blocks longer: a decoder stuck in
    ``read()`` is abandoned to its (daemon) thread. Iteration is single-use: when it ends (end of
    file, ``close()``, or the iterator is closed or dropped) the capture is released.

    Parameters
    ----------
    path : str or Path
        The video file.
    max_decode_failures : int
        Consecutive failed reads after which the file counts as ended (when the container's
        frame count is unknown or already reached, the first failure ends it).
    close_timeout : float
        Seconds ``close()`` waits for a running read to return.

    Attributes
    ----------
    fps : float or None
        Nominal frame rate from the container (None if unknown).
    frame_count : int or None
        Frame count from the container header (an estimate for some formats; None if unknown).
    size : tuple of int
        ``(width, height)`` in pixels.
    creation_time : float or None
        Recording start in seconds since the Unix epoch, when the container says (MP4/MOV).

    Raises
    ------
    InputError
        The file is missing, or is not a video OpenCV can decode.
    """

    live = False

    def __init__(self, path: str | Path, *, max_decode_failures: int = 25,
                 close_timeout: float = 2.0) -> None:
        self.path = Path(path)
        self.stats = CaptureStats()
        self.max_decode_failures = max_decode_failures
        self.close_timeout = float(close_timeout)
        if not self.path.is_file():
            raise InputError(f"video file not found: {self.path}")
        # RLock: close() may run in a signal handler that interrupted the reader inside the lock
        self._cond = threading.Condition(threading.RLock())
        self._closed = False
        self._busy = False                      # a read() runs (in thread self._reader)
        self._reader: int | None = None
        self._cap: cv2.VideoCapture | None = cv2.VideoCapture(str(self.path))
        if not self._cap.isOpened():
            self._cap.release()
            raise InputError(f"cannot decode {self.path}: not a video file or unsupported codec")
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        count = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.fps: float | None = fps if fps > 0 else None
        self.frame_count: int | None = count if count > 0 else None
        self._index = 0
        self._failures = 0
        self._first = self._next()
        if self._first is None:
            self.close()
            raise InputError(f"cannot decode {self.path}: no frame could be read")
        self.size: tuple[int, int] = (self._first.image.shape[1], self._first.image.shape[0])
        self.creation_time: float | None = mp4_creation_time(self.path)

    @property
    def closed(self) -> bool:
        """True once ``close()`` was called or the iteration ended."""
        return self._closed

    @property
    def released(self) -> bool:
        """True once the capture is released (False while a stuck read still holds it)."""
        return self._cap is None

    def _release(self) -> None:
        """Release the capture; the caller holds the lock and no read runs."""
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()
        self._cond.notify_all()

    def _read(self) -> tuple[bool, np.ndarray | None, float] | None:
        """One ``read()`` and the PTS (s) after it, or None once closed.

        The reader releases the capture itself when ``close()`` came during its read.
        """
        with self._cond:
            cap = self._cap
            if self._closed or cap is None:
                return None
            if self._busy:
                raise RuntimeError(f"{self.path.name}: iterated from two threads at once")
            self._busy, self._reader = True, threading.get_ident()
        try:
            ok, image = cap.read()
            t = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0 if ok else 0.0
        finally:
            with self._cond:
                self._busy = False
                if self._closed:
                    self._release()
                self._cond.notify_all()
        return ok, image, t

    def _next(self) -> Frame | None:
        """Decode the next frame, skipping (and counting) undecodable ones; None at the end."""
        while True:
            got = self._read()
            if got is None:
                return None  # closed
            ok, image, t = got
            if ok and image is not None:
                break
            self._failures += 1
            more_expected = self.frame_count is not None and self._index < self.frame_count
            if not more_expected or self._failures >= self.max_decode_failures:
                return None  # end of file: trailing failures are not counted as corrupt
            self._index += 1
        if self._failures:
            log.warning("%s: %d frame(s) before frame %d could not be decoded, skipped",
                        self.path.name, self._failures, self._index)
            self.stats.corrupt += self._failures
            self._failures = 0
        frame = Frame(index=self._index, t=t, image=image, source=self.path.name)
        self._index += 1
        self.stats.read += 1
        return frame

    def __iter__(self) -> Iterator[Frame]:
        frame, self._first = self._first, None
        try:
            while frame is not None and not self._closed:
                yield frame
                frame = self._next()
        finally:  # in the reading thread: end of file, close(), or the iterator closed/dropped
            self.close()

    def close(self) -> None:
        """End iteration and release the capture (never under a running read; see the class doc).

        Safe from any thread and from a signal handler; waits at most ``close_timeout`` s.
        """
        with self._cond:
            self._closed = True
            if not self._busy:
                self._release()
                return
            if self._reader == threading.get_ident():
                return  # a signal handler interrupted the read: the read releases when it returns
            released = self._cond.wait_for(lambda: self._cap is None, timeout=self.close_timeout)
        if not released:
            log.warning("%s: the decoder did not return within %.1f s; capture left to its thread",
                        self.path.name, self.close_timeout)
