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
   warp and a brightness gain/offset) refine the estimate below the log-polar grid.

Every cross-power spectrum is weighted by a Gaussian low-pass, which turns the POMF peak into a
sampled Gaussian; fitting a Gaussian to the 3 samples around the maximum (a parabola on their
logarithms) then locates it without the ~0.1 px bias of a plain parabola.

Conventions (:mod:`photomap.geometry`): OpenCV pixel coordinates (x right, y down, origin at the centre
of the top-left pixel). A registration result ``matrix`` is 2x3 and maps pixels of the new frame
``b`` to pixels of the reference ``a``: ``p_a = matrix @ [x_b, y_b, 1]``; ``angle_deg`` and ``scale``
are read from it as ``degrees(atan2(m10, m00))`` and ``sqrt(det)``, ``shift`` is its last column.

The module is pure: arrays in, arrays out; a :class:`Registrar` only caches constants for one
frame shape, and a :class:`PreparedFrame` caches one frame's spectra so that, in a sequence, each
new frame costs 3 forward and at most 3 inverse real FFTs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.fft

from photomap.config import RegistrationConfig
from photomap.geometry import similarity_matrix

__all__ = ["Prior", "Candidate", "Registration", "PreparedFrame", "Registrar"]

_EPS = 1e-12
_REFINE_SAMPLES = 16384  # the refinement samples about this many pixels on a regular grid
_WEAK_PEAK = 0.5  # below this translation peak, the prior's own rotation/scale is tried too
_EXPECTED_PEAK = 0.35  # a peak at the expected shift wins over higher ones at this fraction of the best
_CLEAR_PEAK = 0.15  # ... and at least this high (well above noise, which scores ~0)


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
    gradients: np.ndarray | None = field(default=None)  # Nx4 steepest-descent images (refinement)
    smooth: np.ndarray | None = field(default=None)  # smoothed gray used by the refinement


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
    return float(np.clip(0.5 * (lm - lp) / den, -0.5, 0.5))


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
    """

    def __init__(self, shape: tuple[int, int], params: RegistrationConfig = RegistrationConfig()) -> None:
        h, w = int(shape[0]), int(shape[1])
        if h < 16 or w < 16:
            raise ValueError(f"frames of {w}x{h} px are too small to register")
        window, window_taper = params.window, params.window_taper
        band_low, band_high, peak_sigma = params.band_low, params.band_high, params.peak_sigma
        angle_bins, radius_bins = params.angle_bins, params.radius_bins
        snr_weighting, candidate_ratio = params.snr_weighting, params.candidate_ratio
        max_candidates, refine_iterations = params.max_candidates, params.refine_iterations
        self.shape = (h, w)
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

        # frequency grid of an rfft2 spectrum (rows: fy in fft order, cols: fx >= 0), cycles/px
        fy = scipy.fft.fftfreq(h)[:, None]
        fx = scipy.fft.rfftfreq(w)[None, :]
        self._radius = np.sqrt(fx ** 2 + fy ** 2).astype(np.float32)
        # Hermitian multiplicity of each rfft2 bin in the full spectrum
        mult = np.full(fx.shape[1], 2.0)
        mult[0] = 1.0
        if w % 2 == 0:
            mult[-1] = 1.0
        self._mult = np.broadcast_to(mult[None, :], (h, fx.shape[1]))
        self._gauss = np.exp(-0.5 * (self._radius / peak_sigma) ** 2).astype(np.float32)
        # phase ramp that turns conj(F) into the spectrum of the point-mirrored image
        ramp = np.exp(-2j * np.pi * (fx * (w - 1) + scipy.fft.fftfreq(h)[:, None] * h * (h - 1) / h))
        self._mirror = ramp.astype(np.complex64)

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
        lfy = scipy.fft.fftfreq(na)[:, None]
        lfx = scipy.fft.rfftfreq(nr)[None, :]
        self._lp_gauss = np.exp(-0.5 * (lfx ** 2 + lfy ** 2) / peak_sigma ** 2).astype(np.float32)
        lmult = np.full(lfx.shape[1], 2.0)
        lmult[0] = 1.0
        if nr % 2 == 0:
            lmult[-1] = 1.0
        self._lp_ref = float((self._lp_gauss * lmult[None, :]).sum() / (na * nr))

        # the refinement runs on a regular grid of about _REFINE_SAMPLES pixels
        self._stride = max(1, int(round(math.sqrt(h * w / _REFINE_SAMPLES))))
        ys, xs = np.mgrid[0:h:self._stride, 0:w:self._stride].astype(np.float32)
        self._xc = (xs - self.center[0]).ravel()
        self._yc = (ys - self.center[1]).ravel()
        self._refine_shape = xs.shape
        self._refine_window = self.window[::self._stride, ::self._stride].ravel()
        # nearest log-polar ring of each rfft2 bin, to spread per-ring SNR weights over a spectrum
        ring = np.searchsorted(self._lp_radius, self._radius)
        self._ring_index = np.clip(ring, 0, nr - 1)
        self._outside_band = self._radius > band_high

    # ------------------------------------------------------------------ preparation
    def _gray(self, frame: np.ndarray) -> np.ndarray:
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
        if img.shape != self.shape:
            raise ValueError(f"frame shape {img.shape} does not match the registrar's {self.shape}")
        return img.astype(np.float32, copy=False)

    def _windowed_spectrum(self, gray: np.ndarray, mean: float) -> np.ndarray:
        return scipy.fft.rfft2((gray - mean) * self.window, workers=1)

    def prepare(self, frame: np.ndarray) -> PreparedFrame:
        """Compute and cache a frame's spectra (grey or BGR; uint8 or float)."""
        gray = self._gray(frame)
        mean = float(gray.mean())
        energy = float(gray.var())
        spec = self._windowed_spectrum(gray, mean)
        mag = np.fft.fftshift(np.abs(spec), axes=0)
        lp = cv2.remap(mag, self._lp_map_x, self._lp_map_y, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        # per-ring power and its noise floor (white noise is flat; take the quietest rings)
        power = np.einsum("ij,ij->j", lp, lp) / lp.shape[0]
        noise = float(np.percentile(power, 5)) if power.size else 0.0
        if self.snr_weighting and noise > 0:
            signal = np.maximum(power - noise, 0.0)
            snr = signal / (signal + noise)
        else:
            snr = np.ones_like(power)
        # whiten (magnitude ~ 1/f for natural images) and weight the rings
        weight = (self._lp_radius * snr * self._lp_window).astype(np.float32)
        lp = lp * weight[None, :]
        lp -= lp.mean()
        lps = scipy.fft.rfft2(lp, workers=1)
        amp = np.abs(lps)
        lps /= amp + _EPS * (float(amp.max()) + _EPS)
        grads = smooth = None
        if self.refine_iterations:
            smooth = cv2.GaussianBlur(gray, (0, 0), 0.7)
            gx = cv2.Scharr(smooth, cv2.CV_32F, 1, 0, scale=1 / 32)
            gy = cv2.Scharr(smooth, cv2.CV_32F, 0, 1, scale=1 / 32)
            gx = gx[::self._stride, ::self._stride].ravel()
            gy = gy[::self._stride, ::self._stride].ravel()
            grads = np.stack([gx, gy, self._xc * gx + self._yc * gy, self._xc * gy - self._yc * gx],
                             axis=1)
        return PreparedFrame(gray=gray, spectrum=spec, logpolar=lps, ring_snr=snr.astype(np.float32),
                             energy=energy, gradients=grads, smooth=smooth)

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
        """The ``count`` highest local maxima (integer positions) of a periodic surface."""
        work = r.copy()
        h, w = r.shape
        out = []
        for _ in range(count):
            idx = int(np.argmax(work))
            iy, ix = divmod(idx, w)
            val = float(work[iy, ix])
            if not np.isfinite(val) or val == -np.inf:
                break
            out.append((iy, ix, float(r[iy, ix])))
            ys = np.arange(iy - exclude, iy + exclude + 1) % h
            xs = np.arange(ix - exclude, ix + exclude + 1) % w
            work[np.ix_(ys, xs)] = -np.inf
        return out

    # ------------------------------------------------------------------ rotation and scale
    def _rotation_scale(self, a: PreparedFrame, b: PreparedFrame,
                        prior: Prior | None) -> list[tuple[float, float, float]]:
        """Candidate (angle_deg mod 180 in (-90, 90], scale, peak) of the matrix b -> a."""
        na, nr = self.angle_bins, self.radius_bins
        cross = np.conj(a.logpolar) * b.logpolar * self._lp_gauss
        r = scipy.fft.irfft2(cross, s=(na, nr), workers=1) / self._lp_ref
        # The log-polar image of b is that of a shifted by (+log s, -angle) (rows: angle, cols: log r).
        # Restrict the radius shift to +-nr/4 (scale within exp(+-nr/4 * step)) and apply priors.
        allowed = np.ones((na, nr), dtype=bool)
        shifts_r = np.fft.fftfreq(nr, 1.0 / nr)
        allowed &= (np.abs(shifts_r) <= nr // 4)[None, :]
        if prior is not None and prior.scale is not None:
            target = math.log(prior.scale) / self._log_step
            tol = max(abs(math.log1p(prior.scale_tol)) / self._log_step, 0.51)
            allowed &= (np.abs(shifts_r - target) <= tol)[None, :]
        if prior is not None and prior.angle_deg is not None and prior.angle_tol_deg < 90:
            shifts_a = np.fft.fftfreq(na, 1.0 / na) * (180.0 / na)  # degrees, = -angle (mod 180)
            diff = (-shifts_a - prior.angle_deg + 90.0) % 180.0 - 90.0
            allowed &= (np.abs(diff) <= max(prior.angle_tol_deg, 180.0 / na))[:, None]
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
    def _translation_weight(self, a: PreparedFrame, b: PreparedFrame) -> np.ndarray:
        if not self.snr_weighting:
            return self._gauss
        snr = np.sqrt(a.ring_snr * b.ring_snr)
        ring = snr[self._ring_index]
        ring[self._outside_band] = 0.0
        return self._gauss * ring

    def _translation(self, a: PreparedFrame, b: PreparedFrame, angle: float, scale: float,
                     prior: Prior | None) -> list[Candidate]:
        """Score the hypotheses ``angle`` and ``angle + 180`` of the matrix b -> a."""
        h, w = self.shape
        # With M = [L | t] (L = scale * R(angle)), b'(q) = b(L^-1 (q - c) + c) = a(q + tau) where
        # t = c + tau - L c: warping b by L about the centre c leaves a pure translation.
        lin_fwd = similarity_matrix(angle, scale, center=self.center)  # maps b pixels to b' pixels
        warped = cv2.warpAffine(b.gray, lin_fwd, (w, h), flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=float(b.gray.mean()))
        spec_b = self._windowed_spectrum(warped, float(b.gray.mean()))
        weight = self._translation_weight(a, b)
        ref = float((weight * self._mult).sum()) / (h * w)
        noise = math.sqrt(float((weight ** 2 * self._mult).sum())) / (h * w)
        if ref <= _EPS:
            return [Candidate(angle, scale, (0.0, 0.0), 0.0)]
        cross = np.conj(a.spectrum) * spec_b
        mag = np.abs(cross)
        cross *= weight / (mag + _EPS * (float(mag.max()) + _EPS))

        hyps = [(angle, cross)]
        want_flip = True
        if prior is not None and prior.angle_deg is not None and prior.angle_tol_deg < 90:
            d0 = abs(_wrap180(angle - prior.angle_deg))
            if d0 > 90:
                hyps = []
            want_flip = d0 > 90 - prior.angle_tol_deg or not hyps
        if want_flip:
            # point mirror of b' about the centre = b' rotated by 180 deg
            flip = np.conj(a.spectrum) * (self._mirror * np.conj(spec_b))
            mag = np.abs(flip)
            flip *= weight / (mag + _EPS * (float(mag.max()) + _EPS))
            hyps.append((_wrap180(angle + 180.0), flip))

        out = []
        k = math.sqrt(2.0 * math.log(h * w)) + 1.0
        for hyp_angle, spectrum in hyps:
            r = scipy.fft.irfft2(spectrum, s=(h, w), workers=1)
            peaks = self._peaks(r, 2, exclude=4)
            if prior is not None and prior.shift is not None:
                # also the best peak within the prior's tolerance (periodic ground)
                peaks += self._peaks(self._mask_shift(r, hyp_angle, scale, prior), 1, exclude=4)
            for iy, ix, _ in dict.fromkeys(peaks):
                fy, fx, height = self._subpixel(r, iy, ix)
                dy = (fy + h / 2) % h - h / 2
                dx = (fx + w / 2) % w - w / 2
                tau = (-dx, -dy)  # b'(q) = a(q + tau) is a shifted by -tau
                m = similarity_matrix(hyp_angle, scale, tau, center=self.center)
                peak = (height - k * noise) / max(ref - k * noise, _EPS)
                out.append(Candidate(hyp_angle, scale, (float(m[0, 2]), float(m[1, 2])),
                                     float(np.clip(peak, 0.0, 1.0))))
        return out

    def _mask_shift(self, r: np.ndarray, angle: float, scale: float, prior: Prior) -> np.ndarray:
        """Keep translation peaks whose matrix shift lies within the prior's tolerance."""
        h, w = self.shape
        ys = scipy.fft.fftfreq(h, 1.0 / h)[:, None]
        xs = scipy.fft.fftfreq(w, 1.0 / w)[None, :]
        # matrix shift for a peak at d: t = c + tau - L c with tau = -d
        lin = similarity_matrix(angle, scale)[:, :2]
        base = np.asarray(self.center) - lin @ np.asarray(self.center)
        tx = base[0] - xs - prior.shift[0]
        ty = base[1] - ys - prior.shift[1]
        return np.where(tx ** 2 + ty ** 2 <= prior.shift_tol ** 2, r, -np.inf)

    # ------------------------------------------------------------------ refinement
    def _refine(self, a: PreparedFrame, b: PreparedFrame, m: np.ndarray) -> np.ndarray | None:
        """Inverse compositional Gauss-Newton on a similarity + brightness gain/offset.

        ``m`` maps b -> a; returns the refined matrix, or None when it does not converge.
        """
        h, w = self.shape
        cx, cy = self.center
        rh, rw = self._refine_shape
        stride = np.diag([self._stride, self._stride, 1.0])  # refinement grid -> pixels
        tmpl = a.smooth[::self._stride, ::self._stride].ravel()
        tmpl_sq = tmpl.astype(np.float64) ** 2  # second moments in float64 (no cancellation)
        sd = a.gradients
        centre = np.array([[1, 0, cx], [0, 1, cy], [0, 0, 1.0]])
        centre_inv = np.array([[1, 0, -cx], [0, 1, -cy], [0, 0, 1.0]])
        m3 = np.vstack([m, [0.0, 0.0, 1.0]])
        start = m3.copy()
        for _ in range(self.refine_iterations):
            # b sampled at the refinement grid of a: NaN where the sample leaves b
            inv = (np.linalg.inv(m3) @ stride)[:2]
            warped = cv2.warpAffine(b.smooth, inv, (rw, rh), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan).ravel()
            wgt = self._refine_window * np.isfinite(warped)
            np.nan_to_num(warped, copy=False)
            wsum = float(wgt.sum())
            if wsum < 0.05 * wgt.size:
                return None
            # brightness gain/offset of the warped image against the template
            mt = float(wgt @ tmpl) / wsum
            mw = float(wgt @ warped) / wsum
            vt = float(wgt @ tmpl_sq) / wsum - mt * mt
            vw = float(wgt @ warped.astype(np.float64) ** 2) / wsum - mw * mw
            if vt <= _EPS or vw <= _EPS:
                return None
            gain = math.sqrt(vw / vt)
            err = (warped - mw) / gain - (tmpl - mt)
            sdw = sd * wgt[:, None]
            hess = sdw.T @ sd
            rhs = sdw.T @ err
            try:
                dp = np.linalg.solve(hess.astype(np.float64), rhs.astype(np.float64))
            except np.linalg.LinAlgError:
                return None
            tx, ty, da, db = dp
            # warp increment about the centre: x -> (1+da) x - db y + tx (centred coordinates)
            d = np.array([[1 + da, -db, tx], [db, 1 + da, ty], [0, 0, 1]])
            m3 = centre @ d @ centre_inv @ m3
            # converged when the frame corners move less than 0.002 px
            if max(abs(tx), abs(ty)) + (abs(da) + abs(db)) * max(cx, cy) * 1.5 < 2e-3:
                break
        # reject a refinement that wandered far from the iFMI estimate (it diverged)
        corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
        if np.abs((m3 - start) @ corners)[:2].max() > max(3.0, 0.03 * max(h, w)):
            return None
        return m3[:2]

    # ------------------------------------------------------------------ public
    def register(self, a: np.ndarray | PreparedFrame, b: np.ndarray | PreparedFrame,
                 prior: Prior | None = None) -> Registration:
        """Register the new frame ``b`` to the reference ``a``.

        Returns the similarity mapping pixels of ``b`` to pixels of ``a`` with its confidence.
        Arrays are prepared on the fly; pass :class:`PreparedFrame` objects to reuse spectra.
        """
        pa = a if isinstance(a, PreparedFrame) else self.prepare(a)
        pb = b if isinstance(b, PreparedFrame) else self.prepare(b)
        if pa.energy <= _EPS or pb.energy <= _EPS:
            return Registration(matrix=similarity_matrix(0.0, 1.0), confidence=0.0)

        cands: list[Candidate] = []
        for angle, scale, _ in self._rotation_scale(pa, pb, prior):
            cands.extend(self._translation(pa, pb, angle, scale, prior))
        if (prior is not None and prior.angle_deg is not None and prior.scale is not None
                and max(c.peak for c in cands) < _WEAK_PEAK):
            # Little overlap starves the log-polar POMF first: also try the expected rotation and
            # scale directly in the translation step (the refinement then corrects them).
            cands.extend(self._translation(pa, pb, prior.angle_deg, prior.scale, prior))
        cands = self._rank(cands, prior)
        best = cands[0]
        m = similarity_matrix(best.angle_deg, best.scale)
        m[:, 2] = best.shift
        ambiguous = any(c.peak >= 0.8 * best.peak and not self._same(c, best) for c in cands[1:])
        refined = False
        if self.refine_iterations and best.peak > 0:
            m_ref = self._refine(pa, pb, m)
            if m_ref is not None:
                m, refined = m_ref, True
        return Registration(matrix=m, confidence=best.peak, ambiguous=ambiguous,
                            candidates=tuple(cands), refined=refined)

    @staticmethod
    def _same(c: Candidate, d: Candidate) -> bool:
        return (abs(_wrap180(c.angle_deg - d.angle_deg)) < 1.0 and abs(c.scale / d.scale - 1) < 0.02
                and math.hypot(c.shift[0] - d.shift[0], c.shift[1] - d.shift[1]) < 2.0)

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
