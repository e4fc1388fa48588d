"""Real survey stills (../shared/data/brighton_beach): the map agrees with the GPS track.

DJI Phantom 3 (FC300S, f = 3.61 mm on a 1/2.3" sensor: about 585 px at the 1000 px width of the
downscaled stills), 40 m above ground, lawn-mower strips with ~65 % forward overlap.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from photomap.config import load_config
from photomap.cli.replay import replay
from photomap.io.trajectory_files import read_trajectory_csv

from conftest import DATA_DIR as DATA
BRIGHTON = DATA / "brighton_beach"


@pytest.fixture(scope="module")
def brighton_run(tmp_path_factory):
    if not (BRIGHTON / "images").is_dir():
        pytest.skip(f"real survey data not found at {BRIGHTON} (shared/data is not in a user's clone)")
    out = tmp_path_factory.mktemp("brighton")
    summary = replay(str(BRIGHTON / "images"), out, load_config())
    with open(BRIGHTON / "poses.csv", newline="") as f:
        poses = list(csv.DictReader(f))
    return summary, read_trajectory_csv(out / "trajectory.csv"), poses


def linked_pairs(rows):
    return [(a, b) for a, b in zip(rows, rows[1:])
            if a.glued and b.glued and a.segment == b.segment and b.status == "registered"]


def test_consecutive_motions_agree_with_gps(brighton_run):
    summary, rows, poses = brighton_run
    pairs = linked_pairs(rows)
    assert len(pairs) >= 6, [r.status for r in rows]
    centre = np.array([499.5, 280.5, 1.0])
    focal, bearing = [], []
    for a, b in pairs:
        pa, pb = poses[a.frame], poses[b.frame]
        lat = math.radians(float(pa["lat"]))
        north = (float(pb["lat"]) - float(pa["lat"])) * 111_320.0
        east = (float(pb["lon"]) - float(pa["lon"])) * 111_320.0 * math.cos(lat)
        alt = (float(pa["rel_alt"]) + float(pb["rel_alt"])) / 2
        rel = np.linalg.inv(np.vstack([a.M, [0, 0, 1]])) @ np.vstack([b.M, [0, 0, 1]])
        d = rel @ centre - centre  # where b's centre lies in a's pixels
        # pixels = metres * focal_px / altitude: the implied focal length must be the camera's
        focal.append(math.hypot(*d[:2]) * alt / math.hypot(north, east))
        # direction: image bearing turned by the gimbal yaw vs GPS bearing; the logged yaw flips by
        # 180 deg at strip ends while the images do not rotate, so compare modulo 180 deg
        image_bearing = math.degrees(math.atan2(d[0], -d[1])) + float(pa["gimbal_yaw"])
        diff = math.degrees(math.atan2(east, north)) - image_bearing
        bearing.append((diff + 90.0) % 180.0 - 90.0)
    focal = np.array(focal)
    assert 500 < np.median(focal) < 680
    assert np.all(np.abs(focal / np.median(focal) - 1) < 0.2), focal
    assert np.all(np.abs(bearing) < 10.0), bearing


def test_unlinkable_stills_start_segments_not_a_corrupt_map(brighton_run):
    summary, rows, _ = brighton_run
    assert summary["segments"] >= 2
    assert summary["frames_in"] == 18 and len(rows) == 18
    # every glued frame of a segment is linked to its predecessor with a confident registration
    for a, b in linked_pairs(rows):
        assert b.confidence >= load_config().mapping.min_confidence
