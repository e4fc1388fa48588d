"""Hazard spots: the detector (flight-relative threshold, size limits, colour), the tracker (one
hazard per spot over many frames, final positions from the corrected poses) and a simulated
flight with planted hot spots replayed with hazards on (found within 2 m, none false, none twice)."""

from __future__ import annotations

import csv
import json
import math
import socket
import threading
import time
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest

from photomap.cli import main as cli
from photomap.cli.wiring import hazard_tracker
from photomap.config import Config, HazardsConfig
from photomap.core.hotspots import FlightLevels, HotSpotDetector
from photomap.core.records import PoseRow
from photomap.errors import ConfigError
from photomap.geo.georef import enu_from_latlon
from photomap.mapping.events import FrameEvent
from photomap.mapping.hazards import HazardTracker
from photomap.sim.hotspots import read_hotspots_csv

W, H = 320, 240


def ground(seed: int, mean: float = 100.0, sigma: float = 8.0, size=(H, W)) -> np.ndarray:
    """A grey 'cool ground' frame: smooth noise about ``mean``."""
    rng = np.random.default_rng(seed)
    g = cv2.GaussianBlur(rng.normal(0, 1, size).astype(np.float32), (0, 0), 2.0)
    g = mean + sigma * g / g.std()
    return np.clip(g, 0, 255).astype(np.uint8)


def disc(img: np.ndarray, x: float, y: float, r: float, value: float) -> np.ndarray:
    """``img`` with a disc of ``value`` (anti-aliased over ~1 px) centred on pixel (x, y)."""
    yy, xx = np.mgrid[: img.shape[0], : img.shape[1]].astype(np.float32)
    a = np.clip(r + 0.5 - np.hypot(xx - x, yy - y), 0, 1)
    if img.ndim == 3:
        a = a[..., None]
    return np.clip(img * (1 - a) + np.asarray(value, np.float32) * a, 0, 255).astype(img.dtype)


# ---------------------------------------------------------------------------------- detector
def test_a_spot_is_found_at_its_centre_with_its_area_and_peak():
    det = HotSpotDetector(detect_px=0)
    for k in range(10):
        assert len(det.detect(ground(k))) == 0  # plain ground: nothing
    blobs = det.detect(disc(ground(99), 123.3, 87.6, 6.0, 250))
    assert len(blobs) == 1
    assert np.hypot(*(blobs.xy[0] - (123.3, 87.6))) < 0.3
    assert 0.6 * math.pi * 36 < blobs.area[0] < 1.3 * math.pi * 36
    assert blobs.peak[0] == 250


def test_the_threshold_is_relative_to_the_flight_not_to_the_frame():
    """A frame of cool ground with a patch at the flight's usual level: a detector that has seen
    the flight finds nothing; one judging the frame against itself would call the patch hot."""
    cool = ground(5, mean=50, sigma=3)
    cool[100:130, 100:130] = 130
    fresh = HotSpotDetector(detect_px=0)
    assert len(fresh.detect(cool)) == 1  # against itself: the patch stands out
    flight = HotSpotDetector(detect_px=0)
    for k in range(30):
        flight.detect(ground(k))
    assert len(flight.detect(cool)) == 0
    assert flight.last_threshold > 140


def test_a_uniformly_warm_frame_is_no_hazard_and_a_hot_spot_in_it_still_is():
    det = HotSpotDetector(detect_px=0)
    for k in range(30):
        det.detect(ground(k))
    assert len(det.detect(ground(50, mean=200))) == 0  # all warm together: no spot
    blobs = det.detect(disc(ground(51), 200.0, 60.0, 5.0, 250))  # and the next spot is found
    assert len(blobs) == 1


def test_size_limits_and_the_border():
    det = HotSpotDetector(detect_px=0, min_area_px=20, max_area_px=2000)
    for k in range(10):
        det.detect(ground(k))
    assert len(det.detect(disc(ground(20), 100, 100, 1.5, 250))) == 0      # ~7 px: too small
    assert len(det.detect(disc(ground(21), 160, 120, 40.0, 250))) == 0     # ~5000 px: too large
    assert len(det.detect(disc(ground(22), 2.0, 120, 6.0, 250))) == 0      # cut by the border
    assert len(det.detect(disc(ground(23), 100, 100, 6.0, 250))) == 1      # ~113 px: a spot


def test_detection_on_a_shrunk_frame_gives_input_pixels():
    big = disc(ground(3, size=(480, 640)), 400.2, 300.7, 10.0, 250)
    blobs = HotSpotDetector(detect_px=320).detect(cv2.merge([big, big, big]))  # BGR: its luminance
    assert len(blobs) == 1
    assert np.hypot(*(blobs.xy[0] - (400.2, 300.7))) < 0.5
    assert 0.8 * math.pi * 100 < blobs.area[0] < 1.2 * math.pi * 100


def test_uint16_radiometric_frames():
    det = HotSpotDetector(detect_px=0, min_excess=400)
    frames = [ground(k).astype(np.uint16) * 100 for k in range(5)]  # ~10000 +- 800
    for f in frames:
        assert len(det.detect(f)) == 0
    hot = frames[0].copy()
    hot[50:60, 70:80] = 30000
    blobs = det.detect(hot)
    assert len(blobs) == 1 and blobs.peak[0] == 30000
    assert np.hypot(*(blobs.xy[0] - (74.5, 54.5))) < 0.01


def test_colour_anomaly():
    field = np.zeros((H, W, 3), np.uint8)
    field[:] = (40, 120, 60)  # green ground
    field = disc(field, 80, 90, 6, (40, 150, 255))     # orange: found
    field = disc(field, 220, 90, 6, (255, 80, 40))     # blue: not the target colour
    blobs = HotSpotDetector("colour", detect_px=0).detect(field)
    assert len(blobs) == 1 and np.hypot(*(blobs.xy[0] - (80, 90))) < 0.3


def test_flight_levels_median_and_mad():
    lv = FlightLevels(256, window_frames=1e9, stride=1)
    values = np.array([10, 11, 12, 13, 100], np.uint8)  # median 12, MAD 1
    lv.add(values.reshape(1, -1))
    assert lv.median_mad() == (12.0, 1.0)


# ---------------------------------------------------------------------------------- tracker
def _shifted(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """The frame of a camera moved by (dx, dy) map px: frame px = map px - (dx, dy)."""
    m = np.float32([[1, 0, -dx], [0, 1, -dy]])
    return cv2.warpAffine(img, m, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def _event(k: int, image: np.ndarray, pose: np.ndarray, segment: int = 0) -> FrameEvent:
    return FrameEvent(k, k / 10.0, False, image, (W, H), "registered", pose, 0.9, segment)


def _translation(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]])


def test_one_spot_over_many_frames_is_one_hazard(tmp_path):
    """The camera moves over a spot at map (150.4, 110.7): 40 frames see it, one hazard, at its
    map position; a spot seen in one frame only (a glint) is no hazard."""
    world = disc(ground(1, size=(H + 100, W + 100)), 150.4, 110.7, 5.0, 250)[:H + 100, :W + 100]
    sent: list[str] = []
    tracker = HazardTracker(HazardsConfig(enabled=True, detect_px=0), tmp_path, send_status=sent.append)
    rows = []
    for k in range(40):
        dx, dy = 1.5 * k - 20, 0.7 * k - 10
        frame = _shifted(world[:H + 100, :W + 100], dx, dy)[:H, :W].copy()
        if k == 20:
            frame = disc(frame, 280, 200, 4, 250)  # a glint in one frame
        tracker.on_frame(_event(k, frame, _translation(dx, dy)))
        rows.append(PoseRow(k, k / 10.0, _translation(dx, dy), 0.9, "registered", 0))
    live = tracker.hazards()["features"]
    assert len(live) == 1 and live[0]["geometry"] is None  # no telemetry: no WGS84
    assert sent == ["photomap: hazard 1 at map 150,111"]
    info = tracker.finish(rows, [])
    assert info["count"] == 1
    p = tracker.hazards()["features"][0]["properties"]
    assert p["id"] == 1 and p["frames"] == 40 and p["first_seen"] == 0 and p["last_seen"] == 39
    assert math.hypot(p["x_px"] - 150.4, p["y_px"] - 110.7) < 0.5
    assert p["lat"] is None and p["uncertainty_m"] is None
    with open(tmp_path / "hazards.csv", newline="") as f:
        got = list(csv.DictReader(f))
    assert [r["id"] for r in got] == ["1"] and got[0]["lat"] == ""


def test_a_spot_is_placed_through_the_view_the_pose_maps(tmp_path):
    """The pipeline gave the map another view of the frame (undistorted, rectified): the event's
    view_points take the blob there before the pose; live and final positions are the pose of the
    view pixel, not of the input pixel."""
    import dataclasses

    from photomap.mapping.frameprep import view_points

    to_view = view_points(None, np.array([[1.1, 0.02, -5.0], [0.0, 1.1, -4.0], [2e-5, 0.0, 1.0]]))
    frame = disc(ground(5), 250.0, 180.0, 5.0, 250)
    tracker = HazardTracker(HazardsConfig(enabled=True, detect_px=0), tmp_path)
    rows = []
    for k in range(6):
        tracker.on_frame(dataclasses.replace(_event(k, frame, _translation(10, 20)), view_points=to_view))
        rows.append(PoseRow(k, k / 10.0, _translation(40, -5), 0.9, "registered", 0))  # corrected at the end
    (vx, vy), = to_view(np.array([[250.0, 180.0]]))
    assert math.hypot(vx - 250.0, vy - 180.0) > 10  # the view moves the spot
    live = tracker.hazards()["features"][0]["properties"]
    assert (live["x_px"], live["y_px"]) == pytest.approx((vx + 10, vy + 20), abs=0.3)
    tracker.finish(rows, [])
    final = tracker.hazards()["features"][0]["properties"]
    assert (final["x_px"], final["y_px"]) == pytest.approx((vx + 40, vy - 5), abs=0.3)


def test_two_passes_split_by_drift_become_one_hazard_with_the_corrected_poses(tmp_path):
    """Live, the second pass's poses have drifted by 60 px: the spot is a second hazard then. The
    final (loop-corrected) poses put both passes on one spot: one hazard, the first one's id."""
    world = disc(ground(2), 160.0, 120.0, 5.0, 250)
    tracker = HazardTracker(HazardsConfig(enabled=True, detect_px=0), tmp_path)
    rows = []
    for k in range(10):
        tracker.on_frame(_event(k, world, _translation(0, 0)))
        rows.append(PoseRow(k, k / 10.0, _translation(0, 0), 0.9, "registered", 0))
    for k in range(40, 50):
        tracker.on_frame(_event(k, world, _translation(60, 0)))  # drifted live
        rows.append(PoseRow(k, k / 10.0, _translation(0, 0), 0.9, "registered", 0))  # corrected
    assert [f["properties"]["id"] for f in tracker.hazards()["features"]] == [1, 2]
    tracker.finish(rows, [])
    final = tracker.hazards()["features"]
    assert len(final) == 1
    p = final[0]["properties"]
    assert p["id"] == 1 and p["frames"] == 20 and p["last_seen"] == 49
    assert math.hypot(p["x_px"] - 160.0, p["y_px"] - 120.0) < 0.3


def test_one_spot_seen_from_two_georeferenced_segments_is_one_hazard_in_wgs84(tmp_path):
    """The map lost track: the spot is a hazard in segment 0 and again in segment 1 live; both
    segments are georeferenced, the spot is at one UTM position in both: one hazard in the files,
    at that position, its uncertainty the georeference's GPS RMS (the sightings agree)."""
    from photomap.geo.georef import utm_inverse

    world = disc(ground(6), 160.0, 120.0, 5.0, 250)
    tracker = HazardTracker(HazardsConfig(enabled=True, detect_px=0), tmp_path)
    rows = []
    for k, seg, pose in [(k, 0, _translation(0, 0)) for k in range(10)] + \
                        [(k, 1, _translation(-100, 0)) for k in range(20, 30)]:
        tracker.on_frame(_event(k, world, pose, segment=seg))
        rows.append(PoseRow(k, k / 10.0, pose, 0.9, "registered", seg))
    assert len(tracker.hazards()["features"]) == 2  # live: one per segment
    maps = [{"segment": 0, "georeference": {"crs": "EPSG:32617", "gps_rms_m": 0.5,
                                            "map_to_crs": [[0.1, 0.0, 500000.0], [0.0, -0.1, 4550000.0]]}},
            {"segment": 1, "georeference": {"crs": "EPSG:32617", "gps_rms_m": 0.5,
                                            "map_to_crs": [[0.1, 0.0, 500010.0], [0.0, -0.1, 4550000.0]]}}]
    assert tracker.finish(rows, maps)["count"] == 1
    (f,) = tracker.hazards()["features"]
    lat, lon = utm_inverse(np.array([500016.0]), np.array([4549988.0]), 32617)
    assert f["geometry"]["coordinates"] == pytest.approx([lon[0], lat[0]], abs=1e-7)
    p = f["properties"]
    assert p["id"] == 1 and p["frames"] == 20 and p["uncertainty_m"] == pytest.approx(0.5, abs=0.01)


def test_hazards_is_safe_to_read_from_another_thread(tmp_path):
    world = disc(ground(3), 160.0, 120.0, 5.0, 250)
    tracker = HazardTracker(HazardsConfig(enabled=True, detect_px=0), tmp_path)
    seen, stop = [], threading.Event()

    def read():
        while not stop.is_set():
            fc = tracker.hazards()
            assert fc["type"] == "FeatureCollection"
            seen.append(len(fc["features"]))

    reader = threading.Thread(target=read)
    reader.start()
    try:
        for k in range(60):
            tracker.on_frame(_event(k, world, _translation(0.5 * k, 0)))
    finally:
        stop.set()
        reader.join()
    assert max(seen) == 1
    fc = tracker.hazards()
    fc["features"][0]["properties"]["id"] = 99  # the caller's own copy
    assert tracker.hazards()["features"][0]["properties"]["id"] == 1


def test_statustext_only_on_a_live_link_when_configured(tmp_path):
    class Reader:
        def send_status(self, text):
            pass

    cfg = Config().updated({"hazards": {"enabled": True}, "telemetry": {"send_statustext": True}})
    assert hazard_tracker(cfg, tmp_path, Reader(), live=True).send_status is not None
    assert hazard_tracker(cfg, tmp_path, Reader(), live=False).send_status is None
    assert hazard_tracker(cfg.updated({"hazards": {"statustext": False}}), tmp_path, Reader(), True).send_status is None
    assert hazard_tracker(Config(), tmp_path, Reader(), live=True) is None  # off by default


def test_one_statustext_per_new_hazard_reaches_the_ground_station(tmp_path):
    """Over a real MAVLink link on loopback: the tracker's sender is the reader's send_status; two
    spots seen over 30 frames give exactly two STATUSTEXTs, one each."""
    from pymavlink import mavutil
    from pymavlink.dialects.v20 import common as mavlink

    from photomap.drivers.mavlink import TelemetryReader

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    world = disc(disc(ground(8), 100.0, 120.0, 5.0, 250), 220.0, 100.0, 5.0, 250)
    with TelemetryReader(f"udpin:127.0.0.1:{port}") as reader:
        peer = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
        try:
            peer.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)
            deadline = time.monotonic() + 5.0
            while reader.stats.total == 0 and time.monotonic() < deadline:
                time.sleep(0.02)  # the reader must have heard the peer to know where to send
            tracker = HazardTracker(HazardsConfig(enabled=True, detect_px=0), tmp_path,
                                    send_status=reader.send_status)
            for k in range(30):
                tracker.on_frame(_event(k, world, _translation(0, 0)))
            texts = []
            while (msg := peer.recv_match(type="STATUSTEXT", blocking=True, timeout=1.0)) is not None:
                texts.append(msg.text)
        finally:
            peer.close()
    assert len(texts) == 2
    assert {t.split(" at ")[0] for t in texts} == {"photomap: hazard 1", "photomap: hazard 2"}
    assert {t.split(" at ")[1] for t in texts} == {"map 100,120", "map 220,100"}


def test_bad_hazard_config_names_the_key():
    with pytest.raises(ConfigError, match="hazards.mode"):
        Config().updated({"hazards": {"mode": "smoke"}})
    with pytest.raises(ConfigError, match="hazards.min_area_px"):
        Config().updated({"hazards": {"min_area_px": 500.0, "max_area_px": 100.0}})


# ---------------------------------------------------------------------------------- the flight
def _distance_m(lat, lon, lat0, lon0) -> float:
    e, n = enu_from_latlon(np.array([lat]), np.array([lon]), lat0, lon0)
    return float(np.hypot(e[0], n[0]))


def _fly_and_find(tmp_path, style: str, mode: str, frames: int, n: int, flight=(), replay=(),
                  within_m: float = 2.0) -> dict:
    """Simulate a flight with ``n`` planted spots (``flight``: more simulate flags), replay it with
    hazards on (``replay``: more replay flags) and assert every spot is found once within
    ``within_m`` (also its uncertainty) and nothing else is; returns run.json."""
    sim, out = tmp_path / "sim", tmp_path / "run"
    assert cli.main(["simulate", "--out", str(sim), "--frames", str(frames), "--size", "640x480",
                     "--hotspots", str(n), "--hotspot-style", style, "--seed", "3", *flight, "-q"]) == 0
    truth = read_hotspots_csv(sim / "hotspots.csv")
    assert len(truth) == n
    assert cli.main(["replay", str(sim / "video.mp4"), "--out", str(out), "--mavlink", str(sim / "telemetry.tlog"),
                     "--hazards", "--set", f"hazards.mode={mode}", *replay, "--no-progress", "-q"]) == 0
    run = json.loads((out / "run.json").read_text())
    assert run["georeference"] is not None  # with telemetry: positions in WGS84
    assert run["hazards"]["count"] == n and run["hazards"]["geojson"] == "hazards.geojson"

    gj = json.loads((out / "hazards.geojson").read_text())
    feats = gj["features"]
    assert gj["type"] == "FeatureCollection" and len(feats) == n  # none on plain terrain
    matched = set()
    for f in feats:
        lon, lat = f["geometry"]["coordinates"]
        d = {t["id"]: _distance_m(lat, lon, t["lat"], t["lon"]) for t in truth}
        best = min(d, key=d.get)
        assert d[best] < within_m, f"hazard {f['properties']['id']} is {d[best]:.2f} m from the nearest spot"
        matched.add(best)
        p = f["properties"]
        assert p["frames"] >= 3 and p["first_seen"] <= p["last_seen"] and p["peak"] > 200
        assert p["uncertainty_m"] is not None and p["uncertainty_m"] < within_m
    assert len(matched) == n  # each spot once: none twice

    ns = {"k": "http://www.opengis.net/kml/2.2"}
    marks = ET.parse(out / "hazards.kml").getroot().findall(".//k:Placemark", ns)
    with open(out / "hazards.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(marks) == len(rows) == n
    by_id = {f["properties"]["id"]: f for f in feats}
    for mark, row in zip(marks, rows):
        lon, lat, _ = (float(v) for v in mark.find("k:Point/k:coordinates", ns).text.split(","))
        f = by_id[int(row["id"])]
        assert mark.find("k:name", ns).text == f"hazard {row['id']}"
        assert (lon, lat) == pytest.approx(tuple(f["geometry"]["coordinates"]), abs=1e-9)
        assert (float(row["lat"]), float(row["lon"])) == pytest.approx((lat, lon), abs=1e-9)
        assert int(row["first_seen"]) == f["properties"]["first_seen"]
    return run


@pytest.mark.parametrize("style, mode, frames, n", [("thermal", "hot", 200, 5), ("visible", "colour", 120, 3)])
def test_planted_hot_spots_are_all_found_within_2_m_none_false_none_twice(tmp_path, style, mode, frames, n):
    _fly_and_find(tmp_path, style, mode, frames, n)


def test_planted_hot_spots_are_found_through_a_distorting_lens_as_through_a_pinhole(tmp_path):
    """Frames through k1 = -0.3 with the lens model given: the map is made of the undistorted
    frames, and each spot seen in a distorted frame is taken through the lens model to the pixels
    the pose maps. Found within 0.1 m, uncertainty below 0.1 m, as through an ideal lens (this
    flight without distortion: 0.005 m, 0.015 m; placed from the distorted pixels, a spot seen
    far from the frame centre is off by up to 1 m: 0.5 m off, 0.9 m uncertain)."""
    run = _fly_and_find(tmp_path, "thermal", "hot", 200, 5, flight=["--hfov", "50", "--k1", "-0.3"],
                        replay=["--set", "camera.k1=-0.3", "--set", "camera.hfov_deg=50"], within_m=0.1)
    assert run["frame_prep"]["lens"]["distortion"][0] == -0.3  # the frames were undistorted


def test_planted_hot_spots_are_found_within_2_m_from_tilted_frames(tmp_path):
    """Roll/pitch up to 4 degrees: frames rectified to nadir by the telemetry (the join's tilt
    decision, ``TelemetryJoin.homography``), each spot placed through the rectified view's pose
    (found within 0.02 m)."""
    run = _fly_and_find(tmp_path, "thermal", "hot", 200, 5, flight=["--tilt", "4"], within_m=0.1)
    assert run["telemetry"]["rectified"] > 150


def test_the_viewer_shows_the_hazards_as_points_on_the_map(tmp_path):
    pytest.importorskip("rerun", reason="rerun-sdk is not installed (the `viewer` extra)")
    from rerun.chunk import RrdReader

    from photomap.config import ViewerConfig
    from photomap.live.viewer import Viewer

    world = disc(ground(4), 160.0, 120.0, 5.0, 250)
    tracker = HazardTracker(HazardsConfig(enabled=True, detect_px=0), tmp_path)
    viewer = Viewer("save", str(tmp_path / "view.rrd"), ViewerConfig(tile_hz=1000.0))
    viewer.show_hazards(tracker.hazards)
    for k in range(8):
        event = _event(k, world, _translation(10, 20))
        tracker.on_frame(event)
        viewer.on_frame(event)
    viewer.close()
    points = []
    for chunk in RrdReader(str(tmp_path / "view.rrd")).stream().to_chunks():
        if chunk.entity_path == "/map/hazards":
            rb = chunk.to_record_batch()
            points += [(p, label) for p, label in zip(rb.column("Points2D:positions").to_pylist(),
                                                      rb.column("Points2D:labels").to_pylist())]
    assert points, "no hazard points in the recording"
    (xy,), (label,) = points[-1]
    assert label == "hazard 1"
    assert xy == pytest.approx([170.0, 140.0], abs=0.3)  # frame (160, 120) through the pose


def test_the_simulator_paints_its_spots_where_hotspots_csv_says(tmp_path):
    """Each planted spot's truth (terrain px), taken into a frame through the ground truth, lands
    on hot pixels of that frame; the thermal frames are grey and the ground stays well below."""
    from photomap.io.trajectory_files import read_groundtruth
    from photomap.sim.flight import latlon_to_pixel
    from photomap.sim.simulate import simulate_flight

    out = simulate_flight(tmp_path / "sim", n_frames=40, size=(320, 240), seed=2, hotspots=3, save_frames=True)
    meta = __import__("yaml").safe_load((out / "meta.yaml").read_text())
    truth = read_hotspots_csv(out / "hotspots.csv")
    gt = read_groundtruth(out / "groundtruth.csv")
    assert meta["hotspots"]["count"] == 3
    seen = 0
    for k in range(0, 40, 5):
        frame = cv2.imread(str(out / "frames" / f"{k:06d}.png"))
        assert np.array_equal(frame[..., 0], frame[..., 2])  # grey
        inv = np.linalg.inv(gt.H[k])
        hot = np.zeros(frame.shape[:2], bool)
        for t in truth:
            x, y = latlon_to_pixel(np.array([t["lat"]]), np.array([t["lon"]]), meta["gsd"],
                                   meta["origin"]["lat"], meta["origin"]["lon"])
            assert (x[0], y[0]) == pytest.approx((t["x_px"], t["y_px"]), abs=1e-3)
            u, v, w = inv @ [t["x_px"], t["y_px"], 1.0]
            u, v = u / w, v / w
            if 3 <= u < 317 and 3 <= v < 237:
                assert frame[int(round(v)), int(round(u)), 0] > 200, (k, t["id"])
                cv2.circle(hot, (int(round(u)), int(round(v))), 8, 1, -1)
                seen += 1
        assert frame[..., 0][~hot].max() <= 125  # the ground, away from the spots
    assert seen >= 10


def test_run_json_is_written_once_at_the_end_with_the_hazards_in_it(tmp_path, monkeypatch):
    """The final run.json carries the hazards' summary: one write, not a second one after it."""
    import photomap.mapping.run_outputs as run_outputs

    sim, out = tmp_path / "sim", tmp_path / "run"
    assert cli.main(["simulate", "--out", str(sim), "--frames", "60", "--size", "320x240", "--hotspots", "2",
                     "--seed", "3", "-q"]) == 0
    written = []
    real = run_outputs.write_json

    def counted(path, data, *a, **kw):
        if path.name == "run.json" and data.get("complete"):
            written.append(json.loads(json.dumps(data, default=str)))
        return real(path, data, *a, **kw)

    monkeypatch.setattr(run_outputs, "write_json", counted)
    assert cli.main(["replay", str(sim / "video.mp4"), "--out", str(out), "--mavlink", str(sim / "telemetry.tlog"),
                     "--hazards", "--no-progress", "-q"]) == 0
    assert len(written) == 1
    assert written[0]["hazards"]["geojson"] == "hazards.geojson"
    assert json.loads((out / "run.json").read_text())["hazards"] == written[0]["hazards"]
