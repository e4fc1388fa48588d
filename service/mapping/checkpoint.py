"""Crash-safe checkpoints of the full-resolution map, and recovering a run from one.

:class:`Checkpointer` is what :mod:`photomap.mapping.run_outputs` calls at each checkpoint: the
worker takes the tiles that changed since the last checkpoint
(:meth:`photomap.io.statestore.MapState.snapshot`: no pixel copied, the map copies a tile before
it changes it) and a background thread writes them and the manifest (PNG encoding, fsync), so
the worker does not wait for the disk. A checkpoint that fails (disk full, I/O error) is logged
once, the previous checkpoint stays valid, and the next interval tries again; mapping goes on.

:func:`recover_run` rebuilds a run folder's outputs (``mosaic.png``, ``mosaic_segment{N}.png``,
full-resolution ``tiles/`` when the map is larger than ``max_mosaic_px``, georeference sidecars
when the checkpoint has them, ``run.json``) from the checkpoint left by a run that was killed
(SIGKILL, power loss, OOM) or could not write its final outputs.
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Mapping

from photomap.core.mosaic import TiledMosaic
from photomap.errors import InputError, PhotomapError
from photomap.io.runfiles import parse_crs, parse_map_to_crs
from photomap.io.statestore import STATE_DIR, CheckpointError, MapState, load_manifest, restore_mosaic
from photomap.io.tilestore import DiskTileStore
from photomap.core.records import STATUSES
from photomap.io.trajectory_files import read_trajectory_csv, write_json
from photomap.mapping.outputs import remove_sidecars, write_png, write_sidecars, write_tiles

log = logging.getLogger(__name__)

__all__ = ["Checkpointer", "recover_run", "state_folder"]


def state_folder(out_dir: str | Path) -> Path:
    """Where a run in ``out_dir`` keeps its checkpointed map."""
    return Path(out_dir) / STATE_DIR


class Checkpointer:
    """Writes checkpoints of the maps into ``folder`` (see :mod:`photomap.io.statestore`).

    Parameters
    ----------
    folder : path
        The state folder (created).
    background : bool
        Write in a background thread (the worker only takes the changed tiles); False: write in
        the caller's thread (tests, the end of a run).
    max_snapshot_bytes : int
        Tile pixels copied per checkpoint at most (the rest go into the next ones).
    """

    def __init__(self, folder: str | Path, *, background: bool = True, max_snapshot_bytes: int = 16 << 20) -> None:
        self.state = MapState(folder, max_snapshot_bytes=max_snapshot_bytes)
        self.background = background
        self._thread: threading.Thread | None = None
        self.written = 0
        self.failed = 0
        self.skipped_busy = 0
        self.failing = False
        self.last_error: str | None = None
        self.snapshot_s: list[float] = []  # worker time per checkpoint (copying the changed tiles)
        self.write_s: list[float] = []  # writer time per checkpoint

    @property
    def folder(self) -> Path:
        return self.state.folder

    @property
    def busy(self) -> bool:
        """A checkpoint is being written."""
        return self._thread is not None and self._thread.is_alive()

    def save(self, mosaics: Mapping[int, TiledMosaic], meta: dict, *, wait: bool = False) -> bool:
        """Checkpoint ``mosaics`` (segment -> map) with ``meta`` in the manifest.

        Returns False when the previous checkpoint is still being written (this one is skipped:
        the next interval takes its changes too). ``wait``: write before returning. Never raises
        for a disk problem (see :attr:`last_error`).
        """
        if self.busy:
            if not wait:
                self.skipped_busy += 1
                return False
            self.wait()
        snap = self.state.snapshot(mosaics, meta)
        self.snapshot_s.append(snap.taken_s)
        if self.background and not wait:
            self._thread = threading.Thread(target=self._write, args=(snap,), name="photomap-checkpoint",
                                            daemon=True)
            self._thread.start()
        else:
            self._write(snap)
        return True

    def _write(self, snap) -> None:
        t0 = time.perf_counter()
        try:
            self.state.write(snap)
        except CheckpointError as exc:
            self.failed += 1
            self.last_error = str(exc)
            if not self.failing:
                log.error("%s; mapping goes on, the previous checkpoint stays, retrying at the next interval", exc)
            else:
                log.debug("%s", exc)
            self.failing = True
            return
        except Exception as exc:  # never let a checkpoint end the run
            self.failed += 1
            self.last_error = f"checkpoint failed: {type(exc).__name__}: {exc}"
            log.error("%s", self.last_error)
            log.debug("checkpoint failed", exc_info=True)
            return
        if self.failing:
            log.warning("checkpoint %d written: checkpoints work again", self.state.generation)
        self.failing = False
        self.last_error = None
        self.written += 1
        self.write_s.append(time.perf_counter() - t0)

    def wait(self) -> None:
        """Until the checkpoint being written is done."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def ok(self) -> bool:
        """The last checkpoint attempt succeeded (and at least one was written)."""
        return self.written > 0 and not self.failing

    def summary(self) -> dict:
        """Counts and timings for run.json ``checkpoint``."""
        def median_ms(values: list[float]) -> float | None:
            return round(1000.0 * sorted(values)[len(values) // 2], 2) if values else None
        return {"folder": self.folder.name, "written": self.written, "failed": self.failed,
                "skipped_busy": self.skipped_busy, "generation": self.state.generation,
                "last_error": self.last_error, "median_worker_ms": median_ms(self.snapshot_s),
                "median_write_ms": median_ms(self.write_s), "bytes_written": self.state.bytes_written}

    def remove(self) -> None:
        self.wait()
        self.state.remove()


# ---------------------------------------------------------------------- recovery
def recover_run(run_dir: str | Path, *, max_mosaic_px: int = 8192, max_tiles_in_memory: int = 256) -> dict:
    """Rebuild the map outputs of ``run_dir`` from its checkpoint; returns the updated summary.

    Writes ``mosaic.png`` (the segment with the most posed frames), ``mosaic_segment{N}.png``,
    ``tiles/`` (full resolution, when the map is larger than ``max_mosaic_px``), world files
    when the checkpoint carries a georeference, and ``run.json`` (``recovered`` says from which
    checkpoint, ``complete`` stays false when the run did not end). Raises InputError when the
    folder has no usable checkpoint.
    """
    run_dir = Path(run_dir)
    folder = state_folder(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"run folder not found: {run_dir}")
    manifest = load_manifest(folder)
    try:
        summary = json.loads((run_dir / "run.json").read_text(encoding="utf-8"))
        if not isinstance(summary, dict):
            summary = {}
    except (OSError, ValueError):
        summary = dict(manifest.get("summary") or {})
    order = [int(s) for s in manifest.get("order") or sorted(manifest["tiles"], key=int)]
    order += [int(s) for s in manifest["tiles"] if int(s) not in order]
    georefs = manifest.get("georeference") or {}
    maps, problems = [], []
    cache = Path(tempfile.mkdtemp(prefix="photomap-recover-"))
    try:
        rank = 0
        for seg in order:
            store = DiskTileStore(cache / f"seg{seg}")
            mosaic, report = restore_mosaic(folder, manifest, seg, store=store,
                                            max_tiles_in_memory=max_tiles_in_memory)
            if report.unreadable:
                problems.append(f"segment {seg}: {len(report.unreadable)} unreadable tile(s)")
                log.warning("segment %d: %d checkpoint tile(s) unreadable, e.g. %s", seg,
                            len(report.unreadable), report.unreadable[0])
            name = "mosaic.png" if rank == 0 else f"mosaic_segment{seg}.png"
            try:
                info = write_png(run_dir / name, mosaic, max_mosaic_px)
            except OSError as exc:
                raise PhotomapError(f"cannot write {run_dir / name}: {exc.strerror or exc}") from None
            if info is None:
                continue
            rank += 1
            remove_sidecars(run_dir, name)
            info["segment"] = seg
            if info["scale"] < 1.0:
                tiles = run_dir / ("tiles" if info["file"] == "mosaic.png" else f"tiles_segment{seg}")
                write_tiles(tiles, mosaic)
                info["tiles"], info["tile_size"] = tiles.name, mosaic.tile_size
            geo = georefs.get(str(seg))
            if geo and geo.get("crs") and geo.get("map_to_crs") is not None:
                ref = SimpleNamespace(map_to_crs=parse_map_to_crs(geo["map_to_crs"]), epsg=parse_crs(geo["crs"]))
                info["georeference"] = {**geo, "world_file": write_sidecars(run_dir, info, ref)}
            maps.append(info)
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    try:  # the counts of the trajectory that survived (run.json may be of another checkpoint)
        rows = read_trajectory_csv(run_dir / "trajectory.csv")
    except InputError:
        rows = None
    if rows is not None:
        counts = {s: sum(r.status == s for r in rows) for s in STATUSES}
        summary.update({"registered": counts["reference"] + counts["registered"],
                        "low_confidence": counts["low_confidence"], "corrupt": counts["corrupt"],
                        "dropped": counts["dropped"], "skipped": counts["low_confidence"] + counts["corrupt"]})
    summary["mosaics"] = maps
    summary["recovered"] = {"generation": manifest.get("generation"), "time_unix": manifest.get("time_unix"),
                            "frames_in": manifest.get("frames_in"), "problems": problems}
    summary.setdefault("complete", False)
    if maps and (maps[0].get("georeference") or {}).get("crs"):
        summary["georeference"] = maps[0]["georeference"]
    write_json(run_dir / "run.json", summary)
    (run_dir / "preview.png").unlink(missing_ok=True)
    return summary
