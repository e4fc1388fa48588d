"""Trajectories in metres and UNIX time, for ``evo`` against GPS (``trajectory_utm.tum``, ``gps_utm.tum``).

``trajectory.tum`` is in map pixels from the first frame's time; a GPS track is in degrees and
UNIX time. These writers put both in the same frame: WGS 84 / UTM easting, northing (metres,
the run's zone), z = 0, UNIX seconds. Then::

    evo_ape tum gps_utm.tum trajectory_utm.tum --plot      # absolute, no alignment
    evo_ape tum gps_utm.tum trajectory_utm.tum -a          # after a rigid alignment

Orientation of a map frame: body axes x = image right, y = image down, z = into the ground
(right-handed); the rotation body -> (east, north, up) is written as the quaternion
``qx qy qz qw`` (Hamilton, scalar last, as TUM). GPS rows carry the identity orientation.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from photomap.errors import InputError
from photomap.core.records import PoseRow
from photomap.geometry import frame_centre
from photomap.geo.georef import utm_forward
from photomap.io.trajectory_files import atomic_write_text, largest_segment

VIDEO_START_HELP = ("the UNIX time of frame time 0 is unknown: record it in run.json as "
                    "video_start_unix (seconds; the telemetry join's video start, or the UNIX time of "
                    "the monotonic clock's zero for a live camera) or pass --video-start UNIX")


def quaternion_from_matrix(r: np.ndarray) -> tuple[float, float, float, float]:
    """``(qx, qy, qz, qw)`` of a 3x3 rotation matrix (Shepperd's method, ``qw >= 0``)."""
    r = np.asarray(r, float)
    t = np.trace(r)
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4.0)
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = (s / 4.0, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s)
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = ((r[0, 1] + r[1, 0]) / s, s / 4.0, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = ((r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4.0, (r[1, 0] - r[0, 1]) / s)
    q = np.array(q) / np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def body_to_enu(pose: np.ndarray, map_to_crs: np.ndarray) -> np.ndarray:
    """3x3 rotation of a frame's body axes (x image right, y image down, z down) into (east,
    north, up), through its pose (frame -> map pixels) and the georeference (map -> CRS)."""
    lin = np.asarray(map_to_crs, float)[:, :2] @ np.asarray(pose, float)[:2, :2]
    dx, dy = lin[:, 0], lin[:, 1]
    dx = dx / np.linalg.norm(dx)
    dy = dy - dx * float(dx @ dy)  # a similarity already has them orthogonal; guard rounding
    dy = dy / np.linalg.norm(dy)
    return np.array([[dx[0], dy[0], 0.0], [dx[1], dy[1], 0.0], [0.0, 0.0, -1.0]])


def format_tum_utm(rows: Sequence[PoseRow], frame_size: tuple[int, int], map_to_crs: np.ndarray,
                   epsg: int, t0_unix: float, segment: int | None = None) -> str:
    """The text of ``trajectory_utm.tum`` for one segment (default: the largest).

    One line ``t x y z qx qy qz qw`` per glued frame of the segment: ``t = t0_unix + row.t``,
    ``x, y`` the frame centre's easting, northing (metres), ``z = 0``; rows whose time does not
    increase are left out.
    """
    if t0_unix is None or not math.isfinite(t0_unix):
        raise InputError(VIDEO_START_HELP)
    seg = largest_segment(rows) if segment is None else segment
    centre = np.array([*frame_centre(*frame_size), 1.0])
    m = np.asarray(map_to_crs, float)
    lines = [f"# t x y z qx qy qz qw | photomap segment {seg}: EPSG:{epsg} easting, northing (m), "
             "z = 0, UNIX time (s); body x = image right, y = image down, z = down"]
    last = -math.inf
    for r in rows:
        if not r.glued or r.segment != seg or not r.t > last - t0_unix:
            continue
        last = t0_unix + r.t
        pose = np.asarray(r.M, float).reshape(-1, 3)[:2]
        e, n = m @ np.append(pose @ centre, 1.0)
        qx, qy, qz, qw = quaternion_from_matrix(body_to_enu(pose, m))
        lines.append(f"{t0_unix + r.t:.6f} {e:.4f} {n:.4f} 0.0 {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}")
    return "\n".join(lines) + "\n"


def write_tum_utm(path: str | Path, rows: Sequence[PoseRow], frame_size: tuple[int, int],
                  map_to_crs: np.ndarray, epsg: int, t0_unix: float, segment: int | None = None) -> None:
    """Write :func:`format_tum_utm` atomically."""
    atomic_write_text(path, format_tum_utm(rows, frame_size, map_to_crs, epsg, t0_unix, segment))


def format_gps_tum(t_unix: np.ndarray, lat: np.ndarray, lon: np.ndarray, epsg: int,
                   t_range: tuple[float, float] | None = None) -> str:
    """GPS fixes as TUM in the same frame (UTM ``epsg``, z = 0, identity orientation).

    ``t_range``: keep only fixes within ``(t_min, t_max)`` (UNIX seconds), e.g. the flight's
    mapped span. Non-finite fixes and non-increasing times are left out.
    """
    t, la, lo = (np.asarray(v, float) for v in (t_unix, lat, lon))
    ok = np.isfinite(t) & np.isfinite(la) & np.isfinite(lo)
    if t_range is not None:
        ok &= (t >= t_range[0]) & (t <= t_range[1])
    t, la, lo = t[ok], la[ok], lo[ok]
    e, n = utm_forward(la, lo, epsg) if len(t) else (np.zeros(0), np.zeros(0))
    lines = [f"# t x y z qx qy qz qw | GPS: EPSG:{epsg} easting, northing (m), z = 0, UNIX time (s)"]
    last = -math.inf
    for ti, ei, ni in zip(t, e, n):
        if ti > last:
            lines.append(f"{ti:.6f} {ei:.4f} {ni:.4f} 0.0 0.0 0.0 0.0 1.0")
            last = ti
    return "\n".join(lines) + "\n"
