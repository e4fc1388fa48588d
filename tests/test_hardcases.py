"""The hard cases of real flights, end to end on small simulated flights with exact truth: each
maps into one piece, no worse than ATE 0.5 % of the path (issue 10; the full-size cases are
``tools/bench_hardcases.py``)."""

from __future__ import annotations

import json

import pytest

from photomap.cli.main import main as photomap
from photomap.io.trajectory_files import read_trajectory_csv


def mapped(tmp_path, flags: list[str], replay: list[str] = ()) -> tuple[dict, dict, list]:
    sim, run = tmp_path / "sim", tmp_path / "run"
    assert photomap(["simulate", "--out", str(sim), *flags, "-q"]) == 0
    stills = "stills" in flags
    source = sim / "stills" if stills else next(p for p in sim.iterdir() if p.stem == "video")
    photomap(["replay", str(source), "--out", str(run), "--no-progress", "-q", *replay])
    assert photomap(["evaluate", str(run), "--truth", str(sim / "groundtruth.csv"), "-q"]) == 0
    return (json.loads((run / "run.json").read_text()), json.loads((run / "evaluation.json").read_text()),
            read_trajectory_csv(run / "trajectory.csv"))


def test_a_floor_of_identical_tiles_is_not_mapped_a_period_off(tmp_path):
    summary, result, _ = mapped(tmp_path, ["--terrain", "tiles", "--terrain-variation", "0", "--terrain-stain", "0",
                                           "--frames", "120", "--size", "320x240", "--seed", "1"])
    assert summary["segments"] == 1 and summary["registered"] == summary["frames_in"]
    assert result["headline"]["ate"]["pct"] < 0.5
    assert result["headline"]["pairs"]["success_rate"] > 0.99  # no step one tile off


def test_objects_above_the_ground_do_not_pull_the_map(tmp_path):
    summary, result, _ = mapped(tmp_path, ["--terrain", "aukerman", "--objects", "0.12", "--object-height", "8",
                                           "--altitude", "35:45", "--frames", "150", "--size", "480x360",
                                           "--seed", "1"])
    assert summary["segments"] == 1
    assert result["headline"]["ate"]["pct"] < 0.5


@pytest.mark.parametrize("yaw", ["flip", "hold"])
def test_stills_with_180_degree_turns_make_one_map(tmp_path, yaw):
    """A lawn-mower survey of stills, 65 % forward overlap, 180-degree turns between strips
    (``hold``: the picture keeps its heading while the telemetry yaw flips)."""
    summary, result, rows = mapped(
        tmp_path, ["--mode", "stills", "--terrain", "aukerman", "--altitude", "60:60", "--strips", "3",
                   "--stills-per-strip", "6", "--side-overlap", "0.4", "--size", "480x360",
                   "--stills-yaw", yaw, "--seed", "1"],
        ["--set", "camera.hfov_deg=60.0"])
    assert summary["segments"] == 1 and summary["registered"] == summary["frames_in"] == 18
    assert result["headline"]["ate"]["pct"] < 0.5
    assert {r.extra.get("method") for r in rows if r.status == "registered"} <= {"ifmi", "sift", "orb"}
