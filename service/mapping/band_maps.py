"""The map of every band of a multi-band flight, written after the run from the final poses.

The pipeline maps the registering band (:class:`~photomap.drivers.images.ImageFolderSource`);
its poses map the registering band's pixels (or their rectified view) to map pixels. At the end
of the run :func:`write_band_maps`:

1. aligns each posed capture's bands to its registering band (:func:`photomap.core.bands.align_capture`,
   each band started from the previous capture's homography); a band that does not fit keeps the
   previous capture's homography (the identity before the first fit), counted and reported in one
   line; and samples each band's 16-bit range over the flight
   (:func:`~photomap.core.bands.robust_range_16bit`; the registering band keeps the one the frames
   were mapped with);
2. paints each band in turn into a map of its own (:class:`~photomap.core.mosaic.TiledMosaic`, gray,
   no exposure gain, the band's own depth: a 16-bit band's map holds its raw values), band
   ``b``'s pixels going through ``H_b`` onto the registering band's, then the run's lens
   undistortion and frame mask (as the frames were prepared), the frame's rectification (if any)
   and pose; each capture's band file is read again (one capture's bands in memory at a time, one
   band's map);
3. writes ``mosaic_band_{name}.png`` per band (8-bit, stretched per band over the flight as
   ``run.json`` ``bands.ranges`` says, BGRA transparent where empty) on the very pixel grid of
   ``mosaic.png`` (same rectangle, same downscale), ``composite.png`` (three bands as red, green,
   blue: ``output.composite``, default false colour nir,red,green) and, georeferenced and with the
   ``geo`` extra, ``map_bands.tif``: one north-up GeoTIFF band per camera band on the grid of
   ``map.tif``, the camera's values unstretched (uint16 when a band is 16-bit, else uint8; band
   descriptions = band names; 0 = no data, a covered pixel's 0 is written as 1).

Only the main map (the largest segment) is written per band.

A single-band flight of 16-bit stills gets the same for its one band (:func:`write_raw_map`):
``map_raw.tif``, the stills' raw values (uint16; 3 bands R, G, B for colour stills) on the grid of
``map.tif``, painted from each posed still read again; its 8-bit map is ``mosaic.png`` itself.
A live source of raw 16-bit frames (a Y16 camera) gets it from the frames
:class:`~photomap.mapping.raw_frames.RawFrameKeeper` kept during the run.
"""

from __future__ import annotations

import logging
import os
import re
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from photomap.config import MosaicConfig
from photomap.core.bands import BandAlignment, align_capture, corner_shift_px, robust_range_16bit
from photomap.core.stretch import to_8bit
from photomap.core.mosaic import TiledMosaic
from photomap.drivers.captures import BAND_ALIASES, Capture, read_band
from photomap.geometry import pose_scale
from photomap.io.geotiff import north_up_grid, rasterio_available, resample_blocks
from photomap.io.mapsource import MapRaster, mosaic_source
from photomap.io.pngstream import PngStreamWriter
from photomap.io.tilestore import DiskTileStore
from photomap.mapping.frameprep import FramePrep
from photomap.mapping.rows import RowView

log = logging.getLogger(__name__)

#: Captures sampled (spread over the flight) for each band's 16-bit range.
RANGE_SAMPLES = 8


def band_file_name(band: str) -> str:
    """``mosaic_band_{name}.png`` with the band name in lower case, spaces as underscores."""
    return f"mosaic_band_{re.sub(r'[^a-z0-9]+', '_', band.lower()).strip('_')}.png"


def composite_bands(spec: str, names: Sequence[str]) -> tuple[str, str, str] | None:
    """The bands of ``composite.png`` as (red, green, blue) of the picture: ``spec`` (e.g.
    ``nir,red,green``; names matched in any case, ``rededge``/``re`` for ``Red edge``) or, when
    empty, false colour NIR/red/green where the camera has them, else red/green/blue, else the first
    three bands. None when fewer than 3 bands (or ``spec`` names a band the camera lacks: logged)."""
    lower = {n.lower(): n for n in names}

    def find(text: str) -> str | None:
        t = text.strip().lower()
        return lower.get(t) or lower.get(BAND_ALIASES.get(t, t).lower())

    if spec.strip():
        picked = [find(p) for p in spec.split(",")]
        if None in picked or len(picked) != 3:
            log.warning("output.composite %r: no such bands among %s; composite.png not written", spec,
                        ", ".join(names))
            return None
        return tuple(picked)  # type: ignore[return-value]
    for choice in (("nir", "red", "green"), ("red", "green", "blue")):
        picked = [find(p) for p in choice]
        if None not in picked:
            return tuple(picked)  # type: ignore[return-value]
    return tuple(names[:3]) if len(names) >= 3 else None  # type: ignore[return-value]


def _align_all(captures: Sequence[Capture], names: Sequence[str], reference: str,
               indices: Sequence[int]) -> tuple[dict[int, list[np.ndarray]], dict]:
    """Band homographies of every posed capture (frame index -> per band H, band order ``names``)
    and what the fits were (failures, corner shifts)."""
    r = names.index(reference)
    previous: list[np.ndarray | None] = [None] * len(names)
    out: dict[int, list[np.ndarray]] = {}
    failed: list[tuple[int, str, str]] = []
    shifts: dict[str, list[float]] = {n: [] for n in names}
    for index in indices:
        capture = captures[index]
        images = [read_band(capture.path(n)) if capture.path(n) is not None else None for n in names]
        ref = images[r]
        if ref is None:
            continue
        size = (ref.shape[1], ref.shape[0])
        # a missing band file: a blank stand-in (its fit fails; it keeps the previous homography)
        stand_in = [img if img is not None else np.zeros_like(ref) for img in images]
        fits: list[BandAlignment] = align_capture(stand_in, r, init=previous)
        hs = []
        for b, (name, fit) in enumerate(zip(names, fits)):
            if b != r and (images[b] is None or not fit.ok):
                failed.append((index, name, "no file" if images[b] is None else (fit.reason or "no fit")))
                H = previous[b] if previous[b] is not None else np.eye(3)
            else:
                H = fit.H
                previous[b] = H
                if b != r:
                    shifts[name].append(corner_shift_px(H, size))
            hs.append(H)
        out[index] = hs
    if failed:
        index, name, reason = failed[0]
        log.warning("band alignment failed for %d band image(s) of %d captures (first: capture %d, %s: %s): "
                    "the previous capture's homography is used", len(failed), len(out), index, name, reason)
    report = {"captures": len(out), "failed": len(failed),
              "median_corner_shift_px": {n: (round(float(np.median(v)), 3) if v else None)
                                         for n, v in shifts.items() if n != reference}}
    return out, report


def _ranges(captures: Sequence[Capture], names: Sequence[str], indices: Sequence[int],
            reference: str, reference_range: tuple[float, float] | None) -> dict[str, tuple[float, float] | None]:
    """Each band's 16-bit range over the flight (None: 8-bit band, as stored)."""
    step = max(1, len(indices) // RANGE_SAMPLES)
    picked = list(indices)[::step][:RANGE_SAMPLES]
    out: dict[str, tuple[float, float] | None] = {}
    for name in names:
        if name == reference:
            out[name] = reference_range
            continue
        sample = [img for i in picked if (p := captures[i].path(name)) is not None and (img := read_band(p)) is not None]
        out[name] = robust_range_16bit(sample) if any(s.dtype == np.uint16 for s in sample) else None
    return out


def _warp(image: np.ndarray, inside: np.ndarray | None, K: np.ndarray, size: tuple[int, int]
          ) -> tuple[np.ndarray, np.ndarray]:
    """``image`` and its validity (None: all valid) through the homography ``K`` onto a ``size``
    grid; the validity eroded by a pixel (no interpolated edge)."""
    warped = cv2.warpPerspective(image, K, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    valid = np.full(image.shape[:2], 255, np.uint8) if inside is None else inside
    valid = cv2.warpPerspective(valid, K, size, flags=cv2.INTER_NEAREST)
    return warped, cv2.erode(valid, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)


def _frame_view(image: np.ndarray, H: np.ndarray, rect: np.ndarray | None, prep: FramePrep | None,
                size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray | None]:
    """A band image as the map's frame was painted: through ``H`` onto the registering band's pixels
    (the input frame), the lens undistortion and frame mask of ``prep`` (as
    :class:`~photomap.mapping.frameprep.FramePrep` prepared the frame), then the rectification
    ``rect``. Returns the view and its validity (None: all valid)."""
    undistort = prep.undistortion if prep is not None else None
    mask = prep.mask if prep is not None else None
    own = np.allclose(H, np.eye(3)) and image.shape[:2] == (size[1], size[0])
    if undistort is None and mask is None:  # one warp for the whole chain
        K = H if rect is None else rect @ H
        if np.allclose(K, np.eye(3)) and own:  # the frame's own pixels (one-band flights)
            return image, None
        return _warp(image, None, K, size)
    warped, inside = (image, None) if own else _warp(image, None, H, size)
    if undistort is not None:
        warped = undistort.apply(warped)
        inside = undistort.apply_mask(inside if inside is not None else np.full(warped.shape[:2], 255, np.uint8))
    if mask is not None:  # the lens's valid view and capture.mask
        inside = mask if inside is None else cv2.min(inside, mask)
    return (warped, inside) if rect is None else _warp(warped, inside, rect, size)


def _paint_band(read: Callable[[int], np.ndarray | None], rows: Sequence[RowView],
                band_to_frame: Callable[[int], np.ndarray | None], frame_size: tuple[int, int], cfg: MosaicConfig,
                view: Callable[[int], np.ndarray | None], store: DiskTileStore | None, *,
                prep: FramePrep | None = None, dtype: type = np.uint8, channels: int = 1) -> TiledMosaic:
    """One band of every posed frame painted into a map of its own (``dtype``, ``channels``; no
    exposure gain; spilling to ``store`` under ``mosaic.max_tiles_in_memory``, as the run's maps
    do) with the frames' final poses: ``read(frame)`` gives the band's image as stored (None: none),
    ``band_to_frame(frame)`` the 3x3 homography from its pixels to the registering band's (None:
    the frame is not painted), then the run's lens undistortion and frame mask (``prep``),
    ``view(frame)`` (the rectification, if any) and the pose (:func:`_frame_view`).
    A uint8 image goes into a uint16 map as it is; a uint16 one into a uint8 map over 0..65535."""
    mosaic = TiledMosaic(replace(cfg, channels=channels, exposure="none"), store, dtype=dtype)
    for row in rows:
        H = band_to_frame(row.frame)
        image = read(row.frame) if H is not None else None
        if image is None:
            continue
        if image.dtype != mosaic.dtype:
            image = image.astype(mosaic.dtype) if image.dtype == np.uint8 else to_8bit(image, (0.0, 65535.0))
        warped, inside = _frame_view(image, H, view(row.frame), prep, frame_size)
        mosaic.add(warped, np.asarray(row.M, np.float64), inside)
    return mosaic


def _write_png(path: Path, mosaic: TiledMosaic, bounds: tuple[int, int, int, int], scale: float,
               value_range: tuple[float, float] | None) -> None:
    """The band's map as an 8-bit BGRA PNG (a 16-bit map stretched over ``value_range``); at full
    resolution a tile row at a time, downscaled at once (the area weights span the rows)."""
    x, y, w, h = bounds
    size = (w, h) if scale == 1 else (max(1, round(w * scale)), max(1, round(h * scale)))
    ts = mosaic.tile_size
    cuts = [y, *range((y // ts + 1) * ts, y + h, ts), y + h] if scale == 1 else [y, y + h]  # tile rows
    strips = list(zip(cuts[:-1], np.diff(cuts).tolist()))
    with PngStreamWriter(path, size[0], size[1], channels=4) as png:
        for top, rows in strips:
            image, alpha, _ = mosaic.render(scale=scale, bounds=(x, top, w, rows))
            if image.dtype != np.uint8:
                image = to_8bit(image, value_range or (0.0, 65535.0))
            png.write(np.dstack([cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), alpha]))


def _write_composite(out_dir: Path, files: dict[str, str], bands: tuple[str, str, str]) -> str:
    """``composite.png`` from three band PNGs already written (red, green, blue of the picture)."""
    layers = [cv2.imread(str(out_dir / files[n]), cv2.IMREAD_UNCHANGED) for n in bands]
    if any(layer is None for layer in layers):
        raise OSError("a band map could not be read back")
    alpha = np.minimum.reduce([layer[..., 3] for layer in layers])
    bgra = np.dstack([layers[2][..., 0], layers[1][..., 0], layers[0][..., 0], alpha])
    with PngStreamWriter(out_dir / "composite.png", bgra.shape[1], bgra.shape[0], channels=4) as png:
        png.write(bgra)
    return "composite.png"


class _BandGeoTiff:
    """A north-up GeoTIFF of one or more band maps (``dtype``, one band per name, 0 = no data) on
    the grid ``map.tif`` gets over the main map's ``bounds`` (:func:`photomap.io.geotiff.resample_blocks`
    at the map's own resolution)."""

    def __init__(self, path: Path, names: Sequence[str], bounds: tuple[int, int, int, int],
                 map_to_crs: np.ndarray, epsg: int, dtype: type = np.uint8) -> None:
        import rasterio
        from rasterio.transform import Affine
        self.path, self.bounds, self.map_to_crs, self.epsg = path, bounds, np.asarray(map_to_crs, float), epsg
        self.gsd = pose_scale(self.map_to_crs)
        west, north, self.width, self.height = north_up_grid(bounds, self.map_to_crs, self.gsd)
        self.block = 512
        fd, self.tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.close(fd)
        self.transform = Affine(self.gsd, 0.0, west, 0.0, -self.gsd, north)
        self.dtype = np.dtype(dtype)
        self.info = {"file": path.name, "crs": f"EPSG:{epsg}", "gsd_m": self.gsd, "size": [self.width, self.height],
                     "dtype": self.dtype.name, "bands": list(names)}
        self._env = rasterio.Env(GDAL_CACHEMAX=128)
        self._env.__enter__()
        self.dst = rasterio.open(self.tmp, "w", driver="GTiff", width=self.width, height=self.height,
                                 count=len(names), dtype=self.dtype.name, crs=f"EPSG:{epsg}",
                                 transform=self.transform, tiled=True, blockxsize=self.block,
                                 blockysize=self.block, compress="DEFLATE", interleave="band", nodata=0,
                                 bigtiff="IF_SAFER")
        for i, name in enumerate(names, 1):
            self.dst.set_band_description(i, name)

    def write_band(self, i: int, mosaic: TiledMosaic) -> None:
        """Band ``i`` (from 1; a 3-channel map: bands ``i .. i + 2`` as R, G, B) from ``mosaic``."""
        from rasterio.windows import Window
        raster = MapRaster(mosaic_source(mosaic), self.bounds, self.map_to_crs, self.epsg)
        for window, got in resample_blocks(raster, self.gsd, self.block):
            if got is None:
                continue
            b, g, r, alpha = got
            layers = [b] if mosaic.channels == 1 else [r, g, b]
            for k, layer in enumerate(layers):
                data = np.where(alpha >= 128, np.maximum(layer, 1), 0).astype(self.dtype)
                self.dst.write(data, i + k, window=Window(*window))

    def close(self, ok: bool) -> dict | None:
        self.dst.close()
        self._env.__exit__(None, None, None)
        if ok:
            os.chmod(self.tmp, 0o644)
            os.replace(self.tmp, self.path)
            return self.info
        Path(self.tmp).unlink(missing_ok=True)
        return None


def write_band_maps(out_dir: Path, source, rows: Sequence[RowView], frame_size: tuple[int, int],
                    cfg: MosaicConfig, main: dict, *, composite: str = "", georef: tuple[np.ndarray, int] | None = None,
                    geotiff: bool = True, view: Callable[[int], np.ndarray | None] = lambda index: None,
                    prep: FramePrep | None = None) -> dict:
    """Write the band maps of a multi-band flight (module docstring); returns ``run.json`` ``bands``.

    Parameters
    ----------
    source : the :class:`~photomap.drivers.images.ImageFolderSource` (its ``captures``, ``band``,
        ``band_range``); frame ``i`` is ``source.captures[i]``.
    rows : the main map's glued rows (final poses).
    main : the main map's ``run.json`` ``mosaics[]`` entry (``bounds``, ``scale``: the band maps use
        ``mosaic.png``'s pixel grid).
    georef : ``(map_to_crs 2x3, epsg)`` of the main map, or None (no GeoTIFF).
    view : frame index -> 3x3 homography from the (undistorted) input frame to the view the map
        got (the telemetry's tilt rectification), or None.
    prep : the run's lens undistortion and frame mask (None: neither).
    """
    captures: list[Capture] = source.captures
    names = list(max((c.bands for c in captures), key=len))
    reference = source.band
    indices = sorted({int(r.frame) for r in rows if 0 <= int(r.frame) < len(captures)})
    log.info("band maps: aligning the %d other bands of %d captures to %s, then one map per band",
             len(names) - 1, len(indices), reference)
    homographies, alignment = _align_all(captures, names, reference, indices)
    ranges = _ranges(captures, names, indices, reference, source.band_range)
    bounds = tuple(int(v) for v in main["bounds"])
    scale = float(main["scale"])
    deep = {n: ranges[n] is not None for n in names}  # 16-bit bands: maps of their raw values
    tif = None
    if georef is not None and geotiff and rasterio_available():
        tif = _BandGeoTiff(out_dir / "map_bands.tif", names, bounds, *georef,
                           dtype=np.uint16 if any(deep.values()) else np.uint8)
    files: dict[str, str] = {}
    ok = True
    try:
        for b, name in enumerate(names):
            store = DiskTileStore() if cfg.max_tiles_in_memory else None  # a temporary folder
            try:
                mosaic = _paint_band(
                    lambda i, n=name: read_band(p) if (p := captures[i].path(n)) is not None else None,
                    rows, lambda i, b=b: homographies[i][b] if i in homographies else None, frame_size, cfg,
                    view, store, prep=prep, dtype=np.uint16 if deep[name] else np.uint8)
                if mosaic.bounds() is None:
                    continue
                files[name] = band_file_name(name)
                _write_png(out_dir / files[name], mosaic, bounds, scale, ranges[name])
                if tif is not None:
                    tif.write_band(b + 1, mosaic)
            finally:
                if store is not None:
                    store.close()
    except BaseException:
        ok = False
        raise
    finally:
        written = tif.close(ok) if tif is not None else None
    out = {"registering": reference, "bands": names, "files": files, "alignment": alignment,
           "ranges": {n: (None if r is None else [round(r[0], 1), round(r[1], 1)]) for n, r in ranges.items()},
           "stretch": "8-bit: each band's range (16-bit values) -> 0..255, linear; map_bands.tif: unstretched",
           "geotiff": written}
    picked = composite_bands(composite, names)
    if picked is not None and all(n in files for n in picked):
        out["composite"] = {"file": _write_composite(out_dir, files, picked), "rgb": list(picked)}
    log.info("band maps: %s%s%s", ", ".join(files.values()),
             f", {out['composite']['file']} ({'/'.join(picked)})" if "composite" in out else "",
             f", {written['file']}" if written else "")
    return out


def write_raw_map(out_dir: Path, raw_frame: Callable[[int], np.ndarray | None], rows: Sequence[RowView],
                  frame_size: tuple[int, int], cfg: MosaicConfig, main: dict, georef: tuple[np.ndarray, int],
                  view: Callable[[int], np.ndarray | None] = lambda index: None,
                  prep: FramePrep | None = None) -> dict | None:
    """``map_raw.tif`` of a single-band flight of 16-bit frames (module docstring); returns its
    ``run.json`` ``exports.raw`` entry (with ``frames``: how many were painted), or None (nothing
    written) when the frames are not 16-bit or rasterio is missing.

    ``raw_frame(i)``: frame ``i``'s pixels as stored when they are 16-bit (uint16, gray or BGR),
    else None (cheaply: it is asked for every row); the frames are painted with ``rows``' poses
    (the main map's) and ``view``, on the grid of ``map.tif`` (``main``: the main map's
    ``run.json`` ``mosaics[]`` entry, ``georef``: its ``(map_to_crs 2x3, epsg)``; ``prep``: the
    run's lens undistortion and frame mask).
    """
    first = next((image for r in rows if (image := raw_frame(int(r.frame))) is not None), None)
    if first is None or first.dtype != np.uint16 or not rasterio_available():
        return None
    channels = 1 if first.ndim == 2 else first.shape[2]
    names = ["raw"] if channels == 1 else ["red", "green", "blue"]
    bounds = tuple(int(v) for v in main["bounds"])
    tif = _BandGeoTiff(out_dir / "map_raw.tif", names, bounds, *georef, dtype=np.uint16)
    store = DiskTileStore() if cfg.max_tiles_in_memory else None
    ok = False
    painted = 0

    def read(index: int) -> np.ndarray | None:
        nonlocal painted
        image = raw_frame(index)
        painted += image is not None
        return image

    try:
        identity = np.eye(3)
        mosaic = _paint_band(read, rows, lambda i: identity, frame_size, cfg, view, store, prep=prep,
                             dtype=np.uint16, channels=channels)
        if mosaic.bounds() is not None:
            tif.write_band(1, mosaic)
            ok = True
    finally:
        written = tif.close(ok)
        if store is not None:
            store.close()
    if written is not None:
        written["frames"] = painted
        log.info("raw map: the 16-bit values of %d of %d posed frames in map_raw.tif", painted, len(rows))
    return written
