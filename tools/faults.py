"""The fault-injection suite, long version: ``tests/test_faults.py`` with ``PHOTOMAP_FAULTS=long``
(ten SIGKILLs at random moments instead of two, both video codecs corrupted, 2000 black frames,
the shuffled flight twice over), and its summary table written into ``docs/faults.md``.

    python tools/faults.py [--quick] [--out docs/faults.md]

``--quick`` runs the suite as CI does (about two minutes on 2 cores). The table lists each fault,
how it is injected, what must hold (what the test asserts on the files left behind) and the
result; the rest of ``docs/faults.md`` is left alone.
"""

from __future__ import annotations

import argparse
import datetime
import os
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tools.report import replace_section  # noqa: E402

# test function -> (fault, how it is injected, what must hold)
FAULTS = {
    "test_checkpoint_survives_a_kill_at_every_write": (
        "kill during a checkpoint", "the k-th file operation of a checkpoint raises, for every k",
        "the previous manifest and every tile it names are intact and equal the map then; no file is left over"),
    "test_sigkill_leaves_a_map_that_recover_rebuilds": (
        "SIGKILL", "`photomap replay` killed at a random moment after its first checkpoint (0.05 s interval)",
        "`photomap recover` rebuilds mosaic.png; it matches the complete run's map (NCC > 0.8 where both are "
        "covered); trajectory.csv evaluates against the truth"),
    "test_interrupt_writes_the_map_and_removes_the_checkpoint": (
        "SIGINT / SIGTERM", "signal to a `--realtime` replay after its first checkpoint",
        "exit 0, run.json complete, mosaic.png, one trajectory row per frame, checkpoint/ and preview.png removed"),
    "test_disk_full_keeps_the_map_in_the_checkpoint": (
        "disk full (write hook)", "every atomic write raises ENOSPC after 1.5 MB",
        "mapping goes on to the last frame; each failing output is named in write_errors; the checkpoint keeps "
        "the map and `recover` writes it once there is room"),
    "test_disk_full_on_a_small_tmpfs": (
        "disk full (1 MB tmpfs)", "`--out` on a 1 MB tmpfs",
        "exit 4, one line per failing output, no traceback; the map is either in mosaic.png or recoverable"),
    "test_out_is_a_file": ("`--out` is a file", "an existing file as `--out`",
                           "exit 4, one line, the file untouched"),
    "test_read_only_out_is_refused_before_any_frame": (
        "read-only `--out`", "a read-only tmpfs", "exit 4, one line, before any frame is mapped"),
    "test_unrecovered_checkpoint_is_not_overwritten": (
        "unrecovered checkpoint in `--out`", "a manifest left by a killed run",
        "exit 4 naming `photomap recover`, the checkpoint untouched"),
    "test_corrupt_video": (
        "corrupt video", "800 bytes flipped in two places in the middle of the MJPG (and MPEG-4) file",
        "no traceback; trajectory.csv and run.json count every status alike; `photomap evaluate` reads it"),
    "test_shuffled_frames_are_not_glued": (
        "shuffled frames", "the flight's frames in a random order",
        "every frame glued into a segment lies where the truth puts it relative to the segment's first frame "
        "(< 10 % of the frame width)"),
    "test_black_video_keeps_memory_bounded": (
        "black video", "all-black 320x240 frames",
        "one-frame segments dropped (frames low_confidence), at most 2 maps in memory at any time, counts agree"),
    "test_garbage_mavlink_log": (
        "garbage MAVLink", "1-32 random bytes spliced in every 50-400 bytes of the .tlog",
        "exit 0, a map, counts agree"),
    "test_silent_link": ("silent MAVLink link", "`udpin:` port where nobody sends (`--realtime`)",
                         "exit 0, vision-only map, no georeference, telemetry status says why"),
    "test_dropped_frames_counted_alike": (
        "live source dropping frames", "gaps in a live source's indices, two frames dropped after the last one",
        "trajectory.csv has a `dropped` row for each, run.json counts the same"),
    "test_bad_config_values_are_one_line": (
        "bad config values", "`--set` with a wrong type, out-of-range values, an unknown key",
        "exit 2, exactly one line on stderr, nothing created"),
    "test_bad_config_file_is_one_line": ("bad config file", "a YAML file that does not parse",
                                         "exit 2, one line"),
}


def run_suite(long: bool) -> list[dict]:
    with tempfile.TemporaryDirectory() as tmp:
        xml = Path(tmp) / "faults.xml"
        env = dict(os.environ, PHOTOMAP_FAULTS="long" if long else "")
        subprocess.run([sys.executable, "-m", "pytest", "tests/test_faults.py", "-q", "-p", "no:cacheprovider",
                        f"--junitxml={xml}"], cwd=REPO, env=env)
        root = ET.parse(xml).getroot()
    results = []
    for case in root.iter("testcase"):
        name = case.get("name", "")
        outcome = "passed"
        for tag in ("failure", "error", "skipped"):
            node = case.find(tag)
            if node is not None:
                outcome = {"failure": "failed", "error": "error", "skipped": "skipped"}[tag]
                outcome += f": {(node.get('message') or '').splitlines()[0][:120]}" if node.get("message") else ""
        results.append({"name": name, "function": name.split("[")[0], "outcome": outcome,
                        "seconds": float(case.get("time", 0))})
    return results


def table(results: list[dict]) -> list[str]:
    grouped: dict[str, list[dict]] = {}
    for r in results:
        grouped.setdefault(r["function"], []).append(r)
    lines = ["| fault | injected | what must hold (asserted on the files left behind) | result | time |",
             "|---|---|---|---|---|"]
    for function, runs in grouped.items():
        fault, how, must = FAULTS.get(function, (function, "", ""))
        passed = sum(r["outcome"] == "passed" for r in runs)
        others = sorted({r["outcome"] for r in runs if r["outcome"] != "passed"})
        result = f"{passed}/{len(runs)} passed" + (f" ({'; '.join(others)})" if others else "")
        lines.append(f"| {fault} | {how} | {must} | {result} | {sum(r['seconds'] for r in runs):.0f} s |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the CI version (PHOTOMAP_FAULTS unset)")
    ap.add_argument("--out", default=str(REPO / "docs" / "faults.md"), help="markdown file for the table")
    args = ap.parse_args(argv)
    results = run_suite(long=not args.quick)
    lines = table(results)
    print("\n".join(lines))
    total = sum(r["seconds"] for r in results)
    body = [f"`python tools/faults.py{' --quick' if args.quick else ''}` on {datetime.date.today()}: "
            f"{sum(r['outcome'] == 'passed' for r in results)}/{len(results)} cases passed in {total:.0f} s "
            f"(a busy 2-core machine).", "", *lines]
    replace_section(Path(args.out), "faults", "\n".join(body))
    return 0 if all(r["outcome"] in ("passed",) or r["outcome"].startswith("skipped") for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
