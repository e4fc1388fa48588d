"""Hot spots and colour anomalies in a frame: the detector of hazard spots (pure: arrays in, arrays out).

Two kinds of spot, both as blobs of connected pixels within size limits:

- **hot** (:class:`HotSpotDetector` with :class:`FlightLevels`): pixels of a thermal or grey frame
  (a BGR frame is reduced to its luminance) above a *flight-relative* threshold, ``median +
  max(k * sigma, min_excess)`` of the grey levels the flight has shown so far (``sigma`` = 1.4826
  MAD, from a running histogram with a forgetting window of ``window_frames`` frames). A frame
  is judged against the flight, not against itself: a uniformly warm frame is no hazard (its
  pixels are warm together: one blob larger than ``max_area_px``, or nothing above the
  threshold), and a frame of cool ground with one patch at the flight's usual level has none.
- **colour** (:func:`colour_mask`): pixels whose HSV colour is within ``hue_tol_deg`` of
  ``hue_deg`` with at least ``min_saturation`` and ``min_value`` (e.g. orange smoke, a
  high-visibility jacket).

Blobs touching the frame's border are left out (only part of the spot is in view: its centroid
would be off; another frame sees it whole). Positions are in input frame pixels (OpenCV
convention: x right, y down, origin at the centre of the top-left pixel) whatever the detection
scale; areas in input pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Blobs", "FlightLevels", "HotSpotDetector", "colour_mask", "find_blobs", "grey_levels"]

MAD_TO_SIGMA = 1.4826
MAX_BLOBS = 64  # per frame: more candidates than this is noise, not hazards


@dataclass(frozen=True)
class Blobs:
    """The spots of one frame: ``xy`` (n, 2) centroids in input frame pixels (weighted by the
    excess over the threshold), ``area`` (n,) input pixels, ``peak`` (n,) the largest value
    (grey level; for colour blobs the HSV value)."""

    xy: np.ndarray
    area: np.ndarray
    peak: np.ndarray

    def __len__(self) -> int:
        return len(self.area)

    @staticmethod
    def empty() -> Blobs:
        return Blobs(np.zeros((0, 2)), np.zeros(0), np.zeros(0))


def grey_levels(image: np.ndarray) -> np.ndarray:
    """The grey levels of a frame: a single-channel frame as it is (uint8 or uint16 radiometric),
    a BGR/BGRA frame's luminance (uint8)."""
    if image.ndim == 2:
        return image
    if image.shape[2] == 1:
        return image[..., 0]
    return cv2.cvtColor(np.ascontiguousarray(image[..., :3]), cv2.COLOR_BGR2GRAY)


class FlightLevels:
    """A running histogram of the flight's grey levels and its robust threshold.

    ``bins``: 256 for uint8 frames, 65536 for uint16. Each :meth:`add` first multiplies the counts
    by ``1 - 1 / window_frames`` (an exponential window over about that many frames), then adds
    the frame's levels (every ``stride``-th pixel in x and y).
    """

    def __init__(self, bins: int = 256, window_frames: float = 300.0, stride: int = 2) -> None:
        self.bins = int(bins)
        self.keep = 1.0 - 1.0 / max(float(window_frames), 1.0)
        self.stride = max(int(stride), 1)
        self.counts = np.zeros(self.bins, np.float64)
        self.frames = 0

    def add(self, grey: np.ndarray) -> None:
        """Add one frame's grey levels (integer array, values below ``bins``)."""
        s = self.stride
        sample = np.ascontiguousarray(grey[::s, ::s]).ravel()
        self.counts *= self.keep
        self.counts += np.bincount(sample, minlength=self.bins)[: self.bins]
        self.frames += 1

    def median_mad(self) -> tuple[float, float]:
        """The median grey level and the median absolute deviation from it (levels)."""
        total = float(self.counts.sum())
        if total <= 0:
            return 0.0, 0.0
        cdf = np.cumsum(self.counts)
        med = int(np.searchsorted(cdf, 0.5 * total))
        d = np.arange(self.bins)
        hi = np.minimum(med + d, self.bins - 1)
        lo = med - d - 1
        mass = cdf[hi] - np.where(lo >= 0, cdf[np.maximum(lo, 0)], 0.0)
        mad = int(np.searchsorted(mass, 0.5 * total))
        return float(med), float(mad)

    def threshold(self, k: float, min_excess: float) -> float:
        """``median + max(k * 1.4826 * MAD, min_excess)``."""
        med, mad = self.median_mad()
        return med + max(k * MAD_TO_SIGMA * mad, min_excess)


def colour_mask(bgr: np.ndarray, hue_deg: float, hue_tol_deg: float, min_saturation: float,
                min_value: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of a BGR frame near a target colour: ``(mask uint8 0/1, value uint8)``. Hue in
    degrees (0-360, red 0, green 120; wraps around), saturation and value 0-255."""
    hsv = cv2.cvtColor(np.ascontiguousarray(bgr[..., :3]), cv2.COLOR_BGR2HSV)
    hue = hsv[..., 0].astype(np.float32) * 2.0  # OpenCV: 0-179 for 0-358 degrees
    dh = np.abs((hue - float(hue_deg) + 180.0) % 360.0 - 180.0)
    mask = (dh <= hue_tol_deg) & (hsv[..., 1] >= min_saturation) & (hsv[..., 2] >= min_value)
    return mask.astype(np.uint8), hsv[..., 2]


def find_blobs(mask: np.ndarray, values: np.ndarray, base: float = 0.0, *, min_area: float, max_area: float,
               factor: float = 1.0) -> Blobs:
    """Connected blobs (8-neighbours) of ``mask`` (uint8, nonzero = in) with ``min_area <= area <=
    max_area`` (pixels of ``mask``), not touching its border; centroid weighted by ``values -
    base`` (the excess over the threshold), peak = the largest of ``values`` inside. ``factor`` =
    input px per ``mask`` px: centroids and areas come back in input pixels (pixel centres:
    ``x_in = (x + 0.5) * factor - 0.5``)."""
    if cv2.countNonZero(mask) == 0:
        return Blobs.empty()
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return Blobs.empty()
    h, w = mask.shape[:2]
    x0, y0 = stats[1:, cv2.CC_STAT_LEFT], stats[1:, cv2.CC_STAT_TOP]
    bw, bh, area = stats[1:, cv2.CC_STAT_WIDTH], stats[1:, cv2.CC_STAT_HEIGHT], stats[1:, cv2.CC_STAT_AREA]
    inner = (x0 > 0) & (y0 > 0) & (x0 + bw < w) & (y0 + bh < h)
    ok = np.flatnonzero(inner & (area >= min_area) & (area <= max_area))
    if len(ok) > MAX_BLOBS:
        ok = ok[np.argsort(-area[ok])[:MAX_BLOBS]]
    xy, areas, peaks = [], [], []
    for i in ok.tolist():
        ys, xs = slice(int(y0[i]), int(y0[i] + bh[i])), slice(int(x0[i]), int(x0[i] + bw[i]))
        inside = labels[ys, xs] == i + 1
        v = values[ys, xs].astype(np.float64)
        wt = np.where(inside, np.maximum(v - base, 1e-6), 0.0)
        total = float(wt.sum())
        cx = float(wt.sum(axis=0) @ np.arange(xs.start, xs.stop, dtype=np.float64)) / total
        cy = float(wt.sum(axis=1) @ np.arange(ys.start, ys.stop, dtype=np.float64)) / total
        xy.append(((cx + 0.5) * factor - 0.5, (cy + 0.5) * factor - 0.5))
        areas.append(float(area[i]) * factor * factor)
        peaks.append(float(v[inside].max()))
    if not xy:
        return Blobs.empty()
    return Blobs(np.array(xy, float), np.array(areas, float), np.array(peaks, float))


class HotSpotDetector:
    """Hot spots (``mode="hot"``) or colour anomalies (``mode="colour"``) frame by frame.

    Parameters
    ----------
    k, min_excess : the hot threshold above the flight's median (see :class:`FlightLevels`).
    min_area_px, max_area_px : blob size limits, input pixels.
    detect_px : longest side of the image the detection runs on (larger frames are shrunk with
        an area resize first, so peaks are those of the shrunk image; 0 = full resolution).
    window_frames : forgetting window of the flight's grey-level histogram, frames.
    hue_deg, hue_tol_deg, min_saturation, min_value : the colour mode's target (see :func:`colour_mask`).
    """

    def __init__(self, mode: str = "hot", *, k: float = 8.0, min_excess: float = 60.0,
                 min_area_px: float = 6.0, max_area_px: float = 4000.0, detect_px: int = 320,
                 window_frames: float = 300.0, hue_deg: float = 25.0, hue_tol_deg: float = 15.0,
                 min_saturation: float = 150.0, min_value: float = 150.0) -> None:
        if mode not in ("hot", "colour"):
            raise ValueError(f"mode must be hot or colour, got {mode!r}")
        self.mode = mode
        self.k, self.min_excess = float(k), float(min_excess)
        self.min_area_px, self.max_area_px = float(min_area_px), float(max_area_px)
        self.detect_px = int(detect_px)
        self.window_frames = float(window_frames)
        self.colour = (float(hue_deg), float(hue_tol_deg), float(min_saturation), float(min_value))
        self.levels: FlightLevels | None = None
        self.last_threshold: float | None = None

    def _shrink(self, image: np.ndarray) -> tuple[np.ndarray, float]:
        h, w = image.shape[:2]
        if self.detect_px <= 0 or max(h, w) <= self.detect_px:
            return image, 1.0
        f = self.detect_px / max(h, w)
        size = (max(1, int(round(w * f))), max(1, int(round(h * f))))
        return cv2.resize(image, size, interpolation=cv2.INTER_AREA), w / size[0]

    def detect(self, image: np.ndarray) -> Blobs:
        """The spots of one frame (uint8/uint16 grey or BGR); the hot mode also adds the frame to
        the flight's levels first (so the first frames are judged against themselves)."""
        small, factor = self._shrink(image)
        min_a, max_a = self.min_area_px / factor ** 2, self.max_area_px / factor ** 2
        if self.mode == "colour":
            if small.ndim != 3 or small.shape[2] < 3:
                return Blobs.empty()
            mask, value = colour_mask(small, *self.colour)
            return find_blobs(mask, value, 0.0, min_area=min_a, max_area=max_a, factor=factor)
        grey = grey_levels(small)
        if self.levels is None:
            self.levels = FlightLevels(65536 if grey.dtype == np.uint16 else 256, self.window_frames)
        if grey.dtype not in (np.uint8, np.uint16):
            grey = np.clip(grey, 0, self.levels.bins - 1).astype(np.uint16)
        self.levels.add(grey)
        thr = self.levels.threshold(self.k, self.min_excess)
        self.last_threshold = thr
        if grey.dtype == np.uint8:
            mask = cv2.threshold(grey, math.floor(thr), 1, cv2.THRESH_BINARY)[1]  # grey > floor(thr)
        else:
            mask = (grey > thr).view(np.uint8)
        return find_blobs(mask, grey, thr, min_area=min_a, max_area=max_a, factor=factor)
