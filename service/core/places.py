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

__all__ = ["PlaceIndex", "place_signature", "place_similarities"]


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


class PlaceIndex:
    """Place signatures of many keyframes in one compact matrix, searched by one product.

    Each row is a flattened signature (:func:`place_signature`) with its key and a group (the
    map segment). Signatures of one flight share much of their spectrum (the camera, the kind of
    ground): every pair scores high. The index compares them *centred* on the mean signature of
    the keys it holds, which leaves what differs between places: a revisit of the same ground
    scores near 1, other ground near 0. A query scores every row of a group at once: the cosine
    of the centred query, shifted by up to ``max_ring_shift`` log-radius rings (a change of
    scale, zero-filled), with the centred row, best over the shifts. Memory: 4 bytes per
    signature value (1.2 kB a keyframe at the default size); a query costs one ``(n, d) @ (d,
    shifts + 1)`` product.
    """

    def __init__(self, shape: tuple[int, int] = (24, 12), max_ring_shift: int = 2) -> None:
        self.shape = (int(shape[0]), int(shape[1]))
        self.max_ring_shift = int(max_ring_shift)
        d = self.shape[0] * self.shape[1]
        self._rows = np.zeros((0, d), np.float32)
        self._keys = np.zeros(0, np.int64)
        self._groups = np.zeros(0, np.int64)
        self._sq = np.zeros(0, np.float64)  # squared norm of each row
        self._sum = np.zeros(d, np.float64)  # of the rows of the keys held
        self._n = 0
        self._row_of: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self._row_of)

    def __contains__(self, key: object) -> bool:
        return key in self._row_of

    def signature(self, key: int) -> np.ndarray:
        """The signature indexed under ``key`` (a copy, shape ``shape``); KeyError if none."""
        return self._rows[self._row_of[key]].reshape(self.shape).copy()

    def add(self, key: int, signature: np.ndarray, group: int) -> None:
        """Index ``signature`` (shape ``shape``) under ``key`` in ``group`` (a key added again
        replaces its row)."""
        sig = np.asarray(signature, np.float32).reshape(-1)
        if sig.size != self._rows.shape[1]:
            raise ValueError(f"a signature of {self.shape} was expected, got {np.shape(signature)}")
        if key in self._row_of:
            row = self._row_of[key]
            self._sum -= self._rows[row]
        else:
            if self._n == len(self._rows):  # grow by half: amortised O(1)
                cap = max(64, self._n + self._n // 2)
                self._rows = np.resize(self._rows, (cap, self._rows.shape[1]))
                self._keys = np.resize(self._keys, cap)
                self._groups = np.resize(self._groups, cap)
                self._sq = np.resize(self._sq, cap)
            row, self._n = self._n, self._n + 1
            self._row_of[key] = row
        self._rows[row], self._keys[row], self._groups[row] = sig, key, group
        self._sq[row] = float(sig.astype(np.float64) @ sig)
        self._sum += sig

    def regroup(self, old: int, new: int) -> None:
        """Every key of group ``old`` now belongs to group ``new`` (segments joined)."""
        g = self._groups[:self._n]
        g[g == old] = new

    def remove(self, key: int) -> None:
        """Forget ``key`` (its row stays, in no group)."""
        row = self._row_of.pop(key, None)
        if row is not None:
            self._groups[row] = -1
            self._sum -= self._rows[row]

    def _queries(self, centred: np.ndarray) -> np.ndarray:
        """``(d, shifts)``: the centred query shifted along the rings (zero-filled), each of unit
        norm."""
        a = centred.reshape(self.shape)
        n = self.shape[0]
        out = []
        for s in range(-self.max_ring_shift, self.max_ring_shift + 1):
            q = np.zeros_like(a)
            if s >= 0:
                q[:n - s] = a[s:]
            else:
                q[-s:] = a[:n + s]
            norm = float(np.linalg.norm(q))
            out.append(q.reshape(-1) / norm if norm > 0 else q.reshape(-1))
        return np.stack(out, axis=1).astype(np.float32)

    def search(self, signature: np.ndarray, group: int, k: int,
               exclude: set[int] | frozenset[int] = frozenset()) -> list[tuple[int, float]]:
        """The ``k`` keys of ``group`` most similar to ``signature`` (not in ``exclude``): (key,
        centred cosine in -1..1) best first, ties by the older row."""
        if not self._row_of or k <= 0:
            return []
        mean = (self._sum / len(self._row_of)).astype(np.float32)
        queries = self._queries(np.asarray(signature, np.float32).reshape(-1) - mean)
        product = self._rows[:self._n] @ np.column_stack([queries, mean])  # the one pass over the rows
        dots = product[:, :-1] - (mean @ queries)[None, :]  # (row - mean) . query
        norms = np.sqrt(np.maximum(self._sq[:self._n] - 2.0 * product[:, -1] + float(mean @ mean), 0.0))
        scores = dots.max(axis=1) / np.maximum(norms, 1e-9)
        ok = (self._groups[:self._n] == group) & (norms > 1e-6)
        for key in exclude:
            row = self._row_of.get(key)
            if row is not None:
                ok[row] = False
        idx = np.flatnonzero(ok)
        if not len(idx):
            return []
        if len(idx) > k:  # the k best (ties at the cut: any), then those in order, ties by the older row
            idx = np.sort(idx[np.argpartition(-scores[idx], k - 1)[:k]])
        best = idx[np.argsort(-scores[idx], kind="stable")]
        return [(int(self._keys[i]), float(scores[i])) for i in best]
