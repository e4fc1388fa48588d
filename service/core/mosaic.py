"""The photo map: an unbounded canvas of fixed-size tiles that frames are glued into.

Conventions
-----------
- Map pixels follow OpenCV: x right, y down, integer coordinates at pixel centres. The map has
  no fixed extent; negative coordinates are fine.
- Map pixel ``(x, y)`` lives in tile ``key = (tx, ty) = (x // ts, y // ts)`` (floor division),
  at row ``y - ty*ts``, column ``x - tx*ts`` of that tile. ``tile_origin(key) = (tx*ts, ty*ts)``.
- A pose ``M`` is a 2x3 affine matrix mapping **frame pixels to map pixels**.
- Rectangles are OpenCV's ``(x, y, w, h)`` in map pixels: the top-left pixel and the size.
- Every map pixel carries a coverage: uncovered pixels are "empty" (alpha 0), not black.

Blending
--------
``overwrite``
    The newest frame is on top wherever it covers (as in the original iFMI mosaics). A map pixel
    takes a frame's value only if all four source pixels of its bilinear interpolation lie
    inside the frame's mask, which is eroded by ``border`` pixels: no dark interpolated edges.
``feather``
    Every frame pixel is weighted by its distance to the frame border, as the product of the
    distances to the nearest vertical and horizontal border (a tent in x times a tent in y,
    1 at the frame centre; times the normalised distance transform of ``mask`` if one is given).
    Each tile keeps the weighted sum and the weight sum (float32) and shows their ratio, so
    overlaps blend without seams. The product, unlike the distance transform (the minimum of
    the two distances), also has no seam where two frames' borders run side by side: there the
    common factor cancels. Warping the premultiplied (value * weight, weight) image makes edge
    interpolation exact.

Exposure
--------
With ``exposure`` ``gain`` or ``channel_gain`` each frame is multiplied, before it is painted, by
a gain fitted where it overlaps what the map already holds (one for all channels, or one per
channel), so that a camera on auto exposure leaves no brightness step at every frame edge; the
gain returns slowly to 1 as new ground comes in, so it cannot drift without bound
(:mod:`photomap.core.exposure`). The overlap is sampled on a grid of map pixels (about
``GAIN_SAMPLES`` points per frame), before the frame is warped. :meth:`TiledMosaic.reset` starts
the gains afresh.

The module is pure computation: no file I/O, no threads. Tiles beyond ``max_tiles_in_memory``
go to a :class:`photomap.io.tilestore.TileStore` (which may write files) and come back transparently.
An instance is not thread-safe.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import Callable, Iterable, Iterator, Mapping, Protocol

import cv2
import numpy as np

from photomap.config import MosaicConfig
from photomap.core.area import AreaRows, premultiplied_planes
from photomap.core.exposure import SequentialGain
from photomap.errors import InputError, PhotomapError
from photomap.geometry import pose_scale

# Overlap samples per frame for the exposure gain: the footprint is sampled on a grid of map
# pixels (multiples of a stride in x and y) with about this many points.
GAIN_SAMPLES = 4096
# How fast the exposure gain returns to 1: the fraction of the way per frame footprint of new ground.
GAIN_PULL = 0.1

TileKey = tuple[int, int]
Rect = tuple[int, int, int, int]
_AREA_ROWS = 32  # area_sums premultiplies and reduces a tile row this many rows at a time

_COVER_STEP = 4  # px: a spilled tile's coverage is kept at this step (uncovered()'s default)
# frame sizes around a frame whose spilled tiles are read ahead: what the next frames paint at
# video rates (0.5 read 20x more tiles, most dropped unused: docs/benchmarks.md, stop 30)
_PREFETCH_MARGIN = 0.1
Tile = dict[str, np.ndarray]


class TileStore(Protocol):
    """Storage for spilled tiles, keyed by ``(tx, ty)`` (implementations: :mod:`photomap.io.tilestore`)."""

    def put(self, key: TileKey, arrays: Mapping[str, np.ndarray]) -> None:
        """Keep ``arrays`` under ``key``, replacing what was there."""

    def get(self, key: TileKey) -> Tile | None:
        """The arrays last put under ``key`` (a copy the caller may modify), or None. May be
        called from another thread while the owner puts and discards: it returns what was
        there before or after (never a mix of both)."""

    def keys(self) -> list[TileKey]:
        """Every key held."""

    def discard(self, key: TileKey) -> None:
        """Forget ``key`` (no error if absent)."""


class TiledMosaic:
    """An unbounded photo map made of ``tile_size`` x ``tile_size`` tiles created on demand.

    Parameters
    ----------
    params : MosaicConfig
        The ``mosaic`` settings: ``tile_size`` (side of a square tile, map pixels), ``channels``
        (3: BGR map, 1: gray; frames are converted), ``blend`` (``overwrite`` or ``feather``, see
        the module docstring), ``exposure`` (``none``, ``gain`` or ``channel_gain``, see the module
        docstring), ``border`` (frame pixels kept out of the map), ``max_tiles_in_memory``
        (the least recently touched tiles beyond it go to ``store`` and come back when touched or
        read; tiles the store holds read ahead count too; ``None``: no cap) and
        ``max_footprint_px`` (a frame whose map footprint, its bounding
        box, exceeds this many map pixels and 4 times the frame's own pixels is refused with
        :class:`InputError`, so that a wild pose cannot exhaust memory). ``cache_dir`` is the caller's (where ``store`` keeps its files).
    store : TileStore or None
        Where spilled tiles go; required with ``max_tiles_in_memory``.
    dtype : ``np.uint8`` (default) or ``np.uint16``
        The pixel type of the frames it takes and of its renders: a ``uint16`` map keeps a
        16-bit camera's raw values (the raw GeoTIFFs, :mod:`photomap.mapping.band_maps`); it has
        no exposure gain.
    """

    def __init__(self, params: MosaicConfig = MosaicConfig(), store: TileStore | None = None, *,
                 dtype: type = np.uint8) -> None:
        if params.max_tiles_in_memory is not None and store is None:
            raise ValueError("a mosaic with max_tiles_in_memory needs a tile store to spill to")
        self.dtype = np.dtype(dtype)
        if self.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"a mosaic holds uint8 or uint16 pixels, not {self.dtype}")
        if self.dtype != np.uint8 and params.exposure != "none":
            raise ValueError("a 16-bit mosaic has no exposure gain (mosaic.exposure none)")
        self._max = float(np.iinfo(self.dtype).max)
        self.tile_size = params.tile_size
        self.channels = params.channels
        self.blend = params.blend
        self.border = params.border
        self.max_tiles_in_memory = params.max_tiles_in_memory
        self.max_footprint_px = int(params.max_footprint_px)
        self.exposure = params.exposure
        self._gain = (None if params.exposure == "none" else
                      SequentialGain(self.channels, per_channel=params.exposure == "channel_gain",
                                     pull=GAIN_PULL))
        self.last_gain: np.ndarray | None = None  # gain (channels,) applied to the last frame added, if any
        self._store = store
        self._tiles: OrderedDict[TileKey, Tile] = OrderedDict()  # in memory, least recent first
        self._spilled: set[TileKey] = set()  # not in memory; current data is in the store
        # where a spilled tile is covered, looked at every _COVER_STEP px (packed bits): uncovered()
        # reads no tile from the store
        self._coverage: dict[TileKey, np.ndarray] = {}
        # tiles whose every pixel uncovered() looks at (every _COVER_STEP px) is covered: it skips
        # them (no read, no OpenCV call); coverage only grows, except where a tile is replaced,
        # emptied or lost (each of those forgets the tile here)
        self._full: set[TileKey] = set()
        self._clean: set[TileKey] = set()  # in memory and equal to the store's copy
        self._lent: set[TileKey] = set()  # in memory, arrays lent out (tile_image_later): copy before a change
        self._frame_cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray | None]] = {}
        # covered pixels of each tile: x0, y0, x1, y1 (map pixels, exclusive): bounds() reads no tile
        self._extent: dict[TileKey, tuple[int, int, int, int]] = {}
        self.lost_tiles = 0  # spilled tiles the store could not give back
        self.spill_failures = 0  # tiles the store could not take (kept in memory instead)
        self._stamps: dict[TileKey, int] = {}  # tile -> stamp of its last change (see tile_stamps)
        self._stamp = 0

    # ------------------------------------------------------------------ adding frames
    def add(self, frame: np.ndarray, M: np.ndarray, mask: np.ndarray | None = None,
            gain: np.ndarray | float | None = None, clip: Iterable[Rect] | None = None) -> set[TileKey]:
        """Glue ``frame`` into the map at pose ``M``.

        Parameters
        ----------
        frame : array (h, w) gray, (h, w, 3) BGR or (h, w, 4) BGRA (alpha ignored), of the
            map's ``dtype``
        M : array-like 2x3
            Pose: frame pixel ``(u, v)`` goes to map pixel ``M @ (u, v, 1)``.
        mask : array (h, w) or None
            Non-zero where the frame is valid (e.g. after undistortion); eroded by ``border``.
        gain : float, array (channels,) or None
            Multiply the frame's values by this gain (e.g. from
            :func:`photomap.core.exposure.joint_gains`) instead of fitting one (``exposure``).
        clip : iterable of rectangles ``(x, y, w, h)`` (map pixels) or None
            Change only the map pixels inside these rectangles (which must not overlap): only
            they are warped, so painting a thin strip of a large frame costs the strip. None:
            the whole footprint. The exposure gain is fitted on the whole footprint either way.

        Returns
        -------
        set of tile keys whose pixels changed.
        """
        img = self._to_channels(frame)
        M = _check_pose(M)
        h, w = img.shape[:2]
        valid, weight = self._frame_mask(h, w, mask)

        # Map pixels that bilinear interpolation of the frame can reach (generous by one pixel).
        corners = np.array([[-1.0, -1.0], [w, -1.0], [-1.0, h], [w, h]])
        mapped = corners @ M[:, :2].T + M[:, 2]
        x0, y0 = (int(v) for v in np.floor(mapped.min(axis=0)))
        x1, y1 = (int(v) + 1 for v in np.ceil(mapped.max(axis=0)))
        bw, bh = x1 - x0, y1 - y0
        if bw * bh > max(self.max_footprint_px, 4 * w * h):
            raise InputError(f"frame footprint of {bw}x{bh} map pixels exceeds the limit of "
                             f"{self.max_footprint_px} (pose scale {pose_scale(M):.3g})")
        boxes = [(x0, y0, x1, y1)]
        if clip is not None:
            boxes = []
            for cx, cy, cw, ch in clip:
                bx0, by0 = max(x0, int(cx)), max(y0, int(cy))
                bx1, by1 = min(x1, int(cx) + int(cw)), min(y1, int(cy) + int(ch))
                if bx1 > bx0 and by1 > by0:
                    boxes.append((bx0, by0, bx1, by1))
        C = self.channels
        if gain is not None:
            try:
                gain = np.broadcast_to(np.asarray(gain, np.float64), (C,)).copy()
            except (TypeError, ValueError):
                raise InputError(f"gain must be a number or {C} numbers, got {gain!r}") from None
            if not np.all(np.isfinite(gain) & (gain > 0)):
                raise InputError(f"gain must be positive and finite, got {gain!r}")
        elif self._gain is not None:
            gain = self._fit_gain(img, valid, M, (x0, y0, x1, y1))
        self.last_gain = gain
        if gain is not None and np.any(gain != 1):  # saturating uint8 products, ~10x faster than cv2.LUT
            if C == 3:
                img = cv2.transform(img, np.diag(gain).astype(np.float32))
            else:
                img = cv2.convertScaleAbs(img, alpha=float(gain[0])).reshape(h, w, 1)
        if self.blend == "overwrite":
            src = img
        else:
            src = cv2.merge([*cv2.split(img.astype(np.float32) * weight[..., None]), weight])
        touched: set[TileKey] = set()
        for box in boxes:
            touched |= self._paint_box(src, valid, M, box)
        return touched

    def _paint_box(self, src: np.ndarray, valid: np.ndarray, M: np.ndarray,
                   box: tuple[int, int, int, int]) -> set[TileKey]:
        """Warp ``src`` (the frame; premultiplied with its weight as the last channel for
        feather) into the map rectangle ``box = (x0, y0, x1, y1)`` and cut it into the tiles.

        The box is warped once: for 320x240 frames in 256 px tiles this measured 1.1-1.9x faster
        than one warpAffine per touched tile. Overwrite warps the colour and the valid mask
        separately and copies with ``cv2.copyTo``: 1.7x faster at 1080p than one BGRA warp and
        numpy masking, with identical pixels.
        """
        x0, y0, x1, y1 = box
        bw, bh = x1 - x0, y1 - y0
        A = M.copy()
        A[:, 2] -= (x0, y0)
        C = self.channels
        warp = dict(flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if self.blend == "overwrite":
            warped = cv2.warpAffine(src, A, (bw, bh), **warp).reshape(bh, bw, C)
            # a map pixel is covered when all four source pixels of its interpolation are valid
            cover = cv2.threshold(cv2.warpAffine(valid, A, (bw, bh), **warp), 254, 255, cv2.THRESH_BINARY)[1]
        else:
            warped = cv2.warpAffine(src, A, (bw, bh), **warp)
            cover = np.where(warped[..., C] > 0, np.uint8(255), np.uint8(0))
        rx, ry, rw, rh = cv2.boundingRect(cover)
        if rw == 0:
            return set()
        cx0, cy0, cx1, cy1 = x0 + rx, y0 + ry, x0 + rx + rw, y0 + ry + rh

        ts = self.tile_size
        touched: set[TileKey] = set()
        for ty in range(cy0 // ts, (cy1 - 1) // ts + 1):
            my0, my1 = max(ty * ts, cy0), min((ty + 1) * ts, cy1)
            for tx in range(cx0 // ts, (cx1 - 1) // ts + 1):
                mx0, mx1 = max(tx * ts, cx0), min((tx + 1) * ts, cx1)
                src_sl = (slice(my0 - y0, my1 - y0), slice(mx0 - x0, mx1 - x0))
                sub_cover = cover[src_sl]
                sx, sy, sw, sh = cv2.boundingRect(sub_cover)
                if sw == 0:
                    continue
                key = (tx, ty)
                tile = self._load(key, write=True)
                dst_sl = (slice(my0 - ty * ts, my1 - ty * ts), slice(mx0 - tx * ts, mx1 - tx * ts))
                sub = warped[src_sl]
                if self.blend == "overwrite":
                    color = tile["color"][dst_sl]
                    cv2.copyTo(sub if C > 1 else sub[..., 0], sub_cover, color if C > 1 else color[..., 0])
                    tile_cover = tile["cover"][dst_sl]
                    cv2.bitwise_or(tile_cover, sub_cover, dst=tile_cover)
                else:
                    tile["sum"][dst_sl] += sub[..., :C]
                    tile["weight"][dst_sl] += sub[..., C]
                self._grow_tile_extent(key, mx0 + sx, my0 + sy, mx0 + sx + sw, my0 + sy + sh)
                self._clean.discard(key)
                touched.add(key)
        for key in touched:
            self._stamp += 1
            self._stamps[key] = self._stamp
        return touched

    def uncovered(self, M: np.ndarray, size: tuple[int, int], *, block: int = 32, step: int = 4,
                  inset: float = 2.0, gap: int = 3, outline: np.ndarray | None = None) -> list[Rect]:
        """Where a frame at pose ``M`` would add ground to the map.

        Parameters
        ----------
        M : array-like 2x3
            Pose of the frame (frame pixels -> map pixels).
        size : (w, h)
            Frame size, pixels.
        block : int
            Granularity, map pixels: the answer is made of ``block`` x ``block`` squares aligned
            on multiples of ``block`` (a divisor of the tile size keeps them inside tiles).
        step : int
            The map's coverage is looked at every ``step`` pixels in x and y (a divisor of
            ``block``): new ground narrower than that may go unnoticed until it is wider.
        inset : float
            Frame pixels beyond ``border`` not looked at along the frame's edge (pixels there
            cannot be covered by interpolation anyway, so they would always look new).
        gap : int
            New squares of a row at most this many squares apart are joined into one rectangle
            (painting a little old ground costs less than another warp).
        outline : array (n, 2) or None
            Frame pixels of a convex polygon inside which the frame is valid (a frame with a
            mask), already inset; None: the frame's rectangle, inset by ``border + inset``.

        Returns
        -------
        list of rectangles ``(x, y, w, h)`` (map pixels) holding a looked-at map pixel inside
        the frame's footprint that no frame covers yet: ``add(..., clip=...)`` of them paints
        the frame's new ground only. Empty when the frame adds nothing.
        """
        M = _check_pose(M)
        w, h = size
        b = self.border + inset
        if outline is not None:
            if len(outline) < 3:
                return []
            quad = np.asarray(outline, np.float64).reshape(-1, 2) @ M[:, :2].T + M[:, 2]
        elif w - 1 - 2 * b <= 0 or h - 1 - 2 * b <= 0:
            return []
        else:
            quad = np.array([[b, b], [w - 1 - b, b], [w - 1 - b, h - 1 - b], [b, h - 1 - b]]) @ M[:, :2].T + M[:, 2]
        gx0, gy0 = (int(v) // block * block for v in np.floor(quad.min(axis=0)))
        gx1, gy1 = (-(-(int(v) + 1) // block) * block for v in np.ceil(quad.max(axis=0)))
        W, H = gx1 - gx0, gy1 - gy0
        if W * H > max(self.max_footprint_px, 4 * w * h):  # the limit of add()
            raise InputError(f"frame footprint of {W}x{H} map pixels exceeds the limit of {self.max_footprint_px}")
        # looked-at pixels: map (gx0 + step*j + step//2, gy0 + step*i + step//2) is todo[i, j]
        o = step // 2
        todo = np.zeros((H // step, W // step), np.uint8)
        cv2.fillConvexPoly(todo, np.rint((quad - (gx0 + o, gy0 + o)) * (16 / step)).astype(np.int32), 255,
                           cv2.LINE_8, 4)
        ts = self.tile_size
        for ty in range(gy0 // ts, (gy1 - 1) // ts + 1):
            for tx in range(gx0 // ts, (gx1 - 1) // ts + 1):
                key = (tx, ty)
                if key not in self._tiles and key not in self._spilled:
                    continue
                mx0, mx1 = max(tx * ts, gx0), min((tx + 1) * ts, gx1)  # multiples of step
                my0, my1 = max(ty * ts, gy0), min((ty + 1) * ts, gy1)
                sub = todo[(my0 - gy0) // step:(my1 - gy0) // step, (mx0 - gx0) // step:(mx1 - gx0) // step]
                if step == _COVER_STEP and key in self._full:
                    sub[...] = 0
                    continue
                if key in self._coverage and step == _COVER_STEP:  # spilled: its summary, no read
                    n = ts // step
                    seen = np.unpackbits(self._coverage[key], count=n * n).reshape(n, n)[
                        (my0 - ty * ts) // step:(my1 - ty * ts) // step, (mx0 - tx * ts) // step:(mx1 - tx * ts) // step]
                else:
                    tile = self._load(key)
                    cover = tile["cover"] if self.blend == "overwrite" else (tile["weight"] > 0).view(np.uint8)
                    seen = cover[my0 - ty * ts + o:my1 - ty * ts:step, mx0 - tx * ts + o:mx1 - tx * ts:step]
                new = cv2.compare(seen, 0, cv2.CMP_EQ)
                if step == _COVER_STEP and my1 - my0 == ts and mx1 - mx0 == ts and not cv2.countNonZero(new):
                    self._full.add(key)  # the whole tile looked at, all covered
                    sub[...] = 0
                    continue
                cv2.bitwise_and(sub, new, dst=sub)
        n = block // step
        grid = todo.reshape(H // block, n, W // step).max(axis=1).reshape(H // block, W // block, n).max(axis=2)
        runs: list[list[int]] = []  # [row, first column, end column, rows] of merged squares
        for r, row in enumerate(grid != 0):
            if not row.any():
                continue
            edges = np.flatnonzero(np.diff(np.concatenate([[False], row, [False]]).astype(np.int8)))
            spans = [[int(edges[0]), int(edges[1])]]
            for c0, c1 in zip(edges[2::2], edges[3::2]):
                if c0 - spans[-1][1] <= gap:
                    spans[-1][1] = int(c1)
                else:
                    spans.append([int(c0), int(c1)])
            for c0, c1 in spans:
                same = [u for u in runs if u[0] + u[3] == r and u[1] == c0 and u[2] == c1]
                if same:
                    same[0][3] += 1  # the same span as the row above: one taller rectangle
                else:
                    runs.append([r, c0, c1, 1])
        return [(gx0 + c0 * block, gy0 + r * block, (c1 - c0) * block, rows * block) for r, c0, c1, rows in runs]

    def merge(self, other: TiledMosaic, transform: np.ndarray, chunk: int = 1024) -> set[TileKey]:
        """Paint the map ``other`` into this one through ``transform`` (3x3: map px of ``other``
        -> map px of this map), e.g. when two map segments turn out to be one; in chunks of at
        most ``chunk`` px a side, so memory stays bounded. Returns the tiles it changed."""
        region = other.bounds()
        if region is None:
            return set()
        t = np.asarray(transform, dtype=np.float64)
        x, y, w, h = region
        pad = self.border + 1  # add() erodes a frame's border: render a little more
        touched: set[TileKey] = set()
        for cy in range(y, y + h, chunk):
            for cx in range(x, x + w, chunk):
                box = (cx - pad, cy - pad, min(chunk, x + w - cx) + 2 * pad, min(chunk, y + h - cy) + 2 * pad)
                image, alpha, (ox, oy) = other.render(1.0, box)
                if not alpha.any():
                    continue
                pose = t @ np.array([[1.0, 0.0, ox], [0.0, 1.0, oy], [0.0, 0.0, 1.0]])
                touched |= self.add(image, pose[:2], mask=alpha == 255, gain=1.0)  # already compensated
        return touched

    def _fit_gain(self, img: np.ndarray, valid: np.ndarray, M: np.ndarray,
                  box: tuple[int, int, int, int]) -> np.ndarray:
        """The exposure gain (channels,) of frame ``img`` (uint8 (h, w, C)) at pose ``M``, from
        its overlap with the map.

        Samples the map pixels of ``box`` (``x0, y0, x1, y1``, exclusive: the frame's footprint)
        whose coordinates are multiples of a stride (about ``GAIN_SAMPLES`` of them): the frame
        there (bilinear, as the warp; covered where ``valid`` is, as in :meth:`add`) and the map.
        """
        bx0, by0, bx1, by1 = box
        s = max(1, math.isqrt((bx1 - bx0) * (by1 - by0) // GAIN_SAMPLES))
        gx0, gy0 = bx0 + (-bx0) % s, by0 + (-by0) % s  # first grid point inside the box
        xs = np.arange(gx0, bx1, s, dtype=np.float64)
        ys = np.arange(gy0, by1, s, dtype=np.float64)
        inv = cv2.invertAffineTransform(M)  # map pixels -> frame pixels
        map_u = (inv[0, 0] * xs[None, :] + inv[0, 1] * ys[:, None] + inv[0, 2]).astype(np.float32)
        map_v = (inv[1, 0] * xs[None, :] + inv[1, 1] * ys[:, None] + inv[1, 2]).astype(np.float32)
        C, ts = self.channels, self.tile_size
        new = cv2.remap(img, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        new = new.reshape(len(ys), len(xs), C).astype(np.float32)
        new_cover = cv2.remap(valid, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                              borderValue=0) == 255
        old = np.zeros(new.shape, np.float32)
        old_cover = np.zeros(new_cover.shape, bool)
        for ty in range(by0 // ts, (by1 - 1) // ts + 1):
            ry0 = max(ty * ts, gy0)
            ry0 += (-ry0) % s
            ry1 = min((ty + 1) * ts, by1)
            if ry0 >= ry1:
                continue
            for tx in range(bx0 // ts, (bx1 - 1) // ts + 1):
                rx0 = max(tx * ts, gx0)
                rx0 += (-rx0) % s
                rx1 = min((tx + 1) * ts, bx1)
                if rx0 >= rx1:
                    continue
                tile = self._peek((tx, ty))
                if tile is None:
                    continue
                src = (slice(ry0 - ty * ts, ry1 - ty * ts, s), slice(rx0 - tx * ts, rx1 - tx * ts, s))
                if self.blend == "overwrite":
                    have, value = tile["cover"][src] == 255, tile["color"][src]
                else:
                    weight = tile["weight"][src]
                    have = weight > 0
                    value = tile["sum"][src] / np.where(have, weight, 1)[..., None]
                dst = (slice((ry0 - gy0) // s, (ry0 - gy0) // s + have.shape[0]),
                       slice((rx0 - gx0) // s, (rx0 - gx0) // s + have.shape[1]))
                old[dst] = value
                old_cover[dst] = have
        both = new_cover & old_cover
        n_new = np.count_nonzero(new_cover)
        new_fraction = 1.0 - np.count_nonzero(both) / n_new if n_new else 1.0
        return self._gain.update(new[both], old[both], new_fraction)

    def _to_channels(self, frame: np.ndarray) -> np.ndarray:
        """``frame`` as (h, w, channels) of the map's dtype."""
        frame = np.asarray(frame)
        if frame.dtype != self.dtype:
            raise InputError(f"mosaic frames must be {self.dtype}, got {frame.dtype}")
        if frame.ndim == 3 and frame.shape[2] == 1:
            frame = frame[..., 0]
        if frame.ndim == 2:
            code = cv2.COLOR_GRAY2BGR if self.channels == 3 else None
        elif frame.ndim == 3 and frame.shape[2] == 3:
            code = None if self.channels == 3 else cv2.COLOR_BGR2GRAY
        elif frame.ndim == 3 and frame.shape[2] == 4:
            code = cv2.COLOR_BGRA2BGR if self.channels == 3 else cv2.COLOR_BGRA2GRAY
        else:
            raise InputError(f"mosaic frames must be gray, BGR or BGRA images, got shape {frame.shape}")
        if min(frame.shape[:2]) < 1:
            raise InputError(f"mosaic frame is empty (shape {frame.shape})")
        if code is not None:
            frame = cv2.cvtColor(frame, code)
        return frame.reshape(frame.shape[0], frame.shape[1], self.channels)

    def _frame_mask(self, h: int, w: int, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        """(valid uint8 0/255 eroded by ``border``, feather weight float32 or None).

        Without a mask both depend only on the frame size and are cached per size.
        """
        if mask is None:
            cached = self._frame_cache.get((h, w))
            if cached is not None:
                return cached
            valid = np.zeros((h, w), np.uint8)
            b = self.border
            valid[b:h - b, b:w - b] = 255
        else:
            mask = np.asarray(mask)
            if mask.shape != (h, w):
                raise InputError(f"mask shape {mask.shape} does not match frame size {(h, w)}")
            valid = np.where(mask != 0, np.uint8(255), np.uint8(0))
            if self.border:
                k = 2 * self.border + 1
                valid = cv2.erode(valid, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT,
                                  borderValue=0)
        weight = None
        if self.blend == "feather":
            # tent in x times tent in y: 1 at the centre, falling to 0 beyond the eroded border
            b = self.border
            weight = np.outer(_tent(h, b), _tent(w, b))
            if mask is not None:
                # and the distance (pixels) to the nearest invalid pixel, normalised to 1
                dist = cv2.distanceTransform(valid, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
                top = float(dist.max())
                weight *= dist / top if top > 0 else dist
        if mask is None:
            self._frame_cache[(h, w)] = (valid, weight)
        return valid, weight

    # ------------------------------------------------------------------ tiles in memory / store
    def _new_tile(self) -> Tile:
        ts, C = self.tile_size, self.channels
        if self.blend == "overwrite":
            return {"color": np.zeros((ts, ts, C), self.dtype), "cover": np.zeros((ts, ts), np.uint8)}
        return {"sum": np.zeros((ts, ts, C), np.float32), "weight": np.zeros((ts, ts), np.float32)}

    def _load(self, key: TileKey, write: bool = False) -> Tile:
        """The tile at ``key`` in memory (loaded or created), marked most recently used.
        ``write``: the caller changes its arrays (copied first when they are lent out)."""
        tile = self._tiles.get(key)
        if tile is not None:
            self._tiles.move_to_end(key)
            if write and key in self._lent:
                self._lent.discard(key)
                tile = self._tiles[key] = {name: a.copy() for name, a in tile.items()}
            return tile
        if key in self._spilled:
            tile = self._store.get(key)
            self._spilled.discard(key)
            self._coverage.pop(key, None)
            if tile is None:
                self.lost_tiles += 1  # the store lost it: start it empty
                self._full.discard(key)
            else:
                self._clean.add(key)
        if tile is None:
            tile = self._new_tile()
        self._make_room(1)
        self._tiles[key] = tile
        return tile

    def _peek(self, key: TileKey) -> Tile | None:
        """The tile at ``key`` for reading (None if there is none), without changing what is
        in memory."""
        tile = self._tiles.get(key)
        if tile is None and key in self._spilled:
            tile = self._store.get(key)
            if tile is None:
                self.lost_tiles += 1  # the store lost it: read it as empty
                tile = self._new_tile()
        return tile

    def _cap(self) -> int | None:
        """How many tiles the map may hold now: ``max_tiles_in_memory`` less the tiles its store
        holds read ahead for it (``store.tiles_read_ahead``, if the store reads ahead): the cap
        bounds both."""
        cap = self.max_tiles_in_memory
        return None if cap is None else cap - int(getattr(self._store, "tiles_read_ahead", 0))

    def _make_room(self, n: int, cap: int | None = None) -> None:
        """Spill least recently used tiles until ``n`` more fit under ``cap`` (None: the map's,
        :meth:`_cap`)."""
        cap = self._cap() if cap is None else cap
        while cap is not None and self._tiles and len(self._tiles) + n > cap:
            key, tile = self._tiles.popitem(last=False)
            if key not in self._clean:
                try:
                    self._store.put(key, tile)
                except Exception:  # e.g. disk full: keep the tile (over the cap) rather than lose it
                    self._tiles[key] = tile
                    self._tiles.move_to_end(key, last=False)
                    self.spill_failures += 1
                    return
            self._lent.discard(key)  # out of memory: the next load brings new arrays
            self._clean.discard(key)
            self._spill_coverage(key, tile)
            self._spilled.add(key)

    def prefetch(self, M: np.ndarray, size: tuple[int, int], margin: float = _PREFETCH_MARGIN) -> None:
        """Ask the store to read ahead the spilled tiles under a frame of ``size`` (w, h) at pose
        ``M`` (2x3), grown by ``margin`` of its size on each side: the next frames will likely
        paint there. Nearest the frame's centre first (a store keeps a bounded number read
        ahead; a store without ``prefetch`` ignores it)."""
        prefetch = getattr(self._store, "prefetch", None)
        if prefetch is None or not self._spilled:
            return
        w, h = size
        u = np.array([-margin * w, (1 + margin) * w])
        v = np.array([-margin * h, (1 + margin) * h])
        corners = np.array([[x, y, 1.0] for x in u for y in v]) @ _check_pose(M).T
        ts = self.tile_size
        (tx0, ty0), (tx1, ty1) = np.floor(corners.min(axis=0) / ts).astype(int), np.floor(corners.max(axis=0) / ts).astype(int)
        keys = [(tx, ty) for ty in range(int(ty0), int(ty1) + 1) for tx in range(int(tx0), int(tx1) + 1)
                if (tx, ty) in self._spilled]
        if keys:
            # the frame's centre in tiles, less half a tile: its distance to a key is the tile centre's
            cx, cy = corners.mean(axis=0) / ts - 0.5
            prefetch(sorted(keys, key=lambda k: (k[0] - cx) ** 2 + (k[1] - cy) ** 2))

    def _spill_coverage(self, key: TileKey, tile: Tile) -> None:
        """Keep where tile ``key``, going to the store, is covered (see ``_coverage``)."""
        cover = tile["cover"] if self.blend == "overwrite" else tile["weight"]
        o = _COVER_STEP // 2
        seen = cover[o::_COVER_STEP, o::_COVER_STEP] != 0
        self._coverage[key] = np.packbits(seen, axis=None)
        if seen.all():
            self._full.add(key)

    def spill(self, max_tiles: int | None = None) -> int:
        """Move the tiles in memory to the store, least recently used first, at most ``max_tiles``
        of them (None: all; a map that no longer grows), and drop cached frame masks. Returns
        how many tiles stay in memory. No effect without a store."""
        if self._store is None:
            return len(self._tiles)
        keep = 0 if max_tiles is None else max(0, len(self._tiles) - max(0, int(max_tiles)))
        self._make_room(0, keep)
        self._frame_cache.clear()
        return len(self._tiles)

    @property
    def stamp(self) -> int:
        """The stamp of the latest change of any tile (see :meth:`tile_stamps`)."""
        return self._stamp

    def tile_stamps(self) -> dict[TileKey, int]:
        """``{key: stamp}`` of every tile: a stamp grows whenever the tile's pixels change, so a
        writer that remembers the stamps it saved knows which tiles changed since (incremental
        checkpoints). A cleared tile loses its stamp."""
        return dict(self._stamps)

    @property
    def tiles_in_memory(self) -> int:
        """Number of tiles currently held in memory."""
        return len(self._tiles)

    def in_memory(self, key: TileKey) -> bool:
        """Whether tile ``key`` is held in memory (reading it reads no store)."""
        return key in self._tiles

    def tiles(self) -> list[TileKey]:
        """Keys of every tile (in memory or spilled), sorted by row, then column."""
        return sorted(set(self._tiles) | self._spilled, key=lambda k: (k[1], k[0]))

    def tile_origin(self, key: TileKey) -> tuple[int, int]:
        """Map coordinates ``(x, y)`` of the top-left pixel of tile ``key``."""
        return key[0] * self.tile_size, key[1] * self.tile_size

    def tile_image(self, key: TileKey, copy: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """One tile as ``(image (ts, ts, C) or (ts, ts) of the map's dtype, alpha uint8 (ts, ts))``.

        Alpha is 255 where covered, 0 where empty (image 0 there). The arrays are copies, or
        with ``copy=False`` maybe views of the map's, to be read before it changes and never
        written (for a caller that makes its own copy at once). Raises KeyError if no such tile.
        """
        tile = self._peek(key)
        if tile is None:
            raise KeyError(f"no map tile {key}")
        image, alpha = self._tile_image_of(tile)
        return (image.copy(), alpha.copy()) if copy else (image, alpha)

    def tile_image_later(self, key: TileKey) -> Callable[[], tuple[np.ndarray, np.ndarray] | None]:
        """:meth:`tile_image` of ``key`` as a function to call later, maybe in another thread.

        A tile in memory is lent, not copied (the map copies its arrays before it changes them:
        copy on write), so the function gives its pixels as of now; a tile the map spilled is
        read from the tile store when the function is called (the store never serves a partly
        written tile, so its pixels are those of now or of a later change), or None if it left
        the store or cannot be read. Raises KeyError if no such tile. The pixels may be views:
        do not change them.
        """
        image_of = self._tile_image_of
        tile = self._tiles.get(key)
        if tile is not None:
            self._lent.add(key)
            return lambda: image_of(tile)
        if key not in self._spilled:
            raise KeyError(f"no map tile {key}")
        store = self._store

        def read() -> tuple[np.ndarray, np.ndarray] | None:
            try:
                tile = store.get(key)
            except PhotomapError:
                return None
            return None if tile is None else image_of(tile)

        return read

    def set_tile(self, key: TileKey, image: np.ndarray, alpha: np.ndarray) -> None:
        """Replace tile ``key`` by the pixels ``image`` (dtype (ts, ts, C) or (ts, ts)) where
        ``alpha`` (uint8 (ts, ts)) is non-zero, e.g. a tile saved by :meth:`tile_image`; the
        inverse of :meth:`tile_image` (a feather tile gets weight 1 where covered)."""
        key = (int(key[0]), int(key[1]))
        ts = self.tile_size
        img = np.asarray(image, self.dtype).reshape(ts, ts, -1)
        if img.shape[2] != self.channels:
            raise InputError(f"tile {key} has {img.shape[2]} channels, the map {self.channels}")
        covered = np.asarray(alpha).reshape(ts, ts) != 0
        tile = self._load(key, write=True)
        self._full.discard(key)
        if self.blend == "overwrite":
            tile["color"][...] = np.where(covered[..., None], img, 0)
            tile["cover"][...] = np.where(covered, np.uint8(255), np.uint8(0))
        else:
            tile["sum"][...] = np.where(covered[..., None], img.astype(np.float32), 0)
            tile["weight"][...] = covered.astype(np.float32)
        self._clean.discard(key)
        self._stamp += 1
        self._stamps[key] = self._stamp
        x, y, w, h = cv2.boundingRect(covered.view(np.uint8))
        if w:
            self._extent[key] = (key[0] * ts + x, key[1] * ts + y, key[0] * ts + x + w, key[1] * ts + y + h)
        else:
            self._extent.pop(key, None)

    def _tile_image_of(self, tile: Tile) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`tile_image` of a tile's arrays (maybe views)."""
        image, alpha = self._tile_pixels(tile)
        return (image[..., 0] if self.channels == 1 else image), alpha

    def _tile_pixels(self, tile: Tile) -> tuple[np.ndarray, np.ndarray]:
        """(image dtype (ts, ts, C), alpha uint8 (ts, ts)) of a tile's arrays (maybe views)."""
        if self.blend == "overwrite":
            return tile["color"], tile["cover"]
        weight = tile["weight"]
        covered = weight > 0
        image = np.zeros(tile["sum"].shape, self.dtype)
        ratio = tile["sum"][covered] / weight[covered][:, None]
        image[covered] = np.clip(np.rint(ratio), 0, self._max).astype(self.dtype)
        return image, np.where(covered, np.uint8(255), np.uint8(0))

    def clear_tiles(self, keys: Iterable[TileKey]) -> None:
        """Forget the given tiles (e.g. to re-render them after a pose-graph correction)."""
        for key in keys:
            key = (int(key[0]), int(key[1]))
            self._tiles.pop(key, None)
            self._lent.discard(key)
            self._spilled.discard(key)
            self._coverage.pop(key, None)
            self._full.discard(key)
            self._clean.discard(key)
            self._stamps.pop(key, None)
            self._extent.pop(key, None)
            if self._store is not None:
                self._store.discard(key)

    def reset(self) -> None:
        """Forget every tile: an empty map."""
        self.clear_tiles(self.tiles())
        if self._gain is not None:
            self._gain.reset()
        self.last_gain = None

    def take_tiles(self) -> dict[TileKey, Tile]:
        """Every tile's arrays (from memory or the store), leaving this map empty.

        For a map rendered aside (e.g. a re-render after a pose-graph correction) whose tiles go
        into another map with :meth:`put_tiles`.
        """
        out = {key: tile for key in self.tiles() if (tile := self._peek(key)) is not None}
        self.reset()
        return out

    def put_tiles(self, tiles: Mapping[TileKey, Tile | None]) -> None:
        """Replace whole tiles: ``key -> arrays`` (as :meth:`take_tiles` gives, same tile size and
        blend; the map keeps them, the caller must not change them) or ``key -> None`` (the tile
        becomes empty). No pixel is copied; with a tile cap, a tile that is not in memory goes
        straight to the store (one write, and no other tile is pushed out)."""
        ts = self.tile_size
        cap = self._cap()
        for key, tile in tiles.items():
            key = (int(key[0]), int(key[1]))
            alpha = None if tile is None else (
                tile["cover"] if self.blend == "overwrite" else (tile["weight"] > 0).view(np.uint8))
            x, y, w, h = (0, 0, 0, 0) if alpha is None else cv2.boundingRect(alpha)
            if w == 0:
                self.clear_tiles([key])
                continue
            self._extent[key] = (key[0] * ts + x, key[1] * ts + y, key[0] * ts + x + w, key[1] * ts + y + h)
            self._clean.discard(key)
            self._full.discard(key)
            self._stamp += 1
            self._stamps[key] = self._stamp
            self._lent.discard(key)  # new arrays (those lent out stay as they were)
            if key in self._tiles:
                self._tiles[key] = tile
                continue
            if cap is not None and len(self._tiles) >= cap:
                try:
                    self._store.put(key, tile)
                    self._spill_coverage(key, tile)
                    self._spilled.add(key)
                    continue
                except Exception:  # e.g. disk full: keep the tile in memory (over the cap)
                    self.spill_failures += 1
            self._spilled.discard(key)
            self._coverage.pop(key, None)
            if self._store is not None:
                self._store.discard(key)
            self._tiles[key] = tile

    # ------------------------------------------------------------------ extent and rendering
    def _grow_tile_extent(self, key: TileKey, x0: int, y0: int, x1: int, y1: int) -> None:
        e = self._extent.get(key)
        self._extent[key] = (x0, y0, x1, y1) if e is None else (
            min(e[0], x0), min(e[1], y0), max(e[2], x1), max(e[3], y1))

    def bounds(self) -> Rect | None:
        """The map rectangle ``(x, y, w, h)`` holding every covered pixel, or None if empty."""
        if not self._extent:
            return None
        e = np.array(list(self._extent.values()))
        x0, y0 = e[:, :2].min(axis=0)
        x1, y1 = e[:, 2:].max(axis=0)
        return int(x0), int(y0), int(x1 - x0), int(y1 - y0)

    def render(self, scale: float = 1.0, bounds: Rect | None = None
               ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """The map (or the rectangle ``bounds``) as one image.

        Parameters
        ----------
        scale : float in (0, 1]
            Downscale factor (preview). The output has ``round(w * scale)`` x ``round(h * scale)``
            pixels and equals ``cv2.resize(full, dsize, interpolation=cv2.INTER_AREA)`` of the
            full-resolution render where the map is covered; at the map's edge, empty pixels do
            not darken it (colours are alpha-weighted, alpha is the covered fraction).
        bounds : (x, y, w, h) or None
            Map rectangle to render; default :meth:`bounds`.

        Returns
        -------
        image : (H, W, 3) BGR, or (H, W) for a gray map, of the map's dtype; 0 where empty
        alpha : uint8 (H, W); 255 covered, 0 empty
        origin_xy : (x, y)
            Map coordinates of the top-left pixel of the rendered rectangle. At ``scale`` 1 this is
            the output's top-left pixel; downscaled, output pixel ``(u, v)`` covers the map pixels
            ``x + [u, u + 1) * w / W``, ``y + [v, v + 1) * h / H``.
            An empty map gives zero-size arrays and origin ``(0, 0)``.
        """
        if not 0 < scale <= 1:
            raise ValueError(f"render scale must be in (0, 1], got {scale!r}")
        region = self.bounds() if bounds is None else tuple(int(v) for v in bounds)
        C = self.channels
        if region is None:
            shape = (0, 0) if C == 1 else (0, 0, C)
            return np.zeros(shape, self.dtype), np.zeros((0, 0), np.uint8), (0, 0)
        x, y, w, h = region
        if w <= 0 or h <= 0:
            raise ValueError(f"render bounds need a positive size, got {region}")
        if scale == 1:
            image, alpha = self._render_full(x, y, w, h)
        else:
            image, alpha = self._render_area(x, y, w, h, max(1, round(w * scale)), max(1, round(h * scale)))
        return (image[..., 0] if C == 1 else image), alpha, (x, y)

    def _region_tiles(self, x: int, y: int, w: int, h: int):
        """(key, tile, (x0, y0, x1, y1) of the tile's part inside the region, tile origin)
        for every tile that meets the region; map coordinates, x1/y1 exclusive. Each tile is
        read (from the store, for a spilled one) as it is yielded."""
        for key, box, origin in self._region_parts(x, y, w, h):
            yield key, self._peek(key), box, origin

    def _region_parts(self, x: int, y: int, w: int, h: int):
        """:meth:`_region_tiles` without the tiles: (key, part, origin), by row, then column."""
        ts = self.tile_size
        tx0, tx1, ty0, ty1 = x // ts, (x + w - 1) // ts, y // ts, (y + h - 1) // ts
        if (tx1 - tx0 + 1) * (ty1 - ty0 + 1) < len(self._tiles) + len(self._spilled):
            # a small region of a large map (a GeoTIFF window): look its keys up, same order
            keys = [(tx, ty) for ty in range(ty0, ty1 + 1) for tx in range(tx0, tx1 + 1)
                    if (tx, ty) in self._tiles or (tx, ty) in self._spilled]
        else:
            keys = self.tiles()
        for key in keys:
            if tx0 <= key[0] <= tx1 and ty0 <= key[1] <= ty1:
                ox, oy = key[0] * ts, key[1] * ts
                mx0, mx1 = max(ox, x), min(ox + ts, x + w)
                my0, my1 = max(oy, y), min(oy + ts, y + h)
                yield key, (mx0, my0, mx1, my1), (ox, oy)

    def _render_full(self, x: int, y: int, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
        image = np.zeros((h, w, self.channels), self.dtype)
        alpha = np.zeros((h, w), np.uint8)
        for _, tile, (mx0, my0, mx1, my1), (ox, oy) in self._region_tiles(x, y, w, h):
            t_img, t_alpha = self._tile_pixels(tile)
            src = (slice(my0 - oy, my1 - oy), slice(mx0 - ox, mx1 - ox))
            dst = (slice(my0 - y, my1 - y), slice(mx0 - x, mx1 - x))
            image[dst] = t_img[src]
            alpha[dst] = t_alpha[src]
        return image, alpha

    def _render_area(self, x: int, y: int, w: int, h: int, ow: int, oh: int
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Area-averaged (``INTER_AREA``) render to (oh, ow), alpha-weighted (:meth:`area_sums`)."""
        *colour, alpha = unpremultiply(np.concatenate(list(self.area_sums((x, y, w, h), (ow, oh)))), self.dtype)
        return (cv2.merge(colour) if len(colour) > 1 else colour[0][..., None]), alpha

    def tile_rows(self, bounds: Rect) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """The map rectangle ``bounds`` (x, y, w, h) one tile row at a time from the top, full
        width: ``(y0, image (n, w, C) of the map's dtype, alpha uint8 (n, w))`` for every tile row
        it meets (zeros where nothing is mapped; ``y0`` its first map row). Each row's tiles are
        read (from the store, for spilled ones) when the row is made: memory is one tile row."""
        x, y, w, h = bounds
        ts, C = self.tile_size, self.channels
        rows: dict[int, list] = {}
        for key, box, origin in self._region_parts(x, y, w, h):  # by row, then column
            rows.setdefault(key[1], []).append((key, box, origin))
        for ty in range(y // ts, (y + h - 1) // ts + 1):
            my0, my1 = max(ty * ts, y), min((ty + 1) * ts, y + h)
            image = np.zeros((my1 - my0, w, C), self.dtype)
            cover = np.zeros((my1 - my0, w), np.uint8)
            for key, (mx0, _, mx1, _), (ox, oy) in rows.pop(ty, ()):
                t_img, t_alpha = self._tile_pixels(self._peek(key))
                src = (slice(my0 - oy, my1 - oy), slice(mx0 - ox, mx1 - ox))
                image[:, mx0 - x:mx1 - x] = t_img[src]
                cover[:, mx0 - x:mx1 - x] = t_alpha[src]
            yield my0, image, cover

    def area_sums(self, bounds: Rect, size: tuple[int, int]) -> Iterator[np.ndarray]:
        """The map rectangle ``bounds`` (x, y, w, h) area-averaged to ``size`` (W, H), as float32
        (n, W, C + 1) blocks of output rows from the top: colour times coverage, coverage (in
        [0, 1]); stacked they are all H rows. One tile row is read at a time (:meth:`tile_rows`), then
        premultiplied and reduced by :class:`~photomap.core.area.AreaRows` a few rows at a time:
        memory is one tile row of the region's pixels and the output rows under way, never the
        whole map."""
        x, y, w, h = bounds
        ow, oh = size
        stream = AreaRows(h, w, oh, ow, self.channels + 1)
        for my0, image, cover in self.tile_rows(bounds):
            if not cover.any():
                continue
            for r0 in range(0, image.shape[0], _AREA_ROWS):  # premultiplied, a few rows at a time (memory)
                part = slice(r0, r0 + _AREA_ROWS)
                yield from stream.add(my0 - y + r0, premultiplied_planes(image[part], cover[part]))
        yield from stream.close()


def _tent(n: int, border: int) -> np.ndarray:
    """float32 (n,): distance of each index to the nearest index outside ``[border, n - border)``,
    counting the first inside index as 1, normalised to a maximum of 1 (all 0 if none inside)."""
    i = np.arange(n)
    d = np.clip(np.minimum(i - border + 1, n - border - i), 0, None).astype(np.float32)
    top = d.max()
    return d / top if top > 0 else d


def unpremultiply(warped: np.ndarray, dtype: type = np.uint8) -> list[np.ndarray]:
    """Planes (colour..., alpha) of alpha-weighted float32 (h, w, C + 1) sums (colour times
    alpha, alpha), as :meth:`TiledMosaic.render` finishes them: colour ``rint(c / a)`` clipped to
    the range of ``dtype`` (uint8, or uint16 for raw values) where ``a > 1e-6``, else 0; alpha
    ``rint(255 a)`` clipped, uint8. Plane by plane on copies (the same float32 operations as one
    expression over the array, a third of its time)."""
    top = float(np.iinfo(dtype).max)
    planes = list(cv2.split(warped))
    cover = planes[-1]
    empty = cover <= 1e-6
    with np.errstate(divide="ignore", invalid="ignore"):  # uncovered pixels: 0 below
        for p in planes[:-1]:
            np.divide(p, cover, out=p)
            np.rint(p, out=p)
            np.clip(p, 0, top, out=p)
            p[empty] = 0
    cover *= 255
    np.rint(cover, out=cover)
    np.clip(cover, 0, 255, out=cover)
    return [p.astype(dtype) for p in planes[:-1]] + [cover.astype(np.uint8)]


def _check_pose(M: np.ndarray) -> np.ndarray:
    """``M`` as a float64 2x3 array; InputError if it is not a finite invertible affine pose."""
    try:
        M = np.asarray(M, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("pose M must be a 2x3 numeric matrix") from None
    if M.shape != (2, 3):
        raise InputError(f"pose M must be a 2x3 matrix, got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise InputError("pose M holds NaN or infinity")
    if abs(np.linalg.det(M[:, :2])) < 1e-12:
        raise InputError("pose M is singular (zero scale)")
    return M
