"""The mapping pipeline on simulated flights with exact ground truth."""

from __future__ import annotations

import json
import threading
import time

import cv2
import numpy as np
import pytest

from photomap.drivers.frames import CaptureStats, Frame
from photomap.config import load_config
from photomap.sim.flight import simulate_sequence
from photomap.mapping.pipeline import MappingPipeline
from photomap.sim.terrain import load_terrain, procedural_terrain, valid_mask
from photomap.core.records import GroundTruth
from photomap.geometry import frame_centre
from photomap.eval.metrics import evaluate_trajectory
from photomap.io.trajectory_files import read_trajectory_csv
from tests.waiting import wait_until

SIZE = (240, 320)  # (h, w)


class ListSource:
    """A replay source over frames held in memory."""

    live = False

    def __init__(self, frames, fps=30.0, gate: threading.Event | None = None, gate_at: int = -1):
        self.frames, self.fps, self.stats = frames, fps, CaptureStats()
        self.gate, self.gate_at = gate, gate_at
        self._closed = threading.Event()

    def __iter__(self):
        for i, image in enumerate(self.frames):
            if self._closed.is_set():
                return
            if i == self.gate_at and self.gate is not None:
                self.gate.wait(5.0)
            self.stats.read += 1
            yield Frame(i, i / self.fps, image, "memory")

    def close(self):
        self._closed.set()


@pytest.fixture(scope="module")
def aukerman():
    terrain = load_terrain("aukerman", zoom=3)
    return terrain, valid_mask(terrain)


def fly(terrain, valid, n, seed, **motion):
    params = dict(gsd=0.1 / 3, altitude=(25.0, 35.0), speed=4.0)
    params.update(motion)
    return simulate_sequence(terrain, n, SIZE, seed=seed, valid=valid, **params)


def evaluate(out_dir, seq):
    rows = read_trajectory_csv(out_dir / "trajectory.csv")
    truth = GroundTruth(frame=np.arange(len(seq.frames)), t=np.asarray(seq.truth.t),
                        H=np.asarray(seq.truth.H), columns=[])
    return evaluate_trajectory(rows, truth, frame_centre(SIZE[1], SIZE[0]))["headline"]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_textured_flight_drifts_less_than_half_a_percent(aukerman, tmp_path, seed):
    seq = fly(*aukerman, 120, seed)
    summary = MappingPipeline(ListSource(seq.frames), load_config(), tmp_path).run()
    assert summary["frames_in"] == 120 and summary["registered"] == 120
    assert summary["segments"] == 1
    head = evaluate(tmp_path, seq)
    assert head["frames_posed"] == 120
    assert head["position_px"]["drift_pct"] < 0.5
    assert head["pairs"]["success_rate"] > 0.95
    for name in ("mosaic.png", "trajectory.csv", "trajectory.tum", "run.json"):
        assert (tmp_path / name).is_file(), name
    run = json.loads((tmp_path / "run.json").read_text())
    assert run["complete"] and run["registered"] == 120


def test_low_texture_flight_frame_to_frame(tmp_path):
    terrain = procedural_terrain("grass", (1536, 1536), seed=4)
    seq = simulate_sequence(terrain, 80, SIZE, seed=4, gsd=0.05, altitude=(18.0, 22.0), speed=3.0, noise=2.0)
    cfg = load_config(overrides=["mapping.keyframes=false"])
    summary = MappingPipeline(ListSource(seq.frames), cfg, tmp_path).run()
    assert summary["registered"] >= 78
    assert evaluate(tmp_path, seq)["position_px"]["drift_pct"] < 2.0


def test_mosaic_matches_the_terrain(aukerman, tmp_path):
    """The map, taken back to terrain pixels through the first frame's true pose, is the terrain."""
    terrain, valid = aukerman
    seq = fly(terrain, valid, 40, 5)
    summary = MappingPipeline(ListSource(seq.frames), load_config(), tmp_path).run()
    info = summary["mosaics"][0]
    mosaic = cv2.imread(str(tmp_path / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    assert info["scale"] == 1.0 and mosaic.shape[2] == 4
    x0, y0 = info["origin_xy"]
    # map pixel (u + x0, v + y0) = frame-0 pixel; terrain pixel = H0 @ that
    h0 = np.asarray(seq.truth.H[0])
    shift = np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1.0]])
    expected = cv2.warpPerspective(terrain, h0 @ shift, (mosaic.shape[1], mosaic.shape[0]),
                                   flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    covered = cv2.erode((mosaic[:, :, 3] == 255).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert covered.sum() > 0.3 * covered.size
    diff = np.abs(mosaic[:, :, :3].astype(float) - expected.astype(float))[covered]
    assert np.median(diff) < 6.0


def test_bad_frames_are_skipped_and_the_map_survives(aukerman, tmp_path):
    seq = fly(*aukerman, 40, 6)
    frames = list(seq.frames)
    frames[10] = np.zeros((100, 100, 3), np.uint8)  # wrong size: corrupt
    for k in range(20, 33):  # the camera sees nothing for 13 frames: link lost
        frames[k] = np.full_like(frames[k], 128)
    cfg = load_config(overrides=["mapping.max_lost_frames=5"])
    summary = MappingPipeline(ListSource(frames), cfg, tmp_path).run()
    assert summary["corrupt"] == 1
    assert summary["segments"] >= 2
    assert any("segment 1" in e for e in summary["events"])
    rows = read_trajectory_csv(tmp_path / "trajectory.csv")
    assert [r.status for r in rows][10] == "corrupt"
    assert all(r.status != "registered" for r in rows[20:26])
    assert rows[0].segment == 0 and rows[-1].segment >= 1
    assert (tmp_path / "mosaic.png").is_file()


def test_stop_writes_the_map_built_so_far(aukerman, tmp_path):
    seq = fly(*aukerman, 60, 7)
    gate = threading.Event()
    source = ListSource(seq.frames, gate=gate, gate_at=30)
    pipeline = MappingPipeline(source, load_config(), tmp_path)
    result = {}
    thread = threading.Thread(target=lambda: result.update(pipeline.run()))
    thread.start()
    while pipeline.stats.frames_in < 25 and thread.is_alive():
        thread.join(0.01)
    pipeline.stop()
    gate.set()
    thread.join(10)
    assert not thread.is_alive()
    assert 25 <= result["frames_in"] < 60
    assert result["complete"]
    assert (tmp_path / "mosaic.png").is_file()
    rows = read_trajectory_csv(tmp_path / "trajectory.csv")
    assert len(rows) == result["frames_in"]


def test_checkpoints_during_the_run(aukerman, tmp_path):
    """A crash mid-flight loses at most one checkpoint interval: the files exist while it runs."""
    seq = fly(*aukerman, 40, 8)
    seen = {}
    names = ("run.json", "trajectory.csv", "preview.png")

    def on_frame(event):
        # the files come from a low-priority writer thread, a checkpoint or two behind (one while
        # the last is still being written is skipped): from frame 10 on, each frame gives it time
        if "run" in seen or event.index < 10:
            return
        run = wait_until(lambda: all((tmp_path / name).is_file() for name in names)
                         and (r := json.loads((tmp_path / "run.json").read_text()))["frames_in"] >= 10 and r, 2.0, 0.01)
        if run:
            seen["run"], seen["index"] = run, event.index
            seen["rows"] = len(read_trajectory_csv(tmp_path / "trajectory.csv"))
            seen["preview"] = cv2.imread(str(tmp_path / "preview.png"), cv2.IMREAD_UNCHANGED)

    cfg = load_config(overrides=["output.checkpoint_interval=0.000001"])
    MappingPipeline(ListSource(seq.frames), cfg, tmp_path, sinks=[on_frame]).run()
    assert "run" in seen, "no checkpoint of 10 frames or more while the flight ran"
    assert seen["run"]["complete"] is False and 10 <= seen["run"]["frames_in"] <= seen["index"] + 1 < 40
    assert seen["rows"] >= seen["run"]["frames_in"]
    assert seen["preview"] is not None and seen["preview"].shape[2] == 4
    assert json.loads((tmp_path / "run.json").read_text())["complete"] is True
    assert not (tmp_path / "preview.png").exists()


def test_checkpoint_files_take_a_bounded_share_of_the_writers_time(aukerman, tmp_path, monkeypatch):
    """A long flight's rows take seconds to write: after a trajectory write that cost 1000 s of
    the writer's CPU (a clock that the test moves) the next checkpoint's files wait 9000 s
    (``_WRITER_SHARE`` 0.1): one checkpoint write in the whole run, whatever the interval."""
    import types

    from photomap.mapping import run_outputs

    seq = fly(*aukerman, 40, 9)
    real = run_outputs.write_trajectory_csv
    cpu = [0.0]
    clock = types.SimpleNamespace(**{name: getattr(time, name) for name in dir(time) if not name.startswith("_")})
    clock.thread_time = lambda: cpu[0]
    checkpoint_writes = []

    def costly(path, rows, frame_size=None):
        rows = list(rows)
        if len(rows) < len(seq.frames):  # a checkpoint's
            checkpoint_writes.append(len(rows))
            cpu[0] += 1000.0
        real(path, rows, frame_size)

    monkeypatch.setattr(run_outputs, "time", clock)
    monkeypatch.setattr(run_outputs, "write_trajectory_csv", costly)
    cfg = load_config(overrides=["output.checkpoint_interval=0.000001"])
    MappingPipeline(ListSource(seq.frames), cfg, tmp_path).run()
    assert len(checkpoint_writes) == 1
    assert len(read_trajectory_csv(tmp_path / "trajectory.csv")) == len(seq.frames)


def test_a_slow_checkpoint_trajectory_never_lands_after_the_final_one(aukerman, tmp_path, monkeypatch):
    """Checkpoint copies of trajectory.csv are written by a background thread from a copy of the
    rows; the final file (written by finish) always has every frame, however slow that thread."""
    import time as _time

    from photomap.mapping import run_outputs

    seq = fly(*aukerman, 30, 9)
    real = run_outputs.write_trajectory_csv
    slow_calls = []

    def slow(path, rows, frame_size=None):
        rows = list(rows)
        if len(rows) < len(seq.frames):  # a checkpoint's copy: make it land late
            slow_calls.append(len(rows))
            _time.sleep(0.3)
        real(path, rows, frame_size)

    monkeypatch.setattr(run_outputs, "write_trajectory_csv", slow)
    cfg = load_config(overrides=["output.checkpoint_interval=0.000001"])
    MappingPipeline(ListSource(seq.frames), cfg, tmp_path).run()
    import threading

    for thread in threading.enumerate():  # a late copy would land now
        if thread.name.startswith("photomap-writer"):
            thread.join(5.0)
    assert slow_calls  # checkpoints wrote (some) copies in the background
    assert len(read_trajectory_csv(tmp_path / "trajectory.csv")) == len(seq.frames)
