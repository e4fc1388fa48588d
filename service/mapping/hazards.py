"""Hazard spots on the map: hot spots / colour anomalies tracked over the frames that see them.

:class:`HazardTracker` is a frame sink (:data:`~photomap.mapping.events.FrameSink`; it runs in the
worker thread). For every posed frame it runs the detector (:mod:`photomap.core.hotspots`) on the
input frame, takes each blob to the pixels the frame's pose maps (the event's ``view_points``:
through the lens model when the pipeline undistorted the frame, then the telemetry's rectifying
homography when it rectified it), places it on the map through the pose (-> map px of the
frame's segment) and associates it with the nearest hazard of the same segment within ``match_m``
metres (``match_px`` view pixels when the ground scale is unknown). A hazard seen in
``min_frames`` frames is confirmed: it gets the next id, one STATUSTEXT goes out (when a sender
is given) and the live files are rewritten. Candidates not confirmed within ``forget_frames``
frames of their last sighting are dropped (noise, a glint).

Position = the observations' area-weighted mean; ``uncertainty_m`` = their 1-sigma radial
spread (combined, after the run, with the georeference's GPS RMS). Live, latitude/longitude come
from the telemetry alone (the camera's position, height and heading, as a nadir pinhole camera);
:meth:`HazardTracker.finish` recomputes everything from the final (loop-corrected) poses and the
run's final georeference, merges hazards that end up within the match distance of each other
(one hazard per real spot) and writes ``hazards.geojson``, ``hazards.kml``, ``hazards.csv``.

:meth:`HazardTracker.hazards` is the thread-safe read (e.g. for a map server): a GeoJSON
FeatureCollection dict of the confirmed hazards so far.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from photomap.config import HazardsConfig
from photomap.core.hotspots import HotSpotDetector
from photomap.geo.georef import latlon_from_enu
from photomap.geometry import frame_centre, pose_scale
from photomap.io.hazardfiles import write_hazard_files
from photomap.io.trackfiles import map_to_lonlat
from photomap.mapping.events import FrameEvent
from photomap.mapping.geo_outputs import georefs_from_maps

log = logging.getLogger(__name__)

_POSED = ("reference", "registered")


@dataclass
class _Obs:
    """One sighting: pixel ``(u, v)`` of the view the frame's pose maps (the input frame's
    undistorted, rectified view), its live map position, the live estimate of metres per map
    pixel and of WGS84 (None when unknown)."""

    frame: int
    t: float
    u: float
    v: float
    peak: float
    area: float
    segment: int
    mx: float
    my: float
    mpp: float | None
    lat: float | None
    lon: float | None


@dataclass
class _Track:
    """A hazard (or a candidate): its sightings and their running area-weighted statistics (so
    that its live feature costs the same however many frames saw it)."""

    obs: list[_Obs] = field(default_factory=list)
    segment: int = 0
    x: float = 0.0
    y: float = 0.0
    id: int = 0  # 0 until confirmed
    frames: int = 0  # distinct frames that saw it
    peak: float = -math.inf
    _sw: float = 0.0
    _swx: float = 0.0
    _swy: float = 0.0
    _swr2: float = 0.0  # sum of w (x^2 + y^2)
    _gw: float = 0.0  # sightings with a live WGS84 estimate
    _gwlat: float = 0.0
    _gwlon: float = 0.0
    _mpp_sum: float = 0.0
    _mpp_n: int = 0

    def add(self, ob: _Obs) -> None:
        if not self.obs or self.obs[-1].frame != ob.frame:
            self.frames += 1
        self.obs.append(ob)
        w = ob.area
        self._sw += w
        self._swx += w * ob.mx
        self._swy += w * ob.my
        self._swr2 += w * (ob.mx * ob.mx + ob.my * ob.my)
        self.x, self.y = self._swx / self._sw, self._swy / self._sw
        self.peak = max(self.peak, ob.peak)
        if ob.lat is not None and ob.lon is not None:
            self._gw += w
            self._gwlat += w * ob.lat
            self._gwlon += w * ob.lon
        if ob.mpp:
            self._mpp_sum += ob.mpp
            self._mpp_n += 1

    def feature(self) -> dict:
        """Its live GeoJSON feature (WGS84 from the telemetry alone)."""
        lonlat = (self._gwlon / self._gw, self._gwlat / self._gw) if self._gw > 0 else None
        unc = None
        if self._mpp_n:
            var = max(self._swr2 / self._sw - (self.x * self.x + self.y * self.y), 0.0)
            unc = math.sqrt(var) * self._mpp_sum / self._mpp_n
        first, last = self.obs[0], self.obs[-1]
        return _feature(self.id, (first.frame, first.t), (last.frame, last.t), self.frames, self.peak,
                        self.segment, (self.x, self.y), lonlat, unc)


def _spread(xy: np.ndarray, w: np.ndarray) -> float:
    """Weighted 1-sigma radial spread of points ``(n, 2)`` about their weighted mean."""
    mean = np.average(xy, axis=0, weights=w)
    return float(math.sqrt(np.average(((xy - mean) ** 2).sum(axis=1), weights=w)))


def _feature(hid: int, first: tuple[int, float], last: tuple[int, float], frames: int, peak: float, segment: int,
             xy: tuple[float, float], lonlat: tuple[float, float] | None, uncertainty_m: float | None) -> dict:
    """A hazard's GeoJSON feature: first/last ``(frame, t)``, ``lonlat`` None without WGS84."""
    props = {"id": hid, "first_seen": int(first[0]), "first_seen_t": round(float(first[1]), 3),
             "last_seen": int(last[0]), "last_seen_t": round(float(last[1]), 3), "frames": int(frames),
             "peak": round(float(peak), 3), "segment": segment,
             "x_px": round(xy[0], 3), "y_px": round(xy[1], 3),
             "lat": None if lonlat is None else round(lonlat[1], 9),
             "lon": None if lonlat is None else round(lonlat[0], 9),
             "uncertainty_m": None if uncertainty_m is None else round(uncertainty_m, 3)}
    geom = None if lonlat is None else {"type": "Point", "coordinates": [props["lon"], props["lat"]]}
    return {"type": "Feature", "geometry": geom, "properties": props}


class HazardTracker:
    """Detects, tracks and writes the hazard spots of a run (see the module docstring).

    Parameters
    ----------
    cfg : the ``hazards`` config section.
    out_dir : where the hazard files go (live: rewritten when a hazard is confirmed).
    send_status : sends one STATUSTEXT line per new hazard (e.g. ``TelemetryReader.send_status``), or None.
    """

    def __init__(self, cfg: HazardsConfig, out_dir: str | Path, *,
                 send_status: Callable[[str], None] | None = None) -> None:
        self.cfg = cfg
        self.out_dir = Path(out_dir)
        self.send_status = send_status
        self.match_m, self.match_px = cfg.match_m, cfg.match_px
        self.detector = HotSpotDetector(cfg.mode, k=cfg.k, min_excess=cfg.min_excess, min_area_px=cfg.min_area_px,
                                        max_area_px=cfg.max_area_px, detect_px=cfg.detect_px,
                                        window_frames=cfg.window_frames, hue_deg=cfg.hue_deg,
                                        hue_tol_deg=cfg.hue_tol_deg, min_saturation=cfg.min_saturation,
                                        min_value=cfg.min_value)
        self._lock = threading.Lock()
        self._tracks: list[_Track] = []
        self._next_id = 1
        self._final: list[dict] | None = None
        self.frames = 0
        self.detect_s = 0.0  # the sink's own time, all frames
        self.max_frame_s = 0.0
        self._warned = False
        self._writer: ThreadPoolExecutor | None = None  # live hazard files, when a hazard is confirmed

    # ------------------------------------------------------------------ worker thread
    def on_frame(self, event: FrameEvent) -> None:
        """The frame sink: never raises (one warning, then the tracker stops)."""
        if self._warned or event.pose is None or event.status not in _POSED:
            return
        t0 = time.perf_counter()
        try:
            self._on_frame(event)
        except Exception as exc:  # a sink must not raise: the map goes on without hazards
            self._warned = True
            log.warning("hazard detection stopped at frame %d: %s: %s", event.index, type(exc).__name__, exc)
            log.debug("hazard detection failed", exc_info=True)
        took = time.perf_counter() - t0
        self.frames += 1
        self.detect_s += took
        self.max_frame_s = max(self.max_frame_s, took)

    def _on_frame(self, event: FrameEvent) -> None:
        blobs = self.detector.detect(event.image)
        if not len(blobs):
            with self._lock:
                self._forget(event.index)
            return
        s = event.telemetry
        w, h = event.frame_size
        uv = event.view_points(blobs.xy) if event.view_points is not None else blobs.xy
        pose = np.asarray(event.pose, float)
        mxy = uv @ pose[:, :2].T + pose[:, 2]
        scale = pose_scale(pose)
        ground = None  # metres per view pixel, from the telemetry's height
        if s is not None and s.height_above_ground and s.height_above_ground > 0 and event.focal_px:
            ground = s.height_above_ground / event.focal_px
        mpp = ground / scale if ground is not None and scale > 0 else None
        radius = self.match_m / mpp if mpp else self.match_px * scale
        geo = self._live_latlon(uv, s, ground, (w, h))
        confirmed = []
        with self._lock:
            for k in range(len(blobs)):
                ob = _Obs(event.index, float(event.t), float(uv[k, 0]), float(uv[k, 1]),
                          float(blobs.peak[k]), float(blobs.area[k]), int(event.segment), float(mxy[k, 0]),
                          float(mxy[k, 1]), mpp, *(geo[k] if geo is not None else (None, None)))
                track = self._nearest(ob, radius)
                if track is None:
                    track = _Track(segment=ob.segment)
                    self._tracks.append(track)
                track.add(ob)
                if not track.id and track.frames >= self.cfg.min_frames:
                    track.id = self._next_id
                    self._next_id += 1
                    confirmed.append(track)
            self._forget(event.index)
        for track in confirmed:
            self._announce(track)

    def _nearest(self, ob: _Obs, radius: float) -> _Track | None:
        best, best_d = None, radius
        for track in self._tracks:
            if track.segment != ob.segment:
                continue
            d = math.hypot(track.x - ob.mx, track.y - ob.my)
            if d <= best_d:
                best, best_d = track, d
        return best

    def _forget(self, frame: int) -> None:
        """Drop candidates not confirmed within ``forget_frames`` of their last sighting."""
        limit = self.cfg.forget_frames
        if any(not t.id and frame - t.obs[-1].frame > limit for t in self._tracks):
            self._tracks = [t for t in self._tracks if t.id or frame - t.obs[-1].frame <= limit]

    @staticmethod
    def _live_latlon(uv: np.ndarray, s, ground: float | None, size: tuple[int, int]) -> list | None:
        """(lat, lon) of view pixels from the telemetry alone (nadir pinhole camera at the
        sample's position, image up along its yaw), or None when a value is unknown."""
        if s is None or ground is None or s.lat is None or s.lon is None or s.yaw is None:
            return None
        cx, cy = frame_centre(*size)
        right, forward = (uv[:, 0] - cx) * ground, (cy - uv[:, 1]) * ground
        sy, cy_ = math.sin(s.yaw), math.cos(s.yaw)
        east, north = right * cy_ + forward * sy, -right * sy + forward * cy_
        lat, lon = latlon_from_enu(east, north, s.lat, s.lon)
        return list(zip(np.atleast_1d(lat).tolist(), np.atleast_1d(lon).tolist()))

    def _announce(self, track: _Track) -> None:
        with self._lock:
            p = track.feature()["properties"]
        where = (f"{p['lat']:.6f},{p['lon']:.6f}" if p["lat"] is not None
                 else f"map {p['x_px']:.0f},{p['y_px']:.0f}")
        log.info("hazard %d at %s (frame %d, peak %g)", track.id, where, p["last_seen"], p["peak"])
        if self.send_status is not None:
            self.send_status(f"photomap: hazard {track.id} at {where}")
        features = self.hazards()["features"]
        if self._writer is None:
            self._writer = ThreadPoolExecutor(1, "photomap-hazards")
        self._writer.submit(self._write_live, features)

    def _write_live(self, features: list[dict]) -> None:
        """The live files (the writer thread: an fsync'd rename costs the worker nothing)."""
        try:
            write_hazard_files(self.out_dir, features)
        except OSError as exc:
            log.warning("hazard files not written: %s", exc.strerror or exc)

    # ------------------------------------------------------------------ any thread
    def hazards(self) -> dict:
        """A GeoJSON FeatureCollection dict of the confirmed hazards so far (after :meth:`finish`:
        the final ones). Thread-safe; the dict is the caller's own."""
        with self._lock:
            if self._final is not None:
                features = [dict(f, properties=dict(f["properties"])) for f in self._final]
            else:
                features = [t.feature() for t in self._tracks if t.id]
        features.sort(key=lambda f: f["properties"]["id"])
        return {"type": "FeatureCollection", "features": features}

    # ------------------------------------------------------------------ end of run
    def finish(self, rows: Sequence, maps: Sequence[dict]) -> dict:
        """The final hazards from the final poses (``rows``: the run's rows, RowView/PoseRow with
        ``frame``, ``M``, ``segment``, ``glued``; a pose maps the same view pixels as the live one
        did) and georeference (``maps``: run.json
        ``mosaics[]`` entries); writes the hazard files; returns a summary for the run."""
        if self._writer is not None:  # a live write must not land after the final one
            self._writer.shutdown(wait=True)
            self._writer = None
        with self._lock:
            tracks = [t for t in self._tracks if t.id]
        georefs = georefs_from_maps(maps)
        gps_rms = {int(m.get("segment", 0)): (m.get("georeference") or {}).get("gps_rms_m") for m in maps}
        by_frame = {}
        wanted = {o.frame for t in tracks for o in t.obs}
        for r in rows:
            if r.frame in wanted and r.glued:
                by_frame[r.frame] = r
        placed = []  # per track: (segment, obs, map xy (n, 2)) in the final poses
        for t in tracks:
            groups: dict[int, list] = {}
            for o in t.obs:
                r = by_frame.get(o.frame)
                if r is None:
                    continue
                m = np.asarray(r.M, float)
                groups.setdefault(int(r.segment), []).append((o, m[:2, :2] @ (o.u, o.v) + m[:2, 2]))
            if groups:
                seg = max(groups, key=lambda s: len(groups[s]))
                placed.append((seg, [o for o, _ in groups[seg]], np.array([xy for _, xy in groups[seg]]), t.id))
        features = self._merge_and_describe(placed, georefs, gps_rms)
        with self._lock:
            self._final = features
        info = {"count": len(features), "frames": self.frames,
                "ms_per_frame": round(1000.0 * self.detect_s / self.frames, 3) if self.frames else None,
                "max_ms": round(1000.0 * self.max_frame_s, 3)}
        try:
            info.update(write_hazard_files(self.out_dir, features))
        except OSError as exc:
            log.error("cannot write the hazard files: %s", exc.strerror or exc)
            info["error"] = str(exc.strerror or exc)
        return info

    def _merge_and_describe(self, placed: list, georefs: dict, gps_rms: dict) -> list[dict]:
        """One hazard per spot: tracks whose final positions lie within ``match_m`` (same
        segment, or both georeferenced) are one, with the smallest of their live ids (the ids
        the STATUSTEXT gave)."""
        def metres(seg: int) -> float | None:
            if seg not in georefs:
                return None
            return pose_scale(np.asarray(georefs[seg][0], float))  # metres per map pixel (UTM)

        means = []
        for seg, obs, xy, _ in placed:
            w = np.array([o.area for o in obs])
            mean = np.average(xy, axis=0, weights=w)
            en = None
            if seg in georefs:
                m2c = np.asarray(georefs[seg][0], float)
                en = m2c[:, :2] @ mean + m2c[:, 2]
            means.append((mean, en))
        parent = list(range(len(placed)))

        def root(i: int) -> int:
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        for i in range(len(placed)):
            for j in range(i + 1, len(placed)):
                si, sj = placed[i][0], placed[j][0]
                (mi, ei), (mj, ej) = means[i], means[j]
                if ei is not None and ej is not None and georefs[si][1] == georefs[sj][1]:
                    close = float(np.hypot(*(ei - ej))) <= self.match_m
                elif si == sj:
                    mpp = metres(si)
                    limit = self.match_m / mpp if mpp else self.match_px
                    close = float(np.hypot(*(mi - mj))) <= limit
                else:
                    close = False
                if close:
                    parent[root(j)] = root(i)
        clusters: dict[int, list[int]] = {}
        for i in range(len(placed)):
            clusters.setdefault(root(i), []).append(i)
        out = []
        for members in clusters.values():
            seg = max((placed[i][0] for i in members), key=lambda s: sum(len(placed[i][1]) for i in members
                                                                          if placed[i][0] == s))
            obs = [o for i in members if placed[i][0] == seg for o in placed[i][1]]
            xy = np.concatenate([placed[i][2] for i in members if placed[i][0] == seg])
            w = np.array([o.area for o in obs])
            mean = np.average(xy, axis=0, weights=w)
            spread_px = _spread(xy, w)
            lonlat, unc = None, None
            mpp = metres(seg)
            if mpp is not None:
                m2c, epsg = georefs[seg]
                ll = map_to_lonlat(mean[None, :], m2c, epsg)[0]
                lonlat = (float(ll[0]), float(ll[1]))
                unc = math.hypot(spread_px * mpp, float(gps_rms.get(seg) or 0.0))
            else:
                mpps = [o.mpp for o in obs if o.mpp]
                unc = spread_px * float(np.median(mpps)) if mpps else None
            all_obs = [o for i in members for o in placed[i][1]]
            out.append((min(placed[i][3] for i in members), all_obs, seg, mean, lonlat, unc))
        out.sort(key=lambda c: c[0])
        features = []
        for hid, obs, seg, mean, lonlat, unc in out:
            first, last = min(obs, key=lambda o: o.frame), max(obs, key=lambda o: o.frame)
            features.append(_feature(hid, (first.frame, first.t), (last.frame, last.t), len({o.frame for o in obs}),
                                     max(o.peak for o in obs), seg, (float(mean[0]), float(mean[1])), lonlat, unc))
        return features
