"""Export a run for GIS and ground stations: GeoTIFF, web tiles, KML/GeoJSON, evo, report.

Reads a run folder (run.json, trajectory.csv, mosaic.png and tiles/) and writes into it (or
where asked). Without an output flag, writes everything it can. Everything but --report needs
a georeferenced run (mapped with GPS telemetry: --mavlink).

outputs:
  --cog        map.tif: north-up Cloud-Optimized GeoTIFF (needs the geo extra: rasterio)
  --tiles      xyz/{z}/{x}/{y}.png: web-mercator tiles for Leaflet, QGIS "XYZ Tiles", GCS maps
  --kml        track.kml: track, footprints, coverage, map overlay (Google Earth, QGC, QGIS)
  --geojson    track.geojson: the same features (QGIS, web maps)
  --tum-utm    trajectory_utm.tum (and gps_utm.tum with --gps-tlog): metres + UNIX time for evo
  --report     report.html: self-contained flight report
  --tile-georef  world files + tiles.vrt for the full-resolution tiles/ of a large map

examples:
  photomap export maps/flight1                      # everything it can
  photomap export maps/flight1 --cog --gsd 0.05
  photomap export maps/flight1 --tiles --zoom 16-21 --tms
  photomap export maps/flight1 --tum-utm --gps-tlog flight1.tlog
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
from pathlib import Path

from photomap.errors import InputError, PhotomapError
from photomap.io import geotiff
from photomap.io.geotrajectory import VIDEO_START_HELP, format_gps_tum, write_tum_utm
from photomap.io.mapsource import run_raster
from photomap.io.report import write_report
from photomap.io.runfiles import RunFiles
from photomap.io.trackfiles import FOOTPRINT_MODES, mosaic_overlay, write_track_files
from photomap.io.tileworld import write_tile_georeference
from photomap.io.trajectory_files import atomic_write_text, largest_segment
from photomap.io.xyz_tiles import leaflet_snippet, write_xyz_tiles

log = logging.getLogger(__name__)

OUTPUTS = ("cog", "tiles", "kml", "geojson", "tum_utm", "report", "tile_georef")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", metavar="RUN_DIR", help="a run folder (written by replay or run)")
    g = parser.add_argument_group("outputs (default: all that the run allows)")
    g.add_argument("--cog", nargs="?", const="map.tif", metavar="FILE",
                   help="north-up Cloud-Optimized GeoTIFF (default RUN_DIR/map.tif; needs the geo extra)")
    g.add_argument("--tiles", nargs="?", const="xyz", metavar="DIR",
                   help="web-mercator PNG tiles DIR/{z}/{x}/{y}.png (default RUN_DIR/xyz)")
    g.add_argument("--kml", action="store_true", help="track.kml (track, footprints, coverage, map overlay)")
    g.add_argument("--geojson", action="store_true", help="track.geojson (track, footprints, coverage)")
    g.add_argument("--tum-utm", action="store_true",
                   help="trajectory_utm.tum: UTM metres and UNIX time, for evo against GPS")
    g.add_argument("--report", action="store_true", help="report.html, a self-contained flight report")
    g.add_argument("--tile-georef", action="store_true",
                   help="world files and tiles.vrt for the full-resolution tiles/ (large maps)")
    o = parser.add_argument_group("options")
    o.add_argument("--segment", type=int, metavar="N", help="map segment for --cog/--tiles/--tum-utm "
                                                             "(default: the main map)")
    o.add_argument("--gsd", type=float, metavar="M", help="GeoTIFF pixel size in metres (default: the map's)")
    o.add_argument("--zoom", metavar="ZMIN-ZMAX", help="tile zoom range, e.g. 15-20 (default: from the map's "
                                                       "resolution down to about one tile)")
    o.add_argument("--tms", action="store_true", help="TMS row numbering (y from the south) instead of XYZ")
    o.add_argument("--footprints", choices=FOOTPRINT_MODES, default="spaced",
                   help="which frames get a footprint in KML/GeoJSON (default: spaced)")
    o.add_argument("--video-start", type=float, metavar="UNIX",
                   help="UNIX time of frame time 0 (default: run.json video_start_unix)")
    o.add_argument("--gps-tlog", metavar="FILE",
                   help="with --tum-utm: also write gps_utm.tum from this log's GPS fixes")


def _zooms(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+))?\s*", text)
    if not m:
        raise InputError(f"--zoom must be Z or ZMIN-ZMAX, got {text!r}")
    lo = int(m.group(1))
    return lo, int(m.group(2)) if m.group(2) else lo


def _out(run: RunFiles, name: str) -> Path:
    p = Path(name)
    return p if p.is_absolute() else run.dir / p


def _t0(run: RunFiles, given: float | None) -> float | None:
    start = given if given is not None else run.video_start_unix
    return None if start is None else start + run.time_offset_s


def export(run_dir: str | Path, *, cog: str | None = None, tiles: str | None = None, kml: bool = False,
           geojson: bool = False, tum_utm: bool = False, report: bool = False, tile_georef: bool = False,
           segment: int | None = None, gsd: float | None = None, zooms: tuple[int, int] | None = None,
           tms: bool = False, footprints: str = "spaced", video_start: float | None = None,
           gps_tlog: str | None = None, everything: bool = False) -> list[str]:
    """Write the asked outputs of a run folder; returns one line per output written.

    ``everything``: write what the run allows, skipping (with an INFO line) what it does not.
    Otherwise an output that cannot be written raises InputError.
    """
    run = RunFiles(run_dir)
    done: list[str] = []

    def attempt(name: str, fn) -> None:
        try:
            done.append(fn())
        except PhotomapError as exc:
            if not everything:
                raise
            log.info("%s skipped: %s", name, exc)

    def do_cog() -> str:
        raster = run_raster(run, segment)
        path = _out(run, cog or "map.tif")
        info = geotiff.write_cog(path, raster, gsd=gsd)
        return (f"GeoTIFF: {path} ({info['size'][0]} x {info['size'][1]} px, "
                f"{info['gsd_m']:.3f} m, {info['crs']}, north-up COG)")

    def do_tiles() -> str:
        folder = _out(run, tiles or "xyz")
        info = write_xyz_tiles(folder, run_raster(run, segment), zooms=zooms, tms=tms)
        return (f"tiles: {info['tiles']} {info['scheme'].upper()} tiles, zoom {info['zooms'][0]}-{info['zooms'][1]}: "
                f"file://{folder.resolve()}/{{z}}/{{x}}/{{y}}.png  (Leaflet: {leaflet_snippet(info)})")

    def do_track(kinds: tuple[str, ...]) -> str:
        georefs = run.georeferences()
        overlay = None
        try:
            entry = run.mosaic()
            if int(entry.get("segment", 0)) in georefs and (run.dir / entry["file"]).is_file():
                overlay = mosaic_overlay(entry, *georefs[int(entry.get("segment", 0))])
        except InputError:
            pass
        info = write_track_files(run.dir, run.rows, run.frame_size, georefs, footprints=footprints,
                                 t0_unix=_t0(run, video_start), overlay=overlay)
        names = [str(run.dir / info[k]) for k in kinds]
        for k in ("geojson", "kml"):
            if k not in kinds:
                (run.dir / info[k]).unlink(missing_ok=True)
        return f"track: {', '.join(names)} ({info['features']} features, {info['area_m2'] / 1e6:.4f} km² covered)"

    def do_tum() -> str:
        t0 = _t0(run, video_start)
        if t0 is None:
            raise InputError(VIDEO_START_HELP)
        georefs = run.georeferences()
        seg = segment if segment is not None else largest_segment(run.rows)
        if seg not in georefs:
            raise InputError(f"segment {seg} has no georeference")
        path = run.dir / "trajectory_utm.tum"
        write_tum_utm(path, run.rows, run.frame_size, *georefs[seg], t0, seg)
        line = f"evo: {path}"
        if gps_tlog:
            from photomap.drivers.mavlink import load_tlog  # drivers only when asked
            if not Path(gps_tlog).is_file():
                raise InputError(f"telemetry log not found: {gps_tlog}")
            buffer, _ = load_tlog(gps_tlog)
            t_lat, lat = buffer.series("lat")
            t_lon, lon = buffer.series("lon")
            if len(t_lat) == 0 or len(t_lat) != len(t_lon):
                raise InputError(f"{gps_tlog} has no GPS positions (GLOBAL_POSITION_INT)")
            times = [r.t for r in run.rows if r.glued and r.segment == seg]
            gps = run.dir / "gps_utm.tum"
            atomic_write_text(gps, format_gps_tum(t_lat, lat, lon, georefs[seg][1],
                                                  (t0 + min(times) - 1.0, t0 + max(times) + 1.0)))
            line += f"; GPS: {gps}; compare: evo_ape tum {gps.name} {path.name} -a --plot"
        return line

    def do_tile_georef() -> str:
        entry = run.mosaic(segment)
        if not entry.get("tiles"):
            raise InputError(f"{entry['file']} is the full map: the run wrote no full-resolution tiles")
        info = write_tile_georeference(run.dir / entry["tiles"], int(entry.get("tile_size") or 256),
                                       *run.georeference(entry))
        return f"tile georeference: {info['tiles']} world files, {run.dir / info['vrt']}"

    def do_report() -> str:
        return f"report: {write_report(run.dir)}"

    if cog is not None:
        attempt("GeoTIFF", do_cog)
    if tiles is not None:
        attempt("tiles", do_tiles)
    if kml or geojson:
        attempt("track", lambda: do_track(tuple(k for k, on in (("kml", kml), ("geojson", geojson)) if on)))
    if tum_utm:
        attempt("trajectory_utm.tum", do_tum)
    if tile_georef:
        attempt("tile georeference", do_tile_georef)
    if report:  # last: it lists the files written before it
        attempt("report", do_report)
    return done


def main(args: argparse.Namespace, cfg: dict) -> int:
    chosen = any(getattr(args, k) not in (None, False) for k in OUTPUTS)
    if not chosen:
        run = RunFiles(args.run_dir)
        cog = "map.tif" if geotiff.rasterio_available() else None
        if cog is None:
            log.info("no GeoTIFF: %s", geotiff.GEO_EXTRA_HINT)
        kwargs = dict(cog=cog, tiles="xyz", kml=True, geojson=True, tum_utm=True, report=True,
                      tile_georef=any(m.get("tiles") for m in run.mosaics), everything=True)
    else:
        kwargs = dict(cog=args.cog, tiles=args.tiles, kml=args.kml, geojson=args.geojson,
                      tum_utm=args.tum_utm, report=args.report, tile_georef=args.tile_georef)
    lines = export(args.run_dir, segment=args.segment, gsd=args.gsd, zooms=_zooms(args.zoom), tms=args.tms,
                   footprints=args.footprints, video_start=args.video_start, gps_tlog=args.gps_tlog, **kwargs)
    for line in lines:
        print(line)
    if not lines:
        print("nothing exported", file=sys.stderr)
        return 1
    return 0
