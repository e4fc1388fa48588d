"""Feature registration (ORB/SIFT + RANSAC) and a photometric check of a placement.

iFMI (:mod:`photomap.core.ifmi`) is the fast first path. On real stills with large rotation,
scale change and little overlap its confidence is often low; this module gives a second opinion
and a way to tell a right placement from a wrong one:

- :class:`FeatureMatcher` detects keypoints once per frame (:meth:`FeatureMatcher.prepare`, like
  :meth:`~photomap.core.ifmi.Registrar.prepare`) and registers two prepared frames with
  ratio-tested nearest-neighbour matches and ``cv2.estimateAffinePartial2D`` (RANSAC, 4-DoF
  similarity); an optional :class:`~photomap.core.ifmi.Prior` filters the matches by keypoint
  orientation and size and rejects a result outside it. :func:`register_features` is the
  one-call form.
- :func:`verify_overlap` warps the moving frame onto the reference with a candidate matrix and
  cross-correlates the gradients of the overlap for every relative offset (masked, normalised):
  a right placement has its own correlation peak at zero offset (within a tolerance for what a
  similarity cannot model) and no rival peak elsewhere that is nearly as high. Exposure and
  vignetting do not matter (normalised gradients); a placement a few percent of the frame off,
  one period off on periodic ground, or on unrelated ground fails.
- :func:`ifmi_confirmed` / :func:`features_confirmed` apply the thresholds,
  :func:`needs_second_opinion` says when to run the features after iFMI, :func:`decide` which
  result to keep, or that none is right (the frame must then not be glued).

Thresholds (module constants below) come from ``tools/bench_pairs.py`` (real seneca and brighton stills
against GPS, simulated pairs with exact truth, wrong pairs); see ``docs/benchmarks.md``.

Conventions (:mod:`photomap.geometry`): OpenCV pixel coordinates (x right, y down, origin at the centre
of the top-left pixel). A matrix is 2x3 and maps pixels of the *moving* frame to pixels of the
*reference*: ``p_ref = matrix @ [x_mov, y_mov, 1]``, as ``photomap.core.ifmi.Registration.matrix``.
Feature results are in pixels of the frames given to :meth:`FeatureMatcher.prepare` (which may
detect on a downscaled copy); :func:`rescale_matrix` converts a matrix to the pixels of resized
frames. Pure: arrays in, arrays out; no I/O, logging or configuration.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from photomap.core.ifmi import Prior, Registration, to_gray
from photomap.geometry import pose_angle_deg, pose_scale, scaling

__all__ = ["KINDS", "FeatureFrame", "FeatureRegistration", "FeatureMatcher", "register_features",
           "OverlapCheck", "verify_overlap", "Decision", "ifmi_confirmed", "features_confirmed",
           "needs_second_opinion", "decide", "rescale_matrix"]

KINDS = ("orb", "sift")

# Keypoint orientation and size are noisy (SIFT: 99 % of inliers within 10 deg and 7 % in size;
# ORB sizes step by its pyramid factor 1.2): a prior filters matches with this much slack.
_ANGLE_SLACK_DEG = 15.0
_LOG_SIZE_SLACK = 0.3


def _wrap180(angle: np.ndarray | float) -> np.ndarray | float:
    return (np.asarray(angle) + 180.0) % 360.0 - 180.0


def rescale_matrix(matrix: np.ndarray, factor: float) -> np.ndarray:
    """A 2x3 matrix between frames, re-expressed for both frames resized by ``factor``.

    ``matrix`` maps moving pixels to reference pixels at one resolution; the result does the same
    for the frames resized by ``factor`` (``cv2.resize``, OpenCV pixel centres:
    ``x_small = factor * (x + 0.5) - 0.5``).
    """
    s = scaling(factor)
    m3 = np.vstack([np.asarray(matrix, np.float64), [0.0, 0.0, 1.0]])
    return (s @ m3 @ np.linalg.inv(s))[:2]


def _params(m: np.ndarray) -> tuple[float, float]:
    """(angle_deg, scale) of a 2x3 similarity."""
    return pose_angle_deg(m), pose_scale(m)


def _gray(frame: np.ndarray) -> np.ndarray:
    img = to_gray(frame)
    if img.ndim != 2 or min(img.shape) < 16:
        raise ValueError(f"need a grey or BGR frame of at least 16x16 px, got shape {np.shape(frame)}")
    return img


def _to_uint8(gray: np.ndarray) -> np.ndarray:
    if gray.dtype == np.uint8:
        return gray
    lo, hi = float(np.min(gray)), float(np.max(gray))
    if gray.dtype != np.uint8 and 0.0 <= lo and hi <= 255.0 and hi > 1.0:
        return np.clip(gray, 0, 255).astype(np.uint8)
    span = max(hi - lo, 1e-12)
    return ((gray.astype(np.float32) - lo) * (255.0 / span)).astype(np.uint8)


def _resize(img: np.ndarray, longest: int) -> tuple[np.ndarray, float]:
    """``img`` downscaled (INTER_AREA) so that its longer side is at most ``longest`` (0: as is)."""
    h, w = img.shape[:2]
    if longest <= 0 or max(h, w) <= longest:
        return img, 1.0
    f = longest / max(h, w)
    size = (max(1, int(round(w * f))), max(1, int(round(h * f))))
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA), size[0] / w


# --------------------------------------------------------------------------- features

@dataclass(frozen=True, eq=False)
class FeatureFrame:
    """One frame's keypoints and descriptors (see :meth:`FeatureMatcher.prepare`).

    ``points`` (N x 2, float32) are in pixels of the frame given to ``prepare`` (not of the
    downscaled copy they were detected on); ``angles`` are OpenCV keypoint orientations (degrees,
    clockwise on screen, the sense of a positive matrix angle); ``sizes`` are keypoint diameters
    in the same pixels; ``factor`` is the detection resolution over the frame's.
    """

    kind: str
    shape: tuple[int, int]  # (h, w) of the frame given to prepare
    factor: float
    points: np.ndarray
    angles: np.ndarray
    sizes: np.ndarray
    descriptors: np.ndarray | None

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass(frozen=True)
class FeatureRegistration:
    """Result of registering a moving frame to a reference by features.

    ``matrix`` (2x3 float64, moving pixels -> reference pixels) is ``None`` when nothing
    plausible was found (``reason`` says why). ``matches``: ratio-tested matches that entered
    RANSAC; ``inliers``: those consistent with ``matrix``; ``score`` in [0, 1]:
    ``inliers / (inliers + score_half)``, a saturating inlier count (random matches on ground
    that does not overlap reach only a handful of inliers; correct pairs tens to hundreds).
    """

    method: str
    matrix: np.ndarray | None
    matches: int = 0
    inliers: int = 0
    score: float = 0.0
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.matrix is not None

    def rescaled(self, factor: float) -> FeatureRegistration:
        """The same result for both frames resized by ``factor`` (see :func:`rescale_matrix`)."""
        if self.matrix is None:
            return self
        return replace(self, matrix=rescale_matrix(self.matrix, factor))

    @property
    def inlier_ratio(self) -> float:
        return self.inliers / self.matches if self.matches else 0.0

    @property
    def angle_deg(self) -> float:
        return _params(self.matrix)[0] if self.matrix is not None else float("nan")

    @property
    def scale(self) -> float:
        return _params(self.matrix)[1] if self.matrix is not None else float("nan")


class FeatureMatcher:
    """ORB or SIFT keypoints + ratio-tested matches + 4-DoF RANSAC (``cv2.estimateAffinePartial2D``).

    Parameters
    ----------
    kind : {"sift", "orb"}
    working_size : int
        Keypoints are detected on a copy downscaled so that its longer side is at most this many
        pixels (0 = as given); results are in the pixels of the frames given.
    max_features : int
        Keypoints kept per frame (the strongest).
    ratio : float
        Lowe's ratio test: a match is kept when its descriptor distance is below ``ratio`` times
        that of the second-best candidate.
    ransac_px : float
        RANSAC inlier threshold, in pixels of the detection resolution.
    ransac_iters : int
        RANSAC iterations (a 2-point model: 5000 iterations find a 5 % inlier set with
        probability > 0.9999).
    max_scale_change : float
        A result scaling by more than this factor (or less than its inverse) is rejected.
    min_inliers : int
        Fewer inliers: ``matrix`` is ``None``.
    score_half : float
        Inlier count at which ``score`` is 0.5.
    """

    def __init__(self, kind: str = "sift", *, working_size: int = 640, max_features: int = 2000,
                 ratio: float = 0.8, ransac_px: float = 3.0, ransac_iters: int = 5000,
                 max_scale_change: float = 2.0, min_inliers: int = 8, score_half: float = 20.0,
                 fast_threshold: int = 10, contrast_threshold: float = 0.02) -> None:
        if kind not in KINDS:
            raise ValueError(f"feature kind must be one of {', '.join(KINDS)}, got {kind!r}")
        if not 0 < ratio <= 1:
            raise ValueError(f"ratio must be in (0, 1], got {ratio}")
        self.kind = kind
        self.working_size = int(working_size)
        self.max_features = int(max_features)
        self.ratio = float(ratio)
        self.ransac_px = float(ransac_px)
        self.ransac_iters = int(ransac_iters)
        self.max_scale_change = float(max_scale_change)
        self.min_inliers = max(3, int(min_inliers))
        self.score_half = float(score_half)
        if kind == "orb":
            self._detector = cv2.ORB_create(nfeatures=self.max_features, fastThreshold=fast_threshold)
            self._norm = cv2.NORM_HAMMING
        else:
            self._detector = cv2.SIFT_create(nfeatures=self.max_features,
                                             contrastThreshold=contrast_threshold)
            self._norm = cv2.NORM_L2
        self._matcher = cv2.BFMatcher(self._norm)
        self._keep: tuple[np.ndarray, tuple[int, int], np.ndarray] | None = None  # (mask, size, keypoint mask)

    # ------------------------------------------------------------------ per frame
    def prepare(self, frame: np.ndarray, mask: np.ndarray | None = None) -> FeatureFrame:
        """Detect and describe keypoints of a frame (grey or BGR, uint8 or float).

        ``mask``: pixel weights in [0, 1] of frames of this aspect ratio, at any size (e.g. a
        registrar's :attr:`~photomap.core.ifmi.Registrar.mask`): keypoints only where it is 1.
        A mask is taken as fixed: the same array at the same detection size is resized once."""
        gray = _to_uint8(_gray(frame))
        small, f = _resize(gray, self.working_size)
        keep = None if mask is None else self._keypoint_mask(mask, (small.shape[1], small.shape[0]))
        kps, desc = self._detector.detectAndCompute(small, keep)
        n = len(kps)
        pts = np.array([k.pt for k in kps], np.float32).reshape(n, 2)
        pts = (pts + 0.5) / f - 0.5  # detection pixels -> frame pixels (pixel centres)
        angles = np.array([k.angle for k in kps], np.float32).reshape(n)
        sizes = np.array([k.size for k in kps], np.float32).reshape(n) / f
        if desc is None or n == 0:
            desc = None
        return FeatureFrame(self.kind, (gray.shape[0], gray.shape[1]), f, pts, angles, sizes, desc)

    def _keypoint_mask(self, mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """uint8 255 where ``mask`` is 1 at the detection size ``(w, h)``; kept for the next frame
        of the same mask and size (one tuple read and written whole: safe from two threads)."""
        cached = self._keep
        if cached is None or cached[0] is not mask or cached[1] != size:
            weights = cv2.resize(np.asarray(mask, np.float32), size, interpolation=cv2.INTER_LINEAR)
            cached = (mask, size, np.where(weights >= 0.999, np.uint8(255), np.uint8(0)))
            self._keep = cached
        return cached[2]

    # ------------------------------------------------------------------ per pair
    def _match(self, ref: FeatureFrame, mov: FeatureFrame) -> tuple[np.ndarray, np.ndarray]:
        """Indices (moving, reference) of ratio-tested nearest-neighbour matches."""
        knn = self._matcher.knnMatch(mov.descriptors, ref.descriptors, k=2)
        im, ir = [], []
        for pair in knn:
            if len(pair) == 2 and pair[0].distance < self.ratio * pair[1].distance:
                im.append(pair[0].queryIdx)
                ir.append(pair[0].trainIdx)
            elif len(pair) == 1:
                im.append(pair[0].queryIdx)
                ir.append(pair[0].trainIdx)
        return np.asarray(im, np.intp), np.asarray(ir, np.intp)

    def _fail(self, reason: str, matches: int = 0, inliers: int = 0) -> FeatureRegistration:
        return FeatureRegistration(self.kind, None, matches, inliers, 0.0, reason)

    def register(self, reference: FeatureFrame | np.ndarray, moving: FeatureFrame | np.ndarray,
                 prior: Prior | None = None) -> FeatureRegistration:
        """Register ``moving`` to ``reference`` (prepared frames or arrays, prepared on the fly).

        ``prior`` (angle/scale of the expected result matrix, shift in the frames' pixels): matches
        whose keypoint orientation or size change contradicts it are dropped before RANSAC, and a
        result outside its tolerances is rejected.
        """
        ref = reference if isinstance(reference, FeatureFrame) else self.prepare(reference)
        mov = moving if isinstance(moving, FeatureFrame) else self.prepare(moving)
        if ref.kind != self.kind or mov.kind != self.kind:
            raise ValueError(f"frames prepared for {ref.kind}/{mov.kind}, matcher is {self.kind}")
        if ref.descriptors is None or mov.descriptors is None or len(ref) < 2 or len(mov) < 2:
            return self._fail("too few keypoints")
        im, ir = self._match(ref, mov)
        if prior is not None and im.size:
            keep = np.ones(im.size, bool)
            if prior.angle_deg is not None and prior.angle_tol_deg < 90.0:
                d = _wrap180(ref.angles[ir] - mov.angles[im] - prior.angle_deg)
                keep &= np.abs(d) <= prior.angle_tol_deg + _ANGLE_SLACK_DEG
            if prior.scale is not None and prior.scale > 0:
                lr = np.log(ref.sizes[ir] / np.maximum(mov.sizes[im], 1e-6) / prior.scale)
                keep &= np.abs(lr) <= abs(math.log1p(prior.scale_tol)) + _LOG_SIZE_SLACK
            im, ir = im[keep], ir[keep]
        n = int(im.size)
        if n < self.min_inliers:
            return self._fail(f"{n} matches", n)
        f = ref.factor
        m, mask = cv2.estimateAffinePartial2D(mov.points[im], ref.points[ir], method=cv2.RANSAC,
                                              ransacReprojThreshold=self.ransac_px / f,
                                              maxIters=self.ransac_iters, confidence=0.999,
                                              refineIters=10)
        if m is None or mask is None:
            return self._fail("RANSAC found no model", n)
        inliers = int(mask.sum())
        m = m.astype(np.float64)
        angle, scale = _params(m)
        if not (1.0 / self.max_scale_change <= scale <= self.max_scale_change):
            return self._fail(f"implausible scale {scale:.3f}", n, inliers)
        if inliers < self.min_inliers:
            return self._fail(f"{inliers} inliers", n, inliers)
        if prior is not None:
            if (prior.angle_deg is not None and prior.angle_tol_deg < 90.0
                    and abs(float(_wrap180(angle - prior.angle_deg))) > prior.angle_tol_deg):
                return self._fail(f"angle {angle:.1f} deg outside the prior", n, inliers)
            if (prior.scale is not None and prior.scale > 0
                    and abs(math.log(scale / prior.scale)) > abs(math.log1p(prior.scale_tol))):
                return self._fail(f"scale {scale:.3f} outside the prior", n, inliers)
            if prior.shift is not None and math.hypot(m[0, 2] - prior.shift[0],
                                                      m[1, 2] - prior.shift[1]) > prior.shift_tol:
                return self._fail("shift outside the prior", n, inliers)
        score = inliers / (inliers + self.score_half)
        return FeatureRegistration(self.kind, m, n, inliers, float(score))


def register_features(reference: FeatureFrame | np.ndarray, moving: FeatureFrame | np.ndarray,
                      prior: Prior | None = None, *, kind: str = "sift",
                      matcher: FeatureMatcher | None = None, **settings) -> FeatureRegistration:
    """One-call feature registration of ``moving`` to ``reference`` (arrays or prepared frames).

    Uses ``matcher`` when given, else a :class:`FeatureMatcher` of ``kind`` built with
    ``settings``. The result's matrix maps moving pixels to reference pixels.
    """
    if matcher is None:
        if isinstance(reference, FeatureFrame):
            kind = reference.kind
        matcher = FeatureMatcher(kind, **settings)
    return matcher.register(reference, moving, prior)


# --------------------------------------------------------------------------- photometric check

@dataclass(frozen=True)
class OverlapCheck:
    """Photometric agreement of two frames over their overlap under a candidate placement.

    The gradients of the reference and of the warped moving frame are cross-correlated over the
    overlap for every relative offset (masked and normalised: 1 = identical gradients over the
    pixels both cover). ``score``: the highest correlation *peak* (local maximum) within the
    tolerance of zero offset, the placement's own alignment (0 when there is none: a placement
    that is off sits on the shoulder of a peak farther away); ``ratio``: the highest peak beyond
    the tolerance over ``score`` (below 1: nothing else explains the images as well; near or
    above 1: the placement is off, e.g. by one period of periodic ground, or the match is noise;
    ``inf`` without an own peak); ``offset``: where the overall best correlation lies (reference
    pixels, x, y: the moving frame would fit better moved by it). ``gradient_ncc``, ``ncc``: NCC
    of the gradient vectors and of the intensities at zero offset, for comparison. ``overlap``:
    fraction of the reference covered by the warped moving frame; ``pixels``: overlap pixels
    compared at the check resolution. All correlations are NaN when the overlap is too small.
    """

    score: float
    ratio: float
    offset: tuple[float, float]
    gradient_ncc: float
    ncc: float
    overlap: float
    pixels: int

    def passes(self, min_score: float, max_ratio: float, min_overlap: float) -> bool:
        """Whether the placement is confirmed: aligned, unambiguous, over enough overlap."""
        return bool(self.overlap >= min_overlap and np.isfinite(self.score) and self.score >= min_score
                    and self.ratio <= max_ratio)


def _gradients(img: np.ndarray, blur: float) -> np.ndarray:
    """HxWx2 float32 gradients (x, y; grey levels per pixel: Sobel / 8) after a Gaussian blur."""
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    return np.dstack([cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=0.125),
                      cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)])


def _ncc(a: np.ndarray, b: np.ndarray, centre: bool) -> float:
    # einsum, not BLAS: a BLAS dot spins up its thread pool, which costs milliseconds on a busy host
    a = a.astype(np.float64).ravel()
    b = b.astype(np.float64).ravel()
    if centre:
        a = a - a.mean()
        b = b - b.mean()
    den = math.sqrt(float(np.einsum("i,i->", a, a)) * float(np.einsum("i,i->", b, b)))
    return float(np.einsum("i,i->", a, b)) / den if den > 0 else float("nan")


@functools.lru_cache(maxsize=8)
def _offsets(fh: int, fw: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offset radius (fh x fw) and the x, y offsets of the columns and rows of a DFT correlation."""
    dy = np.fft.fftfreq(fh, 1.0 / fh)
    dx = np.fft.fftfreq(fw, 1.0 / fw)
    radius = np.hypot(dx[None, :], dy[:, None]).astype(np.float32)
    for a in (radius, dx, dy):
        a.flags.writeable = False
    return radius, dx, dy


def verify_overlap(reference: np.ndarray, moving: np.ndarray, matrix: np.ndarray, *,
                   size: int = 160, blur: float = 1.0, tolerance: float = 0.02,
                   min_pixels: int = 300) -> OverlapCheck:
    """Check a placement: compare ``reference`` with ``moving`` warped by ``matrix``.

    Parameters
    ----------
    reference, moving : grey or BGR frames (any size), in the pixels ``matrix`` refers to.
    matrix : 2x3, moving pixels -> reference pixels.
    size : both frames are downscaled (INTER_AREA) by the factor that brings the reference's
        longer side to at most ``size`` pixels before the comparison.
    blur : Gaussian sigma (pixels at the check resolution) applied before the gradients.
    tolerance : offsets up to this fraction of the reference's longer side count as the
        placement's own (camera tilt, parallax and lens distortion leave a similarity a few pixels
        off in parts of the frame); peaks beyond it are rivals.
    min_pixels : fewer overlap pixels at the check resolution: the correlations are NaN.
    """
    ref = _gray(reference).astype(np.float32, copy=False)
    mov = _gray(moving).astype(np.float32, copy=False)
    ref_s, f = _resize(ref, size)
    if f < 1.0:
        mov_s = cv2.resize(mov, (max(1, int(round(mov.shape[1] * f))), max(1, int(round(mov.shape[0] * f)))),
                           interpolation=cv2.INTER_AREA)
        m = rescale_matrix(matrix, f)
    else:
        mov_s, m = mov, np.asarray(matrix, np.float64)
    h, w = ref_s.shape
    warped = cv2.warpAffine(mov_s, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                            borderValue=0.0)
    valid = cv2.warpAffine(np.ones(mov_s.shape, np.uint8), m, (w, h), flags=cv2.INTER_NEAREST,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    overlap = float(valid.mean())
    # compare only where the blur and Sobel support of the warped frame stays inside it
    margin = int(math.ceil(2 * blur)) + 2
    inner = cv2.erode(valid, np.ones((2 * margin + 1, 2 * margin + 1), np.uint8),
                      borderType=cv2.BORDER_CONSTANT, borderValue=0)
    n = int(inner.sum())
    nan = float("nan")
    if n < min_pixels:
        return OverlapCheck(nan, nan, (nan, nan), nan, nan, overlap, n)
    sel = inner.astype(bool)
    ncc = _ncc(ref_s[sel], warped[sel], True)
    weight = inner.astype(np.float32)
    ga = _gradients(ref_s, blur)
    gb = _gradients(warped, blur)
    ga *= weight[:, :, None]
    gb *= weight[:, :, None]
    # Masked normalised cross-correlation of the gradient fields for every offset d (linear:
    # zero-padded DFTs): corr[d] = sum_p ga(p).gb(p+d) over the pixels where both overlap masks
    # hold, divided by the gradient energies of ga and gb over those same pixels.
    # Padding by half the frame keeps offsets up to h/2, w/2 free of wrap-around; larger ones
    # leave less than half of any overlap in common and are not used anyway.
    fh, fw = cv2.getOptimalDFTSize(h + (h + 1) // 2), cv2.getOptimalDFTSize(w + (w + 1) // 2)

    def dft(x: np.ndarray) -> np.ndarray:
        return cv2.dft(cv2.copyMakeBorder(np.ascontiguousarray(x), 0, fh - h, 0, fw - w, cv2.BORDER_CONSTANT))

    def correlate(fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
        """sum_p x(p) y(p + d) from the DFTs of x and y."""
        return cv2.idft(cv2.mulSpectrums(fy, fx, 0, conjB=True), flags=cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE)

    fax, fay, fbx, fby = dft(ga[:, :, 0]), dft(ga[:, :, 1]), dft(gb[:, :, 0]), dft(gb[:, :, 1])
    fm = dft(weight)
    cross = cv2.idft(cv2.mulSpectrums(fbx, fax, 0, conjB=True) + cv2.mulSpectrums(fby, fay, 0, conjB=True),
                     flags=cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE)
    ea = correlate(dft(cv2.multiply(ga[:, :, 0], ga[:, :, 0]) + cv2.multiply(ga[:, :, 1], ga[:, :, 1])), fm)
    eb = correlate(fm, dft(cv2.multiply(gb[:, :, 0], gb[:, :, 0]) + cv2.multiply(gb[:, :, 1], gb[:, :, 1])))
    area = correlate(fm, fm)
    radius, dx, dy = _offsets(fh, fw)
    # offsets that keep at least half of the overlap (a sliver gives noisy correlations)
    usable = (area >= 0.5 * n) & (np.abs(dy)[:, None] <= fh - h) & (np.abs(dx)[None, :] <= fw - w)
    den = cv2.sqrt(cv2.max(ea, 0.0) * cv2.max(eb, 0.0))
    floor = 1e-6 * float(den.max())
    usable &= den > floor
    corr = np.where(usable, cross / np.maximum(den, floor + 1e-30), -1.0).astype(np.float32)
    gncc = float(corr[0, 0]) if usable[0, 0] else nan
    tol = max(1.5, tolerance * max(h, w))
    # peaks: local maxima over a neighbourhood of about the tolerance (not noise on a shoulder)
    k = 2 * max(1, int(round(tol / 2))) + 1
    peaks = usable & (corr >= cv2.dilate(corr, np.ones((k, k), np.uint8)))
    own = peaks & (radius <= tol)
    # the placement's own peak: a shifted placement has only the shoulder of a peak farther away
    score = float(corr[own].max()) if own.any() else 0.0
    far = peaks & (radius > tol)
    rival = float(corr[far].max()) if far.any() else 0.0
    iy, ix = np.unravel_index(int(np.argmax(corr)), corr.shape)
    offset = (-float(dx[ix]) / f, -float(dy[iy]) / f)
    ratio = rival / score if score > 0 else math.inf
    return OverlapCheck(score, ratio, offset, gncc, ncc, overlap, n)


# --------------------------------------------------------------------------- decision

# Defaults of the decision, chosen by tools/bench_pairs.py (docs/benchmarks.md, "pairs" section).
MIN_SCORE = 0.2  # the placement's own correlation peak
MAX_RATIO = 0.9  # a rival peak this high relative to it makes the placement unconfirmed
MIN_OVERLAP = 0.05  # fraction of the reference frame
MIN_INLIERS = 12  # feature results with fewer inliers are not used
STRONG_INLIERS = 25  # ... with at least this many, a rival peak does not veto (parallax, roads)
STRONG_MIN_SCORE = 0.1  # ... but their own peak must still reach this


@dataclass(frozen=True)
class Decision:
    """What to do with a pair.

    ``matrix``: the chosen placement (moving px -> reference px), ``None`` when nothing is
    accepted; ``method``: ``ifmi``, ``orb``, ``sift`` or ``none``; ``accept``: glue the frame
    (False: it must not be glued; the tracker starts a new segment or waits); ``score``: the
    chosen placement's check score (the best one seen when nothing is accepted); ``reason``: a
    short text for logs.
    """

    matrix: np.ndarray | None
    method: str
    accept: bool
    score: float
    reason: str


def ifmi_confirmed(ifmi: Registration, check: OverlapCheck, *, min_confidence: float = 0.0,
                   min_score: float = MIN_SCORE, max_ratio: float = MAX_RATIO,
                   min_overlap: float = MIN_OVERLAP) -> bool:
    """Whether an iFMI placement is confirmed by its overlap check (and confidence)."""
    return ifmi.confidence >= min_confidence and check.passes(min_score, max_ratio, min_overlap)


def features_confirmed(features: FeatureRegistration | None, check: OverlapCheck | None, *,
                       min_score: float = MIN_SCORE, max_ratio: float = MAX_RATIO,
                       min_overlap: float = MIN_OVERLAP, min_inliers: int = MIN_INLIERS,
                       strong_inliers: int = STRONG_INLIERS,
                       strong_min_score: float = STRONG_MIN_SCORE) -> bool:
    """Whether a feature placement is confirmed.

    Like iFMI's (own peak >= ``min_score``, no rival above ``max_ratio`` of it), except that with
    ``strong_inliers`` RANSAC inliers a rival peak does not veto and the own peak need only reach
    ``strong_min_score``: trees closer to the camera than the ground (parallax) or long roads give
    a second peak next to a right placement, and that many inliers are independent evidence.
    """
    if features is None or not features.ok or check is None or features.inliers < min_inliers:
        return False
    if check.passes(min_score, max_ratio, min_overlap):
        return True
    return bool(features.inliers >= strong_inliers and check.overlap >= min_overlap
                and np.isfinite(check.score) and check.score >= strong_min_score)


def needs_second_opinion(ifmi: Registration, ifmi_check: OverlapCheck, **thresholds) -> bool:
    """Whether to run the features after iFMI: when iFMI's placement is not confirmed.

    ``thresholds``: the keyword arguments of :func:`ifmi_confirmed`.
    """
    return not ifmi_confirmed(ifmi, ifmi_check, **thresholds)


def decide(ifmi: Registration, ifmi_check: OverlapCheck, features: FeatureRegistration | None = None,
           features_check: OverlapCheck | None = None, *, min_confidence: float = 0.0,
           min_score: float = MIN_SCORE, max_ratio: float = MAX_RATIO, min_overlap: float = MIN_OVERLAP,
           min_inliers: int = MIN_INLIERS, strong_inliers: int = STRONG_INLIERS,
           strong_min_score: float = STRONG_MIN_SCORE) -> Decision:
    """Choose between iFMI and a feature result by their overlap checks.

    Matrices must be in the same pixels (those the checks were computed in). Each result is a
    candidate when confirmed (:func:`ifmi_confirmed`, :func:`features_confirmed`); of two, the
    higher check score wins, iFMI on a tie (it is refined to sub-pixel accuracy). None confirmed:
    ``accept`` is False.
    """
    cands: list[tuple[float, int, str, np.ndarray]] = []
    if ifmi_confirmed(ifmi, ifmi_check, min_confidence=min_confidence, min_score=min_score,
                      max_ratio=max_ratio, min_overlap=min_overlap):
        cands.append((ifmi_check.score, 1, "ifmi", ifmi.matrix))
    if features_confirmed(features, features_check, min_score=min_score, max_ratio=max_ratio,
                          min_overlap=min_overlap, min_inliers=min_inliers,
                          strong_inliers=strong_inliers, strong_min_score=strong_min_score):
        cands.append((features_check.score, 0, features.method, features.matrix))
    if not cands:
        seen = [c.score for c in (ifmi_check, features_check) if c is not None and np.isfinite(c.score)]
        return Decision(None, "none", False, max(seen) if seen else float("nan"),
                        "no placement is confirmed by its overlap check")
    score, _, method, matrix = max(cands, key=lambda c: (c[0], c[1]))
    return Decision(np.asarray(matrix, np.float64), method, True, float(score),
                    f"{method} placement confirmed (overlap check {score:.2f})")
