"""Pipeline benchmark on a busy companion computer: throughput per frame size, quiet and beside a
busy neighbour, where the worker's time goes, the live case, and the memory of a long flight.

A companion computer is never idle: camera, video encoder and MAVLink router share its 2-4 cores
with us. This tool measures under the same kind of conditions:

1. *OpenCV threads*: the warps and resizes of a 1080p frame with ``cv2.setNumThreads`` 1 and 2,
   quiet and beside the busy neighbour (the measurement behind ``mapping.opencv_threads``).
2. *Throughput*: for each input size (640x480, 1280x720, 1920x1080, 3840x2160 by default) a
   simulated flight (``simulate_flight``: aukerman, random pattern, 8 m/s at 30 fps, MJPG video)
   is decoded alone (:class:`~photomap.drivers.video.VideoFileSource`: the upper bound) and mapped
   by ``photomap replay`` (:func:`photomap.cli.replay.replay`, default config), each ``--repeats``
   times, quiet and with a *busy neighbour*: a separate process spinning on one core (pinned to
   it) for the duration, started and stopped by this tool. Reported: median fps over the repeats,
   the ratio to decode-only fps measured in the same conditions, and the per-stage times the
   pipeline records itself (``run.json`` ``timing_ms``: median ms per frame of decode, resize,
   register, paint, loop closure, sinks, checkpoint outputs; the worker's longest frame, and its
   longest wait for the re-render thread: a replay waits for a job that is due, ``run.json``
   ``painting`` ``max_wait_ms``).
3. *Live*: the 1080p video fed at 30 fps through a drop-oldest queue of ``capture.queue_size``
   frames (as a camera is: :class:`PacedVideoSource`), beside the busy neighbour: frames mapped
   and dropped.
4. *Long flight*: ``--long-frames`` (10,000) frames of 1920x1080 rendered one by one from a
   lawn-mower flight (revisits: loop closures and re-renders) by a child process, each handed over
   as a fresh frame buffer (:class:`SimulatedSource`), mapped in a fresh process with the onboard
   tile cap (``mosaic.max_tiles_in_memory``); RSS sampled every
   50 ms (psutil): peak, the slope after the first 10 % of the frames (KB per frame; a
   straight-line fit, noisy: the median RSS of each tenth of the flight is written too, and the
   slope of the lowest RSS of each 1 %, right after a heap trim), and the
   worker's largest stall (longest frame, checkpoint, loop closure, re-render swap);
   ``--long-repeats`` (3) runs: the one with the median slope in the table, the worst peak and
   stall of all in the targets.
5. *Split flight*: the first 3,000 frames of that flight with frames 400-699 black (the camera
   saw nothing for 30 s: cloud, a lens cap, a cable): the map breaks into segments, and the
   later one joins the first when the camera sees mapped ground again; the worker's largest
   stall (a live join search reads keyframe images back and asks the features).

    python -m tools.bench_pipeline [--quick] [--sizes 640x480,1920x1080] [--frames N]
                                      [--repeats R] [--long-frames N] [--long-repeats N]
                                      [--no-busy] [--out FILE]

``--quick`` (< 2 minutes on a quiet 2-core computer: 640x480 and 1920x1080, 60 frames, one
repeat, a 600-frame long flight) prints only unless ``--out`` is given. The full run (about
30 minutes on 2 cores) replaces the section between ``<!-- pipeline:start -->`` and
``<!-- pipeline:end -->`` of ``docs/benchmarks.md`` (appended when absent) and leaves the rest of
that file alone. Run it on an otherwise quiet machine: the busy neighbour is the only load the
numbers should see (the 1-minute load average is reported). Needs ``psutil`` (the ``bench`` extra).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import logging
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from photomap.cli.replay import replay
from photomap.config import load_config
from photomap.drivers.frames import CaptureStats, Frame, SourceBase
from photomap.drivers.video import VideoFileSource
from photomap.errors import PhotomapError
from photomap.mapping.pipeline import MappingPipeline
from photomap.sim.flight import Camera, Effects, Motion, Truth, build_pyramid, iter_frames, plan_flight
from photomap.sim.simulate import simulate_flight
from photomap.sim.terrain import TERRAIN_GSD, TERRAIN_ZOOM, load_terrain, valid_mask

if __package__ in (None, ""):  # run as a script: tools/ is not a package on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tools.report import replace_section  # noqa: E402

log = logging.getLogger("bench_pipeline")

REPO = Path(__file__).resolve().parents[1]
SIZES = ((640, 480), (1280, 720), (1920, 1080), (3840, 2160))
SEED = 3
MB = 1024.0 * 1024.0

# Targets (issue 12): reported, never asserted.
TARGET_1080P_QUIET_FPS = 60.0
TARGET_1080P_BUSY_FPS = 30.0
TARGET_1080P_BUSY_RATIO = 0.25
TARGET_4K_QUIET_FPS = 20.0
TARGET_RSS_MB = 600.0
TARGET_SLOPE_KB = 0.5
TARGET_STALL_MS = 100.0

# The long flight: lawn-mower strips over the bundled orthophoto (zoomed 4x: 4212x3240 terrain px,
# 0.1125 m/px) at 8 m/s, 10 frames per second, image up along the track; closed, flown again and again.
LONG_SIZE = (1920, 1080)
LONG_TERRAIN = "aukerman"
LONG_FPS = 10.0
LONG_MOTION = dict(pattern="lawnmower", speed=8.0, yaw_mode="heading", yaw_rate=30.0,
                   altitude=(55.0, 65.0), scale_rate=0.02)
SPLIT_FRAMES, SPLIT_BLACKOUT = 3000, (400, 700)  # frames of the split flight, its black frames [a, b)
# the onboard config's (config/photomap-onboard.yaml) memory and checkpoint settings
LONG_OVERRIDES = ["mosaic.max_tiles_in_memory=256", "output.checkpoint_interval=5", "posegraph.max_solve_nodes=300"]
SERVICE_ENV = {"MALLOC_ARENA_MAX": "2"}  # config/photomap.service


# --------------------------------------------------------------------------- the busy neighbour

@contextlib.contextmanager
def busy_neighbour(enabled: bool = True) -> Iterator[None]:
    """A separate process spinning on one core (the last one, pinned) while the block runs."""
    if not enabled:
        yield
        return
    cpu = (os.cpu_count() or 1) - 1
    code = ("import os\n"
            f"try: os.sched_setaffinity(0, {{{cpu}}})\n"
            "except (AttributeError, OSError): pass\n"
            "while True: pass\n")
    proc = subprocess.Popen([sys.executable, "-c", code])
    time.sleep(0.3)  # let it start spinning
    try:
        yield
    finally:
        proc.kill()
        proc.wait()


def load_average() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


# --------------------------------------------------------------------------- (1) OpenCV threads

def opencv_threads_table(busy_enabled: bool, repeats: int = 15) -> list[str]:
    """Median ms of the 1080p warps and resizes the pipeline runs, per OpenCV thread count."""
    rng = np.random.default_rng(0)
    img = cv2.resize(rng.integers(0, 255, (270, 480, 3), np.uint8), (1920, 1080), interpolation=cv2.INTER_CUBIC)
    valid = np.full((1080, 1920), 255, np.uint8)
    M = cv2.getRotationMatrix2D((960, 540), 25, 1.0)
    M[:, 2] += (250, 350)
    ops = {
        "resize to the working size (1920x1080 -> 320x180, INTER_AREA)":
            lambda: cv2.resize(img, (320, 180), interpolation=cv2.INTER_AREA),
        "resize 3840x2160 -> 320x180 (INTER_AREA)":
            lambda: cv2.resize(big, (320, 180), interpolation=cv2.INTER_AREA),
        "warp a keyframe into the map (BGR + valid mask, 2400x2000)":
            lambda: (cv2.warpAffine(img, M, (2400, 2000)), cv2.warpAffine(valid, M, (2400, 2000))),
        "warp a new-ground strip (1920x64)":
            lambda: cv2.warpAffine(img, M, (1920, 64)),
    }
    big = cv2.resize(img, (3840, 2160), interpolation=cv2.INTER_LINEAR)
    before = cv2.getNumThreads()
    results: dict[tuple[str, bool, int], float] = {}
    try:
        for busy in ((False, True) if busy_enabled else (False,)):
            with busy_neighbour(busy):
                for _ in range(2):  # interleaved: 1, 2, 1, 2 threads
                    for n in (1, 2):
                        cv2.setNumThreads(n)
                        for name, op in ops.items():
                            op()
                            times = []
                            for _ in range(repeats):
                                t = time.perf_counter()
                                op()
                                times.append(time.perf_counter() - t)
                            results.setdefault((name, busy, n), [])
                            results[(name, busy, n)].append(1000 * statistics.median(times))
    finally:
        cv2.setNumThreads(before)
    conds = (False, True) if busy_enabled else (False,)
    head = "| operation | " + " | ".join(f"{'busy' if b else 'quiet'}, {n} thread{'s' if n > 1 else ''}"
                                          for b in conds for n in (1, 2)) + " |"
    lines = [head, "|---|" + "---:|" * (2 * len(conds))]
    for name in ops:
        cells = [f"{statistics.median(results[(name, b, n)]):.2f}" for b in conds for n in (1, 2)]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


# --------------------------------------------------------------------------- (2) throughput

def decode_only(video: Path) -> tuple[int, float]:
    """Frames and seconds to decode ``video`` with :class:`VideoFileSource` (nothing else)."""
    t = time.perf_counter()
    with VideoFileSource(video) as source:
        n = sum(1 for _ in source)
    return n, time.perf_counter() - t


@dataclass
class Condition:
    """One input size in one condition: decode-only and replay fps of every repeat, and the
    replays' run summaries."""

    size: tuple[int, int]
    busy: bool
    label: str = ""
    decode_fps: list[float] = field(default_factory=list)
    replay_fps: list[float] = field(default_factory=list)
    summaries: list[dict] = field(default_factory=list)

    @property
    def fps(self) -> float:
        return statistics.median(self.replay_fps)

    @property
    def ratio(self) -> float:
        return self.fps / statistics.median(self.decode_fps)

    @property
    def longest_wait(self) -> float | None:
        """The worker's longest wait for the re-render thread over the repeats (ms; a replay waits
        for a job that is due, so that its map does not depend on the machine's speed)."""
        values = [s["painting"]["max_wait_ms"] for s in self.summaries if "max_wait_ms" in s.get("painting", {})]
        return max(values) if values else None

    def stage(self, name: str, key: str = "median") -> float | None:
        values = [s["timing_ms"][name][key] for s in self.summaries if name in s.get("timing_ms", {})]
        if not values:
            return None
        return max(values) if key == "max" else statistics.median(values)


def measure(video: Path, out: Path, size: tuple[int, int], busy: bool, repeats: int,
            overrides: list[str], label: str = "") -> Condition:
    cond = Condition(size, busy, label)
    cfg = load_config(overrides=overrides)
    with busy_neighbour(busy):
        for r in range(repeats):  # decode-only and replay interleaved: the same conditions
            n, s = decode_only(video)
            cond.decode_fps.append(n / s)
            t = time.perf_counter()
            summary = replay(str(video), out / f"run{r}", cfg)
            wall = time.perf_counter() - t
            cond.replay_fps.append(summary["frames_in"] / wall)
            cond.summaries.append(summary)
    log.info("%dx%d %s%s: decode %.0f fps, replay %.1f fps (x%.3f)", *size, "busy" if busy else "quiet",
             f" {label}" if label else "", statistics.median(cond.decode_fps), cond.fps, cond.ratio)
    return cond


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def throughput_tables(conds: list[Condition]) -> list[str]:
    lines = ["| input | condition | decode-only fps | replay fps | of decode-only | registered | "
             "worker's longest frame ms | longest wait for the re-render ms |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for c in conds:
        s = c.summaries[-1]
        lines.append(f"| {c.size[0]}x{c.size[1]} | {'busy neighbour' if c.busy else 'quiet'}"
                     f"{', ' + c.label if c.label else ''} | {statistics.median(c.decode_fps):.0f} | "
                     f"{c.fps:.1f} | {c.ratio:.3f} | {s['registered']}/{s['frames_in']} | "
                     f"{_ms(c.stage('frame', 'max'))} | {_ms(c.longest_wait)} |")
    lines += ["", "Median ms per frame of each stage (`run.json` `timing_ms`, median over the repeats): "
              "*decode* runs in its own thread beside the worker; *resize* is the downscale to the "
              "working size; *register* the tracking (registration, pose); *paint* the map update "
              "(keyframes in bands of a tile row, one per frame; other frames their new ground); *loop* "
              "the loop closer's part in the worker; *frame* the worker's whole time per frame (mean in brackets: painting and loop "
              "closure come in bursts).", "",
              "| input | condition | decode | resize | register | paint | loop | frame (mean) |",
              "|---|---|---:|---:|---:|---:|---:|---:|"]
    for c in conds:
        label = f"{'busy' if c.busy else 'quiet'}{', ' + c.label if c.label else ''}"
        lines.append(f"| {c.size[0]}x{c.size[1]} | {label} | "
                     f"{_ms(c.stage('decode'))} | {_ms(c.stage('resize'))} | {_ms(c.stage('register'))} | "
                     f"{_ms(c.stage('paint'))} | {_ms(c.stage('loop_closure'))} | "
                     f"{_ms(c.stage('frame'))} ({_ms(c.stage('frame', 'mean'))}) |")
    return lines


# --------------------------------------------------------------------------- (3) live

class PacedVideoSource(SourceBase):
    """A video file fed like a live camera: decoded at its frame rate by a thread into a
    drop-oldest queue of ``queue_size`` frames (what :class:`~photomap.drivers.camera.CameraSource`
    does), ``live`` True: when the worker falls behind, the oldest frame is dropped and counted."""

    live = True

    def __init__(self, path: Path, fps: float, queue_size: int = 4) -> None:
        self.stats = CaptureStats()
        self._path, self._period, self._size = path, 1.0 / fps, queue_size
        self._queue: deque[Frame] = deque()
        self._cond = threading.Condition()
        self._done = False
        self._failure: Exception | None = None  # the feeding thread's, raised to the reader
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="paced-video", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        t0 = time.monotonic()
        try:
            with VideoFileSource(self._path) as video:
                for k, frame in enumerate(video):
                    if self._stop.is_set():
                        break
                    delay = t0 + k * self._period - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    with self._cond:
                        self.stats.read += 1
                        if len(self._queue) >= self._size:
                            self._queue.popleft()
                            self.stats.dropped += 1
                        self._queue.append(Frame(frame.index, time.monotonic(), frame.image, "paced"))
                        self._cond.notify()
        except Exception as exc:  # e.g. the video removed: the run fails instead of waiting forever
            self._failure = exc
        finally:
            with self._cond:
                self._done = True
                self._cond.notify()

    def __iter__(self) -> Iterator[Frame]:
        while True:
            with self._cond:
                while not self._queue and not self._done:
                    self._cond.wait(0.2)
                if not self._queue:
                    if self._failure is not None:
                        raise RuntimeError(f"the paced video failed: {self._failure}") from self._failure
                    return
                frame = self._queue.popleft()
            yield frame

    def close(self) -> None:
        self._stop.set()


def live_run(video: Path, out: Path, fps: float, busy: bool) -> dict:
    cfg = load_config()
    with busy_neighbour(busy):
        source = PacedVideoSource(video, fps, cfg.capture.queue_size)
        summary = MappingPipeline(source, cfg, out, input_name=video.name).run()
    summary["read"] = source.stats.read
    log.info("live %.0f fps %s: %d read, %d mapped, %d dropped", fps, "busy" if busy else "quiet",
             source.stats.read, summary["frames_in"], summary["dropped"])
    return summary


# --------------------------------------------------------------------------- (4) long flight

class SimulatedSource(SourceBase):
    """The frames of :func:`long_flight`, rendered one at a time in a child process and handed
    over as fresh uint8 BGR arrays, one per frame (never drops).

    What a camera driver hands the service: the renderer's terrain, pyramid and float32 working
    arrays (24 MB each at 1080p, several per frame) stay in the child, as the camera, decoder
    and encoder are other processes on the drone; the measured process holds only the product.
    The child renders a frame when the consumer asks for it and the consumer waits (as it did
    when the frames were rendered in its own thread: the renderer, far costlier than a camera's
    capture, never competes with the mapping for the cores). ``Frame.t`` is
    the flight time ``truth.t`` (s from frame 0). ``live`` as on the drone: the worker never
    waits for its background threads (a replay of a file runs them in lockstep with the frames
    instead, for identical maps; its waits are not the drone's stalls).
    """

    live = True

    def __init__(self, n_frames: int, size: tuple[int, int] = LONG_SIZE, seed: int = SEED,
                 blackout: tuple[int, int] | None = None) -> None:
        self.stats = CaptureStats()
        self._n, self._size, self._seed = n_frames, size, seed
        self._blackout = blackout  # frames [a, b) handed over black
        self._closed = False

    def __len__(self) -> int:
        return self._n

    def __iter__(self) -> Iterator[Frame]:
        w, h = self._size
        code = ("import sys; from tools.bench_pipeline import _render_long_flight; "
                f"_render_long_flight(sys.stdin.buffer, sys.stdout.buffer, {self._n}, ({w}, {h}), {self._seed})")
        child = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE)
        try:
            for k in range(self._n):
                if self._closed:
                    break
                try:
                    child.stdin.write(b"\n")  # the next frame, please
                    child.stdin.flush()
                except BrokenPipeError:
                    pass  # reported below
                header = child.stdout.read(8)
                image = bytearray(w * h * 3)  # a fresh buffer, as a decoder's
                if len(header) < 8 or child.stdout.readinto(image) < len(image):
                    raise RuntimeError(f"the flight renderer stopped at frame {k} (exit code {child.poll()})")
                self.stats.read += 1
                if self._blackout is not None and self._blackout[0] <= k < self._blackout[1]:
                    image[:] = b"\0" * len(image)
                yield Frame(k, float(np.frombuffer(header, np.float64)[0]),
                            np.frombuffer(image, np.uint8).reshape(h, w, 3), "simulated")
        finally:
            child.kill()
            child.wait()
            for pipe in (child.stdin, child.stdout):
                with contextlib.suppress(OSError):
                    pipe.close()

    def close(self) -> None:
        self._closed = True


def _render_long_flight(requests, out, n_frames: int, size: tuple[int, int], seed: int) -> None:
    """The child of :class:`SimulatedSource`: for each line read from ``requests``, writes the
    next frame to ``out`` (binary streams): its time (float64 s), then its pixels."""
    terrain, truth, camera = long_flight(n_frames, size, seed)
    frames = iter_frames(terrain, truth, camera, Effects(), seed,
                         pyramid=build_pyramid(terrain, float(truth.scale.max()) * 1.2))
    with contextlib.suppress(BrokenPipeError):  # the consumer stopped early
        for k in range(n_frames):
            if not requests.readline():
                return
            image = next(frames)
            out.write(np.float64(truth.t[k]).tobytes())
            out.write(np.ascontiguousarray(image).data)
            out.flush()


class RssSampler:
    """Samples the RSS of this process every ``interval`` seconds in a thread."""

    def __init__(self, interval: float = 0.05) -> None:
        import psutil

        self._process = psutil.Process()
        self._interval = interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rss-sampler", daemon=True)
        self.samples: list[tuple[float, float, int]] = []  # (monotonic s, RSS MB, frames done)
        self.frames_done = 0

    def rss_mb(self) -> float:
        return self._process.memory_info().rss / MB

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append((time.monotonic(), self.rss_mb(), self.frames_done))
            self._stop.wait(self._interval)

    def __enter__(self) -> RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.samples.append((time.monotonic(), self.rss_mb(), self.frames_done))


def long_flight(n_frames: int, size: tuple[int, int] = LONG_SIZE, seed: int = SEED
                ) -> tuple[np.ndarray, Truth, Camera]:
    """Terrain, truth and camera of the long lawn-mower flight."""
    zoom = TERRAIN_ZOOM[LONG_TERRAIN]
    terrain = load_terrain(LONG_TERRAIN, zoom=zoom)
    camera = Camera.from_hfov(size[0], size[1], 60.0)
    truth = plan_flight(valid_mask(terrain), n_frames, camera, LONG_FPS, TERRAIN_GSD[LONG_TERRAIN] / zoom,
                        Motion(**LONG_MOTION), seed)
    return terrain, truth, camera


def memory_run(n_frames: int, overrides: list[str], blackout: tuple[int, int] | None = None) -> dict:
    """Map the long flight (frames ``blackout`` [a, b) black) in this process while sampling RSS;
    returns the measurements (MB, s)."""
    import psutil

    rss0 = psutil.Process().memory_info().rss / MB
    source = SimulatedSource(n_frames, blackout=blackout)
    cfg = load_config(overrides=overrides)
    with tempfile.TemporaryDirectory(prefix="bench-pipeline-") as tmp, RssSampler() as sampler:
        before = sampler.rss_mb()

        def on_frame(event) -> None:
            sampler.frames_done += 1

        pipe = MappingPipeline(source, cfg, tmp, sinks=[on_frame], input_name="simulated")
        t = time.perf_counter()
        summary = pipe.run()
        wall = time.perf_counter() - t
        tiles = sum(len(m.tiles()) for m in pipe.mosaics.values())
        in_memory = sum(m.tiles_in_memory for m in pipe.mosaics.values())
    mapping = [(done, rss) for _, rss, done in sampler.samples if done < n_frames]
    at = {f"rss_at_{pct}_mb": next((rss for _, rss, done in sampler.samples if done >= n_frames * pct / 100),
                                   None) for pct in (10, 50, 100)}
    done_rss = np.array(mapping, float).reshape(-1, 2)  # (frames done, RSS MB) while mapping
    late = done_rss[done_rss[:, 0] >= n_frames / 10]
    slope = float(np.polyfit(late[:, 0], late[:, 1], 1)[0]) * 1024.0 if len(late) > 10 else None  # KB/frame
    # the lowest RSS of each 1 % of the flight: right after a heap trim (what the run holds, without
    # the free heap pages of the last second); its slope after the first 10 %
    pct = (done_rss[:, 0] * 100 // n_frames).astype(int)
    floors = np.array([(k * n_frames / 100, done_rss[pct == k, 1].min()) for k in range(10, 100) if (pct == k).any()])
    floor_slope = float(np.polyfit(floors[:, 0], floors[:, 1], 1)[0]) * 1024.0 if len(floors) > 10 else None
    tenths = [[r for d, r in mapping if k * n_frames / 10 <= d < (k + 1) * n_frames / 10] for k in range(10)]
    timing = summary.get("timing_ms", {})
    return {"overrides": overrides, "blackout": blackout, "frames": summary["frames_in"],
            "registered": summary["registered"],
            "segments": summary["segments"], "wall_s": wall, "fps": summary["frames_in"] / wall,
            "rss_start_mb": rss0, "rss_before_mb": before,
            "peak_mapping_mb": max((r for _, r in mapping), default=before),
            "peak_mb": max(rss for _, rss, _ in sampler.samples), "slope_kb_per_frame": slope,
            "floor_slope_kb_per_frame": floor_slope,
            "rss_tenths_mb": [float(np.median(t)) if t else None for t in tenths],
            "tiles": tiles, "tiles_in_memory": in_memory, "painting": summary.get("painting"),
            "loop_closure": summary.get("loop_closure"),
            "stall_ms": {k: timing[k]["max"] for k in ("frame", "outputs", "loop_closure", "map_upkeep",
                                                        "paint") if k in timing},
            **at}


def memory_run_subprocess(n_frames: int, overrides: list[str], blackout: tuple[int, int] | None = None) -> dict:
    """:func:`memory_run` in a fresh interpreter (clean RSS)."""
    spec = json.dumps({"frames": n_frames, "overrides": overrides, "blackout": blackout})
    cmd = [sys.executable, str(Path(__file__).resolve()), "--memory-run", spec]
    env = {**os.environ, **SERVICE_ENV}  # as the systemd unit runs the service
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"memory run {overrides} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def median_run(runs: list[dict]) -> dict:
    """The run of ``runs`` (memory runs of the same flight) whose RSS slope is the median (the
    lower one of an even count), with every run's measurements under ``"runs"``: one run's
    slope moves by 1 KB/frame and more from run to run (the checkpoints' and background jobs'
    bursts land at other moments)."""
    def slope(r: dict) -> float:
        return r["slope_kb_per_frame"] if r["slope_kb_per_frame"] is not None else float("inf")

    ordered = sorted(runs, key=slope)
    return {**ordered[(len(ordered) - 1) // 2], "runs": [
        {"slope_kb_per_frame": r["slope_kb_per_frame"], "floor_slope_kb_per_frame": r["floor_slope_kb_per_frame"],
         "peak_mb": r["peak_mb"], "stall_ms": max(r["stall_ms"].values(), default=0.0)} for r in runs]}


def memory_table(r: dict) -> list[str]:
    at = "/".join("-" if r[f"rss_at_{p}_mb"] is None else f"{r[f'rss_at_{p}_mb']:.0f}" for p in (10, 50, 100))
    slope = r["slope_kb_per_frame"]
    stall = r["stall_ms"]
    worst = max(stall.values(), default=0.0)
    p, lc = r.get("painting") or {}, r.get("loop_closure") or {}
    return [
        "| frames | registered | segments | fps | tiles (in memory) | RSS after imports / before | "
        "RSS at 10/50/100 % | peak RSS (incl. outputs) | slope after 10 % | largest stall |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        f"| {r['frames']} | {r['registered']} | {r['segments']} | {r['fps']:.1f} | {r['tiles']} "
        f"({r['tiles_in_memory']}) | {r['rss_start_mb']:.0f} / {r['rss_before_mb']:.0f} MB | {at} MB | "
        f"{r['peak_mapping_mb']:.0f} ({r['peak_mb']:.0f}) MB | "
        f"{'-' if slope is None else f'{slope:.2f}'} KB/frame | {worst:.0f} ms |", "",
        "Median RSS in each tenth of the flight (MB): "
        + " / ".join("-" if v is None else f"{v:.0f}" for v in r.get("rss_tenths_mb", [])) + ". "
        + ("" if r.get("floor_slope_kb_per_frame") is None else
           f"Slope of the lowest RSS of each 1 % of the flight after the first 10 % (right after a heap "
           f"trim: what the run holds): {r['floor_slope_kb_per_frame']:.2f} KB/frame. ")
        + "Largest worker time (ms): " + ", ".join(f"{k} {v:.0f}" for k, v in stall.items())
        + f". Loop closure: {lc.get('loop_edges', 0)} loop edges, {lc.get('corrections', 0)} corrections, "
        f"{lc.get('joins', 0)} joins; painting: {p.get('whole', 0)} frames whole, {p.get('new_ground', 0)} "
        f"new ground, {p.get('rerender_jobs', 0)} re-render jobs ({p.get('rerendered_tiles', 0)} tiles, "
        f"{p.get('rerender_s', 0):.1f} s in the background thread, longest swap {p.get('max_swap_ms', 0):.1f} ms)."
        + _runs_sentence(r)]


def _runs_sentence(r: dict) -> str:
    """The runs of :func:`median_run` (the table shows the median one), or nothing for one run."""
    runs = r.get("runs") or []
    if len(runs) < 2:
        return ""

    def kb(v: float | None) -> str:
        return "-" if v is None else f"{v:.2f}"

    return (f" The table shows the run with the median slope of {len(runs)} runs of this flight (slope / "
            "lowest-RSS slope KB/frame, peak MB, largest stall ms): " + "; ".join(
                f"{kb(x['slope_kb_per_frame'])} / {kb(x['floor_slope_kb_per_frame'])}, {x['peak_mb']:.0f}, "
                f"{x['stall_ms']:.0f}" for x in runs) + ".")


# --------------------------------------------------------------------------- report

def targets_table(conds: list[Condition], live: dict | None, memory: dict | None,
                  split: dict | None = None) -> list[str]:
    def find(size, busy):
        return next((c for c in conds if c.size == size and c.busy == busy and not c.label), None)

    rows = []
    q = find((1920, 1080), False)
    if q:
        rows.append(("1080p replay, quiet", f">= {TARGET_1080P_QUIET_FPS:.0f} fps", f"{q.fps:.1f} fps",
                     q.fps >= TARGET_1080P_QUIET_FPS))
    b = find((1920, 1080), True)
    if b:
        rows.append(("1080p replay, busy neighbour", f">= {TARGET_1080P_BUSY_FPS:.0f} fps and >= "
                     f"{TARGET_1080P_BUSY_RATIO} x decode-only", f"{b.fps:.1f} fps, x{b.ratio:.3f}",
                     b.fps >= TARGET_1080P_BUSY_FPS and b.ratio >= TARGET_1080P_BUSY_RATIO))
    k = find((3840, 2160), False)
    if k:
        rows.append(("4K replay, quiet", f">= {TARGET_4K_QUIET_FPS:.0f} fps", f"{k.fps:.1f} fps",
                     k.fps >= TARGET_4K_QUIET_FPS))
    if live:
        rows.append(("live 1080p30, busy neighbour", "keeps up (drops counted)",
                     f"{live['frames_in']} of {live['read']} mapped, {live['dropped']} dropped",
                     live["dropped"] <= 0.02 * max(1, live["read"])))
    if memory:
        runs = memory["runs"]  # (median_run)
        of = f" (worst of {len(runs)} runs)" if len(runs) > 1 else ""
        peak = max(x["peak_mb"] for x in runs)
        rows.append((f"{memory['frames']}-frame 1080p flight, peak RSS", f"< {TARGET_RSS_MB:.0f} MB",
                     f"{peak:.0f} MB{of}", peak < TARGET_RSS_MB))
        slope = memory["slope_kb_per_frame"]
        if slope is not None:
            rows.append(("... RSS slope after the first 10 %", f"< {TARGET_SLOPE_KB} KB/frame",
                         f"{slope:.2f} KB/frame" + (f" (median of {len(runs)} runs)" if len(runs) > 1 else ""),
                         slope < TARGET_SLOPE_KB))
        worst = max(x["stall_ms"] for x in runs)
        rows.append(("... largest worker stall (frame incl. checkpoint, loop closure, swap)",
                     f"< {TARGET_STALL_MS:.0f} ms", f"{worst:.0f} ms{of}", worst < TARGET_STALL_MS))
    if split:
        worst = max(split["stall_ms"].values(), default=0.0)
        a, b = split["blackout"]
        rows.append((f"{split['frames']}-frame flight split by {b - a} black frames: largest worker stall",
                     f"< {TARGET_STALL_MS:.0f} ms",
                     f"{worst:.0f} ms (loop closure {split['stall_ms'].get('loop_closure', 0.0):.0f}; "
                     f"{split['loop_closure'].get('joins', 0)} join)", worst < TARGET_STALL_MS))
    lines = ["| target | wanted | measured | met |", "|---|---|---|:---:|"]
    lines += [f"| {a} | {w} | {m} | {'yes' if ok else '**no**'} |" for a, w, m, ok in rows]
    return lines


def render_report(args: argparse.Namespace, threads: list[str], conds: list[Condition], live: dict | None,
                  memory: dict | None, split: dict | None, elapsed: float, load: tuple[float, float]) -> str:
    when = datetime.date.today().isoformat()
    lines = ["## Pipeline", "",
             f"Written by `python -m tools.bench_pipeline{' --quick' if args.quick else ''}` on {when} "
             f"(Python {platform.python_version()}, OpenCV {cv2.__version__}, numpy {np.__version__}, "
             f"{os.cpu_count()} cores, {elapsed / 60:.0f} min; 1-minute load average {load[0]:.1f} at the "
             f"start and {load[1]:.1f} at the end: more than the busy neighbour's 1 means other processes "
             "shared the cores and the speeds are lower bounds). Rerun it after a change to the pipeline, "
             "the registration or the map on an otherwise quiet machine: `python -m tools.bench_pipeline` "
             "(about 30 minutes on 2 cores); it rewrites only this section. The *busy neighbour* is a "
             "separate process spinning on one core for the duration, as a video encoder or a MAVLink "
             "router would.", "", "### Targets", ""]
    lines += targets_table(conds, live, memory, split)
    lines += ["", "### OpenCV threads", "",
              "Median ms of the warps and resizes a 1080p (and 4K) frame costs, with `cv2.setNumThreads` 1 "
              "and 2, quiet and beside the busy neighbour (`mapping.opencv_threads` follows from this; "
              "docs/onboard.md, thread budget).", ""]
    lines += threads
    lines += ["", "### Replay throughput", "",
              f"Simulated flights of {args.frames} frames per size (`simulate_flight`: aukerman, random "
              f"pattern, 8 m/s at 30 fps, seed {SEED}, MJPG), decoded alone and mapped by `photomap replay` "
              f"(default config), {args.repeats} time(s) each in each condition, medians shown. Wall time "
              "from the call to the outputs written.", ""]
    lines += throughput_tables(conds)
    if live:
        lines += ["", "### Live", "",
                  f"The 1080p flight fed at 30 fps through a drop-oldest queue of {load_config().capture.queue_size} "
                  "frames (like a camera), beside the busy neighbour: "
                  f"{live['read']} frames captured, {live['frames_in']} mapped, {live['dropped']} dropped "
                  f"(counted in `run.json` `dropped`); worker's median frame "
                  f"{live['timing_ms'].get('frame', {}).get('median', float('nan')):.1f} ms, longest "
                  f"{live['timing_ms'].get('frame', {}).get('max', float('nan')):.0f} ms."]
    if memory:
        lines += ["", "### Long flight: memory and stalls", "",
                  f"{memory['frames']} frames of {LONG_SIZE[0]}x{LONG_SIZE[1]} rendered one by one (`plan_flight` "
                  "+ `iter_frames`) by a child process, on request, each handed over as a fresh frame buffer "
                  "(as a camera driver does; the renderer's terrain and float arrays are not in the measured "
                  "process): lawn-mower strips over the bundled orthophoto "
                  f"(4212x3240 terrain px at 0.1125 m/px), {LONG_MOTION['speed']:g} m/s at {LONG_FPS:g} fps, "
                  "a closed loop flown again and again (loop closures, re-renders), mapped in a fresh process "
                  f"with `{' '.join(memory['overrides'])}` (as the onboard config) and "
                  f"`{' '.join(f'{k}={v}' for k, v in SERVICE_ENV.items())}` (as the systemd unit). "
                  "RSS sampled every 50 ms; the slope is a straight-line fit of RSS against frames after the "
                  "first 10 % (the target's measure; it includes the heap's free pages between two trims).", ""]
        lines += memory_table(memory)
    if split:
        a, b = split["blackout"]
        lines += ["", "### Split flight: joins and stalls", "",
                  f"The first {split['frames']} frames of the long flight, frames {a}-{b - 1} handed over black "
                  "(the camera saw nothing: cloud, a lens cap, a cable), mapped the same way: the map breaks "
                  "into segments (one-frame ones dropped) and the new one joins the first once the camera sees "
                  "mapped ground again (a live join search runs in the loop thread).", ""]
        lines += memory_table(split)
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- main

def parse_sizes(text: str) -> list[tuple[int, int]]:
    sizes = []
    for item in text.split(","):
        w, h = item.lower().split("x")
        sizes.append((int(w), int(h)))
    return sizes


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke test (< 2 min); prints only unless --out")
    ap.add_argument("--sizes", default=None, help="input sizes, e.g. 640x480,1920x1080 (default: 640x480, "
                    "1280x720, 1920x1080, 3840x2160; --quick: 640x480, 1920x1080)")
    ap.add_argument("--frames", type=int, default=None, help="frames per flight (default 300; --quick 60)")
    ap.add_argument("--repeats", type=int, default=None, help="runs per size and condition (default 3; "
                    "--quick 1)")
    ap.add_argument("--long-frames", type=int, default=None, help="frames of the long flight (default "
                    "10000; --quick 600; 0 = none)")
    ap.add_argument("--long-repeats", type=int, default=None, help="runs of the long flight (default 3: "
                    "the median slope; --quick 1)")
    ap.add_argument("--no-busy", action="store_true", help="quiet runs only")
    ap.add_argument("--out", type=Path, default=None, help="markdown file whose pipeline section is "
                    "replaced (default docs/benchmarks.md; none with --quick)")
    ap.add_argument("--memory-run", metavar="JSON", help=argparse.SUPPRESS)  # internal: one child run
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.memory_run else logging.INFO,
                        format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if args.memory_run:
        spec = json.loads(args.memory_run)
        blackout = spec.get("blackout")
        print(json.dumps(memory_run(int(spec["frames"]), list(spec["overrides"]),
                                    None if blackout is None else (int(blackout[0]), int(blackout[1])))))
        return 0
    sizes = parse_sizes(args.sizes) if args.sizes else ([(640, 480), (1920, 1080)] if args.quick else list(SIZES))
    args.frames = args.frames or (60 if args.quick else 300)
    args.repeats = args.repeats or (1 if args.quick else 3)
    args.long_repeats = args.long_repeats or (1 if args.quick else 3)
    if args.long_frames is None:
        args.long_frames = 600 if args.quick else 10_000
    if args.frames < 2 or args.repeats < 1 or args.long_repeats < 1 or (args.long_frames and args.long_frames < 100):
        print("error: --frames >= 2, --repeats >= 1, --long-repeats >= 1, --long-frames 0 or >= 100",
              file=sys.stderr)
        return 2
    out = args.out if args.out is not None else (None if args.quick else REPO / "docs" / "benchmarks.md")
    busy_runs = (False,) if args.no_busy else (False, True)
    start, load0 = time.perf_counter(), load_average()
    logging.getLogger("photomap").setLevel(logging.WARNING)
    try:
        log.info("OpenCV threads")
        threads = opencv_threads_table(not args.no_busy, repeats=5 if args.quick else 15)
        conds: list[Condition] = []
        live = None
        with tempfile.TemporaryDirectory(prefix="bench-pipeline-") as tmp:
            tmp_dir = Path(tmp)
            for size in sizes:
                log.info("simulating %d frames of %dx%d", args.frames, *size)
                sim = simulate_flight(tmp_dir / f"sim{size[0]}", n_frames=args.frames, size=size, seed=SEED,
                                      video_codec="mjpg")
                video = sim / "video.avi"
                for busy in busy_runs:
                    conds.append(measure(video, tmp_dir / f"out{size[0]}{busy}", size, busy, args.repeats, []))
                if size == (1920, 1080) and not args.no_busy:
                    if not args.quick:  # the thread budget's decision, measured in the product
                        conds.append(measure(video, tmp_dir / "out1080t1", size, True, args.repeats,
                                             ["mapping.opencv_threads=1"], "1 OpenCV thread"))
                        conds.append(measure(video, tmp_dir / "out1080every", size, True, args.repeats,
                                             ["mapping.paint=every"], "every frame painted whole"))
                    live = live_run(video, tmp_dir / "live", 30.0, True)
        memory = split = None
        if args.long_frames:
            log.info("long flight (%d frames of %dx%d)", args.long_frames, *LONG_SIZE)
            runs = []
            for _ in range(args.long_repeats):
                runs.append(memory_run_subprocess(args.long_frames, LONG_OVERRIDES))
                log.info("  peak RSS %.0f MB, slope %s KB/frame, %.0f fps", runs[-1]["peak_mb"],
                         runs[-1]["slope_kb_per_frame"], runs[-1]["fps"])
            memory = median_run(runs)
            n = min(SPLIT_FRAMES, args.long_frames)
            blackout = (SPLIT_BLACKOUT[0] * n // SPLIT_FRAMES, SPLIT_BLACKOUT[1] * n // SPLIT_FRAMES)
            log.info("split flight (%d frames, %d-%d black)", n, blackout[0], blackout[1] - 1)
            split = memory_run_subprocess(n, LONG_OVERRIDES, blackout)
            log.info("  %d joins, largest stall %.0f ms", split["loop_closure"].get("joins", 0),
                     max(split["stall_ms"].values(), default=0.0))
    except PhotomapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    body = render_report(args, threads, conds, live, memory, split, time.perf_counter() - start,
                         (load0, load_average()))
    print(body)
    if out is not None:
        replace_section(out, "pipeline", body)
        log.info("wrote the pipeline section of %s", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
