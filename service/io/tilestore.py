"""Where map tiles go when the mosaic must not keep them all in memory.

A tile is a small mapping of named arrays (what :class:`photomap.core.mosaic.TiledMosaic` keeps per
tile, e.g. ``{"color": uint8 (ts, ts, C), "cover": uint8 (ts, ts)}``). A store keeps tiles by key
``(tx, ty)`` (tile column and row, may be negative) and hands back an equal, independent copy.

- :class:`MemoryTileStore`: a dict (tests, small maps).
- :class:`DiskTileStore`: one uncompressed ``.npz`` per tile in a cache folder, written atomically
  (temporary file, then ``os.replace``), so a reader never sees a half-written tile.
- :class:`WriteBehindTileStore`: another store's writes done by a background thread, so that the
  mapping worker never waits for the disk when it spills a tile (a write stalled for 0.4 s on the
  10,000-frame flight of ``tools/bench_pipeline.py``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
import tempfile
import threading
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Mapping

import numpy as np

from photomap.core.mosaic import TileStore
from photomap.errors import PhotomapError

log = logging.getLogger(__name__)

TileKey = tuple[int, int]
TileArrays = dict[str, np.ndarray]

__all__ = ["TileStore", "MemoryTileStore", "DiskTileStore", "WriteBehindTileStore"]

_NAME = re.compile(r"^tile_(-?\d+)_(-?\d+)\.npz$")
# np.load parses each array's header with ast.literal_eval; in CPython 3.11 two threads parsing
# at once can fail with "SystemError: AST constructor recursion depth mismatch" (cpython
# gh-106905; seen on the long flight: the worker and the tile writer's read-ahead): one read at a time
_READ_LOCK = threading.Lock()


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
        self._dir = str(self.folder)

    def _path(self, key: TileKey) -> str:
        # a str, not a Path: pathlib interns every name it parses, and the interpreter's table of
        # interned strings grows (a step of MBs at a moment of the flight) with the names it has seen
        return os.path.join(self._dir, f"tile_{int(key[0])}_{int(key[1])}.npz")

    def put(self, key: TileKey, arrays: Mapping[str, np.ndarray]) -> None:
        path = self._path(key)
        tmp = None
        try:
            fd, tmp = tempfile.mkstemp(dir=self._dir, prefix=".tile_", suffix=".tmp")
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **arrays)
            os.replace(tmp, path)
        except OSError as exc:
            if tmp is not None:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
            raise PhotomapError(f"cannot write tile cache file {path}: {exc.strerror}") from None

    def get(self, key: TileKey) -> TileArrays | None:
        path = self._path(key)
        try:
            with _READ_LOCK, np.load(path, allow_pickle=False) as z:
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
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self._path(key))

    def close(self) -> None:
        """Remove the folder if this store created it as a temporary folder."""
        if self._temporary:
            shutil.rmtree(self.folder, ignore_errors=True)
            log.debug("removed tile cache %s", self.folder)

    def __enter__(self) -> DiskTileStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class WriteBehindTileStore:
    """A :class:`TileStore` whose ``put`` and ``discard`` are carried out by a background thread
    (oldest first; a thread while there is work), in front of ``store``; :meth:`prefetch` reads
    tiles that will soon be wanted in that thread too.

    Until written, a tile is served from memory (copies, like a disk). At most ``max_pending``
    tiles wait: a ``put`` beyond that waits for the thread (memory stays bounded when the disk is
    slow). A tile the store refuses (disk full) is kept in memory and served from there: a map
    never loses a tile it spilled. At most ``max_ready`` prefetched tiles wait to be taken (the
    oldest are dropped; a :class:`~photomap.core.mosaic.TiledMosaic` counts them in its cap,
    :attr:`tiles_read_ahead`). Thread-safe.
    """

    MAX_READY = 48  # the default ``max_ready``

    def __init__(self, store: TileStore, max_pending: int = 32, max_ready: int = MAX_READY) -> None:
        self.store = store
        self.max_pending = max(1, int(max_pending))
        self.max_ready = max(0, int(max_ready))
        self._pending: OrderedDict[TileKey, TileArrays | None] = OrderedDict()  # None: to discard
        self._held: dict[TileKey, TileArrays] = {}  # refused by the store
        self._wanted: OrderedDict[TileKey, None] = OrderedDict()  # to prefetch
        self._ready: OrderedDict[TileKey, TileArrays] = OrderedDict()  # prefetched, not taken yet
        self._cv = threading.Condition()
        self._busy = False  # a writer thread is running
        self.failures = 0
        self.prefetched = 0  # tiles a get() found read ahead

    def put(self, key: TileKey, arrays: Mapping[str, np.ndarray]) -> None:
        """Keep ``arrays`` (handed over: the caller must not change them afterwards)."""
        with self._cv:
            while len(self._pending) >= self.max_pending and key not in self._pending:
                self._cv.wait(timeout=1.0)
            self._held.pop(key, None)
            self._queue(key, dict(arrays))

    def discard(self, key: TileKey) -> None:
        with self._cv:
            self._held.pop(key, None)
            self._queue(key, None)

    @property
    def tiles_read_ahead(self) -> int:
        """Tiles read ahead and not taken yet (a map counts them in its tile cap)."""
        return len(self._ready)

    def drop_read_ahead(self) -> None:
        """Forget the tiles read ahead and those still to read (their map will not want them)."""
        with self._cv:
            self._ready.clear()
            self._wanted.clear()

    def prefetch(self, keys: list[TileKey]) -> None:
        """Read these tiles ahead, in the thread (after the writes waiting), for a later get():
        the first ``max_ready`` of them (more would push out the first ones before they are
        taken, to be read again at the next request). The tiles of an earlier request not read
        yet are not read any more: the map has moved on."""
        with self._cv:
            self._wanted.clear()
            for key in keys[:self.max_ready]:
                if key not in self._ready and key not in self._pending and key not in self._held:
                    self._wanted[key] = None
            if self._wanted:
                self._start()

    def _queue(self, key: TileKey, arrays: TileArrays | None) -> None:
        self._ready.pop(key, None)  # older than this
        self._wanted.pop(key, None)
        self._pending[key] = arrays
        self._pending.move_to_end(key)
        self._start()

    def _start(self) -> None:
        if not self._busy:
            self._busy = True
            threading.Thread(target=self._work, name="photomap-tile-writer", daemon=True).start()

    def get(self, key: TileKey) -> TileArrays | None:
        with self._cv:
            tile = self._pending[key] if key in self._pending else self._held.get(key)
            if tile is not None or key in self._pending:
                return None if tile is None else {name: a.copy() for name, a in tile.items()}
            self._wanted.pop(key, None)
            ready = self._ready.pop(key, None)  # read for this call: handed over
            if ready is not None:
                self.prefetched += 1
                return ready
        return self.store.get(key)

    def keys(self) -> list[TileKey]:
        with self._cv:
            pending = dict(self._pending)
            held = list(self._held)
        on_disk = set(self.store.keys())
        return sorted((on_disk - {k for k, v in pending.items() if v is None})
                      | {k for k, v in pending.items() if v is not None} | set(held))

    def _work(self) -> None:
        while True:
            with self._cv:
                if not self._pending and self._wanted:
                    key = self._wanted.popitem(last=False)[0]
                else:
                    key = None
            if key is not None:
                self._read_ahead(key)
                continue
            with self._cv:
                if not self._pending:
                    self._busy = False
                    self._cv.notify_all()
                    return
                key, tile = next(iter(self._pending.items()))  # stays served from memory until written
            try:
                if tile is None:
                    self.store.discard(key)
                else:
                    self.store.put(key, tile)
            except Exception as exc:  # e.g. disk full: keep it in memory rather than lose it
                with self._cv:
                    if tile is not None and self._pending.get(key) is tile:
                        self._held[key] = tile
                    self.failures += 1
                    first = self.failures == 1
                if first:
                    log.warning("map tiles kept in memory, the tile cache refused them: %s", exc)
            with self._cv:
                if key in self._pending and self._pending[key] is tile:  # not replaced meanwhile
                    del self._pending[key]
                self._cv.notify_all()

    def _read_ahead(self, key: TileKey) -> None:
        try:
            tile = self.store.get(key)
        except Exception:  # the get() that wants it reads it again, and says why
            return
        with self._cv:
            if tile is None or key in self._pending or key in self._held or self.max_ready == 0:
                return  # a newer version was put meanwhile
            self._ready[key] = tile
            while len(self._ready) > self.max_ready:
                self._ready.popitem(last=False)

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every write is done (True), or ``timeout`` seconds (False)."""
        with self._cv:
            return self._cv.wait_for(lambda: not self._busy, timeout)
