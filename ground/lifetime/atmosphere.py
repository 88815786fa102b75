"""The thermosphere's density for orbit decay: NRLMSIS 2.1 (through `pymsis`), averaged so that an
orbit-averaged decay can use it as a function of altitude alone.

What is averaged: for each altitude on a 10 km grid (100-1,500 km), the mass density of NRLMSIS 2.1
over 8 local times (longitudes 0-315° at 00:00 UTC), the latitudes an orbit of the given inclination
crosses (arguments of latitude at 6 points of a quarter orbit, both hemispheres) and two dates (the
March equinox and the June solstice, 2001; with both hemispheres these stand for the four seasons).
The result is the density an orbit meets on average as its plane turns through local time and season
(which J2 and the year do over the months of a decay). Densities between grid altitudes are
interpolated in log ρ; between activity levels (a solar-cycle run) in log ρ over F10.7 and Ap.

Altitudes here are heights above a sphere of radius `R_EARTH_M` (the equatorial radius), the same
height the decay uses (r − R), passed to NRLMSIS as geodetic heights.

Activity: F10.7 (daily, sfu; of the previous day), F10.7a (81-day mean, sfu) and the daily Ap are given
to NRLMSIS explicitly, so pymsis never reads or downloads its space-weather file. The values accepted
are those NRLMSIS is meant for: F10.7 and F10.7a within 60-300 sfu, Ap within 0-400; anything outside
is an :class:`ActivityError` naming the value.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from fsw.estimation.field_motion import A_WGS84_M

#: heights are r − R_EARTH_M: the WGS84 equatorial radius
R_EARTH_M = A_WGS84_M
ALT_GRID_KM = np.arange(100.0, 1501.0, 10.0)
F107_RANGE_SFU = (60.0, 300.0)
AP_RANGE = (0.0, 400.0)
_DATES = np.array(["2001-03-20T00:00", "2001-06-21T00:00"], dtype="datetime64[m]")
_LONS_DEG = np.arange(0.0, 360.0, 45.0)


class ActivityError(ValueError):
    """Solar or geomagnetic activity outside the range the atmosphere model covers."""


@dataclass(frozen=True)
class Activity:
    """Solar and geomagnetic activity: F10.7 (sfu), its 81-day mean F10.7a (sfu), daily Ap."""
    f107_sfu: float
    f107a_sfu: float
    ap: float

    def check(self, what: str = "activity") -> "Activity":
        lo, hi = F107_RANGE_SFU
        for name, v in (("F10.7", self.f107_sfu), ("F10.7a", self.f107a_sfu)):
            if not (math.isfinite(v) and lo <= v <= hi):
                raise ActivityError(f"{what}: {name} = {v:g} sfu is outside NRLMSIS's range {lo:g}-{hi:g} sfu")
        lo, hi = AP_RANGE
        if not (math.isfinite(self.ap) and lo <= self.ap <= hi):
            raise ActivityError(f"{what}: Ap = {self.ap:g} is outside NRLMSIS's range {lo:g}-{hi:g}")
        return self


def _latitudes_deg(inclination_deg: float) -> np.ndarray:
    """Latitudes an orbit of this inclination spends equal times at (6 per quarter, both hemispheres)."""
    u = (np.arange(6) + 0.5) * (math.pi / 2) / 6
    i = math.radians(inclination_deg)
    lat = np.degrees(np.arcsin(math.sin(i) * np.sin(u)))
    return np.concatenate([lat, -lat])


@functools.lru_cache(maxsize=64)
def _log_profile(f107_sfu: float, f107a_sfu: float, ap: float, inclination_deg: float) -> np.ndarray:
    from pymsis import msis

    n = len(_DATES)
    out = msis.calculate(_DATES, _LONS_DEG, _latitudes_deg(inclination_deg), ALT_GRID_KM,
                         f107s=[f107_sfu] * n, f107as=[f107a_sfu] * n, aps=[[ap] * 7] * n, version=2.1)
    rho = out[..., 0].mean(axis=(0, 1, 2))          # kg/m³, (alts,)
    if not np.all(np.isfinite(rho)) or np.any(rho <= 0):
        raise ActivityError(f"NRLMSIS gave no density for F10.7 {f107_sfu:g}, Ap {ap:g}")
    return np.log(rho)


def log_density_profile(activity: Activity, inclination_deg: float) -> np.ndarray:
    """ln ρ (kg/m³) on `ALT_GRID_KM` for constant activity, averaged as the module docstring says."""
    a = activity.check()
    # rounded so that nearby calls share the cache (0.01 sfu, 0.01 Ap, 0.1°: far below what matters)
    return _log_profile(round(a.f107_sfu, 2), round(a.f107a_sfu, 2), round(a.ap, 2), round(inclination_deg, 1))


# a grid of activity for runs whose activity changes (a solar cycle): log ρ interpolated bilinearly
F107_GRID_SFU = np.arange(60.0, 301.0, 20.0)
AP_GRID = np.array([0.0, 4.0, 8.0, 15.0, 30.0, 60.0, 120.0, 400.0])


def log_density_profiles(f107_sfu: np.ndarray, f107a_sfu: np.ndarray, ap: np.ndarray,
                         inclination_deg: float) -> np.ndarray:
    """ln ρ on `ALT_GRID_KM` for each of many activity levels (rows), F10.7 taken equal to F10.7a on
    the grid and interpolated in (F10.7a, Ap); each level checked against the model's range."""
    f107a_sfu, ap = np.asarray(f107a_sfu, float), np.asarray(ap, float)
    for k, (f, fa, p) in enumerate(zip(np.asarray(f107_sfu, float), f107a_sfu, ap)):
        Activity(float(f), float(fa), float(p)).check(f"activity at step {k}")
    fi = np.clip(np.searchsorted(F107_GRID_SFU, f107a_sfu) - 1, 0, len(F107_GRID_SFU) - 2)
    ai = np.clip(np.searchsorted(AP_GRID, ap) - 1, 0, len(AP_GRID) - 2)
    tf = (f107a_sfu - F107_GRID_SFU[fi]) / (F107_GRID_SFU[fi + 1] - F107_GRID_SFU[fi])
    ta = (ap - AP_GRID[ai]) / (AP_GRID[ai + 1] - AP_GRID[ai])
    inc = round(inclination_deg, 1)
    need = {(int(f), int(a)) for f0, a0 in zip(fi, ai) for f in (f0, f0 + 1) for a in (a0, a0 + 1)}
    prof = {(f, a): _log_profile(float(F107_GRID_SFU[f]), float(F107_GRID_SFU[f]), float(AP_GRID[a]), inc)
            for f, a in need}
    out = np.empty((len(fi), len(ALT_GRID_KM)))
    for k, (f, a, x, y) in enumerate(zip(fi, ai, tf, ta)):
        out[k] = ((1 - x) * (1 - y) * prof[f, a] + x * (1 - y) * prof[f + 1, a]
                  + (1 - x) * y * prof[f, a + 1] + x * y * prof[f + 1, a + 1])
    return out


def density_kgm3(log_profile: np.ndarray, alt_km):
    """ρ at heights (km) from a ln ρ profile on `ALT_GRID_KM` (log-linear; held beyond the grid's top,
    extrapolated along the lowest interval below 100 km)."""
    h = np.asarray(alt_km, float)
    if h.min() >= ALT_GRID_KM[0]:
        return np.exp(np.interp(h, ALT_GRID_KM, log_profile))
    lo = log_profile[0] + (h - ALT_GRID_KM[0]) * (log_profile[1] - log_profile[0]) / 10.0
    return np.exp(np.where(h < ALT_GRID_KM[0], lo, np.interp(h, ALT_GRID_KM, log_profile)))
