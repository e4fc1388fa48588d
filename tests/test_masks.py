"""Frame masks (`--mask`, `capture.mask`): a masked pixel never reaches the map or a registration."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from photomap.config import load_config
from photomap.core.ifmi import Registrar
from photomap.geo.lens import LensModel, Undistortion
from photomap.mapping.frameprep import FramePrep
from photomap.sim.lens import OVERLAY_BGR, Overlay


def magenta_pixels(img: np.ndarray) -> int:
    """Pixels of the overlay's colour (the terrains have none: a clean flight's map has 0)."""
    b, g, r = (img[..., i].astype(int) for i in range(3))
    return int(((np.minimum(b, r) - g) > 90).sum())


def test_the_overlay_mask_covers_what_is_drawn():
    ov = Overlay(320, 240)
    frame = np.full((240, 320, 3), 100, np.uint8)
    ov.draw(frame)
    drawn = np.any(frame != 100, axis=2)
    mask = ov.mask()
    assert drawn.sum() > 500 and not np.any(drawn & (mask != 0))
    assert (mask == 0).mean() < 0.2  # and leaves most of the frame
    assert tuple(int(v) for v in frame[120, 160]) == OVERLAY_BGR  # the crosshair's centre


def test_a_masked_overlay_leaves_registration_to_the_ground():
    """A faint ground under a bright overlay fixed in the frame: the overlay's peak stands at zero
    shift; with the mask in the window the ground's peak is far higher. (Without the mask the
    refinement weights the overlay's misaligned samples down, as a second layer, so both shifts
    end on the ground's.)"""
    rng = np.random.default_rng(0)
    ground = cv2.GaussianBlur(rng.normal(0, 1, (400, 480)).astype(np.float32), (0, 0), 3)
    ground = np.clip(128 + 5 * ground / ground.std(), 0, 255).astype(np.uint8)
    h, w = 240, 320
    a = cv2.cvtColor(ground[60:60 + h, 60:60 + w], cv2.COLOR_GRAY2BGR)
    b = cv2.cvtColor(ground[56:56 + h, 67:67 + w], cv2.COLOR_GRAY2BGR)  # b -> a: shift (7, -4)
    ov = Overlay(w, h)
    ov.draw(a)
    ov.draw(b)
    prep = FramePrep({}, None, ov.mask())
    prep.setup(w, h)
    plain = Registrar((h, w)).register(a, b)
    masked = Registrar((h, w), mask=prep.window((w, h))).register(prep.apply(a), prep.apply(b))
    err = lambda r: math.hypot(r.matrix[0, 2] - 7.0, r.matrix[1, 2] + 4.0)  # noqa: E731
    assert err(masked) < 0.05 and err(plain) < 0.05
    assert masked.confidence > plain.confidence + 0.2


def test_the_mask_is_scaled_to_the_frames_and_undistorted_with_them():
    mask = np.full((60, 80), 255, np.uint8)
    mask[:, :8] = 0  # the left tenth of the raw frame
    prep = FramePrep({}, None, mask)
    prep.setup(640, 480)
    assert prep.mask.shape == (480, 640) and (prep.mask[:, :64] == 0).all() and (prep.mask[:, 64:] == 255).all()
    img = np.full((480, 640, 3), 200, np.uint8)
    img[:, :64] = (255, 0, 255)
    out = prep.apply(img)
    assert magenta_pixels(out) == 0 and magenta_pixels(img) > 0  # filled, the source's frame untouched
    fx = 320 / math.tan(math.radians(30))
    camera = dict(model="brown", fx_px=fx, hfov_deg=0.0, fy_px=0.0, cx_px=0.0, cy_px=0.0, k1=-0.2, k2=0.05,
                  p1=0.0, p2=0.0, k3=0.0, k4=0.0)
    lensed = FramePrep(camera, None, mask)
    lensed.setup(640, 480)
    und = Undistortion.of(LensModel("brown", 640, 480, fx, fx, 319.5, 239.5, (-0.2, 0.05, 0.0, 0.0, 0.0)))
    # the masked band, in the undistorted view, is where the raw frame's band went
    band = und.apply(np.where(np.arange(640) < 64, 0, 255).astype(np.uint8)[None].repeat(480, 0),
                     cv2.INTER_NEAREST)
    assert np.mean((lensed.mask == 0) == (band < 255)) > 0.99
    assert lensed.fx == pytest.approx(fx)


def test_a_mask_that_leaves_nothing_is_refused(tmp_path):
    from photomap.errors import InputError
    mask = np.zeros((48, 64), np.uint8)
    mask[:2, :2] = 255
    with pytest.raises(InputError, match="less than 5 %"):
        FramePrep({}, None, mask).setup(64, 48)


def test_with_the_mask_the_overlay_never_reaches_the_map(tmp_path):
    """A figure-eight with loop closure (re-renders of kept frames) over burned-in OSD: with
    --mask no overlay pixel is in the map and the ATE is that of the flight without the
    overlay; without the mask the overlay is painted along the track."""
    from photomap.cli import main as cli
    from photomap.eval.metrics import evaluate_trajectory
    from photomap.geometry import frame_centre
    from photomap.io.trajectory_files import read_groundtruth, read_trajectory_csv
    from photomap.sim.simulate import simulate_flight
    import json

    kw = dict(n_frames=150, size=(320, 240), fps=10.0, seed=2, pattern="figure8", yaw_mode="heading", speed=6.0,
              terrain_zoom=3.0, gsd=0.1, altitude=(25.0, 35.0), noise=1.0, video_codec="ffv1")
    clean = simulate_flight(tmp_path / "clean", **kw)
    osd = simulate_flight(tmp_path / "osd", osd=True, **kw)
    assert (osd / "mask.png").is_file()

    def run(flight, name, *extra):
        out = tmp_path / name
        assert cli.main(["replay", str(flight / "video.mkv"), "--out", str(out), "--no-progress", "-q", *extra]) == 0
        summary = json.loads((out / "run.json").read_text())
        ate = evaluate_trajectory(read_trajectory_csv(out / "trajectory.csv"),
                                  read_groundtruth(flight / "groundtruth.csv"), frame_centre(320, 240))["headline"]
        return summary, ate["ate"]["pct"], magenta_pixels(cv2.imread(str(out / "mosaic.png")))

    base, base_ate, base_magenta = run(clean, "clean")
    masked, masked_ate, masked_magenta = run(osd, "masked", "--mask", str(osd / "mask.png"))
    _, _, unmasked_magenta = run(osd, "unmasked")
    assert base_magenta == 0
    assert masked["loop_closure"]["corrections"] >= 1  # kept frames were re-rendered
    assert masked_magenta == 0
    assert masked["frame_prep"]["mask"] and 0.02 < masked["frame_prep"]["masked_fraction"] < 0.2
    assert unmasked_magenta > 500
    assert masked["segments"] == base["segments"] == 1 and masked["registered"] == base["registered"]
    assert masked_ate <= base_ate + 0.01  # percent of the path


def test_a_tilted_frame_keeps_its_mask_through_the_rectification():
    """The telemetry's nadir rectification warps the frame mask with the frame: the masked
    corner stays invalid in the view (and the frame's focal length is the lens's)."""
    from photomap.mapping.telemetry_join import TelemetryJoin
    from photomap.telemetry.samples import TelemetrySample

    w, h = 320, 240
    sample = TelemetrySample(t=0.0, roll=math.radians(6.0), pitch=math.radians(-4.0), yaw=0.0)
    join = TelemetryJoin(lambda t: sample, "log", load_config(), video_start=0.0)
    mask = np.full((h, w), 255, np.uint8)
    mask[:60, :80] = 0
    join.use_camera(300.0, mask)
    assert join.focal(w) == 300.0
    img = np.full((h, w, 3), 120, np.uint8)
    view = join.rectify_frame(img, sample, 0)
    assert view.homography is not None
    corner = cv2.perspectiveTransform(np.array([[[40.0, 30.0]]]), view.homography)[0, 0]
    assert view.mask[int(round(corner[1])), int(round(corner[0]))] == 0
    centre = cv2.perspectiveTransform(np.array([[[160.0, 120.0]]]), view.homography)[0, 0]
    assert view.mask[int(round(centre[1])), int(round(centre[0]))] == 255
    assert (join.mask(0) == view.mask).all()  # the same mask when the frame is re-rendered


def test_the_second_opinion_finds_no_keypoints_on_masked_pixels():
    from photomap.core.features import FeatureMatcher

    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.integers(0, 255, (240, 320), dtype=np.uint8), (0, 0), 1.2)
    ov = Overlay(320, 240)
    prep = FramePrep({}, None, ov.mask())
    prep.setup(320, 240)
    weights = prep.window((160, 120))  # the registrar's mask at a working size of half the frame
    sift = FeatureMatcher("sift", working_size=320)
    everywhere, masked = sift.prepare(img), sift.prepare(img, weights)
    hidden = lambda pts: int((ov.mask()[np.round(pts[:, 1]).astype(int), np.round(pts[:, 0]).astype(int)] == 0).sum())  # noqa: E731
    assert hidden(everywhere.points) > 5 and hidden(masked.points) == 0
    assert len(masked) > 0.6 * len(everywhere)
