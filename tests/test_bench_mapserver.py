"""The map server benchmark's statistics (tools/bench_mapserver.py): no timings asserted."""

from __future__ import annotations

import math
import random
import statistics

from tools.bench_mapserver import CONDITIONS, NO_SERVER, flat_out_verdict, mean_interval, paired_effects, \
    pass_order, sandwich_effects


def test_the_interval_holds_the_mean_and_narrows_with_more_passes():
    rng = random.Random(1)
    few = [rng.gauss(0.98, 0.05) for _ in range(6)]
    many = few + [rng.gauss(0.98, 0.05) for _ in range(194)]
    widths = []
    for values in (few, many):
        lo, hi = mean_interval(values)
        assert lo <= statistics.fmean(values) <= hi
        widths.append(hi - lo)
    assert widths[1] < widths[0] / 4  # about 1 / sqrt(200 / 6)
    assert mean_interval(few) == mean_interval(few)  # seeded: the same passes, the same interval


def test_every_pass_with_a_server_lies_between_two_without():
    order = pass_order(4)
    assert len(order) == 1 + 2 * 3 * 4 and order[0] == order[-1] == NO_SERVER
    for cond in CONDITIONS[1:]:
        at = [i for i, c in enumerate(order) if c == cond]
        assert len(at) == 4 and all(order[i - 1] == order[i + 1] == NO_SERVER for i in at)
    assert order[1] != order[7]  # the order turns from round to round


def test_the_sandwich_cancels_a_drift_of_the_machine():
    """A machine slowing steadily by 1 % a pass: a condition costing 5 % comes out at 5 %, one
    costing nothing at 0, where against the first pass without a server they would not."""
    order = pass_order(3)
    cost = {NO_SERVER: 1.0, CONDITIONS[1]: 1.0, CONDITIONS[2]: 0.95, CONDITIONS[3]: 0.95}
    fps = [200.0 * 0.99 ** i * cost[c] for i, c in enumerate(order)]
    effects = sandwich_effects(order, fps)
    assert all(abs(e) < 1e-3 for e in effects[CONDITIONS[1]])
    assert all(abs(math.exp(e) - 0.95) < 1e-3 for e in effects[CONDITIONS[2]] + effects[CONDITIONS[3]])
    assert fps[order.index(CONDITIONS[1])] / fps[0] < 0.995  # the drift a plain ratio would report



def test_a_condition_against_another_of_the_same_round_is_its_cost_beyond_that_one():
    """A server costing 2 % with no client and 5 % with one, on a drifting machine: the client's
    own share comes out at 0.95 / 0.98 in every round, paired with that round's pass."""
    order = pass_order(4)
    cost = {NO_SERVER: 1.0, CONDITIONS[1]: 0.98, CONDITIONS[2]: 0.95, CONDITIONS[3]: 0.90}
    fps = [200.0 * 0.99 ** i * cost[c] for i, c in enumerate(order)]
    effects = sandwich_effects(order, fps)
    paired = paired_effects(effects, CONDITIONS[2], CONDITIONS[1])
    assert len(paired) == 4 and all(abs(math.exp(e) - 0.95 / 0.98) < 1e-3 for e in paired)
    assert all(abs(math.exp(e) - 0.90 / 0.95) < 1e-3 for e in paired_effects(effects, CONDITIONS[3], CONDITIONS[2]))

def test_the_verdict_follows_the_fps_then_the_cpu_interval_and_a_lower_bound_only_fails_it():
    assert flat_out_verdict((0.975, 1.01), (1.05, 1.2), 0.05).startswith("met (the speed-relative fps")
    assert flat_out_verdict((0.90, 0.965), (0.9, 1.0), 0.01).startswith("NOT met (the speed-relative fps")
    assert flat_out_verdict((0.9, 1.05), (0.99, 1.02), 0.05).startswith("met by CPU")
    assert flat_out_verdict((0.9, 1.05), (1.035, 1.06), 0.01).startswith("NOT met by CPU")
    assert flat_out_verdict((0.76, 1.19), (1.0, 1.05), 0.021).startswith("not shown")
    assert flat_out_verdict((0.76, 1.19), (1.0, 1.05), 0.04).startswith("NOT met (the server's own")
