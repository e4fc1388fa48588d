"""The registration benchmark's timing harness (tools/bench_registration.py): no timings asserted."""

from __future__ import annotations

import contextlib
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from tools.bench_registration import TerrainCache, busy_neighbour, keyframe_references, time_ifmi


def _cpu_ticks(pid: int) -> int:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])  # utime + stime


@pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="needs /proc")
def test_busy_neighbour_spins_only_inside_the_block():
    with busy_neighbour() as proc:
        assert proc.poll() is None
        assert _cpu_ticks(proc.pid) > 0  # it has been spinning since it started
    assert proc.poll() is not None


def test_busy_neighbour_is_stopped_when_the_block_fails():
    with pytest.raises(RuntimeError):
        with busy_neighbour() as proc:
            raise RuntimeError("boom")
    assert proc.poll() is not None


def test_quiet_block_starts_nothing():
    with busy_neighbour(False) as proc:
        assert proc is None


def test_time_ifmi_reports_medians_in_each_condition():
    t = time_ifmi((128, 128), 3, TerrainCache(), repeats=1)
    assert set(t.ms) == {"quiet", "busy", "keyframes"}
    for condition in t.ms:
        assert set(t.ms[condition]) == {"iFMI", "iFMI no refine", "host reference"}
        assert all(v > 0 and math.isfinite(v) for v in t.ms[condition].values())
    assert t.samples == 2
    assert set(t.cpu) == set(t.ms)
    assert all(0 < v <= t.ms[c][m] + 0.1 for c in t.cpu for m, v in t.cpu[c].items())  # CPU <= wall
    assert t.ratio_busy("iFMI") == pytest.approx(t.ms["busy"]["iFMI"] / t.ms["quiet"]["iFMI"])
    assert t.ratio_refined("quiet") == pytest.approx(t.ms["quiet"]["iFMI"] / t.ms["quiet"]["iFMI no refine"])


def _straight_flight(n: int, step_px: float, shape=(64, 64)):
    """A flight of n frames moving ``step_px`` frame pixels per frame along x (terrain scale 2);
    frame i is filled with the value i."""
    i = np.arange(n, dtype=float)
    truth = SimpleNamespace(x=2.0 * step_px * i, y=np.zeros(n), scale=np.full(n, 2.0))
    grays = [np.full(shape, k, np.uint8) for k in range(n)]
    return SimpleNamespace(spec=SimpleNamespace(shape=shape), grays=grays, truth=truth)


def test_keyframe_references_hold_a_keyframe_as_the_tracker_does():
    # 64 px frames, 10 px per frame, max shift 0.5: frame 3 is 30 px away, and one more step
    # makes 40 > 32, so it becomes the keyframe of frames 4-6, and so on
    refs = keyframe_references(_straight_flight(11, 10.0), max_shift=0.5)
    assert refs == [0, 0, 0, 3, 3, 3, 6, 6, 6, 9]
    assert keyframe_references(_straight_flight(5, 40.0), max_shift=0.5) == [0, 1, 2, 3]  # each frame
    assert keyframe_references(_straight_flight(5, 1.0), max_shift=0.5) == [0, 0, 0, 0]


def test_time_ifmi_interleaves_conditions_methods_and_registers_as_each_condition_says(monkeypatch):
    """Conditions alternate (q b k | k b q | ...), in each condition each method goes first in
    half of the passes, and each frame is registered against the previous one (quiet, busy) or
    against its keyframe (keyframes)."""
    import tools.bench_registration as br

    state = {"condition": None}
    calls: list[tuple[str, str, int, int]] = []  # (condition, method, reference, new frame)

    @contextlib.contextmanager
    def fake_neighbour(enabled: bool = True):
        state["condition"] = "busy" if enabled else "quiet/keyframes"
        yield None

    class Recording:
        def __init__(self, name: str) -> None:
            self.name = name

        def prepare(self, gray):
            return int(gray[0, 0])

        def register(self, ref, new):
            calls.append((state["condition"], self.name, ref, new))
            return None, None

    flight = _straight_flight(11, 10.0)
    monkeypatch.setattr(br, "busy_neighbour", fake_neighbour)
    monkeypatch.setattr(br, "make_flight", lambda spec, n, terrains, seed: flight)
    monkeypatch.setattr(br, "ifmi_methods", lambda shape: [Recording("iFMI"), Recording("iFMI no refine")])
    t = time_ifmi((64, 64), 11, TerrainCache(), repeats=4)
    assert t.samples == 40
    per_block = 2 + 2 * 10  # a warm-up pair per method, then 10 pairs per method
    blocks = [calls[i:i + per_block] for i in range(0, len(calls), per_block)]
    assert len(blocks) == 4 * 3
    sequence, keyframes = list(range(10)), [0, 0, 0, 3, 3, 3, 6, 6, 6, 9]
    kinds, firsts = [], {}
    for block in blocks:
        warm, timed = block[:2], block[2:]
        assert all(c[2:] == (0, 1) for c in warm)
        assert [c[3] for c in timed] == [i for i in range(1, 11) for _ in range(2)]
        assert all(timed[j][1] != timed[j + 1][1] for j in range(0, 20, 2))  # alternating pair by pair
        refs = [c[2] for c in timed[::2]]
        assert refs in (sequence, keyframes)
        kind = "busy" if block[0][0] == "busy" else ("keyframes" if refs == keyframes else "quiet")
        kinds.append(kind)
        firsts.setdefault(kind, []).append(timed[0][1])
    assert kinds == ["quiet", "busy", "keyframes", "keyframes", "busy", "quiet"] * 2
    for kind in ("quiet", "busy", "keyframes"):
        assert sorted(firsts[kind]) == ["iFMI", "iFMI", "iFMI no refine", "iFMI no refine"]
