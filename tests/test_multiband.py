"""Multi-band cameras: capture grouping, band-to-band alignment, one map per band.

Real material: two MicaSense RedEdge 5-band captures (``shared/data/micasense_captures``, with the
metadata parsed independently into ``captures.csv``); simulated: a small 5-band survey whose lens
homographies are known (``photomap simulate --bands 5``).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from photomap.cli.replay import replay
from photomap.config import load_config
from photomap.core.bands import (align_band, align_capture, corner_shift_px, gradient_correlation,
                                 robust_range_16bit, texture_energy)
from photomap.core.stretch import to_8bit
from photomap.drivers.captures import group_captures, read_band
from photomap.drivers.images import ImageFolderSource
from photomap.drivers.stills_telemetry import stills_telemetry_for
from photomap.errors import ConfigError, InputError
from photomap.mapping.band_maps import band_file_name, composite_bands
from photomap.sim.simulate import simulate_flight

from conftest import shared_data

SIZE = (480, 360)


def _capture_rows():
    folder = shared_data("micasense_captures")
    with open(folder / "captures.csv", newline="") as f:
        return folder, list(csv.DictReader(f))


# ----------------------------------------------------------------------------- real captures

def test_micasense_files_group_into_one_frame_per_capture():
    folder, rows = _capture_rows()
    src = ImageFolderSource(folder)
    assert src.captures is not None and len(src.captures) == 2
    for capture in src.captures:
        want = sorted((r for r in rows if r["capture_id"] == capture.key), key=lambda r: int(r["rig_camera_index"]))
        assert len(want) == 5
        assert [f.path.name for f in capture.files] == [r["file"] for r in want]
        assert list(capture.bands) == [r["band_name"] for r in want]
    # the registering band by default: the most texture in the first capture
    first = src.captures[0]
    energy = {f.band: texture_energy(read_band(f.path)) for f in first.files}
    assert src.band == max(energy, key=energy.get)
    frames = list(src)
    assert len(frames) == 2 and all(f.image.dtype == np.uint8 and f.image.shape == (960, 1280) for f in frames)
    assert src.band_range is not None and 0 < src.band_range[0] < src.band_range[1] <= 65535
    # each frame's telemetry: the GPS of its capture
    tel = stills_telemetry_for(src)
    for capture, sample in zip(src.captures, tel.samples):
        row = next(r for r in rows if r["capture_id"] == capture.key)
        assert sample.lat == pytest.approx(float(row["lat"]), abs=1e-7)
        assert sample.lon == pytest.approx(float(row["lon"]), abs=1e-7)


def test_capture_band_config_chooses_the_registering_band():
    folder, _ = _capture_rows()
    assert ImageFolderSource(folder, band="nir").band == "NIR"
    assert ImageFolderSource(folder, band="RE").band == "Red edge"
    assert ImageFolderSource(folder, band="2").band == "Green"
    with pytest.raises(InputError, match="capture.band"):
        ImageFolderSource(folder, band="swir")


def test_real_capture_aligns_with_small_homographies():
    """IMG_0001 (orchard, 73 m up; half resolution to keep the test quick): every band fits its
    registering band by a near-identity homography and its edges line up better after."""
    folder, _ = _capture_rows()
    images = [cv2.resize(read_band(folder / f"IMG_0001_{b}.tif"), (640, 480), interpolation=cv2.INTER_AREA)
              for b in range(1, 6)]
    ref = 4  # red edge (the default registering band of this capture)
    fits = align_capture(images, ref)
    for b, fit in enumerate(fits):
        assert fit.ok, (b, fit.reason)
        if b == ref:
            continue
        H = fit.H
        scale = np.sqrt(abs(np.linalg.det(H[:2, :2])))
        angle = np.degrees(np.arctan2(H[1, 0], H[0, 0]))
        assert abs(scale - 1) < 0.02 and abs(angle) < 1.0 and np.abs(H[2, :2]).max() < 1e-4
        assert corner_shift_px(H, (640, 480)) < 0.05 * 640  # a few pixels of lens offset
        before, after = gradient_correlation(images[ref], images[b]), gradient_correlation(images[ref], images[b], H)
        assert after > before + 0.2, (b, before, after)


def test_alignment_failure_is_reported_not_guessed():
    folder, _ = _capture_rows()
    ref = cv2.resize(read_band(folder / "IMG_0001_5.tif"), (320, 240), interpolation=cv2.INTER_AREA)
    noise = np.random.default_rng(0).integers(0, 65535, ref.shape).astype(np.uint16)
    fit = align_band(ref, noise)
    assert not fit.ok and fit.reason
    assert np.allclose(fit.H, np.eye(3))  # what it started from


# ----------------------------------------------------------------------------- grouping by name

def _tif(path: Path, value: int = 1000) -> None:
    img = np.random.default_rng(abs(hash(path.name)) % 2**32).integers(value, value + 5000, (40, 48)).astype(np.uint16)
    assert cv2.imwrite(str(path), img)


def test_dji_multispectral_and_sentera_layouts_group(tmp_path):
    dji = tmp_path / "dji"
    dji.mkdir()
    for k in range(3):
        for band in ("G", "R", "RE", "NIR"):
            _tif(dji / f"DJI_2023010112000{k}_000{k}_MS_{band}.TIF")
        cv2.imwrite(str(dji / f"DJI_2023010112000{k}_000{k}_D.JPG"), np.zeros((40, 48, 3), np.uint8))
    caps = group_captures(sorted(dji.iterdir()))
    assert caps is not None and len(caps) == 3
    assert all(c.bands == ("Green", "Red", "Red edge", "NIR") for c in caps)
    src = ImageFolderSource(dji, band="nir")
    assert len(list(src)) == 3 and all(p.name.endswith("_MS_NIR.TIF") for p in src.paths)

    sentera = tmp_path / "sentera"
    for band in ("Red", "NIR", "Green"):
        (sentera / band).mkdir(parents=True)
        for k in range(4):
            _tif(sentera / band / f"IMG_{k:05d}.tif")
    src = ImageFolderSource(sentera)
    assert len(src.captures) == 4 and set(src.captures[0].bands) == {"Green", "Red", "NIR"}
    assert len(list(src)) == 4


def test_plain_stills_are_not_grouped(tmp_path):
    for k in range(4):
        cv2.imwrite(str(tmp_path / f"IMG_{k:04d}.jpg"), np.full((40, 48, 3), 100, np.uint8))
    src = ImageFolderSource(tmp_path)
    assert src.captures is None and len(list(src)) == 4


def test_band_names_and_composite_choice():
    assert band_file_name("Red edge") == "mosaic_band_red_edge.png"
    names = ["Blue", "Green", "Red", "NIR", "Red edge"]
    assert composite_bands("", names) == ("NIR", "Red", "Green")
    assert composite_bands("re,red,green", names) == ("Red edge", "Red", "Green")
    assert composite_bands("", ["Blue", "Green", "Red"]) == ("Red", "Green", "Blue")
    assert composite_bands("swir,red,green", names) is None
    with pytest.raises(ConfigError, match="output.composite"):
        load_config().updated({"output": {"composite": "nir,red"}})


def test_16bit_range_and_stretch():
    img = np.linspace(1000, 50000, 10000).reshape(100, 100).astype(np.uint16)
    lo, hi = robust_range_16bit([img])
    assert 1000 < lo < 1500 and 49500 < hi < 50000
    out = to_8bit(img, (lo, hi))
    assert out.dtype == np.uint8 and out.min() == 0 and out.max() == 255
    # below the range saturates at 0 (it does not fold back up), above at 255, linear between
    probe = np.array([[0, 900, 1000, 1500, 2000, 2100, 65535]], np.uint16)
    assert to_8bit(probe, (1000.0, 2000.0)).tolist() == [[0, 0, 0, 128, 255, 255, 255]]


# ----------------------------------------------------------------------------- simulated survey

@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    out = tmp_path_factory.mktemp("multiband") / "flight"
    simulate_flight(out, mode="stills", stills_bands=5, strips=2, stills_per_strip=5, size=SIZE, seed=3)
    return out


def test_simulated_capture_files(survey):
    names = sorted(p.name for p in (survey / "stills").iterdir())
    assert len(names) == 10 * 5 and names[:2] == ["IMG_0000_1.tif", "IMG_0000_2.tif"]
    src = ImageFolderSource(survey / "stills")
    assert len(src.captures) == 10 and len(list(src)) == 10  # 10 captures x 5 files -> 10 frames


def test_alignment_recovers_the_lens_homographies(survey):
    meta = yaml.safe_load((survey / "meta.yaml").read_text())
    G = [np.array(b["lens_H"]) for b in meta["bands"]]
    src = ImageFolderSource(survey / "stills")
    r = src.captures[0].bands.index(src.band)
    errors = []
    for capture in src.captures[::3]:
        fits = align_capture([read_band(f.path) for f in capture.files], r)
        for b, fit in enumerate(fits):
            truth = np.linalg.inv(G[r]) @ G[b]
            assert fit.ok
            errors.append(corner_shift_px(np.linalg.inv(truth) @ fit.H, SIZE))
    assert max(errors) < 0.5, errors


def _patch_shift(a: np.ndarray, b: np.ndarray, alpha: np.ndarray, size: int = 96) -> list[float]:
    """Shifts (px) between two band maps, by phase correlation of their gradients on covered patches."""
    from photomap.core.bands import gradient_magnitude
    ga, gb = gradient_magnitude(a), gradient_magnitude(b)
    win = cv2.createHanningWindow((size, size), cv2.CV_32F)
    shifts = []
    h, w = a.shape
    for y in range(0, h - size, size):
        for x in range(0, w - size, size):
            if alpha[y:y + size, x:x + size].min() < 255:
                continue
            (dx, dy), _ = cv2.phaseCorrelate(ga[y:y + size, x:x + size], gb[y:y + size, x:x + size], win)
            shifts.append(float(np.hypot(dx, dy)))
    return shifts


def test_simulated_survey_maps_every_band_registered(survey, tmp_path):
    run = tmp_path / "run"
    summary = replay(str(survey / "stills"), run, load_config())
    assert summary["frames_in"] == 10 and summary["registered"] == 10 and summary["segments"] == 1
    info = json.loads((run / "run.json").read_text())["bands"]
    assert info["bands"] == ["Blue", "Green", "Red", "NIR", "Red edge"] and info["alignment"]["failed"] == 0
    mosaic = cv2.imread(str(run / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    maps = {}
    for name, file in info["files"].items():
        maps[name] = cv2.imread(str(run / file), cv2.IMREAD_UNCHANGED)
        assert maps[name].shape == mosaic.shape  # on mosaic.png's pixel grid
    assert set(maps) == set(info["bands"])
    composite = cv2.imread(str(run / "composite.png"), cv2.IMREAD_UNCHANGED)
    assert composite.shape == mosaic.shape and info["composite"]["rgb"] == ["NIR", "Red", "Green"]
    # the NIR map's pixels are the composite's red
    ok = composite[..., 3] == 255
    assert np.array_equal(composite[..., 2][ok], maps["NIR"][..., 0][ok])

    # band 1 (blue) and band 4 (NIR) put the same ground at the same map pixel, though their lenses
    # are several pixels apart (the simulator's truth)
    meta = yaml.safe_load((survey / "meta.yaml").read_text())
    G1, G4 = np.array(meta["bands"][0]["lens_H"]), np.array(meta["bands"][3]["lens_H"])
    lens_offset = corner_shift_px(np.linalg.inv(G4) @ G1, SIZE)
    assert lens_offset > 3.0
    alpha = np.minimum(maps["Blue"][..., 3], maps["NIR"][..., 3])
    shifts = _patch_shift(maps["Blue"][..., 0], maps["NIR"][..., 0], alpha)
    assert len(shifts) >= 10
    assert float(np.median(shifts)) < 1.0 and float(np.percentile(shifts, 90)) < 1.0, shifts

    rasterio = pytest.importorskip("rasterio", reason="the geo extra (rasterio) writes map_bands.tif")
    assert summary.get("georeference"), "the simulated GPS georeferences the map"
    with rasterio.open(run / "map_bands.tif") as ds:
        assert ds.count == 5 and list(ds.descriptions) == info["bands"]
        assert ds.crs is not None and ds.nodata == 0
        nir = ds.read(4)
        assert (nir > 0).mean() > 0.3


def test_a_band_that_does_not_align_keeps_the_previous_homography(survey, tmp_path, caplog):
    """A band image with nothing to align (here: noise) keeps the previous capture's homography:
    one logged line, counted in run.json, and its band map is still written."""
    import shutil
    stills = tmp_path / "stills"
    shutil.copytree(survey / "stills", stills)
    bad = stills / "IMG_0004_1.tif"
    noise = np.random.default_rng(1).integers(0, 65535, (SIZE[1], SIZE[0])).astype(np.uint16)
    from PIL import Image
    from photomap.sim.bands import micasense_xmp, write_band_still
    with Image.open(bad) as im:
        exif = im.getexif()
        for tag in (0x8769, 0x8825):
            exif.get_ifd(tag)  # read the sub-IFDs while the file is open
    write_band_still(bad, noise, exif, micasense_xmp(capture_id="sim3-000004", band=0))  # same capture, same band
    run = tmp_path / "run"
    with caplog.at_level("WARNING"):
        replay(str(stills), run, load_config())
    info = json.loads((run / "run.json").read_text())["bands"]
    assert info["alignment"]["failed"] == 1
    lines = [r.getMessage() for r in caplog.records if "band alignment failed" in r.getMessage()]
    assert len(lines) == 1 and "capture 4, Blue" in lines[0] and "no file" not in lines[0]
    assert (run / info["files"]["Blue"]).is_file()


def test_p4_multispectral_sequential_names_group_by_capture_uuid(tmp_path):
    """A P4 Multispectral numbers its band files in sequence (DJI_0011.TIF .. DJI_0015.TIF): the
    XMP (DJI writes attributes) says which capture and band each is."""
    from PIL import Image
    bands = ["Blue", "Green", "Red", "RedEdge", "NIR"]
    for k in range(2):
        for b, band in enumerate(bands):
            xmp = ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
                   '<rdf:Description rdf:about="" xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" '
                   'xmlns:Camera="http://pix4d.com/camera/1.0/" '
                   f'drone-dji:CaptureUUID="uuid-{k}" Camera:BandName="{band}" Camera:RigCameraIndex="{b + 1}"/>'
                   '</rdf:RDF></x:xmpmeta>').encode()
            img = Image.fromarray(np.full((40, 48), 1000 * (b + 1), np.uint16))
            img.save(tmp_path / f"DJI_{10 + 5 * k + b + 1:04d}.TIF", tiffinfo={700: xmp})
    caps = group_captures(sorted(tmp_path.iterdir()))
    assert caps is not None and [c.key for c in caps] == ["uuid-0", "uuid-1"]
    assert caps[0].bands == ("Blue", "Green", "Red", "Red edge", "NIR")
    assert [f.path.name for f in caps[1].files] == [f"DJI_{n:04d}.TIF" for n in range(16, 21)]


def test_tilted_captures_band_maps_follow_the_rectified_view(tmp_path):
    """Captures with a DJI attitude in their XMP (as a P4 Multispectral writes) are rectified to
    nadir from it: every band goes through the same rectification, so the band maps stay on the
    registering band's map (mosaic.png) and on each other."""
    flight = tmp_path / "flight"
    simulate_flight(flight, mode="stills", stills_bands=5, strips=2, stills_per_strip=5, size=SIZE, seed=3, tilt=4.0)
    run = tmp_path / "run"
    replay(str(flight / "stills"), run, load_config())
    info = json.loads((run / "run.json").read_text())
    assert info["telemetry"]["rectified"] == 10 and info["segments"] == 1
    mosaic = cv2.imread(str(run / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    files = info["bands"]["files"]
    nir = cv2.imread(str(run / files["NIR"]), cv2.IMREAD_UNCHANGED)
    blue = cv2.imread(str(run / files["Blue"]), cv2.IMREAD_UNCHANGED)
    gray = cv2.cvtColor(mosaic[..., :3], cv2.COLOR_BGR2GRAY)
    on_mosaic = _patch_shift(gray, nir[..., 0], np.minimum(mosaic[..., 3], nir[..., 3]))
    on_nir = _patch_shift(blue[..., 0], nir[..., 0], np.minimum(blue[..., 3], nir[..., 3]))
    assert len(on_mosaic) >= 10 and float(np.median(on_mosaic)) < 0.5, on_mosaic
    assert float(np.median(on_nir)) < 1.0 and float(np.percentile(on_nir, 90)) < 1.0, on_nir


def test_a_fit_beyond_a_rigs_lenses_is_refused():
    """A band 5 % larger than the reference is no lens of the same rig: the fit is refused."""
    folder, _ = _capture_rows()
    ref = cv2.resize(read_band(folder / "IMG_0001_5.tif"), (320, 240), interpolation=cv2.INTER_AREA)
    zoom = cv2.getRotationMatrix2D((159.5, 119.5), 0.0, 1.05)
    fit = align_band(ref, cv2.warpAffine(ref, zoom, (320, 240), borderMode=cv2.BORDER_REFLECT))
    assert not fit.ok and "scales by" in fit.reason
    ok = align_band(ref, cv2.warpAffine(ref, np.float64([[1, 0, 2.5], [0, 1, -1.5]]), (320, 240),
                                        borderMode=cv2.BORDER_REFLECT))
    assert ok.ok and abs(ok.H[0, 2] + 2.5) < 0.2 and abs(ok.H[1, 2] - 1.5) < 0.2
