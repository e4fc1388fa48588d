"""The bands of a multi-band capture: which one registers, how the others align to it, 16-bit to 8-bit.

A multispectral camera (MicaSense RedEdge/Altum, DJI P4 Multispectral / Mavic 3M, Sentera) takes
each band through its own lens: the band images of one capture are offset from each other by a
few pixels and a small rotation, which varies a little with the distance to the ground. As
MicaSense's imageprocessing library and OpenDroneMap do, each band is aligned to the
registering band within the capture by a homography fitted with ECC
(``cv2.findTransformECC``, ``MOTION_HOMOGRAPHY``) on gradient-magnitude images (the bands'
brightness differs, their edges do not), coarse to fine over an image pyramid, started from the
identity or from the previous capture's homography.

Conventions: OpenCV pixel coordinates; a band homography ``H`` (3x3) maps pixels of the band's
image to pixels of the registering band's image (so ``cv2.warpPerspective(band, H, size)``
resamples the band onto the registering band's pixel grid). ECC's own warp goes the other way
(reference pixels to band pixels); the functions here return ``H``.

Pure: arrays in, arrays out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

#: Coarsest pyramid level: about this many pixels across.
_COARSE_PX = 160
#: ECC iterations at the coarsest level (halved at each finer one, at least 10: the coarse levels
#: converge from afar, the finer ones refine) and the increment of the correlation that ends a level.
_ITERATIONS = 100
_EPSILON = 1e-6
#: A fitted homography that moves a corner of the image by more than this fraction of the image's
#: larger side is taken as a failed fit (lenses of one rig are a few pixels apart).
MAX_SHIFT_FRACTION = 0.05
#: ... and so is one that scales by more than this fraction or turns by more than this many degrees
#: (the lenses of a rig have the same focal length and are mounted parallel; a band of another
#: size is resized to the reference's first).
MAX_SCALE_CHANGE = 0.02
MAX_ROTATION_DEG = 2.0
#: Images wider than this are fitted on a pyramid level of at most this size (see :func:`align_band`).
MAX_FIT_PX = 2048
#: ... and so is a fit whose ECC correlation (of the gradient images) is below this.
MIN_CORRELATION = 0.3


@dataclass(frozen=True)
class BandAlignment:
    """The fit of one band to the registering band.

    ``H``: band pixels -> registering band pixels (3x3, float64). ``correlation``: ECC's
    correlation coefficient of the gradient images at full resolution (None when ECC failed).
    ``ok``: the fit is usable; otherwise ``reason`` says why and ``H`` is the homography it
    started from.
    """

    H: np.ndarray
    correlation: float | None
    ok: bool
    reason: str | None = None


def robust_range_16bit(images: Sequence[np.ndarray], low: float = 0.5, high: float = 99.5) -> tuple[float, float]:
    """A per-flight display range ``(lo, hi)`` of one band: the ``low`` and ``high`` percentiles of
    the values of ``images`` (some captures of the flight, any dtype), sampled on a grid of about
    250,000 pixels in all. ``hi > lo`` always. The range of a flight whose frames are all known
    up front (multi-band captures); :func:`photomap.core.stretch.to_8bit` maps it to 8 bits.
    """
    values = []
    per = max(1, 250_000 // max(1, len(images)))
    for image in images:
        a = np.asarray(image)
        if a.ndim == 3:
            a = a.mean(axis=2)
        step = max(1, int(math.sqrt(a.size / per)))
        values.append(a[::step, ::step].ravel().astype(np.float64))
    if not values:
        return 0.0, 1.0
    v = np.concatenate(values)
    lo, hi = (float(x) for x in np.percentile(v, [low, high]))
    return lo, (hi if hi > lo else lo + 1.0)


def _normalised(image: np.ndarray) -> np.ndarray:
    """float32 gray ``image`` scaled to 0..1 by its own 0.5/99.5 % range (clipped)."""
    a = np.asarray(image, np.float32)
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY)
    lo, hi = robust_range_16bit([a])
    return np.clip((a - lo) / (hi - lo), 0.0, 1.0)


def _gradient(a: np.ndarray, blur: float = 1.0) -> np.ndarray:
    """``0.5 |d/dx| + 0.5 |d/dy|`` (Sobel 3x3) of a float32 image after a Gaussian blur."""
    if blur > 0:
        a = cv2.GaussianBlur(a, (0, 0), blur)
    gx = cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.addWeighted(np.abs(gx), 0.5, np.abs(gy), 0.5, 0.0)


def gradient_magnitude(image: np.ndarray) -> np.ndarray:
    """float32 gradient magnitude (``0.5 |d/dx| + 0.5 |d/dy|``, Sobel 3x3, after a Gaussian blur
    of 1 px) of ``image`` normalised to 0..1 by its own 0.5/99.5 % range: what ECC aligns."""
    return _gradient(_normalised(image))


def _gradient_pyramid(image: np.ndarray, levels: int) -> list[np.ndarray]:
    """Gradient images of ``image`` at full resolution and ``levels`` halvings: each level's
    gradient is taken on the halved image (a gradient image halved would keep only its density)."""
    a = _normalised(image)
    out = [_gradient(a)]
    for _ in range(levels):
        a = cv2.pyrDown(a)
        out.append(_gradient(a))
    return out


def texture_energy(image: np.ndarray) -> float:
    """Mean squared gradient magnitude of the normalised image: how much texture a band has to
    register with (the default registering band has the most)."""
    g = gradient_magnitude(image)
    return float(np.mean(g.astype(np.float64) ** 2))


def corner_shift_px(H: np.ndarray, size: tuple[int, int]) -> float:
    """Largest displacement (pixels) of the four corners of a ``size = (w, h)`` image under ``H``."""
    w, h = size
    corners = np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]])
    moved = cv2.perspectiveTransform(corners[None], np.asarray(H, np.float64))[0]
    return float(np.max(np.linalg.norm(moved - corners, axis=1)))


def _scaled(W: np.ndarray, factor: float) -> np.ndarray:
    """A homography between pixel grids scaled by ``factor`` (x' = factor x): ``S W S^-1``."""
    S = np.diag([factor, factor, 1.0])
    return S @ W @ np.linalg.inv(S)


def align_band(reference: np.ndarray, band: np.ndarray, *, init: np.ndarray | None = None,
               max_shift_fraction: float = MAX_SHIFT_FRACTION, min_correlation: float = MIN_CORRELATION,
               iterations: int = _ITERATIONS, max_px: int = MAX_FIT_PX) -> BandAlignment:
    """Fit the homography that maps ``band``'s pixels onto ``reference``'s (same scene, same
    instant, another lens of the rig).

    Parameters
    ----------
    reference, band : 2-D arrays (any dtype; 16-bit is fine). A band of another size is resized to
        the reference's first (the scale is part of ``H``).
    init : 3x3 band -> reference homography to start from (the previous capture's), default identity.
    max_shift_fraction, min_correlation : a fit beyond these is refused (``ok`` False).
    iterations : ECC iterations at the coarsest pyramid level (halved at each finer one, at least 10).
    max_px : the finest level fitted is the first of at most this many pixels across (a 2592-pixel
        Mavic 3M band is fitted at 1296; on the real RedEdge capture a fit at half resolution was
        up to 4 px off the full-resolution one in the blue band, so the default keeps 1280 whole).
    """
    ref = np.asarray(reference)
    h, w = ref.shape[:2]
    src = np.asarray(band)
    resize = np.eye(3)
    if src.shape[:2] != (h, w):
        resize = np.diag([w / src.shape[1], h / src.shape[0], 1.0])
        src = cv2.resize(src, (w, h), interpolation=cv2.INTER_AREA)
    start = np.eye(3) if init is None else np.asarray(init, np.float64)
    start_resized = start @ np.linalg.inv(resize)  # resized band pixels -> reference pixels
    levels = max(0, int(math.floor(math.log2(max(w, h) / _COARSE_PX))))
    pyr_ref, pyr_band = _gradient_pyramid(ref, levels), _gradient_pyramid(src, levels)
    W = _scaled(np.linalg.inv(start_resized), 0.5 ** levels)  # ECC: reference pixels -> band pixels
    cc = None
    if init is None:  # the lenses' offset first: a translation on the coarsest level (wide basin)
        try:
            T = np.eye(2, 3, dtype=np.float32)
            T[:, 2] = W[:2, 2]
            _, T = cv2.findTransformECC(pyr_ref[levels], pyr_band[levels], T, cv2.MOTION_TRANSLATION,
                                        (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, _EPSILON), None, 5)
            W[:2, 2] = T[:, 2]
        except cv2.error:
            pass  # the homography's own fit may still converge
    finest = 0  # large images are fitted at a level of at most max_px (0.1 px there is plenty)
    while max(w, h) / 2 ** finest > max_px and finest < levels:
        finest += 1
    at = levels  # the pyramid level whose pixels W maps
    for level in range(levels, finest - 1, -1):
        count = max(10, int(iterations) >> (levels - level))
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, count, _EPSILON)
        try:
            cc, Wf = cv2.findTransformECC(pyr_ref[level], pyr_band[level], W.astype(np.float32),
                                          cv2.MOTION_HOMOGRAPHY, criteria, None, 1)
        except cv2.error as exc:
            text = str(exc).strip().splitlines()  # a coarse fit that a finer level rejects is no fit either
            return BandAlignment(start, None, False, f"ECC did not converge at pyramid level {level} "
                                                     f"({text[-1][-60:] if text else 'no fit'})")
        W, at = Wf.astype(np.float64), level
        if level > finest:
            W, at = _scaled(W, 2.0), level - 1
    W = _scaled(W, 2.0 ** at)  # full resolution
    if not np.all(np.isfinite(W)) or abs(np.linalg.det(W)) < 1e-9:
        return BandAlignment(start, None, False, "ECC gave a degenerate homography")
    H = np.linalg.inv(W) @ resize
    H = H / H[2, 2]
    shift = corner_shift_px(H @ np.linalg.inv(resize), (w, h))  # on the reference's grid
    if shift > max_shift_fraction * max(w, h):
        return BandAlignment(start, float(cc), False, f"the fit moves a corner by {shift:.0f} px "
                                                      f"(more than {max_shift_fraction:.0%} of the image)")
    on_grid = H @ np.linalg.inv(resize)
    scale = math.sqrt(abs(np.linalg.det(on_grid[:2, :2])))
    turn = math.degrees(math.atan2(on_grid[1, 0] - on_grid[0, 1], on_grid[0, 0] + on_grid[1, 1]))
    if abs(scale - 1.0) > MAX_SCALE_CHANGE or abs(turn) > MAX_ROTATION_DEG:
        return BandAlignment(start, float(cc), False, f"the fit scales by {scale:.3f} and turns by {turn:.2f} deg "
                                                      "(not a lens of the same rig)")
    if cc < min_correlation:
        return BandAlignment(start, float(cc), False, f"gradient correlation {cc:.2f} below {min_correlation}")
    return BandAlignment(H, float(cc), True)


def gradient_correlation(reference: np.ndarray, band: np.ndarray, H: np.ndarray | None = None) -> float:
    """Normalised cross-correlation of the gradient images of ``reference`` and of ``band``
    resampled onto it through ``H`` (default identity), over the pixels ``band`` covers: how well
    the two are aligned (1 = the same edges in the same places)."""
    ref = np.asarray(reference)
    h, w = ref.shape[:2]
    src = np.asarray(band)
    M = np.eye(3) if H is None else np.asarray(H, np.float64)
    warped = cv2.warpPerspective(src.astype(np.float32), M, (w, h), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)
    cover = cv2.warpPerspective(np.ones(src.shape[:2], np.uint8), M, (w, h), flags=cv2.INTER_NEAREST) > 0
    cover = cv2.erode(cover.astype(np.uint8), np.ones((11, 11), np.uint8)) > 0
    a = gradient_magnitude(ref)[cover].astype(np.float64)
    b = gradient_magnitude(warped)[cover].astype(np.float64)
    if a.size < 16:
        return 0.0
    a -= a.mean()
    b -= b.mean()
    den = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / den if den > 0 else 0.0


def align_capture(images: Sequence[np.ndarray], reference: int, *,
                  init: Sequence[np.ndarray | None] | None = None) -> list[BandAlignment]:
    """Align every band of one capture to band ``reference`` (see :func:`align_band`).

    A band that does not fit the registering band directly (spectrally far apart: red and red
    edge over vegetation have different edges) is fitted to each band that did fit, nearest in
    the list first (the list is in the camera's band order, which is by wavelength or close to
    it), and the two homographies are chained. ``init``: each band's homography to start from
    (the previous capture's; None: identity). The reference's own entry is the identity.
    """
    n = len(images)
    out: list[BandAlignment | None] = [None] * n
    out[reference] = BandAlignment(np.eye(3), 1.0, True)
    starts = list(init) if init is not None else [None] * n
    for b in range(n):
        if b != reference:
            out[b] = align_band(images[reference], images[b], init=starts[b])
    for b in range(n):
        if out[b].ok:
            continue
        for k in sorted((k for k in range(n) if k not in (b, reference) and out[k].ok), key=lambda k: abs(k - b)):
            via = align_band(images[k], images[b])
            if via.ok:
                H = out[k].H @ via.H
                out[b] = BandAlignment(H / H[2, 2], via.correlation, True, f"through band {k}")
                break
    return out  # type: ignore[return-value]
