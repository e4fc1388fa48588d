"""Pair benchmark: iFMI, ORB and SIFT on real and simulated pairs, and the photometric overlap check.

For every consecutive pair of the real stills (``seneca_nir``, ``brighton_beach`` in the shared
data folder), for shuffled pairs that do not overlap (by GPS), and for simulated pairs with exact
truth (low overlap, large rotation, tilt, exposure change, featureless sand, no overlap, a periodic
texture), it runs iFMI (``photomap.core.ifmi.Registrar`` with the shipped ``registration`` config
at its working size) and ORB and SIFT (``photomap.core.features.FeatureMatcher``), checks every
placement with :func:`photomap.core.features.verify_overlap`, and reports:

- per real set, a table per pair (GPS motion, truth, each method's error, confidence or inliers
  and check score, and what :func:`~photomap.core.features.decide` keeps);
- per simulated case, each method's success rate and errors;
- how well check variants (size, blur, tile search, gradient vs intensity NCC) separate right
  from wrong placements, and the thresholds chosen from that;
- the linking policies (iFMI alone, iFMI + check, iFMI + check + features) on all pairs;
- the resolution sweep for the features and ms per call (ratios to iFMI in the same run).

    python -m tools.bench_pairs [--quick] [--out docs/pairs.md]   (PHOTOMAP_DATA: the real sets, default ../shared/data)
        [--figures DIR]

Truth. Simulated pairs: the exact homography between the two rendered views. Real pairs: a
homography fitted (RANSAC, 2 px) to SIFT matches at full resolution, kept when the camera height
it implies with the GPS distance agrees with the others (within a factor 1.5 of their median;
brighton's logged height is 40 m); pairs without one do not overlap. ``--figures`` writes a
checkerboard overlay of every real truth to look at.

Error of a placement (a similarity, moving px -> reference px): the displacement from the truth
over a grid of moving-frame points that the truth maps inside the reference; the median is
reported, in pixels of the full-resolution frame and in % of its longer side. Right: median
<= 1.5 %; wrong: median >= 4 % or no overlap; in between: grey (not used to pick thresholds).
"""

from __future__ import annotations

import argparse
import csv
import datetime
import logging
import math
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from photomap.config import Config
from photomap.core import features as F
from photomap.core.features import (FeatureMatcher, OverlapCheck, features_confirmed, ifmi_confirmed,
                                    rescale_matrix, verify_overlap)
from photomap.core.ifmi import Registrar
from photomap.sim.flight import (Camera, Effects, apply_effects, build_pyramid, pose_homography, relative_matrix,
                                 render_view, simulate_sequence)
from photomap.sim.terrain import TERRAIN_GSD, load_terrain, valid_mask
from tools.report import replace_section

log = logging.getLogger("bench_pairs")

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("PHOTOMAP_DATA") or REPO.parent / "shared" / "data")
SEED = 11
RIGHT, WRONG = 0.015, 0.04  # median displacement / longer side
FEATURE_SIZE = 640  # chosen working size of the features (see the resolution sweep)
SWEEP_SIZES = (320, 480, 640, 0)  # 0 = full resolution
SENSOR_WIDTH_MM = {"seneca_nir": 6.16, "brighton_beach": 6.17}  # 1/2.3" sensors
FAR_M = {"seneca_nir": 130.0, "brighton_beach": 80.0}  # GPS distance beyond which frames cannot overlap


# --------------------------------------------------------------------------- geometry

def h3(m: np.ndarray) -> np.ndarray:
    m = np.asarray(m, np.float64)
    return m if m.shape[0] == 3 else np.vstack([m, [0.0, 0.0, 1.0]])


def displacement(m: np.ndarray, truth: np.ndarray | None, shape: tuple[int, int]) -> float:
    """Median distance (px) between ``m`` and ``truth`` over moving points inside the reference.

    ``inf`` when there is no truth (no overlap): any placement is wrong.
    """
    if truth is None:
        return math.inf
    h, w = shape
    step = max(4, int(max(h, w) / 60))
    ys, xs = np.mgrid[0:h:step, 0:w:step]
    p = np.c_[xs.ravel(), ys.ravel(), np.ones(xs.size)]
    q = p @ h3(truth).T
    q = q[:, :2] / q[:, 2:3]
    inside = (q[:, 0] >= 0) & (q[:, 0] <= w - 1) & (q[:, 1] >= 0) & (q[:, 1] <= h - 1)
    if inside.sum() < 4:
        return math.inf
    e = p[inside] @ h3(m)[:2].T
    return float(np.median(np.linalg.norm(e - q[inside], axis=1)))


def overlap_fraction(truth: np.ndarray | None, shape: tuple[int, int]) -> float:
    if truth is None:
        return 0.0
    h, w = shape
    mask = cv2.warpPerspective(np.ones((h, w), np.uint8), h3(truth), (w, h), flags=cv2.INTER_NEAREST)
    return float(mask.mean())


def label(err: float, shape: tuple[int, int]) -> str:
    rel = err / max(shape)
    return "right" if rel <= RIGHT else ("wrong" if rel >= WRONG else "grey")


def small(img: np.ndarray, size: int) -> tuple[np.ndarray, float]:
    """``img`` resized (INTER_AREA) to a longer side of ``size`` (the pipeline's rounding) and the factor."""
    h, w = img.shape[:2]
    f = min(1.0, size / max(h, w)) if size > 0 else 1.0
    dsize = (max(16, int(round(w * f))), max(16, int(round(h * f))))
    if dsize == (w, h):
        return img, 1.0
    return cv2.resize(img, dsize, interpolation=cv2.INTER_AREA), dsize[0] / w


def similarity_of(hom: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Least-squares similarity fitted to a homography over the frame (a placement to perturb)."""
    h, w = shape
    ys, xs = np.mgrid[0:h:16, 0:w:16]
    p = np.c_[xs.ravel(), ys.ravel()].astype(np.float32)
    q = cv2.perspectiveTransform(p[None], h3(hom))[0]
    m, _ = cv2.estimateAffinePartial2D(p, q, method=cv2.LMEDS)
    return m.astype(np.float64)


# --------------------------------------------------------------------------- pairs

@dataclass
class Pair:
    group: str  # "seneca_nir", "brighton_beach", "sim: nominal", ...
    name: str
    ref: np.ndarray  # full-resolution grey uint8
    mov: np.ndarray
    truth: np.ndarray | None  # 3x3 moving px -> reference px; None: no overlap
    kind: str  # consecutive | shuffled | sim
    info: dict = field(default_factory=dict)
    extra: list = field(default_factory=list)  # (source, 2x3 matrix) placements to check only
    shape: tuple[int, int] = (0, 0)  # (h, w) of the full-resolution frames

    def __post_init__(self) -> None:
        self.shape = (int(self.ref.shape[0]), int(self.ref.shape[1]))


def gps_m(a: dict, b: dict) -> float:
    lat = math.radians(float(a["lat"]))
    north = (float(b["lat"]) - float(a["lat"])) * 111_320.0
    east = (float(b["lon"]) - float(a["lon"])) * 111_320.0 * math.cos(lat)
    return math.hypot(north, east)


def reference_homography(sift: cv2.SIFT, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray | None, int]:
    """Homography b -> a from full-resolution SIFT (ratio 0.75, RANSAC 2 px) and its inlier count."""
    ka, da = sift.detectAndCompute(a, None)
    kb, db = sift.detectAndCompute(b, None)
    if da is None or db is None or len(ka) < 8 or len(kb) < 8:
        return None, 0
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(db, da, k=2)
    good = [p[0] for p in knn if len(p) == 2 and p[0].distance < 0.75 * p[1].distance]
    if len(good) < 8:
        return None, 0
    src = np.float32([kb[g.queryIdx].pt for g in good])
    dst = np.float32([ka[g.trainIdx].pt for g in good])
    hom, mask = cv2.findHomography(src, dst, cv2.RANSAC, 2.0, maxIters=10000, confidence=0.9999)
    if hom is None:
        return None, 0
    return hom / hom[2, 2], int(mask.sum())


def real_pairs(name: str, rng: np.random.Generator, shuffled: int) -> tuple[list[Pair], dict]:
    folder = DATA / name
    files = sorted((folder / "images").glob("*.jpg"))
    with open(folder / "poses.csv", newline="") as f:
        poses = list(csv.DictReader(f))
    grays = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in files]
    h, w = grays[0].shape
    focal_px = float(poses[0]["focal_mm"]) / SENSOR_WIDTH_MM[name] * w
    stems = [p.stem.split("_")[-1] for p in files]
    sift = cv2.SIFT_create(nfeatures=8000)
    pairs, heights = [], []
    centre = np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
    for k in range(1, len(grays)):
        hom, inliers = reference_homography(sift, grays[k - 1], grays[k])
        dist = gps_m(poses[k - 1], poses[k])
        info = {"gps_m": dist, "ref_inliers": inliers}
        if hom is not None and inliers >= 12:
            c = hom @ centre
            shift = float(np.hypot(*(c[:2] / c[2] - centre[:2])))
            info["shift_px"] = shift
            info["height_m"] = focal_px * dist / max(shift, 1e-6)
            heights.append(info["height_m"])
        else:
            hom = None
        pairs.append(Pair(name, f"{stems[k - 1]}-{stems[k]}", grays[k - 1], grays[k], hom, "consecutive", info))
    logged = [float(p["rel_alt"]) for p in poses if p.get("rel_alt")]
    median_h = statistics.median(heights) if heights else float("nan")
    height = statistics.median(logged) if logged else median_h
    for p in pairs:
        p.info["expected_px"] = p.info["gps_m"] * focal_px / height
        hm = p.info.get("height_m")
        if p.truth is not None and not (median_h / 1.5 <= hm <= median_h * 1.5):
            log.warning("%s %s: reference implies %.0f m (median %.0f m): not used as truth", name, p.name,
                        hm, median_h)
            p.truth = None
    far = [(i, j) for i in range(len(grays)) for j in range(len(grays))
           if abs(i - j) >= 2 and gps_m(poses[i], poses[j]) > FAR_M[name]]
    for n in rng.permutation(len(far))[:shuffled]:
        i, j = far[n]
        pairs.append(Pair(name, f"{stems[i]}-{stems[j]}", grays[i], grays[j], None, "shuffled",
                          {"gps_m": gps_m(poses[i], poses[j])}))
    meta = {"focal_px": focal_px, "height_m": height, "implied_height_m": median_h, "frames": len(grays),
            "size": (w, h)}
    return pairs, meta


@dataclass(frozen=True)
class SimCase:
    name: str
    terrain: str
    shift: tuple[float, float]  # centre displacement, fraction of the frame height
    angle: tuple[float, float]  # |relative rotation| range, deg
    scale: tuple[float, float]  # relative altitude range
    tilt: float = 0.0  # roll/pitch of the second view up to this, deg
    gain: float = 1.0  # brightness gain of the second view
    description: str = ""


SIM_SHAPE = (480, 640)
SIM_CASES = [
    SimCase("nominal", "aukerman", (0.25, 0.35), (0, 15), (0.9, 1.1),
            description="aukerman, ~60 % overlap, up to 15 deg and 10 % scale"),
    SimCase("low overlap", "aukerman", (0.65, 0.8), (0, 15), (0.9, 1.1),
            description="aukerman, 15-30 % overlap"),
    SimCase("large rotation", "aukerman", (0.25, 0.35), (60, 180), (0.85, 1.18),
            description="aukerman, 60-180 deg, up to 18 % scale"),
    SimCase("tilt 8 deg", "aukerman", (0.25, 0.35), (5, 20), (0.85, 1.18), tilt=8.0,
            description="aukerman, second view rolled/pitched up to 8 deg (like the fixed-wing seneca), "
                        "5-20 deg, up to 18 % scale"),
    SimCase("exposure", "aukerman", (0.25, 0.35), (0, 15), (0.9, 1.1), gain=0.7,
            description="aukerman, second view 30 % darker"),
    SimCase("grass", "grass", (0.25, 0.35), (0, 15), (0.9, 1.1),
            description="procedural grass (fine, low contrast)"),
    SimCase("sand", "sand", (0.25, 0.35), (0, 15), (0.9, 1.1),
            description="procedural sand (smooth, 25 % contrast, featureless), noise 1"),
    SimCase("no overlap", "aukerman", (2.2, 3.0), (0, 180), (0.9, 1.1),
            description="aukerman, footprints disjoint (every placement is wrong)"),
]


class Terrains:
    def __init__(self) -> None:
        self._items: dict[str, tuple[list[np.ndarray], np.ndarray | None]] = {}

    def get(self, name: str) -> tuple[list[np.ndarray], np.ndarray | None]:
        if name not in self._items:
            if name == "aukerman":
                t = load_terrain("aukerman", zoom=4.0)
                self._items[name] = (build_pyramid(t, 3.0), valid_mask(t))
            elif name.startswith("periodic"):
                base = cv2.cvtColor(load_terrain("aukerman", zoom=4.0), cv2.COLOR_BGR2GRAY).astype(np.float32)
                amp = float(name.split(":")[1])
                yy, xx = np.mgrid[0:base.shape[0], 0:base.shape[1]]
                rows = 127.0 + 100.0 * np.sin(2 * np.pi * xx / PERIOD_TERRAIN_PX)
                t = np.clip((1 - amp) * base + amp * rows, 0, 255).astype(np.uint8)
                aux = load_terrain("aukerman", zoom=4.0)
                self._items[name] = (build_pyramid(cv2.cvtColor(t, cv2.COLOR_GRAY2BGR), 3.0), valid_mask(aux))
            else:
                t = load_terrain(name, seed=3)
                self._items[name] = (build_pyramid(t, 3.0), None)
        return self._items[name]


PERIOD_TERRAIN_PX = 40.0  # crop rows along y, period in terrain pixels (~33 frame px at 640)
PERIODIC_WEIGHTS = (0.15, 0.3, 0.5)


def render(terrains: Terrains, terrain: str, rng: np.random.Generator, shift_px: float, angle: float,
           scale: float, tilt: float = 0.0, gain: float = 1.0, yaw: float | None = None,
           base: float = 1.2, direction: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two grey 640x480 views and the exact homography b -> a; also ``ha`` (frame a -> terrain)."""
    pyramid, valid = terrains.get(terrain)
    th, tw = pyramid[0].shape[:2]
    cam = Camera.from_hfov(SIM_SHAPE[1], SIM_SHAPE[0], 60.0)
    yaw = rng.uniform(-math.pi, math.pi) if yaw is None else yaw
    direction = rng.uniform(-math.pi, math.pi) if direction is None else direction
    d = shift_px * base
    dx, dy = d * math.cos(direction), d * math.sin(direction)
    # the midpoint of the two views, far enough inside the (valid) terrain for both footprints
    margin = d / 2 + 420 * base * max(1.0, scale)
    for _ in range(2000):
        mx, my = rng.uniform(margin, tw - margin), rng.uniform(margin, th - margin)
        if valid is None:
            break
        ys = np.clip(np.linspace(my - margin, my + margin, 16).astype(int), 0, th - 1)
        xs = np.clip(np.linspace(mx - margin, mx + margin, 16).astype(int), 0, tw - 1)
        if valid[np.ix_(ys, xs)].all():
            break
    alt = cam.fx * base
    ha = pose_homography(cam, mx - dx / 2, my - dy / 2, alt, 0.0, 0.0, yaw)
    roll, pitch = rng.uniform(-1, 1, 2) * math.radians(tilt)
    hb = pose_homography(cam, mx + dx / 2, my + dy / 2, alt * scale, roll, pitch, yaw + math.radians(angle))
    eff = Effects(noise=1.0)
    seed = int(rng.integers(1 << 30))
    a = apply_effects(render_view(pyramid, ha, SIM_SHAPE), eff, np.random.default_rng([seed, 1]))
    b = apply_effects(render_view(pyramid, hb, SIM_SHAPE), eff, np.random.default_rng([seed, 2]), gain=gain)
    t = np.linalg.solve(ha, hb)
    return (cv2.cvtColor(a, cv2.COLOR_BGR2GRAY), cv2.cvtColor(b, cv2.COLOR_BGR2GRAY), t / t[2, 2], ha)


def sim_pairs(terrains: Terrains, n: int, rng: np.random.Generator) -> list[Pair]:
    pairs = []
    for case in SIM_CASES:
        for k in range(n):
            shift = rng.uniform(*case.shift) * SIM_SHAPE[0]
            angle = rng.uniform(*case.angle) * rng.choice([-1, 1])
            scale = math.exp(rng.uniform(math.log(case.scale[0]), math.log(case.scale[1])))
            a, b, t, _ = render(terrains, case.terrain, rng, shift, angle, scale, case.tilt, case.gain)
            truth = None if case.name == "no overlap" else t
            pairs.append(Pair(f"sim: {case.name}", f"{case.name} #{k}", a, b, truth, "sim",
                              {"angle": angle, "scale": scale, "shift_px": shift}))
    return pairs


def periodic_pairs(terrains: Terrains, n: int, rng: np.random.Generator) -> list[Pair]:
    """Crop rows (a sinusoid across terrain x, period 40 terrain px) blended into aukerman with the
    weights of PERIODIC_WEIGHTS; the truth moved by one period across the rows is an extra (wrong)
    placement of each pair."""
    pairs = []
    for amp in PERIODIC_WEIGHTS:
        for k in range(n):
            shift = rng.uniform(0.25, 0.35) * SIM_SHAPE[0]
            a, b, t, ha = render(terrains, f"periodic:{amp}", rng, shift, rng.uniform(-10, 10),
                                 rng.uniform(0.95, 1.05))
            # one period across the rows (terrain x), expressed in a's pixels
            step = np.eye(3)
            step[0, 2] = PERIOD_TERRAIN_PX
            wrong = np.linalg.solve(ha, step @ ha @ t)
            wrong = similarity_of(wrong / wrong[2, 2], SIM_SHAPE)
            pairs.append(Pair(f"sim: periodic {amp:.2f}", f"periodic {amp:.2f} #{k}", a, b, t, "sim",
                              {"period_px": PERIOD_TERRAIN_PX / 1.2}, [("one period off", wrong)]))
    return pairs


def shuffled_video_pairs(n: int, rng: np.random.Generator) -> list[Pair]:
    """Frame pairs 4..30 frames apart of a simulated 640x480 aukerman video (1 fps, 8 m/s at 50-70 m,
    random yaw): mostly no overlap, some a sliver (which counts as overlap: a placement there is
    judged against the truth); the truth is the simulator's."""
    terrain = load_terrain("aukerman", zoom=4.0)
    seq = simulate_sequence(terrain, 60, SIM_SHAPE, SEED, valid=valid_mask(terrain), fps=1.0,
                            gsd=TERRAIN_GSD["aukerman"] / 4.0, pattern="random", speed=8.0, yaw_mode="random",
                            yaw_rate=15.0, altitude=(50.0, 70.0), noise=1.0)
    grays = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in seq.frames]
    pairs = []
    for _ in range(n):
        i = int(rng.integers(0, len(grays) - 31))
        j = i + int(rng.integers(4, 31))
        t = relative_matrix(seq.truth, i, j)
        truth = t if overlap_fraction(t, SIM_SHAPE) > 0 else None  # a sliver of overlap is overlap
        pairs.append(Pair("sim: shuffled video", f"frames {i}-{j}", grays[i], grays[j], truth, "sim", {}))
    return pairs


# --------------------------------------------------------------------------- methods

@dataclass
class Result:
    method: str
    matrix: np.ndarray | None  # full-resolution px, moving -> reference
    confidence: float  # iFMI confidence or feature score
    inliers: int
    ms: float
    err: float = math.inf
    check: OverlapCheck | None = None
    check_ms: float = math.nan
    cpu_ms: float = math.nan  # process CPU time (all threads) of the same call
    check_cpu_ms: float = math.nan


class Methods:
    """iFMI at the pipeline's working size and features at ``feature_size``, frames prepared once."""

    def __init__(self, feature_size: int = FEATURE_SIZE) -> None:
        self.cfg = Config().registration
        self.working = self.cfg.working_size
        self.registrars: dict[tuple[int, int], Registrar] = {}
        self.features = {k: FeatureMatcher(k, working_size=feature_size) for k in ("orb", "sift")}

    def registrar(self, shape: tuple[int, int]) -> Registrar:
        if shape not in self.registrars:
            self.registrars[shape] = Registrar(shape, self.cfg)
        return self.registrars[shape]

    def run(self, pair: Pair) -> tuple[dict[str, Result], np.ndarray, np.ndarray, float]:
        a, f = small(pair.ref, self.working)
        b, _ = small(pair.mov, self.working)
        reg = self.registrar(a.shape)
        out = {}
        pa = reg.prepare(a)
        t0, c0 = time.perf_counter(), time.process_time()
        pb = reg.prepare(b)
        r = reg.register(pa, pb)
        ms, cpu = 1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)
        out["ifmi"] = Result("ifmi", rescale_matrix(r.matrix, 1.0 / f), r.confidence, 0, ms, cpu_ms=cpu)
        for kind, fm in self.features.items():
            fa = fm.prepare(pair.ref)
            t0, c0 = time.perf_counter(), time.process_time()
            fb = fm.prepare(pair.mov)
            fr = fm.register(fa, fb)
            ms, cpu = 1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)
            out[kind] = Result(kind, fr.matrix, fr.score, fr.inliers, ms, cpu_ms=cpu)
        return out, a, b, f


# --------------------------------------------------------------------------- evaluation

@dataclass
class Evaluated:
    pair: Pair
    results: dict[str, Result]
    small_ref: np.ndarray
    small_mov: np.ndarray
    factor: float
    placements: list[tuple[str, np.ndarray, float]]  # (source, full-res matrix, error) to calibrate the check


def evaluate(pairs: list[Pair], methods: Methods) -> list[Evaluated]:
    out = []
    for i, pair in enumerate(pairs):
        results, a, b, f = methods.run(pair)
        placements = []
        for res in results.values():
            if res.matrix is not None:
                res.err = displacement(res.matrix, pair.truth, pair.shape)
                t0, c0 = time.perf_counter(), time.process_time()
                res.check = verify_overlap(a, b, rescale_matrix(res.matrix, f))
                res.check_ms = 1e3 * (time.perf_counter() - t0)
                res.check_cpu_ms = 1e3 * (time.process_time() - c0)
                placements.append((res.method, res.matrix, res.err))
        if pair.truth is not None:
            sim = similarity_of(pair.truth, pair.shape)
            placements.append(("truth", sim, displacement(sim, pair.truth, pair.shape)))
            for ang in (0, 90, 180, 270):  # 30 px off (full resolution) in 4 directions
                moved = sim.copy()
                moved[:, 2] += 30.0 * np.array([math.cos(math.radians(ang)), math.sin(math.radians(ang))])
                placements.append(("truth + 30 px", moved, displacement(moved, pair.truth, pair.shape)))
        for source, m in pair.extra:
            placements.append((source, m, max(displacement(m, pair.truth, pair.shape), WRONG * max(pair.shape) + 1)))
        out.append(Evaluated(pair, results, a, b, f, placements))
        if (i + 1) % 20 == 0:
            log.info("  %d/%d pairs", i + 1, len(pairs))
    return out


def checks_for(ev: Evaluated, **params) -> list[tuple[str, str, OverlapCheck]]:
    """(source, label, check) of every placement of a pair with the given check parameters."""
    rows = []
    for source, m, err in ev.placements:
        chk = verify_overlap(ev.small_ref, ev.small_mov, rescale_matrix(m, ev.factor), **params)
        rows.append((source, label(err, ev.pair.shape), chk))
    return rows


def separation(values_right: np.ndarray, values_wrong: np.ndarray) -> tuple[float, int, int]:
    """Threshold minimising (right rejected + wrong accepted), preferring no wrong accepted."""
    r = np.nan_to_num(values_right, nan=-1.0)
    w = np.nan_to_num(values_wrong, nan=-1.0)
    best = None
    for t in np.unique(np.r_[r, w, 1.01]):
        cost = (int((r < t).sum()) + 3 * int((w >= t).sum()), float(t))
        if best is None or cost < best[0]:
            best = (cost, t)
    t = best[1]
    # centre the threshold in the gap below it
    below = np.r_[w[w < t], r[r < t]]
    lo = float(below.max()) if below.size else t
    t = (lo + t) / 2 if lo < t else t
    return t, int((r < t).sum()), int((w >= t).sum())


# --------------------------------------------------------------------------- report helpers

def fmt(v: float, d: int = 2) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.{d}f}"


def err_cell(res: Result, shape: tuple[int, int]) -> str:
    if res.matrix is None:
        return "none"
    if not np.isfinite(res.err):
        return "**wrong**"
    rel = res.err / max(shape)
    txt = f"{res.err:.0f}" if res.err >= 10 else f"{res.err:.1f}"
    return txt if rel <= RIGHT else (f"**{txt}**" if rel >= WRONG else f"({txt})")


def machine_info() -> list[str]:
    return [f"- {platform.platform()}, Python {platform.python_version()}, OpenCV {cv2.__version__}, "
            f"numpy {np.__version__}, {os.cpu_count()} cores (shared with other jobs: timings are medians, "
            f"compare the ratios), {datetime.date.today().isoformat()}"]


# --------------------------------------------------------------------------- feature working size

def sweep(pairs: list[Pair], sizes=SWEEP_SIZES) -> dict[tuple[str, int], dict]:
    """ORB and SIFT at several working sizes: outcomes on real overlapping pairs and simulated
    pairs, wrong results on pairs without overlap, ms per pair (prepare + register)."""
    out = {}
    for kind in ("orb", "sift"):
        for size in sizes:
            fm = FeatureMatcher(kind, working_size=size)
            stats = {"real": [], "sim": [], "none_wrong": 0, "ms": [], "prep_ms": []}
            for pair in pairs:
                fa = fm.prepare(pair.ref)
                t0 = time.perf_counter()
                fb = fm.prepare(pair.mov)
                t1 = time.perf_counter()
                r = fm.register(fa, fb)
                t2 = time.perf_counter()
                stats["ms"].append(1e3 * (t2 - t0))
                stats["prep_ms"].append(1e3 * (t1 - t0))
                if pair.truth is None:
                    stats["none_wrong"] += int(r.ok and r.inliers >= F.MIN_INLIERS)
                    continue
                if not r.ok or r.inliers < F.MIN_INLIERS:
                    outcome, err = "none", math.inf
                else:
                    err = displacement(r.matrix, pair.truth, pair.shape)
                    outcome = label(err, pair.shape)
                stats["real" if pair.kind != "sim" else "sim"].append((outcome, err))
            out[(kind, size)] = stats
            log.info("  sweep %s %s: done", kind, size or "full")
    return out


def sweep_table(res: dict, real_sizes: dict[str, tuple[int, int]]) -> list[str]:
    lines = ["| method | working size | real overlapping pairs: right / grey / wrong / none | "
             "simulated pairs: right / wrong / none | median sim error (px at 640x480) | "
             "wrong results on pairs without overlap | ms per pair (median) | of which detection |",
             "|---|---|---|---|---:|---:|---:|---:|"]
    for (kind, size), st in res.items():
        rc = {k: sum(1 for o, _ in st["real"] if o == k) for k in ("right", "grey", "wrong", "none")}
        sc = {k: sum(1 for o, _ in st["sim"] if o == k) for k in ("right", "grey", "wrong", "none")}
        errs = [e for o, e in st["sim"] if np.isfinite(e)]
        lines.append(f"| {kind.upper()} | {size or 'full (900/1000)'} | {rc['right']} / {rc['grey']} / "
                     f"{rc['wrong']} / {rc['none']} | {sc['right'] + sc['grey']} / {sc['wrong']} / {sc['none']} | "
                     f"{fmt(float(np.median(errs)) if errs else math.nan)} | {st['none_wrong']} | "
                     f"{np.median(st['ms']):.1f} | {np.median(st['prep_ms']):.1f} |")
    return lines


MATCHER_VARIANTS = [
    ("sift", {}), ("sift", {"contrast_threshold": 0.04}), ("sift", {"max_features": 1000}),
    ("sift", {"max_features": 4000}), ("sift", {"ratio": 0.75}), ("sift", {"ratio": 0.9}),
    ("orb", {}), ("orb", {"fast_threshold": 20}), ("orb", {"max_features": 1000}),
    ("orb", {"max_features": 4000}), ("orb", {"ratio": 0.75}), ("orb", {"ratio": 0.9}),
]


def settings_table(pairs: list[Pair]) -> list[str]:
    """FeatureMatcher settings around the defaults, at the chosen working size, on the overlapping
    real and simulated pairs."""
    lines = ["| matcher | real: right / grey / wrong / none | simulated right | fewest inliers of a real "
             "result | ms per pair (both frames detected) |", "|---|---|---:|---:|---:|"]
    sel = [p for p in pairs if p.truth is not None and "periodic" not in p.group]
    for kind, kw in MATCHER_VARIANTS:
        fm = FeatureMatcher(kind, working_size=FEATURE_SIZE, **kw)
        real, sim, ms = [], [], []
        for p in sel:
            t0 = time.perf_counter()
            r = fm.register(p.ref, p.mov)
            ms.append(1e3 * (time.perf_counter() - t0))
            if not r.ok or r.inliers < F.MIN_INLIERS:
                o = ("none", 0)
            else:
                o = (label(displacement(r.matrix, p.truth, p.shape), p.shape), r.inliers)
            (real if p.kind != "sim" else sim).append(o)
        cnt = lambda rows, k: sum(1 for o, _ in rows if o == k)
        name = kind.upper() + (" default" if not kw else ", " + ", ".join(f"{k} {v}" for k, v in kw.items()))
        inl = [n for o, n in real if o != "none"]
        lines.append(f"| {name} | {cnt(real, 'right')} / {cnt(real, 'grey')} / {cnt(real, 'wrong')} / "
                     f"{cnt(real, 'none')} | {cnt(sim, 'right')} of {len(sim)} | {min(inl) if inl else '-'} | "
                     f"{np.median(ms):.0f} |")
    return lines


# --------------------------------------------------------------------------- policies

def ifmi_only(ev: Evaluated, min_confidence: float) -> tuple[str, np.ndarray | None]:
    r = ev.results["ifmi"]
    return ("ifmi", r.matrix) if r.confidence >= min_confidence else ("none", None)


def combined(ev: Evaluated, feature: str | None, **thresholds) -> tuple[str, np.ndarray | None]:
    """iFMI first; when its placement is not confirmed, ``feature`` (or nothing) decides."""
    r = ev.results["ifmi"]
    fake = _registration(r)
    keys = ("min_confidence", "min_score", "max_ratio", "min_overlap")
    if ifmi_confirmed(fake, r.check, **{k: v for k, v in thresholds.items() if k in keys}):
        return "ifmi", r.matrix
    if feature is None:
        return "none", None
    f = ev.results[feature]
    if features_confirmed(_feature_registration(f), f.check,
                          **{k: v for k, v in thresholds.items() if k != "min_confidence"}):
        return feature, f.matrix
    return "none", None


def features_alone(ev: Evaluated, feature: str, **thresholds) -> tuple[str, np.ndarray | None]:
    f = ev.results[feature]
    if features_confirmed(_feature_registration(f), f.check, **thresholds):
        return feature, f.matrix
    return "none", None


def _registration(r: Result):
    from photomap.core.ifmi import Registration
    return Registration(matrix=r.matrix, confidence=r.confidence)


def _feature_registration(r: Result):
    return F.FeatureRegistration(r.method, r.matrix, r.inliers, r.inliers, r.confidence)


def outcome(ev: Evaluated, method: str, matrix: np.ndarray | None) -> str:
    if matrix is None:
        return "rejected"
    return label(displacement(matrix, ev.pair.truth, ev.pair.shape), ev.pair.shape)


def policy_counts(evs: list[Evaluated], policy) -> dict[str, int]:
    c = {"right": 0, "grey": 0, "wrong": 0, "rejected": 0, "rejected_ok": 0, "overlapping": 0,
         "features_called": 0, "n": 0}
    for ev in evs:
        method, m = policy(ev)
        o = outcome(ev, method, m)
        c["n"] += 1
        if ev.pair.truth is not None:
            c["overlapping"] += 1
        if o == "rejected" and ev.pair.truth is None:
            c["rejected_ok"] += 1
        else:
            c[o] += 1
    return c


def policy_cost(evs: list[Evaluated], feature: str | None) -> tuple[float, float]:
    """Mean ms per pair of iFMI + its check (+ features and their check when called) and the
    fraction of pairs that call the features."""
    total, called = [], 0
    for ev in evs:
        r = ev.results["ifmi"]
        ms = r.ms + (r.check_ms if np.isfinite(r.check_ms) else 0.0)
        if feature is not None and not ifmi_confirmed(_registration(r), r.check):
            called += 1
            f = ev.results[feature]
            ms += f.ms + (f.check_ms if np.isfinite(f.check_ms) else 0.0)
        total.append(ms)
    return float(np.mean(total)), called / max(len(evs), 1)


POLICIES = [
    ("iFMI alone, confidence >= mapping.min_confidence", None),
    ("iFMI + overlap check", ("combined", None)),
    ("iFMI + check, else ORB + check", ("combined", "orb")),
    ("iFMI + check, else SIFT + check (chosen)", ("combined", "sift")),
    ("SIFT + check alone", ("alone", "sift")),
    ("ORB + check alone", ("alone", "orb")),
]


def make_policy(spec, min_confidence: float, **thresholds):
    if spec is None:
        return lambda ev: ifmi_only(ev, min_confidence)
    kind, feature = spec
    if kind == "combined":
        return lambda ev: combined(ev, feature, **thresholds)
    return lambda ev: features_alone(ev, feature, **{k: v for k, v in thresholds.items()
                                                       if k != "min_confidence"})


def policy_table(groups: dict[str, list[Evaluated]], min_confidence: float) -> list[str]:
    lines = ["| policy | set | overlapping pairs accepted right / grey | wrong accepted | overlapping "
             "rejected | non-overlapping rejected | features called | mean ms per pair |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for title, spec in POLICIES:
        pol = make_policy(spec, min_confidence)
        for name, evs in groups.items():
            c = policy_counts(evs, pol)
            feature = None if spec is None else spec[1]
            if spec is not None and spec[0] == "alone":
                cost = float(np.mean([ev.results[feature].ms + ev.results[feature].check_ms
                                      if ev.results[feature].matrix is not None else ev.results[feature].ms
                                      for ev in evs]))
                frac = 1.0
            elif spec is None:
                cost, frac = float(np.mean([ev.results["ifmi"].ms for ev in evs])), 0.0
            else:
                cost, frac = policy_cost(evs, feature)
            non = c["n"] - c["overlapping"]
            lines.append(f"| {title} | {name} | {c['right']} / {c['grey']} of {c['overlapping']} | "
                         f"{'**%d**' % c['wrong'] if c['wrong'] else 0} | {c['rejected']} | "
                         f"{c['rejected_ok']} of {non} | {100 * frac:.0f} % | {cost:.1f} |")
    return lines


def threshold_search(evs: list[Evaluated]) -> list[tuple]:
    """Grid over the decision thresholds for iFMI + check, else SIFT: zero wrong accepted first,
    then the most overlapping real pairs accepted, then the most right simulated ones."""
    grid = {"min_score": [0.1, 0.2, 0.3, 0.4], "max_ratio": [0.8, 0.9, 0.95, 1.0],
            "min_inliers": [8, 12, 20], "strong_inliers": [25, 40, 10 ** 6], "strong_min_score": [0.05, 0.1, 0.2]}
    keys = list(grid)
    real = [ev for ev in evs if ev.pair.kind != "sim"]
    sim = [ev for ev in evs if ev.pair.kind == "sim"]
    rows = []
    for vals in np.array(np.meshgrid(*grid.values(), indexing="ij")).reshape(len(keys), -1).T:
        th = {k: (int(v) if k in ("min_inliers", "strong_inliers") else float(v)) for k, v in zip(keys, vals)}
        pol = make_policy(("combined", "sift"), 0.0, **th)
        cr, cs = policy_counts(real, pol), policy_counts(sim, pol)
        rows.append((cr["wrong"] + cs["wrong"], -(cr["right"] + cr["grey"]), -cs["right"], th, cr, cs))
    rows.sort(key=lambda r: r[:3])
    return rows


# --------------------------------------------------------------------------- the check

def placement_class(ev: Evaluated, source: str) -> str:
    if source == "truth + 30 px":
        return "moved 30 px"
    if source == "one period off":
        return "one period off"
    if source == "truth":
        return "truth"
    if ev.pair.kind == "shuffled" or ev.pair.truth is None:
        return "method, no overlap"
    return "method"


def check_rows(evs: list[Evaluated], **params) -> list[tuple[str, str, str, OverlapCheck]]:
    """(group, class, label, check) for every placement."""
    rows = []
    for ev in evs:
        for (source, lab, chk), (src, _, _) in zip(checks_for(ev, **params), ev.placements):
            rows.append((ev.pair.group, placement_class(ev, src), lab, chk))
    return rows


def accepted(chk: OverlapCheck) -> bool:
    return chk.passes(F.MIN_SCORE, F.MAX_RATIO, F.MIN_OVERLAP)


def metric_comparison(evs: list[Evaluated], base: list) -> list[str]:
    """Right/wrong separation of simple NCC thresholds against the peak test, and check variants."""
    lines = ["| check | threshold | right placements accepted | wrong accepted: method outputs / moved 30 px / "
             "one period off / no overlap | ms per check |", "|---|---|---:|---:|---:|"]

    def summary(rows, ok, name, thr, ms):
        right = [ok(c) for _, _, lab, c in rows if lab == "right"]
        wrong = {k: sum(1 for _, cls, lab, c in rows if lab == "wrong" and cls.startswith(k) and ok(c))
                 for k in ("method", "moved", "one period", "method, no overlap")}
        wrong["method"] -= wrong["method, no overlap"]
        total = {k: sum(1 for _, cls, lab, c in rows if lab == "wrong" and cls.startswith(k))
                 for k in ("method", "moved", "one period", "method, no overlap")}
        total["method"] -= total["method, no overlap"]
        cells = " / ".join(f"{wrong[k]} of {total[k]}" for k in ("method", "moved", "one period",
                                                                  "method, no overlap"))
        lines.append(f"| {name} | {thr} | {100 * np.mean(right):.0f} % of {len(right)} | {cells} | {ms} |")

    for attr, name in (("ncc", "intensity NCC at the placement"), ("gradient_ncc", "gradient NCC at the placement")):
        vals_r = np.array([getattr(c, attr) for _, _, lab, c in base if lab == "right"])
        vals_w = np.array([getattr(c, attr) for _, _, lab, c in base if lab == "wrong"])
        t, _, _ = separation(vals_r, vals_w)
        summary(base, lambda c, a=attr, t=t: np.isfinite(getattr(c, a)) and getattr(c, a) >= t, name,
                f">= {t:.2f} (best)", "")
    summary(base, accepted, "**own peak + rival ratio (chosen: 160 px, blur 1, tolerance 2 %)**",
            f"score >= {F.MIN_SCORE}, ratio <= {F.MAX_RATIO}", "")
    for params in (dict(size=80), dict(size=320), dict(blur=0.7), dict(blur=1.5), dict(tolerance=0.01),
                   dict(tolerance=0.03)):
        t0 = time.perf_counter()
        rows = check_rows(evs, **params)
        ms = 1e3 * (time.perf_counter() - t0) / max(len(rows), 1)
        summary(rows, accepted, "own peak + rival ratio, " + ", ".join(f"{k} {v}" for k, v in params.items()),
                "same", f"{ms:.1f}")
    return lines


def class_table(base: list) -> list[str]:
    lines = ["| placements | label | n | accepted | score: 5 % / median / 95 % | ratio: 5 % / median / 95 % |",
             "|---|---|---:|---:|---|---|"]
    keys = sorted({(g.split(":")[0] if g.startswith("sim") else g, cls, lab) for g, cls, lab, _ in base})
    for grp, cls, lab in keys:
        cs = [c for g, k, l, c in base if (g.split(":")[0] if g.startswith("sim") else g) == grp and k == cls
              and l == lab]
        sc = np.array([c.score for c in cs], float)
        ra = np.array([c.ratio for c in cs], float)
        sc, ra = sc[np.isfinite(sc)], ra[np.isfinite(ra)]
        q = lambda v: " / ".join(f"{x:.2f}" for x in np.percentile(v, [5, 50, 95])) if v.size else "-"
        lines.append(f"| {grp}: {cls} | {lab} | {len(cs)} | {sum(accepted(c) for c in cs)} | {q(sc)} | {q(ra)} |")
    return lines


def periodic_table(evs: list[Evaluated]) -> list[str]:
    lines = ["| crop-row weight | right placement (truth): score / ratio / accepted | one period off: score / "
             "ratio / rejected | methods' placements accepted (right) |", "|---|---|---|---|"]
    for amp in PERIODIC_WEIGHTS:
        sel = [ev for ev in evs if ev.pair.group == f"sim: periodic {amp:.2f}"]
        if not sel:
            continue
        right, off, meth = [], [], []
        for ev in sel:
            for (source, lab, chk), (src, m, err) in zip(checks_for(ev), ev.placements):
                if src == "truth":
                    right.append(chk)
                elif src == "one period off":
                    off.append(chk)
                elif src in ("ifmi", "orb", "sift"):
                    meth.append(accepted(chk) and lab == "right")
        med = lambda cs, a: float(np.median([getattr(c, a) for c in cs]))
        lines.append(f"| {amp:.2f} | {med(right, 'score'):.2f} / {med(right, 'ratio'):.2f} / "
                     f"{sum(accepted(c) for c in right)} of {len(right)} | {med(off, 'score'):.2f} / "
                     f"{med(off, 'ratio'):.2f} / {sum(not accepted(c) for c in off)} of {len(off)} | "
                     f"{sum(meth)} of {len(meth)} |")
    return lines


def shift_table(evs: list[Evaluated], shifts=(5, 10, 15, 20, 30, 45)) -> list[str]:
    """Fraction of right placements moved by N px (full resolution) that the check rejects."""
    lines = ["| set | frame | " + " | ".join(f"moved {s} px" for s in shifts) + " |",
             "|---|---|" + "---:|" * len(shifts)]
    groups: dict[str, list[Evaluated]] = {}
    for ev in evs:
        if ev.pair.truth is not None and "periodic" not in ev.pair.group and ev.pair.kind != "shuffled":
            groups.setdefault(ev.pair.group if ev.pair.kind != "sim" else "simulated (all cases)", []).append(ev)
    for name, sel in groups.items():
        cells = []
        for sh in shifts:
            rej = n = 0
            for ev in sel:
                base = similarity_of(ev.pair.truth, ev.pair.shape)
                if not accepted(verify_overlap(ev.small_ref, ev.small_mov, rescale_matrix(base, ev.factor))):
                    continue  # only placements whose right version passes
                for ang in (0, 90, 180, 270):
                    m = base.copy()
                    m[:, 2] += sh * np.array([math.cos(math.radians(ang)), math.sin(math.radians(ang))])
                    n += 1
                    rej += not accepted(verify_overlap(ev.small_ref, ev.small_mov, rescale_matrix(m, ev.factor)))
            cells.append(f"{100 * rej / max(n, 1):.0f} %")
        h, w = sel[0].pair.shape
        lines.append(f"| {name} | {w}x{h} | " + " | ".join(cells) + " |")
    return lines


# --------------------------------------------------------------------------- per-pair tables

def real_table(evs: list[Evaluated]) -> list[str]:
    lines = ["| pair | GPS m | GPS px | truth shift px / overlap | iFMI conf / err / check | ORB inl / err / check | "
             "SIFT inl / err / check | decision (iFMI, else SIFT) |",
             "|---|---:|---:|---|---|---|---|---|"]
    for ev in evs:
        p = ev.pair
        if p.kind != "consecutive":
            continue
        truth = (f"{p.info['shift_px']:.0f} / {100 * overlap_fraction(p.truth, p.shape):.0f} %"
                 if p.truth is not None else "no overlap")
        cells = []
        for k in ("ifmi", "orb", "sift"):
            r = ev.results[k]
            head = f"{r.confidence:.2f}" if k == "ifmi" else (str(r.inliers) if r.matrix is not None else "-")
            chk = f"{r.check.score:.2f}/{r.check.ratio:.2f}" if r.check is not None else "-"
            ok = (ifmi_confirmed(_registration(r), r.check) if k == "ifmi" and r.check is not None
                  else features_confirmed(_feature_registration(r), r.check))
            cells.append(f"{head} / {err_cell(r, p.shape)} / {chk}{' ✓' if ok else ''}")
        method, m = combined(ev, "sift")
        o = outcome(ev, method, m)
        dec = "rejected" if m is None else f"{method}: {o}"
        if m is None and p.truth is None:
            dec = "rejected (right)"
        lines.append(f"| {p.name} | {p.info['gps_m']:.0f} | {p.info['expected_px']:.0f} | {truth} | "
                     + " | ".join(cells) + f" | {dec} |")
    return lines


def sim_table(evs: list[Evaluated]) -> list[str]:
    lines = ["| case | method | right (err <= 1.5 %) | within 1 px | wrong | none | median err px | "
             "median rot err deg | placements confirmed by the check: right / wrong |",
             "|---|---|---:|---:|---:|---:|---:|---:|---|"]
    groups: dict[str, list[Evaluated]] = {}
    for ev in evs:
        if ev.pair.kind == "sim":
            groups.setdefault(ev.pair.group.split(": ", 1)[1], []).append(ev)
    for name, sel in groups.items():
        for k in ("ifmi", "orb", "sift"):
            labs = [("none" if ev.results[k].matrix is None else label(ev.results[k].err, ev.pair.shape))
                    for ev in sel]
            errs = [ev.results[k].err for ev in sel if np.isfinite(ev.results[k].err)]
            rots = []
            for ev in sel:
                r = ev.results[k]
                if r.matrix is not None and ev.pair.truth is not None:
                    t = similarity_of(ev.pair.truth, ev.pair.shape)
                    d = math.degrees(math.atan2(r.matrix[1, 0], r.matrix[0, 0]) - math.atan2(t[1, 0], t[0, 0]))
                    rots.append(abs((d + 180) % 360 - 180))
            conf_ok = []
            for ev, lab in zip(sel, labs):
                r = ev.results[k]
                if r.check is None:
                    continue
                ok = (ifmi_confirmed(_registration(r), r.check) if k == "ifmi"
                      else features_confirmed(_feature_registration(r), r.check))
                if ok:
                    conf_ok.append(lab)
            n = len(sel)
            within = sum(1 for ev in sel if ev.results[k].err <= 1.0)
            lines.append(f"| {name} | {k} | {labs.count('right')} of {n} | {within} | {labs.count('wrong')} | "
                         f"{labs.count('none')} | {fmt(float(np.median(errs)) if errs else math.nan)} | "
                         f"{fmt(float(np.median(rots)) if rots else math.nan, 3)} | "
                         f"{conf_ok.count('right')} / {conf_ok.count('wrong')} |")
    return lines


def timing_table(evs: list[Evaluated]) -> list[str]:
    """Median wall and CPU ms per call over the pairs of this run, with ratios to iFMI."""
    def med(values) -> float:
        v = [x for x in values if np.isfinite(x)]
        return float(np.median(v)) if v else math.nan

    rows = [("iFMI (prepare the new frame + register), 320 px",
             med(ev.results["ifmi"].ms for ev in evs), med(ev.results["ifmi"].cpu_ms for ev in evs))]
    for k in ("orb", "sift"):
        rows.append((f"{k.upper()} (detect in the new frame + match + RANSAC), {FEATURE_SIZE} px",
                     med(ev.results[k].ms for ev in evs), med(ev.results[k].cpu_ms for ev in evs)))
    rows.append(("overlap check (`verify_overlap` on the 320 px frames, compared at 160 px)",
                 med(r.check_ms for ev in evs for r in ev.results.values()),
                 med(r.check_cpu_ms for ev in evs for r in ev.results.values())))
    wall0, cpu0 = rows[0][1], rows[0][2]
    lines = ["| call | wall ms | / iFMI | CPU ms (all threads) | / iFMI |", "|---|---:|---:|---:|---:|"]
    lines += [f"| {name} | {w:.1f} | {w / wall0:.2f} | {c:.1f} | {c / cpu0:.2f} |" for name, w, c in rows]
    return lines


# --------------------------------------------------------------------------- figures

def truth_sheet(evs: list[Evaluated], path: Path) -> None:
    """Checkerboard overlays of the real truths (reference and warped moving frame alternate in
    squares) at 320 px, four per row, to look at."""
    tiles = []
    for ev in evs:
        if ev.pair.kind != "consecutive":
            continue
        a, b = ev.small_ref, ev.small_mov
        h, w = a.shape
        if ev.pair.truth is None:
            out = np.dstack([a // 2] * 3)
        else:
            s = np.diag([ev.factor, ev.factor, 1.0])
            s[:2, 2] = ev.factor / 2 - 0.5
            hm = s @ h3(ev.pair.truth) @ np.linalg.inv(s)
            wb = cv2.warpPerspective(b, hm, (w, h))
            valid = cv2.warpPerspective(np.ones_like(b), hm, (w, h), flags=cv2.INTER_NEAREST) > 0
            yy, xx = np.mgrid[0:h, 0:w]
            cb = ((yy // 24 + xx // 24) % 2) == 0
            g = np.where(valid & cb, wb, a)
            out = np.dstack([g, g, np.where(valid, g, g // 2)])
        cv2.putText(out, ev.pair.name, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 255, 255), 1)
        tiles.append(out)
    rows = [np.hstack(tiles[i:i + 4] + [np.zeros_like(tiles[0])] * (4 - len(tiles[i:i + 4])))
            for i in range(0, len(tiles), 4)]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.vstack(rows))


# --------------------------------------------------------------------------- report

def render_report(meta: dict, evs: list[Evaluated], sweep_res: dict | None, search: list | None,
                  args, elapsed: float, settings: list[str] | None = None) -> str:
    min_conf = Config().mapping.min_confidence
    base = check_rows(evs)
    real_groups = {name: [ev for ev in evs if ev.pair.group == name] for name in meta}
    sim = [ev for ev in evs if ev.pair.kind == "sim"]
    lines = ["## Pairs: feature second opinion and overlap check", "",
             "Written by `python -m tools.bench_pairs` (about 20 minutes on 2 busy cores; `PHOTOMAP_DATA` "
             "names the folder of the real sets, default `../shared/data`).", "",
             "### Machine", ""] + machine_info() + [
        f"- run: `python -m tools.bench_pairs{' --quick' if args.quick else ''}` (seed {SEED}), "
        f"{elapsed / 60:.1f} min", "",
        "### Data and truth", ""]
    for name, m in meta.items():
        evn = real_groups[name]
        cons = [ev for ev in evn if ev.pair.kind == "consecutive"]
        lines.append(f"- **{name}**: {m['frames']} frames of {m['size'][0]}x{m['size'][1]}, focal length "
                     f"{m['focal_px']:.0f} px; {sum(ev.pair.truth is not None for ev in cons)} of {len(cons)} "
                     f"consecutive pairs overlap (truth: SIFT homography at full resolution, camera height "
                     f"implied with the GPS distance: median {m['implied_height_m']:.0f} m"
                     + (f", logged {m['height_m']:.0f} m" if name == "brighton_beach" else "") + "); "
                     f"{sum(ev.pair.kind == 'shuffled' for ev in evn)} shuffled pairs more than "
                     f"{FAR_M[name]:.0f} m apart (no overlap).")
    lines += ["- simulated 640x480 pairs with exact truth (the homography between two rendered views, camera "
              "hfov 60 deg, noise 1 grey level):", ""]
    lines += ["| case | pairs | what |", "|---|---:|---|"]
    for case in SIM_CASES:
        n = sum(ev.pair.group == f"sim: {case.name}" for ev in evs)
        lines.append(f"| {case.name} | {n} | {case.description} |")
    n = sum(ev.pair.group.startswith("sim: periodic") for ev in evs)
    lines.append(f"| periodic w | {n} | crop rows (sinusoid, period ~33 px) blended into aukerman with weight w "
                 f"= {', '.join(str(w) for w in PERIODIC_WEIGHTS)}; each pair also gets the truth moved by one "
                 "period (wrong) |")
    n = sum(ev.pair.group == "sim: shuffled video" for ev in evs)
    lines.append(f"| shuffled video | {n} | frames 4-30 apart of a simulated 1 fps aukerman flight (mostly no "
                 "overlap) |")
    lines += ["", "Errors: median displacement from the truth over the moving frame's points that land in the "
              "reference, px of the full-resolution frame. **Right** <= 1.5 % of the longer side, **wrong** >= "
              "4 % or no overlap, grey in between (a similarity cannot follow tilt and parallax: on seneca the "
              "best one is 1.5-4 % off in parts of some pairs)."]
    if sweep_res is not None:
        lines += ["", "### Feature working size", "",
                  "ORB and SIFT (`FeatureMatcher`: up to 2000 keypoints, ratio test 0.8, RANSAC 3 px at the "
                  f"working size) on every pair; a result counts with >= {F.MIN_INLIERS} inliers.", ""]
        lines += sweep_table(sweep_res, {})
    if settings is not None:
        lines += ["", f"Matcher settings around the defaults (SIFT: 2000 keypoints, contrastThreshold 0.02; ORB: "
                  f"2000 keypoints, FAST threshold 10; ratio 0.8), at {FEATURE_SIZE} px:", ""] + settings
    for name, evn in real_groups.items():
        lines += ["", f"### Real pairs: {name}", "",
                  "Per consecutive pair: GPS distance and the shift it implies at the height above; the truth's "
                  "centre shift and overlap; per method confidence (iFMI) or RANSAC inliers, error (px at full "
                  "resolution; **bold** = wrong, (parentheses) = grey, none = no result) and overlap check "
                  "score/ratio (✓ = confirmed); what `decide` keeps with iFMI first and SIFT as second opinion.", ""]
        lines += real_table(evn)
    lines += ["", "### Simulated pairs", "", f"iFMI at 320 px (the shipped config), ORB and SIFT at {FEATURE_SIZE} px; "
              "errors in px of the 640x480 frames.", ""]
    lines += sim_table(sim)
    lines += ["", "### The overlap check", "",
              "`verify_overlap` on the tracker's 320 px frames: right and wrong placements (every method's "
              "output, the truth, the truth moved by 30 px in 4 directions, one period off on periodic ground, "
              "all outputs on pairs without overlap).", ""]
    lines += metric_comparison(evs, base)
    lines += ["", "Per class (chosen check):", ""] + class_table(base)
    lines += ["", "Periodic ground (crop rows of weight w over aukerman):", ""] + periodic_table(evs)
    lines += ["", "Right placements moved by N px (full resolution) in 4 directions, rejected by the check:", ""]
    lines += shift_table(evs)
    lines += ["", "### Linking policies", "",
              f"Per set, what each policy glues (iFMI alone uses the shipped `mapping.min_confidence = "
              f"{min_conf:g}`; the others the thresholds below). ms per pair: iFMI + check, plus features + their "
              "check when called (the reference frame's features are cached).", ""]
    groups = dict(real_groups)
    groups["simulated"] = sim
    lines += policy_table(groups, min_conf)
    confident = [(ev.pair.name, ev.results["ifmi"].confidence, ev.results["ifmi"].err, ev.results["ifmi"].check)
                 for ev in evs if ev.results["ifmi"].confidence >= min_conf
                 and label(ev.results["ifmi"].err, ev.pair.shape) == "wrong"]
    lines += ["", f"iFMI placements that are wrong yet reach `mapping.min_confidence` ({len(confident)}): "
              + "; ".join(f"{n}: confidence {c:.2f}, {'no overlap' if not np.isfinite(e) else f'{e:.0f} px off'}, "
                          f"check {k.score:.2f}/{k.ratio:.2f} -> {'accepted' if accepted(k) else 'rejected'}"
                          for n, c, e, k in confident)]
    if search is not None:
        best = search[0]
        lines += ["", "Threshold search (iFMI + check, else SIFT; grid over min_score, max_ratio, min_inliers, "
                  "strong_inliers, strong_min_score; zero wrong first, then real pairs accepted, then simulated "
                  "right):", "",
                  f"- best: {best[3]}: wrong {best[0]}, real accepted {-best[1]}, simulated right {-best[2]}",
                  f"- settings tied with the best: {sum(1 for r in search if r[:3] == best[:3])} of {len(search)}",
                  f"- shipped defaults: min_score {F.MIN_SCORE}, max_ratio {F.MAX_RATIO}, min_inliers "
                  f"{F.MIN_INLIERS}, strong_inliers {F.STRONG_INLIERS}, strong_min_score {F.STRONG_MIN_SCORE}: "
                  + next((f"wrong {r[0]}, real accepted {-r[1]}, simulated right {-r[2]}" for r in search
                          if r[3] == {"min_score": F.MIN_SCORE, "max_ratio": F.MAX_RATIO,
                                      "min_inliers": F.MIN_INLIERS, "strong_inliers": F.STRONG_INLIERS,
                                      "strong_min_score": F.STRONG_MIN_SCORE}), "not in the grid")]
    lines += ["", "### Speed", "", "Median over all pairs of this run; the machine was shared with other jobs, "
              "so compare the ratios.", ""] + timing_table(evs)
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer simulated pairs, no sweep or threshold search "
                    "(a smoke test); prints only unless --out is given")
    ap.add_argument("--out", type=Path, default=None, help="markdown report to update (default "
                    "docs/pairs.md, whose summary docs/benchmarks.md quotes; none with --quick)")
    ap.add_argument("--figures", type=Path, default=None, help="folder for checkerboard overlays of the real truths")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    out = args.out if args.out is not None else (None if args.quick else REPO / "docs" / "pairs.md")
    start = time.perf_counter()
    rng = np.random.default_rng(SEED)
    pairs, meta = [], {}
    for name in ("seneca_nir", "brighton_beach"):
        if not (DATA / name / "poses.csv").is_file():
            print(f"error: {DATA / name} not found (set PHOTOMAP_DATA to the shared data folder)", file=sys.stderr)
            return 1
        log.info("real pairs: %s", name)
        p, meta[name] = real_pairs(name, rng, 5 if args.quick else 20)
        pairs += p
    terrains = Terrains()
    n = 2 if args.quick else 10
    log.info("simulated pairs")
    pairs += sim_pairs(terrains, n, rng)
    pairs += periodic_pairs(terrains, 1 if args.quick else 4, rng)
    pairs += shuffled_video_pairs(4 if args.quick else 20, rng)
    log.info("registering %d pairs", len(pairs))
    with threadpool_limits(limits=1, user_api="blas"):  # as the pipeline's worker
        evs = evaluate(pairs, Methods())
        sweep_res = None if args.quick else sweep([p for p in pairs if "periodic" not in p.group])
        log.info("matcher settings")
        settings = None if args.quick else settings_table(pairs)
    log.info("threshold search")
    search = None if args.quick else threshold_search(evs)
    if args.figures is not None:
        for name in meta:
            truth_sheet([ev for ev in evs if ev.pair.group == name], args.figures / f"truth_{name}.png")
    log.info("report")
    body = render_report(meta, evs, sweep_res, search, args, time.perf_counter() - start, settings)
    print(body)
    if out is not None:
        replace_section(out, "pairs", body)
        log.info("wrote %s", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
