"""Map files of a run: mosaic PNGs, full-resolution tiles, georeference sidecars (all atomic).

``mosaic.png`` is BGRA (transparent where the map is empty). Its placement on the map is
recorded in ``run.json`` (``origin_xy``: map pixel of the PNG's top-left pixel centre;
``pixel_scale``: PNG pixels per map pixel, per axis).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np

from photomap.core.area import AreaRows, premultiplied_planes
from photomap.core.mosaic import TiledMosaic, unpremultiply
from photomap.geo.georef import Georeference, aux_xml_text, compose, png_to_map, prj_text, world_file_text
from photomap.io.parallel_writes import ParallelWrites
from photomap.io.pngstream import PngStreamWriter, encode_png
from photomap.io.trajectory_files import atomic_write_bytes, sync_filesystem


def _bgra(image: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """BGRA of a map image (BGR, or grey as (h, w) or (h, w, 1)) and its alpha."""
    if image.ndim == 2 or image.shape[2] == 1:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return cv2.merge([*cv2.split(image), alpha])


def png_placement(name: str, mosaic: TiledMosaic, max_px: int) -> dict | None:
    """What :func:`write_png` returns for ``mosaic``, without rendering or writing anything
    (e.g. to georeference a map whose PNG could not be written); None for an empty map."""
    bounds = mosaic.bounds()
    if bounds is None:
        return None
    x, y, w, h = bounds
    scale = min(1.0, max_px / max(w, h))
    ow, oh = (w, h) if scale == 1 else (max(1, round(w * scale)), max(1, round(h * scale)))
    return {"file": name, "origin_xy": [int(x), int(y)], "scale": scale, "pixel_scale": [ow / w, oh / h],
            "bounds": [int(v) for v in bounds], "size": [int(ow), int(oh)]}


def render_bands(mosaic: TiledMosaic, scale: float, on_sums: Callable[[np.ndarray], None] | None = None
                 ) -> tuple[tuple[int, int, int, int], tuple[int, int], Iterator[tuple[np.ndarray, np.ndarray]]]:
    """The map of ``mosaic`` at ``scale``, band by band from the top, one tile row at a time.

    Returns ``(bounds, (W, H), bands)``: the map rectangle, the output size, and an iterator of
    ``(image uint8 (n, W, C), alpha uint8 (n, W))`` bands whose rows, stacked, equal
    ``mosaic.render(scale)`` exactly (both are :meth:`TiledMosaic.area_sums` when downscaled). Each
    tile is read once; memory is one band (about a tile row) instead of the whole map, so a
    survey-size map is never one array. ``on_sums``, downscaled: given each band's alpha-weighted
    sums first (:meth:`TiledMosaic.area_sums`; not to be changed).
    """
    bounds = mosaic.bounds()
    if bounds is None:
        raise ValueError("the map is empty")
    if not 0 < scale <= 1:
        raise ValueError(f"render scale must be in (0, 1], got {scale!r}")
    x, y, w, h = bounds
    full = scale == 1
    ow, oh = (w, h) if full else (max(1, round(w * scale)), max(1, round(h * scale)))
    return bounds, (ow, oh), _bands(mosaic, x, y, w, h, ow, oh, full, on_sums)


def _bands(mosaic: TiledMosaic, x: int, y: int, w: int, h: int, ow: int, oh: int, full: bool,
           on_sums: Callable[[np.ndarray], None] | None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    if not full:
        for sums in mosaic.area_sums((x, y, w, h), (ow, oh)):
            if on_sums is not None:
                on_sums(sums)
            yield _finish(sums, mosaic.channels)
        return
    for _, image, alpha in mosaic.tile_rows((x, y, w, h)):
        yield image, alpha


def _finish(acc: np.ndarray, C: int) -> tuple[np.ndarray, np.ndarray]:
    """Alpha-weighted sums -> (image, alpha), as ``TiledMosaic.render`` finishes them."""
    planes = unpremultiply(acc)
    image = planes[0][..., None] if C == 1 else cv2.merge(planes[:C])
    return image, planes[C]


class PngThumbnail:
    """The PNG written by :func:`write_png` area-averaged to at most ``max_px`` on its longer
    side, from its bands as they are written (alpha-weighted, as :meth:`TiledMosaic.render`; a
    downscaled PNG's bands before they are rounded): the report's map without reading the map
    again. :meth:`image` is None until the whole PNG went through."""

    def __init__(self, max_px: int) -> None:
        self.max_px = int(max_px)
        self._rows: AreaRows | None = None
        self._y = 0
        self._blocks: list[np.ndarray] = []

    def start(self, width: int, height: int) -> None:
        """A PNG of ``width`` x ``height`` begins."""
        f = min(1.0, self.max_px / max(width, height))
        self._size = (width, height)
        self._rows = AreaRows(height, width, max(1, round(height * f)), max(1, round(width * f)), 4)
        self._y, self._blocks = 0, []

    def add(self, bgra: np.ndarray) -> None:
        """The PNG's next band (uint8 BGRA rows)."""
        self.add_sums(cv2.merge(premultiplied_planes(bgra[..., :3], bgra[..., 3])))

    def add_sums(self, sums: np.ndarray) -> None:
        """The PNG's next band as alpha-weighted sums (float32 (n, w, 4): colour times
        coverage, coverage in [0, 1]; of a colour map)."""
        self._blocks += self._rows.add(self._y, sums)
        self._y += sums.shape[0]

    def image(self) -> np.ndarray | None:
        """The thumbnail, BGRA uint8, or None."""
        if self._rows is None or self._y != self._size[1]:
            return None
        image, alpha = _finish(np.concatenate(self._blocks + self._rows.close()), 3)
        self._rows = None
        return _bgra(image, alpha)


def write_png(path: Path, mosaic: TiledMosaic, max_px: int, *, thumbnail: PngThumbnail | None = None
              ) -> dict | None:
    """The map of ``mosaic``, downscaled to at most ``max_px`` on its longer side; its placement.

    Written band by band (:func:`render_bands`, :class:`~photomap.io.pngstream.PngStreamWriter`),
    each band encoded on a thread while the next renders: memory stays about two tile rows of the
    PNG whatever the map's size.
    ``thumbnail`` (optional) is given every band too.
    Returns None for an empty map, else ``file``, ``origin_xy``, ``scale``, ``pixel_scale``,
    ``bounds`` (map rectangle x, y, w, h) and ``size`` (PNG w, h).
    """
    if mosaic.bounds() is None:
        return None
    _, _, w, h = mosaic.bounds()
    scale = min(1.0, max_px / max(w, h))
    sums_to = thumbnail.add_sums if thumbnail is not None and scale < 1 and mosaic.channels == 3 else None
    bounds, (ow, oh), bands = render_bands(mosaic, scale, sums_to)
    if thumbnail is not None:
        thumbnail.start(ow, oh)
    with PngStreamWriter(path, ow, oh, channels=4) as png, ThreadPoolExecutor(1, "photomap-png") as encoder:
        encoded = None  # a band is filtered and compressed while the next one renders (two bands in memory)
        for image, alpha in bands:
            band = _bgra(image, alpha)
            if thumbnail is not None and sums_to is None:
                thumbnail.add(band)
            if encoded is not None:
                encoded.result()
            encoded = encoder.submit(png.write, band)
        if encoded is not None:
            encoded.result()
    # exact per-axis scale of the PNG: output size over the map rectangle's size
    return {"file": path.name, "origin_xy": [int(bounds[0]), int(bounds[1])], "scale": scale,
            "pixel_scale": [ow / w, oh / h], "bounds": [int(v) for v in bounds], "size": [int(ow), int(oh)]}


def render_small(mosaic: TiledMosaic, max_px: int) -> np.ndarray | None:
    """The map of ``mosaic`` as one BGRA image of at most ``max_px`` on its longer side, over
    the extent of its PNG (:func:`write_png`); rendered in bands, so memory is the small image
    and one band. None for an empty map."""
    if mosaic.bounds() is None:
        return None
    _, _, w, h = mosaic.bounds()
    _, _, bands = render_bands(mosaic, min(1.0, max_px / max(w, h)))
    return np.vstack([_bgra(image, alpha) for image, alpha in bands])


def _write_tile(path: Path, bgra: np.ndarray) -> None:
    atomic_write_bytes(path, encode_png(bgra), sync=False)  # a third of cv2.imencode's CPU (pngstream)


def write_tiles(folder: Path, mosaic: TiledMosaic, *, sync: bool = True) -> None:
    """Every map tile at full resolution as ``tile_{tx}_{ty}.png`` (BGRA) in ``folder``: read
    here, one tile at a time, encoded and written on :class:`ParallelWrites`' threads.
    ``sync``: made durable at the end (one :func:`sync_filesystem`); False when the caller does that."""
    folder.mkdir(exist_ok=True)
    with ParallelWrites() as writes:
        for key in mosaic.tiles():
            writes.submit(_write_tile, folder / f"tile_{key[0]}_{key[1]}.png", _bgra(*mosaic.tile_image(key)))
    if sync:
        sync_filesystem(folder)


SIDECAR_SUFFIXES = (".pgw", ".prj", ".png.aux.xml")


def remove_sidecars(out_dir: Path, png_name: str) -> None:
    """Delete the georeference files of ``png_name`` left by an earlier run in ``out_dir``."""
    stem = Path(png_name).stem
    for suffix in SIDECAR_SUFFIXES:
        (out_dir / f"{stem}{suffix}").unlink(missing_ok=True)


def write_sidecars(out_dir: Path, info: dict, geo: Georeference) -> str:
    """World file, ``.prj`` and ``.aux.xml`` beside the PNG of ``info`` (see :func:`write_png`),
    so that GIS software places it; returns the world file's name."""
    stem = Path(info["file"]).stem
    png = compose(geo.map_to_crs, png_to_map(info["origin_xy"], info["pixel_scale"]))
    atomic_write_bytes(out_dir / f"{stem}.pgw", world_file_text(png).encode())
    atomic_write_bytes(out_dir / f"{stem}.prj", prj_text(geo.epsg).encode())
    atomic_write_bytes(out_dir / f"{info['file']}.aux.xml", aux_xml_text(geo.epsg).encode())
    return f"{stem}.pgw"
