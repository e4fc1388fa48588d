"""Write a synthetic MAVLink 2 telemetry log (``.tlog``) for a simulated flight.

A ``.tlog`` is a sequence of records: 8-byte big-endian microseconds since the Unix epoch, then
one raw MAVLink frame. Frames are produced with ``mav.send()`` so that the sequence number
advances (``msg.pack()`` alone leaves it at 0 and readers count losses).

Messages and rates: HEARTBEAT 1 Hz, SYSTEM_TIME 1 Hz, ATTITUDE 50 Hz, GLOBAL_POSITION_INT 10 Hz,
VFR_HUD 10 Hz, ALTITUDE 10 Hz, DISTANCE_SENSOR 20 Hz (downward rangefinder). The vehicle state
is given at sample times (e.g. the video frames) and linearly interpolated to each message time
(yaw unwrapped); before the first and after the last sample it is held.
"""

from __future__ import annotations

import math
import os
import struct
from collections import Counter
from pathlib import Path

import numpy as np

os.environ["MAVLINK20"] = "1"     # before any pymavlink import: MAVLink 2 frames (0xFD)
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

RATES_HZ = {
    "HEARTBEAT": 1,
    "SYSTEM_TIME": 1,
    "ATTITUDE": 50,
    "GLOBAL_POSITION_INT": 10,
    "VFR_HUD": 10,
    "ALTITUDE": 10,
    "DISTANCE_SENSOR": 20,
}
_EARTH_R = 6371008.8
RANGEFINDER_MIN_CM = 20
RANGEFINDER_MAX_CM = 13000


class _TimestampedFile:
    """File-like sink for ``MAVLink.send``: prefixes each frame with the current timestamp."""

    def __init__(self, f) -> None:
        self.f = f
        self.t_us = 0

    def write(self, buf: bytes) -> None:
        self.f.write(struct.pack(">Q", self.t_us) + bytes(buf))


def write_tlog(path: str | Path, t: np.ndarray, lat_deg: np.ndarray, lon_deg: np.ndarray,
               rel_alt_m: np.ndarray, roll_deg: np.ndarray, pitch_deg: np.ndarray, yaw_deg: np.ndarray,
               *, t0_unix: float, boot_offset_s: float = 60.0, home_amsl_m: float = 0.0,
               pad_s: float = 1.0, sysid: int = 1, compid: int = 1, fixed_wing: bool = False) -> dict[str, int]:
    """Write a ``.tlog`` for a vehicle state sampled at times ``t``.

    Parameters
    ----------
    t : seconds, increasing (e.g. frame times, 0 = first frame).
    lat_deg, lon_deg : WGS84 position. rel_alt_m : height above home (= above the flat ground).
    roll_deg, pitch_deg, yaw_deg : MAVLink attitude (yaw clockwise from north).
    t0_unix : Unix time of ``t = 0`` (tlog record timestamps, SYSTEM_TIME.time_unix_usec).
    boot_offset_s : autopilot uptime at ``t = 0`` (``time_boot_ms = (t + boot_offset_s) * 1000``).
    home_amsl_m : ground altitude above mean sea level (AMSL altitudes = home + relative).
    pad_s : telemetry starts ``pad_s`` before the first sample and ends ``pad_s`` after the last.
    fixed_wing : HEARTBEAT says MAV_TYPE_FIXED_WING in AUTO (ArduPlane custom mode 10) instead of
        MAV_TYPE_QUADROTOR in GUIDED (ArduCopter custom mode 4).

    Returns
    -------
    Number of messages written per type.
    """
    t = np.asarray(t, float)
    if t.ndim != 1 or t.size == 0 or np.any(np.diff(t) <= 0):
        raise ValueError("t must be a non-empty increasing 1-D array")
    if boot_offset_s < pad_s:
        raise ValueError("boot_offset_s must be at least pad_s (time_boot_ms cannot be negative)")
    lat, lon, alt = (np.asarray(a, float) for a in (lat_deg, lon_deg, rel_alt_m))
    roll, pitch = np.radians(roll_deg), np.radians(pitch_deg)
    yaw = np.unwrap(np.radians(yaw_deg))
    # velocities (NED, m/s) and body rates (rad/s) at the samples
    if t.size > 1:
        vn = np.gradient(np.radians(lat), t) * _EARTH_R
        ve = np.gradient(np.radians(lon), t) * _EARTH_R * np.cos(np.radians(lat))
        vd = -np.gradient(alt, t)
        rates = [np.gradient(a, t) for a in (roll, pitch, yaw)]
    else:
        vn = ve = vd = np.zeros(1)
        rates = [np.zeros(1)] * 3

    def at(values: np.ndarray, ts: float) -> float:
        return float(np.interp(ts, t, values))

    start_us = int(round((t[0] - pad_s) * 1e6))
    end_us = int(round((t[-1] + pad_s) * 1e6))
    events = []
    for order, (name, hz) in enumerate(RATES_HZ.items()):
        period = 1_000_000 // hz
        first = -(-start_us // period) * period          # on the rate's grid of t = 0
        events += [(us, order, name) for us in range(first, end_us + 1, period)]
    events.sort()

    counts: Counter[str] = Counter()
    with open(path, "wb") as f:
        sink = _TimestampedFile(f)
        mav = mavlink2.MAVLink(sink, srcSystem=sysid, srcComponent=compid)
        for us, _, name in events:
            ts = us / 1e6
            sink.t_us = int(round(t0_unix * 1e6)) + us
            boot_ms = int(round((ts + boot_offset_s) * 1000))
            r, p, y = at(roll, ts), at(pitch, ts), at(yaw, ts)
            y = (y + math.pi) % (2 * math.pi) - math.pi
            h = at(alt, ts)
            heading_deg = math.degrees(y) % 360.0
            if name == "HEARTBEAT":
                msg = mav.heartbeat_encode(
                    mavlink2.MAV_TYPE_FIXED_WING if fixed_wing else mavlink2.MAV_TYPE_QUADROTOR,
                    mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                    mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink2.MAV_MODE_FLAG_SAFETY_ARMED,
                    10 if fixed_wing else 4, mavlink2.MAV_STATE_ACTIVE)  # AUTO (Plane) / GUIDED (Copter)
            elif name == "SYSTEM_TIME":
                msg = mav.system_time_encode(sink.t_us, boot_ms)
            elif name == "ATTITUDE":
                msg = mav.attitude_encode(boot_ms, r, p, y, *(at(a, ts) for a in rates))
            elif name == "GLOBAL_POSITION_INT":
                msg = mav.global_position_int_encode(
                    boot_ms, int(round(at(lat, ts) * 1e7)), int(round(at(lon, ts) * 1e7)),
                    int(round((home_amsl_m + h) * 1000)), int(round(h * 1000)),
                    int(round(at(vn, ts) * 100)), int(round(at(ve, ts) * 100)), int(round(at(vd, ts) * 100)),
                    int(round(heading_deg * 100)) % 36000)
            elif name == "VFR_HUD":
                ground = math.hypot(at(vn, ts), at(ve, ts))
                msg = mav.vfr_hud_encode(ground, ground, int(round(heading_deg)) % 360, 50,
                                         home_amsl_m + h, -at(vd, ts))
            elif name == "ALTITUDE":
                msg = mav.altitude_encode(int(round((ts + boot_offset_s) * 1e6)), home_amsl_m + h,
                                          home_amsl_m + h, h, h, h, h)
            else:  # DISTANCE_SENSOR: slant range along the body's down axis to the flat ground
                rng_cm = h * 100.0 / max(math.cos(r) * math.cos(p), 1e-3)
                cur = int(round(min(max(rng_cm, RANGEFINDER_MIN_CM), RANGEFINDER_MAX_CM)))
                msg = mav.distance_sensor_encode(boot_ms, RANGEFINDER_MIN_CM, RANGEFINDER_MAX_CM, cur,
                                                 mavlink2.MAV_DISTANCE_SENSOR_LASER, 0,
                                                 mavlink2.MAV_SENSOR_ROTATION_PITCH_270, 0)
            mav.send(msg)
            counts[name] += 1
    return dict(counts)
