"""The bundled sample flight, end to end: simulate, map, evaluate.

Flies a virtual camera over the bundled CC0 orthophoto (video.mp4, telemetry.tlog and exact ground
truth), maps the video with its telemetry as `photomap replay --mavlink` would (a metric,
georeferenced map: mosaic.png + world file), compares the trajectory with the ground truth
(`photomap evaluate`) and prints where the map is. Takes well under a minute.

example:
  photomap demo --out photomap-demo
"""

from __future__ import annotations

import argparse
from pathlib import Path

from photomap.cli.replay import replay
from photomap.cli.wiring import add_viewer_argument, print_summary
from photomap.config import Config
from photomap.eval.evaluate import evaluate_run, format_table
from photomap.sim.simulate import simulate_flight


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="photomap-demo", metavar="DIR",
                        help="output folder (default ./photomap-demo)")
    parser.add_argument("--frames", type=int, default=300, help="frames to simulate (default 300)")
    parser.add_argument("--seed", type=int, default=1, help="seed of the simulated flight")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_viewer_argument(parser)


def main(args: argparse.Namespace, cfg: Config) -> int:
    out = Path(args.out)
    flight = out / "flight"
    print(f"1/3 simulating {args.frames} frames over the bundled terrain into {flight}/")
    simulate_flight(flight, terrain="aukerman", n_frames=args.frames, size=(640, 480), seed=args.seed)
    print("2/3 mapping the video, joined with its MAVLink telemetry log")
    run_dir = out / "map"
    summary = replay(str(flight / "video.mp4"), run_dir, cfg,
                     progress=not (args.no_progress or args.quiet),
                     mavlink=str(flight / "telemetry.tlog"), viewer=args.viewer)
    print("3/3 comparing with the ground truth")
    result = evaluate_run(run_dir, flight / "groundtruth.csv", run_dir)
    print(format_table(result))
    print_summary(summary, run_dir)
    plots = result.get("plots") or []
    print(f"evaluation: {run_dir / 'evaluation.json'}"
          + (f" and plots {', '.join(str(run_dir / Path(p).name) for p in plots)}" if plots
             else " (pip install 'ifmi-photomap[plots]' for the figures)"))
    return 0
