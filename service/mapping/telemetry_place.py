"""Frames that no registration placed, placed from their telemetry once the telemetry is trusted.

While mapping, a frame that vision leaves unplaced (status ``low_confidence``: open water, glint,
a blank frame) and that has a telemetry sample with a GPS fix is kept aside: its view as the map
would have seen it (rectified, with its validity mask) goes to disk, its sample stays here. Video
keeps at most one such frame every ``_MIN_DT_S`` seconds, and no more than ``_MAX_KEPT`` in all.

Trust is known only once the GPS track is fitted to the vision track, so the placing happens at
the end of the run (:meth:`TelemetryPlacer.place`, after the loop closures' last corrections and
before the final re-render), and only when the telemetry fits the images
(:meth:`~photomap.mapping.telemetry_join.TelemetryJoin.assess` of the main segment's GPS fit):

1. the other map segments whose own GPS fit holds join the main one: their GPS fixes, put into
   the main map's pixels by its georeference, fix the shift of the join; its rotation and scale
   come from the attitude (yaw minus pose angle, height over pose scale, compared between the
   two maps: constant offsets cancel) where both maps tell it (else they are fitted too): the map
   is one piece;
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
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from photomap.geo.georef import Georeference, enu_from_latlon
from photomap.geometry import pose_angle_deg, pose_scale, similarity_fit, to_h
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
    where the kept views go, a folder of its own in the run's scratch space (the maps' cache,
    :meth:`~photomap.mapping.segments.SegmentMaps.cache`): made with the first kept view,
    removed by :meth:`close`.
    """

    def __init__(self, join: TelemetryJoin, frame_size: tuple[int, int], folder: str | Path) -> None:
        self.join = join
        self.frame_size = frame_size
        self._folder = Path(folder)
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
            transform = self._between(rows, seg, main, geo)
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

    def _between(self, rows: TrajectoryRows, seg: int, main: int, dst: Georeference) -> np.ndarray | None:
        """3x3 similarity map px of ``seg`` -> map px of ``main`` (georeference ``dst``).

        Its rotation and scale come from the attitude where both maps tell it (the yaw's offset
        from the pose angles and the heights over the pose scales, each map's mean: a constant
        compass or altitude offset cancels); then the fixes of both maps are fitted at once, in
        complex numbers on the main georeference's tangent plane (east, south): ``g = a z + b``
        for the main map's fixes, ``g = a r z + c + b`` for the segment's (``r`` the known
        rotation and scale, ``c = a t``), linear in ``a, b, c``; the join is ``z -> r z + c / a``.
        So the fixes' noise moves little more than its shift. Without the attitude the segment's
        fixes are fitted on their own, put at their main-map pixels by ``dst``."""
        pts: dict[int, tuple[list[complex], list[complex]]] = {main: ([], []), seg: ([], [])}
        rel: dict[int, list[tuple[float, float, TelemetrySample]]] = {main: [], seg: []}
        for s in (main, seg):
            for k in np.flatnonzero(rows.glued_mask(s)):
                row = rows[int(k)]
                sample = self.join.kept(row.frame)
                if sample is None:
                    continue
                m = to_h(row.M)
                rel[s].append((pose_angle_deg(m), pose_scale(m), sample))
                if sample.lat is not None and sample.lon is not None:
                    p = m @ self.join.gps_point(row.frame, sample, *self.frame_size)
                    east, north = enu_from_latlon(np.array([sample.lat]), np.array([sample.lon]),
                                                  dst.origin_lat, dst.origin_lon)
                    pts[s][0].append(complex(p[0], p[1]))
                    pts[s][1].append(complex(float(east[0]), -float(north[0])))
        if len(pts[seg][0]) < 2:
            return None
        offsets = {s: [math.radians(a) - v.yaw for a, _, v in rel[s] if v.yaw is not None] for s in rel}
        per_m = {s: [c / v.height_above_ground for _, c, v in rel[s]
                     if v.height_above_ground and v.height_above_ground > 0] for s in rel}
        steady = all(len(o) >= 2 and np.hypot(np.cos(o).mean(), np.sin(o).mean()) >= 0.9 for o in offsets.values())
        if not steady or not all(per_m.values()) or len(pts[main][0]) < 2:
            src = np.array([[z.real, z.imag] for z in pts[seg][0]])
            enu = np.array([[g.real, -g.imag] for g in pts[seg][1]])
            inv = np.linalg.inv(to_h(dst.map_to_enu))
            return to_h(similarity_fit(src, (np.c_[enu, np.ones(len(enu))] @ inv.T)[:, :2]))
        a_main, a_seg = (math.atan2(np.sin(offsets[s]).mean(), np.cos(offsets[s]).mean()) for s in (main, seg))
        r = float(np.median(per_m[main]) / np.median(per_m[seg])) * complex(math.cos(a_main - a_seg),
                                                                             math.sin(a_main - a_seg))
        za, ga = np.array(pts[main][0]), np.array(pts[main][1])
        zb, gb = np.array(pts[seg][0]), np.array(pts[seg][1])
        design = np.vstack([np.c_[za, np.ones_like(za), np.zeros_like(za)],
                            np.c_[r * zb, np.ones_like(zb), np.ones_like(zb)]])
        (a, _, c), *_ = np.linalg.lstsq(design, np.concatenate([ga, gb]), rcond=None)
        t = c / a
        return np.array([[r.real, -r.imag, t.real], [r.imag, r.real, t.imag], [0.0, 0.0, 1.0]])

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
        """Remove the kept views and their folder."""
        if self._store is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
        self._store = None
