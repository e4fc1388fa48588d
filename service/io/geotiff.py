"""A north-up Cloud-Optimized GeoTIFF of the map, written block by block (needs the ``geo`` extra).

The map's georeference is a similarity (rotation, scale, y flip) from map pixels to UTM metres;
GIS tools want a grid aligned with easting and northing. :func:`write_cog` builds that grid
(pixel size ``gsd`` metres; by default the map's own resolution), and fills it one
``block`` x ``block`` window at a time: each window's pixel centres are mapped back to source
pixels, the source region under them is rendered (area-averaged when the GeoTIFF is coarser than
the source) and resampled bilinearly, alpha-premultiplied so that empty map pixels do not darken
the edges. Only one window (and the source region under it) is in memory at a time. The same
windows, row by row (:func:`resample_blocks`), make the raw 16-bit GeoTIFFs of
:mod:`photomap.mapping.band_maps` on the same grid.

The windows go into a temporary tiled GeoTIFF (sparse: blocks the map does not cover are not
written; uncompressed: written once and read once, and photo pixels gain a quarter at most from
ZSTD, which took a fifth of the COG's CPU time). They are visited in Z order so that the overview
levels are built as they go (:class:`_Pyramid`: each block of a level the alpha-weighted 2 x 2
means of the four under it, :mod:`photomap.core.pyramid`; about one block per level in memory),
each level into a temporary GeoTIFF of its own. GDAL's COG driver then copies the full
resolution and those overviews (a VRT that lists them, ``OVERVIEWS=FORCE_USE_EXISTING``; GDAL's
own AVERAGE overviews took 1.4 of its 3.7 CPU s on a 13185 x 5864 survey map) into the final
layout: RGBA (band 4 is alpha), 512-pixel tiles, DEFLATE (level 1: a third of level 6's time for
6 % more bytes, the same pixels) with the horizontal predictor, compressed on every core,
overviews down to one tile, the CRS inside. ``gdalinfo`` reports ``LAYOUT=COG``.

Conventions: rasterio/GDAL geotransforms address pixel *corners* (``(0, 0)`` = the top-left
corner of the top-left pixel); the map and the render functions use OpenCV pixel *centres*.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Iterator
from xml.sax.saxutils import escape

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from photomap.core.mosaic import unpremultiply
from photomap.core.pyramid import halve
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
    if _samples_inside(out_to_patch, (w, h), (pw, ph)) and alpha.min() == 255:
        # opaque inside the map: nothing to weight, the image warped as it is (OpenCV's fixed-point
        # bilinear steps of 1/32 pixel: colours within 1 of the weighted float path, a fifth of its time)
        warped = cv2.warpAffine(image, out_to_patch, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_REPLICATE)
        return [*cv2.split(warped), np.full((h, w), 255, np.uint8)]
    dtype, af = image.dtype, alpha.astype(np.float32) * (1.0 / 255.0)
    pre = cv2.merge([*(np.multiply(p, af, dtype=np.float32) for p in cv2.split(image)), af])  # premultiplied
    del image, alpha, af  # the render and its planes: not held through the warp
    warped = cv2.warpAffine(pre, out_to_patch, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))
    if not (warped[..., 3] > 0.5 / 255).any():
        return None
    del pre
    return unpremultiply(warped, dtype)


def _samples_inside(out_to_patch: np.ndarray, size: tuple[int, int], patch: tuple[int, int]) -> bool:
    """True when every output pixel centre of a ``size`` block maps (``out_to_patch``) within the
    pixel centres of a ``patch`` (w, h): bilinear sampling never reaches past its edge."""
    w, h = size
    corners = np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]])
    src = corners @ np.asarray(out_to_patch, float)[:, :2].T + np.asarray(out_to_patch, float)[:, 2]
    return bool((src >= 0).all() and (src[:, 0] <= patch[0] - 1).all() and (src[:, 1] <= patch[1] - 1).all())


Block = tuple[int, int, int, int]


def _grid_to_src(raster: MapRaster, gsd: float) -> tuple[int, int, np.ndarray]:
    """``(width, height, out_to_src)`` of the north-up grid of ``raster`` at ``gsd`` metres: its
    size and the 2x3 affine from its pixel centres to source pixels."""
    west, north, width, height = north_up_grid(raster.bounds, raster.src_to_crs, gsd)
    # output pixel centre (u, v) -> CRS (west + (u + .5) gsd, north - (v + .5) gsd) -> source
    out_to_crs = np.array([[gsd, 0.0, west + 0.5 * gsd], [0.0, -gsd, north - 0.5 * gsd]])
    return width, height, compose(_invert(raster.src_to_crs), out_to_crs)


def _window_planes(raster: MapRaster, out_to_src: np.ndarray, window: Block) -> list[np.ndarray] | None:
    bx, by, bw, bh = window
    shift = np.array([[1.0, 0.0, bx], [0.0, 1.0, by]])
    return resample_planes(raster.render, raster.bounds, compose(out_to_src, shift), (bw, bh))


def resample_blocks(raster: MapRaster, gsd: float, block: int
                    ) -> Iterator[tuple[Block, list[np.ndarray] | None]]:
    """The north-up grid of ``raster`` at ``gsd`` metres (:func:`north_up_grid`) one ``block`` x
    ``block`` window at a time, row by row: ``((col, row, w, h), resample_planes(...))`` for every
    window (blue, green, red, alpha planes; None where the map covers none of it). Only one
    window is in memory at a time."""
    width, height, out_to_src = _grid_to_src(raster, gsd)
    for by in range(0, height, block):
        for bx in range(0, width, block):
            window = (bx, by, min(block, width - bx), min(block, height - by))
            yield window, _window_planes(raster, out_to_src, window)


def overview_sizes(width: int, height: int, block: int) -> list[tuple[int, int]]:
    """The overview levels of a ``width`` x ``height`` COG with ``block`` px tiles: as many as
    GDAL's COG driver makes (each half of the one before, until the last fits one tile), their
    sizes rounded up so that every pixel is exactly 2 x 2 pixels of the level above."""
    sizes = []
    while max(width, height) > block:
        width, height = (width + 1) // 2, (height + 1) // 2
        sizes.append((width, height))
    return sizes


class _Pyramid:
    """The full-resolution windows of a north-up grid and its overview levels, written block by
    block into one GeoTIFF per level (``dsts[k]``, k = 0 the full resolution).

    :meth:`block` of level k > 0 is built from its four blocks of level k - 1, each halved
    (:func:`photomap.core.pyramid.halve`) as soon as it is made, so the windows are visited in
    Z order and memory is about one block per level whatever the map's size. Blocks the map does
    not cover are not written (sparse)."""

    def __init__(self, raster: MapRaster, out_to_src: np.ndarray, sizes: list[tuple[int, int]], block: int,
                 dsts: list, progress: Callable[[int, int], None] | None) -> None:
        self.raster, self.out_to_src, self.sizes, self.size, self.dsts = raster, out_to_src, sizes, block, dsts
        self.progress = progress
        w, h = sizes[0]
        self.windows, self.done, self.written = math.ceil(w / block) * math.ceil(h / block), 0, 0

    def block(self, k: int, i: int, j: int) -> np.ndarray | None:
        """Block ``(i, j)`` of level ``k`` (BGRA uint8, clipped to the level), written; None
        where the map covers none of it (or past the level's edge)."""
        w, h = self.sizes[k]
        x, y, n = i * self.size, j * self.size, self.size
        if x >= w or y >= h:
            return None
        window = (x, y, min(n, w - x), min(n, h - y))
        if k == 0:
            planes = _window_planes(self.raster, self.out_to_src, window)
            self.done += 1
            if self.progress is not None:
                self.progress(self.done, self.windows)
            if planes is None:
                return None
            self.written += 1
            bgra = cv2.merge(planes)
        else:
            bgra = None
            for dj in (0, 1):
                for di in (0, 1):
                    child = self.block(k - 1, 2 * i + di, 2 * j + dj)
                    if child is None:
                        continue
                    half = halve(child)
                    if bgra is None:
                        bgra = np.zeros((window[3], window[2], 4), np.uint8)
                    ox, oy = di * n // 2, dj * n // 2
                    bgra[oy:oy + half.shape[0], ox:ox + half.shape[1]] = half
            if bgra is None:
                return None
            planes = cv2.split(bgra)
        b, g, r, a = planes
        self.dsts[k].write(np.stack([r, g, b, a]), window=((y, y + window[3]), (x, x + window[2])))
        return bgra


def _vrt_with_overviews(files: list[str], size: tuple[int, int], transform, epsg: int) -> str:
    """A VRT of ``files[0]`` (RGBA) whose bands have ``files[1:]`` as their overviews."""
    w, h = size
    bands = []
    for b, interp in enumerate(("Red", "Green", "Blue", "Alpha"), start=1):
        overviews = "".join(f"<Overview><SourceFilename>{escape(f)}</SourceFilename><SourceBand>{b}</SourceBand>"
                            f"</Overview>" for f in files[1:])
        bands.append(f'<VRTRasterBand dataType="Byte" band="{b}"><ColorInterp>{interp}</ColorInterp>'
                     f'<SimpleSource><SourceFilename>{escape(files[0])}</SourceFilename><SourceBand>{b}</SourceBand>'
                     f'<SrcRect xOff="0" yOff="0" xSize="{w}" ySize="{h}"/>'
                     f'<DstRect xOff="0" yOff="0" xSize="{w}" ySize="{h}"/></SimpleSource>{overviews}</VRTRasterBand>')
    gt = (transform.c, transform.a, transform.b, transform.f, transform.d, transform.e)
    return (f'<VRTDataset rasterXSize="{w}" rasterYSize="{h}"><SRS>EPSG:{int(epsg)}</SRS>'
            f'<GeoTransform>{", ".join(repr(float(v)) for v in gt)}</GeoTransform>\n'
            + "\n".join(bands) + "\n</VRTDataset>\n")


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
    sizes = [(width, height)] + overview_sizes(width, height, block)
    _, _, out_to_src = _grid_to_src(raster, gsd)
    work = tempfile.mkdtemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".tmp")
    fd, part = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        files = [os.path.join(work, f"level{k}.tif") for k in range(len(sizes))]
        # GDAL_CACHEMAX bounds GDAL's block cache (default 5 % of the RAM) on small onboard computers
        with rasterio.Env(GDAL_CACHEMAX=128), threadpool_limits(limits=1, user_api="blas"):
            with contextlib.ExitStack() as stack:
                dsts = []
                for f, (w, h) in zip(files, sizes):
                    level_transform = transform @ Affine.scale(width / w, height / h)
                    dst = stack.enter_context(rasterio.open(
                        f, "w", driver="GTiff", width=w, height=h, count=4, dtype="uint8", crs=f"EPSG:{raster.epsg}",
                        transform=level_transform, tiled=True, blockxsize=block, blockysize=block, compress="NONE",
                        photometric="RGB", alpha="YES", sparse_ok=True, bigtiff="IF_SAFER", interleave="pixel"))
                    dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]
                    dsts.append(dst)
                pyramid = _Pyramid(raster, out_to_src, sizes, block, dsts, progress)
                pyramid.block(len(sizes) - 1, 0, 0)
            if pyramid.written == 0:
                raise InputError("the map covers no pixel of the GeoTIFF grid: nothing to write")
            vrt = os.path.join(work, "map.vrt")
            with open(vrt, "w", encoding="utf-8") as f:
                f.write(_vrt_with_overviews(files, (width, height), transform, raster.epsg))
            level = {"LEVEL": "1"} if compress.upper() in ("DEFLATE", "ZSTD") else {}
            rio_copy(vrt, part, driver="COG", COMPRESS=compress, PREDICTOR="YES", BLOCKSIZE=block,
                     OVERVIEWS="FORCE_USE_EXISTING", BIGTIFF="IF_SAFER", NUM_THREADS="ALL_CPUS", **level)
        os.chmod(part, 0o644)
        os.replace(part, path)
    finally:
        shutil.rmtree(work, ignore_errors=True)
        try:
            os.unlink(part)
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
