"""Preflight of a run's output folder: before any frame is read, not after the whole flight.

:func:`check_output_dir` refuses (one :class:`~photomap.errors.OutputError` line) a path that is a
file, a folder that cannot be created or written (a probe file is created, fsynced and removed),
less free space than a floor, or a folder that still holds the checkpoint of a run that did not
finish (recover it first); it warns when the free space is below an estimate for the expected
number of frames.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from pathlib import Path

from photomap.errors import OutputError

log = logging.getLogger(__name__)

__all__ = ["check_output_dir", "BYTES_PER_FRAME"]

BYTES_PER_FRAME = 200_000
"""Disk a run needs per input frame, estimated (bytes): the checkpointed full-resolution map,
mosaic.png and tiles/ of a 640x480 flight measured about 0.1 MB per frame of new ground
(tools/bench_memory.py), with margin."""


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


def check_output_dir(out_dir: str | Path, *, expected_frames: int | None = None, min_free_mb: float = 50.0,
                     bytes_per_frame: int = BYTES_PER_FRAME, state_dir: str = "checkpoint") -> dict:
    """Check (and create) ``out_dir`` for a run; returns ``{"free_mb", "estimate_mb"}``.

    Raises
    ------
    OutputError
        ``out_dir`` is a file or cannot be created; a probe file cannot be written there
        (read-only, permissions, disk full); less than ``min_free_mb`` MB are free; or it holds
        an unfinished run's checkpoint (``state_dir/manifest.json``).
    """
    path = Path(out_dir).expanduser()
    if path.exists() and not path.is_dir():
        raise OutputError(f"output folder {path} is a file, not a folder: choose another --out")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise OutputError(f"output folder {path}: a parent is a file, not a folder") from None
    except OSError as exc:
        raise OutputError(f"cannot create the output folder {path}: {_reason(exc)}") from None
    if (path / state_dir / "manifest.json").is_file():
        raise OutputError(f"{path} holds the checkpoint of a run that did not finish: recover its map "
                          f"with `photomap recover {path} --remove-checkpoint` or choose another --out")
    fd, probe = None, None
    try:
        fd, probe = tempfile.mkstemp(dir=path, prefix=".photomap-probe-")
        os.write(fd, b"photomap")
        os.fsync(fd)
    except OSError as exc:
        raise OutputError(f"output folder {path} is not writable: {_reason(exc)}") from None
    finally:
        if fd is not None:
            os.close(fd)
        if probe is not None:
            try:
                os.unlink(probe)
            except OSError:
                pass
    free_mb = shutil.disk_usage(path).free / 1e6
    if free_mb < min_free_mb:
        raise OutputError(f"only {free_mb:.0f} MB free in {path}: at least {min_free_mb:.0f} MB are needed "
                          f"(output.min_free_mb)")
    estimate_mb = expected_frames * bytes_per_frame / 1e6 if expected_frames else None
    if estimate_mb is not None and free_mb < estimate_mb:
        log.warning("only %.0f MB free in %s, about %.0f MB may be needed for %d frames: the map is "
                    "checkpointed, but it may not all fit", free_mb, path, estimate_mb, expected_frames)
    return {"free_mb": free_mb, "estimate_mb": estimate_mb}
