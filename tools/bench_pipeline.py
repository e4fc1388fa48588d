"""Pipeline benchmark: replay throughput (where the worker's time goes) and peak memory of long flights.

Part (a), in one process: a 640x480 flight is simulated into a temporary folder (``video.mp4``),
then the same file is decoded alone (:class:`photomap.drivers.video.VideoFileSource`, the upper bound) and
mapped by ``photomap replay`` (:func:`photomap.cli.replay.replay`) with the default config and with
``mosaic.blend=feather``. The worker's time is split into registration (``Registrar.prepare`` of
the new frame, ``Registrar.register`` against the reference), gluing into the map
(``TiledMosaic.add``) and the rest (resize to the working size, bookkeeping); decoding runs in its
own thread beside the worker.

Part (b): a long lawn-mower flight (10,000 frames by default) is rendered frame by frame from
:mod:`photomap.sim.flight` into an in-memory frame source (it never holds more than the frame being
rendered; the pipeline's prefetch queue holds 8) and mapped by :class:`MappingPipeline`, with and
without ``mosaic.max_tiles_in_memory``, each configuration in a fresh process so that one run's
freed memory does not inflate the next one's peak. A thread samples the process RSS (psutil)
every 50 ms.

    python -m tools.bench_pipeline [--quick] [--frames N] [--long-frames N] [--max-tiles N] [--out FILE]

``--quick`` is a smoke test (< 1 min) that only prints unless ``--out`` is given; the full run
(about 10 minutes on 2 cores) replaces the section between ``<!-- pipeline:start -->`` and
``<!-- pipeline:end -->`` of ``docs/benchmarks.md`` (appended at the end when absent) and leaves
the rest of that file alone. Needs ``psutil`` (the ``bench`` extra).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import logging
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

import photomap.mapping.pipeline as pipeline_module
from photomap.drivers.frames import CaptureStats, Frame, SourceBase
from photomap.drivers.video import VideoFileSource
from photomap.config import load_config
from photomap.errors import PhotomapError
from photomap.sim.flight import Camera, Effects, Motion, Truth, build_pyramid, iter_frames, plan_flight
from photomap.cli.replay import replay
from photomap.sim.simulate import simulate_flight
from photomap.sim.terrain import TERRAIN_GSD, TERRAIN_ZOOM, load_terrain, valid_mask
from tools.report import replace_section

log = logging.getLogger("bench_pipeline")

REPO = Path(__file__).resolve().parents[1]
SIZE = (640, 480)  # (w, h) of every benchmark frame
SEED = 3
TARGET_FPS = 50.0
TARGET_RSS_MB = 500.0
MB = 1024.0 * 1024.0

# The long flight: lawn-mower strips over the bundled orthophoto (zoomed 4x: 4212x3240 terrain px,
# 0.1125 m/px) at 8 m/s, 10 frames per second (7 terrain px per frame), image up along the track.
LONG_TERRAIN = "aukerman"
LONG_FPS = 10.0
LONG_MOTION = dict(pattern="lawnmower", speed=8.0, yaw_mode="heading", yaw_rate=30.0,
                   altitude=(55.0, 65.0), scale_rate=0.02)


# --------------------------------------------------------------------------- (a) throughput

@dataclass
class StageTimes:
    """Seconds spent in the worker's stages (accumulated by the timed subclasses)."""

    prepare: float = 0.0
    register: float = 0.0
    mosaic: float = 0.0


@contextlib.contextmanager
def timed_stages(acc: StageTimes) -> Iterator[None]:
    """Make :mod:`photomap.mapping.pipeline` build timed subclasses of ``Registrar`` and ``TiledMosaic``
    while the block runs (the pipeline itself is unchanged)."""
    registrar, mosaic = pipeline_module.Registrar, pipeline_module.TiledMosaic

    class TimedRegistrar(registrar):
        def prepare(self, frame):
            t = time.perf_counter()
            try:
                return super().prepare(frame)
            finally:
                acc.prepare += time.perf_counter() - t

        def register(self, a, b, prior=None):
            t = time.perf_counter()
            try:
                return super().register(a, b, prior)
            finally:
                acc.register += time.perf_counter() - t

    class TimedMosaic(mosaic):
        def add(self, frame, M, mask=None):
            t = time.perf_counter()
            try:
                return super().add(frame, M, mask)
            finally:
                acc.mosaic += time.perf_counter() - t

    pipeline_module.Registrar, pipeline_module.TiledMosaic = TimedRegistrar, TimedMosaic
    try:
        yield
    finally:
        pipeline_module.Registrar, pipeline_module.TiledMosaic = registrar, mosaic


def decode_only(video: Path) -> tuple[int, float]:
    """Frames and seconds to decode ``video`` with :class:`VideoFileSource` (nothing else)."""
    t = time.perf_counter()
    with VideoFileSource(video) as source:
        n = sum(1 for _ in source)
    return n, time.perf_counter() - t


@dataclass
class ReplayResult:
    name: str
    summary: dict
    wall_s: float
    stages: StageTimes


def time_replay(video: Path, out_dir: Path, name: str, overrides: list[str]) -> ReplayResult:
    """``photomap replay`` of ``video`` with the config overrides, timed from call to return
    (source opening, mapping, writing the outputs)."""
    cfg = load_config(overrides=overrides)
    stages = StageTimes()
    with timed_stages(stages):
        t = time.perf_counter()
        summary = replay(str(video), out_dir, cfg)
        wall = time.perf_counter() - t
    return ReplayResult(name, summary, wall, stages)


def throughput_table(n_decoded: int, decode_s: float, results: list[ReplayResult]) -> list[str]:
    decode_fps = n_decoded / decode_s
    lines = ["| run | frames | registered | segments | wall s | fps | of decode-only | target >= 50 fps |",
             "|---|---|---|---|---|---|---|---|",
             f"| decode only (VideoFileSource) | {n_decoded} | - | - | {decode_s:.2f} | {decode_fps:.0f} | 1 | |"]
    for r in results:
        s = r.summary
        fps = s["frames_in"] / r.wall_s
        lines.append(f"| replay, {r.name} | {s['frames_in']} | {s['registered']} | {s['segments']} | "
                     f"{r.wall_s:.2f} | {fps:.1f} | {fps / decode_fps:.3f} | "
                     f"{'yes' if fps >= TARGET_FPS else '**no**'} |")
    return lines


def stages_table(n_decoded: int, decode_s: float, results: list[ReplayResult]) -> list[str]:
    lines = ["| run | decode (own thread) | prepare | register | mosaic | resize + rest | worker total | "
             "outside the worker |", "|---|---|---|---|---|---|---|---|"]
    for r in results:
        n = r.summary["frames_in"]
        worker = r.summary["ms_per_frame"]
        prep, reg, mos = (1000.0 * v / n for v in (r.stages.prepare, r.stages.register, r.stages.mosaic))
        outside = 1000.0 * r.wall_s / n - worker
        lines.append(f"| {r.name} | {1000.0 * decode_s / n_decoded:.2f} | {prep:.2f} | {reg:.2f} | {mos:.2f} | "
                     f"{worker - prep - reg - mos:.2f} | {worker:.2f} | {outside:.2f} |")
    return lines


# --------------------------------------------------------------------------- (b) memory

class SimulatedSource(SourceBase):
    """Frames of a planned flight, rendered one at a time as they are consumed (replay: never drops).

    ``Frame.t`` is the flight time ``truth.t`` (seconds from frame 0).
    """

    live = False

    def __init__(self, terrain: np.ndarray, truth: Truth, camera: Camera, effects: Effects | None = None,
                 seed: int = 0) -> None:
        self.stats = CaptureStats()
        self._terrain, self._truth, self._camera = terrain, truth, camera
        self._effects = effects or Effects()
        self._seed = seed
        self._pyramid = build_pyramid(terrain, float(truth.scale.max()) * 1.2)
        self._closed = False

    def __len__(self) -> int:
        return len(self._truth)

    def __iter__(self) -> Iterator[Frame]:
        frames = iter_frames(self._terrain, self._truth, self._camera, self._effects, self._seed,
                             pyramid=self._pyramid)
        for k, image in enumerate(frames):
            if self._closed:
                break
            self.stats.read += 1
            yield Frame(k, float(self._truth.t[k]), image, "simulated")

    def close(self) -> None:
        self._closed = True


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


def long_flight(n_frames: int, seed: int = SEED) -> tuple[np.ndarray, Truth, Camera]:
    """Terrain, truth and camera of the long lawn-mower flight."""
    zoom = TERRAIN_ZOOM[LONG_TERRAIN]
    terrain = load_terrain(LONG_TERRAIN, zoom=zoom)
    camera = Camera.from_hfov(SIZE[0], SIZE[1], 60.0)
    truth = plan_flight(valid_mask(terrain), n_frames, camera, LONG_FPS, TERRAIN_GSD[LONG_TERRAIN] / zoom,
                        Motion(**LONG_MOTION), seed)
    return terrain, truth, camera


def memory_run(n_frames: int, overrides: list[str]) -> dict:
    """Map the long flight in this process while sampling RSS; returns the measurements (MB, s)."""
    import psutil

    rss0 = psutil.Process().memory_info().rss / MB
    terrain, truth, camera = long_flight(n_frames)
    source = SimulatedSource(terrain, truth, camera, seed=SEED)
    cfg = load_config(overrides=overrides)
    with tempfile.TemporaryDirectory(prefix="bench-pipeline-") as tmp, RssSampler() as sampler:
        before = sampler.rss_mb()

        def on_frame(event) -> None:
            sampler.frames_done += 1

        pipe = pipeline_module.MappingPipeline(source, cfg, tmp, sinks=[on_frame], input_name="simulated")
        t = time.perf_counter()
        summary = pipe.run()
        wall = time.perf_counter() - t
        tiles = sum(len(m.tiles()) for m in pipe.mosaics.values())
        in_memory = sum(m.tiles_in_memory for m in pipe.mosaics.values())
    mapping = [rss for _, rss, done in sampler.samples if done < n_frames]
    # RSS when 10 %, 50 % and 100 % of the frames were mapped: a plateau or a leak?
    at = {f"rss_at_{pct}_mb": next((rss for _, rss, done in sampler.samples if done >= n_frames * pct / 100),
                                   None) for pct in (10, 50, 100)}
    return {"overrides": overrides, "frames": summary["frames_in"], "registered": summary["registered"],
            "segments": summary["segments"], "wall_s": wall, "fps": summary["frames_in"] / wall,
            "rss_start_mb": rss0, "rss_before_mb": before,
            "peak_mapping_mb": max(mapping, default=before),
            "peak_mb": max(rss for _, rss, _ in sampler.samples),
            "tiles": tiles, "tiles_in_memory": in_memory, "samples": len(sampler.samples), **at}


def memory_run_subprocess(n_frames: int, overrides: list[str]) -> dict:
    """:func:`memory_run` in a fresh interpreter (clean RSS)."""
    spec = json.dumps({"frames": n_frames, "overrides": overrides})
    cmd = [sys.executable, str(Path(__file__).resolve()), "--memory-run", spec]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    if proc.returncode != 0:
        raise RuntimeError(f"memory run {overrides} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def memory_table(runs: list[tuple[str, dict]]) -> list[str]:
    lines = ["| run | frames | registered | segments | tiles (in memory at end) | fps | RSS after imports | "
             "RSS before | RSS at 10/50/100 % of the frames | peak RSS mapping | peak RSS incl. outputs | "
             "growth | target < 500 MB |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in runs:
        at = "/".join("-" if r[f"rss_at_{p}_mb"] is None else f"{r[f'rss_at_{p}_mb']:.0f}" for p in (10, 50, 100))
        lines.append(f"| {name} | {r['frames']} | {r['registered']} | {r['segments']} | {r['tiles']} "
                     f"({r['tiles_in_memory']}) | {r['fps']:.0f} | {r['rss_start_mb']:.0f} MB | "
                     f"{r['rss_before_mb']:.0f} MB | {at} MB | "
                     f"{r['peak_mapping_mb']:.0f} MB | {r['peak_mb']:.0f} MB | "
                     f"{r['peak_mb'] - r['rss_before_mb']:+.0f} MB | "
                     f"{'yes' if r['peak_mb'] < TARGET_RSS_MB else '**no**'} |")
    return lines


# --------------------------------------------------------------------------- report

def render_report(args: argparse.Namespace, n_decoded: int, decode_s: float, replays: list[ReplayResult],
                  memory: list[tuple[str, dict]], elapsed: float, load: tuple[float, float]) -> str:
    when = datetime.date.today().isoformat()
    lines = ["## Pipeline", "",
             f"Written by `tools/bench_pipeline.py{' --quick' if args.quick else ''}` on {when} "
             f"(Python {platform.python_version()}, OpenCV {cv2.__version__}, numpy {np.__version__}, "
             f"{os.cpu_count()} cores, {cv2.getNumThreads()} OpenCV threads, {elapsed:.0f} s; 1-minute load "
             f"average {load[0]:.1f} at the start and {load[1]:.1f} at the end: above 0 means other "
             "processes shared the cores and the speeds are lower bounds). Rerun it after a change to the "
             "pipeline, the registration or the map: `python -m tools.bench_pipeline` (about 10 minutes "
             "on 2 cores); it rewrites only this section.", "",
             "### Replay throughput", "",
             f"A simulated {SIZE[0]}x{SIZE[1]} flight of {args.frames} frames (`simulate_flight`, aukerman, "
             f"random pattern, 8 m/s at 30 fps, seed {SEED}) decoded alone and mapped by `photomap replay` "
             "(default config: working size 320, overwrite blend) in one process. Wall time from the call "
             "to the outputs written.", ""]
    lines += throughput_table(n_decoded, decode_s, replays)
    lines += ["", "Where the time goes, ms per frame: decoding runs in its own thread beside the worker; "
              "*prepare* is the new frame's spectra (`Registrar.prepare`), *register* the registration "
              "against the reference (`Registrar.register`, with retries), *mosaic* `TiledMosaic.add`; "
              "*resize + rest* is the worker's remainder (downscale to the working size, bookkeeping); "
              "*outside the worker* is wall time per frame not spent in the worker (start-up, waiting, "
              "writing the outputs at the end).", ""]
    lines += stages_table(n_decoded, decode_s, replays)
    lines += ["", "### Peak memory of a long flight", "",
              f"{args.long_frames} frames of {SIZE[0]}x{SIZE[1]} rendered one by one (`plan_flight` + "
              "`iter_frames`) into an in-memory frame source: lawn-mower strips over the bundled "
              f"orthophoto (4212x3240 terrain px at 0.1125 m/px), {LONG_MOTION['speed']:g} m/s at "
              f"{LONG_FPS:g} fps (7 terrain px per frame) around a closed loop of about 1,700 frames, flown "
              "again and again (with a tile cap, revisited tiles are read back from the tile store). Each "
              "run in a fresh "
              "process; RSS sampled every 50 ms (psutil). *RSS after imports*: Python and the packages; "
              "*RSS before*: also the terrain, its pyramid and the planned flight (the benchmark's "
              "frame generator, not the service); *peak RSS mapping*: the peak until the "
              "last frame; *incl. outputs*: also while writing mosaic.png, the tiles and the "
              "trajectory; *growth*: peak minus RSS before.", ""]
    lines += memory_table(memory)
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- main

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small smoke test (< 1 min); prints only unless "
                    "--out is given")
    ap.add_argument("--frames", type=int, default=None, help="frames of the replay flight (default 600; "
                    "--quick: 150)")
    ap.add_argument("--long-frames", type=int, default=None, help="frames of the long flight (default "
                    "10000; --quick: 600)")
    ap.add_argument("--max-tiles", type=int, default=64, help="mosaic.max_tiles_in_memory of the capped "
                    "runs (default 64: the long flight's map has about 100 tiles, a smaller cap spills)")
    ap.add_argument("--out", type=Path, default=None, help="markdown file whose pipeline section is "
                    "replaced (default docs/benchmarks.md; none with --quick)")
    ap.add_argument("--memory-run", metavar="JSON", help=argparse.SUPPRESS)  # internal: one child run
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.memory_run else logging.INFO,
                        format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if args.memory_run:
        spec = json.loads(args.memory_run)
        print(json.dumps(memory_run(int(spec["frames"]), list(spec["overrides"]))))
        return 0
    args.frames = args.frames or (150 if args.quick else 600)
    args.long_frames = args.long_frames or (600 if args.quick else 10_000)
    if args.frames < 2 or args.long_frames < 2 or args.max_tiles < 1:
        print("error: --frames and --long-frames must be at least 2, --max-tiles at least 1", file=sys.stderr)
        return 2
    out = args.out if args.out is not None else (None if args.quick else REPO / "docs" / "benchmarks.md")
    start, load0 = time.perf_counter(), os.getloadavg()[0]
    try:
        with tempfile.TemporaryDirectory(prefix="bench-pipeline-") as tmp:
            tmp_dir = Path(tmp)
            log.info("simulating %d frames of %dx%d", args.frames, *SIZE)
            sim = simulate_flight(tmp_dir / "sim", n_frames=args.frames, size=SIZE, seed=SEED)
            video = sim / "video.mp4"
            n_decoded, decode_s = decode_only(video)
            log.info("decode only: %d frames, %.0f fps", n_decoded, n_decoded / decode_s)
            replays = []
            for name, overrides in (("default (overwrite)", []), ("feather", ["mosaic.blend=feather"])):
                r = time_replay(video, tmp_dir / f"out-{len(replays)}", name, overrides)
                log.info("replay %s: %.1f fps", name, r.summary["frames_in"] / r.wall_s)
                replays.append(r)
        memory = []
        cap = f"mosaic.max_tiles_in_memory={args.max_tiles}"
        for name, overrides in (("overwrite, no tile cap", []),
                                (f"overwrite, {args.max_tiles} tiles", [cap]),
                                ("feather, no tile cap", ["mosaic.blend=feather"]),
                                (f"feather, {args.max_tiles} tiles", ["mosaic.blend=feather", cap])):
            log.info("long flight (%d frames), %s", args.long_frames, name)
            r = memory_run_subprocess(args.long_frames, overrides)
            log.info("  peak RSS %.0f MB, %.0f fps", r["peak_mb"], r["fps"])
            memory.append((name, r))
    except PhotomapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    body = render_report(args, n_decoded, decode_s, replays, memory, time.perf_counter() - start,
                         (load0, os.getloadavg()[0]))
    print(body)
    if out is not None:
        replace_section(out, "pipeline", body)
        log.info("wrote the pipeline section of %s", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
