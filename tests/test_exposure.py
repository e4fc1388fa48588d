"""Exposure compensation of the map (``mosaic.exposure``) against frames with known gains."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from photomap.config import MosaicConfig, load_config
from photomap.core.exposure import SequentialGain, joint_gains, overlap_ratio
from photomap.core.mosaic import TiledMosaic
from photomap.errors import ConfigError, InputError
from photomap.eval.seams import frame_labels, overlap_steps, seam_steps
from photomap.io.tilestore import MemoryTileStore

FRAME = (120, 160)  # (h, w)


def ground(h: int, w: int, seed: int = 0) -> np.ndarray:
    """Smooth random BGR ground in 40..170: no clipping under the gains used here (<= 1.4)."""
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.normal(0, 1, (h, w, 3)).astype(np.float32), (0, 0), 3)
    t = (t - t.min()) / (t.max() - t.min())
    return np.rint(40 + 130 * t).astype(np.uint8)


def survey(n_strip: int = 6) -> list[np.ndarray]:
    """Poses of a two-strip lawn-mower survey over the ground (2x3, frame -> map pixels): 55 %
    forward and 30 % side overlap, sub-pixel offsets and a slight rotation."""
    h, w = FRAME
    poses = []
    for strip in range(2):
        for i in range(n_strip):
            k = i if strip == 0 else n_strip - 1 - i
            a = np.radians(2.0 * (-1) ** k)
            poses.append(np.array([[np.cos(a), -np.sin(a), 20.3 + 0.45 * w * k],
                                   [np.sin(a), np.cos(a), 20.6 + 0.7 * h * strip]]))
    return poses


def shoot(world: np.ndarray, poses, gains) -> list[np.ndarray]:
    """Frames seen at ``poses`` (inverse warp of the ground), times their gain (scalar or BGR)."""
    h, w = FRAME
    out = []
    for M, g in zip(poses, gains):
        f = cv2.warpAffine(world, M, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        out.append(np.clip(np.rint(f * np.asarray(g, np.float32)), 0, 255).astype(np.uint8))
    return out


def paint(frames, poses, **cfg) -> tuple[TiledMosaic, list]:
    m = TiledMosaic(MosaicConfig(tile_size=64, **cfg))
    gains = []
    for f, M in zip(frames, poses):
        m.add(f, M)
        gains.append(None if m.last_gain is None else m.last_gain.copy())
    return m, gains


GAINS = [1.0, 1.3, 0.8, 1.15, 0.75, 1.25, 0.9, 1.35, 0.8, 1.1, 0.85, 1.2]


@pytest.mark.parametrize("blend", ["overwrite", "feather"])
@pytest.mark.parametrize("mode", ["gain", "channel_gain"])
def test_known_gains_leave_no_step_at_frame_edges(blend, mode):
    world = ground(360, 600)
    poses = survey()
    if mode == "gain":
        gains = GAINS
    else:  # white balance changes too: a different gain per channel
        gains = [np.array([g, g * (1.1 if k % 2 else 0.92), g * (0.9 if k % 3 else 1.08)]) if k else 1.0
                 for k, g in enumerate(GAINS)]
    truth, _ = paint(shoot(world, poses, [1.0] * len(poses)), poses, blend=blend)
    gained = shoot(world, poses, gains)
    raw, _ = paint(gained, poses, blend=blend)
    comp, fitted = paint(gained, poses, blend=blend, exposure=mode)

    t_img, t_alpha, origin = truth.render()
    bounds = (*origin, t_img.shape[1], t_img.shape[0])
    labels = frame_labels(poses, (FRAME[1], FRAME[0]), bounds)
    r_img = raw.render(bounds=bounds)[0]
    c_img, c_alpha, _ = comp.render(bounds=bounds)
    assert (c_alpha == t_alpha).all()

    # the brightness step across the frame edges of the map; what is left of it in the un-gained
    # map is the texture (a seam's few dozen pixels do not average it out entirely)
    floor = seam_steps(t_img, labels)
    before, after = seam_steps(r_img, labels), seam_steps(c_img, labels)
    if blend == "overwrite":
        assert before.level_step > floor.level_step + 25 and before.colour_step > floor.colour_step + 25
    else:  # feathering spreads the step over the overlap: less of it shows across the seam
        assert before.level_step > floor.level_step + 1 and before.colour_step > floor.colour_step + 0.5
    assert after.level_step < floor.level_step + 0.3 and after.colour_step < floor.colour_step + 0.3
    # the same on the same ground, texture-free: each pair of frames meeting at a seam, as
    # recorded and times the fitted gains
    o_before = overlap_steps(gained, poses, [None] * len(poses), labels, origin)
    o_after = overlap_steps(gained, poses, fitted, labels, origin)
    assert o_after[2] == o_before[2] >= 12  # forward and side seams
    assert o_after[0] < o_before[0] / 10 and o_after[1] < o_before[1] / 10

    # the compensated map is the un-gained one (the first frame has gain 1), close to the pull
    # toward each frame's own exposure
    err_raw = np.abs(r_img.astype(float) - t_img)[t_alpha > 0].mean()
    err = np.abs(c_img.astype(float) - t_img)[t_alpha > 0].mean()
    assert err_raw > 10 and err < 2.5, (err_raw, err)


def test_gain_returns_to_the_cameras_over_new_ground():
    """After an exposure jump the map matches the new frames to the old ones, then drifts back
    to the camera's exposure in small steps (bounded drift), as new ground comes in."""
    world = ground(200, 2400, seed=1)
    h, w = FRAME
    poses = [np.array([[1.0, 0.0, 10.5 + 0.4 * w * k], [0.0, 1.0, 20.0]]) for k in range(30)]
    gains = [1.0] + [1.4] * 29
    frames = shoot(world, poses, gains)
    m, fitted = paint(frames, poses, exposure="gain")
    g = np.array([f[0] for f in fitted])
    assert g[0] == 1.0
    assert g[1] == pytest.approx(1 / 1.4, rel=0.03)  # the jump is compensated at once...
    log_g = np.log(g[1:])
    assert np.all(np.diff(log_g) > 0)  # ... then relaxes toward 1, monotonically,
    assert np.all(np.diff(log_g) < 0.02)  # by small steps (2 % per frame here),
    assert abs(log_g[-1]) < 0.5 * abs(log_g[0])  # and half way back after 28 frames (11 footprints)
    # the seam steps stay small all along
    img, _, origin = m.render()
    labels = frame_labels(poses, (w, h), (*origin, img.shape[1], img.shape[0]))
    assert seam_steps(img, labels).level_step < 2.0


def test_clipped_pixels_and_moving_objects_do_not_bias_the_gain():
    rng = np.random.default_rng(2)
    scene = rng.uniform(20, 200, (5000, 3)).astype(np.float32)
    frame = scene.copy()
    mapped = np.clip(scene * 1.25, 0, 255)  # the map is 1.25x brighter...
    mapped[:400] = 255.0  # ... with saturated pixels,
    mapped[400:900] = rng.uniform(0, 255, (500, 3))  # a car that drove off,
    frame[900:1000] = 3.0  # and a black shadow edge in the new frame
    ratio = overlap_ratio(frame, mapped, per_channel=True)
    np.testing.assert_allclose(ratio, 1.25, rtol=0.01)
    assert overlap_ratio(frame[:100], mapped[:100], per_channel=False) is None  # too few samples


def test_sequential_gain_pull_and_hold():
    sg = SequentialGain(3, per_channel=False, pull=0.5)
    frame = np.full((1000, 3), 100.0)
    np.testing.assert_allclose(sg.update(frame, frame * 1.5, new_fraction=0.0), 1.5)  # all overlap
    np.testing.assert_allclose(sg.update(frame, frame * 1.5, new_fraction=0.4), 1.5 ** 0.8)
    empty = np.zeros((0, 3))
    np.testing.assert_allclose(sg.update(empty, empty, new_fraction=1.0), 1.5 ** 0.4)  # no overlap
    sg.reset()
    np.testing.assert_allclose(sg.gain, 1.0)
    np.testing.assert_allclose(sg.update(frame, frame * 2.4, new_fraction=0.0), 2.0)  # clipped


def test_exposure_is_deterministic_and_survives_tile_spills():
    world = ground(360, 600, seed=3)
    poses = survey()
    frames = shoot(world, poses, GAINS)
    a, ga = paint(frames, poses, exposure="channel_gain")
    b, gb = paint(frames, poses, exposure="channel_gain")
    spilled = TiledMosaic(MosaicConfig(tile_size=64, exposure="channel_gain", max_tiles_in_memory=2),
                          MemoryTileStore())
    gs = []
    for f, M in zip(frames, poses):
        spilled.add(f, M)
        gs.append(spilled.last_gain.copy())
    np.testing.assert_array_equal(np.array(ga), np.array(gb))
    np.testing.assert_array_equal(np.array(ga), np.array(gs))
    for other in (b, spilled):
        np.testing.assert_array_equal(a.render()[0], other.render()[0])
    # reset forgets the gains: the same frames give the same map again
    a.reset()
    for f, M in zip(frames, poses):
        a.add(f, M)
    np.testing.assert_array_equal(a.render()[0], b.render()[0])


def test_without_exposure_frames_are_painted_as_they_are():
    frames = shoot(ground(360, 600), survey(), GAINS)
    m, gains = paint(frames, survey())
    assert m.exposure == "none" and gains == [None] * len(frames)
    only = TiledMosaic(MosaicConfig(tile_size=64, exposure="gain"))
    only.add(frames[0], survey()[0])  # the first frame of a map keeps its own exposure
    np.testing.assert_array_equal(only.last_gain, [1.0, 1.0, 1.0])


@pytest.mark.parametrize("per_channel", [False, True])
def test_joint_gains_undo_known_gains_up_to_one_factor(per_channel):
    """All frames fitted at once (for a re-render): no frame is the reference, the gains undo the
    known ones up to one common factor, and painting with them leaves no step at the seams."""
    world = ground(360, 600, seed=4)
    poses = survey()
    frames = shoot(world, poses, GAINS)
    g = joint_gains(frames, poses, per_channel=per_channel)
    assert g.shape == (len(frames), 3)
    corrected = g * np.array(GAINS)[:, None]  # = one factor for every frame
    assert np.ptp(np.log(corrected)) < 0.03
    assert abs(np.log(corrected).mean()) < 0.15  # the prior keeps the map near the cameras' exposure
    m = TiledMosaic(MosaicConfig(tile_size=64))
    for f, M, gk in zip(frames, poses, g):
        m.add(f, M, gain=gk)
        np.testing.assert_array_equal(m.last_gain, gk)
    img, _, origin = m.render()
    labels = frame_labels(poses, (FRAME[1], FRAME[0]), (*origin, img.shape[1], img.shape[0]))
    assert overlap_steps(frames, poses, list(g), labels, origin)[0] < 1.0
    assert overlap_steps(frames, poses, [None] * len(frames), labels, origin)[0] > 30


def test_explicit_gain_is_checked():
    m = TiledMosaic(MosaicConfig(tile_size=64, channels=1))
    frame = ground(50, 50)
    for bad in (0.0, -1.0, float("nan"), [1.0, 1.0, 1.0], "bright"):
        with pytest.raises(InputError, match="gain"):
            m.add(frame, np.array([[1.0, 0, 0], [0, 1.0, 0]]), gain=bad)
    m.add(frame, np.array([[1.0, 0, 0], [0, 1.0, 0]]), gain=0.5)
    gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(m.render()[0], np.rint(gray[1:-1, 1:-1] * 0.5).astype(np.uint8))


def test_seam_steps_measure_a_known_step():
    img = np.tile(np.linspace(50, 150, 200)[None, :], (100, 1)).astype(np.float32)  # a ramp: texture
    labels = np.zeros((100, 200), np.int32)
    labels[:, 100:] = 1
    stepped = img.copy()
    stepped[:, 100:] += 20
    flat = seam_steps(np.rint(img).astype(np.uint8), labels)
    step = seam_steps(np.rint(stepped).astype(np.uint8), labels)
    assert flat.seam_pixels == 100 and flat.frame_pairs == 1
    assert step.level_step - flat.level_step == pytest.approx(20, abs=0.6)
    assert flat.level_step == pytest.approx(5 * 100 / 199, abs=0.6)  # the ramp over 5 pixels


def test_exposure_config_key():
    assert load_config(None, ["mosaic.exposure=gain"]).mosaic.exposure == "gain"
    with pytest.raises(ConfigError, match="mosaic.exposure"):
        load_config(None, ["mosaic.exposure=auto"])


@pytest.fixture(scope="module")
def brighton_segments(tmp_path_factory):
    """The Brighton stills at the poses of their replay, in chains of at most 5 consecutive
    stills (a sequential gain drifts over longer chains of these stills: see the measured
    brightness gradient in docs/benchmarks.md, exposure section): [(frames, poses)]."""
    from conftest import shared_data
    from photomap.cli.replay import replay
    from photomap.io.trajectory_files import read_trajectory_csv

    images = shared_data("brighton_beach") / "images"
    out = tmp_path_factory.mktemp("brighton-exposure")
    replay(str(images), out, load_config())
    rows = read_trajectory_csv(out / "trajectory.csv")
    stills = [cv2.imread(str(p)) for p in sorted(images.glob("*.jpg"))]
    segments = []
    for seg in sorted({r.segment for r in rows if r.glued}):
        glued = [r for r in rows if r.glued and r.segment == seg]
        for k in range(0, len(glued), 5):
            chain = glued[k:k + 5]
            if len(chain) >= 3:
                segments.append(([stills[r.frame] for r in chain], [r.M for r in chain]))
    return segments


def test_real_stills_on_auto_exposure_lose_most_of_their_steps(brighton_segments):
    """18 DJI stills on auto exposure (brighton_beach), at the poses of their replay, in chains of
    up to 5: gains fitted jointly over each chain's overlaps
    lower the exposure step at the seams, on the same ground, without clipping the map. (The
    sequential gain drifts on these stills: every overlap sees the same part of their in-frame
    brightness gradient; see the exposure section of docs/benchmarks.md.)"""
    assert brighton_segments, "the replay should link some of the stills"
    before = after = 0.0
    for frames, poses in brighton_segments:
        steps, clipped = {}, {}
        joint = joint_gains(frames, [np.asarray(p)[:2] for p in poses], per_channel=False)
        for mode, chain_gains in (("none", None), ("joint", joint)):
            m = TiledMosaic(MosaicConfig())
            gains = []
            for k, (f, M) in enumerate(zip(frames, poses)):
                g = None if chain_gains is None else chain_gains[k]
                m.add(f, M, gain=g)
                gains.append(m.last_gain if g is None else np.atleast_1d(g))
            img, alpha, origin = m.render()
            labels = frame_labels(poses, (frames[0].shape[1], frames[0].shape[0]),
                                  (*origin, img.shape[1], img.shape[0]))
            steps[mode] = overlap_steps(frames, poses, gains, labels, origin)[0]
            clipped[mode] = (img >= 255).any(axis=2)[alpha > 0].mean()
        assert clipped["joint"] < clipped["none"] + 0.01  # the gains do not blow the map out
        before, after = before + steps["none"], after + steps["joint"]
    assert after < 0.75 * before  # measured 0.57 (the forest chain alone: 1.17, its canopy moves)
