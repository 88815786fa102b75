"""The host's own magnetism at the magnetometer, and what the magnetometer therefore measures.

A magnetometer bolted to a dead spacecraft sees the Earth's field through the host's iron:

    b_meas = S · b_true + h(t)

- hard iron ``h0`` (body axes): remanent magnetisation of the structure, a constant field up to
  ±50 µT on a small spacecraft;
- soft iron ``S`` (3×3): induced magnetisation, which scales and skews the field; ``S = I + E``
  with ``E`` up to ~0.1 in scale and misalignment. ``S`` need not be symmetric;
- a slow change of the hard iron over an orbit, with the thermal cycle (sun and eclipse):
  ``h(t) = h0 + d · sin(2π t / period + phase)``, ``d`` ~1 µT per axis, the period by default the
  orbit's.

The de-orbit kit's magnets are separate (``hil.kit_field``): they switch and turn, the host does not.
Scenario table ``[host]`` (all keys optional, defaults: none of it)::

    hard_iron_uT = [x, y, z]          soft_iron = [[...], [...], [...]]  (the matrix S, identity if absent)
    hard_iron_drift_uT = [x, y, z]    drift_period_s = 0 (0: the orbit's period)   drift_phase_deg = 0
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["HostMagnetics", "HARD_IRON_MAX_T", "SOFT_IRON_MAX_DEVIATION"]

#: the span of hard iron that the scenarios may give (a bigger value is a typo, not a spacecraft)
HARD_IRON_MAX_T = 200e-6
#: the largest element of S − I accepted
SOFT_IRON_MAX_DEVIATION = 0.5


@dataclass(frozen=True, eq=False)
class HostMagnetics:
    """Hard iron, soft iron and the hard iron's thermal drift; SI inside (tesla, seconds, radians)."""

    hard_iron_T: np.ndarray = field(default_factory=lambda: np.zeros(3))
    soft_iron: np.ndarray = field(default_factory=lambda: np.eye(3))
    drift_T: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: the drift's period [s]; 0 means "the orbit's period", resolved by :meth:`with_period`
    drift_period_s: float = 0.0
    drift_phase_rad: float = 0.0

    def __post_init__(self) -> None:
        h = np.asarray(self.hard_iron_T, dtype=float)
        s = np.asarray(self.soft_iron, dtype=float)
        d = np.asarray(self.drift_T, dtype=float)
        if h.shape != (3,) or d.shape != (3,) or s.shape != (3, 3):
            raise ValueError("hard iron and drift are 3-vectors, soft iron a 3x3 matrix")
        if not (np.all(np.isfinite(h)) and np.all(np.isfinite(s)) and np.all(np.isfinite(d))):
            raise ValueError("host magnetics must be finite")
        if np.any(np.abs(h) > HARD_IRON_MAX_T) or np.any(np.abs(d) > HARD_IRON_MAX_T):
            raise ValueError(f"hard iron and its drift must be within ±{HARD_IRON_MAX_T * 1e6:g} µT per axis")
        if np.any(np.abs(s - np.eye(3)) > SOFT_IRON_MAX_DEVIATION):
            raise ValueError(f"soft iron must be within ±{SOFT_IRON_MAX_DEVIATION} of the identity per element")
        if np.linalg.det(s) <= 0:
            raise ValueError("soft iron must have a positive determinant")
        if not (np.isfinite(self.drift_period_s) and self.drift_period_s >= 0):
            raise ValueError("drift_period_s must be >= 0 (0: the orbit's period)")
        object.__setattr__(self, "hard_iron_T", h)
        object.__setattr__(self, "soft_iron", s)
        object.__setattr__(self, "drift_T", d)

    @property
    def is_none(self) -> bool:
        """No host magnetism at all (the measurement is the true field)."""
        return not (np.any(self.hard_iron_T) or np.any(self.drift_T) or np.any(self.soft_iron != np.eye(3)))

    def with_period(self, orbit_period_s: float) -> HostMagnetics:
        """This host with a drift period of 0 resolved to the orbit's period."""
        if self.drift_period_s > 0:
            return self
        return HostMagnetics(self.hard_iron_T, self.soft_iron, self.drift_T, float(orbit_period_s),
                             self.drift_phase_rad)

    def hard_iron_at_T(self, t_s: float | np.ndarray) -> np.ndarray:
        """h(t) = h0 + d sin(2π t / period + phase) [T], (3,) for a scalar t, (N, 3) for N times."""
        t = np.asarray(t_s, dtype=float)
        if not np.any(self.drift_T) or self.drift_period_s <= 0:
            return np.broadcast_to(self.hard_iron_T, t.shape + (3,)).copy()
        s = np.sin(2.0 * np.pi * t / self.drift_period_s + self.drift_phase_rad)
        return self.hard_iron_T + s[..., None] * self.drift_T

    def measured_T(self, b_true_body_T: np.ndarray, t_s: float | np.ndarray) -> np.ndarray:
        """b_meas = S · b_true + h(t): the field at the sensor in body axes [T]."""
        b = np.asarray(b_true_body_T, dtype=float)
        return b @ self.soft_iron.T + self.hard_iron_at_T(t_s)

    def true_from_measured_T(self, b_meas_body_T: np.ndarray, t_s: float | np.ndarray) -> np.ndarray:
        """The inverse: b_true = S⁻¹ (b_meas − h(t)) (what a perfect calibration would give)."""
        return np.linalg.solve(self.soft_iron, (np.asarray(b_meas_body_T, float) - self.hard_iron_at_T(t_s)).T).T

    @classmethod
    def from_table(cls, table: dict) -> HostMagnetics:
        """From a scenario's ``[host]`` table (already type-checked; µT and degrees converted here)."""
        return cls(hard_iron_T=np.asarray(table.get("hard_iron_uT", (0.0, 0.0, 0.0)), float) * 1e-6,
                   soft_iron=np.asarray(table.get("soft_iron", np.eye(3)), float),
                   drift_T=np.asarray(table.get("hard_iron_drift_uT", (0.0, 0.0, 0.0)), float) * 1e-6,
                   drift_period_s=float(table.get("drift_period_s", 0.0)),
                   drift_phase_rad=float(np.radians(table.get("drift_phase_deg", 0.0))))
