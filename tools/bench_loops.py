"""Cost of loops by appearance per keyframe, by the number of keyframes a segment holds.

    python -m tools.bench_loops [--sizes 60,1000,5000,10000] [--out docs/benchmarks.md]

Each new keyframe adds its place signature to the segment's :class:`~photomap.core.places.PlaceIndex`
and searches it (one matrix product over the signatures held): measured here at each size, the
index filled with signatures of views of a simulated terrain (signatures of 200 distinct views,
repeated with a small perturbation: the cost does not depend on the content). The candidates found
are then registered and checked (a fixed number per keyframe, ``mapping.loop_appearance_candidates``,
whatever the flight's length): one registration plus overlap check is timed on the working frame.
Writes the ``loops`` section of ``docs/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from photomap.config import load_config  # noqa: E402
from photomap.core.features import verify_overlap  # noqa: E402
from photomap.core.ifmi import Registrar  # noqa: E402
from photomap.core.places import PlaceIndex, place_signature  # noqa: E402
from photomap.sim.flight import simulate_sequence  # noqa: E402
from photomap.sim.terrain import procedural_terrain  # noqa: E402
from tools.report import replace_section  # noqa: E402


def _views(n: int) -> list[np.ndarray]:
    terrain = procedural_terrain("texture", (2048, 2048), seed=3)
    seq = simulate_sequence(terrain, n, (240, 320), seed=1, gsd=0.05, fps=10.0, altitude=(20.0, 20.0),
                            speed=10.0, pattern="circle", yaw_mode="heading", yaw_rate=0.0)
    return [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in seq.frames]


def _time(fn, repeat: int) -> float:
    """Median wall time of ``fn()`` in ms."""
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t0) * 1000.0)
    return float(np.median(out))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="60,1000,5000,10000", help="keyframes held, comma separated")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks.md")
    args = ap.parse_args(argv)
    with threadpool_limits(limits=1, user_api="blas"):  # as the pipeline runs (MappingPipeline.run)
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    sizes = [int(s) for s in args.sizes.split(",")]
    views = _views(200)
    sigs = np.stack([place_signature(v) for v in views])
    signature_ms = _time(lambda: place_signature(views[7]), 20)
    rng = np.random.default_rng(0)
    rows = []
    for n in sizes:
        index = PlaceIndex()
        for k in range(n):
            index.add(k, sigs[k % len(sigs)] + rng.normal(0, 1e-3, sigs.shape[1:]).astype(np.float32), 0)
        query = sigs[11]
        recent = set(range(n - 8, n))
        search_ms = _time(lambda: index.search(query, 0, 4, recent), 30)
        add_ms = _time(lambda: index.add(n, query, 0), 30)
        rows.append((n, search_ms, add_ms, index._rows.nbytes / 1e6))
    cfg = load_config()
    registrar = Registrar(views[0].shape, cfg.registration)
    a, b = registrar.prepare(views[0]), registrar.prepare(views[3])

    def verify() -> None:
        reg = registrar.register(registrar.prepare(views[0]), b, None)
        verify_overlap(a.gray, b.gray, reg.matrix)

    verify_ms = _time(verify, 10)
    k = cfg.mapping.loop_appearance_candidates
    lines = ["## Loops by appearance", "",
             f"Written by `python -m tools.bench_loops --sizes {args.sizes}`. Per new keyframe: its signature ({signature_ms:.2f} ms, 320x240), the index's add and search "
             f"(top {k}, the newest 8 excluded), then {k} registrations with overlap check of "
             f"{verify_ms:.1f} ms each at 320x240 (no prior; the same at any flight length). BLAS on one "
             f"thread, as the pipeline runs. "
             f"{platform.processor() or platform.machine()}, a shared machine: indicative.", "",
             "| keyframes in the segment | search (ms) | add (ms) | index memory (MB) |", "|---|---|---|---|"]
    lines += [f"| {n} | {s:.3f} | {a_:.4f} | {m:.1f} |" for n, s, a_, m in rows]
    body = "\n".join(lines) + "\n"
    print(body)
    replace_section(args.out, "loops", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
