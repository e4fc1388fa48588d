"""What a run writes into its output folder: checkpoints, the final outputs, the georeference.

:class:`RunOutputs` owns the output folder's writing. At a checkpoint the worker hands it the run
summary: it writes ``preview.png`` (from the painter's thumbnails), checkpoints the
full-resolution map (:class:`~photomap.mapping.checkpoint.Checkpointer`) and gives the
``photomap-writer`` thread the trajectory (a copy of the rows' columns), ``run.json`` and, with
telemetry, the live ``track.kml`` / ``track.geojson``. At the end it writes ``trajectory.csv``,
``trajectory.tum``, ``mosaic.png`` (BGRA, transparent where the map is empty; the largest
segment; other segments as ``mosaic_segment{N}.png``; full-resolution ``tiles/`` when the PNG is
downscaled), the georeference (world files, GeoTIFF, track files: :mod:`photomap.mapping.outputs`,
:mod:`photomap.mapping.geo_outputs`) when the telemetry fits the images, every band's map of
multi-band captures and the raw values of 16-bit stills (:mod:`photomap.mapping.band_maps`),
``run.json`` and ``report.html`` (README, "What a run writes"); all atomically. A write that fails (e.g. disk
full) is logged once per output and listed in ``run.json`` ``write_errors``, never raised: when
the map itself could not be written the checkpoint keeps it (``photomap recover``).
"""

from __future__ import annotations

import logging
import shutil
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Iterable, Mapping

import cv2
import numpy as np

from photomap.config import OutputConfig
from photomap.errors import OutputError, PhotomapError
from photomap.geometry import pose_angle_deg
from photomap.io.report import THUMB_PX, write_report
from photomap.io.statestore import MANIFEST
from photomap.io.trajectory_files import sync_filesystem, tum_skipped_message, write_json, write_trajectory_csv, write_tum
from photomap.mapping.band_maps import write_band_maps, write_raw_map
from photomap.mapping.checkpoint import Checkpointer, state_folder
from photomap.mapping.events import GeoreferenceSink
from photomap.mapping.frameprep import FramePrep
from photomap.mapping.geo_outputs import (georefs_from_maps, refresh_track_files, write_geo_outputs, write_main_cog,
                                         write_tile_georeferences)
from photomap.mapping.loopclosure import LoopCloser
from photomap.mapping.outputs import (PngThumbnail, png_placement, remove_sidecars, render_small, write_png,
                                     write_sidecars, write_tiles)
from photomap.mapping.painter import Painter
from photomap.mapping.raw_frames import RawFrameKeeper
from photomap.mapping.rows import RowView, TrajectoryRows
from photomap.mapping.segments import SegmentMaps
from photomap.mapping.telemetry_join import SegmentFit, TelemetryJoin
from photomap.mapping.threads import WorkerFirst, lower_priority
from photomap.mapping.timing import StageTimes

log = logging.getLogger(__name__)

_WRITER_SHARE = 0.1  # a checkpoint's files (whose rows grow with the flight) take at most this share of the time
_WRITER_REST_AFTER_S = 0.05  # ... once the trajectory takes longer than this to write


class RunOutputs:
    """The files of one run in ``out_dir`` (called from the worker; its writer thread writes a
    checkpoint's trajectory, ``run.json`` and track files).

    Parameters
    ----------
    out_dir : path
        Output folder (created; refused when it holds the checkpoint of a run that did not finish).
    cfg : OutputConfig
        The ``output`` section (checkpoints, preview and PNG sizes, GeoTIFF, footprints).
    rows : TrajectoryRows
        The run's trajectory (read; the georeference adds ``lat``/``lon`` to the rows' extras).
    segments : SegmentMaps
        The run's maps (read).
    telemetry : TelemetryJoin, optional
        The telemetry join (GPS fit, georeference, ``run.json`` ``telemetry``).
    first : WorkerFirst
        Paces the writer thread's Python work behind the worker's frames (live).
    input_name : str
        Recorded in the checkpoint manifest.
    band_source : frame source, optional
        Multi-band stills (their ``captures``): every band's map is written at the end.
    raw_frame : callable, optional
        Single-band stills: frame index -> its pixels when 16-bit, else None
        (:meth:`~photomap.drivers.images.ImageFolderSource.raw_frame`): ``map_raw.tif`` at the end.
    frame_prep : FramePrep, optional
        The run's lens undistortion and frame mask: the band and raw maps prepare frames as the map's.
    final_outputs : mapping, optional
        ``name -> write(rows, maps)``: more outputs written at the end, once the poses and the
        georeference are final (``rows``: the run's rows; ``maps``: run.json ``mosaics[]``), each
        returning its summary, which ``run.json`` gets under ``name`` (e.g. ``hazards``:
        :meth:`~photomap.mapping.hazards.HazardTracker.finish`).
    """

    def __init__(self, out_dir: Path, cfg: OutputConfig, rows: TrajectoryRows, segments: SegmentMaps, *,
                 telemetry: TelemetryJoin | None, first: WorkerFirst, input_name: str, band_source=None,
                 raw_frame: Callable[[int], np.ndarray | None] | None = None,
                 frame_prep: FramePrep | None = None,
                 final_outputs: Mapping[str, Callable[[Iterable[RowView], list[dict]], dict]] | None = None) -> None:
        self.out_dir = out_dir
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
        except (FileExistsError, NotADirectoryError):
            raise OutputError(f"output folder {self.out_dir} is a file, not a folder") from None
        except OSError as exc:
            raise OutputError(f"cannot create the output folder {self.out_dir}: {exc.strerror}") from None
        state = state_folder(self.out_dir)
        if (state / MANIFEST).is_file():
            raise OutputError(f"{self.out_dir} holds the checkpoint of a run that did not finish: recover its map "
                              f"with `photomap recover {self.out_dir} --remove-checkpoint` or choose another output folder")
        if state.is_dir():  # a run that stopped before its first checkpoint: nothing to recover
            shutil.rmtree(state, ignore_errors=True)
        self.cfg = cfg
        self._rows = rows
        self.segments = segments
        self.telemetry = telemetry
        self._first = first
        self.input_name = input_name
        self._frame_size: tuple[int, int] | None = None  # (w, h) of the input, from its first frame
        self._loops: LoopCloser | None = None
        self._painter: Painter | None = None
        self._state: Checkpointer | None = None  # the checkpointed full-resolution map
        self._state_refused = False
        self._write_errors: dict[str, str] = {}  # output -> why it could not be written (once each)
        # told each live GPS fit of the main map (writer thread) and the final one: (segment, fit)
        self.on_georeference: GeoreferenceSink | None = None
        self._tum_skipped: list[int] = []  # frames the final trajectory.tum left out (said once)
        # a checkpoint's trajectory.csv (10,000 rows take ~0.25 s to format: a stall in the worker)
        # and run.json are written by this thread; the worker hands it the rows' fields
        self._writer: ThreadPoolExecutor | None = None
        self._checkpoint_files: Future | None = None
        self._files_due = 0.0  # monotonic s: the next checkpoint's files not before (_WRITER_SHARE)
        self.band_source = band_source  # multi-band stills (their ``captures``): every band's map at the end
        self._final_outputs = dict(final_outputs or {})
        self._composite = cfg.composite  # ... and their composite.png's bands
        self._raw_frame = raw_frame  # single-band stills: frame index -> its 16-bit pixels (map_raw.tif)
        self._frame_prep = frame_prep  # the band and raw maps prepare frames as the map's
        self._raw_keeper: RawFrameKeeper | None = None  # a live deep source's raw frames (offer_raw)

    def start(self, frame_size: tuple[int, int], loops: LoopCloser | None, painter: Painter) -> None:
        """The first frame came: its size (w, h), the loop closer (its keyframe graphs go into
        the checkpoint) and the painter (its thumbnails make the preview)."""
        self._frame_size, self._loops, self._painter = frame_size, loops, painter

    def _write_trajectory(self, rows: Iterable[RowView] | None = None) -> None:
        """``trajectory.csv`` and ``trajectory.tum`` of ``rows`` (default: the rows now; iterated
        several times). Frames the TUM file leaves out are said once, by the final rows' write."""
        if self._frame_size is None:
            return
        final, rows = rows is None, (self._rows if rows is None else rows)
        write_trajectory_csv(self.out_dir / "trajectory.csv", rows, self._frame_size)
        if any(r.glued for r in rows):
            skipped: list[int] = []
            write_tum(self.out_dir / "trajectory.tum", rows, self._frame_size, skipped=skipped)
            if final and skipped and skipped != self._tum_skipped:
                self._tum_skipped = skipped
                log.warning(tum_skipped_message(skipped))

    def _write_later(self, summary: dict) -> None:
        """A checkpoint's files, written by the writer thread: the trajectory (from a copy of the
        rows' columns as of now), then ``run.json``, then the live track (with telemetry). The
        worker goes on; while the previous checkpoint's are still being written, this one's are
        skipped (the next has newer ones), and so are those due before the writer has rested
        1 / ``_WRITER_SHARE`` - 1 times the CPU time the last ones took to write, when that was
        more than ``_WRITER_REST_AFTER_S`` (an hour's rows take seconds)."""
        if self._checkpoint_files is not None and not self._checkpoint_files.done():
            return
        if time.monotonic() < self._files_due:
            return
        if self._writer is None:
            self._writer = ThreadPoolExecutor(1, "photomap-writer", initializer=lower_priority)
        # the rows as of now: a copy of their columns (their extras are never changed in place)
        rows = self._rows.copy() if self._frame_size is not None else None
        track = self._live_track(rows, summary)

        def write() -> None:
            cpu = time.thread_time()  # the writer's own work (not its waits for the CPU or the worker)
            if rows is not None:
                self._attempt("trajectory.csv", self._write_trajectory, self._first.paced(rows))
            self._attempt("run.json", write_json, self.out_dir / "run.json", summary)
            if track is not None:
                track()
            took = time.thread_time() - cpu
            if took > _WRITER_REST_AFTER_S:
                self._files_due = time.monotonic() + took * (1.0 / _WRITER_SHARE - 1.0)

        self._checkpoint_files = self._writer.submit(write)

    @property
    def checkpointing(self) -> bool:
        """Checkpoints keep the full-resolution map (``output.checkpoint_map``, with an interval)."""
        return self.cfg.checkpoint_map and self.cfg.checkpoint_interval > 0

    def _attempt(self, name: str, write, *args, **kwargs):
        """``write(*args, **kwargs)``; a disk error is logged once per output (one line) and
        remembered, never raised: mapping and the other outputs go on. Returns its result or None."""
        try:
            return write(*args, **kwargs)
        except (OSError, PhotomapError) as exc:
            self._write_failed(name, exc)
            return None

    def _write_failed(self, name: str, exc: BaseException) -> None:
        """Log a failed write of ``name`` once and remember why (also from the painter's thread)."""
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        if name not in self._write_errors:
            log.error("cannot write %s: %s", name, reason)
        self._write_errors[name] = reason

    def _state_meta(self, summary: dict) -> dict:
        """What the checkpoint manifest records besides the tiles."""
        segments = {}
        order = self.segments.largest()
        for seg in order:
            graph = self._loops.graphs.get(seg) if self._loops is not None else None
            keyframes = [[kf.index, *np.asarray(kf.pose, float).ravel().tolist()] for kf in graph.keyframes] \
                if graph is not None else []
            segments[str(seg)] = {"keyframes": keyframes}
        return {"input": self.input_name, "frame_size": list(self._frame_size or ()),
                "frames_in": summary["frames_in"], "rows": len(self._rows), "order": order,
                "segments": segments, "summary": summary}

    def _save_state(self, summary: dict, *, final: bool = False, extra: dict | None = None) -> bool:
        """Checkpoint the full-resolution map (in the background unless ``final``: then every
        changed tile is written before returning). Returns whether it is written (or under way)."""
        if not self.checkpointing or self._state_refused or not self.segments.mosaics:
            return False
        if self._state is None:
            try:
                self._state = Checkpointer(state_folder(self.out_dir))
            except PhotomapError as exc:
                self._state_refused = True
                log.error("%s: the full-resolution map is not checkpointed", exc)
                return False
        meta = {**self._state_meta(dict(summary)), **(extra or {})}  # the caller goes on changing summary
        if not final:
            return self._state.save(self.segments.mosaics, meta)
        for _ in range(10000):  # the snapshot budget may need several rounds
            self._state.save(self.segments.mosaics, meta, wait=True)
            if self._state.failing or self._state.state.last_pending == 0:
                break
        return self._state.ok()

    def checkpoint(self, summary: dict) -> None:
        """Rewrite trajectory, run.json (``summary``, marked incomplete) and a mosaic preview
        (atomically), and checkpoint the full-resolution map; a write that fails is logged once
        and tried again next time."""
        summary["complete"] = False
        if self.segments.mosaics and self._painter is not None:  # from thumbnails the painter keeps up to date
            segment = self.segments.largest()[0]
            self._attempt("preview.png", self._painter.write_preview, self.out_dir / "preview.png", segment,
                          self.segments.mosaics[segment], self.cfg.preview_px,
                          on_error=lambda exc: self._write_failed("preview.png", exc))
        self._save_state(summary)
        if self._state is not None:
            summary["checkpoint"] = self._state.summary()
        self._write_later(summary)

    def _live_track(self, rows: TrajectoryRows | None, summary: dict) -> Callable[[], None] | None:
        """The writer's job that rewrites track.kml / track.geojson from the main map's current
        GPS fit (a ground station that reloads them sees the coverage grow), or None when there
        is no telemetry. It reads ``rows`` (the checkpoint's copy) and the telemetry join's kept
        samples (each frame's is set once, by the worker, before its row exists): O(rows) work
        (an hour's fit and files take seconds) off the worker. Nothing while the GPS does not fit."""
        join = self.telemetry
        if rows is None or join is None or not self.segments.mosaics or join.stats.stopped_at_frame is not None:
            return None
        main, footprints = self.segments.largest()[0], self.cfg.footprints

        def refresh() -> None:
            fit = self.gps_fit(rows, main)  # no georeference below georef.min_fixes GPS fixes
            if fit.geo is None or fit.problem is not None:
                return
            if self.on_georeference is not None:
                self.on_georeference(main, fit.geo)
            try:
                refresh_track_files(self.out_dir, self._first.paced(rows), self._frame_size,
                                    {main: (fit.geo.map_to_crs[:2], fit.geo.epsg)},
                                    t0_unix=summary.get("video_start_unix"), footprints=footprints)
            except (OSError, PhotomapError) as exc:
                log.warning("track files not refreshed: %s", exc)

        return refresh

    def gps_fit(self, rows: TrajectoryRows, segment: int) -> SegmentFit:
        """The telemetry join's GPS fit of the glued rows of ``segment`` that have a kept sample
        (:meth:`TelemetryJoin.fit_segment`); from the worker or the writer (the rows' copy)."""
        join, (w, h) = self.telemetry, self._frame_size or (0, 0)
        glued = np.flatnonzero(rows.glued_mask(segment))
        found = [(k, f, s) for k, f in self._first.paced(zip(glued.tolist(), rows.frames[glued].tolist()))
                 if (s := join.kept(f))]
        return join.fit_segment(w, h, list(rows.poses(np.array([k for k, _, _ in found], np.int64))),
                                [s for _, _, s in found], [f for _, f, _ in found])

    def _georeference(self, summary: dict, maps: list[dict]) -> None:
        """Metric scale and georeference per segment, world files beside the mosaics, when the
        telemetry fits the images (else none: ``run.json`` ``telemetry.status`` says why)."""
        join = self.telemetry
        w, h = self._frame_size or (0, 0)
        main = maps[0]["segment"] if maps else 0
        posed = self._rows.glued(main)
        check = join.time_offset_check([r.t for r in posed], [pose_angle_deg(np.asarray(r.M)) for r in posed])
        fits = {info["segment"]: self.gps_fit(self._rows, info["segment"]) for info in maps}
        trusted = join.verdict(check, fits.get(main)) == "ok"
        geo_out = {}
        for info in maps:
            seg = info["segment"]
            fit = fits[seg]
            geo = fit.geo if trusted and fit.problem is None else None
            if fit.problem and trusted:
                log.info("segment %d not georeferenced: %s", seg, fit.problem)
            entry: dict = {"metres_per_pixel": fit.metres_per_px if trusted else None}
            if geo is not None:
                if seg == main and self.on_georeference is not None:
                    self.on_georeference(seg, geo)
                world_file = write_sidecars(self.out_dir, info, geo)
                entry.update({"crs": f"EPSG:{geo.epsg}", "map_to_crs": geo.map_to_crs.tolist(),
                              "origin_lat": geo.origin_lat, "origin_lon": geo.origin_lon,
                              "gps_rms_m": geo.rms_m, "scale_source": geo.scale_source,
                              "world_file": world_file})
                centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
                rows = self._rows.glued(seg)
                if rows:  # all at once (one row at a time: 0.17 s a 1000-frame flight)
                    lat, lon = geo.to_latlon(np.array([np.asarray(r.M) @ centre for r in rows]))
                    for r, la, lo in zip(rows, lat.tolist(), lon.tolist()):
                        r.extra = {**r.extra, "lat": la, "lon": lo}
            info["georeference"] = entry
            geo_out[seg] = entry
        if not trusted:  # nothing from telemetry that does not fit stays in the trajectory
            for r in self._rows:
                if any(key in r.extra for key in ("lat", "lon", "alt_m")):
                    r.extra = {k: v for k, v in r.extra.items() if k not in ("lat", "lon", "alt_m")}
        head = geo_out.get(main) if maps else None
        summary["metres_per_pixel"] = head["metres_per_pixel"] if head else None
        summary["georeference"] = head if head and "crs" in head else None
        summary["telemetry"] = {**join.summary(), "time_offset_check": check}
        if trusted and check is not None and check["residual_offset_s"] is not None \
                and abs(check["residual_offset_s"]) > 0.2:
            log.warning("telemetry seems %.2f s off the video (yaw-rate correlation %.2f): "
                        "consider --time-offset %.2f", check["residual_offset_s"],
                        check["correlation"], join.offset + check["residual_offset_s"])
        self._write_trajectory()

    def _band_maps(self, maps: list[dict]) -> dict | None:
        """Every band's map of a multi-band flight (:mod:`photomap.mapping.band_maps`), on the main
        map's final poses; a failure is one line (the main map is written already)."""
        main = maps[0]
        seg = main["segment"]
        georef = georefs_from_maps(maps).get(seg)
        view = self.telemetry.homography if self.telemetry is not None else (lambda index: None)
        try:
            return write_band_maps(self.out_dir, self.band_source, self._rows.glued(seg), self._frame_size,
                                   self.segments.cfg, main, composite=self._composite, georef=georef,
                                   geotiff=self.cfg.geotiff, view=view, prep=self._frame_prep)
        except (OSError, PhotomapError, RuntimeError, ValueError, cv2.error) as exc:
            self._write_failed("band maps", exc)
            return None

    def offer_raw(self, index: int, image: np.ndarray, pose: np.ndarray | None, segment: int) -> None:
        """A raw deep frame (uint16) of a source that delivers them raw, with its live pose: kept
        on disk where the flight has moved on (:class:`~photomap.mapping.raw_frames.RawFrameKeeper`)
        for ``map_raw.tif`` at the end."""
        if self._raw_keeper is None:
            self._raw_keeper = RawFrameKeeper(self.out_dir)
        self._raw_keeper.offer(index, image, pose, segment)

    def _raw_map(self, maps: list[dict]) -> dict | None:
        """``map_raw.tif`` of a georeferenced flight of 16-bit frames (stills, or a live source's
        kept raw frames), on the main map's final poses
        (:func:`photomap.mapping.band_maps.write_raw_map`); a failure is one line."""
        raw_frame = self._raw_frame
        if self._raw_keeper is not None:
            self._raw_keeper.finish()
            raw_frame = self._raw_keeper.read
        main = maps[0]
        georef = georefs_from_maps(maps).get(main["segment"])
        if georef is None or not self.cfg.geotiff or raw_frame is None:
            return None
        view = self.telemetry.homography if self.telemetry is not None else (lambda index: None)
        try:
            return write_raw_map(self.out_dir, raw_frame, self._rows.glued(main["segment"]), self._frame_size,
                                 self.segments.cfg, main, georef, view=view, prep=self._frame_prep)
        except (OSError, PhotomapError, RuntimeError, ValueError, cv2.error) as exc:
            self._write_failed("map_raw.tif", exc)
            return None

    def finish(self, summary_of: Callable[[], dict], timing: StageTimes, t0: float, *,
               placed: dict | None = None) -> dict:
        """Write the final outputs once the map is final; returns the run summary (``summary_of()``
        once the trajectory is written; also in ``run.json``, with ``timing``'s stages, the
        ``final_outputs`` one from ``t0``, perf_counter s). ``placed``: what telemetry placed of
        what vision did not (``run.json`` ``telemetry.placed``; :mod:`photomap.mapping.telemetry_place`).

        The georeference is fitted on the PNGs' placements first; the main map's GeoTIFF is then
        written on the ``photomap-cog`` thread while this one writes the PNGs (the report's map
        from the main one's bands), the tiles and ``tiles.vrt`` (all only read the map).
        Every write is attempted: one that fails (e.g. disk full) is reported in one line and in
        ``write_errors``; when the map itself could not be written, the checkpoint keeps it
        (``photomap recover``), else the checkpoint is removed."""
        if self._state is not None:
            self._state.wait()
        if self._writer is not None:  # a checkpoint's trajectory.csv must not land after the final one
            self._writer.shutdown(wait=True)
        if self._loops is not None and self._loops.store.folder.parent == state_folder(self.out_dir):
            shutil.rmtree(self._loops.store.folder, ignore_errors=True)  # re-rendered: room for the outputs
        self._attempt("trajectory.csv", self._write_trajectory)
        summary = summary_of()
        maps, unwritten = [], []
        max_px = self.cfg.max_mosaic_px
        order = self.segments.largest()
        names = {seg: "mosaic.png" if rank == 0 else f"mosaic_segment{seg}.png" for rank, seg in enumerate(order)}
        # the placements (and so the georeference) come before the PNGs: the main map's GeoTIFF is
        # written on a thread while the PNGs and tiles are (all only read the map; 2 cores)
        placements = {}
        for seg in order:
            info = png_placement(names[seg], self.segments.mosaics[seg], max_px)
            if info is not None:
                info["segment"] = seg
                placements[seg] = info
                self._attempt(info["file"], remove_sidecars, self.out_dir, info["file"])  # an earlier run's
        if self.telemetry is not None:
            self._attempt("georeference", self._georeference, summary, list(placements.values()))
            summary["telemetry"]["placed"] = placed
        cog = beside = tile_geo = None
        if self.telemetry is not None and self.cfg.geotiff and order and order[0] in placements:
            beside = ThreadPoolExecutor(1, "photomap-cog")
            cog = beside.submit(write_main_cog, self.out_dir, placements[order[0]], self.segments.mosaics)
        thumbnail = PngThumbnail(THUMB_PX)  # the report's map, from the main PNG's bands
        try:
            for rank, seg in enumerate(order):
                name = names[seg]
                info = self._attempt(name, write_png, self.out_dir / name, self.segments.mosaics[seg], max_px,
                                     thumbnail=thumbnail if rank == 0 else None)
                if info is None:
                    if seg in placements:
                        unwritten.append(placements[seg])
                        remove_sidecars(self.out_dir, name)  # no PNG for them
                    continue
                info["segment"] = seg
                if info["scale"] < 1.0:
                    tiles = self.out_dir / ("tiles" if rank == 0 else f"tiles_segment{seg}")
                    if not self._attempt(f"{tiles.name}/", lambda t=tiles, m=self.segments.mosaics[seg]: write_tiles(t, m, sync=False) or True):
                        unwritten.append(info)
                    info["tiles"] = tiles.name
                    info["tile_size"] = self.segments.mosaics[seg].tile_size
                if "georeference" in placements.get(seg, {}):
                    info["georeference"] = placements[seg]["georeference"]
                maps.append(info)
            # tiles.vrt while the GeoTIFF is still being written (a world file per tile: photomap export --tile-georef)
            tile_geo = write_tile_georeferences(self.out_dir, maps, sync=False) if self.telemetry is not None else None
        finally:
            if beside is not None:
                beside.shutdown(wait=True)
        cog_info = self._attempt("map.tif", cog.result) if cog is not None else None
        (self.out_dir / "preview.png").unlink(missing_ok=True)
        if self.telemetry is not None:
            exports = self._attempt("geo outputs", write_geo_outputs, self.out_dir, maps, self.segments.mosaics, self._rows,
                                    self._frame_size, t0_unix=summary["video_start_unix"],
                                    cog=False, footprints=self.cfg.footprints, cog_info=cog_info,
                                    tile_georeference=tile_geo)
            if exports and self.band_source is None and maps:
                raw = self._raw_map(maps)
                if raw:
                    exports["raw"] = raw
            if exports:
                summary["exports"] = exports
        if self.band_source is not None and maps:
            bands = self._band_maps(maps)
            if bands:
                summary["bands"] = bands
        if self._raw_keeper is not None:
            self._raw_keeper.close()
        summary["mosaics"] = maps
        for name, write in self._final_outputs.items():  # e.g. the hazards, from the final poses
            summary[name] = self._attempt(name, write, self._rows, maps)
        summary["complete"] = True
        # the thousands of tiles and world files, unsynced so far, durable before the checkpoint goes
        self._attempt("the outputs (sync to disk)", sync_filesystem, self.out_dir)
        if unwritten:  # the map is not all on disk as outputs: the checkpoint must hold it
            georefs = {str(i["segment"]): i["georeference"] for i in maps + unwritten
                       if (i.get("georeference") or {}).get("crs")}
            kept = self._save_state(summary, final=True, extra={"georeference": georefs, "complete": True})
            where = state_folder(self.out_dir)
            names = ", ".join(i["file"] for i in unwritten)
            if kept:
                log.error("the map could not be written in full (%s); it is kept in %s: free space and run "
                          "`photomap recover %s`", names, where, self.out_dir)
            elif self._state is not None and self._state.state.generation > 0:
                log.error("the map could not be written (%s); checkpoint %d in %s holds it as it was then: "
                          "free space and run `photomap recover %s`", names, self._state.state.generation,
                          where, self.out_dir)
                kept = True
            else:
                log.error("the map could not be written (%s) and no checkpoint holds it", names)
            summary["map_kept_in"] = where.name if kept else None
            summary["map_unwritten"] = [i["file"] for i in unwritten]
        elif self._state is not None:
            self._state.remove()
        elif self.checkpointing:  # keyframes kept for a restart: not needed any more
            shutil.rmtree(state_folder(self.out_dir), ignore_errors=True)
        if self._state is not None:
            summary["checkpoint"] = self._state.summary()
        if self._write_errors:
            summary["write_errors"] = dict(self._write_errors)
        timing.add("final_outputs", time.perf_counter() - t0)
        summary["timing_ms"] = timing.summary()
        self._attempt("run.json", write_json, self.out_dir / "run.json", summary)
        try:  # report.html: the flight at a glance, offline (its map from the PNG's bands, else the tiles)
            main = self.segments.mosaics.get(maps[0]["segment"]) if maps else None
            small = thumbnail.image() if maps and maps[0]["segment"] == order[0] else None
            if small is None and main is not None:
                small = render_small(main, min(THUMB_PX, max(maps[0]["size"])))
            write_report(self.out_dir, map_image=small)
        except (OSError, ValueError, PhotomapError) as exc:
            log.warning("report.html not written: %s", exc)
        return summary
