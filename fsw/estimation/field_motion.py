"""The geomagnetic field along the orbit, for the estimators that remove the field-motion floor.

A rate estimator that takes the field as fixed in inertial space reads the field's own turning as a
body rate: along a LEO orbit B_I turns at about twice the orbital rate (0.1–0.2 °/s), which is the
floor sedelnikov2024 notes in orbital-orientation mode. Given the orbit and a field model, B_I(t) is
known and the attitude filter (attitude_kalman.AttitudeRateKalman) predicts B_body = Rᵀ B_I(t) instead.

Flight code does not import the simulator: the field model here is the same IGRF-14 degree-1
(centred tilted dipole) as hil/field.py and the circular orbit the same as hil/orbit.py
(tests/test_kalman.py checks that they agree); a TLE orbit uses sgp4 (TEME taken as inertial: the
frame's slow precession does not change how fast the field turns).

Conventions: ECI axes, tesla, seconds from the flight software's time origin; the Earth rotation angle
at t = 0 is `era0_rad` (the simulator's convention, 0 by default).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MU_EARTH_M3S2 = 3.986004418e14
A_WGS84_M = 6378137.0
R_REF_M = 6371200.0            # IGRF reference radius
OMEGA_EARTH_RADPS = 7.2921150e-5

# IGRF-14 degree-1 Gauss coefficients (g10, g11, h11) [nT] and secular variation [nT/yr]
_DGRF2020 = (-29403.41, -1451.37, 4653.35)
_IGRF2025 = (-29350.0, -1410.3, 4545.5)
_SV2025 = (12.6, 10.0, -21.5)


def igrf14_degree1_nT(epoch_year: float) -> tuple[float, float, float]:
    """(g10, g11, h11) of IGRF-14 at a decimal year in [2020, 2030] (interpolated / extrapolated)."""
    if not 2020.0 <= epoch_year <= 2030.0:
        raise ValueError(f"epoch_year {epoch_year!r} outside the IGRF-14 span used here [2020, 2030]")
    if epoch_year >= 2025.0:
        return tuple(c + s * (epoch_year - 2025.0) for c, s in zip(_IGRF2025, _SV2025))
    w = (epoch_year - 2020.0) / 5.0
    return tuple((1 - w) * a + w * b for a, b in zip(_DGRF2020, _IGRF2025))


class DipoleModel:
    """Centred tilted dipole: B = a³ (3 (g·r̂) r̂ − g) / r³ with g = (g11, h11, g10) in ECEF axes."""

    def __init__(self, epoch_year: float = 2025.0) -> None:
        g10, g11, h11 = igrf14_degree1_nT(epoch_year)
        self.g_T = 1e-9 * np.array([g11, h11, g10])

    def b_ecef_T(self, r_ecef_m: np.ndarray) -> np.ndarray:
        r = np.asarray(r_ecef_m, float)
        rn = np.linalg.norm(r, axis=-1, keepdims=True)
        rh = r / rn
        return (R_REF_M / rn) ** 3 * (3.0 * np.sum(self.g_T * rh, axis=-1, keepdims=True) * rh - self.g_T)


@dataclass(frozen=True)
class CircularOrbitModel:
    """r_ECI(t) = r · Rz(Ω) Rx(i) [cos u, sin u, 0]ᵀ, u = u₀ + n t, r = a_WGS84 + altitude."""

    altitude_m: float
    inclination_deg: float
    raan_deg: float = 0.0
    arg_lat0_deg: float = 0.0

    def position_eci_m(self, t_s) -> np.ndarray:
        r = A_WGS84_M + self.altitude_m
        n = math.sqrt(MU_EARTH_M3S2 / r ** 3)
        i, raan = math.radians(self.inclination_deg), math.radians(self.raan_deg)
        p = np.array([math.cos(raan), math.sin(raan), 0.0])
        q = np.array([-math.sin(raan) * math.cos(i), math.cos(raan) * math.cos(i), math.sin(i)])
        u = math.radians(self.arg_lat0_deg) + n * np.asarray(t_s, float)
        return r * (np.cos(u)[..., None] * p + np.sin(u)[..., None] * q)


class TleOrbitModel:
    """An orbit from a two-line element set (SGP4); t = 0 is the UTC instant (`year`, ..., `second`).

    Positions are TEME, taken as inertial. Also gives the Earth rotation angle at t = 0 (GMST), which
    :class:`OrbitField` needs to turn the Earth-fixed field model.
    """

    def __init__(self, line1: str, line2: str, utc0: tuple[int, int, int, int, int, float]) -> None:
        from sgp4.api import jday

        from .tle import parse_tle
        self.sat = parse_tle(line1, line2).satrec()  # TleError (a ValueError) for two lines that are not a TLE
        self.jd0, self.fr0 = jday(*utc0)
        self.era0_rad = gmst_rad(self.jd0 + self.fr0)

    def position_eci_m(self, t_s) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_s, float))
        jd = np.full(t.shape, self.jd0)
        fr = self.fr0 + t / 86400.0
        err, r_km, _ = self.sat.sgp4_array(jd, fr)
        if np.any(err):
            raise ValueError(f"SGP4 error codes {sorted(set(err[err != 0].tolist()))}")
        r = r_km * 1e3
        return r[0] if np.ndim(t_s) == 0 else r


def gmst_rad(jd_ut1):
    """Greenwich mean sidereal time (IAU 1982, as in Vallado), radians (a float, or an array for an array)."""
    tu = (np.asarray(jd_ut1, float) - 2451545.0) / 36525.0
    g = (67310.54841 + (876600.0 * 3600.0 + 8640184.812866) * tu + 0.093104 * tu ** 2
         - 6.2e-6 * tu ** 3)
    rad = np.radians((g % 86400.0) / 240.0)
    return float(rad) if rad.ndim == 0 else rad


def rot_z(v: np.ndarray, angle) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.stack((c * x - s * y, s * x + c * y, z + 0.0 * c), axis=-1)


class OrbitField:
    """B_I(t) in ECI [T] along an orbit: the Earth-fixed field model turned with the Earth.

    `orbit` has `position_eci_m(t)`; `field` has `b_ecef_T(r_ecef)`; `era0_rad` is the Earth rotation
    angle at t = 0 (taken from a TLE orbit when it has one).
    """

    def __init__(self, orbit, field=None, era0_rad: float | None = None) -> None:
        self.orbit = orbit
        self.field = field or DipoleModel()
        self.era0_rad = float(era0_rad if era0_rad is not None else getattr(orbit, "era0_rad", 0.0))

    def b_eci_T(self, t_s) -> np.ndarray:
        t = np.asarray(t_s, float)
        theta = self.era0_rad + OMEGA_EARTH_RADPS * t
        r_ecef = rot_z(self.orbit.position_eci_m(t), -theta)
        return rot_z(self.field.b_ecef_T(r_ecef), theta)

    __call__ = b_eci_T

    def turn_rate_radps(self, t_s, dt_s: float = 1.0) -> np.ndarray:
        """How fast the field's direction turns in inertial space, |B̂(t + dt) × B̂(t)| / dt."""
        a, b = self.b_eci_T(t_s), self.b_eci_T(np.asarray(t_s) + dt_s)
        a = a / np.linalg.norm(a, axis=-1, keepdims=True)
        b = b / np.linalg.norm(b, axis=-1, keepdims=True)
        return np.linalg.norm(np.cross(a, b), axis=-1) / dt_s
