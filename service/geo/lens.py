"""Lens model: intrinsics and distortion of the input camera, and the maps that undistort it.

Pure computations (arrays in, arrays out): the calibration files are read by
:mod:`photomap.io.camera_files`, the frames undistorted by :mod:`photomap.mapping.frameprep`.

Conventions
-----------
- Pixels: OpenCV (x right, y down, origin at the centre of the top-left pixel); ``K`` is the
  3x3 camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` at ``width x height`` pixels.
- ``model``: ``brown`` (OpenCV's Brown-Conrady, ``dist = (k1, k2, p1, p2[, k3[, k4, k5, k6]])``,
  ROS ``plumb_bob``/``rational_polynomial``) or ``fisheye`` (OpenCV's equidistant fisheye,
  ``dist = (k1, k2, k3, k4)``, ROS ``equidistant``).
- The undistorted frame is the ideal pinhole view with square pixels and the principal point at
  the frame centre, focal length ``fx`` (:attr:`Undistortion.fx`): the camera model the rest of
  the pipeline assumes (``camera.fx_px``, principal point at the centre).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from photomap.errors import InputError

MODELS = ("brown", "fisheye")
_ASPECT_TOL = 0.01  # relative: a calibration scales to frames of the same aspect ratio only


@dataclass(frozen=True)
class LensModel:
    """Intrinsics and distortion of a camera at ``width x height`` pixels (see the module docstring)."""

    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise InputError(f"lens model must be one of {', '.join(MODELS)}, got {self.model!r}")
        if self.width < 1 or self.height < 1:
            raise InputError(f"lens calibration size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0) or not all(math.isfinite(v) for v in (self.fx, self.fy, self.cx, self.cy)):
            raise InputError(f"lens focal lengths must be > 0 pixels, got fx={self.fx}, fy={self.fy}")
        if not all(math.isfinite(v) for v in self.dist):
            raise InputError("lens distortion coefficients must be finite numbers")
        sizes = (4,) if self.model == "fisheye" else (0, 4, 5, 8)
        if len(self.dist) not in sizes and not (self.model == "fisheye" and len(self.dist) == 0):
            raise InputError(f"a {self.model} lens takes {' or '.join(map(str, sizes))} distortion coefficients, "
                             f"got {len(self.dist)}")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def D(self) -> np.ndarray:
        n = 4 if self.model == "fisheye" else max(4, len(self.dist))
        d = np.zeros(n)
        d[:len(self.dist)] = self.dist
        return d

    @property
    def distorted(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return any(v != 0.0 for v in self.dist)

    def scaled(self, width: int, height: int) -> LensModel:
        """The same lens at frames of ``width x height`` (the sensor read out at another size).

        Pixel centres scale as ``(u + 0.5) * s - 0.5``. A frame of another aspect ratio (a crop)
        is an InputError: the calibration does not say where the crop lies."""
        if (width, height) == (self.width, self.height):
            return self
        if abs(width / height - self.width / self.height) > _ASPECT_TOL * self.width / self.height:
            raise InputError(f"the lens calibration is for {self.width}x{self.height} frames; frames of "
                             f"{width}x{height} have another aspect ratio (calibrate at this size)")
        sx, sy = width / self.width, height / self.height
        return LensModel(self.model, int(width), int(height), self.fx * sx, self.fy * sy,
                         (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5, self.dist)

    def ideal_matrix(self) -> np.ndarray:
        """K of the undistorted view: focal ``fx`` on both axes, principal point at the centre."""
        return np.array([[self.fx, 0.0, (self.width - 1) / 2.0], [0.0, self.fx, (self.height - 1) / 2.0],
                         [0.0, 0.0, 1.0]])

    def undistort_points(self, pts: np.ndarray) -> np.ndarray:
        """Pixels (n, 2) of the distorted frame -> pixels of the undistorted view (iterative inverse)."""
        src = np.ascontiguousarray(np.asarray(pts, np.float64).reshape(-1, 1, 2))
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
        if self.model == "fisheye":
            out = cv2.fisheye.undistortPoints(src, self.K, self.D, R=np.eye(3), P=self.ideal_matrix(),
                                              criteria=criteria)
        else:
            out = cv2.undistortPoints(src, self.K, self.D, R=np.eye(3), P=self.ideal_matrix(), criteria=criteria)
        return out.reshape(-1, 2)

    def distort_points(self, pts: np.ndarray) -> np.ndarray:
        """Pixels (n, 2) of the undistorted view -> pixels of the distorted frame (the forward model)."""
        ideal = self.ideal_matrix()
        p = np.asarray(pts, np.float64).reshape(-1, 2)
        xy = np.column_stack([(p[:, 0] - ideal[0, 2]) / ideal[0, 0], (p[:, 1] - ideal[1, 2]) / ideal[1, 1],
                              np.ones(len(p))])
        obj = np.ascontiguousarray(xy.reshape(-1, 1, 3))
        zero = np.zeros(3)
        if self.model == "fisheye":
            out, _ = cv2.fisheye.projectPoints(obj, zero, zero, self.K, self.D)
        else:
            out, _ = cv2.projectPoints(obj, zero, zero, self.K, self.D)
        return out.reshape(-1, 2)


@dataclass(frozen=True)
class Undistortion:
    """Maps that turn a distorted frame into its ideal pinhole view (``cv2.remap``), once per size.

    ``map1, map2``: fixed-point maps (``CV_16SC2``) of :func:`cv2.initUndistortRectifyMap`;
    ``valid``: uint8, 255 where the view pixel's source lies inside the frame (1 px inside, so
    bilinear interpolation never reads the border), else 0; ``fx``: focal length of the view.
    """

    lens: LensModel
    map1: np.ndarray
    map2: np.ndarray
    valid: np.ndarray
    fx: float

    @classmethod
    def of(cls, lens: LensModel) -> Undistortion:
        size = (lens.width, lens.height)
        ideal = lens.ideal_matrix()
        if lens.model == "fisheye":
            m1, m2 = cv2.fisheye.initUndistortRectifyMap(lens.K, lens.D, np.eye(3), ideal, size, cv2.CV_16SC2)
        else:
            m1, m2 = cv2.initUndistortRectifyMap(lens.K, lens.D, None, ideal, size, cv2.CV_16SC2)
        inside = np.zeros((lens.height, lens.width), np.uint8)
        inside[1:-1, 1:-1] = 255
        valid = cv2.remap(inside, m1, m2, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return cls(lens, m1, m2, valid, float(ideal[0, 0]))

    def apply(self, image: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
        """The undistorted view of ``image`` (its size must be the lens's)."""
        if image.shape[:2] != (self.lens.height, self.lens.width):
            raise InputError(f"frame of {image.shape[1]}x{image.shape[0]} does not match the lens model's "
                             f"{self.lens.width}x{self.lens.height}")
        return cv2.remap(image, self.map1, self.map2, interpolation, borderMode=cv2.BORDER_REPLICATE)

    def apply_mask(self, mask: np.ndarray) -> np.ndarray:
        """A validity mask of the distorted frame (non-zero = valid) in the view's pixels (255/0),
        combined with :attr:`valid`."""
        m = np.where(np.asarray(mask) != 0, np.uint8(255), np.uint8(0))
        out = cv2.remap(m, self.map1, self.map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return np.where((out == 255) & (self.valid != 0), np.uint8(255), np.uint8(0))


def folds_inside(lens: LensModel) -> bool:
    """True when a Brown lens's radial distortion ``r (1 + k1 r^2 + k2 r^4 + k3 r^6)`` stops
    growing before it reaches the frame's corners: beyond that radius the model folds back and
    has no inverse (a calibration extrapolated past what it was fitted on)."""
    if lens.model != "brown" or not lens.distorted:
        return False
    d = lens.D
    k1, k2, k3 = d[0], d[1], (d[4] if len(d) > 4 else 0.0)
    corner = max(math.hypot(max(lens.cx, lens.width - 1 - lens.cx) / lens.fx,
                            max(lens.cy, lens.height - 1 - lens.cy) / lens.fy), 1e-9)
    r = np.linspace(0.0, 4.0 * corner + 1.0, 8001)
    radial = r * (1 + k1 * r ** 2 + k2 * r ** 4 + k3 * r ** 6)
    grows = np.diff(radial) > 0
    stop = int(np.argmin(grows)) if not grows.all() else len(grows)
    return float(radial[:stop + 1].max()) < corner
