"""The map server benchmark's statistics (tools/bench_mapserver.py): no timings asserted."""

from __future__ import annotations

import random
import statistics

from tools.bench_mapserver import flat_out_verdict, median_interval


def test_the_interval_holds_the_median_and_narrows_with_more_passes():
    rng = random.Random(1)
    few = [rng.gauss(0.98, 0.05) for _ in range(6)]
    many = few + [rng.gauss(0.98, 0.05) for _ in range(194)]
    widths = []
    for values in (few, many):
        lo, hi = median_interval(values)
        assert lo <= statistics.median(values) <= hi
        widths.append(hi - lo)
    assert widths[1] < widths[0] / 2
    assert median_interval(few) == median_interval(few)  # seeded: the same passes, the same interval


def test_the_verdict_follows_the_interval_and_falls_back_on_the_cpu_share():
    assert flat_out_verdict(0.975, 1.01, 0.05).startswith("met")
    assert flat_out_verdict(0.90, 0.965, 0.01).startswith("NOT met")
    straddling = flat_out_verdict(0.76, 1.19, 0.021)
    assert straddling.startswith("not decidable") and straddling.endswith(": met")
    assert flat_out_verdict(0.76, 1.19, 0.04).endswith("NOT met")
