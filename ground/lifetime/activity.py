"""Solar and geomagnetic activity over a decay: constant, an idealised solar cycle, or a user's table.

Every schedule is monthly (30.4375-day months from the start of the decay): month k holds one
:class:`~ground.lifetime.atmosphere.Activity`; the decay holds it over the month.

- constant: one level for the whole decay. The ISO 27852 spread uses three of them (`LEVELS`):
  low (F10.7 = F10.7a = 70 sfu, Ap 4), moderate (140 sfu, Ap 15) and high (250 sfu, Ap 25), the
  levels of the solar-minimum, mean and maximum tables of ISO 14222 / ECSS-E-ST-10-04C.
- cycle: an idealised sinusoidal cycle (an analytic model, not measured data):
  F10.7a(t) = F_min + (F_max − F_min) · sin²(π (t / P + φ)), P = 11 years, F_min = 70 sfu,
  F_max = 190 sfu (the average over a cycle, 130 sfu, is that of cycles 19-24), φ the phase at the start
  (0 = solar minimum, 0.5 = maximum); Ap = 6 + 10 (F10.7a − 70) / 120 (6 at minimum, 16 at maximum).
- file: a CSV of monthly rows `f107_sfu,f107a_sfu,ap` (a header line is allowed), the first row the
  month the decay starts; past its last row the last row holds.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass

import numpy as np

from .atmosphere import Activity, ActivityError

DAYS_PER_MONTH = 365.25 / 12
CYCLE_YEARS = 11.0
CYCLE_F107_MIN_SFU, CYCLE_F107_MAX_SFU = 70.0, 190.0

LEVELS = {
    "low": Activity(70.0, 70.0, 4.0),
    "moderate": Activity(140.0, 140.0, 15.0),
    "high": Activity(250.0, 250.0, 25.0),
}


@dataclass(frozen=True)
class Schedule:
    """Monthly activity (arrays of equal length); `name` says where it came from."""
    name: str
    f107_sfu: np.ndarray
    f107a_sfu: np.ndarray
    ap: np.ndarray

    @property
    def constant(self) -> bool:
        return len(self.ap) == 1

    def month(self, t_days: float) -> int:
        return min(int(t_days / DAYS_PER_MONTH), len(self.ap) - 1)

    def check(self) -> "Schedule":
        for k in range(len(self.ap)):
            Activity(float(self.f107_sfu[k]), float(self.f107a_sfu[k]), float(self.ap[k])).check(
                f"{self.name}, month {k}" if not self.constant else self.name)
        return self


def constant(activity: Activity, name: str = "constant activity") -> Schedule:
    activity.check(name)
    return Schedule(name, np.array([activity.f107_sfu]), np.array([activity.f107a_sfu]), np.array([activity.ap]))


def cycle(phase: float = 0.0, years: float = 200.0) -> Schedule:
    """The idealised cycle of the module docstring from `phase` (0 minimum, 0.5 maximum) for `years`."""
    if not (math.isfinite(phase) and 0.0 <= phase <= 1.0):
        raise ActivityError(f"cycle phase must be within 0-1, got {phase:g}")
    t_yr = (np.arange(int(years * 12) + 1) + 0.5) / 12
    swing = CYCLE_F107_MAX_SFU - CYCLE_F107_MIN_SFU
    f = CYCLE_F107_MIN_SFU + swing * np.sin(np.pi * (t_yr / CYCLE_YEARS + phase)) ** 2
    ap = 6.0 + 10.0 * (f - CYCLE_F107_MIN_SFU) / (CYCLE_F107_MAX_SFU - CYCLE_F107_MIN_SFU)
    return Schedule(f"solar cycle from phase {phase:g}", f, f.copy(), ap).check()


def from_file(path: str) -> Schedule:
    """Monthly rows `f107_sfu,f107a_sfu,ap` from a CSV (ActivityError naming the line when one is bad)."""
    rows = []
    with open(path, encoding="utf-8", newline="") as f:
        for n, row in enumerate(csv.reader(f), 1):
            if not row or row[0].lstrip().startswith("#"):
                continue
            try:
                vals = [float(x) for x in row]
            except ValueError:
                if n == 1:
                    continue            # header
                raise ActivityError(f"{path}:{n}: not three numbers: {','.join(row)!r}") from None
            if len(vals) != 3:
                raise ActivityError(f"{path}:{n}: expected f107_sfu,f107a_sfu,ap, got {len(vals)} values")
            try:
                Activity(*vals).check(f"{path}:{n}")
            except ActivityError as e:
                raise ActivityError(str(e)) from None
            rows.append(vals)
    if not rows:
        raise ActivityError(f"{path}: no activity rows")
    a = np.array(rows)
    return Schedule(path, a[:, 0], a[:, 1], a[:, 2])
