"""Write a DJI Mini-style subtitle telemetry file (``.srt``) for a simulated video.

One cue per frame, as a Mini 3/4 or Air 3 records it: the subtitle runs from the frame's time to
the next frame's, and its text holds the frame counter, the UTC date, camera settings, the
position (``[latitude: ..] [longitude: ..]``, 6 decimals), the heights (``[rel_alt: ..
abs_alt: ..]``) and the gimbal (``[gb_yaw: .. gb_pitch: .. gb_roll: ..]``, DJI's convention: a
gimbal pitch of -90 deg looks straight down). :mod:`photomap.drivers.srt` reads it back.
"""

from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

import numpy as np


def _stamp(t: float) -> str:
    ms = int(round(t * 1000.0))
    h, rest = divmod(ms, 3_600_000)
    m, rest = divmod(rest, 60_000)
    s, ms = divmod(rest, 1000)
    return f"{h:02d}:{m:02d}:{s:02d},{ms:03d}"


def write_srt(path: str | Path, t: np.ndarray, lat_deg: np.ndarray, lon_deg: np.ndarray,
              rel_alt_m: np.ndarray, roll_deg: np.ndarray, pitch_deg: np.ndarray, yaw_deg: np.ndarray,
              *, t0_unix: float, home_amsl_m: float = 0.0, focal_35mm: float = 24.0) -> int:
    """Write one cue per sample time ``t`` (seconds of video, increasing); returns the cue count.

    ``lat_deg``, ``lon_deg``: the camera's nadir point (WGS84). ``rel_alt_m``: height above
    take-off (``abs_alt`` = ``home_amsl_m`` + it). ``roll_deg``, ``pitch_deg``, ``yaw_deg``: the
    camera attitude in MAVLink's convention (pitch 0 = nadir); written as the gimbal's
    (``gb_pitch`` = pitch - 90). ``t0_unix``: UTC time of ``t = 0`` (the date lines).
    """
    t = np.asarray(t, float)
    if t.ndim != 1 or t.size == 0 or np.any(np.diff(t) <= 0):
        raise ValueError("t must be a non-empty increasing 1-D array")
    step = float(np.median(np.diff(t))) if t.size > 1 else 1.0 / 30.0
    lines: list[str] = []
    for k in range(t.size):
        end = t[k + 1] if k + 1 < t.size else t[k] + step
        when = datetime.fromtimestamp(t0_unix + t[k], tz=timezone.utc)
        yaw = (float(yaw_deg[k]) + 180.0) % 360.0 - 180.0
        lines += [
            str(k + 1),
            f"{_stamp(t[k])} --> {_stamp(end)}",
            f'<font size="28">FrameCnt: {k + 1}, DiffTime: {round((end - t[k]) * 1000):d}ms',
            when.strftime("%Y-%m-%d %H:%M:%S.") + f"{when.microsecond // 1000:03d}",
            f"[iso: 100] [shutter: 1/1000.0] [fnum: 1.7] [ev: 0] [color_md: default] "
            f"[focal_len: {focal_35mm:.2f}] [latitude: {float(lat_deg[k]):.6f}] "
            f"[longitude: {float(lon_deg[k]):.6f}] [rel_alt: {float(rel_alt_m[k]):.3f} "
            f"abs_alt: {home_amsl_m + float(rel_alt_m[k]):.3f}] [ct: 5500] "
            f"[gb_yaw: {yaw:.1f} gb_pitch: {float(pitch_deg[k]) - 90.0:.1f} gb_roll: {float(roll_deg[k]):.1f}] </font>",
            "",
        ]
    Path(path).write_text("\n".join(lines), encoding="utf-8")
    return int(t.size)
