"""Drift on closed flights (figure-eight, lawn-mower): keyframes, loop closure and the revisit seam."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from photomap.config import load_config
from photomap.sim.flight import simulate_sequence
from photomap.mapping.pipeline import MappingPipeline
from photomap.sim.terrain import load_terrain, procedural_terrain, valid_mask
from photomap.io.trajectory_files import read_trajectory_csv
from test_pipeline import SIZE, ListSource, evaluate

F2F = ["mapping.keyframes=false", "mapping.loop_closure=false"]
KEYFRAMES = ["mapping.keyframes=true", "mapping.loop_closure=false"]
LOOPS = ["mapping.keyframes=true", "mapping.loop_closure=true"]


@pytest.fixture(scope="module")
def terrains():
    aukerman = load_terrain("aukerman", zoom=3)
    sand = procedural_terrain("sand", (2048, 2048), seed=5)
    return {"textured": (aukerman, valid_mask(aukerman), 0.1 / 3, 1.0),
            "featureless": (sand, np.ones(sand.shape[:2], bool), 0.05, 2.0)}


def closed_flight(terrain, valid, gsd, noise, pattern, seed, n=180):
    return simulate_sequence(terrain, n, SIZE, seed=seed, valid=valid, gsd=gsd, fps=10.0,
                             altitude=(25.0, 35.0), speed=6.0, pattern=pattern, yaw_mode="heading",
                             noise=noise)


def mapped(seq, overrides, out):
    summary = MappingPipeline(ListSource(seq.frames), load_config(overrides=overrides), out).run()
    return summary, evaluate(out, seq)


def revisit(seq):
    """The frame of the last third of the flight that comes closest to the first frame."""
    xy = np.c_[seq.truth.x, seq.truth.y]
    late = np.arange(2 * len(xy) // 3, len(xy))
    k = late[np.argmin(np.hypot(*(xy[late] - xy[0]).T))]
    return int(k), float(np.hypot(*(xy[k] - xy[0])))


def anchored_error(out, seq, k):
    """Terrain-pixel error of frame k's centre, the map tied to the truth at frame 0."""
    rows = {r.frame: r for r in read_trajectory_csv(out / "trajectory.csv")}
    c = np.array([(SIZE[1] - 1) / 2, (SIZE[0] - 1) / 2, 1.0])
    m0, mk = (np.vstack([rows[i].M, [0, 0, 1]]) for i in (0, k))
    est = np.asarray(seq.truth.H[0]) @ np.linalg.inv(m0) @ mk @ c
    true = np.asarray(seq.truth.H[k]) @ c
    return float(np.hypot(*(est[:2] / est[2] - true[:2] / true[2])))


@pytest.mark.parametrize("kind", ["textured", "featureless"])
@pytest.mark.parametrize("seed", [1, 2])
def test_loop_closure_on_a_figure_eight(terrains, tmp_path, kind, seed):
    # the figure-eight spans the terrain's flyable area: on the larger sand it takes longer
    seq = closed_flight(*terrains[kind], "figure8", seed, n=180 if kind == "textured" else 240)
    k, distance = revisit(seq)
    assert distance < 0.25 * SIZE[1]  # the flight really comes back over its start
    _, chained = mapped(seq, F2F, tmp_path / "f2f")
    # both ways of optimising: in the background (default) and in the worker
    background = "true" if kind == "textured" else "false"
    summary, closed = mapped(seq, LOOPS + [f"mapping.optimize_in_background={background}"], tmp_path / "loops")
    assert summary["loop_closure"]["loop_edges"] >= 1 and summary["loop_closure"]["corrections"] >= 1
    target = 0.05 if kind == "textured" else 0.5
    assert closed["ate"]["pct"] < target
    seam = anchored_error(tmp_path / "loops", seq, k)
    assert seam < 1.0  # the revisit seam, terrain pixels
    assert seam <= anchored_error(tmp_path / "f2f", seq, k) + 0.05


def test_windowed_solves_while_mapping_still_close_the_loop(terrains, tmp_path, monkeypatch):
    """With posegraph.max_solve_nodes small, every solve while mapping moves only the newest
    keyframes; the solve at the end moves them all: the loop still closes."""
    from photomap.core.keyframes import KeyframeGraph

    solves = []  # (nodes, newest) of each solve
    solve = KeyframeGraph.solve
    monkeypatch.setattr(KeyframeGraph, "solve", staticmethod(
        lambda graph, params, callback=None, newest=None:
        solves.append((graph.num_nodes, newest)) or solve(graph, params, callback, newest)))
    seq = closed_flight(*terrains["textured"], "figure8", 1)
    k, _ = revisit(seq)
    summary, closed = mapped(seq, LOOPS + ["mapping.optimize_in_background=false", "posegraph.max_solve_nodes=8"],
                             tmp_path / "windowed")
    assert summary["loop_closure"]["keyframes"] > 8 and summary["loop_closure"]["corrections"] == len(solves)
    assert any(nodes > 8 for nodes, newest in solves[:-1]) and {newest for _, newest in solves[:-1]} == {8}
    assert solves[-1] == (summary["loop_closure"]["keyframes"], None)  # the last one: all
    assert closed["ate"]["pct"] < 0.05
    assert anchored_error(tmp_path / "windowed", seq, k) < 1.0


def test_lawnmower_keyframes_drift_less_than_frame_to_frame(terrains, tmp_path):
    seq = closed_flight(*terrains["textured"], "lawnmower", 3)
    _, chained = mapped(seq, F2F, tmp_path / "f2f")
    _, keyed = mapped(seq, KEYFRAMES, tmp_path / "kf")
    assert keyed["ate"]["pct"] < chained["ate"]["pct"]
    assert keyed["ate"]["pct"] < 0.05


def map_residual(out, seq, terrain, mask_fn):
    """Median |map - terrain| (grey levels) where ``mask_fn(map xy)`` holds, in covered pixels."""
    import json
    info = json.loads((out / "run.json").read_text())["mosaics"][0]
    mosaic = cv2.imread(str(out / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    x0, y0 = info["origin_xy"]
    shift = np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1.0]])
    expected = cv2.warpPerspective(terrain, np.asarray(seq.truth.H[0]) @ shift,
                                   (mosaic.shape[1], mosaic.shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    covered = cv2.erode((mosaic[:, :, 3] == 255).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    ys, xs = np.mgrid[0:mosaic.shape[0], 0:mosaic.shape[1]]
    sel = covered & mask_fn(xs + x0, ys + y0)
    diff = np.abs(cv2.cvtColor(mosaic[:, :, :3], cv2.COLOR_BGR2GRAY).astype(float)
                  - cv2.cvtColor(expected, cv2.COLOR_BGR2GRAY).astype(float))
    return float(np.median(diff[sel])), int(sel.sum())


def test_the_revisit_shows_no_double_edges(terrains, tmp_path):
    """Around the start (flown over twice) the map is as true to the ground as a single pass."""
    terrain, valid, gsd, noise = terrains["textured"]
    seq = closed_flight(terrain, valid, gsd, noise, "figure8", 4)
    out = tmp_path / "loops"
    mapped(seq, LOOPS, out)
    k, _ = revisit(seq)
    rows = {r.frame: r for r in read_trajectory_csv(out / "trajectory.csv")}
    cx, cy = np.asarray(rows[k].M) @ [(SIZE[1] - 1) / 2, (SIZE[0] - 1) / 2, 1.0]
    near_start = lambda x, y: np.hypot(x - cx, y - cy) < 0.4 * SIZE[0]  # noqa: E731
    far = lambda x, y: ~near_start(x, y)  # noqa: E731
    seam, n_seam = map_residual(out, seq, terrain, near_start)
    single, n_single = map_residual(out, seq, terrain, far)
    assert n_seam > 1000 and n_single > 1000
    assert seam < 1.5 * single + 1.0


def test_map_relative_keyframes_snap_to_the_map(terrains, tmp_path):
    seq = closed_flight(*terrains["textured"], "figure8", 5)
    summary, result = mapped(seq, KEYFRAMES + ["mapping.map_relative=true"], tmp_path / "maprel")
    assert summary["map_relative_fixes"] > 5
    assert result["ate"]["pct"] < 0.05
    k, _ = revisit(seq)
    assert anchored_error(tmp_path / "maprel", seq, k) < 1.0


def test_the_viewer_shows_the_corrected_trajectory(terrains, tmp_path):
    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader

    from photomap.config import ViewerConfig
    from photomap.live.viewer import Viewer

    seq = closed_flight(*terrains["textured"], "figure8", 1)
    rrd = tmp_path / "view.rrd"
    viewer = Viewer("save", str(rrd), ViewerConfig(trajectory_every=10))
    pipeline = MappingPipeline(ListSource(seq.frames), load_config(overrides=LOOPS), tmp_path / "run",
                               sinks=[viewer.on_frame])
    summary = pipeline.run()
    viewer.close()
    assert summary["loop_closure"]["corrections"] >= 1
    texts, strips = [], []
    for chunk in RrdReader(str(rrd)).stream().to_chunks():
        batch = chunk.to_record_batch()
        if chunk.entity_path == "/events":
            texts += [t for row in batch.column("TextLog:text").to_pylist() for t in row]
        if chunk.entity_path == "/map/trajectory" and "LineStrips2D:strips" in batch.schema.names:
            frames = batch.column("frame").to_pylist()
            strips += [(f, s) for f, s in zip(frames, batch.column("LineStrips2D:strips").to_pylist()) if s]
    assert any("loop closed" in t for t in texts)
    # the last path sent ends at the last frame's corrected position in trajectory.csv
    last = max(strips, key=lambda fs: fs[0])[1]
    end = np.array(last[-1][-1])
    rows = read_trajectory_csv(tmp_path / "run" / "trajectory.csv")
    assert np.hypot(*(end - np.array(rows[-1].xy))) < 0.5


def test_loop_closure_with_telemetry_priors(tmp_path):
    """Heading, height and GPS of the keyframes enter the pose graph; the loop still closes."""
    from photomap.cli.replay import replay
    from photomap.sim.simulate import simulate_flight
    from photomap.geometry import frame_centre
    from photomap.eval.metrics import evaluate_trajectory
    from photomap.io.trajectory_files import read_groundtruth

    flight = simulate_flight(tmp_path / "flight", n_frames=220, size=(320, 240), fps=10.0, seed=2,
                             pattern="figure8", yaw_mode="heading", speed=6.0, terrain="aukerman",
                             terrain_zoom=3.0, gsd=0.1, altitude=(25.0, 35.0), noise=1.0, video_codec="ffv1")
    summary = replay(str(flight / "video.mkv"), tmp_path / "run", load_config(overrides=LOOPS),
                     mavlink=str(flight / "telemetry.tlog"))
    assert summary["loop_closure"]["corrections"] >= 1
    assert summary["georeference"] is not None
    head = evaluate_trajectory(read_trajectory_csv(tmp_path / "run" / "trajectory.csv"),
                               read_groundtruth(flight / "groundtruth.csv"), frame_centre(320, 240))["headline"]
    assert head["ate"]["pct"] < 0.05
