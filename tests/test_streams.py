"""Network streams end to end: a simulated flight sent by ffmpeg (MPEG-TS over UDP) and by a real RTSP
server, stopped for 4 s and started again, mapped live by ``photomap run`` and stopped with Ctrl-C; the
stream options and the counted (never printed) decoder messages."""

from __future__ import annotations

import itertools
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from photomap.drivers import native_log
from photomap.drivers.stream import StreamOpener, ffmpeg_options, is_stream
from photomap.errors import InputError
from photomap.sim.simulate import simulate_flight

FFMPEG = shutil.which("ffmpeg")
SYSTEM_PYTHON = "/usr/bin/python3"  # Debian's, where python3-gi and gst-rtsp-server live
PART = 180  # frames in each half of the flight (6 s at 30 fps)
FPS = 30
GAP_S = 4.0


def _need_ffmpeg() -> None:
    if not FFMPEG:
        pytest.skip("ffmpeg is not installed (apt-get install ffmpeg; .ci/run installs it)")


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def halves(tmp_path_factory) -> tuple[Path, Path]:
    """A 12 s, 30 fps 640x480 simulated flight as two H.264 MPEG-TS files (key frame every 15)."""
    _need_ffmpeg()
    folder = tmp_path_factory.mktemp("stream_flight")
    simulate_flight(folder, n_frames=2 * PART, size=(640, 480), fps=float(FPS), seed=11)
    parts = []
    for name, select in (("part1.ts", f"select=lt(n\\,{PART})"),
                         ("part2.ts", f"select=gte(n\\,{PART}),setpts=N/{FPS}/TB")):
        subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", "-i", str(folder / "video.mp4"),
                        "-vf", select, "-r", str(FPS), "-c:v", "libx264", "-preset", "ultrafast", "-tune",
                        "zerolatency", "-g", "15", "-x264-params", "repeat-headers=1", "-f", "mpegts",
                        str(folder / name)], check=True, timeout=120)
        parts.append(folder / name)
    return parts[0], parts[1]


def _photomap_run(url: str, out: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "photomap", "run", "--camera", url, "--out", str(out),
                             "--set", "capture.reconnect_max=1",
                             # a second of frames may wait: a neighbour that takes the CPU for a moment
                             # (or a server that sends its first second at once) drops nothing
                             "--set", "capture.queue_size=30"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_reopen(port: int, gap_s: float, limit_s: float = 20.0) -> None:
    """Stay silent for ``gap_s``, and on until photomap has let the port go and bound it again
    (the lost stream released and reopened: a loaded machine may take longer than the gap to
    notice the loss), at most ``limit_s``: then the stream comes back to a listening receiver."""
    start, released = time.monotonic(), False
    while time.monotonic() - start < limit_s:
        bound = _udp_bound(port)
        released = released or not bound
        if time.monotonic() - start >= gap_s and released and bound:
            return
        time.sleep(0.02)


def _udp_bound(port: int) -> bool:
    """Whether a socket listens on UDP ``port`` (from /proc/net/udp)."""
    try:
        lines = Path("/proc/net/udp").read_text().splitlines()[1:]
    except OSError:
        return False
    return any(line.split()[1].endswith(f":{port:04X}") for line in lines if len(line.split()) > 1)


def _stop_and_check(proc: subprocess.Popen, out: Path, sent: int) -> tuple[dict, str]:
    time.sleep(2.0)  # the last frames reach the map
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, stderr
    summary = json.loads((out / "run.json").read_text())
    assert summary["complete"]
    assert summary["registered"] >= 0.7 * sent, (summary, stderr)
    assert summary["reconnects"] >= 1, summary
    assert summary["segments"] == 1, summary
    assert (out / "mosaic.png").is_file() and (out / "trajectory.csv").is_file()
    # A log a person reads: the loss and the recovery, each once, and no decoder line.
    lines = stderr.splitlines()
    assert not [line for line in lines if native_log.decoder_message(line) or "Last message repeated" in line
                or "Out of memory" in line], stderr
    assert "Traceback" not in stderr
    assert sum("lost (no frame" in line for line in lines) >= 1, stderr
    assert sum("is back" in line for line in lines) >= 1, stderr
    assert len(lines) < 40, stderr
    return summary, stderr


def test_udp_mpegts_stream_that_stops_and_starts_again_is_mapped(halves, tmp_path):
    port = _free_port(socket.SOCK_DGRAM)
    url = f"udp://127.0.0.1:{port}"
    out = tmp_path / "run"
    proc = _photomap_run(url, out)
    try:
        deadline = time.monotonic() + 30
        while not _udp_bound(port) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _udp_bound(port), "photomap run never listened on the port"
        for i, part in enumerate(halves):
            if i:  # the sender is silent: the stream is lost, then reopened
                _wait_for_reopen(port, GAP_S)
            subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-re", "-i", str(part), "-c", "copy",
                            "-f", "mpegts", f"{url}?pkt_size=1316"], check=True, timeout=60)
        _stop_and_check(proc, out, 2 * PART)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def _rtsp_server_available() -> str | None:
    """Why a gst-rtsp-server cannot run here, or None."""
    if not Path(SYSTEM_PYTHON).is_file():
        return f"{SYSTEM_PYTHON} not found"
    probe = subprocess.run([SYSTEM_PYTHON, "-c", "import gi; gi.require_version('GstRtspServer', '1.0'); "
                            "from gi.repository import GstRtspServer; gi.require_version('Gst', '1.0'); "
                            "from gi.repository import Gst; Gst.init(None); "
                            "assert all(Gst.ElementFactory.find(e) for e in "
                            "('tsdemux', 'h264parse', 'rtph264pay'))"],
                           capture_output=True, text=True, timeout=60)
    if probe.returncode:
        return ("no RTSP server: needs python3-gi, gir1.2-gst-rtsp-server-1.0, gstreamer1.0-rtsp and "
                "gstreamer1.0-plugins-bad/good for the system python (.ci/run installs them)")
    return None


def _rtsp_server(port: int, part: Path) -> subprocess.Popen:
    server = subprocess.Popen([SYSTEM_PYTHON, str(Path(__file__).with_name("rtsp_server.py")), str(port), str(part)],
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert server.stdout.readline().strip() == "ready"
    return server


@pytest.mark.parametrize("transport", ["tcp", "udp"])
def test_rtsp_stream_whose_server_goes_away_and_comes_back_is_mapped(halves, tmp_path, transport):
    reason = _rtsp_server_available()
    if reason:
        pytest.skip(reason)
    port = _free_port(socket.SOCK_STREAM)
    url = f"rtsp://127.0.0.1:{port}/cam" + ("?tcp" if transport == "tcp" else "")
    out = tmp_path / "run"
    server = _rtsp_server(port, halves[0])
    proc = None
    try:
        proc = _photomap_run(url, out)
        time.sleep(PART / FPS + 4.0)  # start-up, then the first half plays to its end
        server.kill()
        server.wait()
        time.sleep(GAP_S)  # no server: the stream is lost, reopening fails and backs off
        server = _rtsp_server(port, halves[1])
        time.sleep(PART / FPS + 3.0)  # the camera reconnects and the second half plays
        _stop_and_check(proc, out, 2 * PART)
    finally:
        server.kill()
        server.wait()
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.communicate()


def test_plain_rtp_through_an_sdp_file_as_qgroundcontrol_sends_it(halves, tmp_path):
    """H.264 in RTP on a UDP port with no session set-up (QGroundControl's UDP 5600 convention):
    the .sdp file of docs/streams.md tells FFmpeg what arrives there."""
    from photomap.drivers.capture import open_source
    port = _free_port(socket.SOCK_DGRAM)
    sdp = tmp_path / "video.sdp"
    sdp.write_text("v=0\no=- 0 0 IN IP4 127.0.0.1\ns=photomap\nc=IN IP4 127.0.0.1\nt=0 0\n"
                   f"m=video {port} RTP/AVP 96\na=rtpmap:96 H264/90000\n")
    sender = subprocess.Popen([FFMPEG, "-hide_banner", "-loglevel", "error", "-re", "-i", str(halves[0]),
                               "-c", "copy", "-an", "-f", "rtp", "-payload_type", "96", f"rtp://127.0.0.1:{port}"],
                              stdout=subprocess.DEVNULL)
    try:
        src = open_source(str(sdp), queue_size=PART)
        got = list(itertools.islice(src, 60))
        src.close()
    finally:
        sender.kill()
        sender.wait()
    assert len(got) == 60 and all(f.image.shape == (480, 640, 3) for f in got)
    assert all(a.index + 1 == b.index and a.t <= b.t for a, b in zip(got, got[1:]))
    assert len({f.image[::40, ::40].tobytes() for f in got}) == 60  # the flight moves: every frame new


@pytest.mark.parametrize("kind", ["tcp", "http"])
def test_mpegts_over_tcp_and_http_mjpeg(halves, kind):
    """photomap connects to a server: MPEG-TS over TCP, or an IP camera's HTTP MJPEG stream."""
    from photomap.drivers.capture import open_source
    port = _free_port(socket.SOCK_STREAM)
    if kind == "tcp":
        url, out = f"tcp://127.0.0.1:{port}", ["-c", "copy", "-f", "mpegts", f"tcp://127.0.0.1:{port}?listen=1"]
    else:
        url = f"http://127.0.0.1:{port}/video.mjpg"
        out = ["-an", "-c:v", "mjpeg", "-q:v", "5", "-f", "mpjpeg", "-listen", "1", url]
    server = subprocess.Popen([FFMPEG, "-hide_banner", "-loglevel", "quiet", "-re", "-i", str(halves[0]), *out],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 20
        while True:  # the server listens once ffmpeg has started (a one-client server: no probing)
            try:
                src = open_source(url, queue_size=PART)
                break
            except InputError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        got = list(itertools.islice(src, 45))
        src.close()
    finally:
        server.kill()
        server.wait()
    assert len(got) == 45 and all(f.image.shape == (480, 640, 3) for f in got)
    assert len({f.image[::40, ::40].tobytes() for f in got}) == 45


# ------------------------------------------------------------------------------------ options


def test_stream_specs_are_told_from_devices_and_files():
    for spec in ("rtsp://10.0.0.2:8554/main", "udp://@:5600", "tcp://127.0.0.1:5000", "http://cam/video.mjpg",
                 "https://cam/mjpg", "qgc.sdp", "udpsrc port=5600 ! decodebin ! appsink"):
        assert is_stream(spec), spec
    for spec in ("/dev/video0", "0", "flight.mp4", "frames/*.jpg", 3, "C:/video.mp4"):
        assert not is_stream(spec), spec


def test_low_latency_options_and_rtsp_transport():
    url, opts = ffmpeg_options("udp://127.0.0.1:5600")
    assert url == "udp://127.0.0.1:5600"
    assert opts["fflags"] == "nobuffer" and opts["flags"] == "low_delay" and opts["analyzeduration"] == "0"
    url, opts = ffmpeg_options("rtsp://cam:8554/live?tcp")
    assert (url, opts["rtsp_transport"]) == ("rtsp://cam:8554/live", "tcp")
    url, opts = ffmpeg_options("rtsp://cam/live?transport=tcp&user=a", rtsp_transport="udp")
    assert (url, opts["rtsp_transport"]) == ("rtsp://cam/live?user=a", "tcp")
    assert ffmpeg_options("rtsp://cam/live", rtsp_transport="tcp")[1]["rtsp_transport"] == "tcp"
    assert ffmpeg_options("rtsp://cam/live")[1]["rtsp_transport"] == "udp"
    assert "rtp" in ffmpeg_options("/home/pi/qgc.sdp")[1]["protocol_whitelist"].split(",")
    assert StreamOpener("udp://@:5600").options.startswith("fflags;nobuffer|flags;low_delay|")


def test_gstreamer_pipeline_without_gstreamer_is_one_clear_error(monkeypatch):
    import photomap.drivers.stream as stream
    monkeypatch.setattr(stream, "has_gstreamer", lambda: False)
    with pytest.raises(InputError, match="GStreamer"):
        StreamOpener("udpsrc port=5600 ! application/x-rtp ! rtph264depay ! avdec_h264 ! appsink")


def test_a_silent_udp_port_is_one_input_error_within_the_open_timeout():
    from photomap.drivers.capture import open_source
    port = _free_port(socket.SOCK_DGRAM)
    t0 = time.monotonic()
    with pytest.raises(InputError, match="nothing decodable arrived within 1 s"):
        open_source(f"udp://127.0.0.1:{port}", open_timeout=1.0)
    assert time.monotonic() - t0 < 30  # bounded (the bound itself is not timed here)


# ------------------------------------------------------------------------- decoder messages


def _stderr_lines(code: str) -> list[str]:
    """The stderr lines of ``code`` run in a fresh interpreter (which must exit 0)."""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return proc.stderr.splitlines()


def test_native_decoder_lines_are_counted_and_everything_else_passes():
    """fd 2 written by native code (as FFmpeg's av_log does) through the tap, in a fresh process."""
    code = (
        "import logging, os, sys\n"
        "logging.basicConfig(level=logging.INFO, format='%(levelname)s %(message)s')\n"
        "from photomap.drivers import native_log\n"
        "tap = native_log.acquire()\n"
        "logging.info('python log line before')\n"
        "for i in range(200):\n"
        "    os.write(2, b'[h264 @ 0x55813e5c9880] non-existing PPS 0 referenced\\n')\n"
        "os.write(2, b'[h264 @ 0x55813e5c9880] no frame!\\n    Last message repeated 4 times\\n')\n"
        "os.write(2, b'[ WARN:0@5.010] global cap_ffmpeg_impl.hpp:453 _opencv_ffmpeg_interrupt_callback '\n"
        "         b'Stream timeout triggered after 2006.7 ms\\n')\n"
        "os.write(2, b'some other library line\\n')\n"
        "counts = native_log.release()\n"
        "logging.info('python log line after: %s', native_log.summarise(counts))\n"
    )
    lines = _stderr_lines(code)
    assert lines[0] == "INFO python log line before"
    assert "some other library line" in lines
    assert not [line for line in lines if any(n in line for n in ("@ 0x", "Last message", "WARN:0"))], lines
    assert lines[-1] == ("INFO python log line after: 206 decoder messages (200x 'h264: non-existing PPS 0 "
                         "referenced', 5x 'h264: no frame!', 1x 'opencv: Stream timeout triggered after N ms')")



def test_a_log_line_written_while_a_native_line_is_half_written_is_not_taken_for_it():
    """av_log writes a line's "[h264 @ 0x..] " prefix and its message in two writes: photomap's
    log (``setup_logging``) does not go through the tap, so a warning another thread logs between
    them reaches the real stderr whole, and the decoder line is still counted."""
    code = (
        "import logging, os\n"
        "from photomap.cli.oplog import setup_logging\n"
        "from photomap.drivers import native_log\n"
        "setup_logging(logging.INFO)\n"
        "native_log.acquire()\n"
        "os.write(2, b'[h264 @ 0x55813e5c9880] ')\n"
        "logging.getLogger('photomap.drivers.camera').warning('camera udp://x lost: reconnecting')\n"
        "os.write(2, b'non-existing PPS 0 referenced\\n')\n"
        "counts = native_log.release()\n"
        "logging.getLogger('t').info('after: %s', native_log.summarise(counts))\n"
    )
    lines = _stderr_lines(code)
    assert [line.split(" ", 1)[1] for line in lines] == [
        "WARNING photomap.drivers.camera: camera udp://x lost: reconnecting",
        "INFO t: after: 1 decoder message (1x 'h264: non-existing PPS 0 referenced')"], lines

def test_the_tap_forwards_everything_written_to_it_after_release_returns():
    """A writer that still holds the tap's pipe when the last hold is released (a child process
    that inherited fd 2) writes on past release's wait: every one of its lines reaches the real
    stderr, in order, and the pump ends with the pipe."""
    code = (
        "import subprocess, sys, threading, time\n"
        "from photomap.drivers import native_log\n"
        "native_log.acquire()\n"
        "child = subprocess.Popen([sys.executable, '-c', 'import os, time\\n'\n"
        "    'for i in range(40):\\n'\n"
        "    '    os.write(2, b\"child line %d\\\\n\" % i)\\n'\n"
        "    '    time.sleep(0.1)\\n'])\n"
        "time.sleep(0.3)\n"
        "t0 = time.monotonic()\n"
        "native_log.release()\n"
        "print(f'released after {time.monotonic() - t0:.1f} s', file=sys.stderr, flush=True)\n"
        "child.wait()\n"
        "deadline = time.monotonic() + 5.0\n"
        "pumps = lambda: [t for t in threading.enumerate() if t.name == 'photomap-stderr-tap']\n"
        "while pumps() and time.monotonic() < deadline:\n"
        "    time.sleep(0.01)\n"
        "print(f'pump alive: {bool(pumps())}', file=sys.stderr, flush=True)\n"
    )
    lines = _stderr_lines(code)
    child = [line for line in lines if line.startswith("child line")]
    assert child == [f"child line {i}" for i in range(40)], lines
    released = float(next(line for line in lines if line.startswith("released after")).split()[2])
    assert released <= native_log.CLOSE_WAIT_S + 1.0  # bounded: release does not wait for the child
    assert lines[-1] == "pump alive: False", lines


def test_decoder_message_keys():
    assert native_log.decoder_message("[mpegts @ 0x5581] PES packet size mismatch") == \
        "mpegts: PES packet size mismatch"
    assert native_log.decoder_message("INFO photomap.drivers.camera: camera 0 is back") is None
    assert native_log.decoder_message("[ WARN:2@10.9] global cap.cpp:212 open VIDEOIO(FFMPEG): backend is "
                                      "generally available but can't be used to capture by name") == \
        "opencv: VIDEOIO(FFMPEG): backend is generally available but can't be used to capture by name"
    assert native_log.decoder_message("[tcp @ 0x55a0] Connection to tcp://127.0.0.1:8562?timeout=0 failed") == \
        "tcp: Connection to tcp://127.0.0.1:8562?timeout=0 failed"
    assert native_log.decoder_message("[ WARN:0@1.2] global matrix.cpp:10 something else") is None
    # OpenCV's log prefix, read once for the decoder tap and the still reader (drivers.imread)
    assert native_log.opencv_log("[ WARN:0@0.031] global grfmt_tiff.cpp:123 TIFF_Warning TIFFReadDirectory: x") == \
        ("grfmt_tiff.cpp", "TIFF_Warning TIFFReadDirectory: x")
    assert native_log.opencv_log("[ERROR:0@2.5] something without a source") == ("", "something without a source")
    assert native_log.opencv_log("[h264 @ 0x5581] no frame!") is None


@pytest.mark.parametrize("how", ["--camera", "capture.device"])
def test_run_takes_a_url_and_a_silent_one_is_one_clear_line(tmp_path, how):
    port = _free_port(socket.SOCK_DGRAM)
    url = f"udp://127.0.0.1:{port}"
    where = ["--camera", url] if how == "--camera" else ["--set", f"capture.device={url}"]
    proc = subprocess.run([sys.executable, "-m", "photomap", "run", *where, "--out", str(tmp_path / "run"),
                           "--set", "capture.open_timeout=1"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 3, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"cannot open camera {url}: nothing decodable arrived within 1 s" in lines[0], lines


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class _Decoder:
    """A cv2.VideoCapture stand-in: ``script`` items are frames (True) or reads that fail at once
    (False); each read advances ``clock`` by ``step`` s. After the script every read fails."""

    def __init__(self, script, clock, step=0.1):
        self.script, self.clock, self.step = list(script), clock, step
        self.released = False

    def isOpened(self):
        return True

    def read(self):
        self.clock.now += self.step
        if self.script and self.script.pop(0):
            return True, np.zeros((2, 2, 3), np.uint8)
        return False, None

    def release(self):
        self.released = True


def test_a_stream_read_fails_only_after_the_timeout_without_a_frame():
    from photomap.drivers.stream import StreamCapture
    clock = _Clock()
    # a decoder waiting for its key frame fails 5 reads at once (0.5 s), then decodes
    dec = _Decoder([False] * 5 + [True, True], clock)
    cap = StreamCapture(dec, read_timeout=2.0, clock=clock)
    assert cap.read()[0] and cap.read()[0]
    assert clock.now == pytest.approx(0.7)
    ok, image = cap.read()  # then silence: False once 2 s passed since the last frame
    assert not ok and image is None
    assert clock.now == pytest.approx(0.7 + 2.0)
    released = []
    cap = StreamCapture(_Decoder([], clock), read_timeout=1.0, clock=clock, on_release=lambda: released.append(1))
    cap.release()
    cap.release()
    assert released == [1] and not cap.isOpened() and cap.read() == (False, None)


def test_each_opening_is_bounded_low_latency_and_leaves_the_environment_alone(monkeypatch):
    import cv2
    monkeypatch.delenv("OPENCV_FFMPEG_CAPTURE_OPTIONS", raising=False)
    seen = []

    class Closed:
        def isOpened(self):
            return False

        def release(self):
            pass

    def video_capture(url, api, params):
        seen.append((url, api, dict(zip(params[::2], params[1::2])), os.environ.get("OPENCV_FFMPEG_CAPTURE_OPTIONS")))
        return Closed()

    opener = StreamOpener("rtsp://cam/live?tcp", open_timeout=3.0, read_timeout=1.5, quiet_decoder=False,
                          video_capture=video_capture)
    assert not opener().isOpened()
    url, api, params, options = seen[0]
    assert (url, api) == ("rtsp://cam/live", cv2.CAP_FFMPEG)
    assert params == {cv2.CAP_PROP_OPEN_TIMEOUT_MSEC: 3000, cv2.CAP_PROP_READ_TIMEOUT_MSEC: 1500,
                      cv2.CAP_PROP_N_THREADS: 1}
    assert "rtsp_transport;tcp" in options.split("|") and "fflags;nobuffer" in options.split("|")
    assert "OPENCV_FFMPEG_CAPTURE_OPTIONS" not in os.environ  # a video file opened later is not affected
