"""Georeferencing and telemetry-join math against exact truth: the simulator's flights and tlogs,
published UTM coordinates, and a rendered mosaic."""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import DATA_DIR

from photomap.drivers.mavlink import load_tlog
from photomap.sim.tlog_writer import write_tlog
from photomap.errors import InputError
from photomap.sim.flight import (Camera, Motion, Truth, apply_homography, build_pyramid, pixel_to_latlon, plan_flight,
                            pose_homography, relative_matrix, render_view)
from photomap.geo.georef import (aux_xml_text, compose, enu_from_latlon, epsg_zone, fit_georeference, focal_px,
                            latlon_from_enu, map_heading_deg, metres_per_pixel, nadir_homography, nadir_pixel,
                            parse_world_file, png_to_map, prj_text, telemetry_prior,
                            utm_epsg, utm_forward, utm_inverse, utm_zone, world_file_text)
from photomap.config import MosaicConfig
from photomap.core.mosaic import TiledMosaic
from photomap.geometry import pose_angle_deg, pose_scale
from photomap.telemetry.samples import TelemetrySample
from photomap.telemetry.timesync import estimate_time_offset

ORIGIN = (41.1, -81.7)   # the simulator's default geodetic origin of terrain pixel (0, 0)
GSD = 0.3                # metres per terrain pixel
T0 = 1_700_000_000.0     # Unix time of frame 0


@dataclass
class Flight:
    truth: Truth
    camera: Camera
    fps: float
    buffer: object        # TelemetryBuffer loaded from the flight's telemetry.tlog
    t0_unix: float


def fly(tmp_path, *, n=300, fps=10.0, seed=0, t0_unix=T0, **motion) -> Flight:
    """Plan a simulated flight, write its telemetry.tlog as `photomap simulate` does, load it back."""
    camera = Camera.from_hfov(320, 240, 60.0)
    truth = plan_flight(np.ones((3000, 3000), bool), n, camera, fps, GSD, Motion(**motion), seed)
    lat, lon = pixel_to_latlon(truth.cam_x, truth.cam_y, GSD, *ORIGIN)
    path = tmp_path / f"flight{seed}.tlog"
    write_tlog(path, truth.t, lat, lon, truth.alt_m, truth.roll_deg, truth.pitch_deg, truth.yaw_deg,
               t0_unix=t0_unix)
    buffer, _ = load_tlog(path)
    return Flight(truth, camera, fps, buffer, t0_unix)


def true_poses(truth: Truth, map_scale: float) -> np.ndarray:
    """Exact poses (n, 2, 3): frame pixels -> map pixels, the map = frame 0's pixels * map_scale."""
    m = np.diag([map_scale, map_scale, 1.0]) @ np.linalg.inv(truth.H[0]) @ truth.H
    return (m / m[:, 2:3, 2:3])[:, :2]


def map_px_to_terrain(truth: Truth, map_scale: float) -> np.ndarray:
    """3x3 map pixels -> terrain pixels for :func:`true_poses`."""
    return truth.H[0] @ np.diag([1 / map_scale, 1 / map_scale, 1.0])


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    return fly(tmp_path_factory.mktemp("flight"), n=300, fps=5.0, speed=8.0, yaw_rate=20.0)


# --------------------------------------------------------------------------- UTM and the tangent plane

# (lat, lon, zone epsg, easting, northing, tolerance m). GeographicLib's GeoConvert documentation
# example (cm); the others are published test vectors of UTM converters (sub-mm digits).
UTM_REFERENCE = [
    (33.3, 44.4, 32638, 444140.54, 3684706.36, 0.006),
    (35.720122, 139.752899, 32654, 387203.09, 3953623.37, 0.006),
    (51.0, 60.0, 32641, 289511.142963739, 5654109.17867386, 0.001),
    (37.0, 151.0, 32656, 322037.810222802, 4096742.05929492, 0.001),
    (24.0, 14.0, 32633, 398285.446177773, 2654587.59357066, 0.001),
    (-21.0, 17.0, 32733, 707889.216072834, 7676551.70980184, 0.001),
]


@pytest.mark.parametrize("lat, lon, epsg, easting, northing, tol", UTM_REFERENCE)
def test_utm_forward_matches_published_coordinates(lat, lon, epsg, easting, northing, tol):
    assert utm_epsg(lat, lon) == epsg
    e, n = utm_forward(lat, lon, epsg)
    assert abs(e - easting) < tol and abs(n - northing) < tol
    back = utm_inverse(e, n, epsg)
    assert abs(back[0] - lat) < 1e-8 and abs(back[1] - lon) < 1e-8


def test_utm_identities_zones_and_round_trip():
    # on the central meridian at the equator: the false origin; central meridian of zone z
    assert np.allclose(utm_forward(0.0, 3.0, 32631), (500000.0, 0.0), atol=1e-6)
    assert np.allclose(utm_forward(0.0, -81.0, 32717), (500000.0, 10_000_000.0), atol=1e-6)
    assert (utm_zone(41.1, -81.7), utm_zone(60.0, 5.0), utm_zone(78.0, 15.0), utm_zone(-33.9, 151.2)) == (17, 32, 33, 56)
    assert utm_epsg(-33.9, 151.2) == 32756 and epsg_zone(32756) == (56, False)
    with pytest.raises(ValueError):
        epsg_zone(4326)
    with pytest.raises(InputError):
        utm_zone(85.0, 0.0)
    rng = np.random.default_rng(0)
    lat, lon = rng.uniform(-79, 83, 500), rng.uniform(-180, 180, 500)
    for a, b in zip(lat, lon):
        epsg = utm_epsg(a, b)
        la, lo = utm_inverse(*utm_forward(a, b, epsg), epsg)
        assert abs(la - a) * 111e3 < 1e-3 and abs(lo - b) * 111e3 * math.cos(math.radians(a)) < 1e-3


def test_tangent_plane_round_trip_and_agrees_with_simulator():
    x, y = np.meshgrid(np.linspace(-3000, 3000, 7), np.linspace(-3000, 3000, 7))   # +-900 m
    lat, lon = pixel_to_latlon(x.ravel(), y.ravel(), GSD, *ORIGIN)
    e, n = enu_from_latlon(lat, lon, *ORIGIN)
    # the simulator's plane is equirectangular: 0.1 m off at 900 m from its origin
    assert np.allclose(e, x.ravel() * GSD, atol=0.2) and np.allclose(n, -y.ravel() * GSD, atol=0.2)
    la, lo = latlon_from_enu(e, n, *ORIGIN)
    assert np.allclose(la, lat, atol=1e-10, rtol=0) and np.allclose(lo, lon, atol=1e-10, rtol=0)


# --------------------------------------------------------------------------- metric scale

def test_focal_px_from_camera_config():
    assert focal_px(640, hfov_deg=60.0) == pytest.approx(Camera.from_hfov(640, 480, 60.0).fx)
    assert focal_px(640, fx_px=500.0, hfov_deg=60.0) == 500.0
    assert focal_px(640) is None


def test_metres_per_pixel_from_tlog_heights_matches_truth(flight):
    truth, map_scale = flight.truth, 0.5
    poses = list(true_poses(truth, map_scale))
    heights = [flight.buffer.at(flight.t0_unix + t).height_above_ground for t in truth.t]
    assert all(h is not None for h in heights)
    poses[10] = None                      # unposed frames and frames without telemetry are ignored
    heights[20] = None
    heights[21] = float("nan")
    expected = GSD * truth.scale[0] / map_scale     # terrain metres per map pixel
    got = metres_per_pixel(poses, heights, flight.camera.fx)
    assert got == pytest.approx(expected, rel=0.02)
    assert got == pytest.approx(expected, rel=1e-3)  # rangefinder centimetres are the only error
    assert metres_per_pixel([None, poses[1]], [50.0, None], flight.camera.fx) is None


# --------------------------------------------------------------------------- georeference

def _gps_at_frames(flight: Flight) -> tuple[np.ndarray, np.ndarray]:
    samples = [flight.buffer.at(flight.t0_unix + t) for t in flight.truth.t]
    return np.array([s.lat for s in samples]), np.array([s.lon for s in samples])


def test_georeference_of_noisy_gps_within_metres_of_truth(flight):
    truth, map_scale = flight.truth, 0.5
    poses = true_poses(truth, map_scale)
    centres = poses[:, :, 2] + poses[:, :, :2] @ [flight.camera.cx, flight.camera.cy]
    lat, lon = _gps_at_frames(flight)
    rng = np.random.default_rng(1)
    k_lat = 1.0 / 111_000.0
    k_lon = k_lat / math.cos(math.radians(ORIGIN[0]))
    lat = lat + rng.normal(0, 2.0, len(lat)) * k_lat      # 2 m GPS noise per axis
    lon = lon + rng.normal(0, 2.0, len(lon)) * k_lon
    bad = rng.choice(len(lat), 8, replace=False)          # a few glitches of 40-80 m
    lat[bad] += rng.choice([-1, 1], 8) * rng.uniform(40, 80, 8) * k_lat
    lat = lat.astype(object)
    lat[5] = None                                          # a frame without a fix
    g = fit_georeference(centres, lat, lon)
    assert g is not None and g.scale_source == "gps" and g.epsg == 32617
    assert g.inliers >= g.points - 8 - 5 and g.points == len(lat) - 1
    assert g.rms_m < 4.0
    assert g.metres_per_px == pytest.approx(GSD * truth.scale[0] / map_scale, rel=0.01)
    # true heading of the map's up = yaw of frame 0
    assert abs((g.heading_deg - truth.yaw_deg[0] + 180) % 360 - 180) < 0.5

    # every frame centre (and the map's far corners) within a few metres of the truth
    true_lat, true_lon = pixel_to_latlon(truth.x, truth.y, GSD, *ORIGIN)
    got_lat, got_lon = g.to_latlon(centres)
    e_got, n_got = enu_from_latlon(got_lat, got_lon, *ORIGIN)
    e_true, n_true = enu_from_latlon(true_lat, true_lon, *ORIGIN)
    err = np.hypot(e_got - e_true, n_got - n_true)
    assert err.max() < 2.0
    # UTM coordinates of the map agree with the UTM projection of the true positions
    crs = g.to_crs(centres)
    e_utm, n_utm = utm_forward(true_lat, true_lon, g.epsg)
    assert np.hypot(crs[:, 0] - e_utm, crs[:, 1] - n_utm).max() < 2.0


def test_short_track_needs_the_camera_scale(tmp_path):
    f = fly(tmp_path, n=50, fps=5.0, speed=0.5, yaw_rate=10.0, seed=3)   # 5 m of track: hovering
    truth = f.truth
    poses = true_poses(truth, 1.0)
    centres = poses[:, :, 2] + poses[:, :, :2] @ [f.camera.cx, f.camera.cy]
    lat, lon = _gps_at_frames(f)
    rng = np.random.default_rng(2)
    lat = lat + rng.normal(0, 1.5, len(lat)) / 111_000.0
    assert fit_georeference(centres, lat, lon) is None
    heights = [f.buffer.at(f.t0_unix + t).height_above_ground for t in truth.t]
    yaws = [f.buffer.at(f.t0_unix + t).yaw for t in truth.t]
    mpp = metres_per_pixel(list(poses), heights, f.camera.fx)
    heading = map_heading_deg(list(poses), yaws)
    assert abs((heading - truth.yaw_deg[0] + 180) % 360 - 180) < 0.1
    g = fit_georeference(centres, lat, lon, metres_per_px=mpp, heading_deg=heading)
    assert g is not None and g.scale_source == "camera"
    corners = np.array([[0, 0], [319, 0], [0, 239], [319, 239]], float)    # frame 0's corners
    true_lat, true_lon = pixel_to_latlon(*apply_homography(truth.H[0], corners).T, GSD, *ORIGIN)
    got = g.to_latlon(corners)
    e_got, n_got = enu_from_latlon(*got, *ORIGIN)
    e_true, n_true = enu_from_latlon(true_lat, true_lon, *ORIGIN)
    assert np.hypot(e_got - e_true, n_got - n_true).max() < 1.5


def test_too_few_fixes_give_none():
    xy = np.zeros((3, 2))
    assert fit_georeference(xy, [41.0, None, 41.0], [-81.0, -81.0, None]) is None


# --------------------------------------------------------------------------- files

def _centroid(img: np.ndarray) -> np.ndarray:
    v, u = np.mgrid[:img.shape[0], :img.shape[1]]
    return np.array([(img * u).sum(), (img * v).sum()]) / img.sum()


def test_png_to_map_locates_a_rendered_mosaic_feature():
    """A smooth blob drawn into the map is found at the same map coordinates through a
    downscaled render's origin and scale (its centroid survives area averaging)."""
    mosaic = TiledMosaic(MosaicConfig(tile_size=64, channels=1, border=0))
    v, u = np.mgrid[:160, :200]
    blob = 240.0 * np.exp(-((u - 93.3) ** 2 + (v - 71.8) ** 2) / (2 * 10.0 ** 2))
    frame = np.round(10.0 + blob).astype(np.uint8)
    m = np.array([[1.0, 0.0, -300.0], [0.0, 1.0, 517.0]])
    mosaic.add(frame, m)
    truth = _centroid(frame.astype(float) - 10.0) + m[:, 2]          # map pixels
    _, _, w, h = mosaic.bounds()
    for scale in (1.0, 0.5, 0.3, 0.17):
        image, _, origin = mosaic.render(scale=scale)
        a = png_to_map(origin, (image.shape[1] / w, image.shape[0] / h))
        got = a[:, :2] @ _centroid(image.astype(float) - 10.0) + a[:, 2]
        assert np.allclose(got, truth, atol=0.05), (scale, got, truth)


def test_world_file_and_prj_round_trip(flight):
    truth = flight.truth
    poses = true_poses(truth, 0.5)
    centres = poses[:, :, 2] + poses[:, :, :2] @ [flight.camera.cx, flight.camera.cy]
    g = fit_georeference(centres, *_gps_at_frames(flight))
    origin, scale = (-1234, 567), 0.25
    affine = compose(g.map_to_crs, png_to_map(origin, scale))
    text = world_file_text(affine)
    assert len(text.splitlines()) == 6
    back = parse_world_file(text)
    assert np.array_equal(back, affine)
    a, d, b, e, c, f = (float(v) for v in text.split())
    assert a * e - b * d < 0                      # image y down, northing up: a reflection
    for u, v in [(0, 0), (37, 12), (1000, 2000)]:
        world = (a * u + b * v + c, d * u + e * v + f)
        map_px = (origin[0] + (u + 0.5) / scale - 0.5, origin[1] + (v + 0.5) / scale - 0.5)
        assert np.allclose(world, g.to_crs(map_px)[0], atol=1e-6)
    assert np.allclose((c, f), g.to_crs(png_to_map(origin, scale)[:, 2])[0], atol=1e-6)   # centre of pixel (0, 0)
    with pytest.raises(InputError):
        parse_world_file("1\n2\n3\n")

    wkt = prj_text(g.epsg)
    assert wkt.startswith('PROJCS["WGS 84 / UTM zone 17N"') and wkt.count("[") == wkt.count("]")
    params = dict(re.findall(r'PARAMETER\["(\w+)",(-?[\d.]+)\]', wkt))
    assert float(params["central_meridian"]) == -81.0 and float(params["false_northing"]) == 0.0
    assert float(params["scale_factor"]) == 0.9996 and float(params["false_easting"]) == 500000.0
    assert wkt.endswith('AUTHORITY["EPSG","32617"]]')
    south = dict(re.findall(r'PARAMETER\["(\w+)",(-?[\d.]+)\]', prj_text(32756)))
    assert float(south["central_meridian"]) == 153.0 and float(south["false_northing"]) == 10_000_000.0
    srs = ET.fromstring(aux_xml_text(g.epsg)).find("SRS").text
    assert srs == wkt


# --------------------------------------------------------------------------- tilt

def test_nadir_homography_rectifies_the_simulators_tilted_view():
    camera = Camera.from_hfov(320, 240, 70.0)
    rng = np.random.default_rng(4)
    for _ in range(5):
        roll, pitch, yaw = np.radians(rng.uniform(-15, 15, 2)).tolist() + [math.radians(rng.uniform(-180, 180))]
        place = (rng.uniform(500, 900), rng.uniform(500, 900), rng.uniform(150, 400))
        tilted = pose_homography(camera, *place, roll=roll, pitch=pitch, yaw=yaw)
        nadir = pose_homography(camera, *place, roll=0.0, pitch=0.0, yaw=yaw)
        rect = nadir_homography(camera.fx, camera.cx, camera.cy, roll, pitch)
        h = nadir @ rect
        assert np.allclose(h / h[2, 2], tilted, rtol=1e-9, atol=1e-9)
        below = apply_homography(tilted, np.array([nadir_pixel(camera.fx, camera.cx, camera.cy, roll, pitch)]))
        assert np.allclose(below, [place[:2]], atol=1e-6)


def test_rectified_tilted_frame_equals_nadir_frame():
    rng = np.random.default_rng(5)
    terrain = cv2.GaussianBlur(rng.uniform(0, 255, (600, 600, 3)).astype(np.float32), (0, 0), 2.0)
    terrain = cv2.normalize(terrain, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    pyramid = build_pyramid(terrain, 2.0)
    camera = Camera.from_hfov(160, 120, 60.0)
    roll, pitch, yaw = math.radians(8.0), math.radians(-6.0), math.radians(30.0)
    tilted = pose_homography(camera, 300, 300, 180, roll=roll, pitch=pitch, yaw=yaw)
    nadir = pose_homography(camera, 300, 300, 180, yaw=yaw)
    img_t = render_view(pyramid, tilted, (120, 160))
    img_n = render_view(pyramid, nadir, (120, 160))
    rect = cv2.warpPerspective(img_t, nadir_homography(camera.fx, camera.cx, camera.cy, roll, pitch), (160, 120),
                               flags=cv2.INTER_CUBIC, borderValue=(-1, -1, -1))
    inside = (rect >= 0).all(axis=2)
    inside = cv2.erode(inside.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert inside.mean() > 0.6
    diff = np.abs(rect - img_n)[inside].mean()
    assert diff < 2.0, diff                                   # grey levels (0..255)
    assert np.abs(img_t - img_n)[inside].mean() > 10 * diff   # the tilt did change the view


# --------------------------------------------------------------------------- priors

def test_telemetry_prior_matches_the_truths_relative_matrix(flight):
    truth = flight.truth
    pairs = [(0, 1), (10, 14), (50, 80), (100, 299), (200, 150)]
    # and the largest yaw change of the flight (crosses +-180 if the flight does)
    pairs.append((int(np.argmin(truth.yaw_deg)), int(np.argmax(truth.yaw_deg))))
    for i, j in pairs:
        si, sj = (flight.buffer.at(flight.t0_unix + truth.t[k]) for k in (i, j))
        angle, scale = telemetry_prior(si, sj)
        rel = relative_matrix(truth, i, j)
        assert abs((angle - pose_angle_deg(rel) + 180) % 360 - 180) < 0.01, (i, j)
        assert scale == pytest.approx(pose_scale(rel), rel=2e-3), (i, j)
    assert telemetry_prior(TelemetrySample(t=0.0), TelemetrySample(t=1.0)) == (None, None)
    a, s = telemetry_prior(TelemetrySample(0.0, yaw=math.radians(170), height_above_ground=40.0),
                           TelemetrySample(1.0, yaw=math.radians(-170)))
    assert a == pytest.approx(20.0) and s is None


# --------------------------------------------------------------------------- time offset

@pytest.mark.parametrize("seed, shift", [(0, 3.37), (1, -6.1), (2, 0.013)])
def test_time_offset_recovered_from_a_shifted_tlog(tmp_path, seed, shift):
    f = fly(tmp_path, n=300, fps=10.0, seed=seed, yaw_rate=20.0, t0_unix=T0 + shift)
    truth = f.truth
    rng = np.random.default_rng(seed)
    angles = truth.yaw_deg - truth.yaw_deg[0] + rng.normal(0, 0.1, len(truth.t))   # vision: 0.1 deg noise
    angles[rng.choice(len(angles), 10, replace=False)] = np.nan                    # unposed frames
    tel_t, tel_yaw = f.buffer.series("yaw")
    got = estimate_time_offset(truth.t, angles, tel_t, tel_yaw, nominal_s=T0)
    assert got is not None
    offset, corr = got
    assert abs(offset - (T0 + shift)) < 0.05
    assert corr > 0.95


def test_time_offset_refused_without_yaw_motion_or_agreement(tmp_path):
    f = fly(tmp_path, n=200, fps=10.0, seed=4, yaw_mode="fixed")
    tel_t, tel_yaw = f.buffer.series("yaw")
    angles = f.truth.yaw_deg - f.truth.yaw_deg[0]
    assert estimate_time_offset(f.truth.t, angles, tel_t, tel_yaw, nominal_s=T0) is None
    # vision sees a turning yaw, the telemetry is another flight's
    g = fly(tmp_path, n=200, fps=10.0, seed=5, yaw_rate=20.0)
    other = fly(tmp_path, n=200, fps=10.0, seed=6, yaw_rate=20.0)
    tel_t, tel_yaw = other.buffer.series("yaw")
    angles = g.truth.yaw_deg - g.truth.yaw_deg[0]
    assert estimate_time_offset(g.truth.t, angles, tel_t, tel_yaw, nominal_s=T0) is None


def test_time_offset_machinery_on_a_real_px4_log():
    """Real, irregular (~7 Hz, jittery) ATTITUDE timing and a real mission's yaw: a 30 fps
    "vision" angle track cut from the log's own yaw (plus 0.1 deg noise) at a known offset is
    found again. (A consistency check of resampling and search; the log has no video.)"""
    path = DATA_DIR / "tlogs" / "rural.tlog"
    if not path.is_file():
        pytest.skip(f"real test data not found: {path}")
    buffer, _ = load_tlog(path)
    tel_t, tel_yaw = buffer.series("yaw")
    ok = np.isfinite(tel_yaw)
    frame_t = np.arange(0.0, 100.0, 1.0 / 30.0)
    rng = np.random.default_rng(7)
    for start in (10.0, 90.0, 180.0):            # the log's first 300 s are continuous
        offset = tel_t[0] + start + 0.123
        angles = np.degrees(np.interp(frame_t + offset, tel_t[ok], tel_yaw[ok])) + rng.normal(0, 0.1, len(frame_t))
        got = estimate_time_offset(frame_t, angles, tel_t, tel_yaw, nominal_s=offset - 4.2)
        assert got is not None and abs(got[0] - offset) < 0.05 and got[1] > 0.9
