"""The georeferenced outputs of a run, for :mod:`photomap.mapping.run_outputs` (end of run and checkpoints).

- :func:`write_geo_outputs` (end of run, after the georeference, **before** the tile cache is
  removed): the north-up COG ``map.tif`` of the main map from the live mosaic
  (:func:`write_main_cog`, when the ``geo`` extra is installed; else one INFO line; or written
  already, beside the PNGs), ``tiles.vrt`` over full-resolution ``tiles/``
  (:func:`write_tile_georeferences`; or written already, while the GeoTIFF was), and
  ``track.kml`` / ``track.geojson``.
- :func:`refresh_track_files` (each checkpoint): rewrite ``track.kml`` / ``track.geojson``
  atomically, so a ground station reloading them (a KML network link, a GeoJSON layer) sees the
  coverage grow.

Every argument is explicit: the run.json ``mosaics[]`` entries (with their ``georeference``),
the live mosaics by segment, the rows, the frame size.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Sequence

from photomap.core.mosaic import TiledMosaic
from photomap.errors import PhotomapError
from photomap.core.records import PoseRow
from photomap.io.geotiff import write_cog_if_available
from photomap.io.mapsource import MapRaster, mosaic_source
from photomap.io.runfiles import parse_crs, parse_map_to_crs
from photomap.io.tileworld import write_tile_georeference
from photomap.io.trackfiles import Georefs, mosaic_overlay, write_track_files

log = logging.getLogger(__name__)


def georefs_from_maps(maps: Sequence[dict]) -> Georefs:
    """``{segment: (map_to_crs 2x3, epsg)}`` of the run.json ``mosaics[]`` entries that carry a
    georeference (``georeference.crs`` and ``georeference.map_to_crs``)."""
    out: Georefs = {}
    for m in maps:
        geo = m.get("georeference") or {}
        if geo.get("crs") and geo.get("map_to_crs") is not None:
            out[int(m.get("segment", 0))] = (parse_map_to_crs(geo["map_to_crs"]), parse_crs(geo["crs"]))
    return out


def refresh_track_files(out_dir: str | Path, rows: Sequence[PoseRow], frame_size: tuple[int, int],
                        georefs: Georefs, *, t0_unix: float | None = None, footprints: str = "spaced") -> dict | None:
    """Rewrite ``track.geojson`` and ``track.kml`` (atomically); None (and a debug line) when
    nothing is georeferenced yet. ``georefs``: ``{segment: (map_to_crs, epsg)}``, e.g. from
    :func:`georefs_from_maps` or the telemetry join's current fit."""
    if not georefs or frame_size is None:
        log.debug("track files not written: no georeference yet")
        return None
    return write_track_files(out_dir, rows, frame_size, georefs, footprints=footprints, t0_unix=t0_unix)


def write_main_cog(out_dir: str | Path, main: dict, mosaics: dict[int, TiledMosaic], *,
                   cog_name: str = "map.tif") -> dict | None:
    """The north-up COG ``cog_name`` of the main map: ``main`` is its run.json ``mosaics[]`` entry
    (with its ``georeference``), ``mosaics`` the live mosaics by segment (only read: it may run on
    a thread beside other readers of the map). Returns what was written, or None: not
    georeferenced, no rasterio (one INFO line) or a failure (a warning)."""
    seg = int(main.get("segment", 0))
    georef = georefs_from_maps([main]).get(seg)
    if georef is None or seg not in mosaics or mosaics[seg].bounds() is None:
        return None
    try:
        raster = MapRaster(mosaic_source(mosaics[seg]), mosaics[seg].bounds(), *georef)
        return write_cog_if_available(Path(out_dir) / cog_name, raster)
    except (PhotomapError, OSError, RuntimeError) as exc:  # rasterio errors are RuntimeErrors
        log.warning("GeoTIFF not written: %s", exc)
        return None


def write_tile_georeferences(out_dir: str | Path, maps: Sequence[dict], *, world_files: bool = False,
                             sync: bool = True) -> list[dict]:
    """``tiles.vrt`` (one georeferenced layer over the tiles) of every georeferenced map of
    ``maps`` (run.json ``mosaics[]`` entries) with full-resolution ``tiles``; returns what was
    written (a failure is a warning). ``world_files``: also a world file and CRS per tile (two
    files a tile; ``photomap export --tile-georef``). ``sync``: False when the caller makes them
    durable (:func:`~photomap.io.trajectory_files.sync_filesystem`)."""
    georefs = georefs_from_maps(maps)
    done = []
    for m in maps:
        s = int(m.get("segment", 0))
        if m.get("tiles") and s in georefs:
            try:
                done.append(write_tile_georeference(Path(out_dir) / m["tiles"], int(m.get("tile_size") or 256),
                                                    *georefs[s], world_files=world_files, sync=sync))
            except (PhotomapError, OSError) as exc:
                log.warning("tiles.vrt not written: %s", exc)
    return done


def write_geo_outputs(out_dir: str | Path, maps: Sequence[dict], mosaics: dict[int, TiledMosaic],
                      rows: Sequence[PoseRow], frame_size: tuple[int, int], *, t0_unix: float | None = None,
                      cog: bool = True, cog_name: str = "map.tif", footprints: str = "spaced",
                      cog_info: dict | None = None, tile_georeference: list[dict] | None = None) -> dict:
    """The end-of-run georeferenced outputs; returns what was written (for run.json ``exports``).

    Parameters
    ----------
    maps : run.json ``mosaics[]`` entries (``file``, ``segment``, ``origin_xy``, ``pixel_scale``,
        ``size``, optional ``tiles``/``tile_size``, ``georeference``); the first is the main map.
    mosaics : the live mosaics by segment (still readable: call before removing the tile cache).
    t0_unix : UNIX time of frame time 0 (footprint time stamps), or None.
    cog : write the GeoTIFF of the main map (when rasterio is installed; :func:`write_main_cog`).
    cog_info : the GeoTIFF written already (what :func:`write_main_cog` returned): recorded, not
        written again.
    tile_georeference : the tiles' georeference written already (what
        :func:`write_tile_georeferences` returned): recorded, not written again.

    A failure of one output is logged as a warning and does not stop the others.
    """
    out = Path(out_dir)
    georefs = georefs_from_maps(maps)
    done: dict = {}
    if cog_info is not None:
        done["cog"] = cog_info
    if not georefs:
        return done
    main = maps[0]
    seg = int(main.get("segment", 0))
    if cog and cog_info is None:
        info = write_main_cog(out, main, mosaics, cog_name=cog_name)
        if info is not None:
            done["cog"] = info
    tiles = write_tile_georeferences(out, maps) if tile_georeference is None else tile_georeference
    if tiles:
        done["tile_georeference"] = tiles
    try:
        overlay = mosaic_overlay(main, *georefs[seg]) if seg in georefs else None
        done["track"] = write_track_files(out, rows, frame_size, georefs, footprints=footprints,
                                          t0_unix=t0_unix, overlay=overlay)
    except (PhotomapError, OSError) as exc:
        log.warning("track files not written: %s", exc)
    return done
