"""The mapping pipeline: frames in, a growing photo map and a trajectory out.

Threads live here (and in the drivers): a file source is decoded by a prefetch thread into a
bounded queue (replay never drops); a live source already drops its oldest frames when the worker
falls behind. One worker thread takes each frame through its steps (``_track``: rectify, resize,
register and pose; ``_paint``; ``_record``: its row and counts; ``_close_loops``; ``_emit_frame``:
a :class:`~photomap.mapping.events.FrameEvent` to the sinks) and checkpoints the outputs
periodically; :meth:`MappingPipeline.stop` (SIGINT/SIGTERM) ends capture, lets the worker finish,
and the outputs are written. The map is painted by a :class:`~photomap.mapping.painter.Painter`
(keyframes whole, other frames only their new ground); after a loop-closure correction a
:class:`~photomap.mapping.rerender.Rerenderer` thread re-renders the moved tiles and the worker
swaps them in, never waiting. The thread budget (BLAS pinned to one thread, OpenCV's threads
``mapping.opencv_threads``) holds for the whole run; the pipeline records its per-stage times
(:mod:`photomap.mapping.timing`, ``run.json`` ``timing_ms``).

State has one owner: the pipeline owns the trajectory rows, the run's counters, the tracker and
the painter; :class:`~photomap.mapping.segments.SegmentMaps` the maps (one per segment) and their
life; :class:`~photomap.mapping.run_outputs.RunOutputs` what the run writes (checkpoints, the
final outputs, the georeference); the loop closer returns corrections that the pipeline applies;
sinks only read events.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections import deque
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from photomap.config import Config
from photomap.core.ifmi import Registrar
from photomap.core.matching import PairMatcher
from photomap.core.maprelative import map_correction
from photomap.core.mosaic import TiledMosaic
from photomap.core.stretch import RunningStretch
from photomap.core.tracking import LOW_CONFIDENCE, REFERENCE, TrackStep, Tracker
from photomap.drivers.frames import Frame, FrameSource
from photomap.drivers.images import ImageFolderSource
from photomap.geometry import frame_centre
from photomap.errors import PhotomapError
from photomap.io.keyframestore import KeyframeStore
from photomap.mapping.checkpoint import state_folder
from photomap.mapping.events import FrameEvent, FrameSink, GeoreferenceSink
from photomap.mapping.frameprep import FramePrep, view_points
from photomap.mapping.loopclosure import Correction, Join, LoopCloser
from photomap.mapping.memory import frozen_heap, limit_heap_growth, trimmed_heap
from photomap.mapping.painter import Painter
from photomap.mapping.rerender import Rerenderer
from photomap.mapping.rows import RowView, TrajectoryRows
from photomap.mapping.run_outputs import RunOutputs
from photomap.mapping.segments import SegmentMaps
from photomap.mapping.telemetry_join import TelemetryJoin
from photomap.mapping.telemetry_place import TelemetryPlacer
from photomap.mapping.threads import OUTPUTS_SWITCH_INTERVAL_S, WorkerFirst, switch_interval
from photomap.mapping.timing import StageTimes
from photomap.telemetry.samples import TelemetrySample

log = logging.getLogger(__name__)

_END = object()
# A replay (not live) re-renders and optimises in lockstep with the frames: a re-render job at
# most every this many frames, swapped in (a pose-graph solve applied) this many frames after it
# started, so that the same input makes the same map on any machine.
_LOCKSTEP_FRAMES = 30
_LOOP_LOCKSTEP_FRAMES = 8  # ... and a new keyframe's loop registrations (a few ms each) join its graph


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


@dataclass
class _Placed:
    """A frame rectified and tracked: what the later steps of its work use."""

    image: np.ndarray  # the image the map gets (rectified with telemetry)
    mask: np.ndarray | None  # validity of its pixels (None: all valid)
    small: np.ndarray  # ... resized to the working size
    sample: TelemetrySample | None
    step: TrackStep
    new_segment: bool  # the frame started a map segment
    register_s: float
    touched: set = field(default_factory=set)  # map tiles it changed
    pending: tuple[int, np.ndarray, np.ndarray] | None = None  # the low-confidence frame before it


def _prefetch(source: FrameSource, depth: int, stop: threading.Event, *,
              poll: float = 0.2, join_timeout: float = 5.0, timing: StageTimes | None = None,
              max_bytes: int = 64 << 20, prepare: Callable[[Frame], object] = lambda frame: None
              ) -> Iterator[tuple[Frame, object]]:
    """Decode ``source`` in a thread, ``depth`` frames ahead but at most ``max_bytes`` of frames
    (at least 2; 4K frames are 25 MB each) (blocking: never drops); yields ``(frame,
    prepare(frame))``, ``prepare`` called in that thread too. The time of each frame's reading
    and decoding goes to ``timing`` (stage ``decode``).

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
                if stop.is_set() or not put((frame, prepare(frame))) or stop.is_set():
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
    final_outputs : mapping, optional
        More outputs written at the end, in ``run.json`` under their names (see :class:`RunOutputs`).
    """

    def __init__(self, source: FrameSource, cfg: Config, out_dir: str | Path, *,
                 sinks: Sequence[FrameSink] = (), input_name: str = "",
                 telemetry: TelemetryJoin | None = None, final_outputs: Mapping[str, Callable] | None = None) -> None:
        self.source = source
        # stills that can be read again are painted as decoded and kept by reference
        self._readable_again: Callable[[int], bool] | None = getattr(source, "readable_again", None)
        self.cfg = cfg
        self.out_dir = Path(out_dir)
        self.sinks = tuple(sinks)
        self.input_name = input_name
        self.telemetry = telemetry
        self.stats = RunStats()
        self._rows = TrajectoryRows()  # one per input frame, as columns (a long flight keeps them for hours)
        self.segments = SegmentMaps(cfg.mosaic, self._rows)  # the maps, one per segment
        self.frame_size: tuple[int, int] | None = None  # (w, h) of the input
        self.tracker: Tracker | None = None
        self.loops: LoopCloser | None = None
        self._stop = threading.Event()
        # live: the background threads' Python code waits while the worker maps a frame (a replay
        # has no frame deadline: throughput first)
        self._first = WorkerFirst(enabled=source.live)
        self._prep = FramePrep.from_config(cfg)  # lens undistortion and frame mask (None: neither)
        self.outputs = RunOutputs(self.out_dir, cfg.output, self._rows, self.segments, telemetry=telemetry,
                                  first=self._first, input_name=input_name,  # what the run writes
                                  band_source=source if getattr(source, "captures", None) else None,  # multi-band
                                  raw_frame=getattr(source, "raw_frame", None), frame_prep=self._prep,
                                  final_outputs=final_outputs)
        self._next_index = 0
        self._started = 0.0
        self._last_checkpoint = 0.0
        self._warned: set[str] = set()
        self._pending: tuple[int, np.ndarray, np.ndarray] | None = None  # last low-confidence frame: index, image, small
        self._source_gaps = 0  # rows made for frames the source lost (dropped or undecodable)
        self._painter: Painter | None = None  # paints the maps (made with the tracker)
        self._map_scale = cfg.mapping.map_scale  # map px per input px (mapping.map_px may lower it)
        self._placer: TelemetryPlacer | None = None  # frames vision left unplaced, with telemetry
        self._placed: dict | None = None  # what the placer did (run.json telemetry.placed)
        self._deep = RunningStretch()  # deep frames a source delivers raw (a Y16 camera) to uint8, one range a flight
        self._small: tuple[int, int] | None = None  # the working size (w, h), from the first frame
        self._presized = True  # frames reach the tracker as decoded (:meth:`_presize`; the worker's)

    @property
    def on_georeference(self) -> GeoreferenceSink | None:
        """Told each live GPS fit of the main map (writer thread) and the final one: (segment, fit)."""
        return self.outputs.on_georeference

    @on_georeference.setter
    def on_georeference(self, sink: GeoreferenceSink | None) -> None:
        self.outputs.on_georeference = sink

    @property
    def worker_first(self) -> WorkerFirst:
        """The gate other threads' Python code waits at while the worker maps a frame (live)."""
        return self._first

    @property
    def rows(self) -> tuple[RowView, ...]:
        """The trajectory so far, one row per input frame (read only: the pipeline writes them)."""
        return tuple(self._rows)

    @property
    def mosaics(self) -> dict[int, TiledMosaic]:
        """The maps so far, one per segment (read only: :class:`SegmentMaps` owns them)."""
        return self.segments.mosaics

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
            prefetched = None if self.source.live else _prefetch(self.source, 8, self._stop, timing=self.stats.timing,
                                                                 prepare=self._presize)
            frames = ((frame, None) for frame in self.source) if prefetched is None else prefetched
            try:
                for frame, small in frames:  # after stop(), the frames already queued are drained
                    with self._first.frame():
                        self._process(frame, small)
            except BaseException as exc:  # reported by run(), after the outputs are written
                failure.append(exc)
            finally:
                if prefetched is not None:
                    prefetched.close()  # stops the decode thread (bounded wait), also after an error

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
                with switch_interval(OUTPUTS_SWITCH_INTERVAL_S):
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
        if self._prep is not None:
            self._prep.setup(w, h)
            if self.telemetry is not None:
                self.telemetry.use_camera(self._prep.fx, self._prep.mask)
        mapping = self.cfg.mapping
        # the map's resolution: at most map_px a video frame (survey stills keep theirs)
        if mapping.map_px and max(w, h) > mapping.map_px and not isinstance(self.source, ImageFolderSource):
            mapping = dataclasses.replace(mapping, map_scale=mapping.map_scale * mapping.map_px / max(w, h))
        self._map_scale = mapping.map_scale
        registrar = Registrar((self._small[1], self._small[0]), self.cfg.registration,
                              self._prep.window(self._small) if self._prep is not None else None)
        matcher = PairMatcher(registrar, min_confidence=mapping.min_confidence,
                              trust_confidence=mapping.trust_confidence, verify=mapping.verify_placements,
                              second_opinion=mapping.second_opinion, second_opinion_px=mapping.second_opinion_px)
        self.tracker = Tracker(matcher, f, mapping,
                               telemetry_prior=self.telemetry.prior if self.telemetry else None)
        store = None
        if mapping.keyframes and mapping.loop_closure:
            keyframes = (state_folder(self.out_dir) / "keyframes" if self.outputs.checkpointing and not self.cfg.mosaic.cache_dir
                         else self.segments.cache() / "keyframes")  # kept with the checkpoint: a restart can re-render
            store = KeyframeStore(keyframes, read_again=getattr(self.source, "read_again", None))
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
        self.outputs.start(self.frame_size, self.loops, self._painter)

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
        """The tracker started segment ``current``: the maps retire the others
        (:meth:`SegmentMaps.retire`); the single posed frame of a dropped one counts
        ``low_confidence``."""
        for seg, glued in self.segments.retire(current):
            self._drop_segment(seg, glued)

    def _drop_segment(self, seg: int, glued: list[RowView]) -> None:
        for row in glued:
            row.M, row.status = None, LOW_CONFIDENCE
            self.stats.registered -= 1
            self.stats.low_confidence += 1
            if math.isfinite(row.confidence):
                self.stats.confidence_sum -= row.confidence
        self._painter.forget(seg)
        if self.loops is not None:
            self.loops.forget(seg)
        self.stats.segments_dropped += 1
        self._warn_once("segment-dropped", f"map segment {seg} dropped: nothing registered to its first frame "
                                           f"(featureless or dark ground?); such frames count as low_confidence")

    def _presize(self, frame: Frame) -> np.ndarray | None:
        """The frame at the working size, made in the decode thread ahead of the worker
        (:meth:`_track` takes it when neither the lens nor the tilt changes the frame), or None:
        before the first frame, for another size or a deep frame, and while they do change it."""
        size, presized = self._small, self._presized
        if size is None or not presized or frame.image.dtype != np.uint8 or \
                frame.image.shape[:2] != (self.frame_size[1], self.frame_size[0]):
            return None
        return cv2.resize(frame.image, size, interpolation=cv2.INTER_AREA)

    def _process(self, frame: Frame, small: np.ndarray | None = None) -> None:
        t0 = time.perf_counter()
        try:
            self._process_frame(frame, small)
        finally:  # the worker's whole time for the frame: the largest is its longest stall
            self.stats.timing.add("frame", time.perf_counter() - t0)

    def _process_frame(self, frame: Frame, small: np.ndarray | None = None) -> None:
        """One frame through the worker: tracked, painted, recorded, loops closed, the maps kept
        up, the sinks told, and a checkpoint when one is due. ``small``: :meth:`_presize`."""
        t0 = time.perf_counter()
        timing = self.stats.timing
        self._gaps(frame.index)  # frames before this one that never came: dropped or undecodable
        self._next_index = max(self._next_index, frame.index + 1)
        self.stats.frames_in += 1
        raw = None  # a deep frame as delivered: map_raw.tif's values
        if frame.image.dtype != np.uint8:
            raw = frame.image
            frame = dataclasses.replace(frame, image=self._deep(frame.image))
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
            placed = self._track(frame, t0, small)
            self._paint(frame, placed)
        except Exception as exc:  # never lose the map for one bad frame
            self.stats.errors += 1
            self._warn_once(f"error:{type(exc).__name__}",
                            f"frame {frame.index} skipped: {type(exc).__name__}: {exc}")
            log.debug("frame %d failed", frame.index, exc_info=True)
            self._skip(frame, "corrupt", t0)
            return
        messages = self._record(frame, placed)
        if raw is not None:
            self.outputs.offer_raw(frame.index, raw, placed.step.pose, placed.step.segment)
        corrected_path = self._close_loops(frame, placed, messages)
        t4 = time.perf_counter()
        step = placed.step
        placed.touched |= self._painter.pump(self.mosaics, frame=frame.index).get(step.segment, set())  # re-rendered
        self.segments.spill_retired(self._segment)
        timing.add("map_upkeep", time.perf_counter() - t4)
        self.stats.worker_s += time.perf_counter() - t0
        if self.sinks:
            self._emit_frame(frame, placed, messages, corrected_path, t0)
        interval = self.cfg.output.checkpoint_interval
        if interval > 0 and time.monotonic() - self._last_checkpoint >= interval:
            t6 = time.perf_counter()
            self.checkpoint()
            timing.add("outputs", time.perf_counter() - t6)

    def _track(self, frame: Frame, t0: float, presized: np.ndarray | None = None) -> _Placed:
        """Undistort and mask the frame (``camera`` lens, ``capture.mask``), rectify it with its
        telemetry, resize it to the working size (``presized``: the unchanged frame's, from
        :meth:`_presize`) and track it (a new keyframe snapped to the map when
        ``mapping.map_relative``); ``t0`` (perf_counter s) is when the frame's work began."""
        timing = self.stats.timing
        image = frame.image
        sample = self.telemetry.sample(frame) if self.telemetry else None
        mask = None  # validity of the view's pixels (None: all valid)
        if self._prep is not None:
            image, mask = self._prep.apply(image), self._prep.mask
        if sample is not None:
            view = self.telemetry.rectify_frame(image, sample, frame.index)
            image, mask = view.image, (view.mask if view.homography is not None else mask)
        unchanged = image is frame.image
        self._presized = unchanged  # the decode thread resizes the next frames while frames stay as decoded
        small = presized if unchanged and presized is not None else \
            cv2.resize(image, self._small, interpolation=cv2.INTER_AREA)
        t1 = time.perf_counter()
        timing.add("resize", t1 - t0)
        started = self.tracker.segments
        step = self.tracker.step(small, frame.index, sample, image)
        register_s = time.perf_counter() - t1
        self.stats.register_s += register_s
        if step.keyframe and step.reference is not None and self.cfg.mapping.map_relative:
            self._map_relative(step, small)
        timing.add("register", time.perf_counter() - t1)
        return _Placed(image, mask, small, sample, step, self.tracker.segments > started, register_s)

    def _paint(self, frame: Frame, placed: _Placed) -> None:
        """Paint the tracked frame (and the frame a new segment was anchored at) into its map;
        the maps of segments it left get their last frame."""
        t2 = time.perf_counter()
        step = placed.step
        if placed.new_segment:  # earlier segments got their last frame
            for segment in list(self.mosaics):
                if segment != step.segment:
                    self._painter.end_segment(self.mosaics.get(segment), segment)
        touched: set = set()
        if step.anchor is not None:
            touched |= self._anchor(step)
        if step.pose is not None:
            whole = step.keyframe and (self.cfg.mapping.keyframes or step.status == REFERENCE)
            readable = self._readable_again
            as_read = placed.image is frame.image and readable is not None and readable(frame.index)
            touched |= self._painter.paint(self.segments.mosaic(step.segment), step.segment, frame.index,
                                           placed.image, step.pose, placed.mask, whole=whole, as_read=as_read)
        self.stats.timing.add("paint", time.perf_counter() - t2)
        placed.touched = touched
        placed.pending = self._pending
        self._pending = (frame.index, placed.image, placed.small) if step.status == LOW_CONFIDENCE else None

    def _record(self, frame: Frame, placed: _Placed) -> list[str]:
        """The frame's row, its counts and events (segments retired when it started one);
        returns its messages for the sinks."""
        step, sample = placed.step, placed.sample
        if placed.new_segment:  # this frame started a map segment
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
            self._placer = self._placer or TelemetryPlacer(self.telemetry, self.frame_size,
                                                           self.segments.cache() / "unplaced")  # the run's scratch
            self._placer.keep(frame.index, frame.t, placed.image, placed.mask, placed.sample)
        return messages

    def _close_loops(self, frame: Frame, placed: _Placed, messages: list[str]) -> Callable[[], np.ndarray] | None:
        """Hand the frame to the loop closer and apply the corrections and joins it returns (their
        messages appended to ``messages``); returns the current segment's path as corrected when
        a correction moved it (for the sinks), else None."""
        if self.loops is None:
            return None
        step, pending = placed.step, placed.pending
        corrected_path = None
        t3 = time.perf_counter()
        if step.anchor is not None and pending is not None and pending[0] == step.anchor:
            self.loops.on_anchor(step, pending[2], pending[1])
        for update in self.loops.on_step(frame.index, step, placed.small, placed.image, placed.sample):
            if isinstance(update, Join):
                placed.touched = self._join(update)  # the frame's tiles were in the joined map's frame: none here
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
        self.stats.timing.add("loop_closure", time.perf_counter() - t3)
        return corrected_path

    def _emit_frame(self, frame: Frame, placed: _Placed, messages: list[str],
                    corrected_path: Callable[[], np.ndarray] | None, t0: float) -> None:
        """The frame's event to the sinks (``t0``: perf_counter s when the frame's work began)."""
        t5 = time.perf_counter()
        step, sample = placed.step, placed.sample
        link = self.telemetry.link_summary() if self.telemetry is not None else {}
        anchor = (step.anchor, step.anchor_pose.copy()) if step.anchor is not None else None
        self._emit(FrameEvent(
            frame.index, frame.t, self.source.live, frame.image, self.frame_size, step.status,
            None if self._rows[-1].M is None else np.array(self._rows[-1].M, float), float(step.confidence),
            step.segment,
            keyframe=step.keyframe, new_segment=placed.new_segment, anchor=anchor, messages=tuple(messages),
            touched=frozenset(placed.touched), tiles=self.mosaics.get(step.segment),
            register_ms=1000.0 * placed.register_s, frame_ms=1000.0 * (time.perf_counter() - t0),
            dropped_frames=int(self.source.stats.dropped), reconnects=int(self.source.stats.reconnects),
            telemetry=sample, focal_px=self.telemetry.focal(self.frame_size[0]) if self.telemetry else None,
            link_lost=int(link.get("link_lost", 0)),
            link_regained=int(link.get("link_regained", 0)), path_after_correction=corrected_path,
            view_points=view_points(self._prep, self.telemetry.homography(frame.index) if self.telemetry else None)))
        self.stats.timing.add("sinks", time.perf_counter() - t5)

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
        self.segments.join(join)  # its kept frames are re-rendered into join.into
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
            return self._painter.paint(self.segments.mosaic(step.segment), step.segment, step.anchor, self._pending[1],
                                       step.anchor_pose, self._view_mask(step.anchor), whole=True)
        return set()

    def _view_mask(self, index: int) -> np.ndarray | None:
        """Valid pixels of the image the map got of frame ``index`` (None: all of them)."""
        mask = self.telemetry.mask(index) if self.telemetry is not None else None
        return mask if mask is not None or self._prep is None else self._prep.mask

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
                    "working_size": list(self._small or ()),
                    "reconnects": src.reconnects, "map_scale": self._map_scale,
                    "video_start_unix": self._video_start_unix()})
        if self._prep is not None:
            out["frame_prep"] = self._prep.summary()
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

    def _rerender(self) -> None:
        """Apply a finished loop-closure correction and swap re-rendered tiles in (never waits:
        the re-rendering runs in the painter's background thread)."""
        if self.loops is not None:
            correction = self.loops.poll()
            if correction is not None:
                self._apply(correction)
        if self.tracker is not None:
            self._painter.pump(self.mosaics)

    def checkpoint(self) -> None:
        """Rewrite trajectory, run.json and a mosaic preview (atomically), and checkpoint the
        full-resolution map (:meth:`RunOutputs.checkpoint`)."""
        self._last_checkpoint = time.monotonic()
        self._rerender()
        self.outputs.checkpoint(self.summary())

    def finish(self) -> dict:
        """Apply the last corrections and joins, paint the last re-renders, and write the final
        outputs (:meth:`RunOutputs.finish`); returns the run summary (also in ``run.json``)."""
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
                        self._rows, self.segments.largest(), lambda seg: self.outputs.gps_fit(self._rows, seg),
                        lambda seg, into, t: self._join(Join(seg, into, t, -1, -1, 0.0)),
                        lambda seg, k, img, pose, mask: self._painter.paint(self.segments.mosaic(seg), seg, k, img,
                                                                            pose, mask))
                    self._painter.finish(self.mosaics)  # segments joined by the GPS re-rendered
            except PhotomapError as exc:  # the map stays as painted live: still written
                log.error("%s; the map keeps the poses it was painted with", exc)
            finally:
                self._painter.close()
        self.stats.timing.add("final_rerender", time.perf_counter() - t0)
        self._close_gaps()
        summary = self.outputs.finish(self.summary, self.stats.timing, t0, placed=self._placed)
        self.segments.close()
        if self._placer is not None:
            self._placer.close()
        return summary
