"""Lens model, calibration files and undistortion (photomap.geo.lens, photomap.io.camera_files,
photomap.mapping.frameprep), against the real OpenCV library and the simulator's truth."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from photomap.config import load_config
from photomap.errors import ConfigError, InputError
from photomap.geo.lens import LensModel, Undistortion, folds_inside
from photomap.io.camera_files import read_calibration, read_mask, write_calibration
from photomap.mapping.frameprep import FramePrep, view_points
from photomap.sim.lens import DistortedRender

BROWN = LensModel("brown", 640, 480, 610.0, 612.0, 322.5, 236.0, (-0.28, 0.09, 0.0012, -0.0008, -0.01))
FISHEYE = LensModel("fisheye", 640, 480, 300.0, 300.0, 319.5, 239.5, (0.05, -0.01, 0.002, -0.0005))


@pytest.mark.parametrize("lens", [BROWN, FISHEYE], ids=["brown", "fisheye"])
def test_points_undistort_and_distort_back(lens):
    rng = np.random.default_rng(0)
    pts = rng.uniform([20, 20], [620, 460], (200, 2))
    ideal = lens.undistort_points(pts)
    assert np.abs(ideal - pts).max() > 5  # the lens really bends these points
    np.testing.assert_allclose(lens.distort_points(ideal), pts, atol=1e-6)


def test_scaling_to_the_frame_size_and_refusing_another_aspect():
    half = BROWN.scaled(320, 240)
    assert half.fx == pytest.approx(305.0) and half.cx == pytest.approx((322.5 + 0.5) / 2 - 0.5)
    # the same ray through both: pixel centres scale as (u + 0.5) s - 0.5
    p = np.array([[100.0, 50.0], [600.0, 400.0]])
    np.testing.assert_allclose(half.undistort_points((p + 0.5) / 2 - 0.5), (BROWN.undistort_points(p) + 0.5) / 2 - 0.5,
                               atol=1e-6)
    with pytest.raises(InputError, match="aspect ratio"):
        BROWN.scaled(640, 360)


@pytest.mark.parametrize("lens", [BROWN, FISHEYE], ids=["brown", "fisheye"])
def test_undistortion_maps_invert_the_simulated_lens(lens):
    """A checkerboard seen through the lens (the simulator's forward model), undistorted with
    the maps, is the ideal view again."""
    w, h = lens.width, lens.height
    render = DistortedRender(lens)
    cw, ch = render.canvas
    yy, xx = np.mgrid[0:ch, 0:cw]
    x0, y0 = render.offset
    ideal_canvas = (((xx + x0) // 20 + (yy + y0) // 20) % 2 * 200 + 25).astype(np.float32)
    ideal_canvas = cv2.GaussianBlur(ideal_canvas, (0, 0), 1.5)
    distorted = render.distort(ideal_canvas)
    und = Undistortion.of(lens)
    back = und.apply(distorted)
    truth = ideal_canvas[-y0:-y0 + h, -x0:-x0 + w]
    inner = (und.valid > 0)
    inner[:20], inner[-20:], inner[:, :20], inner[:, -20:] = False, False, False, False
    err = np.abs(back - truth)[inner]
    assert np.median(err) < 2.0 and np.percentile(err, 99) < 20
    assert np.median(np.abs(distorted - truth)[inner]) > 10  # without undistortion it is far off
    assert und.fx == lens.fx


def test_a_brown_model_folding_inside_the_frame_is_recognised():
    fx = 320 / math.tan(math.radians(30))
    assert folds_inside(LensModel("brown", 640, 480, fx, fx, 319.5, 239.5, (-0.3, 0, 0, 0, 0)))
    fx = 320 / math.tan(math.radians(25))
    assert not folds_inside(LensModel("brown", 640, 480, fx, fx, 319.5, 239.5, (-0.3, 0, 0, 0, 0)))
    with pytest.raises(InputError, match="folds"):
        DistortedRender(LensModel("brown", 640, 480, 554.0, 554.0, 319.5, 239.5, (-0.3, 0, 0, 0, 0)))


# ------------------------------------------------------------------------------ files
@pytest.mark.parametrize("suffix", [".yaml", ".json"])
@pytest.mark.parametrize("lens", [BROWN, FISHEYE], ids=["brown", "fisheye"])
def test_filestorage_round_trip(tmp_path, lens, suffix):
    path = tmp_path / f"calib{suffix}"
    write_calibration(path, lens, rms_px=0.31, views=14, board="9x6", square_m=0.025)
    assert read_calibration(path) == lens
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)  # what OpenCV itself reads back
    np.testing.assert_allclose(fs.getNode("camera_matrix").mat(), lens.K)
    assert fs.getNode("avg_reprojection_error").real() == pytest.approx(0.31)
    fs.release()


def test_a_file_written_by_opencv_alone_is_read(tmp_path):
    """The layout of OpenCV's calibration sample: camera_matrix, distortion_coefficients (5x1)."""
    path = tmp_path / "out_camera_data.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("calibration_time", "Tue Dec  1 12:00:00 2026")
    fs.write("image_width", 1280)
    fs.write("image_height", 720)
    fs.write("camera_matrix", np.array([[900.0, 0, 641.0], [0, 901.0, 359.0], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[-0.2], [0.05], [0.0], [0.001], [0.0]]))
    fs.write("avg_reprojection_error", 0.4)
    fs.release()
    lens = read_calibration(path)
    assert (lens.model, lens.width, lens.height, lens.fx, lens.fy, lens.cx, lens.cy) == \
        ("brown", 1280, 720, 900.0, 901.0, 641.0, 359.0)
    assert lens.dist == (-0.2, 0.05, 0.0, 0.001, 0.0)


ROS = """image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [430.215550, 0.000000, 306.691343, 0.000000, 430.531693, 227.224800, 0.000000, 0.000000, 1.000000]
distortion_model: {model}
distortion_coefficients:
  rows: 1
  cols: {n}
  data: [{dist}]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1.000000, 0.000000, 0.000000, 0.000000, 1.000000, 0.000000, 0.000000, 0.000000, 1.000000]
projection_matrix:
  rows: 3
  cols: 4
  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]
"""


def test_ros_camera_info(tmp_path):
    path = tmp_path / "ost.yaml"
    path.write_text(ROS.format(model="plumb_bob", n=5, dist="-0.337586, 0.111476, -0.000923, -0.000067, 0.000000"))
    lens = read_calibration(path)
    assert (lens.model, lens.fx, lens.cy) == ("brown", 430.21555, 227.2248)
    assert lens.dist == (-0.337586, 0.111476, -0.000923, -0.000067, 0.0)
    path.write_text(ROS.format(model="equidistant", n=4, dist="0.01, -0.002, 0.0003, 0.0"))
    lens = read_calibration(path)
    assert lens.model == "fisheye" and lens.dist == (0.01, -0.002, 0.0003, 0.0)


def test_opensfm_cameras_json(tmp_path):
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps({"v2 gopro hero8 3000 4000 brown 0.5208": {
        "projection_type": "brown", "width": 3000, "height": 4000, "focal_x": 0.5207834102328533,
        "focal_y": 0.5207834102328533, "c_x": -0.010331518981731644, "c_y": -0.0036169971231284,
        "k1": -0.10638507280457302, "k2": 0.06769290794144624, "p1": -0.0009394968204580917,
        "p2": -0.0007005575451251272, "k3": -0.005369531191619131}}))
    lens = read_calibration(path)
    assert lens.fx == pytest.approx(0.5207834102328533 * 4000)
    assert lens.cx == pytest.approx(1499.5 - 0.010331518981731644 * 4000)
    assert lens.dist[:2] == (-0.10638507280457302, 0.06769290794144624) and lens.dist[4] == -0.005369531191619131
    path.write_text(json.dumps({"c": {"projection_type": "perspective", "width": 4000, "height": 3000,
                                      "focal": 0.8333, "k1": -0.123, "k2": 0.045}}))
    lens = read_calibration(path)
    assert (lens.fx, lens.cx, lens.cy, lens.dist) == (0.8333 * 4000, 1999.5, 1499.5, (-0.123, 0.045, 0.0, 0.0, 0.0))
    path.write_text(json.dumps({"c": {"projection_type": "fisheye", "width": 4000, "height": 3000,
                                      "focal": 0.5, "k1": -0.02, "k2": 0.001}}))
    assert read_calibration(path).dist == (-0.02, 0.001, 0.0, 0.0)


@pytest.mark.parametrize("text, message", [
    ("\x00\x01garbage: [", "not YAML or JSON"),
    ("just: a mapping\n", "no camera_matrix"),
    ('{"a": {"projection_type": "spherical", "width": 10, "height": 10, "focal": 0.5}}', "not supported"),
    ("camera_matrix: {rows: 3, cols: 3, data: [1, 2, 3]}\nimage_width: 10\nimage_height: 10\n", "3 values for 3x3"),
    ("camera_matrix: {rows: 3, cols: 3, data: [500, 0, 5, 0, 500, 5, 0, 0, 1]}\n", "image_width"),
])
def test_bad_calibration_files_are_one_clear_error(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        read_calibration(path)
    with pytest.raises(InputError, match="not found"):
        read_calibration(tmp_path / "missing.yaml")


def test_camera_config_conflicts_name_the_key(tmp_path):
    with pytest.raises(ConfigError, match="camera.fx_px"):
        load_config(overrides=["camera.calibration=x.yaml", "camera.fx_px=500"])
    with pytest.raises(ConfigError, match="camera.k4"):
        load_config(overrides=["camera.k4=0.1"])
    with pytest.raises(ConfigError, match="camera.p1"):
        load_config(overrides=["camera.model=fisheye", "camera.p1=0.001"])


def test_frameprep_from_a_calibration_file_scales_it_and_tells_the_focal_length(tmp_path):
    path = tmp_path / "calib.yaml"
    write_calibration(path, BROWN)
    prep = FramePrep.from_config(load_config(overrides=[f"camera.calibration={path}"]))
    prep.setup(320, 240)
    assert prep.fx == pytest.approx(BROWN.fx / 2)
    img = np.full((240, 320, 3), 90, np.uint8)
    assert prep.apply(img).shape == img.shape
    with pytest.raises(InputError, match="aspect ratio"):
        FramePrep.from_config(load_config(overrides=[f"camera.calibration={path}"])).setup(320, 180)
    assert FramePrep.from_config(load_config()) is None  # nothing to do: frames pass untouched


def _spot_centre(img: np.ndarray) -> tuple[float, float]:
    m = cv2.moments(img.astype(np.float32))
    return m["m10"] / m["m00"], m["m01"] / m["m00"]


def test_view_points_follow_a_spot_through_the_undistorted_and_rectified_frames():
    """A spot near the corner of a distorted frame: where the frame's undistortion (and a
    rectifying homography) put its pixels is where view_points puts its centre."""
    from photomap.geo.georef import rectifying_homography

    prep = FramePrep.from_config(load_config(overrides=["camera.k1=-0.3", "camera.hfov_deg=50"]))
    prep.setup(320, 240)
    yy, xx = np.mgrid[:240, :320].astype(np.float32)
    raw = (250.0 * np.exp(-((xx - 285.0) ** 2 + (yy - 205.0) ** 2) / (2 * 1.5 ** 2))).astype(np.uint8)
    view = prep.apply(raw)
    assert prep.undistort_points(np.array([[285.0, 205.0]])) == pytest.approx(np.array([_spot_centre(view)]), abs=0.1)
    assert np.hypot(*(np.array(_spot_centre(view)) - (285.0, 205.0))) > 5.0  # the lens moves it
    hmg = rectifying_homography(prep.fx, 320, 240, math.radians(3.0), math.radians(-2.0))
    tilted = cv2.warpPerspective(view, hmg, (320, 240), flags=cv2.INTER_LINEAR)
    assert view_points(prep, hmg)(np.array([[285.0, 205.0]])) == pytest.approx(np.array([_spot_centre(tilted)]),
                                                                               abs=0.15)
    assert view_points(prep, None)(np.array([[285.0, 205.0]])) == pytest.approx(
        prep.undistort_points(np.array([[285.0, 205.0]])))
    assert view_points(None, None) is None  # the view is the input frame
    assert view_points(None, hmg)(np.array([[10.0, 20.0]])) == pytest.approx(
        cv2.perspectiveTransform(np.array([[[10.0, 20.0]]]), hmg)[0])


def test_distortion_keys_need_a_focal_length():
    prep = FramePrep.from_config(load_config(overrides=["camera.k1=-0.2"]))
    with pytest.raises(InputError, match="focal length"):
        prep.setup(640, 480)


def test_read_mask(tmp_path):
    m = np.full((60, 80), 255, np.uint8)
    m[10:20, 30:50] = 0
    cv2.imwrite(str(tmp_path / "m.png"), m)
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png"), m)
    cv2.imwrite(str(tmp_path / "black.png"), np.zeros((8, 8), np.uint8))
    with pytest.raises(InputError, match="black everywhere"):
        read_mask(tmp_path / "black.png")
    (tmp_path / "junk.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="could not be read"):
        read_mask(tmp_path / "junk.png")


# ------------------------------------------------------------------------------ flights
def _ate_pct(flight, run, overrides=()):
    from photomap.cli.replay import replay
    from photomap.eval.metrics import evaluate_trajectory
    from photomap.geometry import frame_centre
    from photomap.io.trajectory_files import read_groundtruth, read_trajectory_csv

    summary = replay(str(flight / "video.mkv"), run, load_config(overrides=list(overrides)))
    assert summary["registered"] == 120 and summary["segments"] == 1
    head = evaluate_trajectory(read_trajectory_csv(run / "trajectory.csv"), read_groundtruth(flight / "groundtruth.csv"),
                               frame_centre(320, 240))["headline"]
    return head["ate"]["pct"]


def test_a_distorted_flight_maps_as_well_as_a_pinhole_one_when_its_lens_is_given(tmp_path):
    """The same flight rendered through k1 = -0.3 and through an ideal lens: with the lens model
    the map's ATE is that of the ideal lens; without it, it is far worse."""
    from photomap.sim.simulate import simulate_flight

    kw = dict(n_frames=120, size=(320, 240), fps=10.0, seed=3, hfov_deg=50.0, video_codec="ffv1", speed=6.0)
    pinhole = simulate_flight(tmp_path / "pinhole", **kw)
    distorted = simulate_flight(tmp_path / "distorted", distortion=(-0.3,), **kw)
    import yaml
    meta = yaml.safe_load((distorted / "meta.yaml").read_text())
    assert meta["camera"]["model"] == "brown" and meta["camera"]["distortion"]["k1"] == -0.3
    ideal = _ate_pct(pinhole, tmp_path / "run_pinhole")
    with_model = _ate_pct(distorted, tmp_path / "run_model", ["camera.k1=-0.3", "camera.hfov_deg=50"])
    without = _ate_pct(distorted, tmp_path / "run_without")
    assert with_model <= ideal + 0.01  # percent of the path: no worse than the ideal lens
    assert without > 0.1 and without > 20 * with_model


def test_simulate_flags_record_the_lens_and_the_overlay(tmp_path):
    import yaml
    from photomap.cli import main as cli

    out = tmp_path / "sim"
    assert cli.main(["simulate", "--out", str(out), "--frames", "3", "--size", "160x120", "--hfov", "50",
                     "--k1", "-0.2", "--k2", "0.05", "--overlay", "--codec", "ffv1", "-q"]) == 0
    meta = yaml.safe_load((out / "meta.yaml").read_text())
    assert meta["camera"]["distortion"] == {"k1": -0.2, "k2": 0.05, "p1": 0.0, "p2": 0.0, "k3": 0.0}
    assert meta["overlay"]["mask"] == "mask.png"
    mask = read_mask(out / "mask.png")
    assert mask.shape == (120, 160) and 0.02 < (mask == 0).mean() < 0.3
    assert cli.main(["simulate", "--out", str(tmp_path / "bad"), "--frames", "3", "--size", "160x120",
                     "--k1", "-0.3", "-q"]) == 3  # folds inside a 60-degree frame: refused
