"""An independent check of `ground.lifetime.decay`: the full equations of motion (two-body + J2 +
drag against the co-rotating atmosphere) in ECI, step-integrated with scipy's `solve_ivp` (DOP853),
with the same atmosphere (the product's orbit-averaged NRLMSIS profile as ρ(h), h = |r| − R).

Nothing of the decay's averaging is shared: no mean elements, no quadrature, no King-Hele factor.
The start: at the ascending node with the circular speed, the radius shot (two passes over the first
revolutions without drag) so that the time-mean radius is the decay's mean semi-major axis (the
decay's `a` is the mean radius of a circular orbit; the osculating a of a J2 orbit is kilometres off).
Re-entry: the first time |r| − R reaches the re-entry height.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp

from ground.lifetime.atmosphere import ALT_GRID_KM, R_EARTH_M

MU = 3.986004418e14
J2 = 1.08262668e-3
OMEGA_E = 7.292115e-5


def make_rhs(log_rho: np.ndarray, b_m2kg: float):
    alt = ALT_GRID_KM.tolist()
    lr = log_rho.tolist()
    slope0 = (lr[1] - lr[0]) / (alt[1] - alt[0])
    interp = np.interp

    def rhs(t, y):
        x, yy, z, vx, vy, vz = y
        r2 = x * x + yy * yy + z * z
        r = math.sqrt(r2)
        mu_r3 = MU / (r2 * r)
        k = 1.5 * J2 * MU * R_EARTH_M ** 2 / (r2 * r2 * r)
        zz = 5.0 * z * z / r2
        ax = -mu_r3 * x - k * x * (1.0 - zz)
        ay = -mu_r3 * yy - k * yy * (1.0 - zz)
        az = -mu_r3 * z - k * z * (3.0 - zz)
        if b_m2kg > 0:
            h = (r - R_EARTH_M) / 1e3
            lrho = lr[0] + (h - alt[0]) * slope0 if h < alt[0] else float(interp(h, alt, lr))
            rho = math.exp(lrho)
            ux, uy, uz = vx + OMEGA_E * yy, vy - OMEGA_E * x, vz       # v − ω × r
            q = -0.5 * rho * b_m2kg * math.sqrt(ux * ux + uy * uy + uz * uz)
            ax += q * ux
            ay += q * uy
            az += q * uz
        return (vx, vy, vz, ax, ay, az)

    return rhs


def _state(r0: float, inc_rad: float) -> np.ndarray:
    v0 = math.sqrt(MU / r0)
    return np.array([r0, 0.0, 0.0, 0.0, v0 * math.cos(inc_rad), v0 * math.sin(inc_rad)])


def mean_radius(y0: np.ndarray, revs: int = 3) -> float:
    """Time-mean |r| over `revs` revolutions without drag."""
    period = 2 * math.pi * math.sqrt(np.linalg.norm(y0[:3]) ** 3 / MU)
    rhs = make_rhs(np.zeros(len(ALT_GRID_KM)), 0.0)
    t = np.linspace(0, revs * period, 400 * revs, endpoint=False)
    sol = solve_ivp(rhs, (0, revs * period), y0, method="DOP853", rtol=1e-11, atol=1e-4, t_eval=t)
    return float(np.linalg.norm(sol.y[:3], axis=0).mean())


def start_state(a_mean_m: float, inclination_deg: float) -> np.ndarray:
    inc = math.radians(inclination_deg)
    r0 = a_mean_m
    for _ in range(2):
        r0 += a_mean_m - mean_radius(_state(r0, inc))
    return _state(r0, inc)


def lifetime_days(a_mean_m: float, inclination_deg: float, log_rho: np.ndarray, b_m2kg: float,
                  reentry_km: float, max_days: float, rtol: float = 1e-9) -> float:
    """Days from the start to |r| − R = reentry_km, integrating the full equations of motion."""
    y0 = start_state(a_mean_m, inclination_deg)
    rhs = make_rhs(log_rho, b_m2kg)

    def down(t, y):
        return math.sqrt(y[0] ** 2 + y[1] ** 2 + y[2] ** 2) - R_EARTH_M - reentry_km * 1e3
    down.terminal = True
    down.direction = -1
    sol = solve_ivp(rhs, (0.0, max_days * 86400.0), y0, method="DOP853", rtol=rtol, atol=1e-3, events=down)
    if not sol.t_events[0].size:
        raise AssertionError(f"no re-entry within {max_days} days")
    return float(sol.t_events[0][0]) / 86400.0
