"""Telemetry places what vision cannot: blank stills of a survey with GPS are placed from it.

A simulated survey (``photomap simulate --mode stills``, EXIF GPS and DJI XMP) with a featureless
patch: a few stills in the middle of a strip are made blank (one grey level), their metadata kept.
Truth: the simulator's frame -> terrain homographies (``groundtruth.csv``) and the photos' GPS.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from stills_fixtures import noisy_geo_txt

from photomap.cli.replay import replay
from photomap.config import load_config
from photomap.drivers.exif import read_still_metadata
from photomap.geo.georef import enu_from_latlon
from photomap.io.trajectory_files import read_groundtruth, read_trajectory_csv
from photomap.mapping.loopclosure import LoopCloser
from photomap.sim.simulate import simulate_flight

SIZE = (480, 384)
BLANK = (12, 13)   # the middle of the second strip (8 stills a strip)
MPP = 60.0 / (SIZE[0] / 2.0 / math.tan(math.radians(30.0)))   # ground metres per frame pixel (60 m, 60 deg)


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    out = tmp_path_factory.mktemp("survey")
    simulate_flight(out, terrain="texture", terrain_size=(3400, 2400), mode="stills", strips=3, stills_per_strip=8,
                    size=SIZE, altitude=(60.0, 60.0), seed=1)
    for k in BLANK:  # a featureless patch under these stills; their EXIF and XMP stay
        path = out / "stills" / f"{k:06d}.jpg"
        with Image.open(path) as im:
            exif, xmp = im.getexif(), im.info.get("xmp")
        Image.fromarray(np.full((SIZE[1], SIZE[0], 3), 118, np.uint8)).save(path, "JPEG", exif=exif, xmp=xmp)
    return out


def test_blank_stills_with_gps_are_placed_from_it(survey, tmp_path):
    """With a consumer GPS (positions 1.5 m sigma off, a geo.txt), judged against the truth."""
    geo = noisy_geo_txt(survey / "stills", tmp_path / "geo.txt", sigma_m=1.5, seed=7)
    summary = replay(str(survey / "stills"), tmp_path / "run", load_config(), geo=str(geo))
    tel = summary["telemetry"]
    assert tel["status"] == "ok" and tel["placed"]["placed"] == len(BLANK)
    assert summary["segments"] == 1 and summary["registered"] == 24
    assert summary["loop_closure"]["joins"] == 1   # the next strip found the map again by vision
    rows = {r.frame: r for r in read_trajectory_csv(tmp_path / "run" / "trajectory.csv")}
    assert {k for k, r in rows.items() if r.extra.get("method") == "telemetry"} == set(BLANK)
    assert len({r.segment for r in rows.values() if r.glued}) == 1
    for k in BLANK:  # the frame centre near the photo's true position (nadir stills): its fix's noise
        meta = read_still_metadata(survey / "stills" / f"{k:06d}.jpg")
        e, n = enu_from_latlon(np.array([rows[k].extra["lat"]]), np.array([rows[k].extra["lon"]]), meta.lat, meta.lon)
        assert math.hypot(float(e[0]), float(n[0])) < 5.0, k   # 3.3 sigma of a 2-D 1.5 m noise
    # ... and in the map's own frame, against the truth: the relative pose to a neighbour that
    # vision placed is the true one (a few pixels, a fraction of a degree)
    gt = read_groundtruth(survey / "groundtruth.csv")
    for k in BLANK:
        ref = BLANK[0] - 1
        est = np.linalg.solve(np.vstack([rows[ref].M, [0, 0, 1]]), np.vstack([rows[k].M, [0, 0, 1]]))
        true = np.linalg.solve(gt.H[ref], gt.H[k])
        c = np.array([(SIZE[0] - 1) / 2.0, (SIZE[1] - 1) / 2.0, 1.0])
        shift = np.hypot(*((est @ c)[:2] - (true @ c)[:2] / (true @ c)[2]))
        assert shift * MPP < 6.0, (k, shift)   # metres: the fixes' noise
        angle = math.degrees(math.atan2(est[1, 0], est[0, 0]) - math.atan2(true[1, 0], true[0, 0]))
        assert abs(math.remainder(angle, 360.0)) < 1.0
    # painted: the map is grey (the blank stills) where they are, not empty
    png = cv2.imread(str(tmp_path / "run" / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    assert png is not None and png.shape[2] == 4


def test_without_telemetry_blank_stills_stay_unplaced(survey, tmp_path):
    bare = tmp_path / "bare"
    bare.mkdir()
    for path in sorted((survey / "stills").glob("*.jpg")):  # the pixels without EXIF or XMP
        cv2.imwrite(str(bare / path.name), cv2.imread(str(path)))
    summary = replay(str(bare), tmp_path / "run", load_config(overrides=["camera.hfov_deg=60.0"]))
    assert summary.get("telemetry") is None or summary["telemetry"].get("placed") is None
    rows = {r.frame: r for r in read_trajectory_csv(tmp_path / "run" / "trajectory.csv")}
    assert all(not rows[k].glued for k in BLANK)
    assert not [r for r in rows.values() if r.extra.get("method") == "telemetry"]


def test_a_strip_cut_by_a_blank_patch_stays_one_map(tmp_path, monkeypatch):
    """One strip of 16 stills, stills 7 and 8 blank: nothing links the stills before the patch to
    those after it but the GPS; the two pieces are joined through their georeferences and the
    blank stills placed between them."""
    out = tmp_path / "strip"
    simulate_flight(out, terrain="texture", terrain_size=(4600, 2000), mode="stills", strips=1, stills_per_strip=16,
                    size=SIZE, altitude=(60.0, 60.0), seed=3)
    for k in (7, 8):
        path = out / "stills" / f"{k:06d}.jpg"
        with Image.open(path) as im:
            exif, xmp = im.getexif(), im.info.get("xmp")
        Image.fromarray(np.full((SIZE[1], SIZE[0], 3), 118, np.uint8)).save(path, "JPEG", exif=exif, xmp=xmp)
    geo = noisy_geo_txt(out / "stills", tmp_path / "geo.txt", sigma_m=1.5, seed=8)
    tried = []  # the join searches of the loop closer (features of each candidate: the costly part)
    place_join = LoopCloser._place_join

    def spy(self, matcher, small, image, candidates, pause=None):
        tried.append(list(candidates))
        return place_join(self, matcher, small, image, candidates, pause)

    monkeypatch.setattr(LoopCloser, "_place_join", spy)
    summary = replay(str(out / "stills"), tmp_path / "run", load_config(), geo=str(geo))
    # a join search tries only old keyframes whose footprint could reach the new one's (by GPS:
    # a frame's diagonal on the ground, 89 m, plus the GPS's error): the first two stills after
    # the patch try the last ones before it, the others none (without the bound: 6 searches of
    # the 4 nearest, each with features)
    assert [len(c) for c in tried] in ([2, 1], [1, 1], [1], [2]), tried
    assert summary["loop_closure"]["joins"] == 0
    placed = summary["telemetry"]["placed"]
    assert placed["joined_segments"] == 1 and placed["placed"] == 2, placed
    assert summary["segments"] == 1 and summary["registered"] == 16
    rows = {r.frame: r for r in read_trajectory_csv(tmp_path / "run" / "trajectory.csv")}
    assert len({r.segment for r in rows.values()}) == 1
    errors = {}
    for k, r in rows.items():  # every frame centre (vision's and the telemetry's) near its photo's true GPS
        meta = read_still_metadata(out / "stills" / f"{k:06d}.jpg")
        e, n = enu_from_latlon(np.array([r.extra["lat"]]), np.array([r.extra["lon"]]), meta.lat, meta.lon)
        errors[k] = math.hypot(float(e[0]), float(n[0]))
    assert np.median(list(errors.values())) < 3.0 and max(errors.values()) < 5.0, errors
    # the piece after the patch sits where the truth puts it relative to the piece before it
    gt = read_groundtruth(out / "groundtruth.csv")
    c = np.array([(SIZE[0] - 1) / 2.0, (SIZE[1] - 1) / 2.0, 1.0])
    est = np.linalg.solve(np.vstack([rows[5].M, [0, 0, 1]]), np.vstack([rows[10].M, [0, 0, 1]])) @ c
    true = np.linalg.solve(gt.H[5], gt.H[10]) @ c
    assert np.hypot(*(est[:2] - true[:2] / true[2])) * MPP < 6.0   # metres: joined through 14 noisy fixes


def test_the_kept_views_live_in_the_runs_scratch_folder_and_go_with_it(survey, tmp_path, monkeypatch):
    """The unplaced stills' views go to the run's cache folder (``mosaic.cache_dir`` here), not
    to a temporary folder of their own, and are removed at the end of the run."""
    import tempfile

    import photomap.mapping.telemetry_place as telemetry_place

    stores = []

    class Recorded(telemetry_place.KeyframeStore):
        def __init__(self, folder, *args, **kwargs):
            stores.append(Path(folder))
            super().__init__(folder, *args, **kwargs)

    monkeypatch.setattr(telemetry_place, "KeyframeStore", Recorded)
    before = set(Path(tempfile.gettempdir()).glob("photomap-unplaced-*"))
    cache = tmp_path / "cache"
    summary = replay(str(survey / "stills"), tmp_path / "run", load_config(overrides=[f"mosaic.cache_dir={cache}"]))
    assert summary["telemetry"]["placed"]["placed"] == len(BLANK)
    assert stores == [cache / "unplaced"]
    assert cache.is_dir() and not (cache / "unplaced").exists()  # the user's folder stays, the views do not
    assert set(Path(tempfile.gettempdir()).glob("photomap-unplaced-*")) == before
