"""Glass-to-map latency of a live stream: 1080p30 H.264 over UDP on loopback, quiet and beside a
busy neighbour.

The simulated 1920x1080 flight (``simulate_flight``: aukerman, random pattern, 30 fps) is encoded
ahead of the run as a camera's encoder would (libx264 ultrafast, zero latency, 8 Mbit/s, a key frame
a second, MPEG-TS with the video PES lengths written), each frame carrying its index as a 16-cell
barcode in its top-left corner. A *sender* process then sends each frame's packets to
``udp://127.0.0.1:PORT`` at 30 frames per second and records, on the host's monotonic clock
(``time.monotonic``, one clock for every process), when each frame leaves: the *glass* time (the
camera's own exposure-to-encoder delay is not ours to measure). The map side is the product:
``open_source(udp://...)`` (the stream driver, default ``capture:`` config) and
:class:`~photomap.mapping.pipeline.MappingPipeline` with a sink that reads the barcode back from
each mapped frame and the time the sink is called, which is after the frame was painted into the
map. Per frame: *arrival* (decoded and queued: ``Frame.t`` minus glass) and *glass to map* (painted
minus glass); median, 95th percentile and largest, plus the frames the capture dropped (drop-oldest
queue), those that never arrived (the sender starts before the receiver has its first key frame) and
those not registered.

    python -m tools.bench_latency [--frames N] [--size WxH] [--no-busy] [--out FILE | --print]

Writes the section between ``<!-- latency:start -->`` and ``<!-- latency:end -->`` of
``docs/benchmarks.md`` (``--out``; ``--print`` only prints). About 3 minutes on 2 cores. Needs
``ffmpeg`` with libx264 on the PATH. Targets (issue 34): median <= 150 ms, nothing dropped.
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import os
import platform
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from photomap.config import load_config
from photomap.drivers.capture import open_source
from photomap.errors import PhotomapError
from photomap.mapping.pipeline import MappingPipeline
from photomap.sim.simulate import simulate_flight

if __package__ in (None, ""):  # run as a script: tools/ is not a package on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tools.bench_pipeline import busy_neighbour, load_average  # noqa: E402
from tools.report import replace_section  # noqa: E402

log = logging.getLogger("bench_latency")

REPO = Path(__file__).resolve().parents[1]
SIZE = (1920, 1080)
FPS = 30.0
SEED = 3
TARGET_MEDIAN_MS = 150.0
BITS, CELL = 16, 32  # the barcode: 16 cells of 32x32 px, most significant bit first
# an HD video link's encoder: 8 Mbit/s, no B-frames, a key frame a second, parameter sets repeated
ENCODER = ["-c:v", "libx264", "-preset", "ultrafast", "-tune", "zerolatency", "-bf", "0", "-g", "30",
           "-b:v", "8M", "-maxrate", "8M", "-bufsize", "2M", "-x264-params", "repeat-headers=1", "-omit_video_pes_length", "0"]


# --------------------------------------------------------------------------- the barcode

def stamp(image: np.ndarray, index: int) -> None:
    """Write ``index`` into the top-left ``BITS`` cells of ``image`` (white = 1), in place."""
    for bit in range(BITS):
        on = (index >> (BITS - 1 - bit)) & 1
        image[:CELL, bit * CELL:(bit + 1) * CELL] = 255 if on else 0


def read_stamp(image: np.ndarray) -> int:
    """The index :func:`stamp` wrote (read from the centre of each cell, after compression)."""
    strip = image[:CELL, :BITS * CELL]  # only the barcode's cells: the sink must cost the worker nothing
    gray = strip if strip.ndim == 2 else strip.mean(axis=2)
    value = 0
    for bit in range(BITS):
        cell = gray[CELL // 4:3 * CELL // 4, bit * CELL + CELL // 4:bit * CELL + 3 * CELL // 4]
        value = (value << 1) | int(float(cell.mean()) > 127.0)
    return value


# --------------------------------------------------------------------------- the sender

VIDEO_PID = 0x100  # ffmpeg's MPEG-TS muxer puts the first stream on PID 256
TS_PACKET = 188


def encode(video: Path, ts_path: Path, frames: int, fps: float, size: tuple[int, int]) -> int:
    """Stamp ``frames`` frames of ``video`` and encode them, ahead of the run, as a camera's encoder
    would (``ENCODER``, MPEG-TS); returns the frames encoded."""
    cap = cv2.VideoCapture(str(video))
    enc = subprocess.Popen([shutil.which("ffmpeg") or "ffmpeg", "-hide_banner", "-loglevel", "error", "-y",
                            "-f", "rawvideo", "-pix_fmt", "bgr24", "-s", f"{size[0]}x{size[1]}",
                            "-framerate", f"{fps:g}", "-i", "-", *ENCODER, "-muxdelay", "0", "-f", "mpegts",
                            str(ts_path)], stdin=subprocess.PIPE)
    n = 0
    for n in range(frames):
        ok, image = cap.read()
        if not ok:
            break
        stamp(image, n)
        enc.stdin.write(image.tobytes())
    else:
        n = frames
    enc.stdin.close()
    enc.wait()
    return n


def ts_frames(ts_path: Path) -> list[bytes]:
    """The transport stream cut before each video PES start: one piece per frame (no B-frames), the
    tables in front going with the first."""
    data = ts_path.read_bytes()
    pieces: list[bytes] = []
    begin = 0
    for pos in range(0, len(data) - TS_PACKET + 1, TS_PACKET):
        pid = ((data[pos + 1] & 0x1F) << 8) | data[pos + 2]
        if pid == VIDEO_PID and data[pos + 1] & 0x40 and pos > 0 and any(
                ((data[q + 1] & 0x1F) << 8 | data[q + 2]) == VIDEO_PID for q in range(begin, pos, TS_PACKET)):
            pieces.append(data[begin:pos])
            begin = pos
    pieces.append(data[begin:])
    return pieces


def send(ts_path: Path, port: int, fps: float, times_path: Path, start_delay: float) -> None:
    """Send each frame's packets of ``ts_path`` to UDP ``port`` on loopback at ``fps`` (7 TS packets a
    datagram, as ``pkt_size=1316``); write each frame's glass time (monotonic s, when its first
    datagram leaves) to ``times_path`` as JSON."""
    pieces = ts_frames(ts_path)
    glass: list[float] = []
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        t0 = time.monotonic() + start_delay
        for i, piece in enumerate(pieces):
            delay = t0 + i / fps - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            glass.append(time.monotonic())
            for off in range(0, len(piece), 7 * TS_PACKET):
                try:  # a camera sends on whether anyone listens (the receiver may be reopening)
                    sock.sendto(piece[off:off + 7 * TS_PACKET], ("127.0.0.1", port))
                except OSError:
                    pass
    times_path.write_text(json.dumps(glass))


# --------------------------------------------------------------------------- the map side

def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def measure(ts_path: Path, out: Path, busy: bool) -> dict:
    """One run: the sender process, the product's stream source and pipeline; per-frame latencies."""
    port = free_udp_port()
    url = f"udp://127.0.0.1:{port}"
    times_path = out.parent / f"{out.name}-glass.json"
    painted: list[tuple[int, float, float, str]] = []  # (stamped index, arrival, painted, status)

    def sink(event) -> None:
        now = time.monotonic()  # the frame is in the map; the barcode is read after the clock
        painted.append((read_stamp(event.image), event.t, now, event.status))

    with busy_neighbour(busy):
        sender = subprocess.Popen([sys.executable, "-m", "tools.bench_latency", "--send",
                                   json.dumps({"ts": str(ts_path), "port": port, "fps": FPS,
                                               "times": str(times_path), "start_delay": 1.0})], cwd=REPO)
        try:
            cfg = load_config()
            source = open_source(url, queue_size=cfg.capture.queue_size, open_timeout=10.0)
            pipeline = MappingPipeline(source, cfg, out, sinks=[sink], input_name=url)
            stopper = threading.Thread(target=lambda: (sender.wait(), time.sleep(1.5), pipeline.stop()),
                                       daemon=True)
            stopper.start()
            summary = pipeline.run()
        finally:
            if sender.poll() is None:
                sender.wait(60)
    glass = json.loads(times_path.read_text())
    arrival, to_map, registered = [], [], 0
    for index, t_in, t_map, status in painted:
        if 0 <= index < len(glass):
            arrival.append((t_in - glass[index]) * 1000.0)
            to_map.append((t_map - glass[index]) * 1000.0)
            registered += status in ("registered", "reference")
    first = min((p[0] for p in painted if p[0] < len(glass)), default=len(glass))
    rate = (len(glass) - 1) / (glass[-1] - glass[0]) if len(glass) > 1 and glass[-1] > glass[0] else 0.0
    return {"busy": busy, "sent": len(glass), "rate": rate, "read": source.stats.read, "mapped": len(painted),
            "registered": registered, "dropped": source.stats.dropped,
            "before_first": first, "never_arrived": len(glass) - source.stats.read,
            "arrival": arrival, "to_map": to_map, "ms_per_frame": summary.get("ms_per_frame")}


def _stats(values: list[float]) -> tuple[float, float, float]:
    if not values:
        return float("nan"), float("nan"), float("nan")
    a = np.asarray(values)
    return float(np.median(a)), float(np.percentile(a, 95)), float(a.max())


def render(runs: list[dict], frames: int, size: tuple[int, int], elapsed: float, load: tuple[float, float]) -> str:
    when = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    ffmpeg_version = subprocess.run([shutil.which("ffmpeg") or "ffmpeg", "-version"], capture_output=True,
                                    text=True).stdout.split("\n")[0].split(" ")[2]
    lines = ["## Stream latency (glass to map)", "",
             f"Written by `python -m tools.bench_latency` on {when} ({platform.machine()}, {os.cpu_count()} cores, "
             f"Python {platform.python_version()}, OpenCV {cv2.__version__}, ffmpeg {ffmpeg_version}; "
             f"{elapsed / 60:.1f} min; 1-minute load average {load[0]:.1f} at the start and {load[1]:.1f} at the "
             "end: more than the busy neighbour's 1 means other processes shared the cores, and the latencies "
             f"are upper bounds). The flight is encoded ahead of the run "
             f"(`{' '.join(ENCODER)}`, MPEG-TS); a sender process sends each frame's packets at 30 fps over UDP "
             "on loopback; `photomap`'s stream source (`udp://127.0.0.1:PORT`, default `capture:` config) and "
             "pipeline map it. *Glass* is when a frame's first packet leaves the sender (each frame carries "
             "its index as a barcode); *arrival* when the capture thread has it decoded; *map* when the "
             f"pipeline's sinks get the frame, after painting. {frames} frames per run; the first frames go by "
             "before the receiver's first key "
             "frame (a key frame a second).", "",
             "| condition | sent (fps) | read | dropped (queue) | before the first key frame | mapped | registered "
             "| arrival median / p95 ms | glass to map median / p95 / max ms |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in runs:
        a, m = _stats(r["arrival"]), _stats(r["to_map"])
        lines.append(f"| {'busy neighbour' if r['busy'] else 'quiet'} | {r['sent']} ({r['rate']:.1f}) "
                     f"| {r['read']} | {r['dropped']} "
                     f"| {r['before_first']} | {r['mapped']} | {r['registered']} | {a[0]:.0f} / {a[1]:.0f} "
                     f"| {m[0]:.0f} / {m[1]:.0f} / {m[2]:.0f} |")
    for r in runs:
        name = "busy neighbour" if r["busy"] else "quiet"
        if r["rate"] < 0.9 * FPS:
            lines += ["", f"*{name}*: the sender reached only {r['rate']:.1f} of its {FPS:g} fps (the host's "
                      "processes left it too little time): rerun on an otherwise quiet machine."]
    lines += ["", "| target | wanted | measured | met |", "|---|---|---|:---:|"]
    for r in runs:
        name = "busy neighbour" if r["busy"] else "quiet"
        med = _stats(r["to_map"])[0]
        if not r["to_map"]:
            lines.append(f"| glass to map, {size[1]}p30, {name} | median <= {TARGET_MEDIAN_MS:.0f} ms | no frame "
                         "mapped | no |")
            continue
        lines.append(f"| glass to map, {size[1]}p30, {name} | median <= {TARGET_MEDIAN_MS:.0f} ms | {med:.0f} ms "
                     f"| {'yes' if med <= TARGET_MEDIAN_MS else 'no'} |")
        lines.append(f"| frames dropped, {size[1]}p30, {name} | 0 | {r['dropped']} | {'yes' if not r['dropped'] else 'no'} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=450, help="frames per run (default 450: 15 s)")
    ap.add_argument("--no-busy", action="store_true", help="quiet run only")
    ap.add_argument("--size", default="1920x1080", help="frame size WxH (default 1920x1080, the target's)")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks.md",
                    help="markdown file whose latency section is replaced (default docs/benchmarks.md)")
    ap.add_argument("--print", action="store_true", help="print the section only")
    ap.add_argument("--send", metavar="JSON", help=argparse.SUPPRESS)  # internal: the sender process
    args = ap.parse_args(argv)
    if args.send:
        spec = json.loads(args.send)
        send(Path(spec["ts"]), int(spec["port"]), float(spec["fps"]), Path(spec["times"]), float(spec["start_delay"]))
        return 0
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if not shutil.which("ffmpeg"):
        print("error: ffmpeg not found (apt-get install ffmpeg)", file=sys.stderr)
        return 1
    logging.getLogger("photomap").setLevel(logging.WARNING)
    w, h = (int(v) for v in args.size.lower().split("x"))
    size = (w, h)
    start, load0 = time.perf_counter(), load_average()
    runs = []
    try:
        with tempfile.TemporaryDirectory(prefix="bench-latency-") as tmp:
            tmp_dir = Path(tmp)
            log.info("simulating %d frames of %dx%d", args.frames, *size)
            sim = simulate_flight(tmp_dir / "sim", n_frames=args.frames, size=size, fps=FPS, seed=SEED,
                                  video_codec="mjpg")
            ts_path = tmp_dir / "flight.ts"
            log.info("encoding it: %d frames", encode(sim / "video.avi", ts_path, args.frames, FPS, size))
            for busy in (False,) if args.no_busy else (False, True):
                runs.append(measure(ts_path, tmp_dir / f"out{int(busy)}", busy))
                r = runs[-1]
                log.info("%s: %d sent, %d read, %d dropped, glass to map median %.0f ms, p95 %.0f ms",
                         "busy" if busy else "quiet", r["sent"], r["read"], r["dropped"], *_stats(r["to_map"])[:2])
    except PhotomapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    body = render(runs, args.frames, size, time.perf_counter() - start, (load0, load_average()))
    print(body)
    if not args.print:
        replace_section(args.out, "latency", body)
        log.info("wrote the latency section of %s", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
