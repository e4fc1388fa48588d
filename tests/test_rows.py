"""The trajectory rows as columns read, change and write exactly as PoseRow objects did."""

from __future__ import annotations

import numpy as np
import pytest

from photomap.core.records import PoseRow
from photomap.io.trackfiles import track_features
from photomap.io.trajectory_files import format_trajectory_csv, format_tum
from photomap.mapping.rows import TrajectoryRows


def pose(rng: np.random.Generator) -> np.ndarray:
    a, s = rng.uniform(-np.pi, np.pi), rng.uniform(0.5, 2.0)
    return np.array([[s * np.cos(a), -s * np.sin(a), rng.uniform(-500, 500)],
                     [s * np.sin(a), s * np.cos(a), rng.uniform(-500, 500)]])


def both(n: int = 50, seed: int = 0) -> tuple[list[PoseRow], TrajectoryRows]:
    """The same rows as PoseRow objects and as columns: gaps without a pose, two segments, a
    low-confidence frame, extras (shared method, telemetry on some), capacity outgrown."""
    rng = np.random.default_rng(seed)
    objects, columns = [], TrajectoryRows(capacity=4)
    for i in range(n):
        M = None if i % 7 == 3 else pose(rng)
        status = "dropped" if M is None else ("low_confidence" if i % 11 == 5 else "registered")
        extra = {} if M is None else {"method": "ifmi" if i % 5 else "sift"}
        if i % 4 == 0 and M is not None:
            extra["alt_m"] = float(rng.uniform(20, 40))
        segment = 0 if i < n // 2 else 1
        conf = float(rng.uniform(0, 1)) if M is not None else float("nan")
        objects.append(PoseRow(i, i / 30.0, M, conf, status, segment, dict(extra)))
        columns.append(i, i / 30.0, M, conf, status, segment, extra)
    return objects, columns


def test_views_write_the_same_files_as_pose_rows():
    objects, columns = both()
    assert len(columns) == len(objects) == 50
    assert format_trajectory_csv(columns, (320, 240)) == format_trajectory_csv(objects, (320, 240))
    assert format_tum(columns, (320, 240)) == format_tum(objects, (320, 240))
    georefs = {0: (np.array([[0.1, 0.0, 500000.0], [0.0, -0.1, 4000000.0]]), 32617),
               1: (np.array([[0.1, 0.0, 500300.0], [0.0, -0.1, 4000000.0]]), 32617)}
    for mode in ("spaced", "all"):  # footprints too (views are new objects at each pass over the rows)
        feats = track_features(columns, (320, 240), georefs, footprints=mode)
        assert feats == track_features(objects, (320, 240), georefs, footprints=mode)
        assert sum(f["properties"]["kind"] == "footprint" for f in feats) > 2
    for obj, view in zip(objects, columns):
        assert (view.frame, view.status, view.segment, view.glued) == (obj.frame, obj.status, obj.segment, obj.glued)
        assert (view.M is None) == (obj.M is None)
    assert [r.frame for r in reversed(columns)] == list(range(49, -1, -1))
    assert [r.frame for r in columns[10:13]] == [10, 11, 12] and columns[-1].frame == 49


def test_a_correction_and_a_join_equal_row_by_row_changes():
    objects, columns = both(seed=1)
    rng = np.random.default_rng(2)
    frames = rng.permutation(np.arange(-3, 60))  # some frames have no row, any order
    poses = np.stack([np.vstack([pose(rng), [0, 0, 1]]) for _ in frames])
    for f, p in zip(frames, poses):  # the old loop: posed rows of the segment only
        if 0 <= f < len(objects) and objects[f].M is not None and objects[f].segment == 1:
            objects[f].M = p[:2]
    columns.set_poses(frames, poses, segment=1)
    t = np.array([[0.8, -0.6, 10.0], [0.6, 0.8, -4.0], [0.0, 0.0, 1.0]])
    for row in objects:
        if row.segment == 0:
            if row.M is not None:
                row.M = (t @ np.vstack([row.M, [0, 0, 1]]))[:2]
            row.segment = 1
    columns.transform_segment(0, t, into=1)
    for obj, view in zip(objects, columns):
        assert view.segment == obj.segment
        if obj.M is None:
            assert view.M is None
        else:
            np.testing.assert_allclose(view.M, obj.M, atol=1e-9)
    assert columns.segment_counts() == {1: sum(r.glued for r in objects)}
    assert [r.frame for r in columns.glued(1, start=20)] == [r.frame for r in objects[20:] if r.glued]


def test_rows_change_through_their_views_and_copies_are_independent():
    _, columns = both()
    snapshot = columns.copy()
    row = columns[columns.index_of(10)]
    row.M, row.status, row.segment, row.confidence = np.eye(3), "reference", 7, 1.0
    assert columns[10].status == "reference" and columns[10].segment == 7
    np.testing.assert_array_equal(columns[10].M, np.eye(3)[:2])
    assert snapshot[10].status != "reference" and snapshot[10].segment != 7
    got = columns[10].M
    got[0, 0] = 99.0  # a copy: the row does not change
    assert columns[10].M[0, 0] == 1.0
    assert columns.index_of(10_000) is None
    assert columns.status_counts()["reference"] == 1


def test_extras_are_shared_read_only_and_replaced():
    _, columns = both()
    a, b = columns[1].extra, columns[2].extra
    assert a == {"method": "ifmi"} and a is b  # one mapping for all rows with the same extras
    with pytest.raises(TypeError):
        a["lat"] = 1.0
    columns[1].extra = {**a, "lat": 1.5}
    assert columns[1].extra == {"method": "ifmi", "lat": 1.5} and columns[2].extra == {"method": "ifmi"}
    assert columns[3].extra == {}  # no pose, no method
