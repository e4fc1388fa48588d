"""Network video (RTSP, MPEG-TS over UDP/TCP, RTP by an .sdp file, HTTP MJPEG, a GStreamer pipeline)
as captures for :class:`~photomap.drivers.camera.CameraSource`.

A stream is read by OpenCV's FFmpeg backend (``cv2.CAP_FFMPEG``) with low-latency options (no input
buffering, low-delay decoding, a small probe) passed through ``OPENCV_FFMPEG_CAPTURE_OPTIONS``, and
with bounded waits: opening gives up after ``open_timeout`` s and a read after ``read_timeout`` s
without a frame (``CAP_PROP_OPEN_TIMEOUT_MSEC``/``CAP_PROP_READ_TIMEOUT_MSEC``). A read that fails at
once (the decoder still waits for a key frame) is retried inside :meth:`StreamCapture.read`, so a
failed read always means ``read_timeout`` s of silence: the source counts as lost then, and
:class:`CameraSource` reopens it with its back-off, stamps frames at arrival and drops the oldest,
exactly as for a V4L2 camera.

FFmpeg's decoder messages never reach the terminal: while a stream is open they are counted
(:mod:`photomap.drivers.native_log`) and :meth:`StreamOpener.notes` summarises them in the one line
logged per loss and recovery.
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import cv2
import numpy as np

from photomap.drivers import native_log
from photomap.errors import InputError

log = logging.getLogger(__name__)

STREAM_SCHEMES = ("rtsp", "rtsps", "udp", "rtp", "tcp", "http", "https", "srt")
# What every stream gets: no input buffer, low-delay decoding, a small probe (one key frame).
LOW_LATENCY = {"fflags": "nobuffer", "flags": "low_delay", "probesize": "32768", "analyzeduration": "0"}
_SCHEME = re.compile(r"^([a-zA-Z][a-zA-Z0-9+.\-]*)://")
_OPTIONS_ENV = "OPENCV_FFMPEG_CAPTURE_OPTIONS"
_env_lock = threading.Lock()  # the options variable is read by the open it is set for
_RETRY_PAUSE = 0.005  # s between reads that failed at once (no busy loop while a decoder waits)


def is_gstreamer_pipeline(spec: str) -> bool:
    """True for a gst-launch style pipeline (``udpsrc port=5600 ! ... ! appsink``)."""
    return " ! " in spec or spec.startswith("gst:")


def is_stream(spec: object) -> bool:
    """True when ``spec`` names a network stream, an .sdp file or a GStreamer pipeline."""
    if not isinstance(spec, (str, Path)):
        return False
    text = str(spec).strip()
    m = _SCHEME.match(text)
    if m:
        return m.group(1).lower() in STREAM_SCHEMES
    return text.lower().endswith(".sdp") or is_gstreamer_pipeline(text)


def has_gstreamer() -> bool:
    """Whether the installed OpenCV was built with GStreamer (``cv2.getBuildInformation()``)."""
    m = re.search(r"^\s*GStreamer:\s*(\S+)", cv2.getBuildInformation(), re.MULTILINE)
    return bool(m) and m.group(1).upper() != "NO"


def ffmpeg_options(url: str, *, rtsp_transport: str = "udp") -> tuple[str, dict[str, str]]:
    """The URL to open and the FFmpeg options for it.

    ``rtsp://...?tcp`` (or ``?transport=tcp``) asks for RTSP interleaved over the TCP connection,
    as ``rtsp_transport="tcp"`` does; the marker is removed from the URL. An .sdp file gets the
    protocol whitelist that FFmpeg needs to follow it to RTP on UDP.
    """
    options = dict(LOW_LATENCY)
    m = _SCHEME.match(url)
    scheme = m.group(1).lower() if m else ""
    if scheme in ("rtsp", "rtsps"):
        parts = urlsplit(url)
        query = parse_qsl(parts.query, keep_blank_values=True)
        transport = rtsp_transport
        kept = []
        for key, value in query:
            if key.lower() == "tcp" and not value:
                transport = "tcp"
            elif key.lower() == "udp" and not value:
                transport = "udp"
            elif key.lower() == "transport" and value.lower() in ("tcp", "udp"):
                transport = value.lower()
            else:
                kept.append((key, value))
        url = urlunsplit(parts._replace(query=urlencode(kept)))
        options["rtsp_transport"] = transport
        if transport == "udp":
            options["reorder_queue_size"] = "0"  # hand packets on as they come (no jitter buffer)
    elif scheme == "udp":
        # 1 MB in the socket (the kernel caps it at net.core.rmem_max) and 1 MB in FFmpeg's FIFO
        # (5576 TS packets; its default is 5.4 MB): room for the bursts of key frames, while a
        # receiver starved of CPU reads stream data at most about 2 s old at 8 Mbit/s (measured:
        # 4 MB held the p95 arrival at 3.9 s). A full FIFO loses packets, not the stream.
        options["buffer_size"] = "1048576"
        options["fifo_size"] = "5576"
        options["overrun_nonfatal"] = "1"
    elif not scheme and url.lower().endswith(".sdp"):
        options["protocol_whitelist"] = "file,udp,rtp,crypto,data"
        options["reorder_queue_size"] = "0"
    return url, options


class StreamCapture:
    """A ``cv2.VideoCapture`` of a stream whose failed read means ``read_timeout`` s of silence.

    The ``isOpened``/``read``/``set``/``get``/``release`` interface of ``cv2.VideoCapture``, as
    :class:`~photomap.drivers.camera.CameraSource` expects. Frames are what the backend decodes:
    uint8 BGR.
    """

    def __init__(self, cap: Any, *, read_timeout: float, clock: Callable[[], float] = time.monotonic,
                 on_release: Callable[[], None] | None = None) -> None:
        self._cap = cap
        self._timeout = read_timeout
        self._clock = clock
        self._last = clock()  # the last frame, or the opening
        self._on_release = on_release

    def isOpened(self) -> bool:
        return self._cap is not None and self._cap.isOpened()

    def read(self) -> tuple[bool, np.ndarray | None]:
        while self._cap is not None:
            ok, image = self._cap.read()
            now = self._clock()
            if ok and image is not None:
                self._last = now
                return True, image
            if now - self._last >= self._timeout:
                return False, None
            time.sleep(_RETRY_PAUSE)
        return False, None

    def set(self, prop: int, value: float) -> bool:
        return self._cap is not None and bool(self._cap.set(prop, value))

    def get(self, prop: int) -> float:
        return float(self._cap.get(prop)) if self._cap is not None else 0.0

    def release(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            try:
                cap.release()
            finally:
                if self._on_release is not None:
                    self._on_release()


class StreamOpener:
    """Opens one stream, again after every loss: the capture factory of a stream's CameraSource.

    Parameters
    ----------
    spec : str
        The URL, .sdp file or GStreamer pipeline (``gst:`` prefix optional).
    open_timeout, read_timeout : float
        Seconds an opening, and reading without a frame, may take.
    rtsp_transport : str
        ``"udp"`` or ``"tcp"`` (interleaved) for rtsp:// without a ``?tcp`` marker.
    decoder_threads : int
        FFmpeg decoder threads (``CAP_PROP_N_THREADS``); 0 lets FFmpeg take one per core, and each
        thread beyond the first holds back a frame (33 ms at 30 fps).
    quiet_decoder : bool
        Count the native decoder messages instead of letting them reach stderr.
    video_capture : callable
        ``video_capture(url, api, params)`` (default ``cv2.VideoCapture``; tests pass a fake).

    Raises
    ------
    InputError
        A GStreamer pipeline, and this OpenCV has no GStreamer.
    """

    def __init__(self, spec: str, *, open_timeout: float = 5.0, read_timeout: float = 2.0,
                 rtsp_transport: str = "udp", decoder_threads: int = 1, quiet_decoder: bool = True,
                 video_capture: Callable[..., Any] = cv2.VideoCapture) -> None:
        self.spec = str(spec).strip()
        self._open_timeout = open_timeout
        self._read_timeout = read_timeout
        self._threads = decoder_threads
        self._video_capture = video_capture
        self._quiet = quiet_decoder
        self._counts: Counter = Counter()
        self._counts_lock = threading.Lock()
        self.gstreamer = is_gstreamer_pipeline(self.spec)
        if self.gstreamer:
            if not has_gstreamer():
                raise InputError("a GStreamer pipeline needs OpenCV built with GStreamer, and this one is not "
                                 "(cv2.getBuildInformation() says GStreamer: NO): give an rtsp://, udp:// "
                                 "or .sdp source instead")
            self.url = self.spec[4:].strip() if self.spec.startswith("gst:") else self.spec
            self._options: dict[str, str] = {}
        else:
            self.url, self._options = ffmpeg_options(self.spec, rtsp_transport=rtsp_transport)

    @property
    def options(self) -> str:
        """The ``OPENCV_FFMPEG_CAPTURE_OPTIONS`` value: ``key;value`` pairs joined by ``|``."""
        return "|".join(f"{k};{v}" for k, v in self._options.items())

    def __call__(self, device: object = None) -> StreamCapture:
        """Open the stream (``device`` is ignored: CameraSource passes its name back)."""
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, int(self._open_timeout * 1000),
                  cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(self._read_timeout * 1000)]
        if self._threads > 0:
            params += [cv2.CAP_PROP_N_THREADS, int(self._threads)]
        if self._quiet:
            native_log.acquire()
        try:
            if self.gstreamer:
                cap = self._video_capture(self.url, cv2.CAP_GSTREAMER)
            else:
                with _env_lock:
                    before = os.environ.get(_OPTIONS_ENV)
                    os.environ[_OPTIONS_ENV] = self.options
                    try:
                        cap = self._video_capture(self.url, cv2.CAP_FFMPEG, params)
                    finally:
                        if before is None:
                            os.environ.pop(_OPTIONS_ENV, None)
                        else:
                            os.environ[_OPTIONS_ENV] = before
        except BaseException:
            self._untap()
            raise
        return StreamCapture(cap, read_timeout=self._read_timeout,
                             on_release=self._untap if self._quiet else None)

    def _untap(self) -> None:
        if self._quiet:
            counts = native_log.release()
            with self._counts_lock:
                self._counts.update(counts)

    def notes(self) -> str:
        """The decoder messages since the last call, as a clause for a log line ("" if none)."""
        tap = native_log.current()
        with self._counts_lock:
            if tap is not None:
                self._counts.update(tap.take())
            counts, self._counts = self._counts, Counter()
        return f"; {native_log.summarise(counts)}" if counts else ""
