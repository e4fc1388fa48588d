"""Survey-size maps in bounded memory: peak RSS of a long georeferenced lawn-mower survey.

A lawn-mower survey (10,000 frames of 320x240 by default) is simulated with telemetry by
``photomap simulate`` over a large procedural terrain (12000 x 8000 terrain px at 0.1 m, the camera
at 30-34 m: about one terrain pixel per frame pixel, so the map is about as large as the terrain),
the speed chosen so that the strips cover it once. It is then mapped by ``photomap replay``'s
library function (:func:`photomap.cli.replay.replay`, with the .tlog: georeferenced, so the run
ends with mosaic.png, tiles/, the north-up COG map.tif and the track files) in a fresh process
whose RSS a thread samples every 50 ms (psutil; ``ru_maxrss`` as a cross-check of the peak
between samples). The time spent in each output (mosaic.png, tiles/, the GeoTIFF and track
files) is recorded, and the peak RSS inside each. The COG is then opened with rasterio: layout,
tiling, overviews.

    python tools/bench_survey.py [--frames N] [--terrain-size WxH] [--max-tiles N] [--work DIR]
                                 [--out FILE | --no-report] [--quick]

``--quick``: 1,500 frames over 4000 x 3000 (a smoke test). The full run (about 10-15 minutes on 2
cores) replaces the section between ``<!-- survey:start -->`` and ``<!-- survey:end -->`` of
``docs/benchmarks.md``. Needs psutil (``bench`` extra) and rasterio (``geo`` extra).

``--stills``: survey stills at survey speed instead. Lawn-mower surveys of JPEG stills with EXIF GPS
and DJI XMP (``photomap simulate --mode stills``): 64 stills of 640x512 in two strips joined by a
180-degree turn, the same with a featureless patch (4 blank stills: the map breaks and rejoins), and
57 stills of 2400x1800 in three strips; each mapped by ``photomap replay`` (georeferenced from the
stills' own telemetry) in a fresh process: wall and CPU time, the worker's loop-closure time,
segments, placed stills, the median distance of the frame centres from the photos' GPS. Replaces
the ``survey-stills`` section of ``docs/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import logging
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Iterator

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tools.report import replace_section  # noqa: E402

log = logging.getLogger("bench_survey")
MB = 1024.0 * 1024.0
TARGET_MB = 1024.0
SIZE = (320, 240)
FPS = 10.0
ALTITUDE = (30.0, 34.0)
HFOV = 60.0
GSD = 0.1  # procedural terrains


def survey_speed(terrain: tuple[int, int], frames: int) -> float:
    """Ground speed (m/s) at which ``frames`` frames fly the lawn-mower loop over ``terrain`` once
    (strip length times strips, as :func:`photomap.sim.flight.plan_flight` lays them out)."""
    from photomap.sim.flight import Camera, footprint_radius

    cam = Camera.from_hfov(SIZE[0], SIZE[1], HFOV)
    smax = ALTITUDE[1] / (cam.fx * GSD)
    radius = footprint_radius(cam, ALTITUDE[1] / GSD, 0.0) + 2.0 * max(smax, 1.0) + 4.0
    spacing = 0.7 * min(SIZE) * (sum(ALTITUDE) / 2) / (cam.fx * GSD)
    w, h = terrain[0] - 2 * radius, terrain[1] - 2 * radius
    if w < h:
        w, h = h, w
    strips = math.ceil(h / spacing) + 1
    strips += strips % 2
    length = strips * w + h + w
    return 0.97 * length / (frames - 1) * GSD * FPS


def simulate(work: Path, frames: int, terrain: tuple[int, int], seed: int) -> Path:
    """The survey's video + telemetry in ``work/sim`` (reused when already there)."""
    sim = work / "sim"
    meta = sim / "meta.yaml"
    if meta.is_file() and f"frames: {frames}\n" in meta.read_text() and f"width: {terrain[0]}\n" in meta.read_text():
        log.info("reusing the simulated survey in %s", sim)
        return sim
    speed = survey_speed(terrain, frames)
    cmd = [sys.executable, "-m", "photomap", "simulate", "--out", str(sim), "--terrain", "texture",
           "--set", f"simulate.terrain_size={terrain[0]}x{terrain[1]}", "--pattern", "lawnmower",
           "--frames", str(frames), "--size", f"{SIZE[0]}x{SIZE[1]}", "--fps", str(FPS),
           "--speed", f"{speed:.3f}", "--yaw-mode", "fixed", "--set", "simulate.yaw0=0",
           "--altitude", f"{ALTITUDE[0]}:{ALTITUDE[1]}", "--scale-rate", "0.01", "--codec", "mjpg",
           "--seed", str(seed), "-q"]
    log.info("simulating %d frames over %dx%d terrain px at %.1f m/s", frames, *terrain, speed)
    t = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=REPO)
    log.info("  simulated in %.0f s", time.perf_counter() - t)
    return sim


# --------------------------------------------------------------------------- the measured child
class RssSampler:
    def __init__(self, interval: float = 0.05) -> None:
        import psutil

        self._p = psutil.Process()
        self._interval = interval
        self._stop = threading.Event()
        self.samples: list[tuple[float, float]] = []
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append((time.monotonic(), self._p.memory_info().rss / MB))
            self._stop.wait(self._interval)

    def __enter__(self) -> RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def peak(self, t0: float = -math.inf, t1: float = math.inf) -> float | None:
        vals = [r for t, r in self.samples if t0 <= t <= t1]
        return max(vals) if vals else None


def measure(sim: Path, out: Path, overrides: list[str]) -> dict:
    """Map the survey in this process; RSS per phase."""
    import photomap.mapping.pipeline as pm
    import photomap.mapping.run_outputs as ro
    from photomap.mapping.painter import Painter
    from photomap.cli.replay import replay
    from photomap.config import load_config

    phases: list[tuple[str, float, float]] = []

    def timed(name, fn):
        def wrapper(*a, **k):
            t0 = time.monotonic()
            try:
                return fn(*a, **k)
            finally:
                phases.append((name, t0, time.monotonic()))
        return wrapper

    ro.write_png = timed("mosaic.png", ro.write_png)
    ro.write_tiles = timed("tiles/", ro.write_tiles)
    ro.write_main_cog = timed("map.tif (on its thread, beside mosaic.png and tiles/)", ro.write_main_cog)
    ro.write_geo_outputs = timed("track files", ro.write_geo_outputs)
    Painter.write_preview = timed("preview", Painter.write_preview)
    finish = pm.MappingPipeline.finish
    pm.MappingPipeline.finish = timed("outputs (all)", finish)
    cfg = load_config(overrides=overrides)
    video = next(p for p in sim.iterdir() if p.name.startswith("video."))
    with RssSampler() as rss:
        t0 = time.monotonic()
        base = rss._p.memory_info().rss / MB
        summary = replay(str(video), out, cfg, mavlink=str(sim / "telemetry.tlog"))
        t1 = time.monotonic()
    end_map = next(t for name, t, _ in phases if name == "outputs (all)")
    previews = [(a, b) for name, a, b in phases if name == "preview" and b <= end_map]
    phases = [p for p in phases if p[1] >= end_map and p[0] != "preview"]  # the end of the run
    entry = summary["mosaics"][0]
    x, y, w, h = entry["bounds"]
    result = {"overrides": overrides, "frames": summary["frames_in"], "registered": summary["registered"],
              "segments": summary["segments"], "wall_s": t1 - t0, "mapping_s": end_map - t0,
              "map_px": [w, h], "one_array_mb": w * h * 4 / MB, "png_size": entry["size"],
              "tiles": len(list((out / entry["tiles"]).glob("tile_*.png"))) if entry.get("tiles") else 0,
              "rss_start_mb": base, "peak_mapping_mb": rss.peak(t0, end_map),
              "peak_mb": rss.peak(), "ru_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
              "georeference": summary.get("georeference"), "exports": summary.get("exports"),
              "phases": [{"name": n, "s": b - a, "peak_mb": rss.peak(a, b)} for n, a, b in phases],
              "previews": {"count": len(previews), "s": sum(b - a for a, b in previews)}}
    return result


def measure_subprocess(sim: Path, out: Path, overrides: list[str]) -> dict:
    spec = json.dumps({"sim": str(sim), "out": str(out), "overrides": overrides})
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--measure", spec],
                          capture_output=True, text=True, cwd=REPO)
    if proc.returncode != 0:
        raise RuntimeError(f"the measured run failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def check_cog(path: Path) -> dict:
    import rasterio

    with rasterio.open(path) as src:
        return {"size": [src.width, src.height], "count": src.count, "crs": str(src.crs),
                "res_m": list(src.res), "blocks": list(src.block_shapes[0]), "overviews": src.overviews(1),
                "layout": src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT"), "compression": str(src.compression),
                "file_mb": path.stat().st_size / MB}


def report(args, r: dict, cog: dict, elapsed: float, load: tuple[float, float]) -> str:
    when = datetime.date.today().isoformat()
    w, h = r["map_px"]
    lines = ["## Survey-size maps", "",
             f"Written by `python -m tools.bench_survey{' --quick' if args.quick else ''}` on {when} (Python "
             f"{platform.python_version()}, {os.cpu_count()} cores, {elapsed:.0f} s; 1-minute load average "
             f"{load[0]:.1f} at the start and {load[1]:.1f} at the end: other processes shared the cores, "
             "times are lower bounds).", "",
             f"A georeferenced lawn-mower survey of {r['frames']} frames of {SIZE[0]}x{SIZE[1]} "
             f"(`photomap simulate --terrain texture --set simulate.terrain_size={args.terrain_size} "
             f"--pattern lawnmower --yaw-mode fixed --altitude {ALTITUDE[0]:g}:{ALTITUDE[1]:g} --fps {FPS:g} "
             "--codec mjpg`, with telemetry.tlog) mapped by `photomap replay` with "
             f"`{' '.join('--set ' + o for o in r['overrides']) or 'the default config'}` in a fresh process; "
             "RSS sampled every 50 ms (psutil).", "",
             "| | |", "|---|---|",
             f"| frames in / registered / segments | {r['frames']} / {r['registered']} / {r['segments']} |",
             f"| map | {w} x {h} px ({w * h / 1e6:.0f} Mpx; as one BGRA array {r['one_array_mb']:.0f} MB), "
             f"{r['tiles']} full-resolution tiles |",
             f"| mosaic.png | {r['png_size'][0]} x {r['png_size'][1]} px |",
             f"| map.tif | {cog.get('size', ['-', '-'])[0]} x {cog.get('size', ['-', '-'])[1]} px, "
             f"{cog.get('res_m', [0])[0]:.3f} m, layout {cog.get('layout')}, {cog.get('blocks')} blocks, "
             f"overviews {cog.get('overviews')}, {cog.get('compression')}, {cog.get('file_mb', 0):.0f} MB |",
             f"| wall time (mapping) | {r['wall_s']:.0f} s ({r['mapping_s']:.0f} s, "
             f"{r['frames'] / r['mapping_s']:.0f} fps) |",
             f"| RSS after imports | {r['rss_start_mb']:.0f} MB |",
             f"| **peak RSS** (sampled / ru_maxrss) | **{r['peak_mb']:.0f} MB** / {r['ru_maxrss_mb']:.0f} MB "
             f"(target < {TARGET_MB:.0f} MB: {'yes' if r['ru_maxrss_mb'] < TARGET_MB else '**no**'}) |",
             f"| peak RSS while mapping | {r['peak_mapping_mb']:.0f} MB |"]
    for p in r["phases"]:
        lines.append(f"| peak RSS in {p['name']} | {p['peak_mb'] or 0:.0f} MB ({p['s']:.1f} s) |")
    pv = r["previews"]
    lines.append(f"| checkpoint previews (preview.png, {pv['count']} while mapping; their thumbnails and encoding in "
                 f"the background) | {pv['s']:.1f} s of the worker in all ({100 * pv['s'] / r['mapping_s']:.1f} % "
                 "of the mapping time) |")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- stills at survey speed
STILLS = {  # name -> (simulate flags, stills made blank)
    "64 x 640x512, 2 strips": (["--strips", "2", "--stills-per-strip", "32", "--size", "640x512",
                                "--set", "simulate.terrain_size=7800x2400", "--side-overlap", "0.6",
                                "--seed", "2"], []),
    "64 x 640x512, 2 strips, 4 blank": (["--strips", "2", "--stills-per-strip", "32", "--size", "640x512",
                                         "--set", "simulate.terrain_size=7800x2400", "--side-overlap", "0.6",
                                         "--seed", "2"], [20, 21, 22, 23]),
    "57 x 2400x1800, 3 strips": (["--strips", "3", "--stills-per-strip", "19", "--size", "2400x1800",
                                  "--set", "simulate.terrain_size=5000x2400", "--seed", "4"], []),
}


def blank_stills(folder: Path, frames: list[int]) -> None:
    """Make stills ``frames`` one grey level, their EXIF and XMP kept (a featureless patch)."""
    import numpy as np
    from PIL import Image

    for k in frames:
        path = folder / f"{k:06d}.jpg"
        with Image.open(path) as im:
            exif, xmp, size = im.getexif(), im.info.get("xmp"), im.size
        Image.fromarray(np.full((size[1], size[0], 3), 118, np.uint8)).save(path, "JPEG", exif=exif, xmp=xmp)


def measure_stills(stills: Path, out: Path) -> dict:
    """Map a folder of stills in this process: times, segments, distance from the photos' GPS."""
    import numpy as np

    from photomap.cli.replay import replay
    from photomap.config import load_config
    from photomap.drivers.exif import read_still_metadata
    from photomap.geo.georef import enu_from_latlon
    from photomap.io.trajectory_files import read_trajectory_csv

    t0, c0 = time.perf_counter(), time.process_time()
    summary = replay(str(stills), out, load_config())
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    files = sorted(stills.glob("*.jpg"))
    errors = []
    for r in read_trajectory_csv(out / "trajectory.csv"):
        if r.glued and "lat" in r.extra:
            m = read_still_metadata(files[r.frame])
            e, n = enu_from_latlon(np.array([r.extra["lat"]]), np.array([r.extra["lon"]]), m.lat, m.lon)
            errors.append(math.hypot(float(e[0]), float(n[0])))
    timing = summary["timing_ms"]
    return {"stills": summary["frames_in"], "registered": summary["registered"], "segments": summary["segments"],
            "wall_s": wall, "cpu_s": cpu, "loop_closure_s": timing.get("loop_closure", {}).get("total_s", 0.0),
            "status": summary["telemetry"]["status"], "placed": (summary["telemetry"].get("placed") or {}).get("placed"),
            "joins": summary.get("loop_closure", {}).get("joins"),
            "median_gps_m": float(np.median(errors)) if errors else None}


def host_reference_s() -> float:
    """Seconds of a fixed single-thread workload (JPEG encode and decode of one synthetic
    2400x1800 frame, deflate of its pixels), the median of 5: the same work on any host, so that
    wall times measured on different hosts (or the same host on another day) can be compared."""
    import zlib

    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    image = cv2.resize(rng.integers(0, 256, (180, 240, 3), dtype=np.uint8), (2400, 1800),
                       interpolation=cv2.INTER_CUBIC)
    cv2.setNumThreads(1)
    times = []
    for _ in range(5):
        t0 = time.process_time()
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
        cv2.imdecode(buf, cv2.IMREAD_COLOR)
        zlib.compress(image.tobytes(), 1)
        times.append(time.process_time() - t0)
    return float(np.median(times))


def _measured_stills(stills: Path, out: Path, package: Path | None = None) -> dict:
    """:func:`measure_stills` in a fresh process; ``package``: a folder holding the ``photomap``
    package to measure instead of the installed one (``--against``)."""
    env = dict(os.environ)
    if package is not None:
        env["PYTHONPATH"] = str(package)
    spec = json.dumps({"stills": str(stills), "out": str(out)})
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--measure-stills", spec],
                          capture_output=True, text=True, cwd=REPO, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"the measured run failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


@contextlib.contextmanager
def _package_at(rev: str, work: Path) -> Iterator[Path]:
    """A folder whose ``photomap`` is the package of git revision ``rev`` (a detached worktree)."""
    tree = work / "against"
    subprocess.run(["git", "worktree", "add", "--detach", "-q", str(tree), rev], check=True, cwd=REPO)
    try:
        (work / "pkg").mkdir()
        (work / "pkg" / "photomap").symlink_to(tree / "service")
        yield work / "pkg"
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=REPO)


def run_stills(work: Path, rounds: int = 1, against: str | None = None) -> list[dict]:
    """Each survey simulated once and mapped ``rounds`` times (medians), alternating with the
    package of git revision ``against`` when given (the same host, the same minutes)."""
    results = []
    with contextlib.ExitStack() as stack:
        package = stack.enter_context(_package_at(against, work)) if against else None
        for name, (flags, blank) in STILLS.items():
            sim = work / f"sim{len(results)}"
            cmd = [sys.executable, "-m", "photomap", "simulate", "--out", str(sim), "--mode", "stills", "--terrain",
                   "texture", "--altitude", "60:60", *flags, "-q"]
            subprocess.run(cmd, check=True, cwd=REPO)
            blank_stills(sim / "stills", blank)
            runs, theirs = [], []
            for _ in range(rounds):
                runs.append(_measured_stills(sim / "stills", work / f"run{len(results)}"))
                if package is not None:
                    theirs.append(_measured_stills(sim / "stills", work / f"against{len(results)}", package))
            row = dict(runs[-1], wall_s=statistics.median(r["wall_s"] for r in runs),
                       cpu_s=statistics.median(r["cpu_s"] for r in runs), case=name)
            if theirs:
                row["against_wall_s"] = statistics.median(r["wall_s"] for r in theirs)
                row["against_cpu_s"] = statistics.median(r["cpu_s"] for r in theirs)
            results.append(row)
            log.info("%s: %.1f s wall, %.1f s CPU%s", name, row["wall_s"], row["cpu_s"],
                     f" ({against}: {row['against_wall_s']:.1f} s, {row['against_cpu_s']:.1f} s)" if theirs else "")
    return results


def report_stills(results: list[dict], elapsed: float, load: tuple[float, float], reference: tuple[float, float],
                  rounds: int = 1, against: str | None = None) -> str:
    when = datetime.date.today().isoformat()
    flags = (f" --rounds {rounds}" if rounds > 1 else "") + (f" --against {against}" if against else "")
    lines = ["## Survey stills at survey speed", "",
             f"Written by `python -m tools.bench_survey --stills{flags}` on {when} (Python {platform.python_version()}, "
             f"{os.cpu_count()} cores, {elapsed:.0f} s; 1-minute load average {load[0]:.1f} at the start and "
             f"{load[1]:.1f} at the end: other processes shared the cores, wall times are upper bounds of a "
             "calm machine's). Simulated lawn-mower surveys of JPEG stills with EXIF GPS and DJI XMP "
             "(`photomap simulate --mode stills --terrain texture --altitude 60:60`), mapped by "
             "`photomap replay` from their own telemetry in a fresh process (target: <= 10 s each). "
             f"The host's speed: {1000 * reference[0]:.0f} ms before and {1000 * reference[1]:.0f} ms after "
             "for a fixed single-thread workload (`host_reference_s`: JPEG encode and decode of a 2400x1800 "
             "frame and deflate of its pixels; lower is faster), to compare runs on different hosts."
             + (f" Wall and CPU s are medians of {rounds} runs." if rounds > 1 else "")
             + (f" Each run alternates with one of the code at `{against}` (git revision, a worktree) on the "
                "same stills: its wall s beside, and the ratio (below 1: this code faster)." if against else ""), "",
             "| survey | stills / placed / segments | wall s | CPU s |" + (f" `{against}` wall s (ratio) |" if against else "")
             + " loop closure s (worker) | joins | telemetry placed | telemetry | frame centres vs photo GPS (median) |",
             "|---|---|---|---|" + ("---|" if against else "") + "---|---|---|---|---|"]
    for r in results:
        gps = f"{r['median_gps_m']:.2f} m" if r["median_gps_m"] is not None else "-"
        theirs = f" {r['against_wall_s']:.1f} ({r['wall_s'] / r['against_wall_s']:.2f}) |" if against else ""
        lines.append(f"| {r['case']} | {r['stills']} / {r['registered']} / {r['segments']} | {r['wall_s']:.1f} | "
                     f"{r['cpu_s']:.1f} |{theirs} {r['loop_closure_s']:.2f} | {r['joins']} | {r['placed'] or 0} | "
                     f"{r['status']} | {gps} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=None, help="frames of the survey (default 10000)")
    ap.add_argument("--terrain-size", default=None, help="WxH terrain px (default 12000x8000)")
    ap.add_argument("--max-tiles", type=int, default=256, help="mosaic.max_tiles_in_memory (default 256)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--work", type=Path, default=None, help="keep the simulation and the run here")
    ap.add_argument("--quick", action="store_true", help="1500 frames over 4000x3000 (smoke test)")
    ap.add_argument("--out", type=Path, default=None, help="markdown file whose survey section is replaced "
                    "(default docs/benchmarks.md; none with --quick)")
    ap.add_argument("--stills", action="store_true", help="survey stills at survey speed (section survey-stills)")
    ap.add_argument("--rounds", type=int, default=1, help="--stills: runs of each survey (medians; default 1)")
    ap.add_argument("--against", metavar="REV", help="--stills: alternate each run with the code of git revision "
                    "REV (a temporary worktree) and report the ratio")
    ap.add_argument("--measure", metavar="JSON", help=argparse.SUPPRESS)
    ap.add_argument("--measure-stills", metavar="JSON", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.measure or args.measure_stills else logging.INFO,
                        format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if args.measure:
        spec = json.loads(args.measure)
        print(json.dumps(measure(Path(spec["sim"]), Path(spec["out"]), spec["overrides"])))
        return 0
    if args.measure_stills:
        spec = json.loads(args.measure_stills)
        print(json.dumps(measure_stills(Path(spec["stills"]), Path(spec["out"]))))
        return 0
    if args.stills:
        start, load0, ref0 = time.perf_counter(), os.getloadavg()[0], host_reference_s()
        with tempfile.TemporaryDirectory(prefix="bench-stills-") as tmp:
            work = args.work or Path(tmp)
            work.mkdir(parents=True, exist_ok=True)
            results = run_stills(work, max(1, args.rounds), args.against)
            body = report_stills(results, time.perf_counter() - start, (load0, os.getloadavg()[0]),
                                 (ref0, host_reference_s()), max(1, args.rounds), args.against)
        print(body)
        out_md = args.out if args.out is not None else REPO / "docs" / "benchmarks.md"
        replace_section(out_md, "survey-stills", body)
        log.info("wrote the survey-stills section of %s", out_md)
        return 0
    args.frames = args.frames or (1500 if args.quick else 10_000)
    args.terrain_size = args.terrain_size or ("4000x3000" if args.quick else "12000x8000")
    terrain = tuple(int(v) for v in args.terrain_size.lower().split("x"))
    out_md = args.out if args.out is not None else (None if args.quick else REPO / "docs" / "benchmarks.md")
    start, load0 = time.perf_counter(), os.getloadavg()[0]
    tmp = None
    work = args.work
    if work is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench-survey-")
        work = Path(tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    try:
        sim = simulate(work, args.frames, terrain, args.seed)
        overrides = [f"mosaic.max_tiles_in_memory={args.max_tiles}"]
        run = work / "run"
        log.info("mapping the survey (%s)", " ".join(overrides))
        r = measure_subprocess(sim, run, overrides)
        cog = check_cog(run / "map.tif") if (run / "map.tif").is_file() else {}
        log.info("peak RSS %.0f MB (ru_maxrss %.0f MB); map %s px", r["peak_mb"], r["ru_maxrss_mb"], r["map_px"])
        body = report(args, r, cog, time.perf_counter() - start, (load0, os.getloadavg()[0]))
        print(body)
        print(json.dumps({**r, "cog": cog}, indent=1, default=str), file=sys.stderr)
        if out_md is not None:
            replace_section(out_md, "survey", body)
            log.info("wrote the survey section of %s", out_md)
    finally:
        if tmp is not None:
            tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
