"""Live operator view of a mapping run in rerun (README, "Watching live").

:meth:`Viewer.on_frame` is a sink of :class:`photomap.mapping.pipeline.MappingPipeline`: it gets
a :class:`~photomap.mapping.events.FrameEvent` per frame in the pipeline's worker thread and only
copies what the view needs (pose, confidence, a downscaled frame and the changed map tiles when
they are due) into a bounded queue; a viewer thread JPEG-encodes and logs. When the viewer thread falls behind
(slow network, stuck sink) the *oldest* queued item is dropped and counted: viewer data is
dropped, frames never are, and the worker never waits on rerun.

Entities (map coordinates follow :mod:`photomap.geometry`: OpenCV map pixels, x right, y down,
integer coordinates at pixel centres):

``map/tiles/{segment}/{ty}_{tx}``
    Mosaic tile ``(tx, ty)`` (JPEG; PNG with alpha where it is partly empty, so the map's edge
    is transparent), re-logged only when it changed and at most ``tile_hz``
    times a second. A static ``Transform3D`` places it at its origin minus half a pixel, because
    rerun puts an image's pixel ``(0, 0)`` on the square ``[0, 1)^2`` while map pixel ``x`` is
    centred on ``x``. When a new map segment
    starts, the previous segment's tiles are cleared (each segment has its own map frame).
``map/trajectory``
    ``Points2D``: the map position of each posed frame's centre (one per posed frame; a frame
    posed later, as the anchor of a new segment, gets its point at its own ``frame``).
    ``LineStrips2D``: the path of the current segment every ``trajectory_every`` frames (rebuilt
    from the corrected poses after a loop closure)
    (thinned to at most ``trajectory_max_points``).
``map/footprint``
    The current frame's outline through its pose (closed ``LineStrips2D``).
``map/hazards``, ``geo/hazards``
    With hazard detection (:meth:`Viewer.show_hazards`): the confirmed hazard spots of the current
    segment as labelled red ``Points2D`` on the map and, georeferenced, ``GeoPoints``.
``camera/image``
    The input frame, downscaled to ``camera_px`` and JPEG-encoded, at most ``camera_hz``.
``health/confidence``, ``health/latency_ms/worker``, ``health/latency_ms/end_to_end``,
``health/dropped``, ``health/queue_depth``
    Time series: registration confidence; worker milliseconds for registration and for the
    whole frame (two series); capture-to-logging latency (live sources only: their ``Frame.t``
    is the monotonic clock); frames dropped by the capture and viewer items dropped
    (cumulative, two series); items waiting for the viewer thread.
``telemetry/altitude_m``, ``telemetry/heading_deg``
    With MAVLink telemetry: height above ground, and the heading from vision (the pose angle,
    tied to the autopilot's heading at the segment's first frame) beside the autopilot's yaw.
``geo/position``, ``geo/footprint``, ``geo/keyframes``, ``geo/track``
    With GPS telemetry: the vehicle's position, the frame's ground outline from the camera model,
    height and yaw, keyframe positions, and the GPS track, for rerun's Map view (web tiles are
    fetched by the viewer when it shows them; without a tile server the other views are unchanged).
``events``
    ``TextLog``: map segments started, link to the map lost, telemetry link lost/regained,
    camera reconnects, viewer overload.

Timelines: ``frame`` (the frame index) and ``capture_time`` (seconds since the first frame).

Serve mode and the network: the gRPC server listens on ``127.0.0.1`` unless an address is given
(``serve=ADDR:PORT``). It has no authentication, and it is read *and write*: any client that
reaches it can watch the camera and the map, and can also log into the stream (rerun's proxy
forwards what an SDK sends to every viewer), e.g. fake ``events``. rerun 0.41 has no read-only
mode, so the only protection is who can reach the port: keep the default and tunnel
(``ssh -N -L 9876:127.0.0.1:9876 USER@DRONE``) or bind to a VPN address.
"""

from __future__ import annotations

import ipaddress
import logging
import math
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable
from urllib.parse import urlsplit

import cv2
import numpy as np

from photomap.config import ViewerConfig
from photomap.core.thinned import ThinnedPath
from photomap.errors import ConfigError, InputError
from photomap.geo.georef import latlon_from_enu
from photomap.geometry import frame_centre, pose_angle_deg

if TYPE_CHECKING:
    from photomap.mapping.events import FrameEvent, TileReader

log = logging.getLogger(__name__)

DEFAULT_CONNECT_URL = "rerun+http://127.0.0.1:9876/proxy"
DEFAULT_SERVE_ADDRESS = "127.0.0.1"
COLOR_BY = ("confidence", "segment")
_URL_SCHEMES = ("rerun", "rerun+http", "rerun+https")
_USAGE = ("expected none, spawn, serve, serve=PORT, serve=ADDR:PORT, connect, "
          "connect=rerun+http://HOST:PORT/proxy or save=FILE.rrd")
_SEGMENT_COLORS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
                   (148, 103, 189), (140, 86, 75), (227, 119, 194), (188, 189, 34)]
_STOP = object()

TileKey = tuple[int, int]


def parse_viewer_mode(text: str) -> tuple[str, str | None]:
    """Split a viewer mode string (config ``viewer.mode`` or ``--viewer MODE``).

    Returns ``(mode, arg)``: ``("none", None)``, ``("spawn", None)``, ``("serve", None)``,
    ``("serve", "PORT")`` or ``("serve", "ADDR:PORT")`` (see :func:`parse_serve_address`),
    ``("connect", URL)`` (``connect`` alone means the local viewer,
    ``rerun+http://127.0.0.1:9876/proxy``), ``("save", "FILE.rrd")``.
    Raises :class:`ConfigError` for anything else.
    """
    raw = str(text if text is not None else "").strip()
    mode, sep, arg = raw.partition("=")
    mode, arg = mode.strip().lower(), arg.strip()
    if mode in ("none", "spawn"):
        if sep:
            raise ConfigError(f"viewer mode '{mode}' takes no argument, got {raw!r}")
        return mode, None
    if mode == "serve":
        if not sep:
            return mode, None
        parse_serve_address(arg, 9876)  # raises ConfigError
        return mode, arg
    if mode == "connect":
        url = arg if sep else DEFAULT_CONNECT_URL
        try:
            parts = urlsplit(url)
            ok = (parts.scheme in _URL_SCHEMES and bool(parts.hostname)
                  and parts.path.rstrip("/") == "/proxy")
            parts.port  # noqa: B018  (raises ValueError for a bad port)
        except ValueError:
            ok = False
        if not ok:
            raise ConfigError(f"viewer mode connect needs a URL like {DEFAULT_CONNECT_URL}, got {raw!r}")
        return mode, url
    if mode == "save":
        if not arg.lower().endswith(".rrd") or len(arg) <= 4:
            raise ConfigError(f"viewer mode save needs a file name ending in .rrd, got {raw!r}")
        return mode, arg
    raise ConfigError(f"unknown viewer mode {raw!r}: {_USAGE}")


def parse_serve_address(arg: str | None, default_port: int) -> tuple[str, int]:
    """The ``(address, port)`` serve mode listens on, from the part after ``serve=``.

    ``None`` or ``""``: ``127.0.0.1`` and ``default_port`` (this machine only). ``PORT``:
    ``127.0.0.1:PORT``. ``ADDR`` or ``ADDR:PORT``: an IPv4 address (``0.0.0.0`` = every interface),
    ``localhost``, or an IPv6 address in brackets (``[::1]:9876``, ``[::]`` = every interface).
    The address is returned without brackets. Raises :class:`ConfigError` for anything else.
    """
    text = (arg or "").strip()
    bad = ConfigError(f"viewer mode serve needs PORT, ADDR or ADDR:PORT (an IP address, [IPv6] in brackets, "
                      f"port 1-65535), got 'serve={text}'")
    if not text:
        return DEFAULT_SERVE_ADDRESS, int(default_port)
    if text.isdigit():
        host, port_text = DEFAULT_SERVE_ADDRESS, text
    elif text.startswith("["):
        host, sep, rest = text[1:].partition("]")
        if not sep or (rest and not rest.startswith(":")):
            raise bad
        port_text = rest[1:] if rest else str(default_port)
        try:
            if ipaddress.ip_address(host).version != 6:
                raise bad
        except ValueError:
            raise bad from None
    else:
        host, sep, port_text = text.partition(":")
        port_text = port_text if sep else str(default_port)
        if host.lower() == "localhost":
            host = DEFAULT_SERVE_ADDRESS
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            raise bad from None
    if not port_text.isdigit() or not 0 < int(port_text) < 65536:
        raise bad
    return host, int(port_text)


def _url_host(address: str) -> str:
    """``address`` as the host part of a URL (IPv6 in brackets)."""
    return f"[{address}]" if ":" in address else address


def confidence_color(confidence: float) -> tuple[int, int, int]:
    """RGB from red (confidence 0) through yellow (0.5) to green (1)."""
    c = min(max(float(confidence), 0.0), 1.0) if math.isfinite(confidence) else 0.0
    return int(round(255 * min(1.0, 2 * (1 - c)))), int(round(255 * min(1.0, 2 * c))), 0


def segment_color(segment: int) -> tuple[int, int, int]:
    """RGB of map segment ``segment`` (a fixed palette, repeating)."""
    return _SEGMENT_COLORS[segment % len(_SEGMENT_COLORS)]


def frame_outline(pose: np.ndarray, width: int, height: int) -> np.ndarray:
    """The frame's outer border through ``pose`` (frame -> map px): 5x2, closed, clockwise on screen.

    The corners are the outer corners of the corner pixels, ``(-0.5, -0.5)`` ... ``(w-0.5, h-0.5)``.
    """
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5],
                        [-0.5, height - 0.5], [-0.5, -0.5]])
    return corners @ np.asarray(pose, float)[:, :2].T + np.asarray(pose, float)[:, 2]


def footprint_tiles(pose: np.ndarray, width: int, height: int, tile_size: int) -> set[TileKey]:
    """Keys ``(tx, ty)`` of the tiles the bounding box of the frame's footprint touches.

    A superset of the tiles :meth:`TiledMosaic.add` changes (it returns the exact set).
    """
    outline = frame_outline(pose, width, height)
    (x0, y0), (x1, y1) = np.floor(outline.min(axis=0)), np.ceil(outline.max(axis=0))
    ts = tile_size
    return {(tx, ty) for ty in range(int(y0) // ts, int(y1) // ts + 1)
            for tx in range(int(x0) // ts, int(x1) // ts + 1)}


def geo_footprint(sample, focal_px: float | None, width: int, height: int) -> np.ndarray | None:
    """The frame's ground outline (5, 2) as (lat, lon), closed, from the telemetry alone.

    A nadir pinhole camera at ``sample``'s position and height above ground, image up along its
    yaw (clockwise from north), focal ``focal_px``: a pixel ``(u, v)`` lies ``(u - cx, cy - v) *
    height / focal`` metres (right, forward) from the point below the camera. None when a value
    is unknown.
    """
    if focal_px is None or sample.height_above_ground is None or sample.yaw is None \
            or sample.lat is None or sample.lon is None or not sample.height_above_ground > 0:
        return None
    k = sample.height_above_ground / focal_px
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    corners = frame_outline(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), width, height)
    right, forward = (corners[:, 0] - cx) * k, (cy - corners[:, 1]) * k
    s, c = math.sin(sample.yaw), math.cos(sample.yaw)
    east, north = right * c + forward * s, -right * s + forward * c
    lat, lon = latlon_from_enu(east, north, sample.lat, sample.lon)
    return np.c_[lat, lon]


def _downscale(image: np.ndarray, max_px: int) -> np.ndarray:
    """A copy of ``image`` whose longer side is at most ``max_px`` (INTER_AREA)."""
    h, w = image.shape[:2]
    f = max_px / max(h, w)
    if f >= 1.0:
        return image.copy()
    return cv2.resize(image, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)


_SPAWN_ARGS: tuple[str, ...] = ()  # more arguments for the spawned viewer (tests: "--headless")


def _has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _port_free(port: int, address: str = "0.0.0.0") -> bool:
    """True if nothing listens on TCP ``address:port`` (or on a wider address that covers it).

    With ``SO_REUSEADDR``, as the server itself binds: connections of a stopped run that linger in
    TIME_WAIT do not count (without it a restart within ~60 s of a stop with a viewer connected
    failed), while a listening socket still does.
    """
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((address, port))
        except OSError:
            return False
    return True


def _listening(url: str, timeout: float = 1.0) -> bool:
    """True if a TCP connection to the host and port of ``url`` succeeds."""
    parts = urlsplit(url)
    port = parts.port or (443 if parts.scheme == "rerun+https" else 9876 if parts.scheme == "rerun" else 80)
    try:
        with socket.create_connection((parts.hostname, port), timeout=timeout):
            return True
    except OSError:
        return False


def _lan_address() -> str | None:
    """This host's address on its default route (no packet is sent), or None."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("192.0.2.1", 9))  # TEST-NET-1: only selects the outgoing interface
            addr = s.getsockname()[0]
        return None if addr.startswith("127.") or addr == "0.0.0.0" else addr
    except OSError:
        return None


@dataclass
class ViewerStats:
    """Counters of a :class:`Viewer`.

    ``dropped``: viewer items (one per frame) discarded because the viewer thread fell behind.
    ``callback_s``: time spent in :meth:`Viewer.on_frame`, i.e. in the pipeline's worker.
    ``thread_cpu_s``: CPU time of the viewer thread (JPEG encoding and ``log`` calls; rerun's
    own encoder/sink threads are not included). ``jpeg_bytes``: encoded image bytes logged.
    """

    frames: int = 0
    dropped: int = 0
    logged: int = 0
    tiles: int = 0
    images: int = 0
    points: int = 0
    jpeg_bytes: int = 0
    errors: int = 0
    callback_s: float = 0.0
    thread_cpu_s: float = 0.0


@dataclass
class _Item:
    """What the viewer thread logs for one frame (all arrays are private copies)."""

    index: int
    t: float  # seconds since the first frame
    t_capture: float | None  # live sources: monotonic capture time, for the end-to-end latency
    confidence: float
    segment: int
    frame_size: tuple[int, int]
    pose: np.ndarray | None = None
    anchor: tuple[int, np.ndarray] | None = None  # (earlier frame, its pose) posed by this step
    color: tuple[int, int, int] = (255, 255, 255)
    register_ms: float | None = None
    frame_ms: float | None = None
    dropped_capture: int = 0
    camera: np.ndarray | None = None
    tiles: list[tuple[int, TileKey, tuple[int, int], np.ndarray]] = field(default_factory=list)
    clear_segments: list[int] = field(default_factory=list)  # segments whose tiles to clear
    strips: list[tuple[np.ndarray, tuple[int, int, int]]] | None = None
    events: list[tuple[str, str]] = field(default_factory=list)  # (level, text)
    health: bool = True  # log the health series (false for the closing refresh)
    altitude: float | None = None  # telemetry height above ground, m
    heading: tuple[float, float] | None = None  # (vision, autopilot), deg
    geo_position: tuple[float, float] | None = None  # GPS (lat, lon) of this frame
    geo_footprint: np.ndarray | None = None  # (5, 2) lat, lon: the frame's ground outline
    geo_track: np.ndarray | None = None  # (N, 2) lat, lon: the GPS track so far (thinned)
    geo_keyframe: tuple[float, float] | None = None  # GPS (lat, lon) of a new keyframe
    hazards: list[tuple[int, float, float, float | None, float | None]] | None = None  # id, x, y, lat, lon


class _DropOldestQueue:
    """A bounded FIFO whose ``put`` never blocks: when full, the oldest item is removed and returned."""

    def __init__(self, maxsize: int) -> None:
        self.maxsize = maxsize
        self._items: deque = deque()
        self._cond = threading.Condition()

    def put(self, item: Any, *, drop: bool = True) -> Any | None:
        with self._cond:
            dropped = self._items.popleft() if drop and len(self._items) >= self.maxsize else None
            self._items.append(item)
            self._cond.notify()
            return dropped

    def get(self) -> Any:
        with self._cond:
            while not self._items:
                self._cond.wait()
            return self._items.popleft()

    def __len__(self) -> int:
        return len(self._items)


class Viewer:
    """Sends a mapping run to rerun; use :meth:`on_frame` as the pipeline's callback.

    Parameters
    ----------
    mode : str
        ``none``; ``spawn`` (a local viewer window; without a display (no ``DISPLAY`` or
        ``WAYLAND_DISPLAY``) one warning and the run carries on without a viewer); ``serve``
        (a gRPC server in this process on ``127.0.0.1:port``, or on the address ``arg`` gives,
        keeping at most ``server_memory_limit`` for viewers that connect late; the operator runs
        ``rerun --connect rerun+http://HOST:PORT/proxy``, through an SSH tunnel for the default
        address; **any client that reaches the server can also write into the stream**, see the module
        docstring);
        ``connect`` (push to ``arg``, a viewer or ``rerun --serve-grpc`` proxy that must
        **already listen**: if nothing answers, one warning and no viewer, because rerun's
        client gives up for good after a few seconds and never reconnects); ``save`` (write
        the recording to the ``.rrd`` file ``arg``). Strings as in :func:`parse_viewer_mode`.
    arg : str or None
        ``PORT``, ``ADDR`` or ``ADDR:PORT`` (serve, :func:`parse_serve_address`), URL (connect)
        or file (save).
    params : ViewerConfig
        The ``viewer`` settings: serve mode's ``port`` (``arg`` wins) and ``server_memory_limit``
        (e.g. ``"256MB"``); ``queue_size`` items (one per frame) waiting for the viewer thread
        before the oldest is dropped; ``tile_hz`` map tile refreshes per second and ``max_tiles``
        changed tiles sent per refresh (the rest wait for the next); ``camera_hz`` camera images
        per second and ``camera_px`` their longest side; ``jpeg_quality`` of tiles and camera
        images; the whole path of the current segment every ``trajectory_every`` frames,
        thinned to at most ``trajectory_max_points``; ``color_by`` ``confidence`` (red low, green
        high) or ``segment``. Its ``mode`` is not used here (see :meth:`from_config`).
    application_id : rerun application id.

    Raises
    ------
    ConfigError
        Bad values, rerun-sdk missing for a mode that needs it, or the serve port in use.
    InputError
        The save file cannot be created.

    Notes
    -----
    Call :meth:`close` after the pipeline's ``run()`` returned: it sends the tiles still
    pending and those the run changed after its last frame (the last keyframe's bands, the
    final re-render; read from the finished mosaic), drains the queue and closes the
    recording cleanly (``disconnect``), so a ``.rrd`` gets its footer.
    """

    def __init__(self, mode: str = "none", arg: str | None = None, params: ViewerConfig = ViewerConfig(),
                 application_id: str = "photomap") -> None:
        mode, arg = parse_viewer_mode(mode if arg is None else f"{mode}={arg}")
        tile_hz, camera_hz = params.tile_hz, params.camera_hz
        max_tiles, camera_px, jpeg_quality = params.max_tiles, params.camera_px, params.jpeg_quality
        trajectory_every, trajectory_max_points = params.trajectory_every, params.trajectory_max_points
        color_by, queue_size = params.color_by, params.queue_size
        port, server_memory_limit = params.port, params.server_memory_limit
        self.mode, self.arg = mode, arg
        self.url: str | None = None
        self.address: tuple[str, int] | None = None  # serve, spawn: where the server listens
        self.spawned_pid: int | None = None  # spawn: the viewer process started (it outlives the run)
        self.connect_hint: str | None = None  # serve on loopback: the SSH tunnel to open first
        self.stats = ViewerStats()
        self._tile_period, self._camera_period = 1.0 / tile_hz, 1.0 / camera_hz
        self._max_tiles, self._camera_px = int(max_tiles), int(camera_px)
        self._jpeg_params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)]
        self._trajectory_every, self._max_points = int(trajectory_every), int(trajectory_max_points)
        self._color_by = color_by
        self._queue = _DropOldestQueue(int(queue_size))
        self._warned: set[str] = set()
        self._closed = False
        # worker-side state (touched only by on_frame, and by close() after the run)
        self._tiles: TileReader | None = None  # the current segment's map (read after the run too)
        self._stamp: int | None = None  # its change stamp at the last frame (tile_stamps, when it has them)
        self._dropped_capture = 0
        self._t0: float | None = None
        self._segment: int | None = None
        self._dirty: set[TileKey] = set()
        self._path: ThinnedPath[tuple[float, float, float]] = ThinnedPath(self._max_points)  # x, y, confidence
        self._last_point: tuple[float, float, float] | None = None
        self._geo: ThinnedPath[tuple[float, float]] = ThinnedPath(self._max_points)  # GPS track (lat, lon)
        self._since_strip = 0
        self._strip_due = False
        self._last_tiles = self._last_camera = -math.inf
        self._prev_reconnects = 0
        self._tel_lost = self._tel_back = 0  # telemetry link losses/returns already shown
        self._heading_offset, self._heading_segment = 0.0, None
        self._carry_events: list[tuple[str, str]] = []
        self._carry_clear: list[int] = []
        self._last_item: _Item | None = None
        self._hazards: Callable[[], dict] | None = None  # show_hazards()
        self._last_hazards = -math.inf
        # viewer-thread state
        self._placed: set[tuple[int, TileKey]] = set()
        self._rec = None
        self._rr = None
        self._thread: threading.Thread | None = None
        if mode != "none":
            self._open(mode, arg, int(port), str(server_memory_limit), application_id)

    @classmethod
    def from_config(cls, params: ViewerConfig, mode: str | None = None) -> Viewer:
        """A viewer from the ``viewer`` settings; ``mode`` (``--viewer MODE``) overrides ``params.mode``."""
        configured = params.mode
        name, arg = parse_viewer_mode(configured if mode is None else mode)
        return cls(name, arg, params)

    @property
    def enabled(self) -> bool:
        """True when frames are being sent to rerun."""
        return self._rec is not None

    # ------------------------------------------------------------------ sinks
    def _open(self, mode: str, arg: str | None, port: int, memory_limit: str, app_id: str) -> None:
        if mode == "spawn" and not _has_display():
            log.warning("viewer: no display (DISPLAY/WAYLAND_DISPLAY unset), so no local viewer is "
                        "spawned; the run carries on without one (use --viewer serve and connect "
                        "through an SSH tunnel)")
            return
        if mode == "connect" and not _listening(arg):
            log.warning("viewer: nothing listens at %s, so the run carries on without a viewer "
                        "(start the viewer first: rerun --serve-grpc, or use --viewer serve)", arg)
            return
        try:
            import rerun as rr
        except ImportError:
            raise ConfigError(f"viewer mode '{mode}' needs rerun-sdk: pip install 'ifmi-photomap[viewer]'"
                              ) from None
        from photomap.live.blueprint import default_blueprint

        if mode == "serve":
            if not 0 < port < 65536:
                raise ConfigError(f"viewer port must be 1-65535, got {port}")
            address, port = parse_serve_address(arg, port)
            if not _port_free(port, address):
                raise ConfigError(f"viewer port {_url_host(address)}:{port} is already in use (or the "
                                  f"address is not this machine's); choose another with "
                                  f"--viewer serve=PORT or --set viewer.port=PORT")
        if mode == "save":
            path = Path(arg).expanduser()
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                path.touch()
            except OSError as exc:
                raise InputError(f"cannot create the viewer recording {path}: {exc.strerror or exc}") from None
        rec = rr.RecordingStream(app_id)
        blueprint = default_blueprint()
        if mode == "spawn":
            if not self._spawn(rec, port, memory_limit, blueprint):
                return
        elif mode == "serve":
            self._serve(rr, rec, address, port, memory_limit, blueprint)
        elif mode == "connect":
            rec.connect_grpc(arg, default_blueprint=blueprint)
            self.url = arg
        else:
            rec.save(str(Path(arg).expanduser()), default_blueprint=blueprint)
        self._rr, self._rec = rr, rec
        rec.log("health/latency_ms/worker", rr.SeriesLines(names=["registration", "whole frame"]),
                static=True)
        rec.log("health/latency_ms/end_to_end", rr.SeriesLines(names="capture to view"), static=True)
        rec.log("health/dropped", rr.SeriesLines(names=["frames (capture)", "viewer data"]), static=True)
        rec.log("telemetry/heading_deg", rr.SeriesLines(names=["vision", "autopilot"]), static=True)
        self._thread = threading.Thread(target=self._run, name="photomap-viewer", daemon=True)
        self._thread.start()

    def _spawn(self, rec: Any, port: int, memory_limit: str, blueprint: Any) -> bool:
        """A local viewer window listening on 127.0.0.1:``port`` only, and stream into it.

        ``rr.spawn`` starts the viewer on every interface (rerun 0.41): anyone on the network could
        watch the camera. A viewer (or an SSH tunnel to one) already listening there is used as it
        is. The window outlives the run (close it when done). False when none came up.
        """
        url = f"rerun+http://127.0.0.1:{port}/proxy"
        if not _listening(url):
            exe = shutil.which("rerun") or shutil.which("rerun", path=str(Path(sys.executable).parent))
            if exe is None:
                log.warning("viewer: the rerun viewer executable is not on PATH, so no window; the run "
                            "carries on without one (pip install 'ifmi-photomap[viewer]')")
                return False
            try:
                proc = subprocess.Popen([exe, "--port", str(port), "--bind", "127.0.0.1", "--memory-limit", "75%",
                                         "--server-memory-limit", memory_limit, "--expect-data-soon", *_SPAWN_ARGS],
                                        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL, start_new_session=True,
                                        env={**os.environ, "RERUN_APP_ONLY": "true"})
            except OSError as exc:
                log.warning("viewer: cannot start %s (%s); the run carries on without a viewer", exe, exc)
                return False
            self.spawned_pid = proc.pid
            deadline = time.monotonic() + 15.0
            while not _listening(url, timeout=0.2):
                if proc.poll() is not None or time.monotonic() > deadline:
                    log.warning("viewer: the spawned viewer did not come up on 127.0.0.1:%d; the run "
                                "carries on without one", port)
                    return False
                time.sleep(0.1)
        rec.connect_grpc(url, default_blueprint=blueprint)
        self.address, self.url = ("127.0.0.1", port), url
        return True

    def _serve(self, rr: Any, rec: Any, address: str, port: int, memory_limit: str, blueprint: Any) -> None:
        """Host the gRPC server in this process on ``address:port``.

        ``RecordingStream.serve_grpc`` always listens on every interface; the sink it wraps,
        ``GrpcServerSink``, takes the address (rerun 0.41).
        """
        try:
            sink = rr.GrpcServerSink(_url_host(address), port, server_memory_limit=memory_limit)
            rec.set_sinks(sink, default_blueprint=blueprint)
        except (RuntimeError, ValueError) as exc:  # "Bad server_memory_limit: ...", a bad address
            raise ConfigError(f"viewer serve: {exc}") from None
        self.address = (address, port)
        ip = ipaddress.ip_address(address)
        local = f"rerun+http://{_url_host(address)}:{port}/proxy"
        if ip.is_loopback:
            self.url = local
            tunnel = f"ssh -N -L {port}:{_url_host(address)}:{port} USER@{socket.gethostname() or 'THIS-HOST'}"
            self.connect_hint = f"from another machine: `{tunnel}` first"
            log.info("viewer: serving on %s:%d, this machine only (from another machine: %s, then "
                     "rerun --connect %s)", _url_host(address), port, tunnel, self.url)
            return
        if ip.is_unspecified:
            lan = _lan_address()
            self.url = f"rerun+http://{lan}:{port}/proxy" if lan else f"rerun+http://127.0.0.1:{port}/proxy"
            where = "every interface"
        else:
            self.url, where = local, _url_host(address)
        log.warning("viewer: serving on %s:%d (%s) WITHOUT authentication: anyone who can reach this "
                    "port can watch the camera and the map and can also write into the live view; "
                    "prefer the default 127.0.0.1 with an SSH tunnel or a VPN address",
                    _url_host(address), port, where)
        log.info("viewer: connect with: rerun --connect %s", self.url)

    # ------------------------------------------------------------------ worker side
    def show_hazards(self, source: Callable[[], dict] | None) -> None:
        """Show hazard spots (``source()``: a GeoJSON FeatureCollection dict whose features carry
        ``id``, ``segment``, ``x_px``, ``y_px``, ``lat``, ``lon``; e.g. ``HazardTracker.hazards``)
        as points on the map (``map/hazards``, the current segment's) and on the globe
        (``geo/hazards``), refreshed with the tiles."""
        self._hazards = source

    def on_frame(self, event: FrameEvent) -> None:
        """The pipeline sink: copy what the view needs and queue it. Never raises or blocks."""
        if self._rec is None or self._closed:
            return
        t0 = time.perf_counter()
        try:
            self._on_frame(event)
        except Exception as exc:  # the view must never cost the map
            self.stats.errors += 1
            self._warn_once(f"frame:{type(exc).__name__}", f"viewer: frame {event.index} not shown: "
                                                            f"{type(exc).__name__}: {exc}")
        finally:
            self.stats.callback_s += time.perf_counter() - t0

    def _telemetry(self, event: FrameEvent, item: _Item) -> None:
        """Altitude, vision vs autopilot heading, and telemetry link events."""
        if event.link_lost > self._tel_lost:
            item.events.append(("WARN", f"telemetry link lost before frame {event.index}: "
                                        "mapping from vision alone"))
        if event.link_regained > self._tel_back:
            item.events.append(("INFO", f"telemetry link regained before frame {event.index}"))
        self._tel_lost, self._tel_back = event.link_lost, event.link_regained
        sample = event.telemetry
        if sample is None or event.pose is None:
            return
        if sample.lat is not None and sample.lon is not None:
            item.geo_position = (sample.lat, sample.lon)
            if event.keyframe:
                item.geo_keyframe = item.geo_position
            self._geo.append((sample.lat, sample.lon))
            item.geo_footprint = geo_footprint(sample, event.focal_px, *event.frame_size)
        item.altitude = sample.height_above_ground
        if sample.yaw is not None:
            angle = pose_angle_deg(event.pose)
            yaw = math.degrees(sample.yaw)
            if self._heading_segment != event.segment:
                self._heading_offset, self._heading_segment = yaw - angle, event.segment
            item.heading = ((angle + self._heading_offset + 180.0) % 360.0 - 180.0,
                            (yaw + 180.0) % 360.0 - 180.0)

    def _on_frame(self, event: FrameEvent) -> None:
        now = time.monotonic()
        self.stats.frames += 1
        if self._t0 is None:
            self._t0 = event.t
        w, h = event.frame_size
        item = _Item(event.index, event.t - self._t0, event.t if event.live else None,
                     float(event.confidence), event.segment, (w, h),
                     dropped_capture=event.dropped_frames,
                     events=self._carry_events, clear_segments=self._carry_clear)
        self._carry_events, self._carry_clear = [], []
        self._dropped_capture = event.dropped_frames

        if event.segment != self._segment:
            if self._segment is None:
                item.events.append(("INFO", f"map segment {event.segment} started at frame {event.index}"))
            else:
                item.clear_segments.append(self._segment)
            self._segment = event.segment
            self._dirty.clear()
            self._path.clear()
            self._strip_due = True
        item.events.extend(("WARN", text) for text in event.messages if not text.startswith("loop closed"))
        if event.reconnects > self._prev_reconnects:
            item.events.append(("WARN", f"camera reconnected (reconnect {event.reconnects}) "
                                        f"before frame {event.index}"))
            self._prev_reconnects = event.reconnects

        self._telemetry(event, item)
        item.register_ms, item.frame_ms = event.register_ms, event.frame_ms
        item.color = self._color(event.confidence, event.segment)
        if event.anchor is not None:  # an earlier frame became the reference
            item.anchor = (int(event.anchor[0]), np.array(event.anchor[1], dtype=float))
        posed = [p for p in (item.anchor[1] if item.anchor else None, event.pose) if p is not None]
        if event.pose is not None:
            item.pose = np.array(event.pose, dtype=float)
        if event.tiles is not None:
            self._tiles = event.tiles
            self._stamp = getattr(event.tiles, "stamp", None)
        cx, cy = frame_centre(w, h)
        for pose in posed:
            x, y = np.asarray(pose, float) @ (cx, cy, 1.0)
            self._append_path(float(x), float(y), float(event.confidence))
        if posed:
            self._dirty.update(event.touched)

        if self._dirty and now - self._last_tiles >= self._tile_period:
            self._last_tiles = now
            item.tiles = self._take_tiles(event.tiles, event.segment, self._max_tiles)
        if self._hazards is not None and now - self._last_hazards >= self._tile_period:
            self._last_hazards = now
            props = [f["properties"] for f in self._hazards().get("features", ())]
            item.hazards = [(p["id"], p["x_px"], p["y_px"], p.get("lat"), p.get("lon"))
                            for p in props if p.get("segment") == event.segment]
        if now - self._last_camera >= self._camera_period:
            self._last_camera = now
            item.camera = _downscale(event.image, self._camera_px)
        if event.corrected_path is not None:
            self._rebuild_path(event.corrected_path)
            item.events.append(("INFO", f"loop closed at frame {event.index}: trajectory and map corrected"))
        self._since_strip += 1
        if self._path and (self._strip_due or self._since_strip >= self._trajectory_every):
            item.strips = self._strips()
            self._since_strip, self._strip_due = 0, False
            if len(self._geo) >= 2:
                item.geo_track = np.array(self._geo.points, dtype=float)

        self._last_item = item
        dropped = self._queue.put(item)
        if dropped is not None:
            self._recover(dropped)

    def _recover(self, dropped: _Item) -> None:
        """Keep what must not be lost from a dropped item: events, tile updates, the path, a clear."""
        self.stats.dropped += 1
        if self.stats.dropped == 1:
            dropped.events.append(("WARN", "viewer falls behind: dropping viewer data (frames are not dropped)"))
        self._carry_events.extend(dropped.events)
        self._carry_clear.extend(dropped.clear_segments)
        if dropped.segment == self._segment:
            self._dirty.update(key for _, key, _, _ in dropped.tiles)
        if dropped.strips is not None:
            self._strip_due = True

    def _color(self, confidence: float, segment: int) -> tuple[int, int, int]:
        return confidence_color(confidence) if self._color_by == "confidence" else segment_color(segment)

    def _rebuild_path(self, path: np.ndarray) -> None:
        """After a pose-graph correction: the path again ((n, 3) x, y, confidence), thinned as
        :meth:`_append_path` would have thinned it point by point."""
        path = np.asarray(path, float).reshape(-1, 3)
        self._path.rebuild(path)
        if len(path):
            self._last_point = tuple(path[-1].tolist())
        self._strip_due = True

    def _append_path(self, x: float, y: float, confidence: float) -> None:
        """The next point of the path (thinned, :class:`~photomap.core.thinned.ThinnedPath`); the
        latest is kept apart so that the drawn path ends at the vehicle."""
        self._path.append((x, y, confidence))
        self._last_point = (x, y, confidence)

    def _strips(self) -> list[tuple[np.ndarray, tuple[int, int, int]]]:
        """The current segment's path as strips: one per colour run (confidence) or one (segment)."""
        pts = list(self._path.points)
        if pts[-1] != self._last_point:
            pts.append(self._last_point)
        arr = np.array(pts, dtype=float)
        if self._color_by == "segment":
            return [(arr[:, :2], segment_color(self._segment))]
        levels = np.clip(np.floor(arr[:, 2] * 4), 0, 3)  # 4 confidence bands
        strips = []
        start = 0
        for i in range(1, len(arr) + 1):
            if i == len(arr) or levels[i] != levels[start]:
                # each run overlaps the next by one point so that the path stays connected
                strips.append((arr[start:min(i + 1, len(arr)), :2],
                               confidence_color((levels[start] + 0.5) / 4)))
                start = i
        return strips

    def _take_tiles(self, mosaic: TileReader | None, segment: int, limit: int | None
                    ) -> list[tuple[int, TileKey, tuple[int, int], np.ndarray]]:
        """Copies of up to ``limit`` dirty tiles (removed from the dirty set); missing tiles are skipped."""
        out = []
        if mosaic is None:
            self._dirty.clear()
            return out
        for key in sorted(self._dirty, key=lambda k: (k[1], k[0]))[:limit]:
            self._dirty.discard(key)
            try:
                image, alpha = mosaic.tile_image(key)
            except KeyError:  # the footprint's bounding box reaches tiles the frame did not cover
                continue
            if alpha.min() < 255:  # a partly covered tile keeps its transparency (sent as PNG)
                image = np.dstack([image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR),
                                   alpha])
            out.append((segment, key, mosaic.tile_origin(key), image))
        return out

    # ------------------------------------------------------------------ viewer thread
    def _run(self) -> None:
        cpu0 = time.thread_time()
        while True:
            item = self._queue.get()
            if item is _STOP:
                break
            try:
                self._log(item)
                self.stats.logged += 1
            except Exception as exc:
                self.stats.errors += 1
                self._warn_once(f"log:{type(exc).__name__}", f"viewer: logging failed: {type(exc).__name__}: {exc}")
            self.stats.thread_cpu_s = time.thread_time() - cpu0

    def _jpeg(self, image: np.ndarray) -> bytes:
        ok, buf = cv2.imencode(".jpg", image, self._jpeg_params)
        if not ok:
            raise RuntimeError(f"JPEG encoding of a {image.shape} image failed")
        self.stats.jpeg_bytes += buf.size
        return buf.tobytes()

    def _log(self, item: _Item) -> None:
        rr, rec = self._rr, self._rec
        rec.set_time("frame", sequence=item.index)  # set_time is thread-local: set it here
        rec.set_time("capture_time", duration=item.t)
        for segment in item.clear_segments:
            rec.log(f"map/tiles/{segment}", rr.Clear(recursive=True))
        for segment, key, (x0, y0), image in item.tiles:
            path = f"map/tiles/{segment}/{key[1]}_{key[0]}"
            if (segment, key) not in self._placed:
                # rerun's pixel (0, 0) covers [0, 1)^2; map pixel x0 is centred on x0
                rec.log(path, rr.Transform3D(translation=[x0 - 0.5, y0 - 0.5, 0.0]), static=True)
                self._placed.add((segment, key))
            if image.ndim == 3 and image.shape[2] == 4:
                ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
                if not ok:
                    raise RuntimeError("PNG encoding of a map tile failed")
                self.stats.jpeg_bytes += buf.size
                rec.log(path, rr.EncodedImage(contents=buf.tobytes(), media_type="image/png"))
            else:
                rec.log(path, rr.EncodedImage(contents=self._jpeg(image), media_type="image/jpeg"))
            self.stats.tiles += 1
        cx, cy = frame_centre(*item.frame_size)
        if item.anchor is not None:  # the point of the earlier frame, at that frame's time
            rec.set_time("frame", sequence=item.anchor[0])
            rec.log("map/trajectory", rr.Points2D([item.anchor[1] @ (cx, cy, 1.0)], colors=[item.color],
                                                  radii=rr.Radius.ui_points(3.0)))
            self.stats.points += 1
            rec.set_time("frame", sequence=item.index)
        if item.pose is not None:
            xy = item.pose @ (cx, cy, 1.0)
            rec.log("map/trajectory", rr.Points2D([xy], colors=[item.color], radii=rr.Radius.ui_points(3.0)))
            self.stats.points += 1
            rec.log("map/footprint", rr.LineStrips2D([frame_outline(item.pose, *item.frame_size)],
                                                     colors=[item.color], radii=rr.Radius.ui_points(1.5)))
        if item.geo_position is not None:
            rec.log("geo/position", rr.GeoPoints(lat_lon=[item.geo_position], radii=rr.Radius.ui_points(5.0),
                                                 colors=[item.color]))
        if item.geo_footprint is not None:
            rec.log("geo/footprint", rr.GeoLineStrings(lat_lon=[item.geo_footprint], radii=rr.Radius.ui_points(1.5),
                                                       colors=[item.color]))
        if item.geo_keyframe is not None:
            rec.log("geo/keyframes", rr.GeoPoints(lat_lon=[item.geo_keyframe], radii=rr.Radius.ui_points(3.0),
                                                  colors=[(255, 255, 255)]))
        if item.geo_track is not None:
            rec.log("geo/track", rr.GeoLineStrings(lat_lon=[item.geo_track], radii=rr.Radius.ui_points(2.0),
                                                   colors=[(255, 64, 0)]))
        if item.hazards:
            red = (255, 32, 32)
            rec.log("map/hazards", rr.Points2D([(x, y) for _, x, y, _, _ in item.hazards],
                                               labels=[f"hazard {i}" for i, _, _, _, _ in item.hazards],
                                               colors=[red], radii=rr.Radius.ui_points(7.0)))
            geo = [(la, lo) for _, _, _, la, lo in item.hazards if la is not None and lo is not None]
            if geo:
                rec.log("geo/hazards", rr.GeoPoints(lat_lon=geo, radii=rr.Radius.ui_points(7.0), colors=[red]))
        if item.strips:
            rec.log("map/trajectory", rr.LineStrips2D([s for s, _ in item.strips],
                                                      colors=[c for _, c in item.strips],
                                                      radii=rr.Radius.ui_points(1.0)))
        if item.camera is not None:
            rec.log("camera/image", rr.EncodedImage(contents=self._jpeg(item.camera), media_type="image/jpeg"))
            self.stats.images += 1
        if item.health:
            rec.log("health/confidence", rr.Scalars(item.confidence))
            if item.register_ms is not None:
                rec.log("health/latency_ms/worker", rr.Scalars([item.register_ms, item.frame_ms]))
            if item.t_capture is not None:
                rec.log("health/latency_ms/end_to_end",
                        rr.Scalars(1000.0 * (time.monotonic() - item.t_capture)))
            rec.log("health/dropped", rr.Scalars([item.dropped_capture, self.stats.dropped]))
            rec.log("health/queue_depth", rr.Scalars(len(self._queue)))
            if item.altitude is not None:
                rec.log("telemetry/altitude_m", rr.Scalars(item.altitude))
            if item.heading is not None:
                rec.log("telemetry/heading_deg", rr.Scalars(list(item.heading)))
        for level, text in item.events:
            rec.log("events", rr.TextLog(text, level=level))

    # ------------------------------------------------------------------ end
    def close(self, timeout: float = 30.0) -> None:
        """Send the pending tiles, drain the queue (at most ``timeout`` s) and close the recording.

        Call it after the pipeline's ``run()`` returned (the pending tiles are read from the
        mosaic, which must no longer change). Idempotent.
        """
        if self._closed:
            return
        self._closed = True
        if self._rec is None:
            return
        last = self._last_item
        if last is not None:
            final = _Item(last.index, last.t, None, last.confidence, last.segment, last.frame_size,
                          dropped_capture=self._dropped_capture,
                          events=self._carry_events, clear_segments=self._carry_clear, health=False)
            try:
                if self._tiles is not None and self._stamp is not None:  # changed after the last frame:
                    self._dirty.update(key for key, stamp in self._tiles.tile_stamps().items()  # the map's end
                                       if stamp > self._stamp)
                if self._dirty:
                    final.tiles = self._take_tiles(self._tiles, last.segment, None)
                if self._path:
                    final.strips = self._strips()
                if len(self._geo) >= 2:
                    final.geo_track = np.array(self._geo.points, dtype=float)
            except Exception as exc:
                self._warn_once("close", f"viewer: final map refresh failed: {type(exc).__name__}: {exc}")
            self._queue.put(final, drop=False)
        self._queue.put(_STOP, drop=False)
        self._thread.join(timeout)
        if self._thread.is_alive():
            log.warning("viewer: still busy after %.0f s; closing the recording anyway (%d items lost)",
                        timeout, len(self._queue))
        try:
            self._rec.flush(timeout_sec=max(1.0, timeout))
            self._rec.disconnect()
        except Exception as exc:
            log.warning("viewer: closing the recording failed: %s: %s", type(exc).__name__, exc)
        if self.stats.dropped:
            log.info("viewer: %d of %d frames' viewer data dropped (the viewer fell behind)",
                     self.stats.dropped, self.stats.frames)

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _warn_once(self, kind: str, message: str) -> None:
        if kind not in self._warned:
            self._warned.add(kind)
            log.warning(message)
