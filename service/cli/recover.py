"""Rebuild the map of a run that did not finish (killed, power loss, out of memory) or could not
write its final outputs (disk full), from the checkpoint it left in DIR/checkpoint/.

Writes mosaic.png (and mosaic_segment{N}.png), full-resolution tiles/ when the map is larger
than output.max_mosaic_px, world files when the checkpoint carries a georeference, and updates
run.json (``recovered``). trajectory.csv is the one of the last checkpoint. The checkpoint is
kept unless --remove-checkpoint is given.

examples:
  photomap recover /var/lib/photomap/flights/flight-20240501-101500
  photomap recover maps/flight1 --remove-checkpoint
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from photomap.config import Config
from photomap.mapping.checkpoint import recover_run, state_folder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", metavar="DIR", help="the run folder (holding checkpoint/)")
    parser.add_argument("--remove-checkpoint", action="store_true",
                        help="delete DIR/checkpoint/ once the map is written")


def main(args: argparse.Namespace, cfg: Config) -> int:
    out = Path(args.run_dir)
    summary = recover_run(out, max_mosaic_px=cfg.output.max_mosaic_px,
                          max_tiles_in_memory=cfg.mosaic.max_tiles_in_memory or 256)
    rec = summary["recovered"]
    maps = summary.get("mosaics") or []
    print(f"recovered checkpoint {rec['generation']} ({rec['frames_in']} frames in): "
          f"{len(maps)} map segment(s)" + (f", {'; '.join(rec['problems'])}" if rec["problems"] else ""))
    if maps:
        print(f"map: {out / maps[0]['file']}" + (f" (full resolution in {out / maps[0]['tiles']})"
                                                 if maps[0].get("tiles") else ""))
        geo = maps[0].get("georeference")
        if geo and geo.get("world_file"):
            print(f"georeferenced: {geo['crs']} (world file {out / geo['world_file']})")
    else:
        print("map: the checkpoint holds no map")
    print(f"trajectory: {out / 'trajectory.csv'}")
    if args.remove_checkpoint and maps:
        shutil.rmtree(state_folder(out), ignore_errors=True)
    return 0 if maps else 1
