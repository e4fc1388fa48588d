"""Drift injected into the estimate, for tests and benchmarks of loop closure.

A simulated flight over good ground registers almost exactly: its estimate rarely drifts far
enough to leave the loop-candidate gate (``mapping.loop_radius`` around the *predicted*
position), the case loops found by appearance are for. :func:`injected_drift` makes it drift on
purpose: while it is active, every placement the tracker accepts (:class:`~photomap.core.tracking.Tracker`,
frame against its reference) is biased by a small rotation about the frame centre and a small
shift, so the chained poses (and the sequential edges of the pose graph) drift steadily, as a
systematic registration bias would. The images and every other registration (loop closures,
joins) are untouched: a loop measured by registration sees the truth. Nothing changes outside
the ``with`` block; the simulated frames and their truth are never altered.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from typing import Iterator

import numpy as np

from photomap.core import tracking
from photomap.geometry import to_h

__all__ = ["injected_drift"]


def _bias(shape: tuple[int, int], rotation_deg: float, shift_px: tuple[float, float]) -> np.ndarray:
    """3x3 at the working resolution: rotate by ``rotation_deg`` about the frame centre, then
    shift by ``shift_px`` (working px)."""
    h, w = shape
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    a = math.radians(rotation_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, cx - c * cx + s * cy + shift_px[0]],
                     [s, c, cy - s * cx - c * cy + shift_px[1]],
                     [0.0, 0.0, 1.0]])


@contextlib.contextmanager
def injected_drift(rotation_deg: float = 0.0, shift_px: tuple[float, float] = (0.0, 0.0)) -> Iterator[None]:
    """While active, each placement a tracker accepts is ``measured @ bias`` (the moving frame's
    pixels are first rotated by ``rotation_deg`` about its centre and shifted by ``shift_px``
    working pixels). A bias of 0.2 deg per keyframe turns a 30-keyframe circle's estimate by 6 deg."""
    original = tracking.Tracker._place

    def biased(self, ref, view, index, sample):  # type: ignore[no-untyped-def]
        match, disagreement = original(self, ref, view, index, sample)
        if not match.accepted:
            return match, disagreement
        bias = _bias(self.registrar.shape, rotation_deg, shift_px)
        return dataclasses.replace(match, matrix=(to_h(match.matrix) @ bias)[:2]), disagreement

    tracking.Tracker._place = biased  # type: ignore[method-assign]
    try:
        yield
    finally:
        tracking.Tracker._place = original  # type: ignore[method-assign]
