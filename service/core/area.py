"""Area-averaged (``INTER_AREA``) downscaling in O(pixels), band by band from the top.

Output pixel ``j`` of an axis of ``n`` source pixels reduced to ``n_out`` averages the source
interval ``[j * step, (j + 1) * step)``, ``step = n / n_out`` (source pixel ``i`` covers
``[i, i + 1)``): its weights are the overlaps divided by ``step``. Each output touches at most
``ceil(step) + 1`` source pixels, so the weights are banded:

- :func:`area_columns` reduces the columns of a full-width band with ``cv2.resize``
  (``INTER_AREA``); OpenCV drops partial weights under 1e-3, so the few outputs whose weights
  differ from the exact ones (measured on a probe) are recomputed from the exact weights.
- :func:`area_rows` gives the partial sums of a band of rows for the outputs it touches (bands
  side by side add up).
- :class:`AreaRows` streams bands of rows (premultiplied colour and alpha, float32) in and
  finished output rows out: memory is one band and the output rows under way.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

_PROBE_TOL = 1e-6  # an OpenCV weight this far from the exact one: that output is recomputed


def premultiplied_planes(image: np.ndarray, alpha: np.ndarray) -> list[np.ndarray]:
    """The float32 planes (colour times coverage..., coverage) that :class:`AreaRows` takes, of
    ``image`` ((h, w, C), any integer type) and its ``alpha`` (uint8 (h, w): coverage ``alpha / 255``)."""
    a = alpha.astype(np.float32) / 255
    return [np.multiply(p, a, dtype=np.float32) for p in cv2.split(image)] + [a]


def banded_weights(a: int, b: int, step: float, n_out: int) -> tuple[int, np.ndarray, np.ndarray]:
    """The exact area weights of source pixels ``[a, b)`` for the outputs that overlap them.

    Returns ``(j0, index, weight)``: the first such output, and per output ``j0 + r`` the source
    pixels ``index[r]`` (int, (outputs, K), relative to ``a``, clipped into ``[0, b - a)``) and
    their float32 weights ``weight[r]`` (overlap / step; 0 for indices outside ``[a, b)``)."""
    j0 = int(math.floor(a / step))
    j1 = min(n_out, int(math.ceil(b / step)))
    j = np.arange(j0, j1, dtype=np.float64)[:, None]
    first = np.maximum(np.floor(j * step), a)
    i = first + np.arange(int(math.ceil(step)) + 1)[None, :]
    overlap = np.minimum(i + 1, (j + 1) * step) - np.maximum(i, j * step)
    weight = (np.clip(overlap, 0, None) / step).astype(np.float32)
    weight[i >= b] = 0
    return j0, np.minimum(i - a, b - a - 1).astype(np.intp), weight


def _weighted_sum(data: np.ndarray, index: np.ndarray, weight: np.ndarray, axis: int) -> np.ndarray:
    """``sum_k weight[:, k] * data[index[:, k]]`` along ``axis`` (0 or 1) of ``data``."""
    shape = [1] * data.ndim
    shape[axis] = -1
    out = None
    for k in range(weight.shape[1]):
        if not weight[:, k].any():
            continue
        term = np.take(data, index[:, k], axis=axis)
        term *= weight[:, k].reshape(shape)
        if out is None:
            out = term
        else:
            out += term
    if out is None:
        out_shape = list(data.shape)
        out_shape[axis] = index.shape[0]
        out = np.zeros(out_shape, np.float32)
    return out


def _opencv_misses(w: int, n_out: int) -> np.ndarray:
    """Outputs whose ``cv2.resize`` ``INTER_AREA`` weights (``w`` columns to ``n_out``) differ
    from the exact ones: each of the ``K`` probe rows is 1 on the columns ``i % K == r``, so each
    output's weights come back one per row (an output touches at most ``K`` columns)."""
    _, index, weight = banded_weights(0, w, w / n_out, n_out)
    K = weight.shape[1]
    probe = (np.arange(w)[None, :] % K == np.arange(K)[:, None]).astype(np.float32)
    got = cv2.resize(probe, (n_out, K), interpolation=cv2.INTER_AREA)  # (K, n_out)
    want = np.zeros((K, n_out), np.float64)
    rows = index % K
    for k in range(K):
        np.add.at(want, (rows[:, k], np.arange(n_out)), weight[:, k])
    return np.flatnonzero(np.abs(got - want).max(axis=0) > _PROBE_TOL)


def column_fixes(w: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What :func:`area_columns` recomputes of ``w`` columns reduced to ``n_out``, the same for
    every band: the outputs OpenCV gets wrong (:func:`_opencv_misses`), their source columns and
    exact weights (rows of :func:`banded_weights`)."""
    misses = _opencv_misses(w, n_out)
    _, index, weight = banded_weights(0, w, w / n_out, n_out)
    return misses, index[misses], weight[misses]


def area_columns(band: np.ndarray, n_out: int,
                 fixes: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """The columns of ``band`` (float32 (rows, w) or (rows, w, C), C <= 4, the full width)
    area-averaged to ``n_out``: ``cv2.resize`` ``INTER_AREA``, the outputs it gets wrong
    recomputed from the exact weights (``fixes``: :func:`column_fixes` of the band's width,
    computed when None)."""
    rows, w = band.shape[:2]
    if n_out == w:
        return band.copy()
    out = cv2.resize(band, (n_out, rows), interpolation=cv2.INTER_AREA)
    if out.ndim < band.ndim:  # OpenCV drops a last axis of 1
        out = out[..., None]
    misses, index, weight = column_fixes(w, n_out) if fixes is None else fixes
    if misses.size:
        out[:, misses] = _weighted_sum(band, index, weight, axis=1)
    return out


def area_rows(data: np.ndarray, a: int, b: int, step: float, n_out: int) -> tuple[int, np.ndarray]:
    """Partial area sums of the rows of ``data`` (float32, rows ``[a, b)`` of the source) for
    the outputs they touch: ``(j0, sums (outputs, ...))`` (bands side by side add up)."""
    j0, index, weight = banded_weights(a, b, step, n_out)
    return j0, _weighted_sum(data, index, weight, axis=0)


class AreaRows:
    """Area-average a ``h`` x ``w`` image given as bands of rows to ``oh`` x ``ow``.

    ``add(y0, band)`` takes the band of source rows ``y0 ..`` as float32 (rows, w, C), or as a
    list of its ``C`` (rows, w) planes (bands in order, not overlapping; rows never given are
    0) and returns the output rows it finished, as a list of float32 (n, ow, C) blocks;
    :meth:`close` returns the rest. Stacked, the blocks are the whole ``oh`` x ``ow`` output.
    The caller premultiplies colour by alpha (:func:`premultiplied_planes`; and unpremultiplies
    the output) so that empty pixels do not darken the map's edge."""

    def __init__(self, h: int, w: int, oh: int, ow: int, channels: int) -> None:
        self.h, self.w, self.oh, self.ow, self.channels = h, w, oh, ow, channels
        self._step = h / oh
        self._start = 0  # first output row not yet returned; _acc holds rows _start ..
        self._acc = np.zeros((0, ow, channels), np.float32)
        self._fixes = column_fixes(w, ow) if ow != w else None  # the same for every band

    def _emit_to(self, j: int) -> list[np.ndarray]:
        """Return the output rows above ``j`` (finished)."""
        out = []
        if j > self._start:
            done = min(j - self._start, self._acc.shape[0])
            if done:
                out.append(self._acc[:done])
            if j - self._start > done:
                out.append(np.zeros((j - self._start - done, self.ow, self.channels), np.float32))
            self._acc = self._acc[done:]
            self._start = j
        return out

    def columns(self, band: np.ndarray | list[np.ndarray]) -> np.ndarray:
        """The band's columns reduced to ``ow`` (:func:`area_columns`): float32 (rows, ow, C)
        (planes merged first: one 4-channel resize takes two thirds of four 1-channel ones)."""
        if isinstance(band, list):
            band = cv2.merge(band)
        return area_columns(band, self.ow, self._fixes)

    def add(self, y0: int, band: np.ndarray | list[np.ndarray]) -> list[np.ndarray]:
        return self.add_columns(y0, self.columns(band))

    def add_columns(self, y0: int, cols: np.ndarray) -> list[np.ndarray]:
        """:meth:`add` of a band whose columns are reduced already (:meth:`columns`)."""
        n = cols.shape[0]
        j0 = int(math.floor(y0 / self._step))
        j1 = min(self.oh, int(math.ceil((y0 + n) / self._step)))
        out = self._emit_to(j0)
        if j1 - self._start > self._acc.shape[0]:
            grow = np.zeros((j1 - self._start - self._acc.shape[0], self.ow, self.channels), np.float32)
            self._acc = np.concatenate([self._acc, grow])
        v0, sums = area_rows(cols, y0, y0 + n, self._step, self.oh)
        self._acc[v0 - self._start:v0 - self._start + sums.shape[0]] += sums
        return out

    def close(self) -> list[np.ndarray]:
        return self._emit_to(self.oh)
