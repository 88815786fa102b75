"""Fixed-step loop: a table of (task, rate, budget) run on an injected clock.

Like ArduPilot's scheduler or an F Prime rate group: the loop runs at a base rate; each task runs every
`base_rate / task_rate` ticks. Time is given to :meth:`Scheduler.tick` by the caller — the simulation
clock in SITL (so runs are deterministic and can go faster than real time), a monotonic clock on target.
The only other time source is `work_timer`, used to *measure* how long the work took (cycle time,
budgets, overruns). Those measured figures, never a clock reading of its own, are also what the sample
pipeline's budget uses:

Sample pipeline: the tasks marked `per_sample` (in the flight software: latch a queued sample, calibrate,
estimate, the every-tick applications, telemetry) process one queued sample (`fsw.sample_queue`) per
pass. The first pass is the tick's ordinary one; while samples wait (`backlog()`) and the tick's work so
far plus the measured cost of a sample (`LoopStats.sample_cost_s`, from the passes that took one) fits
in `sample_budget` of the period, the scheduler runs further passes of the pipeline's every-tick tasks
in the same tick. A pipeline task that takes a sample asks :meth:`Scheduler.fits` first, so a sample that
does not fit waits for a later tick instead of making this one overrun.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .percentiles import percentile_pair


@dataclass
class Task:
    """One row of the task table. `fn(now_s)` is called at `rate_hz`; `budget_s` is its time budget."""

    name: str
    fn: Callable[[float], None]
    rate_hz: float
    budget_s: float
    divider: int = 0
    runs: int = 0
    overruns: int = 0
    last_s: float = 0.0
    max_s: float = 0.0
    #: part of the sample pipeline: run again in the tick's catch-up passes (when its divider is 1)
    per_sample: bool = False


@dataclass
class LoopStats:
    """Cycle-time statistics over a reporting window plus counters since start."""

    ticks: int = 0
    overruns: int = 0
    task_overruns: int = 0
    window: np.ndarray = field(default_factory=lambda: np.zeros(4096))
    window_n: int = 0
    #: the pipeline's work for one sample (s): exponentially weighted mean over the passes that took one,
    #: each pass counted as at most twice the mean so far
    sample_cost_s: float = 0.0
    #: samples taken by the pipeline since start, and the extra passes run to catch up
    samples: int = 0
    catch_up_passes: int = 0
    #: over the current window: samples taken, their pipeline work (s)
    window_samples: int = 0
    window_sample_work_s: float = 0.0

    def summary_us(self) -> tuple[float, float, float, float]:
        """(mean, p50, p99, max) of the work time per tick in the current window, in µs."""
        w = self.window[: min(self.window_n, len(self.window))]
        if w.size == 0:
            return 0.0, 0.0, 0.0, 0.0
        p50, p99 = percentile_pair(w, 50.0, 99.0)
        return float(w.mean() * 1e6), float(p50 * 1e6), float(p99 * 1e6), float(w.max() * 1e6)

    def reset_window(self) -> None:
        self.window_n = 0
        self.window_samples = 0
        self.window_sample_work_s = 0.0

    def window_ticks(self) -> int:
        return min(self.window_n, len(self.window))

    def window_mean_s(self) -> float:
        """Mean work per tick over the window (s)."""
        n = self.window_ticks()
        return float(self.window[:n].mean()) if n else 0.0

    def add_sample_cost(self, work_s: float) -> None:
        self.samples += 1
        self.window_samples += 1
        self.window_sample_work_s += work_s
        self.sample_cost_s = work_s if self.samples == 1 else robust_mean(self.sample_cost_s, work_s)


def robust_mean(mean_s: float, x_s: float) -> float:
    """A measured cost's running mean: exponentially weighted (1/32), each measurement counted as at most twice
    the mean so far (a pass the OS preempted barely moves it); the first measurement starts it."""
    if not mean_s:
        return x_s
    return mean_s + (min(x_s, 2.0 * mean_s) - mean_s) / 32.0


class Scheduler:
    """Runs the task table at a fixed base rate on the time it is given."""

    #: catch-up passes at most per tick
    MAX_PASSES = 8

    def __init__(self, rate_hz: float, tasks: list[Task],
                 work_timer: Callable[[], float] = time.perf_counter, *,
                 backlog: Callable[[], int] | None = None, taken: Callable[[], bool] | None = None,
                 sample_budget: float = 0.7) -> None:
        """`backlog()`: samples waiting for the pipeline (None: no pipeline, no catch-up passes); `taken()`:
        whether the pass just run took a sample (its per-sample tasks' work is then a sample's cost);
        `sample_budget`: the share of the period a tick's work may reach with a sample's processing."""
        if not (0 < rate_hz <= 10_000):
            raise ValueError(f"loop rate must be in (0, 10000] Hz, got {rate_hz!r}")
        self.rate_hz = float(rate_hz)
        self.period_s = 1.0 / self.rate_hz
        self.tasks = tasks
        for task in tasks:
            if not (0 < task.rate_hz <= self.rate_hz):
                raise ValueError(f"task {task.name!r}: rate {task.rate_hz} Hz must be in (0, {self.rate_hz}] Hz")
            task.divider = max(1, round(self.rate_hz / task.rate_hz))
        self.stats = LoopStats()
        #: what measures the work (wall time by default; a lockstep run may measure its own CPU time)
        self.work_timer = work_timer
        if not 0 < sample_budget <= 1:
            raise ValueError(f"sample budget must be in (0, 1] of the period, got {sample_budget!r}")
        self.backlog = backlog
        self.taken = taken
        self.sample_budget_s = sample_budget * self.period_s
        self._pipeline = [t for t in tasks if t.per_sample and t.divider == 1]
        self._start = 0.0

    def task(self, name: str) -> Task:
        return next(t for t in self.tasks if t.name == name)

    def elapsed_s(self) -> float:
        """The current tick's work so far (s), on the work timer."""
        return self.work_timer() - self._start

    def fits(self, cost_s: float | None = None) -> bool:
        """Whether `cost_s` more work (default: a sample's measured cost) keeps the tick within the sample
        budget."""
        cost = self.stats.sample_cost_s if cost_s is None else cost_s
        return self.elapsed_s() + cost <= self.sample_budget_s

    def _run(self, task: Task, now_s: float) -> float:
        timer = self.work_timer
        t0 = timer()
        task.fn(now_s)
        dt = timer() - t0
        task.runs += 1
        task.last_s = dt
        if dt > task.max_s:
            task.max_s = dt
        if dt > task.budget_s:
            task.overruns += 1
            self.stats.task_overruns += 1
        return dt

    def tick(self, now_s: float) -> float:
        """Run the tasks due at this tick, then catch-up passes of the sample pipeline while samples wait and
        the budget has room; returns the work time of the tick in seconds."""
        timer = self.work_timer
        st = self.stats
        n = st.ticks
        start = self._start = timer()
        sample_work = 0.0
        for task in self.tasks:
            if n % task.divider:
                continue
            dt = self._run(task, now_s)
            if task.per_sample:
                sample_work += dt
        if self.taken is not None and self.taken():
            st.add_sample_cost(sample_work)
        if self.backlog is not None and self._pipeline:
            for _ in range(self.MAX_PASSES):
                if not self.backlog() or not self.fits():
                    break
                sample_work = 0.0
                for task in self._pipeline:
                    sample_work += self._run(task, now_s)
                st.catch_up_passes += 1
                if not self.taken():
                    break  # the pipeline declined (it judged the budget itself): no progress this tick
                st.add_sample_cost(sample_work)
        work = timer() - start
        st.window[st.window_n % len(st.window)] = work
        st.window_n += 1
        st.ticks = n + 1
        if work > self.period_s:
            st.overruns += 1
        return work
