"""Telemetry a survey still carries in its own metadata: EXIF and DJI XMP.

Read with Pillow (``Image.getexif()``, its Exif and GPS sub-IFDs, and the raw XMP packet that
Pillow exposes) and, for the XMP packet, the standard library's ``xml.etree.ElementTree`` (a
regular-expression fallback reads packets that are not well-formed XML). Pillow was chosen over
exifread: it is already installed (rerun pulls it in), it reads the XMP packet of JPEG, TIFF,
PNG and WebP files without a second pass over the file, and its tag values come decoded
(rationals as ``IFDRational``, ASCII as ``str``).

What is read, and the conventions of :class:`StillMetadata`
-----------------------------------------------------------
- capture time: EXIF ``DateTimeOriginal`` (+ ``SubSecTimeOriginal``, ``OffsetTimeOriginal``;
  fallback IFD0 ``DateTime``), seconds since the Unix epoch (:func:`parse_exif_datetime`);
- ``lat``, ``lon`` [deg WGS84]: EXIF GPS (degrees/minutes/seconds with their N/S, E/W refs),
  else DJI XMP ``GpsLatitude``/``GpsLongitude`` (or DJI's misspelt ``GpsLongtitude``);
- ``alt`` [m above mean sea level]: EXIF ``GPSAltitude`` with ``GPSAltitudeRef`` (1 = below
  sea level), else DJI XMP ``AbsoluteAltitude``;
- ``relative_alt`` [m above the take-off point]: DJI XMP ``RelativeAltitude``;
- ``lrf_distance`` [m along the optical axis to the ground at the image centre]: the laser range
  finder of DJI enterprise cameras, XMP ``LRFTargetDistance`` where ``LRFStatus`` is ``Normal``
  (or absent); the height over what is under the drone (canopy, roof), where ``relative_alt``
  is over the take-off point;
- DJI gimbal and airframe angles [deg], as written: ``Gimbal{Yaw,Pitch,Roll}Degree``,
  ``Flight{Yaw,Pitch,Roll}Degree``. The ``drone-dji`` namespace is recognised by its prefix or
  by a namespace URI containing ``/drone-dji/`` (DJI has used ``www.dji.com`` and ``www.uav.com``);
- ``focal_px``: focal length in pixels at the still's own resolution (see :func:`focal_length_px`).

Every field is ``None`` when missing, malformed or implausible; reading never raises for bad
metadata. :func:`still_sample` turns a still's metadata into a
:class:`~photomap.telemetry.samples.TelemetrySample` (SI units, radians, MAVLink conventions).
"""

from __future__ import annotations

import calendar
import logging
import math
import re
import statistics
import warnings
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, Mapping
from xml.etree import ElementTree

import numpy as np
from PIL import ExifTags, Image

from photomap.telemetry.samples import TelemetrySample, wrap_angle

log = logging.getLogger(__name__)

# EXIF tags (Exif 2.32 / CIPA DC-008)
_TAG_ORIENTATION = 0x0112
_TAG_MAKE = 0x010F
_TAG_MODEL = 0x0110
_TAG_DATETIME = 0x0132                 # IFD0 DateTime (last modification): fallback only
_TAG_DATETIME_ORIGINAL = 0x9003
_TAG_OFFSET_TIME_ORIGINAL = 0x9011
_TAG_SUBSEC_TIME_ORIGINAL = 0x9291
_TAG_FOCAL_LENGTH = 0x920A
_TAG_FOCAL_35MM = 0xA405
_TAG_PIXEL_X_DIMENSION = 0xA002
_TAG_FOCAL_PLANE_X_RES = 0xA20E
_TAG_FOCAL_PLANE_UNIT = 0xA210
_TAG_XMP = 700                         # TIFF XMLPacket
_GPS_LAT_REF, _GPS_LAT, _GPS_LON_REF, _GPS_LON, _GPS_ALT_REF, _GPS_ALT = 1, 2, 3, 4, 5, 6

_OFFSET = re.compile(r"^([+-])(\d\d):(\d\d)$")
_MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}   # FocalPlaneResolutionUnit: inch, cm, mm, um
_DIAGONAL_35MM = math.hypot(36.0, 24.0)               # mm, diagonal of a 36 x 24 mm frame

#: Sensor widths (mm) of cameras whose EXIF gives a focal length but no sensor size, by
#: lowercase ``"make model"``. Values from OpenSfM's ``opensfm/data/sensor_data.json``
#: (mapillary/OpenSfM); the Hasselblad L1D-20c (DJI Mavic 2 Pro, 1" sensor) from its EXIF
#: (FocalLength 10.26 mm, FocalLengthIn35mmFilm 28 at 5472 x 3648 px).
SENSOR_WIDTH_MM: dict[str, float] = {
    "dji fc220": 6.17,
    "dji fc300c": 6.31,
    "dji fc300s": 6.16,
    "dji fc300x": 6.2,
    "dji fc330": 6.25,
    "dji fc350": 6.17,
    "dji fc6310": 13.2,
    "hasselblad l1d-20c": 13.2,
    "canon canon powershot elph 300 hs": 6.16,
    "canon powershot elph 300 hs": 6.16,
}

# Plausibility limits (a value outside is dropped, as for MAVLink samples)
_ALT_RANGE = (-500.0, 12000.0)        # m AMSL
_REL_ALT_RANGE = (-2000.0, 12000.0)   # m above home
_LRF_RANGE = (0.5, 3000.0)            # m: DJI's range finders read 3-1200 m; 0 = no return
_ANGLE_LIMIT = 360.0                  # deg

# Display rotation of the image's up direction (clockwise, deg) that each EXIF orientation
# implies once a reader (OpenCV's imread does) applies it. 2, 4, 5 and 7 are mirrored.
_ORIENTATION_TURN = {1: 0.0, 3: 180.0, 6: -90.0, 8: 90.0}
_MIRRORED = {2, 4, 5, 7}

_DJI_URI_MARK = "/drone-dji/"
_DJI_ATTR = re.compile(rb"drone-dji:(\w+)\s*=\s*\"([^\"]*)\"")
_DJI_ELEM = re.compile(rb"<drone-dji:(\w+)>([^<]*)</drone-dji:\1>")
_XMP_START = re.compile(rb"<x:xmpmeta|<rdf:RDF")
_XMP_END = re.compile(rb"</x:xmpmeta>|</rdf:RDF>")


@dataclass(frozen=True)
class StillMetadata:
    """What one still's metadata says (see the module docstring for units and sources).

    ``width``, ``height``: the stored image size in pixels (before any EXIF rotation).
    ``orientation``: the EXIF orientation code (1 = as stored). ``problems``: fields that were
    present but dropped, with the reason, e.g. ``("lat/lon: bad GPS ref 'X'",)``.
    """

    name: str
    width: int | None = None
    height: int | None = None
    time: float | None = None
    lat: float | None = None
    lon: float | None = None
    alt: float | None = None
    relative_alt: float | None = None
    lrf_distance: float | None = None
    gimbal_yaw: float | None = None
    gimbal_pitch: float | None = None
    gimbal_roll: float | None = None
    flight_yaw: float | None = None
    flight_pitch: float | None = None
    flight_roll: float | None = None
    focal_px: float | None = None
    focal_source: str | None = None
    orientation: int = 1
    make: str | None = None
    model: str | None = None
    problems: tuple[str, ...] = field(default=())

    @property
    def has_gps(self) -> bool:
        return self.lat is not None and self.lon is not None

    @property
    def has_gimbal(self) -> bool:
        return any(v is not None for v in (self.gimbal_yaw, self.gimbal_pitch, self.gimbal_roll))


# --------------------------------------------------------------------------- time

def parse_exif_datetime(text: str, subsec: str | None = None, offset: str | None = None) -> float:
    """Seconds since the Unix epoch of an EXIF date/time.

    Parameters
    ----------
    text : str
        ``"YYYY:MM:DD HH:MM:SS"`` (EXIF DateTimeOriginal).
    subsec : str, optional
        EXIF SubSecTimeOriginal: the digits of the decimal fraction (``"25"`` = 0.25 s).
    offset : str, optional
        EXIF OffsetTimeOriginal, ``"+HH:MM"``. Without it the clock is taken as UTC (EXIF
        times are the camera's local time; only differences matter within one flight).

    Raises
    ------
    ValueError
        ``text`` (or ``offset``) is not in EXIF format.
    """
    stamp = datetime.strptime(text.strip(), "%Y:%m:%d %H:%M:%S")
    seconds = float(calendar.timegm(stamp.timetuple()))
    digits = (subsec or "").strip()
    if digits.isdigit():
        seconds += int(digits) / 10 ** len(digits)
    if offset and offset.strip():
        m = _OFFSET.match(offset.strip())
        if m is None:
            raise ValueError(f"bad EXIF time offset {offset!r}")
        sign = 1 if m.group(1) == "+" else -1
        seconds -= sign * (int(m.group(2)) * 3600 + int(m.group(3)) * 60)
    return seconds


def _text(value: Any) -> str | None:
    """An EXIF ASCII value as a stripped str (None when empty or not text)."""
    if isinstance(value, bytes):
        value = value.decode("ascii", "replace")
    if not isinstance(value, str):
        return None
    value = value.split("\x00", 1)[0].strip()
    return value or None


def capture_time(ifd0: Mapping[int, Any], exif_ifd: Mapping[int, Any]) -> float | None:
    """Capture time (UNIX seconds) from decoded EXIF: DateTimeOriginal, else IFD0 DateTime."""
    text = _text(exif_ifd.get(_TAG_DATETIME_ORIGINAL))
    subsec = _text(exif_ifd.get(_TAG_SUBSEC_TIME_ORIGINAL))
    offset = _text(exif_ifd.get(_TAG_OFFSET_TIME_ORIGINAL))
    if not text:
        text, subsec, offset = _text(ifd0.get(_TAG_DATETIME)), None, None
    if not text:
        return None
    try:
        return parse_exif_datetime(text, subsec, offset)
    except ValueError:
        try:  # a bad offset or sub-second field does not void the time itself
            return parse_exif_datetime(text)
        except ValueError:
            return None


def read_capture_time(path: str | Path) -> float | None:
    """Capture time of a still from its EXIF (UNIX seconds), or None; never raises."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")   # Pillow warns on corrupt EXIF: no time then
            with Image.open(path) as im:
                exif = im.getexif()
                return capture_time(exif, exif.get_ifd(ExifTags.IFD.Exif))
    except Exception as exc:  # noqa: BLE001 - untrusted file: any parser failure means "no time"
        log.debug("%s: no usable EXIF time (%s: %s)", path, type(exc).__name__, exc)
        return None


# --------------------------------------------------------------------------- numbers

def _float(value: Any) -> float | None:
    """A finite float from an EXIF/XMP value (IFDRational, int, ``"+39.80"``, ``"361/100"``)."""
    try:
        if isinstance(value, (bytes, str)):
            text = value.decode("ascii", "replace") if isinstance(value, bytes) else value
            text = text.strip().strip("\x00")
            if "/" in text:
                num, den = text.split("/", 1)
                v = float(num) / float(den)
            else:
                v = float(text)
        elif isinstance(value, (tuple, list)):
            return None
        else:
            v = float(value)
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return None
    return v if math.isfinite(v) else None


def _in(v: float | None, lo: float, hi: float) -> float | None:
    return v if v is not None and lo <= v <= hi else None


def _dms(value: Any) -> float | None:
    """Degrees from an EXIF (degrees, minutes, seconds) triple, None when malformed."""
    if not isinstance(value, (tuple, list)) or len(value) != 3:
        return None
    d, m, s = (_float(v) for v in value)
    if d is None or m is None or s is None or d < 0 or not 0 <= m < 60 or not 0 <= s < 60.001:
        return None
    return d + m / 60.0 + s / 3600.0


def _ref(value: Any, positive: str, negative: str) -> float | None:
    """+1/-1 for a GPS reference letter, None for anything else."""
    text = (_text(value) or "").upper()
    return 1.0 if text == positive else -1.0 if text == negative else None


def _gps(gps: Mapping[int, Any], problems: list[str]) -> tuple[float | None, float | None, float | None]:
    """(lat, lon, alt AMSL) from a decoded EXIF GPS IFD."""
    lat = lon = alt = None
    if _GPS_LAT in gps or _GPS_LON in gps:
        lat_deg, lon_deg = _dms(gps.get(_GPS_LAT)), _dms(gps.get(_GPS_LON))
        lat_sign = _ref(gps.get(_GPS_LAT_REF), "N", "S")
        lon_sign = _ref(gps.get(_GPS_LON_REF), "E", "W")
        if lat_deg is None or lon_deg is None:
            problems.append("lat/lon: malformed GPS coordinates")
        elif lat_sign is None or lon_sign is None:
            problems.append(f"lat/lon: bad GPS refs {gps.get(_GPS_LAT_REF)!r}/{gps.get(_GPS_LON_REF)!r}")
        elif lat_deg > 90.0 or lon_deg > 180.0:
            problems.append("lat/lon: out of range")
        elif lat_deg == 0.0 and lon_deg == 0.0:
            problems.append("lat/lon: no GPS fix (0/0)")
        else:
            lat, lon = lat_sign * lat_deg, lon_sign * lon_deg
    if _GPS_ALT in gps:
        value = _float(gps.get(_GPS_ALT))
        ref = gps.get(_GPS_ALT_REF, 0)   # Exif: absent means 0 = above sea level
        if isinstance(ref, bytes):
            ref = ref[0] if len(ref) == 1 else None
        sign = {0: 1.0, 1: -1.0}.get(ref) if isinstance(ref, int) else None
        if value is None or sign is None:
            problems.append(f"alt: malformed GPS altitude {gps.get(_GPS_ALT)!r} (ref {gps.get(_GPS_ALT_REF)!r})")
        else:
            alt = _in(sign * value, *_ALT_RANGE)
            if alt is None:
                problems.append("alt: out of range")
    return lat, lon, alt


# --------------------------------------------------------------------------- XMP

def xmp_packet(im: Image.Image) -> bytes | None:
    """The raw XMP packet of an opened image (JPEG APP1, TIFF tag 700, PNG iTXt, WebP), or None."""
    for key in ("xmp", "XML:com.adobe.xmp"):
        value = im.info.get(key)
        if value:
            return value.encode("utf-8") if isinstance(value, str) else bytes(value)
    tags = getattr(im, "tag_v2", None)
    if tags is not None and _TAG_XMP in tags:
        value = tags[_TAG_XMP]
        return value.encode("utf-8") if isinstance(value, str) else bytes(value)
    return None


def parse_dji_xmp(packet: bytes | str) -> dict[str, str]:
    """The ``drone-dji`` properties of an XMP packet: local name -> text, e.g.
    ``{"GimbalPitchDegree": "-89.90", ...}``.

    Properties may be attributes of ``rdf:Description`` (what DJI writes) or child elements.
    A packet that is not well-formed XML (undeclared prefix, trailing bytes, a DOCTYPE, which is
    never parsed) is read with a regular expression over ``drone-dji:Name="value"`` and
    ``<drone-dji:Name>value</drone-dji:Name>``. Never raises; an unreadable packet gives ``{}``.
    """
    data = packet.encode("utf-8") if isinstance(packet, str) else bytes(packet)
    start, end = _XMP_START.search(data), None
    if start is not None:
        ends = list(_XMP_END.finditer(data, start.start()))
        end = ends[-1] if ends else None
    out: dict[str, str] = {}
    if start is not None and end is not None and b"<!DOCTYPE" not in data and b"<!ENTITY" not in data:
        try:
            root = ElementTree.fromstring(data[start.start():end.end()])
        except ElementTree.ParseError:
            root = None
        if root is not None:
            for el in root.iter():
                for key, value in el.attrib.items():
                    ns, _, local = key[1:].partition("}") if key.startswith("{") else ("", "", key)
                    if _DJI_URI_MARK in ns:
                        out.setdefault(local, value.strip())
                if el.tag.startswith("{"):
                    ns, _, local = el.tag[1:].partition("}")
                    if _DJI_URI_MARK in ns and el.text and el.text.strip():
                        out.setdefault(local, el.text.strip())
            return out
    for rx in (_DJI_ATTR, _DJI_ELEM):
        for m in rx.finditer(data):
            out.setdefault(m.group(1).decode("ascii"), m.group(2).decode("utf-8", "replace").strip())
    return out


def _angle(props: Mapping[str, str], name: str, problems: list[str]) -> float | None:
    if name not in props:
        return None
    v = _in(_float(props[name]), -_ANGLE_LIMIT, _ANGLE_LIMIT)
    if v is None:
        problems.append(f"{name}: unreadable {props[name]!r}")
    return v


# --------------------------------------------------------------------------- focal length

def sensor_width_mm(make: str | None, model: str | None) -> float | None:
    """Known sensor width of a camera (:data:`SENSOR_WIDTH_MM`), or None."""
    key = " ".join(s.strip().lower() for s in (make, model) if s and s.strip())
    return SENSOR_WIDTH_MM.get(key)


def focal_length_px(width: int, height: int, *, focal_mm: float | None = None,
                    focal_35mm: float | None = None, plane_x_res: float | None = None,
                    plane_unit: int | None = None, exif_width: int | None = None,
                    sensor_mm: float | None = None) -> tuple[float | None, str | None]:
    """Focal length in pixels at ``width`` x ``height`` (the image as stored), and its source.

    In order of preference:

    1. ``"focal_plane"``: ``focal_mm`` with the sensor width from EXIF FocalPlaneXResolution
       (pixels per ``plane_unit``, at ``exif_width`` pixels, EXIF PixelXDimension, when the
       image was resized since): ``fx = focal_mm * plane_x_res / mm_per_unit * width / exif_width``;
    2. ``"sensor_table"``: ``focal_mm`` with a known sensor width: ``fx = focal_mm / sensor_mm * width``;
    3. ``"35mm"``: FocalLengthIn35mmFilm over the 43.27 mm diagonal of a 36 x 24 mm frame,
       scaled to the image diagonal: ``fx = focal_35mm / 43.27 * hypot(width, height)``
       (approximate: cameras write the nominal value of their native aspect ratio).

    Returns ``(None, None)`` when none applies. Square pixels and a full-sensor image are assumed.
    """
    if width <= 0 or height <= 0:
        return None, None
    if focal_mm and focal_mm > 0:
        mm_per_unit = _MM_PER_UNIT.get(plane_unit or 2)
        if plane_x_res and plane_x_res > 0 and mm_per_unit:
            ref = exif_width if exif_width and exif_width > 0 else width
            return focal_mm * plane_x_res / mm_per_unit * width / ref, "focal_plane"
        if sensor_mm and sensor_mm > 0:
            return focal_mm / sensor_mm * width, "sensor_table"
    if focal_35mm and focal_35mm > 0:
        return focal_35mm / _DIAGONAL_35MM * math.hypot(width, height), "35mm"
    return None, None


# --------------------------------------------------------------------------- one still

def read_still_metadata(path: str | Path) -> StillMetadata:
    """Everything :class:`StillMetadata` holds, from one file; never raises.

    A file Pillow cannot open, or one without metadata, gives a :class:`StillMetadata` whose
    fields are all None (the reason in ``problems``).
    """
    path = Path(path)
    problems: list[str] = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with Image.open(path) as im:
                width, height = im.size
                exif = im.getexif()
                ifd0 = dict(exif)
                exif_ifd = _safe_ifd(exif, ExifTags.IFD.Exif, problems)
                gps_ifd = _safe_ifd(exif, ExifTags.IFD.GPSInfo, problems)
                packet = xmp_packet(im)
        # Pillow warns on corrupt EXIF; a ResourceWarning is some other object's finaliser that
        # the garbage collector happened to run here, not this file's
        problems += [f"EXIF: {w.message}" for w in caught if not issubclass(w.category, ResourceWarning)]
    except Exception as exc:  # noqa: BLE001 - untrusted file: any parser failure means "no metadata"
        log.debug("%s: metadata unreadable (%s: %s)", path, type(exc).__name__, exc)
        return StillMetadata(name=path.name, problems=(f"unreadable: {type(exc).__name__}: {exc}",))
    dji = parse_dji_xmp(packet) if packet else {}

    lat, lon, alt = _gps(gps_ifd, problems)
    if lat is None and lon is None:
        xlat = _in(_float(dji.get("GpsLatitude")), -90.0, 90.0)
        xlon = _in(_float(dji.get("GpsLongitude", dji.get("GpsLongtitude"))), -180.0, 180.0)
        if xlat is not None and xlon is not None and (xlat, xlon) != (0.0, 0.0):
            lat, lon = xlat, xlon
    if alt is None and "AbsoluteAltitude" in dji:
        alt = _in(_float(dji["AbsoluteAltitude"]), *_ALT_RANGE)
        if alt is None:
            problems.append(f"AbsoluteAltitude: unreadable {dji['AbsoluteAltitude']!r}")
    relative_alt = None
    if "RelativeAltitude" in dji:
        relative_alt = _in(_float(dji["RelativeAltitude"]), *_REL_ALT_RANGE)
        if relative_alt is None:
            problems.append(f"RelativeAltitude: unreadable {dji['RelativeAltitude']!r}")

    lrf_distance = _lrf_distance(dji, problems)

    orientation = ifd0.get(_TAG_ORIENTATION, 1)
    if not isinstance(orientation, int) or not 1 <= orientation <= 8:
        problems.append(f"orientation: bad value {orientation!r}")
        orientation = 1
    make, model = _text(ifd0.get(_TAG_MAKE)), _text(ifd0.get(_TAG_MODEL))
    exif_width = exif_ifd.get(_TAG_PIXEL_X_DIMENSION)
    unit = exif_ifd.get(_TAG_FOCAL_PLANE_UNIT)
    fx, source = focal_length_px(
        width, height, focal_mm=_float(exif_ifd.get(_TAG_FOCAL_LENGTH)),
        focal_35mm=_float(exif_ifd.get(_TAG_FOCAL_35MM)),
        plane_x_res=_float(exif_ifd.get(_TAG_FOCAL_PLANE_X_RES)),
        plane_unit=unit if isinstance(unit, int) else None,
        exif_width=exif_width if isinstance(exif_width, int) else None,
        sensor_mm=sensor_width_mm(make, model))
    return StillMetadata(
        name=path.name, width=width, height=height, time=capture_time(ifd0, exif_ifd),
        lat=lat, lon=lon, alt=alt, relative_alt=relative_alt, lrf_distance=lrf_distance,
        gimbal_yaw=_angle(dji, "GimbalYawDegree", problems),
        gimbal_pitch=_angle(dji, "GimbalPitchDegree", problems),
        gimbal_roll=_angle(dji, "GimbalRollDegree", problems),
        flight_yaw=_angle(dji, "FlightYawDegree", problems),
        flight_pitch=_angle(dji, "FlightPitchDegree", problems),
        flight_roll=_angle(dji, "FlightRollDegree", problems),
        focal_px=fx, focal_source=source, orientation=orientation, make=make, model=model,
        problems=tuple(problems))


def _lrf_distance(dji: Mapping[str, str], problems: list[str]) -> float | None:
    """The laser range finder's ``LRFTargetDistance`` (m) where its ``LRFStatus`` says it measured.

    DJI writes the status ``Normal`` for a valid reading (other words: out of range, no return)
    and a distance of 0 without one; such readings are skipped quietly (a still over open
    sky or water), an unreadable number is a problem.
    """
    if "LRFTargetDistance" not in dji:
        return None
    status = dji.get("LRFStatus")
    if status is not None and status.strip().lower() != "normal":
        return None
    value = _float(dji["LRFTargetDistance"])
    if value is None:
        problems.append(f"LRFTargetDistance: unreadable {dji['LRFTargetDistance']!r}")
        return None
    return _in(value, *_LRF_RANGE)


def _safe_ifd(exif: Image.Exif, tag: int, problems: list[str]) -> dict[int, Any]:
    """A sub-IFD as a dict; ``{}`` (and a problem noted) when Pillow cannot read it."""
    try:
        return dict(exif.get_ifd(tag))
    except Exception as exc:  # noqa: BLE001 - a broken sub-IFD voids only its own fields
        problems.append(f"IFD 0x{int(tag):04x}: unreadable ({type(exc).__name__})")
        return {}


# --------------------------------------------------------------------------- to a sample

def _rot_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Body -> NED rotation of MAVLink Euler angles (radians): ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    cy, sy, cp, sp, cr, sr = (math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch),
                              math.cos(roll), math.sin(roll))
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def _euler_zyx(r: np.ndarray) -> tuple[float, float, float]:
    """(yaw, pitch, roll) radians of a body -> NED rotation (inverse of :func:`_rot_zyx`)."""
    pitch = -math.asin(max(-1.0, min(1.0, float(r[2, 0]))))
    return math.atan2(r[1, 0], r[0, 0]), pitch, math.atan2(r[2, 1], r[2, 2])


def camera_attitude(meta: StillMetadata) -> tuple[float | None, float | None, float | None]:
    """(roll, pitch, yaw) in radians of the still's camera, in the convention of MAVLink's
    ``ATTITUDE`` for a camera fixed to the body looking straight down with image up = forward.

    That is what :func:`photomap.geo.georef.nadir_homography` (tilt rectification) and the yaw
    priors expect: ``yaw`` is the heading of the image's up direction (clockwise from north),
    ``pitch`` > 0 tilts the view forward (towards image up) of nadir, ``roll`` > 0 tilts it to
    the left (the right side goes down).

    - With a gimbal recorded (DJI ``Gimbal*Degree``): ``yaw`` = gimbal yaw (flight yaw if the
      gimbal's is missing), ``pitch`` = gimbal pitch + 90 deg (a gimbal at -90 is nadir, so
      -89.9 is 0.1 deg of tilt whatever the airframe does), ``roll`` = gimbal roll (the angles of
      OpenDroneMap and Orthority for DJI stills).
    - Otherwise the camera is taken as fixed to the airframe: ``Flight*Degree`` as they are.
    - An EXIF orientation other than 1 (OpenCV's ``imread`` rotates the image upright) turns
      the image about the optical axis: the angles are those of the rotated image. A mirrored
      orientation gives no attitude.
    """
    if meta.has_gimbal:
        yaw = meta.gimbal_yaw if meta.gimbal_yaw is not None else meta.flight_yaw
        pitch = None if meta.gimbal_pitch is None else meta.gimbal_pitch + 90.0
        roll = meta.gimbal_roll
    else:
        yaw, pitch, roll = meta.flight_yaw, meta.flight_pitch, meta.flight_roll
    if meta.orientation in _MIRRORED:
        return None, None, None
    turn = _ORIENTATION_TURN.get(meta.orientation, 0.0)
    rad = (lambda v: None if v is None else math.radians(v))
    roll_r, pitch_r, yaw_r = rad(roll), rad(pitch), rad(yaw)
    if turn:
        if roll_r is not None and pitch_r is not None:
            r = _rot_zyx(yaw_r or 0.0, pitch_r, roll_r) @ _rot_zyx(math.radians(turn), 0.0, 0.0)
            y2, pitch_r, roll_r = _euler_zyx(r)
            yaw_r = None if yaw_r is None else y2
        elif yaw_r is not None:
            yaw_r += math.radians(turn)
            roll_r = pitch_r = None
        else:
            roll_r = pitch_r = None
    return (None if roll_r is None else wrap_angle(roll_r),
            None if pitch_r is None else wrap_angle(pitch_r),
            None if yaw_r is None else wrap_angle(yaw_r))


def still_sample(meta: StillMetadata, t: float | None = None) -> TelemetrySample | None:
    """The still's telemetry as a sample at time ``t`` (default: its EXIF capture time).

    ``lat``, ``lon`` [deg], ``alt`` [m AMSL], ``relative_alt`` [m above take-off],
    ``roll``, ``pitch``, ``yaw`` [rad] from :func:`camera_attitude`, and ``height_above_ground``:
    the laser range finder's distance tilt-corrected by ``cos(roll) cos(pitch)`` (as a MAVLink
    rangefinder is; ``height_source = "rangefinder"``, ``rangefinder`` the distance), else
    ``relative_alt`` with ``height_source = "home"`` (flat ground). None when the still tells
    nothing (no position, altitude or attitude) or has no time.
    """
    t = meta.time if t is None else t
    if t is None:
        return None
    roll, pitch, yaw = camera_attitude(meta)
    lat, lon = (meta.lat, meta.lon) if meta.has_gps else (None, None)
    values = (lat, meta.alt, meta.relative_alt, roll, pitch, yaw)
    if all(v is None for v in values):
        return None
    height, source = meta.relative_alt, None if meta.relative_alt is None else "home"
    if meta.lrf_distance is not None:
        height = meta.lrf_distance * math.cos(roll or 0.0) * math.cos(pitch or 0.0)
        source = "rangefinder"
    return TelemetrySample(t=float(t), lat=lat, lon=lon, alt=meta.alt,
                           relative_alt=meta.relative_alt, roll=roll, pitch=pitch, yaw=yaw,
                           rangefinder=meta.lrf_distance, height_above_ground=height, height_source=source)


def median_focal_px(metas: list[StillMetadata]) -> float | None:
    """Median focal length (pixels) over the stills that give one, or None."""
    values = [m.focal_px for m in metas if m.focal_px is not None]
    return float(statistics.median(values)) if values else None
