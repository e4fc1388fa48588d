"""The synthetic flight is the project's ground truth: check that the truth is really true."""

from __future__ import annotations

import argparse
import math
import os

import cv2
import numpy as np
import pytest
import yaml

from photomap.cli import simulate as simulate_cli
from photomap.sim import simulate
from photomap.config import load_config
from photomap.io.trajectory_files import read_groundtruth
from photomap.errors import InputError, PhotomapError
from photomap.sim.flight import (Camera, apply_homography, latlon_to_pixel, pixel_to_latlon, pose_homography,
                            relative_matrix, render_pair, simulate_sequence)
from photomap.sim.terrain import load_terrain, procedural_terrain, valid_mask


@pytest.fixture(scope="module")
def texture():
    return procedural_terrain("texture", size=(1024, 1024), seed=3)


@pytest.fixture(scope="module")
def aukerman():
    img = load_terrain("aukerman", zoom=2.0)
    return img, valid_mask(img)


def _overlap_error(src: np.ndarray, dst: np.ndarray, m: np.ndarray) -> tuple[float, float]:
    """Warp ``src`` onto ``dst`` with the 3x3 ``m`` (src pixels -> dst pixels); mean absolute
    grey-level difference inside the (eroded) overlap, and the overlap fraction."""
    h, w = dst.shape[:2]
    warped = cv2.warpPerspective(src, m, (w, h), flags=cv2.INTER_CUBIC).astype(np.float32)
    inside = cv2.warpPerspective(np.full(src.shape[:2], 255, np.uint8), m, (w, h), flags=cv2.INTER_NEAREST)
    inside = cv2.erode(inside, np.ones((7, 7), np.uint8)) > 0
    diff = np.abs(cv2.cvtColor(warped, cv2.COLOR_BGR2GRAY) - cv2.cvtColor(dst.astype(np.float32), cv2.COLOR_BGR2GRAY))
    return float(diff[inside].mean()), float(inside.mean())


def test_conventions_yaw_roll_pitch():
    cam = Camera.from_hfov(320, 240, 60.0)
    # yaw 90 deg: the image's up direction points east (+x on the terrain)
    h = pose_homography(cam, 500.0, 400.0, 300.0, yaw=math.radians(90.0))
    up = apply_homography(h, np.array([[cam.cx, cam.cy - 10.0]]))[0]
    assert up[0] > 500.0 + 1.0 and abs(up[1] - 400.0) < 1e-9
    assert math.degrees(math.atan2(h[1, 0], h[0, 0])) == pytest.approx(90.0)
    # right wing down (roll > 0) at yaw 0: the camera looks west (-x); nose up: it looks north (-y)
    centre = np.array([[cam.cx, cam.cy]])
    x, y = apply_homography(pose_homography(cam, 500.0, 400.0, 300.0, roll=0.1), centre)[0]
    assert x == pytest.approx(500.0 - 300.0 * math.tan(0.1)) and y == pytest.approx(400.0)
    x, y = apply_homography(pose_homography(cam, 500.0, 400.0, 300.0, pitch=0.1), centre)[0]
    assert x == pytest.approx(500.0) and y == pytest.approx(400.0 - 300.0 * math.tan(0.1))


def test_nadir_matrices_are_similarities_with_stated_yaw_and_scale(texture):
    seq = simulate_sequence(texture, 25, frame_size=(120, 160), seed=1, fps=5.0, gsd=0.1,
                            altitude=(8.0, 12.0), scale_rate=0.2, yaw_rate=40.0, speed=5.0)
    tr, cam = seq.truth, seq.camera
    assert len(seq.frames) == 25 and seq.frames[0].shape == (120, 160, 3) and seq.frames[0].dtype == np.uint8
    a = tr.H[:, :2, :2]
    np.testing.assert_allclose(tr.H[:, 2], np.tile([0.0, 0.0, 1.0], (25, 1)), atol=1e-12)
    np.testing.assert_allclose(a[:, 0, 0], a[:, 1, 1], atol=1e-12)
    np.testing.assert_allclose(a[:, 0, 1], -a[:, 1, 0], atol=1e-12)
    angle = np.degrees(np.arctan2(a[:, 1, 0], a[:, 0, 0]))
    np.testing.assert_allclose((angle - tr.yaw_deg + 180) % 360 - 180, 0.0, atol=1e-9)
    np.testing.assert_allclose(np.sqrt(np.linalg.det(a)), tr.scale, rtol=1e-12)
    np.testing.assert_allclose(tr.scale, tr.alt_m / (cam.fx * 0.1), rtol=1e-12)
    assert np.all((tr.alt_m >= 8.0 - 1e-9) & (tr.alt_m <= 12.0 + 1e-9))
    # the motion is real: yaw and scale change, bounded by the stated peak rates
    dyaw = np.abs((np.diff(tr.yaw_deg) + 180) % 360 - 180)
    assert 1.0 < dyaw.max() <= 40.0 / 5.0 + 1e-9
    dlog = np.abs(np.diff(np.log(tr.alt_m)))
    assert 0.005 < dlog.max() <= 0.2 / 5.0 + 1e-9


@pytest.mark.parametrize("tilt", [0.0, 2.0])
def test_relative_matrix_maps_frame_j_onto_frame_i(aukerman, tilt):
    img, valid = aukerman
    seq = simulate_sequence(img, 12, frame_size=(240, 320), seed=2, valid=valid, fps=2.0, gsd=0.225,
                            altitude=(20.0, 30.0), speed=6.0, yaw_rate=20.0, scale_rate=0.1, tilt=tilt)
    if tilt:
        assert np.abs(seq.truth.H[:, 2, :2]).max() > 1e-6       # a real homography, not affine
    for i, j in [(0, 1), (3, 6), (10, 11)]:
        m = relative_matrix(seq.truth, i, j)
        err, frac = _overlap_error(seq.frames[j], seq.frames[i], m)
        assert frac > 0.3
        assert err < 1.0, (i, j, err)
        # the test can fail: a 2-pixel error of the matrix is clearly visible
        shifted = np.array([[1.0, 0.0, 2.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ m
        assert _overlap_error(seq.frames[j], seq.frames[i], shifted)[0] > 2.0 * err + 2.0


def test_footprints_stay_inside_valid_terrain(aukerman):
    img, valid = aukerman
    for pattern in ("random", "lawnmower", "figure8"):
        seq = simulate_sequence(img, 40, frame_size=(120, 160), seed=5, valid=valid, fps=1.0, gsd=0.225,
                                pattern=pattern, speed=15.0, altitude=(20.0, 30.0), tilt=2.0, yaw_mode="heading",
                                yaw_rate=0.0)
        for hk in seq.truth.H:
            poly = apply_homography(hk, np.array([[0, 0], [159, 0], [159, 119], [0, 119]], float))
            fp = np.zeros(valid.shape, np.uint8)
            cv2.fillConvexPoly(fp, np.rint(poly).astype(np.int32), 1)
            assert fp.sum() > 1000 and not (fp.astype(bool) & ~valid).any(), pattern
    # the bundled orthophoto's white border is invalid, the ground inside valid
    assert not valid[0, 0] and not valid[-1, -1] and valid[valid.shape[0] // 2, valid.shape[1] // 2]
    assert 0.6 < valid.mean() < 0.8


@pytest.mark.parametrize("pattern", ["lawnmower", "figure8"])
def test_closed_patterns_revisit_their_start(texture, pattern):
    seq = simulate_sequence(texture, 80, frame_size=(60, 80), seed=0, fps=1.0, gsd=0.1, pattern=pattern,
                            speed=8.0, altitude=(4.0, 4.0), yaw_mode="heading", yaw_rate=0.0)
    p = np.c_[seq.truth.cam_x, seq.truth.cam_y]
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert np.median(step) == pytest.approx(80.0, rel=1e-3)      # 8 m/s at 0.1 m/px, 1 fps
    assert step.max() <= 80.0 + 1e-6                               # chords of the path in turns
    far = np.linalg.norm(p - p[0], axis=1)
    first_away = np.argmax(far > 300.0)
    assert first_away > 0 and far[first_away:].min() < 80.0


def test_render_pair_truth(texture):
    a, b, m = render_pair(texture, (120, 160), angle_deg=25.0, scale=1.15, shift=(12.0, -7.0), seed=4,
                          base_scale=1.5, noise=1.0)
    assert a.shape == b.shape == (120, 160, 3)
    assert math.degrees(math.atan2(m[1, 0], m[0, 0])) == pytest.approx(25.0)
    assert math.sqrt(np.linalg.det(m[:, :2])) == pytest.approx(1.15)
    np.testing.assert_allclose(m @ [79.5, 59.5, 1.0], [79.5 + 12.0, 59.5 - 7.0])
    err, frac = _overlap_error(b, a, np.vstack([m, [0, 0, 1]]))
    assert frac > 0.4 and err < 4.0
    assert _overlap_error(b, a, np.vstack([m + [[0, 0, 2.0], [0, 0, 0]], [0, 0, 1]]))[0] > 2 * err


def test_procedural_terrains():
    sand = procedural_terrain("sand", size=(512, 512), seed=1)
    grey = cv2.cvtColor(sand, cv2.COLOR_BGR2GRAY).astype(float)
    lo, hi = np.percentile(grey, [0.5, 99.5])
    assert (hi - lo) / (hi + lo) == pytest.approx(0.25, abs=0.02)
    b, g, r = sand.reshape(-1, 3).mean(0)
    assert r > g > b                                               # beige
    grass = procedural_terrain("grass", size=(512, 512), seed=1)
    b, g, r = grass.reshape(-1, 3).mean(0)
    assert g > r > b                                               # green
    np.testing.assert_array_equal(grass, procedural_terrain("grass", size=(512, 512), seed=1))
    assert not np.array_equal(grass, procedural_terrain("grass", size=(512, 512), seed=2))
    # no tiling: the two halves of a terrain are uncorrelated
    for img in (sand, grass, procedural_terrain("texture", size=(512, 512), seed=1)):
        g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(float)
        assert abs(np.corrcoef(g[:, :256].ravel(), g[:, 256:].ravel())[0, 1]) < 0.5
        assert valid_mask(img).all()
    with pytest.raises(InputError):
        load_terrain("no-such-terrain")


def test_latlon_round_trip():
    lat, lon = pixel_to_latlon(np.array([0.0, 1000.0]), np.array([0.0, -2000.0]), 0.1, 41.1, -81.7)
    assert lat[0] == 41.1 and lon[0] == -81.7
    assert (lat[1] - 41.1) * 111_000 == pytest.approx(200.0, rel=0.01)  # 2000 px north at 0.1 m
    x, y = latlon_to_pixel(lat, lon, 0.1, 41.1, -81.7)
    np.testing.assert_allclose(np.c_[x, y], [[0.0, 0.0], [1000.0, -2000.0]], atol=1e-6)


def test_simulate_flight_files(tmp_path):
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    out = simulate.simulate_flight(tmp_path / "sim", terrain="texture", terrain_size=(768, 768), n_frames=30,
                                   size=(160, 120), fps=10.0, seed=7, gsd=0.1, t0_unix=1_700_000_000.0,
                                   boot_offset_s=100.0, altitude=(8.0, 10.0), tilt=1.0, yaw_rate=30.0,
                                   speed=4.0, save_frames=True)
    meta = yaml.safe_load((out / "meta.yaml").read_text())
    assert meta["camera"]["width"] == 160 and meta["camera"]["cx"] == 79.5 and meta["gsd"] == 0.1
    gt = read_groundtruth(out / "groundtruth.csv")
    assert list(gt.frame) == list(range(30))
    np.testing.assert_allclose(gt.t, np.arange(30) / 10.0)
    centre = np.einsum("nij,j->ni", gt.H, [79.5, 59.5, 1.0])
    np.testing.assert_allclose(centre[:, :2] / centre[:, 2:], np.c_[gt.columns["x"], gt.columns["y"]], atol=1e-6)

    cap = cv2.VideoCapture(str(out / "video.mp4"))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    assert len(frames) == 30 and frames[0].shape == (120, 160, 3)
    assert len(list((out / "frames").glob("*.png"))) == 30
    png = cv2.imread(str(out / "frames" / "000010.png")).astype(float)
    assert np.abs(png - frames[10]).mean() < 6.0                    # same picture, mp4v-compressed

    conn = mavutil.mavlink_connection(str(out / "telemetry.tlog"))
    msgs = []
    while (m := conn.recv_match(blocking=False)) is not None:
        msgs.append(m)
    types = {m.get_type() for m in msgs}
    assert types == {"HEARTBEAT", "SYSTEM_TIME", "ATTITUDE", "GLOBAL_POSITION_INT", "VFR_HUD", "ALTITUDE",
                     "DISTANCE_SENSOR"}
    log_span = 2.9 + 2 * 1.0                                        # frames span 2.9 s, padded 1 s each side
    for name, hz in {"ATTITUDE": 50, "GLOBAL_POSITION_INT": 10, "DISTANCE_SENSOR": 20, "HEARTBEAT": 1}.items():
        n = sum(m.get_type() == name for m in msgs)
        assert abs(n - log_span * hz) <= 1.0, (name, n)  # message counts, not a timing
    assert conn.WIRE_PROTOCOL_VERSION == "2.0"
    plain = mavutil.mavlogfile(str(out / "telemetry.tlog"))     # the mmap reader's index pass fakes losses
    while plain.recv_match() is not None:
        pass
    assert plain.mav_count == len(msgs) and plain.mav_loss == 0  # sequence numbers advance
    att = {m.time_boot_ms: m for m in msgs if m.get_type() == "ATTITUDE"}
    gpi = {m.time_boot_ms: m for m in msgs if m.get_type() == "GLOBAL_POSITION_INT"}
    for k in range(30):
        ms = 100_000 + 100 * k
        a = att[ms]
        assert abs(a._timestamp - (1_700_000_000.0 + k / 10.0)) < 1e-5
        assert (math.degrees(a.yaw) - gt.columns["yaw_deg"][k] + 180) % 360 - 180 == pytest.approx(0.0, abs=1e-4)
        assert math.degrees(a.roll) == pytest.approx(gt.columns["roll_deg"][k], abs=1e-4)
        g = gpi[ms]
        assert g.relative_alt == round(gt.columns["alt_m"][k] * 1000)
        # GPS = the camera's nadir point; without roll/pitch it would be the frame centre
        px, py = latlon_to_pixel(g.lat / 1e7, g.lon / 1e7, 0.1, meta["origin"]["lat"], meta["origin"]["lon"])
        nadir = apply_homography(gt.H[k], np.array([[79.5, 59.5]]))[0]
        tilt_offset = gt.columns["alt_m"][k] / 0.1 * math.tan(math.radians(2.0))
        assert math.hypot(px - nadir[0], py - nadir[1]) < tilt_offset


def _cli(argv: list[str], overrides: list[str]) -> int:
    parser = argparse.ArgumentParser()
    simulate_cli.add_arguments(parser)
    return simulate_cli.main(parser.parse_args(argv), load_config(overrides=overrides))


def test_cli(tmp_path, capsys):
    out = tmp_path / "cli"
    rc = _cli(["--out", str(out), "--terrain", "sand", "--frames", "6", "--size", "96x64", "--altitude", "5:6",
               "--noise", "2", "--jpeg", "80"], ["simulate.terrain_size=512x512", "simulate.t0_unix=1000.0"])
    assert rc == 0 and str(out) in capsys.readouterr().out
    meta = yaml.safe_load((out / "meta.yaml").read_text())
    assert meta["terrain"]["name"] == "sand" and meta["effects"]["noise"] == 2.0 and meta["t0_unix"] == 1000.0
    assert meta["motion"]["altitude"] == [5.0, 6.0]
    assert len(read_groundtruth(out / "groundtruth.csv").t) == 6
    for bad in (["--altitude", "6:5"], ["--size", "big"], ["--terrain", str(tmp_path / "missing.png")]):
        with pytest.raises(PhotomapError):  # a bad value (ConfigError) or a missing terrain (InputError)
            _cli(["--out", str(out), "--frames", "2", *bad], ["simulate.terrain_size=256x256"])


def test_lossless_codec_reproduces_the_frames(tmp_path):
    """--codec ffv1 writes video.mkv whose decoded frames are exactly the rendered ones."""
    out = simulate.simulate_flight(tmp_path / "f", n_frames=8, size=(160, 120), seed=3, save_frames=True,
                                   video_codec="ffv1")
    cap = cv2.VideoCapture(str(out / "video.mkv"))
    for k in range(8):
        ok, frame = cap.read()
        assert ok
        assert np.array_equal(frame, cv2.imread(str(out / "frames" / f"{k:06d}.png")))
    assert not cap.read()[0]
