"""Lens calibration from views of a checkerboard (OpenCV): corners, view selection, the fit.

Pure computations: images in, a :class:`~photomap.geo.lens.LensModel` and its RMS reprojection
error out (``photomap calibrate`` reads the frames and writes the file).

``board = (cols, rows)`` counts the board's *inner* corners (where four squares meet), as
``cv2.findChessboardCorners`` takes them; ``square`` is a square's side (metres; it sets the
board's scale only, the lens model does not depend on it).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from photomap.errors import InputError
from photomap.geo.lens import LensModel

MIN_VIEWS = 5
_FIND_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
_SUBPIX = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3)


@dataclass(frozen=True)
class Calibration:
    """The fitted lens, its RMS reprojection error (pixels) and the number of views used."""

    lens: LensModel
    rms_px: float
    views: int


def parse_board(text: str) -> tuple[int, int]:
    """``"COLSxROWS"`` (inner corners) -> ``(cols, rows)``."""
    try:
        cols, rows = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise InputError(f"board must be COLSxROWS inner corners, e.g. 9x6; got {text!r}") from None
    if cols < 3 or rows < 3:
        raise InputError(f"board must have at least 3x3 inner corners; got {text!r}")
    return cols, rows


def find_corners(image: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners (n, 2) of the board in ``image`` (grey or BGR), or None.

    Found on a copy at most 1280 px wide (fast on video frames), then refined at full size."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if gray.dtype != np.uint8:
        gray = cv2.normalize(gray, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    f = min(1.0, 1280.0 / max(gray.shape))
    small = cv2.resize(gray, None, fx=f, fy=f, interpolation=cv2.INTER_AREA) if f < 1 else gray
    found, corners = cv2.findChessboardCorners(small, board, flags=_FIND_FLAGS)
    if not found or corners is None:
        return None
    corners = ((corners.reshape(-1, 2) + 0.5) / f - 0.5).astype(np.float32).reshape(-1, 1, 2)
    win = max(3, int(round(0.4 * _corner_spacing(corners))))
    cv2.cornerSubPix(gray, corners, (min(win, 11), min(win, 11)), (-1, -1), _SUBPIX)
    return corners.reshape(-1, 2)


def _corner_spacing(corners: np.ndarray) -> float:
    pts = corners.reshape(-1, 2)
    return float(np.median(np.hypot(*np.diff(pts, axis=0).T)))


def distinct(views: list[np.ndarray], min_move: float) -> list[int]:
    """Indices of ``views`` (corner arrays) kept in order: each moved its corners by a mean of
    ``min_move`` pixels from the last one kept (a board held still gives one view, not 300)."""
    kept: list[int] = []
    for i, c in enumerate(views):
        if not kept or float(np.mean(np.hypot(*(c - views[kept[-1]]).T))) >= min_move:
            kept.append(i)
    return kept


def board_points(board: tuple[int, int], square: float) -> np.ndarray:
    """The board's inner corners on its plane (n, 3), in ``findChessboardCorners`` order."""
    cols, rows = board
    grid = np.zeros((rows * cols, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * float(square)
    return grid


def _fisheye_flag(name: str) -> int:
    """A fisheye calibration flag: in ``cv2.fisheye`` up to OpenCV 4, in ``cv2`` (other values) from 5."""
    value = getattr(cv2.fisheye, name, None)
    return int(value if value is not None else getattr(cv2, name))


def calibrate(views: list[np.ndarray], board: tuple[int, int], square: float, size: tuple[int, int],
              model: str = "brown") -> Calibration:
    """Fit a ``model`` lens (``brown``: k1 k2 p1 p2 k3; ``fisheye``: k1..k4) to the corner
    ``views`` of frames of ``size = (w, h)``."""
    if len(views) < MIN_VIEWS:
        raise InputError(f"the board was found in {len(views)} distinct view(s); at least {MIN_VIEWS} are needed "
                         f"(check --board: inner corners, COLSxROWS)")
    obj = board_points(board, square)
    w, h = size
    if model == "fisheye":
        flags = _fisheye_flag("CALIB_RECOMPUTE_EXTRINSIC") | _fisheye_flag("CALIB_FIX_SKEW")
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-7)
        try:
            rms, k, d, _, _ = cv2.fisheye.calibrate([obj.reshape(1, -1, 3).astype(np.float64) for _ in views],
                                                    [v.reshape(1, -1, 2).astype(np.float64) for v in views],
                                                    (w, h), np.eye(3), np.zeros(4), flags=flags, criteria=criteria)
        except cv2.error as exc:
            raise InputError(f"the fisheye calibration did not converge ({exc.err}): use more, sharper views") from None
    else:
        try:
            rms, k, d, _, _ = cv2.calibrateCamera([obj] * len(views), [v.reshape(-1, 1, 2) for v in views],
                                                  (w, h), None, None)
        except cv2.error as exc:
            raise InputError(f"the calibration failed ({exc.err}): use more views, from other angles") from None
    if not (np.isfinite(rms) and np.all(np.isfinite(k)) and np.all(np.isfinite(d))):
        raise InputError("the calibration did not converge: use more views, from other angles")
    d = np.asarray(d, float).ravel()
    lens = LensModel(model, int(w), int(h), float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                     tuple(float(v) for v in d[:4 if model == "fisheye" else 5]))
    return Calibration(lens, float(rms), len(views))
