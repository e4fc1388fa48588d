"""Map rasters for the exports: something that renders map-pixel regions, and where it is.

An export (GeoTIFF, XYZ tiles) never holds the whole map: it asks a *render function*
``render(x, y, w, h, scale) -> (bgr, alpha)`` for one region at a time. Its contract is that of
:meth:`photomap.core.mosaic.TiledMosaic.render` with ``bounds=(x, y, w, h)``: the region's
source pixels ``x .. x + w - 1``, ``y .. y + h - 1`` (OpenCV pixel centres) rendered to
``max(1, round(w * scale))`` x ``max(1, round(h * scale))`` pixels, area-averaged and
alpha-weighted when ``scale < 1``; ``bgr`` (H, W, 3) uint8 (uint16 from a 16-bit map: its raw
values), 0 where empty; ``alpha`` uint8 (H, W), 255 covered, 0 empty. Output pixel ``(u, v)`` covers the source pixels
``x + [u, u + 1) * w / W`` (the same for y), so :func:`photomap.geo.georef.png_to_map` with
``origin_xy = (x, y)`` and ``scale = (W / w, H / h)`` maps its pixel centres to source pixels.

Sources:

- :func:`mosaic_source`: a live :class:`~photomap.core.mosaic.TiledMosaic` (the pipeline).
- :class:`TileFolderSource`: the full-resolution ``tiles/tile_{tx}_{ty}.png`` of a finished run.
- :class:`ImageSource`: one image (``mosaic.png`` when it is the full map).

:func:`run_raster` picks the best one for a run folder and pairs it with its georeference
(:class:`MapRaster`).
"""

from __future__ import annotations

import logging
import math
import re
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import cv2
import numpy as np

from photomap.errors import InputError
from photomap.geo.georef import compose, png_to_map
from photomap.geometry import pose_scale
from photomap.io.runfiles import RunFiles

if TYPE_CHECKING:
    from photomap.core.mosaic import TiledMosaic

log = logging.getLogger(__name__)

RenderFn = Callable[[int, int, int, int, float], tuple[np.ndarray, np.ndarray]]
Rect = tuple[int, int, int, int]

_TILE_NAME = re.compile(r"^tile_(-?\d+)_(-?\d+)\.png$")


@dataclass(frozen=True)
class MapRaster:
    """A renderable map and its georeference.

    render : the render function (module docstring), in *source pixels*.
    bounds : ``(x, y, w, h)`` source rectangle holding every covered pixel.
    src_to_crs : 2x3, source pixel centre -> projected CRS metres (easting, northing).
    epsg : the CRS (WGS 84 / UTM).
    """

    render: RenderFn
    bounds: Rect
    src_to_crs: np.ndarray
    epsg: int

    @property
    def metres_per_px(self) -> float:
        """Ground metres per source pixel (``sqrt |det|`` of the linear part)."""
        return pose_scale(self.src_to_crs)


def mosaic_source(mosaic: "TiledMosaic") -> RenderFn:
    """A render function over a live mosaic (gray maps come back as BGR)."""

    def render(x: int, y: int, w: int, h: int, scale: float) -> tuple[np.ndarray, np.ndarray]:
        image, alpha, _ = mosaic.render(scale=min(1.0, float(scale)), bounds=(x, y, w, h))
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        return image, alpha

    return render


def _box_axis(data: np.ndarray, a: int, b: int, step: float, n_out: int, axis: int
              ) -> tuple[int, np.ndarray]:
    """INTER_AREA reduction along ``axis`` of ``data``, which covers region pixels ``[a, b)``.

    Output pixel ``j`` averages the region interval ``[j * step, (j + 1) * step)``; returned are
    the first output index ``j0`` touched and, for each touched output, the *partial* sum over
    this data's pixels divided by ``step`` (pieces side by side add up). Exact through the
    prefix sum interpolated linearly between pixel edges: O(pixels).
    """
    j0 = int(math.floor(a / step))
    j1 = min(n_out, int(math.ceil(b / step)))
    n = b - a
    edges = np.clip(np.arange(j0, j1 + 1, dtype=np.float64) * step, a, b) - a
    k = np.minimum(np.floor(edges).astype(np.intp), n)
    frac = edges - k
    d = np.moveaxis(data, axis, 0).astype(np.float64, copy=False)
    s = np.concatenate([np.zeros((1,) + d.shape[1:]), np.cumsum(d, axis=0)], axis=0)
    shape = (-1,) + (1,) * (d.ndim - 1)
    f = s[k] + frac.reshape(shape) * d[np.minimum(k, n - 1)]
    return j0, np.moveaxis((f[1:] - f[:-1]) / step, 0, axis)


def _render_pieces(pieces, x: int, y: int, w: int, h: int, scale: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Render from full-resolution pieces ``(ox, oy, get_bgra)`` (``get_bgra() -> (h, w, 4)``).

    Same result as :meth:`TiledMosaic.render`: a copy at scale 1, else alpha-weighted area
    averaging accumulated one piece at a time.
    """
    if w <= 0 or h <= 0:
        raise ValueError(f"render region needs a positive size, got {(x, y, w, h)}")
    if not 0 < scale <= 1:
        raise ValueError(f"render scale must be in (0, 1], got {scale!r}")
    full = scale == 1
    ow, oh = (w, h) if full else (max(1, round(w * scale)), max(1, round(h * scale)))
    if full:
        out = np.zeros((h, w, 4), np.uint8)
    else:
        acc = np.zeros((oh, ow, 4), np.float32)
    for ox, oy, pw, ph, get in pieces:
        mx0, mx1 = max(ox, x), min(ox + pw, x + w)
        my0, my1 = max(oy, y), min(oy + ph, y + h)
        if mx0 >= mx1 or my0 >= my1:
            continue
        bgra = get()
        sub = bgra[my0 - oy:my1 - oy, mx0 - ox:mx1 - ox]
        if full:
            out[my0 - y:my1 - y, mx0 - x:mx1 - x] = sub
            continue
        a = sub[..., 3].astype(np.float32) / 255
        if not a.any():
            continue
        pre = np.dstack([sub[..., :3] * a[..., None], a])
        v0, rows = _box_axis(pre, my0 - y, my1 - y, h / oh, oh, axis=0)
        u0, block = _box_axis(rows, mx0 - x, mx1 - x, w / ow, ow, axis=1)
        acc[v0:v0 + block.shape[0], u0:u0 + block.shape[1]] += block
    if full:
        return out[..., :3].copy(), out[..., 3].copy()
    cover = acc[..., 3]
    image = np.zeros((oh, ow, 3), np.uint8)
    covered = cover > 1e-6
    image[covered] = np.clip(np.rint(acc[..., :3][covered] / cover[covered][:, None]), 0, 255)
    return image, np.clip(np.rint(cover * 255), 0, 255).astype(np.uint8)


def _read_bgra(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"cannot read map image {path}")
    if image.dtype != np.uint8:
        raise InputError(f"map image {path} is not 8-bit")
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGRA)
    elif image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2BGRA)
    elif image.shape[2] == 1:
        image = cv2.cvtColor(image[..., 0], cv2.COLOR_GRAY2BGRA)
    return image


class ImageSource:
    """One BGRA image (or a path read on first use) as a map whose top-left pixel is ``origin``."""

    def __init__(self, image: np.ndarray | str | Path, origin: tuple[int, int] = (0, 0)) -> None:
        self._path = None if isinstance(image, np.ndarray) else Path(image)
        self._image = image if isinstance(image, np.ndarray) else None
        if self._image is not None and (self._image.ndim != 3 or self._image.shape[2] != 4):
            raise InputError("an image map source needs a BGRA image")
        self.origin = (int(origin[0]), int(origin[1]))

    def image(self) -> np.ndarray:
        if self._image is None:
            self._image = _read_bgra(self._path)
        return self._image

    @property
    def bounds(self) -> Rect:
        h, w = self.image().shape[:2]
        return self.origin[0], self.origin[1], w, h

    def __call__(self, x: int, y: int, w: int, h: int, scale: float) -> tuple[np.ndarray, np.ndarray]:
        ox, oy, pw, ph = self.bounds
        return _render_pieces([(ox, oy, pw, ph, self.image)], x, y, w, h, min(1.0, float(scale)))


class TileFolderSource:
    """The full-resolution tiles of a run (``tile_{tx}_{ty}.png``, ``tile_size`` pixels each;
    tile ``(tx, ty)`` starts at map pixel ``(tx * ts, ty * ts)``), read on demand and kept in a
    small least-recently-used cache of ``cache_tiles`` decoded tiles."""

    def __init__(self, folder: str | Path, tile_size: int, cache_tiles: int = 256) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise InputError(f"map tiles folder not found: {self.folder}")
        self.tile_size = int(tile_size)
        self.keys: set[tuple[int, int]] = set()
        for p in self.folder.iterdir():
            m = _TILE_NAME.match(p.name)
            if m:
                self.keys.add((int(m.group(1)), int(m.group(2))))
        if not self.keys:
            raise InputError(f"no map tiles (tile_X_Y.png) in {self.folder}")
        self._cache: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._cache_tiles = max(1, int(cache_tiles))

    def _tile(self, key: tuple[int, int]) -> np.ndarray:
        tile = self._cache.get(key)
        if tile is not None:
            self._cache.move_to_end(key)
            return tile
        tile = _read_bgra(self.folder / f"tile_{key[0]}_{key[1]}.png")
        self._cache[key] = tile
        while len(self._cache) > self._cache_tiles:
            self._cache.popitem(last=False)
        return tile

    @property
    def bounds(self) -> Rect:
        """The rectangle of all tiles (the covered part may be smaller)."""
        ts = self.tile_size
        xs = [k[0] for k in self.keys]
        ys = [k[1] for k in self.keys]
        return min(xs) * ts, min(ys) * ts, (max(xs) - min(xs) + 1) * ts, (max(ys) - min(ys) + 1) * ts

    def __call__(self, x: int, y: int, w: int, h: int, scale: float) -> tuple[np.ndarray, np.ndarray]:
        ts = self.tile_size
        pieces = []
        for ty in range(y // ts, (y + h - 1) // ts + 1):
            for tx in range(x // ts, (x + w - 1) // ts + 1):
                if (tx, ty) in self.keys:
                    pieces.append((tx * ts, ty * ts, ts, ts, lambda k=(tx, ty): self._tile(k)))
        return _render_pieces(pieces, x, y, w, h, min(1.0, float(scale)))


def run_raster(run: RunFiles, segment: int | None = None) -> MapRaster:
    """The best map raster of a run folder for one segment (default: the main map).

    Full-resolution ``tiles/`` when the run wrote them (its ``mosaic.png`` is downscaled), else
    the mosaic PNG itself (then in PNG pixels, through ``origin_xy`` and ``pixel_scale``).
    Raises InputError when the segment has no map or no georeference.
    """
    entry = run.mosaic(segment)
    map_to_crs, epsg = run.georeference(entry)
    tiles = entry.get("tiles")
    if tiles and (run.dir / tiles).is_dir():
        source = TileFolderSource(run.dir / tiles, int(entry.get("tile_size") or 256))
        x, y, w, h = (int(v) for v in entry["bounds"])
        return MapRaster(source, (x, y, w, h), map_to_crs, epsg)
    png = run.dir / entry["file"]
    if not png.is_file():
        raise InputError(f"map image {png} not found")
    source = ImageSource(png)
    src_to_crs = compose(map_to_crs, png_to_map(entry["origin_xy"], entry.get("pixel_scale") or entry["scale"]))
    if (entry.get("scale") or 1.0) < 1.0:
        log.warning("%s is downscaled and the run has no full-resolution tiles: exporting at its "
                    "resolution", png.name)
    return MapRaster(source, source.bounds, src_to_crs, epsg)
