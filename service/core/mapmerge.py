"""Registering photo maps to each other: the pure pieces (arrays in, arrays out).

Two maps of the same ground (two flights, two drones) differ by a similarity: each map's frame is
its own first frame's. :mod:`photomap.mapping.merge` finds it coarse to fine with iFMI
(:class:`photomap.core.ifmi.Registrar`, which takes any two arrays of one shape): whole-map
overviews on a canvas, then patches at higher resolutions, fitted robustly. Maps are sparse (a
flight's coverage is a thin band) and their empty pixels must not speak: :func:`canvas_gray`
fills them with the covered mean and fades the covered content into it near the edge, so the
map's outline adds no edges of its own to the spectra.

Conventions: OpenCV pixel centres; 3x3 matrices map the *moving* map's pixels to the
*reference* map's pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

from photomap.geometry import pose_angle_deg, pose_scale, similarity_fit


def canvas_gray(image: np.ndarray, alpha: np.ndarray, fade_px: float = 4.0) -> np.ndarray:
    """float32 grey of a map render whose empty pixels carry no structure.

    ``image`` uint8 (H, W[, 3]) BGR or grey, ``alpha`` uint8 (H, W) (255 covered). Covered pixels
    keep their grey value; toward empty ones the deviation from the covered mean fades to 0 over
    about ``fade_px`` pixels (a Gaussian-blurred, eroded coverage); empty pixels are the mean.
    """
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    gray = gray.astype(np.float32)
    cover = (alpha >= 128).astype(np.float32)
    n = float(cover.sum())
    if n == 0:
        return np.zeros(gray.shape, np.float32)
    mean = float((gray * cover).sum() / n)
    if fade_px > 0:
        k = max(1, int(round(fade_px)))
        inner = cv2.erode(cover, np.ones((2 * k + 1, 2 * k + 1), np.uint8), borderType=cv2.BORDER_CONSTANT,
                          borderValue=0)
        weight = cv2.GaussianBlur(inner, (0, 0), fade_px / 2.0) * cover
    else:
        weight = cover
    return (mean + (gray - mean) * weight).astype(np.float32)


def place_on_canvas(gray: np.ndarray, size: int) -> tuple[np.ndarray, tuple[int, int]]:
    """``gray`` centred on a ``size`` x ``size`` canvas filled with the corner-free mean (its
    median); returns the canvas and the offset (canvas px = image px + offset). The image must fit."""
    h, w = gray.shape
    if h > size or w > size:
        raise ValueError(f"a {w}x{h} image does not fit a {size} px canvas")
    canvas = np.full((size, size), float(np.median(gray)) if gray.size else 0.0, np.float32)
    ox, oy = (size - w) // 2, (size - h) // 2
    canvas[oy:oy + h, ox:ox + w] = gray
    return canvas, (ox, oy)


def spread_points(mask: np.ndarray, margin: float, count: int, spacing: float | None = None
                  ) -> list[tuple[float, float]]:
    """Up to ``count`` points (x, y) inside ``mask`` (non-zero) at least ``margin`` pixels from its
    edge, greedily the farthest from the edge and from each other (at least ``spacing`` apart,
    default ``2 * margin``)."""
    m = (np.asarray(mask) > 0).astype(np.uint8)
    if not m.any():
        return []
    dist = cv2.distanceTransform(np.pad(m, 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    spacing = 2.0 * margin if spacing is None else spacing
    points: list[tuple[float, float]] = []
    score = dist.copy()
    score[dist < margin] = 0
    yy, xx = np.mgrid[0:m.shape[0], 0:m.shape[1]]
    while len(points) < count:
        i = int(np.argmax(score))
        y, x = divmod(i, m.shape[1])
        if score[y, x] <= 0:
            break
        points.append((float(x), float(y)))
        score[(xx - x) ** 2 + (yy - y) ** 2 < spacing ** 2] = 0
    return points


def robust_similarity(src: np.ndarray, dst: np.ndarray, tol: float, *, min_inliers: int = 3,
                      weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """3x3 similarity ``dst ~ S src`` from point pairs (n, 2), dropping pairs more than ``tol``
    from the fit (the worst one at a time, then refitting). Returns ``(S, inlier mask)``, or
    None when fewer than ``min_inliers`` pairs agree (two points always fit: never trust them).

    Every pair is also tried as a seed of a pure translation consensus first, so that a
    majority of agreeing pairs wins over a minority of wild ones.
    """
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    n = len(src)
    if n < max(2, min_inliers):
        return None
    # consensus seed: the largest set of pairs moved alike (by translation, within tol * 4)
    shift = dst - src
    best = np.zeros(n, bool)
    for i in range(n):
        agree = np.hypot(*(shift - shift[i]).T) <= 4.0 * tol + 0.02 * np.hypot(*(src - src[i]).T)
        if agree.sum() > best.sum():
            best = agree
    keep = best if best.sum() >= 2 else np.ones(n, bool)
    fit = None
    for _ in range(n):
        if keep.sum() < 2:
            return None
        fit = similarity_fit(src[keep], dst[keep])
        res = np.hypot(*((src @ fit[:, :2].T + fit[:, 2]) - dst).T)
        grown = res <= tol
        if (grown == keep).all():
            break
        worst = int(np.argmax(np.where(keep, res, -1)))
        if res[worst] > tol:
            keep = keep.copy()
            keep[worst] = False
        else:
            keep = grown
    if fit is None or keep.sum() < min_inliers:
        return None
    return np.vstack([fit, [0.0, 0.0, 1.0]]), keep


def similarity_params(S: np.ndarray) -> tuple[float, float]:
    """(angle_deg, scale) of a 2x3/3x3 similarity."""
    S = np.asarray(S, float)
    return pose_angle_deg(S), pose_scale(S)
