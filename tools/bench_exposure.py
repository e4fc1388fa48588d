"""Exposure compensation of the photo map (photomap issue 10, item 7): steps at frame edges.

1. Brighton beach (18 real DJI stills on auto exposure), posed by SIFT + RANSAC similarities
   (evaluation only: the iFMI replay poses 10 of the 18) and, with ``--trajectory``, by the
   ``trajectory.csv`` of a ``photomap replay`` run (per segment). Painted with
   ``mosaic.exposure`` none / gain / channel_gain (sequential, live) and with the gains of
   :func:`photomap.core.exposure.joint_gains` (all frames at once, for a re-render), blends
   overwrite and feather.
2. A simulated video (aukerman, lawn-mower, ``gain_drift``) painted at its true poses, against the
   map of the same flight without gain drift.
3. ms per ``add`` at 640x480 and 1920x1080, video-like motion, the modes interleaved.

Metrics (:mod:`photomap.eval.seams`, grey levels): ``step`` = the exposure step at the seams of
the overwrite map, on the same ground (both frames of each seam pair, times their gains, within
8 px of their seam; texture-free), luminance / mean over channels; ``side`` = the same for pairs
of frames >= 50 apart (survey strips side by side); ``map`` = the luminance step across the seams
in the map itself (texture included); ``sat`` = share of map pixels clipped at 255.

    python tools/bench_exposure.py [--out DIR] [--frames 600] [--trajectory run/trajectory.csv]
                                   [--md docs/benchmarks.md]

With --md, replaces the section between the exposure markers of that file.
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from photomap.config import MosaicConfig
from photomap.core.exposure import joint_gains
from photomap.core.mosaic import TiledMosaic
from photomap.eval.seams import frame_labels, overlap_steps, seam_steps
from photomap.io.trajectory_files import read_trajectory_csv

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tools.report import replace_section  # noqa: E402

MODES = ("none", "gain", "channel_gain", "joint", "joint_channel")
BLENDS = ("overwrite", "feather")


def paint(frames, poses, blend: str, mode: str) -> tuple[TiledMosaic, list[float], list]:
    """A map of ``frames`` at ``poses`` (2x3 or None); ms per add; the gain of each frame."""
    m = TiledMosaic(MosaicConfig(blend=blend, exposure=mode if mode in ("gain", "channel_gain") else "none"))
    given = [None] * len(frames)
    if mode.startswith("joint"):
        keep = [k for k, M in enumerate(poses) if M is not None]
        fitted = joint_gains([frames[k] for k in keep], [poses[k] for k in keep], per_channel=mode == "joint_channel")
        for k, g in zip(keep, fitted):
            given[k] = g
    ms, gains = [], []
    for f, M, g in zip(frames, poses, given):
        if M is None:
            gains.append(None)
            continue
        t0 = time.perf_counter()
        m.add(f, M, gain=g)
        ms.append(1000 * (time.perf_counter() - t0))
        gains.append(None if m.last_gain is None else m.last_gain.copy())
    return m, ms, gains


def measure(m: TiledMosaic, frames, poses, gains, frame_size, bounds=None) -> dict:
    image, alpha, origin = m.render(bounds=bounds)
    box = (*origin, image.shape[1], image.shape[0])
    labels = frame_labels(poses, frame_size, box, m.border)
    step = overlap_steps(frames, poses, gains, labels, origin)
    side = overlap_steps(frames, poses, gains, labels, origin, min_index_gap=50)
    g = np.array([np.mean(x) for x in gains if x is not None] or [1.0])
    covered = alpha > 0
    sat = float(((image >= 255).any(axis=-1) if image.ndim == 3 else image >= 255)[covered].mean())
    return dict(step=step[0], colour=step[1], pairs=step[2], side=side[0], side_pairs=side[2],
                map=seam_steps(image, labels).level_step, sat=100 * sat, gmin=g.min(), gmax=g.max())


def save_png(m: TiledMosaic, path: Path, px: int = 1200) -> None:
    b = m.bounds()
    image, alpha, _ = m.render(scale=min(1.0, px / max(b[2], b[3])))
    cv2.imwrite(str(path), np.dstack([image, alpha]))


def sift_poses(images: list[np.ndarray]) -> list[np.ndarray | None]:
    """Poses of ``images`` in the first one's pixels: each registered (SIFT, ratio test, RANSAC
    similarity) against the earlier posed image with the most inliers."""
    sift = cv2.SIFT_create(4000)
    feats = [sift.detectAndCompute(cv2.cvtColor(i, cv2.COLOR_BGR2GRAY), None) for i in images]
    matcher = cv2.BFMatcher()
    poses: dict[int, np.ndarray] = {0: np.eye(3)}
    for k in range(1, len(images)):
        best = None
        for j in sorted(poses, reverse=True):
            good = [a for a, b in matcher.knnMatch(feats[k][1], feats[j][1], k=2) if a.distance < 0.75 * b.distance]
            if len(good) < 20:
                continue
            pk = np.float32([feats[k][0][a.queryIdx].pt for a in good])
            pj = np.float32([feats[j][0][a.trainIdx].pt for a in good])
            A, inl = cv2.estimateAffinePartial2D(pk, pj, method=cv2.RANSAC, ransacReprojThreshold=3)
            n = 0 if inl is None else int(inl.sum())
            if A is not None and n >= 30 and (best is None or n > best[0]):
                best = (n, poses[j] @ np.vstack([A, [0, 0, 1]]))
        if best is not None:
            poses[k] = best[1]
    return [poses[k][:2] if k in poses else None for k in range(len(images))]


def table(rows: list[dict]) -> str:
    out = ["| set | blend | exposure | step (lum/colour) | side seams | map step | err vs truth | sat % | gains |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        side = f"{r['side']:.2f}" if r["side_pairs"] else "-"
        err = f"{r['err']:.2f}" if "err" in r else "-"
        out.append(f"| {r['set']} | {r['blend']} | {r['exposure']} | {r['step']:.2f} / {r['colour']:.2f} | {side} | "
                   f"{r['map']:.2f} | {err} | {r['sat']:.2f} | {r['gmin']:.2f}..{r['gmax']:.2f} |")
    return "\n".join(out)


def brighton(out: Path, data: Path, trajectory: Path | None) -> list[dict]:
    files = sorted((data / "brighton_beach" / "images").glob("*.jpg"))
    images = [cv2.imread(str(f)) for f in files]
    size = (images[0].shape[1], images[0].shape[0])
    sets = {"brighton-sift": sift_poses(images)}
    if trajectory is not None:
        rows = read_trajectory_csv(trajectory)
        for seg in sorted({r.segment for r in rows if r.M is not None}):
            poses = [r.M if r.M is not None and r.segment == seg else None for r in rows]
            if sum(p is not None for p in poses) > 1:
                sets[f"brighton-replay-seg{seg}"] = poses
    results = []
    for name, poses in sets.items():
        for blend in BLENDS:
            for mode in MODES:
                m, ms, gains = paint(images, poses, blend, mode)
                results.append(dict(set=name, blend=blend, exposure=mode, ms=float(np.median(ms)),
                                    **measure(m, images, poses, gains, size)))
                save_png(m, out / f"{name}-{blend}-{mode}.png")
                print(table(results[-1:]).splitlines()[-1], flush=True)
    return results


def simulated(out: Path, n_frames: int) -> list[dict]:
    from photomap.sim.flight import simulate_sequence
    from photomap.sim.terrain import load_terrain, valid_mask

    terrain = load_terrain("aukerman", zoom=2.0)
    valid = valid_mask(terrain)
    kw = dict(fps=10.0, gsd=0.225, pattern="lawnmower", speed=6.0, yaw_mode="heading", altitude=(40.0, 40.0),
              scale_rate=0.0, noise=1.0, period_s=20.0, side_overlap=0.3)
    drift = simulate_sequence(terrain, n_frames, (480, 640), seed=3, valid=valid, gain_drift=0.3, **kw)
    clean = simulate_sequence(terrain, n_frames, (480, 640), seed=3, valid=valid, **kw)
    s = 0.5 / float(np.median(drift.truth.scale))  # map at half the frames' resolution
    poses = [(np.diag([s, s, 1.0]) @ H)[:2] for H in drift.truth.H]
    results = []
    for blend in BLENDS:
        truth, _, _ = paint(clean.frames, poses, blend, "none")
        t_img, t_alpha, t_org = truth.render()
        bounds = (*t_org, t_img.shape[1], t_img.shape[0])
        save_png(truth, out / f"sim-{blend}-truth.png")
        for mode in ("none", "gain", "channel_gain"):
            m, ms, gains = paint(drift.frames, poses, blend, mode)
            row = dict(set=f"sim-{n_frames}", blend=blend, exposure=mode, ms=float(np.median(ms)),
                       **measure(m, drift.frames, poses, gains, (640, 480), bounds))
            img, alpha, _ = m.render(bounds=bounds)
            both = (alpha > 0) & (t_alpha > 0)
            iv, tv = img[both].astype(np.float64), t_img[both].astype(np.float64)
            level = (iv * tv).sum() / (iv * iv).sum()  # one global gain: the map's level is free
            row["err"] = float(np.abs(np.clip(iv * level, 0, 255) - tv).mean())
            results.append(row)
            save_png(m, out / f"sim-{blend}-{mode}.png")
            print(table(results[-1:]).splitlines()[-1], flush=True)
    return results


def timing(frames: int = 150, repeats: int = 3) -> list[str]:
    """ms per add with video-like motion (a few pixels per frame), 640x480 and 1920x1080: the
    modes interleaved frame by frame (so that a busy machine slows them alike), medians."""
    rng = np.random.default_rng(0)
    lines = []
    modes = ("none", "gain", "channel_gain")
    for w, h in ((640, 480), (1920, 1080)):
        ground = cv2.GaussianBlur(rng.integers(0, 256, (h + 400, w + 800, 3), np.uint8), (0, 0), 3)
        for blend in BLENDS:
            ms: dict[str, list[float]] = {mode: [] for mode in modes}
            for _ in range(repeats):
                maps = {mode: TiledMosaic(MosaicConfig(blend=blend, exposure=mode)) for mode in modes}
                for k in range(frames):
                    x = int(6 * k) % 800
                    f = np.ascontiguousarray(ground[200:200 + h, x:x + w])
                    f = cv2.convertScaleAbs(f, alpha=1.0 + 0.2 * math.sin(k / 20))  # auto exposure
                    M = np.array([[1.0, 0.0, x + 0.3], [0.0, 1.0, 0.6]])
                    for mode, m in maps.items():
                        t0 = time.perf_counter()
                        m.add(f, M)
                        ms[mode].append(1000 * (time.perf_counter() - t0))
            res = {mode: float(np.median(v)) for mode, v in ms.items()}
            lines.append(f"{w}x{h} {blend}: " + ", ".join(f"{k} {v:.2f} ms" for k, v in res.items())
                         + f" (gain adds {res['gain'] - res['none']:+.2f} ms, x{res['gain'] / res['none']:.2f})")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("bench-exposure"))
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PHOTOMAP_DATA", "/work/shared/data")))
    ap.add_argument("--trajectory", type=Path, help="trajectory.csv of a photomap replay of the Brighton stills")
    ap.add_argument("--frames", type=int, default=600, help="frames of the simulated flight (0: skip)")
    ap.add_argument("--no-timing", action="store_true")
    ap.add_argument("--md", type=Path, help="markdown file whose exposure section gets the results")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = brighton(args.out, args.data, args.trajectory)
    if args.frames:
        rows += simulated(args.out, args.frames)
    text = ["## Exposure compensation", "",
            f"Written by `python -m tools.bench_exposure --frames {args.frames} --md docs/benchmarks.md` on "
            f"{datetime.date.today().isoformat()} ({platform.machine()}). Grey levels. *step*: the exposure step at the seams of the overwrite map, on the same ground "
            "(both frames of each pair meeting at a seam, times their gains, within 8 px of the seam: "
            "texture-free), luminance / mean of the channels; *side seams*: the same for frames >= 50 apart "
            "(survey strips side by side); *map step*: the luminance step across the seams of the map itself "
            "(texture included); *err vs truth*: mean |map - map of the flight without gain drift| after one "
            "global gain; *sat*: map pixels clipped at 255. none/gain/channel_gain: `mosaic.exposure` "
            "(sequential, live); joint/joint_channel: `joint_gains` over all frames, then painted with them. "
            "Brighton: 18 DJI stills posed by SIFT (all) or by the iFMI replay (its segments).", "",
            table(rows)]
    if not args.no_timing:
        text += ["", f"ms per `add` ({platform.machine()}, {os.cpu_count()} cores shared with other jobs: "
                     "absolute times are inflated, compare within a line):", ""]
        text += [f"- {line}" for line in timing()]
    print("\n".join(text))
    if args.md:
        replace_section(args.md, "exposure", "\n".join(text))


if __name__ == "__main__":
    main()
