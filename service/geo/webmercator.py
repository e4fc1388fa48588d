"""Web-mercator (EPSG:3857) XYZ tile arithmetic: the tile grid of OpenStreetMap, Leaflet, QGIS
"XYZ Tiles", QGroundControl and Mission Planner custom tile sources.

Conventions
-----------
- Zoom ``z`` has ``2**z`` x ``2**z`` tiles of ``TILE_PX`` (256) pixels. XYZ tile ``(x, y)``:
  x grows east from the antimeridian (180 W), y grows **south** from the top (85.0511 N).
  TMS numbers rows from the bottom instead: ``y_tms = 2**z - 1 - y``.
- Global pixel coordinates at zoom ``z`` are continuous: pixel ``(px, py)`` with the top-left
  corner of tile (0, 0) at (0, 0); the centre of the top-left pixel of tile ``(x, y)`` is
  ``(256 x + 0.5, 256 y + 0.5)``.
- Latitudes and longitudes are WGS84 degrees (web mercator treats them as spherical).

Pure computations (arrays in, arrays out).
"""

from __future__ import annotations

import math

import numpy as np

from photomap.errors import InputError

TILE_PX = 256
EARTH_RADIUS_M = 6378137.0  # the sphere of EPSG:3857
MAX_LAT = math.degrees(math.atan(math.sinh(math.pi)))  # 85.0511...
MAX_ZOOM = 24


def _check_zoom(z: int) -> int:
    if not isinstance(z, (int, np.integer)) or not 0 <= z <= MAX_ZOOM:
        raise InputError(f"zoom must be an integer in 0..{MAX_ZOOM}, got {z!r}")
    return int(z)


def latlon_to_pixel(lat: np.ndarray, lon: np.ndarray, z: int) -> tuple[np.ndarray, np.ndarray]:
    """WGS84 degrees -> continuous global pixel coordinates ``(px, py)`` at zoom ``z``."""
    n = TILE_PX * 2.0 ** _check_zoom(z)
    lat = np.clip(np.asarray(lat, float), -MAX_LAT, MAX_LAT)
    px = (np.asarray(lon, float) + 180.0) / 360.0 * n
    py = (1.0 - np.arcsinh(np.tan(np.radians(lat))) / math.pi) / 2.0 * n
    return px, py


def pixel_to_latlon(px: np.ndarray, py: np.ndarray, z: int) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`latlon_to_pixel`."""
    n = TILE_PX * 2.0 ** _check_zoom(z)
    lon = np.asarray(px, float) / n * 360.0 - 180.0
    lat = np.degrees(np.arctan(np.sinh(math.pi * (1.0 - 2.0 * np.asarray(py, float) / n))))
    return lat, lon


def tile_of(lat: float, lon: float, z: int) -> tuple[int, int]:
    """XYZ tile ``(x, y)`` holding a position at zoom ``z`` (the OSM "slippy map" formula)."""
    px, py = latlon_to_pixel(lat, lon, z)
    last = 2 ** z - 1
    return (min(max(int(px // TILE_PX), 0), last), min(max(int(py // TILE_PX), 0), last))


def tile_bounds(x: int, y: int, z: int) -> tuple[float, float, float, float]:
    """``(south, west, north, east)`` WGS84 degrees of XYZ tile ``(x, y, z)`` (outer edges)."""
    lat0, lon0 = pixel_to_latlon(x * TILE_PX, y * TILE_PX, z)
    lat1, lon1 = pixel_to_latlon((x + 1) * TILE_PX, (y + 1) * TILE_PX, z)
    return float(lat1), float(lon0), float(lat0), float(lon1)


def tms_y(y: int, z: int) -> int:
    """The TMS row of XYZ row ``y`` at zoom ``z`` (and back: the map is its own inverse)."""
    return 2 ** _check_zoom(z) - 1 - int(y)


def ground_resolution(lat: float, z: int) -> float:
    """Ground metres per tile pixel at latitude ``lat`` and zoom ``z`` (east-west, on the sphere)."""
    return 2.0 * math.pi * EARTH_RADIUS_M * math.cos(math.radians(lat)) / (TILE_PX * 2.0 ** _check_zoom(z))


def zoom_for_resolution(lat: float, metres_per_px: float) -> int:
    """The zoom whose tile pixels are closest (in log scale) to ``metres_per_px`` at ``lat``."""
    if not metres_per_px > 0:
        raise InputError(f"ground resolution must be > 0 m, got {metres_per_px!r}")
    z0 = ground_resolution(lat, 0)
    return int(min(MAX_ZOOM, max(0, round(math.log2(z0 / metres_per_px)))))


def tiles_covering(south: float, west: float, north: float, east: float, z: int
                   ) -> list[tuple[int, int]]:
    """Every XYZ tile ``(x, y)`` at zoom ``z`` meeting the box (degrees), row by row."""
    x0, y0 = tile_of(north, west, z)
    x1, y1 = tile_of(south, east, z)
    return [(x, y) for y in range(y0, y1 + 1) for x in range(x0, x1 + 1)]
