"""Where map tiles go when the mosaic must not keep them all in memory.

A tile is a small mapping of named arrays (what :class:`photomap.core.mosaic.TiledMosaic` keeps per
tile, e.g. ``{"color": uint8 (ts, ts, C), "cover": uint8 (ts, ts)}``). A store keeps tiles by key
``(tx, ty)`` (tile column and row, may be negative) and hands back an equal, independent copy.

- :class:`MemoryTileStore`: a dict (tests, small maps).
- :class:`DiskTileStore`: one uncompressed ``.npz`` per tile in a cache folder, written atomically
  (temporary file, then ``os.replace``), so a reader never sees a half-written tile.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import tempfile
import zipfile
from pathlib import Path
from typing import Mapping

import numpy as np

from photomap.core.mosaic import TileStore
from photomap.errors import PhotomapError

log = logging.getLogger(__name__)

TileKey = tuple[int, int]
TileArrays = dict[str, np.ndarray]

__all__ = ["TileStore", "MemoryTileStore", "DiskTileStore"]

_NAME = re.compile(r"^tile_(-?\d+)_(-?\d+)\.npz$")


class MemoryTileStore:
    """A :class:`TileStore` in a dict; copies on put and get, like a disk would."""

    def __init__(self) -> None:
        self._tiles: dict[TileKey, TileArrays] = {}

    def put(self, key: TileKey, arrays: Mapping[str, np.ndarray]) -> None:
        self._tiles[key] = {name: np.array(a, copy=True) for name, a in arrays.items()}

    def get(self, key: TileKey) -> TileArrays | None:
        tile = self._tiles.get(key)
        return None if tile is None else {name: a.copy() for name, a in tile.items()}

    def keys(self) -> list[TileKey]:
        return list(self._tiles)

    def discard(self, key: TileKey) -> None:
        self._tiles.pop(key, None)


class DiskTileStore:
    """A :class:`TileStore` in a folder: ``tile_{tx}_{ty}.npz`` per tile (uncompressed).

    Parameters
    ----------
    folder : path or None
        Cache folder, created if missing. Files of an earlier run in it are overwritten when the
        same key is put again; the mosaic only reads back keys it spilled itself.
        ``None``: a new temporary folder, removed by :meth:`close`.
    """

    def __init__(self, folder: str | os.PathLike | None = None) -> None:
        self._temporary = folder is None
        try:
            if folder is None:
                folder = tempfile.mkdtemp(prefix="photomap-tiles-")
            self.folder = Path(folder)
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise PhotomapError(f"cannot create tile cache folder {folder}: {exc.strerror}") from None

    def _path(self, key: TileKey) -> Path:
        return self.folder / f"tile_{int(key[0])}_{int(key[1])}.npz"

    def put(self, key: TileKey, arrays: Mapping[str, np.ndarray]) -> None:
        path = self._path(key)
        tmp = None
        try:
            fd, tmp = tempfile.mkstemp(dir=self.folder, prefix=".tile_", suffix=".tmp")
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **arrays)
            os.replace(tmp, path)
        except OSError as exc:
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)
            raise PhotomapError(f"cannot write tile cache file {path}: {exc.strerror}") from None

    def get(self, key: TileKey) -> TileArrays | None:
        path = self._path(key)
        try:
            with np.load(path, allow_pickle=False) as z:
                return {name: z[name] for name in z.files}
        except FileNotFoundError:
            return None
        except (OSError, ValueError, zipfile.BadZipFile) as exc:
            raise PhotomapError(f"tile cache file {path} is unreadable: {exc}") from None

    def keys(self) -> list[TileKey]:
        out = []
        for p in self.folder.iterdir():
            m = _NAME.match(p.name)
            if m:
                out.append((int(m.group(1)), int(m.group(2))))
        return out

    def discard(self, key: TileKey) -> None:
        self._path(key).unlink(missing_ok=True)

    def close(self) -> None:
        """Remove the folder if this store created it as a temporary folder."""
        if self._temporary:
            shutil.rmtree(self.folder, ignore_errors=True)
            log.debug("removed tile cache %s", self.folder)

    def __enter__(self) -> DiskTileStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
