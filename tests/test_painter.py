"""Painting only what changes the map, at the map's resolution, and re-rendering in the background.

Truth: the simulator's terrain seen through the true pose of the first frame (as in
tests/test_pipeline.py), maps painted every frame whole (the behaviour before), and maps painted
from scratch with the corrected poses."""

from __future__ import annotations

import json
import math
import threading
import time

import cv2
import numpy as np
import pytest

from photomap.config import MosaicConfig, load_config
from photomap.core.mosaic import TiledMosaic
from photomap.io.keyframestore import KeyframeStore
from photomap.io.tilestore import MemoryTileStore
from photomap.mapping.loopclosure import LoopCloser, PoseTable
from photomap.mapping.painter import Painter, resize_factors
from photomap.mapping.pipeline import MappingPipeline
from photomap.mapping.rerender import KeptFrame, Rerenderer, tile_rects
from photomap.mapping.timing import StageTimes
from photomap.sim.flight import simulate_sequence
from photomap.sim.terrain import load_terrain, valid_mask
from test_pipeline import ListSource


def texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.normal(0, 1, (h, w, 3)).astype(np.float32), (0, 0), 2)
    t = (t - t.min()) / (t.max() - t.min())
    return np.rint(20 + 215 * t).astype(np.uint8)


def pose(angle_deg: float, x: float, y: float, s: float = 1.0) -> np.ndarray:
    a = math.radians(angle_deg)
    return np.array([[s * math.cos(a), -s * math.sin(a), x], [s * math.sin(a), s * math.cos(a), y], [0, 0, 1.0]])


# ---------------------------------------------------------------- new ground
def test_uncovered_is_the_new_ground_and_painting_it_completes_the_map():
    a, b = texture(120, 160, 1), texture(120, 160, 2)
    m = TiledMosaic(MosaicConfig(tile_size=64))
    m.add(a, pose(0, 0, 0)[:2])
    assert m.uncovered(pose(0, 0, 0)[:2], (160, 120)) == []  # over mapped ground: nothing new
    assert m.uncovered(pose(0, 1.5, -0.5)[:2], (160, 120)) == []  # nothing a pixel wide either
    Mb = pose(8, 70.5, 30.25)[:2]
    rects = m.uncovered(Mb, (160, 120), block=16, step=2)
    assert rects and all(x % 16 == 0 and y % 16 == 0 and w % 16 == 0 and h % 16 == 0 for x, y, w, h in rects)
    # no rectangle lies entirely inside frame a's footprint (x, y in 1..158, 1..118)
    assert not any(x >= 1 and y >= 1 and x + w <= 159 and y + h <= 119 for x, y, w, h in rects)
    whole = TiledMosaic(MosaicConfig(tile_size=64))
    whole.add(a, pose(0, 0, 0)[:2])
    whole.add(b, Mb)
    m.add(b, Mb, clip=rects)
    got, want = m.render(bounds=whole.bounds()), whole.render()
    # the same coverage but for the frame's edge band that is not looked at (inset + border)
    lost = (want[1] == 255) & (got[1] != 255)
    assert lost.sum() < 0.01 * (want[1] == 255).sum()
    assert not ((got[1] == 255) & (want[1] != 255)).any()
    # where b was painted it is b (newest on top); elsewhere a as before
    same = (got[1] == 255) & (want[1] == 255)
    assert np.median(np.abs(got[0].astype(int) - want[0])[same]) == 0


class CountingStore(MemoryTileStore):
    def __init__(self) -> None:
        super().__init__()
        self.reads = 0

    def get(self, key):
        self.reads += 1
        return super().get(key)


@pytest.mark.parametrize("blend", ["overwrite", "feather"])
def test_uncovered_reads_no_spilled_tile(blend):
    """A map with a tile cap answers where new ground is from what it keeps of its spilled tiles:
    the same answer as a map without a cap, and no tile read back from the store."""
    frames = [(texture(120, 160, k), pose(5 * k, 60 * k, 15 * k)[:2]) for k in range(4)]
    free = TiledMosaic(MosaicConfig(tile_size=32, blend=blend))
    store = CountingStore()
    capped = TiledMosaic(MosaicConfig(tile_size=32, blend=blend, max_tiles_in_memory=4), store=store)
    for img, M in frames:
        free.add(img, M)
        capped.add(img, M)
    store.reads = 0
    for k, (_, M) in enumerate(frames):  # revisits, and a frame half over new ground
        for probe in (M, pose(-3, 60 * k + 40.5, 15 * k + 20.25)[:2]):
            assert capped.uncovered(probe, (160, 120)) == free.uncovered(probe, (160, 120))
    assert store.reads == 0
    capped.add(*frames[0])  # painting brings its tiles back: their summaries go
    assert capped.uncovered(frames[0][1], (160, 120)) == []



@pytest.mark.parametrize("change", ["put_tiles", "set_tile", "clear_tiles", "lost"])
def test_uncovered_sees_a_covered_tile_replaced_by_less_ground(change):
    """A tile found all covered is not looked at again by uncovered() until it is replaced,
    emptied or lost: then its missing ground is new again, as for a map never asked before."""
    img, M = texture(120, 160, 3), pose(0, 0, 0)[:2]
    key = (1, 1)  # map pixels 32..63: inside the frame's footprint; its left half stays covered
    left = np.zeros((32, 32), np.uint8)
    left[:, :16] = 255

    def changed(asked_before: bool) -> TiledMosaic:
        store = MemoryTileStore()
        m = TiledMosaic(MosaicConfig(tile_size=32, max_tiles_in_memory=64), store=store)
        m.add(img, M)
        if asked_before:
            assert m.uncovered(M, (160, 120)) == []
        if change == "put_tiles":
            half = TiledMosaic(MosaicConfig(tile_size=32))
            half.set_tile(key, np.full((32, 32, 3), 90, np.uint8), left)
            m.put_tiles(half.take_tiles())
        elif change == "set_tile":
            m.set_tile(key, np.full((32, 32, 3), 90, np.uint8), left)
        else:
            if change == "lost":
                m.spill()
                store.discard(key)  # the cache lost it: the next load finds it empty
            else:
                m.clear_tiles([key])
            m.add(np.full((40, 24, 3), 90, np.uint8), pose(0, 28, 28)[:2])  # paints the left half again
        return m

    for asked_before in (False, True):
        rects = changed(asked_before).uncovered(M, (160, 120))
        assert any(x < 64 and x + w > 48 and y < 64 and y + h > 32 for x, y, w, h in rects)  # the right half

def test_a_strip_of_a_large_frame_is_downscaled_alone():
    """New ground of a frame finer than the map: only the strip's part of the frame is resized,
    and the map is the same as with the whole frame resized."""
    big = cv2.resize(texture(300, 400, 4), (1600, 1200), interpolation=cv2.INTER_CUBIC)
    first, second = pose(5, 0, 0, 0.25), pose(5, 60.3, 20.7, 0.25)
    maps = {}
    for whole_frames in (False, True):
        m = TiledMosaic(MosaicConfig(tile_size=64))
        painter = Painter((1600, 1200), 64, whole_frames=whole_frames, min_move_px=0)
        painter.paint(m, 0, 0, big[:, ::-1].copy(), first, whole=True)
        painter.paint(m, 0, 1, big, second)
        maps[whole_frames] = m
        if not whole_frames:
            assert painter.stats.new_ground == 1
    bounds = maps[True].bounds()
    (got, got_a, _), (want, want_a, _) = maps[False].render(bounds=bounds), maps[True].render(bounds=bounds)
    only_first = TiledMosaic(MosaicConfig(tile_size=64))
    Painter((1600, 1200), 64).paint(only_first, 0, 0, big[:, ::-1].copy(), first, whole=True)
    new = (want_a == 255) & (got_a == 255) & (only_first.render(bounds=bounds)[1] != 255)  # the second's ground
    assert new.sum() > 1000
    assert (got_a == 255).sum() > 0.99 * (want_a == 255).sum()
    assert np.median(np.abs(got.astype(int) - want)[new]) <= 1


def test_resize_factors_follow_cv2_resize():
    assert resize_factors((640, 480), pose(30, 5, 5, 0.9)) is None  # not much coarser: warp the frame
    size, to_small = resize_factors((640, 480), pose(30, 5, 5, 0.5))
    assert size == (320, 240)
    frame = texture(480, 640, 3)
    small = cv2.resize(frame, size, interpolation=cv2.INTER_AREA)
    # input pixel (u, v) is small pixel to_small @ (u, v): a 2x2 block's centre
    u, v = 101.5, 57.5
    su, sv = (to_small @ [u, v, 1.0])[:2]
    assert (su, sv) == (50.5, 28.5)
    assert np.allclose(small[28:30, 50:52].mean(), frame[56:60, 100:104].mean(), atol=1)


# ---------------------------------------------------------------- the pipeline's map
@pytest.fixture(scope="module")
def flight():
    terrain = load_terrain("aukerman", zoom=3)
    seq = simulate_sequence(terrain, 90, (480, 640), seed=11, valid=valid_mask(terrain), gsd=0.1 / 3,
                            altitude=(20.0, 25.0), speed=5.0, fps=15.0)
    return terrain, seq


def map_vs_terrain(out, seq, terrain):
    """Median |map - terrain| (grey) over covered pixels, and the covered pixel count."""
    run = json.loads((out / "run.json").read_text())
    info = run["mosaics"][0]
    png = cv2.imread(str(out / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    x0, y0 = info["origin_xy"]
    s = run["map_scale"]
    # map pixel (x, y) = frame-0 pixel scaled by s (OpenCV centres); terrain = H0 @ frame-0 pixel
    map_to_frame0 = np.linalg.inv(np.array([[s, 0, s / 2 - 0.5], [0, s, s / 2 - 0.5], [0, 0, 1.0]]))
    png_to_map = np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1.0]])
    ref = cv2.warpPerspective(terrain, np.asarray(seq.truth.H[0]) @ map_to_frame0 @ png_to_map,
                              png.shape[1::-1], flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    covered = cv2.erode((png[..., 3] == 255).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    diff = np.abs(cv2.cvtColor(png[..., :3], cv2.COLOR_BGR2GRAY).astype(float)
                  - cv2.cvtColor(ref, cv2.COLOR_BGR2GRAY).astype(float))
    return float(np.median(diff[covered])), int((png[..., 3] == 255).sum()), run


def test_new_ground_map_equals_the_every_frame_map(flight, tmp_path):
    terrain, seq = flight
    results = {}
    for paint in ("every", "new_ground"):
        out = tmp_path / paint
        MappingPipeline(ListSource(seq.frames), load_config(overrides=[f"mapping.paint={paint}"]), out).run()
        results[paint] = map_vs_terrain(out, seq, terrain)
    (every, n_every, _), (new, n_new, run) = results["every"], results["new_ground"]
    assert new < 6.0 and new <= every + 0.5  # as true to the ground
    assert 0.99 * n_every <= n_new <= n_every  # the same ground, but for slivers at the outer edge
    painting = run["painting"]
    assert painting["whole"] < 20 and painting["small_move"] > 30  # most frames warp nothing
    timing = run["timing_ms"]
    for stage in ("decode", "resize", "register", "paint", "frame"):
        assert timing[stage]["count"] >= 90 and 0 < timing[stage]["median"] <= timing[stage]["max"]


def test_map_px_maps_a_large_frame_at_the_map_resolution(flight, tmp_path):
    terrain, seq = flight
    out = tmp_path / "half"
    MappingPipeline(ListSource(seq.frames[:40]), load_config(overrides=["mapping.map_px=320"]), out).run()
    residual, covered, run = map_vs_terrain(out, seq, terrain)
    assert run["map_scale"] == pytest.approx(0.5)
    assert residual < 6.0
    full = tmp_path / "full"
    MappingPipeline(ListSource(seq.frames[:40]), load_config(overrides=["mapping.map_px=0"]), full).run()
    assert covered == pytest.approx(map_vs_terrain(full, seq, terrain)[1] / 4, rel=0.03)


# ---------------------------------------------------------------- re-rendering
def render_from_store(store, frames, params):
    m = TiledMosaic(params)
    for f in frames:
        m.add(store.image(f.index), f.pose[:2], store.mask(f.index))
    return m


def assert_footprints_covered(m: TiledMosaic, poses, size, inset: float = 3.0) -> None:
    """No hole 3 px wide or more ``inset`` inside the footprints of frames at ``poses``."""
    w, h = size
    corners = np.array([[inset, inset], [w - 1 - inset, inset], [w - 1 - inset, h - 1 - inset], [inset, h - 1 - inset]])
    quads = [corners @ np.asarray(p)[:2, :2].T + np.asarray(p)[:2, 2] for p in poses]
    x0, y0 = np.floor(np.min([q.min(axis=0) for q in quads], axis=0)).astype(int) - 1
    x1, y1 = np.ceil(np.max([q.max(axis=0) for q in quads], axis=0)).astype(int) + 1
    want = np.zeros((y1 - y0, x1 - x0), np.uint8)
    for q in quads:
        cv2.fillConvexPoly(want, np.rint((q - (x0, y0)) * 16).astype(np.int32), 255, cv2.LINE_8, 4)
    _, alpha, _ = m.render(bounds=(int(x0), int(y0), int(x1 - x0), int(y1 - y0)))
    hole = ((want > 0) & (alpha == 0)).view(np.uint8)  # slivers finer than uncovered()'s step may stay
    assert cv2.countNonZero(cv2.erode(hole, np.ones((3, 3), np.uint8))) == 0


def assert_same_tiles(got: TiledMosaic, want: TiledMosaic, keys) -> None:
    """Equal but for the warp's fixed-point rounding (a clipped warp starts elsewhere)."""
    for key in keys:
        assert (key in got.tiles()) == (key in want.tiles()), key
        if key not in want.tiles():
            continue  # empty in both
        (gi, ga), (wi, wa) = got.tile_image(key), want.tile_image(key)
        assert (ga != wa).mean() < 0.001
        both = (ga == 255) & (wa == 255)
        assert np.abs(gi.astype(int) - wi)[both].max(initial=0) <= 1


@pytest.mark.parametrize("as_table", [False, True])
def test_a_correction_rerenders_the_moved_tiles_in_the_background(tmp_path, as_table):
    params = MosaicConfig(tile_size=64)
    store = KeyframeStore(tmp_path / "kf")
    painter = Painter((160, 120), 64, rerenderer=Rerenderer(store, params, strip_tiles=5), interval_s=0.0)
    live = TiledMosaic(params)
    poses = {i: pose(4 * i, 60.0 * i, 10.0 * i) for i in range(6)}
    mask = np.ones((120, 160), bool)
    mask[:, :20] = False  # a frame valid only in part
    for i, p in poses.items():
        painter.paint(live, 0, i, texture(120, 160, 10 + i), p, mask if i == 2 else None, whole=True)
    painter.rerenderer.wait()
    before = {key: live.tile_image(key) for key in live.tiles()}
    # the pose graph moves frames 3..5 (a drift correction growing along the path)
    corrected = dict(poses)
    for i in (3, 4, 5):
        corrected[i] = pose(4 * i, 60.0 * i - 2.0 * (i - 2), 10.0 * i + 3.5 * (i - 2))
    # as the loop closer hands it over (frames in arrays, with one more frame that was not kept)
    given = PoseTable(np.array([*corrected, 99]), np.array([*corrected.values(), np.eye(3)])) if as_table else corrected
    assert painter.on_correction(0, given) == 3
    changed = painter.finish({0: live})
    assert changed[0] and (0, 0) not in changed[0]
    # the re-rendered tiles are the corrected map (from the kept images), the others untouched
    kept = [KeptFrame(i, corrected[i], (160, 120)) for i in poses]
    assert_same_tiles(live, render_from_store(store, kept, params), changed[0])
    for key in set(before) - changed[0]:
        np.testing.assert_array_equal(live.tile_image(key)[0], before[key][0])
    assert set(live.tiles()) >= set(before) - changed[0]
    assert painter.stats.rerender_jobs == 1 and painter.stats.rerendered_tiles == len(changed[0])
    painter.close()


def test_frames_kept_by_reference_rerender_from_the_inputs_own_pixels(tmp_path):
    """Stills painted as decoded are kept by reference (``as_read``): no JPEG is written, and a
    correction re-renders their tiles from the input's pixels read again, exactly as a map
    painted from scratch at the corrected poses; a frame painted through a mask is kept as a
    JPEG still (its pixels are not the input's)."""
    params = MosaicConfig(tile_size=64)
    images = {i: texture(120, 160, 30 + i) for i in range(4)}
    reads: list[int] = []
    store = KeyframeStore(tmp_path / "kf", read_again=lambda i: reads.append(i) or images.get(i))
    painter = Painter((160, 120), 64, rerenderer=Rerenderer(store, params, strip_tiles=5), interval_s=0.0)
    live = TiledMosaic(params)
    poses = {i: pose(3 * i, 55.0 * i, 8.0 * i) for i in images}
    mask = np.ones((120, 160), bool)
    mask[:, :16] = False
    for i, p in poses.items():
        painter.paint(live, 0, i, images[i], p, mask if i == 3 else None, whole=True, as_read=True)
    painter.rerenderer.wait()
    assert sorted(f.name for f in (tmp_path / "kf").iterdir()) == ["kf0000003.jpg", "kf0000003_mask.png"]
    corrected = {i: pose(3 * i, 55.0 * i - 1.5 * i, 8.0 * i + 2.5 * i) for i in images}
    assert painter.on_correction(0, corrected) == 3
    changed = painter.finish({0: live})
    assert changed[0] and set(reads) == {0, 1, 2}  # frame 3 from its JPEG
    want = TiledMosaic(params)
    for i in images:
        want.add(images[i] if i < 3 else store.image(3), corrected[i][:2], mask if i == 3 else None)
    for key in changed[0]:
        assert (key in live.tiles()) == (key in want.tiles()), key
        if key in want.tiles():
            for a, b in zip(live.tile_image(key), want.tile_image(key)):
                np.testing.assert_array_equal(a, b, err_msg=str(key))
    painter.close()


def test_tiles_painted_during_a_rerender_keep_their_pixels_until_redone(tmp_path):
    params = MosaicConfig(tile_size=64)
    store = KeyframeStore(tmp_path / "kf")
    rerenderer = Rerenderer(store, params)
    painter = Painter((160, 120), 64, rerenderer=rerenderer, interval_s=0.0)
    live = TiledMosaic(params)
    first = pose(0, 0, 0)
    painter.paint(live, 0, 0, texture(120, 160, 1), first, whole=True)
    rerenderer.wait()
    painter.on_correction(0, {0: pose(0, 3, 2)})
    gate = __import__("threading").Event()
    original = rerenderer._render_strips

    def slow(*args):  # the job runs while the worker paints
        gate.wait(10)
        return original(*args)

    rerenderer._render_strips = slow
    painter.pump({0: live}, force=True)  # job submitted
    newer = texture(120, 160, 2)
    painter.paint(live, 0, 1, newer, pose(0, 30.5, 20.5), whole=True)  # painted live meanwhile
    gate.set()
    rerenderer.wait()
    painter.pump({0: live}, force=True)  # swaps what was not painted meanwhile, re-queues the rest
    assert painter.stats.deferred_tiles > 0
    rerenderer._render_strips = original
    deferred = painter.stats.deferred_tiles
    painter.on_correction(0, {0: pose(0, 3, 2)})  # nothing moved further: only the deferred tiles
    changed = painter.finish({0: live})
    kept = [KeptFrame(0, pose(0, 3, 2), (160, 120)), KeptFrame(1, pose(0, 30.5, 20.5), (160, 120))]
    want = render_from_store(store, kept, params)
    assert len(changed[0]) >= deferred
    assert_same_tiles(live, want, changed[0])
    assert set(live.tiles()) == set(want.tiles())
    painter.close()


@pytest.mark.parametrize("border", [0, 1, 3])
def test_a_rerender_paints_each_tile_from_the_newest_frame_covering_it_whole_on(tmp_path, border):
    """Three passes over the same ground (turned, shifted, one frame masked): a re-render that
    skips the frames under the newest one covering a tile whole is pixel for pixel the one that
    paints them all (overwrite map), and paints far fewer frames."""
    params = MosaicConfig(tile_size=32, border=border)
    store = KeyframeStore(tmp_path / "kf")
    rerenderer = Rerenderer(store, params, strip_tiles=1)  # one tile a strip: the same warps both ways
    rng = np.random.default_rng(border)
    frames = []
    for i in range(18):
        along = 40.0 * (i % 6) + rng.uniform(-6, 6)
        p = pose(rng.uniform(-25, 25), 20.0 + along, 15.0 + rng.uniform(-8, 8), rng.uniform(0.9, 1.1))
        mask = None
        if i == 14:  # valid only in part: hides nothing
            mask = np.ones((120, 160), bool)
            mask[30:70, 50:110] = False
        rerenderer.save(i, texture(120, 160, 40 + i), mask)
        frames.append(KeptFrame(i, p, (160, 120), full=mask is None))
    rerenderer.wait()
    keys = sorted(render_from_store(store, frames, params).tiles())
    culled = [rerenderer._render(0, 0, tuple(frames), [key]) for key in keys]
    every = [rerenderer._render(0, 0, tuple(frames), [key], cull=False) for key in keys]
    for key, a, b in zip(keys, culled, every):
        for name in ("color", "cover"):
            np.testing.assert_array_equal(a.tiles[key][name], b.tiles[key][name], err_msg=str(key))
    painted, all_painted = sum(s.frames for s in culled), sum(s.frames for s in every)
    assert painted < 0.6 * all_painted
    # a kept image lost from the disk: what it hid shows again, as in a render of every frame
    for i in (15, 16, 17):
        store.discard(i)
        rerenderer._forget_decoded(i)
    for key in keys:
        a = rerenderer._render(0, 0, tuple(frames), [key]).tiles[key]
        b = rerenderer._render(0, 0, tuple(frames), [key], cull=False).tiles[key]
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_array_equal(a["color"], b["color"], err_msg=str(key))
    rerenderer.close()


def rerender_all(rerenderer: Rerenderer, frames, tiles, scratch_bytes: int = 0) -> TiledMosaic:
    """Re-render ``tiles`` from ``frames`` through ``rerenderer`` and wait for every strip."""
    job = rerenderer.submit(0, frames, tiles, scratch_bytes=scratch_bytes)
    got = TiledMosaic(rerenderer.params)
    while True:
        rerenderer.wait()
        strips = rerenderer.collect()
        for strip in strips:
            assert strip.job == job
            got.put_tiles(strip.tiles)
        if not strips and not rerenderer.busy:
            return got


def three_kept_frames(tmp_path, release_after: float | None):
    """A re-render thread (one tile a strip) that kept 3 frames; returns it, its store, the
    frames, the tiles they cover and the list of the frames whose kept image the store reads
    back (decodes) from now on."""
    params = MosaicConfig(tile_size=64)
    store = KeyframeStore(tmp_path / "kf")
    rerenderer = Rerenderer(store, params, strip_tiles=1, release_after=release_after)
    frames = [KeptFrame(i, pose(0, 50.0 * i, 10.0), (160, 120)) for i in range(3)]
    for f in frames:
        rerenderer.save(f.index, texture(120, 160, 20 + f.index))
    rerenderer.wait()
    tiles = set(render_from_store(store, frames, params).tiles())  # (reads the files once each)
    reads: list[int] = []
    image = store.image
    store.image = lambda index: reads.append(index) or image(index)
    return rerenderer, store, frames, tiles, reads


def test_kept_images_are_decoded_once_for_all_strips_and_anew_when_kept_again(tmp_path):
    """A correction re-renders strip after strip from the same kept frames: each kept image is
    read back (decoded) once, within the cache's budget; a frame kept again is read anew."""
    rerenderer, store, frames, tiles, reads = three_kept_frames(tmp_path, release_after=None)
    params = rerenderer.params
    got = rerender_all(rerenderer, frames, tiles)
    assert len(tiles) > 3 and sorted(reads) == [0, 1, 2]  # 1 tile a strip: every strip, no re-reads
    assert_same_tiles(got, render_from_store(store, frames, params), tiles)
    reads.clear()
    rerenderer.save(1, texture(120, 160, 99))  # frame 1 kept again, with another image
    rerenderer.wait()
    got = rerender_all(rerenderer, frames, tiles)
    assert reads == [1]
    assert_same_tiles(got, render_from_store(store, frames, params), tiles)
    rerenderer.close()


def test_strips_rendered_together_read_each_kept_image_once_to_the_same_tiles(tmp_path):
    """The final re-render renders strips together, frame by frame (``scratch_bytes``): each
    kept image is read back once for them all, where strip after strip read it again and again
    (a cache of two frames); every tile is the same, pixel for pixel, also with a kept image
    lost."""
    params = MosaicConfig(tile_size=32)
    store = KeyframeStore(tmp_path / "kf")
    rerenderer = Rerenderer(store, params, strip_tiles=3, cache_bytes=0, release_after=None)
    rng = np.random.default_rng(7)
    frames = []
    for i in range(12):  # two passes over the same ground, the second turned
        p = pose(rng.uniform(-20, 20) + 90 * (i >= 6), 45.0 * (i % 6) + rng.uniform(-5, 5), rng.uniform(0, 30))
        mask = None
        if i == 8:
            mask = np.ones((120, 160), bool)
            mask[20:60, 40:100] = False
        rerenderer.save(i, texture(120, 160, 60 + i), mask)
        frames.append(KeptFrame(i, p, (160, 120), full=mask is None))
    rerenderer.wait()
    tiles = set(render_from_store(store, frames, params).tiles())
    reads: list[int] = []
    image = store.image
    store.image = lambda index: reads.append(index) or image(index)
    for lost in (None, 10):
        if lost is not None:
            store.discard(lost)
        alone = rerender_all(rerenderer, frames, tiles)
        alone_reads, reads[:] = len(reads), []
        together = rerender_all(rerenderer, frames, tiles, scratch_bytes=1 << 30)
        assert len(tiles) > 12 and alone_reads > 2 * len(frames)
        # once each (a lost image: the strips it hid are rendered again, uncut, together too)
        assert max(reads.count(i) for i in reads) == (1 if lost is None else 2), reads
        reads.clear()
        for key in tiles:
            assert (key in alone.tiles()) == (key in together.tiles()), key
            if key in alone.tiles():
                for a, b in zip(alone.tile_image(key), together.tile_image(key)):
                    np.testing.assert_array_equal(a, b, err_msg=str(key))
    assert rerenderer.lost_frames > 0
    rerenderer.close()


def test_decoded_kept_images_are_let_go_when_no_job_came_for_a_while(tmp_path):
    """Between loop closures the re-render thread holds no decoded image: ``release_after``
    seconds after its last strip it drops them (kept images saved meanwhile do not count as
    jobs), and the next correction reads them back, to the same tiles."""
    rerenderer, _, frames, tiles, reads = three_kept_frames(tmp_path, release_after=1.0)  # (held while checked)
    first = rerender_all(rerenderer, frames, tiles)
    assert sorted(reads) == [0, 1, 2] and rerenderer.decoded_bytes == 3 * 120 * 160 * 3
    rerenderer.save(3, texture(120, 160, 23))  # a kept image is no job: the clock runs on
    deadline = time.monotonic() + 20.0
    while rerenderer.decoded_bytes and time.monotonic() < deadline:
        time.sleep(0.02)
    assert rerenderer.decoded_bytes == 0
    reads.clear()
    again = rerender_all(rerenderer, frames, tiles)
    assert sorted(reads) == [0, 1, 2]
    for key in tiles:
        np.testing.assert_array_equal(again.tile_image(key)[0], first.tile_image(key)[0])
    rerenderer.close()


def test_tile_rects_merge_row_neighbours():
    assert tile_rects([(0, 0), (1, 0), (3, 0), (1, 1)], 10) == [(0, 0, 20, 10), (30, 0, 10, 10), (10, 10, 10, 10)]


# ---------------------------------------------------------------- stage times
def test_stage_times_give_medians_and_maxima():
    t = StageTimes()
    values = [0.001 * k for k in range(1, 102)]  # 1..101 ms
    for v in values:
        t.add("paint", v)
    s = t.summary()["paint"]
    assert s["count"] == 101 and s["max"] == pytest.approx(101.0)
    assert s["median"] == pytest.approx(51.0, rel=0.06) and s["p95"] == pytest.approx(96.0, rel=0.06)
    assert s["mean"] == pytest.approx(51.0) and s["total_s"] == pytest.approx(sum(values), abs=1e-3)


# ---------------------------------------------------------------- outputs in bounded memory
def flight_map(n=12, seed=0, tile_size=64):
    rng = np.random.default_rng(seed)
    m = TiledMosaic(MosaicConfig(tile_size=tile_size))
    for _ in range(n):
        m.add(texture(240, 320, int(rng.integers(1000))), pose(rng.uniform(0, 360), rng.uniform(0, 900),
                                                               rng.uniform(0, 600))[:2])
    return m


def test_overview_preview_follows_the_map_and_reads_only_changed_tiles():
    from photomap.mapping.overview import Overview

    m = flight_map(tile_size=64)
    ov = Overview(64, max_pixels=100_000)  # small: the factor must grow (to 4 here)
    ov.mark(m.tiles())
    assert ov.update(m) == len(m.tiles()) and ov.factor > 1
    preview = ov.render(300)
    scale = 300 / max(m.bounds()[2:])
    want, want_alpha, _ = m.render(scale)
    assert abs(preview.shape[0] - want_alpha.shape[0]) <= 2 and abs(preview.shape[1] - want_alpha.shape[1]) <= 2
    h, w = min(preview.shape[0], want_alpha.shape[0]), min(preview.shape[1], want_alpha.shape[1])
    inside = (want_alpha[:h, :w] == 255) & (preview[:h, :w, 3] == 255)
    inside = cv2.erode(inside.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # placement within a pixel
    assert inside.mean() > 0.2
    # the same picture (the thumbnails' grid may shift it by a fraction of a preview pixel)
    blur = lambda im: cv2.GaussianBlur(im[:h, :w, :3].astype(np.float32), (0, 0), 2)  # noqa: E731
    assert np.median(np.abs(blur(preview) - blur(want))[inside]) <= 3
    # a new frame: only its tiles are read again
    touched = m.add(texture(240, 320, 77), pose(10, 2000, 2000)[:2])
    ov.mark(touched)
    assert ov.update(m) == len(touched)
    assert ov.render(300) is not None


def test_thumbnails_of_spilled_tiles_are_left_to_the_preview(tmp_path):
    """The worker refreshes thumbnails of tiles in memory only: a spilled one is read by the
    next preview, in the background thread."""
    from photomap.mapping.overview import Overview

    class CountingStore(MemoryTileStore):
        reads = 0

        def get(self, key):
            CountingStore.reads += 1
            return super().get(key)

    store = CountingStore()
    m = TiledMosaic(MosaicConfig(tile_size=64, max_tiles_in_memory=4), store)
    ov = Overview(64)
    for i in range(4):
        ov.mark(m.add(texture(120, 160, 40 + i), pose(0, 200.0 * i, 0)[:2]))
    spilled = [key for key in m.tiles() if not m.in_memory(key)]
    assert spilled and m.tiles_in_memory == 4
    reads = CountingStore.reads
    assert ov.update(m) == 4 and ov.stale == len(spilled) and CountingStore.reads == reads
    tasks = []
    assert ov.write(tmp_path / "preview.png", m, 300, later=tasks.append) and ov.stale == 0 and CountingStore.reads == reads
    tasks.pop()()  # the background thread reads the spilled tiles
    assert CountingStore.reads == reads + len(spilled)
    assert ov.update(m) == 0 and len(ov.render(10_000)) > 0


def test_a_preview_leaves_the_thumbnails_to_the_background_thread(tmp_path):
    """The worker only copies the changed tiles; the thumbnails, made later in the background,
    show the map as it was copied, come back to the worker, and never replace newer ones."""
    from photomap.mapping.overview import Overview

    def fresh_render(mosaic):
        ov = Overview(64)
        ov.mark(mosaic.tiles())
        ov.update(mosaic)
        return ov.render(300)

    m, before = flight_map(tile_size=64), fresh_render(flight_map(tile_size=64))
    ov, tasks, path = Overview(64), [], tmp_path / "preview.png"
    ov.mark(m.tiles())
    assert ov.write(path, m, 300, later=tasks.append) and len(tasks) == 1
    assert ov.stale == 0 and not path.exists()  # nothing made in the worker
    touched = m.add(texture(240, 320, 77), pose(30, 300, 250)[:2])  # the map changes meanwhile
    ov.mark(touched)
    assert ov.update(m) == len(touched)
    covered = lambda image: int((image[..., 3] > 0).sum())  # noqa: E731
    partial = covered(ov.render(10_000))  # so far only the thumbnails of `touched`
    tasks.pop()()  # the background thread: thumbnails of the copies, then the PNG
    png = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert png.shape == before.shape and np.array_equal(png, before)  # the map as copied
    after = ov.render(300)  # the copies' thumbnails came back; the newer ones of `touched` stayed
    assert np.array_equal(after, fresh_render(m)) and not np.array_equal(after, before)
    assert partial < 0.8 * covered(ov.render(10_000))


class LiveListSource(ListSource):
    """The frames as a camera gives them (a live run: background threads not in lockstep)."""

    live = True


def blind_flight():
    """A figure-8 flight over aukerman (truth) whose camera sees a uniform grey for 15 frames."""
    from test_drift import closed_flight

    terrain = load_terrain("aukerman", zoom=3)
    seq = closed_flight(terrain, valid_mask(terrain), 0.1 / 3, 1.0, "figure8", 4)
    blind = list(seq.frames)
    for k in range(60, 75):
        blind[k] = np.full_like(blind[k], 128)
    return terrain, seq, blind


@pytest.mark.parametrize("live", [False, True], ids=["replay", "live"])
def test_a_joined_segment_is_rerendered_into_the_map_it_joined(tmp_path, monkeypatch, live):
    """The camera sees nothing for a while (new segments), then flies over mapped ground: the new
    segment joins the first; its kept frames are re-rendered into the first map in the
    background and mosaic.png holds both parts, true to the ground. Live, the search for the
    join (registrations with features, keyframe images read back from disk: 100-400 ms at
    1080p) runs in the loop thread, never in the worker (a replay searches in the worker, in
    step with the frames)."""
    from test_drift import LOOPS, map_residual

    terrain, seq, blind = blind_flight()
    searched = []
    place = LoopCloser._place_join

    def spy(self, *args, **kwargs):
        searched.append(threading.current_thread().name)
        return place(self, *args, **kwargs)

    monkeypatch.setattr(LoopCloser, "_place_join", spy)
    source = LiveListSource if live else ListSource
    runs = {}
    for name, frames in (("whole", seq.frames), ("blind", blind)):
        out = tmp_path / name
        summary = MappingPipeline(source(frames), load_config(overrides=LOOPS + ["mapping.max_lost_frames=5"]),
                                  out).run()
        png = cv2.imread(str(out / "mosaic.png"), cv2.IMREAD_UNCHANGED)
        runs[name] = summary, int((png[..., 3] == 255).sum()), map_residual(out, seq, terrain, lambda x, y: x == x)[0]
    (_, covered, residual), (blind_run, blind_covered, blind_residual) = runs["whole"], runs["blind"]
    assert searched and all(name.startswith("photomap-loops") == live for name in searched), searched
    assert [j["into"] for j in blind_run["joins"]] == [0]
    if not live:
        assert [(j["segment"], j["into"]) for j in blind_run["joins"]] == [(3, 0)]
    assert [m["segment"] for m in blind_run["mosaics"]] == [0]
    assert blind_run["painting"]["rerendered_tiles"] > 0
    # the joined segment's ground is in the main map: its kept (whole) frames are re-rendered
    # there; the new ground of the frames in between is not carried over, and under load a live
    # join comes some frames later than in a replay (its search takes longer): 0.88 of the
    # unbroken flight's map measured then, 0.92 quiet
    assert blind_covered > (0.8 if live else 0.9) * covered
    assert blind_residual <= residual + 1.0


def test_a_map_the_camera_left_goes_to_the_tile_store_a_few_tiles_a_frame(tmp_path):
    """With a tile cap, a map whose segment the camera left (blind frames: a new segment) moves
    its tiles to the store over the next frames, a few each (all at once stalled the worker for
    200 ms at 1080p), until none is left in memory (nor read ahead for it); the maps are those of
    a run without a cap."""
    from photomap.mapping.segments import _SPILL_TILES_PER_FRAME
    from test_drift import LOOPS

    _, _, blind = blind_flight()
    base = LOOPS + ["mapping.max_lost_frames=5", "mosaic.tile_size=64", "mapping.loop_closure=false"]
    held = []  # per frame: tiles in memory of the maps other than the current one
    ahead = []  # ... and tiles their stores read ahead for them

    def sink(event):
        held.append(sum(m.tiles_in_memory for seg, m in pipe.mosaics.items() if seg != event.segment))
        ahead.append(sum(st.tiles_read_ahead for seg, st in pipe.segments.tile_stores.items() if seg != event.segment))

    pipe = MappingPipeline(ListSource(blind), load_config(overrides=base + ["mosaic.max_tiles_in_memory=40"]),
                           tmp_path / "capped", sinks=[sink])
    capped = pipe.run()
    free = MappingPipeline(ListSource(blind), load_config(overrides=base), tmp_path / "free").run()
    assert max(held) > _SPILL_TILES_PER_FRAME  # the left map held more than a frame's share
    assert all(b - a <= _SPILL_TILES_PER_FRAME for a, b in zip(held[1:], held[:-1]))  # a few a frame
    assert held[-1] == 0
    assert max(ahead) > 0 and ahead[-1] == 0  # nor tiles read ahead for them
    assert [m["segment"] for m in capped["mosaics"]] == [m["segment"] for m in free["mosaics"]]
    for m in capped["mosaics"]:
        got = cv2.imread(str(tmp_path / "capped" / m["file"]), cv2.IMREAD_UNCHANGED)
        want = cv2.imread(str(tmp_path / "free" / m["file"]), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(got, want)


@pytest.mark.parametrize("exposure,down", [("none", True), ("gain", True), ("gain", False)])
def test_a_keyframe_is_painted_in_bands_over_the_next_frames(exposure, down):
    """``band_px``: a whole paint warps the band of tile rows ahead of the camera and its new
    ground beyond it (no footprint is left with a hole after any paint), and each later paint
    one band more (the rest before the next whole paint, or at the segment's end), all with
    the exposure gain fitted once: the map is the one of each whole paint at once (to the
    clipped warp's rounding). (Frames in between look for new ground as before: their maps
    are checked against the terrain in test_new_ground_map_equals_the_every_frame_map.)"""
    params = MosaicConfig(tile_size=64, exposure=exposure)
    dy = 9.0 if down else -9.0
    frames = [(np.clip(texture(120, 160, 30 + i).astype(int) * (1.0 + 0.04 * i), 0, 255).astype(np.uint8),
               pose(3 * i, 23.0 * i, 200 + dy * i), i % 5 == 0) for i in range(13)]  # exposure changes
    maps, calls, bands = {}, {}, []
    for band_px in (0, 64):
        painter = Painter((160, 120), 64, min_move_px=1e9, band_px=band_px)  # no new-ground paints
        m = maps[band_px] = TiledMosaic(params)
        calls[band_px] = []

        def band(mosaic, seg, real=painter._band):  # the map rectangle of each band, by the frame painting it
            bands.append((i, seg.bands.rects[0]))
            return real(mosaic, seg)

        painter._band = band
        for i, (img, p, key) in enumerate(frames):
            calls[band_px].append(painter.paint(m, 0, i, img, p, whole=key))
            if band_px:  # no frame painted (whole, even banded) leaves its new ground empty
                assert_footprints_covered(m, [q for _, q, k in frames[:i + 1] if k], (160, 120))
        painter.end_segment(m, 0)
    banded, at_once = maps[64], maps[0]
    assert calls[64][0] == calls[0][0]  # a segment's first frame at once: its map is never empty
    # frame 5, a keyframe over 3-4 tile rows: the rows ahead at once, the others with frames 6, 7, 8
    at_once_rows = sorted({ty for _, ty in calls[0][5]})
    ahead = at_once_rows[::-1] if down else at_once_rows
    assert len(ahead) >= 3 and not any(calls[0][6:10])
    seen = [sorted({(y + h - 1) // 64 for i, (x, y, w, h) in bands if i == 5 + k} |
                   {y // 64 for i, (x, y, w, h) in bands if i == 5 + k}, reverse=down) for k in range(len(ahead))]
    assert ahead[0] in seen[0] and ahead[-1] not in seen[0]
    assert [ty for rows in seen for ty in rows] == ahead  # each row once, in the order of travel
    assert set(banded.tiles()) == set(at_once.tiles())
    assert_same_tiles(banded, at_once, at_once.tiles())


def test_a_masked_frame_looks_for_new_ground_inside_its_valid_part():
    """A rectified view is valid in a quadrilateral only: blocks outside it are never new (else
    they would be painted again at every look)."""
    from photomap.mapping.painter import valid_outline

    mask = np.zeros((240, 320), np.uint8)
    cv2.fillConvexPoly(mask, np.array([[40, 10], [300, 30], [280, 230], [20, 200]], np.int32), 255)
    outline = valid_outline(mask)
    assert all(mask[int(round(y)), int(round(x))] for x, y in outline)  # inside the valid part
    assert cv2.contourArea(outline.astype(np.float32)) > 0.9 * (mask > 0).sum()  # and most of it
    m = TiledMosaic(MosaicConfig(tile_size=64))
    frame = texture(240, 320, 9)
    m.add(frame, pose(0, 0, 0)[:2], mask=mask)
    assert m.uncovered(pose(0, 0, 0)[:2], (320, 240), outline=outline) == []  # all of it is mapped
    assert m.uncovered(pose(0, 0, 0)[:2], (320, 240)) != []  # the rectangle would look new forever


# ---------------------------------------------------------------- merged with main: failures, stills
def test_a_preview_that_cannot_be_written_is_reported_not_raised(tmp_path):
    """The preview is encoded in the background thread; a disk error there goes to on_error (the
    pipeline's one-line write error) and the re-render thread goes on."""
    params = MosaicConfig(tile_size=64)
    painter = Painter((160, 120), 64, rerenderer=Rerenderer(KeyframeStore(tmp_path / "kf"), params))
    live = TiledMosaic(params)
    painter.paint(live, 0, 0, texture(120, 160, 1), pose(0, 0, 0), whole=True)
    errors = []
    assert painter.write_preview(tmp_path / "missing" / "preview.png", 0, live, 100, on_error=errors.append)
    painter.rerenderer.wait()
    assert len(errors) == 1 and isinstance(errors[0], OSError)
    assert painter.rerenderer.collect() == []  # no failure handed to the worker
    assert painter.write_preview(tmp_path / "preview.png", 0, live, 100, on_error=errors.append)
    painter.close()
    back = cv2.imread(str(tmp_path / "preview.png"), cv2.IMREAD_UNCHANGED)
    assert back is not None and back.shape[2] == 4 and len(errors) == 1


def test_a_preview_is_never_made_in_the_worker_when_the_background_thread_is_behind(tmp_path):
    """With the background thread's queue full, a checkpoint's preview is left to the next one
    (no thumbnails or PNG encoding in the worker); its changed tiles stay for it."""
    import threading

    params = MosaicConfig(tile_size=64)
    painter = Painter((160, 120), 64, rerenderer=Rerenderer(KeyframeStore(tmp_path / "kf"), params,
                                                            max_pending_writes=1))
    live = TiledMosaic(params)
    painter.paint(live, 0, 0, texture(120, 160, 1), pose(0, 0, 0), whole=True)
    painter.rerenderer.wait()  # the kept image is written
    release, running = threading.Event(), threading.Event()
    painter.rerenderer.later(lambda: (running.set(), release.wait(10)))  # the thread is busy ...
    assert running.wait(10)
    painter.rerenderer.later(lambda: None)  # ... and its queue full
    path = tmp_path / "preview.png"
    assert not painter.write_preview(path, 0, live, 100)
    assert painter.stats.skipped_previews == 1 and painter.rerenderer.sync_writes == 0
    release.set()
    painter.rerenderer.wait()
    assert not path.exists()
    assert painter.write_preview(path, 0, live, 100)  # the next checkpoint's, with every tile
    painter.close()
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert back is not None and (back[..., 3] > 0).mean() > 0.9  # the frame, all of it


def test_kept_images_with_masks_are_forgotten_with_their_keyframe(tmp_path):
    store = KeyframeStore(tmp_path / "kf")
    image = texture(30, 40, 2)
    mask = np.zeros((30, 40), bool)
    mask[:, 10:] = True
    store.put(7, image)
    store.put_image(7, image, mask)
    assert np.array_equal(store.mask(7) == 255, mask) and store.image(7).shape == image.shape
    store.discard(7)
    assert store.image(7) is None and store.mask(7) is None and list((tmp_path / "kf").iterdir()) == []
    (tmp_path / "kf").rmdir()  # the disk refuses: counted, never raised
    store.put_image(8, image, mask)
    assert store.failures == 1 and store.image(8) is None


@pytest.mark.parametrize("stills", [False, True])
def test_map_px_lowers_the_map_resolution_of_video_only(tmp_path, stills):
    """A frame wider than mapping.map_px: video is mapped at map_px a frame, survey stills keep
    their resolution (the map of a survey is its full-resolution orthophoto)."""
    from photomap.drivers.images import ImageFolderSource

    base = cv2.resize(texture(150, 200, 3), (1400, 1050), interpolation=cv2.INTER_CUBIC)
    frames = [np.ascontiguousarray(base[0 + 30 * k:900 + 30 * k, 0 + 40 * k:1200 + 40 * k]) for k in range(3)]
    if stills:
        for k, f in enumerate(frames):
            cv2.imwrite(str(tmp_path / f"still{k}.png"), f)
        source = ImageFolderSource(tmp_path / "still*.png")
    else:
        source = ListSource(frames)
    cfg = load_config(overrides=["mapping.map_px=600"])
    summary = MappingPipeline(source, cfg, tmp_path / "out").run()
    want = 1.0 if stills else 0.5
    assert summary["map_scale"] == pytest.approx(want)
    x, y, w, h = summary["mosaics"][0]["bounds"]
    assert w == pytest.approx((1200 + 80) * want, abs=4) and h == pytest.approx((900 + 60) * want, abs=4)


def test_a_replay_makes_the_same_map_however_slow_the_background_threads(tmp_path, monkeypatch):
    """Replay runs the loop registrations, the pose-graph solves and the re-renders in lockstep
    with the frames: with the background threads slowed down a lot, the trajectory and
    mosaic.png are identical (batch and replay of the same flight agree; a rerun reproduces a
    map)."""
    import time

    from test_drift import LOOPS, closed_flight

    from photomap.mapping import loopclosure, rerender

    terrain = procedural_terrain_sand()
    seq = closed_flight(terrain, None, 0.05, 2.0, "figure8", 1, n=300)

    def run(name):
        out = tmp_path / name
        summary = MappingPipeline(ListSource(seq.frames), load_config(overrides=LOOPS), out).run()
        return summary, (out / "trajectory.csv").read_text(), cv2.imread(str(out / "mosaic.png"),
                                                                          cv2.IMREAD_UNCHANGED)

    quick, quick_rows, quick_map = run("quick")
    solve, render = loopclosure.KeyframeGraph.solve, rerender.Rerenderer._render_strips
    measure = loopclosure.KeyframeGraph.measure_loops

    def slow_measure(*args, **kwargs):
        time.sleep(0.1)
        return measure(*args, **kwargs)

    def slow_solve(*args, **kwargs):
        time.sleep(0.3)
        return solve(*args, **kwargs)

    def slow_render(self, *args, **kwargs):
        time.sleep(0.2)
        return render(self, *args, **kwargs)

    monkeypatch.setattr(loopclosure.KeyframeGraph, "solve", staticmethod(slow_solve))
    monkeypatch.setattr(rerender.Rerenderer, "_render_strips", slow_render)
    monkeypatch.setattr(loopclosure.KeyframeGraph, "measure_loops", slow_measure)
    slow, slow_rows, slow_map = run("slow")
    assert quick["loop_closure"]["corrections"] >= 1 and quick["painting"]["rerendered_tiles"] > 0
    assert quick["loop_closure"]["loop_edges"] >= 1 and slow["loop_closure"] == quick["loop_closure"]
    assert slow_rows == quick_rows
    assert np.array_equal(slow_map, quick_map)


def procedural_terrain_sand():
    from photomap.sim.terrain import procedural_terrain

    return procedural_terrain("sand", (2048, 2048), seed=5)


def test_a_doubled_factor_shrinks_the_thumbnails_in_the_background(tmp_path):
    """When the thumbnails outgrow their budget the factor doubles; the worker shrinks none of
    them (100 ms for a long flight's map): the next preview's background task does, and the
    preview shows the map as one made at the new factor from the start."""
    from photomap.mapping.overview import Overview

    m = flight_map(tile_size=64)
    ov = Overview(64)  # 32 px thumbnails
    ov.mark(m.tiles())
    ov.update(m)
    n = len(m.tiles())
    ov.max_pixels = n * 16 * 16  # over budget at 32 px: 16 px
    tasks, path = [], tmp_path / "preview.png"
    assert ov.write(path, m, 300, later=tasks.append)
    assert ov.factor == 4 and {t.shape[0] for t in ov._thumbs.values()} == {32}  # the worker shrank none
    tasks.pop()()  # the background thread
    ov.update(m)  # the worker's next call keeps what the background made
    assert {t.shape[0] for t in ov._thumbs.values()} == {16} and len(ov._thumbs) == n
    direct = Overview(64, factor=4)
    direct.mark(m.tiles())
    direct.update(m)
    preview, want = cv2.imread(str(path), cv2.IMREAD_UNCHANGED), direct.render(300)
    assert preview.shape == want.shape
    covered = (preview[..., 3] == 255) & (want[..., 3] == 255)
    assert covered.mean() > 0.2
    assert np.abs(preview.astype(int) - want.astype(int))[covered].max() <= 2  # a shrink of a shrink rounds twice


def test_a_replay_does_not_wait_for_kept_images_being_written(tmp_path):
    """A kept image being written (a JPEG encode: 50 ms for a 2400x1800 still) is no re-render
    job: the thread is not ``busy`` and a replay's worker goes on at a due frame; a correction
    then re-renders from that image once it is written."""
    params = MosaicConfig(tile_size=64)
    store = KeyframeStore(tmp_path / "kf")
    started, gate = threading.Event(), threading.Event()
    put = store.put_image

    def held_put(*args, **kwargs):
        started.set()
        gate.wait(30)
        return put(*args, **kwargs)

    store.put_image = held_put
    painter = Painter((160, 120), 64, rerenderer=Rerenderer(store, params), interval_s=0.0, lockstep_frames=2)
    live = TiledMosaic(params)
    image = texture(120, 160, 5)
    painter.paint(live, 0, 0, image, pose(0, 0, 0), whole=True)
    assert started.wait(30) and not painter.rerenderer.busy
    pump = threading.Thread(target=painter.pump, args=({0: live},), kwargs={"frame": 10})
    pump.start()
    pump.join(10)
    done = not pump.is_alive()
    gate.set()
    pump.join()
    assert done and painter.stats.max_wait_ms == 0.0  # it waited for no write
    painter.on_correction(0, {0: pose(0, 3, 2)})
    painter.finish({0: live})
    want = render_from_store(store, [KeptFrame(0, pose(0, 3, 2), (160, 120))], params)
    assert_same_tiles(live, want, want.tiles())
    painter.close()


def test_a_replay_records_how_long_the_worker_waited_for_the_rerender(tmp_path, monkeypatch):
    """In lockstep (a replay) a job that is due waits for the busy re-render thread, and the
    painter says how long (``max_wait_ms``); live it never waits."""
    render = Rerenderer._render_strips

    def slow_render(self, *args, **kwargs):
        time.sleep(0.3)
        return render(self, *args, **kwargs)

    monkeypatch.setattr(Rerenderer, "_render_strips", slow_render)
    params = MosaicConfig(tile_size=64)
    poses = {i: pose(4 * i, 60.0 * i, 10.0 * i) for i in range(4)}
    moved = {i: pose(4 * i, 60.0 * i + 3.0 * i, 10.0 * i) for i in range(4)}
    for lockstep in (2, None):
        painter = Painter((160, 120), 64, rerenderer=Rerenderer(KeyframeStore(tmp_path / f"kf{lockstep}"), params),
                          interval_s=0.0, lockstep_frames=lockstep)
        live = TiledMosaic(params)
        for i, p in poses.items():
            painter.paint(live, 0, i, texture(120, 160, 10 + i), p, whole=True)
        painter.rerenderer.wait()
        assert painter.on_correction(0, moved) == 3
        painter.pump({0: live}, frame=10)  # starts the job (0.3 s a strip)
        painter.pump({0: live}, frame=12)  # lockstep: the next job is due, so the worker waits
        assert painter.stats.rerender_jobs == 1
        if lockstep:
            assert painter.stats.max_wait_ms >= 100.0  # the strip's sleep, less the few ms since it began
        else:
            assert painter.stats.max_wait_ms == 0.0
        painter.close()
