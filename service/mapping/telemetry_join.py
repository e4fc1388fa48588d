"""Joining MAVLink telemetry to frames: time base, priors, tilt rectification, georeference.

Telemetry is never required: every use falls back to vision alone when a sample (or one of its
fields) is unknown. Times: telemetry samples are on the UNIX clock (host time at receipt live,
recorded time from a ``.tlog``); :meth:`TelemetryJoin.telemetry_time` maps a frame time to that
clock:

- live camera: the frame's host monotonic time, converted to UNIX time;
- a log replay with a ``.tlog``: ``video_start + frame.t + offset``;
- a (real-time) replay with a live link: UNIX time of the first frame + ``frame.t + offset``;
- survey stills with their own telemetry (EXIF/XMP, geo.txt): the still's own time (``frame.t``).

Tilt: a frame with roll/pitch is warped to its *recentred* nadir view
(:func:`~photomap.geo.georef.rectifying_homography`): the tracker, the map and the keyframe
store see that view, and the pose of such a frame (trajectory.csv ``M``) maps the pixels of that
view. Its centre pixel is the input frame's centre pixel, so the row's ``x, y`` (and ``lat, lon``)
are those of the input frame's centre; the input frame's own pixels map by
``M @ rectifying_homography(rect_fx_px, w, h, rect_roll_deg, rect_pitch_deg)`` (the row's
``rect_*`` columns; ``photomap evaluate`` composes it). Pixels of the view that the input frame
does not cover are outside its validity mask and never reach the map.

Trust: telemetry that does not fit the images is refused at the end of the run
(:meth:`TelemetryJoin.verdict`): no sample joined, the yaw rates do not correlate in time, vision
overruled most priors, or the GPS track does not fit the vision track (after the similarity fit:
too few fixes within ``georef.gps_inlier_m``, a short track off the camera's scale, or halves of
the track that need different scales or rotations). Then the map is not georeferenced from it
and ``run.json`` ``telemetry.status`` names the reason. The camera-height scale (the relative
altitude is over the take-off point, not the ground; the focal length may be wrong) and the
compass or gimbal yaw (a constant offset on some models) are priors: one that contradicts a GPS
fit that holds is dropped (the scale and heading are the GPS track's), listed in
``telemetry.problems`` and said once, and the map is still georeferenced from the GPS. After
``max_disagreements_in_a_row`` overruled priors the join stops handing out telemetry for the rest
of the run (vision alone).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import cv2
import numpy as np

from photomap.config import Config
from photomap.drivers.frames import Frame
from photomap.geo.georef import (Georeference, fit_georeference, focal_px, map_heading_deg, metres_per_pixel,
                                 nadir_pixel, rectifying_homography, telemetry_prior)
from photomap.geometry import frame_centre, pose_angle_deg, wrap_deg
from photomap.core.ifmi import Prior
from photomap.telemetry.samples import TelemetrySample
from photomap.telemetry.timesync import sync_time_offset
from photomap.mapping.frameprep import fill_invalid

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
    # telemetry was switched off at this frame (too many disagreements in a row), and the
    # frames after it that were mapped by vision alone
    stopped_at_frame: int | None = None
    frames_ignored: int = 0


@dataclass(frozen=True)
class Rectified:
    """A frame as the map sees it.

    image : the input frame, or its recentred nadir view; pixels the input does not cover are
        filled with the mean of the covered ones (neutral for registration: zero after the
        mean is removed). mask : uint8, 255 where the view is covered by the input frame (None:
        all of it). homography : 3x3 input pixels -> view pixels (None: not rectified).
    """

    image: np.ndarray
    mask: np.ndarray | None = None
    homography: np.ndarray | None = None


@dataclass
class SegmentFit:
    """The metric scale and georeference of one map segment, and what speaks against them.

    metres_per_px : from the camera model and the heights (None when unknown), else (or when
    the camera's scale is dropped) the GPS fit's. camera_mpp : the camera's alone.
    compass_heading_deg : the map's up direction from the yaw (:func:`map_heading_deg`).
    geo : the GPS fit (None when not possible). problem : why the GPS fit contradicts the
    vision track (None: it does not). dropped : the priors that contradict the GPS fit,
    ``(code, text)``: ``camera_scale`` (height and focal length), ``compass`` (yaw).
    """

    metres_per_px: float | None
    geo: Georeference | None
    camera_mpp: float | None = None
    compass_heading_deg: float | None = None
    problem: str | None = None
    dropped: list[tuple[str, str]] = field(default_factory=list)


def _consistent_compass(poses: list[np.ndarray], samples: list[TelemetrySample], min_resultant: float = 0.9) -> bool:
    """Whether yaw minus pose angle is about constant over the frames (the compass can judge the
    GPS fit's rotation): the mean resultant length of those angles is at least ``min_resultant``
    (logged yaw flips by 180 deg, as at a DJI's strip ends, make it small)."""
    d = [s.yaw - math.radians(pose_angle_deg(p)) for p, s in zip(poses, samples)
         if s.yaw is not None and math.isfinite(s.yaw)]
    return bool(d) and float(np.hypot(np.cos(d).mean(), np.sin(d).mean())) >= min_resultant


def _halves_disagree(xy: np.ndarray, samples: list[TelemetrySample], inlier_m: float, min_extent_m: float,
                     min_fixes: int, max_scale_ratio: float, max_heading_error: float) -> str | None:
    """Why the two halves of a GPS track (by frame order) fit the vision track differently, or
    None: each half long enough (``min_extent_m``) and with ``min_fixes`` fixes is fitted on its
    own; scales more than ``max_scale_ratio`` or rotations more than ``max_heading_error`` deg
    apart mean the GPS does not follow the images along the track (a wrong clock, another
    flight's track) however well one similarity fits the whole."""
    fixed = [k for k, s in enumerate(samples) if s.lat is not None and s.lon is not None]
    if len(fixed) < 2 * min_fixes:
        return None
    half = len(fixed) // 2
    fits = []
    for part in (fixed[:half], fixed[half:]):
        geo = fit_georeference(xy[part], [samples[k].lat for k in part], [samples[k].lon for k in part],
                               inlier_m=inlier_m, min_extent_m=min_extent_m / 2.0, min_fixes=min_fixes)
        if geo is None or geo.scale_source != "gps":
            return None
        fits.append(geo)
    ratio = fits[1].metres_per_px / fits[0].metres_per_px
    if max(ratio, 1.0 / ratio) > max_scale_ratio:
        return f"the two halves of the GPS track fit the vision track at scales x{ratio:.2f} apart"
    turn = float(wrap_deg(fits[1].heading_deg - fits[0].heading_deg))
    if abs(turn) > max_heading_error:
        return f"the two halves of the GPS track fit the vision track turned {turn:.0f} deg apart"
    return None


def frame_ranges(frames: list[int], limit: int = 6) -> str:
    """``[3, 4, 5, 9]`` -> ``"3-5, 9"`` (at most ``limit`` ranges, then ``...``)."""
    out: list[str] = []
    start = prev = None
    for f in sorted(frames):
        if prev is not None and f == prev + 1:
            prev = f
            continue
        if start is not None:
            out.append(f"{start}-{prev}" if prev != start else f"{start}")
        start = prev = f
    if start is not None:
        out.append(f"{start}-{prev}" if prev != start else f"{start}")
    return ", ".join(out[:limit]) + (", ..." if len(out) > limit else "")


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
    field_at : callable, optional
        ``(field, t) -> value or None``: one field of what ``sample_at(t)`` gives (a buffer's
        ``value_at``), for checks that read one field over the whole flight (the time-offset
        check reads the yaw every 0.05 s: a whole sample each time cost 0.1 s a 1000-frame flight).
    sample_of : callable, optional
        ``frame -> TelemetrySample or None``: the frame's own sample, used instead of
        ``sample_at`` (survey stills: each still's, also when stills share a capture time).
    """

    def __init__(self, sample_at: Callable[[float], TelemetrySample], mode: str, cfg: Config, *,
                 video_start: float = 0.0, offset: float = 0.0,
                 link_summary: Callable[[], dict] = dict,
                 field_at: Callable[[str, float], float | None] | None = None,
                 sample_of: Callable[[Frame], TelemetrySample | None] | None = None) -> None:
        if mode not in ("live", "log", "link", "stills"):
            raise ValueError(f"unknown telemetry time mode {mode!r}")
        self.sample_at = sample_at
        self.field_at = field_at
        self.sample_of = sample_of
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
        self._frame_mask: np.ndarray | None = None  # valid pixels of every input frame (None: all)
        self._samples: dict[int, TelemetrySample] = {}  # frame index -> sample (posed frames only)
        self.link_summary = link_summary
        self._frames = 0                     # frames asked for their sample
        self._missing: list[int] = []        # frames without telemetry
        self._index: int | None = None       # the frame being processed
        self._tilt: dict[int, tuple[float, float]] = {}  # frame -> (roll, pitch) it was rectified with
        self._size: tuple[int, int] | None = None         # (w, h) of the input frames
        self._in_a_row = 0                   # priors overruled in a row
        self._prior_open = False             # the last prior handed out was not overruled (yet)
        self.stopped = False                 # telemetry switched off for the rest of the run
        self.status = "ok"
        self.problems: list[str] = []
        self._max_in_a_row = self.tcfg.max_disagreements_in_a_row
        self._max_scale_ratio = self.gcfg.max_scale_ratio
        self._max_heading_error = self.gcfg.max_heading_error_deg
        self._min_inlier_fraction = self.gcfg.min_inlier_fraction
        self._alone = (self.gcfg.alone_min_inlier_fraction, self.gcfg.alone_max_rms_fraction)

    def keep(self, index: int, sample: TelemetrySample) -> None:
        """Keep the sample of posed frame ``index`` for the georeference at the end."""
        self._samples[index] = sample

    def kept(self, index: int) -> TelemetrySample | None:
        """The sample kept for frame ``index``, if any."""
        return self._samples.get(index)

    def disagreement(self) -> int:
        """Count one frame where vision overruled telemetry; returns the count so far.

        After ``telemetry.max_disagreements_in_a_row`` in a row (0 = never) the join stops:
        every later frame is mapped by vision alone (said once, as a WARNING).
        """
        self.stats.disagreements += 1
        self._prior_open = False
        self._in_a_row += 1
        limit = self._max_in_a_row
        if limit and self._in_a_row >= limit and not self.stopped:
            self.stopped = True
            self.stats.stopped_at_frame = self._index
            log.warning("telemetry disagreed with the images %d frames in a row (up to frame %s): "
                        "telemetry is ignored for the rest of the run (vision alone)",
                        self._in_a_row, self._index)
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
        """The frame's telemetry sample, or None (unknown, or telemetry switched off)."""
        self._index = frame.index
        self._frames += 1
        if self.stopped:
            self.stats.frames_ignored += 1
            return None
        s = self.sample_of(frame) if self.sample_of is not None else self.sample_at(self.telemetry_time(frame.t))
        known = s is not None and (s.yaw is not None or s.height_above_ground is not None
                                   or s.lat is not None)
        if known:
            self.stats.frames_with_telemetry += 1
            return s
        self.stats.frames_without_telemetry += 1
        self._missing.append(frame.index)
        return None

    def use_camera(self, fx: float | None, mask: np.ndarray | None) -> None:
        """The input frames' camera after lens undistortion (:mod:`photomap.mapping.frameprep`):
        their focal length (None: from the ``camera`` config) and their valid pixels (255; None:
        all), which a rectified view's mask then carries."""
        if fx is not None:
            self._fx = float(fx)
        self._frame_mask = mask

    def focal(self, width: int) -> float | None:
        if self._fx is None:
            self._fx = focal_px(width, self.ccfg.fx_px, self.ccfg.hfov_deg)
        return self._fx

    def _tilt_of(self, s: TelemetrySample | None) -> tuple[float, float] | None:
        """(roll, pitch) to rectify with, or None when the frame is left as it is."""
        if not self.tcfg.rectify_tilt or s is None or s.roll is None or s.pitch is None:
            return None
        if abs(s.roll) < _MIN_TILT_RAD and abs(s.pitch) < _MIN_TILT_RAD:
            return None
        return s.roll, s.pitch

    def rectify_frame(self, image: np.ndarray, s: TelemetrySample | None,
                      index: int | None = None) -> Rectified:
        """Warp a tilted frame to its recentred nadir view (needs roll, pitch and the camera model).

        The view has the input's size; see :class:`Rectified` and the module docstring for the
        pose convention. ``index`` (default: the frame whose sample was asked last) is
        remembered with the attitude, for :meth:`mask` and :meth:`row_columns`.
        """
        h, w = image.shape[:2]
        self._size = (w, h)
        tilt = self._tilt_of(s)
        fx = self.focal(w) if tilt is not None else None
        if tilt is None or fx is None:
            return Rectified(image)
        hmg = rectifying_homography(fx, w, h, *tilt)
        index = self._index if index is None else index
        if index is not None:
            self._tilt[index] = tilt
        self.stats.rectified += 1
        warped = cv2.warpPerspective(image, hmg, (w, h), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_REPLICATE)
        mask = self._warp_mask(hmg, w, h)
        if cv2.countNonZero(mask) < mask.size:
            fill_invalid(warped, mask)
        return Rectified(warped, mask, hmg)

    def rectify(self, image: np.ndarray, s: TelemetrySample | None) -> np.ndarray:
        """The image of :meth:`rectify_frame` (the input itself when it is not rectified)."""
        return self.rectify_frame(image, s).image

    def _warp_mask(self, hmg: np.ndarray, w: int, h: int) -> np.ndarray:
        """255 where the view pixel's source lies inside the input frame (and inside its mask,
        :meth:`use_camera`), else 0.

        The frame's outer pixel centres, moved 1 px in, map to a quadrilateral (convex for any
        tilt that keeps the horizon out of the frame), filled with 1/16 px precision; filling
        covers up to about half a pixel beyond it, so bilinear interpolation of a valid view
        pixel never reads outside the frame.
        """
        quad = np.array([[1.0, 1.0, 1.0], [w - 2.0, 1.0, 1.0], [w - 2.0, h - 2.0, 1.0], [1.0, h - 2.0, 1.0]]) @ hmg.T
        pts = np.round(quad[:, :2] / quad[:, 2:] * 16.0).astype(np.int32)
        mask = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(mask, pts, 255, lineType=cv2.LINE_8, shift=4)
        if self._frame_mask is not None:
            inside = cv2.warpPerspective(self._frame_mask, hmg, (w, h), flags=cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            mask[inside < 255] = 0
        return mask

    def homography(self, index: int) -> np.ndarray | None:
        """3x3 input pixels -> pixels of the view the map got of frame ``index`` (None: the input)."""
        tilt = self._tilt.get(index)
        if tilt is None or self._size is None or self._fx is None:
            return None
        return rectifying_homography(self._fx, *self._size, *tilt)

    def mask(self, index: int) -> np.ndarray | None:
        """Validity mask of frame ``index``'s view (None: all valid), e.g. to re-render it."""
        hmg = self.homography(index)
        return None if hmg is None else self._warp_mask(hmg, *self._size)

    def row_columns(self, index: int) -> dict:
        """trajectory.csv columns saying which pixels the pose of frame ``index`` maps: empty
        for the input frame; ``rect_roll_deg``, ``rect_pitch_deg``, ``rect_fx_px`` for a
        rectified view (:func:`~photomap.geo.georef.rectifying_homography`)."""
        tilt = self._tilt.get(index)
        if tilt is None or self._fx is None:
            return {}
        return {"rect_roll_deg": math.degrees(tilt[0]), "rect_pitch_deg": math.degrees(tilt[1]),
                "rect_fx_px": float(self._fx)}

    def prior(self, reference: TelemetrySample | None, current: TelemetrySample | None) -> Prior | None:
        """Expected registration of ``current`` against ``reference`` from yaw and height."""
        if not self.tcfg.use_priors or self.stopped or reference is None or current is None:
            return None
        angle, scale = telemetry_prior(reference, current)
        if angle is None and scale is None:
            return None
        if self._prior_open:  # the previous prior was not overruled: the run of disagreements ends
            self._in_a_row = 0
        self._prior_open = True
        self.stats.priors_used += 1
        return Prior(angle_deg=angle, angle_tol_deg=self.tcfg.prior_angle_tol_deg,
                     scale=scale, scale_tol=self.tcfg.prior_scale_tol)

    # ------------------------------------------------------------------ after the run
    def time_offset_check(self, frame_t: list[float], angles: list[float]) -> dict | None:
        """Estimate the video/telemetry offset from yaw rates.

        None when it cannot be told (too little data or yaw motion, or the telemetry is the
        stills' own: the same clock by construction); else a dict with ``residual_offset_s`` and
        ``correlation`` (None when refused), ``refused`` (the reason, or None) and
        ``best_correlation``.
        """
        if not frame_t or self.mode == "stills":
            return None
        tel_t = [self.telemetry_time(t) for t in frame_t]
        ts, yaws = [], []
        for t in np.arange(tel_t[0] - self.gcfg.timesync_window_s,
                           tel_t[-1] + self.gcfg.timesync_window_s, 0.05):
            if self.field_at is not None:
                yaw = self.field_at("yaw", float(t))
            else:
                s = self.sample_at(float(t))
                yaw = s.yaw if s is not None else None
            if yaw is not None:
                ts.append(float(t))
                yaws.append(yaw)
        if len(ts) < 10:
            return None
        found = sync_time_offset(tel_t, angles, ts, yaws, nominal_s=0.0,
                                 window_s=self.gcfg.timesync_window_s,
                                 min_correlation=self.gcfg.timesync_min_correlation,
                                 min_rate_deg_s=self.gcfg.timesync_min_yaw_rate)
        if found.reason is not None and not found.refused:
            return None
        return {"residual_offset_s": found.offset_s, "correlation": found.correlation,
                "refused": found.reason, "best_correlation": found.best_correlation}

    def gps_point(self, index: int | None, s: TelemetrySample, width: int, height: int) -> np.ndarray:
        """Homogeneous pixel (of the frame's pose) that the GPS fix belongs to: the ground point
        below the camera (the frame centre when the attitude or camera model is unknown)."""
        cx, cy = frame_centre(width, height)
        hmg = self.homography(index) if index is not None else None
        fx = self.focal(width)
        if fx is None or s.roll is None or s.pitch is None:
            return np.array([cx, cy, 1.0])
        u, v = nadir_pixel(fx, cx, cy, s.roll, s.pitch)  # input pixels
        p = np.array([u, v, 1.0])
        if hmg is not None:
            p = hmg @ p
            p = p / p[2]
        return p

    def fit_segment(self, width: int, height: int, poses: list[np.ndarray], samples: list[TelemetrySample],
                    frames: list[int] | None = None) -> SegmentFit:
        """Metric scale and georeference of one segment, with the checks of the GPS fit.

        ``poses`` (2x3, map pixels of the frames' views), ``samples`` and ``frames`` (indices)
        are parallel. The GPS fit's ``problem`` is set when fewer than
        ``georef.min_inlier_fraction`` of the fixes agree with it, when the two halves of a
        GPS-scaled track need scales (rotations) more than ``georef.max_scale_ratio``
        (``georef.max_heading_error_deg``) apart (:func:`_halves_disagree`), or when a short
        track (camera scale) leaves an RMS residual above half of ``georef.gps_inlier_m``.
        Otherwise a GPS-fitted scale that contradicts the camera's (ratio beyond
        ``georef.max_scale_ratio``) drops the camera's scale, and a GPS-fitted rotation that
        contradicts a consistent compass (beyond ``georef.max_heading_error_deg``) drops the
        compass (``dropped``): the GPS fit stands, if it holds on its own (:meth:`_weak_alone`);
        if it does not, the contradiction is its ``problem``.
        """
        fx = self.focal(width)
        heights = [s.height_above_ground for s in samples]
        camera_mpp = metres_per_pixel(poses, heights, fx) if fx else None
        frames = list(frames) if frames is not None else [None] * len(poses)
        xy = (np.array([(p @ self.gps_point(f, s, width, height))[:2] for p, s, f in zip(poses, samples, frames)])
              if poses else np.zeros((0, 2)))
        heading = map_heading_deg(poses, [s.yaw for s in samples])
        g = self.gcfg
        fixes = sum(1 for s in samples if s.lat is not None and s.lon is not None)
        geo = None
        if fixes >= g.min_fixes:  # fitted even when few fixes agree: that is a finding too
            geo = fit_georeference(xy, [s.lat for s in samples], [s.lon for s in samples],
                                   metres_per_px=camera_mpp, heading_deg=heading, inlier_m=g.gps_inlier_m,
                                   min_extent_m=g.min_extent_m, min_fixes=2)
        if geo is not None and geo.inliers < g.min_fixes:
            log.info("georeference: only %d of %d fixes agree within %.1f m", geo.inliers, geo.points,
                     g.gps_inlier_m)
        fit = SegmentFit(camera_mpp, geo, camera_mpp, heading)
        if geo is None:
            return fit
        if geo.inliers < self._min_inlier_fraction * geo.points:
            fit.problem = (f"only {geo.inliers} of {geo.points} GPS fixes fit the vision track "
                           f"within {g.gps_inlier_m:g} m")
        elif geo.scale_source == "gps":
            fit.problem = _halves_disagree(xy, samples, g.gps_inlier_m, g.min_extent_m, g.min_fixes,
                                           self._max_scale_ratio, self._max_heading_error)
        if fit.problem is None and geo.scale_source == "camera" and geo.rms_m > g.gps_inlier_m / 2:
            fit.problem = (f"the GPS track does not follow the vision track at the camera's scale "
                           f"(RMS {geo.rms_m:.1f} m)")
        contradicted: list[tuple[str, str, str]] = []  # (prior, refusal text, dropping text)
        if fit.problem is None and geo.scale_source == "gps" and camera_mpp:
            ratio = geo.metres_per_px / camera_mpp
            if max(ratio, 1.0 / ratio) > self._max_scale_ratio:
                contradicted.append((
                    "camera_scale",
                    f"the GPS track makes {geo.metres_per_px:.3g} m per map pixel, the camera and height "
                    f"{camera_mpp:.3g} m (x{ratio:.2f})",
                    f"the camera height and focal length make {camera_mpp:.3g} m per map pixel, the GPS "
                    f"track {geo.metres_per_px:.3g} m (x{ratio:.2f}; is the height over the take-off "
                    "point rather than the ground?): the scale is the GPS track's"))
        if fit.problem is None and geo.scale_source == "gps" and heading is not None \
                and _consistent_compass(poses, samples):
            off = float(wrap_deg(heading - geo.heading_deg))
            if abs(off) > self._max_heading_error:
                contradicted.append((
                    "compass", f"the GPS track is turned {-off:.0f} deg against the compass",
                    f"the compass (gimbal) yaw is turned {off:.0f} deg against the GPS track: the map's "
                    "heading is the GPS track's"))
        if contradicted:
            weak = self._weak_alone(geo)
            if weak is not None:  # a GPS fit that needs the priors' support loses to them
                fit.problem = "; ".join(refusal for _, refusal, _ in contradicted) + f" ({weak})"
            else:
                fit.dropped = [(code, text) for code, _, text in contradicted]
                if any(code == "camera_scale" for code, _, _ in contradicted):
                    fit.metres_per_px = geo.metres_per_px
        if geo.inliers < g.min_fixes:
            fit.geo = None
        elif fit.metres_per_px is None:
            fit.metres_per_px = geo.metres_per_px
        return fit

    def _weak_alone(self, geo: Georeference) -> str | None:
        """Why a GPS fit cannot overrule the priors on its own, or None: fewer than
        ``georef.alone_min_inlier_fraction`` of the fixes within ``georef.gps_inlier_m``, or an
        RMS residual above ``georef.alone_max_rms_fraction`` of the track's spread."""
        min_inliers, max_rms = self._alone
        if geo.inliers < min_inliers * geo.points:
            return f"{geo.inliers} of {geo.points} fixes fit"
        if geo.rms_m > max_rms * geo.extent_m:
            return f"RMS {geo.rms_m:.1f} m over a track of {geo.extent_m:.0f} m spread"
        return None

    def georeference(self, width: int, height: int, poses: list[np.ndarray],
                     samples: list[TelemetrySample], frames: list[int] | None = None
                     ) -> tuple[float | None, Georeference | None]:
        """Metres per map pixel and the georeference of one segment (None when unknown); see
        :meth:`fit_segment` for the checks (a contradicted GPS fit gives no georeference)."""
        fit = self.fit_segment(width, height, poses, samples, frames)
        return fit.metres_per_px, (fit.geo if fit.problem is None else None)

    def verdict(self, check: dict | None, fit: SegmentFit | None) -> str:
        """Whether the telemetry fits the images; logs one WARNING when it does not (and one
        naming the frames left without telemetry). Sets and returns :attr:`status`:

        ``ok``; ``no_samples`` (no frame got a sample); ``time_sync_refused`` (the yaw rates of
        video and telemetry do not correlate: ``check`` from :meth:`time_offset_check`);
        ``disagrees`` (vision overruled most priors, or telemetry was switched off for it);
        ``gps_mismatch`` (``fit``, the main segment's :meth:`fit_segment`, has a problem).
        :attr:`problems` lists every reason found, in that order; for trusted telemetry, the
        priors the GPS fit dropped (``fit.dropped``: the status stays ``ok``), one WARNING each.
        """
        problems = self.assess(check, fit)
        dropped = list(fit.dropped) if fit is not None and not problems else []
        self.problems = [f"{code}: {text}" for code, text in problems + dropped]
        self.status = problems[0][0] if problems else "ok"
        if problems:
            log.warning("telemetry refused (%s): the map is not georeferenced from it",
                        "; ".join(text for _, text in problems))
        for _, text in dropped:
            log.warning("telemetry prior dropped: %s", text)
        if not problems and self._missing:
            log.warning("%d of %d frames have no telemetry (frames %s): mapped by vision alone",
                        len(self._missing), self._frames, frame_ranges(self._missing))
        return self.status

    def assess(self, check: dict | None, fit: SegmentFit | None) -> list[tuple[str, str]]:
        """The reasons (code, text) to refuse the telemetry (see :meth:`verdict`, which says
        them); empty when it fits the images. Logs nothing, changes nothing."""
        problems: list[tuple[str, str]] = []
        st = self.stats
        if self._frames and st.frames_with_telemetry == 0:
            problems.append(("no_samples", f"no telemetry sample at any of the {self._frames} frames"
                             + (f" (video start {self.video_start:.1f} on the telemetry clock)"
                                if self.mode == "log" else "")))
        if check is not None and check.get("refused"):
            best = check.get("best_correlation")
            problems.append(("time_sync_refused", "the yaw rates of video and telemetry do not match "
                             f"({check['refused']}"
                             + (f", best correlation {best:.2f}" if best is not None else "") + ")"))
        if st.stopped_at_frame is not None or (
                st.disagreements >= 5 and st.disagreements > 0.5 * st.priors_used):
            problems.append(("disagrees", f"vision overruled {st.disagreements} of {st.priors_used} "
                             "telemetry priors"
                             + (f" (ignored from frame {st.stopped_at_frame} on)"
                                if st.stopped_at_frame is not None else "")))
        if fit is not None and fit.problem:
            problems.append(("gps_mismatch", fit.problem))
        return problems

    def summary(self) -> dict:
        """What the join did and decided (``run.json`` ``telemetry``, without the time check)."""
        return {**asdict(self.stats), "status": self.status, "problems": list(self.problems),
                "frames_missing": frame_ranges(self._missing, limit=20) if self._missing else None,
                "link": self.link_summary(), "time_offset_s": self.offset}
