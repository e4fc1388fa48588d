"""Frame sources: video files, still folders (EXIF times), a live camera driven by a fake capture."""

from __future__ import annotations

import csv
import itertools
import logging
import struct
import threading
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import cv2
import numpy as np
import pytest

from photomap.drivers.camera import CameraSource, backoff_delays
from photomap.drivers.frames import Frame, FrameSource
from photomap.drivers.capture import open_source
from photomap.drivers.images import ImageFolderSource, exif_time, parse_exif_datetime
from photomap.drivers.video import VideoFileSource, mp4_creation_time
from photomap.errors import InputError

from conftest import DATA_DIR as DATA
FPS = 10.0
N_FRAMES = 30
STEP = 8  # gray level per frame index: frame i is uniformly i * STEP


def _gray(i: int, size: tuple[int, int] = (160, 120)) -> np.ndarray:
    return np.full((size[1], size[0], 3), (i * STEP) % 256, np.uint8)


def _decoded_index(image: np.ndarray) -> int:
    return int(round(float(image.mean()) / STEP))


def _write_video(path: Path, fourcc: str) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), FPS, (160, 120))
    assert writer.isOpened()
    for i in range(N_FRAMES):
        writer.write(_gray(i))
    writer.release()
    return path


@pytest.fixture(scope="module")
def videos(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("videos")
    return {
        "mp4": _write_video(folder / "clip.mp4", "mp4v"),
        "avi": _write_video(folder / "clip.avi", "MJPG"),
    }


# --------------------------------------------------------------------------- video files


@pytest.mark.parametrize("kind", ["mp4", "avi"])
def test_video_returns_every_frame_in_order_with_pts(videos, kind):
    with VideoFileSource(videos[kind]) as src:
        assert isinstance(src, FrameSource) and not src.live
        assert src.fps == pytest.approx(FPS)
        assert src.frame_count == N_FRAMES
        assert src.size == (160, 120)
        frames = list(src)
    assert [f.index for f in frames] == list(range(N_FRAMES))
    assert [_decoded_index(f.image) for f in frames] == list(range(N_FRAMES))
    assert [f.t for f in frames] == pytest.approx([i / FPS for i in range(N_FRAMES)], abs=1e-6)
    assert all(f.image.dtype == np.uint8 and f.image.shape == (120, 160, 3) for f in frames)
    assert {f.source for f in frames} == {videos[kind].name}
    assert (src.stats.read, src.stats.corrupt, src.stats.dropped) == (N_FRAMES, 0, 0)


def test_video_skips_and_counts_a_frame_that_does_not_decode(videos, tmp_path, caplog):
    data = bytearray(videos["avi"].read_bytes())
    starts = [i for i in range(len(data) - 2) if data[i:i + 3] == b"\xff\xd8\xff"]
    assert len(starts) == N_FRAMES  # one JPEG per frame
    data[starts[10]:starts[10] + 200] = bytes(200)  # frame 10 loses its JPEG header
    broken = tmp_path / "broken.avi"
    broken.write_bytes(data)
    with caplog.at_level(logging.WARNING, logger="photomap.drivers.video"):
        with VideoFileSource(broken) as src:
            frames = list(src)
    expected = [i for i in range(N_FRAMES) if i != 10]
    assert [f.index for f in frames] == expected
    assert [_decoded_index(f.image) for f in frames] == expected
    assert [f.t for f in frames] == pytest.approx([i / FPS for i in expected], abs=1e-6)
    assert (src.stats.read, src.stats.corrupt) == (N_FRAMES - 1, 1)
    assert len([r for r in caplog.records if "could not be decoded" in r.getMessage()]) == 1


def test_video_close_ends_iteration(videos):
    src = VideoFileSource(videos["mp4"])
    got = []
    for frame in src:
        got.append(frame.index)
        if frame.index == 4:
            src.close()
    assert got == [0, 1, 2, 3, 4]


def test_not_a_video_is_an_input_error(tmp_path):
    fake = tmp_path / "notes.mp4"
    fake.write_text("this is a text file, not a video\n" * 20)
    with pytest.raises(InputError, match="notes.mp4.*not a video"):
        VideoFileSource(fake)
    empty = tmp_path / "empty.avi"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="empty.avi"):
        open_source(empty)


def test_missing_video_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="not found.*nothere.mp4"):
        open_source(tmp_path / "nothere.mp4")


def _box(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I4s", 8 + len(payload), kind) + payload


def test_mp4_creation_time_from_mvhd(tmp_path, videos):
    created = datetime(2024, 5, 17, 10, 30, 15, tzinfo=timezone.utc)
    since_1904 = int((created - datetime(1904, 1, 1, tzinfo=timezone.utc)).total_seconds())
    mvhd_v0 = bytes(4) + struct.pack(">II", since_1904, since_1904) + bytes(88)
    mvhd_v1 = b"\x01\x00\x00\x00" + struct.pack(">QQ", since_1904, since_1904) + bytes(88)
    for name, mvhd in [("v0.mp4", mvhd_v0), ("v1.mov", mvhd_v1)]:
        path = tmp_path / name
        path.write_bytes(_box(b"ftyp", b"isom" + bytes(4)) + _box(b"free", bytes(5))
                         + _box(b"moov", _box(b"trak", bytes(3)) + _box(b"mvhd", mvhd)))
        assert mp4_creation_time(path) == created.timestamp()
    # OpenCV's writer stores 0 (unset); an AVI has no mvhd at all
    assert mp4_creation_time(videos["mp4"]) is None
    assert mp4_creation_time(videos["avi"]) is None
    assert VideoFileSource(videos["mp4"]).creation_time is None


# --------------------------------------------------------------------------- stills


def _tiff_exif(order: str, fields: dict[int, str]) -> bytes:
    """A TIFF block: IFD0 holding only the Exif IFD pointer, then an Exif IFD of ASCII fields."""
    exif_offset = 8 + 2 + 12 + 4
    entries = sorted(fields.items())
    data_offset = exif_offset + 2 + 12 * len(entries) + 4
    ifd, data = b"", b""
    for tag, text in entries:
        value = text.encode("ascii") + b"\x00"
        if len(value) <= 4:
            field = value.ljust(4, b"\x00")
        else:
            field = struct.pack(order + "I", data_offset + len(data))
            data += value
        ifd += struct.pack(order + "HHI", tag, 2, len(value)) + field
    return ((b"II" if order == "<" else b"MM") + struct.pack(order + "HI", 42, 8)
            + struct.pack(order + "HHHII", 1, 0x8769, 4, 1, exif_offset) + struct.pack(order + "I", 0)
            + struct.pack(order + "H", len(entries)) + ifd + struct.pack(order + "I", 0) + data)


def _jpeg_with_exif(path: Path, image: np.ndarray, order: str, fields: dict[int, str]) -> None:
    jpeg = cv2.imencode(".jpg", image)[1].tobytes()
    payload = b"Exif\x00\x00" + _tiff_exif(order, fields)
    path.write_bytes(jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + jpeg[2:])


def test_parse_exif_datetime():
    utc = datetime(2016, 6, 23, 16, 31, 59, tzinfo=timezone.utc).timestamp()
    assert parse_exif_datetime("2016:06:23 16:31:59") == utc
    assert parse_exif_datetime("2016:06:23 16:31:59", "25") == utc + 0.25
    assert parse_exif_datetime("2016:06:23 16:31:59", "007", "+02:00") == pytest.approx(utc - 7200 + 0.007)
    assert parse_exif_datetime("2016:06:23 16:31:59", None, "-05:30") == utc + 5.5 * 3600
    with pytest.raises(ValueError):
        parse_exif_datetime("0000:00:00 00:00:00")


@pytest.mark.parametrize("order", ["<", ">"])
def test_exif_time_from_jpeg_bytes(tmp_path, order):
    path = tmp_path / "shot.jpg"
    _jpeg_with_exif(path, _gray(3), order,
                    {0x9003: "2021:03:04 05:06:07", 0x9291: "5", 0x9011: "+01:00"})
    expected = datetime(2021, 3, 4, 4, 6, 7, 500000, tzinfo=timezone.utc).timestamp()
    assert exif_time(path) == pytest.approx(expected, abs=1e-6)
    plain = tmp_path / "plain.jpg"
    cv2.imwrite(str(plain), _gray(3))
    assert exif_time(plain) is None
    garbage = tmp_path / "garbage.jpg"
    garbage.write_bytes(b"\xff\xd8\xff\xe1\x00\x10Exif\x00\x00II*\x00\xff\xff\xff\xff")
    assert exif_time(garbage) is None  # malformed EXIF: no time, no exception


def test_exif_time_agrees_with_pillow(tmp_path):
    Image = pytest.importorskip("PIL.Image")
    exif = Image.Exif()
    exif.get_ifd(0x8769).update({0x9003: "2019:12:31 23:59:58", 0x9291: "123"})
    path = tmp_path / "pillow.jpg"
    Image.new("RGB", (32, 24), (10, 20, 30)).save(path, exif=exif)
    expected = datetime(2019, 12, 31, 23, 59, 58, 123000, tzinfo=timezone.utc).timestamp()
    assert exif_time(path) == pytest.approx(expected, abs=1e-6)


def test_folder_uses_exif_times(tmp_path):
    start = datetime(2022, 7, 1, 12, 0, 0)
    for i in range(3):
        stamp = (start + timedelta(seconds=2.5 * i)).strftime("%Y:%m:%d %H:%M:%S")
        sub = "5" if i % 2 else "0"
        _jpeg_with_exif(tmp_path / f"img_{i}.jpg", _gray(i), "<", {0x9003: stamp, 0x9291: sub})
    src = ImageFolderSource(tmp_path, rate=99.0)
    frames = list(src)
    t0 = start.replace(tzinfo=timezone.utc).timestamp()
    assert src.exif_times
    assert [f.t for f in frames] == pytest.approx([t0, t0 + 2.5, t0 + 5.0], abs=1e-6)


def test_folder_skips_a_corrupt_image_and_times_by_rate(tmp_path, caplog):
    for i in range(5):
        cv2.imwrite(str(tmp_path / f"f{i:02d}.{'png' if i % 2 else 'jpg'}"), _gray(i, (64, 48)))
    (tmp_path / "f02.jpg").write_bytes(b"\xff\xd8\xff\xe0 definitely not a jpeg " * 10)  # corrupt
    (tmp_path / "readme.txt").write_text("not an image")
    _jpeg_with_exif(tmp_path / "f04.jpg", _gray(4, (64, 48)), "<", {0x9003: "2020:01:01 00:00:00"})
    with caplog.at_level(logging.WARNING, logger="photomap.drivers.images"):
        src = open_source(tmp_path, image_rate=2.0)
        assert isinstance(src, ImageFolderSource)
        frames = list(src)
    assert [f.index for f in frames] == [0, 1, 3, 4]
    assert [f.source for f in frames] == ["f00.jpg", "f01.png", "f03.png", "f04.jpg"]
    assert [_decoded_index(f.image) for f in frames] == [0, 1, 3, 4]
    # only one of five stills has an EXIF time: all are timed by index at 2 per second
    assert not src.exif_times
    assert [f.t for f in frames] == [0.0, 0.5, 1.5, 2.0]
    assert (src.stats.read, src.stats.corrupt) == (4, 1)
    skips = [r for r in caplog.records if "f02.jpg" in r.getMessage()]
    assert len(skips) == 1 and skips[0].levelno == logging.WARNING


def test_glob_selects_stills(tmp_path):
    for name in ["a.jpg", "b.png", "c.jpg"]:
        cv2.imwrite(str(tmp_path / name), _gray(1, (16, 16)))
    src = open_source(str(tmp_path / "*.jpg"))
    assert [f.source for f in src] == ["a.jpg", "c.jpg"]


def test_empty_or_missing_folder_is_an_input_error(tmp_path):
    (tmp_path / "notes.txt").write_text("no images here")
    with pytest.raises(InputError, match="no images"):
        open_source(tmp_path)
    with pytest.raises(InputError, match="no images"):
        open_source(str(tmp_path / "*.jpg"))
    with pytest.raises(InputError, match="not found"):
        ImageFolderSource(tmp_path / "missing")


def test_brighton_beach_stills():
    folder = DATA / "brighton_beach" / "images"
    if not folder.is_dir():
        pytest.skip(f"real data not available: {folder}")
    src = open_source(folder)
    frames = list(src)
    assert len(frames) == 18 and src.stats.corrupt == 0
    assert [f.source for f in frames] == [f"DJI_{n:04d}.jpg" for n in range(18, 36)]
    assert all(f.image.shape == (562, 1000, 3) for f in frames)
    # The downscaled stills carry no EXIF (only JFIF): times fall back to index / rate.
    assert not src.exif_times
    assert [f.t for f in frames] == [float(i) for i in range(18)]
    # The original EXIF times survive in poses.csv: one shot every ~7 s.
    with open(DATA / "brighton_beach" / "poses.csv", newline="") as f:
        times = [parse_exif_datetime(row["datetime"]) for row in csv.DictReader(f)]
    steps = np.diff(times)
    assert len(times) == 18 and np.all(steps >= 6) and np.all(steps <= 10)
    assert np.median(steps) == pytest.approx(7.0)


# --------------------------------------------------------------------------- live camera


class FakeCapture:
    """A cv2.VideoCapture stand-in that plays a script of reads.

    ``script`` items: an int v (a frame whose pixels are all v) or None (a failed read).
    After the script: ``then="fail"`` fails every read; ``then="hold"`` sets ``exhausted`` and
    blocks until ``until()`` is true, then fails.
    """

    def __init__(self, script=(), *, opened=True, then="hold", until=lambda: True):
        self.script = list(script)
        self.opened = opened
        self.then = then
        self.until = until
        self.exhausted = threading.Event()
        self.released = threading.Event()
        self.props: dict[int, float] = {}

    def isOpened(self):
        return self.opened

    def set(self, prop, value):
        self.props[prop] = value
        return True

    def read(self):
        if self.script:
            item = self.script.pop(0)
            return (False, None) if item is None else (True, np.full((4, 6, 3), item, np.uint8))
        self.exhausted.set()
        if self.then == "hold":
            while not self.until():
                time.sleep(0.001)
        return False, None

    def release(self):
        self.released.set()


def _factory(*captures):
    """A capture factory handing out ``captures`` in turn; records the devices asked for."""
    queue = list(captures)
    asked = []

    def factory(device):
        asked.append(device)
        return queue.pop(0)

    factory.asked = asked
    return factory


def test_missing_camera_is_an_input_error():
    with pytest.raises(InputError, match="cannot open camera /dev/video97"):
        CameraSource("/dev/video97", capture_factory=_factory(FakeCapture(opened=False)))
    if not Path("/dev/video97").exists():  # the real V4L2 backend says the same
        with pytest.raises(InputError, match="cannot open camera /dev/video97"):
            open_source("/dev/video97")


def test_camera_drops_the_oldest_frames_for_a_slow_consumer():
    src = None
    fake = FakeCapture(range(10), until=lambda: src.closed)
    src = CameraSource(0, queue_size=4, width=640, fourcc="MJPG", capture_factory=_factory(fake))
    assert src.live and isinstance(src, FrameSource)
    assert fake.exhausted.wait(10), "capture thread did not read the script"
    got = list(itertools.islice(src, 4))
    assert [f.index for f in got] == [6, 7, 8, 9]  # the newest survive
    assert [int(f.image[0, 0, 0]) for f in got] == [6, 7, 8, 9]
    assert all(a.t <= b.t for a, b in zip(got, got[1:]))
    assert (src.stats.read, src.stats.dropped, src.stats.reconnects) == (10, 6, 0)
    assert fake.props[cv2.CAP_PROP_FRAME_WIDTH] == 640
    assert fake.props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter_fourcc(*"MJPG")
    assert cv2.CAP_PROP_FRAME_HEIGHT not in fake.props
    src.close()
    assert fake.released.is_set()


def test_camera_keeps_every_frame_for_a_consumer_that_keeps_up():
    taken = threading.Semaphore(0)

    class LockStep(FakeCapture):
        def read(self):
            if len(self.script) < 10:  # each read after the first waits for the previous take
                taken.acquire()
            return super().read()

    src = None
    fake = LockStep(range(10), until=lambda: src.closed)
    src = CameraSource("/dev/video0", queue_size=1, capture_factory=_factory(fake))
    got = []
    for frame in src:
        got.append(frame.index)
        taken.release()
        if len(got) == 10:
            break
    src.close()
    assert got == list(range(10))
    assert (src.stats.read, src.stats.dropped) == (10, 0)


def test_camera_reconnects_after_it_is_lost():
    src = None
    first = FakeCapture([0, 1, 2], then="fail")  # unplugged after three frames
    still_gone = FakeCapture(opened=False)
    back = FakeCapture([100, 101, 102], until=lambda: src.closed)
    factory = _factory(first, still_gone, back)
    src = CameraSource("/dev/video3", queue_size=16, read_failures=3, reconnect_initial=0.001,
                       reconnect_max=0.002, capture_factory=factory)
    got = list(itertools.islice(src, 6))
    src.close()
    assert [int(f.image[0, 0, 0]) for f in got] == [0, 1, 2, 100, 101, 102]
    assert [f.index for f in got] == list(range(6))
    assert all(a.t <= b.t for a, b in zip(got, got[1:]))
    assert factory.asked == ["/dev/video3"] * 3
    assert first.released.is_set() and still_gone.released.is_set()
    assert (src.stats.reconnects, src.stats.read, src.stats.dropped) == (1, 6, 0)


def test_camera_that_opens_but_stays_dark_is_one_outage(caplog):
    src = None
    first = FakeCapture([0], then="fail")
    dark = FakeCapture([], then="fail")  # reopens fine, still delivers nothing
    back = FakeCapture([5], until=lambda: src.closed)
    with caplog.at_level(logging.WARNING, logger="photomap.drivers.camera"):
        src = CameraSource(4, read_failures=2, reconnect_initial=0.001, reconnect_max=0.001,
                           capture_factory=_factory(first, dark, back))
        got = []
        for frame in src:
            got.append(int(frame.image[0, 0, 0]))
            if len(got) == 2:
                break
        src.close()
    assert got == [0, 5]
    assert dark.released.is_set()
    assert src.stats.reconnects == 1
    messages = [r.getMessage() for r in caplog.records]
    assert sum("lost" in m for m in messages) == 1
    assert sum("is back" in m for m in messages) == 1


def test_close_interrupts_reconnect_back_off_and_joins_the_thread():
    lost = FakeCapture([], then="fail")
    src = CameraSource(1, read_failures=2, reconnect_initial=3600.0, reconnect_max=3600.0,
                       capture_factory=_factory(lost), join_timeout=30.0)
    assert lost.released.wait(10), "the lost camera was not released"
    src.close()  # the thread waits 3600 s before reopening: close must wake it
    assert not [t for t in threading.enumerate() if t.name == "capture 1"]
    assert list(src) == []


def test_capture_thread_error_reaches_the_consumer():
    class Broken(FakeCapture):
        def read(self):
            raise RuntimeError("driver exploded")

    src = CameraSource(2, capture_factory=_factory(Broken()))
    with pytest.raises(RuntimeError, match="driver exploded"):
        list(src)
    src.close()


def test_backoff_delays_double_up_to_the_cap():
    gen = backoff_delays(0.5, 3.0)
    assert [next(gen) for _ in range(6)] == [0.5, 1.0, 2.0, 3.0, 3.0, 3.0]


def test_open_source_routes_specs(tmp_path, videos):
    assert isinstance(open_source(videos["mp4"]), VideoFileSource)
    cv2.imwrite(str(tmp_path / "a.png"), _gray(1, (8, 8)))
    assert isinstance(open_source(tmp_path), ImageFolderSource)
    assert isinstance(open_source(str(tmp_path / "*.png")), ImageFolderSource)
    for spec, device in [(0, 0), ("2", 2), ("/dev/video5", "/dev/video5")]:
        factory = _factory(FakeCapture(then="fail"))
        src = open_source(spec, fourcc="", width=0, reconnect_initial=3600.0, capture_factory=factory)
        assert isinstance(src, CameraSource)
        src.close()
        assert factory.asked == [device]


def test_frame_is_immutable():
    frame = Frame(index=0, t=0.0, image=np.zeros((2, 2), np.uint8), source="x")
    with pytest.raises(AttributeError):
        frame.index = 1  # type: ignore[misc]
