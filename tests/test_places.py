"""Place signatures rank old keyframes for a join: truth is the simulator's terrain (views of
the same ground, shifted and turned, against views of other ground) and the cosine similarity
written out pair by pair."""

from __future__ import annotations

import cv2
import numpy as np

from photomap.core.places import place_signature, place_similarities
from photomap.sim.terrain import load_terrain


def view(terrain: np.ndarray, cx: float, cy: float, angle_deg: float, size: int = 160) -> np.ndarray:
    """A ``size`` x ``size`` grey view of ``terrain`` centred at (cx, cy), turned by ``angle_deg``."""
    M = cv2.getRotationMatrix2D((cx, cy), angle_deg, 1.0)
    M[:, 2] += (size / 2 - cx, size / 2 - cy)
    gray = cv2.cvtColor(terrain, cv2.COLOR_BGR2GRAY) if terrain.ndim == 3 else terrain
    return cv2.warpAffine(gray, M, (size, size), flags=cv2.INTER_LINEAR)


def cosine_best_shift(a: np.ndarray, b: np.ndarray, max_shift: int = 2) -> float:
    best = -1.0
    n = a.shape[0]
    for s in range(-max_shift, max_shift + 1):
        x, y = (a[s:], b[:n - s]) if s >= 0 else (a[:n + s], b[-s:])
        if np.linalg.norm(x) > 0 and np.linalg.norm(y) > 0:
            best = max(best, float(np.sum(x.astype(float) * y)) / (np.linalg.norm(x) * np.linalg.norm(y)))
    return best


def test_similarities_are_the_best_shifted_cosines_pair_by_pair():
    rng = np.random.default_rng(3)
    a = rng.random((24, 12), np.float32)
    others = rng.random((7, 24, 12), np.float32)
    others[2] = np.roll(a, 1, axis=0)  # a's rings shifted by one: a scale change
    others[5] = 0.0  # no signal
    got = place_similarities(a, others)
    assert got.shape == (7,)
    np.testing.assert_allclose(got, [cosine_best_shift(a, b) for b in others], atol=1e-6)
    assert got[5] == -1.0 and got[2] > 0.99


def test_the_same_ground_turned_and_shifted_ranks_first():
    terrain = load_terrain("aukerman", zoom=3)
    h, w = terrain.shape[:2]
    here = place_signature(view(terrain, w * 0.4, h * 0.4, 0.0))
    same = place_signature(view(terrain, w * 0.4 + 12, h * 0.4 - 9, 35.0))  # the same ground, turned
    elsewhere = [place_signature(view(terrain, w * fx, h * fy, 35.0))
                 for fx, fy in ((0.15, 0.2), (0.7, 0.3), (0.25, 0.75), (0.75, 0.75))]
    scores = place_similarities(here, np.stack([*elsewhere, same]))
    assert int(np.argmax(scores)) == len(elsewhere)
