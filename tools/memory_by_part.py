"""Live memory of the long flight by the code that allocated it, tenth by tenth (memray).

The RSS slope of ``tools/bench_pipeline.py`` cannot tell the data a run keeps from the memory the
allocator keeps for it. This tool maps the same long flight (1920x1080 frames rendered one by one,
the onboard tile cap) in this process under ``memray.Tracker`` and attributes every allocation
still alive to the innermost frame of this repository's code on its Python stack (``core/mosaic.py
_new_tile``; allocations of code outside it go to the nearest repository frame, those with none to
``(no repository frame)``); memory mapped directly (``mmap``: e.g. OpenBLAS's per-thread buffers,
mostly never touched; the interpreter's arenas for small objects) is listed apart. Printed: for
each tenth of the flight the mean live MB of the ``--top`` parts (ranked by their largest change
from the second tenth to the last), the sums of all parts but those mapped and of those mapped,
and the process RSS (memray's own samples). Live data that is flat while RSS rises is memory
the allocator holds, not the run.

    python -m tools.memory_by_part [--frames N] [--top K] [--keep FILE]

About 1.3x the plain run's time (10,000 frames: ~8 minutes on 2 cores). Needs ``memray`` (Linux or
macOS; the ``bench`` extra).
"""

from __future__ import annotations

import argparse
import bisect
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from photomap.config import load_config  # noqa: E402
from photomap.mapping.pipeline import MappingPipeline  # noqa: E402
from tools.bench_pipeline import LONG_OVERRIDES, MB, SimulatedSource  # noqa: E402

_ROOTS = (str(REPO / "service"), str(REPO / "tools"))
_MAPPED = " (mmap)"


def part_of(stack: list[tuple[str, str, int]], mapped: bool) -> str:
    """The innermost frame of ``stack`` (memray's ``(function, file, line)``, innermost first) in
    this repository, as ``dir/module.py function``."""
    name = "(no repository frame)"
    for function, filename, _ in stack:
        if filename.startswith(_ROOTS):
            name = f"{Path(filename).parent.name}/{Path(filename).name} {function}"
            break
    return name + _MAPPED if mapped else name


def record(n_frames: int, path: Path) -> list[float]:
    """Map the long flight under memray, capture file ``path``; returns the UNIX times (s) at the
    start and when each tenth of the frames was mapped."""
    import memray

    marks: list[float] = []
    done = 0

    def on_frame(event) -> None:
        nonlocal done
        done += 1
        if done * 10 % n_frames < 10:
            marks.append(time.time())

    source = SimulatedSource(n_frames)
    cfg = load_config(overrides=LONG_OVERRIDES)
    with tempfile.TemporaryDirectory(prefix="memory-by-part-") as tmp:
        pipe = MappingPipeline(source, cfg, tmp, sinks=[on_frame], input_name="simulated")
        with memray.Tracker(path):
            marks.insert(0, time.time())
            pipe.run()
    return marks[:11]


def live_by_part(path: Path, marks: list[float]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Mean live MB of each part in each interval between ``marks``, and the mean RSS (MB)."""
    from memray import AllocatorType, FileReader

    reader = FileReader(path)
    snaps = list(reader.get_memory_snapshots())
    times = [s.time / 1000.0 for s in snaps]
    edges = [min(bisect.bisect_left(times, t), len(snaps) - 1) for t in marks]
    spans = [(a, max(b, a + 1)) for a, b in zip(edges[:-1], edges[1:])]
    steps: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(len(snaps) + 1))
    mapped = {AllocatorType.MMAP}
    for rec in reader.get_temporal_allocation_records(merge_threads=True):
        step = steps[part_of(rec.stack_trace(), rec.allocator in mapped)]
        for iv in rec.intervals:
            step[iv.allocated_before_snapshot] += iv.n_bytes
            if iv.deallocated_before_snapshot is not None:
                step[iv.deallocated_before_snapshot] -= iv.n_bytes
    out = {}
    for name, step in steps.items():
        live = np.cumsum(step)[:len(snaps)] / MB
        out[name] = np.array([live[a:b].mean() for a, b in spans])
    rss = np.array([np.mean([s.rss for s in snaps[a:b]]) / MB for a, b in spans])
    return out, rss


def table(parts: dict[str, np.ndarray], rss: np.ndarray, top: int) -> list[str]:
    """Markdown table: a row per tenth, a column per part."""
    def change(v: np.ndarray) -> float:
        return float(np.max(np.abs(v[1:] - v[1]))) if len(v) > 1 else 0.0

    shown = sorted(parts, key=lambda k: -change(parts[k]))[:top]
    zero = np.zeros(len(rss))
    heap = sum((v for k, v in parts.items() if not k.endswith(_MAPPED)), zero)
    mapped = sum((v for k, v in parts.items() if k.endswith(_MAPPED)), zero)
    lines = ["| tenth | " + " | ".join(f"`{k}`" for k in shown) + " | all but mmap | all mmap | RSS |",
             "|---:|" + "---:|" * (len(shown) + 3)]
    for i in range(len(rss)):
        lines.append(f"| {i + 1} | " + " | ".join(f"{parts[k][i]:.1f}" for k in shown)
                     + f" | {heap[i]:.1f} | {mapped[i]:.1f} | {rss[i]:.1f} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10000, help="frames of the long flight (>= 10)")
    ap.add_argument("--top", type=int, default=8, help="parts shown (those that change most)")
    ap.add_argument("--keep", help="keep memray's capture file here (default: a temporary file)")
    args = ap.parse_args(argv)
    try:
        import memray  # noqa: F401
    except ImportError:
        print("memory_by_part needs memray: pip install memray (Linux or macOS)", file=sys.stderr)
        return 2
    if args.frames < 10:
        ap.error("--frames must be at least 10")
    with tempfile.TemporaryDirectory(prefix="memory-by-part-") as tmp:
        path = Path(args.keep) if args.keep else Path(tmp) / "flight.bin"
        path.unlink(missing_ok=True)
        marks = record(args.frames, path)
        parts, rss = live_by_part(path, marks)
    print(f"Live MB by part, mean over each tenth of a {args.frames}-frame long flight:\n")
    print("\n".join(table(parts, rss, args.top)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
