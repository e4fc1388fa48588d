"""The hazard spots of a run as files: ``hazards.geojson``, ``hazards.kml``, ``hazards.csv``.

Input: GeoJSON features (dicts) as :mod:`photomap.mapping.hazards` makes them: a Point
(WGS84 longitude, latitude; ``geometry`` None when the map is not georeferenced) with the
properties of :data:`HAZARD_COLUMNS`. The KML has one placemark per georeferenced hazard; the
CSV has one row per hazard (lat/lon empty without a georeference). All three are written
atomically (a ground station reloading them never reads half a file).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from xml.sax.saxutils import escape

from photomap.io.trackfiles import geojson_text
from photomap.io.trajectory_files import atomic_write_text

HAZARD_COLUMNS = ("id", "first_seen", "first_seen_t", "last_seen", "last_seen_t", "frames", "peak",
                  "segment", "x_px", "y_px", "lat", "lon", "uncertainty_m")
"""CSV columns (and feature properties): first/last seen frame index and time (s, the run's time
base), frames that saw it, peak value, map segment and map pixel, WGS84 degrees, 1-sigma
position uncertainty in metres."""


def _cell(v) -> str:
    return "" if v is None else str(v)  # the features' values are rounded already


def hazards_csv_text(features: list[dict]) -> str:
    """One row per hazard, columns :data:`HAZARD_COLUMNS`."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(HAZARD_COLUMNS)
    for f in features:
        p = f["properties"]
        w.writerow([_cell(p.get(k)) for k in HAZARD_COLUMNS])
    return buf.getvalue()


def hazards_kml_text(features: list[dict], *, name: str = "photomap hazards") -> str:
    """KML 2.2: one Placemark (a Point, its properties as ExtendedData) per georeferenced hazard."""
    marks = []
    for f in features:
        g, p = f.get("geometry"), f["properties"]
        if not g:
            continue
        lon, lat = g["coordinates"]
        data = "".join(f'<Data name="{escape(str(k))}"><value>{escape(str(v))}</value></Data>'
                       for k, v in p.items() if v is not None)
        marks.append(f"<Placemark><name>hazard {escape(str(p['id']))}</name><styleUrl>#hazard</styleUrl>"
                     f"<ExtendedData>{data}</ExtendedData><Point><coordinates>{lon!r},{lat!r},0"
                     f"</coordinates></Point></Placemark>")
    parts = ['<?xml version="1.0" encoding="UTF-8"?>', '<kml xmlns="http://www.opengis.net/kml/2.2">',
             f"<Document><name>{escape(name)}</name>",
             '<Style id="hazard"><IconStyle><color>ff0000ff</color><scale>1.2</scale></IconStyle></Style>',
             f"<Folder><name>Hazards</name>{''.join(marks)}</Folder>", "</Document></kml>"]
    return "\n".join(parts) + "\n"


def write_hazard_files(out_dir: str | Path, features: list[dict], *, stem: str = "hazards") -> dict:
    """Write ``{stem}.geojson``, ``{stem}.kml`` and ``{stem}.csv`` atomically; returns their names."""
    out = Path(out_dir)
    atomic_write_text(out / f"{stem}.geojson", geojson_text(features))
    atomic_write_text(out / f"{stem}.kml", hazards_kml_text(features, name=f"photomap {out.resolve().name} hazards"))
    atomic_write_text(out / f"{stem}.csv", hazards_csv_text(features))
    return {"geojson": f"{stem}.geojson", "kml": f"{stem}.kml", "csv": f"{stem}.csv"}
