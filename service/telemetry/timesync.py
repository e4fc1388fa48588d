"""Time offset between the video and the telemetry, from the yaw rate seen by both.

Pure: arrays in, numbers out.

Convention: ``telemetry_time = video_time + offset``. The vision yaw rate is the rate of change
of the pose angle (``atan2(m10, m00)`` of the frame -> map matrix, degrees, y-down pixels): for a
down-looking camera whose image up is the heading it equals the rate of the MAVLink yaw
(clockwise positive) with the same sign. Both rates are resampled on one uniform grid,
smoothed alike (so no relative delay is introduced), and cross-correlated (Pearson) over the
lags in ``nominal +- window``; the best lag is refined to a fraction of a grid step by a
parabola through the correlation at the three lags around it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

log = logging.getLogger(__name__)


def _rates(t: np.ndarray, angle_deg: np.ndarray, max_dt: float, max_rate: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """Rates (deg/s) between consecutive valid samples, at their mid-times; pairs farther apart
    than ``max_dt`` or faster than ``max_rate`` (a jump: new map segment, glitch) are dropped."""
    ok = np.isfinite(t) & np.isfinite(angle_deg)
    t, a = t[ok], angle_deg[ok]
    if len(t) < 2:
        return np.empty(0), np.empty(0)
    dt = np.diff(t)
    da = (np.diff(a) + 180.0) % 360.0 - 180.0
    with np.errstate(divide="ignore", invalid="ignore"):
        rate = da / dt
    keep = (dt > 0) & (dt <= max_dt) & (np.abs(rate) <= max_rate)
    return ((t[1:] + t[:-1]) / 2.0)[keep], rate[keep]


def _resample(tr: np.ndarray, r: np.ndarray, grid: np.ndarray, max_dt: float) -> np.ndarray:
    """Linear interpolation of ``(tr, r)`` at ``grid``; NaN where the neighbours are more than
    ``max_dt`` apart or outside the samples."""
    out = np.full(len(grid), np.nan)
    if len(tr) < 2:
        return out
    k = np.searchsorted(tr, grid)
    inside = (k > 0) & (k < len(tr))
    k = np.clip(k, 1, len(tr) - 1)
    near = inside & (tr[k] - tr[k - 1] <= max_dt)
    out[near] = np.interp(grid[near], tr, r)
    return out


def _smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    """NaN-aware Gaussian smoothing (sigma in samples); NaN stays NaN."""
    if sigma <= 0:
        return x
    half = int(math.ceil(3 * sigma))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    m = np.isfinite(x)
    num = np.convolve(np.where(m, x, 0.0), k, mode="same")
    den = np.convolve(m.astype(float), k, mode="same")
    with np.errstate(invalid="ignore", divide="ignore"):
        y = num / den
    y[~m] = np.nan
    return y


def _pearson(a: np.ndarray, b: np.ndarray, min_n: int) -> float:
    m = np.isfinite(a) & np.isfinite(b)
    if m.sum() < min_n:
        return math.nan
    a, b = a[m] - a[m].mean(), b[m] - b[m].mean()
    d = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / d if d > 0 else math.nan


UNDECIDED = ("too_few_samples", "no_yaw_motion")
"""Reasons of :func:`sync_time_offset` that mean "cannot be told" (not evidence of a mismatch)."""


@dataclass(frozen=True)
class TimeSync:
    """Result of :func:`sync_time_offset`.

    offset_s, correlation : the estimate (None when refused). reason : None when accepted, else
    ``too_few_samples`` or ``no_yaw_motion`` (undecided: the data cannot tell) or
    ``no_overlap``, ``weak_correlation``, ``window_edge`` (refused: the yaw rates do not match
    within the window). best_correlation : the best correlation found (None when none was).
    """

    offset_s: float | None
    correlation: float | None
    reason: str | None = None
    best_correlation: float | None = None

    @property
    def refused(self) -> bool:
        """The yaw rates were compared and do not match (telemetry from elsewhere, or far off)."""
        return self.reason is not None and self.reason not in UNDECIDED


def estimate_time_offset(frame_t: Sequence[float], pose_angle_deg: Sequence[float],
                         tel_t: Sequence[float], tel_yaw: Sequence[float], **kwargs
                         ) -> tuple[float, float] | None:
    """Offset (s) with ``telemetry_time = video_time + offset`` and its correlation, or None
    when refused (see :func:`sync_time_offset`, which says why)."""
    found = sync_time_offset(frame_t, pose_angle_deg, tel_t, tel_yaw, **kwargs)
    return None if found.reason is not None else (found.offset_s, found.correlation)


def sync_time_offset(frame_t: Sequence[float], pose_angle_deg: Sequence[float],
                     tel_t: Sequence[float], tel_yaw: Sequence[float], *,
                     nominal_s: float = 0.0, window_s: float = 10.0, step_s: float = 0.02,
                     smooth_s: float = 0.1, min_correlation: float = 0.9,
                     min_rate_deg_s: float = 2.0, max_gap_s: float = 1.0,
                     max_rate_deg_s: float = 360.0) -> TimeSync:
    """Offset (s) with ``telemetry_time = video_time + offset``, and its correlation.

    Parameters
    ----------
    frame_t : video time of each frame, seconds. pose_angle_deg : pose angle of each frame
        (degrees; NaN = not posed). Put NaN at the first frame of a new map segment, or let the
        jump be dropped as faster than ``max_rate_deg_s``.
    tel_t, tel_yaw : telemetry times (s, its own clock) and MAVLink yaw (radians, wrapped or
        unwrapped; NaN = gap), e.g. ``TelemetryBuffer.series("yaw")``.
    nominal_s, window_s : the offset searched is ``nominal_s +- window_s``.
    step_s : grid step of the resampled rates. smooth_s : Gaussian sigma applied to both.
    min_correlation : below it the estimate is refused. min_rate_deg_s : refused when the
        vision yaw rate's standard deviation is below this (the yaw barely changes).
    max_gap_s : consecutive samples farther apart are a gap, not interpolated across.

    Returns a :class:`TimeSync`; refused (logged, with its reason) when there is too little
    data, the yaw barely changes, the correlation is weak, or the best lag is at the window's edge.
    """
    ft, fa = np.asarray(frame_t, float), np.asarray(pose_angle_deg, float)
    tt, ty = np.asarray(tel_t, float), np.degrees(np.asarray(tel_yaw, float))
    if len(ft) != len(fa) or len(tt) != len(ty):
        raise ValueError("frame_t/pose_angle_deg and tel_t/tel_yaw must have equal lengths")
    if step_s <= 0 or window_s <= 0:
        raise ValueError("step_s and window_s must be > 0")
    vt, vr = _rates(ft, fa, max_gap_s, max_rate_deg_s)
    wt, wr = _rates(tt, ty, max_gap_s, max_rate_deg_s)
    if len(vt) < 10 or len(wt) < 10:
        log.info("time sync: too few samples (vision %d, telemetry %d rates)", len(vt), len(wt))
        return TimeSync(None, None, "too_few_samples")
    grid = np.arange(vt[0], vt[-1], step_s)
    sigma = smooth_s / step_s
    v = _smooth(_resample(vt, vr, grid, max_gap_s), sigma)
    if not np.nanstd(v) >= min_rate_deg_s:
        log.info("time sync refused: the yaw barely changes (rate std %.2f deg/s < %.2f)",
                 float(np.nanstd(v)), min_rate_deg_s)
        return TimeSync(None, None, "no_yaw_motion")
    n_lag = int(round(window_s / step_s))
    tel_grid = grid[0] + nominal_s + np.arange(-n_lag, len(grid) + n_lag) * step_s
    w = _smooth(_resample(wt, wr, tel_grid, max_gap_s), sigma)
    min_n = max(10, int(np.isfinite(v).sum()) // 2)
    corr = np.array([_pearson(v, w[k:k + len(grid)], min_n) for k in range(2 * n_lag + 1)])
    if not np.isfinite(corr).any():
        log.info("time sync refused: telemetry and video do not overlap within +-%.1f s", window_s)
        return TimeSync(None, None, "no_overlap")
    k = int(np.nanargmax(corr))
    best = float(corr[k])
    if best < min_correlation:
        log.info("time sync refused: best correlation %.2f < %.2f", best, min_correlation)
        return TimeSync(None, None, "weak_correlation", best)
    if k == 0 or k == len(corr) - 1 or not np.isfinite(corr[k - 1:k + 2]).all():
        log.info("time sync refused: best lag at the edge of the +-%.1f s window", window_s)
        return TimeSync(None, None, "window_edge", best)
    c0, c1, c2 = corr[k - 1:k + 2]
    den = c0 - 2.0 * c1 + c2
    frac = 0.5 * (c0 - c2) / den if den < 0 else 0.0
    return TimeSync(float(nominal_s + (k - n_lag + frac) * step_s), best, None, best)
