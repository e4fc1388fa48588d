"""Loop closure in the running pipeline: keyframe images on disk, graphs per segment, re-rendering.

The pipeline hands every tracked frame to :class:`LoopCloser`. Keyframes are kept on disk (their
working-resolution grey image for registration, and a JPEG of the input frame for re-rendering
the map), so memory stays bounded over a long flight. When a new keyframe closes a loop, the
segment's pose graph is optimised (:mod:`photomap.core.keyframes`), every posed frame of the segment is
re-posed through its keyframe (a frame keeps its measured pose relative to the keyframe it was
registered against), the tracker continues from the corrected pose, and the segment's map is
marked for re-rendering from its keyframes (done at checkpoints and at the end of the run).
The optimisation runs on a snapshot of the graph in a background thread (one at a time), so the
worker never waits for it; its result is applied at the next frame.
"""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from photomap.core.keyframes import KeyframeGraph
from photomap.core.mosaic import TiledMosaic
from photomap.core.tracking import TrackStep, Tracker
from photomap.eval.metrics import PoseRow

log = logging.getLogger(__name__)


class LoopCloser:
    """Keyframe graphs of all segments of a run (used from the worker thread; the optimiser runs
    on snapshots in its own thread)."""

    def __init__(self, folder: Path, tracker: Tracker, frame_size: tuple[int, int],
                 working_scale: float, cfg: dict, priors: dict | None = None) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.tracker = tracker
        self.frame_size = frame_size
        self.working_scale = working_scale
        self.cfg = cfg
        self.priors = priors  # the posegraph config: telemetry prior sigmas (None: no priors)
        self.graphs: dict[int, KeyframeGraph] = {}
        self.relative: dict[int, tuple[int, np.ndarray]] = {}  # frame -> (keyframe, 3x3 measured)
        self.dirty: set[int] = set()  # segments whose map must be re-rendered
        self.corrections = 0
        # optimisation in a background thread: one at a time, on a snapshot of the graph
        self._executor = ThreadPoolExecutor(1, "photomap-posegraph") if cfg["optimize_in_background"] else None
        self._running: tuple[int, Future] | None = None  # (segment, solve of its snapshot)
        self._wanted: set[int] = set()  # segments with loop edges not optimised yet

    def _graph(self, segment: int) -> KeyframeGraph:
        if segment not in self.graphs:
            c = self.cfg
            self.graphs[segment] = KeyframeGraph(
                self.tracker.registrar, self.frame_size, self.working_scale, self._load_small,
                min_gap=c["loop_min_gap"], radius=c["loop_radius"],
                min_confidence=c["loop_min_confidence"], max_candidates=c["loop_candidates"])
        return self.graphs[segment]

    def _path(self, index: int, kind: str) -> Path:
        return self.folder / f"kf{index:07d}.{kind}"

    def _load_small(self, index: int) -> np.ndarray:
        img = cv2.imread(str(self._path(index, "png")), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FileNotFoundError(self._path(index, "png"))
        return img

    def _store(self, index: int, small: np.ndarray, image: np.ndarray) -> None:
        gray = small if small.ndim == 2 else cv2.cvtColor(small, cv2.COLOR_BGR2GRAY)
        cv2.imwrite(str(self._path(index, "png")), gray)
        cv2.imwrite(str(self._path(index, "jpg")), image, [cv2.IMWRITE_JPEG_QUALITY, 92])

    def on_anchor(self, step: TrackStep, small: np.ndarray | None, image: np.ndarray | None) -> None:
        """The earlier frame ``step.anchor`` became the reference of a new segment."""
        if small is not None and image is not None:
            self._store(step.anchor, small, image)
            self._graph(step.segment).add_keyframe(step.anchor, np.vstack([step.anchor_pose, [0, 0, 1]]), None)

    def on_step(self, index: int, step: TrackStep, small: np.ndarray, image: np.ndarray,
                rows: list[PoseRow], sample: Any = None) -> bool:
        """Record a tracked frame (its row already in ``rows``); True when a correction was applied.

        A finished background optimisation is applied after the frame is recorded, so that the
        frame itself is corrected too.
        """
        if step.pose is None:
            return self._collect(rows, wait=False)
        if step.reference is not None:
            self.relative[index] = (step.reference, step.relative)
        if not step.keyframe:
            return self._collect(rows, wait=False)
        self._store(index, small, image)
        graph = self._graph(step.segment)
        edge = None
        if step.reference is not None:
            edge = (step.reference, step.relative, step.confidence)
        graph.add_keyframe(index, np.vstack([step.pose, [0, 0, 1]]), edge, sample, self.priors)
        if graph.close_loops(small):
            log.info("loop closed at frame %d (segment %d): %d loop edges", index, step.segment, graph.loops)
            self._wanted.add(step.segment)
        corrected = self._collect(rows, wait=False)
        return self._start(rows) or corrected

    def _start(self, rows: list[PoseRow]) -> bool:
        """Optimise a segment that needs it: in the background, or here and now."""
        if self._running is not None or not self._wanted:
            return False
        segment = min(self._wanted)
        self._wanted.discard(segment)
        graph = self.graphs[segment]
        if self._executor is None:
            self._finish(segment, graph.optimize(), rows)
            return True
        self._running = (segment, self._executor.submit(KeyframeGraph.solve, graph.snapshot()))
        return False

    def _collect(self, rows: list[PoseRow], wait: bool) -> bool:
        """Apply a finished background optimisation (``wait``: block until it finishes)."""
        if self._running is None or not (wait or self._running[1].done()):
            return False
        segment, future = self._running
        self._running = None
        self._finish(segment, self.graphs[segment].apply(*future.result()), rows)
        self._start(rows)
        return True

    def _finish(self, segment: int, fixes: dict[int, np.ndarray], rows: list[PoseRow]) -> None:
        self._apply(segment, fixes, rows)
        self.corrections += 1
        self.dirty.add(segment)

    def collect(self, rows: list[PoseRow]) -> bool:
        """Apply a background optimisation if it has finished (never waits)."""
        return self._collect(rows, wait=False)

    def flush(self, rows: list[PoseRow]) -> None:
        """Finish every pending optimisation (at the end of the run)."""
        while self._running is not None or self._wanted:
            if not self._collect(rows, wait=True):
                self._start(rows)
        if self._executor is not None:
            self._executor.shutdown(wait=True)

    def _apply(self, segment: int, fixes: dict[int, np.ndarray], rows: list[PoseRow]) -> None:
        poses = {kf.index: kf.pose for kf in self.graphs[segment].keyframes}
        for row in rows:
            if row.M is None or row.segment != segment:
                continue
            if row.frame in poses:
                new = poses[row.frame]
            elif row.frame in self.relative and self.relative[row.frame][0] in poses:
                ref, rel = self.relative[row.frame]
                new = poses[ref] @ rel
            else:
                continue
            row.M = new[:2].copy()
        if segment == self.tracker.segment:  # the tracker goes on from the corrected pose
            latest = self.graphs[segment].keyframes[-1]
            self.tracker.correct(fixes[latest.index])

    def rerender(self, segment: int, mosaic: TiledMosaic) -> set:
        """Re-render a corrected segment's map from its keyframes; returns the tiles now in it."""
        mosaic.reset()
        for kf in self.graphs[segment].keyframes:
            image = cv2.imread(str(self._path(kf.index, "jpg")), cv2.IMREAD_COLOR)
            if image is not None:
                mosaic.add(image, kf.pose[:2])
        self.dirty.discard(segment)
        return set(mosaic.tiles())

    def summary(self) -> dict:
        return {"keyframes": sum(len(g.keyframes) for g in self.graphs.values()),
                "loop_edges": sum(g.loops for g in self.graphs.values()),
                "rejected_loops": sum(g.rejected_loops for g in self.graphs.values()),
                "corrections": self.corrections}
