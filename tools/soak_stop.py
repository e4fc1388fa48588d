"""Stop, interrupt and kill ``photomap replay`` at random moments; count hangs and bad outputs.

Each run is a subprocess ``photomap replay`` of a small simulated flight (the video, or its
frames as a stills folder), sent SIGINT, SIGTERM or SIGKILL at a random moment (seeded), or
run into a configuration error (``--set registration.band_high=0.9``). A run must exit within
``--timeout`` seconds of the signal (else it is a *hang*: killed and counted), and what it
leaves in its output folder must be sound:

* after SIGINT/SIGTERM: exit 0 (mapped), 1 (stopped before any frame was registered) or 130
  (interrupted before mapping started, no outputs); with outputs, ``run.json`` is complete,
  ``trajectory.csv`` has one row per frame index seen (``frames_in`` rows, no gap: the flight has
  no undecodable frame) and agrees with ``run.json``'s counts, ``mosaic.png`` decodes to the size
  that ``run.json`` states, and no preview or temporary file is left;
* after SIGKILL: every output file that exists is whole (JSON parses, the CSV reads back, PNGs
  end with their IEND chunk and decode); hidden ``.*.tmp`` files of an interrupted atomic write
  may remain (counted, never read);
* the error path: a non-zero exit with one ``error:`` line and no traceback.

A signal in the interpreter's first milliseconds can land while ``site`` runs a ``.pth`` line (the
editable install's finder): Python itself then prints that line's traceback between "Error
processing line" and "Remainder of file ignored" and goes on. That report is the interpreter's,
before any photomap code: it is set aside and the rest of stderr judged.

    python tools/soak_stop.py --runs 200 --jobs 2 --seed 1

Prints one line per problem and a summary (runs, hangs, bad outputs, exit codes, median seconds
from the signal to the exit). The test suite runs a few of these (tests/test_stop_soak.py).
"""

from __future__ import annotations

import argparse
import json
import random
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2

from photomap.errors import InputError
from photomap.io.trajectory_files import read_trajectory_csv
from photomap.sim.simulate import simulate_flight

#: Kinds of run: (what is replayed, what happens to it).
KINDS = ("video:SIGINT", "video:SIGTERM", "stills:SIGINT", "stills:SIGTERM", "video:SIGKILL",
         "stills:SIGKILL", "video:error", "video:error+SIGTERM")
_PNG_END = b"IEND\xaeB`\x82"
#: What ``site`` prints when a ``.pth`` line raises (Lib/site.py ``addpackage``).
_SITE_REPORT = re.compile(r"^Error processing line \d+ of .*?\.pth:\n.*?^Remainder of file ignored\n?",
                          re.MULTILINE | re.DOTALL)


@dataclass
class Material:
    """The simulated flight every run replays."""

    video: Path
    stills: Path
    frames: int


def make_material(folder: Path, *, frames: int = 60, size: tuple[int, int] = (320, 240),
                  seed: int = 3, codec: str = "mp4v") -> Material:
    """Simulate a small flight (video with ``codec``: mp4v, mjpg or ffv1; and stills) into ``folder``."""
    simulate_flight(folder, n_frames=frames, size=size, fps=15.0, seed=seed, save_frames=True,
                    video_codec=codec)
    video = next(p for p in folder.glob("video.*"))
    return Material(video, folder / "frames", frames)


@dataclass
class Result:
    kind: str
    delay: float
    rc: int | None = None
    hang: bool = False
    exit_s: float | None = None  # seconds from the signal to the exit
    problems: list[str] = field(default_factory=list)
    tmp_files: int = 0
    frames_in: int | None = None  # frames mapped before the stop (run.json), when readable


def command(material: Material, kind: str, out: Path) -> list[str]:
    """The ``photomap replay`` command line of one run."""
    what = material.video if kind.startswith("video") else material.stills
    args = [sys.executable, "-m", "photomap", "replay", str(what), "--out", str(out),
            "--no-progress", "-q", "--set", "output.checkpoint_interval=0.05"]
    if "error" in kind:
        args += ["--set", "registration.band_high=0.9"]
    return args


def run_once(material: Material, kind: str, out: Path, delay: float, *,
             timeout: float = 60.0) -> Result:
    """One run: start, wait until mapping starts (``out`` exists), ``delay`` s more, signal, check.

    A negative ``delay`` signals ``-delay`` s after the start instead (during start-up).
    """
    result = Result(kind, delay)
    proc = subprocess.Popen(command(material, kind, out), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    sig = {"SIGINT": signal.SIGINT, "SIGTERM": signal.SIGTERM, "SIGKILL": signal.SIGKILL}.get(
        kind.rsplit(":", 1)[-1].split("+")[-1])
    sent = time.monotonic()
    if sig is not None:
        start = time.monotonic()
        if delay >= 0:  # from the moment the pipeline exists (it creates out/)
            while not out.exists() and proc.poll() is None and time.monotonic() - start < timeout:
                time.sleep(0.01)
        time.sleep(abs(delay))
        if proc.poll() is None:
            proc.send_signal(sig)
        sent = time.monotonic()
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        result.hang = True
        result.problems.append(f"no exit within {timeout:g} s of the signal")
        return result
    result.exit_s = time.monotonic() - sent
    result.rc = proc.returncode
    result.problems += check_run(kind, proc.returncode, err, out, material)
    result.tmp_files = len(list(out.glob(".*.tmp"))) if out.exists() else 0
    try:
        result.frames_in = int(json.loads((out / "run.json").read_text())["frames_in"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return result


def check_run(kind: str, rc: int, err: str, out: Path, material: Material) -> list[str]:
    """What is wrong with one finished run (empty when nothing)."""
    problems = []
    err = _SITE_REPORT.sub("", err)
    # died of the signal itself: while Python started (before photomap's main(), no outputs) or
    # after main() returned (outputs complete); either is fine
    by_signal = rc in (-signal.SIGINT, -signal.SIGTERM) or (
        rc == 1 and err.rstrip().endswith("KeyboardInterrupt"))
    if by_signal and not kind.endswith("SIGKILL"):
        if not out.exists():
            return problems
        if "error" not in kind:
            return check_complete(out, material)
    if "Traceback" in err:
        problems.append("traceback on stderr: " + " | ".join(err.strip().splitlines()[-12:]))
    if "error" in kind:
        lines = [line for line in err.splitlines() if "error:" in line]
        if rc == 0 or (rc != 130 and len(lines) != 1):
            problems.append(f"error path: exit {rc}, error lines {lines}")
    if kind.endswith("SIGKILL"):
        if rc not in (-signal.SIGKILL, 0, 1):
            problems.append(f"exit {rc} after SIGKILL")
        return problems + check_whole(out)
    if "error" not in kind and rc not in (0, 1, 130):
        problems.append(f"exit {rc} after {kind}")
    if rc == 130 or "error" in kind:
        return problems + check_whole(out)  # whatever exists must be whole
    return problems + check_complete(out, material)


def check_whole(out: Path) -> list[str]:
    """Every output file in ``out`` is whole (temporary ``.*.tmp`` files are ignored)."""
    problems: list[str] = []
    if not out.exists():
        return problems
    for path in sorted(out.rglob("*")):
        if path.is_dir() or path.name.startswith("."):
            continue
        try:
            if path.suffix == ".json":
                json.loads(path.read_text())
            elif path.suffix == ".csv":
                read_trajectory_csv(path)
            elif path.suffix == ".png":
                data = path.read_bytes()
                if not data.endswith(_PNG_END) or cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is None:
                    problems.append(f"{path.name}: truncated PNG ({len(data)} bytes)")
            elif path.suffix == ".tum":
                for line in path.read_text().splitlines():
                    if line and not line.startswith("#") and len(line.split()) != 8:
                        problems.append(f"{path.name}: bad line {line!r}")
                        break
        except (ValueError, InputError, OSError) as exc:
            problems.append(f"{path.name}: unreadable: {exc}")
    return problems


def check_complete(out: Path, material: Material) -> list[str]:
    """The outputs of a run that stopped cleanly are complete and agree with each other."""
    problems = check_whole(out)
    if problems:
        return problems
    try:
        summary = json.loads((out / "run.json").read_text())
        # no frame seen (stopped at once): no frame size, no trajectory
        rows = (read_trajectory_csv(out / "trajectory.csv")
                if summary["frames_in"] or (out / "trajectory.csv").exists() else [])
    except (OSError, ValueError, KeyError, InputError) as exc:
        return [f"missing or unreadable output: {exc}"]
    if not summary.get("complete"):
        problems.append("run.json not complete")
    n = summary["frames_in"]
    if not 0 <= n <= material.frames:
        problems.append(f"frames_in {n} outside 0..{material.frames}")
    if [r.frame for r in rows] != list(range(len(rows))) or len(rows) != n:
        problems.append(f"trajectory.csv: {len(rows)} rows for {n} frames seen")
    glued = sum(r.status in ("registered", "reference") for r in rows)
    if glued != summary["registered"]:
        problems.append(f"trajectory.csv: {glued} glued rows, run.json says {summary['registered']}")
    if (out / "preview.png").exists():
        problems.append("preview.png left after the final write")
    if list(out.glob(".*.tmp")):
        problems.append("temporary files left after a clean exit")
    mosaics = summary.get("mosaics") or []
    if summary["registered"] > 0:
        if not mosaics:
            problems.append("frames registered but no mosaic in run.json")
        for info in mosaics:
            image = cv2.imread(str(out / info["file"]), cv2.IMREAD_UNCHANGED)
            if image is None or [image.shape[1], image.shape[0]] != info["size"] or image.shape[2] != 4:
                problems.append(f"{info['file']}: does not match run.json")
    return problems


def plan(runs: int, seed: int, kinds: tuple[str, ...] = KINDS, *,
         span: float = 1.5) -> list[tuple[str, float]]:
    """``runs`` (kind, delay) pairs: kinds in turn, delays random (seeded).

    Delays (s) after mapping starts are uniform in [0, span) (about as long as mapping the small
    flight lasts), a fifth of them negative: during start-up instead.
    """
    rng = random.Random(seed)
    out = []
    for i in range(runs):
        kind = kinds[i % len(kinds)]
        delay = rng.uniform(0.0, span)
        if "error" not in kind and rng.random() < 0.2:
            delay = -rng.uniform(0.0, span)
        out.append((kind, round(delay, 3)))
    return out


def soak(material: Material, work: Path, runs: int, seed: int, *, jobs: int = 2,
         timeout: float = 60.0, kinds: tuple[str, ...] = KINDS, span: float = 1.5) -> list[Result]:
    """Run ``runs`` signalled replays, ``jobs`` at a time; returns their results."""
    todo = plan(runs, seed, kinds, span=span)

    def one(i: int) -> Result:
        kind, delay = todo[i]
        out = work / f"run{i:04d}"
        result = run_once(material, kind, out, delay, timeout=timeout)
        if not result.problems:
            shutil.rmtree(out, ignore_errors=True)
        return result

    with ThreadPoolExecutor(max(1, jobs)) as pool:
        return list(pool.map(one, range(len(todo))))


def report(results: list[Result]) -> str:
    """One line per problem, then the summary."""
    lines = []
    for i, r in enumerate(results):
        for p in r.problems:
            lines.append(f"run {i} ({r.kind}, delay {r.delay:+.2f} s, exit {r.rc}): {p}")
    hangs = sum(r.hang for r in results)
    bad = sum(bool(r.problems) and not r.hang for r in results)
    signalled = [r for r in results if r.exit_s is not None and ("SIGINT" in r.kind or "SIGTERM" in r.kind)]
    exits = [r.exit_s for r in signalled]
    codes = Counter((r.kind, r.rc) for r in results)
    part = [r for r in results if "SIGKILL" not in r.kind and "error" not in r.kind]
    n_frames = max((r.frames_in or 0 for r in results), default=0)
    lines.append(f"runs {len(results)}, hangs {hangs}, bad outputs {bad}, "
                 f"temporary files left by SIGKILL {sum(r.tmp_files for r in results)}")
    if exits:
        slowest = max(signalled, key=lambda r: r.exit_s)
        lines.append(f"seconds from signal to exit: median {statistics.median(exits):.2f}, "
                     f"max {max(exits):.2f} ({slowest.kind}, delay {slowest.delay:+.2f} s)")
    if part:
        mid = sum(r.frames_in is not None and 0 < r.frames_in < n_frames for r in part)
        lines.append(f"SIGINT/SIGTERM runs stopped part-way through the flight (complete map of the "
                     f"frames so far): {mid} of {len(part)}")
    for (kind, rc), n in sorted(codes.items(), key=lambda kv: (kv[0][0], str(kv[0][1]))):
        lines.append(f"  {kind:22s} exit {rc}: {n}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--jobs", type=int, default=2, help="runs at a time")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--frames", type=int, default=60, help="frames of the simulated flight")
    parser.add_argument("--size", default="640x480", help="frame size of the simulated flight, WxH")
    parser.add_argument("--codec", default="mp4v", choices=("mp4v", "mjpg", "ffv1"),
                        help="video codec of the simulated flight")
    parser.add_argument("--span", type=float, default=1.5,
                        help="signals land up to this many seconds after mapping starts")
    parser.add_argument("--timeout", type=float, default=60.0,
                        help="seconds after the signal after which a run counts as hung")
    parser.add_argument("--kinds", default=",".join(KINDS), help=f"comma-separated, of {KINDS}")
    parser.add_argument("--work", metavar="DIR", help="keep material and failed runs here")
    args = parser.parse_args(argv)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="photomap-soak-"))
    work.mkdir(parents=True, exist_ok=True)
    w, h = (int(v) for v in args.size.lower().split("x"))
    material = make_material(work / "flight", frames=args.frames, size=(w, h), codec=args.codec)
    started = time.monotonic()
    results = soak(material, work, args.runs, args.seed, jobs=args.jobs, timeout=args.timeout,
                   kinds=tuple(args.kinds.split(",")), span=args.span)
    print(report(results))
    failed = any(r.problems for r in results)
    kept = f"; failed runs kept in {work}" if failed else f"; material kept in {work}" if args.work else ""
    print(f"wall time {time.monotonic() - started:.0f} s{kept}")
    if not args.work and not failed:
        shutil.rmtree(work, ignore_errors=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
