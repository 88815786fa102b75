"""Fixed-step loop: a table of (task, rate, budget) run on an injected clock.

Like ArduPilot's scheduler or an F Prime rate group: the loop runs at a base rate; each task runs every
`base_rate / task_rate` ticks. Time is given to :meth:`Scheduler.tick` by the caller — the simulation
clock in SITL (so runs are deterministic and can go faster than real time), a monotonic clock on target.
The only other time source is `work_timer`, used solely to *measure* how long the work took (cycle
time, budgets, overruns); it never decides what the logic does.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np


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


@dataclass
class LoopStats:
    """Cycle-time statistics over a reporting window plus counters since start."""

    ticks: int = 0
    overruns: int = 0
    task_overruns: int = 0
    window: np.ndarray = field(default_factory=lambda: np.zeros(4096))
    window_n: int = 0

    def summary_us(self) -> tuple[float, float, float, float]:
        """(mean, p50, p99, max) of the work time per tick in the current window, in µs."""
        w = self.window[: min(self.window_n, len(self.window))]
        if w.size == 0:
            return 0.0, 0.0, 0.0, 0.0
        p50, p99 = np.percentile(w, (50.0, 99.0))
        return float(w.mean() * 1e6), float(p50 * 1e6), float(p99 * 1e6), float(w.max() * 1e6)

    def reset_window(self) -> None:
        self.window_n = 0


class Scheduler:
    """Runs the task table at a fixed base rate on the time it is given."""

    def __init__(self, rate_hz: float, tasks: list[Task],
                 work_timer: Callable[[], float] = time.perf_counter) -> None:
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

    def task(self, name: str) -> Task:
        return next(t for t in self.tasks if t.name == name)

    def tick(self, now_s: float) -> float:
        """Run the tasks due at this tick; returns the work time of the tick in seconds."""
        timer = self.work_timer
        n = self.stats.ticks
        start = timer()
        for task in self.tasks:
            if n % task.divider:
                continue
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
        work = timer() - start
        st = self.stats
        st.window[st.window_n % len(st.window)] = work
        st.window_n += 1
        st.ticks = n + 1
        if work > self.period_s:
            st.overruns += 1
        return work
