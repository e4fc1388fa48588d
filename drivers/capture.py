"""Frame sources: one interface for a video file, a folder of stills, a live V4L2 camera and a stream.

Every source yields :class:`~photomap.drivers.frames.Frame` objects in capture order and counts what it read, dropped,
skipped and reconnected in :class:`~photomap.drivers.frames.CaptureStats`. Replay sources (video files, stills) never
drop a frame; a live camera drops the *oldest* queued frame when the consumer falls behind, so
latency stays bounded.

The concrete sources live in :mod:`photomap.drivers.video`, :mod:`photomap.drivers.images` and
:mod:`photomap.drivers.camera`; :func:`open_source` picks one from a spec string.
"""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path
from typing import Any, Callable

from photomap.drivers.camera import CameraSource
from photomap.drivers.frames import FrameSource
from photomap.drivers.images import ImageFolderSource
from photomap.drivers.stream import StreamOpener, is_stream
from photomap.drivers.video import VideoFileSource
from photomap.errors import InputError

_CAMERA_PATH = re.compile(r"^/dev/video\d+$")
_GLOB_CHARS = re.compile(r"[*?\[]")


def _is_camera(spec: str | int | Path) -> bool:
    if isinstance(spec, bool):
        return False
    if isinstance(spec, int):
        return True
    text = str(spec)
    if text.isdigit() or _CAMERA_PATH.match(text):
        return True
    try:  # stable names such as /dev/v4l/by-id/...: any character device
        return stat.S_ISCHR(os.stat(text).st_mode)
    except OSError:
        return False


def open_source(
    spec: str | int | Path,
    *,
    width: int | None = None,
    height: int | None = None,
    fps: float | None = None,
    fourcc: str | None = None,
    queue_size: int = 4,
    read_failures: int = 5,
    open_timeout: float = 5.0,
    stream_timeout: float = 2.0,
    rtsp_transport: str = "udp",
    decoder_threads: int = 1,
    reconnect_initial: float = 0.5,
    reconnect_max: float = 8.0,
    image_rate: float = 1.0,
    band: str = "",
    capture_factory: Callable[[str | int], Any] | None = None,
) -> FrameSource:
    """Open the frame source that ``spec`` names.

    ``/dev/videoN``, an integer or a string of digits opens a V4L2 camera
    (:class:`~photomap.drivers.camera.CameraSource`); a stream URL (``rtsp://``, ``udp://``,
    ``tcp://``, ``http(s)://``, ...), an ``.sdp`` file or a GStreamer pipeline opens the same live
    source on a :class:`~photomap.drivers.stream.StreamOpener` (lost after ``stream_timeout`` s
    without a frame, each opening bounded by ``open_timeout`` s); an existing directory or a glob pattern opens
    the stills it holds (:class:`~photomap.drivers.images.ImageFolderSource`); anything else is a
    video file (:class:`~photomap.drivers.video.VideoFileSource`). The keyword options are the
    ``capture:`` config section; each source takes the ones that concern it (0 or "" for
    width, height, fps, fourcc mean "the camera's default").

    Raises
    ------
    InputError
        The camera, folder or file cannot be opened.
    """
    if is_stream(spec):
        opener = StreamOpener(str(spec), open_timeout=open_timeout, read_timeout=stream_timeout,
                              rtsp_transport=rtsp_transport, decoder_threads=decoder_threads)
        return CameraSource(
            str(spec),
            queue_size=queue_size,
            read_failures=1,  # a failed stream read is already stream_timeout s without a frame
            reconnect_initial=reconnect_initial,
            reconnect_max=reconnect_max,
            capture_factory=capture_factory or opener,
            loss=f"(no frame for {stream_timeout:g} s)",
            notes=opener.notes,
            unavailable=f"nothing decodable arrived within {open_timeout:g} s (capture.open_timeout)",
        )
    if _is_camera(spec):
        device: str | int = spec if isinstance(spec, int) else str(spec)
        if isinstance(device, str) and device.isdigit():
            device = int(device)
        return CameraSource(
            device,
            width=width or None,
            height=height or None,
            fps=fps or None,
            fourcc=fourcc or None,
            queue_size=queue_size,
            read_failures=read_failures,
            reconnect_initial=reconnect_initial,
            reconnect_max=reconnect_max,
            capture_factory=capture_factory,
        )
    text = str(spec)
    try:
        is_dir = Path(text).is_dir()
        is_glob = bool(_GLOB_CHARS.search(text)) and not Path(text).exists()
    except OSError as exc:  # e.g. a parent folder we may not enter
        raise InputError(f"cannot access {text}: {exc.strerror or exc}") from None
    if is_dir or is_glob:
        return ImageFolderSource(text, rate=image_rate, band=band)
    return VideoFileSource(text)

