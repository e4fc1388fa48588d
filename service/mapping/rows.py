"""The run's trajectory rows, one per input frame, held as columns (owned by the mapping worker).

A long flight keeps a row per frame for hours. As :class:`~photomap.core.records.PoseRow`
objects a row cost ~0.5 KB of small Python objects (the row, its floats, a pose array, an
``extra`` dict) that live as long as the run, scattered among each frame's temporaries, and a
loop-closure correction re-posed the rows one by one in Python (O(frames) each time).
:class:`TrajectoryRows` keeps them as NumPy columns (~80 bytes a row): a correction or a join of
segments is one vectorised assignment, and a checkpoint's copy of the rows is a few array copies.

Readers get :class:`RowView` objects, which read (and, for the worker, write) one row's columns
and quack like a ``PoseRow`` for the trajectory writers (``frame``, ``t``, ``M``, ``confidence``,
``status``, ``segment``, ``extra``, ``xy``, ``glued``). A row's ``extra`` mapping is replaced, never
changed in place: rows with the same extras share one read-only mapping.

Conventions: as :class:`~photomap.core.records.PoseRow` (``M``: 2x3, frame pixels -> map pixels
of the row's segment; None when the frame has no pose).
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Iterator, Mapping, overload

import numpy as np

from photomap.core.records import GLUED, STATUSES

__all__ = ["TrajectoryRows", "RowView"]

_CODE = {status: code for code, status in enumerate(STATUSES)}
_GLUED_CODES = np.array([s in GLUED for s in STATUSES])
_NO_EXTRA: Mapping = MappingProxyType({})


class RowView:
    """One row of a :class:`TrajectoryRows` (read and written through to its columns)."""

    __slots__ = ("_rows", "_i")

    def __init__(self, rows: TrajectoryRows, i: int) -> None:
        self._rows, self._i = rows, i

    @property
    def frame(self) -> int:
        return int(self._rows._frame[self._i])

    @property
    def t(self) -> float:
        return float(self._rows._t[self._i])

    @property
    def M(self) -> np.ndarray | None:
        """A copy of the pose (2, 3), or None."""
        rows = self._rows
        return rows._M[self._i].copy() if rows._posed[self._i] else None

    @M.setter
    def M(self, pose: np.ndarray | None) -> None:
        rows = self._rows
        if pose is None:
            rows._posed[self._i] = False
        else:
            rows._M[self._i] = np.asarray(pose, np.float64)[:2]
            rows._posed[self._i] = True

    @property
    def confidence(self) -> float:
        return float(self._rows._confidence[self._i])

    @confidence.setter
    def confidence(self, value: float) -> None:
        self._rows._confidence[self._i] = value

    @property
    def status(self) -> str:
        return STATUSES[self._rows._status[self._i]]

    @status.setter
    def status(self, value: str) -> None:
        self._rows._status[self._i] = _CODE[value]

    @property
    def segment(self) -> int:
        return int(self._rows._segment[self._i])

    @segment.setter
    def segment(self, value: int) -> None:
        self._rows._segment[self._i] = value

    @property
    def extra(self) -> Mapping:
        """Further columns (read-only: assign a new mapping to change them)."""
        return self._rows._extra[self._i]

    @extra.setter
    def extra(self, value: Mapping) -> None:
        self._rows._extra[self._i] = self._rows._shared(value)

    @property
    def xy(self) -> None:
        return None  # writers compute the centre from M and the frame size

    @property
    def glued(self) -> bool:
        rows = self._rows
        return bool(rows._posed[self._i] and _GLUED_CODES[rows._status[self._i]])


class TrajectoryRows:
    """Rows appended in frame order, one per input frame (gaps included), as columns."""

    def __init__(self, capacity: int = 1024) -> None:
        self._n = 0
        self._alloc(max(16, int(capacity)))
        self._extra: list[Mapping] = []
        self._interned: dict[tuple, Mapping] = {}  # shared categorical extras (e.g. {"method": "ifmi"})

    def _alloc(self, capacity: int) -> None:
        def grow(old: np.ndarray | None, shape: tuple, dtype, fill) -> np.ndarray:
            new = np.full(shape, fill, dtype)
            if old is not None:
                new[:self._n] = old[:self._n]
            return new

        self._frame = grow(getattr(self, "_frame", None), (capacity,), np.int64, -1)
        self._t = grow(getattr(self, "_t", None), (capacity,), np.float64, np.nan)
        self._M = grow(getattr(self, "_M", None), (capacity, 2, 3), np.float64, np.nan)
        self._posed = grow(getattr(self, "_posed", None), (capacity,), bool, False)
        self._confidence = grow(getattr(self, "_confidence", None), (capacity,), np.float64, np.nan)
        self._status = grow(getattr(self, "_status", None), (capacity,), np.int8, 0)
        self._segment = grow(getattr(self, "_segment", None), (capacity,), np.int32, 0)

    def _shared(self, extra: Mapping | None) -> Mapping:
        """``extra`` as a read-only mapping; categorical extras (all values strings, e.g. the
        method) are one mapping shared by every row alike."""
        if not extra:
            return _NO_EXTRA
        items = tuple(extra.items())
        if all(isinstance(v, str) for _, v in items):
            return self._interned.setdefault(items, MappingProxyType(dict(items)))
        return MappingProxyType(dict(items))

    def append(self, frame: int, t: float, M: np.ndarray | None, confidence: float = np.nan,
               status: str = "registered", segment: int = 0, extra: Mapping | None = None) -> RowView:
        """Add the row of frame ``frame`` (after the last one); returns its view."""
        if self._n == len(self._frame):
            self._alloc(2 * self._n)
        i = self._n
        self._n += 1
        self._frame[i], self._t[i], self._confidence[i] = frame, t, confidence
        self._status[i], self._segment[i] = _CODE[status], segment
        self._posed[i] = M is not None
        if M is not None:
            self._M[i] = np.asarray(M, np.float64)[:2]
        self._extra.append(self._shared(extra))
        return RowView(self, i)

    def __len__(self) -> int:
        return self._n

    @overload
    def __getitem__(self, i: int) -> RowView: ...

    @overload
    def __getitem__(self, i: slice) -> list[RowView]: ...

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [RowView(self, k) for k in range(*i.indices(self._n))]
        k = int(i) + self._n if i < 0 else int(i)
        if not 0 <= k < self._n:
            raise IndexError(f"row {i} of {self._n}")
        return RowView(self, k)

    def __iter__(self) -> Iterator[RowView]:
        return (RowView(self, k) for k in range(self._n))

    def __reversed__(self) -> Iterator[RowView]:
        return (RowView(self, k) for k in range(self._n - 1, -1, -1))

    # ------------------------------------------------------------------ columns, bulk changes
    @property
    def frames(self) -> np.ndarray:
        """Frame indices (n,), read-only view."""
        v = self._frame[:self._n]
        v.flags.writeable = False
        return v

    def glued_mask(self, segment: int | None = None) -> np.ndarray:
        """(n,) bool: rows whose pose is part of the map (of ``segment``, if given)."""
        n = self._n
        mask = self._posed[:n] & _GLUED_CODES[self._status[:n]]
        return mask if segment is None else mask & (self._segment[:n] == segment)

    def glued(self, segment: int, start: int = 0) -> list[RowView]:
        """The rows of ``segment`` whose pose is part of its map, from row ``start`` on."""
        return [RowView(self, k) for k in (start + np.flatnonzero(self.glued_mask(segment)[start:])).tolist()]

    def poses(self, mask: np.ndarray) -> np.ndarray:
        """The poses (k, 2, 3) of the rows selected by ``mask`` ((n,) bool, or row indices; a copy)."""
        return self._M[:self._n][mask].copy()

    def confidences(self, mask: np.ndarray) -> np.ndarray:
        """The confidences of the rows selected by ``mask`` (a copy)."""
        return self._confidence[:self._n][mask].copy()

    def segment_counts(self) -> dict[int, int]:
        """Glued rows per segment."""
        seg = self._segment[:self._n][self.glued_mask()]
        values, counts = np.unique(seg, return_counts=True)
        return dict(zip(values.tolist(), counts.tolist()))

    def status_counts(self) -> dict[str, int]:
        """Rows per status (every status, zeros included)."""
        counts = np.bincount(self._status[:self._n], minlength=len(STATUSES))
        return {s: int(c) for s, c in zip(STATUSES, counts)}

    def set_poses(self, frames: np.ndarray, poses: np.ndarray, segment: int) -> int:
        """Re-pose the posed rows of ``segment`` among ``frames`` ((k,), any order) with
        ``poses`` ((k, 2, 3) or (k, 3, 3)); frames without a row are ignored. Returns how many
        rows changed."""
        frames = np.asarray(frames, np.int64)
        n = self._n
        if n == 0 or len(frames) == 0:
            return 0
        col = self._frame[:n]
        order = None if np.all(col[1:] >= col[:-1]) else np.argsort(col, kind="stable")  # appended in order
        ordered = col if order is None else col[order]
        at = np.minimum(np.searchsorted(ordered, frames), n - 1)
        ok = ordered[at] == frames
        rows = (at if order is None else order[at])[ok]
        sel = self._posed[rows] & (self._segment[rows] == segment)
        self._M[rows[sel]] = np.asarray(poses, np.float64)[ok][sel][:, :2]
        return int(sel.sum())

    def transform_segment(self, segment: int, transform: np.ndarray, into: int) -> None:
        """Rows of ``segment`` move to segment ``into``; their poses are composed with
        ``transform`` (3x3: map px of ``segment`` -> map px of ``into``)."""
        n = self._n
        rows = np.flatnonzero(self._segment[:n] == segment)
        posed = rows[self._posed[rows]]
        t = np.asarray(transform, np.float64)
        self._M[posed] = np.einsum("ij,kjl->kil", t[:2, :2], self._M[posed])
        self._M[posed, :, 2] += t[:2, 2]
        self._segment[rows] = into

    def index_of(self, frame: int) -> int | None:
        """The row of ``frame``, or None."""
        n = self._n
        if n == 0:
            return None
        k = int(frame - self._frame[0])
        if 0 <= k < n and self._frame[k] == frame:
            return k
        hits = np.flatnonzero(self._frame[:n] == frame)
        return int(hits[-1]) if len(hits) else None

    def copy(self) -> TrajectoryRows:
        """An independent copy (the checkpoint writer's): the columns copied, the extras shared."""
        other = TrajectoryRows.__new__(TrajectoryRows)
        other._n = n = self._n
        other._frame, other._t = self._frame[:n].copy(), self._t[:n].copy()
        other._M, other._posed = self._M[:n].copy(), self._posed[:n].copy()
        other._confidence, other._status = self._confidence[:n].copy(), self._status[:n].copy()
        other._segment = self._segment[:n].copy()
        other._extra = list(self._extra)
        other._interned = dict(self._interned)
        return other
