"""A small copy of a map, kept up to date tile by tile, for the previews written at checkpoints.

Rendering a preview from the map itself reads every tile (from disk when the map spills tiles):
7 s for a 750-tile 1080p map on a busy 2-core computer, in the worker. :class:`Overview` keeps one
thumbnail per map tile, ``factor`` times smaller, refreshed only for the tiles that changed since
the last preview; when the thumbnails outgrow ``max_pixels`` the factor doubles (each thumbnail
halves, in the background thread at the next preview: shrinking the thumbnails of a 766-tile map
took the worker 100 ms). A preview then costs the changed tiles plus a resize of at most ``max_pixels``; the
worker only takes the changed tiles (lent by the map, copy on write), the thumbnails are made
in a background thread.

A thumbnail pixel is the area average (``INTER_AREA``) of its map pixels: alpha is the covered
fraction, colour the average of the covered pixels (empty pixels do not darken the map's edge),
as :meth:`photomap.core.mosaic.TiledMosaic.render` downscales.
"""

from __future__ import annotations

import queue
import time
from pathlib import Path
from typing import Callable, Iterable

import cv2
import numpy as np

from photomap.core.mosaic import TiledMosaic, TileKey
from photomap.io.pngstream import PngStreamWriter


def _shrink(bgra: np.ndarray, size: int) -> np.ndarray:
    """Area-average a BGRA thumbnail (colour = mean of covered pixels) to ``size`` x ``size``."""
    return _resize_bgra(bgra, (size, size))


class Overview:
    """Thumbnails of one map's tiles (see the module docstring).

    Used from the worker thread; :meth:`write` hands the thumbnails it needs made to ``later``
    (a background thread), which returns them through a queue drained by the worker's next call.

    Parameters
    ----------
    tile_size : int
        The map's tile size (a power of two times ``factor``).
    factor : int
        Initial downscale factor (map pixels per thumbnail pixel, each axis).
    max_pixels : int
        Thumbnail pixels kept at most (4 bytes each); beyond, the factor doubles.
    max_tile_bytes : int
        Tile pixels :meth:`write` takes for the background thread at most (what a pending
        preview may hold in memory; tiles beyond keep their previous thumbnail in this preview
        and go with the next ones).
    """

    def __init__(self, tile_size: int, factor: int = 2, max_pixels: int = 1_500_000,
                 max_tile_bytes: int = 16 << 20) -> None:
        self.tile_size = tile_size
        self.factor = factor
        self.max_pixels = max_pixels
        self.max_tile_bytes = max_tile_bytes
        self._thumbs: dict[TileKey, np.ndarray] = {}
        self._made: dict[TileKey, int] = {}  # tile -> clock of the pixels its thumbnail shows
        self._stale: dict[TileKey, int] = {}  # changed tile -> when (mark() calls)
        self._done: queue.SimpleQueue = queue.SimpleQueue()  # (tile, clock, thumbnail or None) from write()
        self._clock = 0

    def mark(self, keys: Iterable[TileKey]) -> None:
        """These tiles changed (painted, swapped in, emptied)."""
        self._clock += 1
        for key in keys:
            self._stale[key] = self._clock

    @property
    def stale(self) -> int:
        """Tiles changed since their thumbnail was made."""
        return len(self._stale)

    @property
    def _size(self) -> int:
        return max(1, self.tile_size // self.factor)

    def update(self, mosaic: TiledMosaic, budget_s: float | None = None, settled: int = 0) -> int:
        """Refresh the thumbnails of the changed tiles from ``mosaic``; returns how many.

        ``budget_s``: for at most that long (the rest stays for the next call). ``settled``: only
        tiles not changed in the last ``settled`` calls of :meth:`mark` (a tile under the camera
        changes again and again: its thumbnail waits until the camera has moved on). Only tiles
        in memory: one the map has spilled meanwhile stays for :meth:`write`, which reads it in
        the background (a tile read from disk in the worker measured up to 50 ms).
        """
        self._drain()
        t0 = time.perf_counter()
        n = 0
        for key, marked in list(self._stale.items()):
            if budget_s is not None and time.perf_counter() - t0 >= budget_s:
                break
            if marked > self._clock - settled or not mosaic.in_memory(key):
                continue
            del self._stale[key]
            try:
                pixels = mosaic.tile_image(key)
            except KeyError:  # emptied
                pixels = None
            self._install(key, self._clock, _thumbnail(pixels, self._size))
            n += 1
        self._fit()
        return n

    def _install(self, key: TileKey, clock: int, thumb: np.ndarray | None) -> None:
        """Keep ``thumb`` (None: the tile is empty) unless a thumbnail of newer pixels is in (one
        made before the factor doubled is kept as it is: the next preview shrinks it)."""
        if self._made.get(key, -1) > clock:
            return
        self._made[key] = clock
        if thumb is None:
            self._thumbs.pop(key, None)
        else:
            self._thumbs[key] = thumb

    def _drain(self) -> None:
        """Keep the thumbnails the background thread made."""
        while True:
            try:
                key, clock, thumb = self._done.get_nowait()
            except queue.Empty:
                break
            self._install(key, clock, thumb)
        self._fit()

    def _fit(self) -> None:
        """Double the factor while the thumbnails would outgrow ``max_pixels`` at its size (those
        of an older size are shrunk by the next :meth:`write`, in the background)."""
        while len(self._thumbs) * self._size ** 2 > self.max_pixels and self._size > 1:
            self.factor *= 2

    def render(self, max_px: int) -> np.ndarray | None:
        """The map as one BGRA image of at most ``max_px`` on its longer side (None if empty)."""
        self._drain()
        return self._render(self._thumbs, max_px, self._size) if self._thumbs else None

    @staticmethod
    def _render(thumbs: dict[TileKey, np.ndarray], max_px: int, t: int) -> np.ndarray:
        """``thumbs`` side by side (``t`` x ``t`` each; larger ones shrunk), cropped to the
        covered part and shrunk to at most ``max_px``."""
        keys = np.array(list(thumbs))
        (kx0, ky0), (kx1, ky1) = keys.min(axis=0), keys.max(axis=0)
        canvas = np.zeros(((ky1 - ky0 + 1) * t, (kx1 - kx0 + 1) * t, 4), np.uint8)
        for (kx, ky), thumb in thumbs.items():
            canvas[(ky - ky0) * t:(ky - ky0 + 1) * t, (kx - kx0) * t:(kx - kx0 + 1) * t] = \
                thumb if thumb.shape[0] == t else _shrink(thumb, t)
        x, y, w, h = cv2.boundingRect(canvas[..., 3])
        canvas = canvas[y:y + h, x:x + w]
        scale = min(1.0, max_px / max(w, h))
        if scale < 1.0:
            size = max(1, round(w * scale))
            canvas = _resize_bgra(canvas, (size, max(1, round(h * scale))))
        return canvas

    def write(self, path: str | Path, mosaic: TiledMosaic, max_px: int,
              later: Callable[[Callable[[], None]], None] | None = None,
              pause: Callable[[], None] | None = None) -> bool:
        """Write the preview PNG (atomically) with the thumbnails of the changed tiles refreshed;
        False when the map is empty. The worker only takes the changed tiles (at most
        ``max_tile_bytes``: :meth:`TiledMosaic.tile_image_later`); ``later`` reads them, makes
        the thumbnails, shrinks those made before the factor doubled, resizes and encodes
        elsewhere (a background thread; None: here), calling ``pause`` before each tile."""
        self._drain()
        taken = []
        budget = self.max_tile_bytes
        for key in list(self._stale):
            if budget <= 0:
                break
            del self._stale[key]
            try:
                pixels = mosaic.tile_image_later(key)
            except KeyError:  # emptied
                pixels = _empty
            taken.append((key, pixels))
            budget -= self.tile_size * self.tile_size * 4
        if not self._thumbs and all(pixels is _empty for _, pixels in taken):
            return False
        thumbs = dict(self._thumbs)  # the thumbnails are replaced, never changed in place
        clock, size, done = self._clock, self._size, self._done
        older = [(key, self._made[key]) for key, thumb in thumbs.items() if thumb.shape[0] != size]

        def encode() -> None:
            for key, pixels in taken:
                if pause is not None:
                    pause()
                thumb = _thumbnail(pixels(), size)
                done.put((key, clock, thumb))
                if thumb is None:
                    thumbs.pop(key, None)
                else:
                    thumbs[key] = thumb
            for key, made in older:  # made before the factor doubled, not made again above
                thumb = thumbs.get(key)
                if thumb is not None and thumb.shape[0] != size:
                    if pause is not None:
                        pause()
                    thumbs[key] = _shrink(thumb, size)
                    done.put((key, made, thumbs[key]))
            if thumbs:
                image = self._render(thumbs, max_px, size)
                with PngStreamWriter(path, image.shape[1], image.shape[0], 4) as png:
                    png.write(image)

        (later or (lambda task: task()))(encode)
        return True


def _empty() -> None:
    """The pixels of an emptied tile."""
    return None


def _thumbnail(pixels: tuple[np.ndarray, np.ndarray] | None, size: int) -> np.ndarray | None:
    """The BGRA ``size`` x ``size`` thumbnail of a tile's ``(image, alpha)`` (None: emptied)."""
    if pixels is None:
        return None
    image, alpha = pixels
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if cv2.countNonZero(alpha) == alpha.size:  # covered: a plain resize
        small = cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)
        return np.dstack([small, np.full((size, size), 255, np.uint8)])
    return _shrink(np.dstack([image, alpha]), size)


def _resize_bgra(bgra: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """INTER_AREA resize of a BGRA image whose colour is the mean of its covered pixels (alpha
    weighted: empty pixels do not darken the edge)."""
    alpha = bgra[..., 3]
    if cv2.countNonZero(cv2.compare(alpha, 255, cv2.CMP_NE)) == 0:  # all covered: a plain resize
        return cv2.resize(bgra, size, interpolation=cv2.INTER_AREA)
    a = alpha.astype(np.float32)
    pre = cv2.merge([*cv2.split(cv2.multiply(bgra[..., :3].astype(np.float32), cv2.merge([a, a, a]))), a])
    small = cv2.resize(pre, size, interpolation=cv2.INTER_AREA)
    cover = small[..., 3]
    inv = np.divide(1.0, cover, out=np.zeros_like(cover), where=cover > 1e-3)
    colour = cv2.multiply(small[..., :3], cv2.merge([inv, inv, inv]))
    return cv2.merge([*cv2.split(np.clip(colour + 0.5, 0, 255).astype(np.uint8)),
                      np.clip(cover + 0.5, 0, 255).astype(np.uint8)])
