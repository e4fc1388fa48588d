"""Map a logged flight: a video file, or a folder/glob of still images.

Frames are processed as fast as possible (never dropped) with a progress bar, or at their original
pace with --realtime. Writes mosaic.png, trajectory.csv, trajectory.tum and run.json to --out.

examples:
  photomap replay flight.mp4 --out maps/flight1
  photomap replay "survey/*.JPG" --out maps/survey --set mosaic.blend=feather
"""

from __future__ import annotations

import argparse
from pathlib import Path

from photomap.cli.wiring import add_hazards_argument, hazards_config
from photomap.cli.wiring import (add_map_server_argument, add_mask_argument, add_telemetry_arguments,
                                 add_viewer_argument, map_source, open_capture, open_stills_telemetry,
                                 open_telemetry, print_summary, telemetry_beside, with_mask_argument)
from photomap.config import Config
from photomap.errors import OutputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", help="video file, folder of images, or a glob such as 'dir/*.jpg'")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--realtime", action="store_true",
                        help="replay at the frames' original pace instead of as fast as possible")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_telemetry_arguments(parser)
    add_mask_argument(parser)
    add_viewer_argument(parser)
    add_hazards_argument(parser)
    add_map_server_argument(parser)
    parser.add_argument("--geo", metavar="FILE",
                        help="positions of the stills in OpenDroneMap's geo.txt format (default: the "
                             "stills' own EXIF GPS / DJI XMP, when they carry it)")
    parser.add_argument("--video-start", type=float, metavar="UNIX",
                        help="UNIX time of the video's first frame, to join a .tlog (default: "
                             "the simulator's meta.yaml, the file's creation time, or the log's start)")


def replay(input_spec: str, out_dir: str | Path, cfg: Config, *, progress: bool = False,
           realtime: bool = False, mavlink: str | None = None,
           video_start: float | None = None, viewer: str | None = None, geo: str | None = None,
           status_interval: float = 0.0, map_server: str | None = None) -> dict:
    """Map a video file or a folder/glob of images into ``out_dir``; returns the run summary.

    ``mavlink`` (default ``telemetry.source``) joins telemetry: a .tlog, a DJI .SRT, or a live link
    (then use ``realtime``; the command finds a video's .SRT beside it). Without it, stills use
    their own telemetry (EXIF GPS, DJI XMP, or ``geo``, a geo.txt file). ``status_interval`` > 0: a status line every that many seconds when no
    progress bar is shown; ``map_server``: ``[ADDR:]PORT`` of the live map server (see
    :func:`photomap.cli.wiring.map_source`).
    """
    source = open_capture(str(input_spec), cfg.capture)
    total = getattr(source, "frame_count", None) or len(getattr(source, "paths", ()) or ()) or None
    spec = mavlink or cfg.telemetry.source
    join = reader = None
    if spec:
        join, reader, cfg = open_telemetry(spec, cfg, source=source, input_spec=str(input_spec),
                                           video_start=video_start, realtime=realtime)
    else:
        join, cfg = open_stills_telemetry(source, cfg, geo)
    try:
        return map_source(source, cfg, out_dir, input_name=str(input_spec), progress=progress,
                          total=total, realtime=realtime, telemetry=join, reader=reader, viewer=viewer,
                          status_interval=status_interval, map_server=map_server)
    finally:
        if reader is not None:
            reader.stop()


def main(args: argparse.Namespace, cfg: Config) -> int:
    cfg = hazards_config(args, cfg)
    cfg = with_mask_argument(args, cfg)
    if args.time_offset is not None:
        cfg = cfg.updated({"telemetry": {"time_offset": args.time_offset}})
    mavlink = args.mavlink
    if not mavlink and not cfg.telemetry.source:
        mavlink = telemetry_beside(args.input)   # DJI_0001.SRT beside DJI_0001.MP4
    summary = replay(args.input, args.out, cfg, progress=not (args.no_progress or args.quiet),
                     realtime=args.realtime, mavlink=mavlink, video_start=args.video_start,
                     viewer=args.viewer, geo=args.geo, status_interval=getattr(args, "status_interval", 0.0),
                     map_server=args.map_server)
    print_summary(summary, args.out)
    if summary.get("write_errors"):
        return OutputError.exit_code
    return 0 if summary["registered"] > 0 else 1
