"""Pose and pixel conventions shared by every layer (docs/architecture.md, "Conventions").

- Pixel coordinates are OpenCV's: x right, y down, origin at the centre of the top-left pixel;
  the centre of a ``w`` x ``h`` frame is ``((w - 1) / 2, (h - 1) / 2)``.
- A pose ``M`` (2x3 affine, or its 3x3 homogeneous form) maps **frame pixels to map pixels**;
  a pairwise registration maps pixels of the new frame to pixels of the reference frame.
- ``angle_deg = degrees(atan2(M[1,0], M[0,0]))`` (with y down, a positive angle turns clockwise on
  screen), ``scale = sqrt(|det(M[:, :2])|)``.
- A frame resized by ``f`` (``cv2.resize``) has pixel ``x_small = f * (x + 0.5) - 0.5``.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

__all__ = ["to_h", "apply_h", "local_linear", "angle_scale", "pose_angle_deg", "pose_scale",
           "frame_centre", "wrap_deg", "similarity_fit", "umeyama", "similarity_matrix", "scaling"]


def to_h(M: np.ndarray) -> np.ndarray:
    """A 2x3 affine (or a 3x3 matrix) as a 3x3 homogeneous matrix (stacked: ``(..., 3, 3)``)."""
    M = np.asarray(M, dtype=float)
    if M.shape[-2:] == (3, 3):
        return M
    bottom = np.broadcast_to(np.array([0.0, 0.0, 1.0]), M.shape[:-2] + (1, 3))
    return np.concatenate([M, bottom], axis=-2)


def apply_h(H: np.ndarray, point: Sequence[float]) -> np.ndarray:
    """Map one pixel ``(x, y)`` through a 3x3 (or 2x3) matrix, or a stack of them: ``(..., 2)``."""
    H = to_h(H)
    p = H @ np.array([point[0], point[1], 1.0])
    return p[..., :2] / p[..., 2:3]


def local_linear(H: np.ndarray, point: Sequence[float]) -> np.ndarray:
    """Jacobian (2x2) of the pixel map of ``H`` at ``point``; the linear part for an affine."""
    H = to_h(H)
    x, y = float(point[0]), float(point[1])
    u, v, w = H @ np.array([x, y, 1.0])
    return (H[:2, :2] - np.outer([u / w, v / w], H[2, :2])) / w


def angle_scale(H: np.ndarray, point: Sequence[float]) -> tuple[float, float]:
    """Rotation (deg) and scale of ``H`` at ``point``.

    The angle is that of the nearest rotation to the local linear map ``J``,
    ``atan2(J10 - J01, J00 + J11)``, which equals DESIGN's ``atan2(M[1,0], M[0,0])`` for a
    similarity; the scale is ``sqrt(|det J|)``.
    """
    J = local_linear(H, point)
    angle = math.degrees(math.atan2(J[1, 0] - J[0, 1], J[0, 0] + J[1, 1]))
    return angle, pose_scale(J)


def pose_angle_deg(M: np.ndarray) -> float:
    """DESIGN's pose angle: ``degrees(atan2(M[1,0], M[0,0]))``."""
    return math.degrees(math.atan2(M[1, 0], M[0, 0]))


def pose_scale(M: np.ndarray) -> float:
    """DESIGN's pose scale: ``sqrt(det(M[:, :2]))`` (of ``|det|``, so a mirror does not fail).

    The 2x2 determinant written out: ``np.linalg.det`` (LAPACK) took 3 us a call, a sixth of
    writing a trajectory row, and reserved OpenBLAS's 32 MB buffer in each thread calling it."""
    m = np.asarray(M, dtype=float)
    return math.sqrt(abs(float(m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0])))


def frame_centre(width: int, height: int) -> tuple[float, float]:
    """Pixel coordinates of a ``width`` x ``height`` frame's centre: ``((w-1)/2, (h-1)/2)``."""
    return (width - 1) / 2.0, (height - 1) / 2.0


def wrap_deg(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles (deg) to [-180, 180)."""
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def similarity_fit(src: np.ndarray, dst: np.ndarray, *, scale: float | None = None,
                   angle_deg: float | None = None) -> np.ndarray:
    """Least-squares 2D similarity ``dst ~ c R src + t`` (Umeyama 1991, no reflection), 2x3.

    ``scale`` fixes ``c``, ``angle_deg`` fixes the rotation (OpenCV sense); both are fitted
    otherwise. Needs two distinct points when anything is free.
    """
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    if angle_deg is None:
        cov = b.T @ a / len(src)
        u, d, vt = np.linalg.svd(cov)
        s = np.diag([1.0, math.copysign(1.0, np.linalg.det(u) * np.linalg.det(vt))])
        rot = u @ s @ vt
    else:
        r = math.radians(angle_deg)
        rot = np.array([[math.cos(r), -math.sin(r)], [math.sin(r), math.cos(r)]])
    if scale is None:
        var = (a ** 2).sum() / len(src)
        scale = float(np.einsum("ij,ij->", b, a @ rot.T) / len(src) / var) if var > 0 else 1.0
    lin = scale * rot
    return np.hstack([lin, (md - lin @ ms)[:, None]])


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True
            ) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~ s * R @ src + t`` of two (N, 2) point sets (Umeyama 1991).

    Returns ``(s, R, t)``; R is a proper rotation (no reflection); ``with_scale=False`` fixes s = 1.
    """
    m = similarity_fit(src, dst, scale=None if with_scale else 1.0)
    s = pose_scale(m)
    return s, m[:, :2] / s, m[:, 2].copy()


def similarity_matrix(angle_deg: float, scale: float, shift: tuple[float, float] = (0.0, 0.0),
                      center: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """2x3 similarity ``p -> scale * R(angle) (p - center) + center + shift`` (OpenCV pixels).

    With ``center=(0, 0)`` the last column is ``shift``; ``R(angle)`` is ``[[c, -s], [s, c]]``,
    which with y pointing down turns clockwise on screen for a positive angle.
    """
    a = math.radians(angle_deg)
    c, s = scale * math.cos(a), scale * math.sin(a)
    cx, cy = float(center[0]), float(center[1])
    return np.array([[c, -s, cx + float(shift[0]) - (c * cx - s * cy)],
                     [s, c, cy + float(shift[1]) - (s * cx + c * cy)]])


def scaling(f: float) -> np.ndarray:
    """3x3 matrix mapping input pixels to pixels of the image resized by ``f`` (cv2.resize)."""
    o = f / 2.0 - 0.5
    return np.array([[f, 0.0, o], [0.0, f, o], [0.0, 0.0, 1.0]])
