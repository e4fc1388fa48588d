"""The live map server (photomap.live.mapserver): on loopback, during replays of simulated flights."""

from __future__ import annotations

import http.client
import json
import math
import shutil
import socket
import subprocess
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from photomap.cli.replay import replay
from photomap.cli.wiring import open_capture, open_telemetry
from photomap.config import load_config
from photomap.errors import ConfigError
from photomap.geo import webmercator as wm
from photomap.io.trajectory_files import read_groundtruth
from photomap.live.mapserver import MapServer, parse_listen
from photomap.mapping.pipeline import MappingPipeline
from photomap.sim.flight import latlon_to_pixel, pixel_to_latlon
from photomap.sim.simulate import simulate_flight
from photomap.sim.terrain import load_terrain
from tests.tiles import tile_bgra
from tests.waiting import wait_until

W, H = 640, 480


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    return simulate_flight(tmp_path_factory.mktemp("mapserver") / "flight", n_frames=160, size=(W, H), fps=20.0,
                           seed=2)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(url: str, timeout: float = 10.0) -> tuple[int, bytes, str]:
    try:
        with urllib.request.urlopen(url, timeout=timeout) as r:
            return r.status, r.read(), r.headers.get("Content-Type", "")
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read(), exc.headers.get("Content-Type", "")


def _status(base: str) -> dict | None:
    try:
        code, body, _ = _get(base + "status.json", timeout=5.0)
    except OSError:
        return None
    return json.loads(body) if code == 200 else None


def _decode(png: bytes) -> np.ndarray:
    assert png.startswith(b"\x89PNG"), "not a PNG"
    return tile_bgra(png)


def _terrain_under(tile_xyz: tuple[int, int, int], flight: Path) -> np.ndarray:
    """The simulator's terrain (grey) at each pixel centre of an XYZ tile: the truth it shows."""
    meta = yaml.safe_load((flight / "meta.yaml").read_text())
    terrain = cv2.cvtColor(load_terrain(meta["terrain"]["name"], zoom=meta["terrain"]["zoom"]), cv2.COLOR_BGR2GRAY)
    x, y, z = tile_xyz
    u = np.arange(wm.TILE_PX) + 0.5
    lat, _ = wm.pixel_to_latlon(0.0, y * wm.TILE_PX + u, z)
    _, lon = wm.pixel_to_latlon(x * wm.TILE_PX + u, 0.0, z)
    lon_g, lat_g = np.meshgrid(lon, lat)
    px, py = latlon_to_pixel(lat_g, lon_g, meta["gsd"], meta["origin"]["lat"], meta["origin"]["lon"])
    blurred = cv2.GaussianBlur(terrain, (0, 0), 1.0)  # the tile's pixels are ~2 terrain pixels
    return cv2.remap(blurred, px.astype(np.float32), py.astype(np.float32), cv2.INTER_LINEAR).astype(float)


def _correlation(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    a, b = a[mask] - a[mask].mean(), b[mask] - b[mask].mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def test_parse_listen():
    assert parse_listen("8000", 8765) == ("127.0.0.1", 8000)
    assert parse_listen("127.0.0.1", 8765) == ("127.0.0.1", 8765)
    assert parse_listen("0.0.0.0:9000", 8765) == ("0.0.0.0", 9000)
    for bad in ("http://x", "99999", "host:1", "1.2.3.4:0"):
        with pytest.raises(ConfigError, match="map server"):
            parse_listen(bad, 8765)
    assert MapServer.from_config(load_config().map_server) is None  # off by default


def test_live_tile_at_the_vehicle_is_mapped_during_a_realtime_replay(flight, tmp_path):
    """During a --realtime replay with telemetry: status answers, the tile at the vehicle's
    position at max_zoom is a 256x256 PNG more than half mapped, showing the true terrain, and
    stays so as frames come in; the run ends with the same tiles in xyz/."""
    port = _free_port()
    base = f"http://127.0.0.1:{port}/"
    cfg = load_config().updated({"output": {"checkpoint_interval": 1.0}})
    out = tmp_path / "run"
    result: dict = {}

    def run() -> None:
        result["summary"] = replay(str(flight / "video.mp4"), out, cfg, realtime=True,
                                   mavlink=str(flight / "telemetry.tlog"), map_server=str(port))

    worker = threading.Thread(target=run)
    worker.start()
    truth = read_groundtruth(flight / "groundtruth.csv")
    meta = yaml.safe_load((flight / "meta.yaml").read_text())
    samples = []
    try:
        st = wait_until(lambda: (s := _status(base)) and s["georeferenced"] and s["position"] and s, 60.0, 0.2)
        assert st is not None, "no georeferenced status during the replay"
        assert st["tiles_url"] == "/tiles/{z}/{x}/{y}.png" and st["telemetry"] == "georeferenced"
        for due in (60, 95, 130):  # of the 160 frames
            st = wait_until(lambda: (s := _status(base)) and s["frames_in"] >= due and s, 30.0, 0.2)
            if st is None:
                break
            z = st["max_zoom"]
            x, y = wm.tile_of(st["position"]["lat"], st["position"]["lon"], z)
            code, png, ctype = _get(f"{base}tiles/{z}/{x}/{y}.png")
            assert code == 200 and ctype == "image/png"
            samples.append((st, (x, y, z), _decode(png)))
            # the position is the latest frame's centre (truth: the simulator's matrix)
            k = st["frame"]
            c = truth.H[k] @ np.array([(W - 1) / 2, (H - 1) / 2, 1.0])
            lat, lon = pixel_to_latlon(c[0] / c[2], c[1] / c[2], meta["gsd"], meta["origin"]["lat"],
                                       meta["origin"]["lon"])
            err = np.hypot((st["position"]["lat"] - lat) * 111_320.0,
                           (st["position"]["lon"] - lon) * 111_320.0 * np.cos(np.radians(lat)))
            assert err < 3.0, f"position {err:.1f} m from the truth at frame {k}"
    finally:
        worker.join(timeout=120)
    assert not worker.is_alive()
    assert len(samples) == 3 and samples[0][0]["frames_in"] < samples[1][0]["frames_in"] < samples[2][0]["frames_in"]
    for st, xyz, tile in samples:
        assert tile.shape == (256, 256, 4)
        covered = tile[..., 3] > 0
        assert covered.mean() > 0.5, f"tile {xyz} at {st['frames_in']} frames: {covered.mean():.0%} mapped"
        grey = cv2.cvtColor(tile[..., :3], cv2.COLOR_BGR2GRAY).astype(float)
        assert _correlation(grey, _terrain_under(xyz, flight), covered) > 0.6  # the terrain that is there
    assert result["summary"]["registered"] == 160
    # the same tiles on disk, as `photomap export --tiles` writes them
    info = json.loads((out / "xyz" / "tiles.json").read_text())
    assert info["zooms"][1] == samples[-1][0]["max_zoom"]
    x, y, z = samples[-1][1]
    disk = tile_bgra(out / "xyz" / str(z) / str(x) / f"{y}.png")
    live = samples[-1][2]
    both = (disk[..., 3] > 0) & (live[..., 3] > 0)
    assert both.mean() > 0.4
    assert _correlation(cv2.cvtColor(disk[..., :3], cv2.COLOR_BGR2GRAY).astype(float),
                        cv2.cvtColor(live[..., :3], cv2.COLOR_BGR2GRAY).astype(float), both) > 0.8


def test_hostile_clients_cost_the_mapping_nothing_and_are_bounded(flight, tmp_path):
    """Slow clients, a huge request and many connections: the map is the same as without the
    server, the server's threads and connections stay within their bounds, and a good client is
    answered once the slow ones are cut off."""
    cfg = load_config().updated({"map_server": {"threads": 2, "max_connections": 4, "timeout_s": 1.0}})
    server = MapServer(cfg.map_server, "127.0.0.1", 0)
    base = f"http://127.0.0.1:{server.port}/"
    slow = []
    try:
        for _ in range(12):  # more than max_connections, each sending half a request line
            s = socket.create_connection(("127.0.0.1", server.port))
            s.sendall(b"GET /status.j")
            slow.append(s)
        huge = socket.create_connection(("127.0.0.1", server.port))
        source = open_capture(str(flight / "video.mp4"), cfg.capture)
        pipeline = MappingPipeline(source, cfg, tmp_path / "with", sinks=[server.on_frame])
        with_server = pipeline.run()
        threads = [t for t in threading.enumerate() if t.name.startswith("photomap-mapserver")]
        assert len(threads) <= 2 + 3  # the pool, the accepting, the idle and the packing thread
        # beyond max_connections a connection is closed at once
        assert server.stats["refused"] >= 12 - 4
        # the slow ones were cut off after the timeout; then a good client is answered
        assert wait_until(lambda: server.stats["timeouts"] >= 2, timeout=30.0)
        try:
            huge.sendall(b"GET /" + b"a" * 20000 + b" HTTP/1.0\r\n\r\n")
        except OSError:
            pass  # refused at once: the pool was full
        got = wait_until(lambda: _status(base), 30.0, 0.2)
        assert got is not None and got["frames_in"] == with_server["frames_in"]
        s = socket.create_connection(("127.0.0.1", server.port))
        s.sendall(b"GET /" + b"a" * 20000 + b" HTTP/1.0\r\n\r\n")
        s.settimeout(10)
        answer = b""
        try:
            while chunk := s.recv(4096):
                answer += chunk
        except OSError:
            pass
        assert answer.startswith(b"HTTP/1.1 431")
        assert server.stats["too_large"] >= 1
    finally:
        for s in slow:
            s.close()
        server.close()
    without = MappingPipeline(open_capture(str(flight / "video.mp4"), cfg.capture), cfg, tmp_path / "without").run()
    assert with_server["registered"] == without["registered"] == 160
    a = (tmp_path / "with" / "trajectory.csv").read_text()
    b = (tmp_path / "without" / "trajectory.csv").read_text()
    assert a == b  # the same map, frame by frame


def test_pixel_frame_without_telemetry(flight, tmp_path):
    """Without a georeference: no web-mercator tiles, the map in its own pixel frame."""
    cfg = load_config()
    server = MapServer(cfg.map_server, "127.0.0.1", 0)
    base = f"http://127.0.0.1:{server.port}/"
    try:
        pipeline = MappingPipeline(open_capture(str(flight / "video.mp4"), cfg.capture), cfg, tmp_path / "run",
                                   sinks=[server.on_frame])
        pipeline.run()
        server.live.flush()
        st = _status(base)
        assert st["telemetry"] == "none" and not st["georeferenced"] and st["tiles_url"].startswith("/pixel/")
        assert _get(f"{base}tiles/19/0/0.png")[0] == 404
        pz = st["pixel_zoom"]
        x, y = (int(v // 256) for v in (st["position"]["x"], st["position"]["y"]))
        code, png, _ = _get(f"{base}pixel/{pz}/{x}/{y}.png")
        tile = _decode(png)
        mosaic = cv2.imread(str(tmp_path / "run" / "mosaic.png"), cv2.IMREAD_UNCHANGED)
        run = json.loads((tmp_path / "run" / "run.json").read_text())
        ox, oy = run["mosaics"][0]["origin_xy"]
        assert run["mosaics"][0]["scale"] == 1.0
        # tile (x, y) at the pixel zoom is map pixels 256 x .. 256 x + 255: the mosaic's there
        crop = mosaic[256 * y - oy:256 * y - oy + 256, 256 * x - ox:256 * x - ox + 256]
        both = (tile[..., 3] > 0) & (crop[..., 3] > 0 if crop.shape[2] == 4 else True)
        assert crop.shape[:2] == (256, 256) and both.mean() > 0.5
        assert np.abs(tile[..., :3][both].astype(int) - crop[..., :3][both].astype(int)).mean() < 3
        track = json.loads(_get(base + "track.geojson")[1])
        assert track["frame"] == "map_pixels" and len(track["features"][0]["geometry"]["coordinates"]) == 160
        hazards = json.loads(_get(base + "hazards.geojson")[1])
        assert hazards == {"type": "FeatureCollection", "features": []}
    finally:
        server.close()


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name) or (f"/usr/bin/{name}" if Path(f"/usr/bin/{name}").exists() else None)
        if path:
            return path
    return None


def screenshot(url: str, out: Path, profile: Path, size: tuple[int, int] = (800, 600),
               budget_ms: int = 8000) -> subprocess.CompletedProcess:
    """Headless Chromium's screenshot of ``url`` (no network beyond it, a fresh profile)."""
    exe = _chromium()
    args = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            "--hide-scrollbars", f"--user-data-dir={profile}", f"--screenshot={out}",
            f"--window-size={size[0]},{size[1]}", f"--virtual-time-budget={budget_ms}", url]
    return subprocess.run(args, capture_output=True, text=True, timeout=120)


class _HeldOpen:
    """A frame source that, after its last frame, waits for ``release`` (at most 120 s) before it
    ends: the run goes on (and its server with it) while the page is looked at."""

    def __init__(self, source, release: threading.Event) -> None:
        self._source, self._release = source, release

    def __getattr__(self, name):
        return getattr(self._source, name)

    def __iter__(self):
        yield from self._source
        self._release.wait(120.0)


def test_page_renders_map_pixels_in_chromium(flight, tmp_path):
    """During a --realtime replay with telemetry, the page at / loads in headless Chromium, uses
    /tiles/ and shows the map's pixels in the served tiles' colours; loaded again (its cache
    holding the tiles) while the map stands still, it shows them from 304 answers alone."""
    if _chromium() is None:
        pytest.skip("chromium is not installed (apt-get install chromium)")
    from photomap.cli.wiring import map_source

    # a tile is rendered whenever its map changed: once the map stands still, nothing changes
    cfg = load_config().updated({"output": {"checkpoint_interval": 1.0}, "map_server": {"min_render_interval_s": 0.0}})
    port = _free_port()
    base = f"http://127.0.0.1:{port}/"
    release = threading.Event()
    source = _HeldOpen(open_capture(str(flight / "video.mp4"), cfg.capture), release)
    join, _, cfg = open_telemetry(str(flight / "telemetry.tlog"), cfg, source=source,
                                  input_spec=str(flight / "video.mp4"), realtime=True)
    worker = threading.Thread(target=lambda: map_source(source, cfg, tmp_path / "run", realtime=True, telemetry=join,
                                                        map_server=str(port)))
    worker.start()
    shot, again = tmp_path / "page.png", tmp_path / "again.png"
    try:
        st = wait_until(lambda: (s := _status(base)) and s["georeferenced"] and s["frames_in"] >= 100 and s, 60.0, 0.2)
        assert st is not None, "no georeferenced status during the replay"
        before = st["server"]["requests"]
        proc = screenshot(base, shot, tmp_path / "profile")
        assert shot.is_file(), proc.stderr[-2000:]
        st = _status(base)
        assert st["tile_renders"] + st["tile_hits"] > 0 and st["server"]["requests"] > before + 3  # /tiles/
        z = st["max_zoom"] - 1  # the page's first zoom: about the whole map in view
        west, south, east, north = st["bounds"]
        tiles = [_decode(_get(f"{base}tiles/{z}/{x}/{y}.png")[1]) for x, y in wm.tiles_covering(south, west, north, east, z)]
        # every frame in, the run held open: the map stands still; the page loaded once more fills
        # its cache with the tiles as they stay, and the next load is answered 304 for every one
        assert wait_until(lambda: (s := _status(base)) and s["frames_in"] == 160, 60.0, 0.2)
        screenshot(base, tmp_path / "fill.png", tmp_path / "profile")
        st = _status(base)
        proc = screenshot(base, again, tmp_path / "profile")
        assert again.is_file(), proc.stderr[-2000:]
        after = _status(base)
        asked = after["tile_renders"] + after["tile_hits"] - st["tile_renders"] - st["tile_hits"]
        assert asked > 3 and after["server"]["not_modified"] - st["server"]["not_modified"] == asked
    finally:
        release.set()
        worker.join(timeout=120)
    # both loads show the map, in the served tiles' colours
    served = np.concatenate([t[..., :3][t[..., 3] > 0].reshape(-1, 3) for t in tiles]).mean(axis=0)
    for path in (shot, again):
        page = cv2.imread(str(path))
        assert page is not None and page.shape[:2] == (600, 800)
        background = np.abs(page.astype(int) - 0x20).max(axis=2) <= 4  # the page's #202020 where no tile is
        mapped = ~background & (page.max(axis=2) < 250)  # not the info box or a white error page
        for bgr in ((255, 224, 0), (0, 208, 255), (48, 48, 255)):  # nor the track, footprint, vehicle
            mapped &= np.abs(page.astype(int) - bgr).max(axis=2) > 60
        assert mapped.mean() > 0.15, f"only {mapped.mean():.0%} of {path.name} shows the map"
        shown = page[mapped].reshape(-1, 3).mean(axis=0)
        assert np.abs(served - shown).max() < 30, (path.name, served, shown)


def _tile_event(index: int, mosaic, touched, pose=np.array([[1.0, 0, 0], [0, 1.0, 0]])):
    from photomap.mapping.events import FrameEvent

    return FrameEvent(index, index / 10.0, False, np.zeros((64, 64, 3), np.uint8), (64, 64), "registered",
                      pose, 0.9, 0, touched=frozenset(touched), tiles=mosaic)


@pytest.mark.parametrize("interval", [0.0, 3600.0])
def test_a_painted_tile_renders_again_at_most_once_per_interval(interval):
    """A served tile follows the map: repainted map tiles reach it (at once with no minimum
    interval), a busy tile is rendered at most once per min_render_interval_s, and the worker's
    copy is of the touched tiles only."""
    from photomap.config import MosaicConfig
    from photomap.core.mosaic import TiledMosaic
    from photomap.live.livemap import LiveMap, TileCache

    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    red = np.zeros((64, 64, 3), np.uint8)
    red[..., 2] = 200
    full = np.full((64, 64), 255, np.uint8)
    mosaic.set_tile((0, 0), red, full)
    mosaic.set_tile((1, 0), red, full)
    live = LiveMap(tile_hz=1e6)
    live.on_frame(_tile_event(0, mosaic, {(0, 0), (1, 0)}))
    cache = TileCache(16, interval)
    # pixel-frame tile (0, 0) at the pixel zoom holds map pixels 0..255: our two tiles at its top left
    first = _decode(cache.get(live.snapshot(), "pixel", 0, 0, 8).body)
    assert (first[:64, :128, 2] == 200).all() and (first[:64, :128, 3] == 255).all()
    assert (first[64:, :, 3] == 0).all() and (first[:, 128:, 3] == 0).all()
    blue = np.zeros((64, 64, 3), np.uint8)
    blue[..., 0] = 180
    mosaic.set_tile((1, 0), blue, full)
    mosaic.set_tile((0, 0), blue, full)  # changed in the map but not said to be touched: not copied
    live.on_frame(_tile_event(1, mosaic, {(1, 0)}))
    again = _decode(cache.get(live.snapshot(), "pixel", 0, 0, 8).body)
    if interval == 0.0:
        assert (again[:64, 64:128, 0] == 180).all() and (again[:64, 64:128, 2] == 0).all()
        assert (again[:64, :64, 2] == 200).all()
        assert cache.renders == 2
    else:
        assert (again == first).all() and cache.renders == 1  # the busy tile waits for its interval
    # an unchanged map: the cached tile, no render
    cache.get(live.snapshot(), "pixel", 0, 0, 8)
    assert cache.renders == (2 if interval == 0.0 else 1) and cache.hits >= 1


def test_a_repainted_tile_is_served_fresh_within_the_render_interval():
    """The staleness bound: a served tile whose map tiles were repainted is the old picture for
    less than min_render_interval_s after its last render, and the repainted one from then on
    (the cache's clock, not the machine's, so that the bound is exact)."""
    from photomap.config import MosaicConfig
    from photomap.core.mosaic import TiledMosaic
    from photomap.live.livemap import LiveMap, TileCache

    now = [100.0]
    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    full = np.full((64, 64), 255, np.uint8)
    live = LiveMap(tile_hz=1e6)
    cache = TileCache(16, 2.0, clock=lambda: now[0])

    def paint(index: int, level: int) -> None:
        mosaic.set_tile((0, 0), np.full((64, 64, 3), level, np.uint8), full)
        live.on_frame(_tile_event(index, mosaic, {(0, 0)}))

    def served() -> int:
        return int(_decode(cache.get(live.snapshot(), "pixel", 0, 0, 8).body)[:64, :64, 1].max())

    paint(0, 50)
    assert served() == 50 and cache.renders == 1  # rendered at t = 100
    paint(1, 120)
    now[0] = 101.99
    assert served() == 50 and cache.renders == 1  # within the bound: the cached picture
    now[0] = 102.0
    assert served() == 120 and cache.renders == 2  # the bound reached: the repainted one
    paint(2, 200)
    now[0] = 103.5
    assert served() == 120
    now[0] = 104.01
    assert served() == 200 and cache.renders == 3
    assert served() == 200 and cache.renders == 3  # unchanged since: no render


def test_a_client_holding_the_tile_is_told_not_modified_until_the_map_changes_it():
    """Conditional GETs, as a browser's or Qt's cache sends them: a tile comes with an ETag; asked
    again with it (alone, weak, or in a list) the answer is 304 with no body while the picture is
    the same, also after a repaint that leaves it the same; a repaint that changes it is a 200
    with the new picture and a new tag."""
    from photomap.config import MosaicConfig
    from photomap.core.mosaic import TiledMosaic

    cfg = load_config().updated({"map_server": {"min_render_interval_s": 0.0}})
    server = MapServer(cfg.map_server, "127.0.0.1", 0)
    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    full = np.full((64, 64), 255, np.uint8)

    def paint(index: int, level: int) -> None:
        mosaic.set_tile((0, 0), np.full((64, 64, 3), level, np.uint8), full)
        server.on_frame(_tile_event(index, mosaic, {(0, 0)}))
        server.live.flush()

    def get(tag: str | None = None) -> tuple[int, bytes, str | None, str | None]:
        conn.request("GET", "/pixel/8/0/0.png", headers={} if tag is None else {"If-None-Match": tag})
        r = conn.getresponse()
        return r.status, r.read(), r.getheader("ETag"), r.getheader("Content-Length")

    try:
        conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
        paint(0, 50)
        code, body, tag, _ = get()
        assert code == 200 and tag and _decode(body)[:64, :64, 1].max() == 50
        for ask in (tag, f"W/{tag}", f'"other", {tag}', "*"):
            code, body, again, length = get(ask)
            assert (code, body, again, length) == (304, b"", tag, None), ask
        assert get('"other"')[0] == 200
        paint(1, 50)  # repainted, the same picture: the same tag
        assert get(tag)[:3] == (304, b"", tag)
        paint(2, 120)
        code, body, new_tag, _ = get(tag)
        assert code == 200 and new_tag != tag and _decode(body)[:64, :64, 1].max() == 120
        assert get(new_tag)[0] == 304
        conn.request("GET", "/status.json")
        stats = json.loads(conn.getresponse().read())["server"]
        assert stats["not_modified"] == 6 and stats["errors"] == 0
        conn.close()
    finally:
        server.close()


def test_tiles_mapped_everywhere_are_jpegs_with_a_jpeg_quality():
    """map_server.jpeg_quality: a tile mapped in every pixel is a JPEG of the same picture (within
    JPEG's error), one with empty pixels stays the PNG it was (transparent there). Without it,
    the first is an RGB PNG (no alpha channel), the second RGBA."""
    from photomap.config import MosaicConfig
    from photomap.core.mosaic import TiledMosaic
    from photomap.live.livemap import LiveMap, TileCache, tile_type

    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (320, 256, 3), dtype=np.uint8), (0, 0), 2.0)
    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    full = np.full((64, 64), 255, np.uint8)
    touched = set()
    for ty in range(5):  # map pixels 0..255 x 0..319: pixel-frame tile (0, 0) whole, (0, 1) a quarter
        for tx in range(4):
            mosaic.set_tile((tx, ty), texture[ty * 64:(ty + 1) * 64, tx * 64:(tx + 1) * 64].copy(), full)
            touched.add((tx, ty))
    live = LiveMap(tile_hz=1e6)
    live.on_frame(_tile_event(0, mosaic, touched))
    snap = live.snapshot()
    png_cache, jpeg_cache = TileCache(16, 0.0), TileCache(16, 0.0, jpeg_quality=90)
    whole_png, whole_jpeg = png_cache.get(snap, "pixel", 0, 0, 8).body, jpeg_cache.get(snap, "pixel", 0, 0, 8).body
    assert tile_type(whole_png) == "image/png" and tile_type(whole_jpeg) == "image/jpeg"
    assert len(whole_jpeg) < len(whole_png) / 3
    a = _decode(whole_png)
    b = cv2.imdecode(np.frombuffer(whole_jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert b.shape == (256, 256, 3) and (a[..., 3] == 255).all()
    assert np.abs(a[..., :3].astype(int) - b).mean() < 4.0  # the same picture, JPEG's error
    part_png, part_jpeg = png_cache.get(snap, "pixel", 0, 1, 8).body, jpeg_cache.get(snap, "pixel", 0, 1, 8).body
    assert tile_type(part_jpeg) == "image/png" and part_jpeg == part_png
    part = _decode(part_jpeg)
    assert (part[:64, :, 3] == 255).all() and (part[64:, :, 3] == 0).all()
    raw = [cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED) for png in (whole_png, part_png)]
    assert [image.shape[2] for image in raw] == [3, 4]


def test_status_bounds_follow_the_map_as_it_grows():
    """The status's bounds (worked out once per change of the served tiles) are those of the
    tiles copied so far, frame after frame."""
    from photomap.config import MosaicConfig
    from photomap.core.mosaic import TiledMosaic
    from photomap.live.livemap import LiveMap, status

    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    full = np.full((64, 64), 255, np.uint8)
    live = LiveMap(tile_hz=1e6)
    mosaic.set_tile((0, 0), np.full((64, 64, 3), 80, np.uint8), full)
    live.on_frame(_tile_event(0, mosaic, {(0, 0)}))
    assert status(live.snapshot())["bounds"] == [0.0, 0.0, 64.0, 64.0]
    live.on_frame(_tile_event(1, mosaic, set()))  # a frame, no new tile: the same bounds
    assert status(live.snapshot())["bounds"] == [0.0, 0.0, 64.0, 64.0]
    mosaic.set_tile((2, 1), np.full((64, 64, 3), 90, np.uint8), full)
    live.on_frame(_tile_event(2, mosaic, {(2, 1)}))
    st = status(live.snapshot())
    assert st["bounds"] == [0.0, 0.0, 192.0, 128.0] and st["frames_in"] == 3


def _status_line_and_headers(head: bytes) -> tuple[str, dict]:
    """An answer's status line and headers (``head``: up to its blank line)."""
    lines = head.decode("latin-1").split("\r\n")
    return lines[0], dict(line.split(": ", 1) for line in lines[1:])


def test_bad_requests_get_one_line_answers():
    """A request line that is not HTTP (or HTTP/1.1 without Host) gets 400, a method but GET and
    HEAD 501, HEAD the headers of the GET without its body: each one whole answer, then the
    connection is closed (HTTP/1.0, or asked to close)."""
    server = MapServer(load_config().map_server, "127.0.0.1", 0)

    def ask(request: bytes) -> tuple[str, dict, bytes]:
        with socket.create_connection(("127.0.0.1", server.port), timeout=10) as s:
            s.sendall(request)
            answer = b""
            while chunk := s.recv(65536):
                answer += chunk
        head, _, body = answer.partition(b"\r\n\r\n")
        return (*_status_line_and_headers(head), body)

    try:
        line, _, _ = ask(b"GARBAGE\r\n\r\n")
        assert line == "HTTP/1.1 400 Bad Request"
        line, _, _ = ask(b"GET /status.json HTTP/1.1\r\n\r\n")  # HTTP/1.1 without Host
        assert line == "HTTP/1.1 400 Bad Request"
        line, _, _ = ask(b"POST /status.json HTTP/1.0\r\nContent-Length: 0\r\n\r\n")
        assert line == "HTTP/1.1 501 Not Implemented"
        line, headers, body = ask(b"GET /status.json?x=1 HTTP/1.1\r\nHost: a\r\nConnection: close\r\n\r\n")
        assert line == "HTTP/1.1 200 OK" and headers["Content-Type"] == "application/json"
        assert headers["Connection"] == "close"
        assert int(headers["Content-Length"]) == len(body) and json.loads(body)["frames_in"] == 0
        line, head_headers, body = ask(b"HEAD /status.json HTTP/1.0\r\n\r\n")
        assert line == "HTTP/1.1 200 OK" and body == b"" and int(head_headers["Content-Length"]) > 0
        line, _, body = ask(b"GET /nothing/here HTTP/1.0\n\n")  # bare newlines too
        assert line == "HTTP/1.1 404 Not Found" and body == b"not found\n"
        assert server.stats["errors"] == 0
    finally:
        server.close()


def _answers(sock: socket.socket, methods: str) -> list[tuple[str, dict, bytes]]:
    """The answers to requests of ``methods`` (``"GGH"``: GET, GET, HEAD) read off one
    connection, each by its Content-Length (none after a HEAD)."""
    data, out, n = b"", [], len(methods)
    while len(out) < n:
        head, sep, rest = data.partition(b"\r\n\r\n")
        if sep:
            line, headers = _status_line_and_headers(head)
            size = 0 if methods[len(out)] == "H" else int(headers["Content-Length"])
            if len(rest) >= size:
                out.append((line, headers, rest[:size]))
                data = rest[size:]
                continue
        chunk = sock.recv(65536)
        assert chunk, f"closed after {len(out)} of {n} answers"
        data += chunk
    return out


def test_keep_alive_connections_answer_request_after_request_and_are_bounded():
    """HTTP/1.1 (and HTTP/1.0 asking for keep-alive) keeps the connection for the next request,
    pipelined ones included, as http.client and browsers use it; an idle one is closed after
    keepalive_s, the longest idle first when a new client needs its slot, and none holds an
    answering thread while it waits."""
    cfg = load_config().updated({"map_server": {"threads": 1, "max_connections": 2, "keepalive_s": 1.0}})
    server = MapServer(cfg.map_server, "127.0.0.1", 0)
    try:
        conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
        for path in ("/status.json", "/track.geojson", "/nothing", "/status.json"):
            conn.request("GET", path)
            answer = conn.getresponse()
            body = answer.read()
            assert answer.status == (404 if path == "/nothing" else 200) and answer.version == 11
            assert answer.getheader("Connection") == "keep-alive"
        assert json.loads(body)["server"]["connections"] == 1  # four answers, one connection
        conn.close()
        with socket.create_connection(("127.0.0.1", server.port), timeout=10) as s:  # pipelined
            s.sendall(b"GET /status.json HTTP/1.1\r\nHost: a\r\n\r\nHEAD /track.geojson HTTP/1.1\r\nHost: a\r\n\r\n"
                      b"GET /footprint.geojson HTTP/1.0\r\nConnection: keep-alive\r\n\r\n")
            (l1, h1, b1), (l2, h2, b2), (l3, h3, b3) = _answers(s, "GHG")
            assert l1 == l2 == l3 == "HTTP/1.1 200 OK" and json.loads(b1)["frames_in"] == 0
            assert b2 == b"" and int(h2["Content-Length"]) > 0 and json.loads(b3)["type"] == "FeatureCollection"
            s.sendall(b"GET /status.json HTTP/1.0\r\n\r\n")  # HTTP/1.0 without keep-alive: closed after
            (line, headers, _), = _answers(s, "G")
            assert headers["Connection"] == "close" and s.recv(1) == b""
        # the closed ones are let go (the server sees them close a moment later) ...
        assert wait_until(lambda: server.open_connections == 0)
        # ... then two idle keep-alive connections fill max_connections, while the one thread is free
        idle = [socket.create_connection(("127.0.0.1", server.port), timeout=10) for _ in range(2)]
        for s in idle:
            s.sendall(b"GET /status.json HTTP/1.1\r\nHost: a\r\n\r\n")
            _answers(s, "G")
            time.sleep(0.05)
        fresh = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
        fresh.request("GET", "/status.json")  # answered: the longest idle was closed for it
        answer = fresh.getresponse()
        assert answer.status == 200 and json.loads(answer.read())["server"]["refused"] == 0
        assert idle[0].recv(1) == b""
        t0 = time.monotonic()
        assert idle[1].recv(1) == b"" and time.monotonic() - t0 < 5  # idle past keepalive_s: closed
        fresh.request("GET", "/status.json")
        st = json.loads(fresh.getresponse().read())
        assert st["server"]["timeouts"] == 0 and st["server"]["errors"] == 0
        fresh.close()
        for s in idle:
            s.close()
    finally:
        server.close()


def test_without_keep_alive_every_answer_closes_its_connection():
    """``map_server.keepalive_s`` 0: HTTP/1.1 answers say ``Connection: close`` and close, and no
    thread waits for idle connections."""
    def idle_threads() -> int:
        return sum(t.name == "photomap-mapserver-idle" for t in threading.enumerate())

    cfg = load_config().updated({"map_server": {"threads": 1, "max_connections": 1, "keepalive_s": 0}})
    before = idle_threads()
    server = MapServer(cfg.map_server, "127.0.0.1", 0)
    try:
        assert idle_threads() == before
        for _ in range(3):  # one connection slot, freed by each answer
            with socket.create_connection(("127.0.0.1", server.port), timeout=10) as s:
                s.sendall(b"GET /status.json HTTP/1.1\r\nHost: a\r\n\r\n")
                (line, headers, body), = _answers(s, "G")
                assert line == "HTTP/1.1 200 OK" and headers["Connection"] == "close" and s.recv(1) == b""
        assert json.loads(body)["server"]["refused"] == 0
    finally:
        server.close()


def test_a_client_asking_without_pause_is_answered_within_the_cpu_share():
    """Status asked for back to back on two connections: every answer comes (200), the answers
    beyond the budget wait their turn, and the answering threads' CPU stays within the bucket
    plus the share of the wall time (plus what the two answers in flight may take)."""
    from photomap.live.cpubudget import BURST_S

    share = 0.01
    cfg = load_config().updated({"map_server": {"cpu_share": share}})
    server = MapServer(cfg.map_server, "127.0.0.1", 0)
    start = time.monotonic()
    codes: list[int] = []

    def ask() -> None:
        conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
        while server.budget.waits < 3 and time.monotonic() - start < 60 and len(codes) < 20000:
            conn.request("GET", "/status.json")
            answer = conn.getresponse()
            answer.read()
            codes.append(answer.status)
        conn.close()

    try:
        askers = [threading.Thread(target=ask) for _ in range(2)]
        for t in askers:
            t.start()
        for t in askers:
            t.join(90)
        elapsed = time.monotonic() - start
        assert server.budget.waits >= 3, (len(codes), server.budget.spent_s)
        assert set(codes) == {200}
        assert server.budget.spent_s <= share * (BURST_S + elapsed) + 0.01, (server.budget.spent_s, elapsed)
        assert _status(f"http://127.0.0.1:{server.port}/")["server"]["budget_waits"] >= 3
    finally:
        server.close()


def test_answers_wait_while_the_worker_maps_a_frame():
    """Live, the server's Python code gives way to the worker's frame (its gate), then answers."""
    from photomap.mapping.threads import WorkerFirst

    server = MapServer(load_config().map_server, "127.0.0.1", 0)
    server.gate = WorkerFirst(enabled=True, max_wait_s=60.0)
    got: dict = {}
    try:
        with server.gate.frame():  # the worker is mapping a frame
            asker = threading.Thread(target=lambda: got.update(st=_status(f"http://127.0.0.1:{server.port}/")))
            asker.start()
            asker.join(timeout=1.0)
            assert asker.is_alive() and "st" not in got  # waiting at the gate, not answered
        asker.join(timeout=30.0)  # the frame is done: answered
        assert got["st"]["frames_in"] == 0
    finally:
        server.close()


def test_tiles_the_flight_left_are_packed_and_still_served():
    """Beyond max_raw_tiles the oldest copies are packed (a fraction of the bytes); what is
    served from them is the same picture (JPEG quality), the alpha exactly."""
    from photomap.config import MosaicConfig
    from photomap.core.mosaic import TiledMosaic
    from photomap.live.livemap import LiveMap, render_png

    terrain = cv2.GaussianBlur(load_terrain("aukerman"), (0, 0), 1.0)[:256, :256]  # real imagery
    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    alpha = np.full((64, 64), 255, np.uint8)
    alpha[40:, 50:] = 0  # a map edge
    keys = [(tx, ty) for ty in range(4) for tx in range(4)]
    for tx, ty in keys:
        mosaic.set_tile((tx, ty), terrain[64 * ty:64 * ty + 64, 64 * tx:64 * tx + 64], alpha)
    live = LiveMap(tile_hz=1e6)
    live.on_frame(_tile_event(0, mosaic, set(keys)))
    before = _decode(render_png(live.snapshot(), "pixel", 0, 0, 8))
    low_before = _decode(render_png(live.snapshot(), "pixel", 0, 0, 6))  # from the tiles' quarter halvings
    raw_bytes = live.nbytes()
    assert live.pack(max_raw=4) == 12 and live.pack(max_raw=4) == 0
    assert live.nbytes() < 0.4 * raw_bytes
    after = _decode(render_png(live.snapshot(), "pixel", 0, 0, 8))
    assert (after[..., 3] == before[..., 3]).all()
    covered = before[..., 3] > 0
    assert np.abs(after[..., :3].astype(int) - before[..., :3].astype(int))[covered].mean() < 3
    # lower zooms come from the halvings kept as pixels: exactly as before
    assert (_decode(render_png(live.snapshot(), "pixel", 0, 0, 6)) == low_before).all()


def test_hazards_found_during_a_replay_are_served_where_they_were_planted(tmp_path):
    """The hazard tracker's spots reach /hazards.geojson while the flight is mapped, at the WGS84
    positions the simulator planted them (hotspots.csv), each once."""
    import csv
    flight = simulate_flight(tmp_path / "hot", n_frames=120, size=(W, H), fps=20.0, seed=3, hotspots=3)
    planted = [(float(r["lat"]), float(r["lon"])) for r in csv.DictReader(open(flight / "hotspots.csv"))]
    port = _free_port()
    base = f"http://127.0.0.1:{port}/"
    cfg = load_config().updated({"hazards": {"enabled": True}})
    result: dict = {}

    def run() -> None:
        result["summary"] = replay(str(flight / "video.mp4"), tmp_path / "run", cfg, realtime=True,
                                   mavlink=str(flight / "telemetry.tlog"), map_server=str(port))

    worker = threading.Thread(target=run)
    worker.start()
    try:
        def served():
            if not _status(base):
                return None
            got = json.loads(_get(base + "hazards.geojson")[1])
            if got["frame"] != "wgs84":  # map pixels before the georeference
                return None
            placed = [f for f in got["features"] if f["geometry"] is not None]
            return placed if len(placed) >= len(planted) else None
        features = wait_until(served, 60.0, 0.2)
    finally:
        worker.join(timeout=120)
    assert not worker.is_alive() and result["summary"]["registered"] == 120
    assert features is not None, "the planted spots never reached /hazards.geojson"
    assert len(features) == len(planted) and len({f["properties"]["id"] for f in features}) == len(planted)
    for lon, lat in (f["geometry"]["coordinates"] for f in features):
        err = min(np.hypot((lat - la) * 111_320.0, (lon - lo) * 111_320.0 * np.cos(np.radians(la)))
                  for la, lo in planted)
        assert err < 2.0, f"a served hazard {err:.1f} m from the nearest planted spot"


def test_the_served_track_after_a_correction_is_the_track_of_its_points_appended():
    """The live map's track (frame centres, thinned to max_path points): after a pose-graph
    correction it is the corrected path thinned as if it had come point by point, and frames
    after it go on from there."""
    from photomap.geometry import frame_centre
    from photomap.live.livemap import LiveMap, track_geojson
    from photomap.mapping.events import FrameEvent

    cx, cy = frame_centre(64, 64)

    def event(k: int, tx: float, ty: float, corrected: np.ndarray | None = None) -> FrameEvent:
        pose = np.array([[1.0, 0, tx], [0, 1.0, ty]])
        return FrameEvent(k, k / 10.0, False, np.zeros((64, 64, 3), np.uint8), (64, 64), "registered", pose,
                          0.9, 0, path_after_correction=None if corrected is None else (lambda: corrected))

    live = LiveMap(tile_hz=1e6, max_path=8)
    for k in range(30):
        live.on_frame(event(k, 10.0 * k, 20.0 * k))
    assert live.snapshot().path == [(10.0 * k + cx, 20.0 * k + cy) for k in range(0, 30, 4)]
    # frame 30 closes a loop: every centre moved by (+1, -1)
    corrected = np.array([[10.0 * k + cx + 1, 20.0 * k + cy - 1, 0.9] for k in range(31)])
    live.on_frame(event(30, 300.0 + 1, 600.0 - 1, corrected))
    for k in range(31, 45):
        live.on_frame(event(k, 10.0 * k + 1, 20.0 * k - 1))
    truth = [(10.0 * k + cx + 1, 20.0 * k + cy - 1) for k in range(45)]
    # 45 centres, at most 8 kept: every 8th, as appends alone keep them
    assert live.snapshot().path == truth[::8] and live.errors == 0
    line = track_geojson(live.snapshot())["features"][0]
    assert line["geometry"]["coordinates"] == [list(p) for p in truth[::8]] and line["properties"]["points"] == 6


def test_a_refit_moving_the_served_map_less_than_half_a_pixel_keeps_the_served_tiles():
    """A new GPS fit that moves no corner of the served map by half a map pixel keeps the
    georeference served (its tiles stay cached: a ground station fetches nothing again); one that
    moves a corner of the map as it has grown since, drifts on past half a pixel against the
    served one, or is of another segment is taken."""
    from photomap.config import MosaicConfig
    from photomap.core.mosaic import TiledMosaic
    from photomap.geo.georef import Georeference
    from photomap.live.livemap import LiveMap, TileCache

    def geo(east: float, turn_deg: float = 0.0) -> Georeference:
        a = math.radians(turn_deg)
        m = 0.5 * np.array([[math.cos(a), -math.sin(a)], [-math.sin(a), -math.cos(a)]])  # 0.5 m a pixel
        return Georeference(41.1, -81.7, np.c_[m, [0.0, 0.0]], 32617, np.c_[m, [440_000.0 + east, 4_550_000.0]],
                            0.5, turn_deg, "gps", 0.5, 10, 10)

    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    grey = np.full((64, 64, 3), 120, np.uint8)
    full = np.full((64, 64), 255, np.uint8)
    for key in [(0, 0), (1, 0), (2, 1)]:
        mosaic.set_tile(key, grey, full)
    live = LiveMap(tile_hz=1e6)
    live.on_frame(_tile_event(0, mosaic, {(0, 0), (1, 0), (2, 1)}))
    cache = TileCache(64, 0.0)
    live.on_georeference(0, served := geo(0.0))
    snap = live.snapshot()
    version, z = snap.geo_version, snap.max_zoom()
    lon, lat = snap.to_lonlat(np.array([[96.0, 64.0]]))[0]
    x, y = wm.tile_of(lat, lon, z)
    cache.get(snap, "xyz", x, y, z)
    # 0.1 m east (0.2 px), then a turn moving the far corner (192, 128) by 0.4 px: kept
    for refit in (geo(0.1), geo(0.0, math.degrees(0.4 * 0.5 / 0.5 / math.hypot(192, 128)))):
        live.on_georeference(0, refit)
        snap = live.snapshot()
        assert snap.geo_version == version and snap.georeference[1] is served
    cache.get(snap, "xyz", x, y, z)
    assert cache.renders == 1 and cache.hits == 1
    live.on_georeference(0, geo(0.3))  # 0.6 px against the served fit: taken
    assert live.snapshot().geo_version == version + 1
    version = live.snapshot().geo_version
    live.on_georeference(0, geo(0.3 + 0.2))  # 0.4 px more: kept
    assert live.snapshot().geo_version == version
    # a turn moving (41 * 64, 31 * 64) by a pixel moves the map's far corner by 0.07 px: kept ...
    turned = geo(0.3, math.degrees(1.0 / math.hypot(41 * 64, 31 * 64)))
    live.on_georeference(0, turned)
    assert live.snapshot().geo_version == version
    # ... until the map has grown to there
    mosaic.set_tile((40, 30), grey, full)
    live.on_frame(_tile_event(1, mosaic, {(40, 30)}))
    live.on_georeference(0, turned)
    assert live.snapshot().geo_version == version + 1 and live.snapshot().georeference[1] is turned
    live.on_georeference(1, live.snapshot().georeference[1])  # another segment: taken
    assert live.snapshot().georeference[0] == 1


def _georeferenced_snapshot():
    """A live map of 8 x 8 mapped 64 px tiles of blurred noise, georeferenced at 5 cm a pixel and
    turned 25 degrees: its snapshot and the lon, lat of the map pixel (256, 256)."""
    from photomap.config import MosaicConfig
    from photomap.core.mosaic import TiledMosaic
    from photomap.geo.georef import Georeference, utm_forward
    from photomap.live.livemap import LiveMap

    a = math.radians(25.0)
    m = 0.05 * np.array([[math.cos(a), -math.sin(a)], [-math.sin(a), -math.cos(a)]])  # 5 cm a pixel, turned
    east, north = (float(v[0]) for v in utm_forward(np.array([41.1]), np.array([-81.7]), 32617))
    geo = Georeference(41.1, -81.7, np.c_[m, [0.0, 0.0]], 32617, np.c_[m, [east, north]],
                       0.05, 25.0, "gps", 0.5, 10, 10)
    mosaic = TiledMosaic(MosaicConfig(tile_size=64))
    rng = np.random.default_rng(3)
    image = cv2.GaussianBlur(rng.integers(0, 256, (512, 512, 3), dtype=np.uint8), (5, 5), 0)
    full = np.full((64, 64), 255, np.uint8)
    keys = {(kx, ky) for kx in range(8) for ky in range(8)}
    for kx, ky in keys:
        mosaic.set_tile((kx, ky), image[64 * ky:64 * ky + 64, 64 * kx:64 * kx + 64], full)
    live = LiveMap(tile_hz=1e6)
    live.on_frame(_tile_event(0, mosaic, keys))
    live.on_georeference(0, geo)
    snap = live.snapshot()
    return snap, snap.to_lonlat(np.array([[256.0, 256.0]]))[0]


def test_web_tiles_at_the_maps_zooms_are_warped_as_affine_and_equal_the_exact_sampling(monkeypatch):
    """Across a tile at the map's own zooms web mercator and UTM are affine to far below a pixel,
    so the tile is one affine warp of the map; it equals the per-pixel sampling (to 1 level where
    the map covers the tile). A tile of hundreds of kilometres is not affine and is sampled per
    pixel."""
    from photomap.io.xyz_tiles import tile_source_grid
    from photomap.live import livemap

    snap, (lon, lat) = _georeferenced_snapshot()
    geo = snap.georeference[1]
    z = snap.max_zoom()

    def grid(zoom: int) -> tuple[np.ndarray, np.ndarray]:
        return tile_source_grid(geo.map_to_crs, geo.epsg, *wm.tile_of(lat, lon, zoom), zoom)[:2]

    assert livemap._grid_affine(*grid(z)) is not None and livemap._grid_affine(*grid(3)) is None
    x, y = wm.tile_of(lat, lon, z)
    warped, _ = livemap._xyz_tile(snap, x, y, z)
    monkeypatch.setattr(livemap, "_grid_affine", lambda gx, gy: None)
    sampled, _ = livemap._xyz_tile(snap, x, y, z)
    both = (warped[..., 3] == 255) & (sampled[..., 3] == 255)
    assert both.mean() > 0.9 and (warped[..., 3] != sampled[..., 3]).mean() < 0.01
    assert np.abs(warped.astype(int) - sampled)[both].max() <= 1


def test_web_tiles_of_a_fully_mapped_region_skip_the_premultiplication_exactly(monkeypatch):
    """Where every source pixel of a tile is mapped, the alpha is neither multiplied in nor
    divided out (the region is its own premultiplied form); a tile over the map's edge has it
    divided out of its part-covered pixels. Both equal the rendering with the two steps."""
    from photomap.live import livemap

    snap, (lon, lat) = _georeferenced_snapshot()
    z = snap.max_zoom()
    x0, y0, _, _ = snap.bounds_px()
    lon0, lat0 = snap.to_lonlat(np.array([[x0 + 2.0, y0 + 2.0]]))[0]
    calls = []
    for name in ("multiply", "divide"):
        def counted(*args, _real=getattr(cv2, name), _name=name, **kwargs):
            calls.append(_name)
            return _real(*args, **kwargs)
        monkeypatch.setattr(livemap.cv2, name, counted)
    places = {"inside": (lat, lon), "edge": (lat0, lon0)}
    tiles, opaque, steps = {}, {}, {}
    for where, (lt, ln) in places.items():
        calls.clear()
        tiles[where], opaque[where] = livemap._xyz_tile(snap, *wm.tile_of(lt, ln, z), z)
        steps[where] = list(calls)
    assert tiles["inside"][..., 3].min() == 255 and steps["inside"] == [] and opaque["inside"]
    assert 0 < tiles["edge"][..., 3].mean() < 255 and steps["edge"] == ["divide"] and not opaque["edge"]
    monkeypatch.setattr(livemap, "_alpha_range", lambda bgra: (0, 255))  # as if part covered: both steps
    for where, (lt, ln) in places.items():
        assert np.array_equal(livemap._xyz_tile(snap, *wm.tile_of(lt, ln, z), z)[0], tiles[where])


def test_hazards_are_served_on_the_map_the_page_shows_with_or_without_a_georeference():
    """A spot of the served segment is drawn at its map pixel: in map pixels before a georeference
    (the page's pixel frame), through the map's georeference after it (on the tiles), whatever
    the tracker's own telemetry estimate; a spot of another segment only with its own WGS84."""
    from photomap.geo.georef import Georeference
    from photomap.live.livemap import LiveMap, hazards_geojson
    from photomap.mapping.events import FrameEvent

    def spot(hid: int, segment: int, x: float, y: float, lonlat=None) -> dict:
        geometry = None if lonlat is None else {"type": "Point", "coordinates": list(lonlat)}
        return {"type": "Feature", "geometry": geometry,
                "properties": {"id": hid, "segment": segment, "x_px": x, "y_px": y}}

    live = LiveMap(tile_hz=1e6)
    live.on_frame(FrameEvent(0, 0.0, False, np.zeros((64, 64, 3), np.uint8), (64, 64), "registered",
                             np.array([[1.0, 0, 5.0], [0, 1.0, 7.0]]), 0.9, 0))
    spots = {"type": "FeatureCollection",
             "features": [spot(1, 0, 40.0, 30.0), spot(2, 0, 10.0, 12.0, (-81.0, 41.0)), spot(3, 1, 9.0, 9.0),
                          spot(4, 1, 8.0, 8.0, (-81.5, 41.5))]}
    pixels = hazards_geojson(spots, live.snapshot())
    assert pixels["frame"] == "map_pixels"
    assert [(f["properties"]["id"], f["geometry"]["coordinates"]) for f in pixels["features"]] == \
        [(1, [40.0, 30.0]), (2, [10.0, 12.0])]
    to_enu = np.array([[0.5, 0.0, 0.0], [0.0, -0.5, 0.0]])  # 0.5 m per pixel, north up
    georef = Georeference(41.1, -81.7, to_enu, 32617, np.array([[0.5, 0.0, 440_000.0], [0.0, -0.5, 4_550_000.0]]),
                          0.5, 0.0, "gps", 0.5, 10, 10)
    live.on_georeference(0, georef)
    geo = hazards_geojson(spots, live.snapshot())
    assert geo["frame"] == "wgs84"
    by_id = {f["properties"]["id"]: f["geometry"]["coordinates"] for f in geo["features"]}
    assert sorted(by_id) == [1, 2, 4] and by_id[4] == [-81.5, 41.5]
    lat, lon = georef.to_latlon(np.array([[40.0, 30.0]]))
    assert by_id[1] == pytest.approx([float(lon[0]), float(lat[0])])
