"""A small copy of a map, kept up to date tile by tile, for the previews written at checkpoints.

Rendering a preview from the map itself reads every tile (from disk when the map spills tiles):
7 s for a 750-tile 1080p map on a busy 2-core computer, in the worker. :class:`Overview` keeps one
thumbnail per map tile, ``factor`` times smaller, refreshed only for the tiles that changed since
the last preview; when the thumbnails outgrow ``max_pixels`` the factor doubles (each thumbnail
halves). A preview then costs the changed tiles plus a resize of at most ``max_pixels``.

A thumbnail pixel is the area average (``INTER_AREA``) of its map pixels: alpha is the covered
fraction, colour the average of the covered pixels (empty pixels do not darken the map's edge),
as :meth:`photomap.core.mosaic.TiledMosaic.render` downscales.
"""

from __future__ import annotations

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

    Parameters
    ----------
    tile_size : int
        The map's tile size (a power of two times ``factor``).
    factor : int
        Initial downscale factor (map pixels per thumbnail pixel, each axis).
    max_pixels : int
        Thumbnail pixels kept at most (4 bytes each); beyond, the factor doubles.
    """

    def __init__(self, tile_size: int, factor: int = 2, max_pixels: int = 1_500_000) -> None:
        self.tile_size = tile_size
        self.factor = factor
        self.max_pixels = max_pixels
        self._thumbs: dict[TileKey, np.ndarray] = {}
        self._stale: dict[TileKey, int] = {}  # changed tile -> when (mark() calls)
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

    def update(self, mosaic: TiledMosaic, budget_s: float | None = None, settled: int = 0) -> int:
        """Refresh the thumbnails of the changed tiles from ``mosaic``; returns how many.

        ``budget_s``: for at most that long (the rest stays for the next call). ``settled``: only
        tiles not changed in the last ``settled`` calls of :meth:`mark` (a tile under the camera
        changes again and again: its thumbnail waits until the camera has moved on).
        """
        t = max(1, self.tile_size // self.factor)
        t0 = time.perf_counter()
        n = 0
        for key, marked in list(self._stale.items()):
            if budget_s is not None and time.perf_counter() - t0 >= budget_s:
                break
            if marked > self._clock - settled:
                continue
            del self._stale[key]
            try:
                image, alpha = mosaic.tile_image(key)
            except KeyError:  # emptied
                self._thumbs.pop(key, None)
                continue
            if image.ndim == 2:
                image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
            if cv2.countNonZero(alpha) == alpha.size:  # covered: a plain resize
                small = cv2.resize(image, (t, t), interpolation=cv2.INTER_AREA)
                self._thumbs[key] = np.dstack([small, np.full((t, t), 255, np.uint8)])
            else:
                self._thumbs[key] = _shrink(np.dstack([image, alpha]), t)
            n += 1
        while len(self._thumbs) * t * t > self.max_pixels and t > 1:
            self.factor *= 2
            t = max(1, self.tile_size // self.factor)
            self._thumbs = {k: _shrink(v, t) for k, v in self._thumbs.items()}
        return n

    def render(self, max_px: int) -> np.ndarray | None:
        """The map as one BGRA image of at most ``max_px`` on its longer side (None if empty)."""
        return self._render(self._thumbs, max_px) if self._thumbs else None

    @staticmethod
    def _render(thumbs: dict[TileKey, np.ndarray], max_px: int) -> np.ndarray:
        t = next(iter(thumbs.values())).shape[0]
        keys = np.array(list(thumbs))
        (kx0, ky0), (kx1, ky1) = keys.min(axis=0), keys.max(axis=0)
        canvas = np.zeros(((ky1 - ky0 + 1) * t, (kx1 - kx0 + 1) * t, 4), np.uint8)
        for (kx, ky), thumb in thumbs.items():
            canvas[(ky - ky0) * t:(ky - ky0 + 1) * t, (kx - kx0) * t:(kx - kx0 + 1) * t] = thumb
        x, y, w, h = cv2.boundingRect(canvas[..., 3])
        canvas = canvas[y:y + h, x:x + w]
        scale = min(1.0, max_px / max(w, h))
        if scale < 1.0:
            size = max(1, round(w * scale))
            canvas = _resize_bgra(canvas, (size, max(1, round(h * scale))))
        return canvas

    def write(self, path: str | Path, mosaic: TiledMosaic, max_px: int,
              later: Callable[[Callable[[], None]], None] | None = None) -> bool:
        """Refresh the thumbnails and write the preview PNG (atomically); False when the map is
        empty. ``later``: runs the resize and the encoding elsewhere (a background thread)."""
        self.update(mosaic)
        if not self._thumbs:
            return False
        thumbs = dict(self._thumbs)  # the thumbnails are replaced, never changed in place

        def encode() -> None:
            image = self._render(thumbs, max_px)
            with PngStreamWriter(path, image.shape[1], image.shape[0], 4) as png:
                png.write(image)

        (later or (lambda task: task()))(encode)
        return True


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
