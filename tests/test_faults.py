"""Fault injection: what a run leaves behind when it is killed, interrupted, out of disk space, given
a read-only or wrong output folder, corrupt or shuffled or black video, garbage or silent MAVLink,
or bad config values. Every test asserts on the files left behind (read back with the real
readers), not only on exit codes. ``tools/faults.py`` runs the longer version.
"""

from __future__ import annotations

import errno
import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from photomap.cli import main as cli
from photomap.config import load_config
from photomap.core.mosaic import TiledMosaic
from photomap.config import MosaicConfig
from photomap.drivers.frames import CaptureStats, Frame
from photomap.io import statestore
from photomap.io.pngstream import PngStreamWriter
from photomap.io.statestore import MapState, load_manifest, restore_mosaic
from photomap.io.trajectory_files import read_groundtruth, read_trajectory_csv
from photomap.mapping.checkpoint import recover_run
from photomap.mapping.pipeline import MappingPipeline
from tests.waiting import wait_until

LONG = os.environ.get("PHOTOMAP_FAULTS") == "long"  # tools/faults.py: more kills, both codecs, longer videos

SIM = ["--frames", "80", "--size", "320x240", "--pattern", "figure8", "--fps", "10", "--altitude", "25:35",
       "--speed", "6", "--yaw-mode", "heading", "--gsd", "0.1", "--set", "simulate.terrain_zoom=3", "-q"]


def _python_env() -> dict:
    env = dict(os.environ)
    env.pop("PYTHONWARNINGS", None)
    return env


def photomap(*args: str, timeout: float = 120, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "photomap", *args], capture_output=True, text=True,
                          timeout=timeout, env=_python_env(), **kw)


def in_process(capsys, *args: str) -> tuple[int, str, str]:
    """``photomap ARGS`` in this process: (exit code, stdout, stderr)."""
    capsys.readouterr()
    code = cli.main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    """A 100-frame 320x240 simulated flight (MJPG video, tlog, ground truth)."""
    out = tmp_path_factory.mktemp("faults") / "flight"
    assert cli.main(["simulate", "--out", str(out), "--codec", "mjpg", *SIM]) == 0
    return out


@pytest.fixture(scope="module")
def reference(flight, tmp_path_factory) -> Path:
    """The complete run of the flight (what a recovered map is compared with)."""
    out = tmp_path_factory.mktemp("faults") / "reference"
    assert cli.main(["replay", str(flight / "video.avi"), "--out", str(out), "--no-progress", "-q"]) == 0
    return out


def map_in_frame(run: Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """(grey image, alpha, origin_xy) of a run's mosaic.png at full scale."""
    summary = json.loads((run / "run.json").read_text())
    info = summary["mosaics"][0]
    assert info["scale"] == 1.0
    bgra = cv2.imread(str(run / info["file"]), cv2.IMREAD_UNCHANGED)
    assert bgra is not None and bgra.shape[2] == 4
    return cv2.cvtColor(bgra[..., :3], cv2.COLOR_BGR2GRAY).astype(float), bgra[..., 3], tuple(info["origin_xy"])


def overlap_ncc(a_run: Path, b_run: Path) -> tuple[float, int]:
    """Normalised cross-correlation of two runs' maps where both are covered (same map frame)."""
    (ga, aa, (ax, ay)), (gb, ab, (bx, by)) = map_in_frame(a_run), map_in_frame(b_run)
    x0, y0 = max(ax, bx), max(ay, by)
    x1, y1 = min(ax + ga.shape[1], bx + gb.shape[1]), min(ay + ga.shape[0], by + gb.shape[0])
    if x1 <= x0 or y1 <= y0:
        return 0.0, 0
    sa = (slice(y0 - ay, y1 - ay), slice(x0 - ax, x1 - ax))
    sb = (slice(y0 - by, y1 - by), slice(x0 - bx, x1 - bx))
    both = (aa[sa] == 255) & (ab[sb] == 255)
    va, vb = ga[sa][both], gb[sb][both]
    va, vb = va - va.mean(), vb - vb.mean()
    return float((va * vb).sum() / np.sqrt((va ** 2).sum() * (vb ** 2).sum())), int(both.sum())


def status_counts_agree(run: Path) -> dict:
    """trajectory.csv (read back) and run.json count every status alike; returns the counts."""
    rows = read_trajectory_csv(run / "trajectory.csv")
    summary = json.loads((run / "run.json").read_text())
    counts = {s: sum(r.status == s for r in rows) for s in ("reference", "registered", "low_confidence",
                                                             "dropped", "corrupt")}
    assert summary["registered"] == counts["reference"] + counts["registered"]
    assert summary["low_confidence"] == counts["low_confidence"]
    assert summary["corrupt"] == counts["corrupt"]
    assert summary["dropped"] == counts["dropped"]
    assert [r.frame for r in rows] == list(range(len(rows)))
    return counts


# ------------------------------------------------------------------------------------ kill
def test_checkpoint_survives_a_kill_at_every_write(tmp_path, monkeypatch):
    """A kill at any moment of a checkpoint (simulated: the k-th file operation of the write
    raises) leaves the previous manifest and every file it names; the next checkpoint succeeds."""
    params = MosaicConfig(tile_size=64)
    rng = np.random.default_rng(0)
    mosaic = TiledMosaic(params)
    mosaic.add(rng.integers(0, 255, (100, 150, 3), dtype=np.uint8), np.array([[1.0, 0, 3], [0, 1, 5]]))
    state = MapState(tmp_path / "state")
    state.write(state.snapshot({0: mosaic}, {"order": [0]}))
    truth = {k: mosaic.tile_image(k) for k in mosaic.tiles()}
    mosaic.add(rng.integers(0, 255, (100, 150, 3), dtype=np.uint8), np.array([[1.0, 0, 90], [0, 1, 40]]))
    real = {name: getattr(statestore, name) for name in ("_write_file", "_fsync_file")}
    kills = 0
    for k in range(1, 100):
        calls = {"n": 0}

        def dying(name, k=k):
            def op(*args):
                calls["n"] += 1
                if calls["n"] == k:
                    raise OSError(errno.EIO, "Input/output error (killed here)")
                return real[name](*args)
            return op

        for name in real:
            monkeypatch.setattr(statestore, name, dying(name))
        snap = state.snapshot({0: mosaic}, {"order": [0]})
        try:
            state.write(snap)
        except statestore.CheckpointError:
            kills += 1
            manifest = load_manifest(tmp_path / "state")
            assert manifest["generation"] == 1
            restored, report = restore_mosaic(tmp_path / "state", manifest, 0)
            assert not report.unreadable and report.restored == len(truth)
            for key, (image, alpha) in truth.items():
                got = restored.tile_image(key)
                assert np.array_equal(got[0], image) and np.array_equal(got[1], alpha)
            continue
        break
    assert kills >= 3  # the tiles and the manifest each had their turn
    monkeypatch.undo()
    manifest = load_manifest(tmp_path / "state")
    assert manifest["generation"] == 2
    restored, report = restore_mosaic(tmp_path / "state", manifest, 0)
    for key in mosaic.tiles():
        assert np.array_equal(restored.tile_image(key)[0], mosaic.tile_image(key)[0])
    names = {p.name for p in (tmp_path / "state" / "seg0").iterdir()}
    assert names == {f"{tx}_{ty}_g{g}.png" for tx, ty, g in manifest["tiles"]["0"]}  # nothing left over


@pytest.mark.parametrize("seed", range(1, 11) if LONG else [1, 2])
def test_sigkill_leaves_a_map_that_recover_rebuilds(flight, reference, tmp_path, seed):
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "photomap", "replay", str(flight / "video.avi"), "--out", str(out),
                             "--no-progress", "-q", "--realtime", "--set", "output.checkpoint_interval=0.05"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=_python_env())
    manifest = out / "checkpoint" / "manifest.json"  # --realtime: 8 s of video, the kill lands mid-run
    deadline = time.monotonic() + 60
    while not manifest.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(random.Random(seed).uniform(0.0, 1.0))
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    proc.stderr.close()
    if not manifest.exists():
        pytest.skip("the run ended before its first checkpoint (machine too fast)")
    assert not (out / "mosaic.png").exists()
    result = photomap("recover", str(out))
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "run.json").read_text())
    assert summary["complete"] is False and summary["recovered"]["problems"] == []
    rows = read_trajectory_csv(out / "trajectory.csv")
    assert len(rows) >= 1
    ncc, n = overlap_ncc(out, reference)
    assert n > 20000 and ncc > 0.8, (ncc, n)
    # the trajectory of the last checkpoint evaluates like any other
    ev = photomap("evaluate", str(out), "--truth", str(flight / "groundtruth.csv"), "--out", str(tmp_path / "eval"))
    assert ev.returncode == 0, ev.stderr


# ------------------------------------------------------------------------------------ interrupt
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_interrupt_writes_the_map_and_removes_the_checkpoint(flight, tmp_path, sig):
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "photomap", "replay", str(flight / "video.avi"), "--out", str(out),
                             "--no-progress", "-q", "--realtime", "--set", "output.checkpoint_interval=0.2"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_python_env())
    deadline = time.monotonic() + 60
    while not (out / "checkpoint" / "manifest.json").exists() and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, stderr
    summary = json.loads((out / "run.json").read_text())
    assert summary["complete"] is True and 0 < summary["frames_in"] < 80
    assert not (out / "checkpoint").exists() and not (out / "preview.png").exists()
    assert cv2.imread(str(out / "mosaic.png"), cv2.IMREAD_UNCHANGED).shape[2] == 4
    assert len(read_trajectory_csv(out / "trajectory.csv")) == summary["frames_in"]
    assert "Traceback" not in stderr


# ------------------------------------------------------------------------------------ disk full
def _enospc_after(monkeypatch, budget: int) -> dict:
    """Every atomic write (and cv2.imwrite) raises ENOSPC once ``budget`` bytes were written."""
    from photomap.io import trajectory_files
    from photomap.mapping import outputs

    used = {"bytes": 0, "refused": 0}
    real = trajectory_files.atomic_write_bytes

    def writer(path, data, **kwargs):
        if used["bytes"] + len(data) > budget:
            used["refused"] += 1
            raise OSError(errno.ENOSPC, "No space left on device")
        used["bytes"] += len(data)
        return real(path, data, **kwargs)

    real_imwrite = cv2.imwrite

    def imwrite(path, image, *args):
        if used["bytes"] > budget:
            return False
        return real_imwrite(path, image, *args)

    class BudgetPng(PngStreamWriter):  # the map PNG is streamed band by band, not one atomic write
        def write(self, band):
            size = np.asarray(band).nbytes // 4  # about what a band compresses to
            if used["bytes"] + size > budget:
                used["refused"] += 1
                raise OSError(errno.ENOSPC, "No space left on device")
            used["bytes"] += size
            super().write(band)

    for module in (trajectory_files, outputs):
        monkeypatch.setattr(module, "atomic_write_bytes", writer)
    monkeypatch.setattr(outputs, "PngStreamWriter", BudgetPng)
    monkeypatch.setattr(statestore, "_write_file", writer)
    monkeypatch.setattr(cv2, "imwrite", imwrite)
    return used


class ListSource:
    live = False

    def __init__(self, frames, fps=10.0):
        self.frames, self.fps, self.stats, self._closed = frames, fps, CaptureStats(), False

    def __iter__(self):
        for i, image in enumerate(self.frames):
            if self._closed:
                return
            self.stats.read += 1
            yield Frame(i, i / self.fps, image, "memory")

    def close(self):
        self._closed = True


def _frames(video: Path, n: int | None = None) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(video))
    frames = []
    while n is None or len(frames) < n:
        ok, image = cap.read()
        if not ok:
            break
        frames.append(image)
    cap.release()
    return frames


def test_disk_full_keeps_the_map_in_the_checkpoint(flight, tmp_path, monkeypatch):
    """ENOSPC partway: mapping goes on to the end, each failing output is reported once, the
    checkpoint keeps the map and recover rebuilds it once there is room again."""
    frames = _frames(flight / "video.avi")
    used = _enospc_after(monkeypatch, 1_500_000)
    filled = {}

    def on_frame(event):
        # checkpoints come from a low-priority writer that skips one while the last is still being
        # written: from frame 30 on, each frame gives it time until the disk is full
        if "at" not in filled and event.index >= 30 and wait_until(lambda: used["refused"], 2.0, 0.01):
            filled["at"] = event.index

    cfg = load_config(overrides=["output.checkpoint_interval=0.000001"])
    pipe = MappingPipeline(ListSource(frames), cfg, tmp_path / "run", sinks=[on_frame])
    summary = pipe.run()  # never raises
    assert filled.get("at", len(frames)) < len(frames) - 1, "the disk did not fill while the flight ran"
    assert summary["frames_in"] == len(frames)
    assert "mosaic.png" in summary["write_errors"] and summary["map_kept_in"] == "checkpoint"
    assert not (tmp_path / "run" / "mosaic.png").exists()
    assert summary["registered"] > 0.9 * len(frames)  # mapping went on
    monkeypatch.undo()  # room again
    recovered = recover_run(tmp_path / "run")
    assert recovered["mosaics"][0]["file"] == "mosaic.png"
    image = cv2.imread(str(tmp_path / "run" / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    assert (image[..., 3] == 255).sum() > 20000
    counts = status_counts_agree(tmp_path / "run")  # recover took the counts of the trajectory that survived
    assert counts["reference"] + counts["registered"] > 0


def _mount_tmpfs(path: Path, options: str) -> bool:
    path.mkdir(parents=True, exist_ok=True)
    if shutil.which("mount") is None or os.geteuid() != 0:
        return False
    return subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)],
                          capture_output=True).returncode == 0


def _umount(path: Path) -> None:
    subprocess.run(["umount", "-l", str(path)], capture_output=True)


def test_disk_full_on_a_small_tmpfs(flight, tmp_path):
    small = tmp_path / "small"
    if not _mount_tmpfs(small, "size=400k"):  # less than the map PNG (~0.5 MB): the disk fills for sure
        pytest.skip("cannot mount a tmpfs here (not root, or no mount permission)")
    try:
        result = photomap("replay", str(flight / "video.avi"), "--out", str(small / "run"), "--no-progress", "-q",
                          "--set", "output.min_free_mb=0.2", "--set", "output.checkpoint_interval=0.05")
        assert result.returncode == 4, result.stderr
        assert "Traceback" not in result.stderr and "No space left on device" in result.stderr
        copy = tmp_path / "copy"
        shutil.copytree(small / "run", copy)
    finally:
        _umount(small)
    if not (copy / "mosaic.png").exists():  # the map did not fit: the checkpoint holds it
        assert "photomap recover" in result.stdout + result.stderr
        recovered = photomap("recover", str(copy))
        assert recovered.returncode == 0, recovered.stdout + recovered.stderr
    else:  # the map fitted, other outputs did not: each named once
        assert "not written:" in result.stdout
    assert cv2.imread(str(copy / "mosaic.png"), cv2.IMREAD_UNCHANGED)[..., 3].any()
    for line in result.stderr.splitlines():  # one line per failing output, not one per attempt
        assert sum(other == line[9:] for other in (x[9:] for x in result.stderr.splitlines())) == 1, result.stderr


# ------------------------------------------------------------------------------------ output folder
def test_out_is_a_file(flight, tmp_path, capsys):
    target = tmp_path / "file.txt"
    target.write_text("not a folder")
    code, out, err = in_process(capsys, "replay", str(flight / "video.avi"), "--out", str(target), "--no-progress", "-q")
    assert code == 4
    assert err.strip().splitlines() == [f"photomap replay: error: output folder {target} is a file, not a folder: "
                                        "choose another --out"]
    assert target.read_text() == "not a folder"


def test_read_only_out_is_refused_before_any_frame(flight, tmp_path, capsys):
    ro = tmp_path / "ro"
    mounted = _mount_tmpfs(ro, "ro,size=1m")
    if not mounted:
        if os.geteuid() == 0:
            pytest.skip("root ignores permission bits and cannot mount a read-only tmpfs here")
        ro.mkdir(exist_ok=True)
        ro.chmod(0o500)
    try:
        code, out, err = in_process(capsys, "replay", str(flight / "video.avi"), "--out", str(ro), "--no-progress", "-q")
        assert code == 4
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "not writable" in lines[0], err
        assert "frames:" not in out  # refused before mapping
        assert list(ro.iterdir()) == []
    finally:
        if mounted:
            _umount(ro)
        else:
            ro.chmod(0o700)


def test_unrecovered_checkpoint_is_not_overwritten(flight, tmp_path, capsys):
    out = tmp_path / "run"
    (out / "checkpoint").mkdir(parents=True)
    (out / "checkpoint" / "manifest.json").write_text("{}")
    code, _, err = in_process(capsys, "replay", str(flight / "video.avi"), "--out", str(out), "--no-progress", "-q")
    assert code == 4 and "photomap recover" in err
    assert (out / "checkpoint" / "manifest.json").read_text() == "{}"


# ------------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize("codec,name", [("mjpg", "video.avi")] + ([("mp4v", "video.mp4")] if LONG else []))
def test_corrupt_video(tmp_path, codec, name):
    sim = tmp_path / "sim"
    assert cli.main(["simulate", "--out", str(sim), "--codec", codec, *SIM]) == 0
    data = bytearray((sim / name).read_bytes())
    rng = np.random.default_rng(5)
    for start in (len(data) // 3, len(data) // 2):  # two stretches of flipped bytes in the middle
        idx = start + rng.integers(0, 20000, 400)
        data_arr = np.frombuffer(bytes(data), np.uint8).copy()
        data_arr[idx] ^= 0xFF
        data = bytearray(data_arr.tobytes())
    (sim / name).write_bytes(bytes(data))
    out = tmp_path / "run"
    result = photomap("replay", str(sim / name), "--out", str(out), "--no-progress", "-q")
    assert result.returncode in (0, 1) and "Traceback" not in result.stderr, result.stderr
    counts = status_counts_agree(out)
    assert counts["reference"] + counts["registered"] > 30
    ev = photomap("evaluate", str(out), "--truth", str(sim / "groundtruth.csv"), "--out", str(tmp_path / "eval"))
    assert ev.returncode == 0, ev.stderr


def test_shuffled_frames_are_not_glued(flight, tmp_path):
    """Frames in a random order: whatever the tracker glues must agree with the truth (a frame glued
    to a reference it does not overlap would put it in a wrong place); the rest start segments or
    are low_confidence."""
    frames = _frames(flight / "video.avi")
    truth = read_groundtruth(flight / "groundtruth.csv")
    order = np.random.default_rng(3).permutation(len(frames))
    if LONG:
        order = np.concatenate([order, np.random.default_rng(4).permutation(len(frames))])
    pipe = MappingPipeline(ListSource([frames[i] for i in order]), load_config(), tmp_path / "run")
    summary = pipe.run()
    rows = read_trajectory_csv(tmp_path / "run" / "trajectory.csv")
    w, h = 320, 240
    centre = np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
    by_segment: dict[int, list] = {}
    for r in rows:
        if r.glued:
            by_segment.setdefault(r.segment, []).append(r)
    for seg, seg_rows in by_segment.items():
        first = seg_rows[0]
        H0 = truth.H[order[first.frame]]
        M0 = np.vstack([first.M, [0, 0, 1]])
        for r in seg_rows[1:]:
            # truth: this frame's centre in the first frame's pixels; estimate: the same from the map
            p_true = np.linalg.solve(H0, truth.H[order[r.frame]] @ centre)
            p_true = p_true[:2] / p_true[2]
            p_est = np.linalg.solve(M0, np.vstack([r.M, [0, 0, 1]]) @ centre)[:2]
            assert np.hypot(*(p_est - p_true)) < 0.1 * w, (seg, r.frame, p_est, p_true)


class BlackSource(ListSource):
    def __init__(self, n):
        super().__init__([np.zeros((240, 320, 3), np.uint8)] * n)


def test_black_video_keeps_memory_bounded(tmp_path):
    """Nothing registers on black frames: the one-frame segments the tracker keeps starting are
    dropped (their frames counted low_confidence), so maps do not pile up."""
    seen = []
    pipe = MappingPipeline(BlackSource(2000 if LONG else 200), load_config(overrides=["output.checkpoint_interval=0.01"]), tmp_path)
    pipe.sinks = (lambda event: seen.append(len(pipe.mosaics)),)
    summary = pipe.run()
    assert summary["segments_started"] > summary["frames_in"] / 15  # one every max_lost_frames + 1 frames
    assert summary["segments_dropped"] >= summary["segments_started"] - 1 and summary["segments"] <= 1
    assert max(seen) <= 2
    counts = status_counts_agree(tmp_path)
    assert counts["low_confidence"] >= summary["frames_in"] - 5 and summary["complete"]


# ------------------------------------------------------------------------------------ telemetry
def test_garbage_mavlink_log(flight, tmp_path):
    """Random bytes spliced into the .tlog: the parser skips them, the run ends with a map."""
    data = (flight / "telemetry.tlog").read_bytes()
    rng = np.random.default_rng(9)
    chunks, pos = [], 0
    while pos < len(data):
        step = int(rng.integers(50, 400))
        chunks += [data[pos:pos + step], rng.integers(0, 256, int(rng.integers(1, 32)), dtype=np.uint8).tobytes()]
        pos += step
    bad = tmp_path / "garbage.tlog"
    bad.write_bytes(b"".join(chunks))
    out = tmp_path / "run"
    result = photomap("replay", str(flight / "video.avi"), "--out", str(out), "--no-progress", "-q",
                      "--mavlink", str(bad))
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr
    summary = json.loads((out / "run.json").read_text())
    assert summary["complete"] and summary["registered"] > 70
    assert summary["telemetry"]["link"]["parse_errors"] > 0  # the garbage was seen, and skipped
    assert (out / "mosaic.png").is_file()
    status_counts_agree(out)


def test_silent_link(flight, tmp_path):
    """A live link that never says anything: vision alone, and run.json says why."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "run"
    result = photomap("replay", str(flight / "video.avi"), "--out", str(out), "--no-progress", "-q", "--realtime",
                      "--mavlink", f"udpin:127.0.0.1:{port}", "--set", "mapping.loop_closure=false", timeout=120)
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr
    summary = json.loads((out / "run.json").read_text())
    assert summary["registered"] > 70 and summary["georeference"] is None
    assert summary["telemetry"]["status"] != "ok"
    assert (out / "mosaic.png").is_file()


# ------------------------------------------------------------------------------------ config
@pytest.mark.parametrize("override", ["mapping.min_confidence=abc", "output.checkpoint_interval=-1",
                                      "mosaic.tile_size=0", "nosuch.key=1", "output.min_free_mb=-5"])
def test_bad_config_values_are_one_line(flight, tmp_path, override, capsys):
    out = tmp_path / "run"
    code, _, err = in_process(capsys, "replay", str(flight / "video.avi"), "--out", str(out), "--no-progress", "-q",
                              "--set", override)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("photomap replay: error:"), err
    assert not out.exists()


def test_bad_config_file_is_one_line(flight, tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("mapping:\n  min_confidence: [1, 2\n")  # not even YAML
    code, _, err = in_process(capsys, "replay", str(flight / "video.avi"), "--out", str(tmp_path / "run"),
                              "--config", str(bad))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err


class GappyLiveSource(ListSource):
    """A live source that drops frames (gaps in the indices), also after the last frame it gives."""

    live = True

    def __iter__(self):
        for i, image in enumerate(self.frames):
            if i % 7 == 3 or i >= len(self.frames) - 2:
                self.stats.dropped += 1  # never handed over
                continue
            self.stats.read += 1
            yield Frame(i, i / self.fps, image, "camera")


def test_dropped_frames_counted_alike(flight, tmp_path):
    frames = _frames(flight / "video.avi", 30)
    source = GappyLiveSource(frames)
    summary = MappingPipeline(source, load_config(), tmp_path).run()
    counts = status_counts_agree(tmp_path)
    assert counts["dropped"] == source.stats.dropped == summary["dropped"] == 4 + 2
    assert len(read_trajectory_csv(tmp_path / "trajectory.csv")) == len(frames)
