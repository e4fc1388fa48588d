"""The mapping pipeline: frames in, a growing photo map and a trajectory out.

Threads live here (and in the drivers): a file source is decoded by a prefetch thread into a
bounded queue (replay never drops); a live source already drops its oldest frames when the worker
falls behind. One worker thread runs prepare -> register -> pose -> map update for each frame and
checkpoints the outputs periodically; :meth:`MappingPipeline.stop` (SIGINT/SIGTERM) ends capture,
lets the worker finish, and the outputs are written.

Files written to the output folder (DESIGN.md section 4): ``mosaic.png`` (BGRA, transparent where
the map is empty; the largest segment; other segments as ``mosaic_segment{N}.png``),
``trajectory.csv``, ``trajectory.tum`` and ``run.json``. All are written atomically.
"""

from __future__ import annotations

import logging
import math
import queue
import shutil
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from photomap.drivers.capture import Frame, FrameSource
from photomap.errors import ConfigError
from photomap.geo.georef import aux_xml_text, compose, png_to_map, prj_text, world_file_text
from photomap.core.ifmi import Registrar
from photomap.mapping.telemetry_join import TelemetryJoin
from photomap.mapping.loopclosure import LoopCloser
from photomap.core.maprelative import map_correction
from photomap.core.mosaic import TiledMosaic
from photomap.io.tilestore import DiskTileStore
from photomap.core.tracking import LOW_CONFIDENCE, TrackStep, Tracker
from photomap.eval.metrics import PoseRow
from photomap.io.trajectory_files import atomic_write_bytes, write_json, write_trajectory_csv, write_tum

log = logging.getLogger(__name__)

_END = object()


@dataclass
class RunStats:
    """Counters of a run (the body of ``run.json``)."""

    frames_in: int = 0
    registered: int = 0
    low_confidence: int = 0
    dropped: int = 0
    corrupt: int = 0
    errors: int = 0
    segments: int = 0
    map_fixes: int = 0
    confidence_sum: float = 0.0
    worker_s: float = 0.0
    register_s: float = 0.0
    events: list[str] = field(default_factory=list)

    def summary(self, wall_s: float) -> dict:
        posed = self.registered
        return {
            "frames_in": self.frames_in,
            "registered": self.registered,
            "skipped": self.low_confidence + self.corrupt + self.errors,
            "low_confidence": self.low_confidence,
            "corrupt": self.corrupt,
            "errors": self.errors,
            "dropped": self.dropped,
            "segments": self.segments,
            "map_relative_fixes": self.map_fixes,
            "mean_confidence": self.confidence_sum / posed if posed else None,
            "ms_per_frame": 1000.0 * self.worker_s / self.frames_in if self.frames_in else None,
            "ms_register_per_frame": 1000.0 * self.register_s / self.frames_in if self.frames_in else None,
            "wall_time_s": wall_s,
            "fps": self.frames_in / wall_s if wall_s > 0 else None,
            "events": self.events[-100:],
        }


def _prefetch(source: FrameSource, depth: int, stop: threading.Event, *,
              poll: float = 0.2, join_timeout: float = 5.0) -> Iterator[Frame]:
    """Decode ``source`` in a thread, ``depth`` frames ahead (blocking: never drops).

    The decode thread is the only one that iterates ``source``; when it stops (end, ``stop``
    set, or this generator closed) it closes its own iterator, so a video source releases its
    decoder in the thread that decoded. Every wait polls with ``poll`` s; closing this generator
    waits at most ``join_timeout`` s for the thread (a daemon: a stuck decoder never keeps the
    process alive). An error of the source is re-raised here, after the frames before it.
    """
    q: queue.Queue = queue.Queue(maxsize=depth)
    failure: list[BaseException] = []
    gone = threading.Event()  # the consumer is gone: the decode thread stops

    def put(item: object) -> bool:
        while not gone.is_set():
            try:
                q.put(item, timeout=poll)
                return True
            except queue.Full:
                continue
        return False

    def reader() -> None:
        frames = iter(source)
        try:
            for frame in frames:
                if stop.is_set() or not put(frame) or stop.is_set():
                    break
        except BaseException as exc:  # handed to the consumer
            failure.append(exc)
        finally:
            close = getattr(frames, "close", None)
            if close is not None:
                try:
                    close()  # this thread read: it ends the iteration (and releases the decoder)
                except Exception as exc:
                    log.warning("closing the frame source failed: %s", exc)
            put(_END)

    thread = threading.Thread(target=reader, name="photomap-decode", daemon=True)
    thread.start()
    try:
        while True:
            try:
                item = q.get(timeout=poll)
            except queue.Empty:
                if not thread.is_alive() and q.empty():
                    break  # the thread died without its end marker: never wait forever
                continue
            if item is _END:
                break
            yield item
    finally:
        gone.set()
        thread.join(timeout=join_timeout)
        if thread.is_alive():
            log.warning("the decode thread did not stop within %.1f s; left to exit with the process",
                        join_timeout)
    if failure:
        raise failure[0]


class MappingPipeline:
    """Builds the photo map of one flight.

    Parameters
    ----------
    source : FrameSource
        Frames to map (live or replay).
    cfg : dict
        The whole config (sections ``registration``, ``mapping``, ``mosaic``, ``output``).
    out_dir : path
        Output folder (created).
    on_frame : callable, optional
        Called in the worker thread after each frame with ``(frame, step, pipeline)``; for sinks
        such as the viewer or a progress bar. It must be quick and must not raise.
    input_name : str
        Recorded in ``run.json``.
    telemetry : TelemetryJoin, optional
        MAVLink telemetry joined to the frames (priors, tilt, metric scale, georeference).
    """

    def __init__(self, source: FrameSource, cfg: dict, out_dir: str | Path, *,
                 on_frame: Callable[[Frame, TrackStep, "MappingPipeline"], None] | None = None,
                 input_name: str = "", telemetry: TelemetryJoin | None = None) -> None:
        self.source = source
        self.cfg = cfg
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.on_frame = on_frame
        self.input_name = input_name
        self.telemetry = telemetry
        self.stats = RunStats()
        self.rows: list[PoseRow] = []
        self.mosaics: dict[int, TiledMosaic] = {}
        self.frame_size: tuple[int, int] | None = None  # (w, h) of the input
        self.tracker: Tracker | None = None
        self.loops: LoopCloser | None = None
        self._stop = threading.Event()
        self._next_index = 0
        self._started = 0.0
        self._last_checkpoint = 0.0
        self._cache_dir: Path | None = None
        self._own_cache = False
        self._warned: set[str] = set()
        self._pending: tuple[int, np.ndarray, np.ndarray] | None = None  # last low-confidence frame: index, image, small
        self.last_touched: set = set()  # map tiles changed by the last frame (for the viewer)

    # ------------------------------------------------------------------ control
    def stop(self) -> None:
        """Stop capture; the worker finishes and the outputs are written.

        Only sets a flag (safe from a signal handler and from any thread): :meth:`run` sees it
        within 0.2 s and closes the source from its own thread.
        """
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def run(self) -> dict:
        """Map the whole source (until its end or :meth:`stop`); returns the run summary."""
        self._started = self._last_checkpoint = time.monotonic()
        failure: list[BaseException] = []

        def work() -> None:
            # BLAS pools pinned to one thread while mapping: the refinement's small products spin
            # against every other busy thread otherwise (10x slower on a busy 2-core computer)
            frames = self.source if self.source.live else _prefetch(self.source, 8, self._stop)
            try:
                with threadpool_limits(limits=1, user_api="blas"):
                    for frame in frames:  # after stop(), the frames already queued are drained
                        self._process(frame)
            except BaseException as exc:  # reported by run(), after the outputs are written
                failure.append(exc)
            finally:
                if frames is not self.source:
                    frames.close()  # stops the decode thread (bounded wait), also after an error

        worker = threading.Thread(target=work, name="photomap-worker", daemon=True)
        worker.start()
        closed = False
        while worker.is_alive():
            worker.join(timeout=0.2)
            if self._stop.is_set() and not closed:  # stop() only flags: close here, not in a handler
                closed = True
                self.source.close()
        self.source.close()  # bounded: never releases a decoder under a running read
        summary = self.finish()
        if failure:
            exc = failure[0]
            if isinstance(exc, ValueError) and self.tracker is None and self.frame_size is not None:
                # the registration could not be built from the configuration (e.g. a band
                # outside 0..0.5): a configuration error, one line for the user
                raise ConfigError(f"registration settings rejected: {exc}") from exc
            raise exc
        return summary

    # ------------------------------------------------------------------ worker
    def _setup(self, image: np.ndarray) -> None:
        h, w = image.shape[:2]
        self.frame_size = (w, h)
        rcfg = dict(self.cfg["registration"])
        working = int(rcfg.pop("working_size"))
        f = min(1.0, working / max(h, w)) if working > 0 else 1.0
        self._small = (max(16, int(round(w * f))), max(16, int(round(h * f))))
        f = self._small[0] / w  # exact factor of cv2.resize in x (and, to rounding, in y)
        self._working_scale = f
        mcfg = self.cfg["mapping"]
        self.tracker = Tracker(Registrar((self._small[1], self._small[0]), **rcfg), f,
                               map_scale=float(mcfg["map_scale"]),
                               min_confidence=mcfg["min_confidence"],
                               max_lost_frames=mcfg["max_lost_frames"], keyframes=mcfg["keyframes"],
                               keyframe_confidence=mcfg["keyframe_confidence"],
                               keyframe_max_shift=mcfg["keyframe_max_shift"],
                               motion_prior=mcfg["motion_prior"],
                               prior_angle_tol_deg=mcfg["prior_angle_tol_deg"],
                               prior_scale_tol=mcfg["prior_scale_tol"],
                               telemetry_prior=self.telemetry.prior if self.telemetry else None)
        if mcfg["keyframes"] and mcfg["loop_closure"]:
            self.loops = LoopCloser(self._cache() / "keyframes", self.tracker, self.frame_size, f, mcfg,
                                    priors=self.cfg["posegraph"] if self.telemetry else None)

    def _cache(self) -> Path:
        """The run's cache folder (configured, or a temporary one removed at the end)."""
        if self._cache_dir is None:
            if self.cfg["mosaic"]["cache_dir"]:
                self._cache_dir = Path(self.cfg["mosaic"]["cache_dir"]).expanduser()
                self._cache_dir.mkdir(parents=True, exist_ok=True)
            else:
                self._cache_dir = Path(tempfile.mkdtemp(prefix="photomap-cache-"))
                self._own_cache = True
        return self._cache_dir

    def _mosaic(self, segment: int) -> TiledMosaic:
        if segment not in self.mosaics:
            m = self.cfg["mosaic"]
            store = None
            if m["max_tiles_in_memory"]:
                store = DiskTileStore(self._cache() / f"segment{segment}")
            self.mosaics[segment] = TiledMosaic(
                tile_size=m["tile_size"], channels=m["channels"], blend=m["blend"],
                max_tiles_in_memory=m["max_tiles_in_memory"], store=store, border=m["border"],
                max_footprint_px=m["max_footprint_px"])
        return self.mosaics[segment]

    def _warn_once(self, kind: str, message: str) -> None:
        if kind not in self._warned:
            self._warned.add(kind)
            log.warning(message)

    def _process(self, frame: Frame) -> None:
        t0 = time.perf_counter()
        for missing in range(self._next_index, frame.index):  # gaps: dropped or undecodable
            self.rows.append(PoseRow(missing, float("nan"), None, status="dropped",
                                     segment=max(self.stats.segments - 1, 0)))
        self._next_index = max(self._next_index, frame.index + 1)
        self.stats.frames_in += 1
        image = frame.image
        if self.tracker is None:
            self._setup(image)
            if self.telemetry is not None:
                self.telemetry.notify("mapping started")
        if image.shape[:2] != (self.frame_size[1], self.frame_size[0]):
            self.stats.corrupt += 1
            self._warn_once("size", f"frame {frame.index}: size {image.shape[1]}x{image.shape[0]} "
                                    f"differs from the first frame's; skipped")
            self.rows.append(PoseRow(frame.index, frame.t, None, status="corrupt",
                                     segment=max(self.stats.segments - 1, 0)))
            return
        try:
            sample = self.telemetry.sample(frame) if self.telemetry else None
            if sample is not None:
                image = self.telemetry.rectify(image, sample)
            small = cv2.resize(image, self._small, interpolation=cv2.INTER_AREA)
            t1 = time.perf_counter()
            step = self.tracker.step(small, frame.index, sample)
            self.stats.register_s += time.perf_counter() - t1
            if step.keyframe and step.reference is not None and self.cfg["mapping"]["map_relative"]:
                self._map_relative(step, small)
            self.last_touched = set()
            if step.anchor is not None:
                self.last_touched |= self._anchor(step)
            if step.pose is not None:
                self.last_touched |= self._mosaic(step.segment).add(image, step.pose)
            pending = self._pending
            self._pending = (frame.index, image, small) if step.status == LOW_CONFIDENCE else None
        except Exception as exc:  # never lose the map for one bad frame
            self.stats.errors += 1
            self._warn_once(f"error:{type(exc).__name__}",
                            f"frame {frame.index} skipped: {type(exc).__name__}: {exc}")
            log.debug("frame %d failed", frame.index, exc_info=True)
            self.rows.append(PoseRow(frame.index, frame.t, None, status="corrupt",
                                     segment=max(self.stats.segments - 1, 0)))
            return
        new_segment = step.segment > 0 and step.segment >= self.stats.segments
        self.stats.segments = step.segment + 1
        for event in step.events:
            log.warning(event)
            self.stats.events.append(event)
        if new_segment and self.telemetry is not None:
            self.telemetry.notify(f"link to map lost, new segment at frame {frame.index}")
        if step.disagreement is not None and self.telemetry is not None:
            self.telemetry.stats.disagreements += 1
            if self.telemetry.stats.disagreements <= 3:  # counted in run.json; logged for the first few
                log.warning(step.disagreement)
                self.stats.events.append(step.disagreement)
        if step.status == LOW_CONFIDENCE:
            self.stats.low_confidence += 1
        else:
            self.stats.registered += 1
            self.stats.confidence_sum += step.confidence
        row = PoseRow(frame.index, frame.t, step.pose, step.confidence, step.status, step.segment)
        if sample is not None:
            row.extra["alt_m"] = sample.height_above_ground
            if step.pose is not None:
                self.telemetry.samples[frame.index] = sample
        self.rows.append(row)
        if self.loops is not None:
            if step.anchor is not None and pending is not None and pending[0] == step.anchor:
                self.loops.on_anchor(step, pending[2], pending[1])
            if self.loops.on_step(frame.index, step, small, image, self.rows, sample):
                self.stats.events.append(f"loop closed at frame {frame.index}: map corrected")
        self.stats.worker_s += time.perf_counter() - t0
        if self.on_frame is not None:
            self.on_frame(frame, step, self)
        interval = float(self.cfg["output"]["checkpoint_interval"])
        if interval > 0 and time.monotonic() - self._last_checkpoint >= interval:
            self.checkpoint()

    def _map_relative(self, step: TrackStep, small: np.ndarray) -> None:
        """Snap a new keyframe to the map rendered at its predicted pose (less drift)."""
        mosaic = self.mosaics.get(step.segment)
        if mosaic is None:
            return
        pose = np.vstack([step.pose, [0.0, 0.0, 1.0]])
        fix = map_correction(self.tracker.registrar, mosaic, pose, small, self.frame_size,
                             self._working_scale,
                             min_confidence=self.cfg["mapping"]["loop_min_confidence"])
        if fix is not None:
            step.pose = (fix @ pose)[:2]
            self.tracker.correct(fix)
            self.stats.map_fixes += 1

    def _anchor(self, step: TrackStep) -> set:
        """A new segment was anchored at the previous, low-confidence frame: glue it, fix its row.

        Returns the map tiles it changed.
        """
        for row in reversed(self.rows):
            if row.frame == step.anchor:
                row.M, row.status, row.segment = step.anchor_pose, "reference", step.segment
                row.confidence = step.confidence
                self.stats.low_confidence -= 1
                self.stats.registered += 1
                self.stats.confidence_sum += 1.0
                break
        if self._pending is not None and self._pending[0] == step.anchor:
            return self._mosaic(step.segment).add(self._pending[1], step.anchor_pose)
        return set()

    # ------------------------------------------------------------------ outputs
    def summary(self) -> dict:
        src = self.source.stats
        self.stats.dropped = src.dropped
        self.stats.corrupt = max(self.stats.corrupt, src.corrupt)
        out = self.stats.summary(time.monotonic() - self._started)
        out.update({"input": self.input_name, "frame_size": list(self.frame_size or ()),
                    "working_size": list(getattr(self, "_small", ())),
                    "reconnects": src.reconnects, "map_scale": self.cfg["mapping"]["map_scale"]})
        if self.loops is not None:
            out["loop_closure"] = self.loops.summary()
        return out

    def _write_trajectory(self) -> None:
        if self.frame_size is None:
            return
        write_trajectory_csv(self.out_dir / "trajectory.csv", self.rows, self.frame_size)
        if any(r.glued for r in self.rows):
            write_tum(self.out_dir / "trajectory.tum", self.rows, self.frame_size)

    def _rerender(self) -> None:
        """Re-render the maps that a loop closure corrected."""
        if self.loops is not None:
            self.loops.collect(self.rows)
            for segment in sorted(self.loops.dirty):
                if segment in self.mosaics:
                    self.last_touched |= self.loops.rerender(segment, self.mosaics[segment])

    def checkpoint(self) -> None:
        """Rewrite trajectory, run.json and a mosaic preview (atomically)."""
        self._last_checkpoint = time.monotonic()
        self._rerender()
        self._write_trajectory()
        summary = self.summary()
        summary["complete"] = False
        if self.mosaics:
            seg = max(self.mosaics, key=lambda s: sum(r.glued and r.segment == s for r in self.rows))
            self._write_png(self.out_dir / "preview.png", self.mosaics[seg],
                            int(self.cfg["output"]["preview_px"]))
        write_json(self.out_dir / "run.json", summary)

    @staticmethod
    def _write_png(path: Path, mosaic: TiledMosaic, max_px: int) -> dict | None:
        bounds = mosaic.bounds()
        if bounds is None:
            return None
        _, _, w, h = bounds
        scale = min(1.0, max_px / max(w, h))
        image, alpha, origin = mosaic.render(scale=scale)
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        ok, buf = cv2.imencode(".png", np.dstack([image, alpha]))
        if not ok:
            raise RuntimeError(f"PNG encoding of {path.name} failed")
        atomic_write_bytes(path, buf.tobytes())
        # exact per-axis scale of the PNG: output size over the map rectangle's size
        return {"file": path.name, "origin_xy": list(origin), "scale": scale,
                "pixel_scale": [image.shape[1] / w, image.shape[0] / h],
                "bounds": [int(v) for v in bounds], "size": [int(image.shape[1]), int(image.shape[0])]}

    def _georeference(self, summary: dict, maps: list[dict]) -> None:
        """Metric scale and georeference per segment; world files beside the mosaics."""
        join = self.telemetry
        w, h = self.frame_size or (0, 0)
        geo_out = {}
        for info in maps:
            seg = info["segment"]
            rows = [r for r in self.rows if r.glued and r.segment == seg and r.frame in join.samples]
            mpp, geo = join.georeference(w, h, [np.asarray(r.M) for r in rows],
                                         [join.samples[r.frame] for r in rows])
            entry: dict = {"metres_per_pixel": mpp}
            if geo is not None:
                stem = Path(info["file"]).stem
                png = compose(geo.map_to_crs, png_to_map(info["origin_xy"], info["pixel_scale"]))
                atomic_write_bytes(self.out_dir / f"{stem}.pgw", world_file_text(png).encode())
                atomic_write_bytes(self.out_dir / f"{stem}.prj", prj_text(geo.epsg).encode())
                atomic_write_bytes(self.out_dir / f"{info['file']}.aux.xml", aux_xml_text(geo.epsg).encode())
                entry.update({"crs": f"EPSG:{geo.epsg}", "map_to_crs": geo.map_to_crs.tolist(),
                              "origin_lat": geo.origin_lat, "origin_lon": geo.origin_lon,
                              "gps_rms_m": geo.rms_m, "scale_source": geo.scale_source,
                              "world_file": f"{stem}.pgw"})
                centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
                for r in self.rows:
                    if r.glued and r.segment == seg:
                        lat, lon = geo.to_latlon((np.asarray(r.M) @ centre)[None, :])
                        r.extra["lat"], r.extra["lon"] = float(lat[0]), float(lon[0])
            info["georeference"] = entry
            geo_out[seg] = entry
        head = geo_out.get(maps[0]["segment"]) if maps else None
        summary["metres_per_pixel"] = head["metres_per_pixel"] if head else None
        summary["georeference"] = head if head and "crs" in head else None
        posed = [r for r in self.rows if r.glued and r.segment == (maps[0]["segment"] if maps else 0)]
        check = join.time_offset_check([r.t for r in posed],
                                       [math.degrees(math.atan2(r.M[1][0], r.M[0][0])) for r in posed])
        summary["telemetry"] = {**asdict(join.stats), "link": join.link_summary(),
                                "time_offset_s": join.offset, "time_offset_check": check}
        if check is not None and abs(check["residual_offset_s"]) > 0.2:
            log.warning("telemetry seems %.2f s off the video (yaw-rate correlation %.2f): "
                        "consider --time-offset %.2f", check["residual_offset_s"],
                        check["correlation"], join.offset + check["residual_offset_s"])
        self._write_trajectory()

    def _write_tiles(self, folder: Path, mosaic: TiledMosaic) -> None:
        folder.mkdir(exist_ok=True)
        for key in mosaic.tiles():
            image, alpha = mosaic.tile_image(key)
            if image.ndim == 2:
                image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
            ok, buf = cv2.imencode(".png", np.dstack([image, alpha]))
            if ok:
                atomic_write_bytes(folder / f"tile_{key[0]}_{key[1]}.png", buf.tobytes())

    def finish(self) -> dict:
        """Write the final outputs; returns the run summary (also in ``run.json``)."""
        if self.loops is not None:
            self.loops.flush(self.rows)
        self._rerender()
        self._write_trajectory()
        summary = self.summary()
        maps = []
        max_px = int(self.cfg["output"]["max_mosaic_px"])
        order = sorted(self.mosaics, key=lambda s: -sum(r.glued and r.segment == s for r in self.rows))
        for rank, seg in enumerate(order):
            name = "mosaic.png" if rank == 0 else f"mosaic_segment{seg}.png"
            info = self._write_png(self.out_dir / name, self.mosaics[seg], max_px)
            if info is None:
                continue
            info["segment"] = seg
            if info["scale"] < 1.0:
                tiles = self.out_dir / ("tiles" if rank == 0 else f"tiles_segment{seg}")
                self._write_tiles(tiles, self.mosaics[seg])
                info["tiles"] = tiles.name
                info["tile_size"] = self.mosaics[seg].tile_size
            maps.append(info)
        (self.out_dir / "preview.png").unlink(missing_ok=True)
        if self.telemetry is not None:
            self._georeference(summary, maps)
        summary["mosaics"] = maps
        summary["complete"] = True
        write_json(self.out_dir / "run.json", summary)
        if self._own_cache and self._cache_dir is not None:
            shutil.rmtree(self._cache_dir, ignore_errors=True)
        return summary
