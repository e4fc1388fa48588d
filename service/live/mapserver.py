"""The live map over HTTP, for the ground station (docs/live-map.md).

``--map-server [ADDR:]PORT`` (or ``map_server.listen``) on ``run`` and ``replay`` starts
:class:`MapServer`: a small HTTP server in its own threads, fed by a
:class:`~photomap.live.livemap.LiveMap` (the pipeline's sink: it copies what is shown, the server
never reads the pipeline's state). It serves:

``/tiles/{z}/{x}/{y}.png``
    XYZ web-mercator tiles of the georeferenced live map, 256 px RGBA, transparent where nothing
    is mapped, zoom 0 .. ``max_zoom`` (the map's resolution) and :data:`OVERZOOM` more
    (upsampled; 404 beyond, and before a georeference): the custom map URL form of
    QGroundControl, Mission Planner, QGIS "XYZ Tiles" and Leaflet.
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
connections are open at once (more are closed at once), a request (line and headers) must arrive
whole within ``timeout_s`` and within 8 KiB, only GET and HEAD are answered, one request per
connection. The mapping worker never waits for any of it.

The network: the server listens on ``127.0.0.1`` unless an address is given. It has no
authentication and is read-only; whoever reaches the port sees the map.
"""

from __future__ import annotations

import json
import logging
import re
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
from photomap.live.livemap import EMPTY_PNG, PIXEL_ZOOM, LiveMap, Snapshot, TileCache, footprint_geojson, \
    hazards_geojson, status, tile_type, track_geojson
from photomap.live.viewer import parse_serve_address
from photomap.mapping.events import FrameEvent
from photomap.mapping.threads import WorkerFirst

log = logging.getLogger(__name__)

MAX_REQUEST_BYTES = 8192
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


def _static(name: str) -> bytes:
    return resources.files("photomap.live").joinpath("static", *name.split("/")).read_bytes()


class _Server(HTTPServer):
    """An HTTP server answering in a bounded pool; a connection beyond ``max_connections`` is
    closed at once."""

    daemon_threads = True
    request_queue_size = 64

    def __init__(self, address: tuple[str, int], owner: "MapServer", threads: int, max_connections: int) -> None:
        self.address_family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
        self.owner = owner
        self._slots = threading.BoundedSemaphore(max_connections)
        self._pool = ThreadPoolExecutor(threads, "photomap-mapserver")
        super().__init__(address, _Handler)

    def server_bind(self) -> None:
        socketserver.TCPServer.server_bind(self)  # HTTPServer's would look the name up (DNS)
        self.server_name, self.server_port = str(self.server_address[0]), int(self.server_address[1])

    def process_request(self, request, client_address) -> None:
        if not self._slots.acquire(blocking=False):
            self.owner.stats["refused"] += 1
            self.shutdown_request(request)
            return
        try:
            self._pool.submit(self._work, request, client_address)
        except RuntimeError:  # shutting down
            self._slots.release()
            self.shutdown_request(request)

    def _work(self, request, client_address) -> None:
        try:
            self.finish_request(request, client_address)
        except Exception:  # a client that vanishes mid-answer, a broken request
            self.owner.stats["errors"] += 1
        finally:
            self.shutdown_request(request)
            self._slots.release()

    def server_close(self) -> None:
        super().server_close()
        self._pool.shutdown(wait=False, cancel_futures=True)


class _Handler(socketserver.BaseRequestHandler):
    """One request per connection: read it whole (:meth:`handle`), answer it with one send.

    The request line is parsed here and the headers are not (nothing here depends on them):
    ``http.server``'s parsing of them (the email package), its buffered files and its
    header-by-header writes were most of the server's CPU per answer beside the tile renders."""

    server: _Server
    requestline: str = ""
    path: str = ""

    def handle(self) -> None:
        """Read the request (line and headers) whole within the timeout and size limit, then answer."""
        owner = self.server.owner
        connection = self.request
        timeout_s = owner.timeout_s
        deadline = time.monotonic() + timeout_s
        data = bytearray()
        while b"\r\n\r\n" not in data and b"\n\n" not in data:
            left = deadline - time.monotonic()
            if left <= 0:
                owner.stats["timeouts"] += 1
                return
            connection.settimeout(left)
            try:
                chunk = connection.recv(4096)
            except (TimeoutError, socket.timeout):
                owner.stats["timeouts"] += 1
                return
            except OSError:
                return
            if not chunk:
                return
            data += chunk
            if len(data) > MAX_REQUEST_BYTES:
                owner.stats["too_large"] += 1
                self._raw(431, b"request too large\n", "text/plain")
                return
        connection.settimeout(timeout_s)  # the answer must be taken within it too
        self.requestline = bytes(data.split(b"\n", 1)[0]).decode("latin-1").rstrip("\r")
        words = self.requestline.split()
        if len(words) != 3 or not _VERSION.match(words[2]):
            self._raw(400, b"bad request\n", "text/plain")
            return
        method, self.path = words[0], words[1]
        if method not in ("GET", "HEAD"):
            self._raw(501, b"unsupported method\n", "text/plain")
            return
        self._answer(head=method == "HEAD")

    def _raw(self, code: int, body: bytes, ctype: str) -> None:
        """An answer before the request is known (no error if the client is gone)."""
        try:
            self._send(code, body, ctype, head=False)
        except OSError:
            pass

    def _send(self, code: int, body: bytes, ctype: str, head: bool, cache: str = "no-cache") -> None:
        """The whole answer (status line, headers and, unless ``head``, the body) in one send."""
        text = (f"HTTP/1.0 {code} {_PHRASES.get(code, '')}\r\nServer: photomap\r\n"
                f"Date: {formatdate(usegmt=True)}\r\nContent-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
                f"Cache-Control: {cache}\r\nAccess-Control-Allow-Origin: *\r\nConnection: close\r\n\r\n")
        if log.isEnabledFor(logging.DEBUG):  # one per request: not even formatted otherwise
            log.debug("map server: %s \"%s\" %d %d", self.client_address[0], self.requestline, code, len(body))
        self.request.sendall(text.encode("latin-1") if head else text.encode("latin-1") + body)

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
                body = owner.tile(m.group(1), int(m.group(2)), int(m.group(3)), int(m.group(4)))
                if body is None:
                    self._send(404, b"no such tile\n", "text/plain", head)
                else:
                    self._send(200, body, tile_type(body), head)
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
        self.stats = {"requests": 0, "refused": 0, "timeouts": 0, "too_large": 0, "errors": 0}
        # answers built from the live map, by name: (what they were built from, the answer)
        self._answers: dict[str, tuple[tuple, object]] = {}
        self._warned: set[str] = set()
        # live: the answers' Python code waits while the worker maps a frame (the pipeline's
        # MappingPipeline.worker_first); None: never waits
        self.gate: WorkerFirst | None = None
        self.page = _static("index.html")
        try:
            self._server = _Server((address, cfg.port if port is None else int(port)), self, cfg.threads,
                                   cfg.max_connections)
        except OSError as exc:
            raise InputError(f"map server cannot listen on {address}:{cfg.port if port is None else port}: "
                             f"{exc.strerror or exc}") from None
        self.address = address
        self.port = int(self._server.server_address[1])
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="photomap-mapserver-accept", daemon=True)
        self._thread.start()
        self._max_raw = int(cfg.max_raw_tiles)
        self._closing = threading.Event()
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
    def tile(self, kind: str, z: int, x: int, y: int) -> bytes | None:
        """A tile's PNG, or None when there is no such tile (zoom out of range, no georeference)."""
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
            return EMPTY_PNG
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
        out.update({"server": dict(self.stats), "tile_renders": self.cache.renders, "tile_hits": self.cache.hits})
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

