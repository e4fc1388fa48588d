"""The raw values of 16-bit flights in the GeoTIFFs: ``map_bands.tif`` of 16-bit band captures,
``map_raw.tif`` of single-band 16-bit stills and of a live Y16 source, uint16 on the grid of
``map.tif``; and the pieces (the uint16 map, the window loop, the raw frame keeper, the band PNGs).

Truth: a simulated 5-band survey (``photomap simulate --bands 5``: 16-bit MicaSense-style TIFFs
with EXIF GPS, the lens homographies in ``meta.yaml``; one band of it as single-band stills) and a
simulated video flight with its telemetry.tlog (frames turned into 16-bit counts). A GeoTIFF pixel
is traced back through ``map.tif``'s georeference (run.json ``georeference.map_to_crs``) and the
last frame's final pose (``trajectory.csv``: it is painted last, so it is on top) into the frame's
file, and the file's raw value there is compared with the GeoTIFF's.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from photomap.cli.replay import replay
from photomap.config import load_config
from photomap.drivers.captures import read_band
from photomap.io.trajectory_files import read_trajectory_csv
from photomap.sim.bands import write_band_still
from photomap.sim.simulate import simulate_flight

rasterio = pytest.importorskip("rasterio", reason="the geo extra (rasterio) writes the GeoTIFFs")

SIZE = (480, 360)


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    out = tmp_path_factory.mktemp("raw16") / "flight"
    simulate_flight(out, mode="stills", stills_bands=5, strips=2, stills_per_strip=5, size=SIZE, seed=3)
    return out


def _single_band(survey: Path, folder: Path, band: int = 4, to_8bit: bool = False) -> list[Path]:
    """Band ``band``'s files of the survey as a folder of single-band stills (``NNNN.tif``, the same
    EXIF GPS and XMP), 16-bit as simulated or reduced to 8 bits."""
    folder.mkdir()
    out = []
    for k, src in enumerate(sorted((survey / "stills").glob(f"IMG_*_{band}.tif"))):
        dst = folder / f"{k:04d}.tif"
        if to_8bit:
            with Image.open(src) as im:  # the EXIF's sub-IFDs are read from the open file
                write_band_still(dst, (np.array(im) >> 8).astype(np.uint8), im.getexif(), im.tag_v2[700])
        else:
            shutil.copy(src, dst)
        out.append(dst)
    return out


def _grid(path: Path) -> tuple:
    with rasterio.open(path) as ds:
        return ds.transform, ds.width, ds.height, ds.crs


def _compare(run: Path, tif: Path, band: int, raw: np.ndarray, band_to_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(GeoTIFF values, the raw file's values bilinearly there) at the covered GeoTIFF pixels
    inside the last capture (``raw``: its band file; ``band_to_frame``: 3x3 band pixels -> frame
    pixels)."""
    info = json.loads((run / "run.json").read_text())
    A = np.vstack([np.array(info["georeference"]["map_to_crs"], float), [0.0, 0.0, 1.0]])
    rows = [r for r in read_trajectory_csv(run / "trajectory.csv") if r.M is not None]
    last = max(rows, key=lambda r: r.frame)
    M = np.vstack([np.asarray(last.M, float)[:2], [0.0, 0.0, 1.0]])
    with rasterio.open(tif) as ds:
        data = ds.read(band)
        T = ds.transform
    r, c = np.mgrid[0:data.shape[0], 0:data.shape[1]]
    cx, ry = c.ravel() + 0.5, r.ravel() + 0.5  # GeoTIFF pixel centres -> CRS metres
    e, n = T.a * cx + T.b * ry + T.c, T.d * cx + T.e * ry + T.f
    # CRS -> map pixels -> frame pixels -> band pixels
    to_band = np.linalg.inv(band_to_frame) @ np.linalg.inv(M) @ np.linalg.inv(A)
    p = to_band @ np.vstack([e, n, np.ones_like(e)])
    u, v = p[0] / p[2], p[1] / p[2]
    h, w = raw.shape
    inside = (u > 8) & (u < w - 9) & (v > 8) & (v < h - 9)
    assert inside.sum() > 5000
    u, v = u[inside], v[inside]
    x0, y0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fx, fy = u - x0, v - y0
    f = raw.astype(np.float64)
    truth = ((1 - fy) * ((1 - fx) * f[y0, x0] + fx * f[y0, x0 + 1])
             + fy * ((1 - fx) * f[y0 + 1, x0] + fx * f[y0 + 1, x0 + 1]))  # bilinear
    got = data.ravel()[inside].astype(np.float64)
    return got[got > 0], truth[got > 0]


def _assert_raw(got: np.ndarray, truth: np.ndarray) -> None:
    """The GeoTIFF holds the raw values (not a stretched copy), within the two bilinear resamplings
    (frame -> map -> north-up grid) of a textured scene."""
    spread = np.percentile(truth, 99) - np.percentile(truth, 1)
    assert truth.max() > 1000 and spread > 1000, "the simulated bands are 16-bit counts"
    diff = np.abs(got - truth)
    assert np.median(diff) < 0.01 * spread and np.percentile(diff, 90) < 0.04 * spread, \
        (np.median(diff), np.percentile(diff, 90), spread)
    assert abs(np.median(got - truth)) < 0.005 * spread  # no offset, no gain
    assert np.corrcoef(got, truth)[0, 1] > 0.98


def test_band_captures_write_their_raw_16bit_values_on_map_tifs_grid(survey, tmp_path):
    run = tmp_path / "run"
    summary = replay(str(survey / "stills"), run, load_config())
    assert summary["registered"] == 10 and summary["segments"] == 1
    info = json.loads((run / "run.json").read_text())
    assert info["telemetry"]["rectified"] == 0  # nadir: the pose maps the band file's own pixels
    assert info["bands"]["geotiff"]["dtype"] == "uint16" and "raw" not in info["exports"]
    assert _grid(run / "map_bands.tif") == _grid(run / "map.tif")
    with rasterio.open(run / "map_bands.tif") as ds:
        assert ds.count == 5 and ds.dtypes == ("uint16",) * 5 and ds.nodata == 0
        assert list(ds.descriptions) == info["bands"]["bands"]
    meta = yaml.safe_load((survey / "meta.yaml").read_text())
    G = [np.array(b["lens_H"], float) for b in meta["bands"]]
    names = info["bands"]["bands"]
    r = names.index(info["bands"]["registering"])
    last = max(p for p in (survey / "stills").glob("IMG_*_1.tif"))
    for b in {r, names.index("Blue")}:
        raw = read_band(last.with_name(last.name.replace("_1.tif", f"_{b + 1}.tif")))
        assert raw.dtype == np.uint16
        got, truth = _compare(run, run / "map_bands.tif", b + 1, raw, np.linalg.inv(G[r]) @ G[b])
        _assert_raw(got, truth)
    assert not (run / "map_raw.tif").exists()


@pytest.mark.parametrize("masked", [False, True])
def test_16bit_stills_write_map_raw_tif_with_their_raw_values(survey, tmp_path, masked):
    """... painted with the map's poses and frame masks (``capture.mask``: its black band stays
    out of both GeoTIFFs alike)."""
    stills = _single_band(survey, tmp_path / "stills")
    cfg = load_config()
    if masked:
        mask = np.full((SIZE[1], SIZE[0]), 255, np.uint8)
        mask[:, : SIZE[0] // 3] = 0  # the left third of every still
        Image.fromarray(mask).save(tmp_path / "mask.png")
        cfg = cfg.updated({"capture": {"mask": str(tmp_path / "mask.png")}})
    run = tmp_path / "run"
    summary = replay(str(tmp_path / "stills"), run, cfg)
    assert summary["registered"] == 10 and summary["segments"] == 1 and "bands" not in summary
    info = json.loads((run / "run.json").read_text())
    raw = info["exports"]["raw"]
    assert raw["file"] == "map_raw.tif" and raw["dtype"] == "uint16" and raw["frames"] == 10
    assert _grid(run / "map_raw.tif") == _grid(run / "map.tif")
    with rasterio.open(run / "map_raw.tif") as ds:
        assert ds.count == 1 and ds.dtypes == ("uint16",) and ds.nodata == 0
        covered = ds.read(1) > 0
    with rasterio.open(run / "map.tif") as ds:
        mapped = ds.read(4) >= 128
    # the map's very footprint (measured: 2e-6 of the grid differs; without the frame mask 5e-3)
    assert (covered != mapped).mean() < 5e-4
    got, truth = _compare(run, run / "map_raw.tif", 1, read_band(stills[-1]), np.eye(3))
    _assert_raw(got, truth)


def test_8bit_stills_write_no_raw_file(survey, tmp_path):
    stills = _single_band(survey, tmp_path / "stills", to_8bit=True)
    assert read_band(stills[0]).dtype == np.uint8
    run = tmp_path / "run"
    replay(str(tmp_path / "stills"), run, load_config())
    info = json.loads((run / "run.json").read_text())
    assert (run / "map.tif").exists() and "raw" not in info["exports"]
    assert not (run / "map_raw.tif").exists()


# ----------------------------------------------------------------------------- the pieces

@pytest.mark.parametrize("blend", ["overwrite", "feather"])
def test_a_uint16_mosaic_keeps_16bit_values_through_tiles_spill_and_render(blend, tmp_path):
    from dataclasses import replace as dc_replace

    from photomap.config import MosaicConfig
    from photomap.core.mosaic import TiledMosaic
    from photomap.errors import InputError
    from photomap.io.tilestore import DiskTileStore
    rng = np.random.default_rng(4)
    frame = rng.integers(0, 65536, (90, 130)).astype(np.uint16)
    cfg = dc_replace(MosaicConfig(), channels=1, exposure="none", blend=blend, tile_size=64, border=0,
                     max_tiles_in_memory=2)
    store = DiskTileStore(tmp_path / "tiles")
    mosaic = TiledMosaic(cfg, store, dtype=np.uint16)
    mosaic.add(frame, np.array([[1.0, 0.0, 37.0], [0.0, 1.0, -20.0]]))  # across tiles, some spilled
    image, alpha, origin = mosaic.render()
    assert image.dtype == np.uint16 and origin == (37, -20) and alpha.all()
    assert np.array_equal(image, frame)  # an integer translation: every raw value as it was
    small, _, _ = mosaic.render(scale=0.5)
    assert small.dtype == np.uint16 and small.max() > 255
    with pytest.raises(InputError, match="uint16"):
        mosaic.add(frame.astype(np.uint8), np.eye(2, 3))
    with pytest.raises(ValueError, match="exposure"):
        TiledMosaic(dc_replace(cfg, exposure="gain"), store, dtype=np.uint16)
    store.close()


def test_resample_block_keeps_the_renders_depth():
    from photomap.io.geotiff import resample_block
    values = np.full((40, 40), 40000, np.uint16)

    def render(x, y, w, h, scale):
        return values[:h, :w], np.full((h, w), 255, np.uint8)

    image, alpha = resample_block(render, (0, 0, 40, 40), np.array([[1.0, 0.0, 5.0], [0.0, 1.0, 5.0]]), (20, 20))
    assert image.dtype == np.uint16 and alpha.min() == 255 and (image == 40000).all()


def test_colour_16bit_stills_give_a_red_green_blue_raw_map(tmp_path):
    """A 16-bit colour still's raw map has bands red, green, blue with its values (BGR in, RGB out)."""
    from types import SimpleNamespace

    from photomap.config import MosaicConfig
    from photomap.mapping.band_maps import write_raw_map
    rng = np.random.default_rng(2)
    still = np.dstack([np.full((60, 80), v, np.uint16) for v in (1000, 30000, 60000)])  # B, G, R
    still[..., 1] += rng.integers(0, 50, (60, 80)).astype(np.uint16)
    rows = [SimpleNamespace(frame=0, M=np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))]
    map_to_crs = np.array([[0.1, 0.0, 500000.0], [0.0, -0.1, 4500000.0]])  # north-up, 10 cm
    info = write_raw_map(tmp_path, lambda i: still, rows, (80, 60), MosaicConfig(), {"bounds": [0, 0, 80, 60]},
                         (map_to_crs, 32633))
    assert info["file"] == "map_raw.tif" and info["bands"] == ["red", "green", "blue"]
    with rasterio.open(tmp_path / "map_raw.tif") as ds:
        assert ds.count == 3 and ds.dtypes == ("uint16",) * 3 and list(ds.descriptions) == ["red", "green", "blue"]
        red, green, blue = ds.read()
    inner = (slice(5, -5), slice(5, -5))
    assert (red[inner] == 60000).all() and (blue[inner] == 1000).all()
    assert abs(float(np.median(green[inner])) - float(np.median(still[5:-5, 5:-5, 1]))) < 3
    assert write_raw_map(tmp_path, lambda i: None, rows, (80, 60), MosaicConfig(), {"bounds": [0, 0, 80, 60]},
                         (map_to_crs, 32633)) is None  # not 16-bit: no file


# ----------------------------------------------------------------------------- a live Y16 camera

class _DeepLive:
    """A live source that delivers raw 16-bit frames, as a Y16 V4L2 thermal core does."""

    live = True

    def __init__(self, frames, fps):
        from photomap.drivers.frames import CaptureStats
        self.frames, self.fps, self.stats = frames, fps, CaptureStats()

    def __iter__(self):
        from photomap.drivers.frames import Frame
        for i, image in enumerate(self.frames):
            self.stats.read += 1
            yield Frame(i, i / self.fps, image, "y16")

    def close(self):
        pass


def test_a_live_y16_source_writes_map_raw_tif_from_the_frames_it_kept(tmp_path):
    from photomap.cli.wiring import open_telemetry
    from photomap.mapping.pipeline import MappingPipeline
    sim = tmp_path / "sim"
    simulate_flight(sim, n_frames=60, size=(320, 240), fps=15.0, seed=5, save_frames=True)
    deep = [(np.asarray(Image.open(p).convert("L"), np.uint32) * 180 + 2500).astype(np.uint16)
            for p in sorted((sim / "frames").glob("*.png"))]
    join, _, cfg = open_telemetry(str(sim / "telemetry.tlog"), load_config(), input_spec=str(sim / "video.mp4"))
    run = tmp_path / "run"
    summary = MappingPipeline(_DeepLive(deep, 15.0), cfg, run, telemetry=join).run()
    assert summary["registered"] == 60 and summary["segments"] == 1 and summary.get("georeference")
    info = json.loads((run / "run.json").read_text())
    assert info["telemetry"]["rectified"] == 0  # nadir: the pose maps the frame's own pixels
    raw = info["exports"]["raw"]
    assert raw["file"] == "map_raw.tif" and raw["dtype"] == "uint16"
    assert 5 <= raw["frames"] < 40  # the frames kept, not all 60
    assert _grid(run / "map_raw.tif") == _grid(run / "map.tif")
    with rasterio.open(run / "map_raw.tif") as ds:
        covered = ds.read(1) > 0
    with rasterio.open(run / "map.tif") as ds:
        mapped = ds.read(4) >= 128
    # the kept frames cover the map's footprint (measured: 0.3 % of the grid differs either way)
    assert (covered & ~mapped).mean() < 0.01 and (mapped & ~covered).mean() < 0.01
    got, truth = _compare(run, run / "map_raw.tif", 1, deep[-1], np.eye(3))
    _assert_raw(got, truth)
    assert not list(run.glob(".raw_frames*"))  # the kept frames are removed


def test_the_raw_frame_keeper_keeps_spaced_frames_and_the_last(tmp_path):
    from photomap.mapping.raw_frames import RawFrameKeeper
    (tmp_path / ".raw_frames.old").mkdir()  # a run that stopped
    keeper = RawFrameKeeper(tmp_path, spacing=0.25)
    frame = np.arange(40 * 60, dtype=np.uint16).reshape(40, 60) * 20
    centre = np.array([29.5, 19.5])
    for i in range(30):  # 2 px a frame to the right up to frame 19, then turning 4 deg a frame about the centre
        angle = math.radians(4.0 * max(0, i - 19))
        R = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
        t = centre + [2.0 * min(i, 19), 0.0] - R @ centre
        keeper.offer(i, frame + i, np.hstack([R, t[:, None]]), segment=0)
    keeper.offer(30, frame.astype(np.uint8), np.eye(2, 3), segment=0)  # 8-bit: never kept
    keeper.offer(31, frame, None, segment=0)  # not posed: never kept
    keeper.finish()
    # moved 10 px (a quarter of the shorter side) every 5 frames; then turned 15 deg (16 at frame
    # 23, 16 again at 27); and the newest frame not kept (29) at the end
    assert sorted(keeper.kept) == [0, 5, 10, 15, 23, 27, 29]
    assert np.array_equal(keeper.read(29), frame + 29) and keeper.read(3) is None
    assert not (tmp_path / ".raw_frames.old").exists()
    keeper.close()
    assert not list(tmp_path.glob(".raw_frames*")) and keeper.read(29) is None


def test_band_maps_take_the_frame_mask_the_map_got(survey, tmp_path):
    """``capture.mask`` keeps the same pixels of every band out of map_bands.tif as out of map.tif."""
    mask = np.full((SIZE[1], SIZE[0]), 255, np.uint8)
    mask[:, : SIZE[0] // 3] = 0
    Image.fromarray(mask).save(tmp_path / "mask.png")
    run = tmp_path / "run"
    replay(str(survey / "stills"), run, load_config().updated({"capture": {"mask": str(tmp_path / "mask.png")}}))
    info = json.loads((run / "run.json").read_text())
    with rasterio.open(run / "map.tif") as ds:
        mapped = ds.read(4) >= 128
    with rasterio.open(run / "map_bands.tif") as ds:
        for b, name in enumerate(info["bands"]["bands"], 1):
            covered = ds.read(b) > 0
            # measured: none of a band beyond the map (1 % of the grid without the mask); up to
            # 0.6 % of the map's edge missing (the lenses' offsets)
            assert (covered & ~mapped).mean() < 0.002, name
            assert (mapped & ~covered).mean() < 0.01, name


@pytest.mark.parametrize("scale", [1.0, 0.37])
def test_a_16bit_band_png_is_the_stretched_render_written_a_tile_row_at_a_time(scale, tmp_path):
    from dataclasses import replace as dc_replace

    import cv2

    from photomap.config import MosaicConfig
    from photomap.core.mosaic import TiledMosaic
    from photomap.core.stretch import to_8bit
    from photomap.mapping.band_maps import _write_png
    rng = np.random.default_rng(1)
    mosaic = TiledMosaic(dc_replace(MosaicConfig(), channels=1, exposure="none", tile_size=64), dtype=np.uint16)
    mosaic.add(rng.integers(0, 65535, (150, 200)).astype(np.uint16), np.array([[0.9, 0.2, -37.0], [-0.2, 0.9, 11.0]]))
    bounds = mosaic.bounds()
    _write_png(tmp_path / "band.png", mosaic, bounds, scale, (1000.0, 60000.0))
    image, alpha, _ = mosaic.render(scale=scale, bounds=bounds)  # the whole map at once
    expected = np.dstack([cv2.cvtColor(to_8bit(image, (1000.0, 60000.0)), cv2.COLOR_GRAY2BGR), alpha])
    assert np.array_equal(cv2.imread(str(tmp_path / "band.png"), cv2.IMREAD_UNCHANGED), expected)


def test_the_raw_frame_keeper_stops_at_its_disk_budget_and_keeps_what_it_has(tmp_path, caplog):
    """Kept frames never take more than ``max_bytes``: past it one line says so, no more are kept
    (not even the last one at the end), and the ones kept are still read back."""
    from photomap.mapping.raw_frames import RawFrameKeeper
    frame = np.arange(40 * 60, dtype=np.uint16).reshape(40, 60)
    keeper = RawFrameKeeper(tmp_path, spacing=0.25, max_bytes=3 * frame.nbytes)
    caplog.set_level(logging.WARNING)
    for i in range(30):  # 10 px every 5 frames: due at 0, 5, 10, 15, 20, 25
        keeper.offer(i, frame + i, np.array([[1.0, 0.0, 2.0 * i], [0.0, 1.0, 0.0]]), segment=0)
    keeper.finish()
    assert sorted(keeper.kept) == [0, 5, 10]
    assert sum(p.stat().st_size for p in keeper.folder.iterdir()) < 3 * frame.nbytes + 3 * 1024  # .npy headers
    assert np.array_equal(keeper.read(10), frame + 10)
    lines = [r.getMessage() for r in caplog.records if "raw frames" in r.getMessage()]
    assert len(lines) == 1 and "no more" in lines[0] and "up to 10" in lines[0], lines
    keeper.close()
