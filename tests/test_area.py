"""Area-averaged downscaling in O(pixels) (photomap.core.area) against the exact area weights
computed densely here, and the report's thumbnail taken from the PNG's bands."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from photomap.core.area import AreaRows, _opencv_misses, area_columns
from photomap.mapping.outputs import PngThumbnail, render_small, write_png

from tests.test_pngstream import _mosaic


def _dense(n: int, n_out: int) -> np.ndarray:
    """(n_out, n) float64: output j averages source [j * n / n_out, (j + 1) * n / n_out)."""
    step = n / n_out
    j = np.arange(n_out)[:, None]
    i = np.arange(n)[None, :]
    return np.clip(np.minimum(i + 1, (j + 1) * step) - np.maximum(i, j * step), 0, None) / step


@pytest.mark.parametrize("w, n_out", [(5758, 3590), (1000, 371), (512, 64), (255, 254), (300, 7)])
def test_area_columns_equal_exact_weights(w, n_out):
    band = np.random.default_rng(w).uniform(0, 255, (5, w, 4)).astype(np.float32)
    want = np.einsum("jw,rwc->rjc", _dense(w, n_out), band.astype(np.float64))
    got = area_columns(band, n_out)
    assert got.shape == (5, n_out, 4)
    assert np.abs(got - want).max() < 2e-3


def test_opencv_partial_weights_are_recomputed():
    """OpenCV drops partial weights under 1e-3: at those outputs its average is off by up to a
    quarter level; area_columns is exact there."""
    w, n_out = 5758, 3590
    misses = _opencv_misses(w, n_out)
    assert misses.size
    band = np.full((2, w), 255, np.float32)
    plain = cv2.resize(band, (n_out, 2), interpolation=cv2.INTER_AREA)
    assert np.abs(plain[:, misses] - 255).max() > 0.05
    assert np.abs(area_columns(band, n_out) - 255).max() < 1e-3


def test_area_rows_stream_equals_dense():
    """Bands of uneven height with a gap of rows never given (0) stream to the 2D area average."""
    h, w, oh, ow = 301, 170, 97, 61
    image = np.random.default_rng(1).uniform(0, 1, (h, w, 2)).astype(np.float32)
    image[120:190] = 0  # not given below
    stream = AreaRows(h, w, oh, ow, 2)
    blocks = []
    for y0, y1 in [(3, 64), (64, 120), (190, 250), (250, 301)]:
        blocks += stream.add(y0, image[y0:y1] if y0 % 2 else list(np.moveaxis(image[y0:y1], 2, 0)))
    blocks += stream.close()
    image[:3] = 0
    got = np.concatenate(blocks)
    want = np.einsum("jy,yxc,ix->jic", _dense(h, oh), image.astype(np.float64), _dense(w, ow))
    assert got.shape == (oh, ow, 2)
    assert np.abs(got - want).max() < 1e-5


@pytest.mark.parametrize("max_px", [150, 400, 10000])
def test_png_thumbnail_is_the_png_downscaled(tmp_path, max_px):
    """The thumbnail fed by write_png's bands (their sums when the PNG is downscaled, its pixels
    at full size) is the PNG read back, area-averaged alpha-weighted: within a level of it
    (the PNG's own rounding) where covered."""
    m = _mosaic("overwrite", 3, seed=5)
    thumb = PngThumbnail(96)
    write_png(tmp_path / "mosaic.png", m, max_px, thumbnail=thumb)
    got = thumb.image()
    png = cv2.imread(str(tmp_path / "mosaic.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    h, w = png.shape[:2]
    f = 96 / max(w, h)
    oh, ow = round(h * f), round(w * f)
    a = png[..., 3:] / 255
    pre = np.einsum("jy,yxc,ix->jic", _dense(h, oh), np.concatenate([png[..., :3] * a, a], axis=2), _dense(w, ow))
    cover = pre[..., 3]
    assert got is not None and got.shape == (oh, ow, 4)
    assert np.abs(got[..., 3] - cover * 255).max() <= 1
    covered = cover > 0.5
    assert covered.sum() > 1000
    assert np.abs(got[..., :3][covered] - pre[..., :3][covered] / cover[covered][:, None]).max() <= 1.5
    if max_px >= max(m.bounds()[2:]):  # the PNG is the map: the thumbnail is the map rendered small
        assert np.abs(got.astype(int) - render_small(m, 96).astype(int)).max() <= 1
    assert PngThumbnail(96).image() is None  # nothing went through


@pytest.mark.parametrize("h, w, opaque", [(64, 64, True), (64, 64, False), (37, 50, False), (51, 33, True)])
def test_halving_is_the_alpha_weighted_mean_of_2x2_pixels(h, w, opaque):
    """photomap.core.pyramid.halve against the mean computed densely in float64: colour
    sum(c a) / sum(a), alpha mean(a), pixels past an odd edge transparent; within 1 of it (8-bit
    rounding), and a transparent neighbour never darkens a colour."""
    from photomap.core.pyramid import halve
    rng = np.random.default_rng(h * w)
    bgra = rng.integers(0, 256, (h, w, 4), np.uint8)
    if opaque:
        bgra[..., 3] = 255
    else:
        bgra[rng.random((h, w)) < 0.3, 3] = 0
    got = halve(bgra)
    assert got.shape == ((h + 1) // 2, (w + 1) // 2, 4) and got.dtype == np.uint8
    x = np.zeros((h + h % 2, w + w % 2, 4))
    x[:h, :w] = bgra
    a = x[..., 3] / 255
    sums = lambda v: v.reshape(x.shape[0] // 2, 2, x.shape[1] // 2, 2).sum(axis=(1, 3))  # noqa: E731
    cover = sums(a)
    colour = np.stack([sums(x[..., c] * a) for c in range(3)], -1) / np.maximum(cover, 1e-12)[..., None]
    want = np.dstack([np.where(cover[..., None] > 0, colour, 0), cover / 4 * 255])
    assert np.abs(got.astype(float) - want).max() <= 1.0
    flat = bgra.copy()
    flat[..., :3] = (30, 140, 250)  # one colour: every covered half pixel keeps it exactly
    half = halve(flat)
    assert (half[half[..., 3] > 0, :3] == (30, 140, 250)).all()
