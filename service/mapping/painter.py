"""Painting frames into the map: only what changes it, at the map's resolution.

Most frames of a video add no ground to the map: at 30 fps a frame overlaps the previous one by
95 % or more. Warping every full-resolution frame into the map (53 ms per 1080p frame, the largest
cost of the worker) is mostly wasted. The :class:`Painter` paints

- *whole*: keyframes, the first frame of a map segment, an anchor (the newest frame is on top
  there, as the ``overwrite`` blend promises: revisited ground shows its latest view), and the
  last frame of a segment when it ends;
- *new ground only*: another frame, once it has moved ``min_move_px`` map pixels from the last
  one painted, paints the map pixels under it that no frame covers yet, in ``block`` x ``block``
  squares (:meth:`TiledMosaic.uncovered`): the map grows with the camera (at most
  ``min_move_px`` behind) at the cost of a strip every few frames; a frame over mapped ground
  paints nothing;
- or, with ``whole_frames``, every frame whole (the behaviour before: for comparisons).

A whole paint is spread over the frames that follow it (``band_px``; the ``overwrite`` blend):
its footprint in horizontal bands of tile height, the first at once (the end ahead of the
camera) with the frame's new ground outside it (a sideways move's, or what spills over a band's
edge: no ground the frame maps is left empty until its band comes), and one more each time the
segment is painted (the rest at once before the next whole paint, or when the segment ends; a
segment's first frame at once).
The frames in between look for new ground as before: where they find it under the keyframe,
its band paints over it later, so the keyframe ends on top as if painted at once (to the warp's
rounding), and no frame pays a whole keyframe's warp (16 ms for a 1080p frame on one
core, 50-150 ms on a busy computer: the worker's largest stalls on a long flight).

A frame whose pixels are much finer than the map's (``mapping.map_px``, ``map_scale`` < 1) is
first downscaled to the map's resolution (``INTER_AREA``: no aliasing, and fewer pixels to warp).

With loop closure, the frames painted whole are *kept* (their image at the map's resolution goes
to the :class:`~photomap.mapping.rerender.Rerenderer`'s store) so that a pose-graph correction
re-renders the tiles whose frames moved, in the background: the worker only swaps finished tiles
in (:meth:`Painter.pump`). A tile the worker painted since a re-render job started keeps its
live pixels and is re-rendered again later (the drone has moved on by then).

Used by the worker thread only (:mod:`photomap.mapping.segments` owns the maps); the rerenderer's thread never touches
a live map. Poses are 2x3 or 3x3, input-frame pixels -> map pixels (OpenCV pixel centres).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from photomap.core.mosaic import TiledMosaic, TileKey
from photomap.errors import PhotomapError
from photomap.geometry import pose_scale, to_h
from photomap.mapping.overview import Overview
from photomap.mapping.rerender import KeptFrame, Rerenderer, reach

log = logging.getLogger(__name__)

_LOCKSTEP_SWAPS = 8  # tiles swapped in per frame in lockstep (a count, not a time: deterministic)


def resize_factors(size: tuple[int, int], pose: np.ndarray, *, below: float = 0.75
                   ) -> tuple[tuple[int, int], np.ndarray] | None:
    """The frame size at the map's resolution and the 3x3 matrix input pixels -> those pixels
    (``cv2.resize`` convention), or None when the map is not coarser than ``below`` times the
    frame (then warping the frame itself is as good)."""
    s = pose_scale(pose)
    if s >= below:
        return None
    w, h = size
    dw, dh = max(1, int(round(w * s))), max(1, int(round(h * s)))
    fx, fy = dw / w, dh / h
    return (dw, dh), np.array([[fx, 0.0, fx / 2 - 0.5], [0.0, fy, fy / 2 - 0.5], [0.0, 0.0, 1.0]])


def valid_outline(mask: np.ndarray, step: int = 4) -> np.ndarray:
    """Convex outline (n, 2 frame pixels) of where ``mask`` is valid, a ``step`` inside its edge
    (looked at on every ``step``-th pixel: cheap)."""
    small = np.ascontiguousarray(np.asarray(mask)[step // 2::step, step // 2::step] != 0).view(np.uint8)
    small = cv2.erode(small, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    points = cv2.findNonZero(small)
    if points is None:
        return np.zeros((0, 2))
    return cv2.convexHull(points).reshape(-1, 2) * float(step) + step // 2


@dataclass
class PaintStats:
    """What the painter did (``run.json`` ``painting``)."""

    whole: int = 0  # frames painted whole
    bands: int = 0  # bands of whole paints painted with later frames
    new_ground: int = 0  # frames that painted their new ground
    nothing_new: int = 0  # frames looked at that added no ground (nothing warped)
    small_move: int = 0  # frames too close to the last painted one to be looked at
    kept: int = 0  # frames kept for re-rendering
    rerender_jobs: int = 0
    rerendered_tiles: int = 0  # tiles swapped in from re-renders
    deferred_tiles: int = 0  # painted live during a re-render: re-rendered again later
    rerender_s: float = 0.0  # background thread time
    max_swap_ms: float = 0.0  # the longest swap in the worker
    max_wait_ms: float = 0.0  # the worker's longest wait for the re-render thread (lockstep: replays)
    moved_frames: int = 0  # kept frames moved by corrections
    lost_frames: int = 0  # kept images that could not be read back
    sync_writes: int = 0
    skipped_previews: int = 0  # checkpoint previews left to the next one (the background thread was behind)

    def summary(self) -> dict:
        return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


@dataclass
class _Kept:
    """A frame kept for re-rendering."""

    index: int
    pose: np.ndarray  # 3x3 input px -> map px (corrected as corrections come)
    to_kept: np.ndarray  # 3x3 input px -> px of the kept image (at the map's resolution)
    size: tuple[int, int]  # (w, h) of the kept image
    gain: np.ndarray | None = None  # the exposure gain it was painted with (None: none)
    full: bool = False  # kept without a mask (valid everywhere)

    def frame(self) -> KeptFrame:
        return KeptFrame(self.index, self.pose @ np.linalg.inv(self.to_kept), self.size, self.gain, self.full)


@dataclass
class _Tail:
    """The last posed frame of a segment (its image is dropped once it is kept)."""

    index: int
    image: np.ndarray | None
    pose: np.ndarray  # 3x3
    mask: np.ndarray | None
    kept: bool


@dataclass
class _Segment:
    """The painter's view of one map segment."""

    kept: list[_Kept] = field(default_factory=list)  # in painting order
    dirty: set[TileKey] = field(default_factory=set)  # tiles to re-render
    painted: dict[TileKey, int] = field(default_factory=dict)  # tile -> paint number of its last live paint
    job: tuple[int, int] | None = None  # (job id, paint number at submission) of the running job
    tail: _Tail | None = None  # the last posed frame
    last_painted: np.ndarray | None = None  # 3x3 pose of the last frame painted or looked at
    overview: Overview | None = None  # thumbnails for previews
    bands: _Bands | None = None  # what is left to paint of the last whole paint


@dataclass
class _Bands:
    """The rest of a whole paint (see ``Painter.band_px``)."""

    image: np.ndarray  # the frame at the map's resolution
    pose: np.ndarray  # 3x3, image px -> map px
    mask: np.ndarray | None
    gain: np.ndarray | None  # the exposure gain (None: fitted by the first band)
    rects: deque  # map rectangles (x, y, w, h) still to paint


class Painter:
    """Paints frames into the maps of a run's segments (see the module docstring).

    Parameters
    ----------
    frame_size : (w, h)
        Input frame size.
    tile_size : int
        The maps' tile size, map pixels.
    whole_frames : bool
        Paint every frame whole (no new-ground painting).
    rerenderer : Rerenderer or None
        The background thread: keeps the frames painted whole, re-renders after corrections,
        encodes previews (None: all in the caller's thread, nothing kept).
    keep : bool
        Keep the frames painted whole for re-rendering (loop closure is on; needs a rerenderer
        with a store).
    block : int
        New-ground granularity, map pixels (a divisor of the tile size).
    min_move_px : float
        A frame is looked at for new ground once a corner of it has moved this far (map
        pixels) from the last frame painted or looked at: the map lags the camera by at most this
        much, and the cost of a new-ground paint is shared by the frames in between.
    move_px : float
        A kept frame whose corners move by more than this (map pixels) in a correction has its
        tiles re-rendered.
    interval_s : float
        At least this long between two re-render jobs of a segment (a tile painted live during a
        job is re-rendered again; this bounds the background work while the drone is still there).
    swap_budget_s : float
        Time the worker spends swapping re-rendered tiles in per call of :meth:`pump` (with a
        tile cap a swapped tile may be a file write); the rest waits for the next frame.
    thumb_budget_s : float
        ... and refreshing the preview thumbnails of changed tiles once the camera has left them
        (30 paints ago, while they are still in memory), so that a checkpoint's preview has
        little left to do.
    band_px : int
        Spread each whole paint over the following paints in bands of this height (map
        pixels; see the module docstring); 0: paint it at once.
    lockstep_frames : int or None
        Replay of a file (None: live): the same input gives the same map, whatever the machine's
        load. Time is counted in frames (``pump(frame=)``) instead of seconds: a job starts at
        most every ``lockstep_frames`` frames, and its tiles are swapped in from
        ``lockstep_frames`` frames after it started (waiting for it if the thread is behind),
        a fixed number per frame; a call without a frame swaps nothing.
    final_scratch_bytes : int
        After the last frame (:meth:`finish`, no live painting to swap around), re-render
        strips together in scratch tiles of this many bytes (``Rerenderer.submit``): each kept
        image is read once for them all (a 2400x1800 survey's final correction read each ~3
        times, one strip after the other).
    """

    def __init__(self, frame_size: tuple[int, int], tile_size: int, *, whole_frames: bool = False,
                 rerenderer: Rerenderer | None = None, keep: bool = True, block: int = 32, min_move_px: float = 32.0,
                 move_px: float = 0.5, interval_s: float = 1.0, swap_budget_s: float = 0.005,
                 thumb_budget_s: float = 0.002, band_px: int = 0, lockstep_frames: int | None = None,
                 final_scratch_bytes: int = 64 << 20) -> None:
        self.frame_size = frame_size
        self.tile_size = tile_size
        self.whole_frames = whole_frames
        self.rerenderer = rerenderer
        self.keep = keep and rerenderer is not None and rerenderer.store is not None
        self.block = block
        self.min_move_px = min_move_px
        self.move_px = move_px
        self.interval_s = interval_s
        self.swap_budget_s = swap_budget_s
        self.thumb_budget_s = thumb_budget_s
        self.band_px = int(band_px)
        self._swaps: deque = deque()  # (segment, job, tile key, tile arrays) waiting to be swapped in
        self.stats = PaintStats()
        self._segments: dict[int, _Segment] = {}
        self._paints = 0  # paint number
        self._last_job = -float("inf")
        self.lockstep_frames = lockstep_frames
        self.final_scratch_bytes = final_scratch_bytes
        self._finishing = False  # in finish(): no live painting any more
        w, h = frame_size
        self._corners = np.array([[0, w - 1, w - 1, 0], [0, 0, h - 1, h - 1], [1.0, 1.0, 1.0, 1.0]])

    def _seg(self, segment: int) -> _Segment:
        seg = self._segments.get(segment)
        if seg is None:
            seg = self._segments[segment] = _Segment(overview=Overview(self.tile_size))
        return seg

    # ------------------------------------------------------------------ live painting
    def paint(self, mosaic: TiledMosaic, segment: int, index: int, image: np.ndarray, pose: np.ndarray,
              mask: np.ndarray | None = None, *, whole: bool = False, as_read: bool = False) -> set[TileKey]:
        """Paint frame ``index`` at ``pose`` into ``mosaic`` (the map of ``segment``): whole, or
        its new ground only (``whole_frames``: whole anyway), after the next band of the last
        whole paint (``band_px``). A frame painted ``whole`` is kept for re-rendering (a
        keyframe): by reference when ``as_read`` (``image`` is the input's frame as its source
        reads it again, :meth:`~photomap.io.keyframestore.KeyframeStore.put_source`) and it is
        painted as it is (no resize, no mask). Returns the tiles it changed."""
        pose = to_h(np.asarray(pose, float))
        mosaic.prefetch(pose[:2], self.frame_size)  # the tiles the next frames will paint, read ahead
        seg = self._seg(segment)
        touched = self._bands(mosaic, seg, every=whole)  # a whole paint goes on top of the last one
        keyframe = whole
        whole = whole or self.whole_frames
        clip = None
        if not whole:
            seg.tail = _Tail(index, image, pose, mask, False)
            if seg.last_painted is not None and \
                    np.abs((pose - seg.last_painted) @ self._corners)[:2].max() < self.min_move_px:
                self.stats.small_move += 1
                return touched
            seg.last_painted = pose
            clip = self._new_ground(mosaic, pose, mask)
            if not clip:
                self.stats.nothing_new += 1
                return touched
        img, pose_m, mask_m, to_kept = self._at_map_resolution(image, pose, mask, clip)
        if whole and self.band_px > 0 and mosaic.blend == "overwrite" and not self.whole_frames \
                and seg.last_painted is not None:  # (a segment's first frame: at once, its map is never empty)
            rects = self._band_rects(img, pose_m)
            if ((pose - seg.last_painted) @ self._corners)[1].mean() > 0:
                rects.reverse()  # moving down the map: its new ground is at the bottom, painted first
            seg.bands = _Bands(img, pose_m, mask_m, None, deque(rects))
            touched |= self._band(mosaic, seg)
            if seg.bands is not None:  # its new ground outside that band at once too (its bands paint over it)
                new = self._new_ground(mosaic, pose, mask)
                if new:
                    touched |= self._add(mosaic, seg, img, pose_m, mask_m, clip=new, gain=seg.bands.gain)
        else:
            touched |= self._add(mosaic, seg, img, pose_m, mask_m, clip=clip)
        if whole:
            self.stats.whole += 1
        else:
            self.stats.new_ground += 1
        if keyframe:  # with the exposure gain it got (maps with mosaic.exposure), for an equal re-render
            self._keep(seg, _Kept(index, pose.copy(), to_kept, (img.shape[1], img.shape[0]),
                                  getattr(mosaic, "last_gain", None), mask_m is None), img, mask_m,
                       as_read=as_read and img is image and mask_m is None)
        kept = keyframe and self.keep  # a kept tail needs no image: end_segment has nothing to paint
        seg.tail = _Tail(index, None if kept else image, pose, None if kept else mask, kept)
        seg.last_painted = pose
        return touched

    def _new_ground(self, mosaic: TiledMosaic, pose: np.ndarray, mask: np.ndarray | None) -> list:
        """The map rectangles under the frame at ``pose`` (3x3, input px -> map px) that no frame
        covers yet, inside its valid part (``mask``)."""
        return mosaic.uncovered(pose[:2], self.frame_size, block=self.block,
                                outline=None if mask is None else valid_outline(mask))

    def _add(self, mosaic: TiledMosaic, seg: _Segment, img: np.ndarray, pose_m: np.ndarray,
             mask_m: np.ndarray | None, clip: list | None = None, gain: np.ndarray | None = None
             ) -> set[TileKey]:
        """``mosaic.add`` and the painter's records of it (paint number, thumbnails)."""
        touched = mosaic.add(img, pose_m[:2], mask_m, gain=gain, clip=clip)
        self._paints += 1
        for tile in touched:
            seg.painted[tile] = self._paints
        seg.overview.mark(touched)
        return touched

    def _band_rects(self, img: np.ndarray, pose_m: np.ndarray) -> list[tuple[int, int, int, int]]:
        """The bounding box of the map pixels ``img`` at ``pose_m`` (3x3, image px -> map px) can
        cover, in bands of ``band_px`` map pixels on multiples of it (a band of tile height is one
        row of tiles; a sliver of less than a quarter band at either end goes with its
        neighbour): map rectangles (x, y, w, h), top to bottom."""
        h, w = img.shape[:2]
        corners = np.array([[0.0, 0.0], [w - 1, 0.0], [0.0, h - 1], [w - 1, h - 1]]) @ pose_m[:2, :2].T + pose_m[:2, 2]
        x0, y0 = (int(v) for v in np.floor(corners.min(axis=0)))
        x1, y1 = (int(v) + 1 for v in np.ceil(corners.max(axis=0)))
        b = self.band_px
        inner = [y for y in range((y0 // b + 1) * b, y1, b) if y - y0 >= b // 4 and y1 - y >= b // 4]
        edges = [y0, *inner, y1]
        return [(x0, a, x1 - x0, c - a) for a, c in zip(edges, edges[1:])]

    def _bands(self, mosaic: TiledMosaic, seg: _Segment, every: bool) -> set[TileKey]:
        """Paint the next band of the segment's last whole paint (``every``: all that are left).
        Returns the tiles they changed."""
        touched: set[TileKey] = set()
        while seg.bands is not None:
            touched |= self._band(mosaic, seg)
            self.stats.bands += 1
            if not every:
                break
        return touched

    def _band(self, mosaic: TiledMosaic, seg: _Segment) -> set[TileKey]:
        """Paint the next band of ``seg.bands``; returns the tiles it changed."""
        bands = seg.bands
        touched = self._add(mosaic, seg, bands.image, bands.pose, bands.mask, clip=[bands.rects.popleft()],
                            gain=bands.gain)
        if bands.gain is None:  # fitted on the whole footprint (the map before the frame)
            bands.gain = getattr(mosaic, "last_gain", None)
        if not bands.rects:
            seg.bands = None
        return touched

    def _at_map_resolution(self, image: np.ndarray, pose: np.ndarray, mask: np.ndarray | None,
                           clip: list | None = None
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
        """(image, 3x3 pose, mask, 3x3 input px -> image px) at the map's resolution; with
        ``clip`` (map rectangles) only the part of the frame they need (a strip of a 4K frame
        costs a strip's resize)."""
        h, w = image.shape[:2]
        found = resize_factors((w, h), pose)
        if found is None:
            return image, pose, mask, np.eye(3)
        if clip:
            corners = np.array([[x, y, 1.0] for cx, cy, cw, ch in clip
                                for x, y in ((cx, cy), (cx + cw, cy), (cx, cy + ch), (cx + cw, cy + ch))])
            uv = corners @ np.linalg.inv(pose)[:2].T
            margin = 2.0 / pose_scale(pose) + 2.0  # a map pixel and then some
            u0, v0 = (max(0, int(np.floor(c - margin))) for c in uv.min(axis=0))
            u1, v1 = (int(np.ceil(c + margin)) for c in uv.max(axis=0))
            u1, v1 = min(w, u1), min(h, v1)
            if u1 > u0 and v1 > v0 and (u1 - u0) * (v1 - v0) < 0.5 * w * h:
                crop = np.array([[1.0, 0.0, u0], [0.0, 1.0, v0], [0.0, 0.0, 1.0]])  # crop px -> input px
                img, pose_c, mask_c, to_c = self._at_map_resolution(
                    image[v0:v1, u0:u1], pose @ crop, None if mask is None else np.asarray(mask)[v0:v1, u0:u1])
                return img, pose_c, mask_c, to_c @ np.linalg.inv(crop)
        size, to_small = found
        small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        if mask is not None:  # valid where the whole area of a new pixel was valid
            mask = cv2.resize(np.where(np.asarray(mask) != 0, np.uint8(255), np.uint8(0)), size,
                              interpolation=cv2.INTER_AREA) == 255
        return small, pose @ np.linalg.inv(to_small), mask, to_small

    def _keep(self, seg: _Segment, kept: _Kept, image: np.ndarray, mask: np.ndarray | None,
              as_read: bool = False) -> None:
        if not self.keep:
            return
        seg.kept.append(kept)
        self.rerenderer.save(kept.index, None if as_read else image, mask)
        self.stats.kept += 1

    def end_segment(self, mosaic: TiledMosaic | None, segment: int) -> set[TileKey]:
        """``segment`` got its last frame: paint (and keep) that frame whole, so that a re-render
        has the segment's end too. Returns the tiles it changed."""
        seg = self._segments.get(segment)
        if seg is None or mosaic is None:
            return set()
        touched = self._bands(mosaic, seg, every=True)
        if seg.tail is None or seg.tail.kept or seg.tail.image is None:
            return touched
        tail = seg.tail
        if not self.keep:  # nothing is re-rendered: its new ground is in the map already
            seg.tail = _Tail(tail.index, None, tail.pose, None, True)
            return touched
        touched |= self.paint(mosaic, segment, tail.index, tail.image, tail.pose, tail.mask, whole=True)
        touched |= self._bands(mosaic, seg, every=True)
        seg.tail = _Tail(tail.index, None, tail.pose, None, True)  # the image is kept (or not needed)
        return touched

    def forget(self, segment: int) -> None:
        """Map ``segment`` was dropped (its frames are not mapped): forget its frames and tiles."""
        self._segments.pop(segment, None)
        self._swaps = deque(item for item in self._swaps if item[0] != segment)

    # ------------------------------------------------------------------ corrections
    def _dirty(self, seg: _Segment, entries: list[_Kept], poses: np.ndarray) -> None:
        """Mark for re-rendering the tiles kept frames ``entries`` reach at ``poses`` ((n, 3, 3),
        input px -> map px), all at once (:func:`~photomap.mapping.rerender.reach`)."""
        to_kept = np.array([e.to_kept for e in entries])
        box = reach(poses @ np.linalg.inv(to_kept), np.array([e.size for e in entries]))
        ts = self.tile_size
        for tx0, ty0, tx1, ty1 in (np.hstack([box[:, :2], box[:, 2:] - 1]) // ts).tolist():
            seg.dirty.update((tx, ty) for ty in range(ty0, ty1 + 1) for tx in range(tx0, tx1 + 1))

    def on_correction(self, segment: int, poses: dict[int, np.ndarray]) -> int:
        """Frames of ``segment`` have new poses (3x3, input px -> map px): mark the tiles of the
        kept frames that moved (before and after) for re-rendering. Returns how many moved."""
        seg = self._segments.get(segment)
        if seg is None:
            return 0
        take = getattr(poses, "take", None)  # a PoseTable looks them all up at once
        if take is not None:
            hit, table = take([entry.index for entry in seg.kept])
            found = list(zip([e for e, h in zip(seg.kept, hit.tolist()) if h], table))
        else:
            found = [(entry, new) for entry in seg.kept if (new := poses.get(entry.index)) is not None]
        moved = 0
        if found:  # how far each kept frame's corners move, and the tiles they cover: all at once
            old = np.array([entry.pose for entry, _ in found])
            new = to_h(np.array([np.asarray(p, float) for _, p in found]))
            far = np.flatnonzero(np.abs((new - old) @ self._corners)[:, :2].max(axis=(1, 2)) > self.move_px)
            entries = [found[k][0] for k in far.tolist()]
            if entries:  # the tiles before and after
                self._dirty(seg, entries, old[far])
                self._dirty(seg, entries, new[far])
            for entry, pose in zip(entries, new[far]):
                entry.pose = pose.copy()  # not a view: it would keep all of new alive
            moved = len(entries)
        if seg.tail is not None and seg.tail.index in poses:
            seg.tail.pose = to_h(np.asarray(poses[seg.tail.index], float))
        self.stats.moved_frames += moved
        return moved

    def on_join(self, segment: int, into: int, transform: np.ndarray) -> None:
        """Map ``segment`` is part of map ``into`` now (``transform``, 3x3: map px of ``segment`` ->
        map px of ``into``): its kept frames are re-rendered into ``into`` (the worker's map of
        ``segment`` is dropped), newest on top."""
        gone = self._segments.pop(segment, None)
        if gone is None:
            return
        seg = self._seg(into)
        t = np.asarray(transform, float)
        for entry in gone.kept:
            entry.pose = t @ entry.pose
            seg.kept.append(entry)
        if gone.kept:
            self._dirty(seg, gone.kept, np.array([entry.pose for entry in gone.kept]))
        seg.kept.sort(key=lambda e: e.index)
        if gone.tail is not None and (seg.tail is None or gone.tail.index > seg.tail.index):
            gone.tail.pose = t @ gone.tail.pose
            seg.tail = gone.tail

    # ------------------------------------------------------------------ swapping re-renders in
    def pump(self, mosaics: dict[int, TiledMosaic], *, now: float | None = None,
             force: bool = False, budget_s: float | None = None, frame: int | None = None
             ) -> dict[int, set[TileKey]]:
        """Swap finished re-render tiles into ``mosaics`` (for at most ``budget_s`` seconds, default
        ``swap_budget_s``; the rest waits for the next call) and start the next job; live, never
        waits for the re-render (in lockstep, see ``lockstep_frames``: ``frame`` drives it, a
        fixed number of tiles a frame, and a job due is waited for). ``force``: start a job now,
        whatever ``interval_s`` says. Returns the tiles changed per segment."""
        changed: dict[int, set[TileKey]] = {}
        if self.rerenderer is None:
            return changed
        t0 = time.perf_counter()
        budget = self.swap_budget_s if budget_s is None else budget_s
        lockstep = self.lockstep_frames is not None and budget_s is None
        if lockstep:
            if frame is None:  # e.g. a checkpoint, at a time that depends on the machine
                return changed
            now = float(frame)
            due = frame - self._last_job >= self.lockstep_frames
            if self.rerenderer.busy and due:
                t_wait = time.perf_counter()
                self.rerenderer.wait()  # a replay waits for the thread: the map does not depend on its speed
                self.stats.max_wait_ms = max(self.stats.max_wait_ms, 1000.0 * (time.perf_counter() - t_wait))
        if not self._swaps and (not lockstep or due):
            for strip in self.rerenderer.collect():
                self.stats.rerender_s += strip.render_s
                self._swaps.extend((strip.segment, strip.job, key, tile) for key, tile in strip.tiles.items())
        swapped = 0
        while self._swaps and (swapped < _LOCKSTEP_SWAPS if lockstep else time.perf_counter() - t0 < budget):
            swapped += 1
            segment, job, key, tile = self._swaps.popleft()
            seg = self._segments.get(segment)
            mosaic = mosaics.get(segment)
            if seg is None or mosaic is None or seg.job is None or seg.job[0] != job:
                continue  # joined into another map meanwhile: that map re-renders it
            if seg.painted.get(key, 0) > seg.job[1]:
                seg.dirty.add(key)  # painted live meanwhile: keep it, re-render it later
                self.stats.deferred_tiles += 1
                continue
            mosaic.put_tiles({key: tile})
            seg.overview.mark([key])
            self.stats.rerendered_tiles += 1
            changed.setdefault(segment, set()).add(key)
        if changed:
            self.stats.max_swap_ms = max(self.stats.max_swap_ms, 1000.0 * (time.perf_counter() - t0))
        for segment, seg in self._segments.items():  # thumbnails of tiles the camera has left (still in memory)
            if budget_s is None and seg.overview.stale and segment in mosaics:
                seg.overview.update(mosaics[segment], budget_s=self.thumb_budget_s, settled=30)
        self.stats.lost_frames = self.rerenderer.lost_frames
        self.stats.sync_writes = self.rerenderer.sync_writes
        now = time.monotonic() if now is None else now
        interval = self.lockstep_frames if lockstep else self.interval_s
        if self._swaps or self.rerenderer.busy or (not force and now - self._last_job < interval):
            return changed
        for segment, seg in sorted(self._segments.items()):
            if seg.dirty and segment in mosaics:
                frames = [e.frame() for e in seg.kept]
                job = self.rerenderer.submit(segment, frames, seg.dirty,
                                             scratch_bytes=self.final_scratch_bytes if self._finishing else 0)
                seg.job = (job, self._paints)
                seg.dirty = set()
                self.stats.rerender_jobs += 1
                self._last_job = now
                break  # one job at a time: the next one gets the poses of then
        return changed

    def write_preview(self, path, segment: int, mosaic: TiledMosaic, max_px: int,
                      on_error: Callable[[BaseException], None] | None = None) -> bool:
        """A small PNG of map ``segment`` (at most ``max_px``), from thumbnails refreshed only where
        the map changed since the last preview (the worker takes those tiles; thumbnails,
        resize and encoding in the background thread);
        False when the map is empty, or when that thread is behind (its queue full: the preview
        waits for the next checkpoint rather than being made in the worker: 110 ms once on the
        long flight). A write that fails there (disk full, read-only) goes to ``on_error`` (else
        it is logged), never to the re-render thread."""
        if self.rerenderer is not None and self.rerenderer.backlogged:
            self.stats.skipped_previews += 1
            return False

        def later(task: Callable[[], None]) -> None:
            def guarded() -> None:
                try:
                    task()
                except (OSError, PhotomapError) as exc:
                    if on_error is not None:
                        on_error(exc)
                    else:
                        log.error("cannot write %s: %s", path, exc)
            (self.rerenderer.later if self.rerenderer is not None else lambda t: t())(guarded)

        return self._seg(segment).overview.write(path, mosaic, max_px, later,
                                                 self.rerenderer.first.wait if self.rerenderer is not None else None)

    def pending(self) -> bool:
        """Tiles waiting for a re-render or a swap, or a job running."""
        return any(s.dirty for s in self._segments.values()) or bool(self._swaps) or (
            self.rerenderer is not None and self.rerenderer.busy)

    def finish(self, mosaics: dict[int, TiledMosaic], timeout_s: float = 600.0) -> dict[int, set[TileKey]]:
        """After the last frame (no live painting any more): re-render every dirty tile and swap
        it in, waiting for it. Returns the tiles changed per segment."""
        changed: dict[int, set[TileKey]] = {}
        if self.rerenderer is None:
            return changed
        deadline = time.monotonic() + timeout_s
        self._finishing = True

        def pump() -> None:
            for segment, keys in self.pump(mosaics, force=True, budget_s=float("inf")).items():
                changed.setdefault(segment, set()).update(keys)

        def idle() -> bool:
            return not self.pending()

        while True:
            pump()
            if idle():
                pump()  # the strips of the jobs that just finished (they may defer tiles again)
                if idle():
                    break
            if time.monotonic() > deadline:
                log.warning("map re-render not finished after %.0f s: some tiles keep their old poses", timeout_s)
                break
            self.rerenderer.wait(timeout=max(0.0, deadline - time.monotonic()))
        return changed

    def close(self) -> None:
        if self.rerenderer is not None:
            self.rerenderer.close()
