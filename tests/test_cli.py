"""The command line as a user runs it: end to end, signals, errors."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from photomap.cli.main import main
from photomap.sim.simulate import simulate_flight


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    out = tmp_path_factory.mktemp("flight")
    simulate_flight(out, n_frames=90, size=(320, 240), fps=15.0, seed=6)
    return out


def photomap(*args: str) -> list[str]:
    return [sys.executable, "-m", "photomap", *args]


def test_simulate_replay_evaluate(flight, tmp_path):
    run = tmp_path / "run"
    assert main(["replay", str(flight / "video.mp4"), "--out", str(run), "--no-progress", "-q"]) == 0
    assert main(["evaluate", str(run), "--truth", str(flight / "groundtruth.csv"), "-q"]) == 0
    result = json.loads((run / "evaluation.json").read_text())
    assert result["headline"]["position_px"]["drift_pct"] < 0.5
    assert (run / "evaluation_poses.png").is_file()


def test_sigint_writes_the_map_and_exits_0(flight, tmp_path):
    run = tmp_path / "run"
    env = dict(os.environ)
    proc = subprocess.Popen(photomap("replay", str(flight / "video.mp4"), "--out", str(run), "--realtime",
                                     "--no-progress", "--set", "output.checkpoint_interval=0.5"),
                            env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 30
    while not (run / "run.json").exists() and time.monotonic() < deadline:
        time.sleep(0.1)  # the first checkpoint is written once mapping runs
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    summary = json.loads((run / "run.json").read_text())
    assert summary["complete"] and 0 < summary["frames_in"] < 90
    assert (run / "mosaic.png").is_file()
    assert "Traceback" not in err


@pytest.mark.parametrize("argv", [["--version"], ["simulate", "--frames", "3", "--out", "SIM", "-q"]])
def test_a_signal_after_the_command_ends_the_process_without_a_traceback(tmp_path, argv):
    """A Ctrl-C that lands after the command is done (while the interpreter shuts down: atexit
    hooks, thread joins) ends the process by the signal, with no KeyboardInterrupt traceback."""
    argv = [str(tmp_path / "sim") if a == "SIM" else a for a in argv]
    code = ("import os, signal, sys, time\n"
            f"sys.argv = ['photomap', *{argv!r}]\n"
            "from photomap.cli.main import main\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n"
            "os.kill(os.getpid(), signal.SIGINT)\n"
            "time.sleep(5)\n"
            "print('still running')\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGINT, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr and "still running" not in proc.stdout


@pytest.mark.parametrize("args, code, words", [
    (["replay", "/no/such/video.mp4", "--out", "OUT"], 3, "not found"),
    (["replay", "VIDEO", "--out", "OUT", "--set", "mapping.no_such_key=1"], 2, "mapping.no_such_key"),
    (["replay", "VIDEO", "--out", "OUT", "--set", "mapping.min_confidence=high"], 2, "must be a number"),
    (["replay", "VIDEO", "--out", "OUT", "--mavlink", "/no/such.tlog"], 3, "not found"),
    (["run", "--camera", "/dev/video97", "--out", "OUT"], 3, "camera"),
])
def test_bad_input_is_one_clear_line(flight, tmp_path, capsys, args, code, words):
    args = [a.replace("VIDEO", str(flight / "video.mp4")).replace("OUT", str(tmp_path / "o")) for a in args]
    assert main(args + ["-q"]) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0] and "Traceback" not in err[0]
