"""Hot spots planted at known terrain positions: the truth of the hazard detector.

A hot spot is a small disc painted into the terrain image before the flight is rendered, so
every frame that sees the ground there sees it (and registration sees it as part of the ground).
``thermal`` turns the whole terrain into a thermal-looking grey image first: the ground a cool,
low-contrast grey (the terrain's luminance squeezed into 45-115), the spots hot
(a flat top of ``peak`` grey with a soft rim), as a thermal camera shows seats of fire. ``visible``
keeps the colour terrain and paints fire-orange spots (for the colour-anomaly detector).

Positions: spread along the flight (at evenly spaced frames, near the frame's centre), at least
``min_separation_m`` apart, so each is seen by many consecutive frames. The truth, in terrain
pixels (x east, y south; OpenCV pixel centres) and WGS84, goes to ``hotspots.csv``
(:func:`write_hotspots_csv`).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from photomap.errors import InputError

HOTSPOT_STYLES = ("thermal", "visible")
HOTSPOT_COLUMNS = ("id", "x_px", "y_px", "lat", "lon", "radius_m", "peak")
FIRE_BGR = (40.0, 150.0, 255.0)  # the core colour of a visible spot (orange)


@dataclass(frozen=True)
class HotSpot:
    """One planted spot: centre in terrain pixels, radius in metres, peak grey level."""

    id: int
    x: float
    y: float
    radius_m: float
    peak: float


def thermal_terrain(img: np.ndarray) -> np.ndarray:
    """A thermal-looking version of a BGR terrain: grey (three equal channels), the ground's
    luminance squeezed linearly so that its 0.5th..99.5th percentiles span 55..105 (clipped to
    45..115: ground well below a fire's heat)."""
    lum = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
    sample = lum[:: max(1, lum.shape[0] // 512), :: max(1, lum.shape[1] // 512)]
    lo, hi = np.percentile(sample, [0.5, 99.5])
    grey = 55.0 + 50.0 * (lum - lo) / max(float(hi - lo), 1.0)
    grey = np.clip(grey, 45.0, 115.0).astype(np.uint8)
    return cv2.merge([grey, grey, grey])


def place_hotspots(centres_x: np.ndarray, centres_y: np.ndarray, n: int, gsd: float, *,
                   radius_m: tuple[float, float] = (0.6, 1.0), min_separation_m: float = 12.0,
                   spread_px: float = 100.0, peak: float = 250.0, shape: tuple[int, int] | None = None,
                   seed: int = 0) -> list[HotSpot]:
    """``n`` spots near the flight's frame centres ``centres_x/y`` (terrain px, in frame order):
    at evenly spaced frames, offset up to ``spread_px`` from the centre, at least
    ``min_separation_m`` apart (a candidate too close to an earlier spot is moved to the next
    frame). ``shape`` = (h, w) keeps them inside the terrain. Fewer than ``n`` is an error."""
    if n <= 0:
        return []
    rng = np.random.default_rng([seed, 36])
    count = len(centres_x)
    sep_px = min_separation_m / gsd
    spots: list[HotSpot] = []
    order = np.linspace(0.1 * count, 0.9 * count, n).astype(int).tolist()
    tries = 0
    k = 0
    while len(spots) < n and tries < 50 * n:
        tries += 1
        i = order[k] if k < len(order) else int(rng.integers(0, count))
        x = float(centres_x[i] + rng.uniform(-spread_px, spread_px))
        y = float(centres_y[i] + rng.uniform(-spread_px, spread_px))
        if shape is not None and not (20 <= x < shape[1] - 20 and 20 <= y < shape[0] - 20):
            continue
        if any(np.hypot(x - s.x, y - s.y) < sep_px for s in spots):
            if k < len(order):
                order[k] = min(order[k] + max(1, count // (4 * n)), count - 1)
            continue
        spots.append(HotSpot(len(spots) + 1, x, y, float(rng.uniform(*radius_m)), float(peak)))
        k += 1
    if len(spots) < n:
        raise InputError(f"cannot place {n} hot spots {min_separation_m:g} m apart along this flight "
                         f"(placed {len(spots)}): fewer spots or a longer flight")
    return spots


def paint_hotspots(img: np.ndarray, spots: list[HotSpot], gsd: float, style: str = "thermal") -> np.ndarray:
    """Paint ``spots`` into the BGR terrain ``img`` (a copy): a flat core to 70 % of the radius,
    then a smooth fall-off to the ground at the radius. ``thermal``: grey ``peak``;
    ``visible``: :data:`FIRE_BGR`."""
    if style not in HOTSPOT_STYLES:
        raise InputError(f"hot spot style must be one of {', '.join(HOTSPOT_STYLES)}, got {style!r}")
    out = img.astype(np.float32)
    h, w = img.shape[:2]
    for s in spots:
        r = s.radius_m / gsd
        x0, x1 = max(int(s.x - r) - 2, 0), min(int(s.x + r) + 3, w)
        y0, y1 = max(int(s.y - r) - 2, 0), min(int(s.y + r) + 3, h)
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float32)
        d = np.hypot(xx - s.x, yy - s.y) / max(r, 1e-6)
        a = np.clip((1.0 - d) / 0.3, 0.0, 1.0)
        a = a * a * (3.0 - 2.0 * a)  # smoothstep: 1 in the core, 0 outside the radius
        colour = np.full(3, s.peak, np.float32) if style == "thermal" else np.asarray(FIRE_BGR, np.float32)
        region = out[y0:y1, x0:x1]
        region[:] = region * (1.0 - a[..., None]) + colour * a[..., None]
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def write_hotspots_csv(path: str | Path, spots: list[HotSpot], lat: np.ndarray, lon: np.ndarray) -> None:
    """``hotspots.csv``: one row per spot, columns :data:`HOTSPOT_COLUMNS` (terrain px, WGS84 degrees)."""
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(HOTSPOT_COLUMNS)
        for s, la, lo in zip(spots, np.atleast_1d(lat), np.atleast_1d(lon)):
            w.writerow([s.id, f"{s.x:.4f}", f"{s.y:.4f}", f"{float(la):.9f}", f"{float(lo):.9f}",
                        f"{s.radius_m:.3f}", f"{s.peak:g}"])


def read_hotspots_csv(path: str | Path) -> list[dict]:
    """The rows of a ``hotspots.csv`` as dicts of floats (``id`` an int)."""
    with open(path, newline="", encoding="utf-8") as f:
        return [{k: (int(v) if k == "id" else float(v)) for k, v in row.items()} for row in csv.DictReader(f)]
