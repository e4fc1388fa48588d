"""What the mapping worker tells its sinks (viewer, progress bar, STATUSTEXT) after each frame.

The pipeline owns its state (trajectory, maps, tracker); sinks get an immutable
:class:`FrameEvent` instead of the pipeline itself. Sinks run in the worker thread: they must be
quick, must not raise, and copy what they keep (the frame image and the map tiles are read-only
views that change after the call; ``corrected_path`` is computed when first read, during the call).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from photomap.geo.georef import Georeference
from photomap.telemetry.samples import TelemetrySample

TileKey = tuple[int, int]


class TileReader(Protocol):
    """Read access to one segment's map tiles (a :class:`photomap.core.mosaic.TiledMosaic`)."""

    tile_size: int

    def tiles(self) -> list[TileKey]:
        """Keys of the tiles the map holds."""

    def tile_origin(self, key: TileKey) -> tuple[int, int]:
        """Map pixel of the tile's top-left pixel."""

    def tile_image(self, key: TileKey, copy: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """The tile's colour (BGR or grey) and alpha (uint8), copies unless ``copy`` is False
        (views to read at once, in the worker); KeyError when there is no such tile."""


@dataclass(frozen=True)
class FrameEvent:
    """One frame, mapped (or not).

    Poses are 2x3 (pixels of the view the map got -> map pixels of ``segment``: the input
    frame's own unless ``view_points`` says otherwise); ``t`` is the frame time (live:
    host monotonic seconds at capture, ``live`` True; replay: seconds from the first frame).
    """

    index: int
    t: float
    live: bool
    image: np.ndarray  # the input frame (read-only)
    frame_size: tuple[int, int]  # (w, h)
    status: str  # reference | registered | low_confidence | corrupt
    pose: np.ndarray | None
    confidence: float
    segment: int
    keyframe: bool = False
    new_segment: bool = False
    # an earlier frame was posed now (it anchors a new segment): (frame index, 2x3 pose)
    anchor: tuple[int, np.ndarray] | None = None
    # what an operator should read: segment started, telemetry disagreed, loop closed ...
    messages: tuple[str, ...] = ()
    touched: frozenset[TileKey] = frozenset()  # map tiles of ``segment`` changed by this frame
    tiles: TileReader | None = None  # the segment's map, for reading the touched tiles
    register_ms: float = 0.0
    frame_ms: float = 0.0
    dropped_frames: int = 0  # cumulative, by the capture
    reconnects: int = 0  # cumulative, camera
    telemetry: TelemetrySample | None = None
    focal_px: float | None = None  # the camera's focal length at the input resolution, when known
    link_lost: int = 0  # cumulative telemetry link losses / regains
    link_regained: int = 0
    # after a pose-graph correction of ``segment``: what computes its whole path again (see
    # corrected_path); None otherwise
    path_after_correction: Callable[[], np.ndarray] | None = None
    # input frame pixels (n, 2) -> the pixels ``pose`` maps (the frame undistorted by the lens
    # model and rectified by the telemetry, as the map got it); None: the input frame's own
    view_points: Callable[[np.ndarray], np.ndarray] | None = None

    @property
    def corrected_path(self) -> np.ndarray | None:
        """After a pose-graph correction of ``segment``: its whole path again, (n, 3) x, y,
        confidence of each posed frame's centre in frame order (computed when first read: a
        pass over the flight's frames that only a sink which shows the path pays for). None,
        at once, for the frames without a correction (a cached property takes a lock on each
        read in Python 3.11, and the live map and the viewer read this every frame)."""
        return None if self.path_after_correction is None else self._corrected_path

    @functools.cached_property
    def _corrected_path(self) -> np.ndarray:
        return self.path_after_correction()


FrameSink = Callable[[FrameEvent], None]

GeoreferenceSink = Callable[[int, Georeference], None]
"""Told the main map's georeference ``(segment, fit)``: each live GPS fit (from the writer thread,
at the checkpoints) and the final one (``finish``). Must be quick and must not raise."""
