"""Time-indexed MAVLink telemetry: decoding with validation, and interpolation to any time.

Pure: no I/O, no threads, no logging. The driver (``drivers/mavlink.py``) feeds decoded
messages in, counts and logs what was rejected, and holds the lock when threads share a buffer.

Time base
---------
Every sample is stamped with the **host's clock in UNIX seconds** at which the message was
received: live, that is the host clock at receipt (made monotonic by the driver); from a
``.tlog``, the recorded receipt time (``_timestamp``, the recording host's clock). The
autopilot's own boot clock is *not* used to stamp samples; ``SYSTEM_TIME`` only provides
``boot_to_unix`` (autopilot boot clock -> autopilot UNIX clock, in seconds).

Units and frames (SI, radians; MAVLink's NED body conventions)
--------------------------------------------------------------
``roll``, ``pitch``, ``yaw`` [rad] (yaw from north, clockwise seen from above, wrapped to
(-pi, pi]); rates [rad/s]; ``lat``, ``lon`` [deg, WGS84]; ``alt`` [m AMSL];
``relative_alt`` [m above home]; ``heading`` [rad, course over ground as the autopilot reports
it, wrapped like yaw]; ``vn``, ``ve``, ``vd`` [m/s, NED]; ``x``, ``y``, ``z`` [m, local NED];
``rangefinder`` [m along a downward sensor's axis]; ``height_above_ground`` [m].
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping

import numpy as np

#: Fields interpolated on the circle (unwrapped when stored, wrapped to (-pi, pi] when read).
ANGLE_FIELDS = frozenset({"roll", "yaw", "heading"})

#: Every field a :class:`TelemetrySample` carries (besides ``t`` and the derived height).
SAMPLE_FIELDS = (
    "roll", "pitch", "yaw", "rollspeed", "pitchspeed", "yawspeed",
    "lat", "lon", "alt", "relative_alt", "heading", "vn", "ve", "vd",
    "airspeed", "groundspeed", "climb",
    "altitude_amsl", "altitude_relative", "altitude_terrain", "bottom_clearance",
    "rangefinder", "x", "y", "z",
)

#: Message types the buffer understands.
MESSAGE_TYPES = (
    "ATTITUDE", "GLOBAL_POSITION_INT", "VFR_HUD", "ALTITUDE",
    "DISTANCE_SENSOR", "LOCAL_POSITION_NED", "SYSTEM_TIME",
)

# Plausibility limits: a value outside them is "absurd" and rejected.
_ANGLE_TOL = 1e-3                 # rad of slack on +-pi (float32 pi > math.pi)
_MAX_RATE = 35.0                  # rad/s (2000 deg/s, a gyro's full range)
_ALT_RANGE = (-500.0, 12000.0)    # m AMSL
_REL_ALT_RANGE = (-2000.0, 12000.0)  # m above home / above terrain
_MAX_SPEED = 150.0                # m/s
_MAX_LOCAL = 1.0e5                # m from the local origin
_MAX_RANGE = 1000.0               # m, longest rangefinder reading accepted
_SENSOR_DOWN = 25                 # MAV_SENSOR_ROTATION_PITCH_270
_UINT16_UNKNOWN = 65535


@dataclass(frozen=True, slots=True)
class TelemetrySample:
    """Telemetry interpolated to time ``t`` (host UNIX seconds). ``None`` means unknown.

    ``height_above_ground`` is the best height estimate: the downward rangefinder
    (tilt-corrected by ``cos(roll) cos(pitch)`` when the attitude is known), else ALTITUDE's
    ``bottom_clearance``, else ``altitude_terrain``, else the height above home
    (``relative_alt`` or ``altitude_relative``: flat-ground assumption). ``height_source``
    names which one: ``"rangefinder"``, ``"bottom_clearance"``, ``"terrain"``, ``"home"``.
    """

    t: float
    roll: float | None = None
    pitch: float | None = None
    yaw: float | None = None
    rollspeed: float | None = None
    pitchspeed: float | None = None
    yawspeed: float | None = None
    lat: float | None = None
    lon: float | None = None
    alt: float | None = None
    relative_alt: float | None = None
    heading: float | None = None
    vn: float | None = None
    ve: float | None = None
    vd: float | None = None
    airspeed: float | None = None
    groundspeed: float | None = None
    climb: float | None = None
    altitude_amsl: float | None = None
    altitude_relative: float | None = None
    altitude_terrain: float | None = None
    bottom_clearance: float | None = None
    rangefinder: float | None = None
    x: float | None = None
    y: float | None = None
    z: float | None = None
    height_above_ground: float | None = None
    height_source: str | None = None


@dataclass
class Decoded:
    """What one message contributed.

    ``values``: field -> accepted SI value. ``rejected``: fields dropped as bad data, and
    ``problems``: why, as ``{what: reason}`` naming only the root causes (``{"yaw": "out of
    range"}`` rejects all of ATTITUDE; ``{"lat/lon": "no GPS fix (0/0)"}``). ``unknown``:
    fields the sender itself flagged as unknown (a documented sentinel such as
    ``hdg = UINT16_MAX``, a NaN in ALTITUDE, a rangefinder reading outside its own min/max).
    Rejected and unknown fields both mark a gap in their series.
    """

    values: dict[str, float] = field(default_factory=dict)
    rejected: list[str] = field(default_factory=list)
    problems: dict[str, str] = field(default_factory=dict)
    unknown: list[str] = field(default_factory=list)


def wrap_angle(a: float) -> float:
    """Wrap an angle in radians to (-pi, pi]."""
    w = math.remainder(a, 2.0 * math.pi)
    return math.pi if w == -math.pi else w


def _check(out: Decoded, name: str, value: Any, lo: float, hi: float) -> None:
    """Accept ``value`` as field ``name`` if finite and within [lo, hi], else reject it."""
    v = float(value)
    if math.isfinite(v) and lo <= v <= hi:
        out.values[name] = v
    else:
        out.rejected.append(name)
        out.problems[name] = "out of range" if math.isfinite(v) else "not finite"


def _group(out: Decoded, names: tuple[str, ...]) -> None:
    """All-or-nothing: if one of ``names`` was rejected, reject the others too."""
    if any(n in out.rejected for n in names):
        for n in names:
            if out.values.pop(n, None) is not None:
                out.rejected.append(n)


def _optional(out: Decoded, name: str, value: Any, lo: float, hi: float,
              unknown_below: float = -math.inf) -> None:
    """Like :func:`_check`, but NaN (or a value below ``unknown_below``) means unknown."""
    v = float(value)
    if math.isnan(v) or v < unknown_below:
        out.unknown.append(name)
    else:
        _check(out, name, v, lo, hi)


def decode_message(msg_type: str, fields: Mapping[str, Any]) -> Decoded:
    """Convert one MAVLink message's fields (as ``msg.to_dict()``) to validated SI values.

    A message type this module does not use gives an empty :class:`Decoded`.
    """
    out = Decoded()
    f = fields
    if msg_type == "ATTITUDE":
        _check(out, "roll", f["roll"], -math.pi - _ANGLE_TOL, math.pi + _ANGLE_TOL)
        _check(out, "pitch", f["pitch"], -math.pi / 2 - _ANGLE_TOL, math.pi / 2 + _ANGLE_TOL)
        _check(out, "yaw", f["yaw"], -math.pi - _ANGLE_TOL, math.pi + _ANGLE_TOL)
        for name in ("rollspeed", "pitchspeed", "yawspeed"):
            _check(out, name, f[name], -_MAX_RATE, _MAX_RATE)
        _group(out, ("roll", "pitch", "yaw", "rollspeed", "pitchspeed", "yawspeed"))
    elif msg_type == "GLOBAL_POSITION_INT":
        if f["lat"] == 0 and f["lon"] == 0:
            out.rejected += ["lat", "lon"]
            out.problems["lat/lon"] = "no GPS fix (0/0)"
        else:
            _check(out, "lat", f["lat"] * 1e-7, -90.0, 90.0)
            _check(out, "lon", f["lon"] * 1e-7, -180.0, 180.0)
            _group(out, ("lat", "lon"))
        _check(out, "alt", f["alt"] * 1e-3, *_ALT_RANGE)
        _check(out, "relative_alt", f["relative_alt"] * 1e-3, *_REL_ALT_RANGE)
        for name, key in (("vn", "vx"), ("ve", "vy"), ("vd", "vz")):
            _check(out, name, f[key] * 1e-2, -_MAX_SPEED, _MAX_SPEED)
        if f["hdg"] == _UINT16_UNKNOWN:
            out.unknown.append("heading")
        else:
            _check(out, "heading", math.radians(f["hdg"] * 1e-2), 0.0, 2.0 * math.pi)
            if "heading" in out.values:
                out.values["heading"] = wrap_angle(out.values["heading"])
    elif msg_type == "VFR_HUD":
        _check(out, "airspeed", f["airspeed"], 0.0, _MAX_SPEED)
        _check(out, "groundspeed", f["groundspeed"], 0.0, _MAX_SPEED)
        _check(out, "climb", f["climb"], -_MAX_SPEED, _MAX_SPEED)
    elif msg_type == "ALTITUDE":
        # MAVLink: NaN = unknown; altitude_terrain < -1000 = unknown.
        _optional(out, "altitude_amsl", f["altitude_amsl"], *_ALT_RANGE)
        _optional(out, "altitude_relative", f["altitude_relative"], *_REL_ALT_RANGE)
        _optional(out, "altitude_terrain", f["altitude_terrain"], *_REL_ALT_RANGE, unknown_below=-1000.0)
        _optional(out, "bottom_clearance", f["bottom_clearance"], 0.0, _REL_ALT_RANGE[1])
    elif msg_type == "DISTANCE_SENSOR":
        if f["orientation"] != _SENSOR_DOWN:
            return out  # not looking down: not a height
        cur, lo, hi = f["current_distance"], f["min_distance"], f["max_distance"]
        quality = f.get("signal_quality", 0)
        if cur == _UINT16_UNKNOWN or cur <= 0 or cur < lo or (hi > 0 and cur > hi) or quality == 1:
            out.unknown.append("rangefinder")  # outside the sensor's own range: no reading
        else:
            _check(out, "rangefinder", cur * 1e-2, 0.0, _MAX_RANGE)
    elif msg_type == "LOCAL_POSITION_NED":
        for name in ("x", "y", "z"):
            _check(out, name, f[name], -_MAX_LOCAL, _MAX_LOCAL)
    elif msg_type == "SYSTEM_TIME":
        # A GCS sends SYSTEM_TIME with time_boot_ms = 0; time_unix_usec = 0 means no UNIX time yet.
        if f["time_unix_usec"] <= 0 or f["time_boot_ms"] <= 0:
            out.unknown.append("boot_to_unix")
        else:
            out.values["boot_to_unix"] = f["time_unix_usec"] * 1e-6 - f["time_boot_ms"] * 1e-3
    return out


class _Series:
    """One field: ascending times and values; NaN marks a gap (a rejected/unknown sample)."""

    __slots__ = ("t", "v", "angle", "last_valid")

    def __init__(self, angle: bool) -> None:
        self.t: list[float] = []
        self.v: list[float] = []
        self.angle = angle
        self.last_valid: float | None = None

    def append(self, t: float, v: float) -> bool:
        if self.t and t < self.t[-1]:
            return False
        if self.angle and not math.isnan(v) and self.last_valid is not None:
            v = self.last_valid + wrap_angle(v - self.last_valid)  # unwrap
        if not math.isnan(v):
            self.last_valid = v
        self.t.append(t)
        self.v.append(v)
        return True

    def prune(self, t_min: float) -> None:
        k = bisect_left(self.t, t_min)
        if k:
            del self.t[:k]
            del self.v[:k]

    def at(self, t: float, max_gap: float, max_hold: float) -> float | None:
        ts, vs = self.t, self.v
        i = bisect_right(ts, t)
        left = i - 1 if i > 0 else None
        right = i if i < len(ts) else None
        lv = vs[left] if left is not None and not math.isnan(vs[left]) else None
        rv = vs[right] if right is not None and not math.isnan(vs[right]) else None
        if lv is not None and rv is not None and ts[right] - ts[left] <= max_gap:
            span = ts[right] - ts[left]
            w = (t - ts[left]) / span if span > 0 else 0.0
            value = lv + w * (rv - lv)
        else:  # at an end of the series or beside a gap: hold the nearest sample briefly
            candidates = []
            if lv is not None and t - ts[left] <= max_hold:
                candidates.append((t - ts[left], lv))
            if rv is not None and ts[right] - t <= max_hold:
                candidates.append((ts[right] - t, rv))
            if not candidates:
                return None
            value = min(candidates)[1]
        return wrap_angle(value) if self.angle else value


class TelemetryBuffer:
    """Telemetry samples per field on the host UNIX clock, interpolated by :meth:`at`.

    Not thread-safe: one thread owns it, or every caller holds the same lock.

    Parameters
    ----------
    max_gap : float
        Seconds. Two neighbouring samples farther apart than this are not interpolated
        across: between them a field is unknown (``None``) unless within ``max_hold``.
    max_hold : float
        Seconds. Beside a gap and beyond either end of a series, the nearest sample is
        returned while it is at most this old (or new); later the field is ``None``.
    horizon : float or None
        Seconds of history kept behind the newest sample (bounded memory); ``None`` keeps
        everything (a whole log).
    """

    def __init__(self, max_gap: float = 2.0, max_hold: float = 0.5,
                 horizon: float | None = 60.0) -> None:
        if max_gap <= 0 or max_hold < 0 or (horizon is not None and horizon <= 0):
            raise ValueError("max_gap and horizon must be > 0, max_hold >= 0")
        self.max_gap = float(max_gap)
        self.max_hold = float(max_hold)
        self.horizon = None if horizon is None else float(horizon)
        self._series: dict[str, _Series] = {}
        self._newest = -math.inf

    def _get(self, name: str) -> _Series:
        s = self._series.get(name)
        if s is None:
            s = self._series[name] = _Series(name in ANGLE_FIELDS)
        return s

    def add(self, t: float, values: Mapping[str, float], gaps: Iterable[str] = ()) -> bool:
        """Store ``values`` (field -> SI value) at time ``t`` and mark ``gaps`` (field names).

        Returns False (storing nothing) when ``t`` is older than a field's last sample.
        """
        t = float(t)
        items = [(n, float(v)) for n, v in values.items()] + [(n, math.nan) for n in gaps]
        if any(self._series[n].t and t < self._series[n].t[-1]
               for n, _ in items if n in self._series):
            return False
        for name, v in items:
            self._get(name).append(t, v)
        if t > self._newest:
            self._newest = t
            if self.horizon is not None:
                for s in self._series.values():
                    s.prune(t - self.horizon)
        return True

    def add_message(self, t: float, msg_type: str, fields: Mapping[str, Any]) -> tuple[Decoded, bool]:
        """Decode one message (:func:`decode_message`) and store it at ``t``.

        Returns the decoding and whether it was stored (False: ``t`` went backwards).
        """
        dec = decode_message(msg_type, fields)
        stored = self.add(t, dec.values, dec.rejected + dec.unknown)
        return dec, stored

    def mark_gap(self, t: float) -> None:
        """Mark every field unknown from ``t`` on (e.g. the link was lost at ``t``)."""
        for s in self._series.values():
            if not s.t or t >= s.t[-1]:
                s.append(float(t), math.nan)

    def value_at(self, name: str, t: float) -> float | None:
        """One field at time ``t`` (see the class doc), ``None`` if unknown."""
        s = self._series.get(name)
        return None if s is None else s.at(float(t), self.max_gap, self.max_hold)

    def at(self, t: float) -> TelemetrySample:
        """All fields interpolated to time ``t`` (host UNIX seconds)."""
        v = {name: self.value_at(name, t) for name in SAMPLE_FIELDS}
        hag, source = v["rangefinder"], "rangefinder"
        if hag is not None:
            if v["roll"] is not None and v["pitch"] is not None:
                hag *= math.cos(v["roll"]) * math.cos(v["pitch"])
        else:
            for name, source in (("bottom_clearance", "bottom_clearance"),
                                 ("altitude_terrain", "terrain"),
                                 ("relative_alt", "home"), ("altitude_relative", "home")):
                hag = v[name]
                if hag is not None:
                    break
        return TelemetrySample(t=float(t), height_above_ground=hag,
                               height_source=None if hag is None else source, **v)

    def latest(self, name: str) -> tuple[float, float] | None:
        """Newest valid ``(t, value)`` of a field (e.g. ``"boot_to_unix"``), or None."""
        s = self._series.get(name)
        if s is None:
            return None
        for t, v in zip(reversed(s.t), reversed(s.v)):
            if not math.isnan(v):
                return t, (wrap_angle(v) if s.angle else v)
        return None

    def series(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Times and values of one field as float arrays (angles unwrapped, NaN = gap)."""
        s = self._series.get(name)
        if s is None:
            return np.empty(0), np.empty(0)
        return np.asarray(s.t, dtype=float), np.asarray(s.v, dtype=float)

    def count(self, name: str) -> int:
        """Number of valid samples of a field currently held."""
        s = self._series.get(name)
        return 0 if s is None else sum(1 for v in s.v if not math.isnan(v))

    @property
    def fields(self) -> list[str]:
        """Names of the fields that have been seen."""
        return sorted(self._series)

    @property
    def span(self) -> tuple[float, float] | None:
        """``(oldest, newest)`` sample time held, or None when empty."""
        ts = [s.t for s in self._series.values() if s.t]
        if not ts:
            return None
        return min(t[0] for t in ts), max(t[-1] for t in ts)
