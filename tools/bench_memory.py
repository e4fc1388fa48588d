"""Memory of a run whatever the input: RSS per frame on a long normal flight, peak RSS on black video,
and what a checkpoint costs the worker.

Each case runs in a fresh interpreter (so one case's freed memory does not inflate the next one's
peak); a thread samples the process RSS (psutil) every 50 ms together with the frames done.

- ``flight``: the long lawn-mower flight of ``tools/bench_pipeline.py`` (640x480, rendered frame
  by frame: the source never holds more than one frame), mapped by :class:`MappingPipeline`.
- ``black``: all-black 640x480 frames (a lens cap, a dead camera): nothing registers.

Reported: RSS when 10 %, 50 % and 100 % of the frames were mapped (100 %: while the final
outputs are rendered), the growth per frame after 10 % (median RSS over the last 20 % of the
frames minus the median over 10-30 %, per frame between them, KB/frame), the peak, segments kept and dropped,
and the checkpoint's worker time (copying the changed tiles) and writer time (medians).

    python tools/bench_memory.py [--frames N] [--black N] [--interval S] [--out docs/benchmarks.md]

Targets (issue 11): a normal flight grows < 0.5 KB/frame after 10 %; 6000 black frames peak
below 400 MB, also with ``config/photomap-onboard.yaml``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterator

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from photomap.config import load_config  # noqa: E402
from photomap.drivers.frames import CaptureStats, Frame, SourceBase  # noqa: E402
from photomap.mapping.pipeline import MappingPipeline  # noqa: E402
from tools.bench_pipeline import MB, RssSampler, SimulatedSource  # noqa: E402

ONBOARD = REPO / "config" / "photomap-onboard.yaml"


class BlackSource(SourceBase):
    """``n`` all-black frames of ``size`` (w, h) at 30 fps (replay)."""

    live = False

    def __init__(self, n: int, size: tuple[int, int] = (640, 480)) -> None:
        self.stats, self.n, self.size, self._closed = CaptureStats(), n, size, False

    def __len__(self) -> int:
        return self.n

    def __iter__(self) -> Iterator[Frame]:
        for k in range(self.n):
            if self._closed:
                break
            self.stats.read += 1
            yield Frame(k, k / 30.0, np.zeros((self.size[1], self.size[0], 3), np.uint8), "black")

    def close(self) -> None:
        self._closed = True


def slope_kb_per_frame(samples: list[tuple[float, float, int]], n: int) -> float | None:
    """RSS growth per frame after 10 %: (median RSS over 80-100 % of the frames - median over
    10-30 %) / the frames between the windows' centres, KB. Medians, not a fit: RSS is a saw
    tooth between checkpoints (each gives freed heap back to the system)."""
    early = [rss for _, rss, done in samples if 0.1 * n <= done < 0.3 * n]
    late = [rss for _, rss, done in samples if 0.8 * n <= done < n]
    if len(early) < 3 or len(late) < 3:
        return None
    return float((np.median(late) - np.median(early)) * 1024.0 / (0.7 * n))


def run_case(case: str, n: int, config: str | None, overrides: list[str]) -> dict:
    """Map one case in this process while sampling RSS."""
    import psutil

    rss0 = psutil.Process().memory_info().rss / MB
    if case == "flight":
        source = SimulatedSource(n)
    else:
        source = BlackSource(n)
    cfg = load_config(config, overrides)
    with tempfile.TemporaryDirectory(prefix="bench-memory-") as tmp, RssSampler() as sampler:
        before = sampler.rss_mb()

        def on_frame(event) -> None:
            sampler.frames_done += 1

        pipe = MappingPipeline(source, cfg, tmp, sinks=[on_frame], input_name=case)
        t = time.perf_counter()
        summary = pipe.run()
        wall = time.perf_counter() - t
        disk = sum(f.stat().st_size for f in Path(tmp).rglob("*") if f.is_file())
    at = {f"rss_at_{p}_mb": next((rss for _, rss, done in sampler.samples if done >= n * p / 100), None)
          for p in (10, 50, 100)}
    ck = summary.get("checkpoint") or {}
    return {"case": case, "config": Path(config).name if config else "default", "overrides": overrides,
            "frames": summary["frames_in"], "registered": summary["registered"],
            "segments": summary["segments"], "segments_dropped": summary.get("segments_dropped", 0),
            "fps": summary["frames_in"] / wall, "rss_start_mb": rss0, "rss_before_mb": before,
            "peak_mb": max(rss for _, rss, _ in sampler.samples),
            "kb_per_frame": slope_kb_per_frame(sampler.samples, n), "outputs_mb": disk / 1e6,
            "checkpoints": ck.get("written", 0), "ck_worker_ms": ck.get("median_worker_ms"),
            "ck_write_ms": ck.get("median_write_ms"), "ck_bytes": ck.get("bytes_written", 0), **at}


def records_growth(n: int, config: str | None, overrides: list[str]) -> dict:
    """Python heap growth per frame from 20 % to the end of the flight that is *not* map tiles
    (tracemalloc; tiles are bounded by ``mosaic.max_tiles_in_memory``, records are not)."""
    import tracemalloc

    source = SimulatedSource(n)
    cfg = load_config(config, overrides)
    snaps = {}

    def on_frame(event) -> None:
        if event.index == n // 5:
            snaps["a"] = (event.index, tracemalloc.take_snapshot())
        elif event.index == n - 1:
            snaps["b"] = (event.index, tracemalloc.take_snapshot())

    tracemalloc.start(8)
    with tempfile.TemporaryDirectory(prefix="bench-memory-") as tmp:
        MappingPipeline(source, cfg, tmp, sinks=[on_frame], input_name="records").run()
    tracemalloc.stop()
    (ia, a), (ib, b) = snaps["a"], snaps["b"]
    tiles = grew = freed = in_flight = 0
    by_line: dict[str, int] = {}
    for stat in b.compare_to(a, "traceback"):
        files = [f.filename for f in stat.traceback]
        if any(f.endswith(("core/mosaic.py", "io/tilestore.py")) for f in files):
            tiles += stat.size_diff
        elif any(f.endswith("io/statestore.py") for f in files):
            in_flight += stat.size_diff  # tile copies of a checkpoint being written (<= its budget)
        elif not any(f.endswith(("sim/flight.py", "bench_pipeline.py")) for f in files):  # the source's frames
            if stat.size_diff > 0:
                grew += stat.size_diff
            else:
                freed -= stat.size_diff
            frame = next((f for f in reversed(stat.traceback) if "photomap" in f.filename or "/service/" in f.filename),
                         stat.traceback[-1])
            key = f"{Path(frame.filename).name}:{frame.lineno}"
            by_line[key] = by_line.get(key, 0) + stat.size_diff
    frames = ib - ia
    top = sorted(by_line.items(), key=lambda kv: -kv[1])[:6]
    return {"frames": frames, "tiles_kb_per_frame": tiles / 1024 / frames, "grew_kb_per_frame": grew / 1024 / frames,
            "freed_mb": freed / 2**20,
            "checkpoint_in_flight_mb": in_flight / 2**20,
            "top": [(k, round(v / 1024 / frames, 3)) for k, v in top]}


def run_subprocess(case: str, n: int, config: str | None, overrides: list[str]) -> dict:
    spec = json.dumps({"case": case, "n": n, "config": config, "overrides": overrides})
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--case", spec],
                          capture_output=True, text=True, cwd=REPO)
    if proc.returncode != 0:
        raise RuntimeError(f"{case} {config} {overrides} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def table(results: list[dict]) -> list[str]:
    lines = ["| case | config | frames | registered | segments (dropped) | fps | RSS before | RSS at 10/50/100 % | "
             "growth after 10 % | peak RSS | checkpoints | checkpoint: worker / writer (median) | disk |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        at = "/".join("-" if r[f"rss_at_{p}_mb"] is None else f"{r[f'rss_at_{p}_mb']:.0f}" for p in (10, 50, 100))
        slope = "-" if r["kb_per_frame"] is None else f"{r['kb_per_frame']:.2f} KB/frame"
        extra = f" {' '.join(r['overrides'])}" if r["overrides"] else ""
        lines.append(f"| {r['case']} | {r['config']}{extra} | {r['frames']} | {r['registered']} | "
                     f"{r['segments']} ({r['segments_dropped']}) | {r['fps']:.1f} | {r['rss_before_mb']:.0f} MB | "
                     f"{at} MB | {slope} | {r['peak_mb']:.0f} MB | {r['checkpoints']} | "
                     f"{r['ck_worker_ms'] if r['ck_worker_ms'] is not None else '-'} ms / "
                     f"{r['ck_write_ms'] if r['ck_write_ms'] is not None else '-'} ms | {r['outputs_mb']:.0f} MB |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10000, help="frames of the normal flight (0 = skip)")
    ap.add_argument("--black", type=int, default=6000, help="black frames (0 = skip)")
    ap.add_argument("--interval", type=float, default=10.0, help="output.checkpoint_interval (s)")
    ap.add_argument("--with-default", action="store_true",
                    help="also map the flight with the default config (no tile cap)")
    ap.add_argument("--records", type=int, default=2000, help="frames of the tracemalloc run (0 = skip)")
    ap.add_argument("--out", help="write the table into this markdown file (section bench_memory)")
    ap.add_argument("--case", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.case:
        spec = json.loads(args.case)
        run = records_growth if spec["case"] == "records" else run_case
        print(json.dumps(run(spec["case"], spec["n"], spec["config"], spec["overrides"])
                         if run is run_case else run(spec["n"], spec["config"], spec["overrides"])))
        return 0
    ck = [f"output.checkpoint_interval={args.interval}"]
    load_before = os.getloadavg()[0]
    cases = []
    if args.black:
        cases += [("black", args.black, None, ck), ("black", args.black, str(ONBOARD), ck)]
    if args.frames:
        cases += [("flight", args.frames, str(ONBOARD), ck)]
        if args.with_default:  # every tile in memory: grows with the map by design
            cases.append(("flight", args.frames, None, ck))
    results = []
    for case, n, config, overrides in cases:
        print(f"{case} x{n} ({Path(config).name if config else 'default'}) ...", file=sys.stderr, flush=True)
        results.append(run_subprocess(case, n, config, overrides))
        print("\n".join(table(results[-1:])[2:]), file=sys.stderr, flush=True)
    lines = table(results)
    if args.records:
        print(f"records x{args.records} (tracemalloc) ...", file=sys.stderr, flush=True)
        rec = run_subprocess("records", args.records, str(ONBOARD), ck)
        lines += ["", f"Python heap growth from 20 % to 100 % of a {args.records}-frame flight (tracemalloc, "
                      f"onboard config): map tiles {rec['tiles_kb_per_frame']:.2f} KB/frame (bounded by "
                      f"`mosaic.max_tiles_in_memory`), a checkpoint being written {rec['checkpoint_in_flight_mb']:.1f} MB "
                      f"(its tile copies); everything else: what grew {rec['grew_kb_per_frame']:.3f} KB/frame "
                      f"(largest: " + ", ".join(f"`{k}` {v:.3f}" for k, v in rec["top"]) + " KB/frame), "
                      f"and {rec['freed_mb']:.1f} MB held at 20 % freed by the end."]
    print("\n".join(lines))
    loads = (load_before, os.getloadavg()[0])
    if args.out:
        from tools.report import replace_section
        body = [f"Written by `python -m tools.bench_memory` on {datetime.date.today()}, {os.cpu_count()} cores, "
                f"1-minute load {loads[0]:.1f} before and {loads[1]:.1f} after (timings are indicative; "
                f"the pipeline section measures speed). RSS sampled every 50 ms (psutil), each case "
                f"in a fresh interpreter; *growth*: median RSS over 80-100 % of the frames minus the median "
                f"over 10-30 %, per frame between them. Checkpoint: worker = copying the tiles changed since the last "
                f"checkpoint, writer = PNG encoding + fsync + manifest in the background thread.", "", *lines]
        replace_section(Path(args.out), "memory", "\n".join(["## Memory whatever the input", "", *body]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
