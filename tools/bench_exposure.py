"""Exposure compensation of the photo map (photomap issue 10, item 7): steps at frame edges.

1. Brighton beach (18 real DJI stills on auto exposure): the stills posed by SIFT + RANSAC
   similarities (evaluation only; the iFMI replay poses 10 of the 18) or by the ``trajectory.csv``
   of a ``photomap replay`` run (``--trajectory``), painted with ``mosaic.exposure`` none, gain and
   channel_gain, blends overwrite and feather: the brightness step across frame edges
   (:mod:`photomap.eval.seams`), ms per ``add``, and downscaled PNGs of the maps.
2. A simulated video (aukerman, lawn-mower, ``gain_drift``) painted at its true poses: the step
   across frame edges and the map's error against the map of the same flight without gain drift;
   ms per ``add`` at 640x480 and 1920x1080.

    python tools/bench_exposure.py [--out DIR] [--frames 600] [--trajectory run/trajectory.csv]
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import cv2
import numpy as np

from photomap.config import MosaicConfig
from photomap.core.mosaic import TiledMosaic
from photomap.eval.seams import frame_labels, seam_steps
from photomap.io.trajectory_files import read_trajectory_csv

MODES = ("none", "gain", "channel_gain")
BLENDS = ("overwrite", "feather")


def paint(frames, poses, blend: str, exposure: str) -> tuple[TiledMosaic, list[float], list]:
    """A map of ``frames`` at ``poses`` (2x3 or None); ms per add; the gain of each frame."""
    m = TiledMosaic(MosaicConfig(blend=blend, exposure=exposure))
    ms, gains = [], []
    for f, M in zip(frames, poses):
        if M is None:
            gains.append(None)
            continue
        t0 = time.perf_counter()
        m.add(f, M)
        ms.append(1000 * (time.perf_counter() - t0))
        gains.append(None if m.last_gain is None else m.last_gain.copy())
    return m, ms, gains


def steps(m: TiledMosaic, poses, frame_size):
    image, _, origin = m.render()
    bounds = (*origin, image.shape[1], image.shape[0])
    return seam_steps(image, frame_labels(poses, frame_size, bounds, m.border))


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
    out = ["| set | blend | exposure | level step | pixel step | texture | ms/add (median) |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['set']} | {r['blend']} | {r['exposure']} | {r['level']:.2f} | {r['pixel']:.2f} | "
                   f"{r['texture']:.2f} | {r['ms']:.2f} |" + (f" err vs truth {r['err']:.2f}" if 'err' in r else ""))
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
                s = steps(m, poses, size)
                results.append(dict(set=name, blend=blend, exposure=mode, level=s.level_step, pixel=s.pixel_step,
                                    texture=s.texture, ms=float(np.median(ms))))
                save_png(m, out / f"{name}-{blend}-{mode}.png")
                if mode != "none" and blend == "overwrite":
                    print(name, mode, "gains:", " ".join("-" if g is None else "/".join(f"{v:.3f}" for v in g)
                                                         for g in gains))
    return results


def simulated(out: Path, n_frames: int) -> list[dict]:
    from photomap.sim.flight import simulate_sequence
    from photomap.sim.terrain import load_terrain, valid_mask

    terrain = load_terrain("aukerman", zoom=2.0)
    kw = dict(fps=10.0, gsd=0.225, pattern="lawnmower", speed=6.0, yaw_mode="heading", altitude=(40.0, 40.0),
              scale_rate=0.0, noise=1.0, period_s=20.0, side_overlap=0.3)
    drift = simulate_sequence(terrain, n_frames, (480, 640), seed=3, valid=valid_mask(terrain), gain_drift=0.3, **kw)
    clean = simulate_sequence(terrain, n_frames, (480, 640), seed=3, valid=valid_mask(terrain), **kw)
    s = 1.0 / float(np.median(drift.truth.scale))  # map pixels per terrain pixel: about frame resolution
    poses = [(np.diag([s, s, 1.0]) @ H)[:2] for H in drift.truth.H]
    size = (640, 480)
    results = []
    for blend in BLENDS:
        truth, _, _ = paint(clean.frames, poses, blend, "none")
        t_img, t_alpha, t_org = truth.render()
        for mode in MODES:
            m, ms, gains = paint(drift.frames, poses, blend, mode)
            st = steps(m, poses, size)
            img, alpha, org = m.render(bounds=(*t_org, t_img.shape[1], t_img.shape[0]))
            both = (alpha > 0) & (t_alpha > 0)
            err = float(np.abs(img.astype(np.float32) - t_img.astype(np.float32))[both].mean())
            results.append(dict(set=f"sim-{n_frames}", blend=blend, exposure=mode, level=st.level_step,
                                pixel=st.pixel_step, texture=st.texture, ms=float(np.median(ms)), err=err))
            save_png(m, out / f"sim-{blend}-{mode}.png")
        save_png(truth, out / f"sim-{blend}-truth.png")
    return results


def timing(frames: int = 150, repeats: int = 3) -> list[str]:
    """ms per add with video-like motion (a few pixels per frame), 640x480 and 1920x1080: the
    modes interleaved frame by frame (so that a busy machine slows them alike), medians."""
    rng = np.random.default_rng(0)
    lines = []
    for w, h in ((640, 480), (1920, 1080)):
        ground = cv2.GaussianBlur(rng.integers(0, 256, (h + 400, w + 800, 3), np.uint8), (0, 0), 3)
        for blend in BLENDS:
            ms: dict[str, list[float]] = {mode: [] for mode in MODES}
            for _ in range(repeats):
                maps = {mode: TiledMosaic(MosaicConfig(blend=blend, exposure=mode)) for mode in MODES}
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
                         + f" (gain adds {res['gain'] - res['none']:+.2f} ms)")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("bench-exposure"))
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PHOTOMAP_DATA", "/work/shared/data")))
    ap.add_argument("--trajectory", type=Path, help="trajectory.csv of a photomap replay of the Brighton stills")
    ap.add_argument("--frames", type=int, default=600, help="frames of the simulated flight (0: skip)")
    ap.add_argument("--no-timing", action="store_true")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = brighton(args.out, args.data, args.trajectory)
    if args.frames:
        rows += simulated(args.out, args.frames)
    print(table(rows))
    if not args.no_timing:
        print("\n".join(timing()))


if __name__ == "__main__":
    main()
