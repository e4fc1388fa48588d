"""The rerun operator view: recordings read back against the run's own poses, modes, backpressure."""

from __future__ import annotations

import csv
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import warnings

import yaml
from pathlib import Path

import cv2
import numpy as np
import pytest

rr = pytest.importorskip("rerun", reason="rerun-sdk is not installed (the `viewer` extra)")
from rerun.chunk import RrdReader  # noqa: E402

from photomap.drivers.frames import CaptureStats, Frame  # noqa: E402
from photomap.config import MosaicConfig, ViewerConfig, load_config  # noqa: E402
from photomap.errors import ConfigError  # noqa: E402
from photomap.core.mosaic import TiledMosaic  # noqa: E402
from photomap.mapping.events import FrameEvent  # noqa: E402
from photomap.mapping.pipeline import MappingPipeline  # noqa: E402
from photomap.geometry import frame_centre  # noqa: E402
from photomap.live.viewer import (Viewer, _port_free, footprint_tiles, frame_outline,  # noqa: E402
                                  parse_serve_address, parse_viewer_mode)
from tests.waiting import wait_until  # noqa: E402

W, H = 160, 120
N_FRAMES = 40


class ListSource:
    """A replay source over a list of frames; optionally waits for ``gate`` before frame ``pause_at``."""

    live = False

    def __init__(self, frames: list[Frame], pause_at: int | None = None,
                 gate: threading.Event | None = None) -> None:
        self.frames, self.pause_at, self.gate = frames, pause_at, gate
        self.stats = CaptureStats()

    def __iter__(self):
        for frame in self.frames:
            if frame.index == self.pause_at:
                assert self.gate.wait(30.0), "test gate never opened"
            self.stats.read += 1
            yield frame

    def close(self) -> None:
        pass


def _texture(h: int = 600, w: int = 800, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.normal(0, 1, (h, w, 3)).astype(np.float32), (0, 0), 3)
    return np.rint(20 + 215 * (t - t.min()) / (t.max() - t.min())).astype(np.uint8)


def _frames(n: int = N_FRAMES) -> list[Frame]:
    """Frames cut from a texture, the window moving by (+3, +2) px per frame."""
    tex = _texture()
    return [Frame(i, i / 30.0, tex[100 + 2 * i:100 + 2 * i + H, 100 + 3 * i:100 + 3 * i + W].copy(), "tex")
            for i in range(n)]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _chunks(path: Path) -> dict[str, list]:
    """Record batches of a recording, by entity path."""
    out: dict[str, list] = {}
    for chunk in RrdReader(str(path)).stream().to_chunks():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def _rows(batches: list, column: str) -> list:
    """All values of ``column`` over the batches that have it, in frame order."""
    rows = []
    for rb in batches:
        if column in rb.schema.names:
            frames = rb.column("frame").to_pylist() if "frame" in rb.schema.names else [None] * rb.num_rows
            rows.extend(zip(frames, rb.column(column).to_pylist()))
    return [v for _, v in sorted(rows, key=lambda fv: -1 if fv[0] is None else fv[0])]


def _has_entity(path: Path, entity: str) -> bool:
    """True if the (maybe still growing, footer-less) recording holds ``entity``."""
    if not path.exists():
        return False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # no footer while the client runs or after it was killed
        try:
            return entity in _chunks(path)
        except Exception:  # a record still being written
            return False


def _run(viewer: Viewer, tmp_path: Path, source: ListSource | None = None) -> MappingPipeline:
    pipeline = MappingPipeline(source or ListSource(_frames()), load_config(), tmp_path / "out",
                               sinks=[viewer.on_frame])
    pipeline.run()
    viewer.close()
    return pipeline


def _rerun_exe() -> Path:
    import rerun_cli

    exe = Path(rerun_cli.__file__).parent / "rerun"
    if not exe.is_file():
        pytest.skip(f"the rerun viewer binary is not installed at {exe}")
    return exe


# --------------------------------------------------------------------------- mode strings
@pytest.mark.parametrize("text, expected", [
    ("none", ("none", None)),
    (" Spawn ", ("spawn", None)),
    ("serve", ("serve", None)),
    ("serve=9877", ("serve", "9877")),
    ("serve=0.0.0.0:9877", ("serve", "0.0.0.0:9877")),
    ("serve=[::1]:9877", ("serve", "[::1]:9877")),
    ("connect", ("connect", "rerun+http://127.0.0.1:9876/proxy")),
    ("connect=rerun+http://10.0.0.5:9876/proxy", ("connect", "rerun+http://10.0.0.5:9876/proxy")),
    ("save=flight/run.rrd", ("save", "flight/run.rrd")),
])
def test_parse_viewer_mode(text, expected):
    assert parse_viewer_mode(text) == expected


@pytest.mark.parametrize("text", ["", "show", "spawn=1", "serve=0", "serve=99999", "serve=abc",
                                  "serve=drone.local:9876", "serve=10.0.0.300:9876", "serve=0.0.0.0:",
                                  "serve=0.0.0.0:0", "serve=::1:9876", "serve=[10.0.0.1]:9876",
                                  "serve=[::1]9876",
                                  "connect=http://host:9876/proxy", "connect=rerun+http://host:9876/",
                                  "connect=rerun+http://host:port/proxy", "save", "save=run.mp4"])
def test_parse_viewer_mode_rejects_garbage(text):
    with pytest.raises(ConfigError, match="viewer mode"):
        parse_viewer_mode(text)


@pytest.mark.parametrize("arg, expected", [
    (None, ("127.0.0.1", 9876)),  # the default: this machine only
    ("9877", ("127.0.0.1", 9877)),
    ("localhost:9877", ("127.0.0.1", 9877)),
    ("0.0.0.0", ("0.0.0.0", 9876)),
    ("10.8.0.1:9000", ("10.8.0.1", 9000)),
    ("[::]:9877", ("::", 9877)),
    ("[::1]", ("::1", 9876)),
])
def test_parse_serve_address(arg, expected):
    assert parse_serve_address(arg, 9876) == expected


# --------------------------------------------------------------------------- geometry
def test_outline_and_footprint_tiles_cover_what_the_mosaic_changes():
    a = np.radians(30.0)
    pose = np.array([[np.cos(a), -np.sin(a), 300.0], [np.sin(a), np.cos(a), -40.0]])
    outline = frame_outline(pose, W, H)
    assert outline.shape == (5, 2) and np.allclose(outline[0], outline[-1])
    assert np.allclose(outline[2], pose @ (W - 0.5, H - 0.5, 1.0))
    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    touched = mosaic.add(np.full((H, W, 3), 128, np.uint8), pose)
    predicted = footprint_tiles(pose, W, H, 64)
    assert touched <= predicted
    assert len(predicted) <= 2 * len(touched)


# --------------------------------------------------------------------------- save mode, read back
def test_saved_recording_matches_the_run(tmp_path):
    rrd = tmp_path / "run.rrd"
    viewer = Viewer("save", str(rrd), ViewerConfig(tile_hz=4.0, jpeg_quality=95, trajectory_every=10))
    pipeline = _run(viewer, tmp_path)
    assert pipeline.stats.frames_in == N_FRAMES and viewer.stats.errors == 0
    assert viewer.stats.dropped == 0

    with open(tmp_path / "out" / "trajectory.csv") as f:
        rows = [r for r in csv.DictReader(f)]
    posed = [r for r in rows if r["x"] not in ("", "nan")]
    assert len(posed) >= N_FRAMES - 2  # the texture registers: (almost) every frame is posed

    chunks = _chunks(rrd)
    for entity in ("/map/trajectory", "/map/footprint", "/camera/image", "/health/confidence",
                   "/health/latency_ms/worker", "/health/dropped", "/health/queue_depth",
                   "/events"):
        assert entity in chunks, entity
    assert RrdReader(str(rrd)).blueprints(), "no default blueprint in the recording"
    RrdReader(str(rrd)).store()  # has a footer: the recording was closed cleanly

    # one trajectory point per posed frame, each at the frame centre through its pose
    points = _rows(chunks["/map/trajectory"], "Points2D:positions")
    assert len(points) == len(posed)
    k = len(posed) // 2
    assert points[k][0] == pytest.approx([float(posed[k]["x"]), float(posed[k]["y"])], abs=1e-3)
    step_pose = pipeline.rows[int(posed[k]["frame"])].M
    assert np.allclose(points[k][0], step_pose @ (*frame_centre(W, H), 1.0), atol=1e-3)
    assert len(_rows(chunks["/health/confidence"], "Scalars:scalars")) == N_FRAMES
    latency = _rows(chunks["/health/latency_ms/worker"], "Scalars:scalars")  # [registration, whole frame]
    assert len(latency) == N_FRAMES and all(0 < reg <= whole for reg, whole in latency)
    strips = _rows(chunks["/map/trajectory"], "LineStrips2D:strips")
    assert strips and np.allclose(strips[-1][-1][-1], points[-1][0], atol=1e-3)  # the path ends at the last point

    # every tile of the map is in the recording; the latest version equals the map's tile
    mosaic = pipeline.mosaics[0]
    tile_entities = {e for e in chunks if e.startswith("/map/tiles/0/")}
    assert tile_entities == {f"/map/tiles/0/{ty}_{tx}" for tx, ty in mosaic.tiles()}
    for tx, ty in mosaic.tiles():
        batches = chunks[f"/map/tiles/0/{ty}_{tx}"]
        ((x0, y0, z),), = _rows(batches, "Transform3D:translation")
        assert (x0, y0, z) == (tx * 256 - 0.5, ty * 256 - 0.5, 0.0)
        blob = _rows(batches, "EncodedImage:blob")[-1]
        logged = cv2.imdecode(np.frombuffer(bytes(blob[0]), np.uint8), cv2.IMREAD_COLOR)
        image, alpha = mosaic.tile_image((tx, ty))
        inner = cv2.erode(alpha, np.ones((17, 17), np.uint8)) > 0  # away from JPEG ringing at map edges
        diff = np.abs(logged.astype(int) - image.astype(int))[inner]
        assert inner.sum() > 0 and diff.mean() < 2.0, (tx, ty, diff.mean())
    events = _rows(chunks["/events"], "TextLog:text")
    assert events[0] == ["map segment 0 started at frame 0"]


# --------------------------------------------------------------------------- backpressure
def _pose(i: int) -> np.ndarray:
    return np.array([[1.0, 0.0, 3.0 * i], [0.0, 1.0, 2.0 * i]])


def _event(frame: Frame, pose: np.ndarray | None, mosaic, segment: int = 0, touched=frozenset(),
           live: bool = False, **kw) -> FrameEvent:
    return FrameEvent(frame.index, frame.t, live, frame.image, (W, H),
                      "registered" if pose is not None else "low_confidence", pose,
                      0.9 if pose is not None else 0.05, segment, touched=frozenset(touched), tiles=mosaic, **kw)


def test_tiles_changed_after_the_last_frame_reach_the_recording(tmp_path):
    """What the run paints after its last frame (the last keyframe's bands, the final
    re-render) is sent at close: the recording's latest version of every tile is the map's."""
    rrd = tmp_path / "end.rrd"
    viewer = Viewer("save", str(rrd), ViewerConfig(tile_hz=1000.0, jpeg_quality=95))
    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    tex = _texture()
    for i in range(4):
        frame = Frame(i, float(i), tex[:H, :W].copy(), "tex")
        viewer.on_frame(_event(frame, _pose(i), mosaic, 0, mosaic.add(frame.image, _pose(i))))
    late = mosaic.add(255 - tex[:H, :W], _pose(1))  # after the last frame: no event tells the viewer
    viewer.close()
    chunks = _chunks(rrd)
    for tx, ty in late:
        blob = _rows(chunks[f"/map/tiles/0/{ty}_{tx}"], "EncodedImage:blob")[-1]
        logged = cv2.imdecode(np.frombuffer(bytes(blob[0]), np.uint8), cv2.IMREAD_COLOR)
        image, alpha = mosaic.tile_image((tx, ty))
        inner = cv2.erode(alpha, np.ones((9, 9), np.uint8)) > 0
        assert inner.sum() > 0 and np.abs(logged.astype(int) - image.astype(int))[inner].mean() < 3.0, (tx, ty)


def test_stuck_viewer_drops_oldest_viewer_data_and_keeps_events(tmp_path):
    rrd = tmp_path / "stuck.rrd"
    viewer = Viewer("save", str(rrd), ViewerConfig(queue_size=4))
    entered, release = threading.Event(), threading.Event()
    log_item = viewer._log

    def stuck_log(item):  # the first item blocks the viewer thread, as a stalled sink would
        entered.set()
        release.wait(30.0)
        log_item(item)

    viewer._log = stuck_log
    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    frames = _frames(20)
    for i, frame in enumerate(frames):
        touched = mosaic.add(frame.image, _pose(i))
        viewer.on_frame(_event(frame, _pose(i), mosaic, touched=touched,
                               messages=("link lost: something",) if i == 3 else ()))
        if i == 0:
            assert entered.wait(10.0)
    # item 0 is in the stuck thread, 4 wait in the queue, the 15 others were dropped
    assert viewer.stats.dropped == 20 - 1 - 4
    release.set()
    viewer.close()
    chunks = _chunks(rrd)
    events = [e[0] for e in _rows(chunks["/events"], "TextLog:text")]
    assert "link lost: something" in events  # carried over from a dropped item
    assert any("viewer falls behind" in e for e in events)
    assert _rows(chunks["/health/dropped"], "Scalars:scalars")[-1] == [0.0, 15.0]  # capture, viewer
    # tile updates of dropped items were re-sent: every tile is there, at its final content
    for tx, ty in mosaic.tiles():
        assert f"/map/tiles/0/{ty}_{tx}" in chunks


def test_new_segment_clears_the_old_map_keeps_the_anchor_and_logs_live_latency(tmp_path):
    rrd = tmp_path / "segments.rrd"
    viewer = Viewer("save", str(rrd), ViewerConfig(tile_hz=1000.0, color_by="segment"))
    mosaics = {0: TiledMosaic(MosaicConfig(tile_size=64)), 1: TiledMosaic(MosaicConfig(tile_size=64))}
    tex = _texture()
    anchor_pose = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    for i in range(12):
        segment = 0 if i < 6 else 1
        pose = _pose(i - 5 if segment else i)
        frame = Frame(i, time.monotonic(), tex[:H, :W].copy(), "tex")  # live: monotonic capture time
        extra: dict = {}
        touched: set = set()
        if i == 5:  # lost; frame 6 starts segment 1 anchored at frame 5
            pose = None
        if i == 6:
            extra = {"messages": ("link lost: map segment 1 started at frame 5",), "anchor": (5, anchor_pose)}
            touched |= mosaics[1].add(tex[:H, :W], anchor_pose)
        if pose is not None:
            touched |= mosaics[segment].add(frame.image, pose)
        viewer.on_frame(_event(frame, pose, mosaics[segment], segment, touched, live=True, **extra))
    viewer.close()
    chunks = _chunks(rrd)
    clears = [rb.column("frame").to_pylist() for rb in chunks["/map/tiles/0"]]
    assert clears == [[6]]  # segment 0's tiles cleared when segment 1 started
    assert {e for e in chunks if e.startswith("/map/tiles/1/")} == \
        {f"/map/tiles/1/{ty}_{tx}" for tx, ty in mosaics[1].tiles()}
    centre = (*frame_centre(W, H), 1.0)
    strips = _rows(chunks["/map/trajectory"], "LineStrips2D:strips")
    assert len(strips[-1]) == 1 and len(strips[-1][0]) == 7  # one strip: segment 1's anchor and six points
    assert np.allclose(strips[-1][0][0], anchor_pose @ centre)
    assert np.allclose(strips[-1][0][1], _pose(1) @ centre)
    points = _rows(chunks["/map/trajectory"], "Points2D:positions")  # in frame order
    assert len(points) == 12 and np.allclose(points[5][0], anchor_pose @ centre)
    colors = _rows(chunks["/map/trajectory"], "Points2D:colors")
    assert len({c[0] for c in colors[:5]}) == 1 and colors[0] != colors[-1]  # coloured by segment
    latency = _rows(chunks["/health/latency_ms/end_to_end"], "Scalars:scalars")
    assert len(latency) == 12 and all(v[0] >= 0 for v in latency)
    events = [e[0] for e in _rows(chunks["/events"], "TextLog:text")]
    assert events == ["map segment 0 started at frame 0", "link lost: map segment 1 started at frame 5"]


# --------------------------------------------------------------------------- modes
def test_spawn_without_display_warns_and_carries_on(tmp_path, monkeypatch, caplog):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with caplog.at_level(logging.WARNING, logger="photomap.live.viewer"):
        viewer = Viewer("spawn")
    assert not viewer.enabled
    assert [r.message for r in caplog.records if "no display" in r.message]
    pipeline = _run(viewer, tmp_path)
    assert pipeline.stats.frames_in == N_FRAMES and viewer.stats.frames == 0


def test_spawned_viewer_listens_on_loopback_only(tmp_path, monkeypatch):
    """``--viewer spawn`` opens a local window whose server is not reachable from the network
    (rerun's own spawn listens on every interface); the run streams into it."""
    from photomap.live import viewer as viewer_module

    monkeypatch.setenv("DISPLAY", ":0")  # as on a desktop ...
    monkeypatch.setattr(viewer_module, "_SPAWN_ARGS", ("--headless",))  # ... but no window here
    monkeypatch.setenv("PATH", f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    port = _free_port()
    viewer = Viewer("spawn", params=ViewerConfig(port=port))
    try:
        assert viewer.enabled and viewer.spawned_pid is not None
        assert viewer.url == f"rerun+http://127.0.0.1:{port}/proxy"
        assert _listeners(port) == {"127.0.0.1"}
        pipeline = _run(viewer, tmp_path)
        assert pipeline.stats.frames_in == N_FRAMES and viewer.stats.frames == N_FRAMES
    finally:
        viewer.close()
        if viewer.spawned_pid is not None:
            os.killpg(viewer.spawned_pid, signal.SIGKILL)


def test_connect_to_nothing_warns_and_carries_on(caplog):
    port = _free_port()
    with caplog.at_level(logging.WARNING, logger="photomap.live.viewer"):
        viewer = Viewer(f"connect=rerun+http://127.0.0.1:{port}/proxy")
    assert not viewer.enabled and "nothing listens" in caplog.text
    viewer.close()


def _listeners(port: int) -> set[str]:
    """Local addresses of the TCP sockets listening on ``port`` (any process)."""
    import psutil

    return {c.laddr.ip for c in psutil.net_connections(kind="tcp")
            if c.status == psutil.CONN_LISTEN and c.laddr.port == port}


def test_serve_listens_on_loopback_unless_told_otherwise(caplog):
    port = _free_port()
    with caplog.at_level(logging.INFO, logger="photomap.live.viewer"):
        viewer = Viewer("serve", str(port))
    assert viewer.address == ("127.0.0.1", port) and viewer.url == f"rerun+http://127.0.0.1:{port}/proxy"
    assert wait_until(lambda: _listeners(port), 15.0, 0.1), "nothing listens"
    assert _listeners(port) == {"127.0.0.1"}  # not reachable from the network
    assert "ssh -N -L" in viewer.connect_hint and "ssh -N -L" in caplog.text
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    viewer.close()
    assert wait_until(lambda: not _listeners(port), 15.0, 0.1), "the server outlived close() with no client"

    port = _free_port()
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="photomap.live.viewer"):
        viewer = Viewer("serve", f"0.0.0.0:{port}")  # exposed deliberately
    assert wait_until(lambda: _listeners(port), 15.0, 0.1) and _listeners(port) == {"0.0.0.0"}
    assert "WITHOUT authentication" in caplog.text and "write into the live view" in caplog.text
    viewer.close()


def test_serve_restarts_at_once_after_a_stop_with_a_viewer_connected(tmp_path):
    """A run stopped while a viewer is connected leaves the server's side of that connection in
    TIME_WAIT (~60 s); the next run must still get the port."""
    port = _free_port()
    service = subprocess.Popen(
        [sys.executable, "-c", "import sys; from photomap.live.viewer import Viewer; "
                               f"v = Viewer('serve', '{port}'); print('up', flush=True); "
                               "sys.stdin.read(); v.close()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    client = None
    try:
        assert service.stdout.readline().strip() == "up"
        client = subprocess.Popen([str(_rerun_exe()), "--save", str(tmp_path / "got.rrd"), "--port", "auto",
                                   "--bind", "127.0.0.1", f"rerun+http://127.0.0.1:{port}/proxy"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        import psutil

        def conns(status: str) -> list:
            return [c for c in psutil.net_connections(kind="tcp")
                    if c.status == status and c.laddr.port == port]
        assert wait_until(lambda: conns(psutil.CONN_ESTABLISHED), 30.0, 0.1), "the viewer never connected"
        service.stdin.close()  # the service stops, its viewer still connected
        assert service.wait(30.0) == 0
    finally:
        if service.poll() is None:
            service.kill()
        if client is not None:
            os.killpg(client.pid, signal.SIGKILL)
            client.wait()
    if not wait_until(lambda: conns(psutil.CONN_TIME_WAIT), 3.0, 0.1):
        pytest.skip("no TIME_WAIT on the server's side this time (the client closed first): nothing to prove")
    with socket.socket() as s:  # a bind without SO_REUSEADDR (the old check) fails here ...
        with pytest.raises(OSError):
            s.bind(("127.0.0.1", port))
    assert _port_free(port, "127.0.0.1")  # ... the check the service makes does not
    viewer = Viewer("serve", str(port))  # the restart gets its port
    assert wait_until(lambda: _listeners(port) == {"127.0.0.1"}, 15.0, 0.1)
    viewer.close()


def test_serve_refuses_a_port_in_use():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        with pytest.raises(ConfigError, match="already in use"):
            Viewer("serve", str(s.getsockname()[1]))


def test_serve_rejects_a_bad_memory_limit():
    with pytest.raises(ConfigError, match="server_memory_limit"):
        Viewer("serve", str(_free_port()), ViewerConfig(server_memory_limit="lots"))


def test_config_section_defaults_to_no_viewer():
    viewer = Viewer.from_config(load_config().viewer)
    assert viewer.mode == "none" and not viewer.enabled
    assert Viewer.from_config(load_config().viewer, "serve=9999").arg == "9999"
    with pytest.raises(ConfigError, match="viewer.jpeg_quality"):
        load_config(overrides=["viewer.jpeg_quality=0"])


def test_serve_client_receives_and_its_death_does_not_stop_the_run(tmp_path):
    port = _free_port()
    viewer = Viewer("serve", str(port), ViewerConfig(tile_hz=100.0))
    assert viewer.url.endswith(f":{port}/proxy")
    got = tmp_path / "got.rrd"
    client = subprocess.Popen([str(_rerun_exe()), "--save", str(got), "--port", "auto", "--bind", "127.0.0.1",
                               f"rerun+http://127.0.0.1:{port}/proxy"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    gate = threading.Event()
    source = ListSource(_frames(), pause_at=N_FRAMES // 2, gate=gate)
    result: dict = {}
    runner = threading.Thread(target=lambda: result.update(p=_run(viewer, tmp_path, source)))
    try:
        runner.start()
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and not _has_entity(got, "/map/trajectory"):
            time.sleep(0.2)
        assert _has_entity(got, "/map/trajectory"), "the client received no frame"
    finally:
        os.killpg(client.pid, signal.SIGKILL)  # the client dies mid-run
        client.wait()
        gate.set()
    runner.join(60.0)
    assert not runner.is_alive()
    assert result["p"].stats.frames_in == N_FRAMES
    assert viewer.stats.frames == N_FRAMES and viewer.stats.errors == 0
    assert _has_entity(got, "/camera/image")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # no footer: the client was killed
        assert RrdReader(str(got)).blueprints(), "the served stream carries no default blueprint"


def test_telemetry_series_are_shown(tmp_path):
    """With a .tlog joined, altitude and vision-vs-autopilot heading are logged and agree."""
    import numpy as np
    from rerun.chunk import RrdReader

    from photomap.config import load_config
    from photomap.cli.replay import replay
    from photomap.sim.simulate import simulate_flight

    flight = simulate_flight(tmp_path / "flight", n_frames=30, size=(320, 240), fps=15.0, seed=2)
    rrd = tmp_path / "view.rrd"
    replay(str(flight / "video.mp4"), tmp_path / "run", load_config(),
           mavlink=str(flight / "telemetry.tlog"), viewer=f"save={rrd}")
    values: dict[str, list] = {"/telemetry/altitude_m": [], "/telemetry/heading_deg": []}
    for chunk in RrdReader(str(rrd)).stream().to_chunks():
        if chunk.entity_path in values and not chunk.is_static:
            values[chunk.entity_path] += chunk.to_record_batch().column("Scalars:scalars").to_pylist()
    assert len(values["/telemetry/altitude_m"]) == 30
    heading = np.array(values["/telemetry/heading_deg"])
    assert heading.shape == (30, 2)
    diff = (heading[:, 0] - heading[:, 1] + 180.0) % 360.0 - 180.0
    assert np.abs(diff).max() < 0.2  # vision follows the autopilot's heading
    # the Map view: GPS positions, and ground footprints where the simulated camera really looked
    from photomap.io.trajectory_files import read_groundtruth
    from photomap.sim.flight import pixel_to_latlon

    chunks = _chunks(rrd)
    positions = _rows(chunks["/geo/position"], "GeoPoints:positions")
    outlines = _rows(chunks["/geo/footprint"], "GeoLineStrings:line_strings")
    assert len(positions) == 30 and len(outlines) == 30 and "/geo/track" in chunks
    meta = yaml.safe_load((flight / "meta.yaml").read_text())
    truth = read_groundtruth(flight / "groundtruth.csv")
    for k in (0, 15, 29):
        corners = np.array([[-0.5, -0.5, 1], [319.5, -0.5, 1], [319.5, 239.5, 1], [-0.5, 239.5, 1]]).T
        px = truth.H[k] @ corners
        lat, lon = pixel_to_latlon(px[0] / px[2], px[1] / px[2], meta["gsd"], meta["origin"]["lat"],
                                   meta["origin"]["lon"])
        got = np.array(outlines[k][0])[:4]
        err_m = np.hypot((got[:, 0] - lat) * 111_320.0, (got[:, 1] - lon) * 111_320.0 * np.cos(np.radians(lat)))
        assert err_m.max() < 1.0, err_m  # the simulator's altitude/attitude give the exact footprint


@pytest.mark.parametrize("n", [0, 1, 7, 8, 9, 50, 1001])
def test_a_corrected_path_is_thinned_as_point_by_point(n):
    """After a loop correction the whole path comes at once (an array): the viewer keeps the same
    points, stride and count as if it had come point by point."""
    path = np.column_stack([np.arange(n) * 1.5, np.arange(n) * -0.5, np.linspace(0, 1, n)])
    one, bulk = (Viewer("none", params=ViewerConfig(trajectory_max_points=8)) for _ in range(2))
    for x, y, c in path.tolist():
        one._append_path(x, y, c)
    bulk._rebuild_path(path)
    assert bulk._path.points == one._path.points
    assert (bulk._path.stride, bulk._path.count, bulk._last_point) == (
        one._path.stride, one._path.count, one._last_point)
    one.close()
    bulk.close()
