"""A catalogue of mapped flights: ``flights.geojson``, one footprint polygon per georeferenced run.

A flight's footprint is the covered outline of its main map (the union of the footprints of the
frames glued into it, :func:`photomap.io.trackfiles.coverage`, the ``coverage`` feature of its
``track.geojson``), taken map pixels -> UTM (the run's ``georeference.map_to_crs``) -> WGS84.
It is read back from the finished run folder (``run.json`` + ``trajectory.csv``), so it works for
any run, not only the ones a batch mapped.

GeoJSON follows RFC 7946 (longitude, latitude; exterior rings counter-clockwise); the file is
written atomically.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

from photomap.errors import InputError
from photomap.io.runfiles import RunFiles
from photomap.io.trackfiles import geojson_text, track_features
from photomap.io.trajectory_files import atomic_write_text


def flight_footprint(run_dir: str | Path, properties: dict | None = None) -> dict | None:
    """The GeoJSON feature (a dict) of the covered outline of a run's main map, or None when the
    run has no georeferenced map (not complete, nothing mapped, or no georeference).

    Properties: ``properties`` plus ``segment``, ``crs``, ``area_m2``, ``area_km2`` and
    ``metres_per_pixel`` of the main map. InputError when ``run_dir`` is no run folder.
    """
    run = RunFiles(run_dir)
    if not run.complete or not run.mosaics:
        return None
    entry = run.mosaic()
    segment = int(entry.get("segment", 0))
    try:
        map_to_crs, epsg = run.georeference(entry)
    except InputError:
        return None
    rows = [r for r in run.rows if r.glued and r.segment == segment]
    if not rows:
        return None
    feats = track_features(rows, run.frame_size, {segment: (map_to_crs, epsg)}, footprints="none")
    cover = next((f for f in feats if f["properties"].get("kind") == "coverage"), None)
    if cover is None:
        return None
    props = dict(properties or {})
    props.update({"segment": segment, "crs": f"EPSG:{epsg}",
                  "area_m2": cover["properties"]["area_m2"], "area_km2": cover["properties"]["area_km2"],
                  "metres_per_pixel": (entry.get("georeference") or {}).get("metres_per_pixel")})
    return {"type": "Feature", "geometry": cover["geometry"], "properties": props}


def write_catalogue(path: str | Path, features: Iterable[dict | None]) -> int:
    """Write the features (None ones left out) as a GeoJSON FeatureCollection; returns their count."""
    feats = [f for f in features if f is not None]
    atomic_write_text(path, geojson_text(feats))
    return len(feats)
