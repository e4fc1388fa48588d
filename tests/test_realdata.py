"""Real stills that nobody on the team produced map into one piece and agree with their GPS.

- ``brighton_beach``: 18 DJI Phantom 3 stills (FC300S, f = 3.61 mm on a 1/2.3" sensor: about 585
  px at the 1000 px width of the downscaled stills), 40 m above ground, three lawn-mower strips
  (DJI_0018-0023 over forest), ~65 % forward overlap; the logged yaw flips at strip ends while the
  images do not rotate.
- ``seneca_nir``: 17 near-infrared stills of a fixed-wing plane without gimbal, bare fields, 5-20
  deg rotation between stills, two strips and a turn (IMG_0470 -> 0471 share no ground).

Truth: the stills' GPS (``poses.csv``). Frame centres of a map are compared with it after the
best similarity (the map has no scale or north of its own without telemetry).
"""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from conftest import shared_data
from photomap.cli.replay import replay
from photomap.config import load_config
from photomap.geo.georef import enu_from_latlon
from photomap.geometry import similarity_fit
from photomap.io.trajectory_files import read_trajectory_csv


def _run(tmp_path_factory, name: str, geo: bool):
    folder = shared_data(name)
    with open(folder / "poses.csv", newline="") as f:
        poses = list(csv.DictReader(f))
    out = tmp_path_factory.mktemp(name)
    geo_txt = None
    if geo:  # the stills' GPS as OpenDroneMap's geo.txt (the shared copies lost their EXIF)
        geo_txt = out / "geo.txt"
        geo_txt.write_text("EPSG:4326\n" + "".join(
            f"{p['file'].rsplit('.', 1)[0]}.jpg {p['lon']} {p['lat']} {p['gps_alt']}\n" for p in poses))
    summary = replay(str(folder / "images"), out / "run", load_config(), geo=str(geo_txt) if geo_txt else None)
    return summary, read_trajectory_csv(out / "run" / "trajectory.csv"), poses


@pytest.fixture(scope="module")
def brighton(tmp_path_factory):
    return _run(tmp_path_factory, "brighton_beach", geo=False)


@pytest.fixture(scope="module")
def brighton_gps(tmp_path_factory):
    return _run(tmp_path_factory, "brighton_beach", geo=True)


@pytest.fixture(scope="module")
def seneca(tmp_path_factory):
    return _run(tmp_path_factory, "seneca_nir", geo=False)


def gps_rms(rows, poses, frames) -> float:
    """RMS (m) of the frame centres of ``frames`` against GPS after the best similarity."""
    rows = {r.frame: r for r in rows}
    assert len({rows[k].segment for k in frames}) == 1, "the frames are not in one map"
    lat = np.array([float(poses[k]["lat"]) for k in frames])
    lon = np.array([float(poses[k]["lon"]) for k in frames])
    east, north = enu_from_latlon(lat, lon, float(lat[0]), float(lon[0]))
    src = np.array([rows[k].xy for k in frames], float)
    dst = np.c_[east, -north]  # map y points down: (east, south) keeps a proper similarity
    m = similarity_fit(src, dst)
    res = src @ m[:, :2].T + m[:, 2] - dst
    return float(np.sqrt((res ** 2).sum(axis=1).mean()))


def linked(rows, a: int, b: int) -> bool:
    ra, rb = rows[a], rows[b]
    return ra.glued and rb.glued and ra.segment == rb.segment


def test_brighton_strips_map_into_one_piece_that_agrees_with_gps(brighton, brighton_gps):
    strips = range(6, 18)  # DJI_0024-0035: two strips over the beach and the park
    # vision alone: one map (measured 3.3 m RMS over all 18 stills)
    summary, rows, poses = brighton
    assert all(rows[k].glued for k in strips), [(r.frame, r.status) for r in rows]
    assert gps_rms(rows, poses, list(strips)) < 4.0
    # with the stills' GPS (a geo.txt): the map holds to it (measured 1.5 m RMS, 40 m up)
    summary, rows, poses = brighton_gps
    assert all(rows[k].glued for k in strips)
    assert gps_rms(rows, poses, list(strips)) < 2.0
    assert summary["georeference"] is not None and summary["georeference"]["gps_rms_m"] < 2.0
    for a, b in zip(rows, rows[1:]):  # what placed each frame is recorded
        if b.glued and b.status == "registered":
            assert b.extra.get("method") in ("ifmi", "sift", "orb")


def test_brighton_consecutive_motions_agree_with_the_camera_model(brighton):
    """Away from the forest (parallax of the canopy), the implied focal length of each linked
    step is the camera's and its direction is the GPS's (modulo the yaw flips)."""
    summary, rows, poses = brighton
    centre = np.array([499.5, 280.5, 1.0])
    focal, bearing = [], []
    for a, b in zip(rows[6:], rows[7:]):
        if not (linked(rows, a.frame, b.frame) and b.status == "registered"):
            continue
        pa, pb = poses[a.frame], poses[b.frame]
        lat = math.radians(float(pa["lat"]))
        north = (float(pb["lat"]) - float(pa["lat"])) * 111_320.0
        east = (float(pb["lon"]) - float(pa["lon"])) * 111_320.0 * math.cos(lat)
        alt = (float(pa["rel_alt"]) + float(pb["rel_alt"])) / 2
        rel = np.linalg.inv(np.vstack([a.M, [0, 0, 1]])) @ np.vstack([b.M, [0, 0, 1]])
        d = rel @ centre - centre  # where b's centre lies in a's pixels
        focal.append(math.hypot(*d[:2]) * alt / math.hypot(north, east))
        image_bearing = math.degrees(math.atan2(d[0], -d[1])) + float(pa["gimbal_yaw"])
        diff = math.degrees(math.atan2(east, north)) - image_bearing
        bearing.append((diff + 90.0) % 180.0 - 90.0)
    assert len(focal) >= 8
    focal = np.array(focal)
    assert 540 < np.median(focal) < 640
    assert np.all(np.abs(focal / np.median(focal) - 1) < 0.2), focal
    assert np.all(np.abs(bearing) < 10.0), bearing


def test_seneca_overlapping_pairs_are_linked_and_the_turn_is_not_forced(seneca):
    summary, rows, poses = seneca
    strips = [(k, k + 1) for k in list(range(0, 6)) + list(range(10, 16))]  # IMG_0463-0469, 0473-0479
    assert sum(linked(rows, a, b) for a, b in strips) >= 10, [(r.frame, r.status, r.segment) for r in rows]
    for first, last in ((0, 6), (10, 16)):  # each strip is one map
        frames = [k for k in range(first, last + 1) if rows[k].glued]
        assert len(frames) >= 6 and len({rows[k].segment for k in frames}) == 1
        assert gps_rms(rows, poses, frames) < 10.0  # metres, ~70 m up, a fixed-wing without gimbal (tilt)


def test_a_frame_is_never_glued_where_gps_says_it_is_not(brighton, seneca):
    """No confident wrong placement: in every map of three or more stills, each linked step
    agrees with GPS to well under a frame (a wrong placement lands anywhere)."""
    for (summary, rows, poses), half_frame_m in ((brighton, 19.0), (seneca, 30.0)):
        for segment in {r.segment for r in rows if r.glued}:
            seg = [r for r in rows if r.glued and r.segment == segment]
            if len(seg) < 3:
                continue
            lat = np.array([float(poses[r.frame]["lat"]) for r in seg])
            lon = np.array([float(poses[r.frame]["lon"]) for r in seg])
            east, north = enu_from_latlon(lat, lon, float(lat[0]), float(lon[0]))
            m = similarity_fit(np.array([r.xy for r in seg], float), np.c_[east, -north])
            metres_per_px = math.sqrt(abs(np.linalg.det(m[:, :2])))
            for a, b in zip(seg, seg[1:]):
                d_map = math.dist(a.xy, b.xy) * metres_per_px
                d_gps = math.hypot(east[seg.index(b)] - east[seg.index(a)], north[seg.index(b)] - north[seg.index(a)])
                assert abs(d_map - d_gps) < half_frame_m, (a.frame, b.frame, d_map, d_gps)
