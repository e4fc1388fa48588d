"""`photomap batch`: many flights on a Dask LocalCluster, their outputs, batch.json, flights.geojson.

The flight tests need Dask (the `batch` extra, also in `test`); they are skipped with the reason
when it is missing. Manifest, sidecar and naming rules are checked without it.
"""

from __future__ import annotations

import csv
import json
import sys

import cv2
import numpy as np
import pytest
import yaml

from photomap.cli.batch import (FlightSpec, discover_flights, read_manifest, sidecar_telemetry,
                                threads_per_host, unique_names)
from photomap.cli.main import main
from photomap.cli.replay import replay
from photomap.config import load_config
from photomap.errors import InputError
from photomap.io.trajectory_files import read_groundtruth, read_trajectory_csv
from photomap.sim.flight import pixel_to_latlon
from photomap.sim.simulate import simulate_flight

FRAMES = 45


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """Two tiny simulated flights (the simulator's layout: video.mp4 + telemetry.tlog) and a
    corrupt video."""
    root = tmp_path_factory.mktemp("batch-flights")
    for seed in (41, 42):
        simulate_flight(root / f"f{seed}", n_frames=FRAMES, size=(320, 240), fps=15.0, seed=seed)
    (root / "broken").mkdir()
    (root / "broken" / "corrupt.mp4").write_bytes(np.random.default_rng(0).bytes(20000))
    return root


def _need_dask():
    pytest.importorskip("distributed", reason="Dask is not installed (pip install 'ifmi-photomap[batch]')")


# ------------------------------------------------------------------ without Dask
def test_sidecar_convention(tmp_path):
    (tmp_path / "a.mp4").write_bytes(b"x")
    (tmp_path / "a.tlog").write_bytes(b"x")
    assert sidecar_telemetry(tmp_path / "a.mp4") == str(tmp_path / "a.tlog")
    sim = tmp_path / "sim"
    sim.mkdir()
    (sim / "video.mp4").write_bytes(b"x")
    (sim / "telemetry.tlog").write_bytes(b"x")
    assert sidecar_telemetry(sim / "video.mp4") == str(sim / "telemetry.tlog")
    (sim / "other.mp4").write_bytes(b"x")  # telemetry.tlog is nobody's in particular now
    assert sidecar_telemetry(sim / "video.mp4") is None
    stills = tmp_path / "survey"
    stills.mkdir()
    assert sidecar_telemetry(stills) is None
    (tmp_path / "survey.tlog").write_bytes(b"x")
    assert sidecar_telemetry(stills) == str(tmp_path / "survey.tlog")


def test_manifest_yaml_and_csv(tmp_path):
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "north.mp4").write_bytes(b"x")
    (tmp_path / "d" / "north.tlog").write_bytes(b"x")
    (tmp_path / "fc.tlog").write_bytes(b"x")
    (tmp_path / "m.yaml").write_text(yaml.safe_dump({"flights": [
        {"input": "d/north.mp4"},
        {"input": "d/north.mp4", "name": "again", "mavlink": "fc.tlog", "time_offset": 0.4},
        {"input": "d/north.mp4", "name": "vision only", "mavlink": "none", "video_start": 1781251200}]}))
    specs = discover_flights([str(tmp_path / "m.yaml")])
    assert [s.name for s in specs] == ["north", "again", "vision_only"]
    assert specs[0].mavlink == str(tmp_path / "d" / "north.tlog")  # sidecar
    assert specs[1].mavlink == str(tmp_path / "fc.tlog") and specs[1].time_offset == 0.4
    assert specs[2].mavlink is None and specs[2].video_start == 1781251200.0
    assert all(s.input == str(tmp_path / "d" / "north.mp4") for s in specs)
    with open(tmp_path / "m.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["input", "name", "mavlink", "time_offset"])
        w.writerow(["d/north.mp4", "", "", ""])
        w.writerow(["d/north.mp4", "late", "fc.tlog", "-1.5"])
    specs = discover_flights([str(tmp_path / "m.csv")])
    assert [(s.name, s.mavlink, s.time_offset) for s in specs] == [
        ("north", str(tmp_path / "d" / "north.tlog"), None), ("late", str(tmp_path / "fc.tlog"), -1.5)]


@pytest.mark.parametrize("text, words", [
    ("flights: 3", "list of flights"),
    ("flights:\n  - {input: a.mp4, mavlnk: b.tlog}", "unknown key(s) mavlnk"),
    ("flights:\n  - {input: a.mp4, time_offset: soon}", "time_offset must be a number"),
    ("flights:\n  - {name: x}", "no input"),
    ("flights: [", "not valid YAML"),
])
def test_bad_manifest_is_one_clear_line(tmp_path, text, words):
    (tmp_path / "m.yaml").write_text(text)
    with pytest.raises(InputError, match=None) as info:
        read_manifest(tmp_path / "m.yaml")
    assert words in str(info.value) and "\n" not in str(info.value)


def test_names_are_unique():
    specs = unique_names([FlightSpec("/x/a/video.mp4", "video"), FlightSpec("/x/b/video.mp4", "video"),
                          FlightSpec("/y/a/video.mp4", "video"), FlightSpec("/z/c.mp4", "c")])
    assert [s.name for s in specs] == ["a-video", "b-video", "a-video-2", "c"]


def test_threads_never_oversubscribe_the_cores():
    workers = {"tcp://10.0.0.1:1": {"nthreads": 1}, "tcp://10.0.0.1:2": {"nthreads": 1},
               "tcp://10.0.0.2:1": {"nthreads": 2}, "tcp://10.0.0.3:1": {"nthreads": 16}}
    cores = {"tcp://10.0.0.1:1": 8, "tcp://10.0.0.1:2": 8, "tcp://10.0.0.2:1": 2, "tcp://10.0.0.3:1": 4}
    assert threads_per_host(workers, cores) == {"10.0.0.1": 4, "10.0.0.2": 1, "10.0.0.3": 1}


def test_without_dask_one_line_says_how_to_get_it(flights, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    code = main(["batch", str(flights / "f41" / "video.mp4"), "--out", str(tmp_path / "b"), "-q"])
    err = capsys.readouterr().err.strip()
    assert code == 3 and err.count("\n") == 0
    assert "pip install 'ifmi-photomap[batch]'" in err


# ------------------------------------------------------------------ on a LocalCluster
def _inside(lonlat: np.ndarray, feature: dict) -> np.ndarray:
    geom = feature["geometry"]
    polys = [geom["coordinates"]] if geom["type"] == "Polygon" else geom["coordinates"]
    out = np.zeros(len(lonlat), bool)
    for poly in polys:
        ring = np.asarray(poly[0], np.float64)
        scale = 1e6  # degrees -> micro-degrees, so that pointPolygonTest works in sensible units
        contour = (ring * scale).astype(np.float32).reshape(-1, 1, 2)
        out |= np.array([cv2.pointPolygonTest(contour, (float(x * scale), float(y * scale)), False) >= 0
                         for x, y in lonlat])
    return out


def test_batch_on_two_workers(flights, tmp_path, capsys):
    _need_dask()
    out = tmp_path / "batch"
    inputs = [str(flights / "f41" / "video.mp4"), str(flights / "f42" / "video.mp4"),
              str(flights / "broken" / "corrupt.mp4")]
    code = main(["batch", *inputs, "--out", str(out), "--workers", "2", "--no-progress", "-q"])
    printed = capsys.readouterr().out
    assert code == 1  # one flight failed, the others finished
    status = json.loads((out / "batch.json").read_text())
    assert status["complete"] and status["workers"] == 2
    assert (status["ok"], status["failed"]) == (2, 1)
    by_name = {f["name"]: f for f in status["flights"]}
    assert set(by_name) == {"f41-video", "f42-video", "corrupt"}
    bad = by_name["corrupt"]
    assert bad["status"] == "failed" and "corrupt.mp4" in bad["error"] and "\n" not in bad["error"]
    assert not (out / "corrupt" / "mosaic.png").exists()
    for seed in (41, 42):
        e = by_name[f"f{seed}-video"]
        assert e["status"] == "ok" and e["frames"] == FRAMES and e["registered"] == FRAMES
        assert e["segments"] == 1 and e["georeferenced"] and e["wall_time_s"] > 0
        assert e["mavlink"] == str(flights / f"f{seed}" / "telemetry.tlog")  # the simulator's sidecar
        assert f"{e['name']}: ok, {FRAMES} frames" in printed
    assert "corrupt: FAILED" in printed and len(printed.strip().splitlines()) == 4

    # each flight's outputs are those of a plain replay (same library function, same config)
    for seed in (41, 42):
        run = out / f"f{seed}-video"
        for name in ("mosaic.png", "trajectory.csv", "run.json", "map.tif", "track.geojson", "mosaic.pgw"):
            assert (run / name).is_file(), name
        ref = tmp_path / f"replay{seed}"
        replay(str(flights / f"f{seed}" / "video.mp4"), ref, load_config(),
               mavlink=str(flights / f"f{seed}" / "telemetry.tlog"))
        a, b = read_trajectory_csv(run / "trajectory.csv"), read_trajectory_csv(ref / "trajectory.csv")
        assert len(a) == len(b) == FRAMES
        # the same poses to float rounding (CI once saw 2.5e-6 px in one of 270 values between the two
        # processes), so the same mosaic but for a rounding flip of one level here and there
        np.testing.assert_allclose(np.array([r.M for r in a]), np.array([r.M for r in b]), rtol=0, atol=1e-4)
        ma = cv2.imread(str(run / "mosaic.png"), cv2.IMREAD_UNCHANGED)
        mb = cv2.imread(str(ref / "mosaic.png"), cv2.IMREAD_UNCHANGED)
        assert ma.shape == mb.shape
        diff = np.abs(ma.astype(np.int16) - mb)
        assert diff.max() <= 1 and np.count_nonzero(diff) <= 1e-3 * diff.size

    # the catalogue: one footprint per georeferenced flight, holding the true frame centres
    catalogue = json.loads((out / "flights.geojson").read_text())
    feats = {f["properties"]["name"]: f for f in catalogue["features"]}
    assert set(feats) == {"f41-video", "f42-video"}
    for seed in (41, 42):
        meta = yaml.safe_load((flights / f"f{seed}" / "meta.yaml").read_text())
        truth = read_groundtruth(flights / f"f{seed}" / "groundtruth.csv")
        lat, lon = pixel_to_latlon(truth.columns["x"], truth.columns["y"], meta["gsd"],
                                   meta["origin"]["lat"], meta["origin"]["lon"])
        assert _inside(np.c_[lon, lat], feats[f"f{seed}-video"]).all()
        # and its area is that of the frames' true footprints (union on the terrain grid)
        h, w = meta["camera"]["height"], meta["camera"]["width"]
        corners = np.array([[-0.5, -0.5, 1], [w - 0.5, -0.5, 1], [w - 0.5, h - 0.5, 1], [-0.5, h - 0.5, 1]]).T
        quads = [(H @ corners)[:2] / (H @ corners)[2] for H in truth.H]
        pts = np.concatenate(quads, axis=1)
        lo = np.floor(pts.min(axis=1)).astype(int)
        grid = np.zeros((int(pts[1].max() - lo[1]) + 2, int(pts[0].max() - lo[0]) + 2), np.uint8)
        for q in quads:
            cv2.fillConvexPoly(grid, np.rint(q.T - lo).astype(np.int32), 1)
        true_area = grid.sum() * meta["gsd"] ** 2
        assert feats[f"f{seed}-video"]["properties"]["area_m2"] == pytest.approx(true_area, rel=0.05)


def test_a_flight_keeps_to_its_opencv_threads(flights, tmp_path, monkeypatch):
    """map_flight's thread budget holds inside the pipeline, which sets OpenCV's pool from
    mapping.opencv_threads (default 2) for its run: 2 flights on 2 cores get 1 thread each."""
    from photomap.cli.batch import map_flight
    from photomap.mapping.pipeline import MappingPipeline

    seen: set[int] = set()
    process = MappingPipeline._process

    def spy(self, frame, small=None):
        seen.add(cv2.getNumThreads())
        return process(self, frame, small)

    monkeypatch.setattr(MappingPipeline, "_process", spy)
    spec = FlightSpec(str(flights / "f41" / "video.mp4"), "f41", str(flights / "f41" / "telemetry.tlog"))
    cfg = load_config()
    assert cfg.mapping.opencv_threads == 2
    before = cv2.getNumThreads()
    entry = map_flight(spec, str(tmp_path), cfg, threads=1)
    assert entry["status"] == "ok" and entry["frames"] == FRAMES
    assert seen == {1}
    assert cv2.getNumThreads() == before  # restored
    seen.clear()
    entry = map_flight(spec, str(tmp_path / "more"), cfg.updated({"mapping": {"opencv_threads": 1}}), threads=2)
    assert entry["status"] == "ok" and seen == {1}  # a lower setting is kept
