"""iFMI registration: improved Fourier-Mellin invariant registration of two frames.

The method (Buelow & Birk, "Fast and robust photomapping with an UAV", IROS 2009; Reddy &
Chatterji 1996 for classic FMI):

1. Both frames are apodized and Fourier transformed. The magnitude spectrum is invariant to
   translation; rotating the image rotates it, scaling the image by ``s`` scales it by ``1/s``.
2. The magnitude (radially band-passed, whitened and weighted by ring signal-to-noise) is resampled
   on a log-polar grid over the half plane (0..180 deg), where rotation and scale become shifts.
3. A phase-only matched filter (POMF, the normalised cross-power spectrum) of the two log-polar
   images has its Dirac peak at (rotation, log scale).
4. The new frame is re-rotated and re-scaled; a second POMF gives the translation. The spectrum
   cannot tell ``a`` from ``a + 180 deg``: both hypotheses are tested, the second one for the price
   of one inverse FFT (the point-mirrored image's spectrum is a phase ramp times the conjugate).
5. Optionally a few Gauss-Newton iterations (inverse compositional Lucas-Kanade with a similarity
   warp and a brightness gain/offset) refine the estimate below the log-polar grid. They run on
   the pyramid level (``cv2.pyrDown``) where signal dominates the reference's gradient energy
   (full resolution for textured ground, 1/4 for smooth, noisy sand: noise gradients would shrink
   every step), on the informative samples of a regular grid on the reference (those whose
   gradient energy exceeds a quarter of the mean, at least 4096), and stop once an update moves the frame
   corners by less than 0.01 px (2-3 iterations on textured ground).

Two depths (roofs, boxes, tree crowns above the ground; docs/hard-cases.md): a nearer layer moves
with the same rotation and scale but farther, so its translation peak lies on the line from the
origin through the ground's, beyond it. Of two such candidates the farther layer (the shorter
displacement) goes first, and the refinement then weights the other layer's samples down (Tukey
biweights); a refinement whose converged residual has a heavy tail is re-weighted alike.

Every cross-power spectrum is weighted by a Gaussian low-pass, which turns the POMF peak into a
sampled Gaussian; fitting a Gaussian to the 3 samples around the maximum (a parabola on their
logarithms) then locates it without the ~0.1 px bias of a plain parabola.

Conventions (:mod:`photomap.geometry`): OpenCV pixel coordinates (x right, y down, origin at the centre
of the top-left pixel). A registration result ``matrix`` is 2x3 and maps pixels of the new frame
``b`` to pixels of the reference ``a``: ``p_a = matrix @ [x_b, y_b, 1]``; ``angle_deg`` and ``scale``
are read from it as ``degrees(atan2(m10, m00))`` and ``sqrt(det)``, ``shift`` is its last column.

The module is pure: arrays in, arrays out; a :class:`Registrar` only caches constants for one
frame shape, and a :class:`PreparedFrame` caches one frame's spectra so that, in a sequence, each
new frame costs 3 forward and at most 3 inverse real FFTs; the refinement's data of a frame is
built on first use and cached in it too.

Speed (issue 12): the FFTs are OpenCV's (``cv2.dft`` in its packed CCS layout, about twice as fast
as ``scipy.fft`` here), everything is float32 but the few sums that need more, and no BLAS product
is large enough for BLAS threads (``@``/``dot`` on all of the refinement's samples ran multithreaded
OpenBLAS, whose threads spin: next to any busy process a 3 ms registration took 30-100 ms). The
large arrays go through OpenCV and ``np.einsum`` (single-threaded), the refinement's products
over its samples (its 6x6 Gauss-Newton matrix, and in each iteration the 6 sums against the
warped image and its square) through matrix products of at most ``_BLAS_ONE_THREAD`` multiply-adds
each (OpenBLAS's size for threads; 3-7x faster than ``np.einsum``), so a Registrar costs the same
in any process, whatever its BLAS thread settings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.fft

from photomap.config import RegistrationConfig
from photomap.geometry import similarity_matrix

__all__ = ["Prior", "Candidate", "Registration", "PreparedFrame", "Registrar", "to_gray"]

_EPS = 1e-12
_REFINE_SAMPLES = 16384  # the refinement samples about this many pixels on a regular grid
_REFINE_BLUR_VAR = 0.5  # the refinement images' 3x3 binomial prefilter: variance, px^2 of their level
_REFINE_SIGNAL = 0.7  # signal share of the gradient energy the refinement level must reach
_REFINE_MAX_LEVEL = 3  # coarsest pyramid level of the refinement (1/8 of the frame size)
_REFINE_TOL = 0.01  # refinement converged once an update moves the frame corners less (pixels)
_REFINE_KEEP = 0.25  # grid samples kept: gradient energy above this fraction of the mean (about
#                      half of them on textured ground, ~97 % of the energy, which is what the
#                      estimate's precision needs; 0.5 keeps ~40 % and loses ~15 % of the precision)
_REFINE_MIN_KEEP = 4096  # ... but at least this many (all of a smaller grid: noisy ground needs them)
_BLAS_ONE_THREAD = 65536 * 4  # OpenBLAS runs a matrix product with m n k up to this on the caller's thread
_REFINE_MARGIN = 2.0  # samples used must map this far inside b (level pixels); see _refine
_TAIL_SIGMAS = 8.0  # a converged residual beyond this many robust sigmas (1.4826 MAD) is in the tail
_TAIL_SHARE = 0.015  # ... and a tail above this share of the samples is a second layer (see _refine)
_TAIL_STRIDE = 8  # ... tested on every 8th sample
_BIWEIGHT_C = 4.685  # Tukey's biweight constant (robust sigmas) of the re-weighted refinement
_LAYER_RATIO = (0.6, 0.97)  # a farther layer moves this fraction of a nearer one's displacement (see _ground_first)
_AROUND = np.array([[-1, -1, -1, 0, 0, 1, 1, 1], [-1, 0, 1, -1, 1, -1, 0, 1]])  # 8 neighbours (dy, dx)
_AROUND.setflags(write=False)
_WEAK_PEAK = 0.5  # below this translation peak, the prior's own rotation/scale is tried too
_EXPECTED_PEAK = 0.35  # a peak at the expected shift wins over higher ones at this fraction of the best
_CLEAR_PEAK = 0.15  # ... and at least this high (well above noise, which scores ~0)


def to_gray(frame: np.ndarray) -> np.ndarray:
    """A grey view of ``frame``: grey (h, w) as is, (h, w, 1) squeezed, BGR or BGRA converted
    (OpenCV channel order). ValueError for another channel count."""
    img = np.asarray(frame)
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.shape[2] == 1:
            img = img[:, :, 0]
        else:
            raise ValueError(f"unsupported frame with {img.shape[2]} channels")
    return img


def _matrix_params(m: np.ndarray) -> tuple[float, float, tuple[float, float]]:
    angle = math.degrees(math.atan2(m[1, 0], m[0, 0]))
    scale = math.sqrt(max(m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0], 0.0))
    return angle, scale, (float(m[0, 2]), float(m[1, 2]))


def _wrap180(angle: float) -> float:
    return (angle + 180.0) % 360.0 - 180.0


@dataclass(frozen=True)
class Prior:
    """Expected motion, e.g. from telemetry or a motion model; it restricts the search.

    ``angle_deg``/``scale``/``shift`` are expectations of the result matrix (new frame -> reference),
    each ``None`` when unknown. A tolerance of 0 locks the value (``scale=1, scale_tol=0`` for a
    constant altitude). ``scale_tol`` is relative (0.05 = +-5 %).
    """

    angle_deg: float | None = None
    angle_tol_deg: float = 10.0
    scale: float | None = None
    scale_tol: float = 0.05
    shift: tuple[float, float] | None = None
    shift_tol: float = 20.0

    def admits(self, matrix: np.ndarray) -> bool:
        """Whether ``matrix`` (2x3 or 3x3) has the rotation and scale expected, within the
        tolerances (the shift is not checked)."""
        angle, scale, _ = _matrix_params(np.asarray(matrix, float))
        if self.angle_deg is not None and abs(_wrap180(angle - self.angle_deg)) > self.angle_tol_deg:
            return False
        return self.scale is None or \
            abs(math.log(max(scale, 1e-9) / max(self.scale, 1e-9))) <= math.log1p(self.scale_tol)


@dataclass(frozen=True)
class Candidate:
    """One hypothesis that was scored in the translation step."""

    angle_deg: float
    scale: float
    shift: tuple[float, float]
    peak: float  # normalised translation-POMF peak height (1 = a clean Dirac)


@dataclass(frozen=True)
class Registration:
    """Result of registering a new frame ``b`` to a reference ``a``.

    ``matrix`` (2x3, float64) maps pixels of ``b`` to pixels of ``a``. ``confidence`` is in [0, 1]:
    the height of the translation POMF peak relative to that of a clean Dirac, with the
    expected noise maximum of the correlation surface subtracted (so noise, blank frames and
    pairs without overlap score near 0). ``ambiguous`` is set when another hypothesis or another
    translation peak scored nearly as high (periodic ground); ``candidates`` lists them, best first.
    """

    matrix: np.ndarray
    confidence: float
    ambiguous: bool = False
    candidates: tuple[Candidate, ...] = ()
    refined: bool = False

    @property
    def angle_deg(self) -> float:
        return _matrix_params(self.matrix)[0]

    @property
    def scale(self) -> float:
        return _matrix_params(self.matrix)[1]

    @property
    def shift(self) -> tuple[float, float]:
        return _matrix_params(self.matrix)[2]


@dataclass(frozen=True, eq=False)
class PreparedFrame:
    """A frame's cached spectra (see :meth:`Registrar.prepare`)."""

    gray: np.ndarray  # float32 HxW, unwindowed
    spectrum: np.ndarray  # rfft2 of the windowed frame
    logpolar: np.ndarray  # rfft2 of the weighted log-polar magnitude, phase-normalised
    ring_snr: np.ndarray  # per-ring Wiener weight S/(S+N) of the frame's spectrum
    energy: float  # variance of the frame (0 for a blank frame)
    refine_level: int = 0  # pyramid level (0 = full resolution) the refinement uses as reference
    # refinement data built on first use (pyramid, smoothed images, template): see Registrar._refine
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def blank(self) -> bool:
        """Nothing to register: a uniform frame (black video, a lens cap)."""
        return self.energy <= _EPS


@dataclass(frozen=True, eq=False)
class _Grid:
    """The refinement's regular sample grid on one pyramid level (pixels of that level)."""

    level: int
    stride: int  # level pixels between samples
    size: tuple[int, int]  # (rows, cols) of samples
    center: tuple[float, float]  # the frame centre in level pixels
    window: np.ndarray  # (rows, cols) float32 apodization weight of each sample
    points: np.ndarray  # (N, 2) float32 sample x, y (level pixels), row-major over the grid


@dataclass(frozen=True, eq=False)
class _Template:
    """A reference frame's refinement data: its informative grid samples (K of them).

    Only samples whose weighted gradient energy exceeds ``_REFINE_KEEP`` of the mean are kept:
    flat samples hardly constrain the warp, and every sample costs in each iteration.
    """

    grid: _Grid
    points: np.ndarray  # (1, K, 2) float32 sample positions (x, y), level pixels
    window: np.ndarray  # (K,) apodization weight
    window_sum: float  # their sum
    sd: np.ndarray  # (6, K) steepest-descent images: d/d(tx, ty, scale, rotation), offset, gain
    #                 (the last row is the centred template itself)


def _tukey(n: int, taper: float) -> np.ndarray:
    """Symmetric Tukey window of length n (taper = fraction of the length that is tapered)."""
    if taper <= 0:
        return np.ones(n)
    x = np.arange(n) / max(n - 1, 1)
    w = np.ones(n)
    edge = taper / 2
    lo = x < edge
    hi = x > 1 - edge
    w[lo] = 0.5 * (1 - np.cos(np.pi * x[lo] / edge))
    w[hi] = 0.5 * (1 - np.cos(np.pi * (1 - x[hi]) / edge))
    return w


def _fit_offset(lm: float, l0: float, lp: float) -> float:
    """Sub-sample offset of a Gaussian peak from the logs of 3 samples (in [-0.5, 0.5])."""
    den = lm - 2.0 * l0 + lp
    if den >= -_EPS:
        return 0.0
    return min(max(0.5 * (lm - lp) / den, -0.5), 0.5)


def _gram(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b.T`` (float64) of a (k, n) and an (l, n) float32 array with k and l small, in
    products of at most ``_BLAS_ONE_THREAD`` multiply-adds: each below OpenBLAS's size for
    threads, so that it runs on the caller's thread whatever the BLAS thread setting."""
    n = a.shape[1]
    chunk = max(1, _BLAS_ONE_THREAD // (a.shape[0] * b.shape[0]))
    if n <= chunk:
        return (a @ b.T).astype(np.float64)
    out = np.zeros((a.shape[0], b.shape[0]))
    for i in range(0, n, chunk):
        out += a[:, i:i + chunk] @ b[:, i:i + chunk].T
    return out


def _percentile(x: np.ndarray, q: float) -> float:
    """``np.percentile(x, q)`` (linear interpolation) of a 1-D array, by partial sort."""
    if not x.size:
        return 0.0
    pos = q / 100.0 * (x.size - 1)
    lo = int(math.floor(pos))
    hi = min(lo + 1, x.size - 1)
    part = np.partition(x, [lo, hi])
    return float(part[lo] + (pos - lo) * (part[hi] - part[lo]))


class _Ccs:
    """OpenCV's packed real DFT layout (CCS) of h x w arrays, with numpy access to its bins.

    ``cv2.dft`` of a real h x w float32 array (about twice as fast as ``scipy.fft.rfft2`` here)
    packs the half spectrum fx >= 0 into h x w floats. Its interior columns fx = 1 .. (w-1)//2
    are (re, im) pairs: :meth:`inner` views them as a complex (h, ni) array without copying. The
    columns fx = 0 and, for even w, fx = w/2 pack their own Hermitian column along the rows:
    :meth:`edges` unpacks them as half columns ky = 0 .. h//2 (complex (h//2 + 1, ne)), each
    entry standing for ``edge_mult`` bins of the full spectrum. :meth:`split` cuts an
    rfft2-layout array (h, w//2 + 1) into the same two parts.
    """

    def __init__(self, h: int, w: int) -> None:
        self.h, self.w = h, w
        self.ni = (w - 1) // 2
        self.nh = (h - 1) // 2
        self.cols = [0, w - 1] if w % 2 == 0 else [0]  # packed columns of the edges
        self.fx = [0, w // 2] if w % 2 == 0 else [0]  # their rfft2 columns
        self.m = h // 2 + 1
        mult = np.full(self.m, 2.0, np.float32)
        mult[0] = 1.0
        if h % 2 == 0:
            mult[-1] = 1.0
        self.edge_mult = mult[:, None]

    @staticmethod
    def forward(img: np.ndarray) -> np.ndarray:
        return cv2.dft(img)

    @staticmethod
    def inverse(packed: np.ndarray) -> np.ndarray:
        return cv2.idft(packed, flags=cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE)

    def inner(self, packed: np.ndarray) -> np.ndarray:
        return packed[:, 1:1 + 2 * self.ni].view(np.complex64)

    def edges(self, packed: np.ndarray) -> np.ndarray:
        cols = packed[:, self.cols]
        nh = self.nh
        e = np.zeros((self.m, len(self.cols)), np.complex64)
        e.real[0] = cols[0]
        e.real[1:1 + nh] = cols[1:1 + 2 * nh:2]
        e.imag[1:1 + nh] = cols[2:2 + 2 * nh:2]
        if self.h % 2 == 0:
            e.real[-1] = cols[-1]
        return e

    def set_edges(self, packed: np.ndarray, e: np.ndarray) -> None:
        nh = self.nh
        cols = np.empty((self.h, len(self.cols)), np.float32)
        cols[0] = e.real[0]
        cols[1:1 + 2 * nh:2] = e.real[1:1 + nh]
        cols[2:2 + 2 * nh:2] = e.imag[1:1 + nh]
        if self.h % 2 == 0:
            cols[-1] = e.real[-1]
        packed[:, self.cols] = cols

    def split(self, full: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (np.ascontiguousarray(full[:, 1:1 + self.ni]),
                np.ascontiguousarray(full[:self.m][:, self.fx]))

    def shifted_abs(self, packed: np.ndarray, edges: np.ndarray) -> np.ndarray:
        """|spectrum| in rfft2 layout (h, w//2 + 1) with rows fftshifted (fy = 0 at row h//2)."""
        h, m, s = self.h, self.m, self.h // 2
        out = np.empty((h, self.w // 2 + 1), np.float32)
        inner = self.inner(packed)
        np.abs(inner[:h - s], out=out[s:, 1:1 + self.ni])
        np.abs(inner[h - s:], out=out[:s, 1:1 + self.ni])
        ea = np.abs(edges)
        for k, fx in enumerate(self.fx):
            col = np.concatenate([ea[:, k], ea[h - m:0:-1, k]])  # rows in FFT order
            out[s:, fx] = col[:h - s]
            out[:s, fx] = col[h - s:]
        return out


def _normalise(inner: np.ndarray, edges: np.ndarray, w_inner: np.ndarray | float,
               w_edges: np.ndarray | float) -> None:
    """Phase-only matched filter in place: ``z *= weight / (|z| + floor)`` on both CCS parts.

    ``floor`` (1e-12 of the largest magnitude) only keeps exact zeros finite.
    """
    mag = np.abs(inner)
    mag_e = np.abs(edges)
    floor = np.float32(_EPS * (max(float(mag.max()), float(mag_e.max())) + _EPS))
    mag += floor
    np.divide(w_inner, mag, out=mag)
    inner *= mag
    mag_e += floor
    edges *= w_edges / mag_e


class Registrar:
    """iFMI registration of frames of one shape; see the module docstring for the method.

    Parameters
    ----------
    shape : (h, w)
        Frame shape in pixels (any size; non-square and non-power-of-two are fine).
    params : RegistrationConfig
        The ``registration`` settings (documented in ``config/default.yaml``): the apodization
        ``window`` (and Tukey ``window_taper``), the log-polar grid (``angle_bins`` over 180 deg,
        ``radius_bins``; 0 picks them from the frame size), the radial band ``band_low`` ..
        ``band_high`` (cycles/pixel) used for rotation/scale, ring SNR (Wiener) weighting
        (``snr_weighting``), the Gaussian low-pass ``peak_sigma`` (cycles/pixel, or cycles/bin on
        the log-polar grid) of every cross-power spectrum, the rotation/scale peaks within
        ``candidate_ratio`` of the best also scored by the translation step (up to
        ``max_candidates``), and the Gauss-Newton (inverse compositional) refinement's
        ``refine_iterations`` (0: off). ``working_size`` is not used here: the caller downscales.
    mask : (h, w) float array in [0, 1], optional
        Weight of each pixel, multiplied into the apodization window (0 = never used: burned-in
        overlays, pixels the lens does not cover; see :mod:`photomap.mapping.frameprep`). It
        weights every frame this registrar prepares, so it belongs to the frames' own pixels
        (a mask fixed in the frame). None: every pixel.
    layered_tail : bool
        A converged refinement whose residual has a heavy tail is taken for a second depth in
        view and re-weighted (frames of one flight). False for images whose tail has other causes:
        map windows composed of many frames (seams, exposure steps), where re-weighting moved
        right placements (photomap.mapping.merge).
    """

    def __init__(self, shape: tuple[int, int], params: RegistrationConfig = RegistrationConfig(),
                 mask: np.ndarray | None = None, layered_tail: bool = True) -> None:
        h, w = int(shape[0]), int(shape[1])
        if h < 16 or w < 16:
            raise ValueError(f"frames of {w}x{h} px are too small to register")
        window, window_taper = params.window, params.window_taper
        band_low, band_high, peak_sigma = params.band_low, params.band_high, params.peak_sigma
        angle_bins, radius_bins = params.angle_bins, params.radius_bins
        snr_weighting, candidate_ratio = params.snr_weighting, params.candidate_ratio
        max_candidates, refine_iterations = params.max_candidates, params.refine_iterations
        self.shape = (h, w)
        self.params = params
        self.center = ((w - 1) / 2.0, (h - 1) / 2.0)
        self.snr_weighting = snr_weighting
        self.candidate_ratio = candidate_ratio
        self.max_candidates = max(1, max_candidates)
        self.refine_iterations = max(0, refine_iterations)

        taper = 1.0 if window == "hann" else window_taper
        self.window = np.outer(_tukey(h, taper), _tukey(w, taper)).astype(np.float32)
        if window == "circular":
            yy, xx = np.mgrid[0:h, 0:w]
            rr = np.hypot((xx - (w - 1) / 2) / ((w - 1) / 2), (yy - (h - 1) / 2) / ((h - 1) / 2))
            self.window = np.where(rr < 1, 0.5 * (1 + np.cos(np.pi * np.clip((rr - (1 - window_taper)) / window_taper, 0, 1))), 0).astype(np.float32)
        self.layered_tail = bool(layered_tail)
        self.mask = None
        if mask is not None:
            mask = np.asarray(mask, np.float32)
            if mask.shape != (h, w):
                raise ValueError(f"registration mask shape {mask.shape} does not match the frames' {(h, w)}")
            self.mask = np.clip(mask, 0.0, 1.0)
            self.window = self.window * self.mask

        # frequency grid of an rfft2 spectrum (rows: fy in fft order, cols: fx >= 0), cycles/px;
        # the constants below are kept split into the CCS layout's interior and edge parts
        self._ccs = _Ccs(h, w)
        fy = scipy.fft.fftfreq(h)[:, None]
        fx = scipy.fft.rfftfreq(w)[None, :]
        radius = np.sqrt(fx ** 2 + fy ** 2).astype(np.float32)
        self._gauss = self._ccs.split(np.exp(-0.5 * (radius / peak_sigma) ** 2).astype(np.float32))
        # phase ramp that turns conj(F) into the spectrum of the point-mirrored image
        ramp = np.exp(-2j * np.pi * (fx * (w - 1) + fy * (h - 1)))
        self._mirror = self._ccs.split(ramp.astype(np.complex64))

        # log-polar grid over the half plane fx >= 0: rows = angle, cols = log radius
        n = min(h, w)
        na = angle_bins or 2 * int(round(0.5 * n))
        nr = radius_bins or max(32, na // 2)
        self.angle_bins, self.radius_bins = na, nr
        self._log_step = math.log(band_high / band_low) / (nr - 1)
        theta = np.deg2rad(-90.0 + 180.0 * np.arange(na) / na)[:, None]
        rad = band_low * np.exp(self._log_step * np.arange(nr))[None, :]
        self._lp_map_x = (rad * np.cos(theta) * w).astype(np.float32)
        self._lp_map_y = (rad * np.sin(theta) * h + h // 2).astype(np.float32)
        self._lp_radius = rad[0].astype(np.float32)
        self._lp_window = _tukey(nr, 0.5).astype(np.float32)
        self._lp_ccs = _Ccs(na, nr)
        lfy = scipy.fft.fftfreq(na)[:, None]
        lfx = scipy.fft.rfftfreq(nr)[None, :]
        lp_gauss = np.exp(-0.5 * (lfx ** 2 + lfy ** 2) / peak_sigma ** 2).astype(np.float32)
        self._lp_gauss = self._lp_ccs.split(lp_gauss)
        lp_sum = 2.0 * float(self._lp_gauss[0].sum())
        lp_sum += float((self._lp_gauss[1] * self._lp_ccs.edge_mult).sum())
        self._lp_ref = lp_sum / (na * nr)
        # scale shifts beyond +-nr/4 bins are never searched
        shifts_r = np.fft.fftfreq(nr, 1.0 / nr)
        self._lp_allowed = np.broadcast_to((np.abs(shifts_r) <= nr // 4)[None, :], (na, nr))

        self._grids: dict[int, _Grid] = {}
        self._shift_axes: tuple[np.ndarray, np.ndarray] | None = None  # fftfreq rows, columns (px)
        self._pair: tuple[PreparedFrame, PreparedFrame, dict] | None = None  # the last pair registered
        # gradient energy weight of each log-polar ring on each pyramid level of the refinement:
        # r^2 (gradient) * r^2 (ring area on the log grid) * |transfer function|^2 of pyrDown^L
        # (Gaussian, sigma 1 px of each level it reads) and the refinement's own smoothing
        levels = 1 + min(_REFINE_MAX_LEVEL, max(0, int(math.log2(min(h, w) / 32))))
        r = self._lp_radius.astype(np.float64)
        var = [sum(4.0 ** k for k in range(lv)) + 4.0 ** lv * _REFINE_BLUR_VAR for lv in range(levels)]
        self._level_weights = np.array([r ** 4 * np.exp(-(2 * np.pi * r) ** 2 * v) for v in var])
        # nearest log-polar ring of each rfft2 bin, to spread per-ring SNR weights over a spectrum;
        # bins outside the band point at an extra ring of weight 0
        ring = np.clip(np.searchsorted(self._lp_radius, radius), 0, nr - 1)
        ring[radius > band_high] = nr
        self._ring_index = self._ccs.split(ring.astype(np.intp))

    # ------------------------------------------------------------------ preparation
    def _gray(self, frame: np.ndarray) -> np.ndarray:
        img = to_gray(frame)
        if img.shape != self.shape:
            raise ValueError(f"frame shape {img.shape} does not match the registrar's {self.shape}")
        return img.astype(np.float32, copy=False)

    def _windowed_spectrum(self, gray: np.ndarray, mean: float) -> np.ndarray:
        """CCS-packed DFT of the mean-free, apodized frame."""
        x = gray - np.float32(mean)
        x *= self.window
        return self._ccs.forward(x)

    def prepare(self, frame: np.ndarray) -> PreparedFrame:
        """Compute and cache a frame's spectra (grey or BGR; uint8 or float)."""
        gray = self._gray(frame)
        mean = float(gray.mean())
        energy = float(gray.var())
        spec = self._windowed_spectrum(gray, mean)
        edges = self._ccs.edges(spec)
        lp = cv2.remap(self._ccs.shifted_abs(spec, edges), self._lp_map_x, self._lp_map_y, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        # per-ring power and its noise floor (white noise is flat; take the quietest rings)
        power = np.einsum("ij,ij->j", lp, lp) / lp.shape[0]
        noise = _percentile(power, 5.0)
        if self.snr_weighting and noise > 0:
            signal = np.maximum(power - noise, 0.0)
            snr = signal / (signal + noise)
        else:
            snr = np.ones_like(power)
        # whiten (magnitude ~ 1/f for natural images) and weight the rings
        weight = (self._lp_radius * snr * self._lp_window).astype(np.float32)
        lp *= weight[None, :]
        lp -= lp.mean()
        lps = self._lp_ccs.forward(lp)
        lp_edges = self._lp_ccs.edges(lps)
        _normalise(self._lp_ccs.inner(lps), lp_edges, 1.0, 1.0)
        self._lp_ccs.set_edges(lps, lp_edges)
        return PreparedFrame(gray=gray, spectrum=spec, logpolar=lps, ring_snr=snr.astype(np.float32),
                             energy=energy, refine_level=self._refine_level(power, noise),
                             _cache={"mean": mean, "edges": edges, "lp_edges": lp_edges})

    def _refine_level(self, power: np.ndarray, noise: float) -> int:
        """Finest pyramid level on which signal dominates the frame's gradient energy.

        Gauss-Newton steps shrink by the noise share of the template's gradient energy (the
        Hessian counts it, the error signal does not): on smooth, noisy ground the refinement
        would crawl at full resolution. ``power`` is the per-ring power of the log-polar
        magnitude, ``noise`` its white-noise floor.
        """
        if not self.refine_iterations or noise <= 0:
            return 0
        signal = np.maximum(power - noise, 0.0)
        share = np.einsum("lj,j->l", self._level_weights, signal) / np.maximum(
            np.einsum("lj,j->l", self._level_weights, power), _EPS)
        good = np.flatnonzero(share >= _REFINE_SIGNAL)
        return int(good[0]) if good.size else len(share) - 1

    # ------------------------------------------------------------------ peaks
    @staticmethod
    def _subpixel(r: np.ndarray, iy: int, ix: int) -> tuple[float, float, float]:
        """Gaussian fit around the integer peak (iy, ix) of a periodic surface."""
        h, w = r.shape
        c = max(float(r[iy, ix]), _EPS)
        l0 = math.log(c)
        vals = []
        for a, b in ((r[(iy - 1) % h, ix], r[(iy + 1) % h, ix]), (r[iy, (ix - 1) % w], r[iy, (ix + 1) % w])):
            vals.append((math.log(max(float(a), c * 1e-3)), math.log(max(float(b), c * 1e-3))))
        dy = _fit_offset(vals[0][0], l0, vals[0][1])
        dx = _fit_offset(vals[1][0], l0, vals[1][1])
        # height of the fitted Gaussian at its centre
        height = c
        for (lm, lp), d in zip(vals, (dy, dx)):
            curv = lm - 2 * l0 + lp
            if curv < 0:
                height *= math.exp(-0.5 * curv * d * d)
        return iy + dy, ix + dx, height

    @staticmethod
    def _peaks(r: np.ndarray, count: int, exclude: int = 3) -> list[tuple[int, int, float]]:
        """The ``count`` highest local maxima (integer positions) of a periodic surface.

        Masks the neighbourhood of each peak found in place and restores it before returning.
        """
        h, w = r.shape
        out: list[tuple[int, int, float]] = []
        saved = []
        for _ in range(count):
            iy, ix = divmod(int(np.argmax(r)), w)
            val = float(r[iy, ix])
            if not np.isfinite(val):
                break
            out.append((iy, ix, val))
            if len(out) == count:
                break
            if exclude <= iy < h - exclude and exclude <= ix < w - exclude:
                block = (slice(iy - exclude, iy + exclude + 1), slice(ix - exclude, ix + exclude + 1))
            else:
                block = np.ix_(np.arange(iy - exclude, iy + exclude + 1) % h,
                               np.arange(ix - exclude, ix + exclude + 1) % w)
            saved.append((block, r[block].copy()))
            r[block] = -np.inf
        for block, values in reversed(saved):
            r[block] = values
        return out

    # ------------------------------------------------------------------ rotation and scale
    def _rotation_scale(self, a: PreparedFrame, b: PreparedFrame, prior: Prior | None,
                        memo: dict | None = None) -> list[tuple[float, float, float]]:
        """Candidate (angle_deg mod 180 in (-90, 90], scale, peak) of the matrix b -> a.

        ``memo``: the pair's surfaces (see :meth:`register`)."""
        na, nr = self.angle_bins, self.radius_bins
        r = memo.get("logpolar") if memo is not None else None
        if r is None:
            ccs = self._lp_ccs
            cross = np.empty((na, nr), np.float32)
            inner = ccs.inner(cross)
            np.conjugate(ccs.inner(a.logpolar), out=inner)
            inner *= ccs.inner(b.logpolar)
            inner *= self._lp_gauss[0]
            ccs.set_edges(cross, np.conj(a._cache["lp_edges"]) * b._cache["lp_edges"] * self._lp_gauss[1])
            r = ccs.inverse(cross)
            r *= np.float32(1.0 / self._lp_ref)
            if memo is not None:
                memo["logpolar"] = r  # only read from here on (the peak search masks a copy)
        # The log-polar image of b is that of a shifted by (+log s, -angle) (rows: angle, cols: log r).
        # Restrict the radius shift to +-nr/4 (scale within exp(+-nr/4 * step)) and apply priors.
        allowed = self._lp_allowed
        shifts_r = np.fft.fftfreq(nr, 1.0 / nr)
        if prior is not None and prior.scale is not None:
            target = math.log(prior.scale) / self._log_step
            tol = max(abs(math.log1p(prior.scale_tol)) / self._log_step, 0.51)
            allowed = allowed & (np.abs(shifts_r - target) <= tol)[None, :]
        if prior is not None and prior.angle_deg is not None and prior.angle_tol_deg < 90:
            shifts_a = np.fft.fftfreq(na, 1.0 / na) * (180.0 / na)  # degrees, = -angle (mod 180)
            diff = (-shifts_a - prior.angle_deg + 90.0) % 180.0 - 90.0
            allowed = allowed & (np.abs(diff) <= max(prior.angle_tol_deg, 180.0 / na))[:, None]
        r_masked = np.where(allowed, r, -np.inf)
        peaks = self._peaks(r_masked, self.max_candidates)
        if not peaks:
            return [(0.0, 1.0, 0.0)]
        best = peaks[0][2]
        out = []
        for iy, ix, val in peaks:
            if out and val < self.candidate_ratio * best:
                break
            fy, fx, height = self._subpixel(r, iy, ix)
            if prior is not None and prior.scale is not None and prior.scale_tol == 0:
                fx = math.log(prior.scale) / self._log_step
            d_angle = (fy + na / 2) % na - na / 2
            d_rad = (fx + nr / 2) % nr - nr / 2
            angle = _wrap180(-d_angle * 180.0 / na)
            angle = (angle + 90.0) % 180.0 - 90.0
            out.append((angle, math.exp(d_rad * self._log_step), height))
        return out

    # ------------------------------------------------------------------ translation
    def _translation_weight(self, a: PreparedFrame,
                            b: PreparedFrame) -> tuple[np.ndarray, np.ndarray, float, float]:
        """Weight of the translation POMF (CCS interior and edges) and its peak reference/noise."""
        gauss_in, gauss_e = self._gauss
        if self.snr_weighting:
            snr = np.zeros(self.radius_bins + 1, np.float32)  # the last ring: outside the band
            np.sqrt(a.ring_snr * b.ring_snr, out=snr[:-1])
            w_in = np.take(snr, self._ring_index[0])
            w_in *= gauss_in
            w_e = np.take(snr, self._ring_index[1]) * gauss_e
        else:
            w_in, w_e = gauss_in, gauss_e
        h, w = self.shape
        mult = self._ccs.edge_mult
        ref = (2.0 * float(w_in.sum(dtype=np.float64)) + float((w_e * mult).sum())) / (h * w)
        energy = 2.0 * float(np.einsum("ij,ij->", w_in, w_in)) + float((w_e * w_e * mult).sum())
        noise = math.sqrt(energy) / (h * w)
        return w_in, w_e, ref, noise

    def _translation(self, a: PreparedFrame, b: PreparedFrame, angle: float, scale: float,
                     prior: Prior | None,
                     weight: tuple[np.ndarray, np.ndarray, float, float],
                     memo: dict | None = None) -> list[Candidate]:
        """Score the hypotheses ``angle`` and ``angle + 180`` of the matrix b -> a.

        ``memo``: the pair's surfaces (see :meth:`register`)."""
        h, w = self.shape
        ccs = self._ccs
        w_in, w_e, ref, noise = weight
        if ref <= _EPS:
            return [Candidate(angle, scale, (0.0, 0.0), 0.0)]
        a_in, a_e = ccs.inner(a.spectrum), a._cache["edges"]
        warped_b: list[tuple[np.ndarray, np.ndarray]] = []

        def spectrum_b() -> tuple[np.ndarray, np.ndarray]:
            """CCS interior and edges of b', once."""
            if not warped_b:
                # With M = [L | t] (L = scale * R(angle)), b'(q) = b(L^-1 (q - c) + c) = a(q + tau)
                # where t = c + tau - L c: warping b by L about the centre c leaves a pure translation.
                lin_fwd = similarity_matrix(angle, scale, center=self.center)  # maps b pixels to b' pixels
                mean_b = b._cache["mean"]
                warped = cv2.warpAffine(b.gray, lin_fwd, (w, h), flags=cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_CONSTANT, borderValue=mean_b)
                spec_b = self._windowed_spectrum(warped, mean_b)
                warped_b.append((ccs.inner(spec_b), ccs.edges(spec_b)))
            return warped_b[0]

        def surface(mirrored: bool) -> np.ndarray:
            """The translation POMF's surface of b' (or its point mirror), through ``memo``."""
            key = ("translation", angle, scale, mirrored)
            r = memo.get(key) if memo is not None else None
            if r is None:
                r = ccs.inverse(pomf(mirrored))
                if memo is not None:
                    memo[key] = r  # the peak search restores what it masks
            return r

        def pomf(mirrored: bool) -> np.ndarray:
            """Weighted, phase-normalised cross-power spectrum of a and b' (or its point mirror),
            CCS-packed: conj(a) b', or conj(a) ramp conj(b') for b' rotated by 180 deg."""
            b_in, b_e = spectrum_b()
            packed = np.empty((h, w), np.float32)
            inner = ccs.inner(packed)
            if mirrored:
                np.multiply(a_in, b_in, out=inner)
                np.conjugate(inner, out=inner)
                inner *= self._mirror[0]
                edges = np.conj(a_e * b_e) * self._mirror[1]
            else:
                np.conjugate(a_in, out=inner)
                inner *= b_in
                edges = np.conj(a_e) * b_e
            _normalise(inner, edges, w_in, w_e)
            ccs.set_edges(packed, edges)
            return packed

        keep, flip = True, True
        if prior is not None and prior.angle_deg is not None and prior.angle_tol_deg < 90:
            d0 = abs(_wrap180(angle - prior.angle_deg))
            keep = d0 <= 90
            flip = d0 > 90 - prior.angle_tol_deg or not keep
        hyps = [(angle, False)] if keep else []
        if flip:
            hyps.append((_wrap180(angle + 180.0), True))

        out = []
        for hyp_angle, mirrored in hyps:
            r = surface(mirrored)
            peaks = self._peaks(r, 2, exclude=4)
            if prior is not None and prior.shift is not None:
                # also the best peak within the prior's tolerance (periodic ground)
                peaks += self._shift_peak(r, hyp_angle, scale, prior)
            if memo is not None:  # for a farther layer's peak (register, _farther_candidate)
                memo.setdefault("surfaces", {})[(hyp_angle, scale)] = r
            for iy, ix, _ in dict.fromkeys(peaks):
                out.append(self._candidate(r, iy, ix, hyp_angle, scale, weight))
        return out

    def _candidate(self, r: np.ndarray, iy: int, ix: int, angle: float, scale: float,
                   weight: tuple[np.ndarray, np.ndarray, float, float]) -> Candidate:
        """The hypothesis of the translation surface ``r``'s peak (iy, ix) for the rotation
        ``angle`` and ``scale`` (b warped by them before the POMF)."""
        h, w = self.shape
        _, _, ref, noise = weight
        k = math.sqrt(2.0 * math.log(h * w)) + 1.0
        fy, fx, height = self._subpixel(r, iy, ix)
        dy = (fy + h / 2) % h - h / 2
        dx = (fx + w / 2) % w - w / 2
        tau = (-dx, -dy)  # b'(q) = a(q + tau) is a shifted by -tau
        m = similarity_matrix(angle, scale, tau, center=self.center)
        peak = (height - k * noise) / max(ref - k * noise, _EPS)
        return Candidate(angle, scale, (float(m[0, 2]), float(m[1, 2])), float(np.clip(peak, 0.0, 1.0)))

    def _farther_candidate(self, best: Candidate, memo: dict,
                           weight: tuple[np.ndarray, np.ndarray, float, float]) -> Candidate | None:
        """A farther layer's hypothesis for ``best``: the highest local maximum of its translation
        surface on the segment from ``_LAYER_RATIO[0]`` to ``_LAYER_RATIO[1]`` of its centre
        displacement (within 1 px of it), or None (none there, or ``best`` too near the origin
        for two layers to part).

        A peak's offset on the surface is minus the frame centre's displacement, so a layer
        farther than ``best``'s lies there (see :meth:`_ground_first`), even where it is not among
        the surface's highest peaks (a large roof fills the view). Reads about 3 samples per
        pixel of the segment.
        """
        r = memo.get("surfaces", {}).get((best.angle_deg, best.scale))
        if r is None:
            return None
        h, w = r.shape
        cx, cy = self.center
        rad = math.radians(best.angle_deg)
        co, si = best.scale * math.cos(rad), best.scale * math.sin(rad)
        py = -(si * cx + co * cy + best.shift[1] - cy)  # the peak's offset: minus the displacement
        px = -(co * cx - si * cy + best.shift[0] - cx)
        norm = math.hypot(py, px)
        lo, hi = _LAYER_RATIO
        if norm * (hi - lo) < 2.0:
            return None
        n = int(math.ceil((hi - lo) * norm)) + 1
        t = np.arange(n) * ((hi - lo) / (n - 1)) + lo
        ys = np.rint(np.concatenate([t * py - px / norm, t * py, t * py + px / norm])).astype(np.intp)
        xs = np.rint(np.concatenate([t * px + py / norm, t * px, t * px - py / norm])).astype(np.intp)
        ys %= h
        xs %= w
        ys *= w
        ys += xs
        flat = r.reshape(-1)
        vals = flat[ys]
        i = int(np.argmax(vals))
        val = float(vals[i])
        # not worth a look well below the peak _ground_first asks for (the sample is up to ~30 %
        # below the fitted height that _candidate normalises)
        _, _, ref, noise = weight
        k = math.sqrt(2.0 * math.log(h * w)) + 1.0
        floor = 0.7 * max(_EXPECTED_PEAK * best.peak, _CLEAR_PEAK)
        if not val - k * noise >= floor * (ref - k * noise):
            return None
        y0, x0 = divmod(int(ys[i]), w)
        around = flat[((y0 + _AROUND[0]) % h) * w + (x0 + _AROUND[1]) % w]
        if val < float(around.max()):
            return None  # the segment's highest value is on a slope, not a peak
        return self._candidate(r, y0, x0, best.angle_deg, best.scale, weight)

    def _shift_peak(self, r: np.ndarray, angle: float, scale: float, prior: Prior) -> list[tuple[int, int, float]]:
        """The highest translation peak whose matrix shift lies within the prior's tolerance
        (``[]`` when none is finite): ``_peaks`` of ``r`` masked to that disc, read on the rows and
        columns the disc can touch only (the mask of the whole surface cost more than the peak)."""
        h, w = self.shape
        if self._shift_axes is None:
            self._shift_axes = (scipy.fft.fftfreq(h, 1.0 / h), scipy.fft.fftfreq(w, 1.0 / w))
        ys, xs = self._shift_axes
        # matrix shift for a peak at d: t = c + tau - L c with tau = -d
        lin = similarity_matrix(angle, scale)[:, :2]
        base = np.asarray(self.center) - lin @ np.asarray(self.center)
        tx2 = (base[0] - xs - prior.shift[0]) ** 2
        ty2 = (base[1] - ys - prior.shift[1]) ** 2
        tol2 = prior.shift_tol ** 2
        # tx^2 + ty^2 <= tol^2 needs tx^2 <= tol^2 and ty^2 <= tol^2 (also in floating point)
        rows, cols = np.flatnonzero(ty2 <= tol2), np.flatnonzero(tx2 <= tol2)
        if not rows.size or not cols.size:
            return []
        inside = tx2[cols][None, :] + ty2[rows][:, None] <= tol2
        masked = np.where(inside, r[np.ix_(rows, cols)], -np.inf)
        # rows and columns ascending: the first maximum here is the first of the whole masked surface
        i, j = divmod(int(np.argmax(masked)), cols.size)
        iy, ix = int(rows[i]), int(cols[j])
        val = float(r[iy, ix])
        return [(iy, ix, val)] if np.isfinite(masked[i, j]) else []

    # ------------------------------------------------------------------ refinement
    def _grid(self, level: int) -> _Grid:
        grid = self._grids.get(level)
        if grid is None:
            h, w = self.shape
            for _ in range(level):  # cv2.pyrDown sizes; level pixel (u, v) is full pixel 2^L (u, v)
                h, w = (h + 1) // 2, (w + 1) // 2
            stride = max(1, int(round(math.sqrt(h * w / _REFINE_SAMPLES))))
            ys = np.arange(0, h, stride)
            xs = np.arange(0, w, stride)
            f = 2 ** level
            yy, xx = np.meshgrid(ys, xs, indexing="ij")
            window = np.ascontiguousarray(self.window[ys * f][:, xs * f])
            grid = _Grid(level, stride, (len(ys), len(xs)), (self.center[0] / f, self.center[1] / f),
                         window, np.stack([xx.ravel(), yy.ravel()], axis=-1).astype(np.float32))
            self._grids[level] = grid
        return grid

    @staticmethod
    def _smooth(frame: PreparedFrame, level: int) -> np.ndarray:
        """The frame on a pyramid level, smoothed for the refinement (cached in the frame)."""
        key = ("smooth", level)
        out = frame._cache.get(key)
        if out is None:
            pyramid = frame._cache.setdefault("pyramid", [frame.gray])
            while len(pyramid) <= level:
                pyramid.append(cv2.pyrDown(pyramid[-1]))
            out = cv2.GaussianBlur(pyramid[level], (3, 3), 0)  # [1, 2, 1] / 4: variance 0.5
            frame._cache[key] = out
        return out

    def _template(self, frame: PreparedFrame) -> _Template:
        """The reference side of the refinement (built once per frame)."""
        tpl = frame._cache.get("template")
        if tpl is None:
            grid = self._grid(frame.refine_level)
            img = self._smooth(frame, grid.level)
            st = grid.stride
            rh, rw = grid.size
            # at each grid sample: twice the gradient (central differences; 0 on the image's
            # border, as with a reflected border) and the level image itself
            at = np.empty((3, rh, rw), np.float32)
            at[2] = img[::st, ::st]
            inner_x = (img.shape[1] - 2) // st  # grid columns 1 .. inner_x have both neighbours
            inner_y = (img.shape[0] - 2) // st
            at[0, :, 0] = 0.0
            at[0, :, inner_x + 1:] = 0.0
            np.subtract(img[::st, st + 1::st][:, :inner_x], img[::st, st - 1::st][:, :inner_x],
                        out=at[0, :, 1:inner_x + 1])
            at[1, 0] = 0.0
            at[1, inner_y + 1:] = 0.0
            np.subtract(img[st + 1::st, ::st][:inner_y], img[st - 1::st, ::st][:inner_y],
                        out=at[1, 1:inner_y + 1])
            energy = at[0] * at[0]
            energy += at[1] * at[1]
            energy *= grid.window
            if energy.size <= _REFINE_MIN_KEEP:
                keep = np.arange(energy.size)
            else:
                # above a fraction of the mean energy, lowered until enough are kept
                level = np.float32(_REFINE_KEEP * cv2.mean(energy)[0])
                keep = np.flatnonzero(energy > level)
                while keep.size < _REFINE_MIN_KEEP and level > 0:
                    level = level * np.float32(0.5) if level > 1e-6 * energy.max() else np.float32(0)
                    keep = np.flatnonzero(energy > level)
            points = np.take(grid.points, keep, axis=0)
            window = np.take(grid.window, keep)
            xc = points[:, 0] - np.float32(grid.center[0])
            yc = points[:, 1] - np.float32(grid.center[1])
            sd = np.empty((6, keep.size), np.float32)
            np.take(at.reshape(3, -1), keep, axis=1, out=sd[:3])
            sd[5] = sd[2]
            sd[:2] *= np.float32(0.5)
            np.multiply(xc, sd[0], out=sd[2])
            sd[2] += yc * sd[1]
            np.multiply(xc, sd[1], out=sd[3])
            sd[3] -= yc * sd[0]
            sd[4] = 1.0
            if keep.size:
                sd[5] -= np.float32(cv2.mean(sd[5])[0])
            tpl = _Template(grid, points[None], window, float(window.sum()), sd)
            frame._cache["template"] = tpl
        return tpl

    def _refine(self, a: PreparedFrame, b: PreparedFrame, m: np.ndarray,
                layered: bool = False) -> np.ndarray | None:
        """Inverse compositional Gauss-Newton on a similarity + brightness gain/offset.

        ``m`` maps b -> a; returns the refined matrix, or None when it does not converge. It runs
        on ``a.refine_level`` of both frames' pyramids, with the informative samples of a grid on
        ``a`` (the template) and ``b`` interpolated at their warped positions. Only
        single-threaded reductions (OpenCV, and BLAS products too small for BLAS threads, whose
        spinning would stall against any busy neighbour process: :func:`_gram`).
        """
        h, w = self.shape
        tpl = self._template(a)
        if tpl.sd.shape[1] < 16:
            return None
        grid = tpl.grid
        img_b = self._smooth(b, grid.level)
        hb, wb_ = img_b.shape
        offset_b = np.float32(b._cache["mean"])
        lo = _REFINE_MARGIN
        f = float(2 ** grid.level)
        cx, cy = grid.center
        reach = max(cx, cy) * 1.5
        # the matrix as plain floats, in level pixels (its linear part is the same, its shift / f)
        m00, m01, m02 = float(m[0, 0]), float(m[0, 1]), float(m[0, 2]) / f
        m10, m11, m12 = float(m[1, 0]), float(m[1, 1]), float(m[1, 2]) / f
        start = np.array([[m00, m01, m02 * f], [m10, m11, m12 * f]])
        moved = math.inf  # level pixels the samples moved since their mask was built
        fit_start = fit_end = -math.inf  # weighted correlation of b with the template
        samples = np.empty((2, tpl.sd.shape[1]), np.float32)  # b at the samples (centred roughly), squared
        robust: np.ndarray | None = None  # per-sample biweight once a second layer showed up
        for it in range(self.refine_iterations):
            # where the template's samples fall in b: the inverse of the matrix
            det = m00 * m11 - m01 * m10
            if abs(det) < _EPS:
                return None
            ia, ib, ic, id_ = m11 / det, -m01 / det, -m10 / det, m00 / det
            where = cv2.transform(tpl.points, np.array([[ia, ib, -(ia * m02 + ib * m12)],
                                                        [ic, id_, -(ic * m02 + id_ * m12)]]))
            warped = cv2.remap(img_b, where, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=0.0).ravel()
            if moved > lo - 0.5:
                # use the samples at least _REFINE_MARGIN inside b: they stay inside (and the
                # mask, Hessian and template moments stay valid) while the warp moves them less
                inside = cv2.inRange(where, (lo, lo), (wb_ - 1 - lo, hb - 1 - lo)).ravel()
                wgt = cv2.multiply(tpl.window, inside, scale=1.0 / 255.0, dtype=cv2.CV_32F).ravel()
                if robust is not None:
                    wgt *= robust
                wsd = tpl.sd * wgt
                # Gauss-Newton matrix and template moments
                hess = _gram(tpl.sd, wsd)
                wsum = float(hess[4, 4])  # row 4: ones
                if wsum < 0.05 * tpl.window_sum:
                    return None
                mt = hess[4, 5] / wsum  # rows 4 and 5: ones and the centred template
                vt = hess[5, 5] / wsum - mt * mt
                if vt <= _EPS:
                    return None
                invertible, inverse = cv2.invert(hess, flags=cv2.DECOMP_LU)
                if not invertible:
                    return None
                solve = inverse[:4]
                # see below: sums of the residual = gain * (proj - mw * ones) - centred template
                ones, tmpl = hess[:, 4], hess[:, 5] - mt * hess[:, 4]
                solve_ones, solve_tmpl = (solve @ ones).tolist(), (solve @ tmpl).tolist()
                ones5, tmpl5 = float(ones[5]), float(tmpl[5])
                moved = 0.0
            # Brightness gain/offset of the warped image against the template from their moments,
            # corrected to first order by the solve together with the warp (the overlap's mean and
            # variance absorb part of a shift of smooth ground; without the joint system each
            # update is a small fraction of the error on featureless ground). With the residual
            # e = g (u - mw) - (t - mt), every sum over the samples comes from one pass:
            # sum w sd_j e = g (sum w sd_j u - mw sum w sd_j) - (sum w sd_j t - mt sum w sd_j).
            np.subtract(warped, offset_b, out=samples[0])  # centred roughly (precision of the float32 sums)
            np.multiply(samples[0], samples[0], out=samples[1])
            sums = _gram(wsd, samples)  # column 0: sum w sd_j u; row 4 of column 1: sum w u^2
            proj = sums[:, 0]
            mw = float(proj[4]) / wsum
            vw = float(sums[4, 1]) / wsum - mw * mw
            if vw <= _EPS:
                return None
            gain = math.sqrt(vt / vw)
            if layered and robust is None and it == 0:
                # a layer at another depth is in view and ``m`` is the ground's: weight its
                # misaligned samples down before they pull the fit
                robust = self._second_layer(samples[0], tpl.sd[5], gain, mw, mt, wgt, always=True)
                if robust is not None:
                    moved = math.inf
                    continue
            # weighted correlation of b with the template: the residual's energy is -2 rhs[5]
            # (row 5 is the centred template; the residual has zero weighted mean)
            fit = 1.0 + (gain * (float(proj[5]) - mw * ones5) - tmpl5) / (wsum * vt)
            if it == 0:
                fit_start = fit
            gm = gain * mw
            tx, ty, da, db = (gain * x - gm * o - t for x, o, t in
                              zip((solve @ proj).tolist(), solve_ones, solve_tmpl))
            # warp increment about the centre, x -> (1+da) x - db y + tx in centred coordinates,
            # composed in front of the matrix
            c, s_ = 1.0 + da, db
            ex, ey = tx + cx - c * cx + s_ * cy, ty + cy - s_ * cx - c * cy
            m00, m01, m02, m10, m11, m12 = (c * m00 - s_ * m10, c * m01 - s_ * m11, c * m02 - s_ * m12 + ex,
                                            s_ * m00 + c * m10, s_ * m01 + c * m11, s_ * m02 + c * m12 + ey)
            # converged when the frame corners move less than _REFINE_TOL (full-resolution pixels)
            step = max(abs(tx), abs(ty)) + (abs(da) + abs(db)) * reach
            if step * f < _REFINE_TOL:
                if robust is None and self.layered_tail and it + 1 < self.refine_iterations:
                    robust = self._second_layer(samples[0], tpl.sd[5], gain, mw, mt, wgt)
                    if robust is not None:
                        # parallax: samples of a second depth pull the fit; continue without them
                        moved = math.inf
                        continue
                fit_end = fit
                break
            moved += step
        out = np.array([[m00, m01, m02 * f], [m10, m11, m12 * f]])
        # reject a refinement that wandered far from the iFMI estimate (it diverged), unless it
        # converged to a better fit and stayed within 10 % of the frame size (iFMI can be off by
        # a few degrees on featureless ground, which moves the corners by more than 3 %)
        moved_px = max(abs(d[0] * x + d[1] * y + d[2]) for d in (out - start).tolist()
                       for x in (0, w - 1) for y in (0, h - 1))
        converged_better = fit_end > fit_start and moved_px <= 0.1 * max(h, w)
        if moved_px > max(3.0, 0.03 * max(h, w)) and not converged_better:
            return None
        return out

    @staticmethod
    def _second_layer(u: np.ndarray, t: np.ndarray, gain: float, mw: float, mt: float,
                      wgt: np.ndarray, always: bool = False) -> np.ndarray | None:
        """Tukey biweights of the refinement's samples when its converged residual has a heavy
        tail, else None.

        ``u`` is b at the samples (centred roughly), ``t`` the centred template, ``gain``, ``mw``,
        ``mt`` the brightness model, ``wgt`` the samples' weights (0 outside). Residuals of one
        depth (noise, interpolation) are near Gaussian: few lie beyond ``_TAIL_SIGMAS`` robust
        sigmas. Where a layer at another depth (roofs, trees above the ground) stands in the view,
        its samples are misaligned once the ground is aligned (or the fit compromises between
        both): more than ``_TAIL_SHARE`` of them lie in the tail, and weighting them down lets the
        fit follow the majority, the ground.
        """
        g, offset = np.float32(gain), np.float32(gain * mw - mt)
        # the test on every _TAIL_STRIDE-th sample (the median and the tail share need no more)
        e = g * u[::_TAIL_STRIDE] - t[::_TAIL_STRIDE]
        e = np.abs(e[wgt[::_TAIL_STRIDE] > 0] - offset)
        if e.size < 64:
            return None
        sigma = 1.4826 * _percentile(e, 50.0)
        if sigma <= _EPS or not always and np.count_nonzero(e > _TAIL_SIGMAS * sigma) <= _TAIL_SHARE * e.size:
            return None
        z = g * u - t
        z -= offset
        np.abs(z, out=z)
        z *= np.float32(1.0 / (_BIWEIGHT_C * sigma))
        np.minimum(z, 1.0, out=z)
        z *= z
        np.subtract(1.0, z, out=z)
        z *= z
        return z

    # ------------------------------------------------------------------ public
    def register(self, a: np.ndarray | PreparedFrame, b: np.ndarray | PreparedFrame,
                 prior: Prior | None = None) -> Registration:
        """Register the new frame ``b`` to the reference ``a``.

        Returns the similarity mapping pixels of ``b`` to pixels of ``a`` with its confidence.
        Arrays are prepared on the fly; pass :class:`PreparedFrame` objects to reuse spectra.
        """
        pa = a if isinstance(a, PreparedFrame) else self.prepare(a)
        pb = b if isinstance(b, PreparedFrame) else self.prepare(b)
        if pa.blank or pb.blank:
            return Registration(matrix=similarity_matrix(0.0, 1.0), confidence=0.0)

        # The prior-free work on this pair (correlation surfaces, refinements) is kept until
        # another pair is registered: the tracker often registers a pair twice in a row, with two
        # priors (telemetry's, then the motion model's), and gets the same results for less.
        pair = self._pair
        if pair is None or pair[0] is not pa or pair[1] is not pb:
            pair = self._pair = (pa, pb, {})
        memo = pair[2]
        cands: list[Candidate] = []
        weight = memo.get("weight")
        if weight is None:
            weight = memo["weight"] = self._translation_weight(pa, pb)
        for angle, scale, _ in self._rotation_scale(pa, pb, prior, memo):
            cands.extend(self._translation(pa, pb, angle, scale, prior, weight, memo))
        if (prior is not None and prior.angle_deg is not None and prior.scale is not None
                and max(c.peak for c in cands) < _WEAK_PEAK):
            # Little overlap starves the log-polar POMF first: also try the expected rotation and
            # scale directly in the translation step (the refinement then corrects them).
            cands.extend(self._translation(pa, pb, prior.angle_deg, prior.scale, prior, weight, memo))
        cands = self._rank(cands, prior)
        farther = self._farther_candidate(cands[0], memo, weight)
        if farther is not None:
            cands.append(farther)
        cands, layered = self._ground_first(cands)
        best = cands[0]
        m = similarity_matrix(best.angle_deg, best.scale)
        m[:, 2] = best.shift
        ambiguous = any(c.peak >= 0.8 * best.peak and not self._same(c, best) for c in cands[1:])
        refined = False
        if self.refine_iterations and best.peak > 0:
            key = ("refined", m.tobytes(), layered)
            if key not in memo:
                memo[key] = self._refine(pa, pb, m, layered)
            m_ref = None if memo[key] is None else memo[key].copy()
            if m_ref is not None:
                m, refined = m_ref, True
        return Registration(matrix=m, confidence=best.peak, ambiguous=ambiguous,
                            candidates=tuple(cands), refined=refined)

    @staticmethod
    def _same(c: Candidate, d: Candidate) -> bool:
        return (abs(_wrap180(c.angle_deg - d.angle_deg)) < 1.0 and abs(c.scale / d.scale - 1) < 0.02
                and math.hypot(c.shift[0] - d.shift[0], c.shift[1] - d.shift[1]) < 2.0)

    def _ground_first(self, cands: list[Candidate]) -> tuple[list[Candidate], bool]:
        """``cands`` with the ground layer's placement first, and whether a layer above it shows.

        Seen from above, a layer at another depth (roofs, boxes, tree crowns) moves with the same
        rotation and scale as the ground but by a displacement of the frame centre that is longer
        (it is nearer): the translation POMF shows a second peak on the line from the centre
        through the ground's (eFMT, Remote Sensing 2021). A clear candidate of the same rotation
        and scale whose centre displacement lies on that line at ``_LAYER_RATIO`` of another's is
        the farther layer of the two: when the best candidate has such a partner, the partner
        (the farthest of several) is the ground and goes first. Peaks a period apart on periodic
        ground are not on that line unless the step is at least 1/(1 - 0.6) periods long along a
        lattice direction.
        """
        best = cands[0]
        floor = max(_EXPECTED_PEAK * best.peak, _CLEAR_PEAK)
        cx, cy = self.center

        def displacement(c: Candidate) -> tuple[float, float]:
            rad = math.radians(c.angle_deg)
            co, si = c.scale * math.cos(rad), c.scale * math.sin(rad)
            return co * cx - si * cy + c.shift[0] - cx, si * cx + co * cy + c.shift[1] - cy

        def farther(near: tuple[float, float], far: tuple[float, float]) -> float | None:
            """``far``'s displacement over ``near``'s when ``far`` is a farther layer of it."""
            norm2 = near[0] * near[0] + near[1] * near[1]
            lam = (far[0] * near[0] + far[1] * near[1]) / max(norm2, _EPS)
            off = abs(far[0] * near[1] - far[1] * near[0]) / math.sqrt(max(norm2, _EPS))
            if _LAYER_RATIO[0] <= lam <= _LAYER_RATIO[1] and off <= 1.0 + 0.03 * math.sqrt(norm2) \
                    and math.hypot(far[0] - near[0], far[1] - near[1]) >= 2.0:
                return lam
            return None

        d_best = displacement(best)
        chosen, ratio, layered = best, 1.0, False
        for c in cands[1:]:
            if c.peak < floor or abs(_wrap180(c.angle_deg - best.angle_deg)) >= 1.0 \
                    or abs(c.scale / best.scale - 1) >= 0.02:
                continue
            d = displacement(c)
            lam = farther(d_best, d)
            if lam is not None and lam < ratio:
                chosen, ratio = c, lam
            layered = layered or lam is not None or farther(d, d_best) is not None
        if chosen is best:
            return cands, layered
        return [chosen] + [c for c in cands if c is not chosen], True

    @staticmethod
    def _rank(cands: list[Candidate], prior: Prior | None) -> list[Candidate]:
        """Best first: by peak; with a prior, near-equal peaks are decided by the prior."""
        cands = sorted(cands, key=lambda c: -c.peak)
        if prior is None or len(cands) < 2:
            return cands

        def distance(c: Candidate) -> float:
            d = 0.0
            if prior.angle_deg is not None:
                d += abs(_wrap180(c.angle_deg - prior.angle_deg)) / max(prior.angle_tol_deg, 1e-3)
            if prior.scale is not None:
                d += abs(math.log(c.scale / prior.scale)) / max(prior.scale_tol, 1e-3)
            if prior.shift is not None:
                d += math.hypot(c.shift[0] - prior.shift[0], c.shift[1] - prior.shift[1]) / max(
                    prior.shift_tol, 1e-3)
            return d

        top = cands[0].peak
        if prior.shift is not None:
            # periodic ground: a peak one period off can be higher than the true one (it overlaps
            # more); a clear peak where the motion model expects the frame wins
            floor = max(_EXPECTED_PEAK * top, _CLEAR_PEAK)
            near = [c for c in cands if c.peak >= floor and math.hypot(
                c.shift[0] - prior.shift[0], c.shift[1] - prior.shift[1]) <= prior.shift_tol]
            if near:
                chosen = min(near, key=distance)
                return [chosen] + [c for c in cands if c is not chosen]
        close = [c for c in cands if c.peak >= 0.7 * top]
        rest = [c for c in cands if c.peak < 0.7 * top]
        return sorted(close, key=distance) + rest
