"""Registration benchmark: iFMI against imreg_dft, ORB/SIFT+RANSAC and ECC on simulated flights.

Every method runs in one process on the same simulated sequences (exact ground truth from
:mod:`photomap.sim.flight`): textured ground (the bundled aukerman orthophoto), grass-like low texture,
featureless sand (25 % contrast) with noise, a hard 640x480 flight with exactly 10 deg rotation and
5 % scale change per frame, and a flight with 2 deg roll/pitch. Per method and sequence it reports
the success rate, median errors, RMS rotation error, ms per pair and the drift of the chained
trajectory; then iFMI's ms per pair at several frame sizes, each quiet and with a busy neighbour
(a separate process spinning on one core, started and stopped by this tool), refined against plain
iFMI in the same run (and against the original paper's C/C++ timings); and a calibration of iFMI's
confidence (correct pairs against no-overlap and noise pairs).

    python -m tools.bench_registration [--quick] [--frames N] [--out docs/benchmarks.md]

``--quick`` is a smoke test (< 1 min) that only prints unless ``--out`` is given; the full run
replaces its section of ``docs/benchmarks.md``, keeping the hand-written intro and the other tools' sections.

Conventions: a result matrix maps pixels of the new frame ``b`` to pixels of the reference ``a``
(:mod:`photomap.geometry`). The translation error is the distance between the estimated and the true
position of ``b``'s centre in ``a``; rotation and scale errors compare with the rotation and scale
of the true (projective, under tilt) relative transform at that centre. A method that returns
nothing is scored as the identity (what a chained trajectory would use).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import logging
import math
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import scipy

from photomap.config import MappingConfig, RegistrationConfig
from photomap.errors import InputError
from photomap.sim.flight import (Camera, Effects, Motion, iter_frames, plan_flight, pose_homography,
                            relative_matrix, render_pair, simulate_sequence)
from photomap.core.ifmi import Registrar
from photomap.sim.terrain import BUNDLED, DEFAULT_GSD, TERRAIN_GSD, TERRAIN_ZOOM, load_terrain, valid_mask

from tools.peers import Method, peer_methods
from tools.report import replace_section

log = logging.getLogger("bench_registration")

REPO = Path(__file__).resolve().parents[1]
SEED = 7
DEFAULT_INTRO = """# Benchmarks

Today's figures of photomap on the machines it is developed on (2 cores, no GPU). Each `##` section
is written by the tool it names: `python -m tools.NAME --out docs/benchmarks.md` rewrites its own
section (between its `<!-- name:start/end -->` markers) and leaves the rest; history is in git.
Targets are tables at the end of their sections.

"""

SUCCESS_PX, SUCCESS_DEG, SUCCESS_SCALE = 1.0, 0.5, 0.01
PAPER_MS = {(256, 256): 230.0, (480, 480): 430.0}  # Buelow & Birk 2009, C/C++ on a 1.7 GHz PC
# (180, 320): what the pipeline registers of a 16:9 video (registration.working_size 320)
TIMING_SHAPES = [(180, 320), (256, 256), (480, 480), (512, 512), (480, 640)]
TARGET_MS = {(256, 256): 2.0, (512, 512): 6.0, (480, 640): 12.0}
TARGET_REFINED_OVER_PLAIN = {(256, 256): 1.25, (512, 512): 1.25}  # refinement's cost, same run
TARGET_BUSY_OVER_QUIET = 1.3  # iFMI with a neighbour spinning on one core against without
# quiet and busy: sequence mode (each frame against the previous one); keyframes: quiet, each frame
# against the current keyframe, held as the tracker holds it (mapping.keyframe_max_shift)
CONDITIONS = ("quiet", "busy", "keyframes")

# A multirotor video at 5 fps (every 6th frame of 30 fps): 8 m/s at 50-70 m, yaw up to 15 deg/s.
_CRUISE = dict(pattern="random", speed=8.0, yaw_mode="random", yaw_rate=15.0, altitude=(50.0, 70.0),
               scale_rate=0.05)


@dataclass(frozen=True)
class SequenceSpec:
    """A simulated sequence: terrain, frame shape ``(h, w)``, frame rate and flight parameters."""

    name: str
    terrain: str
    shape: tuple[int, int]
    fps: float
    params: dict
    description: str
    steady_steps: tuple[float, float] | None = None  # exact (deg, relative scale) per frame


SEQUENCES = [
    SequenceSpec("textured", "aukerman", (256, 256), 5.0, {**_CRUISE, "noise": 1.0},
                 "aukerman orthophoto, 256x256, 5 fps cruise, noise 1 grey level"),
    SequenceSpec("grass", "grass", (256, 256), 5.0, {**_CRUISE, "noise": 1.0},
                 "procedural grass (fine, low-contrast texture), 256x256, 5 fps cruise, noise 1"),
    SequenceSpec("sand", "sand", (256, 256), 5.0, {**_CRUISE, "noise": 2.0},
                 "procedural sand (smooth, 25 % contrast), 256x256, 5 fps cruise, noise 2"),
    SequenceSpec("hard 640x480", "aukerman", (480, 640), 1.0,
                 {"pattern": "random", "speed": 5.0, "yaw_mode": "constant", "yaw_rate": 10.0,
                  "altitude": (40.0, 40.0 * 1.05 ** 8), "noise": 1.0},
                 "aukerman, 640x480, exactly 10 deg and 5 % scale (altitude up/down 8 frames each) "
                 "per frame, 5 m per frame", steady_steps=(10.0, 0.05)),
    SequenceSpec("tilt 2 deg", "aukerman", (256, 256), 5.0, {**_CRUISE, "tilt": 2.0, "noise": 1.0},
                 "aukerman, 256x256, 5 fps cruise with roll/pitch wandering within +-2 deg"),
]


class Ifmi(Method):
    """iFMI on prepared frames: each frame prepared once, ``register(ref_prepared, new_prepared)``."""

    def __init__(self, shape: tuple[int, int], name: str = "iFMI", **settings) -> None:
        self.name = name
        self.registrar = Registrar(shape, RegistrationConfig(**settings))

    def prepare(self, gray: np.ndarray):
        return self.registrar.prepare(gray)

    def register(self, ref, new) -> tuple[np.ndarray | None, float | None]:
        r = self.registrar.register(ref, new)
        return r.matrix, r.confidence


def ifmi_methods(shape: tuple[int, int]) -> list[Method]:
    """iFMI with the shipped registration config, and the same with refinement off."""
    settings = dataclasses.asdict(RegistrationConfig())
    return [Ifmi(shape, "iFMI", **settings),
            Ifmi(shape, "iFMI no refine", **{**settings, "refine_iterations": 0})]


class HostReference(Method):
    """Not a registration: a fixed single-threaded load timed beside iFMI, pair by pair (the
    frame's forward and inverse ``cv2.dft``, float32, three times: FFTs, as most of iFMI).

    Its busy / quiet is what a busy neighbour costs any single-threaded work on this host (vCPUs
    that share a physical core, shared caches); iFMI's above it is iFMI's own (threads spinning).
    """

    name = "host reference"

    def prepare(self, gray: np.ndarray) -> None:
        x = gray.astype(np.float32)
        for _ in range(3):
            x = cv2.idft(cv2.dft(x), flags=cv2.DFT_SCALE)

    def register(self, ref, new) -> tuple[None, None]:
        return None, None


# --------------------------------------------------------------------------- sequences

@dataclass
class Flight:
    spec: SequenceSpec
    grays: list[np.ndarray]
    truth: object  # photomap.sim.flight.Truth

    @property
    def centre(self) -> np.ndarray:
        h, w = self.spec.shape
        return np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])


class TerrainCache:
    """Terrains by name with their validity mask and metres per terrain pixel (loaded once)."""

    def __init__(self) -> None:
        self._items: dict[str, tuple[np.ndarray, np.ndarray | None, float]] = {}

    def get(self, name: str) -> tuple[np.ndarray, np.ndarray | None, float]:
        if name not in self._items:
            if name in BUNDLED:
                zoom = TERRAIN_ZOOM.get(name, 1.0)
                terrain = load_terrain(name, zoom=zoom)
                self._items[name] = (terrain, valid_mask(terrain), TERRAIN_GSD.get(name, DEFAULT_GSD) / zoom)
            else:
                self._items[name] = (load_terrain(name, seed=SEED), None, DEFAULT_GSD)
        return self._items[name]


def _steady_flight(terrain: np.ndarray, valid: np.ndarray | None, gsd: float, n: int, spec: SequenceSpec,
                   seed: int):
    """Frames and truth of a flight turning exactly ``deg`` and scaling exactly ``1 + s`` per frame.

    The simulator's altitude is a sinusoid; here the log altitude is a triangle wave instead
    (8 frames up, 8 down), so every pair changes scale by exactly 5 %. Positions and the constant
    yaw rate come from :func:`plan_flight` (fps 1: rates are per frame).
    """
    deg, rel = spec.steady_steps
    h, w = spec.shape
    params = {k: v for k, v in spec.params.items() if k != "noise"}
    motion = Motion(**{**params, "yaw_rate": deg})
    camera = Camera.from_hfov(w, h, 60.0)
    mask = np.ones(terrain.shape[:2], bool) if valid is None else valid
    truth = plan_flight(mask, n, camera, 1.0, gsd, motion, seed)
    k = np.arange(n)
    tri = 8 - np.abs(k % 16 - 8)
    alt = motion.altitude[0] * (1.0 + rel) ** tri
    hs = np.stack([pose_homography(camera, x, y, a / gsd, 0.0, 0.0, math.radians(yaw))
                   for x, y, a, yaw in zip(truth.cam_x, truth.cam_y, alt, truth.yaw_deg)])
    truth = dataclasses.replace(truth, H=hs, alt_m=alt, scale=alt / (camera.fx * gsd))
    frames = list(iter_frames(terrain, truth, camera, Effects(noise=spec.params.get("noise", 0.0)), seed))
    return frames, truth


def make_flight(spec: SequenceSpec, n: int, terrains: TerrainCache, seed: int) -> Flight:
    terrain, valid, gsd = terrains.get(spec.terrain)
    if spec.steady_steps:
        frames, truth = _steady_flight(terrain, valid, gsd, n, spec, seed)
    else:
        seq = simulate_sequence(terrain, n, spec.shape, seed, valid=valid, fps=spec.fps, gsd=gsd, **spec.params)
        frames, truth = seq.frames, seq.truth
    grays = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in frames]
    return Flight(spec, grays, truth)


# --------------------------------------------------------------------------- errors

def _apply(h: np.ndarray, c: np.ndarray) -> np.ndarray:
    p = h @ c
    return p[:2] / p[2] if h.shape[0] == 3 else p


def local_similarity(h: np.ndarray, c: np.ndarray) -> tuple[float, float]:
    """(angle_deg, scale) of the 3x3 homography ``h`` at the point ``c`` (its Jacobian there)."""
    den = float(h[2] @ c)
    jac = (h[:2, :2] * den - np.outer(h[:2] @ c, h[2, :2])) / den ** 2
    angle = math.degrees(math.atan2(jac[1, 0] - jac[0, 1], jac[0, 0] + jac[1, 1]))
    return angle, math.sqrt(abs(np.linalg.det(jac)))


def pair_errors(m: np.ndarray, truth: np.ndarray, c: np.ndarray) -> tuple[float, float, float]:
    """(translation px, |rotation| deg, |relative scale|) errors of ``m`` (2x3) against ``truth`` (3x3)."""
    t_err = float(np.linalg.norm(_apply(m, c) - _apply(truth, c)))
    angle, scale = local_similarity(truth, c)
    est_angle = math.degrees(math.atan2(m[1, 0], m[0, 0]))
    est_scale = math.sqrt(max(float(np.linalg.det(m[:, :2])), 0.0))
    r_err = abs((est_angle - angle + 180.0) % 360.0 - 180.0)
    return t_err, r_err, abs(est_scale / scale - 1.0)


@dataclass
class Run:
    """Per-pair results of one method on one sequence."""

    method: str
    sequence: str
    t_err: np.ndarray
    r_err: np.ndarray
    s_err: np.ndarray
    ms: np.ndarray
    confidence: np.ndarray  # NaN where the method gives none
    returned: np.ndarray  # bool: the method produced a matrix
    drift_pct: float

    @property
    def success(self) -> np.ndarray:
        return (self.t_err < SUCCESS_PX) & (self.r_err < SUCCESS_DEG) & (self.s_err < SUCCESS_SCALE)


def run_method(method: Method, flight: Flight) -> Run:
    """Register every consecutive pair of ``flight`` (new frame k to reference k-1), timed."""
    grays, truth, c = flight.grays, flight.truth, flight.centre
    prev = method.prepare(grays[0])
    method.register(prev, method.prepare(grays[1]))  # warm-up (caches, lazy init)
    rows, ms, conf, returned = [], [], [], []
    pose = np.eye(3)
    for k in range(1, len(grays)):
        t0 = time.perf_counter()
        cur = method.prepare(grays[k])
        m, confidence = method.register(prev, cur)
        ms.append(1e3 * (time.perf_counter() - t0))
        prev = cur
        returned.append(m is not None)
        if m is None:
            m = np.eye(2, 3)
        conf.append(np.nan if confidence is None else confidence)
        rows.append(pair_errors(m, relative_matrix(truth, k - 1, k), c))
        pose = pose @ np.vstack([m, [0.0, 0.0, 1.0]])
    # drift: chained estimate of the last frame's centre against truth, over the true path length
    centres = np.array([_apply(relative_matrix(truth, 0, k), c) for k in range(len(grays))])
    path = float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())
    drift = float(np.linalg.norm(_apply(pose, c) - centres[-1])) / max(path, 1e-9) * 100.0
    t_err, r_err, s_err = np.array(rows).T
    return Run(method.name, flight.spec.name, t_err, r_err, s_err, np.array(ms), np.array(conf),
               np.array(returned), drift)


def motion_summary(flight: Flight) -> str:
    """Median per-pair motion of a flight: centre shift (px), |rotation| (deg), |scale change| (%)."""
    c = flight.centre
    shifts, rots, scales = [], [], []
    for k in range(1, len(flight.grays)):
        rel = relative_matrix(flight.truth, k - 1, k)
        shifts.append(float(np.linalg.norm(_apply(rel, c) - c[:2])))
        angle, scale = local_similarity(rel, c)
        rots.append(abs(angle))
        scales.append(abs(scale - 1.0) * 100.0)
    return (f"{np.median(shifts):.1f} px, {np.median(rots):.2f} deg, {np.median(scales):.2f} % "
            f"(max {np.max(shifts):.1f} px, {np.max(rots):.2f} deg, {np.max(scales):.2f} %)")


# --------------------------------------------------------------------------- timing

@contextlib.contextmanager
def busy_neighbour(enabled: bool = True) -> Iterator[subprocess.Popen | None]:
    """A separate Python process spinning on one core while the block runs (stopped after it).

    It stands for any other busy process on a companion computer (a video encoder, the flight
    stack's logger): registration must cost the same next to it.
    """
    if not enabled:
        yield None
        return
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(0.3)  # let it start spinning before anything is timed
        yield proc
    finally:
        proc.kill()
        proc.wait()


@dataclass
class Timing:
    """ms per pair of iFMI at one frame size: ``ms[condition][method]`` (medians) and the samples."""

    shape: tuple[int, int]
    ms: dict[str, dict[str, float]]
    samples: int  # timed pairs per method and condition
    load: float = float("nan")  # 1-minute load average when the timing started (0 = idle machine)
    # CPU time of the timing thread per pair (medians, ms): unlike wall time, it hardly depends on
    # how often other processes preempt the benchmark (a shared machine)
    cpu: dict[str, dict[str, float]] = dataclasses.field(default_factory=dict)

    def ratio_busy(self, method: str) -> float:
        return self.ms["busy"][method] / self.ms["quiet"][method]

    def ratio_refined(self, condition: str) -> float:
        return self.ms[condition]["iFMI"] / self.ms[condition]["iFMI no refine"]


def keyframe_references(flight: Flight, max_shift: float | None = None) -> list[int]:
    """Index of the reference of each frame from 1 on, held as the tracker holds its keyframe.

    A frame becomes the next reference once its true centre lies more than ``max_shift`` frame
    sizes (``mapping.keyframe_max_shift`` by default) from its reference, counting one more step
    at its speed (see ``photomap.core.tracking``'s ``_next_shift``). Frame pixels: terrain pixels
    over the truth's scale.
    """
    if max_shift is None:
        max_shift = MappingConfig().keyframe_max_shift
    t = flight.truth
    limit = max_shift * min(flight.spec.shape)
    refs, ref = [], 0
    for i in range(1, len(flight.grays)):
        refs.append(ref)
        shift = math.hypot(t.x[i] - t.x[ref], t.y[i] - t.y[ref]) / t.scale[i]
        step = math.hypot(t.x[i] - t.x[i - 1], t.y[i] - t.y[i - 1]) / t.scale[i]
        if shift + step > limit:
            ref = i
    return refs


def time_ifmi(shape: tuple[int, int], n: int, terrains: TerrainCache, repeats: int = 3) -> Timing:
    """Median ms per pair of iFMI, refinement on and off, in three conditions.

    Each pair is the new frame's ``prepare()`` plus ``register()``, on a textured flight of ``n``
    frames passed ``repeats`` times per condition (every pass prepares its frames afresh).
    *quiet* and *busy* (with :func:`busy_neighbour`): sequence mode, against the previous
    frame, so every frame is a reference once (the refinement's template, built once per
    reference, counts in every pair); *keyframes* (quiet): against the current keyframe, as the
    pipeline's tracker registers (:func:`keyframe_references`). A :class:`HostReference` load is
    timed with them: what a busy neighbour costs on this host whatever the code. The passes
    alternate between the conditions (quiet, busy, keyframes, keyframes, busy, quiet, ...) and
    the methods pair by pair, their order reversed pass by pass: the ratios (busy / quiet,
    refined / plain) compare measurements spread over the same minutes, so a shared host's
    drifting speed and whichever method meets a frame first in the CPU's caches bias none of
    them. Medians, not minima: a companion computer is never idle, and the typical pair is what
    the pipeline pays.
    """
    spec = SequenceSpec("timing", "aukerman", shape, 5.0, {**_CRUISE, "noise": 1.0}, "")
    flight = make_flight(spec, n, terrains, SEED + 100)
    keyframe_refs = keyframe_references(flight)
    methods = ifmi_methods(shape) + [HostReference()]
    samples = {c: {m.name: [] for m in methods} for c in CONDITIONS}
    cpu_samples = {c: {m.name: [] for m in methods} for c in CONDITIONS}
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    for k in range(repeats):
        for c in (range(len(CONDITIONS)) if k % 2 == 0 else reversed(range(len(CONDITIONS)))):
            condition = CONDITIONS[c]
            order = methods if (k + c) % 2 == 0 else methods[::-1]
            with busy_neighbour(condition == "busy"):
                for method in order:  # warm-up (lazy init, caches)
                    method.register(method.prepare(flight.grays[0]), method.prepare(flight.grays[1]))
                ref = {m.name: m.prepare(flight.grays[0]) for m in order}
                for i, gray in enumerate(flight.grays[1:], start=1):
                    # the next frame's reference: this one, or (keyframes) the current keyframe
                    becomes_ref = condition != "keyframes" or i == len(keyframe_refs) or keyframe_refs[i] == i
                    for method in order:
                        t0, c0 = time.perf_counter(), time.thread_time()
                        cur = method.prepare(gray)
                        method.register(ref[method.name], cur)
                        samples[condition][method.name].append(1e3 * (time.perf_counter() - t0))
                        cpu_samples[condition][method.name].append(1e3 * (time.thread_time() - c0))
                        if becomes_ref:
                            ref[method.name] = cur
    ms = {c: {name: float(np.median(v)) for name, v in by.items()} for c, by in samples.items()}
    cpu = {c: {name: float(np.median(v)) for name, v in by.items()} for c, by in cpu_samples.items()}
    return Timing(shape, ms, repeats * (len(flight.grays) - 1), load, cpu)


# --------------------------------------------------------------------------- confidence calibration

def no_overlap_pairs(terrains: TerrainCache, names: list[str], count: int, shape: tuple[int, int],
                     rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """Pairs of views of the same terrain whose footprints are disjoint (circumscribed circles apart)."""
    h, w = shape
    half_diag = math.hypot(w, h) / 2.0
    pairs = []
    for name in names:
        terrain, valid, _ = terrains.get(name)
        for i in range(count):
            scale = float(rng.uniform(0.9, 1.1))
            direction = rng.uniform(0, 2 * math.pi)
            dist = half_diag * (1.0 + scale) * float(rng.uniform(1.1, 1.5))
            shift = (dist * math.cos(direction), dist * math.sin(direction))
            for base_scale in (1.5, 1.0, 0.7):
                try:
                    a, b, _ = render_pair(terrain, shape, float(rng.uniform(-180, 180)), scale, shift,
                                          seed=SEED + i, valid=valid, base_scale=base_scale, noise=1.0)
                except InputError:
                    continue
                pairs.append((cv2.cvtColor(a, cv2.COLOR_BGR2GRAY), cv2.cvtColor(b, cv2.COLOR_BGR2GRAY)))
                break
    return pairs


def noise_pairs(count: int, shape: tuple[int, int], rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """Independent noise frames: white, and smoothed (Gaussian sigma 2 px), std 30 around 128."""
    def frame(sigma: float) -> np.ndarray:
        img = rng.standard_normal(shape).astype(np.float32)
        if sigma:
            img = cv2.GaussianBlur(img, (0, 0), sigma)
        img = (img - img.mean()) / img.std()
        return np.clip(128 + 30 * img, 0, 255).astype(np.uint8)

    return [(frame(s), frame(s)) for s in (0.0, 2.0) for _ in range(count)]


@dataclass
class Calibration:
    classes: dict[str, np.ndarray]  # class name -> confidences
    threshold: float
    accept_correct: float
    reject_wrong: float
    configured: float
    configured_accept: float
    configured_reject: float


def best_threshold(good: np.ndarray, bad: np.ndarray) -> tuple[float, float, float]:
    """Threshold maximising (correct accepted + wrong rejected fractions); ``conf >= t`` accepts.

    Cuts lie halfway between neighbouring confidences; among equally good ones the median is
    taken (with separated classes: the middle of the gap between them). Returns
    ``(threshold, fraction of good accepted, fraction of bad rejected)``.
    """
    values = np.unique(np.concatenate([good, bad, [0.0, 1.0]]))
    cuts = np.concatenate([[values[0]], (values[1:] + values[:-1]) / 2.0, [values[-1] + 1e-6]])
    score = np.array([(good >= t).mean() + (bad < t).mean() for t in cuts])
    best = np.flatnonzero(score >= score.max() - 1e-12)
    t = float(np.median(cuts[best]))
    return t, float((good >= t).mean()), float((bad < t).mean())


def calibrate(runs: list[Run], terrains: TerrainCache, count: int, configured: float) -> Calibration:
    """iFMI's confidence on correct pairs against wrong ones (gross errors, no overlap, noise)."""
    shape = (256, 256)
    rng = np.random.default_rng([SEED, 9])
    ifmi = [r for r in runs if r.method == "iFMI"]
    correct = np.concatenate([r.confidence[r.success] for r in ifmi])
    is_gross = [(r.t_err > 5) | (r.r_err > 2) | (r.s_err > 0.05) for r in ifmi]
    gross = np.concatenate([r.confidence[g] for r, g in zip(ifmi, is_gross)])
    imprecise = np.concatenate([r.confidence[~r.success & ~g] for r, g in zip(ifmi, is_gross)])
    method = Ifmi(shape, "iFMI", **dataclasses.asdict(RegistrationConfig()))
    overlap = [method.register(method.prepare(a), method.prepare(b))[1]
               for a, b in no_overlap_pairs(terrains, ["aukerman", "grass", "sand"], count, shape, rng)]
    noise = [method.register(method.prepare(a), method.prepare(b))[1] for a, b in noise_pairs(count, shape, rng)]
    classes = {"correct (success) pairs": correct, "gross errors (>5 px, >2 deg or >5 %)": gross,
               "no-overlap pairs": np.array(overlap), "noise pairs": np.array(noise),
               "imprecise pairs (neither; not used for the threshold)": imprecise}
    wrong = np.concatenate([gross, overlap, noise])
    t, acc, rej = best_threshold(correct, wrong)
    return Calibration(classes, t, acc, rej, configured, float((correct >= configured).mean()),
                       float((wrong < configured).mean()) if wrong.size else float("nan"))


# --------------------------------------------------------------------------- report

def machine_info() -> list[str]:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return [f"- CPU: {cpu}, {os.cpu_count()} cores (OpenCV threads: {cv2.getNumThreads()}; iFMI's FFTs "
            "run single-threaded)",
            f"- Python {platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}, "
            f"OpenCV {cv2.__version__}",
            f"- date: {datetime.datetime.now().astimezone().strftime('%Y-%m-%d %H:%M %Z')}, load average "
            f"(1 min) at the end of the run: {os.getloadavg()[0]:.2f} (other processes share the cores: "
            "timings are upper bounds)"]


def _fmt(x: float, digits: int = 3) -> str:
    if not np.isfinite(x):
        return "-"
    return f"{x:.{digits}f}" if abs(x) < 1000 else f"{x:.0f}"


def accuracy_table(runs: list[Run]) -> list[str]:
    out = ["| sequence | method | success % | median t err (px) | median rot err (deg) | median scale err (%) "
           "| RMS rot err (deg) | ms/pair | drift (% of path) | no result |",
           "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in runs:
        out.append(f"| {r.sequence} | {r.method} | {100 * r.success.mean():.1f} | {_fmt(np.median(r.t_err))} "
                   f"| {_fmt(np.median(r.r_err))} | {_fmt(100 * np.median(r.s_err))} "
                   f"| {_fmt(math.sqrt(float(np.mean(r.r_err ** 2))))} | {_fmt(np.median(r.ms), 1)} "
                   f"| {_fmt(r.drift_pct, 2)} | {int((~r.returned).sum())} |")
    return out


def timing_table(timings: dict[tuple[int, int], Timing]) -> list[str]:
    out = ["| frame (w x h) | iFMI quiet | iFMI busy | busy / quiet | no refine quiet | no refine busy "
           "| busy / quiet | host reference busy / quiet | refined / plain quiet | refined / plain busy "
           "| refined / plain keyframes | target ms (quiet) | paper C/C++ ms | paper / iFMI | load before |",
           "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for shape, t in timings.items():
        paper = PAPER_MS.get(shape)
        target = TARGET_MS.get(shape)
        quiet, busy = t.ms["quiet"], t.ms["busy"]
        ratio = f"{paper / quiet['iFMI']:.0f}x faster" if paper else "-"
        out.append(f"| {shape[1]}x{shape[0]} | {quiet['iFMI']:.2f} | {busy['iFMI']:.2f} | {t.ratio_busy('iFMI'):.2f} "
                   f"| {quiet['iFMI no refine']:.2f} | {busy['iFMI no refine']:.2f} "
                   f"| {t.ratio_busy('iFMI no refine'):.2f} | {t.ratio_busy(HostReference.name):.2f} "
                   f"| {t.ratio_refined('quiet'):.2f} "
                   f"| {t.ratio_refined('busy'):.2f} | {t.ratio_refined('keyframes'):.2f} "
                   f"| {'<= %g' % target if target else '-'} "
                   f"| {'%g' % paper if paper else '-'} | {ratio} | {_fmt(t.load, 2)} |")
    return out


def calibration_table(cal: Calibration) -> list[str]:
    out = ["| pairs | n | min | 5 % | median | 95 % | max |", "|---|---:|---:|---:|---:|---:|---:|"]
    for name, v in cal.classes.items():
        if v.size:
            q = np.percentile(v, [0, 5, 50, 95, 100])
            out.append(f"| {name} | {v.size} | " + " | ".join(f"{x:.3f}" for x in q) + " |")
        else:
            out.append(f"| {name} | 0 | - | - | - | - | - |")
    out += ["", f"Best separating threshold: **min_confidence = {cal.threshold:.3f}** (accepts "
            f"{100 * cal.accept_correct:.1f} % of correct pairs, rejects {100 * cal.reject_wrong:.1f} % of wrong "
            f"ones). The configured `mapping.min_confidence = {cal.configured:g}` accepts "
            f"{100 * cal.configured_accept:.1f} % of correct pairs and rejects {100 * cal.configured_reject:.1f} % "
            "of wrong ones."]
    return out


def cpu_table(timings: dict[tuple[int, int], Timing]) -> list[str]:
    out = ["| frame (w x h) | iFMI CPU quiet | iFMI CPU busy | no refine CPU quiet | no refine CPU busy "
           "| refined / plain (CPU, quiet) |", "|---|---:|---:|---:|---:|---:|"]
    for shape, t in timings.items():
        if not t.cpu:
            continue
        q, b = t.cpu["quiet"], t.cpu["busy"]
        out.append(f"| {shape[1]}x{shape[0]} | {q['iFMI']:.2f} | {b['iFMI']:.2f} | {q['iFMI no refine']:.2f} "
                   f"| {b['iFMI no refine']:.2f} | {q['iFMI'] / q['iFMI no refine']:.2f} |")
    return out


def targets_table(runs: list[Run], timings: dict[tuple[int, int], Timing]) -> list[str]:
    def get(seq: str) -> Run | None:
        return next((r for r in runs if r.method == "iFMI" and r.sequence == seq), None)

    rows = []
    for shape, target in TARGET_MS.items():
        if shape in timings:
            v = timings[shape].ms["quiet"]["iFMI"]
            rows.append((f"ms/pair {shape[1]}x{shape[0]} (quiet median) <= {target:g}", f"{v:.2f}", v <= target))
    for shape, target in TARGET_REFINED_OVER_PLAIN.items():
        if shape in timings:
            v = timings[shape].ratio_refined("quiet")
            rows.append((f"refined / plain {shape[1]}x{shape[0]} (quiet) <= {target:g}", f"{v:.2f}", v <= target))
    for shape, t in timings.items():
        v = t.ratio_busy("iFMI")
        rows.append((f"busy / quiet {shape[1]}x{shape[0]} <= {TARGET_BUSY_OVER_QUIET:g}",
                     f"{v:.2f} (host reference {t.ratio_busy(HostReference.name):.2f})", v <= TARGET_BUSY_OVER_QUIET))
    tex = get("textured")
    if tex is not None:
        for label, v, lim in (("textured median t err <= 0.02 px", np.median(tex.t_err), 0.02),
                              ("textured median rot err <= 0.02 deg", np.median(tex.r_err), 0.02),
                              ("textured median scale err <= 0.03 %", 100 * np.median(tex.s_err), 0.03),
                              ("textured RMS rot err <= 0.01 deg", math.sqrt(float(np.mean(tex.r_err ** 2))), 0.01)):
            rows.append((label, f"{v:.4f}", v <= lim))
    sand = get("sand")
    if sand is not None:
        v = 100 * sand.success.mean()
        rows.append(("featureless (sand) success >= 95 %", f"{v:.1f}", v >= 95.0))
    return ["| target | measured | met |", "|---|---:|:---:|"] + [
        f"| {a} | {b} | {'yes' if ok else '**no**'} |" for a, b, ok in rows]


def render_report(flights: list[Flight], runs: list[Run], timings, cal: Calibration, args, elapsed: float) -> str:
    lines = ["## Registration", "",
             f"Written by `python -m tools.bench_registration{' --quick' if args.quick else ''} --frames {args.frames}` "
             f"(seed {SEED}, {elapsed / 60:.1f} min) on:", ""] + machine_info() + [
        "", "How iFMI (`service/core/ifmi.py`) compares with other registration methods a user could pick, "
        "on simulated flights with exact ground truth (`service/sim/flight.py`). Success means translation "
        "error < 1 px, rotation error < 0.5 deg and scale error < 1 %. The translation error is the error "
        "of the new frame's centre in the reference frame; rotation and scale are compared with the true "
        "relative transform at that centre. A method that returns nothing counts as the identity. Drift: "
        "the pairwise matrices chained from the first frame, the error of the last frame's centre divided "
        "by the true path length (in first-frame pixels).",
        "", "### Sequences", "",
        "| sequence | frames | what | motion per pair: median (max) shift, rotation, scale change |",
        "|---|---:|---|---|"]
    for f in flights:
        lines.append(f"| {f.spec.name} | {len(f.grays)} | {f.spec.description} | {motion_summary(f)} |")
    lines += ["", "Methods: **iFMI** (`service/core/ifmi.py` with the shipped `registration` config, sequence mode: "
              "every frame prepared once), **iFMI no refine** (the same with `refine_iterations = 0`), "
              "**imreg_dft** (`imreg_dft.similarity`, defaults), **ORB+RANSAC** (1000 ORB features, "
              "cross-checked Hamming matches), **SIFT+RANSAC** (OpenCV defaults, ratio test 0.75), both with "
              "`cv2.estimateAffinePartial2D` (RANSAC 3 px) and keypoints detected once per frame, **ECC** "
              "(`cv2.findTransformECC`, MOTION_AFFINE on a Gaussian pyramid from identity, projected to a "
              "similarity)."
              + ("" if hasattr(cv2, "AKAZE_create") else " AKAZE is absent from this OpenCV build.")
              + " ms/pair: median over the pairs after one warm-up pair, `time.perf_counter`, including the "
              "new frame's per-frame work.", "",
              "### Accuracy, speed and drift", ""] + accuracy_table(runs)
    samples = next(iter(timings.values())).samples if timings else 0
    lines += ["", "### iFMI speed by frame size", "",
              "Median ms per pair on a textured 5 fps flight (the new frame's `prepare()` plus `register()`), "
              f"{samples} pairs per method and condition ({args.timing_pairs} pairs, {args.timing_repeats} passes), "
              "iFMI and iFMI no refine alternating pair by pair (which goes first alternates pass by pass), "
              "the passes of the conditions alternating (quiet, busy, keyframes, keyframes, busy, quiet, ...). "
              "*quiet* and *busy*: sequence mode, each frame against the previous one, so that each pair "
              "also pays the refinement's template of its reference (the worst case for the refinement); "
              "*quiet*: no process started by the tool (*load before*: the 1-minute load average when the "
              "size's timing started; above 0 other processes shared the cores); *busy*: a separate process "
              "spinning on one core for the duration (`while True: pass`, started and stopped by the tool); "
              "*keyframes*: quiet, each frame against the current keyframe, a new one once the flight moved "
              "`mapping.keyframe_max_shift` frame sizes from it, as the pipeline's tracker registers (a "
              "template serves every frame registered against its keyframe: about 20 here). *busy / quiet* "
              "is the cost of a busy neighbour, *refined / plain* the cost of the Gauss-Newton refinement, "
              "both from the same run. *host reference*: a fixed single-threaded load (the frame's forward "
              "and inverse `cv2.dft`, 3 times) timed in the same passes, pair by pair: its busy / quiet is "
              "what the neighbour costs any code on this host (vCPUs sharing a physical core, caches). "
              "Paper: Buelow & Birk, IROS 2009, C/C++ on a 1.7 GHz PC: 230 ms at 256x256, 430 ms at 480x480.", ""]
    lines += timing_table(timings)
    lines += ["", "CPU time of the benchmark's thread per pair (median ms; `time.thread_time`): on a shared "
              "machine it shows the work itself, while the wall times above also count the time other "
              "processes held the cores. Threads that spin (a multithreaded BLAS) show up in the wall time, "
              "not here.", ""]
    lines += cpu_table(timings)
    lines += ["", "### iFMI confidence calibration", "",
              "Confidence of iFMI on the successful pairs of all sequences above against wrong results: pairs "
              "of those sequences with a gross error, pairs of views of the same terrains (aukerman, grass, "
              "sand) with disjoint footprints, and pairs of independent noise frames (white and smoothed).", ""]
    lines += calibration_table(cal)
    lines += ["", "### Targets", ""] + targets_table(runs, timings)
    return "\n".join(lines) + "\n"


def write_report(path: Path, body: str) -> None:
    """Replace the registration section of ``path``, keeping the intro and other tools' sections."""
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(DEFAULT_INTRO, encoding="utf-8")
    replace_section(path, "registration", body)


# --------------------------------------------------------------------------- main

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small smoke-test run (< 1 min); prints only "
                    "unless --out is given")
    ap.add_argument("--frames", type=int, default=None, help="frames per accuracy sequence (default 201; "
                    "--quick: 8)")
    ap.add_argument("--out", type=Path, default=None, help="markdown report to write (default "
                    "docs/benchmarks.md; none with --quick)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    args.frames = args.frames or (8 if args.quick else 201)
    if args.frames < 3:
        print("error: --frames must be at least 3", file=sys.stderr)
        return 2
    out = args.out if args.out is not None else (None if args.quick else REPO / "docs" / "benchmarks.md")
    args.timing_pairs = 5 if args.quick else 40
    args.timing_repeats = 2 if args.quick else 8
    calib_count = 3 if args.quick else 20

    start = time.perf_counter()
    terrains = TerrainCache()
    flights, runs = [], []
    try:
        for i, spec in enumerate(SEQUENCES):
            log.info("simulating %s (%d frames)", spec.name, args.frames)
            flight = make_flight(spec, args.frames, terrains, SEED + i)
            flights.append(flight)
            for method in ifmi_methods(spec.shape) + peer_methods(spec.shape):
                run = run_method(method, flight)
                log.info("  %-14s success %5.1f %%  median %.3f px  %.1f ms/pair", method.name,
                         100 * run.success.mean(), np.median(run.t_err), np.median(run.ms))
                runs.append(run)
        timings = {}
        for shape in TIMING_SHAPES:
            log.info("timing iFMI at %dx%d, quiet, with a busy neighbour and against keyframes", shape[1], shape[0])
            timings[shape] = time_ifmi(shape, args.timing_pairs + 1, terrains, args.timing_repeats)
            t = timings[shape]
            log.info("  ms/pair refined %.2f quiet, %.2f busy (x%.2f); refined / plain %.2f quiet, %.2f busy, "
                     "%.2f keyframes", t.ms["quiet"]["iFMI"], t.ms["busy"]["iFMI"], t.ratio_busy("iFMI"),
                     t.ratio_refined("quiet"), t.ratio_refined("busy"), t.ratio_refined("keyframes"))
        log.info("confidence calibration")
        cal = calibrate(runs, terrains, calib_count, MappingConfig().min_confidence)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    body = render_report(flights, runs, timings, cal, args, time.perf_counter() - start)
    print(body)
    if out is not None:
        write_report(out, body)
        log.info("wrote %s", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
