"""`photomap merge`: maps of overlapping flights placed against the simulator's truth; a pair
that does not overlap is refused, not forced."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import shared_data
from photomap.cli.main import main
from photomap.cli.replay import replay
from photomap.config import load_config
from photomap.core.mapmerge import robust_similarity, spread_points
from photomap.mapping.merge import merge_runs
from photomap.io.trajectory_files import read_groundtruth, read_trajectory_csv
from photomap.sim.simulate import simulate_flight

# seeds over the bundled terrain: 30 and 43 overlap (70 % of the smaller map, the second one
# turned by 82 degrees and 11 % larger); 30 and 32 fly over different parts of it
SEEDS = (30, 43, 32)
FRAMES = 90


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("merge")
    out = {}
    for seed in SEEDS:
        sim = simulate_flight(root / f"sim{seed}", n_frames=FRAMES, size=(320, 240), fps=15.0, seed=seed)
        replay(str(sim / "video.mp4"), root / f"run{seed}", load_config(), mavlink=str(sim / "telemetry.tlog"))
        out[seed] = (root / f"run{seed}", sim)
    return out


def _map_to_terrain(run, sim) -> np.ndarray:
    """3x3 map px -> terrain px through the run's first posed frame and its true matrix."""
    row = next(r for r in read_trajectory_csv(run / "trajectory.csv") if r.M is not None)
    truth = read_groundtruth(sim / "groundtruth.csv")
    return truth.H[row.frame] @ np.linalg.inv(np.vstack([np.asarray(row.M, float), [0, 0, 1]]))


def _errors(runs, ref: int, mov: int, M: np.ndarray) -> np.ndarray:
    """Distances (merged px) between the estimated and the true merged position of every frame
    centre of the moving map."""
    true = np.linalg.inv(_map_to_terrain(*runs[ref])) @ _map_to_terrain(*runs[mov])
    rows = [r for r in read_trajectory_csv(runs[mov][0] / "trajectory.csv") if r.M is not None]
    c = np.array([np.asarray(r.M) @ [159.5, 119.5, 1.0] for r in rows])
    c = np.c_[c, np.ones(len(c))].T
    return np.hypot(*((M @ c)[:2] - (true @ c)[:2]))


@pytest.mark.parametrize("georeference", [False, True])
def test_overlapping_flights_are_placed_within_a_pixel(runs, tmp_path, georeference, capsys):
    out = tmp_path / "merged"
    args = ["merge", str(runs[30][0]), str(runs[43][0]), "--out", str(out), "-q"]
    code = main(args + ([] if georeference else ["--no-georeference"]))
    assert code == 0, capsys.readouterr().out
    summary = json.loads((out / "merge.json").read_text())
    ref, mov = summary["runs"]
    assert ref["reference"] and np.allclose(ref["map_to_merged"], np.eye(3))
    assert mov["placed"] and mov["coarse"] == ("georeference" if georeference else "ifmi")
    M = np.array(mov["map_to_merged"])
    err = _errors(runs, 30, 43, M)
    assert np.median(err) < 0.5 and err.max() < 2.0, err
    assert mov["confidence"] >= 0.3 and mov["levels"][-1]["inliers"] >= 3
    # the merged map holds both: the reference's pixels where it is, the other's elsewhere
    merged = cv2.imread(str(out / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    own = cv2.imread(str(runs[30][0] / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    assert (merged[..., 3] == 255).sum() > 1.1 * (own[..., 3] == 255).sum()
    assert summary["georeference"]["crs"].startswith("EPSG:326") and (out / "mosaic.pgw").is_file()
    # the second map's pixels land on the reference's: compare in the overlap
    mx, my = summary["mosaic"]["origin_xy"]
    info = json.loads((runs[30][0] / "run.json").read_text())["mosaics"][0]
    ox, oy = info["origin_xy"]
    crop = merged[oy - my:oy - my + own.shape[0], ox - mx:ox - mx + own.shape[1]]
    h, w = min(crop.shape[0], own.shape[0]), min(crop.shape[1], own.shape[1])  # painting erodes a border px
    crop, own = crop[:h, :w], own[:h, :w]
    both = (crop[..., 3] == 255) & (own[..., 3] == 255)
    assert both.sum() > 0.9 * (own[..., 3] == 255).sum()
    assert np.abs(crop[..., :3][both].astype(int) - own[..., :3][both]).mean() < 6


def test_flights_that_do_not_overlap_are_refused(runs, tmp_path, capsys):
    out = tmp_path / "merged"
    code = main(["merge", str(runs[30][0]), str(runs[32][0]), "--out", str(out), "--no-georeference", "-q"])
    printed = capsys.readouterr().out
    assert code == 1 and "NOT placed" in printed
    summary = json.loads((out / "merge.json").read_text())
    mov = summary["runs"][1]
    assert not mov["placed"] and mov["map_to_merged"] is None and mov["reason"]
    assert summary["not_placed"] == [str(runs[32][0])]
    # the merged map is the reference's alone
    merged = cv2.imread(str(out / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    own = cv2.imread(str(runs[30][0] / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    assert merged.shape == own.shape and np.array_equal(merged, own)


def test_robust_similarity_drops_a_wild_window():
    rng = np.random.default_rng(1)
    src = rng.uniform(0, 500, (8, 2))
    a = np.deg2rad(30.0)
    S = np.array([[1.1 * np.cos(a), -1.1 * np.sin(a), 40.0], [1.1 * np.sin(a), 1.1 * np.cos(a), -7.0]])
    dst = src @ S[:, :2].T + S[:, 2] + rng.normal(0, 0.2, (8, 2))
    dst[3] += (60.0, -45.0)  # one window matched the wrong place
    fit, keep = robust_similarity(src, dst, tol=1.5)
    assert not keep[3] and keep.sum() == 7
    moved = src @ fit[:2, :2].T + fit[:2, 2]
    assert np.hypot(*(moved - (src @ S[:, :2].T + S[:, 2])).T).max() < 0.5
    assert robust_similarity(src[:2], dst[:2], tol=1.5, min_inliers=3) is None


def test_spread_points_stay_inside_and_apart():
    mask = np.zeros((200, 300), np.uint8)
    cv2.circle(mask, (150, 100), 80, 1, -1)
    pts = spread_points(mask, margin=20, count=10, spacing=30)
    assert 3 <= len(pts) <= 10
    for x, y in pts:
        assert np.hypot(x - 150, y - 100) <= 60.5
    d = [np.hypot(p[0] - q[0], p[1] - q[1]) for i, p in enumerate(pts) for q in pts[i + 1:]]
    assert min(d) >= 30


def test_two_real_surveys_of_one_site(tmp_path):
    """Brighton beach stills split in two overlapping "flights" (stills 6-13 and 10-17, one camera
    at one height): the second map goes onto the first with the small rotation between their
    first stills and no scale, and its windows agree to a pixel or two."""
    images = sorted((shared_data("brighton_beach") / "images").glob("*.jpg"))
    runs = []
    for name, part in (("a", images[6:14]), ("b", images[10:])):  # the beach and park strips
        folder = tmp_path / name
        folder.mkdir()
        for p in part:
            (folder / p.name).symlink_to(p)
        replay(str(folder), tmp_path / f"run_{name}", load_config())
        runs.append(tmp_path / f"run_{name}")
    summary = merge_runs(runs, tmp_path / "merged", load_config(), use_georeference=False)
    mov = summary["runs"][1]
    assert mov["placed"], mov.get("reason")
    assert abs(mov["angle_deg"]) < 10.0 and abs(mov["scale"] - 1.0) < 0.08  # first stills 9 deg apart (gimbal yaw)
    last = mov["levels"][-1]
    assert last["scale"] == 1.0 and last["inliers"] >= 5 and last["rms_px"] < 2.0
