"""The flight as vector data: ``track.geojson`` and ``track.kml`` (track, footprints, coverage).

For ground stations and GIS: QGIS and QGroundControl/Mission Planner load GeoJSON/KML; Google
Earth opens the KML (and, with :func:`mosaic_overlay`, drapes ``mosaic.png`` over the terrain).
Every position goes map pixel -> UTM (the segment's ``map_to_crs``) -> WGS84.

Features, per georeferenced map segment:

- ``track``: LineString through the frame centres ``((w - 1) / 2, (h - 1) / 2)`` of the glued
  frames (``reference``/``registered``), in frame order.
- ``footprint``: Polygon of a frame's outline (the outer edges of its border pixels, the
  rectangle ``(-0.5, -0.5) .. (w - 0.5, h - 0.5)``) through its pose; which frames: see
  :func:`select_footprints`.
- ``coverage``: (Multi)Polygon of the ground that the glued frames cover (their footprints'
  union, rasterised on a grid of about ``coverage_cells`` cells across and traced back, holes
  included), with its area (``area_m2``, counted on the grid in UTM metres).

GeoJSON follows RFC 7946 (WGS84 longitude, latitude; exterior rings counter-clockwise). All files
are written atomically, so a ground station reloading them during a flight never reads half a file.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterable, Sequence
from xml.sax.saxutils import escape

import cv2
import numpy as np

from photomap.errors import InputError
from photomap.core.records import PoseRow
from photomap.geo.georef import compose, png_to_map, utm_inverse
from photomap.geometry import pose_scale
from photomap.io.trajectory_files import atomic_write_text

FOOTPRINT_MODES = ("all", "keyframes", "spaced", "none")

Georefs = dict[int, tuple[np.ndarray, int]]  # segment -> (map_to_crs 2x3, epsg)


def _crs(m: np.ndarray, xy: np.ndarray) -> np.ndarray:
    m = np.asarray(m, float)
    return np.atleast_2d(np.asarray(xy, float)) @ m[:, :2].T + m[:, 2]


def map_to_lonlat(xy: np.ndarray, map_to_crs: np.ndarray, epsg: int) -> np.ndarray:
    """Map pixels ``(n, 2)`` -> ``(n, 2)`` WGS84 ``(lon, lat)`` degrees (GeoJSON order)."""
    en = _crs(map_to_crs, xy)
    lat, lon = utm_inverse(en[:, 0], en[:, 1], epsg)
    return np.c_[lon, lat]


def frame_outline(frame_size: tuple[int, int]) -> np.ndarray:
    """(4, 2) frame pixels of the frame's outer corners, clockwise on screen from the top-left."""
    w, h = frame_size
    return np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])


def _pose(row: PoseRow) -> np.ndarray:
    return np.asarray(row.M, float).reshape(-1, 3)[:2]


def select_footprints(rows: Sequence[PoseRow], frame_size: tuple[int, int], mode: str = "spaced",
                      spacing: float = 0.5) -> list[PoseRow]:
    """The glued rows whose footprints to draw.

    ``all``: every one. ``keyframes``: the rows whose ``extra["keyframe"]`` is true (the
    first glued row of each segment too); ``spaced`` when no row says so. ``spaced``: the first
    of each segment, then each frame whose centre moved at least ``spacing`` times the frame's
    shorter side (in map pixels, through its pose's scale) from the last one drawn. ``none``.
    """
    if mode not in FOOTPRINT_MODES:
        raise InputError(f"footprints must be one of {', '.join(FOOTPRINT_MODES)}, got {mode!r}")
    glued = [r for r in rows if r.glued]
    if mode == "none":
        return []
    if mode == "all":
        return glued
    if mode == "keyframes" and any(r.extra.get("keyframe") for r in glued):
        seen: set[int] = set()
        out = []
        for r in glued:
            if r.extra.get("keyframe") or r.segment not in seen:
                out.append(r)
                seen.add(r.segment)
        return out
    w, h = frame_size
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
    last: dict[int, np.ndarray] = {}
    out = []
    for r in glued:
        m = _pose(r)
        c = m @ centre
        s = pose_scale(m)
        if r.segment not in last or np.linalg.norm(c - last[r.segment]) >= spacing * min(w, h) * s:
            out.append(r)
            last[r.segment] = c
    return out


@dataclass
class Coverage:
    """Covered ground of a segment: polygons in map pixels (each ``[exterior, *holes]``, rings
    ``(n, 2)``) and the area in square metres."""

    polygons: list[list[np.ndarray]]
    area_m2: float


def coverage(rows: Iterable[PoseRow], frame_size: tuple[int, int], map_to_crs: np.ndarray | None = None,
             cells: int = 1024) -> Coverage:
    """Union of the glued frames' footprints (rasterised on ``cells`` cells across the extent).

    ``area_m2`` is the number of covered cells times a cell's area through ``map_to_crs``
    (0 without it); the outline follows the covered cells to a quarter of a cell.
    """
    quads = [(_pose(r) @ np.c_[frame_outline(frame_size), np.ones(4)].T).T for r in rows if r.glued]
    if not quads:
        return Coverage([], 0.0)
    pts = np.concatenate(quads)
    lo = pts.min(axis=0)
    cell = max(float((pts.max(axis=0) - lo).max()) / max(int(cells), 16), 1e-9)
    size = np.ceil((pts.max(axis=0) - lo) / cell).astype(int) + 3
    grid = np.zeros((size[1], size[0]), np.uint8)
    origin = lo - cell  # grid cell (i, j) spans origin + [i, i+1) * cell
    shift = 4
    for q in quads:
        # cell centres at origin + (i + 0.5) cell; fillConvexPoly fills pixels whose centre is inside
        g = np.rint(((q - origin) / cell - 0.5) * (1 << shift)).astype(np.int32)
        cv2.fillConvexPoly(grid, g, 1, lineType=cv2.LINE_8, shift=shift)
    mpp2 = abs(float(np.linalg.det(np.asarray(map_to_crs, float)[:, :2]))) if map_to_crs is not None else 0.0
    area = float(grid.sum()) * cell * cell * mpp2
    # outer edges of the covered cells: trace a 2x upsampled grid (a cell -> 2x2 corners)
    up = cv2.resize(grid, (grid.shape[1] * 2, grid.shape[0] * 2), interpolation=cv2.INTER_NEAREST)
    contours, hierarchy = cv2.findContours(up, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    polygons: list[list[np.ndarray]] = []
    if hierarchy is None:
        return Coverage([], area)
    hier = hierarchy[0]

    def ring(c: np.ndarray) -> np.ndarray:
        c = cv2.approxPolyDP(c, 2.0, True).reshape(-1, 2).astype(float)
        # up-grid pixel centre k -> edge position (k + 0.5) / 2 cells (boundary pixels straddle)
        return origin + (c + 0.5) / 2.0 * cell

    for i, h in enumerate(hier):
        if h[3] != -1:
            continue
        rings = [ring(contours[i])]
        child = h[2]
        while child != -1:
            if len(contours[child]) >= 3:
                rings.append(ring(contours[child]))
            child = hier[child][0]
        if len(rings[0]) >= 3:
            polygons.append(rings)
    return Coverage(polygons, area)


def _signed_area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def _geo_ring(ring_px: np.ndarray, map_to_crs: np.ndarray, epsg: int, ccw: bool) -> list[list[float]]:
    ll = map_to_lonlat(ring_px, map_to_crs, epsg)
    if (_signed_area(ll) > 0) != ccw:
        ll = ll[::-1]
    ll = np.vstack([ll, ll[:1]])
    return [[round(float(lon), 9), round(float(lat), 9)] for lon, lat in ll]


def _iso(t_unix: float) -> str:
    return datetime.fromtimestamp(t_unix, tz=timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def track_features(rows: Sequence[PoseRow], frame_size: tuple[int, int], georefs: Georefs, *,
                   footprints: str = "spaced", t0_unix: float | None = None,
                   coverage_cells: int = 1024) -> list[dict]:
    """GeoJSON features (dicts) of the track, footprints and coverage of each georeferenced
    segment. ``t0_unix``: UNIX time of frame time 0, to stamp footprints with ``time`` (ISO 8601
    UTC) and ``t_unix``."""
    if frame_size is None or len(frame_size) != 2:
        raise InputError("track files need the frame size (w, h)")
    w, h = int(frame_size[0]), int(frame_size[1])
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
    rows = list(rows)  # the same row objects on every pass (TrajectoryRows makes new views each time)
    chosen = {id(r) for r in select_footprints(rows, (w, h), footprints)}
    feats: list[dict] = []
    for seg in sorted(georefs):
        m2c, epsg = georefs[seg]
        seg_rows = [r for r in rows if r.glued and r.segment == seg]
        if not seg_rows:
            continue
        centres = np.array([_pose(r) @ centre for r in seg_rows])
        ll = map_to_lonlat(centres, m2c, epsg)
        coords = [[round(float(a), 9), round(float(b), 9)] for a, b in ll]
        geom = ({"type": "LineString", "coordinates": coords} if len(coords) > 1
                else {"type": "Point", "coordinates": coords[0]})
        feats.append({"type": "Feature", "geometry": geom,
                      "properties": {"kind": "track", "segment": seg, "frames": len(seg_rows),
                                     "first_frame": seg_rows[0].frame, "last_frame": seg_rows[-1].frame,
                                     "crs": f"EPSG:{epsg}"}})
        for r in seg_rows:
            if id(r) not in chosen:
                continue
            outline = (_pose(r) @ np.c_[frame_outline((w, h)), np.ones(4)].T).T
            props = {"kind": "footprint", "segment": seg, "frame": r.frame, "t": round(float(r.t), 6),
                     "confidence": None if not math.isfinite(r.confidence) else round(float(r.confidence), 4)}
            if t0_unix is not None and math.isfinite(r.t):
                props["t_unix"] = round(t0_unix + float(r.t), 3)
                props["time"] = _iso(t0_unix + float(r.t))
            feats.append({"type": "Feature", "properties": props,
                          "geometry": {"type": "Polygon", "coordinates": [_geo_ring(outline, m2c, epsg, True)]}})
        cov = coverage(seg_rows, (w, h), m2c, coverage_cells)
        if cov.polygons:
            polys = [[_geo_ring(rg, m2c, epsg, k == 0) for k, rg in enumerate(p)] for p in cov.polygons]
            geom = ({"type": "Polygon", "coordinates": polys[0]} if len(polys) == 1
                    else {"type": "MultiPolygon", "coordinates": polys})
            feats.append({"type": "Feature", "geometry": geom,
                          "properties": {"kind": "coverage", "segment": seg, "area_m2": round(cov.area_m2, 2),
                                         "area_km2": round(cov.area_m2 / 1e6, 6)}})
    return feats


def geojson_text(features: list[dict]) -> str:
    """A FeatureCollection (RFC 7946) as text."""
    return json.dumps({"type": "FeatureCollection", "features": features}, separators=(",", ":")) + "\n"


def _kml_coords(coords: list) -> str:
    return " ".join(f"{lon!r},{lat!r},0" for lon, lat in coords)


def _kml_polygon(rings: list) -> str:
    out = ["<Polygon><tessellate>1</tessellate>",
           f"<outerBoundaryIs><LinearRing><coordinates>{_kml_coords(rings[0])}</coordinates></LinearRing></outerBoundaryIs>"]
    for hole in rings[1:]:
        out.append(f"<innerBoundaryIs><LinearRing><coordinates>{_kml_coords(hole)}</coordinates></LinearRing></innerBoundaryIs>")
    out.append("</Polygon>")
    return "".join(out)


def kml_text(features: list[dict], *, name: str = "photomap flight",
             overlay: tuple[str, list[tuple[float, float]]] | None = None) -> str:
    """KML 2.2 of :func:`track_features`: folders Track, Footprints, Coverage (and Map: a
    ``gx:LatLonQuad`` ground overlay of ``overlay = (href, [(lon, lat) lower-left, lower-right,
    upper-right, upper-left])``, see :func:`mosaic_overlay`)."""
    folders: dict[str, list[str]] = {"track": [], "footprint": [], "coverage": []}
    for f in features:
        p, g = f["properties"], f["geometry"]
        kind = p["kind"]
        if kind == "track":
            label = f"track, segment {p['segment']}"
            geom = (f"<LineString><tessellate>1</tessellate><coordinates>{_kml_coords(g['coordinates'])}"
                    f"</coordinates></LineString>" if g["type"] == "LineString"
                    else f"<Point><coordinates>{_kml_coords([g['coordinates']])}</coordinates></Point>")
            extra = ""
        elif kind == "footprint":
            label = f"frame {p['frame']}"
            geom = _kml_polygon(g["coordinates"])
            extra = f"<TimeStamp><when>{p['time']}</when></TimeStamp>" if "time" in p else ""
        else:
            label = f"coverage, segment {p['segment']}: {p['area_km2']:.4f} km2"
            polys = [g["coordinates"]] if g["type"] == "Polygon" else g["coordinates"]
            geom = "<MultiGeometry>" + "".join(_kml_polygon(pl) for pl in polys) + "</MultiGeometry>"
            extra = ""
        data = "".join(f'<Data name="{escape(str(k))}"><value>{escape(str(v))}</value></Data>'
                       for k, v in p.items() if v is not None)
        folders[kind].append(f"<Placemark><name>{escape(label)}</name>{extra}<styleUrl>#{kind}</styleUrl>"
                             f"<ExtendedData>{data}</ExtendedData>{geom}</Placemark>")
    parts = ['<?xml version="1.0" encoding="UTF-8"?>',
             '<kml xmlns="http://www.opengis.net/kml/2.2" xmlns:gx="http://www.google.com/kml/ext/2.2">',
             f"<Document><name>{escape(name)}</name>",
             '<Style id="track"><LineStyle><color>ff00ffff</color><width>3</width></LineStyle></Style>',
             '<Style id="footprint"><LineStyle><color>ffff8800</color><width>1</width></LineStyle>'
             '<PolyStyle><color>22ff8800</color></PolyStyle></Style>',
             '<Style id="coverage"><LineStyle><color>ff0000ff</color><width>2</width></LineStyle>'
             '<PolyStyle><fill>0</fill></PolyStyle></Style>']
    if overlay is not None:
        href, quad = overlay
        parts.append(f"<Folder><name>Map</name><GroundOverlay><name>{escape(href)}</name>"
                     f"<Icon><href>{escape(href)}</href></Icon><gx:LatLonQuad><coordinates>"
                     f"{_kml_coords([list(q) for q in quad])}</coordinates></gx:LatLonQuad></GroundOverlay></Folder>")
    for kind, title in (("coverage", "Coverage"), ("track", "Track"), ("footprint", "Footprints")):
        if folders[kind]:
            parts.append(f"<Folder><name>{title}</name>{''.join(folders[kind])}</Folder>")
    parts.append("</Document></kml>")
    return "\n".join(parts) + "\n"


def mosaic_overlay(entry: dict, map_to_crs: np.ndarray, epsg: int) -> tuple[str, list[tuple[float, float]]]:
    """``(href, quad)`` for :func:`kml_text`: a mosaic PNG (run.json ``mosaics[]`` entry with
    ``file``, ``origin_xy``, ``pixel_scale``/``scale``, ``size``) and its outer corners as
    ``(lon, lat)``: lower-left, lower-right, upper-right, upper-left (KML's order)."""
    W, H = entry["size"]
    png = compose(map_to_crs, png_to_map(entry["origin_xy"], entry.get("pixel_scale") or entry["scale"]))
    corners = np.array([[-0.5, H - 0.5], [W - 0.5, H - 0.5], [W - 0.5, -0.5], [-0.5, -0.5]])
    ll = map_to_lonlat(corners, png, epsg)
    return entry["file"], [(float(a), float(b)) for a, b in ll]


def write_track_files(out_dir: str | Path, rows: Sequence[PoseRow], frame_size: tuple[int, int],
                      georefs: Georefs, *, footprints: str = "spaced", t0_unix: float | None = None,
                      overlay: tuple[str, list[tuple[float, float]]] | None = None,
                      stem: str = "track") -> dict:
    """Write ``{stem}.geojson`` and ``{stem}.kml`` atomically (safe at every checkpoint).

    Parameters
    ----------
    rows : the run's rows (``PoseRow``; poses map frame pixels to map pixels of their segment).
    frame_size : ``(w, h)`` of the input frames.
    georefs : ``{segment: (map_to_crs 2x3, epsg)}``; segments missing here are left out.
    footprints : which frames get a footprint (:func:`select_footprints`).
    t0_unix : UNIX time of frame time 0 (footprint time stamps), or None.
    overlay : a map image to drape in the KML (:func:`mosaic_overlay`).

    Returns ``{"geojson", "kml", "features", "area_m2"}`` (area over all segments).
    """
    out = Path(out_dir)
    feats = track_features(rows, frame_size, georefs, footprints=footprints, t0_unix=t0_unix)
    atomic_write_text(out / f"{stem}.geojson", geojson_text(feats))
    atomic_write_text(out / f"{stem}.kml", kml_text(feats, name=f"photomap {out.resolve().name}", overlay=overlay))
    area = sum(f["properties"]["area_m2"] for f in feats if f["properties"]["kind"] == "coverage")
    return {"geojson": f"{stem}.geojson", "kml": f"{stem}.kml", "features": len(feats), "area_m2": area}
