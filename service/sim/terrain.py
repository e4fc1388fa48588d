"""Terrains to fly a simulated camera over: the bundled orthophoto, procedural ground, any image.

A terrain is a uint8 BGR image (OpenCV order); one terrain pixel is ``gsd`` metres on the ground,
x points east and y points south (image up = north). :func:`valid_mask` tells which pixels hold
real ground: orthophotos have a white (or black, or transparent) no-data border.

Procedural terrains are FFT-filtered Gaussian noise (``float32``, one inverse real FFT per
field), so ``grass``, ``sand`` and ``texture`` never repeat inside the image (the noise is periodic
only over the whole size); ``tiles`` and ``rows`` (:mod:`photomap.sim.periodic`) repeat on purpose.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import scipy.fft

from photomap.errors import InputError

log = logging.getLogger(__name__)

BUNDLED = {"aukerman": Path(__file__).resolve().parent / "data" / "aukerman.png"}
PROCEDURAL = ("grass", "sand", "texture", "tiles", "rows")
PERIODIC = ("tiles", "rows")        # procedural with a period (see photomap.sim.periodic)
TERRAIN_NAMES = tuple(BUNDLED) + PROCEDURAL
# Ground sampling distance (metres per pixel of the image as stored) and the upsampling that
# makes a camera footprint fit many times. aukerman's gsd is an estimate from the widths of
# its road and parking lot; procedural terrains and unknown images get DEFAULT_GSD.
DEFAULT_GSD = 0.1
TERRAIN_GSD = {"aukerman": 0.45}
TERRAIN_ZOOM = {"aukerman": 4.0}


def load_terrain(name_or_path: str | Path, zoom: float = 1.0, size: tuple[int, int] = (4096, 4096),
                 seed: int = 0, **periodic) -> np.ndarray:
    """Load a terrain by name (``aukerman``, ``grass``, ``sand``, ``texture``, ``tiles``, ``rows``)
    or image path.

    Parameters
    ----------
    name_or_path : a name from :data:`TERRAIN_NAMES` or the path of any image OpenCV reads.
    zoom : upsampling factor applied to a loaded image (bicubic), e.g. 4 turns the 1053x810
        aukerman orthophoto into 4212x3240 terrain pixels (each then ``gsd / zoom`` metres).
    size : ``(h, w)`` of a procedural terrain (``zoom`` does not apply to it).
    seed : seed of a procedural terrain.
    **periodic : ``period``, ``variation``, ``stain`` of ``tiles`` and ``rows`` (see
        :mod:`photomap.sim.periodic`); ignored by the other terrains.

    Returns
    -------
    uint8 BGR image, shape ``(h, w, 3)``. Transparent pixels of an image with alpha are white.
    """
    key = str(name_or_path)
    if key in PROCEDURAL:
        return procedural_terrain(key, size=size, seed=seed, **(periodic if key in PERIODIC else {}))
    path = BUNDLED.get(key, Path(key))
    if not path.is_file():
        raise InputError(f"terrain {key!r} is neither one of {', '.join(TERRAIN_NAMES)} nor an image file")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim not in (2, 3):
        raise InputError(f"cannot read terrain image {path}")
    if img.dtype != np.uint8:
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.shape[2] == 4:
        alpha = img[..., 3]
        img = img[..., :3].copy()
        img[alpha == 0] = 255
    if zoom <= 0:
        raise InputError(f"terrain zoom must be positive, got {zoom}")
    if zoom != 1.0:
        h, w = img.shape[:2]
        img = cv2.resize(img, (round(w * zoom), round(h * zoom)), interpolation=cv2.INTER_CUBIC)
    return np.ascontiguousarray(img)


def valid_mask(image: np.ndarray, tol: int = 6) -> np.ndarray:
    """Pixels holding real ground: all but the uniform no-data border of an orthophoto.

    The no-data area is every near-white (all channels >= 255 - tol) or near-black
    (all <= tol) region that touches the image border; white or black spots inside the
    ground (roofs, paths, shadows) stay valid. Returns a bool array ``(h, w)``.
    """
    valid = np.ones(image.shape[:2], bool)
    for nodata in (image.min(axis=2) >= 255 - tol, image.max(axis=2) <= tol):
        n, labels = cv2.connectedComponents(nodata.astype(np.uint8), connectivity=8)
        if n <= 1:
            continue
        edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        edge = edge[edge > 0]
        valid &= ~np.isin(labels, edge)
    return valid


def _noise_field(shape: tuple[int, int], rng: np.random.Generator, beta: float,
                 f_low: float = 0.0, f_high: float = 0.5) -> np.ndarray:
    """Gaussian noise with amplitude spectrum ``|f|**-beta`` inside ``[f_low, f_high]`` cycles/px.

    Zero mean, unit standard deviation, float32. Periodic over ``shape`` and nowhere else.
    """
    h, w = shape
    fy = scipy.fft.fftfreq(h).astype(np.float32)[:, None]
    fx = scipy.fft.rfftfreq(w).astype(np.float32)[None, :]
    f = np.sqrt(fy * fy + fx * fx)
    f[0, 0] = 1.0
    amp = f ** np.float32(-beta)
    amp[(f < f_low) | (f > f_high)] = 0.0
    amp[0, 0] = 0.0
    spec = (rng.standard_normal(amp.shape, dtype=np.float32)
            + 1j * rng.standard_normal(amp.shape, dtype=np.float32)).astype(np.complex64)
    spec *= amp
    field = scipy.fft.irfft2(spec, s=(h, w), workers=2).astype(np.float32, copy=False)
    field -= field.mean()
    std = float(field.std())
    return field / std if std > 0 else field


def _low_res_field(shape: tuple[int, int], rng: np.random.Generator, beta: float,
                   factor: int = 8) -> np.ndarray:
    """A smooth noise field computed at ``1/factor`` resolution and upsampled (cheap)."""
    h, w = shape
    small = _noise_field((max(8, h // factor), max(8, w // factor)), rng, beta)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def procedural_terrain(kind: str, size: tuple[int, int] = (4096, 4096), seed: int = 0, **periodic) -> np.ndarray:
    """Generate a procedural terrain, uint8 BGR of shape ``(h, w, 3)``.

    kinds
    -----
    ``grass``: greenish, moderate contrast (luminance std ~10 % of the mean), energy mostly at
        high spatial frequencies: fine texture that fades when the camera flies high.
    ``sand``: beige, smooth (amplitude ~ f^-2: low frequencies only), Michelson contrast 25 %
        between the 0.5th and 99.5th luminance percentiles; featureless.
    ``texture``: rich, natural-image-like texture (amplitude ~ f^-1) with colour variation.
    ``tiles``, ``rows``: periodic floor tiles and crop rows; ``**periodic`` = ``period``,
        ``variation``, ``stain`` (see :func:`photomap.sim.periodic.tiles_terrain`).
    """
    if kind not in PROCEDURAL:
        raise InputError(f"unknown procedural terrain {kind!r} (known: {', '.join(PROCEDURAL)})")
    h, w = int(size[0]), int(size[1])
    if h < 16 or w < 16:
        raise InputError(f"procedural terrain size must be at least 16x16, got {w}x{h}")
    if kind in PERIODIC:
        from photomap.sim.periodic import rows_terrain, tiles_terrain
        return (tiles_terrain if kind == "tiles" else rows_terrain)((h, w), seed, **periodic)
    rng = np.random.default_rng([seed, PROCEDURAL.index(kind)])
    if kind == "grass":
        fine = _noise_field((h, w), rng, beta=0.3, f_low=0.08)
        patches = _low_res_field((h, w), rng, beta=1.5)
        lum = 1.0 + 0.09 * fine + 0.05 * patches
        base = np.array([45.0, 120.0, 80.0], np.float32)       # BGR green
        tint = np.array([-6.0, 4.0, 10.0], np.float32)         # drier patches: more red/green
        img = lum[..., None] * base + (patches[..., None] * 0.5) * tint
    elif kind == "sand":
        field = _noise_field((h, w), rng, beta=2.0)
        lo, hi = np.percentile(field[:: max(1, h // 512), :: max(1, w // 512)], [0.5, 99.5])
        field = (2.0 * (field - lo) / max(hi - lo, 1e-6) - 1.0)  # ~[-1, 1]
        lum = 1.0 + 0.25 * field                               # Michelson contrast 0.25
        img = lum[..., None] * np.array([138.0, 170.0, 190.0], np.float32)  # BGR beige
    else:
        lum = _noise_field((h, w), rng, beta=1.0, f_low=1.0 / max(h, w))
        chroma = np.stack([_low_res_field((h, w), rng, beta=1.2, factor=4) for _ in range(2)], axis=-1)
        base = np.array([95.0, 120.0, 115.0], np.float32)
        img = (1.0 + 0.35 * lum[..., None]) * base
        img[..., 0] += 18.0 * chroma[..., 0]
        img[..., 2] += 18.0 * chroma[..., 1]
        img[..., 1] -= 9.0 * (chroma[..., 0] + chroma[..., 1])
    # Keep clear of pure white/black so that valid_mask() never mistakes ground for no-data.
    return np.clip(img, 12, 243).astype(np.uint8)
