"""What the simulated camera adds between the ground and the file: lens distortion, a burned-in overlay.

- :class:`DistortedRender`: the frames of a camera with lens distortion
  (:class:`~photomap.geo.lens.LensModel`). The ideal pinhole view (the ground truth's frame) is
  rendered over a canvas large enough for the distorted frame's field of view, then each
  distorted pixel samples it where the forward model sends the ideal ray (the exact inverse of
  ``cv2.initUndistortRectifyMap``: undistorting a rendered frame gives the pinhole view back,
  to interpolation).
- :class:`Overlay`: OSD text, a crosshair and a box, fixed in the frame, in magenta
  (:data:`OVERLAY_BGR`), drawn over the finished frame (after the lens and the sensor effects, as
  a camera's OSD chip does); :meth:`Overlay.mask` marks its pixels black (with a margin for
  compression ringing), the file ``photomap replay --mask`` takes.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from photomap.errors import InputError
from photomap.geo.lens import LensModel, folds_inside

OVERLAY_BGR = (255, 0, 255)  # magenta: a colour the terrains do not have
_MASK_MARGIN_PX = 4


class DistortedRender:
    """Maps from the distorted frame to a canvas of the ideal view (see the module docstring)."""

    def __init__(self, lens: LensModel) -> None:
        if folds_inside(lens):
            raise InputError("the lens distortion folds back inside the frame (the radial model stops growing "
                             "before the corners): use a smaller |k1|, a k2 or a narrower field of view")
        w, h = lens.width, lens.height
        xx, yy = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        ideal = lens.undistort_points(np.column_stack([xx.ravel(), yy.ravel()]))
        if not np.all(np.isfinite(ideal)):
            raise InputError("the lens distortion has no inverse over the frame")
        x0 = int(math.floor(ideal[:, 0].min())) - 2
        y0 = int(math.floor(ideal[:, 1].min())) - 2
        x1 = int(math.ceil(ideal[:, 0].max())) + 3
        y1 = int(math.ceil(ideal[:, 1].max())) + 3
        self.lens = lens
        self.offset = (x0, y0)  # canvas pixel (0, 0) is ideal-view pixel (x0, y0)
        self.canvas = (x1 - x0, y1 - y0)  # (w, h)
        self.map_x = (ideal[:, 0] - x0).reshape(h, w).astype(np.float32)
        self.map_y = (ideal[:, 1] - y0).reshape(h, w).astype(np.float32)

    def canvas_homography(self, h_frame: np.ndarray) -> np.ndarray:
        """The 3x3 canvas pixels -> terrain pixels of a frame whose ideal view maps by ``h_frame``."""
        x0, y0 = self.offset
        return h_frame @ np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])

    def distort(self, canvas_view: np.ndarray) -> np.ndarray:
        """The distorted frame from the rendered canvas (bicubic, like the ideal view)."""
        return cv2.remap(canvas_view, self.map_x, self.map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


class Overlay:
    """A burned-in OSD fixed in frames of ``width x height`` (see the module docstring)."""

    def __init__(self, width: int, height: int) -> None:
        self.size = (width, height)
        s = min(width, height)
        self._font_scale = max(0.35, s / 600.0)
        self._thick = max(1, int(round(s / 240.0)))

    def _draw(self, img: np.ndarray, colour) -> None:
        w, h = self.size
        t = self._thick
        cx, cy, arm = w // 2, h // 2, max(6, min(w, h) // 12)
        cv2.line(img, (cx - arm, cy), (cx + arm, cy), colour, t)  # crosshair
        cv2.line(img, (cx, cy - arm), (cx, cy + arm), colour, t)
        bw, bh = max(12, w // 6), max(8, h // 10)  # a box in the lower right corner (a battery gauge)
        cv2.rectangle(img, (w - bw - w // 20, h - bh - h // 20), (w - w // 20, h - h // 20), colour, t)
        for k, text in enumerate(("ALT 052.3M  SPD 08.1", "REC 00:12:34  SAT 14")):
            org = (w // 30, h // 14 + k * int(30 * self._font_scale + 6))
            cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, self._font_scale, colour, t,
                        cv2.LINE_AA)

    def draw(self, frame: np.ndarray) -> np.ndarray:
        """``frame`` (uint8 BGR) with the overlay burned in (in place; returned)."""
        self._draw(frame, OVERLAY_BGR)
        return frame

    def mask(self) -> np.ndarray:
        """uint8 (h, w): 0 on the overlay (and a margin around it), 255 elsewhere."""
        w, h = self.size
        m = np.zeros((h, w), np.uint8)
        self._draw(m, 255)
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * _MASK_MARGIN_PX + 1,) * 2))
        return np.where(m > 0, np.uint8(0), np.uint8(255))
