"""Georeference for the full-resolution map tiles (``tiles/tile_{tx}_{ty}.png``).

A map larger than ``output.max_mosaic_px`` is written downscaled as ``mosaic.png`` and at full
resolution as tiles. :func:`write_tile_georeference` makes those tiles usable in GIS: a world file
(``.pgw``) and a CRS sidecar (``.png.aux.xml``) per tile, and one GDAL VRT (``tiles.vrt`` beside
the folder) that mosaics every tile into a single layer (QGIS: drag it in; GDAL: ``gdalwarp
tiles.vrt ...``). Tile ``(tx, ty)`` holds map pixels ``tx * ts ..``, ``ty * ts ..``. The
georeference keeps the map's rotation (the north-up product is the GeoTIFF).
"""

from __future__ import annotations

import re
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from photomap.errors import InputError
from photomap.geo.georef import aux_xml_text, compose, prj_text, world_file_text
from photomap.io.parallel_writes import ParallelWrites
from photomap.io.trajectory_files import atomic_write_text, sync_filesystem

_TILE = re.compile(r"^tile_(-?\d+)_(-?\d+)\.png$")


def _write_unsynced(path: Path, text: str) -> None:
    atomic_write_text(path, text, sync=False)


def gdal_geotransform(pixel_to_crs: np.ndarray) -> tuple[float, ...]:
    """GDAL's geotransform (pixel *corners*) of a 2x3 pixel-*centre* -> CRS affine."""
    m = np.asarray(pixel_to_crs, float)
    c = m[:, 2] - 0.5 * m[:, 0] - 0.5 * m[:, 1]
    return float(c[0]), float(m[0, 0]), float(m[0, 1]), float(c[1]), float(m[1, 0]), float(m[1, 1])


def write_tile_georeference(tiles_dir: str | Path, tile_size: int, map_to_crs: np.ndarray, epsg: int,
                            *, world_files: bool = True, vrt: bool = True, sync: bool = True) -> dict:
    """World file + ``.aux.xml`` per tile and a ``<folder>.vrt`` over all tiles (atomically).

    Parameters
    ----------
    tiles_dir : the folder of ``tile_{tx}_{ty}.png``.
    tile_size : tile side, map pixels (run.json ``tile_size``).
    map_to_crs : 2x3, map pixel centre -> CRS metres. epsg : the CRS (WGS 84 / UTM).
    sync : the files made durable at the end (one :func:`sync_filesystem`); False when the caller does that.

    Returns ``{"tiles": n, "vrt": name or None, "size": [w, h], "world_files": bool}``.
    """
    folder = Path(tiles_dir)
    keys = sorted((int(m.group(1)), int(m.group(2))) for p in (folder.iterdir() if folder.is_dir() else ())
                  if (m := _TILE.match(p.name)))
    if not keys:
        raise InputError(f"no map tiles (tile_X_Y.png) in {folder}")
    ts = int(tile_size)
    m2c = np.asarray(map_to_crs, float)[:2]
    if world_files:
        aux = aux_xml_text(epsg)
        with ParallelWrites() as writes:  # two small files a tile
            for tx, ty in keys:
                shift = np.array([[1.0, 0.0, tx * ts], [0.0, 1.0, ty * ts]])
                name = f"tile_{tx}_{ty}"
                writes.submit(_write_unsynced, folder / f"{name}.pgw", world_file_text(compose(m2c, shift)))
                writes.submit(_write_unsynced, folder / f"{name}.png.aux.xml", aux)
    tx0, ty0 = min(k[0] for k in keys), min(k[1] for k in keys)
    w = (max(k[0] for k in keys) - tx0 + 1) * ts
    h = (max(k[1] for k in keys) - ty0 + 1) * ts
    name = None
    if vrt:
        gt = gdal_geotransform(compose(m2c, np.array([[1.0, 0.0, tx0 * ts], [0.0, 1.0, ty0 * ts]])))
        bands = []
        for b, interp in enumerate(("Red", "Green", "Blue", "Alpha"), start=1):
            sources = "".join(
                f'<SimpleSource><SourceFilename relativeToVRT="1">{escape(folder.name)}/tile_{tx}_{ty}.png'
                f'</SourceFilename><SourceBand>{b}</SourceBand>'
                f'<SrcRect xOff="0" yOff="0" xSize="{ts}" ySize="{ts}"/>'
                f'<DstRect xOff="{(tx - tx0) * ts}" yOff="{(ty - ty0) * ts}" xSize="{ts}" ySize="{ts}"/>'
                f'</SimpleSource>\n' for tx, ty in keys)
            bands.append(f'<VRTRasterBand dataType="Byte" band="{b}"><ColorInterp>{interp}</ColorInterp>\n'
                         f'{sources}</VRTRasterBand>')
        text = (f'<VRTDataset rasterXSize="{w}" rasterYSize="{h}">\n'
                f'<SRS dataAxisToSRSAxisMapping="1,2">{escape(prj_text(epsg))}</SRS>\n'
                f'<GeoTransform>{", ".join(repr(v) for v in gt)}</GeoTransform>\n'
                + "\n".join(bands) + "\n</VRTDataset>\n")
        name = f"{folder.name}.vrt"
        atomic_write_text(folder.parent / name, text, sync=False)
    if sync:
        sync_filesystem(folder)
    return {"tiles": len(keys), "vrt": name, "size": [w, h], "world_files": bool(world_files)}
