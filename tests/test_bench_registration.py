"""The registration benchmark's timing harness (tools/bench_registration.py): no timings asserted."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from tools.bench_registration import TerrainCache, busy_neighbour, time_ifmi


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


def test_time_ifmi_reports_medians_quiet_and_busy():
    t = time_ifmi((128, 128), 3, TerrainCache(), repeats=1)
    assert set(t.ms) == {"quiet", "busy"}
    for condition in t.ms:
        assert set(t.ms[condition]) == {"iFMI", "iFMI no refine"}
        assert all(v > 0 and math.isfinite(v) for v in t.ms[condition].values())
    assert t.samples == 2
    assert set(t.cpu) == {"quiet", "busy"}
    assert all(0 < v <= t.ms[c][m] + 0.1 for c in t.cpu for m, v in t.cpu[c].items())  # CPU <= wall
    assert t.ratio_busy("iFMI") == pytest.approx(t.ms["busy"]["iFMI"] / t.ms["quiet"]["iFMI"])
    assert t.ratio_refined("quiet") == pytest.approx(t.ms["quiet"]["iFMI"] / t.ms["quiet"]["iFMI no refine"])


def test_time_ifmi_interleaves_conditions_and_which_method_goes_first(monkeypatch):
    """Quiet and busy passes alternate (q b b q), and in each condition each method goes first
    in half of the passes: drift of the host's speed biases neither ratio."""
    import contextlib

    import tools.bench_registration as br

    events: list[tuple[str, str]] = []  # (condition, method) of each timed or warm-up prepare
    condition = ["quiet"]

    @contextlib.contextmanager
    def fake_neighbour(enabled: bool = True):
        condition[0] = "busy" if enabled else "quiet"
        yield None

    class Recording:
        def __init__(self, name: str) -> None:
            self.name = name

        def prepare(self, gray):
            events.append((condition[0], self.name))
            return gray

        def register(self, ref, new):
            return None, None

    monkeypatch.setattr(br, "busy_neighbour", fake_neighbour)
    monkeypatch.setattr(br, "ifmi_methods", lambda shape: [Recording("iFMI"), Recording("iFMI no refine")])
    t = time_ifmi((64, 64), 3, TerrainCache(), repeats=4)
    assert t.samples == 8
    # blocks: runs of one condition; in each, the warm-up (2 prepares per method), the first
    # frame (1 each), then the 2 timed pairs alternating between the methods
    blocks: list[list[tuple[str, str]]] = []
    for ev in events:
        if blocks and blocks[-1][0][0] == ev[0]:
            blocks[-1].append(ev)
        else:
            blocks.append([ev])
    assert [b[0][0] for b in blocks] == ["quiet", "busy", "quiet", "busy", "quiet"]  # q b|b q|q b|b q
    per_pass = 2 * 2 + 2 + 2 * 2
    assert [len(b) for b in blocks] == [per_pass, 2 * per_pass, 2 * per_pass, 2 * per_pass, per_pass]
    passes = [b[i:i + per_pass] for b in blocks for i in range(0, len(b), per_pass)]
    firsts = {"quiet": [], "busy": []}
    for p in passes:
        timed = p[-4:]
        assert timed[0][1] != timed[1][1] and timed[2][1] != timed[3][1]  # alternating pair by pair
        firsts[p[0][0]].append(timed[0][1])
    assert sorted(firsts["quiet"]) == sorted(firsts["busy"]) == ["iFMI", "iFMI", "iFMI no refine", "iFMI no refine"]
