"""The raw 16-bit frames of a live deep source (a Y16 camera), kept for ``map_raw.tif``.

A source that delivers raw deep frames (:class:`~photomap.drivers.camera.CameraSource` in Y16)
is stretched to 8 bits where the frames enter the pipeline; nothing of a frame is left at the end
of the run, when ``map_raw.tif`` is painted with the final poses
(:func:`photomap.mapping.band_maps.write_raw_map`). :class:`RawFrameKeeper` keeps enough of them
on disk for that: a posed frame whose centre has moved ``spacing`` of the frame's shorter side
from the last one kept (or turned ``turn_deg``, or started a segment) is written as it is
(``.npy``: 5 ms for a 640 x 512 frame, where a 16-bit PNG took 55 ms of the worker's time) into a
temporary folder in the output folder; the newest frame not
kept waits in memory (one frame) and is written at :meth:`finish`, so the map's far end is
covered too. Kept frames overlap by ``1 - spacing`` (90 % by default): their union is the map's
footprint to about 1 % (on a simulated 60-frame flight, 0.2 % of the map either way; the live map
paints only new ground between its keyframes), at one frame in a few of a video's (a 640 x 512 Y16
frame is 0.66 MB on disk). The folder is removed by :meth:`close` (one a run that stopped left, by
the next run's first kept frame). They never take more than ``MAX_BYTES`` of disk (2 GiB: past it, no
more are kept, one line says so, and ``map_raw.tif`` covers the flight up to there).

Used by the worker thread only. Poses are 2x3, input-frame pixels -> map pixels.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from pathlib import Path

import numpy as np

from photomap.geometry import pose_angle_deg, pose_scale

log = logging.getLogger(__name__)

#: A frame is kept when its centre moved this share of the frame's shorter side from the last kept.
SPACING = 0.1
#: ... or when it turned this many degrees from it.
TURN_DEG = 15.0
#: Disk the kept frames may take (bytes): beyond it no more are kept (one line), so that they can
#: never fill the disk the map's own checkpoints need (a 640 x 512 Y16 frame: 0.66 MB).
MAX_BYTES = 2 << 30


class RawFrameKeeper:
    """Raw uint16 frames kept on disk (module docstring); :meth:`read` is ``write_raw_map``'s
    ``raw_frame``. A write that fails stops the keeping (one line): no ``map_raw.tif`` then."""

    def __init__(self, out_dir: Path, *, spacing: float = SPACING, turn_deg: float = TURN_DEG,
                 max_bytes: int = MAX_BYTES) -> None:
        self._parent = Path(out_dir)
        self.spacing, self.turn_deg = float(spacing), float(turn_deg)
        self.max_bytes, self.bytes = int(max_bytes), 0
        self.folder: Path | None = None
        self.kept: set[int] = set()
        self.failed = False
        self.full = False  # max_bytes reached: no more kept, the kept ones serve
        self._last: tuple[int, np.ndarray] | None = None  # segment, pose of the last kept frame
        self._pending: tuple[int, np.ndarray, int, np.ndarray] | None = None  # newest not kept

    def offer(self, index: int, image: np.ndarray, pose: np.ndarray | None, segment: int) -> None:
        """A frame's raw pixels (uint16) and its live pose (None: not posed, not kept)."""
        if self.failed or self.full or pose is None or image.dtype != np.uint16:
            return
        pose = np.asarray(pose, float)[:2]
        if self._due(image.shape[:2], pose, segment):
            self._write(index, image, pose, segment)
            self._pending = None
        else:  # a copy: a driver may fill the next frame into the same buffer
            self._pending = (index, image.copy(), segment, pose)

    def _due(self, shape: tuple[int, int], pose: np.ndarray, segment: int) -> bool:
        if self._last is None or self._last[0] != segment:
            return True
        h, w = shape
        centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
        last = self._last[1]
        moved = float(np.hypot(*(pose @ centre - last @ centre))) / max(pose_scale(pose), 1e-12)
        turned = abs((pose_angle_deg(pose) - pose_angle_deg(last) + 180.0) % 360.0 - 180.0)
        return moved >= self.spacing * min(w, h) or turned >= self.turn_deg

    def _write(self, index: int, image: np.ndarray, pose: np.ndarray, segment: int) -> None:
        if self.bytes + image.nbytes > self.max_bytes:
            self.full = True  # what is kept stays: map_raw.tif covers the flight up to here
            log.warning("raw frames: %.0f MB kept on disk, no more (map_raw.tif covers the frames up to %d)",
                        self.bytes / 1e6, max(self.kept, default=index))
            return
        try:
            if self.folder is None:
                for stale in self._parent.glob(".raw_frames.*"):  # left by a run that stopped
                    shutil.rmtree(stale, ignore_errors=True)
                self.folder = Path(tempfile.mkdtemp(prefix=".raw_frames.", dir=self._parent))
            np.save(self._path(index), np.ascontiguousarray(image), allow_pickle=False)
        except OSError as exc:
            self.failed = True
            log.warning("raw frames not kept (no map_raw.tif): %s", exc)
            return
        self.kept.add(index)
        self.bytes += image.nbytes
        self._last = (segment, pose)

    def _path(self, index: int) -> Path:
        return self.folder / f"{index:08d}.npy"  # type: ignore[operator]

    def finish(self) -> None:
        """Write the newest frame not kept (the end of the flight)."""
        if self._pending is not None and not (self.failed or self.full):
            index, image, segment, pose = self._pending
            self._write(index, image, pose, segment)
        self._pending = None

    def read(self, index: int) -> np.ndarray | None:
        """Frame ``index``'s raw pixels when it was kept, else None."""
        if index not in self.kept or self.failed:
            return None
        try:
            image = np.load(self._path(index), allow_pickle=False)
        except (OSError, ValueError):
            return None
        return image if image.dtype == np.uint16 else None

    def close(self) -> None:
        """Remove the kept frames."""
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)
            self.folder = None
        self.kept.clear()

