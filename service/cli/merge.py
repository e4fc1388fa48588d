"""Merge the maps of several runs (flights, drones) over one site into one map.

The first RUN_DIR is the reference: the merged map is in its map frame (and georeferenced when
it is). Every other run's map is registered to it on the images themselves, coarse to fine
(iFMI on whole-map overviews, then windows at higher resolutions fitted robustly); when both
runs are georeferenced, their GPS placement replaces the coarse step unless --no-georeference.
A run that cannot be placed is listed in merge.json with the reason, never forced into the map.

Writes to --out: mosaic.png (+ tiles/ when downscaled; world file and map.tif when the
reference is georeferenced) and merge.json: per run map_to_merged (3x3, that run's map pixels
-> merged map pixels), the confidence and the windows that agreed.

examples:
  photomap merge maps/north maps/south --out maps/site
  photomap merge maps/season/*/ --out maps/site --no-georeference
"""

from __future__ import annotations

import argparse
from pathlib import Path

from photomap.config import Config
from photomap.mapping.merge import merge_runs


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("runs", nargs="+", metavar="RUN_DIR",
                        help="run folders written by replay/run/batch (the first is the reference)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--no-georeference", action="store_true",
                        help="place the maps by the images alone, even when both runs are georeferenced")


def main(args: argparse.Namespace, cfg: Config) -> int:
    summary = merge_runs(args.runs, args.out, cfg, use_georeference=not args.no_georeference)
    out = Path(args.out)
    for e in summary["runs"]:
        if e["reference"]:
            print(f"{e['run']}: reference")
        elif e["placed"]:
            print(f"{e['run']}: placed (confidence {e['confidence']:.2f}, rotation {e['angle_deg']:.1f} deg, "
                  f"scale {e['scale']:.3f}, {e['coarse']})")
        else:
            print(f"{e['run']}: NOT placed: {e['reason']}")
    print(f"map: {out / 'mosaic.png'}; {out / 'merge.json'}")
    return 0 if not summary["not_placed"] else 1
