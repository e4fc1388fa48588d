"""Web-mercator XYZ (or TMS) PNG tiles of the map: ``DIR/{z}/{x}/{y}.png``.

What Leaflet (``L.tileLayer('DIR/{z}/{x}/{y}.png')``), QGIS "XYZ Tiles"
(``file:///abs/DIR/{z}/{x}/{y}.png``), QGroundControl and Mission Planner custom tile sources
(over HTTP, e.g. ``python -m http.server`` in DIR) load. Tiles are 256 x 256 PNGs: RGBA,
transparent where the map is empty, or RGB where the map covers every pixel; tiles the map does
not touch are not written (viewers show nothing there). Needs only OpenCV and numpy (no GDAL).

Each tile pixel centre is mapped exactly (per pixel: web mercator -> WGS84 -> UTM -> source
pixel), the source region under the tile is rendered at about the tile's resolution (area
averaged) and sampled bilinearly, alpha-premultiplied.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from photomap.errors import InputError
from photomap.geo import webmercator as wm
from photomap.geo.georef import png_to_map, utm_forward, utm_inverse
from photomap.io.mapsource import MapRaster
from photomap.io.pngstream import encode_png
from photomap.io.trajectory_files import atomic_write_bytes, sync_filesystem, write_json

log = logging.getLogger(__name__)


_GRID = 17


def _interp_weights(n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation from m samples at ``linspace(0, n - 1, m)`` to 0..n-1: output ``i``
    is ``(1 - f[i]) * s[k[i]] + f[i] * s[k[i] + 1]``; returns ``(k, f)``."""
    pos = np.arange(n) * (m - 1) / (n - 1)
    k = np.minimum(np.floor(pos).astype(np.intp), m - 2)
    return k, pos - k


_K, _F = _interp_weights(wm.TILE_PX, _GRID)


def upsample_grid(grid: np.ndarray) -> np.ndarray:
    """A (17, 17) grid of :func:`tile_source_grid` interpolated bilinearly to the tile's (256,
    256) pixels (rows, then columns), in the grid's float type. Indexing, not a matrix product:
    BLAS threads would spin on cores the mapping uses (the live map server)."""
    f = _F.astype(grid.dtype)
    g = 1 - f
    rows = grid[_K] * g[:, None] + grid[_K + 1] * f[:, None]
    # the columns by np.take and in place: the same operations, 40 % less time than fancy indexing
    out = np.take(rows, _K, axis=1)
    out *= g
    right = np.take(rows, _K + 1, axis=1)
    right *= f
    out += right
    return out


def raster_latlon_box(raster: MapRaster) -> tuple[float, float, float, float]:
    """``(south, west, north, east)`` degrees of the raster's source rectangle (its corners)."""
    x, y, w, h = raster.bounds
    c = np.array([[x - 0.5, y - 0.5], [x + w - 0.5, y - 0.5], [x - 0.5, y + h - 0.5], [x + w - 0.5, y + h - 0.5]])
    en = c @ raster.src_to_crs[:, :2].T + raster.src_to_crs[:, 2]
    lat, lon = utm_inverse(en[:, 0], en[:, 1], raster.epsg)
    return float(lat.min()), float(lon.min()), float(lat.max()), float(lon.max())


def default_zooms(raster: MapRaster) -> tuple[int, int]:
    """``(zmin, zmax)``: ``zmax`` matches the map's resolution; at ``zmin`` the map spans about
    one tile."""
    s, w, n, e = raster_latlon_box(raster)
    lat = (s + n) / 2.0
    zmax = wm.zoom_for_resolution(lat, raster.metres_per_px)
    extent_m = max(raster.bounds[2], raster.bounds[3]) * raster.metres_per_px
    zmin = wm.zoom_for_resolution(lat, extent_m / wm.TILE_PX)
    return min(zmin, zmax), zmax


def tile_source_grid(src_to_crs: np.ndarray, epsg: int, x: int, y: int, z: int
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    """Where XYZ tile ``(x, y, z)``'s pixel centres lie in a map whose source pixel centres map
    to the CRS by ``src_to_crs`` (2x3): source pixel coordinates ``(gx, gy)`` exact on a
    (17, 17) grid of the tile's pixel centres (its corners and every 255/16 pixels; bilinear
    between, :func:`upsample_grid`: < 1 mm off within a tile that meets a map), and the source
    pixels per tile pixel (the spacing across the tile)."""
    n = wm.TILE_PX
    u = np.linspace(0.5, n - 0.5, _GRID)
    lat, _ = wm.pixel_to_latlon(0.0, y * n + u, z)
    _, lon = wm.pixel_to_latlon(x * n + u, 0.0, z)
    lon_g, lat_g = np.meshgrid(lon, lat)
    e, nn = utm_forward(lat_g, lon_g, epsg)
    inv = cv2.invertAffineTransform(np.asarray(src_to_crs, float))
    # the CRS -> source map is affine: interpolating its values on the grid is interpolating the CRS
    gx = inv[0, 0] * e + inv[0, 1] * nn + inv[0, 2]
    gy = inv[1, 0] * e + inv[1, 1] * nn + inv[1, 2]
    return gx, gy, math.hypot(gx[0, -1] - gx[0, 0], gy[0, -1] - gy[0, 0]) / (n - 1)


def render_tile(raster: MapRaster, x: int, y: int, z: int) -> tuple[np.ndarray, np.ndarray] | None:
    """XYZ tile ``(x, y, z)`` of the map as ``(bgr uint8 (256, 256, 3), alpha uint8)``, or None
    when the map does not cover it."""
    n = wm.TILE_PX
    gx, gy, step = tile_source_grid(raster.src_to_crs, raster.epsg, x, y, z)
    sx, sy = upsample_grid(gx), upsample_grid(gy)
    bx, by, bw, bh = raster.bounds
    scale = min(1.0, 1.0 / step) if step > 0 else 1.0
    margin = 2.0 / scale
    x0 = max(math.floor(sx.min() - margin), bx)
    y0 = max(math.floor(sy.min() - margin), by)
    x1 = min(math.ceil(sx.max() + margin) + 1, bx + bw)
    y1 = min(math.ceil(sy.max() + margin) + 1, by + bh)
    if x1 <= x0 or y1 <= y0:
        return None
    image, alpha = raster.render(x0, y0, x1 - x0, y1 - y0, scale)
    if not alpha.any():
        return None
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    ph, pw = alpha.shape
    # source pixel -> patch pixel (inverse of png_to_map)
    p2s = png_to_map((x0, y0), (pw / (x1 - x0), ph / (y1 - y0)))
    map_x = ((sx - p2s[0, 2]) / p2s[0, 0]).astype(np.float32)
    map_y = ((sy - p2s[1, 2]) / p2s[1, 1]).astype(np.float32)
    af = alpha.astype(np.float32) * (1.0 / 255.0)
    pre = np.dstack([image.astype(np.float32) * af[..., None], af])
    warped = cv2.remap(pre, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                       borderValue=(0, 0, 0, 0))
    cover = warped[..., 3]
    if not (cover > 0.5 / 255).any():
        return None
    colour = np.divide(warped[..., :3], cover[..., None], out=np.zeros((n, n, 3), np.float32),
                       where=cover[..., None] > 1e-6)
    out = np.clip(np.rint(colour), 0, 255).astype(np.uint8)
    return out, np.clip(np.rint(cover * 255), 0, 255).astype(np.uint8)


def write_xyz_tiles(folder: str | Path, raster: MapRaster, *, zooms: tuple[int, int] | None = None,
                    tms: bool = False, max_tiles: int = 200_000,
                    progress: Callable[[int, int], None] | None = None) -> dict:
    """Write the map as web-mercator PNG tiles ``folder/{z}/{x}/{y}.png`` (each atomically; all
    made durable at the end with one :func:`~photomap.io.trajectory_files.sync_filesystem`).

    Parameters
    ----------
    zooms : ``(zmin, zmax)`` inclusive (default :func:`default_zooms`).
    tms : number rows from the south (TMS, ``y = 2**z - 1 - y_xyz``) instead of XYZ.
    max_tiles : refuse (InputError) a zoom range needing more candidate tiles than this.

    Returns (and writes as ``folder/tiles.json``) ``{"scheme", "zooms", "tiles", "bounds":
    [west, south, east, north], "url": "{z}/{x}/{y}.png"}``.
    """
    folder = Path(folder)
    zmin, zmax = zooms if zooms is not None else default_zooms(raster)
    if not 0 <= zmin <= zmax <= wm.MAX_ZOOM:
        raise InputError(f"tile zoom range must satisfy 0 <= zmin <= zmax <= {wm.MAX_ZOOM}, got {zmin}-{zmax}")
    box = raster_latlon_box(raster)
    jobs = [(z, x, y) for z in range(zmin, zmax + 1) for x, y in wm.tiles_covering(*box, z)]
    if len(jobs) > max_tiles:
        raise InputError(f"zoom {zmin}-{zmax} needs up to {len(jobs)} tiles (> {max_tiles}); "
                         f"lower the largest zoom")
    written = 0
    with threadpool_limits(limits=1, user_api="blas"):  # tiny products: no BLAS threads spinning
        for i, (z, x, y) in enumerate(jobs):
            tile = render_tile(raster, x, y, z)
            if tile is not None:
                bgr, alpha = tile
                buf = encode_png(bgr if alpha.min() == 255 else np.dstack(tile))  # opaque: RGB
                row = wm.tms_y(y, z) if tms else y
                path = folder / str(z) / str(x) / f"{row}.png"
                path.parent.mkdir(parents=True, exist_ok=True)
                atomic_write_bytes(path, buf, sync=False)
                written += 1
            if progress is not None:
                progress(i + 1, len(jobs))
    info = {"scheme": "tms" if tms else "xyz", "zooms": [zmin, zmax], "tiles": written,
            "bounds": [box[1], box[0], box[3], box[2]], "url": "{z}/{x}/{y}.png"}
    folder.mkdir(parents=True, exist_ok=True)
    sync_filesystem(folder)
    write_json(folder / "tiles.json", info)
    log.info("wrote %d %s tiles, zoom %d-%d, to %s", written, info["scheme"].upper(), zmin, zmax, folder)
    return info


def leaflet_snippet(info: dict) -> str:
    """A one-line hint for loading the tiles (``tms: true`` for TMS)."""
    opts = f"{{maxNativeZoom: {info['zooms'][1]}{', tms: true' if info['scheme'] == 'tms' else ''}}}"
    return f"L.tileLayer('{info['url']}', {opts})"

