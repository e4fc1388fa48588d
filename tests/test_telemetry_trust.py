"""Telemetry that helps or is refused.

- Tilt: a tilted simulated flight mapped with its own telemetry (frames warped to their nadir
  view) is at least as accurate as vision alone, its map equals the terrain (no smeared borders),
  and ``photomap evaluate`` judges the input frames' poses.
- Trust: telemetry of another flight (the real rural.tlog), a GPS track from elsewhere, or no
  sample at all is refused: run.json ``telemetry.status`` says why and the map is not
  georeferenced from it; a log that ends halfway is named once.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
import yaml

from conftest import shared_data
from photomap.cli.replay import replay
from photomap.config import load_config
from photomap.drivers.frames import Frame
from photomap.eval.evaluate import evaluate_run
from photomap.eval.metrics import input_pose
from photomap.geo.georef import nadir_homography, png_to_map, rectifying_homography
from photomap.geometry import to_h
from photomap.io.trajectory_files import read_groundtruth, read_trajectory_csv
from photomap.mapping.telemetry_join import TelemetryJoin, frame_ranges
from photomap.sim.flight import Camera, Motion, pixel_to_latlon, plan_flight, pose_homography
from photomap.sim.simulate import simulate_flight
from photomap.sim.terrain import load_terrain
from photomap.sim.tlog_writer import write_tlog
from photomap.telemetry.samples import TelemetrySample
from photomap.telemetry.timesync import sync_time_offset

W, H = 320, 240


# --------------------------------------------------------------------------- helpers

def run_json(run_dir) -> dict:
    return json.loads((run_dir / "run.json").read_text())


def map_vs_terrain(run_dir, flight_dir) -> np.ndarray:
    """Blurred |map - terrain| (grey levels) at every covered pixel of mosaic.png.

    The terrain is rendered into the PNG through the truth of the run's first frame:
    ``terrain_from_map = H_true[f0] @ inv(input pose of f0)``. A smeared border differs from the
    terrain it covers; a misplaced frame too.
    """
    meta = yaml.safe_load((flight_dir / "meta.yaml").read_text())
    terrain = load_terrain(meta["terrain"]["name"], zoom=meta["terrain"]["zoom"])
    gt = read_groundtruth(flight_dir / "groundtruth.csv")
    run = run_json(run_dir)
    info = run["mosaics"][0]
    w, h = run["frame_size"]
    row = next(r for r in read_trajectory_csv(run_dir / "trajectory.csv")
               if r.glued and r.segment == info["segment"])
    terrain_from_map = gt.H[list(gt.frame).index(row.frame)] @ np.linalg.inv(input_pose(row, ((w - 1) / 2, (h - 1) / 2)))
    terrain_from_png = terrain_from_map @ to_h(png_to_map(info["origin_xy"], info["pixel_scale"]))
    png = cv2.imread(str(run_dir / info["file"]), cv2.IMREAD_UNCHANGED)
    ref = cv2.warpPerspective(terrain, terrain_from_png, png.shape[1::-1],
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    # covered pixels at least 5 px inside the map's outline (the 9x9 blur stays inside)
    covered = cv2.erode((png[..., 3] == 255).astype(np.uint8), np.ones((11, 11), np.uint8)).astype(bool)
    diff = np.abs(cv2.cvtColor(png[..., :3], cv2.COLOR_BGR2GRAY).astype(np.float32)
                  - cv2.cvtColor(ref, cv2.COLOR_BGR2GRAY).astype(np.float32))
    return cv2.blur(diff, (9, 9))[covered]


def truth_centre_latlon(flight_dir):
    meta = yaml.safe_load((flight_dir / "meta.yaml").read_text())
    gt = read_groundtruth(flight_dir / "groundtruth.csv")
    xy = np.array([hk @ [(W - 1) / 2, (H - 1) / 2, 1.0] for hk in gt.H])
    lat, lon = pixel_to_latlon(xy[:, 0] / xy[:, 2], xy[:, 1] / xy[:, 2], meta["gsd"],
                               meta["origin"]["lat"], meta["origin"]["lon"])
    return np.asarray(lat), np.asarray(lon)


def refused_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.levelno == logging.WARNING and r.getMessage().startswith("telemetry refused")]


def assert_not_georeferenced(run_dir, summary):
    assert summary["georeference"] is None and summary["metres_per_pixel"] is None
    for name in ("mosaic.pgw", "mosaic.prj", "map.tif", "track.kml", "track.geojson"):
        assert not (run_dir / name).exists(), name
    header = (run_dir / "trajectory.csv").read_text().splitlines()[0].split(",")
    assert "lat" not in header and "lon" not in header


# --------------------------------------------------------------------------- tilt: geometry

def test_rectifying_homography_is_a_recentred_nadir_view():
    camera = Camera.from_hfov(W, H, 60.0)
    rng = np.random.default_rng(7)
    c = np.array([camera.cx, camera.cy, 1.0])
    for _ in range(5):
        roll, pitch = np.radians(rng.uniform(-15, 15, 2))
        yaw = math.radians(rng.uniform(-180, 180))
        tilted = pose_homography(camera, 800.0, 700.0, 300.0, roll, pitch, yaw)
        nadir = pose_homography(camera, 800.0, 700.0, 300.0, 0.0, 0.0, yaw)
        rect = rectifying_homography(camera.fx, W, H, roll, pitch)
        view = tilted @ np.linalg.inv(rect)  # view pixels -> terrain
        view /= view[2, 2]
        # an exact nadir view: a similarity with the nadir camera's scale and the yaw's angle
        assert np.allclose(view[2], [0, 0, 1], atol=1e-12)
        assert np.allclose(view[:2, :2], nadir[:2, :2] / nadir[2, 2], rtol=1e-9, atol=1e-12)
        # whose centre pixel sees what the tilted frame's centre pixel sees
        assert np.allclose(rect @ c / (rect @ c)[2], c, atol=1e-9)
        # while the plain nadir homography moves it by about fx * tan(tilt)
        moved = nadir_homography(camera.fx, camera.cx, camera.cy, roll, pitch) @ c
        assert np.hypot(*(moved[:2] / moved[2] - c[:2])) > 0.5 * camera.fx * math.tan(max(abs(roll), abs(pitch)))


def test_rectified_frame_mask_fill_and_pose_columns():
    cfg = load_config().updated({"camera": {"fx_px": 277.0}})
    join = TelemetryJoin(lambda t: None, "log", cfg)
    rng = np.random.default_rng(3)
    image = cv2.GaussianBlur(rng.uniform(0, 255, (H, W, 3)).astype(np.float32), (0, 0), 2.0)
    image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    sample = TelemetrySample(t=0.0, roll=math.radians(12.0), pitch=math.radians(-7.0), yaw=0.3)
    view = join.rectify_frame(image, sample, index=4)
    hmg = rectifying_homography(277.0, W, H, sample.roll, sample.pitch)
    assert np.allclose(view.homography, hmg)
    # the mask is 0 wherever bilinear interpolation would read outside the input frame (source
    # beyond its outer pixel centres), and 255 wherever the source is 2 px or more inside
    ys, xs = np.mgrid[0:H, 0:W]
    src = np.linalg.solve(hmg, np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]))
    sx, sy = (src[:2] / src[2]).reshape(2, H, W)
    inside = (sx >= 2.0) & (sx <= W - 3.0) & (sy >= 2.0) & (sy <= H - 3.0)
    outside = (sx < 0.0) | (sx > W - 1.0) | (sy < 0.0) | (sy > H - 1.0)
    assert outside.mean() > 0.02                                      # 12 deg: slivers to fill
    assert (view.mask[inside] == 255).all() and (view.mask[outside] == 0).all()
    # outside pixels hold the mean of the inside ones (neutral for registration: no black edge)
    fill = view.image[view.mask > 0].reshape(-1, 3).mean(axis=0)
    assert np.abs(view.image[view.mask == 0].astype(float) - fill).max() <= 1.0
    # the same mask again for a re-render; the pose columns rebuild the same homography
    assert np.array_equal(join.mask(4), view.mask)
    cols = join.row_columns(4)
    assert cols["rect_fx_px"] == 277.0 and cols["rect_roll_deg"] == pytest.approx(12.0)

    class Row:
        M = np.array([[2.0, 0.0, 5.0], [0.0, 2.0, 7.0]])
        extra = cols
    assert np.allclose(input_pose(Row, ((W - 1) / 2, (H - 1) / 2)), to_h(Row.M) @ hmg)
    assert join.mask(5) is None and join.row_columns(5) == {}   # not rectified
    flat = TelemetrySample(t=0.0, roll=0.001, pitch=0.0)
    assert join.rectify_frame(image, flat, index=6).image is image  # below the tilt threshold


# --------------------------------------------------------------------------- tilt: end to end

@pytest.fixture(scope="module", params=[5.0, 12.0], ids=["tilt5", "tilt12"])
def tilted(request, tmp_path_factory):
    tilt = request.param
    root = tmp_path_factory.mktemp(f"tilt{tilt:g}")
    flight = simulate_flight(root / "sim", terrain="aukerman", n_frames=150, size=(W, H), fps=15.0,
                             seed=11, tilt=tilt)
    with_tel = replay(str(flight / "video.mp4"), root / "tel", load_config(),
                      mavlink=str(flight / "telemetry.tlog"))
    vision = replay(str(flight / "video.mp4"), root / "vision", load_config())
    return tilt, flight, root, with_tel, vision


def test_tilted_flight_with_its_telemetry_is_no_worse_than_vision(tilted):
    tilt, flight, root, with_tel, vision = tilted
    assert with_tel["telemetry"]["status"] == "ok" and with_tel["telemetry"]["rectified"] == 150
    assert with_tel["registered"] == vision["registered"] == 150
    ev_t = evaluate_run(root / "tel", flight / "groundtruth.csv")["headline"]
    ev_v = evaluate_run(root / "vision", flight / "groundtruth.csv")["headline"]
    assert ev_t["frames_posed"] == 150
    assert ev_t["ate"]["pct"] <= ev_v["ate"]["pct"], (ev_t["ate"], ev_v["ate"])
    assert ev_t["ate"]["pct"] < 0.05
    # evaluate judges the input frames: anchored heading and scale of M @ rectification agree
    # with the truth (the rectified view alone differs in scale by ~1/cos(tilt) at the centre)
    assert ev_t["heading_deg"]["max"] < 0.1 and ev_t["scale_pct"]["max"] < 0.2
    assert ev_t["position_px"]["max"] < 1.0


def test_tilted_map_has_no_smear(tilted):
    tilt, flight, root, with_tel, vision = tilted
    diff = map_vs_terrain(root / "tel", flight)
    # the map equals the terrain wherever it has pixels: a smeared border (constant streaks)
    # or the frame's own keystone slivers would differ by tens of grey levels
    assert diff.size > 100_000
    assert np.percentile(diff, 99.9) < 10.0, np.percentile(diff, [50, 99, 99.9])
    assert np.median(diff) < 4.0


def test_tilted_telemetry_georeferences_the_input_frames(tilted):
    tilt, flight, root, with_tel, vision = tilted
    meta = yaml.safe_load((flight / "meta.yaml").read_text())
    gt = read_groundtruth(flight / "groundtruth.csv")
    # the map is frame 0's nadir view: metres per map pixel = gsd * altitude / (fx * gsd)
    assert with_tel["metres_per_pixel"] == pytest.approx(gt.columns["alt_m"][0] / meta["camera"]["fx"], rel=0.01)
    assert with_tel["georeference"]["gps_rms_m"] < 0.2   # GPS fixes at the nadir point, not the centre
    lat, lon = truth_centre_latlon(flight)
    rows = [r for r in read_trajectory_csv(root / "tel" / "trajectory.csv") if r.glued]
    err = [math.hypot((r.extra["lat"] - lat[r.frame]) * 111_320.0,
                      (r.extra["lon"] - lon[r.frame]) * 111_320.0 * math.cos(math.radians(lat[r.frame])))
           for r in rows]
    assert max(err) < 0.5, max(err)   # metres; lat/lon are the input frame centre's
    # x, y of the trajectory are the input frame centre's map position (the view keeps the centre)
    for r in rows[::10]:
        p = input_pose(r, ((W - 1) / 2, (H - 1) / 2)) @ [(W - 1) / 2, (H - 1) / 2, 1.0]
        assert np.allclose(p[:2] / p[2], r.xy, atol=1e-3)


# --------------------------------------------------------------------------- trust

@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    out = tmp_path_factory.mktemp("flight")
    simulate_flight(out, terrain="aukerman", n_frames=60, size=(W, H), fps=15.0, seed=3, yaw_rate=20.0)
    return out


RURAL_T0 = 1723734165.723  # first record of rural.tlog (UNIX s)


@pytest.mark.parametrize("into_log_s", [10.0, 100.0, 150.0])
def test_telemetry_of_another_flight_is_refused(flight, tmp_path, caplog, into_log_s):
    """The real PX4 log (another continent, another flight) joined to a simulated video with a
    video start inside the log: refused, not georeferenced, said once."""
    tlog = shared_data("tlogs") / "rural.tlog"
    caplog.set_level(logging.INFO)
    summary = replay(str(flight / "video.mp4"), tmp_path, load_config(), mavlink=str(tlog),
                     video_start=RURAL_T0 + into_log_s)
    tel = summary["telemetry"]
    assert summary["registered"] == 60
    assert tel["frames_with_telemetry"] > 0
    assert tel["status"] != "ok" and tel["status"] in ("time_sync_refused", "disagrees", "gps_mismatch")
    assert tel["problems"] and tel["problems"][0].startswith(tel["status"])
    assert_not_georeferenced(tmp_path, summary)
    assert run_json(tmp_path)["telemetry"]["status"] == tel["status"]
    assert len(refused_warnings(caplog)) == 1
    # the disagreeing telemetry stopped early: vision alone for the rest of the run
    if tel["stopped_at_frame"] is not None:
        assert tel["frames_ignored"] == 60 - 1 - tel["stopped_at_frame"]
        assert tel["priors_used"] <= tel["stopped_at_frame"]
        stops = [r for r in caplog.records if "ignored for the rest of the run" in r.getMessage()]
        assert len(stops) == 1


def test_the_simulators_own_log_is_accepted(flight, tmp_path, caplog):
    caplog.set_level(logging.INFO)
    summary = replay(str(flight / "video.mp4"), tmp_path, load_config(), mavlink=str(flight / "telemetry.tlog"))
    tel = summary["telemetry"]
    assert tel["status"] == "ok" and tel["problems"] == [] and tel["disagreements"] == 0
    assert tel["time_offset_check"]["refused"] is None and tel["time_offset_check"]["correlation"] > 0.95
    assert summary["georeference"]["crs"].startswith("EPSG:326") and (tmp_path / "mosaic.pgw").is_file()
    assert not refused_warnings(caplog)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING and "telemetry" in r.getMessage()]


def test_no_sample_joined_is_refused(flight, tmp_path, caplog):
    caplog.set_level(logging.INFO)
    meta = yaml.safe_load((flight / "meta.yaml").read_text())
    summary = replay(str(flight / "video.mp4"), tmp_path, load_config(), mavlink=str(flight / "telemetry.tlog"),
                     video_start=meta["t0_unix"] + 3600.0)
    assert summary["telemetry"]["status"] == "no_samples"
    assert summary["telemetry"]["frames_with_telemetry"] == 0
    assert_not_georeferenced(tmp_path, summary)
    assert len(refused_warnings(caplog)) == 1


def write_flight_tlog(flight, path, *, frames=None, reverse_gps=False):
    """The flight's own telemetry (as the simulator writes it), for some frames, or with the GPS
    track played backwards (same place and extent, another shape)."""
    meta = yaml.safe_load((flight / "meta.yaml").read_text())
    gt = read_groundtruth(flight / "groundtruth.csv")
    c = gt.columns
    # the simulator's tlog position is the camera's nadir point: the ground below the camera
    fx, n = meta["camera"]["fx"], len(gt.t)
    below = np.array([hk @ np.linalg.solve(nadir_homography(fx, (W - 1) / 2, (H - 1) / 2, math.radians(r),
                                                            math.radians(p)), [(W - 1) / 2, (H - 1) / 2, 1.0])
                      for hk, r, p in zip(gt.H, c["roll_deg"], c["pitch_deg"])])
    lat, lon = pixel_to_latlon(below[:, 0] / below[:, 2], below[:, 1] / below[:, 2], meta["gsd"],
                               meta["origin"]["lat"], meta["origin"]["lon"])
    if reverse_gps:
        lat, lon = lat[::-1], lon[::-1]
    k = np.arange(n) if frames is None else np.asarray(frames)
    write_tlog(path, gt.t[k], lat[k], lon[k], c["alt_m"][k], c["roll_deg"][k], c["pitch_deg"][k], c["yaw_deg"][k],
               t0_unix=meta["t0_unix"], boot_offset_s=meta["boot_offset_s"], home_amsl_m=meta["origin"]["amsl_m"])
    return path


def test_gps_track_from_elsewhere_is_refused(flight, tmp_path, caplog):
    caplog.set_level(logging.INFO)
    tlog = write_flight_tlog(flight, tmp_path / "reversed.tlog", reverse_gps=True)
    summary = replay(str(flight / "video.mp4"), tmp_path / "run", load_config(), mavlink=str(tlog))
    tel = summary["telemetry"]
    assert tel["status"] == "gps_mismatch", tel["problems"]
    assert tel["disagreements"] == 0   # yaw and heights are right: only the GPS does not fit
    assert_not_georeferenced(tmp_path / "run", summary)
    assert len(refused_warnings(caplog)) == 1


def test_log_ending_halfway_names_the_frames_without_telemetry(flight, tmp_path, caplog):
    caplog.set_level(logging.INFO)
    tlog = write_flight_tlog(flight, tmp_path / "half.tlog", frames=range(30))
    summary = replay(str(flight / "video.mp4"), tmp_path / "run", load_config(), mavlink=str(tlog))
    tel = summary["telemetry"]
    assert tel["status"] == "ok"
    # max_hold keeps the last sample for 0.5 s = 7 frames at 15 fps, plus the log's 1 s padding
    first = 60 - tel["frames_without_telemetry"]
    assert 30 <= first <= 30 + 8 + 15 and tel["frames_missing"] == f"{first}-59"
    named = [r.getMessage() for r in caplog.records
             if r.levelno == logging.WARNING and "have no telemetry" in r.getMessage()]
    assert named == [f"{60 - first} of 60 frames have no telemetry (frames {first}-59): mapped by vision alone"]
    assert not refused_warnings(caplog)
    assert summary["georeference"] is not None   # the half that has telemetry still georeferences


# --------------------------------------------------------------------------- trust: units

def test_priors_stop_after_disagreements_in_a_row(caplog):
    caplog.set_level(logging.INFO)
    cfg = load_config(overrides=["telemetry.max_disagreements_in_a_row=3"])
    s = TelemetrySample(t=0.0, yaw=0.1, height_above_ground=50.0)
    join = TelemetryJoin(lambda t: s, "log", cfg)

    def frame(k):
        return join.sample(Frame(index=k, t=k / 10.0, image=np.zeros((4, 4), np.uint8), source="test"))

    # two overruled, one agreeing (the run ends), then three overruled in a row: stop
    for k, overruled in enumerate([True, True, False, True, True, True]):
        assert frame(k) is s and join.prior(s, s) is not None
        if overruled:
            join.disagreement()
        assert join.stopped == (k == 5)
    assert frame(6) is None and join.prior(s, s) is None        # vision alone from now on
    assert join.stats.stopped_at_frame == 5 and join.stats.frames_ignored == 1
    assert len([r for r in caplog.records if "ignored for the rest of the run" in r.getMessage()]) == 1
    assert join.verdict(None, None) == "disagrees"


def truth_track(n=300, fps=5.0, yaw0=40.0):
    """Nadir flight of ``n`` frames: poses (frame 0 = map), samples with GPS at the frame centre."""
    camera = Camera.from_hfov(W, H, 60.0)
    gsd, lat0, lon0 = 0.1, 41.1, -81.7
    motion = Motion(speed=8.0, yaw_mode="random", yaw_rate=20.0, yaw0=yaw0, altitude=(50.0, 70.0))
    truth = plan_flight(np.ones((6000, 6000), bool), n, camera, fps, gsd, motion, seed=2)
    poses = [(np.linalg.solve(truth.H[0], hk))[:2] for hk in truth.H]
    lat, lon = pixel_to_latlon(truth.x, truth.y, gsd, lat0, lon0)
    samples = [TelemetrySample(t=float(t), lat=float(a), lon=float(o), yaw=math.radians(y), height_above_ground=float(h))
               for t, a, o, y, h in zip(truth.t, lat, lon, truth.yaw_deg, truth.alt_m)]
    return camera, poses, samples, lat, lon


def moved_track(samples, lat, lon, factor=1.0, turn_deg=0.0, frames=None):
    """The GPS track scaled and turned about its first fix (``frames``: only those fixes moved)."""
    e = (lon - lon[0]) * math.cos(math.radians(lat[0]))
    nrt = lat - lat[0]
    a = math.radians(turn_deg)
    e2, n2 = factor * (math.cos(a) * e - math.sin(a) * nrt), factor * (math.sin(a) * e + math.cos(a) * nrt)
    out = []
    for k, (s, x, y) in enumerate(zip(samples, e2, n2)):
        if frames is not None and k not in frames:
            out.append(s)
            continue
        out.append(TelemetrySample(t=s.t, lat=float(lat[0] + y), lon=float(lon[0] + x / math.cos(math.radians(lat[0]))),
                                   yaw=s.yaw, height_above_ground=s.height_above_ground))
    return out


def test_gps_fit_drops_the_camera_scale_and_compass_that_contradict_it():
    """The priors (camera-height scale, compass yaw) are judged by the GPS fit, not the other way
    round: a height off by a factor or a yaw off by a constant leaves the GPS georeference."""
    camera, poses, samples, lat, lon = truth_track()
    cfg = load_config().updated({"camera": {"fx_px": camera.fx}})
    join = TelemetryJoin(lambda t: None, "log", cfg)
    good = join.fit_segment(W, H, poses, samples)
    assert good.geo is not None and good.geo.scale_source == "gps" and good.problem is None and not good.dropped
    assert good.geo.metres_per_px == pytest.approx(good.camera_mpp, rel=0.005)
    assert abs((good.geo.heading_deg - good.compass_heading_deg + 180) % 360 - 180) < 0.5

    # the heights over the take-off point, 0.75 of those over the ground: the scale is the GPS's
    low = [replace(s, height_above_ground=0.75 * s.height_above_ground) for s in samples]
    scaled = join.fit_segment(W, H, poses, low)
    assert scaled.problem is None and [code for code, _ in scaled.dropped] == ["camera_scale"]
    assert "x1.33" in scaled.dropped[0][1]
    assert scaled.metres_per_px == pytest.approx(good.geo.metres_per_px, rel=1e-6)
    assert scaled.camera_mpp == pytest.approx(0.75 * good.camera_mpp, rel=1e-6)
    assert np.allclose(join.georeference(W, H, poses, low)[1].map_to_crs, good.geo.map_to_crs)
    # a gimbal yaw 55 deg off the body's: the heading is the GPS's
    off = [replace(s, yaw=s.yaw + math.radians(55.0)) for s in samples]
    turned = join.fit_segment(W, H, poses, off)
    assert turned.problem is None and [code for code, _ in turned.dropped] == ["compass"]
    assert "turned 55 deg" in turned.dropped[0][1]
    assert np.allclose(turned.geo.map_to_crs, good.geo.map_to_crs)
    assert join.verdict(None, turned) == "ok" and join.problems == [f"compass: {turned.dropped[0][1]}"]
    both = join.fit_segment(W, H, poses, [replace(s, yaw=o.yaw) for s, o in zip(low, off)])
    assert [code for code, _ in both.dropped] == ["camera_scale", "compass"]
    assert join.fit_segment(W, H, poses, moved_track(samples, lat, lon, 1.1, 5.0)).dropped == []  # within tolerance
    # a compass whose logged yaw flips by 180 deg now and then (DJI strip ends) cannot judge the rotation
    flipped = [replace(s, yaw=s.yaw + (math.pi if (k // 40) % 2 else 0.0))
               for k, s in enumerate(moved_track(samples, lat, lon, turn_deg=60.0))]
    assert join.fit_segment(W, H, poses, flipped).dropped == []


def test_gps_fit_refuses_a_track_that_does_not_follow_the_images():
    """Where the GPS itself is wrong it is refused, priors or not: another flight's shape, a
    wrong clock, a track whose halves need different scales or rotations."""
    camera, poses, samples, lat, lon = truth_track()
    cfg = load_config().updated({"camera": {"fx_px": camera.fx}})
    join = TelemetryJoin(lambda t: None, "log", cfg)
    n = len(samples)
    reversed_track = [replace(s, lat=o.lat, lon=o.lon) for s, o in zip(samples, samples[::-1])]
    late = [replace(s, lat=samples[min(k + 25, n - 1)].lat, lon=samples[min(k + 25, n - 1)].lon)
            for k, s in enumerate(samples)]   # the GPS 5 s late
    second = set(range(n // 2, n))
    stretched = moved_track(samples, lat, lon, factor=1.6, frames=second)
    twisted = moved_track(samples, lat, lon, turn_deg=40.0, frames=second)
    for track in (reversed_track, late, stretched, twisted):
        fit = join.fit_segment(W, H, poses, track)
        assert fit.problem is not None and "of 300 GPS fixes fit" in fit.problem, fit
        assert join.georeference(W, H, poses, track)[1] is None
        assert join.verdict(None, fit) == "gps_mismatch" and join.problems[0].startswith("gps_mismatch")
    # a shorter track (60 fixes, 28 m spread), its second half stretched or turned: most fixes
    # still fit one similarity, its halves do not
    camera, poses, samples, lat, lon = truth_track(n=60)
    second = set(range(30, 60))
    for track, why in ((moved_track(samples, lat, lon, factor=1.5, frames=second), "at scales x1.50 apart"),
                       (moved_track(samples, lat, lon, turn_deg=35.0, frames=second), "turned -35 deg apart")):
        fit = join.fit_segment(W, H, poses, track)
        assert fit.problem == f"the two halves of the GPS track fit the vision track {why}", fit
    assert join.fit_segment(W, H, poses, samples).problem is None
    # shorter still (40 fixes): a GPS fit that contradicts the camera's scale and holds only
    # loosely (RMS 3.9 m over 30 m) loses to the prior
    camera, poses, samples, lat, lon = truth_track(n=40)
    fit = join.fit_segment(W, H, poses, moved_track(samples, lat, lon, factor=1.5, frames=set(range(20, 40))))
    assert fit.problem.startswith("the GPS track makes") and "over a track of 30 m spread" in fit.problem
    assert fit.dropped == []


def test_time_sync_tells_refused_from_undecided():
    t = np.arange(0.0, 20.0, 1 / 15)
    rng = np.random.default_rng(1)
    yaw = np.cumsum(rng.normal(0, 1.0, t.size))
    yaw = np.convolve(yaw, np.ones(15) / 15, mode="same") * 3.0          # deg, smooth turns
    tel_t = np.arange(-5.0, 25.0, 0.1)
    same = np.radians(np.interp(tel_t, t, yaw))
    ok = sync_time_offset(t, yaw, tel_t, same)
    assert ok.reason is None and abs(ok.offset_s) < 0.05 and not ok.refused
    other = np.radians(np.cumsum(np.random.default_rng(9).normal(0, 2.0, tel_t.size)))
    bad = sync_time_offset(t, yaw, tel_t, other)
    assert bad.refused and bad.reason in ("weak_correlation", "window_edge") and bad.offset_s is None
    still = sync_time_offset(t, np.zeros_like(t), tel_t, same)
    assert still.reason == "no_yaw_motion" and not still.refused


def test_frame_ranges():
    assert frame_ranges([9, 3, 4, 5]) == "3-5, 9"
    assert frame_ranges(list(range(0, 20, 2)), limit=3) == "0, 2, 4, ..."
