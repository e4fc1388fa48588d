"""Stills in every format OpenCV reads, 16-bit stills stretched once per flight, and the image
libraries' warnings summarised instead of flooding stderr."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image, TiffImagePlugin

from conftest import shared_data
from photomap.cli.replay import replay
from photomap.config import load_config
from photomap.core.stretch import RunningStretch
from photomap.drivers.images import IMAGE_SUFFIXES, ImageFolderSource, list_images
from photomap.drivers.imread import ImageReader, warning_kind
from photomap.errors import InputError
from photomap.eval.evaluate import evaluate_run
from photomap.sim.simulate import simulate_flight

W, H = 320, 240


def texture(h: int = 80, w: int = 96, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur((rng.random((h, w, 3)) * 255).astype(np.uint8), (3, 3), 0)


def tiff_with_unknown_tags(path: Path, image: np.ndarray) -> None:
    """A 16-bit TIFF carrying private tags libtiff does not know (as MicaSense and DJI write)."""
    info = TiffImagePlugin.ImageFileDirectory_v2()
    info[48020] = "band"
    info[51022] = 3
    Image.fromarray(image).save(path, tiffinfo=info)


# ------------------------------------------------------------------ formats

def test_the_formats_of_this_build_are_listed():
    for suffix in (".jpg", ".png", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".pbm", ".pnm"):
        assert suffix in IMAGE_SUFFIXES
    assert (".webp" in IMAGE_SUFFIXES) == cv2.haveImageWriter("x.webp")
    assert (".jp2" in IMAGE_SUFFIXES) == cv2.haveImageWriter("x.jp2")


def test_every_format_is_read_at_its_depth_in_any_case(tmp_path):
    img = texture()
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    written = {"a.PGM": grey, "b.ppm": img, "c.Bmp": img, "d.TIF": img, "e.png": img, "f.pnm": img}
    if ".webp" in IMAGE_SUFFIXES:
        written["g.WEBP"] = img
    if ".jp2" in IMAGE_SUFFIXES:
        written["h.jp2"] = img
    for name, im in written.items():
        params = [cv2.IMWRITE_WEBP_QUALITY, 101] if name.lower().endswith(".webp") else []
        if name.endswith(".jp2"):
            params = [cv2.IMWRITE_JPEG2000_COMPRESSION_X1000, 1000]
        assert cv2.imwrite(str(tmp_path / name), im, params), name
    cv2.imwrite(str(tmp_path / "i.pbm"), np.where(grey > 128, 255, 0).astype(np.uint8))
    (tmp_path / "notes.txt").write_text("not an image")
    paths = list_images(tmp_path)
    assert [p.name for p in paths] == sorted([*written, "i.pbm"])
    frames = list(ImageFolderSource(tmp_path))
    assert len(frames) == len(paths)
    for frame in frames:
        assert frame.image.dtype == np.uint8 and frame.image.shape[:2] == (80, 96), frame.source
        if frame.source in ("a.PGM", "b.ppm", "c.Bmp", "d.TIF", "e.png", "f.pnm", "g.WEBP"):
            assert np.array_equal(frame.image, written[frame.source]), frame.source   # lossless
        if frame.source == "h.jp2":
            assert np.abs(frame.image.astype(int) - img).mean() < 2.0


def test_no_image_error_names_the_formats(tmp_path):
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(InputError, match=r"no images in .* \(formats read: jpg, .*pgm"):
        ImageFolderSource(tmp_path)


# ------------------------------------------------------------------ 16-bit: one range per flight

def test_stretch_is_per_flight_not_per_frame():
    rng = np.random.default_rng(3)
    scene = (8000 + rng.random((200, 300)) * 20000).astype(np.uint16)
    shadowed = scene.copy()
    shadowed[:, 150:] //= 4            # a cloud shadow over the right half
    flight, per_frame = RunningStretch(), RunningStretch(rate=1.0, widen_rate=1.0)
    a, b = flight(scene), flight(shadowed)
    diff = np.abs(a[:, :150].astype(int) - b[:, :150].astype(int))
    assert a.dtype == np.uint8 and diff.max() <= 5, diff.max()   # the same ground, the same grey (5 % drift)
    pa, pb = per_frame(scene), per_frame(shadowed)
    assert np.abs(pa[:, :150].astype(int) - pb[:, :150].astype(int)).mean() > 20   # what per frame would do
    # the robust range spans the scene: about 0.5 % saturates at each end
    assert 0.002 < (a == 255).mean() < 0.02 and 0.002 < (a == 0).mean() < 0.02
    # a blank frame first (lens cap) does not set the range; nor does one later
    late = RunningStretch()
    late(np.full((50, 50), 1000, np.uint16))
    assert np.array_equal(late(scene), flight_first := RunningStretch()(scene))
    late(np.full((50, 50), 60000, np.uint16))
    assert np.array_equal(late.apply(scene), flight_first)
    # uint8 passes through; NaN of a float frame is 0
    img8 = np.full((20, 20), 7, np.uint8)
    assert flight(img8) is img8
    f = np.linspace(0, 1, 400, dtype=np.float32).reshape(20, 20)
    f[0, 0] = np.nan
    out = RunningStretch()(f)
    assert out[0, 0] == 0 and out[-1, -1] == 255
    assert np.isnan(f[0, 0]) and f[-1, -1] == 1.0   # the input is left as it was


@pytest.fixture(scope="module")
def frames_png(tmp_path_factory):
    """A simulated video flight's frames as PNGs, with its truth."""
    out = tmp_path_factory.mktemp("seq")
    simulate_flight(out / "sim", terrain="aukerman", n_frames=90, size=(W, H), fps=15.0, seed=5,
                    save_frames=True)
    return out / "sim"


def test_pgm_sequence_maps_in_one_piece(frames_png, tmp_path):
    folder = tmp_path / "pgm"
    folder.mkdir()
    for p in sorted((frames_png / "frames").glob("*.png")):
        cv2.imwrite(str(folder / (p.stem + ".pgm")), cv2.imread(str(p), cv2.IMREAD_GRAYSCALE))
    summary = replay(str(folder), tmp_path / "run", load_config())
    assert summary["frames_in"] == summary["registered"] == 90 and summary["segments"] == 1
    ev = evaluate_run(tmp_path / "run", frames_png / "groundtruth.csv")["headline"]
    assert ev["frames_posed"] == 90 and ev["ate"]["pct"] < 1.0, ev["ate"]


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_16_bit_sequence_maps_and_keeps_one_range(frames_png, tmp_path, suffix):
    folder = tmp_path / "deep"
    folder.mkdir()
    grey8 = []
    for p in sorted((frames_png / "frames").glob("*.png")):
        g = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        grey8.append(g)
        deep = (g.astype(np.uint32) * 180 + 2500).astype(np.uint16)   # a 16-bit sensor's counts
        if suffix == ".tif":
            tiff_with_unknown_tags(folder / (p.stem + suffix), deep)
        else:
            assert cv2.imwrite(str(folder / (p.stem + suffix)), deep)
    source = ImageFolderSource(folder)
    frames = list(source)
    assert all(f.image.dtype == np.uint8 for f in frames) and source.stretch.frames == 90
    # one affine map from the sensor's counts to 8 bits at a time, moving slowly over the
    # flight: the same brightness gives the same grey in consecutive frames (what registration
    # and the map's seams see), and within a few levels across the whole flight
    def grey_of(k: int, level: float) -> float:
        fit = np.polyfit(grey8[k].ravel().astype(float), frames[k].image.ravel().astype(float), 1)
        assert fit[0] > 0.9
        return float(np.polyval(fit, level))
    for k in (0, 30, 60, 88):
        assert grey_of(k, 128.0) == pytest.approx(grey_of(k + 1, 128.0), abs=1.0)
    assert grey_of(0, 128.0) == pytest.approx(grey_of(89, 128.0), abs=12.0)
    summary = replay(str(folder), tmp_path / "run", load_config())
    assert summary["frames_in"] == summary["registered"] == 90 and summary["segments"] == 1


# ------------------------------------------------------------------ library warnings

def test_warning_kinds():
    line = ("[ WARN:0@0.031] global grfmt_tiff.cpp:123 TIFF_Warning TIFFReadDirectory: Unknown field "
            "with tag 48020 (0xbb94) encountered")
    assert warning_kind(line) == ("libtiff", "TIFFReadDirectory: Unknown field with tag N (N) encountered")
    assert warning_kind("Corrupt JPEG data: 12 extraneous bytes before marker 0xd9") == \
        ("libjpeg", "Corrupt JPEG data: N extraneous bytes before marker N")
    assert warning_kind("12:00:01 INFO photomap.cli: something") is None


def test_reader_counts_libtiff_warnings_and_passes_other_output(tmp_path, capfd):
    for k in range(3):
        tiff_with_unknown_tags(tmp_path / f"{k}.tif", (np.arange(6400).reshape(80, 80) * 7).astype(np.uint16))
    reader = ImageReader()
    for k in range(3):
        assert reader.read(tmp_path / f"{k}.tif").dtype == np.uint16
    assert reader.read(tmp_path / "missing.tif") is None
    err = capfd.readouterr().err
    assert "TIFFReadDirectory" not in err
    assert reader.summary() == ["libtiff warned 6 time(s) in 3 file(s) (first 0.tif): TIFFReadDirectory: "
                                "Unknown field with tag N (N) encountered",
                                "OpenCV warned 1 time(s) in 1 file(s) (first missing.tif): findDecoder "
                                "imread_('...'): can't open/read file: check file path/integrity"]


def test_other_output_during_a_read_reaches_stderr_as_written(monkeypatch, capfd):
    """What another thread writes to stderr while a still decodes (a progress bar's update, a
    log line) is passed on unchanged; only the library's warning is held back."""
    import os
    import photomap.drivers.imread as imread

    def noisy_imread(path, flags):
        os.write(2, b"mapping  50%|#####     |\r")
        os.write(2, b"[ WARN:0@1.0] global grfmt_tiff.cpp:123 TIFF_Warning TIFFReadDirectory: odd\n")
        os.write(2, b"12:00:00 INFO photomap.x: a log line\n")
        return np.zeros((4, 4), np.uint8)

    monkeypatch.setattr(imread.cv2, "imread", noisy_imread)
    reader = ImageReader()
    assert reader.read("x.tif").shape == (4, 4)
    assert capfd.readouterr().err == "mapping  50%|#####     |\r12:00:00 INFO photomap.x: a log line\n"
    assert list(reader.warnings) == [("libtiff", "TIFFReadDirectory: odd")]


def test_a_truncated_jpeg_is_read_and_its_warning_counted(tmp_path, capfd):
    ok, data = cv2.imencode(".jpg", texture(120, 160))
    (tmp_path / "cut.jpg").write_bytes(data.tobytes()[: len(data) // 2])
    reader = ImageReader()
    for _ in range(2):
        assert reader.read(tmp_path / "cut.jpg").shape == (120, 160, 3)   # libjpeg fills the rest
    assert "JPEG" not in capfd.readouterr().err
    assert reader.summary() == ["libjpeg warned 2 time(s) in 2 file(s) (first cut.jpg): Premature end of JPEG file"]


def test_stills_read_again_give_back_the_pixels_yielded_and_only_those(tmp_path, capfd):
    """What a re-render reads instead of a kept JPEG copy: the still's pixels exactly, from any
    8-bit single-band still whose read printed nothing; never a 16-bit one (stretched by the
    flight's range) nor one whose read warned (a second read would print it again)."""
    img = texture(120, 160)
    cv2.imwrite(str(tmp_path / "a.jpg"), img)
    cv2.imwrite(str(tmp_path / "b.png"), cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    cv2.imwrite(str(tmp_path / "c.png"), cv2.cvtColor(img, cv2.COLOR_BGR2BGRA))
    cv2.imwrite(str(tmp_path / "d.png"), (texture(120, 160, seed=1).astype(np.uint16) * 257))
    ok, data = cv2.imencode(".jpg", texture(120, 160, seed=2))
    (tmp_path / "e.jpg").write_bytes(data.tobytes()[: len(data) // 2])  # libjpeg warns, fills the rest
    source = ImageFolderSource(tmp_path)
    frames = {f.source: f for f in source}
    assert sorted(frames) == ["a.jpg", "b.png", "c.png", "d.png", "e.jpg"]
    for name in ("a.jpg", "b.png", "c.png"):
        frame = frames[name]
        assert source.readable_again(frame.index), name
        again = source.read_again(frame.index)
        assert again.dtype == np.uint8 and np.array_equal(again, frame.image), name
    for name in ("d.png", "e.jpg"):
        assert not source.readable_again(frames[name].index) and source.read_again(frames[name].index) is None
    (tmp_path / "a.jpg").unlink()  # gone since: None, not an error
    assert source.read_again(frames["a.jpg"].index) is None
    assert capfd.readouterr().err == ""


_QUIET_SCRIPT = """
import logging, sys
logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(levelname)s %(message)s")
from photomap.drivers.images import ImageFolderSource
n = sum(1 for _ in ImageFolderSource(sys.argv[1]))
print(n)
"""


def test_stderr_stays_quiet_for_a_folder_of_tiffs_with_private_tags(tmp_path):
    for k in range(12):
        ramp = ((np.indices((64, 64)).sum(0) + k) * 300).astype(np.uint16)
        tiff_with_unknown_tags(tmp_path / f"IMG_{k:04d}_1.tif", ramp)
    run = subprocess.run([sys.executable, "-c", _QUIET_SCRIPT, str(tmp_path)], capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0 and run.stdout.strip() == "12", run.stderr
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert not [line for line in lines if "TIFF_Warning" in line], lines
    warned = [line for line in lines if "libtiff warned" in line]
    assert warned == ["INFO libtiff warned 24 time(s) in 12 file(s) (first IMG_0000_1.tif): TIFFReadDirectory: "
                      "Unknown field with tag N (N) encountered"], lines
    assert len(lines) <= 3, lines


def test_a_real_micasense_tiff_is_read_quietly(capfd):
    path = shared_data("micasense_captures") / "IMG_0000_1.tif"
    reader = ImageReader()
    image = reader.read(path)
    assert image.dtype == np.uint16 and image.shape == (960, 1280)
    assert "TIFF" not in capfd.readouterr().err
    (kind, count), = reader.warnings.items()
    assert kind[0] == "libtiff" and "Unknown field with tag" in kind[1] and count >= 1


# ------------------------------------------------------------------ deep frames from a source
class _DeepLive:
    """A live source that delivers raw 16-bit frames, as a Y16 V4L2 thermal core does."""

    live = True

    def __init__(self, frames):
        from photomap.drivers.frames import CaptureStats
        self.frames, self.stats = frames, CaptureStats()

    def __iter__(self):
        from photomap.drivers.frames import Frame
        for i, image in enumerate(self.frames):
            self.stats.read += 1
            yield Frame(i, i / 15.0, image, "y16")

    def close(self):
        pass


def test_raw_16_bit_frames_of_a_live_source_map_through_one_stretch(frames_png, tmp_path):
    from photomap.mapping.pipeline import MappingPipeline
    paths = sorted((frames_png / "frames").glob("*.png"))[:40]
    deep = [(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).astype(np.uint32) * 180 + 2500).astype(np.uint16)
            for p in paths]
    pipe = MappingPipeline(_DeepLive(deep), load_config(), tmp_path / "run")
    summary = pipe.run()
    assert summary["registered"] == 40 and summary["segments"] == 1
    assert pipe._deep.frames == 40 and pipe._deep.low >= 2500 and pipe._deep.high <= 255 * 180 + 2500
    mosaic = cv2.imread(str(tmp_path / "run" / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    assert mosaic.dtype == np.uint8 and mosaic[..., 3].any()
    ev = evaluate_run(tmp_path / "run", frames_png / "groundtruth.csv")["headline"]
    assert ev["frames_posed"] == 40 and ev["ate"]["pct"] < 1.0, ev["ate"]
