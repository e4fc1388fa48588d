"""The checkpointed map (photomap.io.statestore, photomap.mapping.checkpoint) and the preflight of
--out (photomap.io.preflight), on small maps with known pixels."""

from __future__ import annotations

import json
import logging
import shutil
from collections import namedtuple

import cv2
import numpy as np
import pytest

from photomap.config import MosaicConfig
from photomap.core.mosaic import TiledMosaic
from photomap.errors import OutputError
from photomap.io import preflight
from photomap.io.preflight import check_output_dir
from photomap.io.statestore import MapState, load_manifest, restore_mosaic
from photomap.mapping.checkpoint import Checkpointer, recover_run

RNG = np.random.default_rng(1)


def frame(h=100, w=150):
    return RNG.integers(0, 255, (h, w, 3), dtype=np.uint8)


def shift(x, y):
    return np.array([[1.0, 0.0, x], [0.0, 1.0, y]])


def files(folder):
    return sorted(p.name for p in (folder / "seg0").iterdir())


def test_only_changed_tiles_are_written(tmp_path):
    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    mosaic.add(frame(), shift(0, 0))  # tiles x 0..2, y 0..1
    state = MapState(tmp_path)
    state.write(state.snapshot({0: mosaic}, {}))
    first = files(tmp_path)
    assert len(first) == 6 and all(name.endswith("_g1.png") for name in first)
    mosaic.add(frame(20, 20), shift(5, 5))  # inside tile (0, 0) only
    snap = state.snapshot({0: mosaic}, {})
    assert [key for _, key, _, _ in snap.tiles] == [(0, 0)]
    state.write(snap)
    assert files(tmp_path) == sorted(["0_0_g2.png"] + [n for n in first if not n.startswith("0_0_")])
    restored, report = restore_mosaic(tmp_path, load_manifest(tmp_path), 0)
    for key in mosaic.tiles():
        assert np.array_equal(restored.tile_image(key)[0], mosaic.tile_image(key)[0])
        assert np.array_equal(restored.tile_image(key)[1], mosaic.tile_image(key)[1])
    assert restored.bounds() == mosaic.bounds()


def test_a_grey_map_is_checkpointed_and_restored(tmp_path):
    """A grey map's tiles are saved as grey + alpha PNGs (which OpenCV cannot write) and come back
    pixel for pixel."""
    mosaic = TiledMosaic(MosaicConfig(tile_size=64, channels=1))
    mosaic.add(frame()[..., 1], shift(3, 2))
    state = MapState(tmp_path)
    state.write(state.snapshot({0: mosaic}, {}))
    restored, report = restore_mosaic(tmp_path, load_manifest(tmp_path), 0)
    assert report.unreadable == [] and report.restored == len(mosaic.tiles()) == 6
    for key in mosaic.tiles():
        assert np.array_equal(restored.tile_image(key)[0], mosaic.tile_image(key)[0])
        assert np.array_equal(restored.tile_image(key)[1], mosaic.tile_image(key)[1])


def test_snapshot_budget_spreads_a_big_change_over_checkpoints(tmp_path):
    mosaic = TiledMosaic(MosaicConfig(tile_size=32, blend="feather"))
    mosaic.add(frame(), shift(-7, 3))
    state = MapState(tmp_path, max_snapshot_bytes=32 * 32 * 4 * 5)  # five tiles a checkpoint
    total = len(mosaic.tiles())
    written = 0
    for _ in range(10):
        snap = state.snapshot({0: mosaic}, {})
        state.write(snap)
        written += len(snap.tiles)
        named = load_manifest(tmp_path)["tiles"]["0"]
        assert len(named) == written  # a consistent subset, growing
        if snap.pending == 0:
            break
    assert written == total
    restored, _ = restore_mosaic(tmp_path, load_manifest(tmp_path), 0)
    image, alpha = mosaic.render()[:2]
    got, got_alpha = restored.render()[:2]
    assert np.array_equal(alpha, got_alpha) and np.array_equal(image, got)


def test_spilled_tiles_are_read_by_the_writer_as_they_are_then(tmp_path):
    """The worker does not read spilled tiles for a checkpoint: the writer does. A tile repainted
    in between is written as the store has it then (and again by the next checkpoint: its stamp
    moved); a tile cleared in between is left to the next checkpoint; the map is restored."""
    from photomap.io.tilestore import DiskTileStore

    def same_map(restored, mosaic):
        for got, want in zip(restored.render()[:2], mosaic.render()[:2]):
            assert np.array_equal(got, want)

    mosaic = TiledMosaic(MosaicConfig(tile_size=32, max_tiles_in_memory=2), store=DiskTileStore(tmp_path / "cache"))
    mosaic.add(frame(), shift(0, 0))
    state = MapState(tmp_path / "state")
    snap = state.snapshot({0: mosaic}, {})
    spilled = [key for _, key, _, _ in snap.tiles if key not in mosaic._tiles]
    assert len(spilled) >= 4
    before = mosaic.tile_image(spilled[0])[0]
    mosaic.add(frame(20, 20), shift(*(np.array(spilled[0]) * 32 + 4)))  # repainted
    mosaic.clear_tiles([spilled[1]])
    state.write(snap)
    named = {tuple(k[:2]) for k in load_manifest(tmp_path / "state")["tiles"]["0"]}
    assert spilled[0] in named and spilled[1] not in named
    first, _ = restore_mosaic(tmp_path / "state", load_manifest(tmp_path / "state"), 0)
    written = first.tile_image(spilled[0])[0]  # as at the snapshot, or as repainted (in the store then)
    assert np.array_equal(written, before) or np.array_equal(written, mosaic.tile_image(spilled[0])[0])
    mosaic.add(frame(20, 20), shift(*(np.array(spilled[1]) * 32 + 4)))  # the cleared one comes back
    again = state.snapshot({0: mosaic}, {})
    assert {key for _, key, _, _ in again.tiles} >= {spilled[0], spilled[1]}
    state.write(again)
    restored, report = restore_mosaic(tmp_path / "state", load_manifest(tmp_path / "state"), 0)
    assert not report.unreadable
    same_map(restored, mosaic)


def test_a_joined_or_dropped_segment_leaves_the_checkpoint(tmp_path):
    a, b = TiledMosaic(MosaicConfig(tile_size=64)), TiledMosaic(MosaicConfig(tile_size=64))
    a.add(frame(), shift(0, 0))
    b.add(frame(), shift(300, 0))
    state = MapState(tmp_path)
    state.write(state.snapshot({0: a, 1: b}, {}))
    assert (tmp_path / "seg1").is_dir()
    state.write(state.snapshot({0: a}, {}))
    assert not (tmp_path / "seg1").exists() and list(load_manifest(tmp_path)["tiles"]) == ["0"]


def test_checkpointer_reports_a_failure_once_and_recovers(tmp_path, caplog, monkeypatch):
    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    mosaic.add(frame(), shift(0, 0))
    ck = Checkpointer(tmp_path / "ck", background=False)
    from photomap.io import statestore

    def full(path, data):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(statestore, "_write_file", full)
    with caplog.at_level(logging.DEBUG):
        for _ in range(3):
            ck.save({0: mosaic}, {})
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "No space left on device" in errors[0].getMessage()
    assert ck.failed == 3 and not ck.ok() and list((tmp_path / "ck").rglob("*.png")) == []
    monkeypatch.undo()
    ck.save({0: mosaic}, {})
    assert ck.ok() and load_manifest(tmp_path / "ck")["generation"] == 1


def test_recover_writes_the_georeference(tmp_path):
    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    mosaic.add(frame(), shift(-20, 10))
    map_to_crs = [[0.1, 0.0, 500000.0], [0.0, -0.1, 4500000.0]]
    run = tmp_path / "run"
    ck = Checkpointer(run / "checkpoint", background=False)
    ck.save({0: mosaic}, {"order": [0], "georeference": {"0": {"crs": "EPSG:32617", "map_to_crs": map_to_crs}}})
    (run / "run.json").write_text(json.dumps({"complete": False, "frames_in": 7}))
    summary = recover_run(run)
    info = summary["mosaics"][0]
    x0, y0, w, h = mosaic.bounds()  # the frame less its 1-pixel border
    assert info["origin_xy"] == [x0, y0] == [-19, 11] and summary["georeference"]["crs"] == "EPSG:32617"
    png = cv2.imread(str(run / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    assert png.shape == (h, w, 4) == (98, 148, 4) and (png[..., 3] == 255).all()
    a, d, b, e, c, f = (float(v) for v in (run / "mosaic.pgw").read_text().split())
    assert (a, e) == pytest.approx((0.1, -0.1))
    # the world file's (c, f) is the CRS position of the PNG's top-left pixel centre: map pixel (-19, 11)
    assert (c, f) == pytest.approx((500000.0 - 1.9, 4500000.0 - 1.1))
    assert (run / "mosaic.prj").is_file() and summary["frames_in"] == 7


def test_recover_without_a_checkpoint_is_one_clear_error(tmp_path):
    from photomap.errors import InputError

    with pytest.raises(InputError, match="no checkpoint"):
        recover_run(tmp_path)


Usage = namedtuple("Usage", "total used free")


def test_preflight_refuses_below_the_floor_and_warns_below_the_estimate(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(preflight.shutil, "disk_usage", lambda p: Usage(10**9, 10**9 - 30 * 10**6, 30 * 10**6))
    with pytest.raises(OutputError, match="only 30 MB free .* at least 50 MB .*output.min_free_mb"):
        check_output_dir(tmp_path / "a", min_free_mb=50)
    with caplog.at_level(logging.WARNING):
        info = check_output_dir(tmp_path / "b", min_free_mb=10, expected_frames=1000)
    assert info["estimate_mb"] == pytest.approx(1000 * preflight.BYTES_PER_FRAME / 1e6)
    assert any("may be needed for 1000 frames" in r.getMessage() for r in caplog.records)
    assert list((tmp_path / "b").iterdir()) == []  # the probe file is gone
    monkeypatch.setattr(preflight.shutil, "disk_usage", shutil.disk_usage)
