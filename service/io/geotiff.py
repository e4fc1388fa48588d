"""A north-up Cloud-Optimized GeoTIFF of the map, written block by block (needs the ``geo`` extra).

The map's georeference is a similarity (rotation, scale, y flip) from map pixels to UTM metres;
GIS tools want a grid aligned with easting and northing. :func:`write_cog` builds that grid
(pixel size ``gsd`` metres; by default the map's own resolution), and fills it one
``block`` x ``block`` window at a time: each window's pixel centres are mapped back to source
pixels, the source region under them is rendered (area-averaged when the GeoTIFF is coarser than
the source) and resampled bilinearly, alpha-premultiplied so that empty map pixels do not darken
the edges. Only one window (and the source region under it) is in memory at a time. The window
loop (:func:`resample_blocks`) also writes the raw 16-bit GeoTIFFs of
:mod:`photomap.mapping.band_maps` on the same grid.

The windows go into a temporary tiled GeoTIFF (sparse: blocks the map does not cover are not
written; uncompressed: written once and read twice, and photo pixels gain a quarter at most from
ZSTD, which took a fifth of the COG's CPU time), which GDAL's COG driver then copies into the final layout: RGBA (band 4 is alpha),
512-pixel tiles, DEFLATE (level 1: a third of level 6's time for 6 % more bytes, the same pixels)
with the horizontal predictor, compressed on every core, overviews down to one tile
(area-averaged, alpha-aware), the CRS inside. ``gdalinfo`` reports ``LAYOUT=COG``.

Conventions: rasterio/GDAL geotransforms address pixel *corners* (``(0, 0)`` = the top-left
corner of the top-left pixel); the map and the render functions use OpenCV pixel *centres*.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from photomap.core.mosaic import unpremultiply
from photomap.errors import InputError
from photomap.geo.georef import compose, png_to_map
from photomap.geometry import pose_scale
from photomap.io.mapsource import MapRaster, RenderFn

log = logging.getLogger(__name__)

GEO_EXTRA_HINT = "pip install 'ifmi-photomap[geo]' (rasterio)"


def rasterio_available() -> bool:
    """True when rasterio (the ``geo`` extra) can be imported."""
    try:
        import rasterio  # noqa: F401
    except ImportError:
        return False
    return True


def _invert(m: np.ndarray) -> np.ndarray:
    m = np.asarray(m, float)
    return cv2.invertAffineTransform(m)


def north_up_grid(bounds: tuple[int, int, int, int], src_to_crs: np.ndarray, gsd: float
                  ) -> tuple[float, float, int, int]:
    """The north-up grid over a source rectangle: ``(west, north, width, height)``.

    ``west``/``north`` are the outer edges (metres, multiples of ``gsd``) of the grid whose
    ``gsd``-metre pixels cover the rotated rectangle ``bounds`` (source pixels; its outer edges
    are half a pixel beyond the extreme pixel centres).
    """
    x, y, w, h = bounds
    corners = np.array([[x - 0.5, y - 0.5], [x + w - 0.5, y - 0.5],
                        [x - 0.5, y + h - 0.5], [x + w - 0.5, y + h - 0.5]])
    en = corners @ np.asarray(src_to_crs, float)[:, :2].T + np.asarray(src_to_crs, float)[:, 2]
    west = math.floor(en[:, 0].min() / gsd) * gsd
    north = math.ceil(en[:, 1].max() / gsd) * gsd
    width = max(1, math.ceil((en[:, 0].max() - west) / gsd - 1e-9))
    height = max(1, math.ceil((north - en[:, 1].min()) / gsd - 1e-9))
    return west, north, width, height


def resample_block(render: RenderFn, bounds: tuple[int, int, int, int], out_to_src: np.ndarray,
                   size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray] | None:
    """Render output pixels ``(0..w-1, 0..h-1)`` whose centres map to source pixels by
    ``out_to_src`` (2x3). Returns ``(bgr, alpha uint8)`` or None when nothing is covered; ``bgr``
    has the render's dtype (uint8, or uint16 for a 16-bit map's raw values).

    The source region under the block is rendered at ``scale = min(1, 1 / step)`` (``step``:
    source pixels per output pixel, so it is area-averaged to about the output resolution),
    then warped bilinearly, alpha-premultiplied.
    """
    planes = resample_planes(render, bounds, out_to_src, size)
    return None if planes is None else (cv2.merge(planes[:3]), planes[3])


def resample_planes(render: RenderFn, bounds: tuple[int, int, int, int], out_to_src: np.ndarray,
                    size: tuple[int, int]) -> list[np.ndarray] | None:
    """:func:`resample_block` as four (h, w) planes: blue, green, red (the render's dtype), alpha (uint8)."""
    w, h = size
    a = np.asarray(out_to_src, float)
    step = pose_scale(a)
    scale = min(1.0, 1.0 / step) if step > 0 else 1.0
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    src = corners @ a[:, :2].T + a[:, 2]
    margin = 2.0 / scale
    bx, by, bw, bh = bounds
    x0 = max(math.floor(src[:, 0].min() - margin), bx)
    y0 = max(math.floor(src[:, 1].min() - margin), by)
    x1 = min(math.ceil(src[:, 0].max() + margin) + 1, bx + bw)
    y1 = min(math.ceil(src[:, 1].max() + margin) + 1, by + bh)
    if x1 <= x0 or y1 <= y0:
        return None
    image, alpha = render(x0, y0, x1 - x0, y1 - y0, scale)
    if not alpha.any():
        return None
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    ph, pw = alpha.shape
    patch_to_src = png_to_map((x0, y0), (pw / (x1 - x0), ph / (y1 - y0)))
    out_to_patch = compose(_invert(patch_to_src), a)
    af = alpha.astype(np.float32) * (1.0 / 255.0)
    colour = [np.multiply(p, af, dtype=np.float32) for p in cv2.split(image)]
    pre = cv2.merge([*colour, af])  # premultiplied colour, alpha
    warped = cv2.warpAffine(pre, out_to_patch, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))
    if not (warped[..., 3] > 0.5 / 255).any():
        return None
    return unpremultiply(warped, image.dtype)


Block = tuple[int, int, int, int]


def resample_blocks(raster: MapRaster, gsd: float, block: int
                    ) -> Iterator[tuple[Block, list[np.ndarray] | None]]:
    """The north-up grid of ``raster`` at ``gsd`` metres (:func:`north_up_grid`) one ``block`` x
    ``block`` window at a time, row by row: ``((col, row, w, h), resample_planes(...))`` for every
    window (blue, green, red, alpha planes; None where the map covers none of it). Only one
    window is in memory at a time."""
    west, north, width, height = north_up_grid(raster.bounds, raster.src_to_crs, gsd)
    # output pixel centre (u, v) -> CRS (west + (u + .5) gsd, north - (v + .5) gsd) -> source
    out_to_crs = np.array([[gsd, 0.0, west + 0.5 * gsd], [0.0, -gsd, north - 0.5 * gsd]])
    out_to_src = compose(_invert(raster.src_to_crs), out_to_crs)
    for by in range(0, height, block):
        for bx in range(0, width, block):
            bw, bh = min(block, width - bx), min(block, height - by)
            shift = np.array([[1.0, 0.0, bx], [0.0, 1.0, by]])
            yield (bx, by, bw, bh), resample_planes(raster.render, raster.bounds, compose(out_to_src, shift), (bw, bh))


def write_cog(path: str | Path, raster: MapRaster, *, gsd: float | None = None, block: int = 512,
              compress: str = "DEFLATE", progress: Callable[[int, int], None] | None = None) -> dict:
    """Write ``raster`` as a north-up RGBA Cloud-Optimized GeoTIFF at ``path`` (atomically).

    Parameters
    ----------
    path : output ``.tif``.
    raster : the map and its georeference (:func:`photomap.io.mapsource.run_raster`, or
        ``MapRaster(mosaic_source(mosaic), mosaic.bounds(), map_to_crs, epsg)`` in the pipeline).
    gsd : pixel size, metres (default: the map's resolution, ``raster.metres_per_px``).
    block : window and internal tile size, pixels (multiple of 16).
    compress : GDAL compression of the COG (DEFLATE, ZSTD, LZW, WEBP, ...).
    progress : called with ``(windows done, windows)``.

    Returns ``{"file", "crs", "gsd_m", "size": [w, h], "transform": [a, b, c, d, e, f]}``
    (rasterio's affine: ``E = a col + b row + c``, ``N = d col + e row + f``, corners).
    Raises InputError without rasterio (the ``geo`` extra) or for a bad ``gsd``.
    """
    try:
        import rasterio
        from rasterio.enums import ColorInterp
        from rasterio.shutil import copy as rio_copy
        from rasterio.transform import Affine
        from rasterio.windows import Window
    except ImportError:
        raise InputError(f"writing a GeoTIFF needs rasterio: {GEO_EXTRA_HINT}") from None
    path = Path(path)
    gsd = float(gsd) if gsd else raster.metres_per_px
    if not (math.isfinite(gsd) and gsd > 0):
        raise InputError(f"GeoTIFF pixel size must be > 0 m, got {gsd!r}")
    if block % 16 or block < 64:
        raise InputError(f"GeoTIFF block size must be a multiple of 16 >= 64, got {block}")
    west, north, width, height = north_up_grid(raster.bounds, raster.src_to_crs, gsd)
    if width * height > 4e10:
        raise InputError(f"GeoTIFF of {width} x {height} pixels at {gsd} m is too large; choose a coarser gsd")
    transform = Affine(gsd, 0.0, west, 0.0, -gsd, north)
    profile = dict(driver="GTiff", width=width, height=height, count=4, dtype="uint8",
                   crs=f"EPSG:{raster.epsg}", transform=transform, tiled=True, blockxsize=block,
                   blockysize=block, compress="NONE", photometric="RGB", alpha="YES",
                   sparse_ok=True, bigtiff="IF_SAFER", interleave="pixel")
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".tmp.tif")
    os.close(fd)
    fd, part = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    blocks = math.ceil(width / block) * math.ceil(height / block)
    written = 0
    try:
        # GDAL_CACHEMAX bounds GDAL's block cache (default 5 % of the RAM) on small onboard computers;
        # COG_TMP_COMPRESSION=NONE: the COG driver's temporary overview file (a third of the map's
        # pixels, removed at the end) is not ZSTD-compressed and read back: 40 % of the COG's time
        with rasterio.Env(GDAL_CACHEMAX=128, COG_TMP_COMPRESSION="NONE"), \
                threadpool_limits(limits=1, user_api="blas"):
            with rasterio.open(tmp, "w", **profile) as dst:
                dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]
                for i, (window, planes) in enumerate(resample_blocks(raster, gsd, block)):
                    if planes is not None:
                        b, g, r, alpha = planes
                        dst.write(np.stack([r, g, b, alpha]), window=Window(*window))
                        written += 1
                    if progress is not None:
                        progress(i + 1, blocks)
            if written == 0:
                raise InputError("the map covers no pixel of the GeoTIFF grid: nothing to write")
            level = {"LEVEL": "1"} if compress.upper() in ("DEFLATE", "ZSTD") else {}
            rio_copy(tmp, part, driver="COG", COMPRESS=compress, PREDICTOR="YES", BLOCKSIZE=block,
                     RESAMPLING="AVERAGE", OVERVIEW_RESAMPLING="AVERAGE", BIGTIFF="IF_SAFER",
                     NUM_THREADS="ALL_CPUS", **level)
        os.chmod(part, 0o644)
        os.replace(part, path)
    finally:
        for p in (tmp, part):
            try:
                os.unlink(p)
            except FileNotFoundError:
                pass
    log.info("wrote %s: %d x %d pixels at %.3f m, EPSG:%d", path.name, width, height, gsd, raster.epsg)
    return {"file": path.name, "crs": f"EPSG:{raster.epsg}", "gsd_m": gsd, "size": [width, height],
            "transform": [transform.a, transform.b, transform.c, transform.d, transform.e, transform.f]}


def write_cog_if_available(path: str | Path, raster: MapRaster, **kwargs) -> dict | None:
    """:func:`write_cog` when rasterio is installed; else one INFO line saying how to get it
    and None. For the pipeline's end of run (an onboard install keeps PNG + world file)."""
    if not rasterio_available():
        log.info("no GeoTIFF written (mosaic.png + world file are): for a north-up COG, %s",
                 GEO_EXTRA_HINT)
        return None
    return write_cog(path, raster, **kwargs)
