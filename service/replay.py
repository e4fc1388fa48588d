"""Map a logged flight: a video file, or a folder/glob of still images.

Frames are processed as fast as possible (never dropped) with a progress bar, or at their original
pace with --realtime. Writes mosaic.png, trajectory.csv, trajectory.tum and run.json to --out.

examples:
  photomap replay flight.mp4 --out maps/flight1
  photomap replay "survey/*.JPG" --out maps/survey --set mosaic.blend=feather
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from pathlib import Path

from tqdm import tqdm

from drivers.capture import Frame, open_source
from .pipeline import MappingPipeline
from .tracking import TrackStep

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", help="video file, folder of images, or a glob such as 'dir/*.jpg'")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--realtime", action="store_true",
                        help="replay at the frames' original pace instead of as fast as possible")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


class _Pacer:
    """Sleeps so that frame times advance no faster than wall time (for --realtime)."""

    def __init__(self) -> None:
        self._t0: tuple[float, float] | None = None

    def __call__(self, frame: Frame) -> None:
        if self._t0 is None:
            self._t0 = (frame.t, time.monotonic())
            return
        delay = (frame.t - self._t0[0]) - (time.monotonic() - self._t0[1])
        if delay > 0:
            time.sleep(delay)


def map_source(source, cfg: dict, out_dir: str | Path, *, input_name: str = "",
               progress: bool = False, total: int | None = None, realtime: bool = False) -> dict:
    """Run the mapping pipeline over ``source`` and write the outputs; returns the run summary.

    SIGINT/SIGTERM (when called from the main thread) stop capture, drain the queue and write
    the outputs.
    """
    bar = tqdm(total=total, unit="frame", disable=not progress, file=sys.stderr, dynamic_ncols=True)
    pacer = _Pacer() if realtime else None

    def on_frame(frame: Frame, step: TrackStep, pipeline: MappingPipeline) -> None:
        bar.update(1)
        if pacer is not None:
            pacer(frame)

    pipeline = MappingPipeline(source, cfg, out_dir, on_frame=on_frame, input_name=input_name)
    previous = {}
    if threading.current_thread() is threading.main_thread():
        def handler(signum, _frame):
            log.warning("%s: stopping, writing the map", signal.Signals(signum).name)
            pipeline.stop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, handler)
    try:
        summary = pipeline.run()
    finally:
        bar.close()
        for sig, old in previous.items():
            signal.signal(sig, old)
    return summary


def replay(input_spec: str, out_dir: str | Path, cfg: dict, *, progress: bool = False,
           realtime: bool = False) -> dict:
    """Map a video file or a folder/glob of images into ``out_dir``; returns the run summary."""
    source = open_source(input_spec, **cfg["capture"])
    total = getattr(source, "frame_count", None) or len(getattr(source, "paths", ()) or ()) or None
    return map_source(source, cfg, out_dir, input_name=str(input_spec), progress=progress,
                      total=total, realtime=realtime)


def print_summary(summary: dict, out_dir: str | Path) -> None:
    out = Path(out_dir)
    mosaics = summary.get("mosaics") or []
    print(f"frames: {summary['frames_in']} in, {summary['registered']} registered, "
          f"{summary['skipped']} skipped, {summary['dropped']} dropped; "
          f"{summary['segments']} segment(s); "
          f"{summary['ms_per_frame'] or 0:.1f} ms/frame ({summary['fps'] or 0:.1f} fps)")
    if mosaics:
        print(f"map: {out / mosaics[0]['file']}")
    else:
        print("map: nothing was mapped")
    print(f"trajectory: {out / 'trajectory.csv'}")


def main(args: argparse.Namespace, cfg: dict) -> int:
    summary = replay(args.input, args.out, cfg, progress=not (args.no_progress or args.quiet),
                     realtime=args.realtime)
    print_summary(summary, args.out)
    return 0 if summary["registered"] > 0 else 1
