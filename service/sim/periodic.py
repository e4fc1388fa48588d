"""Periodic ground for the simulator: floor tiles and crop rows.

Real floors and fields repeat: the phase correlation of two views then has peaks one period
apart of nearly equal height. These terrains reproduce that with an exact, known period.

Conventions as in :mod:`photomap.sim.terrain`: uint8 BGR, x east, y south, one terrain pixel is
``gsd`` metres. The period is an integer number of terrain pixels. With ``variation = 0`` and
``stain = 0`` tiles are strictly periodic, ``img[y, x] == img[y + period, x] == img[y, x + period]``
to the last bit; rows then have an exactly periodic stripe profile under random plant texture.
"""

from __future__ import annotations

import numpy as np

from photomap.errors import InputError
from photomap.sim.terrain import _low_res_field as _smooth
from photomap.sim.terrain import _noise_field as _noise


def _check(size: tuple[int, int], period: int, variation: float, stain: float) -> tuple[int, int]:
    h, w = int(size[0]), int(size[1])
    if h < 16 or w < 16:
        raise InputError(f"procedural terrain size must be at least 16x16, got {w}x{h}")
    if int(period) != period or not 8 <= period <= min(h, w) // 2:
        raise InputError(f"terrain period must be a whole number of pixels in 8..{min(h, w) // 2}, got {period}")
    if not 0.0 <= variation <= 1.0 or not 0.0 <= stain <= 1.0:
        raise InputError(f"terrain variation and stain must be in 0..1, got {variation}, {stain}")
    return h, w


def tiles_terrain(size: tuple[int, int] = (4096, 4096), seed: int = 0, *, period: int = 80,
                  variation: float = 0.1, stain: float = 0.3, grout: int = 3) -> np.ndarray:
    """A floor of square tiles, ``period`` terrain pixels apart, with grout lines.

    Parameters
    ----------
    size : ``(h, w)`` in terrain pixels.
    period : tile pitch (tile + grout), whole terrain pixels, along x and y.
    variation : 0..1, how much tiles differ from each other: the fraction of each tile's marble
        texture that is its own (the rest is shared by all tiles) and a per-tile brightness
        jitter of ``8 % * variation``. 0 = identical tiles.
    stain : 0..1, amplitude of a faint, smooth, non-periodic dirt layer (brightness factor
        ``1 + 0.12 * stain * field``). 0 = none.
    grout : width of the grout lines, pixels (on the tile's left and top edges).

    Returns uint8 BGR ``(h, w, 3)``; tile ``(i, j)`` covers ``x`` in ``[j*period, (j+1)*period)``.
    """
    h, w = _check(size, period, variation, stain)
    period = int(period)
    if not 0 <= grout < period // 2:
        raise InputError(f"grout width must be in 0..{period // 2 - 1} px, got {grout}")
    rng = np.random.default_rng([seed, 10])
    # one marble texture shared by all tiles (seamless over the tile: the noise is periodic)
    shared = _noise((period, period), rng, beta=1.0, f_low=1.0 / period)
    ny, nx = -(-h // period), -(-w // period)
    lum = np.tile(shared, (ny, nx))[:h, :w]
    if variation > 0:
        own = _noise((h, w), rng, beta=1.0, f_low=1.0 / period)
        jitter = rng.standard_normal((ny, nx)).astype(np.float32)
        jitter = np.repeat(np.repeat(jitter, period, axis=0), period, axis=1)[:h, :w]
        lum = (1.0 - variation) * lum + variation * own + 0.8 * variation * jitter
    img = (1.0 + 0.10 * lum)[..., None] * np.array([150.0, 170.0, 196.0], np.float32)   # BGR warm beige
    # grout: darker grey lines at the left and top edge of every tile
    yy = (np.arange(h) % period) < grout
    xx = (np.arange(w) % period) < grout
    line = yy[:, None] | xx[None, :]
    img[line] = np.array([92.0, 96.0, 100.0], np.float32)
    if stain > 0:
        dirt = _smooth((h, w), rng, beta=1.5)
        img *= (1.0 + 0.12 * stain * dirt)[..., None]
    return np.clip(img + 0.5, 12, 243).astype(np.uint8)


def rows_terrain(size: tuple[int, int] = (4096, 4096), seed: int = 0, *, period: int = 80,
                 variation: float = 0.1, stain: float = 0.3) -> np.ndarray:
    """Crop rows running north-south (along y), ``period`` terrain pixels apart along x.

    Across a row the plants form a soft band about 0.6 period wide; along the rows the
    plants are clumpy random texture (not periodic). Between rows: brown soil.

    Parameters
    ----------
    period : row spacing, whole terrain pixels.
    variation : 0..1, per-row irregularity: row centres shift by up to ``+-0.08 * variation``
        periods and widths change by up to ``+-25 % * variation``. 0 = identical rows.
    stain : 0..1, a smooth non-periodic brightness/wetness layer over everything. 0 = none.

    Returns uint8 BGR ``(h, w, 3)``. With ``variation = 0`` and ``stain = 0`` the row profile is
    exactly periodic in x, but the plant texture along the rows is random, so only the stripes
    repeat.
    """
    h, w = _check(size, period, variation, stain)
    period = int(period)
    rng = np.random.default_rng([seed, 11])
    n_rows = -(-w // period) + 1
    shift = variation * 0.08 * period * rng.uniform(-1, 1, n_rows)
    width = 0.6 * period * (1.0 + 0.25 * variation * rng.uniform(-1, 1, n_rows))
    x = np.arange(w, dtype=np.float64)
    k = np.floor(x / period).astype(int)
    # distance to the nearest row centre (row k centred at (k + 0.5) * period + shift[k])
    d = np.full(w, np.inf)
    for dk in (-1, 0, 1):
        kk = np.clip(k + dk, 0, n_rows - 1)
        centre = (kk + 0.5) * period + shift[kk]
        d = np.minimum(d, np.abs(x - centre) / width[kk])
    band = np.where(d < 0.5, np.cos(np.pi * d) ** 2, 0.0).astype(np.float32)   # 1 at the row centre
    clumps = _noise((h, w), rng, beta=0.8, f_low=2.0 / period)
    soil_tex = _noise((h, w), rng, beta=0.5, f_low=0.1)
    density = np.clip(band[None, :] * (1.0 + 0.45 * clumps), 0.0, 1.2)
    soil = np.array([60.0, 92.0, 128.0], np.float32) * (1.0 + 0.06 * soil_tex)[..., None]     # BGR brown
    plant = np.array([48.0, 150.0, 88.0], np.float32) * (1.0 + 0.10 * clumps)[..., None]     # BGR green
    img = soil + density[..., None] * (plant - soil)
    if stain > 0:
        wet = _smooth((h, w), rng, beta=1.5)
        img *= (1.0 + 0.15 * stain * wet)[..., None]
    return np.clip(img + 0.5, 12, 243).astype(np.uint8)
