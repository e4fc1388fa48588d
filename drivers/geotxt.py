"""OpenDroneMap's image geolocation file (``geo.txt``): positions of stills without EXIF GPS.

Format (OpenDroneMap docs, "Image Geolocation Files", ODM 2.0 and later)::

    <projection>
    image_name geo_x geo_y [geo_z] [yaw pitch roll [horz_accuracy vert_accuracy [extras...]]]

The first line names the projection: ``EPSG:4326`` (``geo_x`` = longitude, ``geo_y`` =
latitude, degrees), a WGS 84 / UTM code ``EPSG:326zz`` / ``EPSG:327zz``, ``WGS84 UTM <zone>N|S``
or a PROJ string ``+proj=utm +zone=<zone> [+south] ...`` on the WGS 84 datum (``geo_x`` =
easting, ``geo_y`` = northing, metres); ``+proj=longlat`` on WGS 84 is EPSG:4326. Other
projections are refused (convert the file to EPSG:4326). ``geo_z`` is the altitude in metres
(taken as above mean sea level). The angles are in degrees in OpenDroneMap's convention: yaw 0
= the top of the image points north, 90 = east; pitch 0 = nadir, > 0 looking forward; roll 0;
OpenDroneMap writes 0 for angles it does not know, so a line whose three angles are all 0 has
no attitude. Blank lines and lines starting with ``#`` are skipped.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from photomap.errors import InputError
from photomap.geo.georef import epsg_zone, utm_inverse

log = logging.getLogger(__name__)

_UTM_NAME = re.compile(r"^WGS\s*84\s+UTM\s+(\d{1,2})\s*([NS])$", re.IGNORECASE)
_EPSG = re.compile(r"^EPSG:(\d+)$", re.IGNORECASE)

Projection = Callable[[float, float], tuple[float, float]]


@dataclass(frozen=True)
class GeoEntry:
    """One line of a geo.txt, with the position converted to WGS 84.

    ``lat``, ``lon`` [deg]; ``alt`` [m] or None; ``yaw``, ``pitch``, ``roll`` [deg, the file's
    OpenDroneMap convention] or None; accuracies [m] or None.
    """

    name: str
    lat: float
    lon: float
    alt: float | None = None
    yaw: float | None = None
    pitch: float | None = None
    roll: float | None = None
    horizontal_accuracy: float | None = None
    vertical_accuracy: float | None = None


@dataclass
class GeoFile:
    """A parsed geo.txt: ``entries`` by image name, the ``projection`` line, the ``bad_lines``
    skipped (1-based line numbers) and the file it came from."""

    entries: dict[str, GeoEntry]
    projection: str
    bad_lines: list[int]
    path: str = ""

    def find(self, name: str) -> GeoEntry | None:
        """The entry of an image: exact name, else case-insensitive name, else a unique
        case-insensitive stem (``DJI_0018.JPG`` matches ``dji_0018.png``)."""
        entry = self.entries.get(name)
        if entry is not None:
            return entry
        folded = name.casefold()
        for key, value in self.entries.items():
            if key.casefold() == folded:
                return value
        stem = Path(name).stem.casefold()
        hits = [v for k, v in self.entries.items() if Path(k).stem.casefold() == stem]
        return hits[0] if len(hits) == 1 else None


def parse_projection(header: str) -> Projection:
    """``(geo_x, geo_y) -> (lat, lon)`` for a geo.txt projection line.

    Raises
    ------
    InputError
        The projection is not WGS 84 geographic or WGS 84 / UTM.
    """
    text = header.strip().strip("'\"")
    m = _EPSG.match(text)
    if m:
        code = int(m.group(1))
        if code == 4326:
            return _lonlat
        try:
            epsg_zone(code)
        except ValueError:
            raise InputError(_unsupported(header)) from None
        return _utm(code)
    m = _UTM_NAME.match(text)
    if m and 1 <= int(m.group(1)) <= 60:
        return _utm((32600 if m.group(2).upper() == "N" else 32700) + int(m.group(1)))
    if text.startswith("+proj") or " +proj" in text:
        args = dict(part.lstrip("+").partition("=")[::2] for part in text.split() if part.startswith("+"))
        wgs84 = args.get("datum", "").upper() == "WGS84" or args.get("ellps", "").upper() == "WGS84"
        if wgs84 and args.get("proj") in ("longlat", "latlong", "lonlat"):
            return _lonlat
        if wgs84 and args.get("proj") == "utm" and args.get("zone", "").isdigit() and 1 <= int(args["zone"]) <= 60:
            return _utm((32700 if "south" in args else 32600) + int(args["zone"]))
    raise InputError(_unsupported(header))


def _unsupported(header: str) -> str:
    return (f"geo.txt: projection {header.strip()!r} is not supported: use EPSG:4326 (lon lat), "
            f"EPSG:326zz/327zz, 'WGS84 UTM <zone>N|S' or '+proj=utm +zone=<zone> [+south] +datum=WGS84'")


def _lonlat(x: float, y: float) -> tuple[float, float]:
    return y, x


def _utm(epsg: int) -> Projection:
    def convert(x: float, y: float) -> tuple[float, float]:
        lat, lon = utm_inverse(np.array([x]), np.array([y]), epsg)
        return float(lat[0]), float(lon[0])
    return convert


def parse_geo_txt(text: str, *, path: str = "") -> GeoFile:
    """Parse the text of a geo.txt (see the module docstring).

    Lines with fewer than three fields, non-numeric coordinates or a position outside
    WGS 84's range are skipped and listed in ``bad_lines``; a later line for the same image
    replaces an earlier one.

    Raises
    ------
    InputError
        No projection line, or an unsupported projection.
    """
    lines = text.splitlines()
    header_at = next((i for i, line in enumerate(lines)
                      if line.strip() and not line.lstrip().startswith("#")), None)
    if header_at is None:
        raise InputError(f"geo.txt {path}: empty, no projection line" if path else "geo.txt: empty, no projection line")
    header = lines[header_at].strip()
    to_latlon = parse_projection(header)
    entries: dict[str, GeoEntry] = {}
    bad: list[int] = []
    for number, line in enumerate(lines[header_at + 1:], start=header_at + 2):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        entry = _entry(parts, to_latlon)
        if entry is None:
            bad.append(number)
        else:
            entries[entry.name] = entry
    if bad:
        log.warning("geo.txt %s: %d malformed line(s) skipped (first: line %d)", path, len(bad), bad[0])
    return GeoFile(entries=entries, projection=header, bad_lines=bad, path=path)


def _number(text: str) -> float | None:
    try:
        v = float(text)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


def _entry(parts: list[str], to_latlon: Projection) -> GeoEntry | None:
    if len(parts) < 3:
        return None
    x, y = _number(parts[1]), _number(parts[2])
    if x is None or y is None:
        return None
    try:
        lat, lon = to_latlon(x, y)
    except (ValueError, FloatingPointError):
        return None
    if not (math.isfinite(lat) and math.isfinite(lon) and -90 <= lat <= 90 and -180 <= lon <= 180):
        return None
    alt = _number(parts[3]) if len(parts) >= 4 else None
    if len(parts) >= 4 and alt is None:
        return None
    yaw = pitch = roll = None
    if len(parts) >= 7:
        angles = [_number(p) for p in parts[4:7]]
        if any(a is None for a in angles):
            return None
        if any(a != 0.0 for a in angles):   # all zero: "not available" (OpenDroneMap docs)
            yaw, pitch, roll = angles
    h_acc = v_acc = None
    if len(parts) >= 9:
        h_acc, v_acc = _number(parts[7]), _number(parts[8])
    return GeoEntry(name=parts[0], lat=lat, lon=lon, alt=alt, yaw=yaw, pitch=pitch, roll=roll,
                    horizontal_accuracy=h_acc, vertical_accuracy=v_acc)


def read_geo_txt(path: str | Path) -> GeoFile:
    """Read and parse a geo.txt file.

    Raises
    ------
    InputError
        The file is missing or unreadable, has no projection line, or an unsupported one.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig", errors="replace")
    except OSError as exc:
        raise InputError(f"geo.txt not readable: {path} ({exc.strerror or exc})") from None
    return parse_geo_txt(text, path=str(path))
