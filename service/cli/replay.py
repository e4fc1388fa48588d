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

import yaml

from photomap.drivers.capture import Frame, open_source
from photomap.drivers.mavlink import TelemetryReader, load_tlog
from photomap.errors import InputError
from photomap.mapping.telemetry_join import TelemetryJoin
from photomap.mapping.pipeline import MappingPipeline
from photomap.telemetry.samples import TelemetryBuffer
from photomap.core.tracking import TrackStep
from photomap.live.viewer import Viewer

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", help="video file, folder of images, or a glob such as 'dir/*.jpg'")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--realtime", action="store_true",
                        help="replay at the frames' original pace instead of as fast as possible")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_telemetry_arguments(parser)
    add_viewer_argument(parser)
    parser.add_argument("--video-start", type=float, metavar="UNIX",
                        help="UNIX time of the video's first frame, to join a .tlog (default: "
                             "the simulator's meta.yaml, the file's creation time, or the log's start)")


def add_telemetry_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mavlink", metavar="CONNECTION",
                        help="MAVLink telemetry: a .tlog file, udpin:0.0.0.0:14550, tcp:HOST:PORT, "
                             "/dev/ttyUSB0,57600 ... (default: telemetry.source; none = vision only)")
    parser.add_argument("--time-offset", type=float, metavar="SECONDS",
                        help="seconds added to frame times to get telemetry times")


def add_viewer_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--viewer", metavar="MODE",
                        help="live view in rerun (needs the viewer extra): none, spawn, serve[=PORT] "
                             "(an operator runs `rerun rerun+http://HOST:PORT/proxy`), "
                             "connect=URL, save=FILE.rrd (default: viewer.mode)")


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


def _video_metadata(input_spec: str) -> dict:
    """The simulator's meta.yaml beside a video (camera model, UNIX time of frame 0), if any."""
    meta = Path(input_spec).parent / "meta.yaml"
    if not Path(input_spec).is_file() or not meta.is_file():
        return {}
    try:
        data = yaml.safe_load(meta.read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError):
        return {}
    return data if isinstance(data, dict) else {}


def open_telemetry(spec: str, cfg: dict, *, source=None, input_spec: str = "",
                   video_start: float | None = None, realtime: bool = False,
                   live: bool = False) -> tuple[TelemetryJoin, TelemetryReader | None]:
    """A telemetry join for ``spec`` (a .tlog or a live link) and the reader to stop (or None)."""
    tcfg = cfg["telemetry"]
    offset = float(tcfg["time_offset"])
    meta = _video_metadata(input_spec) if input_spec else {}
    camera = meta.get("camera") or {}
    if not cfg["camera"]["fx_px"] and not cfg["camera"]["hfov_deg"] and camera.get("fx"):
        cfg["camera"]["fx_px"] = float(camera["fx"])  # the video's own camera model
    if spec.lower().endswith(".tlog") and not live:
        if not Path(spec).is_file():
            raise InputError(f"telemetry log not found: {spec}")
        buffer, stats = load_tlog(spec, max_gap=tcfg["max_gap"], max_hold=tcfg["max_hold"],
                                  link_timeout=tcfg["link_timeout"], system_id=tcfg["system_id"])
        if video_start is None:
            video_start = meta.get("t0_unix") or getattr(source, "creation_time", None)
        if video_start is None and getattr(source, "exif_times", None):
            video_start = 0.0  # stills carry UNIX times already
        if video_start is None:
            span = buffer.span
            video_start = span[0] if span else 0.0
            log.warning("video start time unknown: assuming it starts with the telemetry log "
                        "(use --video-start or --time-offset)")
        join = TelemetryJoin(buffer.at, "log", cfg, video_start=float(video_start), offset=offset)
        join.link_summary = lambda: _link_summary(spec, stats)
        return join, None
    buffer = TelemetryBuffer(max_gap=tcfg["max_gap"], max_hold=tcfg["max_hold"], horizon=tcfg["horizon"])
    reader = TelemetryReader(spec, buffer, link_timeout=tcfg["link_timeout"],
                             send_heartbeat=tcfg["send_heartbeat"] and live, baud=tcfg["baud"],
                             source_system=tcfg["source_system"], system_id=tcfg["system_id"]).start()
    if not live and not realtime:
        log.warning("a live telemetry link with a replay as fast as possible cannot be joined in "
                    "time: use --realtime")
    join = TelemetryJoin(reader.at, "live" if live else "link", cfg, offset=offset)
    join.link_summary = lambda: _link_summary(spec, reader.stats)
    if live and tcfg["send_statustext"]:
        join.notify = lambda text: reader.send_status(f"photomap: {text}")
    return join, reader


def _link_summary(spec: str, stats) -> dict:
    return {"source": spec, "messages": stats.total, "gaps": stats.gaps,
            "link_lost": stats.link_lost, "link_regained": stats.link_regained,
            "rejected_samples": sum(stats.rejected.values()), "parse_errors": stats.receive_errors,
            "system_id": stats.system_id,
            "other_systems": {str(k): v for k, v in sorted(stats.other_systems.items())},
            "span": list(stats.span) if stats.span else None}


def map_source(source, cfg: dict, out_dir: str | Path, *, input_name: str = "",
               progress: bool = False, total: int | None = None, realtime: bool = False,
               telemetry: TelemetryJoin | None = None, viewer: str | None = None) -> dict:
    """Run the mapping pipeline over ``source`` and write the outputs; returns the run summary.

    SIGINT/SIGTERM (when called from the main thread) stop capture, drain the queue and write
    the outputs. ``viewer`` is a ``--viewer`` mode string (default: the ``viewer.mode`` config).
    """
    view = Viewer.from_config(cfg["viewer"], viewer)
    if view.url:
        print(f"viewer: connect with `rerun {view.url}`")
    bar = tqdm(total=total, unit="frame", disable=not progress, file=sys.stderr, dynamic_ncols=True)
    pacer = _Pacer() if realtime else None

    def on_frame(frame: Frame, step: TrackStep, pipeline: MappingPipeline) -> None:
        bar.update(1)
        if view.enabled:
            view.on_frame(frame, step, pipeline)
        if pacer is not None:
            pacer(frame)

    pipeline = MappingPipeline(source, cfg, out_dir, on_frame=on_frame, input_name=input_name,
                               telemetry=telemetry)
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
        view.close()
        for sig, old in previous.items():
            signal.signal(sig, old)
    return summary


def replay(input_spec: str, out_dir: str | Path, cfg: dict, *, progress: bool = False,
           realtime: bool = False, mavlink: str | None = None,
           video_start: float | None = None, viewer: str | None = None) -> dict:
    """Map a video file or a folder/glob of images into ``out_dir``; returns the run summary.

    ``mavlink`` (default ``telemetry.source``) joins telemetry: a .tlog, or a live link (then use
    ``realtime``).
    """
    source = open_source(input_spec, **cfg["capture"])
    total = getattr(source, "frame_count", None) or len(getattr(source, "paths", ()) or ()) or None
    spec = mavlink or cfg["telemetry"]["source"]
    join, reader = (open_telemetry(spec, cfg, source=source, input_spec=str(input_spec),
                                   video_start=video_start, realtime=realtime)
                    if spec else (None, None))
    try:
        return map_source(source, cfg, out_dir, input_name=str(input_spec), progress=progress,
                          total=total, realtime=realtime, telemetry=join, viewer=viewer)
    finally:
        if reader is not None:
            reader.stop()


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
    geo = summary.get("georeference")
    if geo:
        print(f"georeferenced: {geo['crs']}, {summary['metres_per_pixel']:.3f} m per map pixel "
              f"(world file {out / geo['world_file']}; opens in place in QGIS)")
    elif summary.get("metres_per_pixel"):
        print(f"scale: {summary['metres_per_pixel']:.3f} m per map pixel")
    print(f"trajectory: {out / 'trajectory.csv'}")


def main(args: argparse.Namespace, cfg: dict) -> int:
    if args.time_offset is not None:
        cfg["telemetry"]["time_offset"] = args.time_offset
    summary = replay(args.input, args.out, cfg, progress=not (args.no_progress or args.quiet),
                     realtime=args.realtime, mavlink=args.mavlink, video_start=args.video_start,
                     viewer=args.viewer)
    print_summary(summary, args.out)
    return 0 if summary["registered"] > 0 else 1
