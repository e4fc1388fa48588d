"""Reading a run folder back (``run.json``, ``trajectory.csv``) for the exports.

A finished run's ``run.json`` lists ``mosaics[]`` (file, ``origin_xy``, ``scale``,
``pixel_scale``, ``bounds``, ``size``, optional ``tiles``/``tile_size``, ``segment`` and a
``georeference`` with ``crs`` ``"EPSG:326zz"`` and ``map_to_crs``: map pixel -> CRS metres,
2x3 or 3x3). A checkpoint (``complete: false``) has neither unless the pipeline wrote them.
"""

from __future__ import annotations

import json
import math
from functools import cached_property
from pathlib import Path

import numpy as np

from photomap.errors import InputError
from photomap.core.records import PoseRow
from photomap.geo.georef import epsg_zone
from photomap.io.trajectory_files import read_trajectory_csv

NO_GEOREFERENCE = ("has no georeference: map with GPS telemetry (--mavlink FILE.tlog or a live "
                   "link) so that run.json lists mosaics[] with georeference.map_to_crs")


def parse_map_to_crs(value) -> np.ndarray:
    """``map_to_crs`` of run.json (2x3 or 3x3 nested lists) as a finite 2x3 float array."""
    try:
        m = np.asarray(value, float)
    except (TypeError, ValueError):
        raise InputError("georeference map_to_crs is not a numeric matrix") from None
    if m.shape == (3, 3):
        m = m[:2]
    if m.shape != (2, 3) or not np.isfinite(m).all() or abs(np.linalg.det(m[:, :2])) < 1e-18:
        raise InputError(f"georeference map_to_crs must be a finite invertible 2x3 or 3x3 matrix")
    return m


def parse_crs(crs) -> int:
    """EPSG code of ``"EPSG:326zz"`` (WGS 84 / UTM only); InputError otherwise."""
    try:
        epsg = int(str(crs).upper().removeprefix("EPSG:"))
        epsg_zone(epsg)
    except ValueError:
        raise InputError(f"georeference CRS {crs!r} is not WGS 84 / UTM (EPSG:326zz or 327zz)") from None
    return epsg


class RunFiles:
    """A run folder: its summary, rows and georeferences. InputError on a missing or bad file."""

    def __init__(self, run_dir: str | Path) -> None:
        self.dir = Path(run_dir)
        path = self.dir / "run.json"
        if not self.dir.is_dir():
            raise InputError(f"run folder not found: {self.dir}")
        try:
            self.summary: dict = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(f"{path} not found: not a photomap run folder") from None
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read {path}: {exc}") from None
        if not isinstance(self.summary, dict):
            raise InputError(f"{path} does not hold a JSON object")

    @property
    def complete(self) -> bool:
        return bool(self.summary.get("complete"))

    @cached_property
    def rows(self) -> list[PoseRow]:
        return read_trajectory_csv(self.dir / "trajectory.csv")

    @property
    def frame_size(self) -> tuple[int, int]:
        size = self.summary.get("frame_size") or []
        if len(size) != 2:
            raise InputError(f"{self.dir / 'run.json'} has no frame_size")
        return int(size[0]), int(size[1])

    @property
    def mosaics(self) -> list[dict]:
        return [m for m in (self.summary.get("mosaics") or []) if isinstance(m, dict)]

    def mosaic(self, segment: int | None = None) -> dict:
        """The ``mosaics[]`` entry of ``segment`` (default: the first, the main map)."""
        maps = self.mosaics
        if not maps:
            state = "is a checkpoint of an unfinished run" if not self.complete else "lists no map"
            raise InputError(f"{self.dir / 'run.json'} {state}: no mosaics[] to export")
        if segment is None:
            return maps[0]
        for m in maps:
            if int(m.get("segment", -1)) == int(segment):
                return m
        raise InputError(f"{self.dir / 'run.json'} has no map of segment {segment}")

    def georeference(self, entry: dict | None = None) -> tuple[np.ndarray, int]:
        """``(map_to_crs 2x3, epsg)`` of a mosaics[] entry (default: the main map)."""
        if entry is None:
            if not self.mosaics:
                geo = self.summary.get("georeference")
                if geo and "map_to_crs" in geo:
                    return parse_map_to_crs(geo["map_to_crs"]), parse_crs(geo.get("crs"))
            entry = self.mosaic()
        geo = entry.get("georeference") or {}
        if "map_to_crs" not in geo or "crs" not in geo:
            raise InputError(f"{self.dir.name}: segment {entry.get('segment', 0)} {NO_GEOREFERENCE}")
        return parse_map_to_crs(geo["map_to_crs"]), parse_crs(geo["crs"])

    def georeferences(self) -> dict[int, tuple[np.ndarray, int]]:
        """Every georeferenced segment: ``{segment: (map_to_crs, epsg)}``; InputError if none."""
        out = {}
        for m in self.mosaics:
            geo = m.get("georeference") or {}
            if "map_to_crs" in geo and "crs" in geo:
                out[int(m.get("segment", 0))] = (parse_map_to_crs(geo["map_to_crs"]), parse_crs(geo["crs"]))
        if not out:
            geo = self.summary.get("georeference") or {}
            if "map_to_crs" in geo and "crs" in geo:  # a checkpoint with the main segment's
                out[int(geo.get("segment", 0))] = (parse_map_to_crs(geo["map_to_crs"]), parse_crs(geo["crs"]))
        if not out:
            if not self.complete:
                raise InputError(f"{self.dir.name} is a checkpoint of an unfinished run: its run.json has no "
                                 f"georeference yet (written at the end of a run with GPS telemetry)")
            raise InputError(f"{self.dir.name} {NO_GEOREFERENCE}")
        return out

    @property
    def video_start_unix(self) -> float | None:
        """UNIX time of frame time 0 (``run.json`` ``video_start_unix``), None if not recorded."""
        v = self.summary.get("video_start_unix")
        return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None

    @property
    def time_offset_s(self) -> float:
        """The telemetry time offset of the run (``telemetry.time_offset_s``; 0 if none)."""
        v = (self.summary.get("telemetry") or {}).get("time_offset_s")
        return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else 0.0
