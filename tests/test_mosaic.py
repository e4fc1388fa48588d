"""The tiled photo map against exact synthetic truth, and the tile stores."""

from __future__ import annotations

import math
import threading

import cv2
import numpy as np
import pytest

from photomap.config import MosaicConfig, load_config
from photomap.errors import ConfigError, InputError
from photomap.core.mosaic import TiledMosaic
from photomap.io.tilestore import DiskTileStore, MemoryTileStore, WriteBehindTileStore


def noise(h: int, w: int, channels: int = 3, seed: int = 0) -> np.ndarray:
    """Uniform random uint8 image: every pixel differs, so any misplacement shows."""
    return np.random.default_rng(seed).integers(0, 256, (h, w, channels), np.uint8)


def smooth_texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """Smooth random BGR texture in 20..235 (no clipping under a brightness change)."""
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.normal(0, 1, (h, w, 3)).astype(np.float32), (0, 0), 4)
    t = (t - t.min()) / (t.max() - t.min())
    return np.rint(20 + 215 * t).astype(np.uint8)


def shift(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]])


# ---------------------------------------------------------------- exact placement
@pytest.mark.parametrize("blend", ["overwrite", "feather"])
def test_identity_reproduces_frame_pixels(blend):
    frame = noise(100, 150)
    m = TiledMosaic(MosaicConfig(tile_size=64, blend=blend))
    touched = m.add(frame, shift(0, 0))
    assert touched == {(tx, ty) for tx in range(3) for ty in range(2)}
    assert m.bounds() == (1, 1, 148, 98)  # the 1 px border stays out
    image, alpha, origin = m.render()
    assert origin == (1, 1)
    np.testing.assert_array_equal(image, frame[1:-1, 1:-1])
    assert (alpha == 255).all()


@pytest.mark.parametrize("blend", ["overwrite", "feather"])
def test_integer_translation_across_tiles(blend):
    frame = noise(90, 120, seed=1)
    m = TiledMosaic(MosaicConfig(tile_size=32, blend=blend))
    m.add(frame, shift(70, 45))
    image, alpha, origin = m.render(bounds=(71, 46, 118, 88))
    assert origin == (71, 46)
    np.testing.assert_array_equal(image, frame[1:-1, 1:-1])
    assert (alpha == 255).all()
    # nothing outside the footprint is covered
    _, alpha_all, origin_all = m.render(bounds=(0, 0, 256, 256))
    assert alpha_all.sum() == 255 * 118 * 88


def test_rotation_90_deg_reproduces_rotated_frame():
    frame = noise(60, 80, seed=2)
    a = math.radians(90)  # cos(a) is 6e-17, not 0: the placement must still be exact
    M = np.array([[math.cos(a), -math.sin(a), 200.0], [math.sin(a), math.cos(a), 10.0]])
    m = TiledMosaic(MosaicConfig(tile_size=64))
    m.add(frame, M)
    # frame (u, v) -> map (200 - v, 10 + u): the frame turned clockwise on screen
    image, alpha, origin = m.render()
    assert origin == (200 - 58, 11)
    np.testing.assert_array_equal(image, np.rot90(frame, k=-1)[1:-1, 1:-1])
    assert (alpha == 255).all()


def test_negative_coordinates_make_negative_tile_keys():
    frame = noise(50, 70, seed=3)
    m = TiledMosaic(MosaicConfig(tile_size=64))
    touched = m.add(frame, shift(-100, -40))
    # covered map pixels x in [-99, -32), y in [-39, 9)
    assert touched == {(-2, -1), (-1, -1), (-2, 0), (-1, 0)}
    assert m.bounds() == (-99, -39, 68, 48)
    image, alpha, origin = m.render()
    assert origin == (-99, -39)
    np.testing.assert_array_equal(image, frame[1:-1, 1:-1])
    assert m.tile_origin((-2, -1)) == (-128, -64)
    tile, tile_alpha = m.tile_image((-2, -1))
    # map pixel (-99, -39) is tile (-2, -1) row 25, column 29
    np.testing.assert_array_equal(tile[25:64, 29:], frame[1:40, 1:36])
    assert tile_alpha[25:, 29:].all() and not tile_alpha[:25].any() and not tile_alpha[:, :29].any()


def test_uncovered_pixels_are_empty_not_black():
    m = TiledMosaic(MosaicConfig(tile_size=32))
    m.add(np.zeros((20, 20, 3), np.uint8), shift(0, 0))  # a black frame
    m.add(np.full((20, 20, 3), 9, np.uint8), shift(40, 0))
    image, alpha, origin = m.render()
    assert origin == (1, 1) and alpha.shape == (18, 58)
    assert (alpha[:, :18] == 255).all() and (alpha[:, 18:40] == 0).all()  # black frame vs gap
    assert (image[:, 40:] == 9).all() and (alpha[:, 40:] == 255).all()


def test_gray_frames_into_gray_and_colour_maps():
    gray = noise(40, 40, channels=1, seed=4)[..., 0]
    g = TiledMosaic(MosaicConfig(tile_size=32, channels=1))
    g.add(gray, shift(0, 0))
    image, _, _ = g.render()
    assert image.shape == (38, 38)
    np.testing.assert_array_equal(image, gray[1:-1, 1:-1])
    c = TiledMosaic(MosaicConfig(tile_size=32))
    c.add(gray, shift(0, 0))
    image, _, _ = c.render()
    assert image.shape == (38, 38, 3)
    np.testing.assert_array_equal(image, np.repeat(gray[1:-1, 1:-1, None], 3, axis=2))


def test_mask_keeps_invalid_pixels_out():
    frame = noise(40, 40, seed=5)
    mask = np.ones((40, 40), bool)
    mask[:, 20:] = False
    m = TiledMosaic(MosaicConfig(tile_size=32))
    m.add(frame, shift(0, 0), mask=mask)
    assert m.bounds() == (1, 1, 18, 38)  # eroded by 1 px on every side of the valid part


# ---------------------------------------------------------------- blending
def test_overwrite_puts_newest_on_top():
    dark, bright = np.full((40, 60, 3), 50, np.uint8), np.full((40, 60, 3), 200, np.uint8)
    m = TiledMosaic(MosaicConfig(tile_size=32, blend="overwrite"))
    m.add(dark, shift(0, 0))
    m.add(bright, shift(30, 0))
    image, _, _ = m.render(bounds=(10, 10, 70, 1))
    assert (image[0, :21] == 50).all() and (image[0, 21:] == 200).all()  # bright from x=31
    m.add(dark, shift(0, 0))
    image, _, _ = m.render(bounds=(10, 10, 70, 1))
    assert (image[0, :49] == 50).all() and (image[0, 49:] == 200).all()  # dark up to x=58


@pytest.mark.parametrize("blend", ["overwrite", "feather"])
def test_dark_frame_edge_stays_out_at_subpixel_pose(blend):
    """A frame whose outermost pixel ring is black (as in real video) at a sub-pixel pose:
    the black ring neither shows nor darkens the interpolated map pixels next to it."""
    frame = np.full((40, 50, 3), 200, np.uint8)
    frame[0, :] = frame[-1, :] = frame[:, 0] = frame[:, -1] = 0
    m = TiledMosaic(MosaicConfig(tile_size=32, blend=blend))
    m.add(frame, shift(10.5, 20.25))
    image, alpha, _ = m.render()
    assert (image[alpha == 255] == 200).all()
    assert (alpha == 255).sum() >= 46 * 36  # all but the eroded ring and one interpolated pixel


def test_feather_reproduces_texture_from_two_frames():
    tex = smooth_texture(200, 300)
    a, b = tex[0:160, 0:200], tex[30:200, 110:300]  # offsets (0, 0) and (110, 30)
    m = TiledMosaic(MosaicConfig(tile_size=64, blend="feather"))
    m.add(a, shift(0, 0))
    m.add(b, shift(110, 30))
    image, alpha, (x, y) = m.render(bounds=(1, 1, 298, 198))
    covered = alpha == 255
    # a covers map x 1..198, y 1..158; b covers x 111..298, y 31..198
    assert covered.sum() == 298 * 198 - 100 * 30 - 110 * 40  # the two corners no frame covers
    diff = np.abs(image.astype(int) - tex[1:199, 1:299])
    assert diff[covered].max() <= 1


def _residual_jumps(image: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Largest change of (render - truth) between horizontal neighbours, per pixel pair."""
    r = image.astype(float).mean(axis=2) - truth.astype(float).mean(axis=2)
    return np.abs(np.diff(r, axis=1))


def test_feather_has_no_seam_where_overwrite_has_one():
    """Second frame 24 levels brighter: overwrite shows a step at its border, feather none."""
    tex = smooth_texture(120, 300, seed=1)
    a = tex[:, 0:180]
    b = np.clip(tex[:, 100:300].astype(int) + 24, 0, 255).astype(np.uint8)
    rect = (1, 1, 298, 118)  # every row, also those beside the frames' common top/bottom border
    truth = tex[1:119, 1:299]
    jumps = {}
    for blend in ("overwrite", "feather"):
        m = TiledMosaic(MosaicConfig(tile_size=64, blend=blend))
        m.add(a, shift(0, 0))
        m.add(b, shift(100, 0))
        image, alpha, _ = m.render(bounds=rect)
        assert (alpha == 255).all()
        jumps[blend] = _residual_jumps(image, truth)
    # overwrite: a 24-level step where frame b begins (map x=101, between columns 99 and 100)
    assert jumps["overwrite"][:, 99].min() >= 23
    # feather: the residual ramps across the overlap (map x 101..178, ~0.3 levels/px), in every
    # row: no jump beyond the 1-level rounding of the ramp, not even beside the frames' borders
    f = jumps["feather"]
    assert f.max() <= 1 + 1e-9
    r = image.astype(float).mean(axis=2) - truth.astype(float).mean(axis=2)
    assert abs(r[:, :95]).max() <= 0.5 and abs(r[:, 185:] - 24).max() <= 0.5


# ---------------------------------------------------------------- memory cap and tile stores
def _flight(m: TiledMosaic, frame: np.ndarray, n: int = 24) -> list[set]:
    """Out along a line, then back over the start (tiles must come back from the store)."""
    xs = [17.5 * i for i in range(n)] + [17.5 * (n - i) + 3.25 for i in range(n)]
    return [m.add(frame, np.array([[1.0, 0.0, x], [0.0, 1.0, 0.5 * x - 0.25]])) for x in xs]


class CheckingStore(MemoryTileStore):
    """Fails if the mosaic holds more tiles than its cap whenever it talks to the store."""

    def __init__(self, mosaic_ref: list, cap: int) -> None:
        super().__init__()
        self.ref, self.cap, self.puts, self.gets = mosaic_ref, cap, 0, 0

    def put(self, key, arrays):
        assert self.ref[0].tiles_in_memory <= self.cap
        self.puts += 1
        super().put(key, arrays)

    def get(self, key):
        assert self.ref[0].tiles_in_memory <= self.cap
        self.gets += 1
        return super().get(key)


@pytest.mark.parametrize("blend", ["overwrite", "feather"])
def test_cap_bounds_tiles_in_memory_and_render_is_unchanged(blend):
    frame = smooth_texture(60, 80, seed=2)
    free = TiledMosaic(MosaicConfig(tile_size=32, blend=blend))
    _flight(free, frame)
    ref: list = []
    store = CheckingStore(ref, cap=3)
    capped = TiledMosaic(MosaicConfig(tile_size=32, blend=blend, max_tiles_in_memory=3), store=store)
    ref.append(capped)
    for touched in _flight(capped, frame):
        assert capped.tiles_in_memory <= 3
    assert store.puts > 0 and store.gets > 0
    assert capped.tiles() == free.tiles() and len(free.tiles()) > 20
    assert capped.bounds() == free.bounds()
    for got, want in zip(capped.render(), free.render()):
        np.testing.assert_array_equal(got, want)
    assert capped.tiles_in_memory <= 3  # rendering does not pull tiles into memory


def test_spill_to_disk_is_lossless(tmp_path):
    frame = smooth_texture(60, 80, seed=3)
    free = TiledMosaic(MosaicConfig(tile_size=32, blend="feather"))
    _flight(free, frame)
    store = DiskTileStore(tmp_path / "cache")
    capped = TiledMosaic(MosaicConfig(tile_size=32, blend="feather", max_tiles_in_memory=4), store=store)
    _flight(capped, frame)
    files = sorted(p.name for p in (tmp_path / "cache").iterdir())
    assert files and all(n.startswith("tile_") and n.endswith(".npz") for n in files)  # no temp left
    # tiles on disk are bit-identical to the tiles of the uncapped map
    key = next(k for k in store.keys() if k not in capped._tiles)
    arrays = store.get(key)
    np.testing.assert_array_equal(arrays["sum"], free._tiles[key]["sum"])
    np.testing.assert_array_equal(arrays["weight"], free._tiles[key]["weight"])
    for got, want in zip(capped.render(), free.render()):
        np.testing.assert_array_equal(got, want)
    for got, want in zip(capped.render(scale=0.5), free.render(scale=0.5)):
        np.testing.assert_array_equal(got, want)


def test_a_downscaled_render_reads_a_spilled_map_one_tile_row_at_a_time(tmp_path):
    """area_sums (mosaic.png, render(scale < 1), the report) holds about one tile row of a map
    spilled to disk, never the whole map: the tiles read from the store and still alive, counted
    while the rows are produced, stay within a row's worth."""
    import weakref

    store = DiskTileStore(tmp_path / "cache")
    mosaic = TiledMosaic(MosaicConfig(tile_size=16, max_tiles_in_memory=2), store=store)
    mosaic.add(smooth_texture(160, 160, seed=4), np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
    assert len(mosaic.tiles()) >= 100 and mosaic.tiles_in_memory <= 2
    alive, peak, real_get = set(), [0], store.get

    def counting_get(key):
        arrays = real_get(key)
        if arrays:
            first = next(iter(arrays.values()))
            alive.add(id(first))
            weakref.finalize(first, alive.discard, id(first))
            peak[0] = max(peak[0], len(alive))
        return arrays

    store.get = counting_get
    rows = sum(len(block) for block in mosaic.area_sums(mosaic.bounds(), (80, 80)))
    assert rows == 80 and 0 < peak[0] <= 12, peak


def test_disk_tile_store_round_trip(tmp_path):
    store = DiskTileStore(tmp_path)
    arrays = {"color": noise(8, 8, seed=4), "cover": np.full((8, 8), 255, np.uint8)}
    store.put((-3, 7), arrays)
    store.put((2, -1), {"sum": np.linspace(0, 1, 64, dtype=np.float32).reshape(8, 8)})
    assert sorted(store.keys()) == [(-3, 7), (2, -1)]
    back = store.get((-3, 7))
    assert set(back) == {"color", "cover"}
    for name in arrays:
        assert back[name].dtype == arrays[name].dtype
        np.testing.assert_array_equal(back[name], arrays[name])
    assert store.get((0, 0)) is None
    store.discard((-3, 7))
    assert store.keys() == [(2, -1)]
    with DiskTileStore() as temporary:
        folder = temporary.folder
        temporary.put((0, 0), arrays)
    assert not folder.exists()


@pytest.mark.parametrize("store_kind", ["disk", "memory"])
def test_tile_image_later_lends_tiles_in_memory_and_reads_spilled_ones_later(tmp_path, store_kind):
    """What a checkpoint or a preview takes from the worker: a tile in memory as it is now; a
    spilled tile as the store has it when read (another thread, later); None once it is gone.
    A tile in memory is lent: the map copies it before it changes it."""
    store = DiskTileStore(tmp_path) if store_kind == "disk" else MemoryTileStore()
    m = TiledMosaic(MosaicConfig(tile_size=32, max_tiles_in_memory=2), store=store)
    m.add(noise(40, 40, seed=1), shift(0, 0))
    m.add(noise(40, 40, seed=2), shift(100, 0))
    in_memory = next(k for k in m.tiles() if k in m._tiles)
    spilled = next(k for k in m.tiles() if k not in m._tiles)
    now = {k: m.tile_image(k) for k in (in_memory, spilled)}
    later = {k: m.tile_image_later(k) for k in (in_memory, spilled)}
    with pytest.raises(KeyError):
        m.tile_image_later((50, 50))
    for k in (in_memory, spilled):  # unchanged map: the same pixels
        for got, want in zip(later[k](), now[k]):
            np.testing.assert_array_equal(got, want)
    m.add(noise(200, 200, seed=3), shift(-20, -20))  # paints over both (and spills again)
    for got, want in zip(later[in_memory](), now[in_memory]):
        np.testing.assert_array_equal(got, want)  # as it was when asked
    assert spilled not in m._tiles
    for got, want in zip(later[spilled](), m.tile_image(spilled)):
        np.testing.assert_array_equal(got, want)  # read when called: the newer pixels
    assert not np.array_equal(m.tile_image(spilled)[0], now[spilled][0])
    m.clear_tiles([spilled])
    assert later[spilled]() is None
    # copy on write: a tile lent out and then replaced keeps the lent pixels for the reader
    key = next(k for k in m.tiles() if k in m._tiles)
    lent, before = m.tile_image_later(key), m.tile_image(key)
    m.set_tile(key, np.zeros_like(before[0]), np.full_like(before[1], 255))
    for got, want in zip(lent(), before):
        np.testing.assert_array_equal(got, want)
    assert not m.tile_image(key)[0].any() and m.tile_image(key)[1].all()


def test_clear_tiles_then_re_render(tmp_path):
    frame = noise(40, 40, seed=6)
    m = TiledMosaic(MosaicConfig(tile_size=32, max_tiles_in_memory=1), store=DiskTileStore(tmp_path))
    m.add(frame, shift(0, 0))
    m.add(frame, shift(100, 0))
    assert m.bounds() == (1, 1, 138, 38)
    right = [k for k in m.tiles() if k[0] >= 3]
    m.clear_tiles(right)
    assert m.bounds() == (1, 1, 38, 38)
    assert all(k[0] < 3 for k in m.tiles())
    # re-rendered with another frame: the cleared (spilled) data must not come back
    other = noise(40, 40, seed=7)
    m.add(other, shift(100, 0))
    image, _, _ = m.render(bounds=(101, 1, 38, 38))
    np.testing.assert_array_equal(image, other[1:-1, 1:-1])
    m.reset()
    assert m.tiles() == [] and m.bounds() is None
    image, alpha, origin = m.render()
    assert image.size == 0 and alpha.size == 0


# ---------------------------------------------------------------- clipped painting, tile swaps
@pytest.mark.parametrize("blend", ["overwrite", "feather"])
def test_clipped_add_changes_only_the_rectangles_and_matches_the_full_add(blend):
    base, frame = smooth_texture(80, 100, seed=8), noise(90, 130, seed=9)
    a = math.radians(27)
    M = np.array([[0.9 * math.cos(a), -0.9 * math.sin(a), 80.3], [0.9 * math.sin(a), 0.9 * math.cos(a), 20.6]])
    clip = [(60, 30, 40, 25), (100, 90, 70, 33), (-50, -50, 20, 20)]  # the last one misses the frame
    full, part = (TiledMosaic(MosaicConfig(tile_size=32, blend=blend)) for _ in range(2))
    for m in (full, part):
        m.add(base, shift(30, 10))
    before = part.render(bounds=(0, 0, 260, 200))
    full.add(frame, M)
    touched = part.add(frame, M, clip=clip)
    after, want = part.render(bounds=(0, 0, 260, 200)), full.render(bounds=(0, 0, 260, 200))
    inside = np.zeros((200, 260), bool)
    for x, y, w, h in clip:
        inside[max(y, 0):max(y + h, 0), max(x, 0):max(x + w, 0)] = True
    for got, ref, old in zip(after[:2], want[:2], before[:2]):
        assert np.abs(got[inside].astype(int) - ref[inside]).max() <= 1  # warp rounding
        np.testing.assert_array_equal(got[~inside], old[~inside])
    assert (after[1][inside] != before[1][inside]).any()  # the frame did add ground there
    assert touched <= set(full.tiles()) and touched == {(x // 32, y // 32) for y, x in zip(*np.nonzero(
        inside & ((after[0] != before[0]).any(axis=2) | (after[1] != before[1]))))}


def test_put_tiles_swaps_in_a_map_rendered_aside(tmp_path):
    frame, other = noise(70, 90, seed=10), noise(70, 90, seed=11)
    live = TiledMosaic(MosaicConfig(tile_size=32, max_tiles_in_memory=2), store=DiskTileStore(tmp_path))
    live.add(frame, shift(0, 0))
    live.add(frame, shift(150, 5))
    aside = TiledMosaic(MosaicConfig(tile_size=32))
    aside.add(other, shift(3.5, 2.25))
    right = [k for k in live.tiles() if k[0] >= 4]
    keys_left = [k for k in live.tiles() if k[0] < 4]
    tiles = aside.take_tiles()
    assert aside.tiles() == [] and aside.bounds() is None
    assert set(tiles) == {k for k in tiles if k[0] < 4}
    live.put_tiles({**tiles, **{k: None for k in keys_left if k not in tiles}})
    assert live.tiles_in_memory <= 2
    want = TiledMosaic(MosaicConfig(tile_size=32))  # what the swap must give
    want.add(other, shift(3.5, 2.25))
    want.add(frame, shift(150, 5))
    assert live.tiles() == want.tiles() and set(right) <= set(live.tiles())
    assert live.bounds() == want.bounds()
    for got, ref in zip(live.render(), want.render()):
        np.testing.assert_array_equal(got, ref)


# ---------------------------------------------------------------- downscaled render
@pytest.mark.parametrize("scale", [0.5, 0.3])
def test_downscaled_render_matches_inter_area(scale):
    frame = smooth_texture(150, 200, seed=4)
    m = TiledMosaic(MosaicConfig(tile_size=64))
    a = math.radians(20)
    m.add(frame, np.array([[math.cos(a), -math.sin(a), 60.5], [math.sin(a), math.cos(a), -30.25]]))
    m.add(frame, shift(-70, 40))
    full, full_alpha, origin = m.render()
    small, small_alpha, small_origin = m.render(scale=scale)
    assert small_origin == origin
    h, w = full_alpha.shape
    assert small_alpha.shape == (round(h * scale), round(w * scale))
    want = cv2.resize(full, small_alpha.shape[::-1], interpolation=cv2.INTER_AREA)
    want_alpha = cv2.resize(full_alpha, small_alpha.shape[::-1], interpolation=cv2.INTER_AREA)
    assert np.abs(small_alpha.astype(int) - want_alpha).max() <= 1
    inside = want_alpha == 255  # output pixels fed by covered map pixels only
    assert inside.mean() > 0.3
    assert np.abs(small.astype(int) - want)[inside].max() <= 1
    # at the map's edge the empty pixels do not darken the preview
    edge = (want_alpha > 60) & (want_alpha < 200)
    assert small[edge].mean() > want[edge].mean() + 20


# ---------------------------------------------------------------- bad input and config
def test_bad_input_is_an_input_error():
    m = TiledMosaic(MosaicConfig(tile_size=32))
    frame = noise(10, 10)
    with pytest.raises(InputError, match="uint8"):
        m.add(frame.astype(np.float32), shift(0, 0))
    with pytest.raises(InputError, match="NaN"):
        m.add(frame, np.array([[1.0, 0, np.nan], [0, 1, 0]]))
    with pytest.raises(InputError, match="2x3"):
        m.add(frame, np.eye(3))
    with pytest.raises(InputError, match="singular"):
        m.add(frame, np.zeros((2, 3)))
    with pytest.raises(InputError, match="mask shape"):
        m.add(frame, shift(0, 0), mask=np.ones((5, 5), bool))
    with pytest.raises(InputError, match="footprint"):
        m.add(frame, np.array([[1e4, 0, 0], [0, 1e4, 0]]))
    assert m.tiles() == []


def test_config_section_builds_a_mosaic():
    section = load_config().mosaic
    m = TiledMosaic(section)
    assert (m.tile_size, m.blend) == (section.tile_size, section.blend)
    with pytest.raises(ConfigError, match="mosaic.blend"):
        MosaicConfig(blend="median")
    with pytest.raises(ValueError, match="store"):
        TiledMosaic(MosaicConfig(max_tiles_in_memory=8))


def test_twenty_megapixel_stills_are_mapped_but_a_wild_pose_is_not():
    """A 20 MP DJI still (5472x3648) covers more map pixels than max_footprint_px by itself: it is
    mapped (a footprint up to 4 times the frame's pixels is fine), a pose 3x larger is refused."""
    m = TiledMosaic(MosaicConfig(channels=1, tile_size=1024))
    still = np.full((3648, 5472), 128, np.uint8)
    assert m.add(still, np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
    assert m.add(still, np.array([[1.0, 0.0, 1800.0], [0.0, 1.0, 0.0]]))
    with pytest.raises(InputError, match="footprint"):
        m.add(still, np.array([[3.0, 0.0, 0.0], [0.0, 3.0, 0.0]]))


class GatedStore(MemoryTileStore):
    """A store whose writes wait for ``gate`` (a slow disk), or fail (a full one)."""

    def __init__(self, fail: bool = False) -> None:
        super().__init__()
        self.gate = threading.Event()
        self.fail = fail
        self.writing = 0

    def put(self, key, arrays):
        self.writing += 1
        self.gate.wait(30)
        if self.fail:
            raise OSError("No space left on device")
        super().put(key, arrays)


def _tile(value: int) -> dict:
    return {"color": np.full((8, 8, 3), value, np.uint8), "cover": np.full((8, 8), 255, np.uint8)}


def test_write_behind_store_serves_tiles_until_written_and_bounds_what_waits():
    slow = GatedStore()
    store = WriteBehindTileStore(slow, max_pending=3)
    for k in range(3):
        store.put((k, 0), _tile(k))  # returns at once: the disk is stalled
    assert slow.keys() == [] and sorted(store.keys()) == [(0, 0), (1, 0), (2, 0)]
    got = store.get((1, 0))
    assert got["color"][0, 0, 0] == 1
    got["color"][...] = 99  # a copy: what is written stays as put
    store.discard((2, 0))
    assert store.get((2, 0)) is None
    blocked = threading.Thread(target=store.put, args=((3, 0), _tile(3)))
    blocked.start()
    blocked.join(0.3)
    assert blocked.is_alive()  # a fourth waits for the disk: memory stays bounded
    slow.gate.set()
    blocked.join(10)
    assert store.flush(10)
    assert sorted(slow.keys()) == [(0, 0), (1, 0), (3, 0)]
    assert [slow.get((k, 0))["color"][0, 0, 0] for k in (0, 1, 3)] == [0, 1, 3]


def test_write_behind_store_keeps_what_the_disk_refuses(caplog):
    full = GatedStore(fail=True)
    full.gate.set()
    store = WriteBehindTileStore(full)
    with caplog.at_level("WARNING"):
        for k in range(4):
            store.put((k, 0), _tile(k))
        assert store.flush(10)
    assert store.failures == 4 and full.keys() == []
    assert [store.get((k, 0))["color"][0, 0, 0] for k in range(4)] == [0, 1, 2, 3]  # nothing lost
    assert sum("kept in memory" in r.getMessage() for r in caplog.records) == 1  # said once


def test_a_capped_map_over_a_write_behind_disk_store_is_the_same_map(tmp_path):
    rng = np.random.default_rng(3)
    frames = [(rng.integers(0, 255, (60, 80, 3), np.uint8), np.array([[1.0, 0, 37.0 * k], [0, 1, 11.0 * k]]))
              for k in range(12)]
    free = TiledMosaic(MosaicConfig(tile_size=32))
    capped = TiledMosaic(MosaicConfig(tile_size=32, max_tiles_in_memory=3),
                         store=WriteBehindTileStore(DiskTileStore(tmp_path)))
    for img, M in frames + frames[::-1]:
        free.add(img, M)
        capped.add(img, M)
    for a, b in zip(free.render(), capped.render()):
        np.testing.assert_array_equal(a, b)


def test_write_behind_store_reads_ahead_and_never_serves_a_stale_tile():
    disk = MemoryTileStore()
    store = WriteBehindTileStore(disk)
    for k in range(3):
        disk.put((k, 0), _tile(k))
    store.prefetch([(0, 0), (1, 0), (2, 0), (9, 9)])  # (9, 9): nothing there
    assert store.flush(10)
    store.put((1, 0), _tile(11))  # newer than what was read ahead
    assert store.flush(10)
    assert [store.get((k, 0))["color"][0, 0, 0] for k in range(3)] == [0, 11, 2]
    assert store.prefetched == 2 and store.get((9, 9)) is None


def test_a_painted_map_reads_its_spilled_tiles_ahead(tmp_path):
    """The painter asks for the tiles under (and around) each frame: a revisit finds them read."""
    rng = np.random.default_rng(5)
    img = rng.integers(0, 255, (60, 80, 3), np.uint8)
    store = WriteBehindTileStore(DiskTileStore(tmp_path))
    m = TiledMosaic(MosaicConfig(tile_size=32, max_tiles_in_memory=6), store=store)
    for k in range(10):  # out ...
        m.add(img, np.array([[1.0, 0, 50.0 * k], [0, 1, 0]]))
    assert store.flush(10)
    m.prefetch(np.array([[1.0, 0, 20.0], [0, 1, 0]]), (80, 60))  # ... and back
    assert store.flush(10)
    m.add(img, np.array([[1.0, 0, 20.0], [0, 1, 0]]))
    assert store.prefetched >= 4


def test_read_ahead_takes_the_tiles_nearest_the_frame_and_no_more_than_it_keeps(tmp_path):
    """A frame back over spilled ground: its store reads at most ``max_ready`` tiles, those
    nearest the frame's centre, each once (more would push out the first before they are taken,
    to be read again for the next frame), and the frame's paint takes them."""

    class Counting(DiskTileStore):
        def __init__(self, root):
            super().__init__(root)
            self.reads: list = []

        def get(self, key):
            self.reads.append(key)
            return super().get(key)

    rng = np.random.default_rng(7)
    img = rng.integers(0, 255, (60, 80, 3), np.uint8)
    disk = Counting(tmp_path)
    store = WriteBehindTileStore(disk, max_ready=4)
    m = TiledMosaic(MosaicConfig(tile_size=32, max_tiles_in_memory=6), store=store)
    for k in range(10):  # out ...
        m.add(img, np.array([[1.0, 0, 50.0 * k], [0, 1, 0]]))
    assert store.flush(10)
    disk.reads.clear()
    back = np.array([[1.0, 0, 20.0], [0, 1, 0]])  # ... and back: x 20..99, y 0..59 (tiles 0-3, 0-1)
    for _ in range(3):  # the next frames ask again: nothing is read twice
        m.prefetch(back, (80, 60))
        assert store.flush(10)
    nearest = {(1, 0), (1, 1), (2, 0), (2, 1)}  # centre (59.5, 29.5): tiles 1-2 of x, 0-1 of y
    assert sorted(disk.reads) == sorted(nearest)
    assert store.tiles_read_ahead == 4
    m.add(img, back)
    assert store.prefetched == 4


def test_tiles_read_ahead_count_in_the_maps_tile_cap(tmp_path):
    """``max_tiles_in_memory`` bounds the map's tiles and those its store read ahead together:
    a tile read ahead pushes one of the map's out at its next change; the map is the same."""
    rng = np.random.default_rng(6)
    img = rng.integers(0, 255, (60, 80, 3), np.uint8)
    cap = 8
    store = WriteBehindTileStore(DiskTileStore(tmp_path), max_ready=4)
    m = TiledMosaic(MosaicConfig(tile_size=32, max_tiles_in_memory=cap), store=store)
    free = TiledMosaic(MosaicConfig(tile_size=32))
    held = []
    for k in range(10):  # out ...
        for mosaic in (m, free):
            mosaic.add(img, np.array([[1.0, 0, 50.0 * k], [0, 1, 0]]))
        assert store.flush(10)
        held.append(m.tiles_in_memory + store.tiles_read_ahead)
    m.prefetch(np.array([[1.0, 0, 20.0], [0, 1, 0]]), (80, 60))  # ... and back
    assert store.flush(10)
    assert store.tiles_read_ahead == 4  # what it reads ahead is held beside the map ...
    for k in (10, 11):  # ... until a change, which makes room for them
        for mosaic in (m, free):
            mosaic.add(img, np.array([[1.0, 0, 50.0 * k], [0, 1, 0]]))
        held.append(m.tiles_in_memory + store.tiles_read_ahead)
    assert max(held) <= cap
    for mosaic in (m, free):
        mosaic.add(img, np.array([[1.0, 0, 20.0], [0, 1, 0]]))
    assert store.prefetched >= 2
    for a, b in zip(free.render(), m.render()):
        np.testing.assert_array_equal(a, b)
