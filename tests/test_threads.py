"""The worker's frames first: background threads wait at their pause points while it maps one."""

from __future__ import annotations

import threading

import numpy as np

from photomap.config import MosaicConfig, PosegraphConfig
from photomap.core.mosaic import TiledMosaic
from photomap.core.posegraph import PoseGraph, optimize
from photomap.io.keyframestore import KeyframeStore
from photomap.mapping.rerender import KeptFrame, Rerenderer
from photomap.mapping.threads import WorkerFirst


def background_wait(first: WorkerFirst) -> threading.Thread:
    """A thread that makes one background wait (started)."""
    thread = threading.Thread(target=first.wait)
    thread.start()
    return thread


def test_a_background_wait_lasts_as_long_as_the_workers_frame():
    first = WorkerFirst(max_wait_s=60.0)
    between = background_wait(first)  # between frames: it returns at once
    between.join(10.0)
    assert not between.is_alive()
    with first.frame():
        waiting = background_wait(first)
        first.wait()  # the worker's own thread (work it does itself): returns, else this would block
        waiting.join(0.2)
        assert waiting.is_alive()  # still waiting for the frame's end
    waiting.join(10.0)  # a guard against a hang, not a speed
    assert not waiting.is_alive()


def test_a_frame_longer_than_max_wait_does_not_starve_the_background():
    first = WorkerFirst(max_wait_s=0.05)
    with first.frame():
        thread = background_wait(first)
        thread.join(10.0)
        assert not thread.is_alive()  # returned while the frame still runs


def test_disabled_never_waits_and_paced_is_reiterable():
    first = WorkerFirst(enabled=False, max_wait_s=60.0)
    with first.frame():
        thread = threading.Thread(target=lambda: [first.wait() for _ in range(100)])
        thread.start()
        thread.join(10.0)
        assert not thread.is_alive()  # returned while the frame still runs
    waits = []
    first.wait = lambda: waits.append(1)
    paced = first.paced(list(range(10)), every=4)
    assert list(paced) == list(range(10)) == list(paced)  # iterated twice
    assert len(waits) == 6  # before items 0, 4 and 8, each time


def test_a_rerender_waits_for_the_workers_frame(tmp_path):
    """The re-render thread's strips are rendered between the worker's frames."""
    params = MosaicConfig(tile_size=64)
    first = WorkerFirst(max_wait_s=5.0)
    rerenderer = Rerenderer(KeyframeStore(tmp_path / "kf"), params, first=first)
    rng = np.random.default_rng(0)
    rerenderer.save(0, rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    rerenderer.wait()
    frame = KeptFrame(0, np.eye(3), (160, 120))
    with first.frame():
        rerenderer.submit(0, [frame], {(0, 0), (1, 0)})
        rerenderer.wait(0.3)
        assert rerenderer.collect() == []  # waiting at its pause point while the frame runs
    rerenderer.wait(5.0)
    strips = rerenderer.collect()
    assert len(strips) == 1 and strips[0].frames == 1
    mosaic = TiledMosaic(params)
    mosaic.put_tiles(strips[0].tiles)
    assert set(mosaic.tiles()) == {(0, 0), (1, 0)}
    rerenderer.close()


def test_the_solver_calls_back_before_each_evaluation():
    graph = PoseGraph((160, 120))
    poses = [np.eye(3), np.array([[1.0, 0, 40], [0, 1, 0], [0, 0, 1]])]
    for p in poses:
        graph.add_node(p)
    graph.fix(0)
    graph.add_edge(0, 1, np.array([[1.0, 0, 50], [0, 1, 3], [0, 0, 1]]))
    for solver in ("lm", "trf"):
        calls = []
        result = optimize(graph, PosegraphConfig(solver=solver), callback=lambda: calls.append(1))
        assert len(calls) >= result.nfev - 1 > 0
        np.testing.assert_allclose(result.poses[1][:2, 2], [50, 3], atol=1e-3)
