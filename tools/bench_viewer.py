"""Viewer benchmark: what the rerun operator view costs in bytes and CPU.

A 640x480 flight over the bundled aukerman terrain is simulated in memory
(:func:`photomap.sim.flight.simulate_sequence`), then mapped by :class:`MappingPipeline` from a source
that delivers the frames at the flight's frame rate (as a camera would, so that the viewer's
wall-clock rate limits apply as in a live flight): without a viewer (twice, before and after), and
with ``--viewer save=...`` in the default and a lean (low-bandwidth) configuration (the bytes a
connected viewer receives are the bytes of the recording).

Printed per run: bytes of the recording per minute of flight, JPEG bytes, tiles and camera images
logged, viewer items dropped, the worker's time (``RunStats.worker_s``), the time spent in the
viewer callback inside the worker, the viewer thread's CPU time, and the process CPU time, whose
difference to the run without a viewer includes rerun's own encoder and sink threads.
Target: viewer CPU < 15 % of the worker's time.

    python -m tools.bench_viewer [--frames 600] [--fps 30] [--as-fast-as-possible]
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path

from photomap.drivers.frames import CaptureStats, Frame
from photomap.config import load_config
from photomap.sim.flight import simulate_sequence
from photomap.mapping.pipeline import MappingPipeline
from photomap.sim.terrain import TERRAIN_GSD, TERRAIN_ZOOM, load_terrain, valid_mask
from photomap.live.viewer import Viewer


class PacedSource:
    """Replays in-memory frames at ``fps`` (0 = as fast as the worker takes them); never drops."""

    live = False

    def __init__(self, frames: list[Frame], fps: float) -> None:
        self.frames, self.fps = frames, fps
        self.stats = CaptureStats()
        self._closed = False

    def __iter__(self):
        start = time.monotonic()
        for frame in self.frames:
            if self._closed:
                return
            if self.fps > 0:
                time.sleep(max(0.0, start + frame.index / self.fps - time.monotonic()))
            self.stats.read += 1
            yield frame

    def close(self) -> None:
        self._closed = True


LEAN = {"camera_hz": 1.0, "camera_px": 320, "tile_hz": 1.0, "jpeg_quality": 60}


def run_once(frames: list[Frame], fps: float, folder: Path, viewer: dict | None) -> dict:
    """Map ``frames``; ``viewer``: None (no viewer) or overrides of the ``viewer`` config section
    for a run saved to ``folder/view.rrd``."""
    cfg = load_config()
    view = None
    if viewer is not None:
        view = Viewer.from_config(cfg.updated({"viewer": viewer}).viewer, f"save={folder / 'view.rrd'}")
    pipeline = MappingPipeline(PacedSource(frames, fps), cfg, folder / "out",
                               sinks=[view.on_frame] if view else ())
    cpu0, wall0 = time.process_time(), time.monotonic()
    pipeline.run()
    if view:
        view.close()
    out = {"wall_s": time.monotonic() - wall0, "cpu_s": time.process_time() - cpu0,
           "worker_s": pipeline.stats.worker_s, "frames": pipeline.stats.frames_in,
           "registered": pipeline.stats.registered}
    if view:
        s = view.stats
        out.update(rrd_bytes=(folder / "view.rrd").stat().st_size, jpeg_bytes=s.jpeg_bytes,
                   tiles=s.tiles, images=s.images, dropped=s.dropped, callback_s=s.callback_s,
                   thread_cpu_s=s.thread_cpu_s)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=600, help="frames of the flight (default 600)")
    ap.add_argument("--fps", type=float, default=30.0, help="frame rate of the flight (default 30)")
    ap.add_argument("--as-fast-as-possible", action="store_true",
                    help="feed frames as fast as the worker takes them (rate limits then see a faster clock)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    t0 = time.monotonic()
    terrain = load_terrain("aukerman", zoom=TERRAIN_ZOOM["aukerman"])
    seq = simulate_sequence(terrain, args.frames, (480, 640), args.seed, valid=valid_mask(terrain),
                            fps=args.fps, gsd=TERRAIN_GSD["aukerman"] / TERRAIN_ZOOM["aukerman"])
    frames = [Frame(i, i / args.fps, img, "sim") for i, img in enumerate(seq.frames)]
    print(f"simulated {len(frames)} frames 640x480 at {args.fps:g} fps in {time.monotonic() - t0:.1f} s")
    pace = 0.0 if args.as_fast_as_possible else args.fps
    minutes = len(frames) / args.fps / 60.0

    runs: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="bench-viewer-") as tmp:
        # the baseline twice (before and after), its lower CPU figures count: runs are noisy
        for name, viewer in (("no viewer", None), ("default", {}), ("lean", LEAN), ("no viewer 2", None)):
            runs[name] = run_once(frames, pace, Path(tmp) / name.replace(" ", "_"), viewer)
    b2 = runs.pop("no viewer 2")
    base = runs["no viewer"] = {k: min(v, b2[k]) if k.endswith("_s") else v for k, v in runs["no viewer"].items()}

    def pct(x: float, of: float) -> str:
        return f"{100 * x / of:.1f} %"

    names = list(runs)
    table = [("frames (registered)", [f"{r['frames']} ({r['registered']})" for r in runs.values()]),
             ("wall time, s", [f"{r['wall_s']:.1f}" for r in runs.values()]),
             ("worker time, s", [f"{r['worker_s']:.2f}" for r in runs.values()]),
             ("process CPU, s", [f"{r['cpu_s']:.2f}" for r in runs.values()])]
    views = [runs[n] for n in names[1:]]
    dash = ["-"]
    table += [
        ("recording, MB per minute of flight", dash + [f"{r['rrd_bytes'] / minutes / 1e6:.2f}" for r in views]),
        ("JPEG, MB per minute of flight", dash + [f"{r['jpeg_bytes'] / minutes / 1e6:.2f}" for r in views]),
        ("tiles / camera images logged", dash + [f"{r['tiles']} / {r['images']}" for r in views]),
        ("viewer items dropped", dash + [str(r["dropped"]) for r in views]),
        ("callback in worker, % of worker", dash + [pct(r["callback_s"], r["worker_s"]) for r in views]),
        ("viewer thread CPU, % of worker", dash + [pct(r["thread_cpu_s"], r["worker_s"]) for r in views]),
        ("callback + thread, % of worker", dash + [pct(r["callback_s"] + r["thread_cpu_s"], r["worker_s"])
                                                   for r in views]),
        ("extra process CPU (incl. rerun), % of worker",
         dash + [pct(r["cpu_s"] - base["cpu_s"], base["worker_s"]) for r in views]),
    ]
    w0 = max(len(name) for name, _ in table)
    print(f"\n{'':{w0}}" + "".join(f"  {n:>14}" for n in names))
    for name, cells in table:
        print(f"{name:{w0}}" + "".join(f"  {c:>14}" for c in cells))
    print(f"\nflight {minutes * 60:.1f} s; 'default' = config/default.yaml viewer section; 'lean' = {LEAN}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
