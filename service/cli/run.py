"""Map live from a camera until stopped (Ctrl-C / SIGTERM writes the map and exits 0).

Frames that arrive while the worker is busy are dropped, oldest first, and counted, so latency
stays bounded. Outputs go to --out, or to a time-stamped folder under output.data_dir. Outputs are
checkpointed every output.checkpoint_interval seconds, so a power loss loses at most that much.

examples:
  photomap run --camera /dev/video0
  photomap run --camera udp://@:5600                 # MPEG-TS over UDP
  photomap run --camera rtsp://192.168.144.25:8554/main.264?tcp
  photomap run --camera qgc-5600.sdp                 # plain RTP (QGroundControl's UDP 5600), docs/streams.md
  photomap run --camera 0 --out /data/flights/today --set capture.width=640 --set capture.height=480
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from photomap.cli.wiring import add_hazards_argument, hazards_config
from photomap.cli.wiring import (add_map_server_argument, add_mask_argument, add_telemetry_arguments,
                                 add_viewer_argument, map_source, open_capture, open_telemetry, print_summary,
                                 with_mask_argument)
from photomap.config import Config
from photomap.errors import OutputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--camera", default=None,
                        help="V4L2 device path or index, or a stream URL / .sdp file (docs/streams.md); "
                             "default capture.device, else /dev/video0")
    parser.add_argument("--out", metavar="DIR",
                        help="output folder (default: a time-stamped folder under output.data_dir)")
    add_telemetry_arguments(parser)
    add_mask_argument(parser)
    add_viewer_argument(parser)
    add_hazards_argument(parser)
    add_map_server_argument(parser)


def flight_folder(data_dir: str | Path) -> Path:
    """A new time-stamped folder for one flight's outputs (never an existing one: a board
    without a real-time clock can repeat a time)."""
    base = Path(data_dir).expanduser() / time.strftime("flight-%Y%m%d-%H%M%S")
    folder, n = base, 1
    while folder.exists():
        n += 1
        folder = base.with_name(f"{base.name}-{n}")
    return folder


def main(args: argparse.Namespace, cfg: Config) -> int:
    cfg = hazards_config(args, cfg)
    out = Path(args.out) if args.out else flight_folder(cfg.output.data_dir)
    cfg = with_mask_argument(args, cfg)
    if args.time_offset is not None:
        cfg = cfg.updated({"telemetry": {"time_offset": args.time_offset}})
    spec = args.mavlink or cfg.telemetry.source
    join = reader = None
    if spec:
        join, reader, cfg = open_telemetry(spec, cfg, live=True)
    configured = cfg.capture.device
    args.camera = args.camera or configured or "/dev/video0"
    try:
        source = open_capture(args.camera, cfg.capture)
        print(f"mapping from {args.camera} into {out} (Ctrl-C to stop)")
        summary = map_source(source, cfg, out, input_name=str(args.camera), telemetry=join, reader=reader,
                             viewer=args.viewer, status_interval=getattr(args, "status_interval", 0.0),
                             map_server=args.map_server)
    finally:
        if reader is not None:
            reader.stop()
    print_summary(summary, out)
    return OutputError.exit_code if summary.get("write_errors") else 0
