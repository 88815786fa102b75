"""Orbit decay over years: mean elements a, e under drag, averaged over each orbit, plus J2's secular
turn of the node and perigee; a fixed-step RK4 in time whose steps lower a by at most 2 km.

The rates (Gauss's equations with a drag acceleration along the velocity relative to the co-rotating
atmosphere, a_T = −½ ρ B v² f², B = C_D A / m, f = 1 − ω_E h cos i / v² the atmosphere's rotation;
King-Hele's averaging over the mean anomaly, by quadrature over the eccentric anomaly with 24 nodes):

    da/dt = ⟨2 a² v a_T / μ⟩,   de/dt = ⟨2 (e + cos ν) a_T / v⟩,
    dΩ/dt = −3/2 n J2 (R/p)² cos i,   dω/dt = 3/4 n J2 (R/p)² (5 cos² i − 1),

ρ the orbit-averaged NRLMSIS density at the height r − R (`ground.lifetime.atmosphere`). J2 changes
neither a nor e on average; its short-period terms are averaged away, and `a` here is the mean
semi-major axis whose circular orbit has the mean radius a (the reference propagation in the tests
starts its osculating state so). With the latitude-averaged atmosphere the perigee's turn does not
feed back into the density; Ω and ω are carried for the record.

The decay stops when the perigee height falls to `reentry_km` (default 120 km: below it a decaying
object comes down within a revolution or two); the crossing is interpolated within the last step.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from fsw.estimation.field_motion import MU_EARTH_M3S2, OMEGA_EARTH_RADPS

from . import activity as act
from .atmosphere import ALT_GRID_KM, R_EARTH_M, density_kgm3, log_density_profile, log_density_profiles

J2 = 1.08262668e-3
DAY_S = 86400.0
YEAR_DAYS = 365.25
REENTRY_KM = 120.0
_NODES = 24
_E = (np.arange(_NODES) + 0.5) * (2 * math.pi / _NODES)
_COS_E = np.cos(_E)


@dataclass(frozen=True)
class Orbit:
    """Mean elements at the start: semi-major axis (m), eccentricity, inclination (deg)."""
    a_m: float
    e: float
    inclination_deg: float

    @classmethod
    def from_heights(cls, perigee_km: float, apogee_km: float, inclination_deg: float) -> "Orbit":
        rp, ra = R_EARTH_M + perigee_km * 1e3, R_EARTH_M + apogee_km * 1e3
        return cls((rp + ra) / 2, (ra - rp) / (ra + rp), inclination_deg)

    @property
    def perigee_km(self) -> float:
        return (self.a_m * (1 - self.e) - R_EARTH_M) / 1e3

    @property
    def apogee_km(self) -> float:
        return (self.a_m * (1 + self.e) - R_EARTH_M) / 1e3


@dataclass
class Decay:
    """A decay's history (days, km) and its lifetime (None: still in orbit at `max_years`)."""
    t_days: np.ndarray
    perigee_km: np.ndarray
    apogee_km: np.ndarray
    lifetime_days: float | None
    steps: int
    extra: dict = field(default_factory=dict)

    @property
    def lifetime_years(self) -> float | None:
        return None if self.lifetime_days is None else self.lifetime_days / YEAR_DAYS


class _Density:
    """ρ(h, t) from a schedule: one ln ρ profile per month (or one for all time)."""

    def __init__(self, schedule: act.Schedule, inclination_deg: float, max_days: float) -> None:
        self.schedule = schedule
        if schedule.constant:
            from .atmosphere import Activity
            self.profiles = log_density_profile(Activity(float(schedule.f107_sfu[0]), float(schedule.f107a_sfu[0]),
                                                         float(schedule.ap[0])), inclination_deg)[None, :]
        else:
            n = min(len(schedule.ap), int(max_days / act.DAYS_PER_MONTH) + 2)
            self.profiles = log_density_profiles(schedule.f107_sfu[:n], schedule.f107a_sfu[:n], schedule.ap[:n],
                                                 inclination_deg)

    def __call__(self, h_km: np.ndarray, t_days: float) -> np.ndarray:
        k = 0 if len(self.profiles) == 1 else min(int(t_days / act.DAYS_PER_MONTH), len(self.profiles) - 1)
        return density_kgm3(self.profiles[k], h_km)


def rates(a_m: float, e: float, cos_i: float, b_m2kg: float, rho: Callable[[np.ndarray], np.ndarray]):
    """Orbit-averaged (da/dt m/s, de/dt 1/s) under drag (module docstring)."""
    one = 1.0 - e * _COS_E
    r = a_m * one
    v2 = MU_EARTH_M3S2 * (2.0 / r - 1.0 / a_m)
    v = np.sqrt(v2)
    h = math.sqrt(MU_EARTH_M3S2 * a_m * (1.0 - e * e))
    f = 1.0 - OMEGA_EARTH_RADPS * h * cos_i / v2
    a_t = -0.5 * rho((r - R_EARTH_M) / 1e3) * b_m2kg * v2 * f * f
    w = one / _NODES                                   # dM = (1 − e cos E) dE
    da = float(np.dot(w, 2.0 * a_m * a_m * v * a_t / MU_EARTH_M3S2))
    cos_nu = (_COS_E - e) / one
    de = float(np.dot(w, 2.0 * (e + cos_nu) * a_t / v))
    return da, de


def j2_rates_radps(a_m: float, e: float, inclination_deg: float) -> tuple[float, float]:
    """Secular dΩ/dt, dω/dt (rad/s) of J2."""
    n = math.sqrt(MU_EARTH_M3S2 / a_m ** 3)
    k = n * J2 * (R_EARTH_M / (a_m * (1 - e * e))) ** 2
    c = math.cos(math.radians(inclination_deg))
    return -1.5 * k * c, 0.75 * k * (5 * c * c - 1)


def decay(orbit: Orbit, b_m2kg: float, schedule: act.Schedule, *, reentry_km: float = REENTRY_KM,
          max_years: float = 200.0, max_step_days: float | None = None, max_da_m: float = 2000.0,
          progress: Callable[[float], None] | None = None) -> Decay:
    """Decay `orbit` with ballistic coefficient `b_m2kg` (C_D A / m) until its perigee reaches
    `reentry_km` or `max_years` pass. `progress(fraction)` is called as the perigee comes down.
    Steps lower a by at most `max_da_m` and last at most `max_step_days` (default 30 days for constant
    activity, 5 days for a monthly schedule)."""
    if max_step_days is None:
        max_step_days = 30.0 if schedule.constant else 5.0
    max_days = max_years * YEAR_DAYS
    dens = _Density(schedule, orbit.inclination_deg, max_days)
    cos_i = math.cos(math.radians(orbit.inclination_deg))
    a, e, t = orbit.a_m, orbit.e, 0.0
    rp_stop = R_EARTH_M + reentry_km * 1e3
    hp0 = orbit.perigee_km
    ts, hp, ha = [0.0], [orbit.perigee_km], [orbit.apogee_km]
    steps = 0
    lifetime = None

    def f(t_d, a_, e_):
        def rho(h):
            return dens(h, t_d)
        da, de = rates(a_, max(e_, 0.0), cos_i, b_m2kg, rho)
        return da * DAY_S, de * DAY_S          # per day

    while t < max_days:
        da0, de0 = f(t, a, e)
        dt = max_step_days if da0 == 0 else min(max_step_days, max_da_m / abs(da0))
        dt = min(dt, max_days - t)
        k1 = (da0, de0)
        k2 = f(t + dt / 2, a + dt / 2 * k1[0], e + dt / 2 * k1[1])
        k3 = f(t + dt / 2, a + dt / 2 * k2[0], e + dt / 2 * k2[1])
        k4 = f(t + dt, a + dt * k3[0], e + dt * k3[1])
        a_new = a + dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        e_new = max(e + dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1]), 0.0)
        steps += 1
        rp_old, rp_new = a * (1 - e), a_new * (1 - e_new)
        if rp_new <= rp_stop or a_new * (1 - e_new) < R_EARTH_M + ALT_GRID_KM[0] * 1e3:
            x = (rp_old - rp_stop) / (rp_old - rp_new) if rp_old > rp_new else 1.0
            lifetime = t + min(max(x, 0.0), 1.0) * dt
            ts.append(lifetime)
            hp.append(reentry_km)
            ha.append((a + x * (a_new - a)) * (1 + e + x * (e_new - e)) / 1e3 - R_EARTH_M / 1e3)
            break
        a, e, t = a_new, e_new, t + dt
        ts.append(t)
        hp.append((a * (1 - e) - R_EARTH_M) / 1e3)
        ha.append((a * (1 + e) - R_EARTH_M) / 1e3)
        if progress is not None:
            progress(min(1.0, (hp0 - hp[-1]) / max(hp0 - reentry_km, 1e-9)))
    if progress is not None and lifetime is not None:
        progress(1.0)
    return Decay(np.array(ts), np.array(hp), np.array(ha), lifetime, steps)
