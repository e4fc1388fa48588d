"""Georeferencing: metric scale, GPS fit of a map segment, UTM, world files, tilt, telemetry priors.

Pure computations (arrays in, arrays out); the pipeline joins telemetry and writes the files.

Conventions
-----------
- Pixels: OpenCV (x right, y down, origin at the centre of the top-left pixel). A pose is a 2x3
  matrix mapping frame pixels to map pixels (see :mod:`photomap.geometry`).
- Angles: telemetry in radians (MAVLink ``ATTITUDE``: yaw = heading of the image's up direction,
  clockwise from north); registration angles in degrees, ``atan2(m10, m00)`` in y-down pixels,
  so a clockwise yaw change is a positive angle.
- Local tangent plane (ENU): east, north in metres on the plane tangent to the WGS84 ellipsoid at
  an origin (the first GPS fix). Fits are done in (east, south) so that map pixels (y down) relate
  to it by a proper similarity (no reflection).
- Projected CRS: WGS 84 / UTM (EPSG:326zz north, 327zz south), easting/northing in metres.
- ``map_to_crs`` and the other "affine" results are 2x3 matrices acting on ``(x, y, 1)``.

References: Umeyama (1991), least-squares similarity; Krueger series of the transverse Mercator
projection as given by Karney (2011), "Transverse Mercator with an accuracy of a few
nanometers", truncated at n^3 (sub-millimetre within a UTM zone).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Sequence
from xml.sax.saxutils import escape

import numpy as np

from photomap.errors import InputError
from photomap.geometry import pose_angle_deg, pose_scale, similarity_fit

log = logging.getLogger(__name__)

# WGS84
WGS84_A = 6378137.0
WGS84_INV_F = 298.257223563
_F = 1.0 / WGS84_INV_F
_E2 = _F * (2.0 - _F)
UTM_K0 = 0.9996
UTM_FALSE_EASTING = 500000.0
UTM_FALSE_NORTHING_SOUTH = 10000000.0

_N = _F / (2.0 - _F)
_UTM_A = WGS84_A / (1.0 + _N) * (1.0 + _N ** 2 / 4.0 + _N ** 4 / 64.0)
_ALPHA = (_N / 2 - 2 * _N ** 2 / 3 + 5 * _N ** 3 / 16, 13 * _N ** 2 / 48 - 3 * _N ** 3 / 5, 61 * _N ** 3 / 240)
_BETA = (_N / 2 - 2 * _N ** 2 / 3 + 37 * _N ** 3 / 96, _N ** 2 / 48 + _N ** 3 / 15, 17 * _N ** 3 / 480)
_E_CONF = 2.0 * math.sqrt(_N) / (1.0 + _N)   # the eccentricity e, written through n


# --------------------------------------------------------------------------- camera and scale

def focal_px(width: int, fx_px: float = 0.0, hfov_deg: float = 0.0) -> float | None:
    """Focal length in pixels at an input resolution of ``width`` pixels (the ``camera:`` config).

    ``fx_px`` wins when > 0; else ``fx = (width / 2) / tan(hfov / 2)`` when ``hfov_deg`` > 0;
    else None (camera model unknown).
    """
    if fx_px and fx_px > 0:
        return float(fx_px)
    if hfov_deg and hfov_deg > 0:
        if not hfov_deg < 180.0:
            raise InputError(f"camera horizontal field of view must be below 180 deg, got {hfov_deg}")
        return (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return None


def metres_per_pixel(poses: Sequence[np.ndarray | None], heights: Sequence[float | None],
                     fx: float) -> float | None:
    """Ground metres per map pixel of a map segment, from the camera model and the height.

    A nadir frame at height ``h`` (metres above ground) has a ground sampling distance of
    ``h / fx`` metres per frame pixel (``fx`` in pixels at the input resolution); its pose maps
    one frame pixel to ``s = sqrt(det(M[:, :2]))`` map pixels, so one map pixel is
    ``h / (fx * s)`` metres. Returns the median over the frames that have both a pose and a
    positive finite height (None when there is none).
    """
    if not fx or fx <= 0:
        raise ValueError(f"focal length must be > 0 pixels, got {fx!r}")
    if len(poses) != len(heights):
        raise ValueError(f"{len(poses)} poses but {len(heights)} heights")
    values = []
    for pose, h in zip(poses, heights):
        if pose is None or h is None or not math.isfinite(h) or h <= 0:
            continue
        s = pose_scale(pose)
        if s > 0 and math.isfinite(s):
            values.append(h / (fx * s))
    return float(np.median(values)) if values else None


def map_heading_deg(poses: Sequence[np.ndarray | None], yaws: Sequence[float | None]) -> float | None:
    """Heading of the map's up direction (deg, clockwise from north), from compass yaw.

    A frame's up direction has heading ``yaw`` (radians, MAVLink) and is turned by the pose
    angle ``theta`` in the map, so the map's up has heading ``yaw - theta``. Circular mean over
    the frames with both (None when there is none). Use it to fix the rotation of a
    georeference when the GPS track is too short (``fit_georeference(heading_deg=...)``).
    """
    diffs = [math.degrees(y) - pose_angle_deg(p) for p, y in zip(poses, yaws)
             if p is not None and y is not None and math.isfinite(y)]
    if not diffs:
        return None
    r = np.radians(diffs)
    return math.degrees(math.atan2(np.sin(r).mean(), np.cos(r).mean()))


# --------------------------------------------------------------------------- tilt

def _tilt_rotation(roll: float, pitch: float) -> np.ndarray:
    """Rotation from the tilted camera's axes to the nadir camera's axes (same yaw).

    Camera axes are OpenCV's (x right, y down, z optical axis); the camera looks down with
    image up = body forward (see :mod:`photomap.sim.flight`). Equals ``R_nadir^T R_tilted``.
    """
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])    # pitch about body y (right)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])    # roll about body x (forward)
    r_bc = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # camera -> body
    return r_bc.T @ ry @ rx @ r_bc


def nadir_homography(fx: float, cx: float, cy: float, roll: float, pitch: float) -> np.ndarray:
    """3x3 homography mapping pixels of a tilted frame to pixels of the nadir frame.

    The nadir frame is what the same camera would see at the same place and yaw with roll and
    pitch zero: ``H = K R K^-1`` with ``R = R_nadir^T R_tilted`` (a pure rotation, exact for
    any scene). ``roll``, ``pitch`` in radians (MAVLink ``ATTITUDE``), ``fx`` and the principal
    point ``(cx, cy)`` in pixels. Rectify with ``cv2.warpPerspective(frame, H, (w, h))``.
    """
    k = np.array([[fx, 0.0, cx], [0.0, fx, cy], [0.0, 0.0, 1.0]])
    h = k @ _tilt_rotation(roll, pitch) @ np.linalg.inv(k)
    return h / h[2, 2]


def rectifying_homography(fx: float, width: int, height: int, roll: float, pitch: float) -> np.ndarray:
    """3x3 homography mapping pixels of a tilted frame to its *recentred* nadir view.

    :func:`nadir_homography` (principal point at the frame centre ``c = ((w-1)/2, (h-1)/2)``)
    followed by the translation that brings the image of ``c`` back to ``c``. The result is
    still an exact nadir view (same focal length, so same metres per pixel as the nadir camera;
    the nadir point moves off-centre), but its centre pixel sees the same ground as the tilted
    frame's centre pixel and it covers nearly the same ground as the tilted frame, so a frame of
    the same size loses only the keystone slivers. Consequently the pose of the rectified frame
    (a similarity) maps the tilted frame's centre exactly; the full map of the tilted frame's
    pixels is ``pose @ rectifying_homography(...)``.
    """
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    h = nadir_homography(fx, cx, cy, roll, pitch)
    q = h @ [cx, cy, 1.0]
    shift = np.array([[1.0, 0.0, cx - q[0] / q[2]], [0.0, 1.0, cy - q[1] / q[2]], [0.0, 0.0, 1.0]])
    out = shift @ h
    return out / out[2, 2]


def nadir_pixel(fx: float, cx: float, cy: float, roll: float, pitch: float) -> tuple[float, float]:
    """Pixel of a tilted frame that sees the ground point straight below the camera.

    (The principal point of the rectified frame mapped back; the GPS position belongs to this
    pixel, not to the frame centre, when the camera is tilted.)
    """
    p = np.linalg.solve(nadir_homography(fx, cx, cy, roll, pitch), [cx, cy, 1.0])
    return float(p[0] / p[2]), float(p[1] / p[2])


# --------------------------------------------------------------------------- priors

def telemetry_prior(sample_i: Any, sample_j: Any) -> tuple[float | None, float | None]:
    """Expected registration of frame j (new) against frame i (reference) from telemetry.

    In the convention of :mod:`photomap.core.ifmi` (the result maps new-frame pixels to reference
    pixels): ``angle_deg = degrees(yaw_j - yaw_i)`` wrapped to (-180, 180] (a clockwise yaw
    change is a positive angle in y-down pixels) and ``scale = h_j / h_i`` (the new frame
    seen from higher up covers more ground per pixel). The samples are
    :class:`photomap.telemetry.samples.TelemetrySample` (``yaw`` radians, ``height_above_ground``
    metres); a missing value gives None for that part.
    """
    angle = scale = None
    yi, yj = getattr(sample_i, "yaw", None), getattr(sample_j, "yaw", None)
    if yi is not None and yj is not None:
        d = math.degrees(math.remainder(yj - yi, 2.0 * math.pi))
        angle = 180.0 if d == -180.0 else d
    hi, hj = getattr(sample_i, "height_above_ground", None), getattr(sample_j, "height_above_ground", None)
    if hi is not None and hj is not None and hi > 0 and hj > 0:
        scale = hj / hi
    return angle, scale


# --------------------------------------------------------------------------- local tangent plane

def _ecef(lat: np.ndarray, lon: np.ndarray, h: np.ndarray | float = 0.0) -> np.ndarray:
    phi, lam = np.radians(lat), np.radians(lon)
    n = WGS84_A / np.sqrt(1.0 - _E2 * np.sin(phi) ** 2)
    return np.stack([(n + h) * np.cos(phi) * np.cos(lam), (n + h) * np.cos(phi) * np.sin(lam),
                     (n * (1.0 - _E2) + h) * np.sin(phi)], axis=-1)


def _enu_basis(lat0: float, lon0: float) -> np.ndarray:
    """Rows: east, north, up unit vectors in ECEF at the origin."""
    p, l = math.radians(lat0), math.radians(lon0)
    return np.array([[-math.sin(l), math.cos(l), 0.0],
                     [-math.sin(p) * math.cos(l), -math.sin(p) * math.sin(l), math.cos(p)],
                     [math.cos(p) * math.cos(l), math.cos(p) * math.sin(l), math.sin(p)]])


def _geodetic(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ECEF -> (lat, lon) degrees (Bowring's iteration; heights near the ellipsoid, where it
    converges to the last bit in two steps from the start used here: three are taken)."""
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    p = np.hypot(x, y)
    phi = np.arctan2(z, p * (1.0 - _E2))
    for _ in range(3):
        n = WGS84_A / np.sqrt(1.0 - _E2 * np.sin(phi) ** 2)
        phi = np.arctan2(z + _E2 * n * np.sin(phi), p)
    return np.degrees(phi), np.degrees(np.arctan2(y, x))


def enu_from_latlon(lat: np.ndarray, lon: np.ndarray, lat0: float, lon0: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """WGS84 degrees (on the ellipsoid) -> east, north metres on the tangent plane at (lat0, lon0)."""
    d = _ecef(np.asarray(lat, float), np.asarray(lon, float)) - _ecef(np.float64(lat0), np.float64(lon0))
    enu = d @ _enu_basis(lat0, lon0).T
    return enu[..., 0], enu[..., 1]


def latlon_from_enu(east: np.ndarray, north: np.ndarray, lat0: float, lon0: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`enu_from_latlon`: the ellipsoid point whose (east, north) are given."""
    e, n = np.asarray(east, float), np.asarray(north, float)
    basis = _enu_basis(lat0, lon0)
    origin = _ecef(np.float64(lat0), np.float64(lon0))
    up = np.zeros_like(e)
    for _ in range(3):  # the ellipsoid drops below the plane by ~d^2 / 2R: find its height there
        lat, lon = _geodetic(origin + np.stack([e, n, up], axis=-1) @ basis)
        up = (_ecef(lat, lon) - origin) @ basis[2]
    return lat, lon


# --------------------------------------------------------------------------- UTM

def utm_zone(lat: float, lon: float) -> int:
    """UTM zone number of a position, with the Norway (32V) and Svalbard exceptions."""
    if not -80.0 <= lat <= 84.0:
        raise InputError(f"latitude {lat:.4f} is outside UTM (80S..84N)")
    lon = (lon + 180.0) % 360.0 - 180.0
    zone = int((lon + 180.0) // 6.0) + 1
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        zone = 32
    elif lat >= 72.0 and 0.0 <= lon < 42.0:
        zone = 31 if lon < 9.0 else 33 if lon < 21.0 else 35 if lon < 33.0 else 37
    return min(zone, 60)


def utm_epsg(lat: float, lon: float) -> int:
    """EPSG code of WGS 84 / UTM for a position: 326zz north of the equator, 327zz south."""
    return (32600 if lat >= 0 else 32700) + utm_zone(lat, lon)


def epsg_zone(epsg: int) -> tuple[int, bool]:
    """``(zone, north)`` of a WGS 84 / UTM EPSG code; ValueError for any other code."""
    epsg = int(epsg)
    if 32601 <= epsg <= 32660:
        return epsg - 32600, True
    if 32701 <= epsg <= 32760:
        return epsg - 32700, False
    raise ValueError(f"EPSG:{epsg} is not a WGS 84 / UTM zone (32601-32660, 32701-32760)")


def _central_meridian(zone: int) -> float:
    return zone * 6.0 - 183.0


def utm_forward(lat: np.ndarray, lon: np.ndarray, epsg: int) -> tuple[np.ndarray, np.ndarray]:
    """WGS84 degrees -> (easting, northing) metres in the UTM zone of ``epsg``."""
    zone, north = epsg_zone(epsg)
    phi = np.radians(np.asarray(lat, float))
    dlam = np.radians((np.asarray(lon, float) - _central_meridian(zone) + 180.0) % 360.0 - 180.0)
    sphi = np.sin(phi)
    t = np.sinh(np.arctanh(sphi) - _E_CONF * np.arctanh(_E_CONF * sphi))
    xi = np.arctan2(t, np.cos(dlam))
    eta = np.arctanh(np.sin(dlam) / np.sqrt(1.0 + t * t))
    x, y = eta.copy(), xi.copy()
    for j, a in enumerate(_ALPHA, start=1):
        x += a * np.cos(2 * j * xi) * np.sinh(2 * j * eta)
        y += a * np.sin(2 * j * xi) * np.cosh(2 * j * eta)
    easting = UTM_FALSE_EASTING + UTM_K0 * _UTM_A * x
    northing = UTM_K0 * _UTM_A * y + (0.0 if north else UTM_FALSE_NORTHING_SOUTH)
    return easting, northing


def utm_inverse(easting: np.ndarray, northing: np.ndarray, epsg: int) -> tuple[np.ndarray, np.ndarray]:
    """(easting, northing) metres in the UTM zone of ``epsg`` -> WGS84 degrees."""
    zone, north = epsg_zone(epsg)
    xi = (np.asarray(northing, float) - (0.0 if north else UTM_FALSE_NORTHING_SOUTH)) / (UTM_K0 * _UTM_A)
    eta = (np.asarray(easting, float) - UTM_FALSE_EASTING) / (UTM_K0 * _UTM_A)
    xp, ep = xi.copy(), eta.copy()
    for j, b in enumerate(_BETA, start=1):
        xp -= b * np.sin(2 * j * xi) * np.cosh(2 * j * eta)
        ep -= b * np.cos(2 * j * xi) * np.sinh(2 * j * eta)
    taup = np.sin(xp) / np.hypot(np.sinh(ep), np.cos(xp))   # tan of the conformal latitude
    tau = taup / (1.0 - _E2)
    for _ in range(4):  # Newton for tan(latitude) (Karney 2011, eqs. 7-9 and 19-21)
        sig = np.sinh(_E_CONF * np.arctanh(_E_CONF * tau / np.hypot(1.0, tau)))
        f = tau * np.hypot(1.0, sig) - sig * np.hypot(1.0, tau)
        tau = tau + (taup - f) * (1.0 + (1.0 - _E2) * tau * tau) / (
            (1.0 - _E2) * np.hypot(1.0, f) * np.hypot(1.0, tau))
    phi = np.arctan(tau)
    lon = _central_meridian(zone) + np.degrees(np.arctan2(np.sinh(ep), np.cos(xp)))
    return np.degrees(phi), (lon + 180.0) % 360.0 - 180.0


def _apply(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return np.asarray(pts, float) @ m[:, :2].T + m[:, 2]


def robust_similarity(src: np.ndarray, dst: np.ndarray, inlier_tol: float, *,
                      scale: float | None = None, angle_deg: float | None = None,
                      iterations: int = 300, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC over point pairs, then least squares on the inliers (iterated to a fixed point).

    Returns the 2x3 similarity and the boolean inlier mask (residual <= ``inlier_tol``, in
    ``dst`` units). Deterministic for a given ``seed``.
    """
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    n = len(src)
    rng = np.random.default_rng(seed)
    best, best_key = None, (-1, math.inf)
    pairs = rng.integers(0, n, size=(iterations, 2)) if n > 2 else np.array([[0, n - 1]])
    for i, j in pairs:
        if i == j:
            continue
        m = similarity_fit(src[[i, j]], dst[[i, j]], scale=scale, angle_deg=angle_deg)
        res = np.linalg.norm(_apply(m, src) - dst, axis=1)
        inl = res <= inlier_tol
        key = (int(inl.sum()), -float(res[inl].sum()))
        if key > best_key:
            best, best_key = inl, key
    inliers = best if best is not None and best.sum() >= 2 else np.ones(n, bool)
    m = similarity_fit(src[inliers], dst[inliers], scale=scale, angle_deg=angle_deg)
    for _ in range(10):
        new = np.linalg.norm(_apply(m, src) - dst, axis=1) <= inlier_tol
        if new.sum() < 2 or np.array_equal(new, inliers):
            break
        inliers = new
        m = similarity_fit(src[inliers], dst[inliers], scale=scale, angle_deg=angle_deg)
    return m, inliers


# --------------------------------------------------------------------------- georeference

_FLIP = np.diag([1.0, -1.0])  # (east, south) <-> (east, north)


@dataclass(frozen=True)
class Georeference:
    """Georeference of one map segment.

    origin_lat, origin_lon : origin of the local tangent plane (the first GPS fix), degrees.
    map_to_enu : 2x3, map pixel -> (east, north) metres on that plane (a similarity composed
        with the y flip: its determinant is negative).
    epsg : WGS 84 / UTM zone of the first fix. map_to_crs : 2x3, map pixel -> (easting,
        northing) metres in that zone, linearised about the fixes' centroid (measured error:
        3 mm within 1 km of it, 2 cm within 3 km, 0.25 m within 10 km).
    metres_per_px : ground metres per map pixel. heading_deg : heading of the map's up direction
        (clockwise from north). scale_source : "gps" (fitted) or "camera" (given).
    rms_m : RMS residual of the inlier fixes, metres. inliers, points : fixes used / given.
    extent_m : RMS distance of the fixes from their centroid, metres (the track's spread).
    """

    origin_lat: float
    origin_lon: float
    map_to_enu: np.ndarray
    epsg: int
    map_to_crs: np.ndarray
    metres_per_px: float
    heading_deg: float
    scale_source: str
    rms_m: float
    inliers: int
    points: int
    extent_m: float = 0.0

    def to_latlon(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map pixels ``(n, 2)`` -> WGS84 (lat, lon) degrees (exact through the tangent plane)."""
        enu = _apply(self.map_to_enu, np.atleast_2d(np.asarray(xy, float)))
        return latlon_from_enu(enu[:, 0], enu[:, 1], self.origin_lat, self.origin_lon)

    def to_crs(self, xy: np.ndarray) -> np.ndarray:
        """Map pixels ``(n, 2)`` -> UTM (easting, northing) ``(n, 2)``."""
        return _apply(self.map_to_crs, np.atleast_2d(np.asarray(xy, float)))


def fit_georeference(map_xy: np.ndarray, lat: Sequence[float | None], lon: Sequence[float | None], *,
                     metres_per_px: float | None = None, heading_deg: float | None = None,
                     inlier_m: float = 10.0, min_extent_m: float = 20.0, min_fixes: int = 5,
                     ) -> Georeference | None:
    """Fit the georeference of a map segment to the GPS positions of its frames.

    Parameters
    ----------
    map_xy : (n, 2) map pixels of the point each fix belongs to (the frame centre, or the
        :func:`nadir_pixel` through the pose when the camera is tilted).
    lat, lon : WGS84 degrees of the fixes (None or NaN = no fix for that frame).
    metres_per_px : ground metres per map pixel from the camera (:func:`metres_per_pixel`);
        used only when the track is too short to fix the scale.
    heading_deg : heading of the map's up direction (:func:`map_heading_deg`); used only with a
        short track, to fix the rotation too.
    inlier_m : a fix farther than this from the fit is an outlier (GPS glitch), metres.
    min_extent_m : the track's RMS distance from its centroid below which GPS alone does not
        fix scale and rotation (then ``metres_per_px`` is required).
    min_fixes : fewer valid fixes give None.

    Returns None when there are too few fixes, or the track is short and no
    ``metres_per_px`` is given, or fewer than ``min_fixes`` fixes agree with the fit.
    """
    xy = np.asarray(map_xy, float).reshape(-1, 2)
    la = np.array([np.nan if v is None else v for v in lat], float)
    lo = np.array([np.nan if v is None else v for v in lon], float)
    if not len(xy) == len(la) == len(lo):
        raise ValueError(f"{len(xy)} map points but {len(la)} latitudes and {len(lo)} longitudes")
    ok = np.isfinite(la) & np.isfinite(lo) & np.isfinite(xy).all(axis=1)
    n = int(ok.sum())
    if n < max(min_fixes, 2):
        log.info("georeference: %d GPS fixes, need %d", n, max(min_fixes, 2))
        return None
    xy, la, lo = xy[ok], la[ok], lo[ok]
    lat0, lon0 = float(la[0]), float(lo[0])
    east, north = enu_from_latlon(la, lo, lat0, lon0)
    es = np.c_[east, -north]
    extent = float(np.sqrt(((es - es.mean(axis=0)) ** 2).sum(axis=1).mean()))
    if extent >= min_extent_m:
        sim, inliers = robust_similarity(xy, es, inlier_m)
        source = "gps"
    elif metres_per_px:
        sim, inliers = robust_similarity(xy, es, inlier_m, scale=metres_per_px, angle_deg=heading_deg)
        source = "camera"
    else:
        log.info("georeference: GPS track spans %.1f m RMS (< %.1f m) and no camera scale", extent, min_extent_m)
        return None
    if inliers.sum() < max(min_fixes, 2):
        log.info("georeference: only %d of %d fixes agree within %.1f m", inliers.sum(), n, inlier_m)
        return None
    rms = float(np.sqrt((np.linalg.norm(_apply(sim, xy[inliers]) - es[inliers], axis=1) ** 2).mean()))
    mpp = pose_scale(sim)
    heading = pose_angle_deg(sim)
    map_to_enu = _FLIP @ sim

    # UTM, linearised about the centroid of the inlier fixes
    epsg = utm_epsg(lat0, lon0)
    c = es[inliers].mean(axis=0) * [1.0, -1.0]
    d = 1.0
    pts = np.array([c, c + [d, 0.0], c - [d, 0.0], c + [0.0, d], c - [0.0, d]])
    plat, plon = latlon_from_enu(pts[:, 0], pts[:, 1], lat0, lon0)
    pe, pn = utm_forward(plat, plon, epsg)
    u = np.c_[pe, pn]
    jac = np.c_[(u[1] - u[2]) / (2 * d), (u[3] - u[4]) / (2 * d)]
    enu_to_crs = np.hstack([jac, (u[0] - jac @ c)[:, None]])
    return Georeference(lat0, lon0, map_to_enu, epsg, compose(enu_to_crs, map_to_enu), mpp, heading, source, rms,
                        int(inliers.sum()), n, extent)


# --------------------------------------------------------------------------- files

def png_to_map(origin_xy: Sequence[float], scale: float | Sequence[float]) -> np.ndarray:
    """2x3 affine mapping pixels ``(u, v)`` of a rendered mosaic PNG to map pixels.

    ``origin_xy`` and ``scale`` are those of ``run.json`` (:meth:`TiledMosaic.render`): output
    pixel ``u`` covers the map pixel indices ``x0 + [u, u + 1) / s``; in pixel-centre
    coordinates its centre is ``x = x0 - 0.5 + (u + 0.5) / s``, i.e.
    ``x = u / s + x0 + 0.5 / s - 0.5`` (the same for y). ``scale`` may be ``(sx, sy)``: the
    exact factors are ``png_width / map_width`` and ``png_height / map_height`` (the PNG size is
    rounded); with the single ``scale`` the far edge is off by at most ``0.5 / s`` map pixels.
    """
    sx, sy = (float(scale), float(scale)) if np.isscalar(scale) else (float(scale[0]), float(scale[1]))
    if sx <= 0 or sy <= 0:
        raise ValueError(f"scale must be > 0, got {scale!r}")
    x0, y0 = float(origin_xy[0]), float(origin_xy[1])
    return np.array([[1.0 / sx, 0.0, x0 + 0.5 / sx - 0.5], [0.0, 1.0 / sy, y0 + 0.5 / sy - 0.5]])


def compose(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """2x3 affine ``outer o inner`` (apply ``inner`` first)."""
    o, i = np.asarray(outer, float), np.asarray(inner, float)
    return np.hstack([o[:, :2] @ i[:, :2], (o[:, :2] @ i[:, 2] + o[:, 2])[:, None]])


def world_file_text(affine: np.ndarray) -> str:
    """World file (``.pgw``/``.wld``) for a 2x3 affine image pixel -> projected coordinates.

    Six lines ``A, D, B, E, C, F`` with ``X = A u + B v + C``, ``Y = D u + E v + F``, where
    ``(u, v)`` are pixel centres, so ``(C, F)`` is the centre of the top-left pixel (this is the
    world-file convention and OpenCV's, so the affine's translation is written as is).
    For a mosaic PNG: ``compose(georef.map_to_crs, png_to_map(origin_xy, scale))``.
    """
    m = np.asarray(affine, float)
    if m.shape != (2, 3) or not np.isfinite(m).all():
        raise ValueError("world file needs a finite 2x3 affine")
    return "".join(f"{float(v)!r}\n" for v in (m[0, 0], m[1, 0], m[0, 1], m[1, 1], m[0, 2], m[1, 2]))


def parse_world_file(text: str) -> np.ndarray:
    """Inverse of :func:`world_file_text`: the 2x3 affine. InputError on anything but 6 numbers."""
    try:
        a, d, b, e, c, f = (float(v) for v in text.split())
    except ValueError:
        raise InputError("a world file holds exactly six numbers") from None
    return np.array([[a, b, c], [d, e, f]])


def prj_text(epsg: int) -> str:
    """WKT (OGC WKT 1, as GDAL writes it, with EPSG authorities) of WGS 84 / UTM ``epsg``.

    For a ``.prj`` beside the world file. GDAL (hence QGIS) does not read a raster's ``.prj``,
    so also write :func:`aux_xml_text` as ``mosaic.png.aux.xml``.
    """
    zone, north = epsg_zone(epsg)
    hemi = "N" if north else "S"
    return (f'PROJCS["WGS 84 / UTM zone {zone}{hemi}",'
            'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563,'
            'AUTHORITY["EPSG","7030"]],AUTHORITY["EPSG","6326"]],'
            'PRIMEM["Greenwich",0,AUTHORITY["EPSG","8901"]],'
            'UNIT["degree",0.0174532925199433,AUTHORITY["EPSG","9122"]],AUTHORITY["EPSG","4326"]],'
            'PROJECTION["Transverse_Mercator"],'
            'PARAMETER["latitude_of_origin",0],'
            f'PARAMETER["central_meridian",{_central_meridian(zone):g}],'
            'PARAMETER["scale_factor",0.9996],'
            'PARAMETER["false_easting",500000],'
            f'PARAMETER["false_northing",{0 if north else 10000000}],'
            'UNIT["metre",1,AUTHORITY["EPSG","9001"]],'
            'AXIS["Easting",EAST],AXIS["Northing",NORTH],'
            f'AUTHORITY["EPSG","{int(epsg)}"]]')


def aux_xml_text(epsg: int) -> str:
    """GDAL PAM sidecar (``mosaic.png.aux.xml``) declaring the CRS; the world file holds the transform."""
    return f"<PAMDataset>\n  <SRS>{escape(prj_text(epsg))}</SRS>\n</PAMDataset>\n"
