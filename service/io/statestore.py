"""The full-resolution map of a run on disk, checkpointed so that a kill at any moment leaves a
consistent, recoverable map.

Layout of the state folder (``checkpoint/`` in the run folder)::

    manifest.json                 written last, atomically: what the checkpoint holds
    seg{S}/{tx}_{ty}_g{G}.png     one map tile of segment S (BGRA PNG, alpha 0 = empty), as
                                  saved by checkpoint generation G
    keyframes/                    keyframe images (see photomap.io.keyframestore), when kept here

Consistency: a tile file is never rewritten in place. Checkpoint ``G`` writes only the tiles
that changed since the last checkpoint, under new names ending in ``_g{G}`` (each through a
temporary file, fsync and rename); then ``manifest.json`` (fsync, rename, fsync of the folder);
only then are the files the new manifest no longer names deleted. A kill or power loss at any
moment therefore leaves the manifest of ``G`` or of ``G - 1`` and every file it names. A
checkpoint that fails (ENOSPC, EIO) removes its partial files and leaves the previous manifest;
its tiles stay "changed" and are written by the next one.

A tile's pixels are those of :meth:`photomap.core.mosaic.TiledMosaic.tile_image` (the blended
map as shown), which :meth:`~photomap.core.mosaic.TiledMosaic.set_tile` puts back. Map pixel
conventions: :mod:`photomap.core.mosaic` (tile ``(tx, ty)`` starts at map pixel
``(tx * tile_size, ty * tile_size)`` of its segment).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping

import cv2
import numpy as np

from photomap.config import MosaicConfig
from photomap.core.mosaic import TiledMosaic
from photomap.errors import InputError, PhotomapError
from photomap.io.pngstream import encode_png
from photomap.io.trajectory_files import write_json

log = logging.getLogger(__name__)

__all__ = ["MANIFEST", "STATE_DIR", "MapState", "Snapshot", "CheckpointError", "load_manifest",
           "restore_mosaic"]

STATE_DIR = "checkpoint"
MANIFEST = "manifest.json"
FORMAT = 1
_TILE = re.compile(r"^(-?\d+)_(-?\d+)_g(\d+)\.png$")

TileKey = tuple[int, int]


class CheckpointError(PhotomapError):
    """A checkpoint could not be written (disk full, I/O error); the previous one stays valid."""


@dataclass
class Snapshot:
    """What one checkpoint writes, taken in the worker thread (copies: the maps go on changing).

    ``stamps``: segment -> {tile: stamp} of every tile of the segment's map now; ``tiles``:
    (segment, tile, stamp, :meth:`TiledMosaic.tile_image_later` of it) of the tiles that changed
    since the last checkpoint
    (at most the snapshot's byte budget; the rest wait for the next checkpoint); ``meta``:
    what the manifest records besides the tiles (frame size, segments' keyframes, counts...).
    """

    stamps: dict[int, dict[TileKey, int]]
    tiles: list[tuple[int, TileKey, int, Callable[[], tuple[np.ndarray, np.ndarray] | None] | None]]
    meta: dict
    tile_size: int
    channels: int
    pending: int = 0  # changed tiles left for the next checkpoint (byte budget)
    taken_s: float = 0.0


def _tile_png(pixels: np.ndarray) -> bytes:
    """A saved tile's PNG: 8-bit ones by :func:`~photomap.io.pngstream.encode_png` (a third of
    OpenCV's CPU; grey + alpha too, which OpenCV cannot write), others by OpenCV."""
    if pixels.dtype == np.uint8:
        return encode_png(pixels)
    ok, buf = cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise OSError("PNG encoding of a tile failed")
    return buf.tobytes()


def _with_alpha(image: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """A tile's pixels as one PNG image: BGRA, or grey + alpha for a grey map."""
    if image.ndim == 2:
        return cv2.merge([image, alpha])
    bgra = cv2.cvtColor(image, cv2.COLOR_BGR2BGRA)
    bgra[..., 3] = alpha
    return bgra


@dataclass
class _Written:
    """A tile on disk: the stamp it was saved at and the generation (file name) holding it."""

    stamp: int
    gen: int


class MapState:
    """The checkpointed map of a run in ``folder`` (created).

    Use from one thread at a time: :meth:`snapshot` (cheap, in the worker) then :meth:`write`
    (anywhere, e.g. a background thread), never two writes at once and no snapshot during a write.

    Parameters
    ----------
    folder : path
        The state folder. An existing manifest is taken over (generation numbers go on from it),
        so files of the run being continued stay valid until replaced.
    max_snapshot_bytes : int
        Budget of tile pixels taken per checkpoint (BGRA bytes); changed tiles beyond it are
        written by the next checkpoints (until then the manifest names their previous version).
        The worker takes the tiles (:meth:`TiledMosaic.tile_image_later`: tiles in memory are
        lent, copy on write; spilled ones are read by the writer), which bounds the memory the
        pending checkpoint holds.
    """

    def __init__(self, folder: str | Path, *, max_snapshot_bytes: int = 16 << 20) -> None:
        self.folder = Path(folder)
        self._dir = str(self.folder)
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CheckpointError(f"cannot create the checkpoint folder {self.folder}: {exc.strerror}") from None
        self.max_snapshot_bytes = int(max_snapshot_bytes)
        self.generation = 0
        self._written: dict[int, dict[TileKey, _Written]] = {}
        self._mosaic_ids: dict[int, int] = {}
        self.bytes_written = 0
        self.last_write_s = 0.0
        self.last_tiles = 0
        self.last_pending = 0  # changed tiles the last checkpoint left for the next one

    # ------------------------------------------------------------------ worker side
    def snapshot(self, mosaics: Mapping[int, TiledMosaic], meta: dict) -> Snapshot:
        """Copy what changed in ``mosaics`` (segment -> map) since the last written checkpoint."""
        t0 = time.perf_counter()
        stamps: dict[int, dict[TileKey, int]] = {}
        changed: list[tuple[int, TileKey, int]] = []
        tile_size, channels = 256, 3
        for seg, mosaic in mosaics.items():
            tile_size, channels = mosaic.tile_size, mosaic.channels
            if self._mosaic_ids.get(seg) not in (None, id(mosaic)):
                self._written.pop(seg, None)  # another map under this number: write it all
            current = mosaic.tile_stamps()
            stamps[seg] = current
            written = self._written.get(seg, {})
            changed += [(seg, key, st) for key, st in current.items()
                        if key not in written or written[key].stamp != st]
        tiles = []
        budget = self.max_snapshot_bytes
        per_tile = tile_size * tile_size * 4
        for seg, key, st in changed:
            if budget < per_tile and tiles:
                break
            tiles.append((seg, key, st, mosaics[seg].tile_image_later(key)))  # read by the writer
            budget -= per_tile
        for seg, mosaic in mosaics.items():
            self._mosaic_ids[seg] = id(mosaic)
        return Snapshot(stamps, tiles, dict(meta), tile_size, channels, pending=len(changed) - len(tiles),
                        taken_s=time.perf_counter() - t0)

    # ------------------------------------------------------------------ writer side
    def _tile_path(self, seg: int, key: TileKey, gen: int) -> str:
        # a str, not a Path: pathlib interns every name it parses (the interpreter's table of
        # interned strings would grow with the tiles written)
        return os.path.join(self._dir, f"seg{seg}", f"{key[0]}_{key[1]}_g{gen}.png")

    def write(self, snap: Snapshot) -> dict:
        """Write checkpoint ``generation + 1`` from ``snap``; returns its manifest.

        Raises CheckpointError (after removing its partial files) when the disk refuses; the
        previous checkpoint stays valid and its tiles are written again next time.
        """
        t0 = time.perf_counter()
        gen = self.generation + 1
        new_files: list[tuple[str, str]] = []  # (temporary, tile file)
        nbytes = 0
        fresh = {(seg, key): st for seg, key, st, _ in snap.tiles}
        try:
            for i, (seg, key, st, pixels) in enumerate(snap.tiles):
                snap.tiles[i] = (seg, key, st, None)  # the copy goes as soon as it is encoded
                tile = pixels()
                if tile is None:  # left the map's tile store meanwhile: the next checkpoint decides
                    del fresh[(seg, key)]
                    continue
                buf = _tile_png(_with_alpha(*tile))
                del tile, pixels
                path = self._tile_path(seg, key, gen)
                folder, name = os.path.split(path)
                with contextlib.suppress(FileExistsError):
                    os.mkdir(folder)
                tmp = os.path.join(folder, f".{name}.tmp")  # a kill leaves no partial file under a tile's name
                new_files.append((tmp, path))
                _write_file(tmp, buf)
                nbytes += len(buf)
            for tmp, _ in new_files:  # one journal commit for all of them, not one per tile
                _fsync_file(tmp)
            for tmp, path in new_files:
                os.replace(tmp, path)  # a new name: no manifest names it before it is synced
            for folder in {os.path.dirname(path) for _, path in new_files}:
                _fsync_dir(folder)
            written: dict[int, dict[TileKey, _Written]] = {}
            for seg, current in snap.stamps.items():
                old = self._written.get(seg, {})
                entries = {}
                for key in current:
                    if (seg, key) in fresh:
                        entries[key] = _Written(fresh[(seg, key)], gen)
                    elif key in old:
                        entries[key] = old[key]
                written[seg] = entries
            manifest = {
                "format": FORMAT, "generation": gen, "time_unix": time.time(),
                "tile_size": snap.tile_size, "channels": snap.channels, "pending_tiles": snap.pending,
                **snap.meta,
                "tiles": {str(seg): sorted([k[0], k[1], w.gen] for k, w in entries.items())
                          for seg, entries in written.items()},
            }
            write_json(self.folder / MANIFEST, manifest, indent=None)  # every keyframe's pose: large
            _fsync_dir(self.folder)
        except (OSError, PhotomapError) as exc:
            for path in (p for pair in new_files for p in pair):
                with contextlib.suppress(OSError):
                    os.unlink(path)
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise CheckpointError(f"checkpoint {gen} not written to {self.folder}: {reason}") from None
        superseded = []
        for seg, old in self._written.items():
            now = written.get(seg)
            for key, w in old.items():
                if now is None or key not in now or now[key].gen != w.gen:
                    superseded.append(self._tile_path(seg, key, w.gen))
        gone = set(self._written) - set(written)
        self._written = written
        self.generation = gen
        for path in superseded:  # the new manifest is durable: these are no longer named
            with contextlib.suppress(OSError):
                os.unlink(path)
        for seg in gone:
            shutil.rmtree(self.folder / f"seg{seg}", ignore_errors=True)
        self.bytes_written += nbytes
        self.last_tiles = len(snap.tiles)
        self.last_pending = snap.pending
        self.last_write_s = time.perf_counter() - t0
        return manifest

    def remove(self) -> None:
        """Delete the state folder (the final outputs hold the map)."""
        shutil.rmtree(self.folder, ignore_errors=True)


def _write_file(path: str, data) -> None:
    """Write ``data`` to the new file ``path`` (no fsync: see :func:`_fsync_file`)."""
    with open(path, "wb") as f:
        f.write(data)


def _fsync_file(path: str) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: str | Path) -> None:
    """Make renames in ``folder`` durable (no-op where directories cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# ---------------------------------------------------------------------- reading back
def load_manifest(folder: str | Path) -> dict:
    """The manifest of the checkpoint in ``folder``; InputError when there is none or it is bad."""
    path = Path(folder) / MANIFEST
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"no checkpoint in {folder} ({MANIFEST} not found)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"checkpoint manifest {path} is unreadable: {exc}") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT or "tiles" not in manifest:
        raise InputError(f"checkpoint manifest {path} is not a photomap checkpoint (format {FORMAT})")
    return manifest


@dataclass
class RestoreReport:
    """What :func:`restore_mosaic` could read: tiles restored and tiles unreadable (named)."""

    restored: int = 0
    unreadable: list[str] = field(default_factory=list)


def restore_mosaic(folder: str | Path, manifest: dict, segment: int, *, store=None,
                   max_tiles_in_memory: int | None = None) -> tuple[TiledMosaic, RestoreReport]:
    """The map of ``segment`` rebuilt from the checkpoint's tiles (an overwrite-blend map; pass
    a tile ``store`` with ``max_tiles_in_memory`` to bound memory). Unreadable tiles are
    skipped and named in the report."""
    folder = Path(folder)
    params = MosaicConfig(tile_size=int(manifest["tile_size"]), channels=int(manifest["channels"]),
                          blend="overwrite", border=0, max_tiles_in_memory=max_tiles_in_memory)
    mosaic = TiledMosaic(params, store)
    report = RestoreReport()
    channels = params.channels
    for tx, ty, gen in manifest["tiles"].get(str(segment), []):
        path = folder / f"seg{segment}" / f"{tx}_{ty}_g{gen}.png"
        bgra = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if channels == 1 and bgra is not None and bgra.ndim == 3 and bgra.shape[2] == 4:
            bgra = bgra[..., [0, 3]]  # grey + alpha, which OpenCV reads as BGRA
        if bgra is None or bgra.ndim != 3 or bgra.shape[:2] != (params.tile_size,) * 2 \
                or bgra.shape[2] != channels + 1:
            report.unreadable.append(path.name)
            continue
        mosaic.set_tile((tx, ty), bgra[..., :channels], bgra[..., channels])
        report.restored += 1
    return mosaic, report
