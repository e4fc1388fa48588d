"""Objects standing above the ground (box roofs, tree crowns): a second depth layer with parallax.

The ground truth stays the ground plane; objects are what a real flight sees on top of it and
what breaks the single-plane model: their tops are closer to the camera, so they look larger
and move faster than the ground beneath them.

Geometry
--------
All object tops lie on one plane ``height_m`` above the ground. The layer is an RGBA image on
the terrain's pixel grid (x east, y south, ``gsd`` metres per pixel): pixel ``(x, y)`` of the
layer is the top surface point above terrain pixel ``(x, y)``. For a pinhole camera whose nadir
point is ``(cam_x, cam_y)`` at ``alt_px`` terrain pixels, the frame -> layer homography is the
ground one with the camera brought down by the object height::

    H_top = S @ H_ground,  S = scaling of terrain coordinates about (cam_x, cam_y) by (A - h) / A

with ``A = alt_px`` and ``h = height_px`` (exact for any attitude: the ray through a pixel meets
the plane ``h`` above the ground at ``(A - h) / A`` of its ground offset from the nadir point).
So the top of an object appears ``A / (A - h)`` times larger than the ground and displaced away
from the nadir point. It occludes the ground beneath it. Walls are drawn simply: ``n`` copies of
the footprint at heights ``h k / n`` (``k = 0..n-1``), darkened, under the top.

Colours are stored premultiplied by alpha (uint8), so that pyramid filtering is correct.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from photomap.errors import InputError
from photomap.sim.flight import Truth, apply_homography, build_pyramid, render_view

# BGR top colours: roofs (terracotta, grey, dark grey, brown, light concrete) and tree greens
ROOF_COLOURS = np.array([[60, 80, 170], [120, 120, 125], [70, 72, 78], [50, 75, 110], [175, 180, 180]], np.float32)
CROWN_COLOURS = np.array([[25, 62, 30], [40, 88, 72], [30, 76, 45]], np.float32)


@dataclass(frozen=True)
class SceneObject:
    """One object: ``kind`` ``box`` (a rectangle of ``length`` x ``width`` turned by ``angle_deg``,
    counter-clockwise in the image = clockwise on the map) or ``crown`` (a disc of diameter
    ``length``), centred on terrain pixel ``(cx, cy)``; sizes in terrain pixels."""

    kind: str
    cx: float
    cy: float
    length: float
    width: float
    angle_deg: float
    colour: tuple[float, float, float]


def random_objects(shape: tuple[int, int], gsd: float, *, cover: float, size_m: tuple[float, float] = (4.0, 12.0),
                   seed: int = 0, crowns: float = 0.35) -> list[SceneObject]:
    """Objects scattered uniformly over a terrain of ``shape = (h, w)`` pixels.

    ``cover`` is the expected fraction of the ground under object tops (overlaps merge),
    ``size_m`` the range of box lengths and crown diameters in metres (a box's width is 0.5-1
    times its length), ``crowns`` the fraction of objects that are tree crowns.
    """
    if not 0.0 <= cover < 1.0:
        raise InputError(f"object cover must be in 0..1, got {cover}")
    lo, hi = float(size_m[0]), float(size_m[1])
    if not 0 < lo <= hi:
        raise InputError(f"object size range must satisfy 0 < min <= max metres, got {lo}:{hi}")
    rng = np.random.default_rng([seed, 20])
    h, w = shape
    lo_px, hi_px = lo / gsd, hi / gsd
    mean_area = 0.75 * (lo_px * lo_px + lo_px * hi_px + hi_px * hi_px) / 3.0 * 0.85
    n = int(rng.poisson(cover * h * w / max(mean_area, 1e-9))) if cover > 0 else 0
    out = []
    for _ in range(n):
        length = rng.uniform(lo_px, hi_px)
        cx, cy = rng.uniform(0, w - 1), rng.uniform(0, h - 1)
        if rng.uniform() < crowns:
            out.append(SceneObject("crown", cx, cy, length, length, 0.0,
                                   tuple(CROWN_COLOURS[rng.integers(len(CROWN_COLOURS))].tolist())))
        else:
            out.append(SceneObject("box", cx, cy, length, length * rng.uniform(0.5, 1.0), rng.uniform(0, 180),
                                   tuple(ROOF_COLOURS[rng.integers(len(ROOF_COLOURS))].tolist())))
    return out


def draw_objects(shape: tuple[int, int], objects: list[SceneObject], seed: int = 0,
                 kinds: tuple[str, ...] = ("box", "crown")) -> np.ndarray:
    """The layer image of the ``objects`` of the given ``kinds``: uint8 ``(h, w, 4)``, BGR
    premultiplied by alpha, alpha 255 on the tops (anti-aliased edges, ~1 px), 0 elsewhere.

    Boxes have a gable (the two halves along their length differ in brightness, 1 and 0.85)
    and a slightly darker rim (0.92); crowns are brighter in the middle; both carry a fine
    random texture (~2.5 % rms). Walls (:class:`ObjectScene`) are darker still (0.2-0.6).
    """
    h, w = shape
    rng = np.random.default_rng([seed, 21])
    acc = np.zeros((h, w, 4), np.float32)
    for ob in objects:
        if ob.kind not in kinds:
            continue
        r = 0.5 * math.hypot(ob.length, ob.width) + 2.0
        x0, x1 = max(int(ob.cx - r), 0), min(int(ob.cx + r) + 2, w)
        y0, y1 = max(int(ob.cy - r), 0), min(int(ob.cy + r) + 2, h)
        if x1 <= x0 or y1 <= y0:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float32)
        dx, dy = xx - ob.cx, yy - ob.cy
        tex = 1.0 + 0.07 * rng.standard_normal(dx.shape).astype(np.float32)
        tex = cv2.GaussianBlur(tex, (0, 0), 0.8)
        if ob.kind == "crown":
            rad = ob.length / 2.0
            dist = np.hypot(dx, dy)
            inside = rad - dist
            shade = 1.25 - 0.55 * np.clip(dist / rad, 0, 1) ** 2
        else:
            a = math.radians(ob.angle_deg)
            u = dx * math.cos(a) + dy * math.sin(a)          # along the length
            v = -dx * math.sin(a) + dy * math.cos(a)         # across
            inside = np.minimum(ob.length / 2.0 - np.abs(u), ob.width / 2.0 - np.abs(v))
            shade = np.where(v >= 0, 1.0, 0.85) * np.where(inside < 2.0, 0.92, 1.0)
        alpha = np.clip(inside + 0.5, 0.0, 1.0)
        colour = np.asarray(ob.colour, np.float32) * (shade * tex)[..., None]
        a3 = alpha[..., None]
        region = acc[y0:y1, x0:x1]
        region[..., :3] = region[..., :3] * (1.0 - a3) + colour * a3
        region[..., 3] = region[..., 3] * (1.0 - alpha) + alpha
    layer = np.empty((h, w, 4), np.uint8)
    layer[..., :3] = np.clip(acc[..., :3] + 0.5, 0, 255).astype(np.uint8)
    layer[..., 3] = np.clip(acc[..., 3] * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return layer


def top_homography(h: np.ndarray, cam_x: float, cam_y: float, alt_px: float, height_px: float) -> np.ndarray:
    """Frame pixels -> layer pixels of the plane ``height_px`` above the ground, from the
    ground homography ``h`` of a camera at ``alt_px`` above nadir point ``(cam_x, cam_y)``."""
    if not 0 <= height_px < alt_px:
        raise InputError(f"object height ({height_px:.1f} px) must be below the camera ({alt_px:.1f} px)")
    f = (alt_px - height_px) / alt_px
    s = np.array([[f, 0.0, (1.0 - f) * cam_x], [0.0, f, (1.0 - f) * cam_y], [0.0, 0.0, 1.0]])
    m = s @ h
    return m / m[2, 2]


def _over(dst: np.ndarray, premult: np.ndarray) -> None:
    """Composite premultiplied BGRA float ``premult`` over BGR float ``dst`` in place."""
    a = np.clip(premult[..., 3:4] * np.float32(1.0 / 255.0), 0.0, 1.0)
    dst *= 1.0 - a
    dst += np.maximum(premult[..., :3], 0.0)


def box_corners(ob: SceneObject) -> np.ndarray:
    """The four corners ``(4, 2)`` of a box's footprint in terrain pixels, in order around it."""
    a = math.radians(ob.angle_deg)
    along, across = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    signs = ((1, 1), (1, -1), (-1, -1), (-1, 1))
    return np.array([[ob.cx, ob.cy] + su * ob.length / 2 * along + sv * ob.width / 2 * across for su, sv in signs])


class ObjectScene:
    """Objects standing on the ground, ready to render over the ground views of a flight.

    Parameters
    ----------
    objects : the objects (their tops are drawn from ``layer``, the walls of the boxes from
        their corners).
    layer : uint8 ``(h, w, 4)`` premultiplied BGRA of the tops on the terrain grid
        (:func:`draw_objects`); None = draw it from ``objects`` (needs ``shape``).
    height_m : height of the tops above the ground, metres. gsd : metres per terrain pixel.
    walls : draw the boxes' walls (flat-shaded quads; tree crowns have none).
    max_scale : largest terrain px per frame px of the flight (pyramid depth).
    """

    def __init__(self, objects: list[SceneObject], height_m: float, gsd: float, *,
                 layer: np.ndarray | None = None, shape: tuple[int, int] | None = None, walls: bool = True,
                 max_scale: float = 1.0, seed: int = 0) -> None:
        if height_m <= 0 or gsd <= 0:
            raise InputError(f"object height and gsd must be positive, got {height_m}, {gsd}")
        if layer is None:
            if shape is None:
                raise ValueError("give the layer or the terrain shape")
            layer = draw_objects(shape, objects, seed)
        self.objects = list(objects)
        self.height_m = float(height_m)
        self.gsd = float(gsd)
        self.pyramid = build_pyramid(layer, max_scale * 1.2)
        boxes = [ob for ob in self.objects if ob.kind == "box"] if walls else []
        self._corners = np.array([box_corners(ob) for ob in boxes]).reshape(-1, 4, 2)
        self._colours = np.array([ob.colour for ob in boxes], float).reshape(-1, 3)

    def composite(self, view: np.ndarray, h: np.ndarray, cam_x: float, cam_y: float, alt_m: float) -> np.ndarray:
        """Draw the objects over the float BGR ground ``view`` rendered with ``h``; returns it."""
        fh, fw = view.shape[:2]
        alt_px, hgt_px = alt_m / self.gsd, self.height_m / self.gsd
        h_top = top_homography(h, cam_x, cam_y, alt_px, hgt_px)
        if len(self._corners):
            self._draw_walls(view, h, h_top, cam_x, cam_y)
        _over(view, render_view(self.pyramid, h_top, (fh, fw)))
        return view

    def _draw_walls(self, view: np.ndarray, h: np.ndarray, h_top: np.ndarray, cam_x: float, cam_y: float) -> None:
        """Walls: one flat-shaded quad per box side facing the camera (whose centre is above
        ``(cam_x, cam_y)``), from its ground edge to its top edge."""
        fh, fw = view.shape[:2]
        flat = self._corners.reshape(-1, 2)
        ground = apply_homography(np.linalg.inv(h), flat).reshape(-1, 4, 2)
        top = apply_homography(np.linalg.inv(h_top), flat).reshape(-1, 4, 2)
        lo = np.minimum(ground.min(axis=1), top.min(axis=1))
        hi = np.maximum(ground.max(axis=1), top.max(axis=1))
        seen = (hi[:, 0] >= 0) & (hi[:, 1] >= 0) & (lo[:, 0] <= fw - 1) & (lo[:, 1] <= fh - 1)
        if not seen.any():
            return
        canvas = np.zeros((fh, fw, 4), np.uint8)        # premultiplied BGRA (LINE_AA blends into it)
        frac = 16                                       # vertices in 1/16 px (shift=4 fractional bits)
        for b in np.flatnonzero(seen):
            c = self._corners[b]
            centre = c.mean(axis=0)
            for e in range(4):
                f = (e + 1) % 4
                mid = (c[e] + c[f]) / 2.0
                normal = np.array([c[f, 1] - c[e, 1], -(c[f, 0] - c[e, 0])])
                normal /= max(np.linalg.norm(normal), 1e-9)
                if normal @ (mid - centre) < 0:
                    normal = -normal                                            # outward
                if normal @ ([cam_x, cam_y] - mid) <= 0:
                    continue                                                    # faces away
                light = 0.4 + 0.2 * float(normal @ [0.6, -0.8])                 # sun from the north-east
                quad = np.array([ground[b, e], ground[b, f], top[b, f], top[b, e]])
                colour = (*(self._colours[b] * light).tolist(), 255.0)
                cv2.fillConvexPoly(canvas, np.rint(quad * frac).astype(np.int32), colour,
                                   lineType=cv2.LINE_AA, shift=4)
        _over(view, canvas.astype(np.float32))

    def overlay(self, truth: Truth):
        """A callable ``(k, view) -> view`` for :func:`photomap.sim.flight.iter_frames`."""
        def draw(k: int, view: np.ndarray) -> np.ndarray:
            return self.composite(view, truth.H[k], float(truth.cam_x[k]), float(truth.cam_y[k]),
                                  float(truth.alt_m[k]))
        return draw
