"""Fleet benchmark: `photomap batch` against serial `photomap replay`, and `photomap merge` against truth.

Part (a): four small simulated flights (320x240, ``--frames`` each, with telemetry) are mapped
serially by :func:`photomap.cli.replay.replay` in this process (the baseline: no start-up cost
per flight), then by :func:`photomap.cli.batch.run_batch` on a LocalCluster of 1 and 2 worker
processes, and of 1 worker process with 2 threads (the processes-vs-threads measurement). Every
configuration runs ``--repeat`` times; the table shows the median wall time (from the call to the
last output, cluster start-up and shutdown included) and the speed-up over the serial median.
Every batch flight's ``trajectory.csv`` and ``mosaic.png`` are compared with the serial replay's.

Then the same as a user runs it, each command a fresh process: ``photomap replay`` per flight,
one after the other, against one ``photomap batch``.

Part (b): pairs of simulated flights over the bundled terrain (overlapping ones and one that does
not overlap) are mapped and merged by :func:`photomap.mapping.merge.merge_runs`, by the images
alone and with the georeference as a prior. The error is the distance, in merged-map pixels,
between where ``map_to_merged`` puts each frame centre of the second map and where the truth
does (both maps' pixels go to the terrain through their first frame's ground-truth matrix).

    python -m tools.bench_batch [--quick] [--frames N] [--repeat N] [--skip-merge] [--out FILE]

The full run replaces the section between ``<!-- batch:start -->`` and ``<!-- batch:end -->``
of ``docs/benchmarks.md``; ``--quick`` only prints. Needs the ``batch`` extra (Dask).
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from photomap.cli.batch import FlightSpec, run_batch  # noqa: E402
from photomap.cli.replay import replay  # noqa: E402
from photomap.config import load_config  # noqa: E402
from photomap.io.trajectory_files import read_groundtruth, read_trajectory_csv  # noqa: E402
from photomap.mapping.merge import merge_runs  # noqa: E402
from photomap.sim.simulate import simulate_flight  # noqa: E402
from tools.report import replace_section  # noqa: E402

log = logging.getLogger("bench_batch")
BATCH_SEEDS = (11, 12, 13, 14)
# (reference, moving, frames): 30/43 and 31/49 overlap; 41/42 (the pair) overlap at the
# end of 300 frames; 30/32 fly over different parts of the terrain
MERGE_PAIRS = ((30, 43, 90), (31, 49, 150), (41, 42, 300), (30, 32, 90))


def _same_outputs(a: Path, b: Path) -> tuple[bool, float, bool]:
    """(trajectories equal to 1e-6, max pose difference, mosaic.png pixels equal)."""
    ra, rb = read_trajectory_csv(a / "trajectory.csv"), read_trajectory_csv(b / "trajectory.csv")
    if len(ra) != len(rb) or any((x.M is None) != (y.M is None) for x, y in zip(ra, rb)):
        return False, float("inf"), False
    diff = max((float(np.abs(np.asarray(x.M) - np.asarray(y.M)).max()) for x, y in zip(ra, rb)
                if x.M is not None), default=0.0)
    ia = cv2.imread(str(a / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    ib = cv2.imread(str(b / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    return diff < 1e-6, diff, ia is not None and ib is not None and ia.shape == ib.shape and np.array_equal(ia, ib)


def batch_part(root: Path, frames: int, repeat: int, commands: bool = True) -> dict:
    cfg = load_config()
    flights = []
    for seed in BATCH_SEEDS:
        sim = simulate_flight(root / f"sim{seed}", n_frames=frames, size=(320, 240), fps=15.0, seed=seed)
        flights.append(FlightSpec(str(sim / "video.mp4"), f"flight{seed}", str(sim / "telemetry.tlog")))
    configs = [("serial replay, this process", None), ("batch, 1 worker process", (1, True)),
               ("batch, 2 worker processes", (2, True)), ("batch, 1 worker, 2 threads", (2, False))]
    times: dict[str, list[float]] = {name: [] for name, _ in configs}
    cpu: dict[str, list[float]] = {name: [] for name, _ in configs}
    same: dict[str, list] = {name: [] for name, _ in configs}
    for rep in range(repeat):
        for name, how in configs:
            out = root / f"rep{rep}-{len(times[name])}-{name.split(',')[0].replace(' ', '')}{id(how)}"
            t = time.perf_counter()
            c0 = _cpu_s()
            if how is None:
                for f in flights:
                    replay(f.input, out / f.name, cfg, mavlink=f.mavlink)
            elif how[1]:
                run_batch(flights, out, cfg, workers=how[0], processes=True, echo=None)
                _stop_fork_server()
            else:  # one worker process... as threads of this process: LocalCluster(processes=False)
                run_batch_threads(flights, out, cfg, threads=how[0])
            times[name].append(time.perf_counter() - t)
            cpu[name].append(_cpu_s() - c0)
            log.info("%s: %.1f s (CPU %.1f s)", name, times[name][-1], cpu[name][-1])
            if how is not None:
                serial = next(p for p in root.iterdir() if p.name.startswith(f"rep{rep}-") and "serial" in p.name)
                same[name].append([_same_outputs(out / f.name, serial / f.name) for f in flights])
    base = statistics.median(times[configs[0][0]])
    rows = []
    for name, _ in configs:
        med = statistics.median(times[name])
        checks = [c for rep in same[name] for c in rep]
        rows.append({"name": name, "median_s": med, "all_s": times[name], "speedup": base / med,
                     "cpu_s": statistics.median(cpu[name]),
                     "cores_used": statistics.median(c / w for c, w in zip(cpu[name], times[name])),
                     "trajectories_equal": all(c[0] for c in checks) if checks else None,
                     "max_pose_diff": max((c[1] for c in checks), default=None),
                     "mosaics_equal": all(c[2] for c in checks) if checks else None})
    cmds = commands_part(root, flights, repeat) if commands else None
    return {"frames": frames, "flights": len(flights), "repeat": repeat, "rows": rows, "commands": cmds}


def commands_part(root: Path, flights: list, repeat: int, workers: int = 2) -> dict:
    """Wall time of the commands a user runs, each a fresh process (imports included): ``photomap
    replay`` of one flight after the other, against one ``photomap batch`` of them all."""
    py = [sys.executable, "-m", "photomap"]

    def run(cmd: list[str]) -> None:
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=root)
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd[2:4])} failed:\n{proc.stderr[-2000:]}")

    serial, batch = [], []
    for rep in range(repeat):
        t = time.perf_counter()
        for f in flights:
            run(py + ["replay", f.input, "--out", str(root / f"cmd{rep}" / f.name), "--mavlink", f.mavlink,
                      "--no-progress", "-q"])
        serial.append(time.perf_counter() - t)
        t = time.perf_counter()
        run(py + ["batch", *[f.input for f in flights], "--out", str(root / f"cmdbatch{rep}"),
                  "--workers", str(workers), "--no-progress", "-q"])
        batch.append(time.perf_counter() - t)
        log.info("commands: replay one after the other %.1f s, batch %.1f s", serial[-1], batch[-1])
    return {"serial_s": serial, "batch_s": batch, "workers": workers}


def _stop_fork_server() -> None:
    """End the fork server the batch's worker processes came from (Python's, private API): the
    next batch starts its own, as a fresh `photomap batch` does, and the workers' CPU time (its
    children) comes back to this process's children's rusage."""
    import multiprocessing.forkserver as fs

    stop = getattr(getattr(fs, "_forkserver", None), "_stop", None)
    if stop is not None:
        stop()


def _cpu_s() -> float:
    """CPU seconds of this process and its finished children (the local workers, once closed)."""
    import resource

    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def run_batch_threads(flights, out: Path, cfg, threads: int) -> dict:
    """run_batch on one worker with ``threads`` threads in this process (Dask's processes=False)."""
    from photomap.cli.batch import local_cluster

    cluster = local_cluster(1, processes=False, threads_per_worker=threads)
    try:
        return run_batch(flights, out, cfg, scheduler=cluster.scheduler_address, echo=None)
    finally:
        cluster.close()


def merge_part(root: Path) -> list[dict]:
    cfg = load_config()
    runs: dict[tuple[int, int], tuple[Path, Path]] = {}
    out = []
    for ref, mov, frames in MERGE_PAIRS:
        for seed in (ref, mov):
            if (seed, frames) not in runs:
                sim = simulate_flight(root / f"m{seed}-{frames}", n_frames=frames, size=(320, 240), fps=15.0,
                                      seed=seed)
                run = root / f"r{seed}-{frames}"
                replay(str(sim / "video.mp4"), run, cfg, mavlink=str(sim / "telemetry.tlog"))
                runs[(seed, frames)] = (run, sim)
        for georef in (False, True):
            t = time.perf_counter()
            dest = root / f"merge{ref}-{mov}-{int(georef)}"
            summary = merge_runs([runs[(ref, frames)][0], runs[(mov, frames)][0]], dest, cfg,
                                 use_georeference=georef)
            wall = time.perf_counter() - t
            e = summary["runs"][1]
            truth = np.linalg.inv(_map_to_terrain(*runs[(ref, frames)])) @ _map_to_terrain(*runs[(mov, frames)])
            rows = [r for r in read_trajectory_csv(runs[(mov, frames)][0] / "trajectory.csv") if r.M is not None]
            c = np.array([np.asarray(r.M) @ [159.5, 119.5, 1.0] for r in rows])
            c = np.c_[c, np.ones(len(c))].T
            overlap = _true_overlap(runs[(ref, frames)][0], runs[(mov, frames)][0], truth)
            row = {"pair": f"{ref} + {mov}", "frames": frames, "prior": "georeference" if georef else "none",
                   "true_overlap": overlap, "placed": e["placed"], "confidence": e["confidence"],
                   "reason": e.get("reason"), "wall_s": wall,
                   "windows": e["levels"][-1]["inliers"] if e.get("levels") else 0}
            if e["placed"]:
                err = np.hypot(*((np.array(e["map_to_merged"]) @ c)[:2] - (truth @ c)[:2]))
                row.update({"median_px": float(np.median(err)), "max_px": float(err.max())})
            out.append(row)
            log.info("merge %s (%s): %s", row["pair"], row["prior"], row)
    return out


def _map_to_terrain(run: Path, sim: Path) -> np.ndarray:
    row = next(r for r in read_trajectory_csv(run / "trajectory.csv") if r.M is not None)
    truth = read_groundtruth(sim / "groundtruth.csv")
    return truth.H[row.frame] @ np.linalg.inv(np.vstack([np.asarray(row.M, float), [0, 0, 1]]))


def _true_overlap(ref_run: Path, mov_run: Path, truth: np.ndarray) -> float:
    """Fraction of the smaller map covered by both, through the true transform."""
    ref = cv2.imread(str(ref_run / "mosaic.png"), cv2.IMREAD_UNCHANGED)[..., 3] == 255
    mov = cv2.imread(str(mov_run / "mosaic.png"), cv2.IMREAD_UNCHANGED)[..., 3] == 255
    ro = json.loads((ref_run / "run.json").read_text())["mosaics"][0]["origin_xy"]
    mo = json.loads((mov_run / "run.json").read_text())["mosaics"][0]["origin_xy"]
    A = np.array([[1, 0, -ro[0]], [0, 1, -ro[1]], [0, 0, 1.0]]) @ truth @ np.array(
        [[1, 0, mo[0]], [0, 1, mo[1]], [0, 0, 1.0]])
    warped = cv2.warpAffine(mov.astype(np.uint8), A[:2], (ref.shape[1], ref.shape[0]), flags=cv2.INTER_NEAREST)
    return float((ref & (warped > 0)).sum()) / max(min(ref.sum(), mov.sum() * abs(np.linalg.det(A[:2, :2]))), 1)


def report(args, b: dict, m: list[dict], elapsed: float, load: tuple[float, float]) -> str:
    when = datetime.date.today().isoformat()
    shared = (": **the machine was shared with other jobs**, so times and speed-ups are what this busy machine "
              "gave, not what an idle one gives" if load[0] > 1.0 else ": a quiet machine when it started")
    lines = ["## Batch and merge", "",
             f"Written by `python -m tools.bench_batch{' --quick' if args.quick else ''}` on {when} (Python "
             f"{platform.python_version()}, {os.cpu_count()} cores, {elapsed:.0f} s; 1-minute load average "
             f"{load[0]:.1f} at the start and {load[1]:.1f} at the end{shared}).", "",
             f"### photomap batch: {b['flights']} flights of {b['frames']} frames (320x240, with telemetry)", "",
             f"Median of {b['repeat']} runs each, wall time from the call to the last output (the batch's "
             "cluster start-up and shutdown included). Serial: `replay` of one flight after the other in one "
             "process (no start-up per flight: the strictest baseline). Outputs: every batch flight's "
             "trajectory.csv and mosaic.png against the serial replay's.", "",
             "*CPU s*: user + system time of this process and its workers; *cores used*: CPU s over wall s "
             "(2 would be both cores to ourselves: below it, other jobs had them).", "",
             "| configuration | median s | runs s | speed-up over serial | CPU s | cores used | trajectories equal "
             "(max pose diff) | mosaic.png pixels equal |", "|---|---|---|---|---|---|---|---|"]
    for r in b["rows"]:
        eq = "-" if r["trajectories_equal"] is None else (
            f"{'yes' if r['trajectories_equal'] else '**no**'} ({r['max_pose_diff']:.1g})")
        mo = "-" if r["mosaics_equal"] is None else ("yes" if r["mosaics_equal"] else "**no**")
        lines.append(f"| {r['name']} | {r['median_s']:.1f} | {', '.join(f'{v:.1f}' for v in r['all_s'])} | "
                     f"{r['speedup']:.2f}x | {r['cpu_s']:.1f} | {r['cores_used']:.2f} | {eq} | {mo} |")
    c = b.get("commands")
    if c:
        ser, bat = statistics.median(c["serial_s"]), statistics.median(c["batch_s"])
        lines += ["", "As a user runs them, each command a fresh process (Python, NumPy, OpenCV and photomap "
                  f"imported by each): `photomap replay` of one flight after the other against one `photomap "
                  f"batch ... --workers {c['workers']}` (median of {len(c['serial_s'])}):", "",
                  "| commands | median s | runs s | speed-up |", "|---|---|---|---|",
                  f"| {b['flights']} x `photomap replay`, one after the other | {ser:.1f} | "
                  f"{', '.join(f'{v:.1f}' for v in c['serial_s'])} | 1.00x |",
                  f"| `photomap batch`, {c['workers']} workers | {bat:.1f} | "
                  f"{', '.join(f'{v:.1f}' for v in c['batch_s'])} | {ser / bat:.2f}x |"]
    lines += ["", "### photomap merge against the simulator's truth", "",
              "Error: distance (merged-map px) between where `map_to_merged` puts each frame centre of the "
              "second map and where the truth does. *True overlap*: the part of the smaller map that the "
              "other covers, through the true transform.", "",
              "| pair (seeds) | frames | prior | true overlap | placed | confidence | windows | median px | "
              "max px | s |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in m:
        placed = "yes" if r["placed"] else f"no: {r['reason']}"
        med = f"{r['median_px']:.2f}" if "median_px" in r else "-"
        mx = f"{r['max_px']:.2f}" if "max_px" in r else "-"
        lines.append(f"| {r['pair']} | {r['frames']} | {r['prior']} | {r['true_overlap']:.0%} | {placed} | "
                     f"{r['confidence']:.2f} | {r['windows']} | {med} | {mx} | {r['wall_s']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small and once (prints only)")
    ap.add_argument("--frames", type=int, default=None, help="frames per batch flight (default 1000)")
    ap.add_argument("--repeat", type=int, default=None, help="runs per configuration (default 3)")
    ap.add_argument("--skip-merge", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    logging.getLogger("photomap").setLevel(logging.WARNING)
    args.frames = args.frames or (120 if args.quick else 1000)
    args.repeat = args.repeat or (1 if args.quick else 3)
    out_md = args.out if args.out is not None else (None if args.quick else REPO / "docs" / "benchmarks.md")
    start, load0 = time.perf_counter(), os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-batch-") as tmp:
        root = Path(tmp)
        b = batch_part(root / "batch", args.frames, args.repeat)
        m = [] if args.skip_merge else merge_part(root / "merge")
    body = report(args, b, m, time.perf_counter() - start, (load0, os.getloadavg()[0]))
    print(body)
    if out_md is not None:
        replace_section(out_md, "batch", body)
        log.info("wrote the batch section of %s", out_md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
