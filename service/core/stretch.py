"""Deep frames (16-bit, float) to 8 bits with one brightness range per flight.

Pure: arrays in, arrays out. A source that yields frames deeper than 8 bits (16-bit TIFF/PNG
stills, thermal or multispectral cameras, a Y16 V4L2 camera) keeps one :class:`RunningStretch`
for the whole flight and passes every frame through it where the frame enters, so the rest of
the pipeline sees ``uint8`` frames whose grey levels mean the same brightness from frame to
frame (the map's seams and the registration's brightness assumptions hold). A per-frame
min/max stretch would not: a frame with a dark river in it would come out brighter everywhere
else.

The range is robust (the ``low_pct`` and ``high_pct`` percentiles of a subsample of the frame,
all channels together, so colour balance is kept) and follows the flight slowly: the first
frame with any contrast sets it (a blank frame does not move it); a later frame whose percentiles lie outside it widens it by ``widen_rate`` of the
way (brighter or darker ground soon fits, instead of saturating for the rest of the flight),
one whose percentiles lie inside narrows it by ``rate`` of the way (an exponential average over
about ``1 / rate`` frames, by default 500: the range is nearly the flight's envelope). Values
outside the range saturate at 0 and 255. ``uint8`` frames pass through unchanged.

:func:`to_8bit` is the linear map of a range to 0..255 itself: the running stretch uses it, and
so do the multi-band captures, whose files are all known up front and get one fixed range per
band from a sample of the flight (:func:`photomap.core.bands.robust_range_16bit`).
"""

from __future__ import annotations

import numpy as np


def to_8bit(image: np.ndarray, value_range: tuple[float, float]) -> np.ndarray:
    """``image`` (any dtype) linearly mapped from ``value_range = (lo, hi)`` to 0..255, rounded;
    values outside it saturate at 0 and 255, NaN -> 0. The one mapping of deep values to 8 bits
    (:class:`RunningStretch`, the band maps of multi-band flights); ``uint8`` is mapped too.
    ``uint16`` goes through a table of all 65536 values (no float copy of the frame)."""
    lo, hi = float(value_range[0]), float(value_range[1])
    scale = 255.0 / max(hi - lo, 1e-12)
    if image.dtype == np.uint16:
        return np.take(_map(np.arange(65536, dtype=np.float32), lo, scale), image)
    return _map(np.array(image, dtype=np.float32), lo, scale)  # a copy: the input stays


def _map(values: np.ndarray, lo: float, scale: float) -> np.ndarray:
    """float32 ``values`` -> ``uint8`` of ``(values - lo) * scale``, rounded and saturated
    (NaN -> 0); ``values`` is overwritten."""
    out = values
    out -= np.float32(lo)
    out *= np.float32(scale)
    np.nan_to_num(out, copy=False, nan=0.0, posinf=255.0, neginf=0.0)
    np.clip(out, 0.0, 255.0, out=out)
    return (out + 0.5).astype(np.uint8)


class RunningStretch:
    """Map frames of any depth to ``uint8`` with a slowly moving robust range (one per flight).

    Parameters
    ----------
    low_pct, high_pct : float
        Percentiles (0..100) of a frame's values that its range aims at: ``low_pct`` maps to 0,
        ``high_pct`` to 255.
    rate : float
        0 < rate <= 1: how far a frame whose percentiles lie inside the range narrows it
        towards them (1 = a per-frame stretch; 0.002: over about 500 frames, so the grey of a
        brightness stays within a few levels over a flight).
    widen_rate : float
        0 < widen_rate <= 1: how far a frame whose percentiles lie outside the range widens it.
    max_samples : int
        About this many pixels (per channel) of a frame are used for its percentiles.

    Attributes
    ----------
    low, high : float or None
        The current range in the input's units (None before the first deep frame).
    frames : int
        Deep frames stretched so far.

    Examples
    --------
    >>> stretch = RunningStretch()
    >>> for frame in frames_uint16:       # doctest: +SKIP
    ...     image = stretch(frame)        # uint8, same shape
    """

    def __init__(self, low_pct: float = 0.5, high_pct: float = 99.5, rate: float = 0.002,
                 widen_rate: float = 0.05, max_samples: int = 20_000) -> None:
        if not 0.0 <= low_pct < high_pct <= 100.0:
            raise ValueError("need 0 <= low_pct < high_pct <= 100")
        if not (0.0 < rate <= 1.0 and 0.0 < widen_rate <= 1.0):
            raise ValueError("rate and widen_rate must be in (0, 1]")
        if max_samples < 1:
            raise ValueError("max_samples must be >= 1")
        self.low_pct, self.high_pct, self.rate = float(low_pct), float(high_pct), float(rate)
        self.widen_rate = float(widen_rate)
        self.max_samples = int(max_samples)
        self.low: float | None = None
        self.high: float | None = None
        self.frames = 0
        self._flat = False

    def percentiles(self, image: np.ndarray) -> tuple[float, float] | None:
        """``(low, high)`` percentiles of a subsample of ``image`` (finite values only), or None
        when it has no finite value."""
        h, w = image.shape[:2]
        step = max(1, int(np.sqrt(h * w / self.max_samples)))
        sample = np.asarray(image[::step, ::step], dtype=np.float64).ravel()
        sample = sample[np.isfinite(sample)]
        if sample.size == 0:
            return None
        lo, hi = np.percentile(sample, [self.low_pct, self.high_pct])
        return float(lo), float(hi)

    def update(self, image: np.ndarray) -> tuple[float, float] | None:
        """Move the range towards ``image``'s percentiles (set it at the first frame); returns
        the range, or None while no frame has had a finite value."""
        p = self.percentiles(image)
        if p is not None:
            flat = p[1] <= p[0]
            if self.low is None or self.high is None or (self._flat and not flat):
                self.low, self.high = p
                self._flat = flat   # a blank first frame does not set the flight's range
            elif not flat:
                self.low += (self.widen_rate if p[0] < self.low else self.rate) * (p[0] - self.low)
                self.high += (self.widen_rate if p[1] > self.high else self.rate) * (p[1] - self.high)
        if self.low is None or self.high is None:
            return None
        return self.low, self.high

    def apply(self, image: np.ndarray) -> np.ndarray:
        """``image`` mapped to ``uint8`` through the current range, without updating it
        (:func:`to_8bit`; before any range is known, the dtype's full range is used)."""
        if image.dtype == np.uint8:
            return image
        if self.low is None or self.high is None:
            info = np.iinfo(image.dtype) if np.issubdtype(image.dtype, np.integer) else None
            return to_8bit(image, (float(info.min), float(info.max)) if info else (0.0, 1.0))
        return to_8bit(image, (self.low, self.high))

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """:meth:`update` with ``image``, then :meth:`apply` it (``uint8`` passes unchanged)."""
        if image.dtype == np.uint8:
            return image
        self.update(image)
        self.frames += 1
        return self.apply(image)

    def describe(self) -> str:
        """The current range, for a log line."""
        if self.low is None or self.high is None:
            return "no range yet"
        return f"{self.low:.6g}..{self.high:.6g} -> 0..255 over {self.frames} frame(s)"
