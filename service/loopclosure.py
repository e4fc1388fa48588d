"""Loop closure in the running pipeline: keyframe images on disk, graphs per segment, re-rendering.

The pipeline hands every tracked frame to :class:`LoopCloser`. Keyframes are kept on disk (their
working-resolution grey image for registration, and a JPEG of the input frame for re-rendering
the map), so memory stays bounded over a long flight. When a new keyframe closes a loop, the
segment's pose graph is optimised (:mod:`service.mapgraph`), every posed frame of the segment is
re-posed through its keyframe (a frame keeps its measured pose relative to the keyframe it was
registered against), the tracker continues from the corrected pose, and the segment's map is
marked for re-rendering from its keyframes (done at checkpoints and at the end of the run).
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from .mapgraph import KeyframeGraph
from .mosaic import TiledMosaic
from .tracking import TrackStep, Tracker
from .trajectory import PoseRow

log = logging.getLogger(__name__)


class LoopCloser:
    """Keyframe graphs of all segments of a run (used from the worker thread only)."""

    def __init__(self, folder: Path, tracker: Tracker, frame_size: tuple[int, int],
                 working_scale: float, cfg: dict) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.tracker = tracker
        self.frame_size = frame_size
        self.working_scale = working_scale
        self.cfg = cfg
        self.graphs: dict[int, KeyframeGraph] = {}
        self.relative: dict[int, tuple[int, np.ndarray]] = {}  # frame -> (keyframe, 3x3 measured)
        self.dirty: set[int] = set()  # segments whose map must be re-rendered
        self.corrections = 0

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
                rows: list[PoseRow]) -> bool:
        """Record a tracked frame; returns True when a loop closure corrected the segment."""
        if step.pose is None:
            return False
        if step.reference is not None:
            self.relative[index] = (step.reference, step.relative)
        if not step.keyframe:
            return False
        self._store(index, small, image)
        graph = self._graph(step.segment)
        edge = None
        if step.reference is not None:
            edge = (step.reference, step.relative, step.confidence)
        graph.add_keyframe(index, np.vstack([step.pose, [0, 0, 1]]), edge)
        if not graph.close_loops(small):
            return False
        fixes = graph.optimize()
        self._apply(step.segment, fixes, rows)
        self.corrections += 1
        self.dirty.add(step.segment)
        log.info("loop closed at frame %d (segment %d): %d loop edges, map corrected",
                 index, step.segment, graph.loops)
        return True

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
