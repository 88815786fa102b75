"""Circular Keplerian orbit and the ECI <-> ECEF rotation.

Scope and simplifications (deliberate, for a magnetometer simulator):

* Two-body circular orbit; no J2, drag or third bodies. Altitude is measured
  from the WGS-84 equatorial radius, ``r = A_WGS84_M + altitude`` (so a
  "485 km" orbit has ``r = 6863.137 km`` everywhere along the orbit).
* ECI is treated as J2000 and ECEF is obtained by a single rotation about the
  common z axis by the Earth rotation angle ``era0 + OMEGA_EARTH_RADPS * t``.
  Precession, nutation and polar motion are ignored (together well under 1° over
  a mission of days, far below the accuracy of a degree-1 field model).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "MU_EARTH_M3S2",
    "R_EARTH_M",
    "A_WGS84_M",
    "F_WGS84",
    "OMEGA_EARTH_RADPS",
    "CircularOrbit",
    "earth_rotation_angle_rad",
    "eci_to_ecef_matrix",
    "eci_to_ecef",
    "ecef_to_eci",
]

MU_EARTH_M3S2 = 3.986004418e14
"""Earth's gravitational parameter GM [m³/s²] (WGS-84 / IERS 2010)."""

R_EARTH_M = 6371200.0
"""IGRF reference radius a = 6371.2 km [m]; the radius of the field model's expansion."""

A_WGS84_M = 6378137.0
"""WGS-84 equatorial radius [m]; altitude of a circular orbit is measured from it."""

F_WGS84 = 1.0 / 298.257223563
"""WGS-84 flattening."""

OMEGA_EARTH_RADPS = 7.2921150e-5
"""Earth's sidereal rotation rate [rad/s] (WGS-84); one turn in 86164.09 s."""


class CircularOrbit:
    """Circular orbit in ECI given by altitude, inclination, RAAN and the argument of latitude at t = 0.

    Position at time t (argument of latitude ``u = u0 + n t``)::

        r_ECI = r · Rz(Ω) Rx(i) [cos u, sin u, 0]ᵀ

    with ``r = A_WGS84_M + altitude_m`` and mean motion ``n = sqrt(μ / r³)``.
    ``t_s`` may be a scalar (returns shape (3,)) or an array of N times (returns (N, 3)).
    """

    def __init__(
        self,
        altitude_m: float,
        inclination_deg: float,
        raan_deg: float = 0.0,
        arg_lat0_deg: float = 0.0,
    ) -> None:
        if not np.isfinite(altitude_m) or altitude_m <= 0.0:
            raise ValueError(f"altitude_m must be positive and finite, got {altitude_m!r}")
        if not 0.0 <= inclination_deg <= 180.0:
            raise ValueError(f"inclination_deg must be within [0, 180], got {inclination_deg!r}")
        self.altitude_m = float(altitude_m)
        self.inclination_deg = float(inclination_deg)
        self.raan_deg = float(raan_deg)
        self.arg_lat0_deg = float(arg_lat0_deg)
        self.radius_m = A_WGS84_M + self.altitude_m
        self.mean_motion_radps = float(np.sqrt(MU_EARTH_M3S2 / self.radius_m**3))
        self.period_s = 2.0 * np.pi / self.mean_motion_radps
        i, raan = np.radians(self.inclination_deg), np.radians(self.raan_deg)
        # columns: in-plane unit vectors P (towards u = 0, the ascending node) and Q (u = 90°)
        self._p_hat = np.array([np.cos(raan), np.sin(raan), 0.0])
        self._q_hat = np.array([-np.sin(raan) * np.cos(i), np.cos(raan) * np.cos(i), np.sin(i)])
        self._u0_rad = np.radians(self.arg_lat0_deg)

    def arg_lat_rad(self, t_s: float | np.ndarray) -> float | np.ndarray:
        """Argument of latitude u(t) = u0 + n t [rad] (not wrapped)."""
        return self._u0_rad + self.mean_motion_radps * np.asarray(t_s, dtype=float)

    def position_eci_m(self, t_s: float | np.ndarray) -> np.ndarray:
        """Position in ECI [m]."""
        u = self.arg_lat_rad(t_s)
        c, s = np.cos(u)[..., None], np.sin(u)[..., None]
        return self.radius_m * (c * self._p_hat + s * self._q_hat)

    def velocity_eci_mps(self, t_s: float | np.ndarray) -> np.ndarray:
        """Velocity in ECI [m/s]; magnitude sqrt(μ/r)."""
        u = self.arg_lat_rad(t_s)
        c, s = np.cos(u)[..., None], np.sin(u)[..., None]
        return (self.radius_m * self.mean_motion_radps) * (-s * self._p_hat + c * self._q_hat)


def earth_rotation_angle_rad(t_s: float | np.ndarray, era0_rad: float = 0.0) -> float | np.ndarray:
    """Angle of the ECI -> ECEF rotation about z: ``era0 + OMEGA_EARTH_RADPS · t``, wrapped to [0, 2π).

    ``era0_rad`` is the angle at t = 0 (the Greenwich meridian's right ascension);
    precession, nutation and polar motion are ignored.
    """
    return np.mod(era0_rad + OMEGA_EARTH_RADPS * np.asarray(t_s, dtype=float), 2.0 * np.pi)


def eci_to_ecef_matrix(t_s: float, era0_rad: float = 0.0) -> np.ndarray:
    """Rotation matrix C with ``v_ECEF = C v_ECI`` (= Rz(θ)ᵀ, θ the Earth rotation angle)."""
    theta = earth_rotation_angle_rad(t_s, era0_rad)
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def _rotate_z(v: np.ndarray, angle_rad: float | np.ndarray) -> np.ndarray:
    """Active rotation of vectors v (..., 3) about z by angle (scalar or broadcastable to v[..., 0])."""
    v = np.asarray(v, dtype=float)
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.stack((c * x - s * y, s * x + c * y, np.broadcast_to(z, np.broadcast(x, c).shape)), axis=-1)


def eci_to_ecef(v_eci: np.ndarray, t_s: float | np.ndarray, era0_rad: float = 0.0) -> np.ndarray:
    """Express ECI vector(s) (..., 3) in ECEF at time(s) t_s (scalar, or one per vector)."""
    return _rotate_z(v_eci, -earth_rotation_angle_rad(t_s, era0_rad))


def ecef_to_eci(v_ecef: np.ndarray, t_s: float | np.ndarray, era0_rad: float = 0.0) -> np.ndarray:
    """Express ECEF vector(s) (..., 3) in ECI at time(s) t_s (scalar, or one per vector)."""
    return _rotate_z(v_ecef, earth_rotation_angle_rad(t_s, era0_rad))


class TleOrbit:
    """An orbit propagated by SGP4 (``sgp4``, Vallado's implementation) from a two-line element set;
    t = 0 is the UTC instant ``utc0`` (a timezone-aware or naive-UTC ``datetime``).

    Frame: positions and velocities are in TEME, the frame SGP4 produces, used as the simulator's
    inertial frame. The Earth-fixed field is turned into it with GMST (IAU 1982, ``sgp4``'s
    ``gstime``, UT1 taken as UTC): ``era0_rad`` is GMST at ``utc0``, and the angle then grows at
    ``OMEGA_EARTH_RADPS`` (the difference from the GMST rate is 8.6e-12 rad/s: 0.04 arcsec a day).
    TEME → ECEF by that one rotation about z is exact up to polar motion (< 0.5 arcsec).
    """

    def __init__(self, line1: str, line2: str, utc0) -> None:
        from sgp4.api import SGP4_ERRORS, Satrec, jday
        from sgp4.propagation import gstime

        self.line1, self.line2 = line1, line2
        self.sat = Satrec.twoline2rv(line1, line2)
        self.utc0 = utc0
        self.jd0, self.fr0 = jday(utc0.year, utc0.month, utc0.day, utc0.hour, utc0.minute,
                                  utc0.second + utc0.microsecond * 1e-6)
        self.era0_rad = float(gstime(self.jd0 + self.fr0))
        self._errors = SGP4_ERRORS
        e, r, _ = self.sat.sgp4(self.jd0, self.fr0)
        if e:
            raise ValueError(f"SGP4 cannot propagate this TLE to {utc0}: {SGP4_ERRORS.get(e, e)}")
        self.mean_motion_radps = self.sat.no_kozai / 60.0
        self.period_s = 2.0 * np.pi / self.mean_motion_radps
        self.radius_m = float(self.sat.a * self.sat.radiusearthkm * 1e3)
        self.altitude_m = self.radius_m - A_WGS84_M
        self.inclination_deg = float(np.degrees(self.sat.inclo))
        self.epoch_age_s = float((self.jd0 - self.sat.jdsatepoch + self.fr0 - self.sat.jdsatepochF) * 86400.0)

    def _propagate(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        jd = np.full(t.shape, self.jd0)
        err, r_km, v_kms = self.sat.sgp4_array(jd, self.fr0 + t / 86400.0)
        if np.any(err):
            raise ValueError(f"SGP4: {self._errors.get(int(err[err != 0][0]), 'error')}")
        return r_km * 1e3, v_kms * 1e3

    def position_eci_m(self, t_s: float | np.ndarray) -> np.ndarray:
        """Position in TEME [m]; a scalar time gives (3,), N times (N, 3)."""
        r, _ = self._propagate(t_s)
        return r[0] if np.ndim(t_s) == 0 else r

    def velocity_eci_mps(self, t_s: float | np.ndarray) -> np.ndarray:
        """Velocity in TEME [m/s]."""
        _, v = self._propagate(t_s)
        return v[0] if np.ndim(t_s) == 0 else v
