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

Pure computation: arrays in, arrays out, deterministic (no randomness; the caller chooses the
samples on a fixed grid).
"""

from __future__ import annotations

import math

import numpy as np

# Samples whose value (0..255) is at or below DARK or at or above BRIGHT in any channel, in the
# frame or in the map, are not used: clipping breaks the proportionality.
DARK = 6.0
BRIGHT = 249.0
# Samples whose luminance log-ratio differs from the median one by more than this are outliers.
MAX_LOG_DEVIATION = 0.3


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
