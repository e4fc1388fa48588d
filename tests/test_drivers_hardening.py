"""Drivers that never hang: a capture is released only by (or without) its reader; stills that
cannot be registered are skipped; unreadable folders are one clear line."""

from __future__ import annotations

import logging
import random
import shutil
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from photomap.cli.main import main
from photomap.config import load_config
from photomap.drivers.camera import CameraSource
from photomap.drivers.images import ImageFolderSource
from photomap.drivers.video import VideoFileSource
from photomap.errors import ConfigError, InputError
from photomap.io.trajectory_files import read_trajectory_csv
from photomap.mapping.pipeline import MappingPipeline
from photomap.sim.simulate import simulate_flight

REAL_CAPTURE = cv2.VideoCapture


class WatchedCapture:
    """A real ``cv2.VideoCapture`` that records what must never happen: a ``release()`` while a
    ``read()`` runs, or a ``read()`` after ``release()``. Reads take a little longer (sleep), so
    a close from another thread lands inside one; ``hold`` (an Event) blocks reads while clear."""

    made: list["WatchedCapture"] = []
    hold: threading.Event | None = None

    def __init__(self, *args) -> None:
        self._cap = REAL_CAPTURE(*args)
        self.reading = 0
        self.released = threading.Event()
        self.violations: list[str] = []
        self.in_read = threading.Event()
        WatchedCapture.made.append(self)

    def read(self):
        self.reading += 1
        self.in_read.set()
        try:
            if self.released.is_set():
                self.violations.append("read after release")
            if WatchedCapture.hold is not None:
                WatchedCapture.hold.wait(30)
            threading.Event().wait(0.003)
            return self._cap.read()
        finally:
            self.reading -= 1

    def release(self) -> None:
        if self.reading:
            self.violations.append("release during read")
        self.released.set()
        self._cap.release()

    def isOpened(self):
        return self._cap.isOpened()

    def get(self, prop):
        return self._cap.get(prop)


@pytest.fixture
def watched(monkeypatch):
    WatchedCapture.made = []
    WatchedCapture.hold = None
    monkeypatch.setattr(cv2, "VideoCapture", WatchedCapture)
    yield WatchedCapture
    WatchedCapture.hold = None


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("flight")
    simulate_flight(out, n_frames=30, size=(320, 240), fps=15.0, seed=4, save_frames=True)
    return out


def test_close_from_another_thread_never_releases_under_a_read(flight, watched):
    """The bug: close() released the capture while the decode thread was inside read() (FFmpeg
    deadlock or crash). Close at random moments of a read loop, many times."""
    rng = random.Random(5)
    for trial in range(15):
        src = VideoFileSource(flight / "video.mp4")
        got: list[int] = []
        reader = threading.Thread(target=lambda: got.extend(f.index for f in src), daemon=True)
        reader.start()
        threading.Event().wait(rng.uniform(0.0, 0.05))
        src.close()
        reader.join(10)
        assert not reader.is_alive(), f"trial {trial}: the reader did not end"
        cap = watched.made[-1]
        assert cap.violations == [], f"trial {trial}: {cap.violations}"
        assert cap.released.is_set() and src.released
        assert got == list(range(len(got)))  # in order, no gap, whatever was read before close
    assert sum(len(c.violations) for c in watched.made) == 0


def test_close_does_not_wait_forever_for_a_stuck_decoder(flight, watched, caplog):
    src = VideoFileSource(flight / "video.mp4", close_timeout=0.2)
    cap = watched.made[-1]
    watched.hold = threading.Event()  # the next read blocks: a decoder stuck in read()
    cap.in_read.clear()
    reader = threading.Thread(target=lambda: list(src), daemon=True)
    reader.start()
    assert cap.in_read.wait(10)
    with caplog.at_level(logging.WARNING, logger="photomap.drivers.video"):
        src.close()  # returns after close_timeout, leaving the capture to the stuck reader
    assert not src.released and not cap.released.is_set()
    assert any("did not return" in r.getMessage() for r in caplog.records)
    watched.hold.set()  # the decoder comes back: its thread releases the capture
    reader.join(10)
    assert not reader.is_alive() and src.released and cap.violations == []


@pytest.mark.parametrize("how", ["stop", "error"])
def test_pipeline_stop_or_error_releases_the_decoder_in_its_thread(flight, watched, tmp_path, how,
                                                                    monkeypatch):
    if how == "error":  # the worker fails while the decoder runs ahead
        def fail(self, image):
            raise RuntimeError("worker failed")
        monkeypatch.setattr(MappingPipeline, "_setup", fail)
    src = VideoFileSource(flight / "video.mp4")
    pipeline = MappingPipeline(src, load_config(), tmp_path)
    if how == "stop":
        pipeline.stop()  # before run(): it maps nothing beyond what was already queued
        summary = pipeline.run()
        rows = read_trajectory_csv(tmp_path / "trajectory.csv") if summary["frames_in"] else []
        assert summary["complete"] and len(rows) == summary["frames_in"] < 30
    else:
        with pytest.raises(RuntimeError, match="worker failed"):
            pipeline.run()
    cap = watched.made[-1]
    assert cap.released.wait(10) and cap.violations == []
    decode = [t for t in threading.enumerate() if t.name == "photomap-decode"]
    for t in decode:
        t.join(10)
    assert not any(t.is_alive() for t in decode)


class BlockingCamera:
    """A fake V4L2 capture: frames until ``stuck`` is set, then a read that blocks until
    ``unstick`` is set (a driver hung in VIDIOC_DQBUF). Records releases under a running read."""

    def __init__(self) -> None:
        self.reading = 0
        self.stuck = threading.Event()
        self.unstick = threading.Event()
        self.in_stuck_read = threading.Event()
        self.released = threading.Event()
        self.violations: list[str] = []

    def isOpened(self):
        return True

    def set(self, prop, value):
        return True

    def read(self):
        self.reading += 1
        try:
            if self.stuck.is_set():
                self.in_stuck_read.set()
                self.unstick.wait(30)
            threading.Event().wait(0.002)
            return True, np.zeros((4, 6, 3), np.uint8)
        finally:
            self.reading -= 1

    def release(self):
        if self.reading:
            self.violations.append("release during read")
        self.released.set()


def test_camera_close_lets_the_capture_thread_release(caplog):
    cams = [BlockingCamera() for _ in range(10)]
    for cam in cams:  # close at once, from another thread, while the thread reads
        src = CameraSource(0, capture_factory=lambda device, cam=cam: cam, join_timeout=10.0)
        threading.Event().wait(0.01)
        src.close()
        assert cam.released.is_set() and cam.violations == []
    cam = BlockingCamera()
    cam.stuck.set()
    src = CameraSource(1, capture_factory=lambda device: cam, join_timeout=0.2)
    assert cam.in_stuck_read.wait(10)
    with caplog.at_level(logging.WARNING, logger="photomap.drivers.camera"):
        src.close()  # returns after join_timeout; the stuck thread keeps its capture
    assert not cam.released.is_set() and list(src) == []
    assert any("did not stop" in r.getMessage() for r in caplog.records)
    cam.unstick.set()  # the driver returns: the thread releases its own capture and ends
    assert cam.released.wait(10) and cam.violations == []


def test_band_high_error_is_one_line_and_exits(flight, tmp_path, capsys):
    code = main(["replay", str(flight / "video.mp4"), "--out", str(tmp_path / "o"), "-q",
                 "--set", "registration.band_high=0.9"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "band_high" in err[0] and "error:" in err[0]


# --------------------------------------------------------------------------- stills


def _stills(flight: Path, folder: Path, n: int = 12) -> list[Path]:
    """Frames 0..n-1 of the flight as 001.png, 002.png, ... (000 is left for a bad first still)."""
    folder.mkdir()
    paths = []
    for i in range(n):
        paths.append(folder / f"{i + 1:03d}.png")
        shutil.copy(flight / "frames" / f"{i:06d}.png", paths[-1])
    return paths


def test_stills_too_small_to_register_are_skipped_and_counted(tmp_path, caplog):
    cv2.imwrite(str(tmp_path / "a.png"), np.full((1, 1, 3), 200, np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.full((40, 15, 3), 200, np.uint8))   # 15 px wide
    for name in ("c.png", "d.png"):
        cv2.imwrite(str(tmp_path / name), np.full((16, 16, 3), 100, np.uint8))  # the least usable
    (tmp_path / "e.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")            # undecodable
    with caplog.at_level(logging.WARNING, logger="photomap.drivers.images"):
        src = ImageFolderSource(tmp_path)
        frames = list(src)
    assert [(f.index, f.source) for f in frames] == [(2, "c.png"), (3, "d.png")]
    assert (src.stats.read, src.stats.corrupt) == (2, 3)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3 and all("\n" not in m for m in lines)
    assert "a.png" in lines[0] and "1x1" in lines[0] and "too small" in lines[0]
    assert "b.png" in lines[1] and "15x40" in lines[1]
    assert "e.png" in lines[2] and "not a readable image" in lines[2]


def test_a_tiny_first_still_does_not_set_the_frame_size(flight, tmp_path):
    """The bug: a 1x1 first image set the frame size and every other still was 'corrupt'."""
    folder = tmp_path / "stills"
    paths = _stills(flight, folder)
    cv2.imwrite(str(folder / "000.png"), np.zeros((1, 1, 3), np.uint8))
    summary = MappingPipeline(ImageFolderSource(folder), load_config(), tmp_path / "out").run()
    assert summary["frame_size"] == [320, 240]
    assert summary["frames_in"] == len(paths) and summary["corrupt"] == 1
    assert summary["registered"] == len(paths)
    rows = read_trajectory_csv(tmp_path / "out" / "trajectory.csv")
    assert [r.frame for r in rows] == list(range(len(paths) + 1))
    assert rows[0].M is None and all(r.glued for r in rows[1:])
    assert cv2.imread(str(tmp_path / "out" / "mosaic.png"), cv2.IMREAD_UNCHANGED) is not None


def test_unreadable_folder_is_one_line(flight, tmp_path, monkeypatch, capsys):
    folder = tmp_path / "locked"
    _stills(flight, folder, 2)
    real_iterdir = Path.iterdir

    def denied(self):
        if self == folder:
            raise PermissionError(13, "Permission denied", str(self))
        return real_iterdir(self)

    monkeypatch.setattr(Path, "iterdir", denied)
    with pytest.raises(InputError, match="cannot read image folder .*Permission denied"):
        ImageFolderSource(folder)
    assert main(["replay", str(folder), "--out", str(tmp_path / "o"), "-q"]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Permission denied" in err[0] and str(folder) in err[0]


@pytest.mark.skipif(not hasattr(__import__("os"), "geteuid") or __import__("os").geteuid() == 0,
                    reason="root reads any folder: the permission cannot be denied")
def test_folder_without_read_permission_is_one_line(flight, tmp_path, capsys):
    folder = tmp_path / "locked"
    _stills(flight, folder, 2)
    folder.chmod(0o300)  # no read: cannot be listed
    try:
        assert main(["replay", str(folder), "--out", str(tmp_path / "o"), "-q"]) == 3
    finally:
        folder.chmod(0o700)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot read image folder" in err[0]
