"""V4L2 cameras as they are: MJPG, YUYV, GREY and Y16 (16-bit thermal) pixel formats, a camera that
delivers another size or format than asked for, and a real V4L2 device where v4l2loopback exists."""

from __future__ import annotations

import logging
import shutil
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from photomap.config import load_config
from photomap.drivers.camera import CameraSource, fourcc_text, normalize_fourcc
from photomap.errors import ConfigError, InputError


def _code(text: str) -> int:
    return cv2.VideoWriter_fourcc(*text)


class V4L2Like:
    """A capture that negotiates as OpenCV's V4L2 backend does.

    ``offers`` maps the pixel formats the camera has to the one size it delivers in each.
    Setting an offered FOURCC switches to it (another one is refused and the format stays);
    width/height are clamped to the format's size; with CAP_PROP_CONVERT_RGB on, frames are
    uint8 BGR (as OpenCV converts them); off, GREY gives uint8 HxW and Y16 uint16 HxW, the raw
    values. Frame ``i`` holds ``base + i`` everywhere.
    """

    def __init__(self, offers: dict[str, tuple[int, int]], *, start: str, base: int = 0, n: int = 5,
                 until=lambda: True) -> None:
        self.offers = offers
        self.format = start
        self.convert = True
        self.base, self.n, self.until = base, n, until
        self.sets: list[tuple[int, float]] = []
        self.reads = 0

    def isOpened(self) -> bool:
        return True

    def set(self, prop: int, value: float) -> bool:
        self.sets.append((prop, value))
        if prop == cv2.CAP_PROP_FOURCC:
            text = fourcc_text(value).ljust(4)
            if text not in self.offers:
                return False
            self.format = text
            return True
        if prop == cv2.CAP_PROP_CONVERT_RGB:
            self.convert = bool(value)
            return True
        return prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT, cv2.CAP_PROP_FPS)

    def get(self, prop: int) -> float:
        w, h = self.offers[self.format]
        return {cv2.CAP_PROP_FOURCC: float(_code(self.format)), cv2.CAP_PROP_FRAME_WIDTH: float(w),
                cv2.CAP_PROP_FRAME_HEIGHT: float(h), cv2.CAP_PROP_FPS: 30.0}.get(prop, -1.0)

    def read(self):
        if self.reads >= self.n:
            while not self.until():
                time.sleep(0.001)
            return False, None
        value = self.base + self.reads
        self.reads += 1
        w, h = self.offers[self.format]
        if self.convert:
            return True, np.full((h, w, 3), min(value, 255), np.uint8)
        if self.format == "Y16 ":
            return True, np.full((h, w), value, np.uint16)
        if self.format == "GREY":
            return True, np.full((h, w), value, np.uint8)
        raise AssertionError(f"{self.format} without conversion is not a frame")

    def release(self) -> None:
        pass


def _frames(src: CameraSource, n: int) -> list:
    got = []
    for frame in src:
        got.append(frame)
        if len(got) == n:
            break
    src.close()
    return got


def test_y16_thermal_frames_keep_their_16_bit_values(caplog):
    src = None
    cam = V4L2Like({"YUYV": (640, 480), "Y16 ": (640, 512)}, start="YUYV", base=30000,
                   until=lambda: src.closed)
    with caplog.at_level(logging.INFO, logger="photomap.drivers.camera"):
        src = CameraSource("/dev/video1", fourcc="Y16", width=640, height=512, queue_size=32, capture_factory=lambda d: cam)
        got = _frames(src, 5)
    assert (cv2.CAP_PROP_FOURCC, _code("Y16 ")) in cam.sets
    assert (cv2.CAP_PROP_CONVERT_RGB, 0) in cam.sets  # OpenCV would otherwise cut them to 8 bits
    assert all(f.image.dtype == np.uint16 and f.image.shape == (512, 640) for f in got)
    assert [int(f.image[0, 0]) for f in got] == [30000, 30001, 30002, 30003, 30004]
    said = [r.getMessage() for r in caplog.records]
    assert said == ["camera /dev/video1: asked for 640x512 Y16, delivers uint16 gray 640x512 (Y16 at 30 fps)"]


@pytest.mark.parametrize("asked, dtype, shape", [("MJPG", np.uint8, (480, 640, 3)),
                                                 ("YUYV", np.uint8, (480, 640, 3)),
                                                 ("GREY", np.uint8, (480, 640))])
def test_8_bit_formats(asked, dtype, shape):
    src = None
    cam = V4L2Like({"MJPG": (640, 480), "YUYV": (640, 480), "GREY": (640, 480)}, start="MJPG", base=7,
                   until=lambda: src.closed)
    src = CameraSource(0, fourcc=asked.lower(), queue_size=32, capture_factory=lambda d: cam)
    got = _frames(src, 3)
    assert cam.format == asked
    assert ((cv2.CAP_PROP_CONVERT_RGB, 0) in cam.sets) == (asked == "GREY")
    assert all(f.image.dtype == dtype and f.image.shape == shape for f in got)
    assert [int(f.image.flat[0]) for f in got] == [7, 8, 9]


def test_what_the_camera_delivers_instead_is_said_once(caplog):
    src = None
    # A UVC camera with YUYV only, at 640x480: asked for MJPG at 1280x720.
    cam = V4L2Like({"YUYV": (640, 480)}, start="YUYV", n=20, until=lambda: src.closed)
    with caplog.at_level(logging.INFO, logger="photomap.drivers.camera"):
        src = CameraSource(0, fourcc="MJPG", width=1280, height=720, fps=30, queue_size=32, capture_factory=lambda d: cam)
        got = _frames(src, 20)
    assert len(got) == 20 and all(f.image.shape == (480, 640, 3) for f in got)
    said = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert said[0] == ("WARNING", "camera 0: could not set property 6 to 1196444237")  # CAP_PROP_FOURCC
    assert said[1:] == [
        ("INFO", "camera 0: asked for 1280x720 MJPG at 30 fps, delivers uint8 BGR 640x480 (YUYV at 30 fps)"),
        ("WARNING", "camera 0 delivers YUYV, not the MJPG asked for"),
        ("WARNING", "camera 0 delivers 640x480, not the 1280x720 asked for"),
    ]


def test_fourcc_codes():
    assert normalize_fourcc("Y16") == "Y16 " and normalize_fourcc("mjpg") == "MJPG"
    assert fourcc_text(_code("YUYV")) == "YUYV" and fourcc_text(_code("Y16 ")) == "Y16"
    assert fourcc_text(0) == "" and fourcc_text(-1) == ""
    with pytest.raises(InputError, match="fourcc"):
        CameraSource(0, fourcc="MJPEG", capture_factory=lambda d: V4L2Like({}, start="MJPG"))


def test_config_takes_the_v4l2_formats_and_names_a_bad_one():
    for code in ("MJPG", "YUYV", "GREY", "Y16", ""):
        assert load_config(overrides=[f"capture.fourcc={code}"]).capture.fourcc == code
    with pytest.raises(ConfigError, match="capture.fourcc"):
        load_config(overrides=["capture.fourcc=MJPEG"])


# ------------------------------------------------------------------------ a real V4L2 device


def _loopback_device() -> Path | None:
    """A v4l2loopback video device, if the kernel has one."""
    for name in sorted(Path("/sys/class/video4linux").glob("video*/name")) if Path("/sys/class/video4linux").is_dir() \
            else []:
        try:
            label = name.read_text().strip().lower()
        except OSError:
            continue
        if "loopback" in label or "dummy" in label:
            return Path("/dev") / name.parent.name
    return None


@pytest.mark.parametrize("fourcc, pix_fmt, shape", [("YUYV", "yuyv422", (240, 320, 3)),
                                                    ("GREY", "gray", (240, 320))])
def test_a_real_v4l2_loopback_device(fourcc, pix_fmt, shape):
    device = _loopback_device()
    if device is None:
        pytest.skip("no v4l2loopback device: the kernel module is not loaded here "
                    "(modprobe v4l2loopback exclusive_caps=1, as root, where the kernel has it)")
    ffmpeg = shutil.which("ffmpeg")
    if not ffmpeg:
        pytest.skip("ffmpeg is not installed (it feeds the loopback device)")
    feeder = subprocess.Popen([ffmpeg, "-hide_banner", "-loglevel", "error", "-re", "-f", "lavfi", "-i",
                               "testsrc=size=320x240:rate=30", "-t", "20", "-pix_fmt", pix_fmt, "-f", "v4l2",
                               str(device)], stdin=subprocess.DEVNULL)
    try:
        time.sleep(1.0)  # the device takes its format from the first frame written
        src = CameraSource(str(device), fourcc=fourcc)
        got = _frames(src, 10)
        assert len(got) == 10 and all(f.image.shape == shape and f.image.dtype == np.uint8 for f in got)
        assert all(a.index < b.index and a.t <= b.t for a, b in zip(got, got[1:]))
        assert len({f.image.tobytes() for f in got}) > 1  # the test pattern moves
    finally:
        feeder.kill()
        feeder.wait()
