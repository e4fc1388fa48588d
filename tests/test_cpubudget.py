"""The map server's CPU budget (photomap.live.cpubudget), on a clock of its own."""

from __future__ import annotations

import random

from photomap.live.cpubudget import CpuBudget


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0
        self.slept: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.now += seconds


def test_a_burst_goes_at_once_and_what_is_overspent_is_waited_for():
    clock = _Clock()
    budget = CpuBudget(0.25, burst_s=2.0, clock=clock, sleep=clock.sleep)
    budget.wait()
    budget.spend(0.4)  # within the full bucket (0.5 CPU s)
    budget.wait()
    assert clock.slept == [] and budget.waits == 0
    budget.spend(0.4)  # 0.3 CPU s overspent: 1.2 s at a quarter of a core
    budget.wait()
    assert len(clock.slept) == 1 and abs(clock.slept[0] - 1.2) < 1e-9 and budget.waits == 1
    budget.wait()  # paid off: no second wait
    assert len(clock.slept) == 1
    clock.now += 60.0  # an idle minute fills the bucket to its size, not beyond
    budget.spend(0.5)
    budget.wait()
    assert len(clock.slept) == 1
    budget.spend(0.05)
    budget.wait()
    assert abs(clock.slept[-1] - 0.2) < 1e-9


def test_however_much_is_asked_the_cpu_stays_within_the_share():
    """Answers of random cost asked back to back (a hostile client): the CPU spent never exceeds
    the bucket plus the share of the wall time, and the share is used (not starved)."""
    clock = _Clock()
    budget = CpuBudget(0.25, burst_s=2.0, clock=clock, sleep=clock.sleep)
    rng = random.Random(3)
    start = clock.now
    for _ in range(5000):
        budget.wait()
        cost = rng.uniform(0.0005, 0.01)
        clock.now += cost  # the answer takes its CPU time in wall time too
        budget.spend(cost)
        assert budget.spent_s <= 0.5 + 0.25 * (clock.now - start) + 0.01 + 1e-9
    assert budget.spent_s >= 0.95 * 0.25 * (clock.now - start)


def test_no_limit_and_an_early_stop():
    clock = _Clock()
    free = CpuBudget(0.0, clock=clock, sleep=clock.sleep)
    free.spend(100.0)
    free.wait()
    assert clock.slept == []
    stopped: list[float] = []
    closing = CpuBudget(0.1, burst_s=1.0, clock=clock, sleep=lambda s: stopped.append(s) or True)
    closing.spend(10.0)
    closing.wait()  # the server closes: the wait ends at once, not after 99 s and more
    assert len(stopped) == 1
