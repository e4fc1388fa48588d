"""The mapping pipeline: frames in, a growing photo map and a trajectory out.

Threads live here (and in the drivers): a file source is decoded by a prefetch thread into a
bounded queue (replay never drops); a live source already drops its oldest frames when the worker
falls behind. One worker thread runs prepare -> register -> pose -> map update for each frame,
hands a :class:`~photomap.mapping.events.FrameEvent` to its sinks and checkpoints the outputs
periodically; :meth:`MappingPipeline.stop` (SIGINT/SIGTERM) ends capture, lets the worker finish,
and the outputs are written. The map is painted by a :class:`~photomap.mapping.painter.Painter`
(keyframes whole, other frames only their new ground); after a loop-closure correction a
:class:`~photomap.mapping.rerender.Rerenderer` thread re-renders the moved tiles and the worker
swaps them in, never waiting. The thread budget (BLAS pinned to one thread, OpenCV's threads
``mapping.opencv_threads``) holds for the whole run; the pipeline records its per-stage times
(:mod:`photomap.mapping.timing`, ``run.json`` ``timing_ms``).

State has one owner: the pipeline owns the trajectory rows, the maps (one per segment) and the
tracker; the loop closer returns corrections that the pipeline applies; sinks only read events.

Files written to the output folder (README, "What a run writes"): ``mosaic.png`` (BGRA, transparent where
the map is empty; the largest segment; other segments as ``mosaic_segment{N}.png``),
``trajectory.csv``, ``trajectory.tum`` and ``run.json``. All are written atomically.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections import deque
import queue
import shutil
import tempfile
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from photomap.config import Config
from photomap.core.ifmi import Registrar
from photomap.core.matching import PairMatcher
from photomap.core.maprelative import map_correction
from photomap.core.mosaic import TiledMosaic
from photomap.core.tracking import LOW_CONFIDENCE, REFERENCE, TrackStep, Tracker
from photomap.drivers.frames import Frame, FrameSource
from photomap.drivers.images import ImageFolderSource
from photomap.geometry import frame_centre, pose_angle_deg
from photomap.errors import OutputError, PhotomapError
from photomap.io.keyframestore import KeyframeStore
from photomap.io.report import THUMB_PX, write_report
from photomap.io.statestore import MANIFEST
from photomap.io.tilestore import DiskTileStore, WriteBehindTileStore
from photomap.io.trajectory_files import tum_skipped_message, write_json, write_trajectory_csv, write_tum
from photomap.mapping.checkpoint import Checkpointer, state_folder
from photomap.mapping.events import FrameEvent, FrameSink
from photomap.mapping.geo_outputs import refresh_track_files, write_geo_outputs
from photomap.mapping.loopclosure import Correction, Join, LoopCloser
from photomap.mapping.memory import frozen_heap, limit_heap_growth, trimmed_heap
from photomap.mapping.outputs import png_placement, remove_sidecars, render_small, write_png, write_sidecars, write_tiles
from photomap.mapping.painter import Painter
from photomap.mapping.rerender import Rerenderer
from photomap.mapping.rows import RowView, TrajectoryRows
from photomap.mapping.telemetry_join import SegmentFit, TelemetryJoin
from photomap.mapping.telemetry_place import TelemetryPlacer
from photomap.mapping.threads import WorkerFirst, lower_priority, switch_interval
from photomap.mapping.timing import StageTimes

log = logging.getLogger(__name__)

_END = object()
# A replay (not live) re-renders and optimises in lockstep with the frames: a re-render job at
# most every this many frames, swapped in (a pose-graph solve applied) this many frames after it
# started, so that the same input makes the same map on any machine.
_LOCKSTEP_FRAMES = 30
_WRITER_SHARE = 0.1  # a checkpoint's files (whose rows grow with the flight) take at most this share of the time
_WRITER_REST_AFTER_S = 0.05  # ... once the trajectory takes longer than this to write
_LOOP_LOCKSTEP_FRAMES = 8  # ... and a new keyframe's loop registrations (a few ms each) join its graph
# tiles of a map the camera left moved to the tile store per frame (all at once: 256 tiles took the
# worker 200 ms, waiting for the tile writer)
_SPILL_TILES_PER_FRAME = 8


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
    segments_dropped: int = 0
    map_fixes: int = 0
    confidence_sum: float = 0.0
    worker_s: float = 0.0
    register_s: float = 0.0
    events: deque = field(default_factory=lambda: deque(maxlen=100))  # the latest (bounded memory)
    timing: StageTimes = field(default_factory=StageTimes)

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
            "segments_dropped": self.segments_dropped,
            "map_relative_fixes": self.map_fixes,
            "mean_confidence": self.confidence_sum / posed if posed else None,
            "ms_per_frame": 1000.0 * self.worker_s / self.frames_in if self.frames_in else None,
            "ms_register_per_frame": 1000.0 * self.register_s / self.frames_in if self.frames_in else None,
            "wall_time_s": wall_s,
            "fps": self.frames_in / wall_s if wall_s > 0 else None,
            "timing_ms": self.timing.summary(),
            "events": list(self.events),
        }


def _prefetch(source: FrameSource, depth: int, stop: threading.Event, *,
              poll: float = 0.2, join_timeout: float = 5.0,
              timing: StageTimes | None = None, max_bytes: int = 64 << 20) -> Iterator[Frame]:
    """Decode ``source`` in a thread, ``depth`` frames ahead but at most ``max_bytes`` of frames
    (at least 2; 4K frames are 25 MB each) (blocking: never drops); the time of each frame's
    reading and decoding goes to ``timing`` (stage ``decode``).

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

    def timed(frames: Iterator[Frame]) -> Iterator[Frame]:
        while True:
            t = time.perf_counter()
            try:
                frame = next(frames)
            except StopIteration:
                return
            if timing is not None:
                timing.add("decode", time.perf_counter() - t)
            yield frame

    def reader() -> None:
        frames = iter(source)
        sized = False
        try:
            for frame in timed(frames):
                if not sized:  # the first frame tells the frame size
                    with q.mutex:
                        q.maxsize = max(2, min(depth, max_bytes // max(1, frame.image.nbytes)))
                    sized = True
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
    cfg : Config
        The configuration (sections ``registration``, ``mapping``, ``mosaic``, ``output``,
        ``posegraph``).
    out_dir : path
        Output folder (created).
    sinks : sequence of callables
        Each is called in the worker thread with the :class:`FrameEvent` of every frame (viewer,
        progress bar, STATUSTEXT). They must be quick and must not raise.
    input_name : str
        Recorded in ``run.json``.
    telemetry : TelemetryJoin, optional
        MAVLink telemetry joined to the frames (priors, tilt, metric scale, georeference).
    """

    def __init__(self, source: FrameSource, cfg: Config, out_dir: str | Path, *,
                 sinks: Sequence[FrameSink] = (), input_name: str = "",
                 telemetry: TelemetryJoin | None = None) -> None:
        self.source = source
        self.cfg = cfg
        self.out_dir = Path(out_dir)
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
        self.sinks = tuple(sinks)
        self.input_name = input_name
        self.telemetry = telemetry
        self.stats = RunStats()
        self._rows = TrajectoryRows()  # one per input frame, as columns (a long flight keeps them for hours)
        self.mosaics: dict[int, TiledMosaic] = {}
        self.frame_size: tuple[int, int] | None = None  # (w, h) of the input
        self.tracker: Tracker | None = None
        self.loops: LoopCloser | None = None
        self._stop = threading.Event()
        # live: the background threads' Python code waits while the worker maps a frame (a replay
        # has no frame deadline: throughput first)
        self._first = WorkerFirst(enabled=source.live)
        self._tum_skipped: list[int] = []  # frames the final trajectory.tum left out (said once)
        self._placer: TelemetryPlacer | None = None  # frames vision left unplaced, with telemetry
        self._placed: dict | None = None  # what the placer did (run.json telemetry.placed)
        self._next_index = 0
        self._started = 0.0
        self._last_checkpoint = 0.0
        self._cache_dir: Path | None = None
        self._tile_stores: dict[int, WriteBehindTileStore] = {}  # segment -> where its map spills
        self._own_cache = False
        self._warned: set[str] = set()
        self._pending: tuple[int, np.ndarray, np.ndarray] | None = None  # last low-confidence frame: index, image, small
        self._state: Checkpointer | None = None  # the checkpointed full-resolution map
        self._state_refused = False
        self._write_errors: dict[str, str] = {}  # output -> why it could not be written (once each)
        # a checkpoint's trajectory.csv (10,000 rows take ~0.25 s to format: a stall in the worker)
        # and run.json are written by this thread; the worker hands it the rows' fields
        self._writer: ThreadPoolExecutor | None = None
        self._checkpoint_files: Future | None = None
        self._files_due = 0.0  # monotonic s: the next checkpoint's files not before (_WRITER_SHARE)
        self._source_gaps = 0  # rows made for frames the source lost (dropped or undecodable)
        self._segment_start: dict[int, int] = {}  # segment -> position in the rows where it started
        self._kept: set[int] = set()  # segments known to hold more than one posed frame
        self._spilling: set[int] = set()  # segments left by the camera whose tiles go to the store
        self._painter: Painter | None = None  # paints the maps (made with the tracker)
        self._map_scale = cfg.mapping.map_scale  # map px per input px (mapping.map_px may lower it)

    @property
    def rows(self) -> tuple[RowView, ...]:
        """The trajectory so far, one row per input frame (read only: the pipeline writes them)."""
        return tuple(self._rows)

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
        limit_heap_growth()  # flat RSS over long runs (see photomap.mapping.memory)
        failure: list[BaseException] = []

        def work() -> None:
            frames = self.source if self.source.live else _prefetch(self.source, 8, self._stop,
                                                                    timing=self.stats.timing)
            try:
                for frame in frames:  # after stop(), the frames already queued are drained
                    with self._first.frame():
                        self._process(frame)
            except BaseException as exc:  # reported by run(), after the outputs are written
                failure.append(exc)
            finally:
                if frames is not self.source:
                    frames.close()  # stops the decode thread (bounded wait), also after an error

        # The thread budget, for the whole run (the worker, the loop closer's optimiser, the
        # re-render thread, the viewer and the final outputs): BLAS pools pinned to one thread
        # (the refinement's small products spin against every other busy thread otherwise: 10x
        # slower on a busy 2-core computer); OpenCV's pool as configured (docs/onboard.md); the
        # interpreter's switch interval (photomap.mapping.threads) and the objects the garbage
        # collector walks (photomap.mapping.memory) set for the worker's latency.
        opencv_threads = cv2.getNumThreads()
        if self.cfg.mapping.opencv_threads > 0:
            cv2.setNumThreads(self.cfg.mapping.opencv_threads)
        try:
            with threadpool_limits(limits=1, user_api="blas"), switch_interval(), frozen_heap(), \
                    trimmed_heap(wait=self._first.wait):
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
        finally:
            cv2.setNumThreads(opencv_threads)
        if failure:
            raise failure[0]
        return summary

    # ------------------------------------------------------------------ worker
    def _setup(self, image: np.ndarray) -> None:
        h, w = image.shape[:2]
        self.frame_size = (w, h)
        working = self.cfg.registration.working_size
        f = min(1.0, working / max(h, w)) if working > 0 else 1.0
        self._small = (max(16, int(round(w * f))), max(16, int(round(h * f))))
        f = self._small[0] / w  # exact factor of cv2.resize in x (and, to rounding, in y)
        self._working_scale = f
        mapping = self.cfg.mapping
        # the map's resolution: at most map_px a video frame (survey stills keep theirs)
        if mapping.map_px and max(w, h) > mapping.map_px and not isinstance(self.source, ImageFolderSource):
            mapping = dataclasses.replace(mapping, map_scale=mapping.map_scale * mapping.map_px / max(w, h))
        self._map_scale = mapping.map_scale
        registrar = Registrar((self._small[1], self._small[0]), self.cfg.registration)
        matcher = PairMatcher(registrar, min_confidence=mapping.min_confidence,
                              trust_confidence=mapping.trust_confidence, verify=mapping.verify_placements,
                              second_opinion=mapping.second_opinion, second_opinion_px=mapping.second_opinion_px)
        self.tracker = Tracker(matcher, f, mapping,
                               telemetry_prior=self.telemetry.prior if self.telemetry else None)
        store = None
        if mapping.keyframes and mapping.loop_closure:
            keyframes = (state_folder(self.out_dir) / "keyframes" if self._checkpointing and not self.cfg.mosaic.cache_dir
                         else self._cache() / "keyframes")  # kept with the checkpoint: a restart can re-render
            store = KeyframeStore(keyframes)
            self.loops = LoopCloser(store, matcher, self.frame_size,
                                    f, mapping, self.cfg.posegraph, use_priors=self.telemetry is not None,
                                    settle_on_priors=self.telemetry is not None and self.telemetry.mode == "stills",
                                    lockstep_frames=None if self.source.live else _LOCKSTEP_FRAMES,
                                    loop_lockstep_frames=_LOOP_LOCKSTEP_FRAMES, first=self._first)
        # the painter's background thread: kept images, re-renders after corrections, previews
        self._painter = Painter(self.frame_size, self.cfg.mosaic.tile_size,
                                rerenderer=Rerenderer(store, self.cfg.mosaic, first=self._first),
                                keep=self.loops is not None,
                                whole_frames=mapping.paint == "every", band_px=self.cfg.mosaic.tile_size,
                                lockstep_frames=None if self.source.live else _LOCKSTEP_FRAMES)

    def _cache(self) -> Path:
        """The run's cache folder (configured, or a temporary one removed at the end)."""
        if self._cache_dir is None:
            if self.cfg.mosaic.cache_dir:
                self._cache_dir = Path(self.cfg.mosaic.cache_dir).expanduser()
                self._cache_dir.mkdir(parents=True, exist_ok=True)
            else:
                self._cache_dir = Path(tempfile.mkdtemp(prefix="photomap-cache-"))
                self._own_cache = True
        return self._cache_dir

    def _mosaic(self, segment: int) -> TiledMosaic:
        if segment not in self.mosaics:
            store = None
            if self.cfg.mosaic.max_tiles_in_memory:
                # spilled tiles are written by a thread: the worker never waits for the disk
                # its read-ahead counts in the map's tile cap: at most a quarter of it
                store = self._tile_stores[segment] = WriteBehindTileStore(
                    DiskTileStore(self._cache() / f"segment{segment}"),
                    max_ready=min(WriteBehindTileStore.MAX_READY, self.cfg.mosaic.max_tiles_in_memory // 4))
            self.mosaics[segment] = TiledMosaic(self.cfg.mosaic, store)
        return self.mosaics[segment]

    def _warn_once(self, kind: str, message: str) -> None:
        if kind not in self._warned:
            self._warned.add(kind)
            log.warning(message)

    @property
    def _segment(self) -> int:
        """The current map segment (0 before the first frame)."""
        return max(self.tracker.segment, 0) if self.tracker is not None else 0

    def _skip(self, frame: Frame, status: str, t0: float) -> None:
        """A frame that cannot be mapped: a row, and an event for the sinks."""
        segment = self._segment
        self._rows.append(frame.index, frame.t, None, status=status, segment=segment)
        w, h = self.frame_size or (frame.image.shape[1], frame.image.shape[0])
        self._emit(FrameEvent(frame.index, frame.t, self.source.live, frame.image, (w, h), status, None,
                              math.nan, segment, frame_ms=1000.0 * (time.perf_counter() - t0),
                              dropped_frames=int(self.source.stats.dropped),
                              reconnects=int(self.source.stats.reconnects)))

    def _gaps(self, index: int) -> None:
        """Rows for the frames before ``index`` that never reached the worker: ``dropped`` by a
        live source that fell behind, ``corrupt`` (undecodable) in a file, as the source counts them."""
        status = "dropped" if self.source.live else "corrupt"
        for missing in range(self._next_index, index):
            self._rows.append(missing, float("nan"), None, status=status, segment=self._segment)
            self._source_gaps += 1

    def _close_gaps(self) -> None:
        """At the end: rows for frames the source lost after the last one processed, so that
        trajectory.csv and run.json count every status alike."""
        src = self.source.stats
        lost = int(src.dropped if self.source.live else src.corrupt)
        if lost > self._source_gaps and self.frame_size is not None:
            self._gaps(self._next_index + lost - self._source_gaps)
            self._next_index = self._rows[-1].frame + 1

    def _retire_segments(self, current: int) -> None:
        """The tracker started segment ``current``: a segment it left with a single posed frame
        (nothing registered to its reference) is dropped, its frame counted ``low_confidence``,
        so featureless or black video cannot pile up maps; the others are spilled to the tile
        store when one bounds memory (only the current map holds tiles in memory)."""
        self._segment_start[current] = max(0, len(self._rows) - 1)
        for seg in list(self.mosaics):
            if seg == current:
                continue
            if seg not in self._kept:
                glued = self._rows.glued(seg, self._segment_start.get(seg, 0))
                if len(glued) <= 1:
                    self._drop_segment(seg, glued)
                    continue
                self._kept.add(seg)
            if self.cfg.mosaic.max_tiles_in_memory is not None:
                self._spilling.add(seg)  # a few tiles a frame: _spill_retired

    def _spill_retired(self) -> None:
        """Move a few tiles of the maps the camera left to the tile store (only the current map
        holds tiles in memory once they are all gone, its store the only ones read ahead)."""
        if not self._spilling:
            return
        seg = min(self._spilling)  # one map a frame
        mosaic = self.mosaics.get(seg)
        if mosaic is None or seg == self._segment or not mosaic.spill(_SPILL_TILES_PER_FRAME):
            self._spilling.discard(seg)  # joined, dropped, current again, or done
            if seg != self._segment and seg in self._tile_stores:
                self._tile_stores[seg].drop_read_ahead()  # read for frames that went elsewhere

    def _drop_segment(self, seg: int, glued: list[RowView]) -> None:
        for row in glued:
            row.M, row.status = None, LOW_CONFIDENCE
            self.stats.registered -= 1
            self.stats.low_confidence += 1
            if math.isfinite(row.confidence):
                self.stats.confidence_sum -= row.confidence
        self.mosaics.pop(seg, None)
        if seg in self._tile_stores:
            self._tile_stores.pop(seg).flush()  # its writes done before its folder goes
        if self.cfg.mosaic.max_tiles_in_memory and self._cache_dir is not None:
            shutil.rmtree(self._cache_dir / f"segment{seg}", ignore_errors=True)
        self._painter.forget(seg)
        self._segment_start.pop(seg, None)
        if self.loops is not None:
            self.loops.forget(seg)
        self.stats.segments_dropped += 1
        self._warn_once("segment-dropped", f"map segment {seg} dropped: nothing registered to its first frame "
                                           f"(featureless or dark ground?); such frames count as low_confidence")

    def _process(self, frame: Frame) -> None:
        t0 = time.perf_counter()
        try:
            self._process_frame(frame)
        finally:  # the worker's whole time for the frame: the largest is its longest stall
            self.stats.timing.add("frame", time.perf_counter() - t0)

    def _process_frame(self, frame: Frame) -> None:
        t0 = time.perf_counter()
        timing = self.stats.timing
        self._gaps(frame.index)  # frames before this one that never came: dropped or undecodable
        self._next_index = max(self._next_index, frame.index + 1)
        self.stats.frames_in += 1
        image = frame.image
        if self.tracker is None:
            self._setup(image)
        if image.shape[:2] != (self.frame_size[1], self.frame_size[0]):
            self.stats.corrupt += 1
            self._warn_once("size", f"frame {frame.index}: size {image.shape[1]}x{image.shape[0]} "
                                    f"differs from the first frame's; skipped")
            self._skip(frame, "corrupt", t0)
            return
        try:
            sample = self.telemetry.sample(frame) if self.telemetry else None
            mask = None  # validity of a rectified view's pixels (None: all valid)
            if sample is not None:
                view = self.telemetry.rectify_frame(image, sample, frame.index)
                image, mask = view.image, view.mask
            small = cv2.resize(image, self._small, interpolation=cv2.INTER_AREA)
            t1 = time.perf_counter()
            timing.add("resize", t1 - t0)
            started = self.tracker.segments
            step = self.tracker.step(small, frame.index, sample, image)
            register_s = time.perf_counter() - t1
            self.stats.register_s += register_s
            if step.keyframe and step.reference is not None and self.cfg.mapping.map_relative:
                self._map_relative(step, small)
            t2 = time.perf_counter()
            timing.add("register", t2 - t1)
            if self.tracker.segments > started:  # earlier segments got their last frame
                for segment in list(self.mosaics):
                    if segment != step.segment:
                        self._painter.end_segment(self.mosaics.get(segment), segment)
            touched: set = set()
            if step.anchor is not None:
                touched |= self._anchor(step)
            if step.pose is not None:
                whole = step.keyframe and (self.cfg.mapping.keyframes or step.status == REFERENCE)
                touched |= self._painter.paint(self._mosaic(step.segment), step.segment, frame.index, image,
                                               step.pose, mask, whole=whole)
            timing.add("paint", time.perf_counter() - t2)
            pending = self._pending
            self._pending = (frame.index, image, small) if step.status == LOW_CONFIDENCE else None
        except Exception as exc:  # never lose the map for one bad frame
            self.stats.errors += 1
            self._warn_once(f"error:{type(exc).__name__}",
                            f"frame {frame.index} skipped: {type(exc).__name__}: {exc}")
            log.debug("frame %d failed", frame.index, exc_info=True)
            self._skip(frame, "corrupt", t0)
            return
        new_segment = self.tracker.segments > started  # this frame started a map segment
        if new_segment:
            self._retire_segments(step.segment)
        self.stats.segments = self.tracker.segments
        messages = list(step.events)
        for event in step.events:
            log.warning(event)
            self.stats.events.append(event)
        if step.disagreement is not None and self.telemetry is not None:
            if self.telemetry.disagreement() <= 3:  # counted in run.json; logged for the first few
                log.warning(step.disagreement)
                self.stats.events.append(step.disagreement)
            messages.append(step.disagreement)
        if step.status == LOW_CONFIDENCE:
            self.stats.low_confidence += 1
        else:
            self.stats.registered += 1
            self.stats.confidence_sum += step.confidence
        extra = {}
        if step.pose is not None:
            extra["method"] = step.method  # which method placed the frame: ifmi, sift, orb
        if sample is not None:
            extra["alt_m"] = sample.height_above_ground
            extra.update(self.telemetry.row_columns(frame.index))  # which pixels the pose maps
            if step.pose is not None:
                self.telemetry.keep(frame.index, sample)
        self._rows.append(frame.index, frame.t, step.pose, step.confidence, step.status, step.segment, extra)
        if self.telemetry is not None and step.status == LOW_CONFIDENCE:  # placed at the end, if trusted
            self._placer = self._placer or TelemetryPlacer(self.telemetry, self.frame_size)
            self._placer.keep(frame.index, frame.t, image, mask, sample)
        corrected_path = None
        t3 = time.perf_counter()
        if self.loops is not None:
            if step.anchor is not None and pending is not None and pending[0] == step.anchor:
                self.loops.on_anchor(step, pending[2], pending[1])
            for update in self.loops.on_step(frame.index, step, small, image, sample):
                if isinstance(update, Join):
                    touched = self._join(update)  # the frame's tiles were in the joined map's frame: none here
                    message = (f"map segment {update.segment} joined segment {update.into} at frame "
                               f"{frame.index} (confidence {update.confidence:.2f})")
                    log.info(message)
                else:
                    self._apply(update)
                    message = f"loop closed at frame {frame.index}: map corrected"
                self.stats.events.append(message)
                messages.append(message)
                if update.segment == step.segment or getattr(update, "into", None) == self._segment:
                    corrected_path = functools.partial(self._path, self._segment)
            if self._segment != step.segment:  # joined: this frame now lives in another map
                step.segment = self._segment
            timing.add("loop_closure", time.perf_counter() - t3)
        t4 = time.perf_counter()
        touched |= self._painter.pump(self.mosaics, frame=frame.index).get(step.segment, set())  # re-rendered
        self._spill_retired()
        timing.add("map_upkeep", time.perf_counter() - t4)
        self.stats.worker_s += time.perf_counter() - t0
        if self.sinks:
            t5 = time.perf_counter()
            link = self.telemetry.link_summary() if self.telemetry is not None else {}
            anchor = (step.anchor, step.anchor_pose.copy()) if step.anchor is not None else None
            self._emit(FrameEvent(
                frame.index, frame.t, self.source.live, frame.image, self.frame_size, step.status,
                None if self._rows[-1].M is None else np.array(self._rows[-1].M, float), float(step.confidence),
                step.segment,
                keyframe=step.keyframe, new_segment=new_segment, anchor=anchor, messages=tuple(messages),
                touched=frozenset(touched), tiles=self.mosaics.get(step.segment),
                register_ms=1000.0 * register_s, frame_ms=1000.0 * (time.perf_counter() - t0),
                dropped_frames=int(self.source.stats.dropped), reconnects=int(self.source.stats.reconnects),
                telemetry=sample, focal_px=self.telemetry.focal(self.frame_size[0]) if self.telemetry else None,
                link_lost=int(link.get("link_lost", 0)),
                link_regained=int(link.get("link_regained", 0)), path_after_correction=corrected_path))
            timing.add("sinks", time.perf_counter() - t5)
        interval = self.cfg.output.checkpoint_interval
        if interval > 0 and time.monotonic() - self._last_checkpoint >= interval:
            t6 = time.perf_counter()
            self.checkpoint()
            timing.add("outputs", time.perf_counter() - t6)

    def _emit(self, event: FrameEvent) -> None:
        for sink in self.sinks:
            sink(event)

    def _path(self, segment: int) -> np.ndarray:
        """The map positions of the frame centres of ``segment``, (n, 3): x, y, confidence, in order."""
        glued = self._rows.glued_mask(segment)
        centre = np.array([*frame_centre(*self.frame_size), 1.0])
        xy = self._rows.poses(glued) @ centre  # one product for all
        return np.column_stack([xy, self._rows.confidences(glued)])

    def _apply(self, correction: Correction) -> None:
        """Re-pose the frames of a corrected segment; the tracker goes on from the corrected pose."""
        self._rows.set_poses(correction.poses.frames, correction.poses.poses, correction.segment)
        if correction.segment == self.tracker.segment:
            self.tracker.correct(correction.latest)
        self._painter.on_correction(correction.segment, correction.poses)  # re-rendered in the background

    def _join(self, join: Join) -> set:
        """Segment ``join.segment`` is part of ``join.into``: one map frame from now on.

        The joined map's frames are re-rendered into ``join.into`` in the background (the tiles
        come to the sinks as they are swapped in); returns no tiles."""
        t = join.transform
        self._rows.transform_segment(join.segment, t, join.into)
        self._mosaic(join.into)
        self.mosaics.pop(join.segment, None)  # its kept frames are re-rendered into join.into
        self._painter.on_join(join.segment, join.into, t)
        if self.tracker.segment == join.segment:
            self.tracker.rejoin(join.into, t)
        return set()

    def _map_relative(self, step: TrackStep, small: np.ndarray) -> None:
        """Snap a new keyframe to the map rendered at its predicted pose (less drift)."""
        mosaic = self.mosaics.get(step.segment)
        if mosaic is None:
            return
        pose = np.vstack([step.pose, [0.0, 0.0, 1.0]])
        fix = map_correction(self.tracker.registrar, mosaic, pose, small, self.frame_size,
                             self._working_scale, min_confidence=self.cfg.mapping.loop_min_confidence)
        if fix is not None:
            step.pose = (fix @ pose)[:2]
            self.tracker.correct(fix)
            self.stats.map_fixes += 1

    def _anchor(self, step: TrackStep) -> set:
        """A new segment was anchored at the previous, low-confidence frame: glue it, fix its row.

        Returns the map tiles it changed.
        """
        k = self._rows.index_of(step.anchor)
        if k is not None:
            row = self._rows[k]
            row.M, row.status, row.segment = step.anchor_pose, "reference", step.segment
            row.confidence = step.confidence
            self.stats.low_confidence -= 1
            self.stats.registered += 1
            self.stats.confidence_sum += 1.0
        if self._pending is not None and self._pending[0] == step.anchor:
            return self._painter.paint(self._mosaic(step.segment), step.segment, step.anchor, self._pending[1],
                                       step.anchor_pose, self._view_mask(step.anchor), whole=True)
        return set()

    def _view_mask(self, index: int) -> np.ndarray | None:
        """Valid pixels of the image the map got of frame ``index`` (None: all of them)."""
        return self.telemetry.mask(index) if self.telemetry is not None else None

    # ------------------------------------------------------------------ outputs
    def summary(self) -> dict:
        src = self.source.stats
        self.stats.dropped = src.dropped
        self.stats.corrupt = max(self.stats.corrupt, src.corrupt)
        out = self.stats.summary(time.monotonic() - self._started)
        counts = self._rows.status_counts()  # run.json counts what trajectory.csv says, status by status
        out.update({"registered": counts.get("reference", 0) + counts.get("registered", 0),
                    "low_confidence": counts.get("low_confidence", 0), "corrupt": counts.get("corrupt", 0),
                    "dropped": max(counts.get("dropped", 0), int(src.dropped))})
        out["skipped"] = out["low_confidence"] + out["corrupt"]
        out.update({"input": self.input_name, "frame_size": list(self.frame_size or ()),
                    "working_size": list(getattr(self, "_small", ())),
                    "reconnects": src.reconnects, "map_scale": self._map_scale,
                    "video_start_unix": self._video_start_unix()})
        if self._painter is not None:
            out["painting"] = self._painter.stats.summary()
        if self.loops is not None:
            out["loop_closure"] = self.loops.summary()
            out["joins"] = [{"segment": j.segment, "into": j.into, "frame": j.frame, "match": j.match,
                             "confidence": j.confidence} for j in self.loops.joins]
        out["segments_started"] = out["segments"]
        out["segments"] = len(self.mosaics) if self.mosaics else out["segments"]
        return out

    def _video_start_unix(self) -> float | None:
        """UNIX time of frame time 0 (live: frames carry the monotonic clock), when known."""
        if self.telemetry is not None:
            return self.telemetry.video_start_unix()
        if self.source.live:
            return time.time() - time.monotonic()
        if getattr(self.source, "exif_times", False):
            return 0.0  # stills timed by their EXIF capture time
        return getattr(self.source, "creation_time", None)

    def _write_trajectory(self, rows: Iterable[RowView] | None = None) -> None:
        """``trajectory.csv`` and ``trajectory.tum`` of ``rows`` (default: the rows now; iterated
        several times). Frames the TUM file leaves out are said once, by the final rows' write."""
        if self.frame_size is None:
            return
        final, rows = rows is None, (self._rows if rows is None else rows)
        write_trajectory_csv(self.out_dir / "trajectory.csv", rows, self.frame_size)
        if any(r.glued for r in rows):
            skipped: list[int] = []
            write_tum(self.out_dir / "trajectory.tum", rows, self.frame_size, skipped=skipped)
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
        rows = self._rows.copy() if self.frame_size is not None else None
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

    def _rerender(self) -> None:
        """Apply a finished loop-closure correction and swap re-rendered tiles in (never waits:
        the re-rendering runs in the painter's background thread)."""
        if self.loops is not None:
            correction = self.loops.poll()
            if correction is not None:
                self._apply(correction)
        if self.tracker is not None:
            self._painter.pump(self.mosaics)

    def _largest_segments(self) -> list[int]:
        """Segments with a map, the one with the most posed frames first."""
        glued = self._rows.segment_counts()
        counts = {s: glued.get(s, 0) for s in self.mosaics}
        return sorted(counts, key=lambda s: -counts[s])

    @property
    def _checkpointing(self) -> bool:
        """Checkpoints keep the full-resolution map (``output.checkpoint_map``, with an interval)."""
        return self.cfg.output.checkpoint_map and self.cfg.output.checkpoint_interval > 0

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
        order = self._largest_segments()
        for seg in order:
            graph = self.loops.graphs.get(seg) if self.loops is not None else None
            keyframes = [[kf.index, *np.asarray(kf.pose, float).ravel().tolist()] for kf in graph.keyframes] \
                if graph is not None else []
            segments[str(seg)] = {"keyframes": keyframes}
        return {"input": self.input_name, "frame_size": list(self.frame_size or ()),
                "frames_in": self.stats.frames_in, "rows": len(self._rows), "order": order,
                "segments": segments, "summary": summary}

    def _save_state(self, summary: dict, *, final: bool = False, extra: dict | None = None) -> bool:
        """Checkpoint the full-resolution map (in the background unless ``final``: then every
        changed tile is written before returning). Returns whether it is written (or under way)."""
        if not self._checkpointing or self._state_refused or not self.mosaics:
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
            return self._state.save(self.mosaics, meta)
        for _ in range(10000):  # the snapshot budget may need several rounds
            self._state.save(self.mosaics, meta, wait=True)
            if self._state.failing or self._state.state.last_pending == 0:
                break
        return self._state.ok()

    def checkpoint(self) -> None:
        """Rewrite trajectory, run.json and a mosaic preview (atomically), and checkpoint the
        full-resolution map; a write that fails is logged once and tried again next time."""
        self._last_checkpoint = time.monotonic()
        self._rerender()
        summary = self.summary()
        summary["complete"] = False
        if self.mosaics and self._painter is not None:  # from thumbnails the painter keeps up to date
            segment = self._largest_segments()[0]
            self._attempt("preview.png", self._painter.write_preview, self.out_dir / "preview.png", segment,
                          self.mosaics[segment], self.cfg.output.preview_px,
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
        if rows is None or join is None or not self.mosaics or join.stats.stopped_at_frame is not None:
            return None
        main, footprints = self._largest_segments()[0], self.cfg.output.footprints

        def refresh() -> None:
            fit = self._gps_fit(rows, main)  # no georeference below georef.min_fixes GPS fixes
            if fit.geo is None or fit.problem is not None:
                return
            try:
                refresh_track_files(self.out_dir, self._first.paced(rows), self.frame_size,
                                    {main: (fit.geo.map_to_crs[:2], fit.geo.epsg)},
                                    t0_unix=summary.get("video_start_unix"), footprints=footprints)
            except (OSError, PhotomapError) as exc:
                log.warning("track files not refreshed: %s", exc)

        return refresh

    def _gps_fit(self, rows: TrajectoryRows, segment: int) -> SegmentFit:
        """The telemetry join's GPS fit of the glued rows of ``segment`` that have a kept sample
        (:meth:`TelemetryJoin.fit_segment`); from the worker or the writer (the rows' copy)."""
        join, (w, h) = self.telemetry, self.frame_size or (0, 0)
        glued = np.flatnonzero(rows.glued_mask(segment))
        found = [(k, f, s) for k, f in self._first.paced(zip(glued.tolist(), rows.frames[glued].tolist()))
                 if (s := join.kept(f))]
        return join.fit_segment(w, h, list(rows.poses(np.array([k for k, _, _ in found], np.int64))),
                                [s for _, _, s in found], [f for _, f, _ in found])

    def _georeference(self, summary: dict, maps: list[dict]) -> None:
        """Metric scale and georeference per segment, world files beside the mosaics, when the
        telemetry fits the images (else none: ``run.json`` ``telemetry.status`` says why)."""
        join = self.telemetry
        w, h = self.frame_size or (0, 0)
        main = maps[0]["segment"] if maps else 0
        posed = self._rows.glued(main)
        check = join.time_offset_check([r.t for r in posed], [pose_angle_deg(np.asarray(r.M)) for r in posed])
        fits = {info["segment"]: self._gps_fit(self._rows, info["segment"]) for info in maps}
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

    def finish(self) -> dict:
        """Write the final outputs; returns the run summary (also in ``run.json``).

        Every write is attempted: one that fails (e.g. disk full) is reported in one line and in
        ``write_errors``; when the map itself could not be written, the checkpoint keeps it
        (``photomap recover``), else the checkpoint is removed."""
        t0 = time.perf_counter()
        if self.loops is not None:
            for update in self.loops.flush():
                if isinstance(update, Join):
                    self._join(update)
                    message = (f"map segment {update.segment} joined segment {update.into} "
                               f"(confidence {update.confidence:.2f})")
                    log.info(message)
                    self.stats.events.append(message)
                else:
                    self._apply(update)
        if self._painter is not None:
            try:
                for segment in list(self.mosaics):  # every segment got its last frame
                    self._painter.end_segment(self.mosaics.get(segment), segment)
                self._painter.finish(self.mosaics)  # the re-renders the corrections need, in strips
                if self._placer is not None and self.mosaics:  # what vision left unplaced, by trusted telemetry
                    self._placed = self._placer.place(
                        self._rows, self._largest_segments(), lambda seg: self._gps_fit(self._rows, seg),
                        lambda seg, into, t: self._join(Join(seg, into, t, -1, -1, 0.0)),
                        lambda seg, k, img, pose, mask: self._painter.paint(self._mosaic(seg), seg, k, img, pose, mask))
                    self._painter.finish(self.mosaics)  # segments joined by the GPS re-rendered
            except PhotomapError as exc:  # the map stays as painted live: still written
                log.error("%s; the map keeps the poses it was painted with", exc)
            finally:
                self._painter.close()
        self.stats.timing.add("final_rerender", time.perf_counter() - t0)
        self._close_gaps()
        if self._state is not None:
            self._state.wait()
        if self._writer is not None:  # a checkpoint's trajectory.csv must not land after the final one
            self._writer.shutdown(wait=True)
        if self.loops is not None and self.loops.store.folder.parent == state_folder(self.out_dir):
            shutil.rmtree(self.loops.store.folder, ignore_errors=True)  # re-rendered: room for the outputs
        self._attempt("trajectory.csv", self._write_trajectory)
        summary = self.summary()
        maps, unwritten = [], []
        max_px = self.cfg.output.max_mosaic_px
        for rank, seg in enumerate(self._largest_segments()):
            name = "mosaic.png" if rank == 0 else f"mosaic_segment{seg}.png"
            info = self._attempt(name, write_png, self.out_dir / name, self.mosaics[seg], max_px)
            if info is None:
                info = png_placement(name, self.mosaics[seg], max_px)
                if info is not None:
                    info["segment"] = seg
                    unwritten.append(info)
                continue
            self._attempt(name, remove_sidecars, self.out_dir, name)  # an earlier run's georeference must not stay
            info["segment"] = seg
            if info["scale"] < 1.0:
                tiles = self.out_dir / ("tiles" if rank == 0 else f"tiles_segment{seg}")
                if not self._attempt(f"{tiles.name}/", lambda t=tiles, m=self.mosaics[seg]: write_tiles(t, m) or True):
                    unwritten.append(info)
                info["tiles"] = tiles.name
                info["tile_size"] = self.mosaics[seg].tile_size
            maps.append(info)
        (self.out_dir / "preview.png").unlink(missing_ok=True)
        if self.telemetry is not None:
            self._attempt("georeference", self._georeference, summary, maps + [u for u in unwritten if u not in maps])
            summary["telemetry"]["placed"] = self._placed
            for info in unwritten:
                if info not in maps:
                    remove_sidecars(self.out_dir, info["file"])  # no PNG for them
            exports = self._attempt("geo outputs", write_geo_outputs, self.out_dir, maps, self.mosaics, self._rows,
                                    self.frame_size, t0_unix=summary["video_start_unix"],
                                    cog=self.cfg.output.geotiff, footprints=self.cfg.output.footprints)
            if exports:
                summary["exports"] = exports
        summary["mosaics"] = maps
        summary["complete"] = True
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
        elif self._checkpointing:  # keyframes kept for a restart: not needed any more
            shutil.rmtree(state_folder(self.out_dir), ignore_errors=True)
        if self._state is not None:
            summary["checkpoint"] = self._state.summary()
        if self._write_errors:
            summary["write_errors"] = dict(self._write_errors)
        self.stats.timing.add("final_outputs", time.perf_counter() - t0)
        summary["timing_ms"] = self.stats.timing.summary()
        self._attempt("run.json", write_json, self.out_dir / "run.json", summary)
        try:  # report.html: the flight at a glance, offline (its map from the tiles, not the PNG)
            main = self.mosaics.get(maps[0]["segment"]) if maps else None
            small = render_small(main, min(THUMB_PX, max(maps[0]["size"]))) if main is not None else None
            write_report(self.out_dir, map_image=small)
        except (OSError, ValueError, PhotomapError) as exc:
            log.warning("report.html not written: %s", exc)
        for store in self._tile_stores.values():
            store.flush()  # its writes done before the folder goes
        if self._own_cache and self._cache_dir is not None:
            shutil.rmtree(self._cache_dir, ignore_errors=True)
        if self._placer is not None:
            self._placer.close()
        return summary
