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
