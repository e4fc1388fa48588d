"""Loop closure in the running pipeline: keyframe graphs per segment and their corrections.

The pipeline hands every tracked frame to :class:`LoopCloser`. Keyframes are kept on disk
(:class:`photomap.io.keyframestore.KeyframeStore`: here the working-resolution image; the image
that re-renders the map is the painter's), so memory stays bounded over a long flight.
When a new keyframe closes a loop, the segment's pose graph is optimised
(:mod:`photomap.core.keyframes`) and the loop closer returns a :class:`Correction`: the new pose
of every frame it can re-pose (a frame keeps its measured pose relative to the keyframe it was
registered against). The pipeline, which owns the trajectory, the tracker and the maps, applies
it. The optimisation runs on a snapshot of the graph in a background thread (one at a time), so
the worker never waits for it; a finished solution is returned by the next call. The loop
registrations of a new keyframe (against up to ``loop_candidates`` old keyframes read back from
the store) run in another background thread; their edges join the graph when they are done.

Loops by appearance: drift can carry the estimate of a revisit past ``loop_radius``, where no
candidate is looked for. Each new keyframe's place signature is therefore also searched among
the older keyframes of its segment (:class:`photomap.core.places.PlaceIndex`: one matrix product
over the segment's signatures, the newest ``loop_min_gap`` keyframes left out); the best
``loop_appearance_candidates`` are registered without a prior, in the same background job as the
nearby candidates, and kept when the overlap check confirms them. Their edges are not held to the
drifted prediction: the pose graph's robust loss judges them (a wrong one loses its pull and is
dropped). At the end of the run the last tracked frame is searched the same way.

Segments rejoin: a new map segment (started when the link to the map was lost) is not forever.
Each of its new keyframes is also registered against keyframes of the other segments: the
nearest by GPS when the keyframes carry a fix, else the most similar by their place signature
(:mod:`photomap.core.places`, translation and rotation invariant, as iFMI's magnitude spectra
are). A confident match joins the two segments into one map frame (a ``join`` edge of one pose
graph); the loop closer returns a :class:`Join` that the pipeline applies to its trajectory, maps
and tracker. Live, that search (a few registrations with features, keyframe images read back:
100-400 ms at 1080p) runs in the loop registrations' thread, one keyframe at a time, and its join
comes with a later frame; a replay searches in the worker, so that its map does not depend on the
machine's speed.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Iterator, Mapping

import cv2
import numpy as np

from photomap.config import MappingConfig, PosegraphConfig
from photomap.core.matching import PairMatcher, View
from photomap.core.ifmi import Registrar
from photomap.core.keyframes import KeyframeGraph, KeyframePriors, LoopCandidate, LoopMeasurement
from photomap.core.places import PlaceIndex, place_signature, place_similarities
from photomap.core.tracking import TrackStep
from photomap.geo.georef import enu_from_latlon
from photomap.geometry import pose_scale, scaling, to_h
from photomap.io.keyframestore import KeyframeStore
from photomap.mapping.threads import WorkerFirst, lower_priority
from photomap.telemetry.samples import TelemetrySample

log = logging.getLogger(__name__)

# Live, a pose-graph solve starts at most this often (s): each correction costs the worker time
# in proportion to the flight's frames (a replay: one every lockstep_frames at most).
SOLVE_INTERVAL_S = 1.0
# Join candidates whose spectra and features are kept (a few MB each at most).
_JOIN_VIEWS = 16
# Ground scale from GPS: keyframe pairs at least this many GPS sigmas apart, looked for among the
# previous keyframes of a chain; the median of the latest pairs, once there are a few.
_GROUND_BASE_SIGMAS = 5.0
_GROUND_LOOKBACK = 20
_GROUND_PAIRS = 200
_GROUND_MIN_PAIRS = 5
# A join candidate farther (GPS) than the frame diagonal on the ground plus this many GPS sigmas
# cannot overlap the new keyframe: not tried.
_JOIN_GPS_SIGMAS = 4.0


class PoseTable(Mapping[int, np.ndarray]):
    """Frame index -> 3x3 pose, held in two arrays: ``frames`` (n,) sorted, ``poses`` (n, 3, 3),
    read-only (a consumer may keep views of them)."""

    def __init__(self, frames: np.ndarray, poses: np.ndarray) -> None:
        frames = np.asarray(frames, np.int64)
        order = np.argsort(frames, kind="stable")
        self.frames = frames[order]
        self.poses = np.asarray(poses, np.float64).reshape(-1, 3, 3)[order]
        self.frames.flags.writeable = self.poses.flags.writeable = False

    def __getitem__(self, frame: int) -> np.ndarray:
        i = int(np.searchsorted(self.frames, frame))
        if i < len(self.frames) and self.frames[i] == frame:
            return self.poses[i]
        raise KeyError(frame)

    def take(self, frames: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Which of ``frames`` the table holds (bool (n,)) and their poses (in that order), at once."""
        frames = np.asarray(frames, np.int64)
        i = np.minimum(np.searchsorted(self.frames, frames), max(len(self.frames) - 1, 0))
        hit = (self.frames[i] == frames) if len(self.frames) else np.zeros(len(frames), bool)
        return hit, self.poses[i[hit]]

    def __iter__(self) -> Iterator[int]:
        return iter(self.frames.tolist())

    def __len__(self) -> int:
        return len(self.frames)


@dataclass(frozen=True)
class Correction:
    """A pose-graph correction of one segment.

    ``poses``: frame index -> new 3x3 pose (input pixels -> map pixels) of every frame that could
    be re-posed (a :class:`PoseTable`: apply it in bulk through its arrays); ``latest``: the 3x3
    correction (old map px -> new map px) of the segment's newest keyframe, which the tracker
    applies to go on from the corrected pose; ``keyframes``: the segment's keyframes (index, new
    3x3 pose) in order, to re-render the map from.
    """

    segment: int
    poses: PoseTable
    latest: np.ndarray
    keyframes: tuple[tuple[int, np.ndarray], ...]


@dataclass(frozen=True)
class Join:
    """Segment ``segment`` now belongs to segment ``into``: ``transform`` (3x3) maps map px of
    ``segment`` to map px of ``into``; found between keyframe ``frame`` (of ``segment``) and
    keyframe ``match`` (of ``into``) at registration ``confidence``."""

    segment: int
    into: int
    transform: np.ndarray
    frame: int
    match: int
    confidence: float


Update = Correction | Join


class RelativePoses:
    """Frame -> (its keyframe, measured 3x3 input px of the frame -> input px of the keyframe),
    for every tracked frame of a segment, in compact arrays (56 bytes a frame rather than about
    400 in a dict of tuples of arrays: a long flight's memory stays flat)."""

    def __init__(self) -> None:
        self._frames = np.zeros(0, np.int64)
        self._refs = np.zeros(0, np.int64)
        self._rel = np.zeros((0, 2, 3))
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def add(self, frame: int, ref: int, rel: np.ndarray) -> None:
        if self._n == len(self._frames):  # grow by half: amortised O(1), at most 1.5x the size
            cap = max(64, self._n + self._n // 2)
            self._frames = np.resize(self._frames, cap)
            self._refs = np.resize(self._refs, cap)
            self._rel = np.resize(self._rel, (cap, 2, 3))
        self._frames[self._n], self._refs[self._n] = frame, ref
        self._rel[self._n] = np.asarray(rel, float)[:2]
        self._n += 1

    def update(self, other: RelativePoses) -> None:
        for frame, ref, rel in zip(other._frames[:other._n], other._refs[:other._n], other._rel[:other._n]):
            self.add(int(frame), int(ref), rel)

    def poses(self, keyframes: np.ndarray, keyframe_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frame indices (n,) and 3x3 poses (n, 3, 3) ``pose of ref @ rel`` of the frames whose
        keyframe is among ``keyframes`` (indices, (k,)) with poses ``keyframe_poses`` (k, 3, 3),
        keyframes themselves left out."""
        frames, refs = self._frames[:self._n], self._refs[:self._n]
        keep = ~np.isin(frames, keyframes) & np.isin(refs, keyframes)
        frames, refs, rel = frames[keep], refs[keep], self._rel[:self._n][keep]
        order = np.argsort(keyframes)
        stack = np.asarray(keyframe_poses, np.float64)[order][np.searchsorted(keyframes[order], refs)]
        full = np.zeros((len(rel), 3, 3))
        full[:, :2], full[:, 2, 2] = rel, 1.0
        return frames, np.matmul(stack, full)  # one product for all


class LoopCloser:
    """Keyframe graphs of all segments of a run (used from the worker thread; the optimiser runs
    on snapshots in its own thread).

    Parameters
    ----------
    store : KeyframeStore
        Where keyframe images go.
    matcher : PairMatcher
        Places keyframes against each other (iFMI at the working resolution, checked; features
        as a second opinion for joins).
    frame_size : (w, h)
        Input frame size.
    working_scale : float
        Working resolution / input resolution.
    params, graph_params : the ``mapping`` and ``posegraph`` settings.
    use_priors : bool
        Telemetry of keyframes becomes pose-graph priors.
    join_candidates : int
        Keyframes of other segments tried per new keyframe of a segment (the nearest by GPS,
        else the most similar by place signature).
    settle_on_priors : bool
        At the end, optimise every segment with telemetry priors even without loop closures
        (stills: chains of few, weak links, that the GPS and altitude of each still hold together).
    first : WorkerFirst or None
        The background solves and loop registrations wait at its pause points (before each
        registration, each evaluation of a solve) while the worker maps a frame.
    """

    def __init__(self, store: KeyframeStore, matcher: PairMatcher, frame_size: tuple[int, int],
                 working_scale: float, params: MappingConfig, graph_params: PosegraphConfig,
                 use_priors: bool = False, join_candidates: int = 4, settle_on_priors: bool = False,
                 lockstep_frames: int | None = None, loop_lockstep_frames: int | None = None,
                 first: WorkerFirst | None = None) -> None:
        self.store = store
        self._first = first or WorkerFirst(enabled=False)
        self.matcher = matcher
        self.registrar = matcher.registrar
        self.frame_size = frame_size
        self.working_scale = working_scale
        self.params = params
        self.graph_params = graph_params
        self.use_priors = use_priors
        self.graphs: dict[int, KeyframeGraph] = {}
        # segment -> frame -> (keyframe, 3x3 measured: input px of frame -> of keyframe)
        self.relative: dict[int, RelativePoses] = {}
        self.corrections = 0
        self.join_candidates = join_candidates
        self.settle_on_priors = settle_on_priors
        self.joins: list[Join] = []
        self._merged_into: dict[int, int] = {}  # joined segment -> the segment it joined
        self._segment_of: dict[int, int] = {}  # keyframe -> its segment (after joins)
        self._places = PlaceIndex()  # keyframe -> place signature, by segment: loops by appearance, joins
        self._position: dict[int, tuple[float, float]] = {}  # keyframe -> (east, north) m, with GPS
        # ground metres per input pixel, one value per keyframe with GPS (see _ground_scale)
        self._ground_m_per_px: deque[float] = deque(maxlen=_GROUND_PAIRS)
        # (keyframe, image shape) -> its view as a join candidate, the newest last (see _join_view)
        self._join_views: dict[tuple[int, tuple[int, int]], View] = {}
        self._to_small = scaling(working_scale)
        self._from_small = np.linalg.inv(self._to_small)
        self._enu_origin: tuple[float, float] | None = None  # first GPS fix of the run
        # optimisation in a background thread (at low priority: the worker comes first): one at
        # a time, on a snapshot of the graph
        self._executor = (ThreadPoolExecutor(1, "photomap-posegraph", initializer=lower_priority)
                          if params.optimize_in_background else None)
        self._running: tuple[int, Future] | None = None  # (segment, solve of its snapshot)
        # ... and a new keyframe's loop registrations in another (with a registrar of its own)
        self._loop_executor = (ThreadPoolExecutor(1, "photomap-loops", initializer=lower_priority)
                               if params.optimize_in_background else None)
        self._loop_registrar = (Registrar(self.registrar.shape, self.registrar.params, self.registrar.mask)
                                if self._loop_executor is not None else None)
        self._loop_jobs: deque[tuple[int, int, Future]] = deque()  # (keyframe, frame submitted, measurements)
        # live: a new keyframe's search for a join to another segment (a few registrations with
        # features and keyframe images read from disk: 100-400 ms at 1080p) runs in that thread
        # too, one at a time, with a matcher of its own; a replay searches in the worker (the
        # map does not depend on the machine's speed)
        self._join_matcher = (matcher.twin(self._loop_registrar)
                              if self._loop_executor is not None and lockstep_frames is None else None)
        self._join_job: tuple[int, Future] | None = None  # (keyframe, its placement against another segment)
        # the newest keyframe that came while a search ran: searched next (index, small, image)
        self._join_next: tuple[int, np.ndarray, np.ndarray] | None = None
        # replay: a background solve (a keyframe's loop registrations) is applied exactly
        # lockstep_frames (loop_lockstep_frames) frames after it started, waiting for it if
        # needed, so that the map does not depend on the machine's speed
        self.lockstep_frames = lockstep_frames
        self.loop_lockstep_frames = lockstep_frames if loop_lockstep_frames is None else loop_lockstep_frames
        self._frame = 0  # the latest frame index seen by on_step
        self._started_frame = 0  # ... when the running solve started
        self._last_start = -float("inf")  # monotonic s (live)
        self._deferred = False  # the last frame left a finished solve to this one
        self._flushing = False  # the run has ended: solves move every keyframe
        self._wanted: set[int] = set()  # segments with loop edges not optimised yet
        # the latest tracked frame when it is no keyframe: (index, its keyframe, 3x3 input px of it
        # -> of its keyframe, confidence, working image); the end of the run searches it
        self._last_frame: tuple[int, int, np.ndarray, float, np.ndarray] | None = None

    def _graph(self, segment: int) -> KeyframeGraph:
        if segment not in self.graphs:
            self.graphs[segment] = KeyframeGraph(self.registrar, self.frame_size, self.working_scale,
                                                 self.store.small, self.params, self.graph_params)
        return self.graphs[segment]

    def _priors(self, sample: TelemetrySample | None) -> KeyframePriors | None:
        if sample is None or not self.use_priors:
            return None
        east_north = None
        if sample.lat is not None and sample.lon is not None:
            if self._enu_origin is None:
                self._enu_origin = (sample.lat, sample.lon)
            east, north = enu_from_latlon(np.array([sample.lat]), np.array([sample.lon]), *self._enu_origin)
            east_north = (float(east[0]), float(north[0]))
        return KeyframePriors(sample.yaw, sample.height_above_ground, east_north)

    def _keep(self, index: int, segment: int, small: np.ndarray, image: np.ndarray,
              priors: KeyframePriors | None) -> None:
        self.store.put(index, small)  # the image that re-renders the map: the painter keeps it
        self._segment_of[index] = segment
        self._places.add(index, place_signature(small), segment)
        if priors is not None and priors.east_north is not None:
            self._position[index] = priors.east_north

    def on_anchor(self, step: TrackStep, small: np.ndarray, image: np.ndarray) -> None:
        """The earlier frame ``step.anchor`` became the reference of a new segment."""
        self._keep(step.anchor, step.segment, small, image, None)
        self._graph(step.segment).add_keyframe(step.anchor, np.vstack([step.anchor_pose, [0, 0, 1]]), None)

    def on_step(self, index: int, step: TrackStep, small: np.ndarray, image: np.ndarray,
                sample: TelemetrySample | None = None) -> list[Update]:
        """Record a tracked frame; returns what changed the map: a join of its segment to
        another, and corrections of optimisations that finished.

        A finished background optimisation is returned after the frame is recorded, so that the
        frame itself is re-posed too.
        """
        self._frame = index
        if step.pose is not None and step.reference is not None:
            self.relative.setdefault(step.segment, RelativePoses()).add(index, step.reference, step.relative)
        if step.pose is not None:
            self._last_frame = None if step.keyframe or step.reference is None else \
                (index, step.reference, step.relative, step.confidence, small)
        if step.pose is None or not step.keyframe:
            self._collect_loops()
            return self._collected_join() + self._polled()
        priors = self._priors(sample)
        self._keep(index, step.segment, small, image, priors)
        graph = self._graph(step.segment)
        edge = (step.reference, step.relative, step.confidence) if step.reference is not None else None
        graph.add_keyframe(index, np.vstack([step.pose, [0, 0, 1]]), edge, priors)
        self._ground_scale(graph)
        updates: list[Update] = []
        if self._join_matcher is None:
            join = self._try_join(index, step.segment, small, image)
        else:
            join = None
            self._search_join(index, step.segment, small, image)
        if join is not None:
            updates.append(join)
            graph = self.graphs[join.into]
        segment = join.into if join is not None else step.segment
        if self._loop_executor is None:
            self._added(segment, graph.close_loops(small, self._by_appearance(index, segment, graph)))
        else:
            candidates = graph.loop_candidates()
            candidates += self._by_appearance(index, segment, graph)
            if candidates:
                self._loop_jobs.append((index, index, self._loop_executor.submit(
                    graph.measure_loops, small, candidates, self._loop_registrar, self._first.wait)))
        self._collect_loops()
        return updates + self._collected_join() + self._polled(keyframe=True)

    def _by_appearance(self, index: int, segment: int, graph: KeyframeGraph) -> list[LoopCandidate]:
        """Loop candidates of keyframe ``index`` found by its place signature among the older
        keyframes of ``segment`` (not the newest ``loop_min_gap``): the best
        ``loop_appearance_candidates`` scoring at least ``loop_appearance_min_score``. One that is
        also a nearby candidate is tried again without a prior: that prior comes from the drifted
        estimate and may exclude the true placement."""
        if not self.params.loop_appearance or index not in self._places:
            return []
        found = self._places.search(self._places.signature(index), segment, self.params.loop_appearance_candidates,
                                    set(graph.recent()))
        return graph.appearance_candidates([k for k, score in found
                                            if score >= self.params.loop_appearance_min_score])

    def _close_last_frame(self) -> None:
        """A flight often ends where it began (a drone flies home): the run's last tracked frame,
        when it is no keyframe, is searched by appearance too; a confirmed match becomes a loop
        edge of its keyframe (the match composed with the frame's measured pose relative to it)."""
        last, self._last_frame = self._last_frame, None
        if last is None or not self.params.loop_appearance:
            return
        index, ref, rel, confidence, small = last
        segment = self._segment_of.get(ref)  # (after joins)
        if segment is None or segment not in self.graphs:
            return  # its keyframe was forgotten meanwhile
        graph = self.graphs[segment]
        found = self._places.search(place_signature(small), segment, self.params.loop_appearance_candidates,
                                    set(graph.recent()) | {ref})
        refs = [k for k, score in found if score >= self.params.loop_appearance_min_score]
        candidates = [LoopCandidate(k, index, np.linalg.inv(graph.pose_of(k)) @ graph.pose_of(ref) @ rel, None, True)
                      for k in refs]
        back = np.linalg.inv(rel)  # input px of the keyframe -> of the frame
        measured = []
        for m in graph.measure_loops(small, candidates):
            c = m.candidate
            measured.append(LoopMeasurement(
                LoopCandidate(c.ref, ref, c.predicted @ back, None, True, seen_from=index),
                None if m.measured is None else m.measured @ back, min(m.confidence, confidence), m.periodic))
        self._added(segment, graph.add_loops(measured))

    def _added(self, segment: int, added: int) -> None:
        if added:
            log.info("loop closed at frame %d (segment %d): %d loop edges", self._frame, segment,
                     self.graphs[segment].loops)
            self._wanted.add(segment)

    def _collect_loops(self, wait: bool = False) -> None:
        """Add the loop edges of finished background registrations, oldest first (in lockstep:
        those started ``loop_lockstep_frames`` ago, waited for; ``wait``: all of them)."""
        while self._loop_jobs:
            index, started, future = self._loop_jobs[0]
            if not wait:
                if self.lockstep_frames is not None:
                    if self._frame - started < self.loop_lockstep_frames:
                        return
                elif not future.done():
                    return
            self._loop_jobs.popleft()
            try:
                measurements: list[LoopMeasurement] = future.result()
            except Exception as exc:  # e.g. an old keyframe's image lost: no loop edge from it
                if index in self._segment_of:
                    log.warning("loop closure of keyframe %d skipped: %s: %s", index, type(exc).__name__, exc)
                continue
            segment = self._segment_of.get(index)
            if segment is None or segment not in self.graphs:  # its segment was forgotten meanwhile
                continue
            self._added(segment, self.graphs[segment].add_loops(measurements))

    def _polled(self, keyframe: bool = False) -> list[Update]:
        """A finished solve's correction, and the correction of a solve started now (when the
        solver runs here). A keyframe's frame (the worker paints it whole) leaves a finished
        solve to the next frame, so that the two never add up in one frame (at most one frame
        later: stills are all keyframes)."""
        if keyframe and not self._deferred:
            self._deferred = True
            started = self._start()
            return [started] if started is not None else []
        self._deferred = False
        done = self.poll(frame=self._frame)
        started = self._start()
        return [c for c in (done, started) if c is not None]

    def _ground_scale(self, graph: KeyframeGraph) -> None:
        """Learn the ground metres per input pixel from the newest keyframe of ``graph`` and an
        earlier one of its chain with a GPS fix at least ``_GROUND_BASE_SIGMAS`` GPS sigmas away
        (their GPS distance over their map distance, in input pixels of the newest)."""
        kfs = graph.keyframes
        here = self._position.get(kfs[-1].index)
        if here is None or len(kfs) < 2:
            return
        pose = kfs[-1].pose
        centre = pose @ graph.centre
        base = _GROUND_BASE_SIGMAS * self.graph_params.gps_sigma_m
        for kf in kfs[-2:-_GROUND_LOOKBACK - 2:-1]:
            there = self._position.get(kf.index)
            if there is None:
                continue
            metres = float(np.hypot(here[0] - there[0], here[1] - there[1]))
            if metres < base:
                continue
            px = float(np.hypot(*(kf.pose @ graph.centre - centre)[:2])) / max(pose_scale(pose), 1e-9)
            if px > 1.0:
                self._ground_m_per_px.append(metres / px)
            return

    def _join_reach_m(self) -> float | None:
        """How far apart (metres, by GPS) two keyframes can be while their footprints may still
        overlap: the frame diagonal on the ground (:meth:`_ground_scale`, median) plus
        ``_JOIN_GPS_SIGMAS`` GPS sigmas; None while fewer than ``_GROUND_MIN_PAIRS`` pairs tell it."""
        if len(self._ground_m_per_px) < _GROUND_MIN_PAIRS:
            return None
        diagonal = float(np.hypot(*self.frame_size)) * float(np.median(self._ground_m_per_px))
        return diagonal + _JOIN_GPS_SIGMAS * self.graph_params.gps_sigma_m

    def _join_candidates(self, index: int, segment: int) -> list[int]:
        """Keyframes of the other segments to try against keyframe ``index``, best first (by GPS:
        the nearest, none whose footprint cannot reach this one's)."""
        others = [k for k, s in self._segment_of.items() if s != segment and s in self.graphs]
        if not others:
            return []
        here = self._position.get(index)
        if here is not None and all(k in self._position for k in others):
            key = {k: np.hypot(self._position[k][0] - here[0], self._position[k][1] - here[1]) for k in others}
            reach = self._join_reach_m()
            near = sorted(others, key=key.get)[:self.join_candidates]
            return [k for k in near if reach is None or key[k] <= reach]
        similar = place_similarities(self._places.signature(index),
                                     np.stack([self._places.signature(k) for k in others]))
        return [others[i] for i in np.argsort(-similar, kind="stable")[:self.join_candidates]]

    def _try_join(self, index: int, segment: int, small: np.ndarray, image: np.ndarray) -> Join | None:
        """Place keyframe ``index`` of ``segment`` against other segments' keyframes and join the
        first placement the images confirm, here and now."""
        candidates = self._join_candidates(index, segment)
        placed = self._place_join(self.matcher, small, image, candidates) if candidates else None
        return None if placed is None else self._join(index, *placed)

    def _search_join(self, index: int, segment: int, small: np.ndarray, image: np.ndarray) -> None:
        """:meth:`_try_join` in the loop thread (its result joins at a later frame:
        :meth:`_collected_join`); while an earlier keyframe's search runs, this keyframe waits
        for it (replacing one that waited: the newest is the likeliest to join)."""
        if self._join_job is not None:
            self._join_next = (index, small, image)
            return
        candidates = self._join_candidates(index, segment)
        if candidates:
            self._join_job = (index, self._loop_executor.submit(
                self._place_join, self._join_matcher, small, image, candidates, self._first.wait))

    def _collected_join(self, wait: bool = False) -> list[Join]:
        """The join found by a finished search of the loop thread (``wait``: wait for it)."""
        if self._join_job is None or not (wait or self._join_job[1].done()):
            return []
        index, future = self._join_job
        self._join_job = None
        try:
            placed = future.result()
        except Exception as exc:  # e.g. an old keyframe's image lost: no join from this keyframe
            log.warning("join search of keyframe %d skipped: %s: %s", index, type(exc).__name__, exc)
            placed = None
        join = None if placed is None else self._join(index, *placed)
        waiting, self._join_next = self._join_next, None
        if waiting is not None and waiting[0] in self._segment_of:  # (its segment, after this join)
            self._search_join(waiting[0], self._segment_of[waiting[0]], waiting[1], waiting[2])
        return [] if join is None else [join]

    def _place_join(self, matcher: PairMatcher, small: np.ndarray, image: np.ndarray, candidates: list[int],
                    pause: Callable[[], None] | None = None) -> tuple[int, np.ndarray, float] | None:
        """The first of the keyframes ``candidates`` that the new keyframe (``small``, ``image``)
        is placed against and the images confirm (the overlap check, or the features' second
        opinion): (that keyframe, 3x3 input px of the new keyframe -> of it, confidence), or
        None. Reads only the keyframe store (any thread)."""
        view = matcher.view(small, image)
        for match in candidates:
            if pause is not None:
                pause()
            ref = self._join_view(matcher, match, image.shape[:2])
            placed = matcher.match(ref, view, always_check=True)
            ref.image = None  # its features, if asked, are kept with it; the image is read again if needed
            if placed.accepted:
                return match, self._from_small @ to_h(placed.matrix) @ self._to_small, float(placed.confidence)
        return None

    def _join_view(self, matcher: PairMatcher, match: int, shape: tuple[int, int]) -> View:
        """Keyframe ``match`` as a join candidate: its spectra and features are kept (the last
        ``_JOIN_VIEWS`` candidates: a new segment's keyframes try the same few old ones again and
        again, and the features were most of a stills join search's time); its image is read
        from the store, resized to ``shape`` (h, w) of the new keyframe, only while its features
        are not known."""
        key = (match, shape)
        ref = self._join_views.pop(key, None)
        if ref is None:
            ref = matcher.view(self.store.small(match))
        self._join_views[key] = ref  # the newest last
        while len(self._join_views) > _JOIN_VIEWS:
            self._join_views.pop(next(iter(self._join_views)))
        if ref.features is None:
            old = self.store.image(match)  # as the painter kept it: maybe at the map's (lower) resolution
            if old is not None and old.shape[:2] != shape:
                # the features' placement assumes both images at one scale: the input frame's
                old = cv2.resize(old, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
            ref.image = old
            ref.image_scale = ref.prepared.gray.shape[1] / old.shape[1] if old is not None else 1.0
        return ref

    def _join(self, index: int, match: int, measured: np.ndarray, confidence: float) -> Join | None:
        """Join the segment of keyframe ``index`` to that of keyframe ``match`` (``measured``: 3x3
        input px of ``index`` -> of ``match``); None when they are one segment by now, or one of
        them was forgotten."""
        segment, into = self._segment_of.get(index), self._segment_of.get(match)
        if segment is None or into is None or segment == into or segment not in self.graphs \
                or into not in self.graphs:
            return None
        old = self.graphs[into].pose_of(match)
        new = self.graphs[segment].pose_of(index)
        transform = old @ measured @ np.linalg.inv(new)
        self.graphs[into].absorb(self.graphs.pop(segment), transform, (match, index, measured, confidence))
        self.relative.setdefault(into, RelativePoses()).update(self.relative.pop(segment, RelativePoses()))
        for k, s in self._segment_of.items():
            if s == segment:
                self._segment_of[k] = into
        self._places.regroup(segment, into)
        self._wanted = {into if s == segment else s for s in self._wanted}
        self._merged_into[segment] = into
        join = Join(segment, into, transform, index, match, confidence)
        self.joins.append(join)
        log.info("segment %d joined segment %d: keyframe %d matches keyframe %d (confidence %.2f)",
                 segment, into, index, match, confidence)
        return join

    def _start(self, now: bool = False) -> Correction | None:
        """Optimise a segment that needs it: in the background (None), or here and now. Live, a
        background solve starts at most every ``SOLVE_INTERVAL_S`` (``now``: whenever)."""
        if self._running is not None or not self._wanted:
            return None
        if self._executor is not None and self.lockstep_frames is None and not now:
            if time.monotonic() - self._last_start < SOLVE_INTERVAL_S:
                return None
            self._last_start = time.monotonic()
        segment = min(self._wanted)
        self._wanted.discard(segment)
        graph = self.graphs[segment]
        newest = None if self._flushing else self.graph_params.max_solve_nodes  # the last solve: all
        if self._executor is None:
            return self._finish(segment, *KeyframeGraph.solve(graph.snapshot(), self.graph_params,
                                                              newest=newest))
        self._running = (segment, self._executor.submit(KeyframeGraph.solve, graph.snapshot(),
                                                        self.graph_params, self._first.wait, newest))
        self._started_frame = self._frame
        return None

    def poll(self, wait: bool = False, frame: int | None = None) -> Correction | None:
        """The correction of a finished background optimisation, if any (``wait``: block for it).

        In lockstep (replay) only a call for ``frame`` ``lockstep_frames`` after the solve
        started returns it (waiting if needed); other calls return None."""
        if self._running is None:
            return None
        if self.lockstep_frames is not None and not wait:
            if frame is None or frame - self._started_frame < self.lockstep_frames:
                return None
            wait = True
        if not (wait or self._running[1].done()):
            return None
        segment, future = self._running
        self._running = None
        correction = self._finish(segment, *future.result())
        self._start()
        return correction

    def _finish(self, segment: int, poses: np.ndarray, dropped: list[int]) -> Correction | None:
        if segment not in self.graphs:  # joined into another segment while it was optimised
            while segment in self._merged_into:
                segment = self._merged_into[segment]
            if segment in self.graphs:  # else it was forgotten
                self._wanted.add(segment)
            return None
        if dropped:
            log.warning("dropped %d loop closure(s) that disagree with the rest of the map", len(dropped))
        graph = self.graphs[segment]
        fixes = graph.apply(poses, dropped)
        self.corrections += 1
        indices = np.array([kf.index for kf in graph.keyframes], np.int64)
        keyframe_poses = np.array([kf.pose for kf in graph.keyframes])
        frames, frame_poses = (self.relative[segment].poses(indices, keyframe_poses) if segment in self.relative
                               else (np.zeros(0, np.int64), np.zeros((0, 3, 3))))
        table = PoseTable(np.concatenate([indices, frames]), np.concatenate([keyframe_poses, frame_poses]))
        latest = graph.keyframes[-1]
        return Correction(segment, table, fixes[latest.index],
                          tuple((kf.index, kf.pose.copy()) for kf in graph.keyframes))

    def forget(self, segment: int) -> None:
        """Drop ``segment`` (the pipeline found nothing worth keeping in it): its graph, its
        frames' relative poses and its keyframes (also on disk) are gone; no join can reach it."""
        self.graphs.pop(segment, None)
        self.relative.pop(segment, None)
        self._wanted.discard(segment)
        for k in [k for k, s in self._segment_of.items() if s == segment]:
            del self._segment_of[k]
            self._places.remove(k)
            self._position.pop(k, None)
            for key in [key for key in list(self._join_views) if key[0] == k]:
                self._join_views.pop(key, None)
            self.store.discard(k)

    def flush(self) -> list[Update]:
        """Finish every pending join search and optimisation (at the end of the run); returns the
        join and the corrections. The solves started here move every keyframe (while mapping,
        at most ``max_solve_nodes``, the newest), once more for a graph that is larger.

        With ``settle_on_priors``, segments whose keyframes carry telemetry priors (GPS, heading,
        altitude) are optimised once more with them, loop closed or not, so that a weak chain
        (stills) agrees with the GPS track and the altitude.
        """
        out: list[Update] = []
        while self._join_job is not None:
            out.extend(self._collected_join(wait=True))
        if self.settle_on_priors:
            self._wanted |= {s for s, g in self.graphs.items() if len(g.keyframes) >= 2 and g.graph.has_priors}
        self._collect_loops(wait=True)
        self._close_last_frame()
        # solves while mapping moved only the newest keyframes of a long graph: once more, all
        newest = self.graph_params.max_solve_nodes
        self._wanted |= {s for s, g in self.graphs.items() if newest is not None and g.loops
                         and g.graph.num_nodes > newest}
        self._flushing = True
        while self._running is not None or self._wanted:
            correction = self.poll(wait=True) if self._running is not None else self._start(now=True)
            if correction is not None:
                out.append(correction)
        for executor in (self._executor, self._loop_executor):
            if executor is not None:
                executor.shutdown(wait=True)
        return out

    def summary(self) -> dict:
        return {"keyframes": sum(len(g.keyframes) for g in self.graphs.values()),
                "joins": len(self.joins),
                "loop_edges": sum(g.loops for g in self.graphs.values()),
                "rejected_loops": sum(g.rejected_loops for g in self.graphs.values()),
                "corrections": self.corrections}
