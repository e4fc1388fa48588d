"""unpremultiply (the finishing step of map renders, the GeoTIFF's windows and mosaic.png's bands)
equals the one-expression form it replaced, bit for bit, at the edges that matter: empty pixels,
covers at and around the 1e-6 threshold, colours that round at .5 and that overflow the pixel type (8 and 16 bits)."""

from __future__ import annotations

import numpy as np
import pytest

from photomap.core.mosaic import unpremultiply


def _reference(acc: np.ndarray, dtype=np.uint8) -> tuple[np.ndarray, np.ndarray]:
    C, top = acc.shape[2] - 1, np.iinfo(dtype).max
    cover = acc[..., C]
    with np.errstate(divide="ignore", invalid="ignore"):
        colour = np.rint(acc[..., :C] / cover[..., None])
    image = np.where((cover > 1e-6)[..., None], np.clip(colour, 0, top), 0).astype(dtype)
    return image, np.clip(np.rint(cover * 255), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("channels, dtype", [(1, np.uint8), (3, np.uint8), (3, np.uint16)])
def test_unpremultiply_equals_the_expression(channels, dtype):
    rng = np.random.default_rng(7)
    h, w = 61, 47
    cover = rng.random((h, w), dtype=np.float32)
    cover[:5] = 0.0  # empty
    cover[5, :10] = np.float32(1e-6)  # at the threshold: empty
    cover[5, 10:20] = np.nextafter(np.float32(1e-6), np.float32(1))  # just above: covered
    cover[6] = np.float32(0.5 / 255)  # alpha rounds at .5
    cover[7] = 1.0
    colour = rng.random((h, w, channels), dtype=np.float32) * 1.2 * np.iinfo(dtype).max  # some clipped
    colour[8] = 127.5  # colour rounds at .5 (to even)
    acc = np.concatenate([colour * cover[..., None], cover[..., None]], axis=2)
    keep = acc.copy()
    planes = unpremultiply(acc, dtype)
    image, alpha = _reference(acc, dtype)
    assert np.array_equal(acc, keep)  # the sums are not changed
    assert len(planes) == channels + 1 and all(p.shape == (h, w) for p in planes)
    assert all(p.dtype == dtype for p in planes[:channels]) and planes[channels].dtype == np.uint8
    assert np.array_equal(np.stack(planes[:channels], axis=2), image)
    assert np.array_equal(planes[channels], alpha)
    assert image[:5].max() == 0 and image[5, :10].max() == 0 and alpha[7].min() == 255
