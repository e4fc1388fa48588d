"""What an operator reads: no progress bar in redirected logs, a periodic status line, JSON log lines."""

from __future__ import annotations

import io
import json
import logging
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from photomap.cli.oplog import JsonFormatter, StatusReporter
from photomap.cli.wiring import progress_sink
from photomap.mapping.events import FrameEvent
from photomap.sim.simulate import simulate_flight
from photomap.telemetry.samples import TelemetrySample

N_FRAMES = 30


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    out = tmp_path_factory.mktemp("flight")
    simulate_flight(out, n_frames=N_FRAMES, size=(320, 240), fps=15.0, seed=3)
    return out


def _photomap(args: list[str], stderr_path, env_drop: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    """``photomap ARGS`` in a subprocess whose stderr is a file (not a terminal)."""
    env = {k: v for k, v in os.environ.items() if k not in env_drop}
    with open(stderr_path, "w") as err:
        return subprocess.run([sys.executable, "-m", "photomap", *args], stdout=subprocess.PIPE, stderr=err,
                              text=True, env=env, timeout=300)


# --------------------------------------------------------------------------- progress bar
def test_no_progress_bar_when_stderr_is_a_file(flight, tmp_path):
    err = tmp_path / "stderr.txt"
    result = _photomap(["replay", str(flight / "video.mp4"), "--out", str(tmp_path / "run"),
                        "--status-interval", "0"], err)  # the progress bar is asked for (the default)
    assert result.returncode == 0, err.read_text()
    text = err.read_text()
    assert "\r" not in text and "frame/s" not in text and "it/s" not in text
    assert "run finished: 30 frames in" in text  # stderr was written, just not the bar


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bar_is_drawn_on_a_terminal(monkeypatch):
    """The other side of the gate: the same sink on a terminal draws the bar."""
    for stream, drawn in ((_Terminal(), True), (io.StringIO(), False)):
        monkeypatch.setattr(sys, "stderr", stream)
        tick, close = progress_sink(5, True)
        for _ in range(5):
            tick(None)
        close()
        assert ("5/5" in stream.getvalue()) == drawn


# --------------------------------------------------------------------------- status line
class _Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def _event(i: int, t: float, *, live: bool = True, status: str = "registered", segment: int = 0,
           dropped: int = 0, link_lost: int = 0, link_regained: int = 0,
           telemetry: TelemetrySample | None = None) -> FrameEvent:
    return FrameEvent(i, t, live, np.zeros((4, 4), np.uint8), (4, 4), status, None, 0.9, segment,
                      frame_ms=10.0 + i % 2, dropped_frames=dropped, link_lost=link_lost,
                      link_regained=link_regained, telemetry=telemetry)


def test_status_line_counts_what_the_sink_saw(caplog):
    clock = _Clock()
    reporter = StatusReporter(5.0, telemetry=True, clock=clock)
    sample = TelemetrySample(t=0.0)
    with caplog.at_level(logging.INFO, logger="photomap.status"):
        # 50 frames over 5 s, each mapped 40 ms after capture; 10 low-confidence; segment 1 from frame 40
        for i in range(50):
            clock.t += 0.1
            reporter.on_frame(_event(i, clock.t - 0.040, status="low_confidence" if i % 5 == 0 else "registered",
                                     segment=1 if i >= 40 else 0, dropped=i // 10, telemetry=sample))
        first = reporter.report()
        # the link drops; then no frame for 12 s
        clock.t += 0.1
        reporter.on_frame(_event(50, clock.t - 0.2, segment=1, dropped=5, link_lost=1, telemetry=None))
        clock.t += 12.0
        second = reporter.report()
        third = reporter.report()
    assert first["frames"] == 50 and first["fps"] == pytest.approx(10.0)
    assert first["registered_pct"] == 80.0 and first["dropped"] == 4 and first["segments"] == 2
    assert first["latency_ms"] == pytest.approx(40.0, abs=0.1) and first["telemetry"] == "ok"
    assert first["worker_ms"] == pytest.approx(10.5)
    assert second["frames"] == 51 and second["telemetry"] == "lost" and second["idle_s"] == pytest.approx(12.0)
    assert second["latency_max_ms"] == pytest.approx(200.0, abs=0.1)
    lines = [r.getMessage() for r in caplog.records if r.name == "photomap.status"]
    assert lines[0] == ("status: 50 frames, 10.0 fps, 80% registered, 4 dropped, 2 segments, "
                        "latency 40 ms (max 40), telemetry ok")
    assert lines[1].startswith("status: 51 frames") and "last frame 12 s ago" in lines[1]
    assert "telemetry lost" in lines[1]
    assert third["fps"] == 0.0 and lines[2].startswith("status: no frames for 12 s (51 in total)")


def test_status_sink_never_raises():
    reporter = StatusReporter(1.0)
    reporter.on_frame(None)  # not an event at all
    assert reporter.report()["frames"] == 0
    with pytest.raises(ValueError):
        StatusReporter(0.0)


def test_replay_logs_status_lines_while_it_runs(flight, tmp_path):
    err = tmp_path / "stderr.txt"
    result = _photomap(["replay", str(flight / "video.mp4"), "--out", str(tmp_path / "run"), "--realtime",
                        "--mavlink", str(flight / "telemetry.tlog"), "--status-interval", "0.3"], err)
    assert result.returncode == 0, err.read_text()
    lines = [line for line in err.read_text().splitlines() if " photomap.status: status: " in line]
    assert lines, err.read_text()  # a realtime replay of 30 frames at 15 fps lasts 2 s
    frames = [int(m.group(1)) for m in map(re.compile(r"status: status: (\d+) frames, ").search, lines) if m]
    assert frames == sorted(frames) and 0 < frames[-1] <= N_FRAMES
    assert all("telemetry ok" in line for line in lines if "fps" in line)


# --------------------------------------------------------------------------- JSON lines
def test_json_log_lines_parse(flight, tmp_path):
    err = tmp_path / "stderr.txt"
    # --viewer spawn without a display: a WARNING record; --realtime: status lines
    result = _photomap(["replay", str(flight / "video.mp4"), "--out", str(tmp_path / "run"), "--realtime",
                        "--viewer", "spawn", "--status-interval", "0.3", "--log-format", "json"], err,
                       env_drop=("DISPLAY", "WAYLAND_DISPLAY"))
    assert result.returncode == 0, err.read_text()
    records = [json.loads(line) for line in err.read_text().splitlines()]  # every line is one object
    assert all({"time", "level", "logger", "message"} <= set(r) for r in records)
    assert any(r["level"] == "WARNING" and "no display" in r["message"] for r in records)
    status = [r for r in records if r["logger"] == "photomap.status"]
    assert status and all(isinstance(r["frames"], int) and "fps" in r and "telemetry" in r for r in status)
    (done,) = [r for r in records if r["message"].startswith("run finished")]
    assert done["frames_in"] == N_FRAMES and done["registered"] == N_FRAMES
    assert "frames: 30 in" in result.stdout  # the summary for a person stays on stdout


def test_json_formatter_fields_and_exceptions():
    fmt = JsonFormatter()
    record = logging.LogRecord("photomap.x", logging.ERROR, __file__, 1, "failed %d times", (3,), None)
    tmp = object()
    record.fps, record.latency_ms, record.path = 12.5, float("nan"), tmp
    out = json.loads(fmt.format(record))
    assert out["message"] == "failed 3 times" and out["level"] == "ERROR" and out["logger"] == "photomap.x"
    assert out["fps"] == 12.5 and out["latency_ms"] is None and out["path"] == str(tmp)
    assert out["time"].endswith("+00:00")
    try:
        raise RuntimeError("boom")
    except RuntimeError:
        record = logging.LogRecord("photomap.x", logging.ERROR, __file__, 1, "crash", (), sys.exc_info())
    out = json.loads(fmt.format(record))
    assert "RuntimeError: boom" in out["exception"] and "\n" not in fmt.format(record)
