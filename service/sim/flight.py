"""A virtual down-looking pinhole camera flown over a terrain image: trajectories and rendering.

Pure computations (arrays in, arrays out); :mod:`photomap.sim.simulate` writes the files.

Frames
------
Terrain pixels: OpenCV convention, x east, y south (image up = north), origin at the centre of
the top-left pixel; one terrain pixel is ``gsd`` metres. The world frame used for the camera
is (east, south, down) in terrain pixels, the ground is the plane z = 0, the camera is at
``(cam_x, cam_y, -alt_m / gsd)``.

Attitude follows MAVLink ``ATTITUDE`` (NED, Z-Y-X Euler angles ``yaw, pitch, roll``). The camera
is fixed to the body and looks down; the image's "up" is the body's forward axis, its x axis
the body's right. So ``yaw`` is the heading (clockwise from north) of the image's up direction,
and for a nadir view the frame->terrain matrix is a similarity whose
``angle_deg = degrees(atan2(H[1,0], H[0,0]))`` equals ``yaw_deg`` (y-down pixels turn a
clockwise heading into a positive OpenCV angle) and whose scale is
``alt_m / (fx * gsd)`` terrain pixels per frame pixel.

``H`` (3x3) maps homogeneous frame pixels to terrain pixels; ``relative_matrix(truth, i, j)``
maps pixels of frame j to pixels of frame i.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

import cv2
import numpy as np

from photomap.errors import InputError
from photomap.geo.georef import enu_from_latlon, latlon_from_enu
from photomap.geometry import pose_scale, similarity_matrix
from photomap.sim.lens import DistortedRender, Overlay

PATTERNS = ("random", "lawnmower", "figure8", "circle")
GRAVITY = 9.80665            # m/s^2
ROLL_RATE_MAX = 90.0         # deg/s: how fast a banking airframe can roll into and out of a turn
YAW_MODES = ("random", "constant", "heading", "fixed")

# --------------------------------------------------------------------------- camera and poses

@dataclass(frozen=True)
class Camera:
    """Pinhole camera: ``fx == fy``, principal point at the image centre (pixels)."""

    width: int
    height: int
    fx: float

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_deg: float) -> Camera:
        """Camera whose horizontal field of view is ``hfov_deg``."""
        if not 1.0 <= hfov_deg <= 170.0:
            raise InputError(f"horizontal field of view must be in 1..170 deg, got {hfov_deg}")
        return cls(int(width), int(height), (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0))

    @property
    def fy(self) -> float:
        return self.fx

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2.0

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2.0

    @property
    def hfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan((self.width / 2.0) / self.fx))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fx, self.cy], [0.0, 0.0, 1.0]])


def camera_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation (3x3) from camera axes (OpenCV: x right, y down, z optical axis) to the
    terrain frame (east, south, down) for a MAVLink attitude in radians."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    r_nb = np.array([[cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],   # body -> NED
                     [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
                     [-sp, sr * cp, cr * cp]])
    r_tn = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])   # NED -> (E, S, D)
    r_bc = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])   # camera -> body
    return r_tn @ r_nb @ r_bc


def pose_homography(camera: Camera, cam_x: float, cam_y: float, alt_px: float,
                    roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    """Exact 3x3 homography frame pixels -> terrain pixels of the ground plane.

    ``(cam_x, cam_y)`` is the terrain point below the camera, ``alt_px`` its height in terrain
    pixels, angles in radians (MAVLink attitude). ``H = [[A,0,x],[0,A,y],[0,0,1]] R K^-1``.
    """
    place = np.array([[alt_px, 0.0, cam_x], [0.0, alt_px, cam_y], [0.0, 0.0, 1.0]])
    h = place @ camera_rotation(roll, pitch, yaw) @ np.linalg.inv(camera.K)
    return h / h[2, 2]


def relative_matrix(truth: Truth, i: int, j: int) -> np.ndarray:
    """3x3 matrix mapping pixels of frame ``j`` to pixels of frame ``i`` (``inv(H_i) @ H_j``)."""
    m = np.linalg.solve(truth.H[i], truth.H[j])
    return m / m[2, 2]


def apply_homography(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Map ``(n, 2)`` points by a 3x3 homography."""
    p = np.asarray(pts, float) @ h[:, :2].T + h[:, 2]
    return p[:, :2] / p[:, 2:3]


def frame_outline(camera: Camera, step: float = 8.0) -> np.ndarray:
    """Points along the border of the frame (pixel centres of the outer pixels), ``(n, 2)``."""
    w, h = camera.width - 1, camera.height - 1
    xs = np.linspace(0, w, max(2, int(w / step) + 1))
    ys = np.linspace(0, h, max(2, int(h / step) + 1))
    return np.concatenate([np.c_[xs, np.zeros_like(xs)], np.c_[xs, np.full_like(xs, h)],
                           np.c_[np.zeros_like(ys), ys], np.c_[np.full_like(ys, w), ys]])


# --------------------------------------------------------------------------- georeference

def pixel_to_latlon(x: np.ndarray, y: np.ndarray, gsd: float, origin_lat: float,
                    origin_lon: float) -> tuple[np.ndarray, np.ndarray]:
    """Terrain pixels -> WGS84 degrees through the local tangent plane at terrain pixel (0, 0).

    East = ``x * gsd`` metres, north = ``-y * gsd`` metres (:func:`photomap.geo.georef.latlon_from_enu`).
    """
    return latlon_from_enu(np.asarray(x, float) * gsd, -np.asarray(y, float) * gsd, origin_lat, origin_lon)


def latlon_to_pixel(lat: np.ndarray, lon: np.ndarray, gsd: float, origin_lat: float,
                    origin_lon: float) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`pixel_to_latlon`."""
    east, north = enu_from_latlon(np.asarray(lat, float), np.asarray(lon, float), origin_lat, origin_lon)
    return east / gsd, -north / gsd


# --------------------------------------------------------------------------- parameters

@dataclass
class Motion:
    """How the camera moves. Rates are peak values; ``period_s`` sets how fast random signals
    wander (yaw rate, roll/pitch, gain). With ``fps=1`` every rate is per frame.

    pattern : ``random`` (smooth random curve), ``lawnmower`` (parallel strips, closed loop
        back to the start) or ``figure8`` (closed, crosses its start twice per loop).
    speed : ground speed, m/s.
    yaw_mode : ``random`` (yaw rate wanders in +-yaw_rate), ``constant`` (spins at yaw_rate),
        ``heading`` (image up follows the direction of travel, turning at most at yaw_rate;
        0 = unlimited), ``fixed`` (yaw0 throughout).
    yaw_rate : deg/s. yaw0 : initial yaw (deg, clockwise from north); None = random.
    altitude : (min, max) metres above the ground; the altitude moves sinusoidally between
        them with a peak relative rate ``scale_rate`` (1/s; d ln(alt)/dt, i.e. the scale change).
    tilt : roll and pitch amplitude, deg (0 = exact nadir, matrices are similarities).
    side_overlap : lawn-mower strip spacing as the overlap of neighbouring footprints (0..1).
    max_bank : coordinated turns of a fixed-wing with the camera fixed to the airframe (no
        gimbal): roll = atan(v * course_rate / g), clipped to +-max_bank deg, rolling at most
        :data:`ROLL_RATE_MAX` deg/s, added to the random ``tilt`` roll. 0 = off.
    pitch_offset : constant pitch added to every frame, deg (nose up > 0; a fixed-wing's
        angle of attack). 0 = off.
    """

    pattern: str = "random"
    speed: float = 8.0
    yaw_mode: str = "random"
    yaw_rate: float = 15.0
    yaw0: float | None = None
    altitude: tuple[float, float] = (50.0, 70.0)
    scale_rate: float = 0.05
    tilt: float = 0.0
    period_s: float = 10.0
    side_overlap: float = 0.3
    max_bank: float = 0.0
    pitch_offset: float = 0.0

    def check(self) -> None:
        if self.pattern not in PATTERNS:
            raise InputError(f"unknown pattern {self.pattern!r} (known: {', '.join(PATTERNS)})")
        if self.yaw_mode not in YAW_MODES:
            raise InputError(f"unknown yaw mode {self.yaw_mode!r} (known: {', '.join(YAW_MODES)})")
        lo, hi = self.altitude
        if not 0 < lo <= hi:
            raise InputError(f"altitude range must satisfy 0 < min <= max, got {lo}:{hi}")
        if self.speed < 0 or self.yaw_rate < 0 or self.scale_rate < 0 or self.period_s <= 0:
            raise InputError("speed, yaw rate and scale rate must be >= 0 and period_s > 0")
        if not 0 <= self.tilt < 45:
            raise InputError(f"tilt must be in 0..45 deg, got {self.tilt}")
        if not 0 <= self.side_overlap < 1:
            raise InputError(f"side overlap must be in 0..1, got {self.side_overlap}")
        if not 0 <= self.max_bank < 80 or not -45 < self.pitch_offset < 45:
            raise InputError(f"max bank must be in 0..80 deg and pitch offset in -45..45 deg, got "
                             f"{self.max_bank}, {self.pitch_offset}")


@dataclass
class Effects:
    """Sensor effects applied after rendering, in this order.

    gain_drift : slow brightness gain change, peak fraction (0.1 = gain in 0.9..1.1).
    blur : Gaussian blur sigma, frame pixels. noise : Gaussian noise sigma, grey levels (0..255).
    jpeg_quality : JPEG round trip at this quality (1..100); 0 = off.
    """

    gain_drift: float = 0.0
    blur: float = 0.0
    noise: float = 0.0
    jpeg_quality: int = 0

    def check(self) -> None:
        if self.gain_drift < 0 or self.blur < 0 or self.noise < 0 or not 0 <= self.jpeg_quality <= 100:
            raise InputError("effects: gain_drift, blur, noise must be >= 0 and jpeg_quality in 0..100")


@dataclass
class Truth:
    """Ground truth of a flight, one entry per frame (arrays of length n).

    t : seconds since frame 0. H : (n, 3, 3) frame -> terrain pixels. x, y : terrain position of
    the frame centre. yaw_deg, roll_deg, pitch_deg : MAVLink attitude. scale : terrain px per
    frame px at nadir (``alt_m / (fx * gsd)``). alt_m : height above ground.
    cam_x, cam_y : terrain point below the camera (differs from x, y only under tilt).
    """

    t: np.ndarray
    H: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw_deg: np.ndarray
    scale: np.ndarray
    roll_deg: np.ndarray
    pitch_deg: np.ndarray
    alt_m: np.ndarray
    cam_x: np.ndarray
    cam_y: np.ndarray

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class Sequence:
    """An in-memory simulated flight: uint8 BGR ``frames`` and their ``truth``."""

    frames: list[np.ndarray]
    truth: Truth
    camera: Camera
    gsd: float
    fps: float
    params: dict = field(default_factory=dict)


def split_params(kwargs: dict) -> tuple[Motion, Effects]:
    """Build :class:`Motion` and :class:`Effects` from keyword arguments named like their fields."""
    mnames = {f.name for f in fields(Motion)}
    enames = {f.name for f in fields(Effects)}
    unknown = set(kwargs) - mnames - enames
    if unknown:
        raise TypeError(f"unknown motion/effect parameters: {', '.join(sorted(unknown))}")
    motion = Motion(**{k: v for k, v in kwargs.items() if k in mnames})
    motion.altitude = (float(motion.altitude[0]), float(motion.altitude[1]))
    effects = Effects(**{k: v for k, v in kwargs.items() if k in enames})
    motion.check()
    effects.check()
    return motion, effects


# --------------------------------------------------------------------------- trajectory

def _smooth_random(t: np.ndarray, period_s: float, rng: np.random.Generator, k: int = 4) -> np.ndarray:
    """Smooth random signal on times ``t``: a sum of sinusoids with periods around
    ``period_s``, scaled so that its peak magnitude over ``t`` is exactly 1."""
    freq = rng.uniform(0.5, 2.0, k) / period_s
    amp = rng.uniform(0.5, 1.0, k)
    phase = rng.uniform(0.0, 2.0 * np.pi, k)
    s = (amp * np.sin(2.0 * np.pi * freq * t[:, None] + phase)).sum(axis=1)
    peak = np.abs(s).max()
    return s / peak if peak > 0 else s


def _distance_inside(valid: np.ndarray) -> np.ndarray:
    """Distance (px) of every pixel to the nearest invalid pixel, outside the image = invalid."""
    return cv2.distanceTransform(np.pad(valid, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]


def _safe_rectangle(valid: np.ndarray, radius: float) -> tuple[float, float, float, float]:
    """Largest axis-aligned rectangle ``(x0, y0, x1, y1)`` of camera positions whose disc of
    ``radius`` terrain pixels lies inside ``valid``. Raises InputError if there is none."""
    safe = _distance_inside(valid) > radius
    h, w = safe.shape
    q = max(1, int(math.ceil(max(h, w) / 256)))
    hq, wq = h // q, w // q
    coarse = safe[: hq * q, : wq * q].reshape(hq, q, wq, q).all(axis=(1, 3))
    best, rect = 0, None
    heights = np.zeros(wq + 1, int)
    for r in range(hq):
        heights[:wq] = np.where(coarse[r], heights[:wq] + 1, 0)
        stack: list[int] = []
        for c in range(wq + 1):
            while stack and heights[stack[-1]] >= heights[c]:
                hgt = heights[stack.pop()]
                left = stack[-1] + 1 if stack else 0
                area = hgt * (c - left)
                if area > best:
                    best, rect = area, (left, r - hgt + 1, c - 1, r)
            stack.append(c)
    if rect is None:
        raise InputError(f"the terrain ({w}x{h} px) has no room for this footprint (radius {radius:.0f} "
                         "terrain px): fly lower, narrow the field of view or give the terrain a larger gsd")
    c0, r0, c1, r1 = rect
    return float(c0 * q), float(r0 * q), float(c1 * q + q - 1), float(r1 * q + q - 1)


def _fillet(poly: np.ndarray, radius: float, n_arc: int = 24) -> np.ndarray:
    """Closed polyline with every corner replaced by a tangent circular arc (radius limited by
    half the adjacent segments). Returns dense points of the closed curve."""
    keep = np.linalg.norm(poly - np.roll(poly, 1, axis=0), axis=1) > 1e-9
    poly = poly[keep] if keep.any() else poly[:1]
    if len(poly) < 2:
        return poly
    out = []
    n = len(poly)
    for i in range(n):
        p0, p1, p2 = poly[i - 1], poly[i], poly[(i + 1) % n]
        d0, d1 = p1 - p0, p2 - p1
        l0, l1 = np.linalg.norm(d0), np.linalg.norm(d1)
        u0, u1 = d0 / l0, d1 / l1
        turn = math.atan2(u0[0] * u1[1] - u0[1] * u1[0], float(u0 @ u1))
        if abs(turn) < 1e-9:
            out.append(p1)
            continue
        cut = min(radius * math.tan(abs(turn) / 2.0), l0 / 2.0, l1 / 2.0)
        r = cut / math.tan(abs(turn) / 2.0)
        a = p1 - u0 * cut
        normal = np.array([-u0[1], u0[0]]) * math.copysign(1.0, turn)
        centre = a + normal * r
        ang0 = math.atan2(*(a - centre)[::-1])
        angs = ang0 + np.linspace(0.0, turn, n_arc)
        out.extend(centre + r * np.c_[np.cos(angs), np.sin(angs)])
    return np.asarray(out)


def _curve(pattern: str, rect: tuple[float, float, float, float], spacing: float,
           rng: np.random.Generator, length_needed: float) -> tuple[np.ndarray, bool]:
    """Dense points of the path inside ``rect`` and whether it is closed."""
    x0, y0, x1, y1 = rect
    cx, cy, hx, hy = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2, (y1 - y0) / 2
    if pattern == "circle":  # a 4096-gon whose perimeter is the flight's length
        r = length_needed / (2 * 4096 * math.sin(math.pi / 4096))
        if r > min(hx, hy):
            raise InputError(f"a circle of {length_needed:.0f} px does not fit the terrain: fewer frames or a lower speed")
        tau = np.linspace(0.0, 2.0 * np.pi, 4097)[:-1]
        return np.c_[cx + r * np.sin(tau), cy - r * np.cos(tau)], True
    if pattern == "figure8":
        tau = np.linspace(0.0, 2.0 * np.pi, 4097)[:-1]
        return np.c_[cx + hx * np.sin(tau), cy + hy * np.sin(2.0 * tau)], True
    if pattern == "lawnmower":
        along_x = hx >= hy
        if not along_x:            # work in a transposed rectangle, swap back at the end
            x0, y0, x1, y1 = y0, x0, y1, x1
        lead = min(spacing, (x1 - x0) / 4)  # the return leg runs at x0, the strips start at x0 + lead
        n = max(2, int(math.ceil((y1 - y0) / max(spacing, 1e-9))) + 1)
        n += n % 2
        ys = np.linspace(y0, y1, n)
        pts = []
        for k, y in enumerate(ys):
            xs = (x0 + lead, x1) if k % 2 == 0 else (x1, x0 + lead)
            pts += [(xs[0], y), (xs[1], y)]
        pts += [(x0, ys[-1]), (x0, ys[0])]
        poly = np.asarray(pts, float)
        poly = np.roll(poly, -1, axis=0)     # start the loop at the beginning of the first strip
        curve = _fillet(poly, radius=(ys[1] - ys[0]) / 2.0)
        curve = np.roll(curve, 1, axis=0)
        return (curve if along_x else curve[:, ::-1]), True
    # random: sums of sinusoids, bounded by the rectangle
    k = 3
    pieces, length, start = [], 0.0, 0.0
    wx, wy = rng.uniform(0.5, 1.5, k), rng.uniform(0.5, 1.5, k)
    ax, ay = rng.uniform(0.3, 1.0, k), rng.uniform(0.3, 1.0, k)
    px, py = rng.uniform(0, 2 * np.pi, k), rng.uniform(0, 2 * np.pi, k)
    while not pieces or (length <= length_needed and max(hx, hy) > 0):
        tau = start + np.linspace(0.0, 2.0 * np.pi, 4097)[:-1]
        x = cx + hx * (ax * np.sin(wx * tau[:, None] + px)).sum(1) / ax.sum()
        y = cy + hy * (ay * np.sin(wy * tau[:, None] + py)).sum(1) / ay.sum()
        piece = np.c_[x, y]
        if pieces:
            length += np.linalg.norm(piece[0] - pieces[-1][-1])
        length += np.linalg.norm(np.diff(piece, axis=0), axis=1).sum()
        pieces.append(piece)
        start += 2.0 * np.pi
    return np.concatenate(pieces), False


def _walk(curve: np.ndarray, closed: bool, step: float, n: int) -> np.ndarray:
    """Positions ``(n, 2)`` at arc length ``k * step`` along the curve (wrapping if closed)."""
    pts = np.vstack([curve, curve[:1]]) if closed else curve
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    want = np.arange(n) * step
    want = np.mod(want, s[-1]) if closed and s[-1] > 0 else np.minimum(want, s[-1])
    return np.c_[np.interp(want, s, pts[:, 0]), np.interp(want, s, pts[:, 1])]


def footprint_radius(camera: Camera, alt_px: float, tilt_deg: float, extra_deg: float = 0.0) -> float:
    """Largest distance (terrain px) from the camera's ground point to a frame corner's ground
    point, for any yaw and roll, pitch within +-tilt_deg, plus ``extra_deg`` of further
    off-nadir angle (bank, pitch offset)."""
    corner = math.atan(math.hypot(camera.width / 2.0, camera.height / 2.0) / camera.fx)
    off = corner + math.radians(2.0 * tilt_deg + extra_deg)
    if off >= math.radians(85.0):
        raise InputError("tilt plus half the field of view reach the horizon: lower --tilt or the FOV")
    return alt_px * math.tan(off)


def plan_flight(valid: np.ndarray, n_frames: int, camera: Camera, fps: float, gsd: float,
                motion: Motion, seed: int = 0) -> Truth:
    """Plan a flight whose every footprint lies inside ``valid`` (bool, terrain shape).

    ``gsd`` is metres per terrain pixel. Deterministic for a given seed.
    """
    if n_frames < 1 or fps <= 0 or gsd <= 0:
        raise InputError("need at least one frame, fps > 0 and gsd > 0")
    rng = np.random.default_rng([seed, 1])
    t = np.arange(n_frames) / fps
    alt_lo, alt_hi = motion.altitude
    smax = alt_hi / (camera.fx * gsd)
    margin = 2.0 * max(smax, 1.0) + 4.0          # interpolation and pyramid kernel support
    radius = footprint_radius(camera, alt_hi / gsd, motion.tilt, motion.max_bank + abs(motion.pitch_offset)) + margin
    rect = _safe_rectangle(valid, radius)
    step = motion.speed / (gsd * fps)
    spacing = (1.0 - motion.side_overlap) * min(camera.width, camera.height) * (alt_lo + alt_hi) / 2 / (camera.fx * gsd)
    curve, closed = _curve(motion.pattern, rect, spacing, rng, step * (n_frames - 1))
    pos = _walk(curve, closed, step, n_frames)

    # altitude: ln(alt) = mid + half * sin(phase0 + w t), peak |d ln(alt)/dt| = scale_rate
    mid, half = (math.log(alt_lo) + math.log(alt_hi)) / 2, (math.log(alt_hi) - math.log(alt_lo)) / 2
    phase0 = rng.uniform(0, 2 * np.pi)
    w = motion.scale_rate / half if half > 0 else 0.0
    if motion.pattern == "circle" and w > 0 and n_frames > 1:  # whole periods: the last frame is the first
        w = 2 * np.pi * max(1, round(w * t[-1] / (2 * np.pi))) / t[-1]
    alt = np.exp(mid + half * np.sin(phase0 + w * t))

    yaw0 = rng.uniform(0.0, 360.0) if motion.yaw0 is None else float(motion.yaw0)
    yaw_signal = _smooth_random(t, motion.period_s, rng)
    if motion.yaw_mode == "fixed":
        yaw = np.full(n_frames, yaw0)
    elif motion.yaw_mode == "constant":
        yaw = yaw0 + motion.yaw_rate * t
    elif motion.yaw_mode == "random":
        rate = motion.yaw_rate * yaw_signal
        yaw = yaw0 + np.concatenate([[0.0], np.cumsum((rate[1:] + rate[:-1]) / 2.0) / fps])
    else:
        yaw = _heading_yaw(pos, yaw0, motion.yaw_rate / fps, periodic=motion.pattern == "circle")
    yaw = np.mod(yaw + 180.0, 360.0) - 180.0

    roll = motion.tilt * _smooth_random(t, motion.period_s, rng) if motion.tilt > 0 else np.zeros(n_frames)
    pitch = motion.tilt * _smooth_random(t, motion.period_s, rng) if motion.tilt > 0 else np.zeros(n_frames)
    if motion.max_bank > 0:
        roll = roll + coordinated_bank(pos * gsd, t, motion.max_bank)
    if motion.pitch_offset:
        pitch = pitch + motion.pitch_offset

    hs = np.stack([pose_homography(camera, px, py, a / gsd, math.radians(r), math.radians(p), math.radians(y))
                   for (px, py), a, r, p, y in zip(pos, alt, roll, pitch, yaw)])
    centre = np.einsum("nij,j->ni", hs, [camera.cx, camera.cy, 1.0])
    truth = Truth(t=t, H=hs, x=centre[:, 0] / centre[:, 2], y=centre[:, 1] / centre[:, 2], yaw_deg=yaw,
                  scale=alt / (camera.fx * gsd), roll_deg=roll, pitch_deg=pitch, alt_m=alt,
                  cam_x=pos[:, 0].copy(), cam_y=pos[:, 1].copy())
    bad = footprints_outside(truth, camera, valid, margin=2.0)
    if bad.size:
        raise InputError(f"planned footprints leave the valid terrain at frames {bad[:5].tolist()}")
    return truth


def coordinated_bank(pos_m: np.ndarray, t: np.ndarray, max_bank: float,
                     max_rate: float = ROLL_RATE_MAX, smooth_s: float = 0.25) -> np.ndarray:
    """Roll (deg, right wing down > 0) of a coordinated turn along the path ``pos_m``.

    ``pos_m`` is ``(n, 2)`` metres (east, south) at times ``t`` (s). The bank is
    ``atan(v * course_rate / g)`` with ``v`` the ground speed and ``course_rate`` the turn rate
    of the track (rad/s, smoothed by a Gaussian of ``smooth_s`` seconds against the polyline
    corners of the planned path), clipped to ``+-max_bank`` and then followed at no more than
    ``max_rate`` deg/s (the airframe needs time to roll into a turn). Zero when not moving.
    """
    from scipy.ndimage import gaussian_filter1d

    n = len(t)
    if n < 3:
        return np.zeros(n)
    vel = np.gradient(pos_m, t, axis=0)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    course = np.unwrap(np.arctan2(vel[:, 0], -vel[:, 1]))            # clockwise from north
    rate = np.gradient(course, t)
    dt = float(np.median(np.diff(t)))
    if smooth_s > 0:
        rate = gaussian_filter1d(rate, smooth_s / dt, mode="nearest")
    target = np.clip(np.degrees(np.arctan(speed * rate / GRAVITY)), -max_bank, max_bank)
    target[speed < 1e-6] = 0.0
    roll = np.empty(n)
    cur = target[0]
    for k in range(n):
        step = max_rate * (t[k] - t[k - 1]) if k else 0.0
        cur += np.clip(target[k] - cur, -step, step) if k else 0.0
        roll[k] = cur
    return roll


def _heading_yaw(pos: np.ndarray, yaw0: float, max_step: float, periodic: bool = False) -> np.ndarray:
    """Yaw following the direction of travel (deg, clockwise from north), turning at most
    ``max_step`` deg per frame (0 = unlimited); ``yaw0`` while not moving. ``periodic``: the
    path's last position is its first (the direction there is taken across the seam)."""
    d = np.gradient(pos, axis=0) if len(pos) > 1 else np.zeros_like(pos)
    if periodic and len(pos) > 2:
        d[0] = d[-1] = (pos[1] - pos[-2]) / 2.0
    moving = np.hypot(d[:, 0], d[:, 1]) > 1e-9
    heading = np.degrees(np.arctan2(d[:, 0], -d[:, 1]))   # east over north (y is south)
    yaw = np.empty(len(pos))
    cur = heading[0] if moving[0] else yaw0
    for k in range(len(pos)):
        if moving[k]:
            diff = (heading[k] - cur + 180.0) % 360.0 - 180.0
            cur += np.clip(diff, -max_step, max_step) if max_step > 0 else diff
        yaw[k] = cur
    return yaw


def footprints_outside(truth: Truth, camera: Camera, valid: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Indices of frames whose footprint border comes closer than ``margin`` terrain pixels to
    invalid terrain (or leaves the image)."""
    dist = _distance_inside(valid)
    outline = frame_outline(camera)
    h, w = valid.shape
    bad = []
    for k, hk in enumerate(truth.H):
        p = apply_homography(hk, outline)
        xi, yi = np.rint(p[:, 0]).astype(int), np.rint(p[:, 1]).astype(int)
        inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
        if not inside.all() or (dist[yi, xi] <= margin).any():
            bad.append(k)
    return np.asarray(bad, int)


# --------------------------------------------------------------------------- rendering

def build_pyramid(terrain: np.ndarray, max_scale: float) -> list[np.ndarray]:
    """Gaussian pyramid (``cv2.pyrDown``) deep enough for views of up to ``max_scale`` terrain
    px per frame px. Level ``L`` pixel ``(x, y)`` sits at level-0 pixel ``(2**L x, 2**L y)``."""
    levels = [terrain]
    while 2 ** len(levels) <= max_scale and min(levels[-1].shape[:2]) >= 32:
        levels.append(cv2.pyrDown(levels[-1]))
    return levels


def render_view(pyramid: list[np.ndarray], h: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Render the frame ``size = (height, width)`` whose pixels map to terrain by ``h``.

    Anti-aliased: the pyramid level below the local scale, plus a Gaussian of
    ``sigma = sqrt(s**2 - 1) / sqrt(3)`` level pixels for the remaining factor ``s`` in [1, 2)
    (it matches pyrDown's sigma at s = 2), then bicubic sampling. Returns float32 BGR.
    """
    fh, fw = size
    c = np.array([(fw - 1) / 2.0, (fh - 1) / 2.0, 1.0])
    jac = (h[:2, :2] * (h[2] @ c) - np.outer(h[:2] @ c, h[2, :2])) / (h[2] @ c) ** 2
    scale = pose_scale(jac)
    level = min(max(0, int(math.floor(math.log2(scale)))) if scale > 1 else 0, len(pyramid) - 1)
    img = pyramid[level]
    hl = np.diag([0.5 ** level, 0.5 ** level, 1.0]) @ h
    rest = scale / 2 ** level
    sigma = math.sqrt(rest * rest - 1.0) / math.sqrt(3.0) if rest > 1.0 else 0.0
    corners = apply_homography(hl, np.array([[0, 0], [fw - 1, 0], [0, fh - 1], [fw - 1, fh - 1]], float))
    pad = int(math.ceil(3 * sigma)) + 3
    x0 = max(int(math.floor(corners[:, 0].min())) - pad, 0)
    y0 = max(int(math.floor(corners[:, 1].min())) - pad, 0)
    x1 = min(int(math.ceil(corners[:, 0].max())) + pad + 1, img.shape[1])
    y1 = min(int(math.ceil(corners[:, 1].max())) + pad + 1, img.shape[0])
    if x1 <= x0 or y1 <= y0:
        return np.zeros((fh, fw, 3), np.float32)
    roi = img[y0:y1, x0:x1].astype(np.float32)
    if sigma > 0.1:
        cv2.GaussianBlur(roi, (0, 0), sigma, dst=roi)
    hr = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]]) @ hl
    return cv2.warpPerspective(roi, hr, (fw, fh), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REFLECT)


def apply_effects(img: np.ndarray, effects: Effects, rng: np.random.Generator, gain: float = 1.0) -> np.ndarray:
    """Gain, blur, Gaussian noise, uint8 quantization, optional JPEG round trip (see :class:`Effects`).

    ``img`` (float32 BGR) is left unchanged; the arithmetic runs in place on one working copy
    (a 1080p frame is 24 MB as float32: a long simulated flight would otherwise churn the heap
    with several of them per frame)."""
    out = np.multiply(img, np.float32(gain), dtype=np.float32)  # the working copy
    if effects.blur > 0:
        cv2.GaussianBlur(out, (0, 0), effects.blur, dst=out)
    if effects.noise > 0:
        noise = rng.standard_normal(out.shape, dtype=np.float32)
        noise *= np.float32(effects.noise)
        out += noise
        del noise
    out += np.float32(0.5)
    out = np.clip(out, 0, 255, out=out).astype(np.uint8)
    if effects.jpeg_quality > 0:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(effects.jpeg_quality)])
        out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return out


def iter_frames(terrain: np.ndarray, truth: Truth, camera: Camera, effects: Effects, seed: int = 0,
                period_s: float = 10.0, pyramid: list[np.ndarray] | None = None, overlay=None,
                lens: DistortedRender | None = None, osd: Overlay | None = None):
    """Yield the uint8 BGR frames of ``truth`` one by one (deterministic for a seed).

    ``overlay(k, view) -> view`` draws over the float BGR ground view of frame ``k`` before the
    sensor effects (e.g. :meth:`photomap.sim.objects.ObjectScene.overlay`). ``lens``: the frames
    are seen through its distortion (the truth stays the ideal pinhole view); ``osd``: burned in
    over each finished frame (:mod:`photomap.sim.lens`).
    """
    if pyramid is None:
        pyramid = build_pyramid(terrain, float(truth.scale.max()) * 1.2)
    gain = 1.0 + effects.gain_drift * _smooth_random(truth.t, period_s, np.random.default_rng([seed, 2]))
    for k, hk in enumerate(truth.H):
        if lens is not None:
            view = lens.distort(render_view(pyramid, lens.canvas_homography(hk), lens.canvas[::-1]))
        else:
            view = render_view(pyramid, hk, (camera.height, camera.width))
        if overlay is not None:
            view = overlay(k, view)
        frame = apply_effects(view, effects, np.random.default_rng([seed, 3, k]), float(gain[k]))
        yield osd.draw(frame) if osd is not None else frame


def simulate_sequence(terrain: np.ndarray, n_frames: int, frame_size: tuple[int, int] = (480, 640),
                      seed: int = 0, *, valid: np.ndarray | None = None, fps: float = 30.0,
                      gsd: float = 0.1, hfov_deg: float = 60.0, **params) -> Sequence:
    """Fly and render a whole sequence in memory.

    Parameters
    ----------
    terrain : uint8 BGR terrain; ``valid`` its bool validity mask (default: all valid).
    n_frames, frame_size : number of frames and their ``(height, width)``.
    fps, gsd, hfov_deg : frame rate, metres per terrain pixel, horizontal field of view.
    **params : fields of :class:`Motion` (pattern, speed, yaw_mode, yaw_rate, yaw0, altitude,
        scale_rate, tilt, period_s, side_overlap) and :class:`Effects` (gain_drift, blur,
        noise, jpeg_quality).
    """
    motion, effects = split_params(params)
    camera = Camera.from_hfov(frame_size[1], frame_size[0], hfov_deg)
    if valid is None:
        valid = np.ones(terrain.shape[:2], bool)
    truth = plan_flight(valid, n_frames, camera, fps, gsd, motion, seed)
    frames = list(iter_frames(terrain, truth, camera, effects, seed, motion.period_s))
    params = {"seed": seed, "fps": fps, "gsd": gsd, "hfov_deg": hfov_deg, **asdict(motion), **asdict(effects)}
    return Sequence(frames=frames, truth=truth, camera=camera, gsd=gsd, fps=fps, params=params)


def render_pair(terrain: np.ndarray, shape: tuple[int, int], angle_deg: float, scale: float,
                shift: tuple[float, float], seed: int = 0, *, valid: np.ndarray | None = None,
                base_scale: float = 1.0, pyramid: list[np.ndarray] | None = None,
                **effects) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two views ``a``, ``b`` of shape ``(h, w)`` cut from the terrain with a known similarity.

    ``M_true`` (2x3) maps pixels of ``b`` to pixels of ``a``:
    ``p_a = c + scale * R(angle_deg) (p_b - c) + shift`` with ``c`` the image centre, so
    ``scale > 1`` means ``b`` sees a larger area (is zoomed out) relative to ``a``.
    ``a`` is a nadir view at ``base_scale`` terrain px per pixel with a random yaw and position
    (from ``seed``) inside ``valid``; both are rendered from the terrain, never from each other.
    ``**effects``: fields of :class:`Effects`, applied independently to each view.
    ``pyramid``: ``build_pyramid(terrain, ...)`` reused across many calls (saves its cost).
    """
    eff = Effects(**effects)
    eff.check()
    h, w = int(shape[0]), int(shape[1])
    rng = np.random.default_rng([seed, 4])
    m = similarity_matrix(angle_deg, scale, shift, center=((w - 1) / 2.0, (h - 1) / 2.0))
    half_diag = math.hypot(w, h) / 2.0
    need = base_scale * (math.hypot(*shift) + half_diag * max(1.0, scale)) + 2.0 * base_scale * max(1.0, scale) + 4
    th, tw = terrain.shape[:2]
    too_small = InputError(f"terrain {tw}x{th} too small for a pair of {w}x{h} views at base scale "
                           f"{base_scale} with this shift/scale")
    if valid is None:
        if min(tw, th) - 1 <= 2 * need:
            raise too_small
        centre = rng.uniform([need, need], [tw - 1 - need, th - 1 - need])
    else:
        ys, xs = np.nonzero(_distance_inside(valid) > need)
        if xs.size == 0:
            raise too_small
        pick = rng.integers(xs.size)
        centre = np.array([xs[pick], ys[pick]], float)
    ha = np.eye(3)
    ha[:2] = similarity_matrix(rng.uniform(-180.0, 180.0), base_scale)
    ha[:2, 2] = centre - ha[:2, :2] @ [(w - 1) / 2.0, (h - 1) / 2.0]
    hb = ha @ np.vstack([m, [0.0, 0.0, 1.0]])
    if pyramid is None:
        pyramid = build_pyramid(terrain, base_scale * max(1.0, scale) * 1.2)
    a = apply_effects(render_view(pyramid, ha, (h, w)), eff, np.random.default_rng([seed, 5]))
    b = apply_effects(render_view(pyramid, hb, (h, w)), eff, np.random.default_rng([seed, 6]))
    return a, b, m
