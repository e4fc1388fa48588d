"""Merging the maps of several runs (flights, drones) over one site into one map.

Each run's main map (``run.json`` ``mosaics[0]``: its full-resolution ``tiles/`` when it has them,
else ``mosaic.png``) is registered to the reference run's map (the first one), coarse to fine,
on the maps themselves (:mod:`photomap.core.mapmerge`):

1. **Coarse**: both maps rendered whole at one common scale onto an ``overview`` x ``overview``
   canvas (each centred, at most half the canvas, so any overlap is a shift the translation
   POMF can see), registered by iFMI (rotation, scale, translation). With a georeference in both
   runs and ``use_georeference``, the GPS placement (``map_to_crs`` of both) replaces this step:
   telemetry is only a prior, the next steps measure on the images.
2. **Fine**: at scales growing 4x per level up to the maps' own resolution, ``patch`` x
   ``patch`` windows spread over the overlap are rendered from both maps on one grid (the
   moving map resampled through the current estimate) and registered (iFMI with a prior near
   identity, then the Gauss-Newton refinement); each gives one point pair, and a similarity is
   fitted robustly to them. A run is **placed** when the last level has at least
   ``min_patches`` agreeing windows with a median confidence of at least ``min_confidence``;
   otherwise it is listed as not placed with the reason, never forced into the map.

The merged map is the reference run's map frame: placed maps are painted into one
:class:`~photomap.core.mosaic.TiledMosaic` in chunks (reference first), and it is written like a
run's (``mosaic.png`` + ``tiles/`` when downscaled, world file and COG when the reference is
georeferenced) with ``merge.json``: per run ``map_to_merged`` (3x3, that run's map pixels ->
merged map pixels), the confidence and the inlier windows.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from photomap.config import Config, MosaicConfig, RegistrationConfig
from photomap.core.features import FeatureMatcher, features_confirmed, verify_overlap
from photomap.core.ifmi import Prior, Registrar
from photomap.core.mapmerge import canvas_gray, place_on_canvas, robust_similarity, similarity_params, spread_points
from photomap.core.mosaic import TiledMosaic
from photomap.errors import InputError, PhotomapError
from photomap.geo.georef import aux_xml_text, compose, png_to_map, prj_text, world_file_text
from photomap.geometry import pose_scale, to_h
from photomap.io.geotiff import write_cog_if_available
from photomap.io.mapsource import ImageSource, MapRaster, RenderFn, TileFolderSource, mosaic_source
from photomap.io.runfiles import RunFiles
from photomap.io.tilestore import DiskTileStore
from photomap.io.tileworld import write_tile_georeference
from photomap.io.trajectory_files import atomic_write_bytes, write_json
from photomap.mapping.outputs import remove_sidecars, write_png, write_tiles

log = logging.getLogger(__name__)


@dataclass
class RunMap:
    """A run's main map as a render source.

    ``render`` works in *source* pixels (map pixels for tiles or a full-resolution PNG, PNG
    pixels for a downscaled PNG without tiles); ``src_to_map`` (3x3) maps them to the run's map
    pixels. ``map_to_crs``/``epsg``: the georeference, or None.
    """

    dir: Path
    name: str
    render: RenderFn
    bounds: tuple[int, int, int, int]
    src_to_map: np.ndarray
    map_to_crs: np.ndarray | None = None
    epsg: int | None = None

    @property
    def georeferenced(self) -> bool:
        return self.map_to_crs is not None


def load_run_map(run_dir: str | Path) -> RunMap:
    """The main map of a finished run folder; InputError when it has none."""
    run = RunFiles(run_dir)
    entry = run.mosaic()
    try:
        m2c, epsg = run.georeference(entry)
    except InputError:
        m2c, epsg = None, None
    tiles = entry.get("tiles")
    if tiles and (run.dir / tiles).is_dir():
        source = TileFolderSource(run.dir / tiles, int(entry.get("tile_size") or 256))
        x, y, w, h = (int(v) for v in entry["bounds"])
        return RunMap(run.dir, run.dir.name, source, (x, y, w, h), np.eye(3), m2c, epsg)
    png = run.dir / entry["file"]
    if not png.is_file():
        raise InputError(f"map image {png} not found")
    pixel_scale = entry.get("pixel_scale") or entry.get("scale") or 1.0
    if (entry.get("scale") or 1.0) >= 1.0:  # the PNG is the map at full resolution
        origin = tuple(int(v) for v in entry["origin_xy"])
        source = ImageSource(png, origin)
        return RunMap(run.dir, run.dir.name, source, source.bounds, np.eye(3), m2c, epsg)
    log.warning("%s is downscaled and the run has no tiles: merging at its resolution", png)
    source = ImageSource(png)
    return RunMap(run.dir, run.dir.name, source, source.bounds,
                  to_h(png_to_map(entry["origin_xy"], pixel_scale)), m2c, epsg)


@dataclass
class Placement:
    """Where a run's map goes in the reference's: ``transform`` (3x3 source px -> reference
    source px) and how sure: ``confidence`` (coarse peak, then the median of the inlier windows
    of the last level), ``windows`` (inliers, tried) per level, ``reason`` when not placed."""

    placed: bool
    transform: np.ndarray | None = None
    confidence: float = 0.0
    coarse_confidence: float | None = None  # the overview's iFMI peak (None: a georeference prior)
    coarse: str = "ifmi"
    overlap: float = 0.0
    levels: list[dict] = field(default_factory=list)
    reason: str | None = None


def _render_px_to_src(x: int, y: int, w: int, h: int, ow: int, oh: int) -> np.ndarray:
    return to_h(png_to_map((x, y), (ow / w, oh / h)))


def _overview(m: RunMap, scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grey overview of the whole map at ``scale`` (<= 1), its alpha and overview px -> source px."""
    x, y, w, h = m.bounds
    image, alpha = m.render(x, y, w, h, min(1.0, scale))
    return image, alpha, _render_px_to_src(x, y, w, h, alpha.shape[1], alpha.shape[0])


def _affine(t: np.ndarray) -> np.ndarray:
    return np.asarray(t, float)[:2]


class MapRegistrar:
    """Registers run maps to a reference map (see the module docstring).

    Parameters
    ----------
    registration : the ``registration`` settings for every iFMI call.
    overview : canvas side of the coarse step, pixels.
    patch : side of a refinement window, pixels.
    windows : refinement windows per level (at most).
    min_patches : agreeing windows needed at the last level to place a run.
    min_confidence : lowest confidence of a window, and lowest median of the agreeing ones, to
        place a run.
    min_coarse : lowest overview peak to go on to the windows (which decide: windows placed
        by a wrong overview estimate do not agree). Measured: 0.04 for maps of different ground,
        0.13 for two real stills surveys of one site, 0.43-0.6 for simulated pairs.
    tol : a window's point further than this from the fitted similarity is an outlier, in
        pixels of its level.
    """

    def __init__(self, registration: RegistrationConfig = RegistrationConfig(), *, overview: int = 512,
                 patch: int = 128, windows: int = 16, min_patches: int = 3, min_confidence: float = 0.15,
                 min_coarse: float = 0.08, tol: float = 2.0) -> None:
        self.params = registration
        self.overview, self.patch = int(overview), int(patch)
        self.windows, self.min_patches = int(windows), int(min_patches)
        self.min_confidence, self.min_coarse, self.tol = float(min_confidence), float(min_coarse), float(tol)
        # map windows: their residual tails are seams and exposure steps, not a second depth
        self._coarse = Registrar((self.overview, self.overview), registration, layered_tail=False)
        self._features = FeatureMatcher("sift", working_size=0)
        self._fine = Registrar((self.patch, self.patch), registration, layered_tail=False)

    # ------------------------------------------------------------------ coarse
    def coarse(self, ref: RunMap, mov: RunMap) -> tuple[np.ndarray, float, float, np.ndarray, np.ndarray]:
        """iFMI of whole-map overviews. Returns (3x3 mov source px -> ref source px, peak,
        the overview scale, the reference overview's coverage, the moving one's warped onto it)."""
        n = self.overview
        rel = pose_scale(mov.src_to_map) / pose_scale(ref.src_to_map)  # ref source px per mov source px
        side = max(ref.bounds[2], ref.bounds[3], mov.bounds[2] * rel, mov.bounds[3] * rel)
        s = min(1.0, 0.5 * n / side)
        s_mov = min(1.0, s * rel)
        ri, ra, r_to_src = _overview(ref, s)
        mi, ma, m_to_src = _overview(mov, s_mov)
        rc, ro = place_on_canvas(canvas_gray(ri, ra), n)
        mc, mo = place_on_canvas(canvas_gray(mi, ma), n)
        reg = self._coarse.register(rc, mc)
        matrix, confidence = reg.matrix, float(reg.confidence)
        if confidence < self.min_coarse:
            # maps that share a small part of their area starve the overview POMF: features
            # (SIFT) on the overviews, kept when the overlap check confirms them
            feats = self._features.register(self._features.prepare(rc), self._features.prepare(mc))
            if feats.ok:
                check = verify_overlap(rc, mc, feats.matrix)
                if features_confirmed(feats, check):
                    matrix, confidence = feats.matrix, max(confidence, float(check.score))
        R = to_h(matrix)  # mov canvas -> ref canvas
        shift_r = np.array([[1, 0, -ro[0]], [0, 1, -ro[1]], [0, 0, 1.0]])
        shift_m = np.array([[1, 0, -mo[0]], [0, 1, -mo[1]], [0, 0, 1.0]])
        T = r_to_src @ shift_r @ R @ np.linalg.inv(shift_m) @ np.linalg.inv(m_to_src)
        cover_r = np.zeros((n, n), np.uint8)
        cover_r[ro[1]:ro[1] + ra.shape[0], ro[0]:ro[0] + ra.shape[1]] = (ra >= 128)
        cover_m = np.zeros((n, n), np.uint8)
        cover_m[mo[1]:mo[1] + ma.shape[0], mo[0]:mo[0] + ma.shape[1]] = (ma >= 128)
        warped = cv2.warpAffine(cover_m, matrix, (n, n), flags=cv2.INTER_NEAREST)
        return T, confidence, s, cover_r, warped

    def _overlap_points(self, ref: RunMap, mov: RunMap, T: np.ndarray, scale: float, margin_src: float
                        ) -> tuple[list[np.ndarray], float]:
        """Window centres (reference source px) spread over the overlap of the two maps under
        ``T``, from coverage masks at ``scale``; and the overlap's fraction of the smaller map."""
        x, y, w, h = ref.bounds
        _, ra, r_to_src = _overview(ref, scale)
        mx, my, mw, mh = mov.bounds
        s_mov = min(1.0, scale * pose_scale(T))
        _, ma, m_to_src = _overview(mov, s_mov)
        # mov overview px -> ref overview px
        A = np.linalg.inv(r_to_src) @ T @ m_to_src
        warped = cv2.warpAffine((ma >= 128).astype(np.uint8), A[:2], (ra.shape[1], ra.shape[0]),
                                flags=cv2.INTER_NEAREST)
        both = (ra >= 128) & (warped > 0)
        smaller = min(int((ra >= 128).sum()), int((ma >= 128).sum() * abs(np.linalg.det(A[:2, :2]))))
        fraction = float(both.sum()) / max(smaller, 1)
        margin = margin_src * scale
        points = spread_points(both, margin, self.windows, spacing=1.3 * margin)
        return [r_to_src @ np.array([px, py, 1.0]) for px, py in points], fraction

    # ------------------------------------------------------------------ fine
    def _window(self, ref: RunMap, mov: RunMap, T: np.ndarray, centre: np.ndarray, scale: float):
        """Reference and moving windows on one grid around ``centre`` (ref source px) at
        ``scale``; (ref gray, mov gray, window px -> ref source px) or None if not covered."""
        P = self.patch
        w_src = max(1, int(round(P / scale)))
        x0 = int(round(centre[0] - w_src / 2.0))
        y0 = int(round(centre[1] - w_src / 2.0))
        rx, ry, rw, rh = ref.bounds
        if x0 < rx or y0 < ry or x0 + w_src > rx + rw or y0 + w_src > ry + rh:
            return None
        s_eff = P / w_src
        ri, ra = ref.render(x0, y0, w_src, w_src, min(1.0, s_eff))
        if ra.shape != (P, P) or (ra >= 250).mean() < 0.97:
            return None
        A = _render_px_to_src(x0, y0, w_src, w_src, P, P)  # window px -> ref source px
        Tinv = np.linalg.inv(T)
        corners = np.array([[-1, -1, 1], [P, -1, 1], [-1, P, 1], [P, P, 1]], float).T
        mc = (Tinv @ A @ corners)[:2]
        mx, my, mw, mh = mov.bounds
        bx0 = max(int(math.floor(mc[0].min())) - 2, mx)
        by0 = max(int(math.floor(mc[1].min())) - 2, my)
        bx1 = min(int(math.ceil(mc[0].max())) + 3, mx + mw)
        by1 = min(int(math.ceil(mc[1].max())) + 3, my + mh)
        if bx1 - bx0 < 4 or by1 - by0 < 4:
            return None
        s_mov = min(1.0, s_eff * pose_scale(T))
        mi, ma = mov.render(bx0, by0, bx1 - bx0, by1 - by0, s_mov)
        B = _render_px_to_src(bx0, by0, bx1 - bx0, by1 - by0, ma.shape[1], ma.shape[0])
        W = np.linalg.inv(B) @ Tinv @ A  # window px -> mov render px
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        mg = cv2.warpAffine(cv2.cvtColor(mi, cv2.COLOR_BGR2GRAY) if mi.ndim == 3 else mi, W[:2], (P, P),
                            flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        mask = cv2.warpAffine(ma, W[:2], (P, P), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if (mask >= 250).mean() < 0.97:
            return None
        rg = cv2.cvtColor(ri, cv2.COLOR_BGR2GRAY) if ri.ndim == 3 else ri
        return rg, mg, A

    def refine_level(self, ref: RunMap, mov: RunMap, T: np.ndarray, scale: float, centres: list[np.ndarray]
                     ) -> tuple[np.ndarray | None, dict]:
        """One level: register windows at ``scale`` around ``centres``; the refitted T or None."""
        P = self.patch
        q = np.array([(P - 1) / 2.0, (P - 1) / 2.0, 1.0])
        src, dst, conf = [], [], []
        prior = Prior(angle_deg=0.0, angle_tol_deg=4.0, scale=1.0, scale_tol=0.04, shift=(0.0, 0.0),
                      shift_tol=P / 4.0)
        tried = 0
        for c in centres:
            win = self._window(ref, mov, T, c, scale)
            if win is None:
                continue
            tried += 1
            rg, mg, A = win
            reg = self._fine.register(rg, mg, prior)
            if reg.confidence < self.min_confidence:
                continue
            R = to_h(reg.matrix)  # mov window px -> ref window px
            src.append((np.linalg.inv(T) @ A @ q)[:2])
            dst.append((A @ R @ q)[:2])
            conf.append(float(reg.confidence))
        info = {"scale": round(scale, 6), "windows_tried": tried, "windows_confident": len(src), "inliers": 0,
                "median_confidence": None, "rms_px": None}
        if len(src) < 2:
            return None, info
        src_a, dst_a, conf_a = np.array(src), np.array(dst), np.array(conf)
        tol_src = self.tol / scale
        # with few windows, a fit needs them all; with more, min_patches must agree
        fit = robust_similarity(src_a, dst_a, tol_src, min_inliers=min(self.min_patches, len(src)))
        if fit is None:
            return None, info
        S, keep = fit
        res = np.hypot(*((src_a[keep] @ S[:2, :2].T + S[:2, 2]) - dst_a[keep]).T) * scale
        info.update({"inliers": int(keep.sum()), "median_confidence": round(float(np.median(conf_a[keep])), 4),
                     "rms_px": round(float(np.sqrt(np.mean(res ** 2))), 4)})
        if len(src) == 2 and keep.sum() == 2:  # two windows fit any similarity: only the shift
            mean_shift = (dst_a - src_a @ T[:2, :2].T - T[:2, 2]).mean(axis=0)
            S = T.copy()
            S[:2, 2] += mean_shift
        return S, info

    def place(self, ref: RunMap, mov: RunMap, prior: np.ndarray | None = None) -> Placement:
        """Place ``mov`` in ``ref``'s map; ``prior`` (3x3 source px -> ref source px, e.g. from
        both georeferences) replaces the coarse iFMI step."""
        if prior is not None:
            T, coarse_conf, how = np.asarray(prior, float), None, "georeference"
            side = max(ref.bounds[2], ref.bounds[3])
            s0 = min(1.0, 0.5 * self.overview / side)
        else:
            T, coarse_conf, s0, _, _ = self.coarse(ref, mov)
            how = "ifmi"
            if coarse_conf < self.min_coarse:
                return Placement(False, None, coarse_conf, coarse_conf, how,
                                 reason=f"the maps do not match (overview peak {coarse_conf:.3f} "
                                        f"< {self.min_coarse})")
        # levels: from a few times the overview's resolution up to the maps' own
        scales = []
        s = min(1.0, 4.0 * s0)
        while s < 1.0:
            scales.append(s)
            s = min(1.0, s * 4.0)
        scales.append(1.0)
        levels: list[dict] = []
        overlap = 0.0
        last_conf = None
        for k, s in enumerate(scales):
            centres, fraction = self._overlap_points(ref, mov, T, min(1.0, s0 * 2), 0.6 * self.patch / s)
            if k == 0:
                overlap = fraction
            if not centres:
                return Placement(False, None, 0.0, coarse_conf, how, overlap, levels,
                                 reason=f"no overlap found (overlap {fraction:.1%} of the smaller map)")
            S, info = self.refine_level(ref, mov, T, s, centres)
            levels.append(info)
            if S is None:
                return Placement(False, None, 0.0, coarse_conf, how, overlap, levels,
                                 reason=f"windows at scale {s:.3g} do not agree ({info['windows_confident']} "
                                        f"confident of {info['windows_tried']})")
            T = S
            last_conf = info["median_confidence"]
        final = levels[-1]
        if final["inliers"] < min(self.min_patches, max(final["windows_tried"], 1)) or final["inliers"] < 2:
            return Placement(False, None, 0.0, coarse_conf, how, overlap, levels,
                             reason=f"only {final['inliers']} agreeing windows at full resolution")
        if last_conf is None or last_conf < self.min_confidence:
            return Placement(False, None, 0.0, coarse_conf, how, overlap, levels,
                             reason=f"windows at full resolution are not confident ({last_conf})")
        return Placement(True, T, float(last_conf), coarse_conf, how, overlap, levels)


def georeference_prior(ref: RunMap, mov: RunMap) -> np.ndarray | None:
    """3x3 mov source px -> ref source px through both georeferences (same UTM zone), or None."""
    if not (ref.georeferenced and mov.georeferenced) or ref.epsg != mov.epsg:
        return None
    r = to_h(ref.map_to_crs) @ ref.src_to_map
    m = to_h(mov.map_to_crs) @ mov.src_to_map
    return np.linalg.inv(r) @ m


def paint(mosaic: TiledMosaic, source: RunMap, transform: np.ndarray, chunk: int = 1024) -> None:
    """Paint a run's map into ``mosaic`` through ``transform`` (3x3 source px -> mosaic px), in
    chunks of at most ``chunk`` source pixels a side (bounded memory)."""
    x, y, w, h = source.bounds
    pad = mosaic.border + 2  # bilinear interpolation at a chunk's edge reads its neighbours
    for cy in range(y, y + h, chunk):
        for cx in range(x, x + w, chunk):
            bx, by = max(cx - pad, x), max(cy - pad, y)
            bw = min(cx + chunk + pad, x + w) - bx
            bh = min(cy + chunk + pad, y + h) - by
            image, alpha = source.render(bx, by, bw, bh, 1.0)
            if not (alpha == 255).any():
                continue
            pose = np.asarray(transform, float) @ np.array([[1.0, 0, bx], [0, 1.0, by], [0, 0, 1.0]])
            mosaic.add(image, pose[:2], mask=alpha == 255)


def merge_runs(run_dirs: Sequence[str | Path], out_dir: str | Path, cfg: Config, *,
               use_georeference: bool = True, registrar: MapRegistrar | None = None) -> dict:
    """Merge the main maps of ``run_dirs`` (the first is the reference) into ``out_dir``;
    returns the body of ``merge.json``.

    ``use_georeference``: when a run and the reference are both georeferenced, their GPS
    placement replaces the coarse iFMI step (the windows still measure on the images).
    """
    if len(run_dirs) < 2:
        raise InputError("merge needs at least two run folders")
    maps = [load_run_map(d) for d in run_dirs]
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create output folder {out}: {exc.strerror}") from None
    registrar = registrar or MapRegistrar(cfg.registration)
    ref = maps[0]
    ref_to_merged = ref.src_to_map  # merged map px = the reference's map px
    entries = [{"run": str(ref.dir), "reference": True, "placed": True,
                "map_to_merged": np.eye(3).tolist(), "confidence": 1.0}]
    placed: list[tuple[RunMap, np.ndarray]] = [(ref, ref_to_merged)]
    for m in maps[1:]:
        prior = georeference_prior(ref, m) if use_georeference else None
        try:
            p = registrar.place(ref, m, prior)
        except (ValueError, cv2.error) as exc:
            p = Placement(False, reason=f"registration failed: {exc}")
        entry: dict = {"run": str(m.dir), "reference": False, "placed": p.placed,
                       "confidence": round(p.confidence, 4), "coarse": p.coarse,
                       "coarse_confidence": None if p.coarse_confidence is None else round(p.coarse_confidence, 4),
                       "overlap": round(p.overlap, 4),
                       "levels": p.levels}
        if p.placed:
            src_to_merged = ref.src_to_map @ p.transform
            map_to_merged = src_to_merged @ np.linalg.inv(m.src_to_map)
            angle, scale = similarity_params(map_to_merged)
            entry.update({"map_to_merged": map_to_merged.tolist(), "angle_deg": round(angle, 4),
                          "scale": round(scale, 6)})
            placed.append((m, src_to_merged))
            log.info("%s placed: confidence %.2f, rotation %.1f deg, scale %.3f", m.dir.name, p.confidence,
                     angle, scale)
        else:
            entry.update({"map_to_merged": None, "reason": p.reason})
            log.warning("%s not placed: %s", m.dir.name, p.reason)
        entries.append(entry)
    # the merged map, painted reference first
    # border 0: the maps' own coverage already ends where their pixels do
    mcfg: MosaicConfig = dataclasses.replace(cfg.mosaic, border=0)
    store = DiskTileStore(mcfg.cache_dir) if mcfg.max_tiles_in_memory else None
    try:
        merged = TiledMosaic(mcfg, store)
        for m, t in placed:
            paint(merged, m, t)
        summary = _write_merged(out, merged, ref, cfg)
    finally:
        if store is not None:
            store.close()
    summary.update({"reference": str(ref.dir), "runs": entries,
                    "placed": sum(e["placed"] for e in entries), "not_placed": [e["run"] for e in entries
                                                                                 if not e["placed"]],
                    "conventions": "map_to_merged: 3x3, a run's map pixels (its run.json/trajectory.csv "
                                   "frame) -> merged map pixels (the reference run's map frame); OpenCV "
                                   "pixel centres"})
    write_json(out / "merge.json", summary)
    return summary


def _write_merged(out: Path, merged: TiledMosaic, ref: RunMap, cfg: Config) -> dict:
    """mosaic.png (+ tiles/ when downscaled), world file and COG when the reference is georeferenced."""
    info = write_png(out / "mosaic.png", merged, cfg.output.max_mosaic_px)
    if info is None:
        raise PhotomapError("the merged map is empty")
    remove_sidecars(out, "mosaic.png")
    if info["scale"] < 1.0:
        write_tiles(out / "tiles", merged)
        info["tiles"] = "tiles"
        info["tile_size"] = merged.tile_size
    summary: dict = {"mosaic": info, "georeference": None}
    if ref.georeferenced:
        m2c = np.asarray(ref.map_to_crs, float)
        png = compose(m2c, png_to_map(info["origin_xy"], info["pixel_scale"]))
        atomic_write_bytes(out / "mosaic.pgw", world_file_text(png).encode())
        atomic_write_bytes(out / "mosaic.prj", prj_text(ref.epsg).encode())
        atomic_write_bytes(out / "mosaic.png.aux.xml", aux_xml_text(ref.epsg).encode())
        summary["georeference"] = {"crs": f"EPSG:{ref.epsg}", "map_to_crs": m2c.tolist(),
                                   "metres_per_pixel": pose_scale(m2c),
                                   "world_file": "mosaic.pgw"}
        if info.get("tiles"):
            try:
                write_tile_georeference(out / "tiles", merged.tile_size, m2c, ref.epsg)
            except (PhotomapError, OSError) as exc:
                log.warning("tile world files not written: %s", exc)
        if cfg.output.geotiff:
            try:
                cog = write_cog_if_available(out / "map.tif", MapRaster(mosaic_source(merged), merged.bounds(),
                                                                        m2c, ref.epsg))
                if cog is not None:
                    summary["cog"] = cog
            except (PhotomapError, OSError, RuntimeError) as exc:
                log.warning("GeoTIFF not written: %s", exc)
    return summary
