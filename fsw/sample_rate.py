"""The magnetometer's sample rate chosen from the loop's budget, rather than the loop falling behind.

Once a second the flight software hands :func:`choose` the loop's own cycle-time figures over the last
second (`fsw.scheduler.LoopStats`: the median work per tick, the samples the pipeline took, its cost per
sample — measured on the scheduler's work timer, never a clock read here). They split into a cost per
tick that does not depend on the samples (uplink, sensor poll, status) and a cost per sample (gate,
calibration, estimators, applications, telemetry); the work a second at sample rate r is then

    W(r) = base_per_tick × loop rate + cost_per_sample × r     [s of work per s]

and the rate in force holds when W(r) ≤ `WORK_SHARE` and, when a sample comes every tick or two (where
a late tick lets the chip overwrite one), fewer than `OVERRUN_SHARE` of the ticks overran. When it does
not in two windows in a row (one long window is no reason: a burst of the operating system's own work),
or the sample queue has refused samples or holds more than half its capacity, the highest rate the chip
offers below it (its continuous-mode rates,
`fsw.drivers.mmc5983ma.Mmc5983ma.available_rates_hz`) with W(r) ≤ `WORK_SHARE` is chosen, the lowest
if none fits. The rate only goes down: a rate given up is not tried again in the run (a box that cannot
hold it once will not be faster later), which also keeps it from oscillating.
"""
from __future__ import annotations

from dataclasses import dataclass

#: share of a window's ticks that may overrun before the rate in force is judged not held (a tick in a
#: hundred: the once-a-second peaks of a slow CPU stay below it, a loop that cannot keep up does not)
OVERRUN_SHARE = 0.01

#: share of each second the loop's work may take at the chosen rate: the rest absorbs the peaks (a
#: calibration solve, a knot of the field along the orbit) and the operating system
WORK_SHARE = 0.6


@dataclass(frozen=True)
class Budget:
    """The loop's costs: per tick whatever the samples (s) and per sample (s), at its loop rate."""

    loop_rate_hz: float
    base_per_tick_s: float
    cost_per_sample_s: float

    @classmethod
    def from_window(cls, loop_rate_hz: float, median_tick_s: float, samples_per_tick: float,
                    cost_per_sample_s: float) -> "Budget":
        """From a window's median work per tick (robust to the rare long tick, the OS's preemption), its
        samples per tick and the pipeline's measured cost per sample."""
        return cls(loop_rate_hz, max(0.0, median_tick_s - min(1.0, samples_per_tick) * cost_per_sample_s),
                   cost_per_sample_s)

    def work_share(self, sample_rate_hz: float) -> float:
        """W(r): the share of a second the loop's work takes at `sample_rate_hz`."""
        return self.base_per_tick_s * self.loop_rate_hz + self.cost_per_sample_s * sample_rate_hz


def choose(budget: Budget, current_hz: float, rates_hz: list[float], *, behind: bool = False,
           share: float = WORK_SHARE) -> float:
    """The sample rate to fly: `current_hz` when it fits `share` and the loop is not `behind`; else the
    highest of `rates_hz` below it that fits, or the lowest of them."""
    if not behind and budget.work_share(current_hz) <= share:
        return current_hz
    lower = sorted((r for r in rates_hz if r < current_hz), reverse=True)
    if not lower:
        return current_hz
    return next((r for r in lower if budget.work_share(r) <= share), lower[-1])
