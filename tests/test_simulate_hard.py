"""The simulator's hard cases of real flights: each mode produces what it claims, measured from
its output (pixels, files read back), never from its parameters alone."""

from __future__ import annotations

import argparse
import math
import os
import re

import cv2
import numpy as np
import pytest
import yaml

from photomap.config import load_config
from photomap.drivers.images import exif_time
from photomap.errors import ConfigError, InputError
from photomap.io.trajectory_files import read_groundtruth
from photomap.cli import simulate as simulate_cli
from photomap.sim import simulate
from photomap.sim.flight import (Camera, apply_homography, camera_rotation, latlon_to_pixel, pose_homography,
                                 relative_matrix, render_view, simulate_sequence)
from photomap.sim.objects import ObjectScene, SceneObject, box_corners
from photomap.sim.periodic import rows_terrain, tiles_terrain

PIL = pytest.importorskip("PIL", reason="stills need Pillow (ifmi-photomap[sim])")
from PIL import Image  # noqa: E402


# --------------------------------------------------------------------------- helpers

def _autocorrelation_peak(frame: np.ndarray, min_radius: float, across: np.ndarray | None = None) -> np.ndarray:
    """Shift ``(dx, dy)`` (frame px, sub-pixel) of the strongest autocorrelation peak of a
    frame at least ``min_radius`` from zero shift (linear, zero-padded correlation); with the
    unit vector ``across``, at least ``min_radius`` along it (skips the ridge of stripes)."""
    g = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY).astype(np.float64)
    g -= g.mean()
    h, w = g.shape
    spec = np.fft.rfft2(g, s=(2 * h, 2 * w))
    ac = np.fft.fftshift(np.fft.irfft2(spec * np.conj(spec), s=(2 * h, 2 * w)))
    cy, cx = h, w
    yy, xx = np.mgrid[: 2 * h, : 2 * w]
    ac[np.hypot(xx - cx, yy - cy) < min_radius] = -np.inf
    if across is not None:
        ac[np.abs((xx - cx) * across[0] + (yy - cy) * across[1]) < min_radius] = -np.inf
    ac[:, cx + 1:] = -np.inf          # the autocorrelation is symmetric: keep one half
    y, x = np.unravel_index(np.argmax(ac), ac.shape)
    # sub-pixel: parabola through the 3 neighbours in x and in y
    def vertex(a, b, c):
        den = a - 2 * b + c
        return 0.0 if den == 0 or not np.isfinite(den) else 0.5 * (a - c) / den
    fx = vertex(ac[y, x - 1], ac[y, x], ac[y, x + 1]) if np.isfinite(ac[y, x + 1]) else 0.0
    fy = vertex(ac[y - 1, x], ac[y, x], ac[y + 1, x])
    return np.array([x + fx - cx, y + fy - cy])


def _footprint(h: np.ndarray, cam: Camera) -> np.ndarray:
    return apply_homography(h, np.array([[0, 0], [cam.width - 1, 0], [cam.width - 1, cam.height - 1],
                                         [0, cam.height - 1]], float)).astype(np.float32)


def _overlap(h_a: np.ndarray, h_b: np.ndarray, cam: Camera) -> float:
    """Area of the intersection of two ground footprints over the area of one footprint."""
    a, b = _footprint(h_a, cam), _footprint(h_b, cam)
    inter, _ = cv2.intersectConvexConvex(a, b)
    return float(inter) / float(cv2.contourArea(a))


def _warp_error(src: np.ndarray, dst: np.ndarray, m: np.ndarray) -> float:
    """Mean absolute grey difference of ``src`` warped onto ``dst`` by ``m`` (src -> dst), inside
    the eroded overlap."""
    h, w = dst.shape[:2]
    warped = cv2.warpPerspective(src, m, (w, h), flags=cv2.INTER_LINEAR).astype(np.float32)
    inside = cv2.warpPerspective(np.full(src.shape[:2], 255, np.uint8), m, (w, h), flags=cv2.INTER_NEAREST)
    inside = cv2.erode(inside, np.ones((9, 9), np.uint8)) > 0
    diff = np.abs(cv2.cvtColor(warped, cv2.COLOR_BGR2GRAY) - cv2.cvtColor(dst.astype(np.float32), cv2.COLOR_BGR2GRAY))
    return float(diff[inside].mean())


def _read_tlog(path):
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil
    conn = mavutil.mavlink_connection(str(path))
    msgs = []
    while (m := conn.recv_match(blocking=False)) is not None:
        msgs.append(m)
    return msgs


# --------------------------------------------------------------------------- periodic ground

def test_tiles_are_strictly_periodic_only_without_variation_and_stain():
    img = tiles_terrain((400, 400), seed=2, period=64, variation=0.0, stain=0.0)
    assert np.array_equal(img[64:], img[:-64]) and np.array_equal(img[:, 64:], img[:, :-64])
    assert not np.array_equal(img[32:], img[:-32])
    for kw in ({"variation": 0.2, "stain": 0.0}, {"variation": 0.0, "stain": 0.5}):
        other = tiles_terrain((400, 400), seed=2, period=64, **kw)
        diff = np.abs(other[64:].astype(int) - other[:-64].astype(int))
        assert 0.5 < diff.mean() < 20.0, kw                     # faint, but not periodic
    with pytest.raises(InputError):
        tiles_terrain((400, 400), period=4.5)


@pytest.mark.parametrize("kind, variation, stain", [("tiles", 0.0, 0.0), ("tiles", 0.2, 0.5), ("rows", 0.0, 0.0),
                                                    ("rows", 0.15, 0.4)])
def test_period_by_autocorrelation_equals_the_set_period(kind, variation, stain):
    """The autocorrelation of a rendered frame peaks at the terrain period mapped through the
    truth into frame pixels (rotation by the yaw, scale by the altitude)."""
    period = 72
    make = tiles_terrain if kind == "tiles" else rows_terrain
    terrain = make((1536, 1536), seed=4, period=period, variation=variation, stain=stain)
    seq = simulate_sequence(terrain, 3, frame_size=(240, 320), seed=6, fps=1.0, gsd=0.1, altitude=(22.0, 22.0),
                            yaw0=27.0, yaw_mode="fixed", speed=2.0)
    tr = seq.truth
    scale = tr.scale[0]
    assert abs(scale - 1.0) > 0.2                                # frame px differ from terrain px
    a_inv = np.linalg.inv(tr.H[0][:2, :2])
    lattice = [a_inv @ [period, 0.0]] + ([a_inv @ [0.0, period]] if kind == "tiles" else [])
    n = lattice[0] / np.linalg.norm(lattice[0])                 # across the rows, frame px
    for frame in seq.frames[:2]:
        if kind == "tiles":
            peak = _autocorrelation_peak(frame, min_radius=0.5 * period / scale)
            err = min(np.linalg.norm(peak - s * v) for v in lattice for s in (1, -1))
            assert err < 0.5, (peak, lattice)
        else:   # stripes: off the ridge along the rows, the peak is one period across them
            peak = _autocorrelation_peak(frame, min_radius=0.5 * period / scale, across=n)
            assert abs(abs(peak @ n) - period / scale) < 0.5, (peak, lattice)
    # and a wrong period would have been caught: 5 % off is more than 3 px here
    assert 0.05 * period / scale > 3.0


# --------------------------------------------------------------------------- parallax

RED = (30.0, 30.0, 250.0)


def _red_mask(frame: np.ndarray) -> np.ndarray:
    """The red roof: brighter than its walls (<= 0.6 of the roof colour) and than the grass."""
    b, g, r = (frame[..., i].astype(int) for i in range(3))
    return (r > 160) & (g < 100) & (b < 100)


@pytest.mark.parametrize("walls", [False, True])
def test_object_top_parallax_follows_the_pinhole_formula(walls):
    """A red box top at height h under a camera at altitude A appears A/(A-h) times larger than
    its ground footprint, displaced away from the nadir point: measured in rendered frames."""
    gsd, alt_m, hgt_m = 0.1, 30.0, 6.0
    terrain = np.full((1200, 1200, 3), (60, 140, 70), np.uint8)
    box = SceneObject("box", 640.0, 600.0, 60.0, 40.0, 20.0, RED)
    scene = ObjectScene([box], hgt_m, gsd, shape=terrain.shape[:2], walls=walls, max_scale=1.0)
    cam = Camera.from_hfov(480, 360, 60.0)
    alt_px = alt_m / gsd
    f = alt_m / (alt_m - hgt_m)
    centres = []
    for cam_xy, yaw in (((590.0, 560.0), 0.0), ((700.0, 640.0), 35.0), ((610.0, 660.0), -60.0)):
        h = pose_homography(cam, *cam_xy, alt_px, yaw=math.radians(yaw))
        view = scene.composite(render_view([terrain], h, (cam.height, cam.width)), h, *cam_xy, alt_m)
        frame = np.clip(view + 0.5, 0, 255).astype(np.uint8)
        mask = _red_mask(frame)
        # centre of the roof: of its interior, so that edge pixels mixed with wall or grass
        # (which the colour test treats differently) cannot bias it
        ys, xs = np.nonzero(cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)))
        measured = np.array([xs.mean(), ys.mean()])
        hinv = np.linalg.inv(h)
        ground = apply_homography(hinv, np.array([[box.cx, box.cy]]))[0]
        nadir = apply_homography(hinv, np.array([cam_xy]))[0]
        expected = nadir + (ground - nadir) * f                 # pinhole: scale A/(A-h) about nadir
        assert np.linalg.norm(measured - expected) < 0.5, (measured, expected)
        assert np.linalg.norm(expected - ground) > 8.0          # a parallax far above the tolerance
        ground_area = cv2.contourArea(apply_homography(hinv, box_corners(box)).astype(np.float32))
        assert mask.sum() / ground_area == pytest.approx(f * f, rel=0.04)
        centres.append((measured, ground))
        # the ground under the object is hidden: at the footprint's centre we see wall or roof
        gx, gy = np.rint(ground).astype(int)
        seen = frame[gy, gx].astype(int)
        if walls or mask[gy, gx]:
            assert np.abs(seen - (60, 140, 70)).sum() > 40
    # between two frames the top moves by the ground motion plus the pinhole parallax
    (m0, g0), (m1, g1) = centres[0], centres[1]
    assert np.linalg.norm((m1 - m0) - (g1 - g0)) > 5.0


def test_object_top_under_tilt_matches_a_3d_projection():
    """With roll and pitch the top's corners land where a 3-D pinhole projection puts them."""
    gsd, alt_m, hgt_m = 0.1, 30.0, 6.0
    terrain = np.full((1200, 1200, 3), (60, 140, 70), np.uint8)
    box = SceneObject("box", 600.0, 610.0, 80.0, 80.0, 0.0, RED)
    scene = ObjectScene([box], hgt_m, gsd, shape=terrain.shape[:2], walls=False)
    cam = Camera.from_hfov(480, 360, 60.0)
    roll, pitch, yaw = math.radians(12.0), math.radians(-7.0), math.radians(20.0)
    c = np.array([560.0, 580.0, -alt_m / gsd])
    h = pose_homography(cam, c[0], c[1], -c[2], roll, pitch, yaw)
    frame = np.clip(scene.composite(render_view([terrain], h, (cam.height, cam.width)), h, c[0], c[1], alt_m)
                    + 0.5, 0, 255).astype(np.uint8)
    ys, xs = np.nonzero(_red_mask(frame))
    r = camera_rotation(roll, pitch, yaw)                       # camera -> (E, S, D)
    top = np.c_[box_corners(box), np.full(4, -hgt_m / gsd)]
    p = (cam.K @ r.T @ (top - c).T).T
    proj = p[:, :2] / p[:, 2:3]
    poly = proj.astype(np.float32)
    inside = np.array([cv2.pointPolygonTest(poly, (float(x), float(y)), True) >= -1.0 for x, y in zip(xs, ys)])
    frame_rect = np.array([[-0.5, -0.5], [cam.width - 0.5, -0.5], [cam.width - 0.5, cam.height - 0.5],
                           [-0.5, cam.height - 0.5]], np.float32)
    visible, _ = cv2.intersectConvexConvex(poly, frame_rect)
    assert inside.all() and xs.size == pytest.approx(visible, rel=0.03)
    assert visible / cv2.contourArea(poly) < 0.95                # part of it is out of the frame


# --------------------------------------------------------------------------- stills

@pytest.fixture(scope="module")
def stills_flight(tmp_path_factory):
    out = simulate.simulate_flight(tmp_path_factory.mktemp("st") / "sim", terrain="texture", terrain_size=(1024, 1024),
                                   size=(320, 240), seed=5, gsd=0.1, altitude=(20.0, 20.0), speed=6.0,
                                   t0_unix=1_700_000_000.25, mode="stills", strips=3, stills_per_strip=6,
                                   forward_overlap=0.65, side_overlap=0.3)
    return out, yaml.safe_load((out / "meta.yaml").read_text()), read_groundtruth(out / "groundtruth.csv")


def test_stills_overlap_and_strip_turns(stills_flight):
    out, meta, gt = stills_flight
    cam = Camera(meta["camera"]["width"], meta["camera"]["height"], meta["camera"]["fx"])
    stills = sorted((out / "stills").glob("*.jpg"))
    assert len(stills) == len(gt.t) == 18 and not (out / "video.mp4").exists()
    yaw = gt.columns["yaw_deg"]
    for s in range(3):
        k = np.arange(6) + 6 * s
        fwd = [_overlap(gt.H[i], gt.H[i + 1], cam) for i in k[:-1]]
        assert all(0.6 <= o <= 0.7 for o in fwd), fwd
        assert np.ptp(yaw[k]) < 1e-9                            # straight strips
        if s:
            turn = (yaw[k[0]] - yaw[k[0] - 1]) % 360.0
            assert turn == pytest.approx(180.0, abs=1e-6)
            side = _overlap(gt.H[k[0]], gt.H[k[0] - 1], cam)    # strips run back and forth: aligned
            assert side == pytest.approx(0.3, abs=0.02)
    assert np.all(np.diff(gt.t) > 1.0)                          # stills, seconds apart
    # the stills are the pictures of their truth, across a 180-degree turn too
    imgs = [cv2.imread(str(p)) for p in stills]
    for i, j in ((0, 1), (5, 6), (12, 13)):
        m = relative_matrix(gt, i, j)                           # j -> i
        err = _warp_error(imgs[j], imgs[i], m)
        off = _warp_error(imgs[j], imgs[i], np.array([[1, 0, 3.0], [0, 1, 0], [0, 0, 1]]) @ m)
        assert err < 4.0 and off > 1.5 * err, (i, j, err, off)


def test_stills_exif_and_xmp_read_back(stills_flight):
    out, meta, gt = stills_flight
    cam = meta["camera"]
    t0 = meta["t0_unix"]
    origin = meta["origin"]
    gsd = meta["gsd"]
    # the GPS is the camera's nadir point: the frame centre for these nadir stills
    for k, path in enumerate(sorted((out / "stills").glob("*.jpg"))):
        im = Image.open(path)
        exif = im.getexif()
        gps = exif.get_ifd(0x8825)

        def deg(v, ref):
            return (float(v[0]) + float(v[1]) / 60 + float(v[2]) / 3600) * (-1 if ref in ("S", "W") else 1)

        lat, lon = deg(gps[2], gps[1]), deg(gps[4], gps[3])
        px, py = latlon_to_pixel(lat, lon, gsd, origin["lat"], origin["lon"])
        dist_m = math.hypot(px - gt.columns["x"][k], py - gt.columns["y"][k]) * gsd
        assert dist_m < 0.01                                    # brief: 1 m; rationals give ~1e-5 m
        assert float(gps[6]) == pytest.approx(origin["amsl_m"] + gt.columns["alt_m"][k], abs=0.01)
        assert exif_time(path) == pytest.approx(t0 + gt.t[k], abs=1.5e-3)     # the project's reader
        ex = exif.get_ifd(0x8769)
        assert ex[0x9003] == exif[0x0132] and len(ex[0x9291]) == 3
        fx = float(ex[0x920A]) * float(ex[0xA20E]) / 10.0                     # mm * px/cm / (mm/cm)
        assert fx == pytest.approx(cam["fx"], rel=1e-5)
        assert ex[0xA405] == round(cam["fx"] * 43.2666 / math.hypot(cam["width"], cam["height"]))
        xmp = im.info["xmp"].decode()
        attrs = dict(re.findall(r'drone-dji:(\w+)="([^"]*)"', xmp))
        assert float(attrs["RelativeAltitude"]) == pytest.approx(gt.columns["alt_m"][k], abs=1e-3)
        assert float(attrs["GimbalYawDegree"]) == pytest.approx(gt.columns["yaw_deg"][k], abs=0.006)
        assert float(attrs["FlightYawDegree"]) == pytest.approx(gt.columns["yaw_deg"][k], abs=0.006)
        assert float(attrs["GimbalPitchDegree"]) == pytest.approx(-90.0)
        assert float(attrs["CalibratedFocalLength"]) == pytest.approx(cam["fx"], abs=1e-3)
    # the telemetry covers the whole survey, turns included
    msgs = _read_tlog(out / "telemetry.tlog")
    gpi = [m for m in msgs if m.get_type() == "GLOBAL_POSITION_INT"]
    span = gpi[-1]._timestamp - gpi[0]._timestamp
    assert gpi[0]._timestamp < t0 and span > gt.t[-1] + 2.0
    # times where the aircraft is in a turn (between strips) have a heading between the strips'
    hdg = np.array([m.hdg / 100.0 for m in gpi])
    assert np.any((hdg > 100) & (hdg < 260))


def test_stills_hold_yaw_keeps_the_picture_while_the_telemetry_turns(tmp_path):
    out = simulate.simulate_flight(tmp_path / "hold", terrain="texture", terrain_size=(1024, 1024), size=(320, 240),
                                   seed=6, gsd=0.1, altitude=(20.0, 20.0), speed=6.0, t0_unix=1_700_000_000.0,
                                   boot_offset_s=100.0, mode="stills", strips=2, stills_per_strip=4,
                                   forward_overlap=0.7, stills_yaw="hold")
    gt = read_groundtruth(out / "groundtruth.csv")
    meta = yaml.safe_load((out / "meta.yaml").read_text())
    cam = Camera(meta["camera"]["width"], meta["camera"]["height"], meta["camera"]["fx"])
    np.testing.assert_allclose(gt.columns["yaw_deg"], 90.0)                 # the picture never turns
    assert all(0.65 <= _overlap(gt.H[i], gt.H[i + 1], cam) <= 0.75 for i in (0, 1, 2, 4, 5, 6))
    msgs = _read_tlog(out / "telemetry.tlog")
    att = [m for m in msgs if m.get_type() == "ATTITUDE"]
    for k, path in enumerate(sorted((out / "stills").glob("*.jpg"))):
        attrs = dict(re.findall(r'drone-dji:(\w+)="([^"]*)"', Image.open(path).info["xmp"].decode()))
        heading = 90.0 if k < 4 else -90.0                                   # the aircraft turns around
        assert float(attrs["FlightYawDegree"]) == pytest.approx(heading)
        assert float(attrs["GimbalYawDegree"]) == pytest.approx(90.0)
        t = meta["t0_unix"] + gt.t[k]
        a = min(att, key=lambda m: abs(m._timestamp - t))
        assert abs(a._timestamp - t) <= 0.011 and math.degrees(a.yaw) == pytest.approx(heading, abs=0.01)
    imgs = [cv2.imread(str(p)) for p in sorted((out / "stills").glob("*.jpg"))]
    err = _warp_error(imgs[4], imgs[3], relative_matrix(gt, 3, 4))           # across the turn
    assert err < 4.0


# --------------------------------------------------------------------------- bank in turns

def test_coordinated_turns_bank_to_the_limit_and_the_tlog_agrees(tmp_path):
    out = simulate.simulate_flight(tmp_path / "bank", terrain="texture", terrain_size=(2048, 2048), n_frames=240,
                                   size=(160, 120), fps=10.0, seed=2, gsd=0.1, altitude=(25.0, 25.0), speed=15.0,
                                   pattern="figure8", yaw_mode="heading", yaw_rate=0.0, max_bank=30.0,
                                   pitch_offset=3.0, t0_unix=1_700_000_000.0, boot_offset_s=100.0, save_frames=True)
    gt = read_groundtruth(out / "groundtruth.csv")
    roll, pitch, yaw = gt.columns["roll_deg"], gt.columns["pitch_deg"], gt.columns["yaw_deg"]
    assert np.abs(roll).max() == pytest.approx(30.0, abs=1e-9)               # reaches the limit, never more
    assert np.all(np.abs(np.diff(roll)) <= 90.0 / 10.0 + 1e-9)               # rolls at <= 90 deg/s
    np.testing.assert_allclose(pitch, 3.0)
    # the camera's nadir point from the truth matrices: H K = s [[A,0,x],[0,A,y],[0,0,1]] R, so
    # with r3 = the unit third row, x = row0 . r3 / s and y = row1 . r3 / s
    meta = yaml.safe_load((out / "meta.yaml").read_text())
    cam = Camera(meta["camera"]["width"], meta["camera"]["height"], meta["camera"]["fx"])
    q = gt.H @ cam.K
    s = np.linalg.norm(q[:, 2], axis=1)
    r3 = q[:, 2] / s[:, None]
    nadir = np.c_[(q[:, 0] * r3).sum(1), (q[:, 1] * r3).sum(1)] / s[:, None]
    # the bank follows the turn of the path: atan(v * course rate / g)
    vel = np.gradient(nadir * 0.1, 0.1, axis=0)
    course = np.unwrap(np.arctan2(vel[:, 0], -vel[:, 1]))
    rate = np.gradient(course, 0.1)
    expect = np.degrees(np.arctan(np.hypot(vel[:, 0], vel[:, 1]) * rate / 9.80665))
    steady = (np.abs(expect) < 25.0) & (np.abs(np.gradient(expect, 0.1)) < 20.0)   # (smoothed, rate-limited)
    assert steady.sum() > 40 and np.abs(roll[steady] - expect[steady]).max() < 2.5
    hard_right, hard_left = expect > 33.0, expect < -33.0                    # tighter than the limit allows
    assert hard_right.sum() > 3 and hard_left.sum() > 3
    assert np.all(roll[hard_right] > 20.0) and np.all(roll[hard_left] < -20.0)  # right turn: right wing down
    assert (np.abs(roll) == 30.0).sum() > 10                                # held at the limit in turns
    # the tlog: GPS at the nadir point, ATTITUDE = the truth (frames fall on its 50 Hz grid)
    msgs = _read_tlog(out / "telemetry.tlog")
    gpi = {m.time_boot_ms: m for m in msgs if m.get_type() == "GLOBAL_POSITION_INT"}
    att = {m.time_boot_ms: m for m in msgs if m.get_type() == "ATTITUDE"}
    ms = [100_000 + 100 * k for k in range(240)]
    x, y = latlon_to_pixel(np.array([gpi[m].lat / 1e7 for m in ms]), np.array([gpi[m].lon / 1e7 for m in ms]),
                           0.1, meta["origin"]["lat"], meta["origin"]["lon"])
    assert np.hypot(x - nadir[:, 0], y - nadir[:, 1]).max() * 0.1 < 0.02
    for k, m in enumerate(ms):
        a = att[m]
        assert math.degrees(a.roll) == pytest.approx(roll[k], abs=1e-4)
        assert math.degrees(a.pitch) == pytest.approx(pitch[k], abs=1e-4)
        assert (math.degrees(a.yaw) - yaw[k] + 180) % 360 - 180 == pytest.approx(0.0, abs=1e-4)
    hb = [m for m in msgs if m.get_type() == "HEARTBEAT"]
    assert hb and all(m.type == 1 for m in hb)                                # MAV_TYPE_FIXED_WING
    # the banked frames are the pictures of their truth
    frames = [cv2.imread(str(out / "frames" / f"{k:06d}.png")) for k in range(240)]
    k = int(np.argmax(np.abs(roll)))
    m = relative_matrix(gt, k, k + 1)
    err = _warp_error(frames[k + 1], frames[k], m)
    off = _warp_error(frames[k + 1], frames[k], np.array([[1, 0, 2.0], [0, 1, 0], [0, 0, 1]]) @ m)
    assert err < 4.0 and off > 4 * err, (err, off)            # 2 px off is clearly worse


# --------------------------------------------------------------------------- command line

def _cli(argv: list[str], overrides: list[str]) -> int:
    parser = argparse.ArgumentParser()
    simulate_cli.add_arguments(parser)
    return simulate_cli.main(parser.parse_args(argv), load_config(overrides=overrides))


def test_cli_hard_cases(tmp_path, capsys):
    out = tmp_path / "tiles"
    assert _cli(["--out", str(out), "--terrain", "tiles", "--terrain-period", "64", "--terrain-variation", "0",
                 "--terrain-stain", "0", "--objects", "0.05", "--object-height", "4", "--object-size", "3:6",
                 "--frames", "4", "--size", "96x64", "--altitude", "12:12", "--max-bank", "20"],
                ["simulate.terrain_size=768x768", "simulate.t0_unix=1000.0"]) == 0
    meta = yaml.safe_load((out / "meta.yaml").read_text())
    assert meta["terrain"]["period"] == 64 and meta["objects"]["height_m"] == 4.0 and meta["motion"]["max_bank"] == 20.0
    assert meta["objects"]["count"] > 0 and (out / "video.mp4").is_file()
    out = tmp_path / "stills"
    assert _cli(["--out", str(out), "--terrain", "rows", "--mode", "stills", "--strips", "2", "--stills-per-strip", "3",
                 "--forward-overlap", "0.7", "--size", "96x64", "--altitude", "8:8"],
                ["simulate.terrain_size=512x512", "simulate.t0_unix=1000.0"]) == 0
    assert "6 stills" in capsys.readouterr().out
    assert len(list((out / "stills").glob("*.jpg"))) == 6 and (out / "telemetry.tlog").is_file()
    with pytest.raises(InputError):        # too many stills for the terrain: one clear line
        _cli(["--out", str(tmp_path / "x"), "--terrain", "rows", "--mode", "stills", "--strips", "9",
              "--size", "96x64", "--altitude", "8:8"], ["simulate.terrain_size=512x512"])
    with pytest.raises(ConfigError):  # out of range: named by the config check
        _cli(["--out", str(tmp_path / "y"), "--terrain", "tiles", "--terrain-period", "3", "--frames", "2"],
             ["simulate.terrain_size=256x256"])
