"""Re-rendering map tiles after a pose-graph correction, off the worker thread.

When loop closure moves frames, the map tiles under them must be rendered again from the frames
kept for that (the images the painter stored at the map's resolution, in a
:class:`~photomap.io.keyframestore.KeyframeStore`). :class:`Rerenderer` does it in one background
thread at low priority (nice +10 on Linux: it gets the CPU the worker and the camera leave), in
strips of at most ``strip_tiles`` tiles, each rendered into a scratch map of its own: memory stays
bounded and the live map is never touched by this thread (after the last frame, several strips
together: each kept image read once for them all). The worker swaps finished strips in
(:meth:`photomap.core.mosaic.TiledMosaic.put_tiles`, no pixel copied) when it polls, so it never
waits for a re-render. The same thread writes the images kept for re-rendering (JPEG encoding off
the worker).

Conventions: poses are 3x3, pixels of the kept image -> map pixels; tile keys and rectangles as
in :mod:`photomap.core.mosaic`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict, deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np

from photomap.config import MosaicConfig
from photomap.core.mosaic import Tile, TiledMosaic, TileKey
from photomap.errors import PhotomapError
from photomap.io.keyframestore import KeyframeStore
from photomap.mapping.threads import BACKGROUND_NICE, WorkerFirst, lower_priority

log = logging.getLogger(__name__)

_READ_AHEAD = 2  # kept images read at once while strips render together


@dataclass(frozen=True)
class KeptFrame:
    """A frame kept for re-rendering: its index, its pose (3x3, pixels of the kept image -> map
    pixels), the kept image's size ``(w, h)``, the exposure gain it was painted with (None:
    none; with ``mosaic.exposure`` the re-render applies the same gain rather than fitting one)
    and whether the kept image is valid everywhere (kept without a mask: in an overwrite map it
    hides the older frames of the tiles it covers whole)."""

    index: int
    pose: np.ndarray
    size: tuple[int, int]
    gain: np.ndarray | None = None
    full: bool = False


def reach(poses: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Map pixels the interpolation of images of ``sizes`` ((n, 2): w, h) at ``poses`` ((n, 3, 3),
    image px -> map px) can reach: (n, 4) ints ``x0, y0, x1, y1``, exclusive."""
    w, h = np.asarray(sizes, float).T
    corners = np.zeros((len(w), 4, 3))  # (-1, -1), (w, -1), (-1, h), (w, h): one pixel beyond the edge
    corners[:, :, 2] = 1.0
    corners[:, [0, 1], 1] = corners[:, [0, 2], 0] = -1.0
    corners[:, [1, 3], 0], corners[:, [2, 3], 1] = w[:, None], h[:, None]
    mapped = np.einsum("nij,nkj->nki", np.asarray(poses, float)[:, :2], corners)
    return np.hstack([np.floor(mapped.min(axis=1)), np.ceil(mapped.max(axis=1)) + 1]).astype(int)


@dataclass(frozen=True)
class Strip:
    """A finished part of a re-render job: the new arrays of ``tiles`` (None: the tile is empty
    now) of map ``segment``."""

    job: int
    segment: int
    tiles: dict[TileKey, Tile | None]
    frames: int  # frames painted into it
    render_s: float


def hidden_before(frames: Sequence[KeptFrame], keys: Sequence[TileKey], tile_size: int, border: int
                  ) -> np.ndarray:
    """For each tile of ``keys``, the position in ``frames`` (in painting order, the newest on
    top) of the newest ``full`` frame that covers the whole tile, 0 if none: in an overwrite map
    (every pixel a frame covers is replaced) the frames before it change nothing there. int
    ``(len(keys),)``.

    Covered means every map pixel of the tile interpolates from valid pixels of the frame: the
    tile's corner pixels (the affine image of a rectangle is convex) land in the frame's valid
    rectangle (``border`` pixels in from its edges, see :meth:`TiledMosaic.add`), one pixel in
    from it for the interpolation's second sample and one more for the warp's fixed-point
    coordinates."""
    full = [i for i, f in enumerate(frames) if f.full]
    if not full or not len(keys):
        return np.zeros(len(keys), int)
    k = np.asarray(keys, float) * tile_size
    hi = tile_size - 1.0
    corners = np.stack([k, k + (hi, 0.0), k + (0.0, hi), k + hi], axis=1)  # (tiles, 4, 2) map px
    pose = np.array([frames[i].pose for i in full], float)
    inv = np.linalg.inv(pose)  # map px -> kept image px
    src = np.einsum("nij,tcj->ntci", inv[:, :2, :2], corners) + inv[:, None, None, :2, 2]  # (n, tiles, 4, 2)
    size = np.array([frames[i].size for i in full], float)[:, None, None, :]  # (w, h)
    lo = border + 2.0
    covers = ((src >= lo) & (src <= size - 1.0 - lo)).all(axis=(2, 3))  # (n, tiles)
    newest = len(full) - 1 - np.argmax(covers[::-1], axis=0)
    return np.where(covers.any(axis=0), np.asarray(full)[newest], 0)


def tile_rects(keys: Sequence[TileKey], tile_size: int) -> list[tuple[int, int, int, int]]:
    """The tiles ``keys`` as map rectangles ``(x, y, w, h)``, neighbours in a row merged."""
    rects = []
    for key in sorted(set(keys), key=lambda k: (k[1], k[0])):
        x, y = key[0] * tile_size, key[1] * tile_size
        if rects and rects[-1][1] == y and rects[-1][0] + rects[-1][2] == x:
            rx, ry, rw, rh = rects[-1]
            rects[-1] = (rx, ry, rw + tile_size, rh)
        else:
            rects.append((x, y, tile_size, tile_size))
    return rects


class Rerenderer:
    """One background thread that keeps frame images and re-renders map tiles from them.

    Parameters
    ----------
    store : KeyframeStore or None
        Where kept images go (``put_image``) and come back from (None: no frame is kept, the
        thread only runs :meth:`later` tasks).
    params : MosaicConfig
        The map's settings (tile size, channels, blend, border): strips are rendered exactly as
        the live map paints.
    strip_tiles : int
        Most tiles rendered at once (memory: ``strip_tiles`` tiles of the scratch map).
    max_pending_writes : int
        Kept images waiting for the thread; beyond, :meth:`save` writes in the caller's thread
        (memory stays bounded when the thread gets no CPU).
    max_done : int
        Finished strips waiting for :meth:`collect` (strips rendered together count as one);
        the thread renders no more until they are taken (memory stays bounded when the worker
        swaps slowly).
    nice : int
        Added to the thread's nice value (0: same priority as the worker).
    cache_bytes : int
        Kept images (and masks) held decoded between strips, the least recently used dropped
        beyond this many bytes (at least 2 frames). A loop-closure correction re-renders its
        tiles from every kept frame over them, strip after strip: with 2 frames held, each
        strip decoded its frames' JPEGs again (0.4 ms a 320x240 frame, 10x that at 1080p).
    release_after : float or None
        Seconds after the last strip, with no job queued, after which the decoded images are
        dropped (None: held to the end; kept images saved meanwhile do not count): a
        correction's strips share them; between loop closures the thread does not hold
        ``cache_bytes`` it is not using.
    first : WorkerFirst or None
        The thread waits at its pause points (before each task, each kept frame of a strip)
        while the worker maps a frame; None: never.
    """

    def __init__(self, store: KeyframeStore | None, params: MosaicConfig, *, strip_tiles: int = 32,
                 max_pending_writes: int = 4, max_done: int = 1, nice: int = BACKGROUND_NICE,
                 cache_bytes: int = 32 << 20, release_after: float | None = 2.0,
                 first: WorkerFirst | None = None) -> None:
        self.store = store
        self.first = first or WorkerFirst(enabled=False)  # its pause points: each task, each frame of a strip
        self.params = replace(params, max_tiles_in_memory=None)  # a scratch map never spills
        self.strip_tiles = max(1, int(strip_tiles))
        self.max_pending_writes = max(1, int(max_pending_writes))
        self.max_done = max(1, int(max_done))
        self.nice = nice
        self._cond = threading.Condition()
        self._writes: deque[Callable[[], None]] = deque()  # kept images, previews: before any strip
        # (job, segment, frames, strips, strips rendered together)
        self._jobs: deque[tuple[int, int, tuple[KeptFrame, ...], list[list[TileKey]], int]] = deque()
        self._done: list[Strip] = []
        self._active = 0  # tasks (strips, writes) being run right now (0 or 1)
        self._rendering = 0  # of which strips
        self._next_job = 0
        self._closing = False
        self._failure: BaseException | None = None
        self._cache: OrderedDict[int, tuple[np.ndarray | None, np.ndarray | None]] = OrderedDict()
        self._cache_lock = threading.Lock()
        self._cache_bytes = 0
        self.cache_bytes = int(cache_bytes)
        self.release_after = release_after
        self._last_strip = 0.0  # when the last strip was rendered (monotonic s)
        self.writes = 0  # kept images
        self.sync_writes = 0  # tasks run by the caller because the thread was behind
        self.lost_frames = 0  # kept images that could not be read back
        self._thread = threading.Thread(target=self._run, name="photomap-rerender", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ caller side
    def save(self, index: int, image: np.ndarray | None, mask: np.ndarray | None = None) -> None:
        """Keep the image of frame ``index`` (and its valid ``mask``) for re-rendering; None:
        the input reads it again (:meth:`~photomap.io.keyframestore.KeyframeStore.put_source`).
        The arrays must not change afterwards (the caller hands them over)."""
        self.later(lambda: self._put(index, image, mask))
        self.writes += 1

    def _put(self, index: int, image: np.ndarray | None, mask: np.ndarray | None) -> None:
        self._forget_decoded(index)  # a frame kept again is read back anew
        if image is None:
            self.store.put_source(index)
        else:
            self.store.put_image(index, image, mask)

    def later(self, task: Callable[[], None]) -> None:
        """Run ``task`` in the background thread, before any further re-render strip (in the
        caller's thread when ``max_pending_writes`` tasks are already waiting)."""
        with self._cond:
            if self._takes_tasks():
                self._writes.append(task)
                self._cond.notify()
                return
        task()
        self.sync_writes += 1

    def submit(self, segment: int, frames: Sequence[KeptFrame], tiles: set[TileKey], *,
               scratch_bytes: int = 0) -> int:
        """Re-render ``tiles`` of map ``segment`` from ``frames`` (painted in this order, the
        newest on top); returns the job id that its :class:`Strip` results carry.
        ``scratch_bytes``: strips rendered together, as many as fit their scratch tiles in this
        many bytes (at least one; each kept image is then read once for all of them, not once a
        strip), and handed over together."""
        keys = sorted(tiles, key=lambda k: (k[1], k[0]))
        strips = [keys[i:i + self.strip_tiles] for i in range(0, len(keys), self.strip_tiles)]
        together = max(1, int(scratch_bytes) // (self.strip_tiles * self._tile_bytes()))
        with self._cond:
            job = self._next_job
            self._next_job += 1
            if strips:
                self._jobs.append((job, segment, tuple(frames), strips, together))
                self._cond.notify()
        return job

    def _tile_bytes(self) -> int:
        """Bytes of one tile of a scratch map (:class:`TiledMosaic`: colour and cover bytes, or
        float32 sums and weights)."""
        per_px = self.params.channels + 1
        return self.params.tile_size ** 2 * (per_px if self.params.blend == "overwrite" else 4 * per_px)

    def collect(self) -> list[Strip]:
        """The strips finished since the last call (never blocks)."""
        self._raise()
        with self._cond:
            done, self._done = self._done, []
            self._cond.notify_all()
        return done

    @property
    def backlogged(self) -> bool:
        """Its queue of tasks is full (or it is closing): :meth:`later` would run the next one in
        the caller's thread."""
        with self._cond:
            return not self._takes_tasks()

    def _takes_tasks(self) -> bool:
        """Room for one more task of :meth:`later` (with ``self._cond`` held)."""
        return len(self._writes) < self.max_pending_writes and not self._closing

    @property
    def decoded_bytes(self) -> int:
        """Bytes of kept images (and masks) held decoded right now."""
        with self._cache_lock:
            return self._cache_bytes

    @property
    def busy(self) -> bool:
        """Jobs queued or being rendered (kept images being written do not count: a job
        submitted meanwhile renders after them, and a replay's worker does not wait for them)."""
        with self._cond:
            return bool(self._jobs) or self._rendering > 0

    def wait(self, timeout: float | None = None) -> None:
        """Block until every queued write and job is done (or ``timeout`` seconds); the strips
        stay for :meth:`collect`."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while (self._writes or self._active or (self._jobs and len(self._done) < self.max_done)) \
                    and self._failure is None:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    break
                self._cond.wait(left)
        self._raise()

    def close(self) -> None:
        """Finish the queued writes, drop queued jobs, end the thread."""
        with self._cond:
            self._closing = True
            self._jobs.clear()
            self._cond.notify_all()
        self._thread.join(timeout=30.0)

    def _raise(self) -> None:
        if self._failure is not None:
            failure, self._failure = self._failure, None
            raise PhotomapError(f"map re-render failed: {type(failure).__name__}: {failure}") from failure

    # ------------------------------------------------------------------ the thread
    def _run(self) -> None:
        lower_priority(self.nice)
        while True:
            with self._cond:
                while not self._writes and not self._closing and (
                        not self._jobs or len(self._done) >= self.max_done):
                    if self._jobs or not self._cache or self.release_after is None:
                        self._cond.wait()
                        continue
                    left = self._last_strip + self.release_after - time.monotonic()
                    if left <= 0:
                        self._drop_decoded()
                    else:
                        self._cond.wait(left)
                if self._writes:  # kept images first: a job may need them, and they hold memory
                    task = ("write", self._writes.popleft())
                elif self._jobs and len(self._done) < self.max_done:
                    job, segment, frames, strips, together = self._jobs[0]
                    group = [strips.pop(0) for _ in range(min(together, len(strips)))]
                    if not strips:
                        self._jobs.popleft()
                    task = ("strips", (job, segment, frames, group))
                    self._rendering += 1
                else:
                    return  # closing, nothing left to write
                self._active += 1
            try:
                self.first.wait()
                if task[0] == "write":
                    task[1]()
                else:
                    done = self._render_strips(*task[1])
                    with self._cond:
                        self._done.extend(done)
                        self._last_strip = time.monotonic()
            except BaseException as exc:  # handed to the worker by collect()
                log.debug("re-render thread failed", exc_info=True)
                with self._cond:
                    self._failure = exc
            finally:
                with self._cond:
                    self._active -= 1
                    if task[0] != "write":
                        self._rendering -= 1
                    self._cond.notify_all()

    @staticmethod
    def _nbytes(found: tuple[np.ndarray | None, np.ndarray | None]) -> int:
        return sum(a.nbytes for a in found if a is not None)

    def _forget_decoded(self, index: int) -> None:
        with self._cache_lock:
            found = self._cache.pop(index, None)
            if found is not None:
                self._cache_bytes -= self._nbytes(found)

    def _drop_decoded(self) -> None:
        with self._cache_lock:
            self._cache.clear()
            self._cache_bytes = 0

    def _image(self, index: int) -> tuple[np.ndarray | None, np.ndarray | None]:
        """A kept image and its mask, through a cache of ``cache_bytes`` (the strips of a
        correction paint the same frames; so does a correction within ``release_after``)."""
        with self._cache_lock:
            if index in self._cache:
                self._cache.move_to_end(index)
                return self._cache[index]
        found = (self.store.image(index), self.store.mask(index))
        with self._cache_lock:
            self.lost_frames += found[0] is None
            self._cache[index] = found
            self._cache_bytes += self._nbytes(found)
            while len(self._cache) > 2 and self._cache_bytes > self.cache_bytes:
                self._cache_bytes -= self._nbytes(self._cache.popitem(last=False)[1])
        return found

    def _render(self, job: int, segment: int, frames: tuple[KeptFrame, ...], keys: list[TileKey],
                cull: bool = True) -> Strip:
        """Render the strip ``keys`` alone (:meth:`_render_strips`)."""
        return self._render_strips(job, segment, frames, [keys], cull)[0]

    def _render_strips(self, job: int, segment: int, frames: tuple[KeptFrame, ...], strips: list[list[TileKey]],
                       cull: bool = True) -> list[Strip]:
        """Render each strip of ``strips`` (tile keys) from ``frames`` (oldest first) into a scratch
        map of its own, the strips together frame by frame: each kept image is read once for all
        of them (with more than one strip, the next ones on :data:`_READ_AHEAD` threads while one is
        painted, and half of the strips painted on a second thread: after the last frame no worker
        needs the CPU), and every scratch map gets the same paints as when rendered alone.
        ``cull``: each tile only from the newest frame that covers it whole on
        (:func:`hidden_before`: the same pixels in an overwrite map; a correction late in a flight
        that went over the same ground again and again re-renders each tile from the few frames
        on top, not from every pass)."""
        t = time.perf_counter()
        boxes = reach(np.array([f.pose for f in frames], float).reshape(-1, 3, 3),
                      np.array([f.size for f in frames], float).reshape(-1, 2))
        plans = [self._plan(frames, boxes, keys, cull) for keys in strips]
        steps = []  # (frame, [(plan, clip)]) in painting order, the frames that paint something
        for i in sorted({i for plan in plans for i in plan.near}):
            x0, y0, x1, y1 = boxes[i].tolist()
            todo = []
            for plan in plans:
                pos = plan.near.get(i)
                if pos is None:
                    continue
                mine = [key for key, s in zip(plan.keys, plan.start) if s <= pos] if plan.cull else plan.keys
                rects = plan.rects if len(mine) == len(plan.keys) else tile_rects(mine, self.params.tile_size)
                clip = [r for r in rects if x0 < r[0] + r[2] and r[0] < x1 and y0 < r[1] + r[3] and r[1] < y1]
                if clip:
                    todo.append((plan, clip))
            if todo:
                steps.append((frames[i], todo))
        # strips together (after the last frame): the next kept images are read while one is painted
        together = len(plans) > 1 and len(steps) > 1
        ahead = ThreadPoolExecutor(_READ_AHEAD, "photomap-rerender-read", initializer=lower_priority,
                                   initargs=(self.nice,)) if together else None
        # ... and painted into half of the strips on a second thread (each strip's own scratch map)
        painter = ThreadPoolExecutor(1, "photomap-rerender-paint", initializer=lower_priority,
                                     initargs=(self.nice,)) if together else None
        reads: deque = deque()
        try:
            for k, (frame, todo) in enumerate(steps):
                if all(plan.failed for plan in plans):
                    break  # each to be rendered again, uncut
                self.first.wait()
                if ahead is not None:
                    while len(reads) < _READ_AHEAD and k + len(reads) < len(steps):
                        reads.append(ahead.submit(self._image, steps[k + len(reads)][0].index))
                    image, mask = reads.popleft().result()
                else:
                    image, mask = self._image(frame.index)
                if painter is not None and len(todo) > 1:  # the strips in two halves, one on each thread
                    other = painter.submit(_paint, frame, image, mask, todo[1::2])
                    _paint(frame, image, mask, todo[::2])
                    other.result()
                else:
                    _paint(frame, image, mask, todo)
        finally:
            for pool in (ahead, painter):
                if pool is not None:
                    pool.shutdown(wait=True, cancel_futures=True)
        render_s = (time.perf_counter() - t) / len(plans)
        failed = [plan.keys for plan in plans if plan.failed]
        again = iter(self._render_strips(job, segment, frames, failed, cull=False) if failed else ())
        done = []
        for plan in plans:
            if plan.failed:
                done.append(next(again))
                continue
            tiles = plan.scratch.take_tiles()
            done.append(Strip(job, segment, {key: tiles.get(key) for key in plan.keys}, plan.painted, render_s))
        return done

    def _plan(self, frames: tuple[KeptFrame, ...], boxes: np.ndarray, keys: list[TileKey], cull: bool) -> _Plan:
        """What rendering the strip ``keys`` paints: the frames that reach it and, with ``cull``,
        the first of them each tile takes (``boxes``: :func:`reach` of ``frames``)."""
        ts = self.params.tile_size
        sx0 = min(k[0] for k in keys) * ts
        sy0 = min(k[1] for k in keys) * ts
        sx1 = (max(k[0] for k in keys) + 1) * ts
        sy1 = (max(k[1] for k in keys) + 1) * ts
        near = np.flatnonzero((boxes[:, 2] > sx0) & (boxes[:, 0] < sx1) & (boxes[:, 3] > sy0) & (boxes[:, 1] < sy1))
        # a tile takes the frames from the newest one that covers it whole (overwrite maps)
        # (a frame with no gain under mosaic.exposure would fit one against what is under it)
        cull = cull and self.params.blend == "overwrite" and (
            self.params.exposure == "none" or all(frames[i].gain is not None for i in near.tolist()))
        start = (hidden_before([frames[i] for i in near], keys, ts, self.params.border) if cull
                 else np.zeros(len(keys), int))
        return _Plan(keys, tile_rects(keys, ts), {i: pos for pos, i in enumerate(near.tolist())}, cull,
                     start.tolist(), cull and bool(start.any()), TiledMosaic(self.params))


def _paint(frame: KeptFrame, image: np.ndarray | None, mask: np.ndarray | None,
           todo: list[tuple["_Plan", list]]) -> None:
    """Paint the kept image of ``frame`` into each strip of ``todo`` (``(plan, clip)``); a strip
    it cannot be painted into is marked to be rendered again (``plan.failed``)."""
    for plan, clip in todo:
        if plan.failed:
            continue
        if image is None:
            plan.failed = plan.redo  # a frame that hides others not painted: render them all
            continue
        try:
            extra = {} if frame.gain is None else {"gain": frame.gain}
            plan.scratch.add(image, frame.pose[:2], mask, clip=clip, **extra)
            plan.painted += 1
        except PhotomapError as exc:
            plan.failed = plan.redo
            log.debug("frame %d not re-rendered: %s", frame.index, exc)


@dataclass
class _Plan:
    """One strip of :meth:`Rerenderer._render_strips`."""

    keys: list[TileKey]
    rects: list[tuple[int, int, int, int]]  # the strip's tiles as map rectangles (tile_rects)
    near: dict[int, int]  # position in the frames -> position among those that reach the strip
    cull: bool
    start: list[int]  # per tile, the position (in near) of the first frame it takes
    redo: bool  # culled: a frame that cannot be painted means rendering the strip again, uncut
    scratch: TiledMosaic
    painted: int = 0
    failed: bool = False
