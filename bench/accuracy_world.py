"""The simulated passes of the accuracy benchmark's rows (`bench.accuracy`): its worlds and motions.

Worlds: ``dipole`` — the true field is the IGRF-14 dipole along a 485 km, 97.5° circular orbit with random
node and phase, the very model the estimators are given; ``igrf`` — IGRF-14 to degree 13 along the shipped
``isoi_sgp4`` TLE through SGP4, the host's iron taken out by the box's calibration off by its residual, the
estimators given the onboard model along the box's older TLE at its clock; ``igrf_exact`` — the same truth,
the box knowing it exactly (bench.accuracy's docstring says more). Motions: a free tumble (undirected), one
damped by a discrete −Ḃ law (bdot), an orbital-frame attitude with a libration (orbital). Samples: the true
field plus white noise σ_B, the MMC5983MA's own noise and its 18-bit quantisation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fsw.estimation import field_motion as fm
from fsw.estimation import rotations as rot
from bench.realistic import HOST_RESIDUAL_T, BoxField, HostResidual
from hil import dynamics
from hil.field import DipoleField, FieldAlongOrbit
from hil.orbit import CircularOrbit

ALTITUDE_M, INCLINATION_DEG, EPOCH = 485e3, 97.5, 2025.5
#: the IGRF rows' world: the shipped scenario with a TLE, the box's older TLE and the host's iron; the box's
#: clock this far ahead (the box's calibration residual: bench.realistic.HostResidual)
IGRF_SCENARIO, IGRF_CLOCK_OFFSET_S = "isoi_sgp4", 2.0
WORLDS = ("dipole", "igrf")
#: the IGRF rows' truth with the box knowing it exactly (no field-model, TLE, clock or calibration error):
#: what the world's own geometry costs, apart from what the box's knowledge costs
IGRF_EXACT = "igrf_exact"
CHIP_NOISE_T = 0.04e-6
LSB_T = 1e-4 / 16384.0
BODIES = {"asymmetric": np.diag([175.0, 200.0, 285.0]), "near_symmetric": np.diag([1.0, 1.02, 1.04])}
MODES = {"undirected": (5.0, 28.0), "bdot": (5.0, 23.0), "orbital": (0.5, 3.0)}
BDOT_TAU_S, BDOT_B_NOM_T, BDOT_SAT_RADPS, BDOT_DISTURB_T = 1800.0, 35e-6, math.radians(10.0), 0.3e-6


@dataclass
class Run:
    """One simulated pass: all samples (warm-up and record) with their truth."""

    t_s: np.ndarray
    b_T: np.ndarray
    b_true_T: np.ndarray
    w_true_radps: np.ndarray
    record: slice
    field: fm.OrbitField
    meta: dict = field(default_factory=dict)
    q_true: np.ndarray | None = None   # (N, 4) body → ECI, for the information limit
    #: the 1-σ per axis of the hard iron the box's calibration leaves (None: no host), as the box publishes it
    hard_iron_sigma_T: float | None = None


def _random_unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _measure(b_true: np.ndarray, sigma_T: float, rng) -> np.ndarray:
    noise = rng.normal(scale=math.hypot(sigma_T, CHIP_NOISE_T), size=b_true.shape)
    return np.round((b_true + noise) / LSB_T) * LSB_T


def _igrf_world(rng, drift_tracked: bool = True, exact: bool = False):
    """Truth and the box's view for the IGRF rows (module docstring): (truth field, the box's field,
    the host's residual after the box's calibration); `exact`: the box's field is the truth and no host."""
    from hil import scenario as scenarios
    from hil.field import FieldTable, IgrfField
    from hil.orbit import TleOrbit
    from ground.field import tle_field
    from datetime import timedelta

    scn = scenarios.load(IGRF_SCENARIO)
    start = scn.utc0 + timedelta(seconds=float(rng.uniform(0.0, 86400.0)))
    orbit = TleOrbit(*scn.tle, start)
    truth = FieldAlongOrbit(orbit, IgrfField(EPOCH, 13), orbit.era0_rad)
    table = FieldTable(truth.b_eci_T, step_s=1.0)
    truth_field = type("TruthField", (), {"b_eci_T": staticmethod(table), "orbit": orbit})()
    if exact:
        return truth_field, BoxField(truth_field, 0.0), None
    box = BoxField(tle_field(*(scn.box_tle or scn.tle), start), IGRF_CLOCK_OFFSET_S)
    host = scn.host.with_period(orbit.period_s)
    return truth_field, box, HostResidual(host, rng, drift_tracked=drift_tracked)


def simulate(mode: str, body: str, dt_s: float, sigma_T: float, rng: np.random.Generator, *,
             record_samples: int = 120, warmup_s: float = 300.0, world: str = "dipole",
             drift_tracked: bool = True, inertia_kgm2=None, rate_range_dps=None) -> Run:
    """A seeded pass of `mode` for `body` sampled every `dt_s` with noise `sigma_T` (see the module docstring);
    `world` "dipole" (truth = the estimators' model) or "igrf" (the realistic truth of the IGRF rows;
    `drift_tracked`: the box's calibration follows the hard iron's thermal drift); `inertia_kgm2` (3×3) instead of
    the body's, `rate_range_dps` (lo, hi) instead of the mode's: a campaign's dispersions."""
    lo, hi = MODES[mode] if rate_range_dps is None else rate_range_dps
    raan, u0 = rng.uniform(0, 360), rng.uniform(0, 360)
    host = None
    if world in ("igrf", IGRF_EXACT):  # its own draws, from the node and phase drawn: the rest as the dipole row's
        truth_field, est_field, host = _igrf_world(np.random.default_rng([int(raan * 1e6), int(u0 * 1e6)]),
                                                   drift_tracked, exact=world == IGRF_EXACT)
    else:
        truth_field = FieldAlongOrbit(CircularOrbit(ALTITUDE_M, INCLINATION_DEG, raan, u0), DipoleField(EPOCH))
        est_field = fm.OrbitField(fm.CircularOrbitModel(ALTITUDE_M, INCLINATION_DEG, raan, u0),
                                  fm.DipoleModel(EPOCH))
    n_warm = int(round(warmup_s / dt_s))
    n = n_warm + record_samples
    t = np.arange(n) * dt_s
    b_i = truth_field.b_eci_T(t)
    rate = math.radians(rng.uniform(lo, hi))
    if mode == "orbital":
        b_true, w, q = _orbital(t, truth_field.orbit, b_i, rate, rng)
        b_meas = _measure(b_true, sigma_T, rng)
    else:
        J = BODIES[body] if inertia_kgm2 is None else np.asarray(inertia_kgm2, float)
        b_true, w, b_meas, q = _tumble(t, J, b_i, truth_field, rate, mode == "bdot", sigma_T, rng)
    if host is not None:  # the host's iron in, the box's calibration out (its residual stays)
        b_meas = host(b_meas, t)
    return Run(t, b_meas, b_true, w, slice(n_warm, n), est_field,
               {"mode": mode, "body": body, "dt_s": dt_s, "sigma_uT": sigma_T * 1e6, "raan_deg": raan,
                "arg_lat0_deg": u0, "rate0_dps": math.degrees(rate), "world": world}, q,
               None if host is None else HOST_RESIDUAL_T)


def _tumble(t, J, b_i, truth_field, rate, bdot, sigma_T, rng):
    """Rigid body (hil.dynamics, RK4) between the samples; with `bdot` the discrete −Ḃ law."""
    q0 = rot.quat_normalize(rng.normal(size=4))
    body_ = dynamics.RigidBody(J, q0, _random_unit(rng) * rate)
    n = len(t)
    b_true, w, b_meas = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    q = np.zeros((n, 4))
    k_gain = float(np.trace(J)) / 3.0 / (BDOT_TAU_S * BDOT_B_NOM_T ** 2)
    m_max = k_gain * BDOT_B_NOM_T * BDOT_SAT_RADPS
    m = np.zeros(3)
    for k in range(n):
        if k:
            t0, t1 = t[k - 1], t[k]
            steps = max(1, int(math.ceil((t1 - t0) * max(np.linalg.norm(body_.omega_radps), 1e-3) / 0.03)))
            h = (t1 - t0) / steps
            for j in range(steps):
                M = np.zeros(3)
                if bdot:
                    tm = t0 + (j + 0.5) * h
                    b_body = rot.quat_to_dcm(body_.q).T @ truth_field.b_eci_T(tm)
                    M = np.cross(m, b_body)
                body_.step(h, M)
        b_true[k] = rot.quat_to_dcm(body_.q).T @ b_i[k]
        q[k] = body_.q
        w[k] = body_.omega_radps
        meas = _measure(b_true[k], sigma_T, rng)
        if bdot:
            meas = meas + BDOT_DISTURB_T * m / m_max
            if k:
                m = np.clip(-k_gain * (meas - b_meas[k - 1]) / (t[k] - t[k - 1]), -m_max, m_max)
        b_meas[k] = meas
    return b_true, w, b_meas, q


def _orbital(t, orbit, b_i, rate, rng):
    """Orbital-frame attitude with a libration; ω from the attitude by central differences."""
    periods = rng.uniform(40.0, 120.0, size=3)
    phases = rng.uniform(0, 2 * math.pi, size=3)
    weights = rng.dirichlet(np.ones(3))
    # RMS of θ̇ᵢ = aᵢ 2π/Tᵢ / √2; Σ over axes = rate²
    amp = np.sqrt(weights) * rate * math.sqrt(2.0) * periods / (2 * math.pi)

    def dcm(tt):
        r = orbit.position_eci_m(tt)
        v = orbit.velocity_eci_mps(tt)
        x = v / np.linalg.norm(v)
        z = -r / np.linalg.norm(r)
        y = np.cross(z, x)
        R_lo = np.column_stack([x, y, z])
        return R_lo @ rot.so3_exp(amp * np.sin(2 * math.pi * tt / periods + phases))

    n = len(t)
    b_true, w, q = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 4))
    h = 1e-3
    for k in range(n):
        R = dcm(t[k])
        b_true[k] = R.T @ b_i[k]
        q[k] = rot.quat_from_dcm(R)
        dR = dcm(t[k] - h).T @ dcm(t[k] + h)
        w[k] = rot.quat_log(rot.quat_from_dcm(dR)) / (2 * h)
    return b_true, w, q
