"""Joining MAVLink telemetry to frames: time base, priors, tilt rectification, georeference.

Telemetry is never required: every use falls back to vision alone when a sample (or one of its
fields) is unknown. Times: telemetry samples are on the UNIX clock (host time at receipt live,
recorded time from a ``.tlog``); :meth:`TelemetryJoin.telemetry_time` maps a frame time to that
clock:

- live camera: the frame's host monotonic time, converted to UNIX time;
- a log replay with a ``.tlog``: ``video_start + frame.t + offset``;
- a (real-time) replay with a live link: UNIX time of the first frame + ``frame.t + offset``;
- survey stills with their own telemetry (EXIF/XMP, geo.txt): the still's own time (``frame.t``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from photomap.config import Config
from photomap.drivers.frames import Frame
from photomap.geo.georef import (Georeference, fit_georeference, focal_px, map_heading_deg, metres_per_pixel,
                     nadir_homography, telemetry_prior)
from photomap.core.ifmi import Prior
from photomap.telemetry.samples import TelemetrySample
from photomap.telemetry.timesync import estimate_time_offset

log = logging.getLogger(__name__)

_MIN_TILT_RAD = math.radians(0.2)  # below this, frames are not rectified


@dataclass
class JoinStats:
    """What the join did (reported in run.json)."""

    frames_with_telemetry: int = 0
    frames_without_telemetry: int = 0
    priors_used: int = 0
    rectified: int = 0
    disagreements: int = 0


class TelemetryJoin:
    """Telemetry for each frame, and what the map makes of it.

    Parameters
    ----------
    sample_at : callable
        ``t -> TelemetrySample`` on the telemetry clock (a buffer's or reader's ``at``).
    mode : {"live", "log", "link", "stills"}
        How frame times map to the telemetry clock (see the module docstring).
    video_start : float
        UNIX time of video time 0 (``log`` mode).
    offset : float
        Added to every frame time, seconds (``--time-offset``).
    cfg : Config
        The configuration (sections ``telemetry``, ``camera``, ``georef``).
    link_summary : callable
        What the link saw (messages, gaps, link losses), for ``run.json``.
    """

    def __init__(self, sample_at: Callable[[float], TelemetrySample], mode: str, cfg: Config, *,
                 video_start: float = 0.0, offset: float = 0.0,
                 link_summary: Callable[[], dict] = dict) -> None:
        if mode not in ("live", "log", "link", "stills"):
            raise ValueError(f"unknown telemetry time mode {mode!r}")
        self.sample_at = sample_at
        self.mode = mode
        self.video_start = video_start
        self.offset = offset
        self.tcfg = cfg.telemetry
        self.ccfg = cfg.camera
        self.gcfg = cfg.georef
        self.stats = JoinStats()
        self._mono_to_unix = time.time() - time.monotonic()
        self._link_start: float | None = None
        self._fx: float | None = None
        self._samples: dict[int, TelemetrySample] = {}  # frame index -> sample (posed frames only)
        self.link_summary = link_summary

    def keep(self, index: int, sample: TelemetrySample) -> None:
        """Keep the sample of posed frame ``index`` for the georeference at the end."""
        self._samples[index] = sample

    def kept(self, index: int) -> TelemetrySample | None:
        """The sample kept for frame ``index``, if any."""
        return self._samples.get(index)

    def disagreement(self) -> int:
        """Count one frame where vision overruled telemetry; returns the count so far."""
        self.stats.disagreements += 1
        return self.stats.disagreements

    # ------------------------------------------------------------------ per frame
    def telemetry_time(self, t: float) -> float:
        """The telemetry-clock time of a frame at time ``t`` (``Frame.t``)."""
        if self.mode == "live":
            return t + self._mono_to_unix + self.offset
        if self.mode == "link":
            if self._link_start is None:
                self._link_start = time.time() - t
            return self._link_start + t + self.offset
        if self.mode == "stills":
            return t
        return self.video_start + t + self.offset

    def video_start_unix(self) -> float | None:
        """UNIX time of frame time 0 on the telemetry clock, without ``offset`` (None until known)."""
        if self.mode == "live":
            return self._mono_to_unix
        if self.mode == "link":
            return self._link_start
        if self.mode == "stills":
            return 0.0
        return self.video_start

    def sample(self, frame: Frame) -> TelemetrySample | None:
        s = self.sample_at(self.telemetry_time(frame.t))
        known = s is not None and (s.yaw is not None or s.height_above_ground is not None
                                   or s.lat is not None)
        if known:
            self.stats.frames_with_telemetry += 1
            return s
        self.stats.frames_without_telemetry += 1
        return None

    def focal(self, width: int) -> float | None:
        if self._fx is None:
            self._fx = focal_px(width, self.ccfg.fx_px, self.ccfg.hfov_deg)
        return self._fx

    def rectify(self, image: np.ndarray, s: TelemetrySample | None) -> np.ndarray:
        """Warp a tilted frame to the nadir view (needs roll, pitch and the camera model)."""
        if not self.tcfg.rectify_tilt or s is None or s.roll is None or s.pitch is None:
            return image
        if abs(s.roll) < _MIN_TILT_RAD and abs(s.pitch) < _MIN_TILT_RAD:
            return image
        h, w = image.shape[:2]
        fx = self.focal(w)
        if fx is None:
            return image
        hmg = nadir_homography(fx, (w - 1) / 2.0, (h - 1) / 2.0, s.roll, s.pitch)
        self.stats.rectified += 1
        return cv2.warpPerspective(image, hmg, (w, h), flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_REPLICATE)

    def prior(self, reference: TelemetrySample | None, current: TelemetrySample | None) -> Prior | None:
        """Expected registration of ``current`` against ``reference`` from yaw and height."""
        if not self.tcfg.use_priors or reference is None or current is None:
            return None
        angle, scale = telemetry_prior(reference, current)
        if angle is None and scale is None:
            return None
        self.stats.priors_used += 1
        return Prior(angle_deg=angle, angle_tol_deg=self.tcfg.prior_angle_tol_deg,
                     scale=scale, scale_tol=self.tcfg.prior_scale_tol)

    # ------------------------------------------------------------------ after the run
    def time_offset_check(self, frame_t: list[float], angles: list[float]) -> dict | None:
        """Estimate the video/telemetry offset from yaw rates; None when it cannot be told (or the
        telemetry is the stills' own: the same clock by construction)."""
        if not frame_t or self.mode == "stills":
            return None
        tel_t = [self.telemetry_time(t) for t in frame_t]
        ts, yaws = [], []
        for t in np.arange(tel_t[0] - self.gcfg.timesync_window_s,
                           tel_t[-1] + self.gcfg.timesync_window_s, 0.05):
            s = self.sample_at(float(t))
            if s is not None and s.yaw is not None:
                ts.append(float(t))
                yaws.append(s.yaw)
        if len(ts) < 10:
            return None
        found = estimate_time_offset(tel_t, angles, ts, yaws, nominal_s=0.0,
                                     window_s=self.gcfg.timesync_window_s,
                                     min_correlation=self.gcfg.timesync_min_correlation,
                                     min_rate_deg_s=self.gcfg.timesync_min_yaw_rate)
        if found is None:
            return None
        offset, corr = found
        return {"residual_offset_s": float(offset), "correlation": float(corr)}

    def georeference(self, width: int, height: int, poses: list[np.ndarray],
                     samples: list[TelemetrySample]) -> tuple[float | None, Georeference | None]:
        """Metres per map pixel and the georeference of one segment (None when unknown)."""
        fx = self.focal(width)
        heights = [s.height_above_ground for s in samples]
        mpp = metres_per_pixel(poses, heights, fx) if fx else None
        centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0, 1.0])
        xy = np.array([p @ centre for p in poses]) if poses else np.zeros((0, 2))
        heading = map_heading_deg(poses, [s.yaw for s in samples])
        geo = fit_georeference(xy, [s.lat for s in samples], [s.lon for s in samples],
                               metres_per_px=mpp, heading_deg=heading,
                               inlier_m=self.gcfg.gps_inlier_m,
                               min_extent_m=self.gcfg.min_extent_m,
                               min_fixes=self.gcfg.min_fixes)
        if mpp is None and geo is not None:
            mpp = geo.metres_per_px
        return mpp, geo
