"""The live map over HTTP, for the ground station (docs/live-map.md).

``--map-server [ADDR:]PORT`` (or ``map_server.listen``) on ``run`` and ``replay`` starts
:class:`MapServer`: a small HTTP server in its own threads, fed by a
:class:`~photomap.live.livemap.LiveMap` (the pipeline's sink: it copies what is shown, the server
never reads the pipeline's state). It serves:

``/tiles/{z}/{x}/{y}.png``
    XYZ web-mercator tiles of the georeferenced live map, 256 px PNG (RGBA, transparent where
    nothing is mapped; RGB where every pixel is), zoom 0 .. ``max_zoom`` (the map's resolution)
    and :data:`OVERZOOM` more (upsampled; 404 beyond, and before a georeference): the custom map
    URL form of QGroundControl, Mission Planner, QGIS "XYZ Tiles" and Leaflet. Each with an ``ETag``
    (``Cache-Control: no-cache``): a client that asks again with ``If-None-Match`` (as a
    browser's or Qt's cache does) gets ``304 Not Modified`` and no body while the tile is the
    picture it has.
``/pixel/{z}/{x}/{y}.png``
    The same in the map's own pixel frame (:mod:`photomap.live.livemap`), before a georeference.
``/status.json``
    ``frames_in``, ``registered``, ``segments``, ``fps``, ``telemetry``, ``position``, ``bounds``,
    ``max_zoom``, ``tiles_url`` ... (:func:`photomap.live.livemap.status`).
``/track.geojson``, ``/footprint.geojson``, ``/hazards.geojson``
    The path, the current frame's outline and the hazard spots (the ``hazards`` callable's
    FeatureCollection; empty without one). Coordinates are lon, lat when georeferenced, else map
    pixels (the collection's ``"frame"`` says which).
``/``
    A page (Leaflet, shipped in the package: no internet needed) with all of it, following the
    flight.

Bounds: ``threads`` threads answer (live, their Python code waits while the worker maps a frame:
:attr:`MapServer.gate`; not at a lowered priority: a thread holding the interpreter lock while the
kernel runs others would keep the worker waiting), at most ``max_connections``
connections are open at once (a new one beyond closes the longest idle, or itself when none is),
a request (line and headers) must arrive whole within ``timeout_s`` and within 8 KiB, only GET
and HEAD are answered. A connection is kept for the next request (HTTP/1.1 keep-alive) for
``keepalive_s`` and :data:`KEEPALIVE_REQUESTS` answers, waiting in one selector thread, not in an
answering thread. The answering threads together take at most ``cpu_share`` of one core
(:class:`~photomap.live.cpubudget.CpuBudget`, by their own clocks): however much clients ask,
beyond it each answer waits its turn. The mapping worker never waits for any of it.

The network: the server listens on ``127.0.0.1`` unless an address is given. It has no
authentication and is read-only; whoever reaches the port sees the map.
"""

from __future__ import annotations

import json
import logging
import re
import select
import selectors
import socket
import socketserver
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from email.utils import formatdate
from http import HTTPStatus
from http.server import HTTPServer
from importlib import resources
from pathlib import Path
from typing import Callable

from photomap.config import MapServerConfig
from photomap.errors import ConfigError, InputError, PhotomapError
from photomap.geo import webmercator as wm
from photomap.live.cpubudget import CpuBudget
from photomap.live.livemap import EMPTY_TILE, PIXEL_ZOOM, LiveMap, Snapshot, Tile, TileCache, footprint_geojson, \
    hazards_geojson, status, tile_type, track_geojson
from photomap.live.viewer import parse_serve_address
from photomap.mapping.events import FrameEvent
from photomap.mapping.threads import WorkerFirst

log = logging.getLogger(__name__)

MAX_REQUEST_BYTES = 8192
KEEPALIVE_REQUESTS = 1000  # answers on one connection before it is closed (nginx's keepalive_requests)
LINGER_S = 0.002  # an answering thread waits this long for a keep-alive client's next request before parking it
_FIELDS = frozenset({"connection", "content-length", "transfer-encoding", "host", "if-none-match"})
OVERZOOM = 3  # web tiles are served this many zooms beyond the map's resolution (upsampled)
_VERSION = re.compile(r"^HTTP/\d\.\d$")
_PHRASES = {int(s): s.phrase for s in HTTPStatus}
_TILE_PATH = re.compile(r"^/(tiles|pixel)/(\d{1,2})/(-?\d{1,9})/(-?\d{1,9})\.png$")
_STATIC = {"leaflet.js": "application/javascript", "leaflet.css": "text/css", "LICENSE": "text/plain",
           "images/layers.png": "image/png", "images/layers-2x.png": "image/png",
           "images/marker-icon.png": "image/png", "images/marker-icon-2x.png": "image/png",
           "images/marker-shadow.png": "image/png"}

Hazards = Callable[[], dict]


def parse_listen(text: str | None, default_port: int) -> tuple[str, int]:
    """``(address, port)`` from ``[ADDR:]PORT`` (``--map-server``, ``map_server.listen``):
    ``PORT`` or nothing listens on 127.0.0.1 (this machine only); ``ADDR`` alone takes
    ``default_port``. Raises :class:`ConfigError` naming the value."""
    try:
        return parse_serve_address(text, default_port)
    except ConfigError:
        raise ConfigError(f"map server needs PORT, ADDR or ADDR:PORT (an IP address, [IPv6] in brackets, "
                          f"port 1-65535), got {text!r}") from None


def _encode(obj: dict) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def _head_end(data: bytearray) -> int:
    """The length of the request head at the start of ``data`` (through its blank line), or -1."""
    crlf, lf = data.find(b"\r\n\r\n"), data.find(b"\n\n")
    if crlf >= 0 and (lf < 0 or crlf + 2 < lf):
        return crlf + 4
    return lf + 2 if lf >= 0 else -1


def _fields(lines: list[str]) -> dict[str, str]:
    """The header fields this server looks at, by lower-case name (values lower-cased)."""
    out = {}
    for line in lines[1:]:
        name, sep, value = line.partition(":")
        name = name.strip().lower()
        if sep and name in _FIELDS:
            out[name] = value.strip().lower()
    return out


def _matches(if_none_match: str, etag: str) -> bool:
    """Whether an ``If-None-Match`` value (lower-cased: tags here are) names ``etag`` (weakly, as
    RFC 9110 compares for GET), or is ``*``."""
    if not if_none_match:
        return False
    tags = {t.strip().removeprefix("w/") for t in if_none_match.split(",")}
    return etag in tags or "*" in tags


def _readable(sock: socket.socket, timeout: float) -> bool:
    """Whether ``sock`` has data (or its end) to read within ``timeout`` seconds (False for a
    descriptor ``select`` cannot take)."""
    try:
        return bool(select.select([sock], [], [], timeout)[0])
    except (OSError, ValueError):
        return False


def _static(name: str) -> bytes:
    return resources.files("photomap.live").joinpath("static", *name.split("/")).read_bytes()


class _Connection:
    """A client's connection: its socket, the bytes read past the last request (a pipelined next
    one), the answers given on it and when it was last parked."""

    __slots__ = ("sock", "address", "pending", "answered", "parked_at")

    def __init__(self, sock: socket.socket, address) -> None:
        self.sock, self.address = sock, address
        self.pending = bytearray()
        self.answered = 0
        self.parked_at = 0.0


class _Parking(threading.Thread):
    """Idle keep-alive connections, waiting for their next request in one selector instead of
    in answering threads. A connection that becomes readable goes back to the pool
    (``resume``); one idle for ``idle_s`` is closed (``drop``), as is the longest idle when a
    new connection needs its slot (:meth:`evict_oldest`)."""

    def __init__(self, idle_s: float, resume: Callable[[_Connection], None],
                 drop: Callable[[_Connection], None]) -> None:
        super().__init__(name="photomap-mapserver-idle", daemon=True)
        self.idle_s, self._resume, self._drop = idle_s, resume, drop
        self._selector = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._selector.register(self._wake_r, selectors.EVENT_READ, None)
        self._lock = threading.Lock()
        self._parked: dict[_Connection, None] = {}  # oldest first
        self._closing = False

    def park(self, conn: _Connection) -> None:
        conn.parked_at = time.monotonic()
        with self._lock:
            closing, wake = self._closing, not self._parked  # nothing parked: the loop waits without a deadline
            if not closing:
                self._selector.register(conn.sock, selectors.EVENT_READ, conn)
                self._parked[conn] = None
        if closing:
            self._drop(conn)
        elif wake:
            self._wake()

    def evict_oldest(self) -> bool:
        """Close the connection idle longest (its slot is free on return); False if none is idle."""
        with self._lock:
            conn = next(iter(self._parked), None)
            if conn is not None:
                self._unpark(conn)
        if conn is None:
            return False
        self._drop(conn)
        return True

    def close(self) -> None:
        with self._lock:
            self._closing = True
        self._wake()
        self.join(timeout=5.0)

    def run(self) -> None:
        while True:
            with self._lock:
                if self._closing:
                    break
                oldest = next(iter(self._parked), None)
            timeout = None if oldest is None else max(0.0, oldest.parked_at + self.idle_s - time.monotonic())
            events = self._selector.select(timeout)
            ready, expired = [], []
            with self._lock:
                for key, _ in events:
                    if key.data is None:
                        self._drain()
                    elif key.data in self._parked:
                        self._unpark(key.data)
                        ready.append(key.data)
                now = time.monotonic()
                for conn in list(self._parked):
                    if now - conn.parked_at < self.idle_s:
                        break
                    self._unpark(conn)
                    expired.append(conn)
            for conn in ready:
                self._resume(conn)
            for conn in expired:
                self._drop(conn)
        with self._lock:
            left = list(self._parked)
            for conn in left:
                self._unpark(conn)
        for conn in left:
            self._drop(conn)
        self._selector.close()
        self._wake_r.close()
        self._wake_w.close()

    def _unpark(self, conn: _Connection) -> None:  # under the lock
        del self._parked[conn]
        self._selector.unregister(conn.sock)

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"w")
        except OSError:  # closed, or its buffer full of wakes: awake anyway
            pass

    def _drain(self) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except OSError:
            pass


class _Server(HTTPServer):
    """An HTTP server answering in a bounded pool. At most ``max_connections`` connections are
    open: a new one beyond closes the longest idle keep-alive connection, or is closed at once
    when none is idle. Between requests a keep-alive connection waits in :class:`_Parking`, not
    in a pool thread."""

    daemon_threads = True
    request_queue_size = 64

    def __init__(self, address: tuple[str, int], owner: "MapServer", threads: int, max_connections: int,
                 keepalive_s: float) -> None:
        self.address_family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
        self.owner = owner
        self.keepalive_s = keepalive_s
        self._slots = threading.BoundedSemaphore(max_connections)
        self._open_lock = threading.Lock()
        self.open_connections = 0  # holding a slot (being answered or parked)
        self._pool = ThreadPoolExecutor(threads, "photomap-mapserver")
        super().__init__(address, _Handler)
        # no keep-alive (``keepalive_s`` 0): every answer closes its connection, nothing parks
        self._parking = _Parking(keepalive_s, self._resume, self._close) if keepalive_s > 0 else None
        if self._parking is not None:
            self._parking.start()

    def server_bind(self) -> None:
        socketserver.TCPServer.server_bind(self)  # HTTPServer's would look the name up (DNS)
        self.server_name, self.server_port = str(self.server_address[0]), int(self.server_address[1])

    def process_request(self, request, client_address) -> None:
        self.owner.stats["connections"] += 1
        if not self._slots.acquire(blocking=False) and not (
                self._parking is not None and self._parking.evict_oldest() and self._slots.acquire(blocking=False)):
            self.owner.stats["refused"] += 1
            self.shutdown_request(request)
            return
        with self._open_lock:
            self.open_connections += 1
        self._resume(_Connection(request, client_address))

    def _resume(self, conn: _Connection) -> None:
        try:
            self._pool.submit(self._work, conn)
        except RuntimeError:  # shutting down
            self._close(conn)

    def _work(self, conn: _Connection) -> None:
        keep = False
        try:
            handler = _Handler(conn, self)
            keep = self._serve(handler)
            # a client fetching several tiles sends the next request as soon as it has an answer:
            # taken here if it comes within LINGER_S, instead of parking and resuming (two thread
            # hand-offs and selector updates: most of a cached answer's CPU)
            while keep and _readable(conn.sock, LINGER_S):
                keep = self._serve(handler)
        except Exception:  # a client that vanishes mid-answer, a broken request
            self.owner.stats["errors"] += 1
        if keep:  # (only with keepalive_s > 0: there is a parking)
            self._parking.park(conn)
        else:
            self._close(conn)

    def _serve(self, handler: "_Handler") -> bool:
        """The connection's ready requests answered within the server's CPU budget."""
        budget = self.owner.budget
        budget.wait()
        t0 = time.thread_time()
        try:
            return handler.serve()
        finally:
            budget.spend(time.thread_time() - t0)

    def _close(self, conn: _Connection) -> None:
        with self._open_lock:  # its slot free before the client sees the end (and may connect again)
            self.open_connections -= 1
        self._slots.release()
        self.shutdown_request(conn.sock)

    def server_close(self) -> None:
        super().server_close()
        if getattr(self, "_parking", None) is not None:  # none without keep-alive, or when the port could not be bound
            self._parking.close()
        self._pool.shutdown(wait=False, cancel_futures=True)


class _Handler:
    """The requests of one connection while they come (:meth:`serve`): each read whole, answered
    with one send.

    The request line is parsed and of the headers only ``Connection``, ``Content-Length``,
    ``Transfer-Encoding``, ``Host`` and ``If-None-Match`` are looked at (nothing else here
    depends on them):
    ``http.server``'s parsing of them (the email package), its buffered files and its
    header-by-header writes were most of the server's CPU per answer beside the tile renders.
    HTTP/1.1 connections stay open unless the client says ``Connection: close`` (HTTP/1.0 ones
    when it says ``keep-alive``), for at most :data:`KEEPALIVE_REQUESTS` answers; a request with
    a body, or one answered with an error, closes its connection."""

    def __init__(self, conn: _Connection, server: _Server) -> None:
        self.conn, self.server = conn, server
        self.requestline = ""
        self.path = ""
        self.keep = False
        self.if_none_match = ""

    def serve(self) -> bool:
        """Answer the connection's requests while they are ready; True to park it for the next."""
        while True:
            if not self._one():
                return False
            self.conn.answered += 1
            if not self.conn.pending:  # a pipelined request is answered at once
                return True

    def _one(self) -> bool:
        """Read one request (line and headers) whole within the timeout and size limit and answer
        it; True when the connection stays open."""
        owner = self.server.owner
        conn = self.conn
        connection = conn.sock
        timeout_s = owner.timeout_s
        deadline = time.monotonic() + timeout_s
        data = conn.pending
        while (end := _head_end(data)) < 0 and len(data) <= MAX_REQUEST_BYTES:
            left = deadline - time.monotonic()
            if left <= 0:
                owner.stats["timeouts"] += 1
                return False
            connection.settimeout(left)
            try:
                chunk = connection.recv(4096)
            except (TimeoutError, socket.timeout):
                owner.stats["timeouts"] += 1
                return False
            except OSError:
                return False
            if not chunk:  # the client closed it (between requests: as a keep-alive client does)
                return False
            data += chunk
        if not 0 <= end <= MAX_REQUEST_BYTES:  # no blank line within the limit
            owner.stats["too_large"] += 1
            self._raw(431, b"request too large\n", "text/plain")
            return False
        head = bytes(data[:end]).decode("latin-1")
        del data[:end]
        connection.settimeout(timeout_s)  # the answer must be taken within it too
        lines = head.split("\n")
        self.requestline = lines[0].rstrip("\r")
        words = self.requestline.split()
        if len(words) != 3 or not _VERSION.match(words[2]):
            self._raw(400, b"bad request\n", "text/plain")
            return False
        fields = _fields(lines)
        method, self.path, version = words
        self.if_none_match = fields.get("if-none-match", "")
        if version == "HTTP/1.1" and "host" not in fields:
            self._raw(400, b"no Host header\n", "text/plain")
            return False
        if method not in ("GET", "HEAD"):
            self._raw(501, b"unsupported method\n", "text/plain")
            return False
        tokens = {t.strip() for t in fields.get("connection", "").split(",")}
        self.keep = (self.server.keepalive_s > 0 and conn.answered + 1 < KEEPALIVE_REQUESTS
                     and fields.get("content-length", "0") == "0" and "transfer-encoding" not in fields
                     and ("keep-alive" in tokens if version == "HTTP/1.0" else "close" not in tokens))
        self._answer(head=method == "HEAD")
        return self.keep

    def _raw(self, code: int, body: bytes, ctype: str) -> None:
        """An answer before the request is known (no error if the client is gone)."""
        try:
            self._send(code, body, ctype, head=False)
        except OSError:
            pass

    def _send(self, code: int, body: bytes, ctype: str, head: bool, cache: str = "no-cache",
              etag: str | None = None) -> None:
        """The whole answer (status line, headers and, unless ``head``, the body) in one send;
        a 304 has no body and no length."""
        if code >= 400 and code != 404:  # an error answer closes the connection
            self.keep = False
        persist = (f"keep-alive\r\nKeep-Alive: timeout={self.server.keepalive_s:g}" if self.keep else "close")
        length = "" if code == 304 else f"Content-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
        tag = "" if etag is None else f"ETag: {etag}\r\n"
        text = (f"HTTP/1.1 {code} {_PHRASES.get(code, '')}\r\nServer: photomap\r\n"
                f"Date: {formatdate(usegmt=True)}\r\n{length}{tag}"
                f"Cache-Control: {cache}\r\nAccess-Control-Allow-Origin: *\r\nConnection: {persist}\r\n\r\n")
        if log.isEnabledFor(logging.DEBUG):  # one per request: not even formatted otherwise
            log.debug("map server: %s \"%s\" %d %d", self.conn.address[0], self.requestline, code, len(body))
        self.conn.sock.sendall(text.encode("latin-1") if head else text.encode("latin-1") + body)

    def _json(self, obj: dict, head: bool, ctype: str = "application/json") -> None:
        self._send(200, _encode(obj), ctype, head)

    def _answer(self, head: bool) -> None:
        owner = self.server.owner
        owner.stats["requests"] += 1
        owner.pause()
        path = self.path.split("?", 1)[0].split("#", 1)[0]
        try:
            m = _TILE_PATH.match(path)
            if m:
                tile = owner.tile(m.group(1), int(m.group(2)), int(m.group(3)), int(m.group(4)))
                if tile is None:
                    self._send(404, b"no such tile\n", "text/plain", head)
                elif _matches(self.if_none_match, tile.etag):
                    owner.stats["not_modified"] += 1
                    self._send(304, b"", "", head=True, etag=tile.etag)
                else:
                    self._send(200, tile.body, tile_type(tile.body), head, etag=tile.etag)
            elif path == "/status.json":
                self._json(owner.status(), head)
            elif path == "/track.geojson":
                self._send(200, owner.answer("track", track_geojson), "application/geo+json", head)
            elif path == "/footprint.geojson":
                self._send(200, owner.answer("footprint", footprint_geojson), "application/geo+json", head)
            elif path == "/hazards.geojson":
                self._json(owner.hazard_spots(), head, "application/geo+json")
            elif path in ("/", "/index.html"):
                self._send(200, owner.page, "text/html; charset=utf-8", head)
            elif path.startswith("/leaflet/") and path[len("/leaflet/"):] in _STATIC:
                name = path[len("/leaflet/"):]
                self._send(200, _static("leaflet/" + name), _STATIC[name], head, "max-age=86400")
            else:
                self._send(404, b"not found\n", "text/plain", head)
        except (BrokenPipeError, ConnectionResetError, TimeoutError, socket.timeout):
            owner.stats["errors"] += 1
        except Exception as exc:  # a bug must not take the server (or the map) down
            owner.stats["errors"] += 1
            owner.warn_once(f"answer:{type(exc).__name__}", f"map server: {path} failed: {type(exc).__name__}: {exc}")
            try:
                self._send(500, b"internal error\n", "text/plain", head)
            except OSError:
                pass


class MapServer:
    """The HTTP server over a :class:`LiveMap` (module docstring).

    ``on_frame`` and ``on_georeference`` are the pipeline's hooks (a frame sink and
    :attr:`MappingPipeline.on_georeference`). ``hazards``: a thread-safe callable returning a
    GeoJSON FeatureCollection dict (points with properties such as ``id``, ``peak``,
    ``first_seen``), called per ``/hazards.geojson`` request; None serves an empty collection.
    ``port`` 0 takes a free port (see :attr:`port`).
    """

    def __init__(self, cfg: MapServerConfig, address: str = "127.0.0.1", port: int | None = None, *,
                 hazards: Hazards | None = None) -> None:
        self.live = LiveMap(cfg.tile_hz)
        self.cache = TileCache(cfg.cache_tiles, cfg.min_render_interval_s, jpeg_quality=cfg.jpeg_quality)
        self.hazards = hazards
        self.timeout_s = float(cfg.timeout_s)
        self._closing = threading.Event()
        # the answering threads' CPU: at most cfg.cpu_share of a core (beyond, answers wait)
        self.budget = CpuBudget(cfg.cpu_share, sleep=self._closing.wait)
        self.stats = {"connections": 0, "requests": 0, "not_modified": 0, "refused": 0, "timeouts": 0,
                      "too_large": 0, "errors": 0}
        # answers built from the live map, by name: (what they were built from, the answer)
        self._answers: dict[str, tuple[tuple, object]] = {}
        self._warned: set[str] = set()
        # live: the answers' Python code waits while the worker maps a frame (the pipeline's
        # MappingPipeline.worker_first); None: never waits
        self.gate: WorkerFirst | None = None
        self.page = _static("index.html")
        try:
            self._server = _Server((address, cfg.port if port is None else int(port)), self, cfg.threads,
                                   cfg.max_connections, float(cfg.keepalive_s))
        except OSError as exc:
            raise InputError(f"map server cannot listen on {address}:{cfg.port if port is None else port}: "
                             f"{exc.strerror or exc}") from None
        self.address = address
        self.port = int(self._server.server_address[1])
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="photomap-mapserver-accept", daemon=True)
        self._thread.start()
        self._max_raw = int(cfg.max_raw_tiles)
        self._packer = threading.Thread(target=self._pack, name="photomap-mapserver-pack", daemon=True)
        self._packer.start()

    @classmethod
    def from_config(cls, cfg: MapServerConfig, listen: str | None = None, *,
                    hazards: Hazards | None = None) -> "MapServer | None":
        """The server ``listen`` (``--map-server``; default ``map_server.listen``) asks for, or
        None when it is off (``""``/``none``)."""
        configured = cfg.listen
        text = configured if listen is None else listen
        if text is None or str(text).strip().lower() in ("", "none", "off"):
            return None
        address, port = parse_listen(str(text), cfg.port)
        return cls(cfg, address, port, hazards=hazards)

    @property
    def url(self) -> str:
        host = f"[{self.address}]" if ":" in self.address else self.address
        if host in ("0.0.0.0", "[::]"):
            host = socket.gethostname()
        return f"http://{host}:{self.port}/"

    @property
    def open_connections(self) -> int:
        """Connections open right now (being answered, or idle between keep-alive requests)."""
        return self._server.open_connections

    def on_frame(self, event: FrameEvent) -> None:
        self.live.on_frame(event)

    def on_georeference(self, segment: int, geo) -> None:
        self.live.on_georeference(segment, geo)

    def pause(self) -> None:
        """A pause point of the server threads (see :attr:`gate`)."""
        gate = self.gate
        if gate is not None:
            gate.wait()

    def warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            log.warning(text)

    # ------------------------------------------------------------------ answers (server threads)
    def tile(self, kind: str, z: int, x: int, y: int) -> Tile | None:
        """A tile, or None when there is no such tile (zoom out of range, no georeference)."""
        snap = self.live.snapshot()
        if kind == "tiles":
            if snap.georeference is None or not 0 <= z <= min(wm.MAX_ZOOM, snap.max_zoom() + OVERZOOM):
                return None
            if not (0 <= x < 2 ** z and 0 <= y < 2 ** z):
                return None
            return self.cache.get(snap, "xyz", x, y, z, pause=self.pause)
        if not 0 <= z <= PIXEL_ZOOM:
            return None
        if snap.served_segment is None:
            return EMPTY_TILE
        return self.cache.get(snap, "pixel", x, y, z, pause=self.pause)

    def answer(self, name: str, build: Callable[[Snapshot], dict], encode: bool = True):
        """``build(snapshot)`` (JSON-encoded unless ``encode`` is False), built again only when
        what it shows may have changed (a frame, a copied tile, a georeference), not per request."""
        snap = self.live.snapshot()
        key = (snap.frames_in, snap.version, snap.geo_version)
        got = self._answers.get(name)
        if got is None or got[0] != key:
            obj = build(snap)
            got = self._answers[name] = (key, _encode(obj) if encode else obj)
        return got[1]

    def status(self) -> dict:
        out = dict(self.answer("status", status, encode=False))
        out.update({"server": {**self.stats, "open": self.open_connections, "budget_waits": self.budget.waits},
                    "tile_renders": self.cache.renders,
                    "tile_hits": self.cache.hits})
        return out

    def hazard_spots(self) -> dict:
        if self.hazards is None:
            return {"type": "FeatureCollection", "features": []}
        try:
            spots = self.hazards()
        except Exception as exc:
            self.warn_once("hazards", f"map server: hazard spots not served: {type(exc).__name__}: {exc}")
            return {"type": "FeatureCollection", "features": []}
        return hazards_geojson(spots, self.live.snapshot())

    def _pack(self) -> None:
        """Once a second, pack the tiles beyond ``map_server.max_raw_tiles`` (the oldest copies)."""
        while not self._closing.wait(1.0):
            try:
                self.live.pack(self._max_raw, self.pause)
            except Exception as exc:  # memory, not the map: say it once and go on
                self.warn_once("pack", f"map server: tiles not packed: {type(exc).__name__}: {exc}")

    def close(self) -> None:
        """Stop answering and close the port."""
        self._closing.set()
        self._packer.join(timeout=5.0)
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5.0)


def write_run_tiles(out_dir: str | Path) -> dict | None:
    """Write the finished run's web tiles to ``out_dir/xyz`` exactly as ``photomap export
    --tiles`` does; None (one INFO line) when the run has no georeferenced map."""
    from photomap.io.mapsource import run_raster
    from photomap.io.runfiles import RunFiles
    from photomap.io.xyz_tiles import write_xyz_tiles

    out = Path(out_dir)
    try:
        return write_xyz_tiles(out / "xyz", run_raster(RunFiles(out)))
    except PhotomapError as exc:
        log.info("xyz tiles not written: %s", exc)
        return None
    except OSError as exc:
        log.error("cannot write xyz tiles: %s", exc.strerror or exc)
        return None

