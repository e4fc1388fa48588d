"""Per-frame records of a run: the trajectory rows and a simulated flight's ground truth.

Conventions: :mod:`photomap.geometry` (a pose maps frame pixels to map pixels of its segment).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["STATUSES", "GLUED", "PoseRow", "GroundTruth"]

STATUSES = ("reference", "registered", "low_confidence", "dropped", "corrupt")
"""Allowed values of a row's ``status``."""

GLUED = frozenset({"reference", "registered"})
"""Statuses whose pose is part of the map (the only ones evaluated and written to TUM)."""

@dataclass(slots=True)
class PoseRow:
    """One input frame of a run (slots: a reader makes one per row of a file; the mapping worker
    keeps its rows as columns, :mod:`photomap.mapping.rows`).

    Parameters
    ----------
    frame : int
        Input frame index.
    t : float
        Time of the frame, seconds (the run's time base).
    M : ndarray (2, 3) or None
        Pose mapping frame pixels to map pixels of ``segment``; None when the frame has no pose
        (writers also accept a 3x3 affine and use its first two rows).
    confidence : float
        Registration confidence (NaN when unknown).
    status : str
        One of :data:`STATUSES`.
    segment : int
        Map segment; each segment has its own map frame.
    extra : dict
        Further columns (e.g. joined telemetry ``lat``, ``lon``, ``alt_m``), written after the
        standard ones.
    xy : (float, float) or None
        Map position of the frame centre. Filled by the reader; writers compute it from ``M``
        and the frame size when they are given one.
    """

    frame: int
    t: float
    M: np.ndarray | None
    confidence: float = math.nan
    status: str = "registered"
    segment: int = 0
    extra: dict = field(default_factory=dict)
    xy: tuple[float, float] | None = None

    @property
    def glued(self) -> bool:
        """True when the frame's pose is part of the map."""
        return self.M is not None and self.status in GLUED


@dataclass
class GroundTruth:
    """Exact frame-to-terrain matrices of a simulated flight.

    ``H[i]`` (3x3) maps pixels of frame ``frame[i]`` to terrain pixels; ``columns`` holds every
    numeric column of the file by name (``x``, ``yaw_deg``, ``alt_m``, ...).
    """

    frame: np.ndarray
    t: np.ndarray
    H: np.ndarray
    columns: dict[str, np.ndarray] = field(default_factory=dict)
