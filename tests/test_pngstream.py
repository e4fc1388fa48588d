"""mosaic.png written band by band: the same pixels as one render of the whole map, read back by
OpenCV and PIL; memory bounded by a tile row."""

from __future__ import annotations

import io

import cv2
import numpy as np
import pytest
from PIL import Image

from photomap.config import MosaicConfig
from photomap.core.mosaic import TiledMosaic
from photomap.io.pngstream import PngStreamWriter
from photomap.io.tilestore import DiskTileStore
from photomap.mapping.outputs import render_bands, write_png


def _mosaic(blend: str, channels: int, store=None, cap=None, seed: int = 0) -> TiledMosaic:
    rng = np.random.default_rng(seed)
    m = TiledMosaic(MosaicConfig(tile_size=64, channels=channels, blend=blend, max_tiles_in_memory=cap), store)
    base = cv2.resize(rng.integers(0, 256, (40, 60, 3), dtype=np.uint8), (300, 200), interpolation=cv2.INTER_CUBIC)
    for k in range(7):
        a = np.deg2rad(rng.uniform(-180, 180))
        s = rng.uniform(0.7, 1.3)
        M = np.array([[s * np.cos(a), -s * np.sin(a), rng.uniform(-250, 300)],
                      [s * np.sin(a), s * np.cos(a), rng.uniform(-150, 200)]])
        m.add(np.roll(base, 17 * k, axis=1), M)
    return m


@pytest.mark.parametrize("blend, channels", [("overwrite", 3), ("feather", 3), ("overwrite", 1)])
@pytest.mark.parametrize("scale", [1.0, 0.5, 0.37, 0.013])
def test_bands_equal_one_render(blend, channels, scale):
    m = _mosaic(blend, channels)
    image, alpha, origin = m.render(scale)
    bounds, size, bands = render_bands(m, scale)
    parts = list(bands)
    got_img = np.concatenate([p[0] for p in parts])
    got_alpha = np.concatenate([p[1] for p in parts])
    assert origin == bounds[:2] and size == (alpha.shape[1], alpha.shape[0])
    assert np.array_equal(got_alpha, alpha)
    assert np.array_equal(got_img[..., 0] if channels == 1 else got_img, image)
    assert alpha.any() and max(p[1].shape[0] for p in parts) <= 64 * scale + 2


def test_png_reads_back_equal_with_spilled_tiles(tmp_path):
    with DiskTileStore(tmp_path / "cache") as store:
        m = _mosaic("overwrite", 3, store=store, cap=4, seed=3)
        image, alpha, _ = m.render(0.8)
        info = write_png(tmp_path / "mosaic.png", m, max_px=int(max(m.bounds()[2:]) * 0.8))
    back = cv2.imread(str(tmp_path / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    assert back.shape == (*alpha.shape, 4) and info["size"] == [alpha.shape[1], alpha.shape[0]]
    assert np.array_equal(back[..., :3], image) and np.array_equal(back[..., 3], alpha)
    with Image.open(tmp_path / "mosaic.png") as pil:  # a second reader agrees (RGBA order)
        rgba = np.asarray(pil.convert("RGBA"))
    assert np.array_equal(rgba[..., [2, 1, 0, 3]], back)


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_stream_writer_round_trip(tmp_path, channels):
    rng = np.random.default_rng(channels)
    img = rng.integers(0, 256, (37, 29, channels), dtype=np.uint8)
    img[10:20] = 7  # flat rows: None/Sub/Up win there, Paeth on noise
    with PngStreamWriter(tmp_path / "a.png", 29, 37, channels) as png:
        for r0 in range(0, 37, 5):
            png.write(img[r0:r0 + 5])
    back = cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(back.reshape(img.shape), img)


@pytest.mark.parametrize("deflate", ["isal", "zlib"])
@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_encode_png_reads_back_equal(channels, deflate, monkeypatch):
    """encode_png with ISA-L's deflate, and with zlib where isal is not installed: PIL reads the
    pixels back exactly (grey + alpha too); OpenCV too for gray, BGR and BGRA."""
    from photomap.io import pngstream

    if deflate == "zlib":
        monkeypatch.setattr(pngstream, "_isal", None)
    elif pngstream._isal is None:
        pytest.skip("isal (a dependency) is not installed here")
    rng = np.random.default_rng(channels)
    img = rng.integers(0, 256, (256, 256, channels), dtype=np.uint8)
    img[40:90] = 7  # flat rows and noise
    data = pngstream.encode_png(img if channels > 1 else img[..., 0])
    with Image.open(io.BytesIO(data)) as pil:
        back = np.asarray(pil).reshape(img.shape)
    order = {1: [0], 2: [0, 1], 3: [2, 1, 0], 4: [2, 1, 0, 3]}[channels]  # PIL's RGB(A) against BGR(A)
    assert np.array_equal(back, img[..., order])
    if channels != 2:
        cv = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(cv.reshape(img.shape), img)
    with pytest.raises(ValueError, match="uint8"):
        pngstream.encode_png(img.astype(np.uint16))


def test_stream_writer_leaves_nothing_on_error(tmp_path):
    with pytest.raises(ValueError, match="got only 5"):
        with PngStreamWriter(tmp_path / "a.png", 4, 10, 3) as png:
            png.write(np.zeros((5, 4, 3), np.uint8))
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(RuntimeError):  # the render failed half way: no file, no temporary
        with PngStreamWriter(tmp_path / "b.png", 4, 10, 3) as png:
            png.write(np.zeros((5, 4, 3), np.uint8))
            raise RuntimeError("the render failed")
    assert list(tmp_path.iterdir()) == []
