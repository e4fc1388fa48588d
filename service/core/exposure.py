"""Exposure compensation between frames: a gain per frame, fitted where it overlaps the map.

A camera on auto exposure (or auto white balance) records the same ground brighter or darker
from frame to frame; painted as is, every frame edge in the map shows a brightness step. Here
each new frame gets a gain ``g`` (one per colour channel, or one for all) so that, where the
warped frame overlaps what the map already holds, ``g * frame`` matches the map:

1. ``overlap_ratio``: from samples of the same map pixels in the new (un-gained) frame and in
   the map, the robust ratio of means ``sum(map) / sum(frame)``. Pixels near black or white in
   either (clipped: their ratio is wrong) are left out, and so are pixels whose own luminance
   ratio is far from the median one (moving objects, misregistration, specular glints).
2. ``SequentialGain``: the gain of the new frame is that ratio, pulled toward 1 in proportion
   to how much new ground the frame adds: ``log g = (1 - pull * f_new) * log ratio``, where
   ``f_new`` is the fraction of the frame's footprint the map did not yet cover. The map matches
   each frame to its neighbours (no step at its edges) but, over ``~1 / pull`` frame footprints
   of new ground, returns to the camera's own exposure, so errors cannot accumulate into a
   drift of the whole map's brightness over a long flight. Counting new ground (not frames)
   makes this the same for 30 frames/s video and for stills a few seconds apart.

A frame with too little usable overlap (the first of a map, or one over empty map) keeps the
previous gain, pulled toward 1 as for a frame of all new ground.

For a re-render of a finished set (stills, keyframes), :func:`joint_gains` fits the gains of all
frames at once from all their overlaps instead: no frame is the reference, and nothing drifts.

Pure computation: arrays in, arrays out, deterministic (no randomness; the caller chooses the
samples on a fixed grid).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

# Samples whose value (0..255) is at or below DARK or at or above BRIGHT in any channel, in the
# frame or in the map, are not used: clipping breaks the proportionality.
DARK = 6.0
BRIGHT = 249.0
# Samples whose luminance log-ratio differs from the median one by more than this are outliers.
MAX_LOG_DEVIATION = 0.3
# Ridge of the joint fit, relative to the mean overlap weight: it only sets the common level.
RIDGE = 1e-3


def overlap_ratio(frame: np.ndarray, mapped: np.ndarray, *, per_channel: bool,
                  min_samples: int = 256) -> np.ndarray | None:
    """Gain that makes ``frame`` match ``mapped``: a robust ratio of means.

    Parameters
    ----------
    frame, mapped : float array (N, C)
        The same N map pixels (C channels, 0..255): the new frame warped into the map, before any
        gain, and what the map holds there.
    per_channel : bool
        One ratio per channel; otherwise one ratio (of the sums over all channels) repeated C times.
    min_samples : int
        Fewest usable samples (after leaving out clipped pixels and outliers) for an answer.

    Returns
    -------
    float64 array (C,) of ratios ``sum(mapped) / sum(frame)`` over the usable samples, or None
    when fewer than ``min_samples`` are usable.
    """
    frame = np.asarray(frame, np.float32)
    mapped = np.asarray(mapped, np.float32)
    if frame.ndim != 2 or frame.shape != mapped.shape:
        raise ValueError(f"overlap samples must be two (N, C) arrays of one shape, got {frame.shape} "
                         f"and {mapped.shape}")
    C = frame.shape[1]
    if frame.shape[0] < min_samples:
        return None
    ok = ((frame > DARK) & (frame < BRIGHT) & (mapped > DARK) & (mapped < BRIGHT)).all(axis=1)
    if np.count_nonzero(ok) < min_samples:
        return None
    f, m = frame[ok], mapped[ok]
    lf, lm = f.sum(axis=1), m.sum(axis=1)
    d = np.log(lm) - np.log(lf)
    keep = np.abs(d - np.median(d)) <= MAX_LOG_DEVIATION
    if np.count_nonzero(keep) < min_samples:
        return None
    f, m = f[keep].astype(np.float64), m[keep].astype(np.float64)
    if per_channel:
        return m.sum(axis=0) / f.sum(axis=0)
    return np.full(C, m.sum() / f.sum())


class SequentialGain:
    """The gain of each new frame of one map, fitted to what the map holds (see the module docstring).

    Parameters
    ----------
    channels : int
        Colour channels of the map (1 or 3).
    per_channel : bool
        One gain per channel (also evens out white balance changes) or one for all channels.
    pull : float in [0, 1]
        Fraction of the way back to gain 1 per frame footprint of new ground (0: never; the gain
        may then drift with the errors of each fit).
    limits : (low, high)
        Each measured ratio is clipped to this range first.
    min_samples : int
        Fewest usable overlap samples for a fit (see :func:`overlap_ratio`).
    """

    def __init__(self, channels: int, *, per_channel: bool, pull: float = 0.1,
                 limits: tuple[float, float] = (0.5, 2.0), min_samples: int = 256) -> None:
        if not 0 <= pull <= 1:
            raise ValueError(f"pull must be in [0, 1], got {pull!r}")
        if not 0 < limits[0] <= 1 <= limits[1]:
            raise ValueError(f"gain limits must satisfy 0 < low <= 1 <= high, got {limits!r}")
        self.channels = int(channels)
        self.per_channel = bool(per_channel)
        self.pull = float(pull)
        self.log_limits = (math.log(limits[0]), math.log(limits[1]))
        self.min_samples = int(min_samples)
        self._log_gain = np.zeros(self.channels)

    @property
    def gain(self) -> np.ndarray:
        """The gain of the last frame, float64 (channels,) (ones before the first)."""
        return np.exp(self._log_gain)

    def reset(self) -> None:
        """Back to gain 1 (a new, empty map)."""
        self._log_gain = np.zeros(self.channels)

    def update(self, frame: np.ndarray, mapped: np.ndarray, new_fraction: float) -> np.ndarray:
        """The gain of a new frame.

        Parameters
        ----------
        frame, mapped : float array (N, C)
            The frame (before gain) and the map at the N sampled map pixels that both cover.
        new_fraction : float in [0, 1]
            Fraction of the frame's footprint (counted on the same sample grid) not yet covered
            by the map.

        Returns
        -------
        float64 array (C,): multiply the frame's channel values by it before painting.
        """
        shrink = 1.0 - self.pull * min(max(float(new_fraction), 0.0), 1.0)
        ratio = overlap_ratio(frame, mapped, per_channel=self.per_channel, min_samples=self.min_samples)
        if ratio is None:
            log_gain = self._log_gain  # nothing to fit: the camera's exposure changes slowly
        else:
            log_gain = np.clip(np.log(ratio), *self.log_limits)
        self._log_gain = shrink * log_gain
        return self.gain


def joint_gains(frames: list[np.ndarray], poses: list[np.ndarray], *, per_channel: bool, border: int = 1,
                scale: float = 0.25, min_samples: int = 256) -> np.ndarray:
    """Gains of a set of frames fitted jointly over all their overlaps (for a re-render).

    For every pair of overlapping frames, the robust ratio of their means on the same ground
    (:func:`overlap_ratio`, on the frames warped into the map at ``scale``: means need no detail)
    gives the difference of their log gains; the log gains are their least-squares solution,
    weighted by the overlap sizes, with a weak ridge that sets the common level (the mean log gain
    is about 0: the map keeps the cameras' average exposure and no frame is the reference).

    OpenCV's ``cv2.detail.GainCompensator`` solves the same problem with a prior that keeps each
    gain near 1; on frames with known gains 0.75..1.35 that prior left ~10 % of each step
    (measured), hence this fit. Deterministic; memory: the frames warped at ``scale``.

    Parameters
    ----------
    frames : uint8 (h, w, 3) BGR or (h, w) gray frames
    poses : 2x3 poses, frame pixels -> map pixels
    per_channel : one gain per channel or one for all
    border : frame pixels left out (as ``mosaic.border``)
    scale : map resolution of the fit, (0, 1]
    min_samples : fewest usable samples (at ``scale``) for an overlap to count

    Returns
    -------
    float64 array (n, channels): the gain of each frame (multiply its values by it).
    """
    if len(frames) != len(poses):
        raise ValueError(f"{len(frames)} frames but {len(poses)} poses")
    if not 0 < scale <= 1:
        raise ValueError(f"scale must be in (0, 1], got {scale!r}")
    n = len(frames)
    channels = 1 if n and np.asarray(frames[0]).ndim == 2 else 3
    warped = []  # (x0, y0, image float32 (h, w, C), cover bool (h, w)) in map pixels at scale
    for frame, M in zip(frames, poses):
        f = np.asarray(frame)
        h, w = f.shape[:2]
        valid = np.zeros((h, w), np.uint8)
        valid[border:h - border, border:w - border] = 255
        A = np.asarray(M, np.float64)[:2] * scale
        box = np.array([[-1.0, -1.0], [w, -1.0], [-1.0, h], [w, h]]) @ A[:, :2].T + A[:, 2]
        x0, y0 = (int(v) for v in np.floor(box.min(axis=0)))
        x1, y1 = (int(v) + 1 for v in np.ceil(box.max(axis=0)))
        A[:, 2] -= (x0, y0)
        size = (x1 - x0, y1 - y0)
        img = cv2.warpAffine(f, A, size, flags=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
        cover = cv2.warpAffine(valid, A, size, flags=cv2.INTER_LINEAR) == 255
        warped.append((x0, y0, img.reshape(size[1], size[0], channels).astype(np.float32), cover))
    rows, weights, targets = [], [], []
    for i in range(n):
        xi, yi, fi, ci = warped[i]
        for j in range(i + 1, n):
            xj, yj, fj, cj = warped[j]
            ox0, oy0 = max(xi, xj), max(yi, yj)
            ox1, oy1 = min(xi + ci.shape[1], xj + cj.shape[1]), min(yi + ci.shape[0], yj + cj.shape[0])
            if ox1 - ox0 <= 0 or oy1 - oy0 <= 0:
                continue
            si = (slice(oy0 - yi, oy1 - yi), slice(ox0 - xi, ox1 - xi))
            sj = (slice(oy0 - yj, oy1 - yj), slice(ox0 - xj, ox1 - xj))
            both = ci[si] & cj[sj]
            count = int(np.count_nonzero(both))
            if count < min_samples:
                continue
            ratio = overlap_ratio(fj[sj][both], fi[si][both], per_channel=per_channel, min_samples=min_samples)
            if ratio is None:
                continue
            rows.append((i, j))
            weights.append(count)
            targets.append(np.log(ratio))  # log g_j - log g_i
    if not rows:
        return np.ones((n, channels))
    idx = np.array(rows)
    wts = np.array(weights, np.float64)
    D = np.zeros((len(rows), n))
    D[np.arange(len(rows)), idx[:, 1]] = 1.0
    D[np.arange(len(rows)), idx[:, 0]] = -1.0
    normal = D.T @ (D * wts[:, None])
    normal += RIDGE * wts.mean() * np.eye(n)  # the ridge: sets the common level, and frames without overlap
    log_gains = np.linalg.solve(normal, D.T @ (np.array(targets) * wts[:, None]))
    return np.exp(log_gains)
