"""The memory attribution tool (tools/memory_by_part.py): parts from stacks, live MB from memray."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tools.memory_by_part import REPO, part_of, table


def test_part_is_the_innermost_frame_of_the_repository():
    stack = [("concatenate", "/usr/lib/python3/numpy/_core/shape_base.py", 10),
             ("_thumbnail", str(REPO / "service" / "mapping" / "overview.py"), 227),
             ("run", str(REPO / "service" / "mapping" / "pipeline.py"), 500)]
    assert part_of(stack, False) == "mapping/overview.py _thumbnail"
    assert part_of(stack, True) == "mapping/overview.py _thumbnail (mmap)"
    assert part_of(stack[:1], False) == "(no repository frame)"
    assert part_of([("main", str(REPO / "tests" / "test_x.py"), 1)], False) == "(no repository frame)"


def test_table_ranks_parts_by_their_change_after_the_first_tenth():
    parts = {"a": np.array([0.0, 10.0, 10.0]), "b": np.array([50.0, 1.0, 9.0]), "c": np.array([5.0, 5.0, 5.0]),
             "d (mmap)": np.array([0.0, 0.0, 32.0])}
    lines = table(parts, np.array([100.0, 110.0, 120.0]), top=2)
    assert lines[0] == "| tenth | `d (mmap)` | `b` | all but mmap | all mmap | RSS |"
    assert lines[2] == "| 1 | 0.0 | 50.0 | 55.0 | 0.0 | 100.0 |"
    assert lines[4] == "| 3 | 32.0 | 9.0 | 24.0 | 32.0 | 120.0 |"


def test_live_memory_of_a_part_between_marks(tmp_path):
    memray = pytest.importorskip("memray", reason="memray (the bench extra) is not installed")
    from photomap.core.mosaic import TiledMosaic
    from tools.memory_by_part import live_by_part

    mosaic = TiledMosaic()  # 256 px tiles of 3 channels: 256 KB each, no temporaries
    path = tmp_path / "capture.bin"
    with memray.Tracker(path, memory_interval_ms=5):
        marks = [time.time()]
        kept = [mosaic._new_tile() for _ in range(32)]  # 8 MB made in core/mosaic.py
        time.sleep(0.3)
        marks.append(time.time())
        del kept
        time.sleep(0.3)
        marks.append(time.time())
    parts, rss = live_by_part(path, marks)
    tiles = parts["core/mosaic.py _new_tile"]
    assert tiles[0] == pytest.approx(8.0, abs=0.2)
    assert tiles[1] == pytest.approx(0.0, abs=0.1)
    assert len(rss) == 2 and rss.min() > 0
