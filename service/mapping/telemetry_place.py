"""Frames that no registration placed, placed from their telemetry once the telemetry is trusted.

While mapping, a frame that vision leaves unplaced (status ``low_confidence``: open water, glint,
a blank frame) and that has a telemetry sample with a GPS fix is kept aside: its view as the map
would have seen it (rectified, with its validity mask) goes to disk, its sample stays here. Video
keeps at most one such frame every ``_MIN_DT_S`` seconds, and no more than ``_MAX_KEPT`` in all.

Trust is known only once the GPS track is fitted to the vision track, so the placing happens at
the end of the run (:meth:`TelemetryPlacer.place`, after the loop closures' last corrections and
before the final re-render), and only when the telemetry fits the images
(:meth:`~photomap.mapping.telemetry_join.TelemetryJoin.assess` of the main segment's GPS fit):

1. the other map segments whose own GPS fit holds join the main one through the two
   georeferences (their frame centres to WGS84 and back into the main map's pixels, a
   similarity fitted to them): the map is one piece;
2. each kept frame is posed in the main map: the georeference's inverse puts its GPS fix
   (the ground point below the camera, :meth:`~TelemetryJoin.gps_point`) at its map pixel; its
   angle and scale are those of the nearest frame (by index) that vision placed, turned by the
   yaw change and scaled by the height ratio between the two samples (relative, so a constant
   gimbal-yaw or take-off-altitude offset does not matter);
3. it is painted where the map has no ground yet (vision's frames stay on top), its row becomes
   ``registered`` with ``method=telemetry`` (confidence 0); it never enters the loop-closure graph.

Without telemetry, or with telemetry that is refused, nothing changes. Poses map frame pixels
(of the view the map sees) to map pixels, as everywhere (:mod:`photomap.geometry`).
"""

from __future__ import annotations

import logging
import math
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from photomap.geo.georef import Georeference, enu_from_latlon
from photomap.geometry import frame_centre, pose_angle_deg, pose_scale, similarity_fit, to_h
from photomap.io.keyframestore import KeyframeStore
from photomap.mapping.rows import TrajectoryRows
from photomap.mapping.telemetry_join import SegmentFit, TelemetryJoin, frame_ranges
from photomap.telemetry.samples import TelemetrySample

log = logging.getLogger(__name__)

_MIN_DT_S = 0.5      # video: at most one unplaced frame kept this often (stills: every one)
_MAX_KEPT = 2000     # unplaced frames kept in all (JPEG on disk)


@dataclass(frozen=True)
class _Unplaced:
    t: float
    sample: TelemetrySample


class TelemetryPlacer:
    """Unplaced frames with a GPS fix, kept while mapping and placed at the end (module docstring).

    ``join``: the run's telemetry join; ``frame_size``: (w, h) of the input frames; ``folder``:
    where the kept views go (default: a temporary folder, removed by :meth:`close`).
    """

    def __init__(self, join: TelemetryJoin, frame_size: tuple[int, int], folder: str | Path | None = None) -> None:
        self.join = join
        self.frame_size = frame_size
        self._folder = Path(folder) if folder is not None else None
        self._own = folder is None
        self._store: KeyframeStore | None = None
        self._kept: dict[int, _Unplaced] = {}
        self._last_t = -math.inf
        self.skipped = 0  # unplaced frames with a fix not kept (the cap)
        self.placed: list[int] = []
        self.joined: list[int] = []

    def keep(self, index: int, t: float, image: np.ndarray, mask: np.ndarray | None,
             sample: TelemetrySample | None) -> None:
        """Keep frame ``index`` (time ``t``), which vision did not place, if ``sample`` has a fix."""
        if sample is None or sample.lat is None or sample.lon is None:
            return
        if self.join.mode != "stills" and t - self._last_t < _MIN_DT_S:
            return
        if len(self._kept) >= _MAX_KEPT:
            self.skipped += 1
            return
        if self._store is None:
            if self._folder is None:
                self._folder = Path(tempfile.mkdtemp(prefix="photomap-unplaced-"))
            self._store = KeyframeStore(self._folder)
        failures = self._store.failures
        self._store.put_image(index, image, mask)
        if self._store.failures == failures:
            self._kept[index] = _Unplaced(float(t), sample)
            self._last_t = float(t)

    @property
    def kept(self) -> list[int]:
        return sorted(self._kept)

    def place(self, rows: TrajectoryRows, segments: Sequence[int], fit_of: Callable[[int], SegmentFit],
              join_segments: Callable[[int, int, np.ndarray], None],
              paint: Callable[[int, int, np.ndarray, np.ndarray, np.ndarray | None], None]) -> dict:
        """Join segments and place the kept frames when the telemetry is trusted (module doc).

        ``segments``: the segments with a map, the main (largest) first; ``fit_of(segment)``:
        the GPS fit of a segment's vision-placed frames; ``join_segments(segment, into,
        transform)`` joins a segment (3x3 map px of ``segment`` -> map px of ``into``);
        ``paint(segment, index, image, pose, mask)`` paints a frame's new ground. Returns what
        was done (``run.json`` ``telemetry.placed``).
        """
        out = {"kept": len(self._kept), "placed": 0, "joined_segments": 0}
        if not segments or (not self._kept and len(segments) < 2):
            return out
        main = segments[0]
        fit = fit_of(main)
        posed = rows.glued(main)
        check = self.join.time_offset_check([r.t for r in posed], [pose_angle_deg(to_h(r.M)) for r in posed])
        if fit.geo is None or self.join.assess(check, fit):
            return out  # refused (the verdict says why) or no georeference: vision alone
        geo = fit.geo
        for seg in segments[1:]:
            other = fit_of(seg)
            if other.geo is None or other.problem is not None:
                continue
            transform = self._between(rows, seg, other.geo, geo)
            if transform is None:
                continue
            join_segments(seg, main, transform)
            self.joined.append(seg)
            log.info("map segment %d joined segment %d by the GPS (no image links them)", seg, main)
        for index in self.kept:
            k = rows.index_of(index)
            if k is None or rows[k].glued:
                continue
            pose = self._pose(rows, main, geo, index)
            if pose is None:
                continue
            image = self._store.image(index)
            if image is None:
                continue
            paint(main, index, image, pose, self._store.mask(index))
            row = rows[k]
            row.M, row.status, row.segment, row.confidence = pose[:2], "registered", main, 0.0
            row.extra = {**row.extra, "method": "telemetry"}
            self.placed.append(index)
        out.update(placed=len(self.placed), joined_segments=len(self.joined))
        if self.placed or self.joined:
            log.info("telemetry placed %d frame(s) that no registration placed (frames %s)%s",
                     len(self.placed), frame_ranges(self.placed) if self.placed else "none",
                     f"; {len(self.joined)} map segment(s) joined by the GPS" if self.joined else "")
        if self.skipped:
            log.warning("%d unplaced frames with GPS were not kept for placing (at most %d are)",
                        self.skipped, _MAX_KEPT)
        return out

    def _between(self, rows: TrajectoryRows, seg: int, src: Georeference, dst: Georeference) -> np.ndarray | None:
        """3x3 similarity map px of ``seg`` (georeference ``src``) -> map px of ``dst``'s map,
        fitted to the segment's frame centres carried through WGS84."""
        glued = rows.glued_mask(seg)
        if glued.sum() < 2:
            return None
        centre = np.array([*frame_centre(*self.frame_size), 1.0])
        xy = rows.poses(glued) @ centre
        lat, lon = src.to_latlon(xy[:, :2])
        return to_h(similarity_fit(xy[:, :2], self._map_xy(dst, lat, lon)))

    @staticmethod
    def _map_xy(geo: Georeference, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        """WGS84 degrees -> map pixels of ``geo``'s map (the inverse of its ``map_to_enu``)."""
        east, north = enu_from_latlon(np.asarray(lat, float), np.asarray(lon, float), geo.origin_lat, geo.origin_lon)
        inv = np.linalg.inv(to_h(geo.map_to_enu))
        return (np.c_[np.atleast_1d(east), np.atleast_1d(north), np.ones(np.size(east))] @ inv.T)[:, :2]

    def _pose(self, rows: TrajectoryRows, main: int, geo: Georeference, index: int) -> np.ndarray | None:
        """3x3 pose of kept frame ``index`` in the map of ``main`` (module docstring, step 2)."""
        sample = self._kept[index].sample
        glued = np.flatnonzero(rows.glued_mask(main))
        frames = rows.frames[glued]
        if not len(frames):
            return None
        telemetry_placed = np.isin(frames, self.placed)
        vision = glued[~telemetry_placed]
        if not len(vision):
            return None
        near = vision[np.argmin(np.abs(rows.frames[vision] - index))]
        neighbour = rows[int(near)]
        theirs = self.join.kept(neighbour.frame)
        m = to_h(neighbour.M)
        angle, scale = pose_angle_deg(m), pose_scale(m)
        if theirs is not None and theirs.yaw is not None and sample.yaw is not None:
            angle += math.degrees(math.remainder(sample.yaw - theirs.yaw, 2.0 * math.pi))
        if theirs is not None and theirs.height_above_ground and sample.height_above_ground \
                and theirs.height_above_ground > 0 and sample.height_above_ground > 0:
            scale *= sample.height_above_ground / theirs.height_above_ground
        a = math.radians(angle)
        r = scale * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        p = self.join.gps_point(index, sample, *self.frame_size)[:2]
        xy = self._map_xy(geo, np.array([sample.lat]), np.array([sample.lon]))[0]
        pose = np.eye(3)
        pose[:2, :2], pose[:2, 2] = r, xy - r @ p
        return pose

    def close(self) -> None:
        """Remove the kept views (the folder too when it is this placer's own)."""
        if self._folder is not None and self._own:
            shutil.rmtree(self._folder, ignore_errors=True)
        self._store = None
