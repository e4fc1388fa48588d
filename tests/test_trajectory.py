"""Trajectory files, metrics against exact synthetic truth, and `photomap evaluate`."""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys

import cv2
import numpy as np
import pytest

from photomap.cli import main as cli
from photomap.eval import evaluate
from photomap.errors import InputError
from photomap.core.records import GroundTruth, PoseRow
from photomap.geometry import angle_scale, frame_centre, local_linear, pose_angle_deg, pose_scale, umeyama
from photomap.eval.metrics import evaluate_trajectory, segment_metrics
from photomap.io.trajectory_files import (GROUNDTRUTH_COLUMNS, TRAJECTORY_COLUMNS, read_groundtruth,
                            read_trajectory_csv, write_json, write_trajectory_csv, write_tum)

W, H = 64, 48
C = frame_centre(W, H)


def sim(angle_deg: float = 0.0, scale: float = 1.0, tx: float = 0.0, ty: float = 0.0) -> np.ndarray:
    """3x3 similarity: rotate by angle_deg and scale about the origin, then translate."""
    a = math.radians(angle_deg)
    return np.array([[scale * math.cos(a), -scale * math.sin(a), tx],
                     [scale * math.sin(a), scale * math.cos(a), ty], [0.0, 0.0, 1.0]])


def about_centre(S: np.ndarray) -> np.ndarray:
    """The linear part of S applied about the frame centre (C is a fixed point)."""
    return sim(tx=C[0], ty=C[1]) @ S @ sim(tx=-C[0], ty=-C[1])


def truth_poses(n: int) -> np.ndarray:
    """A curved flight with changing yaw and altitude (frame -> terrain px)."""
    return np.array([sim(10 + 2.5 * i, 2.0 * (1 + 0.01 * i), 300 + 12 * i, 200 + 0.3 * i * i)
                     for i in range(n)])


def chain(relative: list[np.ndarray]) -> np.ndarray:
    """Poses M_0 = I, M_i = M_{i-1} @ E_i as (N, 2, 3)."""
    M = [np.eye(3)]
    for E in relative:
        M.append(M[-1] @ E)
    return np.array(M)[:, :2, :]


# --- metrics ------------------------------------------------------------------------------

def test_estimate_equal_to_truth_up_to_a_similarity_has_no_error():
    Ht = truth_poses(25)
    G = sim(-37.0, 0.25, -40.0, 900.0)  # arbitrary map frame
    M = (G @ Ht)[:, :2, :]
    res = segment_metrics(M, Ht, C)
    for key in ("translation_px", "rotation_deg", "scale_pct"):
        assert res["pairs"][key]["max"] == pytest.approx(0.0, abs=1e-9)
    assert res["pairs"]["success_rate"] == 1.0
    assert res["position_px"]["max"] == pytest.approx(0.0, abs=1e-8)
    assert res["position_px"]["drift_pct"] == pytest.approx(0.0, abs=1e-9)
    assert res["ate"]["rmse_px"] == pytest.approx(0.0, abs=1e-8)
    assert res["ate"]["scale"] == pytest.approx(4.0)
    assert res["heading_deg"]["max"] == pytest.approx(0.0, abs=1e-9)
    assert res["scale_pct"]["max"] == pytest.approx(0.0, abs=1e-9)


def test_constant_heading_error_gives_known_drift():
    n, v, delta = 40, 10.0, 0.3  # frames, px per frame, deg per pair
    Ht = np.array([sim(tx=v * i) for i in range(n)])
    E = sim(tx=v) @ about_centre(sim(delta))  # true step + rotation about the centre
    M = chain([E] * (n - 1))
    res = segment_metrics(M, Ht, C)
    # estimated centre after k steps: C + v * sum_{j<k} exp(i j delta); truth: C + (k v, 0)
    k = n - 1
    z = np.exp(1j * math.radians(delta))
    final = abs(v * (1 - z ** k) / (1 - z) - k * v)
    assert res["position_px"]["final"] == pytest.approx(final, rel=1e-9)
    assert res["position_px"]["drift_pct"] == pytest.approx(100 * final / (k * v), rel=1e-9)
    assert res["path_length_px"] == pytest.approx(k * v)
    assert res["pairs"]["rotation_deg"]["median"] == pytest.approx(delta)
    assert res["pairs"]["rotation_deg"]["max"] == pytest.approx(delta)
    assert res["pairs"]["translation_px"]["max"] == pytest.approx(0.0, abs=1e-9)
    assert res["heading_deg"]["final"] == pytest.approx(k * delta)
    assert res["pairs"]["success_rate"] == 1.0  # 0.3 deg < 0.5 deg
    assert res["per_frame"]["heading_error_deg"] == pytest.approx([i * delta for i in range(n)])


def test_translation_bias_and_scale_error_per_pair():
    n = 15
    Ht = truth_poses(n)
    bias = np.array([0.72, -0.96])  # |bias| = 1.2 px, in pixels of the earlier frame
    steps = [sim(tx=bias[0], ty=bias[1]) @ np.linalg.solve(Ht[i - 1], Ht[i]) for i in range(1, n)]
    res = segment_metrics(chain(steps), Ht, C)
    assert res["pairs"]["translation_px"]["median"] == pytest.approx(1.2)
    assert res["pairs"]["translation_px"]["rms"] == pytest.approx(1.2)
    assert res["pairs"]["rotation_deg"]["max"] == pytest.approx(0.0, abs=1e-9)
    assert res["pairs"]["success_rate"] == 0.0  # 1.2 px is not < 1 px

    steps = [np.linalg.solve(Ht[i - 1], Ht[i]) @ about_centre(sim(scale=1.02)) for i in range(1, n)]
    res = segment_metrics(chain(steps), Ht, C)
    assert res["pairs"]["scale_pct"]["median"] == pytest.approx(2.0)
    assert res["pairs"]["translation_px"]["max"] == pytest.approx(0.0, abs=1e-9)
    assert res["scale_pct"]["final"] == pytest.approx(100 * (1.02 ** (n - 1) - 1))


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(30, 2)) * 50
    G = sim(123.0, 0.7, 5.0, -9.0)
    s, R, t = umeyama(src, src @ G[:2, :2].T + G[:2, 2])
    assert s == pytest.approx(0.7)
    assert s * R == pytest.approx(G[:2, :2])
    assert t == pytest.approx(G[:2, 2])


def test_pose_angle_and_scale_of_a_similarity_and_a_mirror():
    a, s = math.radians(-137.5), 0.8125
    M = np.array([[s * math.cos(a), -s * math.sin(a), 12.0], [s * math.sin(a), s * math.cos(a), -3.0]])
    assert pose_angle_deg(M) == pytest.approx(-137.5, abs=1e-12)
    assert pose_scale(M) == pytest.approx(s, rel=1e-15)
    assert pose_scale([[2.0, 0.0, 0.0], [0.0, -0.5, 0.0]]) == pytest.approx(1.0, rel=1e-15)  # a mirror: |det|


def test_local_linear_of_a_homography_matches_finite_differences():
    Hp = sim(20, 1.5, 3, 4) @ np.array([[1, 0, 0], [0, 1, 0], [1e-3, -2e-3, 1.0]])
    p, eps = np.array([10.0, 20.0]), 1e-5

    def f(q):
        u = Hp @ np.array([q[0], q[1], 1.0])
        return u[:2] / u[2]

    num = np.column_stack([(f(p + d) - f(p - d)) / (2 * eps) for d in np.eye(2) * eps])
    assert local_linear(Hp, p) == pytest.approx(num, rel=1e-6)
    assert angle_scale(sim(-170.0, 3.0), p) == pytest.approx((-170.0, 3.0))


def test_segments_are_anchored_separately_and_the_largest_is_the_headline():
    n = 30
    Ht = truth_poses(n)
    truth = GroundTruth(frame=np.arange(n), t=np.arange(n) / 10, H=Ht)
    rows = []
    for i in range(n):
        if i < 18:  # segment 0: map frame = frame 0, exact
            rows.append(PoseRow(i, i / 10, np.linalg.solve(Ht[0], Ht[i])[:2], 0.9,
                                "reference" if i == 0 else "registered", 0))
        elif i == 18:
            rows.append(PoseRow(i, i / 10, None, math.nan, "dropped", 0))
        else:  # segment 1: a new map frame at frame 19, its own scale
            M = (sim(5, 3.0) @ np.linalg.solve(Ht[19], Ht[i]))[:2]
            rows.append(PoseRow(i, i / 10, M, 0.8, "reference" if i == 19 else "registered", 1))
    rows[5].status = "low_confidence"  # not glued: not evaluated
    res = evaluate_trajectory(rows, truth, C)
    assert res["frames"] == n and res["frames_posed"] == n - 2
    assert res["fraction_posed"] == pytest.approx((n - 2) / n)
    assert [s["segment"] for s in res["segments"]] == [0, 1]
    assert res["headline"]["segment"] == 0 and res["headline"]["frames_posed"] == 17
    assert res["segments"][1]["anchor_frame"] == 19
    for s in res["segments"]:
        assert s["position_px"]["max"] == pytest.approx(0.0, abs=1e-7)
        assert s["ate"]["rmse_px"] == pytest.approx(0.0, abs=1e-7)
    # path length of segment 0 runs along the truth through every frame 0..17, including 5
    centres = (Ht[:18, :2, :2] @ np.array(C) + Ht[:18, :2, 2])
    assert res["segments"][0]["path_length_px"] == pytest.approx(
        np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())


# --- files --------------------------------------------------------------------------------

def sample_rows() -> list[PoseRow]:
    return [
        PoseRow(0, 0.0, np.eye(3)[:2], 1.0, "reference", 0,
                {"lat": 47.5, "lon": 8.25, "alt_m": np.float64(30.0)}),
        PoseRow(1, 0.1, sim(3.0, 1.01, 5.5, -2.25)[:2], 0.8, "registered", 0,
                {"lat": 47.50001, "lon": 8.25002, "alt_m": 30.5}),
        PoseRow(2, 0.2, sim(6.0, 1.02, 11.0, -4.5)[:2], 0.1, "low_confidence", 0,
                {"lat": None, "lon": None, "alt_m": None}),
        PoseRow(3, 0.3, None, math.nan, "dropped", 0, {"mode": "AUTO"}),
        PoseRow(4, 0.4, None, 0.0, "corrupt", 0),
        PoseRow(5, 0.5, np.eye(3)[:2], 0.9, "reference", 1),
        PoseRow(6, 0.6, sim(-1.0, 1.0, 1.0 / 3.0, 2.0)[:2], 0.7, "registered", 1),
    ]


def test_trajectory_csv_round_trip(tmp_path):
    path = tmp_path / "trajectory.csv"
    rows = sample_rows()
    write_trajectory_csv(path, rows, frame_size=(W, H))
    with path.open(newline="") as f:
        raw = list(csv.reader(f))
    assert raw[0] == [*TRAJECTORY_COLUMNS, "lat", "lon", "alt_m", "mode"]
    dropped = dict(zip(raw[0], raw[4]))
    assert all(dropped[c] == "" for c in ("x", "y", "angle_deg", "scale", "m00", "m12", "confidence"))
    assert dropped["status"] == "dropped" and dropped["mode"] == "AUTO"
    second = dict(zip(raw[0], raw[2]))
    assert float(second["angle_deg"]) == pytest.approx(3.0)
    assert float(second["scale"]) == pytest.approx(1.01)

    back = read_trajectory_csv(path)
    assert len(back) == len(rows)
    for a, b in zip(rows, back):
        assert (b.frame, b.status, b.segment) == (a.frame, a.status, a.segment)
        assert b.t == pytest.approx(a.t)
        if a.M is None:
            assert b.M is None and b.xy is None
        else:
            assert np.array_equal(b.M, a.M)  # exact: written with repr
            assert b.xy == pytest.approx(tuple(a.M[:, :2] @ np.array(C) + a.M[:, 2]), abs=1e-6)
        assert (math.isnan(b.confidence) if math.isnan(a.confidence)
                else b.confidence == pytest.approx(a.confidence))
    assert back[0].extra == {"lat": 47.5, "lon": 8.25, "alt_m": 30.0, "mode": None}
    assert back[1].extra == {"lat": 47.50001, "lon": 8.25002, "alt_m": 30.5, "mode": None}
    assert back[2].extra["lat"] is None and back[3].extra["mode"] == "AUTO"

    # the reader accepts columns in another order and more columns
    with path.open(newline="") as f:
        table = list(csv.DictReader(f))
    cols = ["extra_first", *reversed(TRAJECTORY_COLUMNS)]
    with (tmp_path / "other.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, cols, extrasaction="ignore")
        w.writeheader()
        w.writerows({**r, "extra_first": "x"} for r in table)
    other = read_trajectory_csv(tmp_path / "other.csv")
    assert np.array_equal(other[6].M, rows[6].M) and other[6].extra == {"extra_first": "x"}


def test_trajectory_csv_bad_input(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_trajectory_csv(tmp_path / "missing.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("frame,t,x\n0,0,0\n")
    with pytest.raises(InputError, match="lacks column"):
        read_trajectory_csv(bad)
    write_trajectory_csv(bad, sample_rows()[:2], frame_size=(W, H))
    text = bad.read_text().splitlines()
    bad.write_text("\n".join([text[0], text[1].replace("reference", "glued")]) + "\n")
    with pytest.raises(InputError, match="line 2: status 'glued'"):
        read_trajectory_csv(bad)


def test_long_trajectories_are_written_piece_by_piece_and_atomically(tmp_path, monkeypatch):
    import photomap.io.trajectory_files as tf

    rng = np.random.default_rng(4)
    rows = [PoseRow(i, i / 30.0, sim(float(rng.uniform(-180, 180)), 1.0, *rng.uniform(-500, 500, 2))[:2],
                    float(rng.uniform(0, 1)), "registered", 0, {"method": "ifmi"} if i % 3 else {})
            for i in range(3 * tf._CHUNK_ROWS + 5)]
    csv_path, tum_path = tmp_path / "trajectory.csv", tmp_path / "trajectory.tum"
    write_trajectory_csv(csv_path, rows, frame_size=(W, H))
    write_tum(tum_path, rows, frame_size=(W, H))
    monkeypatch.setattr(tf, "_CHUNK_ROWS", 10 ** 9)  # the whole file at once: the same text
    assert csv_path.read_text() == tf.format_trajectory_csv(rows, (W, H))
    assert tum_path.read_text() == tf.format_tum(rows, (W, H))
    back = read_trajectory_csv(csv_path)
    assert [r.frame for r in back] == [r.frame for r in rows]
    assert all(np.array_equal(a.M, b.M) for a, b in zip(rows, back))
    assert len(tum_path.read_text().splitlines()) == len(rows) + 1
    # a bad row in a later piece: the previous file stays whole, no temporary file is left
    monkeypatch.setattr(tf, "_CHUNK_ROWS", 64)
    before = csv_path.read_bytes()
    rows[1000] = PoseRow(1000, 1000 / 30.0, None, 0.0, "glued", 0)
    with pytest.raises(ValueError, match="status 'glued'"):
        write_trajectory_csv(csv_path, rows, frame_size=(W, H))
    assert csv_path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["trajectory.csv", "trajectory.tum"]


def test_tum_is_valid_for_evo(tmp_path):
    rows = sample_rows()
    rows.append(PoseRow(7, 0.6, sim(2.0)[:2], 0.9, "registered", 1))  # t does not increase
    path = tmp_path / "trajectory.tum"
    # default: the largest segment, 1 (frames 5, 6, 7 glued); frame 7 is skipped
    write_tum(path, rows, frame_size=(W, H))
    lines = path.read_text().splitlines()
    assert lines[0].startswith("#") and "segment 1" in lines[0]
    data = np.array([[float(v) for v in ln.split()] for ln in lines[1:]])
    assert data.shape == (2, 8) and list(data[:, 0]) == [0.5, 0.6]

    # segment 0: frames 0 and 1 (frame 2 is low_confidence, not glued)
    write_tum(path, rows, frame_size=(W, H), segment=0)
    data = np.loadtxt(path, comments="#")
    assert data.shape == (2, 8)
    assert np.all(np.diff(data[:, 0]) > 0)
    M1 = rows[1].M
    assert data[1, 1:3] == pytest.approx(M1[:, :2] @ np.array(C) + M1[:, 2], abs=1e-6)
    assert data[1, 3:6] == pytest.approx([0, 0, 0])
    assert 2 * math.degrees(math.atan2(data[1, 6], data[1, 7])) == pytest.approx(3.0)
    assert np.linalg.norm(data[:, 4:], axis=1) == pytest.approx([1, 1])


def test_tum_says_the_frames_it_skips_once_with_a_count(tmp_path, caplog):
    """Capture times of one-second resolution (EXIF) repeat: one line for all the frames left out."""
    rows = sample_rows()
    rows += [PoseRow(7, 0.6, sim(2.0)[:2], 0.9, "registered", 1), PoseRow(8, 0.6, sim(2.5)[:2], 0.9, "registered", 1)]
    with caplog.at_level("WARNING"):
        write_tum(tmp_path / "a.tum", rows, frame_size=(W, H))
    said = [r.getMessage() for r in caplog.records if "TUM" in r.getMessage()]
    assert said == ["TUM: 2 frame(s) skipped (frames 7, 8): their times do not increase "
                    "(e.g. capture times of one-second resolution)"]
    caplog.clear()
    skipped: list[int] = []  # the caller collects them (and says them once for the run)
    with caplog.at_level("WARNING"):
        write_tum(tmp_path / "b.tum", rows, frame_size=(W, H), skipped=skipped)
    assert skipped == [7, 8] and not caplog.records
    assert (tmp_path / "a.tum").read_text() == (tmp_path / "b.tum").read_text()


def test_writes_are_atomic(tmp_path, monkeypatch):
    path = tmp_path / "trajectory.csv"
    for k in range(3):
        write_trajectory_csv(path, sample_rows()[: k + 2], frame_size=(W, H))
        write_tum(tmp_path / "trajectory.tum", sample_rows(), frame_size=(W, H))
        write_json(tmp_path / "run.json", {"k": k})
    assert sorted(os.listdir(tmp_path)) == ["run.json", "trajectory.csv", "trajectory.tum"]
    before = path.read_bytes()

    def fail(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        write_trajectory_csv(path, sample_rows(), frame_size=(W, H))
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["run.json", "trajectory.csv", "trajectory.tum"]


def test_write_json_is_strict_json(tmp_path):
    path = tmp_path / "e.json"
    write_json(path, {"a": np.float32(1.5), "b": np.arange(3), "c": math.nan, "d": (1, math.inf),
                      "e": np.int64(7)})
    assert json.loads(path.read_text()) == {"a": 1.5, "b": [0, 1, 2], "c": None, "d": [1, None],
                                            "e": 7}


def write_groundtruth(path, Ht: np.ndarray, extra: bool = True) -> None:
    """groundtruth.csv as `photomap simulate` writes it (plus an extra column)."""
    cols = [*GROUNDTRUTH_COLUMNS, "note"] if extra else list(GROUNDTRUTH_COLUMNS)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for i, h in enumerate(Ht):
            xy = h[:2, :2] @ np.array(C) + h[:2, 2]
            a, s = angle_scale(h, C)
            w.writerow([i, i / 10, *xy, a, s, 0, 0, 30.0, *(repr(float(v)) for v in h.ravel()),
                        *(["n/a"] if extra else [])])


def test_read_groundtruth(tmp_path):
    Ht = truth_poses(5)
    path = tmp_path / "groundtruth.csv"
    write_groundtruth(path, Ht)
    gt = read_groundtruth(path)
    assert list(gt.frame) == [0, 1, 2, 3, 4]
    assert np.array_equal(gt.H, Ht)
    assert gt.columns["alt_m"] == pytest.approx([30.0] * 5)
    assert "note" not in gt.columns
    with pytest.raises(InputError, match="not found"):
        read_groundtruth(tmp_path / "nope.csv")
    path.write_text("frame,t,h00\n0,0,1\n")
    with pytest.raises(InputError, match="lacks column"):
        read_groundtruth(path)


# --- photomap evaluate --------------------------------------------------------------------

def make_run(tmp_path, n: int = 30, delta: float = 0.2):
    """A run dir whose segment 0 has a constant heading error of delta deg per pair and whose
    segment 1 is exact; frame 20 is dropped."""
    Ht = truth_poses(n)
    run = tmp_path / "run"
    run.mkdir()
    rows, M = [], None
    for i in range(n):
        if i < 20:
            if i == 0:
                M = np.eye(3)
            else:
                M = M @ np.linalg.solve(Ht[i - 1], Ht[i]) @ about_centre(sim(delta))
            rows.append(PoseRow(i, i / 10, M[:2], 0.9, "reference" if i == 0 else "registered", 0))
        elif i == 20:
            rows.append(PoseRow(i, i / 10, None, math.nan, "dropped", 0))
        else:
            rows.append(PoseRow(i, i / 10, np.linalg.solve(Ht[21], Ht[i])[:2], 0.9,
                                "reference" if i == 21 else "registered", 1, {"alt_m": 30.0}))
    write_trajectory_csv(run / "trajectory.csv", rows, frame_size=(W, H))
    write_groundtruth(tmp_path / "groundtruth.csv", Ht)
    return run, tmp_path / "groundtruth.csv"


def test_evaluate_run_writes_numbers_and_plots(tmp_path):
    pytest.importorskip("matplotlib", reason="matplotlib (extra 'plots') draws the figures")
    run, gt = make_run(tmp_path)
    out = tmp_path / "eval"
    res = evaluate_run_checked(run, gt, out)
    saved = json.loads((out / "evaluation.json").read_text())
    assert saved["headline"]["segment"] == 0
    assert saved["frame_centre"] == list(C)  # exact: rounded to 0.5 px
    assert saved["fraction_posed"] == pytest.approx(29 / 30)
    h = saved["headline"]
    assert h["pairs"]["rotation_deg"]["median"] == pytest.approx(0.2)
    assert h["heading_deg"]["final"] == pytest.approx(19 * 0.2)
    assert h["pairs"]["translation_px"]["max"] == pytest.approx(0.0, abs=1e-6)
    assert h["position_px"]["drift_pct"] > 0.5
    assert saved["segments"][1]["ate"]["rmse_px"] == pytest.approx(0.0, abs=1e-6)
    assert h["position_px"]["final"] == pytest.approx(res["headline"]["position_px"]["final"])
    assert [os.path.basename(p) for p in saved["plots"]] == [evaluate.POSES_PNG,
                                                             evaluate.TRAJECTORY_PNG]
    for name in (evaluate.POSES_PNG, evaluate.TRAJECTORY_PNG):
        img = cv2.imread(str(out / name))
        assert img is not None and img.shape[0] > 300 and img.shape[1] > 300
        assert img.std() > 10  # axes, lines and text, not a blank canvas
    assert not [p for p in os.listdir(out) if p.endswith(".tmp")]
    assert "per_frame" not in h
    with (out / evaluate.FRAMES_CSV).open(newline="") as f:
        frames = list(csv.DictReader(f))
    assert [int(r["frame"]) for r in frames] == [*range(20), *range(21, 30)]
    seg0 = [r for r in frames if r["segment"] == "0"]
    assert [float(r["heading_error_deg"]) for r in seg0] == pytest.approx(
        [0.2 * i for i in range(20)], abs=1e-6)
    assert seg0[0]["pair_rotation_deg"] == "" and float(seg0[5]["pair_rotation_deg"]) == 0.2


def evaluate_run_checked(run, gt, out):
    res = evaluate.evaluate_run(run, gt, out)
    table = evaluate.format_table(res)
    assert "headline: segment 0" in table and "segment 1:" in table
    return res


def test_evaluate_without_matplotlib_still_writes_numbers(tmp_path, monkeypatch, capsys):
    run, gt = make_run(tmp_path)
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)  # import fails
    args = argparse.Namespace(run_dir=str(run), truth=str(gt), out=None)
    assert evaluate.main(args, {}) == 0
    out = capsys.readouterr().out
    assert evaluate.PLOTS_HINT in out and "pair rotation deg" in out
    saved = json.loads((run / "evaluation.json").read_text())
    assert saved["plots"] == [] and saved["headline"]["frames_posed"] == 20
    assert not (run / evaluate.POSES_PNG).exists()


def test_cli_evaluate_missing_inputs(tmp_path, monkeypatch, capsys):
    run, gt = make_run(tmp_path)
    monkeypatch.setattr(cli, "COMMANDS", {"evaluate": cli.COMMANDS["evaluate"]})
    assert cli.main(["evaluate", str(tmp_path / "nope"), "--truth", str(gt)]) == InputError.exit_code
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "run directory not found" in err
    assert cli.main(["evaluate", str(run), "--truth", str(tmp_path / "gt.csv")]) == 3
    err = capsys.readouterr().err
    assert "ground truth not found" in err and "Traceback" not in err
