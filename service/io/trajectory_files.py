"""Trajectory files of a run (``trajectory.csv``, ``trajectory.tum``, JSON) and ``groundtruth.csv``.

Every writer is atomic: it writes a temporary file in the target's folder and ``os.replace``-s it
over the target, so a periodic checkpoint of a live run never leaves a half-written file.
Readers accept extra columns and raise :class:`InputError` with the file and line on bad input.
Formats: README, "What a run writes"; conventions: :mod:`photomap.geometry`.
"""

from __future__ import annotations

import contextlib
import csv
import ctypes
import io
import json
import logging
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any, Iterable, Sequence

import numpy as np

from photomap.errors import InputError
from photomap.core.records import GroundTruth, PoseRow, STATUSES
from photomap.geometry import frame_centre, pose_angle_deg, pose_scale

log = logging.getLogger(__name__)

M_COLUMNS = ("m00", "m01", "m02", "m10", "m11", "m12")
TRAJECTORY_COLUMNS = ("frame", "t", "x", "y", "angle_deg", "scale", "confidence", "status",
                      *M_COLUMNS, "segment")
H_COLUMNS = tuple(f"h{i}{j}" for i in range(3) for j in range(3))
GROUNDTRUTH_COLUMNS = ("frame", "t", "x", "y", "yaw_deg", "scale", "roll_deg", "pitch_deg",
                       "alt_m", *H_COLUMNS)
_GROUNDTRUTH_REQUIRED = ("frame", "t", *H_COLUMNS)


# --- atomic writes ------------------------------------------------------------------------

@contextlib.contextmanager
def atomic_file(path: str | Path, mode: str = "wb", *, sync: bool = True) -> Iterator[IO]:
    """A new file (``mode`` "wb", or "w": UTF-8 text, newlines as written) that replaces ``path``
    when the block ends without an error (a temporary file in the same folder, ``os.replace``;
    after an error it is removed and ``path`` is untouched). ``sync``: fsync before the rename
    (durable after power loss; without it a kill still never leaves a partial file under
    ``path``). Large outputs are written piece by piece: no copy of the whole file in memory."""
    path = os.fspath(path)  # not a Path: pathlib interns every name it parses
    folder, name = os.path.split(path)
    fd, tmp = tempfile.mkstemp(dir=folder or ".", prefix=f".{name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode, **({} if "b" in mode else {"encoding": "utf-8", "newline": ""})) as f:
            yield f
            if sync:
                f.flush()
                os.fsync(f.fileno())
        mode_bits = os.stat(path).st_mode & 0o777 if os.path.exists(path) else 0o644
        os.chmod(tmp, mode_bits)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def sync_filesystem(path: str | Path) -> None:
    """Flush every file written on the filesystem that holds ``path`` to its disk (Linux
    ``syncfs``; ``os.sync`` elsewhere). Thousands of files written with ``sync=False`` become
    durable with this one call instead of an fsync (a journal commit) each; temporaries removed
    before it (GDAL's) are never written out. OSError when the disk reports an error."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        os.sync()
        return
    try:
        syncfs = getattr(ctypes.CDLL(None, use_errno=True), "syncfs", None)
        if syncfs is None:
            os.sync()
        elif syncfs(fd) != 0:
            err = ctypes.get_errno()
            raise OSError(err, os.strerror(err), os.fspath(path))
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | Path, data: bytes, *, sync: bool = True) -> None:
    """Write ``data`` to ``path`` atomically (:func:`atomic_file`)."""
    with atomic_file(path, "wb", sync=sync) as f:
        f.write(data)


def atomic_write_text(path: str | Path, text: str, *, sync: bool = True) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically (:func:`atomic_file`)."""
    atomic_write_bytes(path, text.encode("utf-8"), sync=sync)


def _jsonable(obj: Any) -> Any:
    """numpy values to Python ones, NaN/inf to None, tuples to lists, Paths to str."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in (obj.tolist() if isinstance(obj, np.ndarray) else obj)]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(path: str | Path, obj: Any, *, indent: int | None = 2) -> None:
    """Write ``obj`` as JSON, atomically (NaN/inf become ``null``; numpy is accepted); indented
    for people to read, or compact (``indent=None``: json's C encoder, ~2x faster, ~40 % smaller)
    for large machine-read files."""
    atomic_write_text(path, json.dumps(_jsonable(obj), indent=indent, allow_nan=False) + "\n")


# --- trajectory.csv -----------------------------------------------------------------------

def _fmt(value: float | None, spec: str) -> str:
    if value is None or not math.isfinite(value):
        return ""
    return format(float(value), spec)


def _centre_xy(row: PoseRow, centre: tuple[float, float] | None) -> tuple[float, float] | None:
    if row.M is None:
        return None
    if centre is not None:
        M = np.asarray(row.M, dtype=float)[:2]
        p = M[:, :2] @ np.asarray(centre) + M[:, 2]
        return float(p[0]), float(p[1])
    if row.xy is None:
        raise ValueError(f"frame {row.frame}: give frame_size or the row's xy")
    return row.xy


def _fmt_extra(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, (float, np.floating)):
        return repr(float(v)) if math.isfinite(v) else ""
    return str(v)


_CHUNK_ROWS = 2048  # rows formatted at a time: a long flight's file is never all in memory


def _trajectory_csv_chunks(rows: Iterable[PoseRow], frame_size: tuple[int, int] | None) -> Iterator[str]:
    """The text of ``trajectory.csv``, a header then ``_CHUNK_ROWS`` rows at a time."""
    rows = list(rows) if isinstance(rows, Iterator) else rows  # iterated twice
    centre = frame_centre(*frame_size) if frame_size is not None else None
    extra_cols: list[str] = []
    for r in rows:
        extra_cols += [k for k in r.extra if k not in extra_cols and k not in TRAJECTORY_COLUMNS]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*TRAJECTORY_COLUMNS, *extra_cols])
    for n, r in enumerate(rows, 1):
        if r.status not in STATUSES:
            raise ValueError(f"frame {r.frame}: status {r.status!r} is not one of {STATUSES}")
        if r.M is None:
            derived, m = [""] * 4, [""] * 6
        else:
            M = np.asarray(r.M, dtype=float)[:2].reshape(2, 3)
            x, y = _centre_xy(r, centre)
            derived = [_fmt(x, ".6f"), _fmt(y, ".6f"), _fmt(pose_angle_deg(M), ".6f"),
                       _fmt(pose_scale(M), ".8f")]
            m = [repr(float(v)) for v in M.ravel()]
        extras = [_fmt_extra(r.extra.get(k)) for k in extra_cols]
        w.writerow([int(r.frame), _fmt(r.t, ".6f"), *derived, _fmt(r.confidence, ".6g"),
                    r.status, *m, int(r.segment), *extras])
        if n % _CHUNK_ROWS == 0:
            yield buf.getvalue()
            buf.seek(0)
            buf.truncate()
    yield buf.getvalue()


def format_trajectory_csv(rows: Iterable[PoseRow], frame_size: tuple[int, int] | None = None) -> str:
    """The text of ``trajectory.csv`` (see :func:`write_trajectory_csv`)."""
    return "".join(_trajectory_csv_chunks(rows, frame_size))


def write_trajectory_csv(path: str | Path, rows: Iterable[PoseRow],
                         frame_size: tuple[int, int] | None = None) -> None:
    """Write ``trajectory.csv`` atomically: one row per input frame.

    Parameters
    ----------
    path : path
        Target file.
    rows : iterable of PoseRow
        In frame order. Rows without ``M`` get empty pose fields. Keys of ``extra`` become
        columns after the standard ones (in order of first appearance).
    frame_size : (width, height), optional
        Input frame size in pixels; ``x, y`` are then ``M`` applied to ``((w-1)/2, (h-1)/2)``.
        Without it every posed row must carry ``xy``.
    """
    with atomic_file(path, "w") as f:
        for chunk in _trajectory_csv_chunks(rows, frame_size):
            f.write(chunk)


def read_text_input(path: str | Path, what: str, *, reason=str) -> str:
    """The UTF-8 text of the input file ``path`` (``what`` names it in the error), or one
    :class:`InputError` line: not found, or unreadable (``reason`` of the exception)."""
    path = Path(path)
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{what} not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read {what} {path}: {reason(exc)}") from None


def _open_csv(path: str | Path, what: str) -> tuple[list[str], list[tuple[int, dict]]]:
    path = Path(path)
    text = read_text_input(path, what)
    reader = csv.DictReader(io.StringIO(text))
    header = [h.strip() for h in (reader.fieldnames or [])]
    if not header:
        raise InputError(f"{what} {path} is empty")
    reader.fieldnames = header
    return header, [(i + 2, row) for i, row in enumerate(reader)]


def _check_header(path: str | Path, what: str, header: Sequence[str],
                  required: Sequence[str]) -> None:
    missing = [c for c in required if c not in header]
    if missing:
        raise InputError(f"{what} {path} lacks column(s) {', '.join(missing)}")


def _parse_extra(text: str | None) -> Any:
    if text is None or text.strip() == "":
        return None
    try:
        return float(text)
    except ValueError:
        return text


def read_trajectory_csv(path: str | Path) -> list[PoseRow]:
    """Read a run's ``trajectory.csv`` into :class:`PoseRow` s (``xy`` filled from ``x, y``).

    Extra columns go to ``extra`` (numbers as float, empty as None, else the text).
    Raises InputError for a missing file, a missing column or a malformed row.
    """
    header, records = _open_csv(path, "trajectory")
    _check_header(path, "trajectory", header, TRAJECTORY_COLUMNS)
    extra_cols = [c for c in header if c not in TRAJECTORY_COLUMNS]
    rows = []
    for line, rec in records:
        try:
            status = (rec["status"] or "").strip()
            if status not in STATUSES:
                raise ValueError(f"status {status!r} is not one of {', '.join(STATUSES)}")
            m = [(rec[c] or "").strip() for c in M_COLUMNS]
            if all(m):
                M = np.array([float(v) for v in m]).reshape(2, 3)
            elif not any(m):
                M = None
            else:
                raise ValueError("pose fields m00..m12 are partly empty")
            x, y = (rec["x"] or "").strip(), (rec["y"] or "").strip()
            conf = (rec["confidence"] or "").strip()
            seg = (rec["segment"] or "").strip()
            t = (rec["t"] or "").strip()  # empty for a frame never received (a dropped row)
            rows.append(PoseRow(
                frame=int(rec["frame"]), t=float(t) if t else math.nan, M=M,
                confidence=float(conf) if conf else math.nan, status=status,
                segment=int(seg) if seg else 0,
                extra={c: _parse_extra(rec.get(c)) for c in extra_cols},
                xy=(float(x), float(y)) if x and y else None))
        except (TypeError, ValueError) as exc:
            raise InputError(f"trajectory {path}, line {line}: {exc}") from None
    return rows


# --- trajectory.tum -----------------------------------------------------------------------

def largest_segment(rows: Iterable[PoseRow]) -> int | None:
    """The segment with the most glued rows (the lowest id on a tie), None if none is glued."""
    counts: dict[int, int] = {}
    for r in rows:
        if r.glued:
            counts[r.segment] = counts.get(r.segment, 0) + 1
    return min(counts, key=lambda s: (-counts[s], s)) if counts else None


def _tum_chunks(rows: Iterable[PoseRow], frame_size: tuple[int, int] | None,
                segment: int | None, skipped: list[int] | None = None) -> Iterator[str]:
    """The text of ``trajectory.tum``, a header then ``_CHUNK_ROWS`` lines at a time; the frames
    left out because their time does not increase are appended to ``skipped`` (or, without it,
    said in one warning at the end)."""
    warn = skipped is None
    skipped = [] if skipped is None else skipped
    rows = list(rows) if isinstance(rows, Iterator) else rows  # iterated twice
    seg = largest_segment(rows) if segment is None else segment
    centre = frame_centre(*frame_size) if frame_size is not None else None
    lines = [f"# t x y z qx qy qz qw | photomap segment {seg}: map pixels, x right, y down, "
             "z = 0, yaw about z = angle_deg (scale dropped)\n"]
    last_t = -math.inf
    for r in rows:
        if not r.glued or r.segment != seg:
            continue
        if not r.t > last_t:
            skipped.append(r.frame)
            continue
        last_t = r.t
        x, y = _centre_xy(r, centre)
        half = math.radians(pose_angle_deg(np.asarray(r.M, dtype=float))) / 2.0
        lines.append(f"{r.t:.6f} {x:.6f} {y:.6f} 0.0 0.0 0.0 {math.sin(half):.9f} "
                     f"{math.cos(half):.9f}\n")
        if len(lines) >= _CHUNK_ROWS:
            yield "".join(lines)
            lines = []
    yield "".join(lines)
    if warn and skipped:
        log.warning(tum_skipped_message(skipped))


def tum_skipped_message(frames: Sequence[int]) -> str:
    """One line naming the frames a TUM trajectory leaves out (their times do not increase)."""
    shown = ", ".join(str(f) for f in list(frames)[:5]) + (", ..." if len(frames) > 5 else "")
    return (f"TUM: {len(frames)} frame(s) skipped (frames {shown}): their times do not increase "
            "(e.g. capture times of one-second resolution)")


def format_tum(rows: Iterable[PoseRow], frame_size: tuple[int, int] | None = None,
               segment: int | None = None) -> str:
    """The text of ``trajectory.tum`` (see :func:`write_tum`)."""
    return "".join(_tum_chunks(rows, frame_size, segment))


def write_tum(path: str | Path, rows: Iterable[PoseRow], frame_size: tuple[int, int] | None = None,
              segment: int | None = None, skipped: list[int] | None = None) -> None:
    """Write the glued poses of one segment as a TUM trajectory (``evo`` reads it), atomically.

    One line ``t x y z qx qy qz qw`` per ``reference``/``registered`` frame after a ``#`` header.
    ``x, y`` are the frame centre in map pixels written as-is, so y points down; with z = 0 and z
    pointing into the ground the frame is still right-handed, and ``yaw`` (about z) is
    ``angle_deg``, positive from x towards y. The scale of the pose is not representable and is
    dropped (use ``evo_ape --align --correct_scale``). Frames whose ``t`` does not increase are
    skipped: with ``skipped`` (a list) their frame numbers are appended to it for the caller to
    report, else one warning with their count is logged.

    Parameters
    ----------
    segment : int, optional
        Map segment to write (each has its own map frame); default: the one with the most
        glued frames.
    frame_size : (width, height), optional
        As for :func:`write_trajectory_csv`.
    """
    with atomic_file(path, "w") as f:
        for chunk in _tum_chunks(rows, frame_size, segment, skipped):
            f.write(chunk)


# --- groundtruth.csv ----------------------------------------------------------------------

def read_groundtruth(path: str | Path) -> GroundTruth:
    """Read ``groundtruth.csv`` of ``photomap simulate``.

    Needs ``frame``, ``t`` and ``h00..h22`` (the 3x3 frame -> terrain matrix); every other column
    that holds numbers is kept in ``columns``. Raises InputError on a missing file or column or a
    malformed row.
    """
    header, records = _open_csv(path, "ground truth")
    _check_header(path, "ground truth", header, _GROUNDTRUTH_REQUIRED)
    if not records:
        raise InputError(f"ground truth {path} has no rows")
    cols: dict[str, list] = {c: [] for c in header}
    for line, rec in records:
        for c in header:
            v = _parse_extra(rec.get(c))
            if c in _GROUNDTRUTH_REQUIRED and not isinstance(v, float):
                raise InputError(f"ground truth {path}, line {line}: column {c} is not a number")
            cols[c].append(v if isinstance(v, float) else math.nan)
    H = np.column_stack([cols[c] for c in H_COLUMNS]).reshape(-1, 3, 3)
    return GroundTruth(frame=np.asarray(cols["frame"]).astype(int), t=np.asarray(cols["t"]), H=H,
                       columns={c: np.asarray(v) for c, v in cols.items()
                                if not np.isnan(np.asarray(v)).all()})
