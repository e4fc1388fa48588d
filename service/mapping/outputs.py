"""Map files of a run: mosaic PNGs, full-resolution tiles, georeference sidecars (all atomic).

``mosaic.png`` is BGRA (transparent where the map is empty). Its placement on the map is
recorded in ``run.json`` (``origin_xy``: map pixel of the PNG's top-left pixel centre;
``pixel_scale``: PNG pixels per map pixel, per axis).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from photomap.core.mosaic import TiledMosaic
from photomap.geo.georef import Georeference, aux_xml_text, compose, png_to_map, prj_text, world_file_text
from photomap.io.pngstream import PngStream
from photomap.io.trajectory_files import atomic_write_bytes


def _bgra(image: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return np.dstack([image, alpha])


def write_png(path: Path, mosaic: TiledMosaic, max_px: int, band_bytes: int = 16 << 20) -> dict | None:
    """The map of ``mosaic``, downscaled to at most ``max_px`` on its longer side; its placement.

    Rendered and written in bands of rows (:class:`~photomap.io.pngstream.PngStream`), each
    taking about ``band_bytes`` of render memory: an 8192 px mosaic needs tens of MB, not the
    1.4 GB of one render and one encoding.

    Returns None for an empty map, else ``file``, ``origin_xy``, ``scale``, ``pixel_scale``,
    ``bounds`` (map rectangle x, y, w, h) and ``size`` (PNG w, h).
    """
    bounds = mosaic.bounds()
    if bounds is None:
        return None
    x, y, w, h = bounds
    scale = min(1.0, max_px / max(w, h))
    W, H = mosaic.render_size(scale, bounds)
    band = max(16, min(4096, band_bytes // (20 * W)))  # float32 accumulator + image per output pixel
    with PngStream(path, W, H, 4) as png:
        for v0 in range(0, H, band):
            image, alpha, _ = mosaic.render(scale, bounds, rows=(v0, min(H, v0 + band)))
            png.write(_bgra(image, alpha))
    # exact per-axis scale of the PNG: output size over the map rectangle's size
    return {"file": path.name, "origin_xy": [x, y], "scale": scale, "pixel_scale": [W / w, H / h],
            "bounds": [int(v) for v in bounds], "size": [int(W), int(H)]}


def write_tiles(folder: Path, mosaic: TiledMosaic) -> None:
    """Every map tile at full resolution as ``tile_{tx}_{ty}.png`` (BGRA) in ``folder``."""
    folder.mkdir(exist_ok=True)
    for key in mosaic.tiles():
        ok, buf = cv2.imencode(".png", _bgra(*mosaic.tile_image(key)))
        if ok:
            atomic_write_bytes(folder / f"tile_{key[0]}_{key[1]}.png", buf.tobytes())


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
