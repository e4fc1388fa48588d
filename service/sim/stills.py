"""A survey of still images, like a DJI mapping mission: lawn-mower strips, fixed forward overlap,
180-degree turns between strips; stills written as JPEG with EXIF (and DJI-style XMP).

Planning is pure (arrays in, arrays out); :func:`write_still` writes one file with Pillow.

Survey geometry
---------------
Strips run east-west (along terrain x), the first one eastwards, the next one ``spacing`` to the
south, and so on; consecutive strips are joined by a half circle of radius ``spacing / 2``
(right turn at the east end, left turn at the west end). The aircraft's heading follows the
track. With ``yaw_mode = "flip"`` the camera's up axis is the heading, so the picture turns by
exactly 180 degrees from one strip to the next; with ``"hold"`` a gimbal keeps the camera's
heading east on every strip (the picture never turns) while the aircraft, and the telemetry's
yaw, turn around: the telemetry then disagrees with the images by 180 degrees on every other
strip (as in real DJI logs, where the logged yaw flips and the picture does not). ``spacing = (1 - side_overlap) * width * s`` and the distance between
consecutive stills is ``d = (1 - forward_overlap) * height * s``, with ``s`` terrain px per frame
px at nadir (the frame's width is across the track, its height along it). Each strip holds
``per_strip`` stills, the first ``d / 2`` after the strip's start. The survey flies at the middle
of the altitude range, at constant height and speed.

Times: ``t = 0`` at the first still; the telemetry samples start at the first strip's start
(``t < 0``) and end at the last strip's end.
"""

from __future__ import annotations

import math
from dataclasses import fields
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from photomap.errors import InputError, PhotomapError
from photomap.sim.flight import (Camera, Motion, Truth, _safe_rectangle, _smooth_random, coordinated_bank,
                                 footprint_radius, footprints_outside, pose_homography)

# Sensor width (mm) assumed for the EXIF focal length in millimetres (a 1/2.3" sensor, as on
# many small drones); the focal length in pixels is exact through FocalPlaneXResolution.
SENSOR_WIDTH_MM = 6.17
FULL_FRAME_DIAGONAL_MM = 43.2666       # 36 x 24 mm
SURVEY_YAW_MODES = ("flip", "hold")


def subset(truth: Truth, idx: np.ndarray) -> Truth:
    """The entries ``idx`` of a truth."""
    return Truth(**{f.name: getattr(truth, f.name)[idx] for f in fields(Truth)})


def plan_survey(valid: np.ndarray, camera: Camera, gsd: float, motion: Motion, *, strips: int, per_strip: int,
                forward_overlap: float, yaw_mode: str = "flip", rate_hz: float = 20.0,
                seed: int = 0) -> tuple[Truth, np.ndarray, np.ndarray]:
    """Plan a still-image survey over ``valid`` (bool, terrain shape), see the module docstring.

    Parameters
    ----------
    camera, gsd : the camera and metres per terrain pixel.
    motion : speed, altitude (the middle of the range is flown), side_overlap, tilt (random
        roll/pitch amplitude), max_bank / pitch_offset (a fixed-wing's coordinated turns),
        period_s; pattern and yaw settings do not apply.
    strips, per_strip : number of strips and of stills per strip.
    forward_overlap : overlap of consecutive stills along a strip, 0..1.
    yaw_mode : ``flip`` (the camera turns with the aircraft) or ``hold`` (a gimbal keeps it
        heading east).
    rate_hz : telemetry sample rate (the tlog interpolates between samples).

    Returns
    -------
    truth : every sample (telemetry grid plus the still times, increasing ``t``); its yaw is
        the camera's (the angle of H).
    stills : indices of the stills in ``truth``, in capture order.
    flight_yaw : the aircraft's heading at every sample (deg, clockwise from north): the course;
        equal to ``truth.yaw_deg`` with ``flip``.
    """
    if yaw_mode not in SURVEY_YAW_MODES:
        raise InputError(f"survey yaw mode must be one of {', '.join(SURVEY_YAW_MODES)}, got {yaw_mode!r}")
    if strips < 1 or per_strip < 2:
        raise InputError(f"a survey needs at least 1 strip of 2 stills, got {strips} x {per_strip}")
    if not 0.0 <= forward_overlap < 1.0:
        raise InputError(f"forward overlap must be in 0..1, got {forward_overlap}")
    if motion.speed <= 0:
        raise InputError("a survey needs a ground speed > 0")
    alt = (motion.altitude[0] + motion.altitude[1]) / 2.0
    scale = alt / (camera.fx * gsd)
    spacing = (1.0 - motion.side_overlap) * camera.width * scale
    d = (1.0 - forward_overlap) * camera.height * scale
    r = spacing / 2.0
    length = per_strip * d
    box_w, box_h = length + 2.0 * r, (strips - 1) * spacing
    margin = 2.0 * max(scale, 1.0) + 4.0
    radius = footprint_radius(camera, alt / gsd, motion.tilt, motion.max_bank + abs(motion.pitch_offset)) + margin
    x0, y0, x1, y1 = _safe_rectangle(valid, radius)
    if box_w > x1 - x0 or box_h > y1 - y0:
        raise InputError(f"a survey of {strips} strips x {per_strip} stills needs {box_w:.0f}x{box_h:.0f} terrain px "
                         f"of room for the camera, the terrain has {x1 - x0:.0f}x{y1 - y0:.0f}: use fewer stills, "
                         "a larger terrain or fly lower")
    xa = (x0 + x1) / 2.0 - length / 2.0          # west end of the strips
    xb = xa + length
    ys = (y0 + y1) / 2.0 - box_h / 2.0 + spacing * np.arange(strips)

    # arc length of every piece: strip k, then the turn after it (none after the last strip)
    turn = math.pi * r
    starts = np.arange(strips) * (length + turn)
    total = starts[-1] + length
    still_s = (starts[:, None] + d / 2.0 + d * np.arange(per_strip)[None, :]).ravel()
    v_px = motion.speed / gsd                      # terrain px per second
    t_first = still_s[0] / v_px
    grid = np.arange(0.0, total / v_px + 1e-9, 1.0 / rate_hz)
    t_all = np.unique(np.concatenate([grid, still_s / v_px]))
    # drop grid samples within 1 ms of a still (the still's own sample stays)
    t_still = still_s / v_px
    near = np.abs(t_all[:, None] - t_still[None, :]).min(axis=1) < 1e-3
    keep = ~near | np.isin(t_all, t_still)
    t_all = t_all[keep]
    s_all = t_all * v_px

    k = np.minimum((s_all // (length + turn)).astype(int), strips - 1)
    u = s_all - starts[k]                          # arc length into piece k (strip, then turn)
    east = k % 2 == 0
    on_strip = u <= length
    x = np.where(east, xa + np.minimum(u, length), xb - np.minimum(u, length))
    y = ys[k].astype(float).copy()
    course = np.where(east, 90.0, -90.0)
    phi = np.clip((u - length) / r, 0.0, math.pi)  # angle turned in the half circle
    tx = np.where(east, xb + r * np.sin(phi), xa - r * np.sin(phi))
    ty = ys[k] + r - r * np.cos(phi)
    tc = np.where(east, 90.0 + np.degrees(phi), -90.0 - np.degrees(phi))
    x = np.where(on_strip, x, tx)
    y = np.where(on_strip, y, ty)
    course = np.where(on_strip, course, tc)
    flight_yaw = np.mod(course + 180.0, 360.0) - 180.0
    yaw = flight_yaw if yaw_mode == "flip" else np.full(len(course), 90.0)

    t = t_all - t_first
    n = len(t)
    rng = np.random.default_rng([seed, 30])
    roll = motion.tilt * _smooth_random(t, motion.period_s, rng) if motion.tilt > 0 else np.zeros(n)
    pitch = motion.tilt * _smooth_random(t, motion.period_s, rng) if motion.tilt > 0 else np.zeros(n)
    if motion.max_bank > 0:
        roll = roll + coordinated_bank(np.c_[x, y] * gsd, t, motion.max_bank)
    pitch = pitch + motion.pitch_offset
    alt_m = np.full(n, alt)
    hs = np.stack([pose_homography(camera, px, py, alt / gsd, math.radians(rr), math.radians(pp), math.radians(yy))
                   for px, py, rr, pp, yy in zip(x, y, roll, pitch, yaw)])
    centre = np.einsum("nij,j->ni", hs, [camera.cx, camera.cy, 1.0])
    truth = Truth(t=t, H=hs, x=centre[:, 0] / centre[:, 2], y=centre[:, 1] / centre[:, 2], yaw_deg=yaw,
                  scale=np.full(n, scale), roll_deg=roll, pitch_deg=pitch, alt_m=alt_m, cam_x=x, cam_y=y)
    stills = np.searchsorted(t_all, t_still)
    bad = footprints_outside(subset(truth, stills), camera, valid, margin=2.0)
    if bad.size:
        raise InputError(f"planned stills leave the valid terrain at stills {bad[:5].tolist()}")
    return truth, stills, flight_yaw


# --------------------------------------------------------------------------- EXIF / XMP

def _rational(value: float, den: int = 1_000_000):
    """An EXIF RATIONAL (Pillow's IFDRational) ``round(value * den) / den``."""
    from PIL.TiffImagePlugin import IFDRational
    return IFDRational(int(round(value * den)), den)


def _dms(deg: float) -> tuple:
    """Unsigned degrees -> (deg, min, sec) rationals, seconds to 1e-6 arc-second."""
    a = abs(deg)
    d = int(a)
    m = int((a - d) * 60.0)
    sec = (a - d - m / 60.0) * 3600.0
    return _rational(d, 1), _rational(m, 1), _rational(sec)


def focal_35mm(camera: Camera) -> float:
    """35 mm equivalent focal length (mm) by the diagonal: ``fx * 43.27 / diagonal_px``."""
    return camera.fx * FULL_FRAME_DIAGONAL_MM / math.hypot(camera.width, camera.height)


def dji_attributes(*, rel_alt_m: float, amsl_m: float, lat: float, lon: float, roll: float, pitch: float,
                   yaw: float, camera: Camera, flight_yaw: float | None = None,
                   lrf_m: float | None = None) -> dict[str, str]:
    """The ``drone-dji:`` properties of :func:`dji_xmp` (name -> text); with ``lrf_m``, a laser
    range finder's reading as DJI enterprise cameras store it (``LRFStatus="Normal"``,
    ``LRFTargetDistance``: metres along the optical axis to the ground at the image centre)."""
    def f(v: float, nd: int = 2) -> str:
        return f"{v:+.{nd}f}"

    return {
        "GpsLatitude": f(lat, 9), "GpsLongitude": f(lon, 9),
        "AbsoluteAltitude": f(amsl_m, 3), "RelativeAltitude": f(rel_alt_m, 3),
        "GimbalRollDegree": f(roll), "GimbalYawDegree": f(yaw), "GimbalPitchDegree": f(pitch - 90.0),
        "FlightRollDegree": f(roll), "FlightYawDegree": f(yaw if flight_yaw is None else flight_yaw),
        "FlightPitchDegree": f(pitch),
        "CalibratedFocalLength": f"{camera.fx:.4f}", "CalibratedOpticalCenterX": f"{camera.cx:.4f}",
        "CalibratedOpticalCenterY": f"{camera.cy:.4f}",
    } | ({} if lrf_m is None else {"LRFStatus": "Normal", "LRFTargetDistance": f"{lrf_m:.3f}"})


def dji_xmp(*, rel_alt_m: float, amsl_m: float, lat: float, lon: float, roll: float, pitch: float, yaw: float,
            camera: Camera, flight_yaw: float | None = None, lrf_m: float | None = None) -> bytes:
    """A DJI-style XMP packet (``drone-dji:`` attributes, values like ``"+39.80"``).

    Gimbal angles are the camera's (deg; yaw clockwise from north), in DJI's convention (pitch
    -90 = straight down, so ``GimbalPitchDegree = pitch - 90`` for the camera's MAVLink-style
    ``pitch``); flight angles the airframe's: the same roll and pitch, yaw ``flight_yaw``
    (default: the camera's).
    ``CalibratedFocalLength`` and ``CalibratedOpticalCenterX/Y`` are in pixels (exact).
    """
    attrs = dji_attributes(rel_alt_m=rel_alt_m, amsl_m=amsl_m, lat=lat, lon=lon, roll=roll, pitch=pitch, yaw=yaw,
                           camera=camera, flight_yaw=flight_yaw, lrf_m=lrf_m)
    body = "\n".join(f'   drone-dji:{k}="{v}"' for k, v in attrs.items())
    text = ('<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n'
            '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
            ' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
            '  <rdf:Description rdf:about="DJI Meta Data"\n'
            '   xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"\n'
            f'{body}>\n'
            '  </rdf:Description>\n'
            ' </rdf:RDF>\n'
            '</x:xmpmeta>\n'
            '<?xpacket end="w"?>')
    return text.encode("utf-8")


def still_exif(*, t_unix: float, lat: float, lon: float, amsl_m: float, camera: Camera):
    """The EXIF of a simulated still (see :func:`write_still`), a Pillow ``Image.Exif``."""
    try:
        from PIL import Image
    except ImportError:
        raise PhotomapError("writing stills needs Pillow: pip install 'ifmi-photomap[sim]'") from None
    ms = int(round(t_unix * 1000.0))
    stamp = datetime.fromtimestamp(ms // 1000, tz=timezone.utc)
    when = stamp.strftime("%Y:%m:%d %H:%M:%S")
    exif = Image.Exif()
    exif[0x010F] = "photomap"                      # Make
    exif[0x0110] = "simulated pinhole"             # Model
    exif[0x0112] = 1                               # Orientation
    exif[0x0131] = "photomap simulate"             # Software
    exif[0x0132] = when                            # DateTime
    ex = exif.get_ifd(0x8769)
    ex[0x9003] = when                              # DateTimeOriginal
    ex[0x9291] = f"{ms % 1000:03d}"                # SubSecTimeOriginal
    ex[0x9011] = "+00:00"                          # OffsetTimeOriginal
    px_per_cm = camera.width / (SENSOR_WIDTH_MM / 10.0)
    ex[0x920A] = _rational(camera.fx * SENSOR_WIDTH_MM / camera.width)   # FocalLength, mm
    ex[0xA405] = int(round(focal_35mm(camera)))    # FocalLengthIn35mmFilm
    ex[0xA20E] = _rational(px_per_cm, 1000)        # FocalPlaneXResolution
    ex[0xA20F] = _rational(px_per_cm, 1000)        # FocalPlaneYResolution
    ex[0xA210] = 3                                 # FocalPlaneResolutionUnit: cm
    ex[0xA002] = int(camera.width)                 # PixelXDimension
    ex[0xA003] = int(camera.height)                # PixelYDimension
    gps = exif.get_ifd(0x8825)
    gps[0x00] = b"\x02\x03\x00\x00"                # GPSVersionID
    gps[0x01] = "N" if lat >= 0 else "S"
    gps[0x02] = _dms(lat)
    gps[0x03] = "E" if lon >= 0 else "W"
    gps[0x04] = _dms(lon)
    gps[0x05] = b"\x00" if amsl_m >= 0 else b"\x01"   # GPSAltitudeRef: above sea level
    gps[0x06] = _rational(abs(amsl_m), 1000)
    gps[0x07] = (_rational(stamp.hour, 1), _rational(stamp.minute, 1), _rational(stamp.second + (ms % 1000) / 1000.0, 1000))
    gps[0x12] = "WGS-84"                           # GPSMapDatum
    gps[0x1D] = stamp.strftime("%Y:%m:%d")         # GPSDateStamp
    return exif


def write_still(path: str | Path, bgr: np.ndarray, *, t_unix: float, lat: float, lon: float, amsl_m: float,
                rel_alt_m: float, camera: Camera, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0,
                flight_yaw: float | None = None, quality: int = 92, xmp: bool = True,
                lrf_m: float | None = None) -> None:
    """Write a uint8 BGR still as JPEG with EXIF and, if ``xmp``, DJI-style XMP (Pillow >= 11.1).

    EXIF: Make/Model, Orientation 1, DateTimeOriginal + SubSecTimeOriginal (milliseconds) +
    OffsetTimeOriginal ``+00:00`` (UTC, ``t_unix``); GPS (WGS84) latitude/longitude, altitude
    ``amsl_m`` above sea level, GPS date/time stamp; FocalLength (mm, for a
    :data:`SENSOR_WIDTH_MM` sensor), FocalPlaneX/YResolution (pixels per cm: ``fx`` =
    FocalLength * FocalPlaneXResolution / 10 exactly), FocalLengthIn35mmFilm (diagonal rule,
    rounded to whole mm as the tag is an integer).
    """
    exif = still_exif(t_unix=t_unix, lat=lat, lon=lon, amsl_m=amsl_m, camera=camera)
    kwargs = {"quality": int(quality), "exif": exif}
    if xmp:
        kwargs["xmp"] = dji_xmp(rel_alt_m=rel_alt_m, amsl_m=amsl_m, lat=lat, lon=lon, roll=roll, pitch=pitch,
                                yaw=yaw, camera=camera, flight_yaw=flight_yaw, lrf_m=lrf_m)
    from PIL import Image
    try:
        Image.fromarray(np.ascontiguousarray(bgr[..., ::-1])).save(str(path), "JPEG", **kwargs)
    except OSError as exc:
        raise PhotomapError(f"cannot write still {path}: {exc}") from None
