"""A growing path kept to a bounded number of points (the live views' track lines).

:class:`ThinnedPath` keeps every ``stride``-th point offered, in order; when more than
``max_points`` are kept it drops every other one and doubles the stride. After ``n`` points
it holds exactly the points ``0, s, 2 s, ...`` below ``n`` for the least power-of-two stride
``s`` with ``ceil(n / s) <= max_points``, so :meth:`ThinnedPath.rebuild` (a whole path at once,
e.g. after a pose-graph correction) ends in the state point-by-point appends would have left.
"""

from __future__ import annotations

from typing import Generic, Sequence, TypeVar

import numpy as np

P = TypeVar("P")


def _stride_for(n: int, max_points: int) -> int:
    stride = 1
    while -(-n // stride) > max_points:
        stride *= 2
    return stride


class ThinnedPath(Generic[P]):
    """Every ``stride``-th of the points offered, at most ``max_points`` (>= 2) of them.

    :attr:`points` is only ever appended to in place; thinning and rebuilding replace it with a
    new list, so a reader holding the list and its length at one moment keeps seeing those
    points (the live map server reads it from another thread that way).
    """

    def __init__(self, max_points: int) -> None:
        self.max_points = max(2, int(max_points))
        self.points: list[P] = []
        self.stride = 1
        self.count = 0  # points offered since the last clear / rebuild (including the rebuilt ones)

    def __len__(self) -> int:
        return len(self.points)

    def append(self, point: P) -> None:
        """Offer the next point: kept when its index is a multiple of the stride."""
        if self.count % self.stride == 0:
            self.points.append(point)
            if len(self.points) > self.max_points:
                self.points = self.points[::2]
                self.stride *= 2
        self.count += 1

    def rebuild(self, points: Sequence[P] | np.ndarray) -> None:
        """The whole path again (it replaces what was offered), thinned as appends would thin it;
        the rows of an (n, k) array are kept as tuples of floats."""
        self.stride = _stride_for(len(points), self.max_points)
        kept = points[::self.stride]
        self.points = [tuple(p) for p in kept.tolist()] if isinstance(kept, np.ndarray) else list(kept)
        self.count = len(points)

    def clear(self) -> None:
        self.points, self.stride, self.count = [], 1, 0
