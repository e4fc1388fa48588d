"""Feature registration (ORB/SIFT + RANSAC), the photometric overlap check and the decision.

Simulated pairs are cut from the bundled aukerman orthophoto with an exact similarity
(``photomap.sim.flight.render_pair``); the real seneca and brighton stills are checked against
their GPS (``shared/data``, skipped when absent).
"""

from __future__ import annotations

import csv
import math
import statistics

import cv2
import numpy as np
import pytest

from conftest import shared_data
from photomap.config import Config
from photomap.core.features import (FeatureMatcher, FeatureRegistration, decide, features_confirmed,
                                    needs_second_opinion, register_features, rescale_matrix, verify_overlap)
from photomap.core.ifmi import Prior, Registrar, Registration
from photomap.core.matching import PairMatcher
from photomap.geometry import similarity_matrix
from photomap.sim.flight import build_pyramid, render_pair
from photomap.sim.terrain import load_terrain, valid_mask

SHAPE = (480, 640)


@pytest.fixture(scope="module")
def terrain():
    t = load_terrain("aukerman", zoom=4.0)
    return t, valid_mask(t), build_pyramid(t, 3.0)


def pair(terrain, angle, scale, shift, seed=1, base=1.2, **effects):
    t, valid, pyramid = terrain
    a, b, m = render_pair(t, SHAPE, angle, scale, shift, seed, valid=valid, base_scale=base, pyramid=pyramid,
                          noise=1.0, **effects)
    return cv2.cvtColor(a, cv2.COLOR_BGR2GRAY), cv2.cvtColor(b, cv2.COLOR_BGR2GRAY), m


def errors(m, truth, shape=SHAPE):
    """(centre error px, |angle error| deg, |relative scale error|)."""
    h, w = shape
    c = np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
    t_err = float(np.linalg.norm((m - truth) @ c))
    da = math.degrees(math.atan2(m[1, 0], m[0, 0]) - math.atan2(truth[1, 0], truth[0, 0]))
    ds = math.sqrt(np.linalg.det(m[:, :2]) / np.linalg.det(truth[:, :2])) - 1
    return t_err, abs((da + 180) % 360 - 180), abs(ds)


def moved(m, dx, dy):
    out = np.array(m, float).copy()
    out[:, 2] += (dx, dy)
    return out


# --------------------------------------------------------------------------- registration

@pytest.mark.parametrize("kind", ["orb", "sift"])
@pytest.mark.parametrize("angle, scale, shift", [
    (12.0, 1.08, (60.0, -140.0)),     # ordinary motion, ~60 % overlap
    (-150.0, 0.87, (-90.0, 70.0)),    # large rotation and scale change
    (20.0, 1.15, (430.0, 60.0)),      # low overlap (about a quarter of the frame)
])
def test_known_motion_is_recovered(terrain, kind, angle, scale, shift):
    a, b, truth = pair(terrain, angle, scale, shift)
    r = register_features(a, b, kind=kind)
    assert r.ok and r.method == kind, r.reason
    t_err, a_err, s_err = errors(r.matrix, truth)
    # ORB keypoints sit on a coarser scale pyramid (factor 1.2 per level) than SIFT's
    tol = (1.0, 0.2, 0.003) if kind == "sift" else (2.0, 0.3, 0.005)
    assert t_err < tol[0] and a_err < tol[1] and s_err < tol[2], (t_err, a_err, s_err)
    assert r.inliers >= 30 and 0 < r.score < 1 and r.inlier_ratio <= 1


def test_results_are_in_the_pixels_of_the_frames_given(terrain):
    """Detection on a downscaled copy still reports a matrix in the input frames' pixels."""
    a, b, truth = pair(terrain, 8.0, 1.05, (50.0, 80.0), seed=2)
    fm = FeatureMatcher("sift", working_size=320)
    fa, fb = fm.prepare(a), fm.prepare(b)
    assert fa.factor == pytest.approx(0.5) and fa.shape == SHAPE
    assert fa.points[:, 0].max() > 400  # input pixels, not those of the 320 px copy
    r = fm.register(fa, fb)
    assert errors(r.matrix, truth)[0] < 2.0
    # and a result converts to the pixels of resized frames with the pixel-centre convention
    f = 0.5
    small = r.rescaled(f).matrix
    p = np.array([100.0, 200.0, 1.0])
    expected = f * (r.matrix @ p + 0.5) - 0.5
    q = np.array([f * (p[0] + 0.5) - 0.5, f * (p[1] + 0.5) - 0.5, 1.0])
    assert np.allclose(small @ q, expected)
    assert np.allclose(rescale_matrix(small, 1 / f), r.matrix)


def test_prior_filters_and_rejects(terrain):
    a, b, truth = pair(terrain, 30.0, 1.0, (40.0, 40.0), seed=3)
    fm = FeatureMatcher("sift")
    fa, fb = fm.prepare(a), fm.prepare(b)
    right = fm.register(fa, fb, Prior(angle_deg=28.0, angle_tol_deg=10.0, scale=1.0, scale_tol=0.1))
    assert right.ok and errors(right.matrix, truth)[0] < 1.0
    unfiltered = fm.register(fa, fb)
    assert right.matches < unfiltered.matches  # matches contradicting the prior were dropped
    wrong = fm.register(fa, fb, Prior(angle_deg=-60.0, angle_tol_deg=10.0))
    assert not wrong.ok and wrong.matrix is None


def test_featureless_frames_give_no_result():
    flat = np.full(SHAPE, 120, np.uint8)
    noise = np.random.default_rng(0).integers(0, 255, SHAPE).astype(np.uint8)
    for kind in ("orb", "sift"):
        r = register_features(flat, noise, kind=kind)
        assert not r.ok and r.reason
    with pytest.raises(ValueError):
        FeatureMatcher("akaze")
    with pytest.raises(ValueError):
        FeatureMatcher("sift").prepare(np.zeros((8, 8), np.uint8))



def test_a_uniform_frame_is_rejected_without_asking_the_features(terrain):
    """Black video (a lens cap, a lost link): the matcher rejects it at once; a frame of other
    ground that iFMI cannot place is given to the features (the second opinion is what costs:
    50-150 ms a pair at 1080p)."""
    a, b, _ = pair(terrain, 10.0, 1.0, (760.0, 0.0))  # textured, no overlap
    matcher = PairMatcher(Registrar((240, 320)), second_opinion="orb")

    def view(gray):
        return matcher.view(cv2.resize(gray, (320, 240), interpolation=cv2.INTER_AREA), gray)

    ref, black, other = view(a), view(np.zeros_like(a)), view(b)
    got = matcher.match(ref, black)
    assert not got.accepted and got.how == "rejected"
    assert ref.features is None and black.features is None  # no features asked
    assert not matcher.match(ref, other).accepted
    assert ref.features is not None and other.features is not None

# --------------------------------------------------------------------------- overlap check

def test_check_accepts_right_placements(terrain):
    for seed, (angle, scale, shift) in enumerate([(5.0, 1.0, (100.0, 50.0)), (-120.0, 1.12, (0.0, -200.0)),
                                                  (15.0, 0.9, (420.0, 0.0))]):
        a, b, truth = pair(terrain, angle, scale, shift, seed=10 + seed)
        chk = verify_overlap(a, b, truth)
        assert chk.passes(0.2, 0.9, 0.05), chk
        assert chk.score > 0.9 and abs(chk.offset[0]) <= 4 and abs(chk.offset[1]) <= 4
    # a darker second view (exposure) still passes: gradients are normalised
    a, b, truth = pair(terrain, 5.0, 1.0, (100.0, 50.0), seed=13)
    dark = np.clip(0.6 * b.astype(np.float32) + 10, 0, 255).astype(np.uint8)
    assert verify_overlap(a, dark, truth).passes(0.2, 0.9, 0.05)


@pytest.mark.parametrize("direction", [0, 90, 180, 270])
def test_check_rejects_a_placement_30_px_off(terrain, direction):
    a, b, truth = pair(terrain, 10.0, 1.05, (80.0, -60.0), seed=20)
    dx, dy = 30 * math.cos(math.radians(direction)), 30 * math.sin(math.radians(direction))
    chk = verify_overlap(a, b, moved(truth, dx, dy))
    assert not chk.passes(0.2, 0.9, 0.05), chk
    # the check says where the images agree instead: about 30 px back (4 px steps at 160 px)
    assert abs(chk.offset[0] + dx) <= 6 and abs(chk.offset[1] + dy) <= 6, chk.offset


def test_check_rejects_non_overlapping_and_shuffled_frames(terrain):
    # centres 944 px apart, circumscribed circles (radius 400 px) disjoint
    a, b, truth = pair(terrain, 10.0, 1.0, (760.0, 560.0), seed=30, base=1.0)
    identity = similarity_matrix(0.0, 1.0)
    for m in (identity, truth, similarity_matrix(40.0, 1.1, (30.0, -20.0), center=(319.5, 239.5))):
        assert not verify_overlap(a, b, m).passes(0.2, 0.9, 0.05)
    # shuffled: a frame of one pair placed with the (right) matrix of another
    c, d, other = pair(terrain, -5.0, 1.0, (60.0, 60.0), seed=31)
    assert verify_overlap(c, d, other).passes(0.2, 0.9, 0.05)
    assert not verify_overlap(a, d, other).passes(0.2, 0.9, 0.05)
    assert not verify_overlap(c, b, other).passes(0.2, 0.9, 0.05)


def test_check_rejects_one_period_off_on_crop_rows(terrain):
    """Crop rows (period 32 px) blended into the orthophoto: one period off is rejected."""
    t, valid, _ = terrain
    grey = cv2.cvtColor(t, cv2.COLOR_BGR2GRAY).astype(np.float32)
    xx = np.arange(grey.shape[1], dtype=np.float32)[None, :]
    rows = 127.0 + 100.0 * np.sin(2 * np.pi * xx / 32.0)
    periodic = cv2.cvtColor(np.clip(0.85 * grey + 0.15 * rows, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    # views without yaw (render_pair turns view a randomly): cut them directly
    h, w = SHAPE
    c = ((w - 1) / 2, (h - 1) / 2)
    a_to_t = similarity_matrix(0.0, 1.0, (2100 - c[0], 1600 - c[1]))
    truth = similarity_matrix(6.0, 1.02, (40.0, 90.0), center=c)
    b_to_t = (np.vstack([a_to_t, [0, 0, 1]]) @ np.vstack([truth, [0, 0, 1]]))[:2]
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    a = cv2.cvtColor(cv2.warpAffine(periodic, a_to_t, (w, h), flags=flags), cv2.COLOR_BGR2GRAY)
    b = cv2.cvtColor(cv2.warpAffine(periodic, b_to_t, (w, h), flags=flags), cv2.COLOR_BGR2GRAY)
    assert verify_overlap(a, b, truth).passes(0.2, 0.9, 0.05)
    for k in (-1, 1):
        chk = verify_overlap(a, b, moved(truth, 32.0 * k, 0.0))
        assert not chk.passes(0.2, 0.9, 0.05), chk
        assert chk.score > 0.5  # the rows still match: only the rival peak gives it away


def test_check_of_a_tiny_overlap_is_not_a_pass(terrain):
    a, b, truth = pair(terrain, 0.0, 1.0, (0.0, 0.0), seed=40)
    far = moved(truth, 630.0, 470.0)  # one corner pixel in common
    chk = verify_overlap(a, b, far)
    assert chk.overlap < 0.01 and not chk.passes(0.2, 0.9, 0.05)
    assert math.isnan(chk.score)


# --------------------------------------------------------------------------- decision

def test_decide_prefers_a_confirmed_placement(terrain):
    a, b, truth = pair(terrain, 10.0, 1.05, (80.0, -60.0), seed=50)
    right = verify_overlap(a, b, truth)
    wrong_m = moved(truth, 120.0, 0.0)
    wrong = verify_overlap(a, b, wrong_m)
    sift = FeatureRegistration("sift", truth, 200, 150, 150 / 170)
    ifmi_good = Registration(truth, 0.6)
    ifmi_bad = Registration(wrong_m, 0.9)  # confident but wrong: the check overrules it

    d = decide(ifmi_good, right)
    assert d.accept and d.method == "ifmi" and not needs_second_opinion(ifmi_good, right)
    assert needs_second_opinion(ifmi_bad, wrong)
    d = decide(ifmi_bad, wrong)
    assert not d.accept and d.matrix is None and d.method == "none"
    d = decide(ifmi_bad, wrong, sift, right)
    assert d.accept and d.method == "sift" and np.allclose(d.matrix, truth)
    d = decide(ifmi_bad, wrong, FeatureRegistration("orb", wrong_m, 40, 30, 0.6), wrong)
    assert not d.accept
    # too few inliers: not used even when the check passes
    assert not decide(ifmi_bad, wrong, FeatureRegistration("sift", truth, 9, 9, 0.3), right).accept


def test_many_inliers_outweigh_a_rival_peak():
    """Parallax (trees above the ground) gives a right placement a rival peak; with many RANSAC
    inliers the placement is still confirmed, with few it is not."""
    from photomap.core.features import OverlapCheck
    chk = OverlapCheck(score=0.18, ratio=2.0, offset=(0.0, -14.0), gradient_ncc=0.15, ncc=0.6, overlap=0.6,
                       pixels=9000)
    m = similarity_matrix(0.0, 1.0)
    assert features_confirmed(FeatureRegistration("sift", m, 60, 40, 0.6), chk)
    assert not features_confirmed(FeatureRegistration("sift", m, 30, 15, 0.4), chk)
    assert not features_confirmed(FeatureRegistration("sift", m, 60, 40, 0.6),
                                  OverlapCheck(0.05, 2.0, (0.0, 0.0), 0.0, 0.0, 0.6, 9000))


# --------------------------------------------------------------------------- real stills

def gps_m(a: dict, b: dict) -> float:
    lat = math.radians(float(a["lat"]))
    north = (float(b["lat"]) - float(a["lat"])) * 111_320.0
    east = (float(b["lon"]) - float(a["lon"])) * 111_320.0 * math.cos(lat)
    return math.hypot(north, east)


def link_stills(folder):
    """Every consecutive pair through the combination the tracker is to use: iFMI at the working
    size, its overlap check, SIFT at 640 px when iFMI is not confirmed, ``decide``.

    Returns per pair (GPS distance m, decision, moving-frame centre shift in full-resolution px).
    """
    files = sorted((folder / "images").glob("*.jpg"))
    with open(folder / "poses.csv", newline="") as f:
        poses = list(csv.DictReader(f))
    frames = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in files]
    cfg = Config().registration
    working = cfg.working_size
    h, w = frames[0].shape
    size = (working, int(round(h * working / w)))
    f = size[0] / w
    small = [cv2.resize(g, size, interpolation=cv2.INTER_AREA) for g in frames]
    registrar = Registrar(small[0].shape, cfg)
    prepared = [registrar.prepare(s) for s in small]
    matcher = FeatureMatcher("sift", working_size=640)
    feats = {}
    out = []
    centre = np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
    for k in range(1, len(frames)):
        reg = registrar.register(prepared[k - 1], prepared[k])
        chk = verify_overlap(small[k - 1], small[k], reg.matrix)
        if needs_second_opinion(reg, chk):
            for i in (k - 1, k):
                if i not in feats:
                    feats[i] = matcher.prepare(frames[i])
            fr = matcher.register(feats[k - 1], feats[k]).rescaled(f)
            fchk = verify_overlap(small[k - 1], small[k], fr.matrix) if fr.ok else None
            d = decide(reg, chk, fr, fchk)
        else:
            d = decide(reg, chk)
        shift = math.nan
        if d.accept:
            m = rescale_matrix(d.matrix, 1 / f)
            shift = float(np.hypot(*(m @ centre - centre[:2])))
        out.append((gps_m(poses[k - 1], poses[k]), d, shift))
    return out


def consistent_with_gps(links):
    """Accepted placements move the frame centre in proportion to the GPS distance (one camera
    height, within a factor 1.5): a wrong placement is off by hundreds of pixels."""
    ratios = [shift / dist for dist, d, shift in links if d.accept]
    med = statistics.median(ratios)
    return [r for r in ratios if not med / 1.5 <= r <= med * 1.5]


def test_seneca_stills_link(tmp_path):
    folder = shared_data("seneca_nir")
    links = link_stills(folder)
    # the two strips (GPS ~30 m apart, ~45-60 % overlap): 12 pairs; iFMI alone links 4 of them
    strips = [(dist, d) for dist, d, _ in links if dist < 40]
    assert len(strips) == 12
    assert sum(d.accept for _, d in strips) >= 11, [(round(x), d.method, d.reason) for x, d in strips]
    # the turn: 0470-0471 (103 m, no overlap) must not be glued
    far = [d for dist, d, _ in links if dist > 100]
    assert len(far) == 1 and not far[0].accept
    assert not consistent_with_gps(links)


def test_brighton_stills_link():
    folder = shared_data("brighton_beach")
    links = link_stills(folder)
    assert len(links) == 17
    # the strip over forest (parallax) included: iFMI alone breaks the set into segments
    assert sum(d.accept for _, d, _ in links) >= 16, [(d.method, d.reason) for _, d, _ in links]
    assert not consistent_with_gps(links)


def test_a_fixed_mask_is_resized_once_and_a_new_mask_is_not_mistaken_for_it(terrain, monkeypatch):
    """Keypoints only where the mask is 1, frame after frame; the mask's resized copy is made once
    per mask and detection size, and another mask of the same shape gets its own."""
    a, b, _ = pair(terrain, 0.0, 1.0, (0.0, 0.0))
    left = np.zeros(SHAPE, np.float32)
    left[:, : SHAPE[1] // 2] = 1.0
    right = 1.0 - left
    resized = []
    real = cv2.resize

    def counting(src, *args, **kwargs):
        if src.dtype == np.float32:
            resized.append(src.shape)
        return real(src, *args, **kwargs)

    matcher = FeatureMatcher("orb", working_size=320)
    monkeypatch.setattr(cv2, "resize", counting)
    first = [matcher.prepare(img, left) for img in (a, b, a)]
    assert resized == [SHAPE]  # once for three frames
    assert np.array_equal(first[0].points, first[2].points) and len(first[0])
    assert (first[0].points[:, 0] < SHAPE[1] / 2).all() and (first[1].points[:, 0] < SHAPE[1] / 2).all()
    other = matcher.prepare(a, right)
    assert len(resized) == 2 and len(other) and (other.points[:, 0] > SHAPE[1] / 2 - 2).all()
    fresh = FeatureMatcher("orb", working_size=320).prepare(b, left)
    assert np.array_equal(matcher.prepare(b, left).points, fresh.points)
