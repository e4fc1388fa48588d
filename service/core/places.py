"""Place recognition for iFMI: which old keyframes might show the ground of a new one.

A frame's Fourier magnitude does not change when the frame is shifted (the Fourier shift
theorem); resampled on a log-polar grid, a rotation of the frame becomes a circular shift along
the angle axis, and the magnitude of a Fourier transform along that axis no longer changes
either. The signature is that magnitude, per log-radius ring, whitened and normalised: invariant
to translation and rotation, and (comparing a few ring shifts) tolerant to a small change of
scale. Two frames that overlap well share much of their spectrum and score high; it ranks
candidates cheaply, the registration decides.

Pure: arrays in, arrays out.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["place_signature", "place_similarities"]


def place_signature(gray: np.ndarray, size: int = 128, angles: int = 64, radii: int = 24,
                    coefficients: int = 12) -> np.ndarray:
    """The signature of a frame (grey or BGR): float32 ``(radii, coefficients)``, unit norm.

    The frame is resampled to ``size`` x ``size``, windowed (Hann); its centred magnitude
    spectrum is sampled on ``angles`` x ``radii`` log-polar bins (the lowest eighth of the radius
    range is left out: it holds the window's own spectrum); each ring is whitened (zero mean, unit
    variance over angle) and replaced by the magnitudes of its first ``coefficients`` angular
    Fourier coefficients after the constant one.
    """
    img = gray if gray.ndim == 2 else cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
    img = cv2.resize(img.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)
    img -= float(img.mean())
    img *= cv2.createHanningWindow((size, size), cv2.CV_32F)
    mag = np.abs(np.fft.fftshift(np.fft.fft2(img))).astype(np.float32)
    mag = np.log1p(mag)
    centre = (size / 2.0, size / 2.0)
    lp = cv2.warpPolar(mag, (radii * 8, angles), centre, size / 2.0,
                       cv2.INTER_LINEAR | cv2.WARP_POLAR_LOG)  # rows: angle, cols: log radius
    lp = lp[:, radii:][:, ::7][:, :radii]  # drop the lowest eighth, keep `radii` rings
    lp = lp - lp.mean(axis=0, keepdims=True)
    lp /= lp.std(axis=0, keepdims=True) + 1e-6
    spec = np.abs(np.fft.rfft(lp, axis=0))[1:coefficients + 1].T  # (radii, coefficients)
    spec = spec.astype(np.float32)
    norm = float(np.linalg.norm(spec))
    return spec / norm if norm > 0 else spec


def place_similarities(a: np.ndarray, others: np.ndarray, max_ring_shift: int = 2) -> np.ndarray:
    """Cosine similarity of signature ``a`` with each of ``others`` (stacked: ``(n, radii,
    coefficients)``), the best over ring shifts up to ``max_ring_shift`` (a scale change of the
    frame shifts its spectrum along the log-radius axis); float64 ``(n,)``, -1 against an
    all-zero signature."""
    others = np.asarray(others, np.float32).reshape(-1, *a.shape)
    best = np.full(len(others), -1.0)
    n = a.shape[0]
    for s in range(-max_ring_shift, max_ring_shift + 1):
        x, y = (a[s:], others[:, :n - s]) if s >= 0 else (a[:n + s], others[:, -s:])
        nx = float(np.linalg.norm(x))
        ny = np.sqrt(np.einsum("kij,kij->k", y, y, dtype=np.float64))
        dot = np.einsum("ij,kij->k", x, y, dtype=np.float64)
        ok = (ny > 0) & (nx > 0)
        np.maximum(best, np.where(ok, dot / np.where(ok, nx * ny, 1.0), -1.0), out=best)
    return best
