"""GIS and ground-station exports, read back with the real libraries and checked against the
simulator's truth (terrain pixel -> WGS84 by ``photomap.sim.flight.pixel_to_latlon``)."""

from __future__ import annotations

import html.parser
import json
import math
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from photomap.cli.main import main
from photomap.config import MosaicConfig
from photomap.core.mosaic import TiledMosaic
from photomap.geo import webmercator as wm
from photomap.geo.georef import enu_from_latlon, parse_world_file, utm_epsg, utm_forward, utm_inverse
from photomap.io.mapsource import ImageSource, MapRaster, TileFolderSource, mosaic_source, run_raster
from photomap.io.runfiles import RunFiles
from photomap.io.trajectory_files import read_groundtruth
from photomap.io.xyz_tiles import render_tile
from photomap.sim.flight import latlon_to_pixel, pixel_to_latlon
from photomap.sim.simulate import simulate_flight
from photomap.sim.terrain import load_terrain
from tests.tiles import tile_bgra
from tests.waiting import wait_until

T0_UNIX = None  # set from meta.yaml in the fixture


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """A georeferenced run of a simulated flight; the map is larger than max_mosaic_px, so the
    run also has full-resolution tiles/."""
    root = tmp_path_factory.mktemp("export")
    sim = root / "sim"
    simulate_flight(sim, n_frames=90, fps=15.0, seed=3)
    run = root / "run"
    assert main(["replay", str(sim / "video.mp4"), "--out", str(run), "--mavlink", str(sim / "telemetry.tlog"),
                 "--no-progress", "-q", "--set", "output.max_mosaic_px=700"]) == 0
    meta = yaml.safe_load((sim / "meta.yaml").read_text())
    return sim, run, meta


def _truth_latlon(meta: dict, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return pixel_to_latlon(x, y, meta["gsd"], meta["origin"]["lat"], meta["origin"]["lon"])


def _metres(lat1, lon1, lat2, lon2) -> np.ndarray:
    e, n = enu_from_latlon(np.asarray(lat2), np.asarray(lon2), float(np.mean(lat1)), float(np.mean(lon1)))
    e0, n0 = enu_from_latlon(np.asarray(lat1), np.asarray(lon1), float(np.mean(lat1)), float(np.mean(lon1)))
    return np.hypot(e - e0, n - n0)


def _truth_footprints(sim: Path, meta: dict) -> list[np.ndarray]:
    """(4, 2) lat, lon of every frame's outer corners, from groundtruth.csv."""
    gt = read_groundtruth(sim / "groundtruth.csv")
    w, h = meta["camera"]["width"], meta["camera"]["height"]
    corners = np.array([[-0.5, -0.5, 1], [w - 0.5, -0.5, 1], [w - 0.5, h - 0.5, 1], [-0.5, h - 0.5, 1]])
    out = []
    for H in gt.H:
        p = corners @ H.T
        lat, lon = _truth_latlon(meta, p[:, 0] / p[:, 2], p[:, 1] / p[:, 2])
        out.append(np.c_[lat, lon])
    return out


# --------------------------------------------------------------------------- web mercator

def test_xyz_tile_indices_match_published_values():
    # mercantile's documented examples (mapbox/mercantile tests and README)
    assert wm.tile_of(40.1222, 20.6852, 9) == (285, 193)
    s, w, n, e = wm.tile_bounds(486, 332, 10)
    assert (w, e) == pytest.approx((-9.140625, -8.7890625), abs=1e-9)
    assert (s, n) == pytest.approx((53.12040528310657, 53.33087298301705), abs=1e-9)
    assert wm.tile_of(0.0, 0.0, 0) == (0, 0) and wm.tile_of(-10.0, 10.0, 1) == (1, 1)
    assert wm.tms_y(332, 10) == 1023 - 332 and wm.tms_y(wm.tms_y(5, 4), 4) == 5
    assert wm.ground_resolution(0.0, 0) == pytest.approx(156543.03392804097, rel=1e-12)
    px, py = wm.latlon_to_pixel(53.2, -9.0, 10)
    lat, lon = wm.pixel_to_latlon(px, py, 10)
    assert (float(lat), float(lon)) == pytest.approx((53.2, -9.0), abs=1e-12)
    assert wm.tiles_covering(53.2, -9.1, 53.3, -8.7, 10) == [(486, 332), (487, 332)]
    assert wm.tiles_covering(53.2, -9.1, 53.3, -8.9, 10) == [(486, 332)]


# --------------------------------------------------------------------------- sources

def test_render_sources_agree_with_the_mosaic_render(tmp_path):
    rng = np.random.default_rng(0)
    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    mosaic.add(rng.integers(0, 255, (300, 400, 3), np.uint8), np.array([[0.9, -0.3, 17.3], [0.3, 0.9, -40.2]]))
    bx, by, bw, bh = mosaic.bounds()
    full, alpha, origin = mosaic.render(1.0)
    image = ImageSource(np.dstack([full, alpha]), origin)
    for key in mosaic.tiles():
        t_img, t_alpha = mosaic.tile_image(key)
        cv2.imwrite(str(tmp_path / f"tile_{key[0]}_{key[1]}.png"), np.dstack([t_img, t_alpha]))
    tiles = TileFolderSource(tmp_path, 64, cache_tiles=3)
    live = mosaic_source(mosaic)
    for region, scale in [((bx, by, bw, bh), 0.3), ((bx + 5, by + 7, 123, 77), 0.77),
                          ((bx - 20, by + 30, 300, 200), 0.1), ((bx, by, 50, 50), 1.0)]:
        ref_img, ref_alpha = live(*region, scale)
        for source in (image, tiles):
            img, a = source(*region, scale)
            assert img.shape == ref_img.shape and a.shape == ref_alpha.shape
            assert np.abs(img.astype(int) - ref_img).max() <= 1  # rounding of the weighted mean
            assert np.abs(a.astype(int) - ref_alpha).max() <= 1


# --------------------------------------------------------------------------- GeoTIFF

def test_cog_is_a_north_up_cog_where_the_simulator_says(flight, tmp_path):
    rasterio = pytest.importorskip("rasterio", reason="the geo extra (rasterio) is not installed")
    sim, run, meta = flight
    assert main(["export", str(run), "--cog", str(tmp_path / "map.tif"), "-q"]) == 0
    with rasterio.open(tmp_path / "map.tif") as src:
        assert src.crs.to_epsg() == utm_epsg(meta["origin"]["lat"], meta["origin"]["lon"])
        t = src.transform
        assert t.b == 0 and t.d == 0 and t.a > 0 and t.e == -t.a  # north-up, square pixels
        m2c, _ = RunFiles(run).georeference()
        assert t.a == pytest.approx(math.sqrt(-np.linalg.det(m2c[:, :2])), rel=1e-9)  # the map's resolution
        structure = src.tags(ns="IMAGE_STRUCTURE")
        assert structure.get("LAYOUT") == "COG" and structure.get("COMPRESSION") == "DEFLATE"
        assert src.profile["tiled"] and src.block_shapes[0] == (512, 512)
        assert src.overviews(1), "a COG larger than a tile carries overviews"
        assert src.colorinterp[3] == rasterio.enums.ColorInterp.alpha
        data = src.read()
        ovr = src.read(4, out_shape=(src.height // src.overviews(4)[0], src.width // src.overviews(4)[0]))
    alpha = data[3]
    assert (alpha == 0).any() and (alpha == 255).mean() > 0.3 and ovr.max() == 255

    # every COG pixel centre -> UTM -> WGS84 -> terrain pixel of the simulator: the same picture
    h, w = alpha.shape
    cols, rows = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    lat, lon = utm_inverse(t.c + t.a * cols, t.f + t.e * rows, src.crs.to_epsg())
    tx, ty = latlon_to_pixel(lat, lon, meta["gsd"], meta["origin"]["lat"], meta["origin"]["lon"])
    terrain = load_terrain(meta["terrain"]["name"], zoom=meta["terrain"]["zoom"])
    truth = cv2.cvtColor(cv2.remap(terrain, tx.astype(np.float32), ty.astype(np.float32), cv2.INTER_LINEAR),
                         cv2.COLOR_BGR2GRAY).astype(np.float32)
    ours = cv2.cvtColor(np.ascontiguousarray(data[:3].transpose(1, 2, 0)), cv2.COLOR_RGB2GRAY).astype(np.float32)
    inside = alpha == 255
    a = (ours - ours[inside].mean()) * inside
    b = (truth - truth[inside].mean()) * inside
    (dx, dy), _ = cv2.phaseCorrelate(b, a, cv2.createHanningWindow((w, h), cv2.CV_32F))
    assert math.hypot(dx, dy) * t.a < 0.25, f"COG off the truth by {math.hypot(dx, dy) * t.a:.2f} m"
    assert np.abs(ours - truth)[inside].mean() < 8.0  # same content (video compression, resampling)

    # the map's corners: the extreme covered pixels against the union of the true footprints
    corners = np.concatenate(_truth_footprints(sim, meta))
    e, n = utm_forward(corners[:, 0], corners[:, 1], src.crs.to_epsg())
    cov_rows, cov_cols = np.nonzero(alpha >= 128)
    ours_box = (t.c + t.a * cov_cols.min(), t.c + t.a * (cov_cols.max() + 1),
                t.f + t.e * (cov_rows.max() + 1), t.f + t.e * cov_rows.min())
    truth_box = (e.min(), e.max(), n.min(), n.max())
    assert np.abs(np.subtract(ours_box, truth_box)).max() < 1.0, (ours_box, truth_box)


def test_cog_writer_falls_back_to_one_info_line_without_rasterio(flight, monkeypatch, caplog, tmp_path):
    from photomap.io import geotiff

    monkeypatch.setattr(geotiff, "rasterio_available", lambda: False)
    raster = run_raster(RunFiles(flight[1]))
    with caplog.at_level("INFO"):
        assert geotiff.write_cog_if_available(tmp_path / "map.tif", raster) is None
    assert not (tmp_path / "map.tif").exists()
    assert any("ifmi-photomap[geo]" in r.getMessage() for r in caplog.records)


# --------------------------------------------------------------------------- web tiles

def test_xyz_tiles_are_where_the_simulator_says(flight, tmp_path):
    sim, run, meta = flight
    assert main(["export", str(run), "--tiles", str(tmp_path / "xyz"), "-q"]) == 0
    info = json.loads((tmp_path / "xyz" / "tiles.json").read_text())
    zmin, zmax = info["zooms"]
    assert zmin < zmax and info["tiles"] > 4
    mpp = json.loads((run / "run.json").read_text())["metres_per_pixel"]
    lat0 = meta["origin"]["lat"]
    assert 0.5 < wm.ground_resolution(lat0, zmax) / mpp < 2.0  # the deepest zoom keeps the resolution
    files = sorted((tmp_path / "xyz" / str(zmax)).glob("*/*.png"))
    assert len(files) >= 4
    # the tile with the most map in it: pixel centres -> WGS84 -> terrain, compared with the terrain
    best = max(files, key=lambda p: int((tile_bgra(p)[..., 3] == 255).sum()))
    tile = tile_bgra(best)
    assert tile.shape == (256, 256, 4)
    x, y = int(best.parent.name), int(best.stem)
    u = np.arange(256) + 0.5
    px, py = np.meshgrid(x * 256 + u, y * 256 + u)
    lat, lon = wm.pixel_to_latlon(px, py, zmax)
    tx, ty = latlon_to_pixel(lat, lon, meta["gsd"], meta["origin"]["lat"], meta["origin"]["lon"])
    terrain = load_terrain(meta["terrain"]["name"], zoom=meta["terrain"]["zoom"])
    truth = cv2.cvtColor(cv2.remap(terrain, tx.astype(np.float32), ty.astype(np.float32), cv2.INTER_LINEAR),
                         cv2.COLOR_BGR2GRAY).astype(np.float32)
    ours = cv2.cvtColor(tile[..., :3], cv2.COLOR_BGR2GRAY).astype(np.float32)
    inside = tile[..., 3] == 255
    assert inside.mean() > 0.5
    a, b = (ours - ours[inside].mean()) * inside, (truth - truth[inside].mean()) * inside
    (dx, dy), _ = cv2.phaseCorrelate(b, a, cv2.createHanningWindow((256, 256), cv2.CV_32F))
    assert math.hypot(dx, dy) * wm.ground_resolution(lat0, zmax) < 0.5
    assert np.abs(ours - truth)[inside].mean() < 10.0
    # TMS numbering: the same tile under the flipped row
    assert main(["export", str(run), "--tiles", str(tmp_path / "tms"), "--tms", "--zoom", str(zmax), "-q"]) == 0
    flipped = tile_bgra(tmp_path / "tms" / str(zmax) / str(x) / f"{wm.tms_y(y, zmax)}.png")
    assert np.array_equal(flipped, tile)


def test_an_empty_tile_is_not_rendered(flight):
    raster = run_raster(RunFiles(flight[1]))
    assert render_tile(raster, 0, 0, 5) is None  # far from the flight


# --------------------------------------------------------------------------- vectors

def test_kml_and_geojson_match_the_trajectory_and_the_truth(flight, tmp_path):
    sim, run, meta = flight
    work = tmp_path / "run"
    shutil.copytree(run, work)
    summary = json.loads((work / "run.json").read_text())
    summary["video_start_unix"] = meta["t0_unix"]
    (work / "run.json").write_text(json.dumps(summary))
    assert main(["export", str(work), "--kml", "--geojson", "--footprints", "all", "-q"]) == 0
    rows = [r for r in RunFiles(work).rows if r.glued]
    csv_lat = np.array([r.extra["lat"] for r in rows])
    csv_lon = np.array([r.extra["lon"] for r in rows])

    gj = json.loads((work / "track.geojson").read_text())
    assert gj["type"] == "FeatureCollection"
    kinds = [f["properties"]["kind"] for f in gj["features"]]
    assert kinds.count("track") == 1 and kinds.count("footprint") == len(rows) and kinds.count("coverage") == 1
    track = np.array(next(f for f in gj["features"] if f["properties"]["kind"] == "track")["geometry"]["coordinates"])
    assert len(track) == len(rows)
    assert _metres(csv_lat, csv_lon, track[:, 1], track[:, 0]).max() < 1.0

    # footprints against the true frame corners (frame 0 is the map's reference)
    truth = _truth_footprints(sim, meta)
    fps = [f for f in gj["features"] if f["properties"]["kind"] == "footprint"]
    for f in (fps[0], fps[len(fps) // 2], fps[-1]):
        ring = np.array(f["geometry"]["coordinates"][0])
        assert len(ring) == 5 and np.array_equal(ring[0], ring[-1])
        area2 = np.sum(ring[:-1, 0] * ring[1:, 1] - ring[1:, 0] * ring[:-1, 1])
        assert area2 > 0, "RFC 7946: exterior rings are counter-clockwise"
        got = ring[:-1][:, ::-1]  # (lat, lon)
        want = truth[f["properties"]["frame"]]
        # each true corner has one of ours within the tolerance
        d = max(_metres(np.full(4, la), np.full(4, lo), got[:, 0], got[:, 1]).min() for la, lo in want)
        assert d < 1.0, f"footprint of frame {f['properties']['frame']} off by {d:.2f} m"
        assert f["properties"]["time"].startswith("20") and f["properties"]["t_unix"] == pytest.approx(
            meta["t0_unix"] + f["properties"]["t"], abs=1e-3)

    # coverage: its area against the mosaic's covered pixels
    cov = next(f for f in gj["features"] if f["properties"]["kind"] == "coverage")["properties"]
    png = cv2.imread(str(work / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    entry = summary["mosaics"][0]
    mosaic_m2 = (png[..., 3].astype(float) / 255).sum() / np.prod(entry["pixel_scale"]) * summary["metres_per_pixel"] ** 2
    assert cov["area_m2"] == pytest.approx(mosaic_m2, rel=0.03)

    # KML: the same track, read with xml.etree
    ns = {"k": "http://www.opengis.net/kml/2.2", "gx": "http://www.google.com/kml/ext/2.2"}
    root = ET.parse(work / "track.kml").getroot()
    lines = root.findall(".//k:Placemark/k:LineString/k:coordinates", ns)
    assert len(lines) == 1
    coords = np.array([[float(v) for v in c.split(",")] for c in lines[0].text.split()])
    assert _metres(csv_lat, csv_lon, coords[:, 1], coords[:, 0]).max() < 1.0
    assert len(root.findall(".//k:Placemark/k:Polygon", ns)) == len(rows)
    assert len(root.findall(".//k:Placemark/k:TimeStamp/k:when", ns)) == len(rows)
    quad = root.find(".//gx:LatLonQuad/k:coordinates", ns)
    assert quad is not None and root.find(".//k:GroundOverlay/k:Icon/k:href", ns).text == "mosaic.png"
    assert len(quad.text.split()) == 4


# --------------------------------------------------------------------------- evo

def test_tum_utm_positions_times_and_heading(flight, tmp_path):
    from scipy.spatial.transform import Rotation

    sim, run, meta = flight
    work = tmp_path / "run"
    shutil.copytree(run, work)
    assert main(["export", str(work), "--tum-utm", "--video-start", str(meta["t0_unix"]),
                 "--gps-tlog", str(sim / "telemetry.tlog"), "-q"]) == 0
    data = np.loadtxt(work / "trajectory_utm.tum")
    rows = [r for r in RunFiles(work).rows if r.glued]
    assert len(data) == len(rows)
    assert data[:, 0] == pytest.approx(meta["t0_unix"] + np.array([r.t for r in rows]), abs=1e-6)
    epsg = utm_epsg(meta["origin"]["lat"], meta["origin"]["lon"])
    e, n = utm_forward(np.array([r.extra["lat"] for r in rows]), np.array([r.extra["lon"] for r in rows]), epsg)
    assert np.hypot(data[:, 1] - e, data[:, 2] - n).max() < 0.05
    # heading of the image's up direction (true north, through the grid convergence) vs the truth's yaw
    gt = read_groundtruth(sim / "groundtruth.csv")
    yaw = dict(zip(gt.frame.tolist(), gt.columns["yaw_deg"].tolist()))
    up = Rotation.from_quat(data[:, 4:8]).apply([0.0, -1.0, 0.0])
    lat1, lon1 = utm_inverse(data[:, 1], data[:, 2], epsg)
    lat2, lon2 = utm_inverse(data[:, 1] + up[:, 0], data[:, 2] + up[:, 1], epsg)
    de, dn = enu_from_latlon(lat2, lon2, float(lat1[0]), float(lon1[0]))
    de0, dn0 = enu_from_latlon(lat1, lon1, float(lat1[0]), float(lon1[0]))
    heading = np.degrees(np.arctan2(de - de0, dn - dn0))
    diff = (heading - np.array([yaw[r.frame] for r in rows]) + 180.0) % 360.0 - 180.0
    assert np.abs(diff).max() < 1.0
    assert np.abs(up[:, 2]).max() < 1e-9  # level: the image plane is horizontal
    # GPS in the same frame: at the frames' times the GPS and the map agree within a metre
    gps = np.loadtxt(work / "gps_utm.tum")
    ge = np.interp(data[:, 0], gps[:, 0], gps[:, 1])
    gn = np.interp(data[:, 0], gps[:, 0], gps[:, 2])
    assert np.hypot(ge - data[:, 1], gn - data[:, 2]).max() < 1.0


def test_tum_utm_without_the_video_start_says_what_is_missing(flight, tmp_path, capsys):
    work = tmp_path / "run"
    shutil.copytree(flight[1], work)
    summary = json.loads((work / "run.json").read_text())
    summary["video_start_unix"] = None  # e.g. a video file without a creation time, no telemetry
    (work / "run.json").write_text(json.dumps(summary))
    assert main(["export", str(work), "--tum-utm"]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "video_start_unix" in err[0] and "--video-start" in err[0]


# --------------------------------------------------------------------------- tiles/ georeference

def test_full_resolution_tiles_get_world_files_and_a_vrt(flight, tmp_path):
    rasterio = pytest.importorskip("rasterio", reason="the geo extra (rasterio) is not installed")
    work = tmp_path / "run"
    shutil.copytree(flight[1], work)
    assert main(["export", str(work), "--tile-georef", "-q"]) == 0
    run = RunFiles(work)
    m2c, epsg = run.georeference()
    entry = run.mosaic()
    ts = entry["tile_size"]
    tile = sorted((work / "tiles").glob("tile_*.png"))[0]
    tx, ty = (int(v) for v in tile.stem.split("_")[1:])
    world = parse_world_file((work / "tiles" / f"{tile.stem}.pgw").read_text())
    assert world[:, :2] == pytest.approx(m2c[:, :2], abs=1e-12)
    assert world[:, 2] == pytest.approx(m2c @ [tx * ts, ty * ts, 1.0], abs=1e-6)
    with rasterio.open(tile) as src:  # GDAL reads the world file and the .aux.xml CRS
        assert src.crs.to_epsg() == epsg
        assert src.transform @ (0.5, 0.5) == pytest.approx(tuple(m2c @ [tx * ts, ty * ts, 1.0]), abs=1e-6)
    with rasterio.open(work / "tiles.vrt") as vrt:
        assert vrt.crs.to_epsg() == epsg and vrt.count == 4
        x0, y0 = vrt.transform @ (0.5, 0.5)  # centre of the VRT's top-left pixel
        keys = [tuple(int(v) for v in p.stem.split("_")[1:]) for p in (work / "tiles").glob("tile_*.png")]
        kx, ky = min(k[0] for k in keys), min(k[1] for k in keys)
        assert (x0, y0) == pytest.approx(tuple(m2c @ [kx * ts, ky * ts, 1.0]), abs=1e-6)
        win = rasterio.windows.Window((tx - kx) * ts, (ty - ky) * ts, ts, ts)
        data = vrt.read(window=win)
    png = cv2.imread(str(tile), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(data[0], png[..., 2]) and np.array_equal(data[3], png[..., 3])


# --------------------------------------------------------------------------- report and errors

class _Links(html.parser.HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.refs: list[str] = []
        self.tags: set[str] = set()

    def handle_starttag(self, tag, attrs):
        self.tags.add(tag)
        self.refs += [v for k, v in attrs if k in ("src", "href") and v]


def test_report_is_self_contained_and_says_what_happened(flight, tmp_path):
    work = tmp_path / "run"
    shutil.copytree(flight[1], work)
    assert main(["export", str(work), "--report", "-q"]) == 0
    text = (work / "report.html").read_text()
    parser = _Links()
    parser.feed(text)
    assert parser.refs and all(r.startswith("data:image/") for r in parser.refs)
    assert "script" not in parser.tags and "link" not in parser.tags and "svg" in parser.tags
    summary = json.loads((work / "run.json").read_text())
    assert f"<th>frames in</th><td>{summary['frames_in']}</td>" in text
    assert "EPSG:32617" in text and "km²" in text and "in sync" in text
    assert f"{summary['metres_per_pixel'] * 100:.2f} cm/pixel" in text


def test_the_runs_report_draws_its_map_from_the_tiles_as_the_png_shows_it(flight, tmp_path, monkeypatch):
    """A run writes report.html without reading its (maybe huge) PNG back: the thumbnail comes
    from the map's tiles in bands. It shows what `export --report` draws from the PNG."""
    import base64

    from photomap.io import report

    def thumbnail(text):
        parser = _Links()
        parser.feed(text)
        uri = next(r for r in parser.refs if r.startswith("data:image/"))
        return cv2.imdecode(np.frombuffer(base64.b64decode(uri.split(",", 1)[1]), np.uint8), cv2.IMREAD_UNCHANGED)

    sim, work = flight[0], tmp_path / "run"
    with monkeypatch.context() as m:
        m.setattr(report, "_thumbnail", lambda *a, **k: pytest.fail("the run read its PNG back"))
        assert main(["replay", str(sim / "video.mp4"), "--out", str(work), "--no-progress", "-q",
                     "--set", "output.max_mosaic_px=700"]) == 0
    from_tiles = thumbnail((work / "report.html").read_text())
    assert main(["export", str(work), "--report", "-q"]) == 0
    from_png = thumbnail((work / "report.html").read_text())
    png = cv2.imread(str(work / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    assert from_tiles.shape == from_png.shape and max(from_png.shape[:2]) == min(960, max(png.shape[:2]))
    inside = (from_tiles[..., 3] == 255) & (from_png[..., 3] == 255)
    assert inside.mean() > 0.3
    diff = np.abs(from_tiles[..., :3].astype(int) - from_png[..., :3])[inside]
    assert np.median(diff) <= 4  # the same picture (both WebP-encoded)


def test_export_without_georeference_is_one_clear_line(flight, tmp_path, capsys):
    work = tmp_path / "run"
    shutil.copytree(flight[1], work)
    summary = json.loads((work / "run.json").read_text())
    for m in summary["mosaics"]:
        m["georeference"] = {"metres_per_pixel": None}
    summary["georeference"] = None
    (work / "run.json").write_text(json.dumps(summary))
    for name in ("track.kml", "track.geojson", "map.tif"):  # what the run itself wrote
        (work / name).unlink(missing_ok=True)
    for flag in ("--cog", "--tiles", "--kml"):
        assert main(["export", str(work), flag]) == 3
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "georeference" in err[0] and "--mavlink" in err[0], err
    # without a flag: what it can (the report), no error
    assert main(["export", str(work), "-q"]) == 0
    assert (work / "report.html").is_file() and not (work / "track.kml").exists()
    assert main(["export", str(tmp_path / "nothing-here")]) == 3
    assert "not found" in capsys.readouterr().err


# --------------------------------------------------------------------------- pipeline hooks

def test_pipeline_hook_writes_the_same_cog_from_the_live_mosaic(flight, tmp_path):
    rasterio = pytest.importorskip("rasterio", reason="the geo extra (rasterio) is not installed")
    from photomap.mapping.geo_outputs import refresh_track_files, write_geo_outputs

    work = tmp_path / "run"
    shutil.copytree(flight[1], work)
    run = RunFiles(work)
    entry = run.mosaic()
    ts = entry["tile_size"]
    # the live mosaic, rebuilt exactly from its full-resolution tiles
    mosaic = TiledMosaic(MosaicConfig(tile_size=ts, border=0))
    for p in (work / "tiles").glob("tile_*.png"):
        tx, ty = (int(v) for v in p.stem.split("_")[1:])
        bgra = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        mosaic.add(bgra[..., :3], np.array([[1.0, 0, tx * ts], [0, 1.0, ty * ts]]), mask=bgra[..., 3])
    done = write_geo_outputs(work, run.mosaics, {entry["segment"]: mosaic}, run.rows, run.frame_size)
    assert set(done) == {"cog", "tile_georeference", "track"}
    assert main(["export", str(work), "--cog", str(tmp_path / "from_files.tif"), "-q"]) == 0
    with rasterio.open(work / "map.tif") as a, rasterio.open(tmp_path / "from_files.tif") as b:
        assert a.transform == b.transform and a.crs == b.crs
        assert np.array_equal(a.read(), b.read())
    assert (work / "tiles.vrt").is_file() and (work / "track.kml").is_file()
    # a checkpoint before any georeference writes nothing; with one it rewrites the files
    (work / "track.kml").unlink()
    assert refresh_track_files(work, run.rows, run.frame_size, {}) is None and not (work / "track.kml").exists()
    assert refresh_track_files(work, run.rows[:30], run.frame_size, run.georeferences())["features"] >= 3
    assert (work / "track.kml").is_file()


def test_cog_of_a_rotated_map_is_written_by_windows_and_resampled_right(tmp_path):
    """A procedural map (a smooth pattern known at every map point) under a 30-degree georeference:
    the GeoTIFF holds the pattern at each pixel's map point, and writing it never held the whole
    image (Python's peak allocation stays a fraction of it)."""
    rasterio = pytest.importorskip("rasterio", reason="the geo extra (rasterio) is not installed")
    import tracemalloc

    from photomap.io.geotiff import write_cog

    n = 2000

    def pattern(u, v):
        return (np.sin(u / 23.0) + np.cos(v / 31.0)) * 60.0 + 128.0

    def render(x, y, w, h, s):
        ow, oh = max(1, round(w * s)), max(1, round(h * s))
        u, v = np.meshgrid(x + (np.arange(ow) + 0.5) * w / ow - 0.5, y + (np.arange(oh) + 0.5) * h / oh - 0.5)
        inside = (u >= -0.5) & (u < size - 0.5) & (v >= -0.5) & (v < size - 0.5)
        img = np.zeros((oh, ow, 3), np.uint8)
        img[..., 1] = np.where(inside, np.rint(pattern(u, v)), 0).astype(np.uint8)
        return img, np.where(inside, 255, 0).astype(np.uint8)

    th, mpp = math.radians(30.0), 0.05
    m2c = np.array([[mpp * math.cos(th), mpp * math.sin(th), 400000.0],
                    [mpp * math.sin(th), -mpp * math.cos(th), 4500000.0]])
    peaks, sizes = [], []
    for size in (n // 2, n):  # the peak allocation must not grow with the image
        tracemalloc.start()
        try:
            info = write_cog(tmp_path / "rot.tif", MapRaster(render, (0, 0, size, size), m2c, 32617))
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
        sizes.append(info["size"][0] * info["size"][1])
    assert sizes[1] > 3.5 * sizes[0] and peaks[1] < 1.5 * peaks[0], (sizes, peaks)
    assert peaks[1] < sizes[1] * 4  # less than one whole RGBA image
    with rasterio.open(tmp_path / "rot.tif") as src:
        t = src.transform
        green, alpha = src.read(2), src.read(4)
    rows, cols = np.nonzero(alpha == 255)
    pick = np.random.default_rng(1).choice(len(rows), 2000, replace=False)
    e = t.c + t.a * (cols[pick] + 0.5)
    nn = t.f + t.e * (rows[pick] + 0.5)
    uv = np.c_[e - m2c[0, 2], nn - m2c[1, 2]] @ np.linalg.inv(m2c[:, :2]).T
    err = np.abs(green[rows[pick], cols[pick]].astype(float) - pattern(uv[:, 0], uv[:, 1]))
    assert np.median(err) < 0.5 and err.max() < 2.0  # bilinear on a smooth pattern, 8-bit rounding


def test_opaque_blocks_warped_directly_match_the_alpha_weighted_warp(monkeypatch):
    """A GeoTIFF block whose source is opaque and inside the map is warped as it is: the same
    colours (within 1) as the alpha-weighted float warp, at any rotation and scale; a block that
    reaches past the map's edge still takes the weighted warp (its edge pixels partly transparent)."""
    from photomap.io import geotiff

    rng = np.random.default_rng(3)
    photo = cv2.GaussianBlur(rng.integers(0, 256, (700, 700, 3), np.uint8), (0, 0), 1.5)
    photo = np.clip(photo.astype(np.float32) * 4 - 380, 0, 255).astype(np.uint8)  # full range, sharp

    def render(x, y, w, h, scale):
        image, alpha = photo[y:y + h, x:x + w], np.full((h, w), 255, np.uint8)
        if scale < 1:
            size = (max(1, round(w * scale)), max(1, round(h * scale)))
            image, alpha = (cv2.resize(a, size, interpolation=cv2.INTER_AREA) for a in (image, alpha))
        return image, alpha

    direct, taken = geotiff._samples_inside, []

    def spy(*args):
        taken.append(direct(*args))
        return taken[-1]

    for angle in np.radians([0.0, 17.0, 90.0, 143.0, 251.0]):
        s = rng.uniform(0.6, 1.4)
        a = np.array([[s * math.cos(angle), -s * math.sin(angle), 0.0],
                      [s * math.sin(angle), s * math.cos(angle), 0.0]])
        for centre, inside in (((350.0, 350.0), True), ((30.0, 350.0), False)):  # in the map; past its edge
            a[:, 2] = np.asarray(centre) - a[:, :2] @ [60.0, 60.0]
            monkeypatch.setattr(geotiff, "_samples_inside", spy)
            fast = geotiff.resample_planes(render, (0, 0, 700, 700), a, (120, 120))
            assert taken[-1] == inside and (fast[3].min() == 255) == inside
            monkeypatch.setattr(geotiff, "_samples_inside", lambda *args: False)  # always weighted
            weighted = geotiff.resample_planes(render, (0, 0, 700, 700), a, (120, 120))
            assert np.array_equal(fast[3], weighted[3])
            diff = np.abs(np.stack(fast[:3]).astype(int) - np.stack(weighted[:3]).astype(int))
            assert diff.max() <= 1 and (diff > 0).mean() < 0.01, (math.degrees(angle), diff.max())


def test_cog_overviews_are_the_alpha_weighted_halvings_of_its_full_resolution(tmp_path):
    """The COG's overviews, read back with rasterio: GDAL's COG layout and level sizes, each level
    the alpha-weighted 2 x 2 halving of the level above (within 1: 8-bit rounding), and a map of
    one colour keeps that colour at every covered pixel of every level (empty pixels never darken
    its edges)."""
    rasterio = pytest.importorskip("rasterio", reason="the geo extra (rasterio) is not installed")
    from photomap.core.pyramid import halve
    from photomap.io.geotiff import overview_sizes, write_cog

    size, colour = 700, None

    def render(x, y, w, h, s):
        ow, oh = max(1, round(w * s)), max(1, round(h * s))
        u, v = np.meshgrid(x + (np.arange(ow) + 0.5) * w / ow - 0.5, y + (np.arange(oh) + 0.5) * h / oh - 0.5)
        disc = np.hypot(u - size / 2, v - size / 2) < size * 0.45
        img = np.zeros((oh, ow, 3), np.uint8)
        img[...] = colour if colour is not None else np.dstack(
            [np.rint((np.sin(u / 9.0) + np.cos(v / 13.0)) * 60 + 128)] * 3).astype(np.uint8)
        return img, np.where(disc, 255, 0).astype(np.uint8)

    th, mpp = math.radians(20.0), 0.05
    m2c = np.array([[mpp * math.cos(th), mpp * math.sin(th), 400000.0],
                    [mpp * math.sin(th), -mpp * math.cos(th), 4500000.0]])
    for colour in (None, (40, 200, 90)):
        info = write_cog(tmp_path / "map.tif", MapRaster(render, (0, 0, size, size), m2c, 32617), block=64)
        sizes = overview_sizes(*info["size"], 64)
        assert len(sizes) >= 3
        with rasterio.open(tmp_path / "map.tif") as src:
            assert src.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
            assert [(src.width + f - 1) // f for f in src.overviews(1)] == [w for w, _ in sizes]
            level = np.dstack(src.read()[[2, 1, 0, 3]])  # BGRA
        for k, (w, h) in enumerate(sizes):
            with rasterio.open(tmp_path / "map.tif", overview_level=k) as ovr:
                got = np.dstack(ovr.read()[[2, 1, 0, 3]])
            assert got.shape == (h, w, 4)
            want = halve(level)
            diff = np.abs(got.astype(int) - want.astype(int))
            assert diff.max() <= 1 and (diff > 0).mean() < 0.05, (k, diff.max())
            covered = got[..., 3] > 0
            assert covered.mean() > 0.3
            if colour is not None:
                assert (got[covered, :3] == colour).all()
            level = got


def test_track_files_grow_during_a_live_run(flight, tmp_path):
    """At each checkpoint the track is rewritten from the current GPS fit: a ground station that
    reloads track.geojson sees the coverage grow, at the simulator's true positions."""
    from photomap.cli.wiring import open_telemetry
    from photomap.config import load_config
    from photomap.drivers.video import VideoFileSource
    from photomap.mapping.pipeline import MappingPipeline

    sim = flight[0]
    out = tmp_path / "live"
    cfg = load_config(overrides=["output.checkpoint_interval=0.000001"])
    join, _, cfg = open_telemetry(str(sim / "telemetry.tlog"), cfg, input_spec=str(sim / "video.mp4"))
    seen = {}

    def watch(event):
        # the track comes from a low-priority checkpoint writer: from frame 10 on, a frame that finds
        # none yet gives it time (a loaded host had the writer far behind the frames)
        path = out / "track.geojson"
        if wait_until(path.is_file, 2.0 if event.index >= 10 and not seen else 0.0, 0.01):
            seen.setdefault(event.index, json.loads(path.read_text()))

    MappingPipeline(VideoFileSource(sim / "video.mp4"), cfg, out, sinks=[watch], telemetry=join).run()
    early = min(seen)
    assert early < 60  # long before the end of the 90 frames
    tracks = [f for f in seen[early]["features"] if f["geometry"]["type"] == "LineString"]
    assert tracks and len(tracks[0]["geometry"]["coordinates"]) < 90
    meta = yaml.safe_load((sim / "meta.yaml").read_text())
    truth = read_groundtruth(sim / "groundtruth.csv")
    lon, lat = tracks[0]["geometry"]["coordinates"][0]
    c = truth.H[0] @ np.array([319.5, 239.5, 1.0])
    tlat, tlon = pixel_to_latlon(c[0] / c[2], c[1] / c[2], meta["gsd"], meta["origin"]["lat"], meta["origin"]["lon"])
    assert math.hypot((lat - tlat) * 111_320.0, (lon - tlon) * 111_320.0 * math.cos(math.radians(lat))) < 1.0


def test_report_thumbnail_is_the_alpha_weighted_downscale(tmp_path, monkeypatch):
    """The report's map thumbnail (built a band of rows at a time) equals the alpha-weighted
    INTER_AREA downscale of the whole PNG: transparent where the map is, no dark fringe."""
    import base64

    from photomap.io.report import _thumbnail

    rng = np.random.default_rng(4)
    h, w = 2100, 3333
    image = cv2.resize(rng.integers(0, 256, (43, 67, 3), dtype=np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)
    alpha = np.zeros((h, w), np.uint8)
    cv2.circle(alpha, (w // 2, h // 2), 1000, 255, -1)
    image[alpha == 0] = 0
    cv2.imwrite(str(tmp_path / "m.png"), np.dstack([image, alpha]))
    encode = cv2.imencode
    monkeypatch.setattr(cv2, "imencode", lambda ext, *a: (False, None) if ext == ".webp" else encode(ext, *a))
    uri, scale, size = _thumbnail(tmp_path / "m.png", max_px=500)
    monkeypatch.undo()
    got = cv2.imdecode(np.frombuffer(base64.b64decode(uri.split(",", 1)[1]), np.uint8), cv2.IMREAD_UNCHANGED)
    a = alpha[..., None].astype(np.float32) / 255
    want = cv2.resize(np.dstack([image * a, a]), size, interpolation=cv2.INTER_AREA)
    cover = want[..., 3:]
    colour = np.where(cover > 1e-6, want[..., :3] / np.maximum(cover, 1e-6), 0)
    want = np.dstack([np.clip(np.rint(colour), 0, 255), np.clip(np.rint(cover * 255), 0, 255)]).astype(np.uint8)
    inside = cover[..., 0] > 0.99
    assert got.shape == (size[1], size[0], 4) and size == (500, 315) and scale == pytest.approx(500 / w)
    assert uri.startswith("data:image/png")  # lossless here: the pixels can be compared
    diff = np.abs(got.astype(int) - want)
    assert np.median(diff[..., :3][inside]) <= 1 and diff[..., :3][inside].max() <= 3
    assert diff[..., 3].max() <= 3
