"""The box's estimate of UTC: the offset of UTC from its own monotonic clock and that clock's drift.

Pure: :class:`UtcEstimator` is given pairs (monotonic time, UTC) — each a time set from the ground —
and answers UTC at any monotonic time. Nothing here reads a clock.

- The offset is UTC − monotonic at the latest set (the ground's clock is the reference; the latest
  set is the best one).
- The drift (the box's clock rate error, s/s) is the least-squares slope of the offsets of the last
  `window` sets against monotonic time, once they span at least `min_span_s`; before that it is
  unknown and taken as 0.
- A set that disagrees with the prediction by more than `max_step_s` (a clock step on either side,
  or a set that was wrong) starts the drift history afresh from that set (counted in `steps`).

UTC is in seconds since the Unix epoch (1970-01-01T00:00:00Z), leap seconds not counted (POSIX time,
as MAVLink's SYSTEM_TIME.time_unix_usec).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np


class UtcEstimator:
    """UTC as a function of the box's monotonic clock, from the ground's time sets."""

    def __init__(self, *, window: int = 8, min_span_s: float = 600.0, max_step_s: float = 1.0,
                 max_drift: float = 1e-3) -> None:
        """`window` sets kept for the drift, `min_span_s` the shortest span they must cover before a
        drift is estimated, `max_step_s` the disagreement that counts as a step, `max_drift` the
        largest clock rate error believed (a larger slope: the drift stays unknown)."""
        self.window = int(window)
        self.min_span_s = float(min_span_s)
        self.max_step_s = float(max_step_s)
        self.max_drift = float(max_drift)
        self._sets: deque[tuple[float, float]] = deque(maxlen=self.window)  # (mono, utc − mono)
        self.sets = 0
        self.steps = 0
        self.drift = math.nan      # s/s; NaN while unknown
        self.last_set_mono_s = math.nan
        self.last_residual_s = math.nan  # the latest set against the prediction before it

    @property
    def known(self) -> bool:
        return self.sets > 0

    @property
    def drift_ppm(self) -> float:
        return self.drift * 1e6

    def set(self, mono_s: float, utc_s: float) -> None:
        """A time set: UTC was `utc_s` at the box's monotonic time `mono_s`."""
        mono_s, utc_s = float(mono_s), float(utc_s)
        if not (math.isfinite(mono_s) and math.isfinite(utc_s)):
            raise ValueError("time set with a non-finite time")
        if self._sets:
            if mono_s <= self._sets[-1][0]:  # not after the previous set: history cannot hold it
                self._sets.clear()
            else:
                self.last_residual_s = utc_s - self.utc_s(mono_s)
                if abs(self.last_residual_s) > self.max_step_s:
                    self.steps += 1
                    self._sets.clear()
        self._sets.append((mono_s, utc_s - mono_s))
        self.sets += 1
        self.last_set_mono_s = mono_s
        self.drift = self._fit_drift()

    def _fit_drift(self) -> float:
        if len(self._sets) < 2:
            return math.nan
        m = np.array([s[0] for s in self._sets])
        off = np.array([s[1] for s in self._sets])
        if m[-1] - m[0] < self.min_span_s:
            return math.nan
        slope = float(np.polyfit(m - m[-1], off, 1)[0])
        return slope if abs(slope) <= self.max_drift else math.nan

    def utc_s(self, mono_s):
        """UTC [s since the Unix epoch] at monotonic time(s) `mono_s`; NaN before the first set."""
        if not self._sets:
            return np.full(np.shape(mono_s), math.nan) if np.ndim(mono_s) else math.nan
        m0, off0 = self._sets[-1]
        drift = 0.0 if math.isnan(self.drift) else self.drift
        return np.asarray(mono_s, float) * (1.0 + drift) + off0 - drift * m0 if np.ndim(mono_s) else \
            float(mono_s) + off0 + drift * (float(mono_s) - m0)
