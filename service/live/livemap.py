"""The map server's own copy of the live map, and the web tiles rendered from it.

:meth:`LiveMap.on_frame` is a sink of the mapping pipeline (a
:class:`~photomap.mapping.events.FrameEvent` per frame, in the worker thread). It only copies:
the frame's pose, counts and telemetry position always; the map tiles painted or re-rendered
since the last copy (``touched``) at most ``tile_hz`` times a second (each a copy of the tile's
pixels, ~50 us). Each copy replaces the tile in a dictionary under a lock held for that
assignment only, so the worker never waits on a request. The server threads read only this
copy, never the pipeline's maps. :meth:`LiveMap.on_georeference` is told the main map's GPS fit
(:data:`~photomap.mapping.events.GeoreferenceSink`); a new fit that moves no corner of the served
map by half a map pixel or more against the one served is not taken (the served tiles stay
valid: a ground station does not fetch the whole view again for a refit it cannot see).
:meth:`LiveMap.pack` (the server's packing
thread) packs the oldest copies beyond a count, so that the copy of a long flight's map stays
small.

Tiles (rendered on request, :class:`TileCache`):

- georeferenced: XYZ web-mercator tiles of the georeferenced segment (each pixel placed as
  ``photomap export --tiles`` places it, :func:`photomap.io.xyz_tiles.tile_source_grid`), zoom
  0 .. ``max_zoom`` (the zoom of the map's resolution,
  :func:`photomap.geo.webmercator.zoom_for_resolution`);
- in the map's own pixel frame (no georeference yet): tile ``(x, y)`` at zoom ``z`` covers map
  pixels ``[256 x, 256 (x + 1)) * 2**(PIXEL_ZOOM - z)`` (the same for y) of the current segment,
  so at ``PIXEL_ZOOM`` one tile pixel is one map pixel: Leaflet ``L.CRS.Simple`` with
  ``latlng = (-y, x) / 2**PIXEL_ZOOM``.

Both are 256 x 256 PNGs: RGBA, transparent where nothing is mapped, and RGB where every pixel
is mapped (or, with a JPEG quality, JPEGs there: :func:`render_png`). A rendered tile is kept with
the versions of the map tiles it was made from; it is served again while they are unchanged, and
while younger than ``min_render_interval_s`` even when they changed (a client asking for a busy
tile many times a second gets one render per interval). Each rendered picture has an entity tag
(:class:`Tile`), the same for as long as the picture is: a client that has it is answered "not
modified" (HTTP 304, no body) instead of the picture again.
"""

from __future__ import annotations

import itertools
import math
import os
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, NamedTuple

import cv2
import numpy as np

from photomap.core.mosaic import unpremultiply
from photomap.core.thinned import ThinnedPath
from photomap.geo import webmercator as wm
from photomap.geo.georef import Georeference, utm_forward
from photomap.geometry import frame_centre
from photomap.io.pngstream import encode_png
from photomap.io.xyz_tiles import tile_source_grid, upsample_grid
from photomap.live.viewer import frame_outline, geo_footprint

if TYPE_CHECKING:
    from photomap.mapping.events import FrameEvent, TileReader

TileKey = tuple[int, int]
PIXEL_ZOOM = 8  # pixel-frame zoom at which one tile pixel is one map pixel
_MAX_PATH = 5000  # track points kept (thinned by halving beyond)
_FPS_WINDOW_S = 5.0


EMPTY_PNG = encode_png(np.zeros((wm.TILE_PX, wm.TILE_PX, 4), np.uint8))


def _bgra(image: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """BGRA uint8 of a BGR or grey uint8 image and its alpha, in one OpenCV pass (np.dstack
    took 7 times as long: the worker copies the painted tiles with it)."""
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGRA if image.ndim == 2 else cv2.COLOR_BGR2BGRA)
    out[..., 3] = alpha
    return out


def _alpha4(bgra: np.ndarray) -> np.ndarray:
    """``(a, a, a, 255)`` per pixel of a BGRA uint8 image: the factor that premultiplies its
    colour (``* a / 255``) or divides it out (``* 255 / a``) leaving its alpha as it is."""
    return cv2.cvtColor(np.ascontiguousarray(bgra[..., 3]), cv2.COLOR_GRAY2BGRA)


def _premultiplied(bgra: np.ndarray) -> np.ndarray:
    a = bgra[..., 3:4].astype(np.float32) * (1.0 / 255.0)
    return np.concatenate([bgra[..., :3].astype(np.float32) * a, a], axis=2)


def _unpremultiplied(pre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(bgr uint8, alpha uint8) of a premultiplied float32 BGRA image (alpha 0..1)
    (:func:`photomap.core.mosaic.unpremultiply`)."""
    b, g, r, alpha = unpremultiply(pre)
    return cv2.merge([b, g, r]), alpha


_PACK_JPEG_QUALITY = 90


class _Tile:
    """A copied map tile: BGRA uint8 pixels, its version (grows with every copy), and its
    halvings (``level(n)``: side ``ts >> n``, alpha-weighted 2x2 means; made on first use).

    A *packed* tile (:meth:`packed`, for tiles the flight has left) keeps its colour as JPEG and
    its alpha as PNG (about a tenth of the pixels' bytes) and its halvings from ``ts / 4`` down;
    its full-size pixels are decoded when asked for. Never changed once shared: packing makes a
    new tile."""

    __slots__ = ("version", "_bgra", "_jpeg", "_alpha", "mips")

    def __init__(self, bgra: np.ndarray | None, version: int, packed: tuple[bytes, bytes] | None = None,
                 mips: dict | None = None) -> None:
        self.version = version
        self._bgra = bgra
        self._jpeg, self._alpha = packed if packed is not None else (None, None)
        self.mips: dict[int, np.ndarray] = mips if mips is not None else {}

    @property
    def is_packed(self) -> bool:
        return self._bgra is None

    @property
    def nbytes(self) -> int:
        """Bytes held (pixels or their encodings, and the halvings)."""
        own = self._bgra.nbytes if self._bgra is not None else len(self._jpeg) + len(self._alpha)
        return own + sum(m.nbytes for m in self.mips.values())

    @property
    def bgra(self) -> np.ndarray:
        if self._bgra is not None:
            return self._bgra
        colour = cv2.imdecode(np.frombuffer(self._jpeg, np.uint8), cv2.IMREAD_COLOR)
        alpha = cv2.imdecode(np.frombuffer(self._alpha, np.uint8), cv2.IMREAD_GRAYSCALE)
        return _bgra(colour, alpha)

    def level(self, n: int) -> np.ndarray:
        if n == 0:
            return self.bgra
        got = self.mips.get(n)
        if got is None:
            prev = self.level(n - 1)
            h, w = prev.shape[:2]
            half = cv2.resize(_premultiplied(prev), (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_AREA)
            image, alpha = _unpremultiplied(half)
            got = self.mips[n] = _bgra(image, alpha)
        return got

    def packed(self) -> "_Tile":
        """This tile packed (see the class docstring); itself when already packed."""
        if self._bgra is None:
            return self
        side = self._bgra.shape[0]
        levels = max(0, int(math.log2(side)))
        for n in range(2, levels + 1):
            self.level(n)
        ok, jpeg = cv2.imencode(".jpg", np.ascontiguousarray(self._bgra[..., :3]),
                                [cv2.IMWRITE_JPEG_QUALITY, _PACK_JPEG_QUALITY])
        if not ok:
            return self
        return _Tile(None, self.version, (jpeg.tobytes(), encode_png(self._bgra[..., 3])),
                     {n: m for n, m in self.mips.items() if n >= 2})


@dataclass(frozen=True)
class Snapshot:
    """What the server reads of the live map at one moment (immutable; tiles are shared)."""

    frames_in: int
    frame: int | None  # index of the latest frame
    registered: int
    segments: int
    segment: int | None  # of the latest frame
    fps: float
    frame_size: tuple[int, int] | None
    pose: np.ndarray | None  # the latest posed frame's, in map pixels of pose_segment
    pose_segment: int | None
    gps: tuple[float, float] | None  # the latest telemetry position (lat, lon)
    gps_sample: tuple | None  # (the latest sample with a position, the focal length in px)
    telemetry: str  # none | no_fix | gps | georeferenced
    georeference: tuple[int, Georeference] | None
    geo_version: int
    tile_size: int
    tiles: dict[TileKey, _Tile]  # of the served segment (georeferenced one, else the current one)
    path: list[tuple[float, float]]  # frame centres of the served segment, map pixels
    version: int  # grows whenever a served tile or the georeference changes
    # what is worked out from ``tiles`` once, shared by the snapshots holding the same tiles
    memo: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def served_segment(self) -> int | None:
        return self.georeference[0] if self.georeference is not None else self.segment

    def bounds_px(self) -> tuple[int, int, int, int] | None:
        """``(x, y, w, h)`` map pixels of the served tiles' rectangle, or None when there are none
        (a pass over the tiles once per change of them: :attr:`memo`)."""
        if not self.tiles:
            return None
        box = self.memo.get("bounds_px")
        if box is None:
            ts = self.tile_size
            xs = [k[0] for k in self.tiles]
            ys = [k[1] for k in self.tiles]
            box = self.memo["bounds_px"] = (min(xs) * ts, min(ys) * ts, (max(xs) - min(xs) + 1) * ts,
                                            (max(ys) - min(ys) + 1) * ts)
        return box

    def max_zoom(self) -> int:
        """The zoom of the map's resolution (georeferenced), else :data:`PIXEL_ZOOM`."""
        if self.georeference is None:
            return PIXEL_ZOOM
        geo = self.georeference[1]
        lat = geo.origin_lat
        return wm.zoom_for_resolution(lat, geo.metres_per_px)

    def to_lonlat(self, xy: np.ndarray) -> np.ndarray:
        """Map pixels (n, 2) of the georeferenced segment -> (n, 2) lon, lat degrees."""
        lat, lon = self.georeference[1].to_latlon(np.asarray(xy, float).reshape(-1, 2))
        return np.c_[lon, lat]


class LiveMap:
    """The live map as the server sees it (module docstring). ``tile_hz``: map tiles are copied
    at most this often; ``max_path``: track points kept per segment."""

    def __init__(self, tile_hz: float = 2.0, max_path: int = _MAX_PATH) -> None:
        self._lock = threading.Lock()
        self._period = 1.0 / float(tile_hz)
        self._max_path = max(2, int(max_path))
        self._tiles: dict[int, dict[TileKey, _Tile]] = {}  # segment -> its copied tiles
        self._raw: OrderedDict[tuple[int, TileKey], None] = OrderedDict()  # unpacked tiles, oldest copy first
        self._tile_size = 256
        self._version = 0
        self._dirty: dict[int, set[TileKey]] = {}  # segment -> tiles changed since their copy
        self._extent: dict[int, tuple[int, int, int, int]] = {}  # segment -> tile keys' (x0, y0, x1, y1), grown
        self._readers: dict[int, TileReader] = {}  # segment -> its map (read in the worker only)
        self._last_copy = -math.inf
        self._paths: dict[int, ThinnedPath[tuple[float, float]]] = {}  # segment -> its frame centres
        self._frames_in = 0
        self._frame: int | None = None
        self._registered = 0
        self._segments: set[int] = set()
        self._segment: int | None = None
        self._arrivals: deque[float] = deque()
        self._frame_size: tuple[int, int] | None = None
        self._pose: np.ndarray | None = None
        self._pose_segment: int | None = None
        self._gps: tuple[float, float] | None = None
        self._gps_sample: tuple | None = None
        self._had_telemetry = False
        self._georef: tuple[int, Georeference] | None = None
        self._geo_version = 0
        # the snapshots' tiles and memo, by (served segment, version)
        self._shown: tuple[tuple | None, dict[TileKey, _Tile], dict] = (None, {}, {})
        self.errors = 0

    # ------------------------------------------------------------------ worker thread
    def on_frame(self, event: FrameEvent) -> None:
        """The pipeline sink: copy what the server shows. Never raises."""
        try:
            self._on_frame(event)
        except Exception:  # the server must never cost the map
            self.errors += 1

    def _on_frame(self, event: FrameEvent) -> None:
        now = time.monotonic()
        seg = event.segment
        posed = event.pose is not None
        if event.tiles is not None:
            if self._readers.get(seg) is not event.tiles or any("joined" in m for m in event.messages):
                self._dirty[seg] = set(event.tiles.tiles())  # a map new to the server: all of it
            self._readers[seg] = event.tiles
            self._tile_size = int(event.tiles.tile_size)
        if event.touched:
            self._dirty.setdefault(seg, set()).update(event.touched)
        if posed:
            cx, cy = frame_centre(*event.frame_size)
            (a, b, c), (d, e, f) = np.asarray(event.pose, float).tolist()  # in floats: a third of NumPy's time
            x, y = a * cx + b * cy + c, d * cx + e * cy + f
            path = self._paths.get(seg)
            if path is None:
                path = ThinnedPath(self._max_path)
                with self._lock:
                    self._paths[seg] = path
            # no lock: the server takes the points list and then its length (see snapshot)
            if event.corrected_path is not None:
                path.rebuild(np.asarray(event.corrected_path, float)[:, :2])
            else:
                path.append((x, y))
        sample = event.telemetry
        with self._lock:
            self._frames_in += 1
            self._frame = int(event.index)
            if event.status in ("reference", "registered"):
                self._registered += 1
            self._segments.add(seg)
            self._segment = seg
            self._frame_size = event.frame_size
            self._arrivals.append(now)
            while self._arrivals and self._arrivals[0] < now - _FPS_WINDOW_S:
                self._arrivals.popleft()
            if posed:
                self._pose, self._pose_segment = np.array(event.pose, float), seg
            if sample is not None:
                self._had_telemetry = True
                if sample.lat is not None and sample.lon is not None:
                    self._gps = (float(sample.lat), float(sample.lon))
                    self._gps_sample = (sample, event.focal_px)
        if now - self._last_copy >= self._period or event.new_segment:
            self._last_copy = now
            self._copy_dirty()

    def _copy_dirty(self) -> None:
        """Copy the changed tiles of every segment (worker thread) and swap them in."""
        for seg, keys in list(self._dirty.items()):
            reader = self._readers.get(seg)
            if reader is None or not keys:
                continue
            copies: dict[TileKey, np.ndarray | None] = {}
            for key in keys:
                try:
                    image, alpha = reader.tile_image(key, copy=False)  # views: _bgra copies them
                except KeyError:  # cleared (re-rendered later) or never covered
                    copies[key] = None
                    continue
                copies[key] = _bgra(image, alpha)
            keys.clear()
            with self._lock:
                store = self._tiles.setdefault(seg, {})
                for key, pixels in copies.items():
                    if pixels is None:
                        self._raw.pop((seg, key), None)
                        if store.pop(key, None) is not None:
                            self._version += 1
                        continue
                    self._version += 1
                    store[key] = _Tile(pixels, self._version)
                    x0, y0, x1, y1 = self._extent.get(seg, (key[0], key[1], key[0], key[1]))
                    self._extent[seg] = (min(x0, key[0]), min(y0, key[1]), max(x1, key[0]), max(y1, key[1]))
                    self._raw[(seg, key)] = None
                    self._raw.move_to_end((seg, key))

    def flush(self) -> None:
        """Copy every tile changed so far (the worker thread, e.g. at the end of the run)."""
        self._copy_dirty()

    # ------------------------------------------------------------------ writer / worker thread
    def on_georeference(self, segment: int, geo: Georeference) -> None:
        """The pipeline's live (and final) GPS fit of the main map segment (not taken when it
        moves the served map by less than half a map pixel: module docstring)."""
        with self._lock:
            old, extent = self._georef, self._extent.get(int(segment))
            if old is not None and old[0] == int(segment) and extent is not None \
                    and _refit_moves_px(old[1], geo, extent, self._tile_size) < 0.5:
                return
            self._georef = (int(segment), geo)
            self._geo_version += 1
            self._version += 1

    # ------------------------------------------------------------------ the packing thread
    def pack(self, max_raw: int, pause: Callable[[], None] = lambda: None) -> int:
        """Pack the least recently copied tiles beyond ``max_raw`` unpacked ones (all segments);
        ``pause`` is called between tiles. Returns how many were packed."""
        with self._lock:
            excess = len(self._raw) - max(0, int(max_raw))
            if excess <= 0:
                return 0
            oldest = [(seg, key, self._tiles[seg][key]) for seg, key in itertools.islice(self._raw, excess)]
        done = 0
        for seg, key, tile in oldest:
            pause()
            packed = tile.packed()
            with self._lock:
                store = self._tiles.get(seg)
                if store is not None and store.get(key) is tile:  # not copied again meanwhile
                    store[key] = packed
                    self._raw.pop((seg, key), None)
                    done += 1
        if done:
            with self._lock:
                self._shown = (None, {}, {})  # the next snapshot holds the packed tiles, not the raw ones
        return done

    def nbytes(self) -> int:
        """Bytes the copied tiles hold."""
        with self._lock:
            tiles = [t for store in self._tiles.values() for t in store.values()]
        return sum(t.nbytes for t in tiles)

    # ------------------------------------------------------------------ server threads
    def snapshot(self) -> Snapshot:
        """The live map now (cheap: references, no pixel copies)."""
        with self._lock:
            georef = self._georef
            served = georef[0] if georef is not None else self._segment
            span = (self._arrivals[-1] - self._arrivals[0]) if len(self._arrivals) > 1 else 0.0
            fps = (len(self._arrivals) - 1) / span if span > 0 else 0.0
            if not self._had_telemetry:
                telemetry = "none"
            elif georef is not None:
                telemetry = "georeferenced"
            else:
                telemetry = "gps" if self._gps is not None else "no_fix"
            shown = (served, self._version)
            if self._shown[0] != shown:  # copied once per change (at most tile_hz a second), not per request
                self._shown = (shown, dict(self._tiles.get(served, {})) if served is not None else {}, {})
            path = self._paths.get(served) if served is not None else None
            points = path.points if path is not None else []
            n = len(points)
            _, tiles, memo = self._shown
            snap = (self._frames_in, self._frame, self._registered, len(self._segments), self._segment, fps,
                    self._frame_size, self._pose, self._pose_segment, self._gps, self._gps_sample, telemetry,
                    georef, self._geo_version, self._tile_size, tiles)
            version = self._version
        # the list's first n points stay as they are: ThinnedPath appends in place and thins into a new list
        return Snapshot(*snap, points[:n], version, memo)


def _refit_moves_px(old: Georeference, new: Georeference, extent: tuple[int, int, int, int],
                    tile_size: int) -> float:
    """How far (map pixels of ``old``) ``new`` moves the corners of the tiles ``extent`` (tile
    keys x0, y0, x1, y1, inclusive) against ``old``; infinite in another CRS."""
    if old.epsg != new.epsg:
        return math.inf
    x0, y0, x1, y1 = extent
    corners = np.array([[x0, y0], [x1 + 1, y0], [x0, y1 + 1], [x1 + 1, y1 + 1]], float) * tile_size
    moved = np.linalg.norm(new.to_crs(corners) - old.to_crs(corners), axis=1).max()
    return float(moved) / old.metres_per_px


# ---------------------------------------------------------------------------------- rendering
def _keys_in(snap: Snapshot, x0: float, y0: float, x1: float, y1: float) -> dict[TileKey, int]:
    """``{key: version}`` of the served tiles meeting the map-pixel rectangle ``[x0, x1) x [y0, y1)``."""
    ts = snap.tile_size
    kx0, ky0 = math.floor(x0 / ts), math.floor(y0 / ts)
    kx1, ky1 = math.floor((x1 - 1e-9) / ts), math.floor((y1 - 1e-9) / ts)
    if (kx1 - kx0 + 1) * (ky1 - ky0 + 1) > len(snap.tiles):
        return {k: t.version for k, t in snap.tiles.items() if kx0 <= k[0] <= kx1 and ky0 <= k[1] <= ky1}
    return {(kx, ky): t.version for ky in range(ky0, ky1 + 1) for kx in range(kx0, kx1 + 1)
            if (t := snap.tiles.get((kx, ky))) is not None}


def _compose(snap: Snapshot, level: int, lx0: int, ly0: int, lx1: int, ly1: int) -> np.ndarray:
    """The served tiles' halvings at ``level`` over the level-pixel rectangle ``[lx0, lx1) x
    [ly0, ly1)``: BGRA uint8, zero where nothing is mapped."""
    f = 1 << level
    lts = snap.tile_size // f
    comp = np.zeros((ly1 - ly0, lx1 - lx0, 4), np.uint8)
    for k in _keys_in(snap, lx0 * f, ly0 * f, lx1 * f, ly1 * f):
        tile = snap.tiles[k].level(level)
        ox, oy = k[0] * lts, k[1] * lts
        mx0, mx1 = max(ox, lx0), min(ox + lts, lx1)
        my0, my1 = max(oy, ly0), min(oy + lts, ly1)
        if mx0 < mx1 and my0 < my1:
            comp[my0 - ly0:my1 - ly0, mx0 - lx0:mx1 - lx0] = tile[my0 - oy:my1 - oy, mx0 - ox:mx1 - ox]
    return comp


def _level_for(snap: Snapshot, scale: float) -> int:
    """The halving level just finer than ``scale`` (output pixels per map pixel, <= 1)."""
    max_level = max(0, int(math.log2(snap.tile_size)))
    return 0 if scale >= 1.0 else min(max_level, int(math.floor(math.log2(1.0 / scale) + 1e-9)))


def _render_fn(snap: Snapshot):
    """A render function (:mod:`photomap.io.mapsource`) over the snapshot's tiles, for ``scale``
    < 1 (at scale 1 :func:`render_png` takes the composed tiles themselves): it composes the
    tiles' halvings at the level just finer than ``scale`` and samples that bilinearly
    (alpha-weighted): work in proportion to the output, whatever the region's size."""

    def render(x: int, y: int, w: int, h: int, scale: float) -> tuple[np.ndarray, np.ndarray]:
        scale = min(1.0, float(scale))
        level = _level_for(snap, scale)
        f = 1 << level
        lx0, ly0 = x // f, y // f
        lx1, ly1 = -(-(x + w) // f), -(-(y + h) // f)
        comp = _compose(snap, level, lx0, ly0, lx1, ly1)
        ow, oh = max(1, round(w * scale)), max(1, round(h * scale))
        # output pixel u covers source x + [u, u + 1) w / ow; its centre in comp pixel coordinates
        sx, sy = w / ow / f, h / oh / f
        m = np.array([[sx, 0.0, x / f + 0.5 * sx - lx0 - 0.5], [0.0, sy, y / f + 0.5 * sy - ly0 - 0.5]])
        pre = cv2.warpAffine(_premultiplied(comp), m, (ow, oh), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))
        return _unpremultiplied(pre)

    return render


def _xyz_tile(snap: Snapshot, x: int, y: int, z: int) -> tuple[np.ndarray, bool] | None:
    """XYZ tile ``(x, y, z)`` of the georeferenced segment as BGRA uint8 and whether it is
    mapped in every pixel, or None where nothing is mapped: each tile pixel centre placed as
    :func:`photomap.io.xyz_tiles.render_tile` places it, sampled bilinearly (alpha-premultiplied)
    from the halving just finer than the tile's resolution: one resampling, where render_tile
    (made for any map raster) renders the region at the tile's scale and resamples that."""
    if not snap.tiles:
        return None
    geo = snap.georeference[1]
    gx, gy, step = tile_source_grid(np.asarray(geo.map_to_crs, float)[:2], geo.epsg, x, y, z)
    level = _level_for(snap, min(1.0, 1.0 / step) if step > 0 else 1.0)
    f = 1 << level
    # map pixel centre s is level pixel (s + 0.5) / f - 0.5 (level pixel j covers map [j f, (j + 1) f));
    # on the grid (bilinear between its nodes: the same affine map, the extremes at the nodes)
    lx, ly = (gx + 0.5) / f - 0.5, (gy + 0.5) / f - 0.5
    bx, by, bw, bh = snap.bounds_px()
    lx0, ly0 = max(math.floor(lx.min()) - 1, bx // f), max(math.floor(ly.min()) - 1, by // f)
    lx1, ly1 = min(math.ceil(lx.max()) + 2, -(-(bx + bw) // f)), min(math.ceil(ly.max()) + 2, -(-(by + bh) // f))
    if lx1 <= lx0 or ly1 <= ly0:
        return None
    comp = _compose(snap, level, lx0, ly0, lx1, ly1)
    lowest, highest = _alpha_range(comp)
    if highest == 0:
        return None
    # premultiplied in 8 bits (OpenCV, no float copies): exact where the map is covered or empty
    # (the map's alpha is 0 or 255; the halvings' edges are within a level at 1/16 cover and up).
    # All four channels at once, by (a, a, a, 255): the alpha stays as it is (a 3-channel product
    # of strided views took 8 times as long). A region mapped in every pixel is its own
    # premultiplied form, and a tile that comes out opaque its own division: both skipped (each
    # an OpenCV call its thread pool takes, a map tile's most common case)
    if lowest < 255:
        comp = cv2.multiply(comp, _alpha4(comp), scale=1.0 / 255.0)
    affine = _grid_affine(lx - lx0, ly - ly0)
    if affine is not None:  # one affine warp: no per-pixel coordinates
        pre = cv2.warpAffine(comp, affine, (wm.TILE_PX, wm.TILE_PX), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))
    else:  # the 256 x 256 coordinates in float32, relative to the region (< 1e-3 px off)
        map_x = upsample_grid((lx - lx0).astype(np.float32))
        map_y = upsample_grid((ly - ly0).astype(np.float32))
        pre = cv2.remap(comp, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                        borderValue=(0, 0, 0, 0))
    lowest, highest = _alpha_range(pre)
    if highest == 0:
        return None
    if lowest == 255:
        return pre, True
    return cv2.divide(pre, _alpha4(pre), scale=255.0), False  # colour 0 where alpha is 0; alpha as it is


def _alpha_range(bgra: np.ndarray) -> tuple[int, int]:
    """The lowest and highest alpha of a BGRA uint8 image."""
    lowest, highest, _, _ = cv2.minMaxLoc(cv2.extractChannel(bgra, 3))
    return int(lowest), int(highest)


_NODES = np.linspace(0.0, wm.TILE_PX - 1.0, 17)  # tile pixel indices of tile_source_grid's nodes
_NODE_XY1 = np.c_[np.tile(_NODES, 17), np.repeat(_NODES, 17), np.ones(17 * 17)]  # (i, j, 1), grid order
_NODE_FIT = np.linalg.pinv(_NODE_XY1)
_AFFINE_PX = 1.0 / 64  # a grid this close to affine is warped as affine (OpenCV's bilinear steps: 1/32 px)


def _grid_affine(gx: np.ndarray, gy: np.ndarray) -> np.ndarray | None:
    """The 2x3 affine (tile pixel index -> source pixel) of a (17, 17) grid of
    :func:`~photomap.io.xyz_tiles.tile_source_grid` when it is within :data:`_AFFINE_PX` of one
    at every node, else None. At the map's own zooms web mercator and UTM bend by parts per
    million across a tile; far out (a tile of kilometres) they do not."""
    nodes = np.c_[gx.ravel(), gy.ravel()]
    m = _NODE_FIT @ nodes  # (3, 2): least squares
    return m.T if np.abs(_NODE_XY1 @ m - nodes).max() <= _AFFINE_PX else None


def xyz_source_rect(snap: Snapshot, x: int, y: int, z: int) -> tuple[float, float, float, float]:
    """Map-pixel rectangle ``(x0, y0, x1, y1)`` under XYZ tile ``(x, y, z)`` of the georeferenced
    segment (its corners' bounding box, with a 2-pixel margin)."""
    geo = snap.georeference[1]
    s, w, n, e = wm.tile_bounds(x, y, z)
    east, north = utm_forward(np.array([s, s, n, n]), np.array([w, e, w, e]), geo.epsg)
    inv = cv2.invertAffineTransform(np.asarray(geo.map_to_crs, float)[:2])
    px = inv[:, :2] @ np.vstack([east, north]) + inv[:, 2:3]
    return px[0].min() - 2, px[1].min() - 2, px[0].max() + 3, px[1].max() + 3


def pixel_source_rect(x: int, y: int, z: int) -> tuple[int, int, int, int]:
    """Map-pixel rectangle ``(x0, y0, x1, y1)`` of pixel-frame tile ``(x, y, z)``."""
    f = wm.TILE_PX << (PIXEL_ZOOM - z)
    return x * f, y * f, (x + 1) * f, (y + 1) * f


def render_png(snap: Snapshot, kind: str, x: int, y: int, z: int, pause: Callable[[], None] = lambda: None,
               jpeg_quality: int = 0) -> bytes:
    """The PNG of tile ``(x, y, z)``: ``kind`` ``xyz`` (georeferenced) or ``pixel``; ``pause``
    is called between the steps (rendering, encoding). A tile mapped in every pixel is an RGB
    PNG (no alpha channel to filter and compress: on a photo tile 0.67 against 0.98 ms and 140
    against 152 KB), others RGBA with alpha 0 where nothing is mapped. ``jpeg_quality`` 1-100:
    a tile mapped in every pixel is a JPEG of that quality instead (:func:`tile_type` tells
    them apart)."""
    pause()
    if kind == "xyz":
        rendered = _xyz_tile(snap, x, y, z)
    elif z == PIXEL_ZOOM:  # a tile pixel per map pixel: the composed tiles themselves
        tile = _compose(snap, 0, *pixel_source_rect(x, y, z))
        lowest, highest = _alpha_range(tile)
        rendered = (tile, lowest == 255) if highest > 0 else None
    else:
        x0, y0, x1, y1 = pixel_source_rect(x, y, z)
        image, alpha = _render_fn(snap)(x0, y0, x1 - x0, y1 - y0, wm.TILE_PX / (x1 - x0))
        rendered = (_bgra(image, alpha), bool(alpha.min() == 255)) if alpha.any() else None
    if rendered is None:
        return EMPTY_PNG
    tile, opaque = rendered
    pause()
    if not opaque:
        return encode_png(tile)  # a third of cv2.imencode's CPU (photomap.io.pngstream)
    colour = cv2.cvtColor(tile, cv2.COLOR_BGRA2BGR)  # mapped in every pixel: no alpha channel
    if jpeg_quality > 0:
        ok, buf = cv2.imencode(".jpg", colour, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        return buf.tobytes() if ok else EMPTY_PNG
    return encode_png(colour)


def tile_type(body: bytes) -> str:
    """The media type of a tile :func:`render_png` made."""
    return "image/jpeg" if body[:3] == b"\xff\xd8\xff" else "image/png"


class Tile(NamedTuple):
    """A served tile: its encoded picture and its entity tag (an HTTP ``ETag`` value, quoted)."""

    body: bytes
    etag: str


EMPTY_TILE = Tile(EMPTY_PNG, '"empty"')


@dataclass
class _Entry:
    tile: Tile
    deps: dict[TileKey, int]
    made: float
    rect: tuple  # the map-pixel rectangle under the tile (fixed by its key)


class TileCache:
    """Rendered tiles by ``(kind, geo_version, z, x, y)``, least recently used beyond
    ``max_entries``; see the module docstring for when a tile is rendered again.

    Entity tags are this cache's (a random prefix per cache, so that a tag from another run
    never matches) and a count of the pictures it made; a render that makes the same bytes
    keeps the tag it had."""

    def __init__(self, max_entries: int = 256, min_interval_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic, jpeg_quality: int = 0) -> None:
        self._entries: OrderedDict[tuple, _Entry] = OrderedDict()
        self._jpeg_quality = int(jpeg_quality)  # see render_png
        self._lock = threading.Lock()
        self._max = max(1, int(max_entries))
        self._interval = float(min_interval_s)
        self._clock = clock
        self._tag_prefix = os.urandom(4).hex()
        self._made = itertools.count(1)
        self.renders = 0
        self.hits = 0

    def get(self, snap: Snapshot, kind: str, x: int, y: int, z: int,
            pause: Callable[[], None] = lambda: None) -> Tile:
        """The tile (``pause``: see :func:`render_png`)."""
        key = (kind, snap.geo_version if kind == "xyz" else 0, z, x, y)
        with self._lock:
            entry = self._entries.get(key)
        if entry is not None:
            rect = entry.rect
        else:
            rect = xyz_source_rect(snap, x, y, z) if kind == "xyz" else pixel_source_rect(x, y, z)
        deps = _keys_in(snap, *rect)
        now = self._clock()
        if entry is not None and (entry.deps == deps or now - entry.made < self._interval):
            with self._lock:
                if key in self._entries:
                    self._entries.move_to_end(key)
                self.hits += 1
            return entry.tile
        png = render_png(snap, kind, x, y, z, pause, self._jpeg_quality) if deps else EMPTY_PNG
        if png is EMPTY_PNG:
            tile = EMPTY_TILE
        elif entry is not None and entry.tile.body == png:
            tile = entry.tile
        else:
            tile = Tile(png, f'"{self._tag_prefix}.{next(self._made)}"')
        with self._lock:
            self.renders += 1
            self._entries[key] = _Entry(tile, deps, now, rect)
            self._entries.move_to_end(key)
            while len(self._entries) > self._max:
                self._entries.popitem(last=False)
        return tile


# ---------------------------------------------------------------------------------- GeoJSON
def _feature(geometry: dict | None, **properties) -> dict:
    return {"type": "Feature", "geometry": geometry, "properties": properties}


def _collection(features: list[dict], snap: Snapshot) -> dict:
    """A FeatureCollection; without a georeference its coordinates are map pixels (x, y), said
    by ``"frame": "map_pixels"`` (else ``"wgs84"``: lon, lat)."""
    return {"type": "FeatureCollection", "frame": "wgs84" if snap.georeference is not None else "map_pixels",
            "features": features}


def _coords(snap: Snapshot, xy: np.ndarray) -> list[list[float]]:
    xy = np.asarray(xy, float).reshape(-1, 2)
    return (snap.to_lonlat(xy) if snap.georeference is not None else xy).tolist()


def track_geojson(snap: Snapshot) -> dict:
    """The served segment's path (frame centres) as a LineString."""
    if len(snap.path) < 2:
        return _collection([], snap)
    return _collection([_feature({"type": "LineString", "coordinates": _coords(snap, np.array(snap.path))},
                                 segment=snap.served_segment, points=len(snap.path))], snap)


def hazards_geojson(spots: dict, snap: Snapshot) -> dict:
    """The hazard spots (a FeatureCollection of :meth:`~photomap.mapping.hazards.HazardTracker.hazards`)
    where the page draws them over the served map: a spot of the served segment at its map pixel
    (``x_px``, ``y_px``), through the map's georeference when there is one (on the tiles the operator
    sees), else in map pixels (``"frame": "map_pixels"``: the ground team's map without GPS); a spot
    of another segment only with its own WGS84 position, when georeferenced."""
    features = []
    for f in spots.get("features", []) if isinstance(spots, dict) else []:
        p = f.get("properties") or {}
        x, y = p.get("x_px"), p.get("y_px")
        if p.get("segment") == snap.served_segment and x is not None and y is not None:
            features.append(dict(f, geometry={"type": "Point", "coordinates": _coords(snap, np.array([x, y]))[0]}))
        elif snap.georeference is not None and f.get("geometry") is not None:
            features.append(f)
    return _collection(features, snap)


def footprint_geojson(snap: Snapshot) -> dict:
    """The latest frame's outline: through its pose when it lies in the served segment, else
    (georeferenced) from the telemetry alone."""
    if snap.pose is not None and snap.pose_segment == snap.served_segment and snap.frame_size:
        ring = frame_outline(snap.pose, *snap.frame_size)
        return _collection([_feature({"type": "Polygon", "coordinates": [_coords(snap, ring)]},
                                     source="map")], snap)
    outline = None
    if snap.georeference is not None and snap.gps_sample is not None and snap.frame_size:
        outline = geo_footprint(snap.gps_sample[0], snap.gps_sample[1], *snap.frame_size)
    if outline is not None:
        ring = [[float(lon), float(lat)] for lat, lon in outline]
        return _collection([_feature({"type": "Polygon", "coordinates": [ring]}, source="telemetry")], snap)
    return _collection([], snap)


def position(snap: Snapshot) -> dict | None:
    """The latest frame centre: ``{"lat", "lon"}`` (georeferenced; from the map when the frame
    lies in the georeferenced segment, else the telemetry's), ``{"x", "y"}`` map pixels, or None."""
    centre = None
    if snap.pose is not None and snap.pose_segment == snap.served_segment and snap.frame_size:
        centre = np.asarray(snap.pose, float) @ (*frame_centre(*snap.frame_size), 1.0)
    if snap.georeference is not None:
        if centre is not None:
            lon, lat = snap.to_lonlat(centre[None])[0]
            return {"lat": float(lat), "lon": float(lon), "source": "map"}
        if snap.gps is not None:
            return {"lat": snap.gps[0], "lon": snap.gps[1], "source": "telemetry"}
        return None
    return None if centre is None else {"x": float(centre[0]), "y": float(centre[1]), "source": "map"}


def status(snap: Snapshot, extra: dict | None = None) -> dict:
    """``/status.json``: counts, rate, telemetry, position, bounds, zooms, the tile URL."""
    bounds = snap.memo.get("bounds", ())
    if bounds == ():  # once per change of the tiles or the georeference (memo), not per frame
        box = snap.bounds_px()
        bounds = None
        if box is not None:
            x, y, w, h = box
            corners = np.array([[x, y], [x + w, y], [x, y + h], [x + w, y + h]], float)
            if snap.georeference is not None:
                ll = snap.to_lonlat(corners)
                bounds = [float(ll[:, 0].min()), float(ll[:, 1].min()), float(ll[:, 0].max()), float(ll[:, 1].max())]
            else:
                bounds = [float(x), float(y), float(x + w), float(y + h)]
        snap.memo["bounds"] = bounds
    geo = snap.georeference[1] if snap.georeference is not None else None
    out = {"frames_in": snap.frames_in, "frame": snap.frame, "registered": snap.registered, "segments": snap.segments,
           "segment": snap.segment, "fps": round(snap.fps, 2), "telemetry": snap.telemetry,
           "georeferenced": geo is not None, "position": position(snap),
           "bounds": bounds, "bounds_frame": "wgs84" if geo is not None else "map_pixels",
           "max_zoom": snap.max_zoom(), "min_zoom": 0, "version": snap.version,
           "tiles_url": "/tiles/{z}/{x}/{y}.png" if geo is not None else "/pixel/{z}/{x}/{y}.png",
           "pixel_zoom": PIXEL_ZOOM, "map_tiles": len(snap.tiles),
           "metres_per_pixel": geo.metres_per_px if geo is not None else None,
           "crs": f"EPSG:{geo.epsg}" if geo is not None else None}
    out.update(extra or {})
    return out
