"""ThinnedPath (photomap.core.thinned): the live views' bounded track lines."""

from __future__ import annotations

import numpy as np
import pytest

from photomap.core.thinned import ThinnedPath


def _appended(n: int, cap: int) -> ThinnedPath:
    path = ThinnedPath(cap)
    for i in range(n):
        path.append((float(i), -float(i)))
    return path


@pytest.mark.parametrize("cap", [2, 3, 8, 100])
def test_keeps_every_stride_th_point_within_the_cap(cap):
    for n in range(0, 5 * cap + 3):
        path = _appended(n, cap)
        s = path.stride
        assert len(path) <= cap and path.count == n
        assert path.points == [(float(i), -float(i)) for i in range(0, n, s)]  # points 0, s, 2s, ... in order
        # the stride is the least power of two that fits the cap: half of it would not
        assert s & (s - 1) == 0 and (s == 1 or -(-n // (s // 2)) > cap)


@pytest.mark.parametrize("n", [0, 1, 7, 8, 9, 17, 50, 1001])
def test_a_rebuilt_path_then_appends_is_the_path_of_appends_alone(n):
    """A correction gives the whole path at once (an array); the points, stride and count are
    those of point-by-point appends, and so they stay as points keep coming."""
    cap = 8
    xy = np.column_stack([np.arange(n) * 1.5, np.arange(n) * -0.5])
    one = ThinnedPath(cap)
    for p in xy.tolist():
        one.append(tuple(p))
    bulk = _appended(3 * n + 5, cap)  # a different history before the correction
    bulk.rebuild(xy)
    assert (bulk.points, bulk.stride, bulk.count) == (one.points, one.stride, one.count)
    for i in range(n, n + 40):
        p = (i * 1.5, i * -0.5)
        one.append(p)
        bulk.append(p)
        assert (bulk.points, bulk.stride, bulk.count) == (one.points, one.stride, one.count)


def test_a_reader_holding_the_list_and_its_length_keeps_its_points():
    """Appends go to the end of the list in place; thinning replaces the list: what a reader
    took (the list, then its length) is unchanged by later appends, thinning and rebuilds."""
    path = _appended(5, 6)
    held = path.points
    n = len(held)
    before = list(held[:n])
    for i in range(5, 40):
        path.append((float(i), -float(i)))
    path.rebuild([(0.0, 0.0)] * 50)
    assert held[:n] == before
    path.clear()
    assert (path.points, path.stride, path.count) == ([], 1, 0) and held[:n] == before
