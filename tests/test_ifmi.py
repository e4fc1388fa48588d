"""iFMI registration against exact ground truth: pairs cut from one terrain with a known similarity."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from photomap.config import RegistrationConfig
from photomap.core.ifmi import Prior, Registrar
from photomap.geometry import similarity_matrix
from photomap.sim.terrain import BUNDLED

TERRAIN_PATH = BUNDLED["aukerman"]


@pytest.fixture(scope="module")
def terrain() -> np.ndarray:
    img = cv2.imread(str(TERRAIN_PATH), cv2.IMREAD_COLOR)
    assert img is not None
    return cv2.resize(img, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)


def smooth_noise(shape, sigma, seed, contrast=1.0):
    """Band-limited random texture with values around 128 (no repetition)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
    img = (img - img.mean()) / img.std()
    return np.clip(128 + 40 * contrast * img, 0, 255).astype(np.uint8)


def cut_pair(terrain, shape, angle, scale, shift, centre=(1000.0, 800.0)):
    """Frames a and b cut from ``terrain`` and the exact 2x3 matrix mapping b pixels to a pixels."""
    h, w = shape
    c = ((w - 1) / 2, (h - 1) / 2)
    a_to_t = similarity_matrix(0.0, 1.0, (centre[0] - c[0], centre[1] - c[1]))
    b_to_a = similarity_matrix(angle, scale, shift, center=c)
    b_to_t = (np.vstack([a_to_t, [0, 0, 1]]) @ np.vstack([b_to_a, [0, 0, 1]]))[:2]
    flags = cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP
    a = cv2.warpAffine(terrain, a_to_t, (w, h), flags=flags)
    b = cv2.warpAffine(terrain, b_to_t, (w, h), flags=flags)
    return a, b, b_to_a


def centre_error(m_est, m_true, shape):
    h, w = shape
    c = np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
    return float(np.linalg.norm((m_est - m_true) @ c))


def angle_error(m_est, m_true):
    a = math.degrees(math.atan2(m_est[1, 0], m_est[0, 0]) - math.atan2(m_true[1, 0], m_true[0, 0]))
    return abs((a + 180) % 360 - 180)


def scale_error(m_est, m_true):
    return abs(math.sqrt(np.linalg.det(m_est[:, :2]) / np.linalg.det(m_true[:, :2])) - 1)


@pytest.mark.parametrize("shape", [(256, 256), (240, 320), (199, 251)])
def test_full_circle_rotation_scale_and_translation(terrain, shape):
    reg = Registrar(shape)
    rng = np.random.default_rng(sum(shape))
    angles = [-179.5, -135.0, -90.0, -30.0, 0.0, 12.3, 90.0, 150.0, 179.0]
    for angle in angles:
        scale = float(rng.uniform(0.8, 1.25))
        shift = tuple(rng.uniform(-0.15, 0.15, 2) * np.array(shape[::-1]))
        a, b, truth = cut_pair(terrain, shape, angle, scale, shift)
        r = reg.register(a, b)
        assert angle_error(r.matrix, truth) < 0.05, (angle, r.angle_deg)
        assert scale_error(r.matrix, truth) < 5e-4, (scale, r.scale)
        assert centre_error(r.matrix, truth, shape) < 0.1
        assert r.confidence > 0.4


def test_large_translation_forty_percent(terrain):
    shape = (240, 320)
    reg = Registrar(shape)
    for shift in [(128.0, 0.0), (-120.0, 40.0), (30.0, -96.0)]:
        a, b, truth = cut_pair(terrain, shape, 3.0, 1.02, shift)
        r = reg.register(a, b)
        assert centre_error(r.matrix, truth, shape) < 0.1, shift
        assert angle_error(r.matrix, truth) < 0.05


def test_grey_and_colour_agree(terrain):
    shape = (240, 320)
    reg = Registrar(shape)
    a, b, truth = cut_pair(terrain, shape, -7.0, 0.95, (12.0, -8.0))
    r_col = reg.register(a, b)
    r_gray = reg.register(cv2.cvtColor(a, cv2.COLOR_BGR2GRAY), cv2.cvtColor(b, cv2.COLOR_BGR2GRAY).astype(np.float32))
    np.testing.assert_allclose(r_col.matrix, r_gray.matrix, atol=1e-6)
    assert centre_error(r_col.matrix, truth, shape) < 0.05


def test_prepared_frames_give_the_same_result(terrain):
    shape = (256, 256)
    reg = Registrar(shape)
    a, b, _ = cut_pair(terrain, shape, 20.0, 1.1, (5.0, 9.0))
    r1 = reg.register(a, b)
    r2 = reg.register(reg.prepare(a), reg.prepare(b))
    np.testing.assert_allclose(r1.matrix, r2.matrix, atol=1e-9)
    assert r1.confidence == pytest.approx(r2.confidence)


def test_subpixel_peak_fit_is_unbiased_without_refinement():
    """Pure fractional translations: the Gaussian fit leaves no systematic bias."""
    shape = (256, 256)
    big = smooth_noise((600, 600), 1.5, seed=3)
    reg = Registrar(shape, RegistrationConfig(refine_iterations=0))
    errors = []
    for frac in np.linspace(0.0, 0.9, 10):
        a, b, truth = cut_pair(big, shape, 0.0, 1.0, (7.0 + frac, -3.0 - frac / 2), centre=(300.0, 300.0))
        r = reg.register(a, b)
        errors.append(r.matrix[:, 2] - truth[:, 2])
    errors = np.array(errors)
    assert np.abs(errors.mean(axis=0)).max() < 0.02  # bias
    assert np.abs(errors).max() < 0.06


def test_refinement_improves_rotation_precision(terrain):
    shape = (256, 256)
    coarse = Registrar(shape, RegistrationConfig(refine_iterations=0))
    fine = Registrar(shape, RegistrationConfig(refine_iterations=2))
    rng = np.random.default_rng(7)
    err_c, err_f = [], []
    for _ in range(8):
        angle, scale = float(rng.uniform(-10, 10)), float(rng.uniform(0.95, 1.05))
        a, b, truth = cut_pair(terrain, shape, angle, scale, tuple(rng.uniform(-20, 20, 2)))
        err_c.append(angle_error(coarse.register(a, b).matrix, truth))
        r = fine.register(a, b)
        assert r.refined
        err_f.append(angle_error(r.matrix, truth))
    rms_f = math.sqrt(np.mean(np.square(err_f)))
    assert rms_f < 0.01
    assert rms_f < math.sqrt(np.mean(np.square(err_c)))


def test_confidence_is_low_for_noise_blank_and_no_overlap(terrain):
    shape = (240, 320)
    reg = Registrar(shape)
    rng = np.random.default_rng(0)
    a, b, _ = cut_pair(terrain, shape, 0.0, 1.0, (10.0, 5.0))
    good = reg.register(a, b).confidence
    assert good > 0.6
    noise1 = rng.integers(0, 256, shape, dtype=np.uint8)
    noise2 = rng.integers(0, 256, shape, dtype=np.uint8)
    assert reg.register(noise1, noise2).confidence < 0.1
    blank = np.full(shape, 90, np.uint8)
    assert reg.register(a, blank).confidence == 0.0
    assert reg.register(blank, blank).confidence == 0.0
    # two views of the terrain that do not overlap at all
    far_a, _, _ = cut_pair(terrain, shape, 0.0, 1.0, (0.0, 0.0), centre=(500.0, 500.0))
    far_b, _, _ = cut_pair(terrain, shape, 0.0, 1.0, (0.0, 0.0), centre=(1500.0, 1100.0))
    assert reg.register(far_a, far_b).confidence < 0.15
    # confidence falls with overlap
    a, b, _ = cut_pair(terrain, shape, 0.0, 1.0, (200.0, 0.0))
    assert reg.register(a, b).confidence < good


def test_featureless_ground_registers(terrain):
    """Sand-like ground: 25 % contrast, smooth texture, sensor noise."""
    shape = (256, 256)
    sand = smooth_noise((800, 800), 4.0, seed=11, contrast=0.25)
    reg = Registrar(shape)
    rng = np.random.default_rng(5)
    ok = 0
    for _ in range(10):
        angle, scale = float(rng.uniform(-8, 8)), float(rng.uniform(0.96, 1.04))
        a, b, truth = cut_pair(sand, shape, angle, scale, tuple(rng.uniform(-25, 25, 2)), centre=(400.0, 400.0))
        a = np.clip(a + rng.normal(0, 2.0, a.shape), 0, 255).astype(np.uint8)
        b = np.clip(b + rng.normal(0, 2.0, b.shape), 0, 255).astype(np.uint8)
        r = reg.register(a, b)
        ok += centre_error(r.matrix, truth, shape) < 1 and angle_error(r.matrix, truth) < 0.5
    assert ok >= 9


def test_locked_scale_and_angle_prior(terrain):
    shape = (240, 320)
    reg = Registrar(shape)
    a, b, truth = cut_pair(terrain, shape, 25.0, 1.0, (6.0, -4.0))
    r = reg.register(a, b, Prior(scale=1.0, scale_tol=0.0))
    assert abs(r.scale - 1.0) < 1e-4
    assert angle_error(r.matrix, truth) < 0.05
    r = reg.register(a, b, Prior(angle_deg=22.0, angle_tol_deg=5.0))
    assert angle_error(r.matrix, truth) < 0.05
    # the prior forbids the true angle: the search stays inside the tolerance
    r = reg.register(a, b, Prior(angle_deg=-60.0, angle_tol_deg=5.0))
    assert abs(((r.angle_deg + 60.0) + 180) % 360 - 180) <= 5.5


def test_periodic_ground_is_ambiguous_and_the_prior_decides():
    """Rows of crops: ground periodic in x (period 24 px) moved by half a period.

    Shifts of +12 and -12 px explain the images equally well: the result must say so, and a
    motion prior must pick the one it expects.
    """
    shape = (256, 256)
    rng = np.random.default_rng(2)
    field = np.tile(smooth_noise((600, 24), 1.2, seed=4), (1, 26))
    reg = Registrar(shape, RegistrationConfig(refine_iterations=0))
    a, b, _ = cut_pair(field, shape, 0.0, 1.0, (12.0, 3.0), centre=(360.0, 300.0))
    a = np.clip(a + rng.normal(0, 2.0, a.shape), 0, 255).astype(np.uint8)
    b = np.clip(b + rng.normal(0, 2.0, b.shape), 0, 255).astype(np.uint8)
    assert reg.register(a, b).ambiguous
    for expect_x in (12.0, -12.0):
        r = reg.register(a, b, Prior(angle_deg=0.0, angle_tol_deg=3.0, scale=1.0, scale_tol=0.01,
                                     shift=(expect_x + 3.0, 2.0), shift_tol=8.0))
        assert r.ambiguous
        assert abs(r.shift[0] - expect_x) < 0.2, (expect_x, r.shift)
        assert abs(r.shift[1] - 3.0) < 0.2
    # non-periodic ground is not reported ambiguous
    big = smooth_noise((600, 600), 1.5, seed=9)
    a, b, _ = cut_pair(big, shape, 0.0, 1.0, (5.0, 3.0), centre=(300.0, 300.0))
    assert not reg.register(a, b).ambiguous


@pytest.mark.parametrize("shape", [(256, 256), (240, 320), (199, 251), (200, 251), (199, 250)])
def test_packed_spectrum_matches_rfft2(shape):
    """cv2.dft's CCS layout, read through _Ccs, is scipy's rfft2; set_edges + idft invert it."""
    import scipy.fft

    from photomap.core.ifmi import _Ccs

    rng = np.random.default_rng(1)
    img = rng.standard_normal(shape).astype(np.float32)
    ccs = _Ccs(*shape)
    packed = ccs.forward(img)
    ref = scipy.fft.rfft2(img.astype(np.float64))
    inner, edges = ccs.split(ref)
    scale = np.abs(ref).max()
    np.testing.assert_allclose(ccs.inner(packed), inner, atol=1e-5 * scale)
    np.testing.assert_allclose(ccs.edges(packed), edges[:ccs.m], atol=1e-5 * scale)
    np.testing.assert_allclose(ccs.shifted_abs(packed, ccs.edges(packed)),
                               np.fft.fftshift(np.abs(ref), axes=0), atol=1e-5 * scale)
    rebuilt = np.zeros_like(packed)
    ccs.inner(rebuilt)[...] = inner
    ccs.set_edges(rebuilt, edges[:ccs.m].astype(np.complex64))
    np.testing.assert_allclose(ccs.inverse(rebuilt), img, atol=1e-4)


def test_percentile_matches_numpy():
    from photomap.core.ifmi import _percentile

    rng = np.random.default_rng(3)
    for n in (1, 2, 7, 128, 255):
        x = rng.standard_normal(n).astype(np.float32)
        for q in (0.0, 5.0, 50.0, 100.0):
            assert _percentile(x, q) == pytest.approx(float(np.percentile(x, q)), rel=1e-6, abs=1e-7)


def test_gram_matrix_in_chunks_matches_the_full_product():
    from photomap.core.ifmi import _BLAS_ONE_THREAD, _gram

    rng = np.random.default_rng(5)
    for rows in (6, 2):
        chunk = _BLAS_ONE_THREAD // (6 * rows)
        for n in (1, 100, chunk, chunk + 1, 3 * chunk - 7):
            a = rng.standard_normal((6, n)).astype(np.float32)
            b = a[:rows] * rng.random(n).astype(np.float32)
            want = a.astype(np.float64) @ b.astype(np.float64).T
            got = _gram(a, b)
            assert got.dtype == np.float64 and got.shape == (6, rows)
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * math.sqrt(n))


@pytest.fixture(scope="module")
def sand() -> np.ndarray:
    """The simulator's procedural sand (smooth, low contrast), grey."""
    from photomap.sim.terrain import load_terrain

    return cv2.cvtColor(load_terrain("sand", size=(800, 800), seed=7), cv2.COLOR_BGR2GRAY)


def test_refinement_level_follows_the_signal_band(terrain, sand):
    """Textured ground is refined at full resolution, smooth noisy ground on a coarser level."""
    shape = (256, 256)
    reg = Registrar(shape)
    textured, _, _ = cut_pair(terrain, shape, 0.0, 1.0, (0.0, 0.0))
    assert reg.prepare(textured).refine_level == 0
    rng = np.random.default_rng(4)
    noisy = np.clip(sand[:256, :256] + rng.normal(0, 2.0, shape), 0, 255).astype(np.uint8)
    assert reg.prepare(noisy).refine_level >= 1
    assert Registrar(shape, RegistrationConfig(refine_iterations=0)).prepare(noisy).refine_level == 0


def test_refinement_corrects_a_few_degrees_on_smooth_ground(sand):
    """Featureless ground: the refinement converges from an estimate 3 deg and 1 px off (its
    corners 9 px off: more than the 3 % a refinement may usually move them)."""
    shape = (256, 256)
    rng = np.random.default_rng(6)
    a, b, truth = cut_pair(sand, shape, 5.0, 1.02, (8.0, -6.0), centre=(400.0, 400.0))
    a = np.clip(a + rng.normal(0, 2.0, a.shape), 0, 255).astype(np.uint8)
    b = np.clip(b + rng.normal(0, 2.0, b.shape), 0, 255).astype(np.uint8)
    reg = Registrar(shape)
    pa, pb = reg.prepare(a), reg.prepare(b)
    start = similarity_matrix(8.0, 1.02, (9.0, -6.0), center=((shape[1] - 1) / 2, (shape[0] - 1) / 2))
    assert angle_error(start, truth) > 2.9
    refined = reg._refine(pa, pb, start)
    assert refined is not None
    assert angle_error(refined, truth) < 0.3
    assert centre_error(refined, truth, shape) < 0.5
    assert scale_error(refined, truth) < 0.005



def test_the_shift_prior_peak_is_that_of_the_whole_masked_surface():
    """The translation peak within a shift prior is read on the rows and columns its disc can
    touch only: the same peak (position and value, ties to the first) as masking the whole
    surface, also for discs that wrap around the periodic surface's edges or hold nothing."""
    import scipy.fft

    h, w = 60, 80
    reg = Registrar((h, w))
    rng = np.random.default_rng(5)

    def whole(r, angle, scale, prior):  # the former full-surface mask
        ys = scipy.fft.fftfreq(h, 1.0 / h)[:, None]
        xs = scipy.fft.fftfreq(w, 1.0 / w)[None, :]
        lin = similarity_matrix(angle, scale)[:, :2]
        base = np.asarray(reg.center) - lin @ np.asarray(reg.center)
        tx, ty = base[0] - xs - prior.shift[0], base[1] - ys - prior.shift[1]
        return Registrar._peaks(np.where(tx ** 2 + ty ** 2 <= prior.shift_tol ** 2, r, -np.inf), 1, exclude=4)

    found = empty = 0
    for k in range(400):
        r = rng.normal(size=(h, w)).astype(np.float32)
        if k % 3 == 0:
            r = np.round(r)  # ties: the first in row-major order wins
        angle, scale = float(rng.uniform(-180, 180)), float(rng.uniform(0.8, 1.25))
        shift = (float(rng.uniform(-w, w)), float(rng.uniform(-h, h)))
        prior = Prior(shift=shift, shift_tol=float(rng.choice([0.3, 2.0, 4.5, 12.0, 40.0])))
        want = whole(r, angle, scale, prior)
        assert reg._shift_peak(r, angle, scale, prior) == want
        found += bool(want)
        empty += not want
    assert found > 50 and empty > 10  # both cases were exercised


def test_a_pair_registered_again_gives_what_a_fresh_registrar_gives(terrain):
    """The registrar keeps the last pair's prior-free work (surfaces, refinements): registering
    the same pair again with other priors (as the tracker does) gives exactly the results of a
    registrar that never saw the pair, and the second registration reuses that work."""
    shape = (120, 160)
    pairs = [cut_pair(terrain, shape, angle, scale, shift, centre)
             for angle, scale, shift, centre in ((7.0, 1.03, (9.0, -5.0), (900.0, 700.0)),
                                                 (-31.0, 0.97, (-14.0, 6.0), (1200.0, 900.0)),
                                                 (95.0, 1.0, (3.0, 11.0), (700.0, 1100.0)))]
    priors = [None, Prior(angle_deg=5.0, angle_tol_deg=10.0, scale=1.0, scale_tol=0.1),
              Prior(angle_deg=0.0, angle_tol_deg=180.0, scale=1.0, scale_tol=10.0, shift=(8.0, -4.0), shift_tol=6.0),
              Prior(angle_deg=-30.0, angle_tol_deg=5.0, scale=0.97, scale_tol=0.0, shift=(-12.0, 5.0), shift_tol=3.0),
              Prior(angle_deg=170.0, angle_tol_deg=20.0, scale=1.2, scale_tol=0.05)]
    kept = Registrar(shape)
    inverses = []
    for a, b, _ in pairs:
        pa, pb = kept.prepare(a), kept.prepare(b)
        for prior in priors:
            fresh = Registrar(shape)
            want = fresh.register(fresh.prepare(a), fresh.prepare(b), prior)
            calls = []
            inverse = kept._ccs.inverse
            kept._ccs.inverse = lambda packed, calls=calls, inverse=inverse: calls.append(1) or inverse(packed)
            try:
                got = kept.register(pa, pb, prior)
            finally:
                del kept._ccs.inverse
            inverses.append(len(calls))
            assert np.array_equal(got.matrix, want.matrix)
            assert (got.confidence, got.ambiguous, got.refined) == (want.confidence, want.ambiguous, want.refined)
            assert got.candidates == want.candidates
    assert sum(inverses[1:len(priors)]) < (len(priors) - 1) * inverses[0]  # surfaces were reused
