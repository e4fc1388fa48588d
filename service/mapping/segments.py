"""The maps of a run, one per segment, and their life: started, retired, spilled, dropped, joined.

:class:`SegmentMaps` owns the maps (a :class:`~photomap.core.mosaic.TiledMosaic` per segment),
the tile stores they spill to when ``mosaic.max_tiles_in_memory`` bounds memory, and the run's
cache folder (``mosaic.cache_dir``, or a temporary one removed at the end). The pipeline's
worker thread calls it: a map is made with its segment's first painted frame; when the tracker
starts a segment the others are retired (a segment left with a single posed frame is dropped;
the others, with a tile cap, move their tiles to the store a few a frame); a joined segment's
map goes (its kept frames are re-rendered into the map it joined). The trajectory rows are
read, never written, here.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from photomap.config import MosaicConfig
from photomap.core.mosaic import TiledMosaic
from photomap.io.tilestore import DiskTileStore, WriteBehindTileStore
from photomap.mapping.loopclosure import Join
from photomap.mapping.rows import RowView, TrajectoryRows

# tiles of a map the camera left moved to the tile store per frame (all at once: 256 tiles took the
# worker 200 ms, waiting for the tile writer)
_SPILL_TILES_PER_FRAME = 8


class SegmentMaps:
    """The maps of the segments of one run (worker thread only).

    Parameters
    ----------
    cfg : MosaicConfig
        Tile size, tile cap (``max_tiles_in_memory``) and ``cache_dir``.
    rows : TrajectoryRows
        The run's trajectory (read: which frames each segment glued).
    """

    def __init__(self, cfg: MosaicConfig, rows: TrajectoryRows) -> None:
        self.cfg = cfg
        self._rows = rows
        self.mosaics: dict[int, TiledMosaic] = {}
        self.tile_stores: dict[int, WriteBehindTileStore] = {}  # segment -> where its map spills
        self._cache_dir: Path | None = None
        self._own_cache = False
        self._segment_start: dict[int, int] = {}  # segment -> position in the rows where it started
        self._kept: set[int] = set()  # segments known to hold more than one posed frame
        self._spilling: set[int] = set()  # segments left by the camera whose tiles go to the store

    def cache(self) -> Path:
        """The run's cache folder (configured, or a temporary one removed at the end)."""
        if self._cache_dir is None:
            if self.cfg.cache_dir:
                self._cache_dir = Path(self.cfg.cache_dir).expanduser()
                self._cache_dir.mkdir(parents=True, exist_ok=True)
            else:
                self._cache_dir = Path(tempfile.mkdtemp(prefix="photomap-cache-"))
                self._own_cache = True
        return self._cache_dir

    def mosaic(self, segment: int) -> TiledMosaic:
        """The map of ``segment`` (made empty the first time)."""
        if segment not in self.mosaics:
            store = None
            if self.cfg.max_tiles_in_memory:
                # spilled tiles are written by a thread: the worker never waits for the disk
                # its read-ahead counts in the map's tile cap: at most a quarter of it
                store = self.tile_stores[segment] = WriteBehindTileStore(
                    DiskTileStore(self.cache() / f"segment{segment}"),
                    max_ready=min(WriteBehindTileStore.MAX_READY, self.cfg.max_tiles_in_memory // 4))
            self.mosaics[segment] = TiledMosaic(self.cfg, store)
        return self.mosaics[segment]

    def retire(self, current: int) -> list[tuple[int, list[RowView]]]:
        """The tracker started segment ``current``: a segment it left with a single posed frame
        (nothing registered to its reference) is dropped, so featureless or black video cannot
        pile up maps; the others are spilled to the tile store when one bounds memory (only the
        current map holds tiles in memory). Returns the dropped segments with their glued rows
        (the caller un-poses them)."""
        self._segment_start[current] = max(0, len(self._rows) - 1)
        dropped = []
        for seg in list(self.mosaics):
            if seg == current:
                continue
            if seg not in self._kept:
                glued = self._rows.glued(seg, self._segment_start.get(seg, 0))
                if len(glued) <= 1:
                    self._drop(seg)
                    dropped.append((seg, glued))
                    continue
                self._kept.add(seg)
            if self.cfg.max_tiles_in_memory is not None:
                self._spilling.add(seg)  # a few tiles a frame: spill_retired
        return dropped

    def spill_retired(self, current: int) -> None:
        """Move a few tiles of the maps the camera left (``current`` is the segment it is in) to
        the tile store (only the current map holds tiles in memory once they are all gone, its
        store the only ones read ahead)."""
        if not self._spilling:
            return
        seg = min(self._spilling)  # one map a frame
        mosaic = self.mosaics.get(seg)
        if mosaic is None or seg == current or not mosaic.spill(_SPILL_TILES_PER_FRAME):
            self._spilling.discard(seg)  # joined, dropped, current again, or done
            if seg != current and seg in self.tile_stores:
                self.tile_stores[seg].drop_read_ahead()  # read for frames that went elsewhere

    def _drop(self, seg: int) -> None:
        """Forget the map of ``seg``, its tile store and its cache folder."""
        self.mosaics.pop(seg, None)
        if seg in self.tile_stores:
            self.tile_stores.pop(seg).flush()  # its writes done before its folder goes
        if self.cfg.max_tiles_in_memory and self._cache_dir is not None:
            shutil.rmtree(self._cache_dir / f"segment{seg}", ignore_errors=True)
        self._segment_start.pop(seg, None)

    def join(self, join: Join) -> None:
        """Segment ``join.segment`` is part of ``join.into``: its map goes (its kept frames are
        re-rendered into the map of ``join.into``, made here if it has none yet)."""
        self.mosaic(join.into)
        self.mosaics.pop(join.segment, None)

    def largest(self) -> list[int]:
        """Segments with a map, the one with the most posed frames first."""
        glued = self._rows.segment_counts()
        counts = {s: glued.get(s, 0) for s in self.mosaics}
        return sorted(counts, key=lambda s: -counts[s])

    def close(self) -> None:
        """At the end of the run: the tile stores' writes done, a temporary cache folder removed."""
        for store in self.tile_stores.values():
            store.flush()  # its writes done before the folder goes
        if self._own_cache and self._cache_dir is not None:
            shutil.rmtree(self._cache_dir, ignore_errors=True)
