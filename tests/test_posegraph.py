"""Pose graph: exact synthetic truth (a figure-eight flight of similarity poses)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from photomap.config import PosegraphConfig
from photomap.errors import ConfigError
from photomap.core.posegraph import (PoseGraph, _Problem, correction, interpolate_corrections, optimize,
                               pose_matrix, pose_params)

W, H = 640, 480
C = ((W - 1) / 2, (H - 1) / 2)
N = 200


def figure_eight(n: int = N, a: float = 2000.0, b: float = 1200.0) -> np.ndarray:
    """(n, 3, 3) true poses along a closed figure-eight; image up along the flight direction."""
    t = 2 * np.pi * np.arange(n) / n
    x, y = a * np.sin(t), b * np.sin(t) * np.cos(t)
    heading = np.arctan2(a * np.cos(t), -b * np.cos(2 * t))
    logs = np.log(1 + 0.05 * np.sin(3 * t))  # altitude changes
    return pose_matrix(np.c_[x, y, heading, logs], C)


def about_centre(deg: float, scale: float, shift=(0.0, 0.0)) -> np.ndarray:
    """3x3 similarity of frame pixels that rotates/scales about the frame centre, then shifts."""
    return pose_matrix(np.array([C[0] + shift[0], C[1] + shift[1], math.radians(deg), math.log(scale)]), C)


def relative(truth: np.ndarray, i: int, j: int) -> np.ndarray:
    """True registration of frame j against frame i (pixels of j -> pixels of i)."""
    return np.linalg.inv(truth[i]) @ truth[j]


def centres(poses: np.ndarray) -> np.ndarray:
    return (poses @ np.r_[C, 1.0])[:, :2]


def ate(poses: np.ndarray, truth: np.ndarray) -> float:
    """RMS error (map px) of the frame centres; node 0 is locked at the truth, so no alignment."""
    return float(np.sqrt(((centres(poses) - centres(truth)) ** 2).sum(axis=1).mean()))


def chained_graph(truth: np.ndarray, seed: int = 0, rot_bias_deg: float = 0.02, scale_bias: float = 3e-4,
                  t_noise: float = 0.3, loops: bool = True) -> tuple[PoseGraph, list[tuple[int, int]]]:
    """Nodes at the chained (drifting) poses; sequential edges with a known bias per edge; loop
    closures (exact truth + small noise) between every pair of frames >= 15 apart that overlap."""
    rng = np.random.default_rng(seed)
    g = PoseGraph((W, H), PosegraphConfig(sigma_px=1.0))
    seq = [relative(truth, k, k + 1) @ about_centre(rot_bias_deg, 1 + scale_bias, rng.normal(0, t_noise, 2))
           for k in range(len(truth) - 1)]
    pose = truth[0]
    g.add_node(pose)
    for z in seq:
        pose = pose @ z
        g.add_node(pose)
    for k, z in enumerate(seq):
        g.add_edge(k, k + 1, z, confidence=0.9)
    pairs: list[tuple[int, int]] = []
    if loops:
        cen = centres(truth)
        pairs = [(i, j) for i in range(len(truth)) for j in range(i + 15, len(truth))
                 if np.linalg.norm(cen[i] - cen[j]) < 250]
        for i, j in pairs:
            z = relative(truth, i, j) @ about_centre(rng.normal(0, 0.005), 1 + rng.normal(0, 5e-5),
                                                     rng.normal(0, 0.2, 2))
            g.add_edge(i, j, z, confidence=0.7, kind="loop")
    return g, pairs


@pytest.fixture(scope="module")
def truth() -> np.ndarray:
    return figure_eight()


# --------------------------------------------------------------------------- parametrisation

def test_pose_params_roundtrip_and_centre_position():
    m = about_centre(33.0, 1.2, (10.0, -4.0))
    p = pose_params(m, C)
    assert p[0] == pytest.approx(C[0] + 10.0) and p[1] == pytest.approx(C[1] - 4.0)  # map position of the centre
    assert p[2] == pytest.approx(math.radians(33.0)) and p[3] == pytest.approx(math.log(1.2))
    np.testing.assert_allclose(pose_matrix(p, C), m, atol=1e-12)
    np.testing.assert_allclose(pose_params(m[:2], C), p)  # 2x3 accepted


def test_edge_weight_from_confidence():
    g = PoseGraph((W, H), PosegraphConfig(sigma_px=0.5, min_confidence=0.1))
    r = 0.5 * math.hypot(W, H)
    np.testing.assert_allclose(g.edge_sigmas(1.0), [0.5, 0.5, 0.5 / r, 0.5 / r])
    np.testing.assert_allclose(g.edge_sigmas(0.25), [2.0, 2.0, 2.0 / r, 2.0 / r])
    np.testing.assert_allclose(g.edge_sigmas(0.0), g.edge_sigmas(0.1))  # clipped, never infinite


@pytest.mark.parametrize("loss", ["linear", "soft_l1", "cauchy", "huber"])
def test_analytic_jacobian_matches_finite_differences(loss, truth):
    g, _ = chained_graph(truth[:40], loops=False)
    g.add_edge(3, 30, relative(truth, 3, 30) @ about_centre(20.0, 1.1, (50.0, 9.0)), kind="loop")  # far out
    g.add_edge(30, 5, relative(truth, 30, 5), kind="loop")
    g.fix(7)
    rng = np.random.default_rng(3)
    for k in range(0, 40, 6):
        g.add_position_prior(k, centres(truth)[k] + rng.normal(0, 5, 2), 3.0)
        g.add_gps_prior(k + 1, centres(truth)[k + 1] * [0.05, -0.05] + rng.normal(0, 0.2, 2), 0.3)
        g.add_heading_prior(k + 2, rng.normal(0, 0.1), 0.02)
        g.add_scale_prior(k + 3, 50.0 + rng.normal(0, 1), 0.01)
    prob = _Problem(g, loss, 2.0)
    x = prob.x0 + rng.normal(0, 1e-3, prob.x0.shape)
    f, jac = prob.evaluate(x)
    num = np.empty((len(f), len(x)))
    for k in range(len(x)):
        h = 1e-6 * max(1.0, abs(x[k]))
        e = np.zeros_like(x)
        e[k] = h
        num[:, k] = (prob.evaluate(x + e)[0] - prob.evaluate(x - e)[0]) / (2 * h)
    np.testing.assert_allclose(jac.toarray(), num, atol=2e-5 * np.abs(num).max())
    assert jac.shape[1] == 4 * 39 + 1 + 1 + 4  # node 7 locked; heading, scale and GPS globals


# --------------------------------------------------------------------------- loop closures

def test_exact_graph_is_a_fixed_point(truth):
    g = PoseGraph((W, H))
    for p in truth:
        g.add_node(p)
    for k in range(N - 1):
        g.add_edge(k, k + 1, relative(truth, k, k + 1)[:2])
    g.add_edge(0, N - 1, relative(truth, 0, N - 1), kind="loop")
    r = optimize(g)
    np.testing.assert_allclose(r.poses, truth, atol=1e-6)
    assert np.abs(r.edge_errors).max() < 1e-6 and len(r.outliers) == 0


def test_loop_closures_remove_drift(truth):
    g, pairs = chained_graph(truth)
    assert len(pairs) > 20  # crossing and start/end overlap
    chained = ate(g.initial_poses(), truth)
    assert chained > 50.0  # the biased chain drifts
    r = optimize(g)
    assert r.success
    assert ate(r.poses, truth) < chained / 10
    # the loop's end meets its start: the last node's centre (and its corners) within 1 px
    corners = np.array([[0, 0, 1], [W - 1, 0, 1], [0, H - 1, 1], [W - 1, H - 1, 1.0]]).T
    assert np.abs((r.poses[-1] - truth[-1]) @ corners).max() < 1.0
    assert len(r.outliers) == 0
    np.testing.assert_array_equal(r.poses[0], g.initial_poses()[0])  # node 0 is the gauge


def test_trf_solver_agrees_with_lm(truth):
    g, _ = chained_graph(truth[:120], loops=False)
    g.add_edge(0, 110, relative(truth, 0, 110), kind="loop")
    g.add_edge(20, 90, relative(truth, 20, 90), kind="loop")
    lm, trf = optimize(g, PosegraphConfig(solver="lm")), optimize(g, PosegraphConfig(solver="trf"))
    assert trf.success and lm.success
    np.testing.assert_allclose(centres(trf.poses), centres(lm.poses), atol=0.05)
    assert trf.cost == pytest.approx(lm.cost, rel=1e-4)


def test_one_wrong_loop_closure_is_rejected_by_the_robust_loss(truth):
    g, _ = chained_graph(truth)
    # a confident but wrong closure: frames 40 and 150 do not overlap, the registration says they do
    wrong = g.add_edge(40, 150, about_centre(12.0, 1.08, (60.0, -35.0)), confidence=0.95, kind="loop")
    good = optimize(g, PosegraphConfig(robust="cauchy"))
    assert ate(good.poses, truth) < 3.0
    assert list(good.outliers) == [wrong]
    assert good.edge_norms[wrong] > 100
    plain = optimize(g, PosegraphConfig(robust="linear"))
    assert ate(plain.poses, truth) > 10 * ate(good.poses, truth)  # without it one edge wrecks the map
    # the wrong edge keeps a small pull (Cauchy's influence decays as 1/residual): under 1 px here;
    # dropping it and re-optimising from the result gives the clean graph's answer
    clean, _ = chained_graph(truth)
    clean_poses = optimize(clean).poses
    np.testing.assert_allclose(centres(good.poses), centres(clean_poses), atol=1.0)
    g.drop_edges(good.outliers)
    g.set_poses(good.poses)
    again = optimize(g)
    assert again.nfev < good.nfev and len(again.outliers) == 0
    np.testing.assert_allclose(again.poses, clean_poses, atol=1e-5)


def test_locked_node_stays_put(truth):
    g, _ = chained_graph(truth)
    g.fix(120)
    r = optimize(g)
    initial = g.initial_poses()
    np.testing.assert_array_equal(r.poses[120], initial[120])
    assert np.linalg.norm(centres(r.poses)[0] - centres(initial)[0]) > 1.0  # node 0 is not the gauge now
    # the shape is right: relative to the locked node, the truth is recovered
    fixed_truth = initial[120] @ np.linalg.inv(truth[120]) @ truth
    assert ate(r.poses, fixed_truth) < 3.0


def test_a_windowed_solve_moves_only_the_newest_nodes_and_matches_the_full_solve(truth):
    from photomap.core.keyframes import KeyframeGraph

    g, _ = chained_graph(truth[:120], loops=False)  # a drifting chain: its own optimum
    g.add_edge(90, 115, relative(truth, 90, 115), confidence=0.8, kind="loop")
    wrong = g.add_edge(100, 118, about_centre(10.0, 1.05, (50.0, 20.0)), confidence=0.95, kind="loop")
    params = PosegraphConfig()
    initial = g.initial_poses()
    full, full_dropped = KeyframeGraph.solve(g.copy(), params)
    win, win_dropped = KeyframeGraph.solve(g.copy(), params, newest=40)
    assert full_dropped == win_dropped == [wrong]  # an edge index of the whole graph
    np.testing.assert_array_equal(win[:80], initial[:80])  # older than the window: untouched
    assert np.abs(centres(win[80:]) - centres(initial[80:])).max() > 5.0  # the loop pulled the window
    # the loop lies inside the window, the chain before it is a rigid branch: the same optimum
    np.testing.assert_allclose(centres(win), centres(full), atol=1e-3)
    # a graph no larger than the window is solved whole
    same, _ = KeyframeGraph.solve(g.copy(), params, newest=120)
    np.testing.assert_allclose(same, full, atol=1e-9)


def test_window_holds_the_newest_nodes_by_the_older_ones_they_reach(truth):
    g, _ = chained_graph(truth[:120], loops=False)
    g.add_edge(10, 110, relative(truth, 10, 110), confidence=0.8, kind="loop")  # reaches far back
    g.add_edge(20, 30, relative(truth, 20, 30), confidence=0.8, kind="loop")  # among old nodes
    g.add_gps_prior(5, (0.0, 0.0), 3.0)
    g.add_gps_prior(100, (10.0, 0.0), 3.0)
    sub, nodes, edges = g.window(40)
    np.testing.assert_array_equal(nodes, [10, 79] + list(range(80, 120)))
    assert sub.fixed == {0, 1}  # the older nodes come along locked
    pairs = g.edge_pairs
    np.testing.assert_array_equal(sub.edge_pairs, np.searchsorted(nodes, pairs[edges]))
    assert sorted(map(tuple, pairs[edges].tolist())) == sorted([(k, k + 1) for k in range(79, 119)] + [(10, 110)])
    assert [p[0] for p in sub._gps] == [int(np.searchsorted(nodes, 100))]  # node 5 is not in it
    np.testing.assert_array_equal(sub.initial_poses(), g.initial_poses()[nodes])
    # solved: the locked node keeps its pose, and the window is bent onto it (the chain drifted)
    r = optimize(sub)
    np.testing.assert_array_equal(r.poses[:2], sub.initial_poses()[:2])
    loop = int(np.flatnonzero((pairs[edges] == (10, 110)).all(axis=1))[0])
    before = optimize(sub, PosegraphConfig(max_nfev=1)).edge_norms[loop]
    assert before > 20 and r.edge_norms[loop] < 1.0


# --------------------------------------------------------------------------- priors

def test_gps_priors_in_metres_pull_a_drifting_chain_back(truth):
    g, _ = chained_graph(truth, loops=False)
    chained = ate(g.initial_poses(), truth)
    # true map px -> (east, north): 0.05 m/px, map up 30 deg east of north, origin offset
    a = 0.05 * np.exp(1j * math.radians(30.0))
    rng = np.random.default_rng(5)
    z = centres(truth) @ [1.0, 1j]
    es = a * z + (120.0 - 40.0j)  # (east, -north)
    for k in range(0, N, 4):
        g.add_gps_prior(k, (es[k].real + rng.normal(0, 0.5), -es[k].imag + rng.normal(0, 0.5)), 0.5)
    r = optimize(g)
    assert ate(r.poses, truth) < chained / 5
    # the estimated map -> metres similarity: scale and rotation of the truth (up to what the
    # biased chain leaves, node 0 being locked), and it maps the corrected track onto the fixes
    m = r.map_to_enu
    assert math.hypot(m[0, 0], m[1, 0]) == pytest.approx(0.05, rel=0.01)
    assert math.degrees(math.atan2(-m[1, 0], m[0, 0])) == pytest.approx(30.0, abs=1.0)
    enu = centres(r.poses) @ m[:, :2].T + m[:, 2]
    err = enu[::4] - np.c_[es.real, -es.imag][::4]
    assert np.sqrt((err ** 2).sum(axis=1).mean()) < 1.0  # metres; GPS noise 0.5 m per axis
    assert r.heading_offset is None and r.log_scale_offset is None


def test_position_priors_in_map_pixels_and_gps_outlier(truth):
    g, _ = chained_graph(truth, loops=False)
    chained = ate(g.initial_poses(), truth)
    rng = np.random.default_rng(6)
    cen = centres(truth)
    for k in range(0, N, 4):
        g.add_position_prior(k, cen[k] + rng.normal(0, 5.0, 2), 5.0)
    g.add_position_prior(100, cen[100] + [300.0, 0.0], 5.0)  # a GPS glitch
    r = optimize(g)
    assert ate(r.poses, truth) < chained / 5
    assert list(r.prior_outliers["position"]) == [N // 4]  # the glitch, as the last prior added


def test_heading_priors_with_free_offset(truth):
    g, _ = chained_graph(truth, rot_bias_deg=0.05, loops=False)
    rng = np.random.default_rng(7)
    true_theta = np.arctan2(truth[:, 1, 0], truth[:, 0, 0])
    offset = 0.6  # map up vs north, unknown to the graph
    for k in range(N):
        g.add_heading_prior(k, true_theta[k] - offset + rng.normal(0, math.radians(0.5)), math.radians(0.5))

    def heading_rms(poses):
        return float(np.sqrt((((np.arctan2(poses[:, 1, 0], poses[:, 0, 0]) - true_theta + np.pi)
                               % (2 * np.pi) - np.pi) ** 2).mean()))

    r = optimize(g)
    assert heading_rms(r.poses) < heading_rms(g.initial_poses()) / 5
    assert r.heading_offset == pytest.approx(offset, abs=math.radians(0.5))  # drift was 10 deg


def test_scale_priors_from_altitude(truth):
    g, _ = chained_graph(truth, scale_bias=1e-3, loops=False)
    rng = np.random.default_rng(8)
    true_logs = 0.5 * np.log(np.linalg.det(truth[:, :2, :2]))
    altitude = 80.0 * np.exp(true_logs) * (1 + rng.normal(0, 0.002, N))  # scale ~ altitude
    for k in range(N):
        g.add_scale_prior(k, altitude[k], 0.005)
    r = optimize(g)

    def logs_rms(poses):
        return float(np.sqrt(((0.5 * np.log(np.linalg.det(poses[:, :2, :2])) - true_logs) ** 2).mean()))

    assert logs_rms(r.poses) < logs_rms(g.initial_poses()) / 5
    assert r.log_scale_offset == pytest.approx(-math.log(80.0), abs=0.01)  # drift was 0.2


# --------------------------------------------------------------------------- applying corrections

def test_correction_and_interpolation():
    old = [about_centre(5.0, 1.1, (10.0, 20.0)), about_centre(-3.0, 0.9, (400.0, 30.0))]
    new = [about_centre(6.0, 1.12, (12.0, 18.0)), about_centre(-1.0, 0.95, (410.0, 25.0))]
    cs = np.array([correction(o, n) for o, n in zip(old, new)])
    np.testing.assert_allclose(cs[0] @ old[0], new[0], atol=1e-9)
    # frames 0..20, keyframes at 5 and 15: before/at 5 -> C5, 6..14 follow keyframe 5, >= 15 -> C15
    frames = np.arange(21)
    per = interpolate_corrections([15, 5], cs[::-1], frames)
    np.testing.assert_allclose(per[:15], np.broadcast_to(cs[0], (15, 3, 3)))
    np.testing.assert_allclose(per[15:], np.broadcast_to(cs[1], (6, 3, 3)))
    # blended: the pivot goes to the linear blend of both corrections; angle/scale interpolate
    pivots = np.tile([300.0, 200.0], (21, 1))
    bl = interpolate_corrections([5, 15], cs, frames, blend=True, pivots=pivots)
    np.testing.assert_allclose(bl[[0, 5]], np.broadcast_to(cs[0], (2, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(bl[15], cs[1], atol=1e-12)
    p = np.r_[pivots[0], 1.0]
    np.testing.assert_allclose(bl[8] @ p, 0.7 * cs[0] @ p + 0.3 * cs[1] @ p, atol=1e-9)
    ang = np.degrees(np.arctan2(bl[:, 1, 0], bl[:, 0, 0]))
    ang_c = np.degrees(np.arctan2(cs[:, 1, 0], cs[:, 0, 0]))
    assert ang[10] == pytest.approx(ang_c.mean())
    assert np.linalg.det(bl[10, :2, :2]) == pytest.approx(np.sqrt(np.prod(np.linalg.det(cs[:, :2, :2]))))


def test_bad_input_is_refused():
    g = PoseGraph((W, H))
    g.add_node(np.eye(3))
    g.add_node(np.eye(3)[:2])
    with pytest.raises(ValueError, match="does not exist"):
        g.add_edge(0, 5, np.eye(3))
    with pytest.raises(ValueError, match="two different nodes"):
        g.add_edge(1, 1, np.eye(3))
    with pytest.raises(ValueError, match="finite"):
        g.add_edge(0, 1, np.full((2, 3), np.nan))
    with pytest.raises(ValueError, match="not a similarity"):
        g.add_edge(0, 1, np.diag([1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="kind"):
        g.add_edge(0, 1, np.eye(3), kind="guess")
    with pytest.raises(ConfigError, match="posegraph.robust"):
        optimize(g, PosegraphConfig(robust="l2"))
    with pytest.raises(ValueError, match="no nodes"):
        optimize(PoseGraph((W, H)))
    with pytest.raises(ValueError, match="edge indices"):
        g.drop_edges([0])
    with pytest.raises(ValueError, match="2 nodes"):
        g.set_poses(np.stack([np.eye(3)] * 3))
    with pytest.raises(ValueError, match="unique"):
        interpolate_corrections([1, 1], np.stack([np.eye(3)] * 2), [0])


def test_sparse_spd_solve_matches_spsolve_and_falls_back_when_singular():
    import warnings

    import scipy.sparse
    import scipy.sparse.linalg

    from photomap.core.posegraph import _solve_spd

    rng = np.random.default_rng(11)
    n, k = 300, 4  # a chain of nodes with loop edges, 4 parameters a node (as the pose graph)
    pairs = [(i, i + 1) for i in range(n - 1)] + [tuple(sorted(rng.choice(n, 2, replace=False))) for _ in range(200)]
    rows, cols, vals = [], [], []
    for i, j in pairs:  # J^T J of one relative-pose residual block per edge
        jac = np.zeros((k, n * k))
        jac[:, i * k:(i + 1) * k] = rng.standard_normal((k, k))
        jac[:, j * k:(j + 1) * k] = rng.standard_normal((k, k))
        block = scipy.sparse.coo_matrix(jac)
        rows.append(block.row + len(rows) * k)
        cols.append(block.col)
        vals.append(block.data)
    jac = scipy.sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))))
    a = (jac.T @ jac + scipy.sparse.eye(n * k)).tocsc()
    b = rng.standard_normal(n * k)
    x = _solve_spd(a, b)
    np.testing.assert_allclose(x, scipy.sparse.linalg.spsolve(a, b), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(a @ x, b, atol=1e-9)
    singular = scipy.sparse.csc_matrix(np.diag([1.0, 0.0, 2.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # spsolve's "exactly singular"
        assert np.isnan(_solve_spd(singular, np.ones(3))).all()
