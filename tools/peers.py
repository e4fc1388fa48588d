"""Peer registration methods wrapped for the registration benchmark (``tools/bench_registration.py``).

Every method registers a new grey frame ``b`` to a reference ``a`` and returns the 2x3 matrix that
maps pixels of ``b`` to pixels of ``a`` (OpenCV pixel coordinates, :mod:`photomap.geometry`), or ``None``
when it finds nothing. Each is split as a user would run it on a video: :meth:`prepare` does the
per-frame work that can be reused for the next pair (feature detection), :meth:`register` the
per-pair work. Methods that cannot reuse anything (imreg_dft, ECC) do everything in
:meth:`register`.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import cv2
import numpy as np

log = logging.getLogger(__name__)

__all__ = ["Method", "ImregDft", "Features", "Ecc", "peer_methods", "to_similarity"]


class Method:
    """Interface of a benchmarked method (frame shape fixed at construction)."""

    name = "method"

    def prepare(self, gray: np.ndarray) -> Any:
        """Per-frame work on a uint8 grey frame, reused by every pair the frame is in."""
        return gray

    def register(self, ref: Any, new: Any) -> tuple[np.ndarray | None, float | None]:
        """Return ``(matrix new -> ref or None, confidence or None)``."""
        raise NotImplementedError


def to_similarity(m: np.ndarray, center: tuple[float, float]) -> np.ndarray:
    """Closest similarity to the 2x3 affine ``m`` that maps ``center`` to the same point.

    The linear part ``[[a, -b], [b, a]]`` takes ``a``, ``b`` as the means of the matching
    entries of ``m`` (the Frobenius-nearest similarity).
    """
    a = 0.5 * (m[0, 0] + m[1, 1])
    b = 0.5 * (m[1, 0] - m[0, 1])
    lin = np.array([[a, -b], [b, a]])
    c = np.asarray(center, float)
    t = m[:, :2] @ c + m[:, 2] - lin @ c
    return np.c_[lin, t]


class ImregDft(Method):
    """``imreg_dft.similarity`` (Fourier-Mellin in Python, Tomas Krejci), as documented.

    numpy 2 / scipy 1.17 workaround: imreg_dft 2.0.0 imports ``scipy.ndimage.interpolation``,
    a namespace deprecated since scipy 1.8 that warns on every call (and is to be removed in
    scipy 2). Its ``ndii`` alias is pointed at ``scipy.ndimage``; nothing else was needed.

    Result convention (checked on exact pairs): ``transform_img(b, scale, angle, tvec) == a`` with
    ``angle`` in degrees counter-clockwise on screen (the opposite of OpenCV's sign) and
    ``tvec = (ty, tx)``, rotation and scale about the image centre. So the matrix b -> a is the
    similarity with angle ``-angle``, scale ``scale`` and shift ``(tx, ty)`` about the centre.
    """

    name = "imreg_dft"

    def __init__(self, shape: tuple[int, int]) -> None:
        import scipy.ndimage
        import imreg_dft
        import imreg_dft.imreg

        imreg_dft.imreg.ndii = scipy.ndimage
        self._similarity = imreg_dft.similarity
        h, w = shape
        self.center = ((w - 1) / 2.0, (h - 1) / 2.0)

    def prepare(self, gray: np.ndarray) -> np.ndarray:
        return gray.astype(np.float64)

    def register(self, ref: np.ndarray, new: np.ndarray) -> tuple[np.ndarray | None, float | None]:
        try:
            r = self._similarity(ref, new)
        except (ValueError, IndexError, FloatingPointError) as exc:
            log.debug("imreg_dft failed: %s", exc)
            return None, None
        angle = math.radians(-float(r["angle"]))
        s = float(r["scale"])
        lin = s * np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
        c = np.asarray(self.center)
        t = c + np.array([float(r["tvec"][1]), float(r["tvec"][0])]) - lin @ c
        return np.c_[lin, t], float(r["success"])


class Features(Method):
    """Keypoints + descriptors, brute-force matching, ``cv2.estimateAffinePartial2D`` (RANSAC).

    ``kind``: ``"orb"`` (1000 features, Hamming, cross-check), ``"sift"`` (OpenCV defaults, L2,
    Lowe ratio 0.75) or ``"akaze"`` (only where ``cv2.AKAZE_create`` exists; Hamming, ratio 0.8).
    Keypoints are detected once per frame (:meth:`prepare`). The RANSAC reprojection threshold is
    3 px (OpenCV's default), with OpenCV's default Levenberg-Marquardt refinement of the inliers.
    Confidence: the inlier ratio.
    """

    def __init__(self, kind: str) -> None:
        self.name = f"{kind.upper()}+RANSAC"
        if kind == "orb":
            self.detector = cv2.ORB_create(nfeatures=1000)
            self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
            self.ratio = None
        elif kind == "sift":
            self.detector = cv2.SIFT_create()
            self.matcher = cv2.BFMatcher(cv2.NORM_L2)
            self.ratio = 0.75
        elif kind == "akaze":
            self.detector = cv2.AKAZE_create()
            self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
            self.ratio = 0.8
        else:
            raise ValueError(f"unknown feature kind {kind!r}")

    def prepare(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        kps, desc = self.detector.detectAndCompute(gray, None)
        pts = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        return pts, desc

    def register(self, ref: tuple, new: tuple) -> tuple[np.ndarray | None, float | None]:
        (pts_a, desc_a), (pts_b, desc_b) = ref, new
        if desc_a is None or desc_b is None or len(pts_a) < 3 or len(pts_b) < 3:
            return None, None
        if self.ratio is None:
            pairs = [(m.queryIdx, m.trainIdx) for m in self.matcher.match(desc_b, desc_a)]
        else:
            pairs = [(m[0].queryIdx, m[0].trainIdx) for m in self.matcher.knnMatch(desc_b, desc_a, k=2)
                     if len(m) == 2 and m[0].distance < self.ratio * m[1].distance]
        if len(pairs) < 3:
            return None, None
        ib, ia = np.array(pairs).T
        m, inliers = cv2.estimateAffinePartial2D(pts_b[ib], pts_a[ia], method=cv2.RANSAC,
                                                 ransacReprojThreshold=3.0)
        if m is None:
            return None, None
        return m.astype(np.float64), float(inliers.sum()) / len(pairs)


class Ecc(Method):
    """OpenCV's ECC (``cv2.findTransformECC``, MOTION_AFFINE) on a Gaussian pyramid, from identity.

    Levels are halved (``cv2.pyrDown``) down to a shorter side of >= 64 px; each level runs at
    most 50 iterations (epsilon 1e-5) from the finer-scaled result of the coarser one, with
    OpenCV's default 5x5 Gaussian pre-filter. ECC's warp maps template (``a``) pixels to input
    (``b``) pixels; its inverse, projected to the nearest similarity about the frame centre, is
    the result. Confidence: the final correlation coefficient. Non-convergence gives ``None``.
    """

    name = "ECC (pyramid)"

    def __init__(self, shape: tuple[int, int], min_side: int = 64) -> None:
        h, w = shape
        self.center = ((w - 1) / 2.0, (h - 1) / 2.0)
        self.levels = max(0, int(math.floor(math.log2(min(h, w) / min_side))))
        self.criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-5)

    def _pyramid(self, gray: np.ndarray) -> list[np.ndarray]:
        levels = [gray.astype(np.float32)]
        for _ in range(self.levels):
            levels.append(cv2.pyrDown(levels[-1]))
        return levels

    def register(self, ref: np.ndarray, new: np.ndarray) -> tuple[np.ndarray | None, float | None]:
        pa, pb = self._pyramid(ref), self._pyramid(new)
        warp = np.eye(2, 3, dtype=np.float32)
        cc = 0.0
        for level in range(self.levels, -1, -1):
            try:
                cc, warp = cv2.findTransformECC(pa[level], pb[level], warp, cv2.MOTION_AFFINE,
                                                self.criteria, None, 5)
            except cv2.error as exc:
                log.debug("ECC did not converge at level %d: %s", level, exc)
                return None, None
            if level:
                warp[:, 2] *= 2.0  # pyrDown: coarse pixel x sits at fine pixel 2x
        w3 = np.vstack([warp.astype(np.float64), [0.0, 0.0, 1.0]])
        try:
            m = np.linalg.inv(w3)[:2]
        except np.linalg.LinAlgError:
            return None, None
        return to_similarity(m, self.center), float(cc)


def peer_methods(shape: tuple[int, int]) -> list[Method]:
    """All peers available on this machine for frames of ``shape`` (AKAZE only if OpenCV has it)."""
    methods: list[Method] = [ImregDft(shape), Features("orb"), Features("sift")]
    if hasattr(cv2, "AKAZE_create"):
        methods.append(Features("akaze"))
    methods.append(Ecc(shape))
    return methods
