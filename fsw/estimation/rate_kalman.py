"""The onboard rate filter: Kalman filtering of the body rate from magnetometer samples with the field
taken as fixed in inertial space over a step (causal; also the ground's quick estimate).

Model (physics-and-seeds.md §2). The field in body axes is B = Rᵀ B_I with R = R_bodyToInertial, so

    dB/dt = B × ω + Rᵀ dB_I/dt,      J ω̇ + ω × (J ω) = M.

The Boer formula sees only the part of ω perpendicular to B; a filter that carries ω as a state also
gets the part along B, from how the perpendicular part turns as B moves in the body.

:class:`RateKalman`: state x = [B (3), ω (3)]; B turns rigidly over a step, B_{k+1} = exp(−[ω Δt]ₓ) B_k
(exact for constant ω, any angle per step). ω is a random walk whose strength follows the physics of a
torque-free body: |ω̇| = |J⁻¹(ω × Jω)| ≤ κ|ω|² with κ ≈ 0.5 for bodies with principal moments within a
factor of two. Its predict and update are compiled pure functions over (x, P) in
:mod:`fsw.estimation.rate_kf`; this module is the thin stateful wrapper (no array is created per step:
see the class docstring). The attitude filter, which removes the fixed-field floor and follows Euler's
equations, is in :mod:`fsw.estimation.attitude_kalman`; banks of it in :mod:`fsw.estimation.filter_banks`.

Units inside: field in µT (so that P is well scaled), rate in rad/s, time in s; the public interfaces
take tesla.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import rate_kf
from .rate_formulas import SIGMA_UNOBSERVED_RADPS, unobserved_sigma

UT_PER_T = 1e6
#: Flags, same bit values as DEBRIS_ESTIMATE_FLAGS in the telemetry dialect.
PERPENDICULAR_ONLY, DEGENERATE, NO_ESTIMATE, DATA_GAP = 1, 2, 4, 8


@dataclass
class RateKalmanTuning:
    """Process and initial uncertainty of :class:`RateKalman` (SI units).

    kappa: |ω̇| ≤ κ|ω|² for a torque-free body; the random walk of ω has per-step variance
      (κ|ω|²Δt)²/3 per axis, which matches the Euler term's change over one step. κ = 0.5 covers
      principal moments within a factor of two (Aist-2D: 0.49); a near-symmetric body needs less.
    rate_accel_radps2: floor of the rate's change per second (external torques, an actuator).
    rate_time_constant_s: an optional pull of ω to zero (Ornstein–Uhlenbeck; a component nothing observes
      then stays bounded); off by default, since it biases a constant rate towards zero.
    field_rate_radps: how fast the field may turn in inertial space (about twice the orbital rate,
      ≈2.3e-3 rad/s in LEO) — a random walk of B on top of the rigid rotation.
    sigma_rate0_radps: 1-σ of the rate before the first estimate.
    adapt_samples, adapt_max, adapt_min: the process noise is scaled by a factor f ∈ [adapt_min,
      adapt_max] that follows the innovations (an exponential mean of NIS/3 over about `adapt_samples`
      samples: f doubles while it exceeds 1.5, shrinks by 1.25 while it is below 0.7). Above 1 it scales
      the floor: a body driven by torques the model does not know (flywheels, magnetorquers) gets the
      process noise it needs, and an honest σ, without hand tuning. Below 1 it scales the whole: the
      κ bound is sized for moments up to 2× apart, and a near-symmetric body's rate changes far less
      (accuracy benchmark, the 16 near-symmetric tumbling rows: RMS ×0.51–0.90 of what the fixed bound
      gives, 1-σ coverage 89–99 % → 59–81 %; the realistic slow heavy tumble 64 → 77 %, RMS +0.7 %). From
      1/256 back to 1 takes eight samples of large innovations.
    max_step_angle_rad: a step longer than this many radians of rotation at the current rate (or than
      `max_gap_s`) restarts the filter: beyond about half a turn the samples cannot say which way B went.
    sigma_flag_radps: an axis whose 1-σ exceeds this is reported DEGENERATE (not to be trusted).
    """

    kappa: float = 0.5
    rate_accel_radps2: float = 1e-4
    rate_time_constant_s: float = math.inf
    field_rate_radps: float = 2.5e-3
    sigma_rate0_radps: float = 0.5
    max_step_angle_rad: float = 2.5
    max_gap_s: float = 60.0
    gap_factor: float = 1.8
    sigma_flag_radps: float = 0.1
    nis_reset: float = 1e4
    adapt_samples: float = 10.0
    adapt_max: float = 1e4
    adapt_min: float = 1.0 / 256


class RateKalman:
    """Onboard Kalman filter of ω from B samples, one sample at a time (full vector, with 1-σ).

    Interface as the streaming formulas (fsw/estimation/rate_formulas.py): :meth:`update` with a
    sample, then `omega_radps`, `sigma_radps` (1-σ per axis), `flags`, `t_s`.

    The step is :func:`fsw.estimation.rate_kf.predict` and :func:`~fsw.estimation.rate_kf.update`
    (compiled, in place) on x = [B (µT), ω (rad/s)] and the 6×6 P this wrapper owns, with work arrays
    allocated once here: a step creates no array. The field's rotation over a step is exact (Rodrigues)
    and its Jacobian closed form: F = [[E, G], [0, I]], E = exp(−[ωΔt]ₓ), G = Δt [B⁻]ₓ J_r(ωΔt).
    """

    PERPENDICULAR_ONLY, DEGENERATE, NO_ESTIMATE, DATA_GAP = PERPENDICULAR_ONLY, DEGENERATE, NO_ESTIMATE, DATA_GAP
    #: estimates after a data gap that the flight software should widen: none, the filter's own
    #: propagation across the gap widens σ (fsw/flight.py, sample_gate.mark_gap)
    gap_history = 0

    def __init__(self, sigma_b_T: float, tuning: RateKalmanTuning | None = None) -> None:
        if not sigma_b_T > 0:
            raise ValueError(f"sigma_b_T must be > 0, got {sigma_b_T!r}")
        self.sigma_b_T = float(sigma_b_T)
        self.tuning = tuning or RateKalmanTuning()
        self._r = (self.sigma_b_T * UT_PER_T) ** 2
        self.omega_radps = np.zeros(3)
        self.sigma_radps = np.full(3, SIGMA_UNOBSERVED_RADPS)
        self.flags = NO_ESTIMATE
        self.t_s = 0.0
        self.nis = 0.0
        self.resets = 0
        self.x = np.zeros(6)
        self._P = np.zeros((6, 6))
        self._z = np.zeros(3)
        self._F, self._T, self._K = np.zeros((6, 6)), np.zeros((6, 6)), np.zeros((6, 3))
        self._started = False
        self._dt_nominal = math.inf
        self._gap = False
        self._bad = 0
        self.adapt = 1.0
        self._nis_mean = 3.0

    # -- public -----------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget everything; the next sample starts the filter afresh."""
        self._started = False
        self._bad = 0
        self.omega_radps[:] = 0.0
        self.sigma_radps[:] = SIGMA_UNOBSERVED_RADPS
        self.flags = NO_ESTIMATE

    @property
    def b_T(self) -> np.ndarray:
        """The filtered field (tesla, body axes)."""
        return self.x[:3] / UT_PER_T

    @property
    def P(self) -> np.ndarray:
        """The 6×6 covariance (B in µT, ω in rad/s), a copy."""
        return self._P.copy()

    def update(self, t_s: float, b_T) -> bool:
        """Add a field sample (tesla, body axes) taken at `t_s`; True when an estimate was published.

        A non-finite sample is refused (False) and the next estimate is flagged DATA_GAP.
        """
        bx, by, bz = float(b_T[0]) * UT_PER_T, float(b_T[1]) * UT_PER_T, float(b_T[2]) * UT_PER_T
        if not (math.isfinite(bx) and math.isfinite(by) and math.isfinite(bz)):
            self._gap = True
            return False
        if not self._started:
            self._start(t_s, bx, by, bz)
            return True
        dt = t_s - self.t_s
        if not dt > 0:
            return False
        tun = self.tuning
        gap = self._gap or dt > tun.gap_factor * self._dt_nominal
        self._gap = False
        if dt < self._dt_nominal:
            self._dt_nominal = dt
        x = self.x
        b0, b1, b2_, wx, wy, wz = x.tolist()
        w2 = wx * wx + wy * wy + wz * wz
        if dt > tun.max_gap_s or dt * math.sqrt(w2) > tun.max_step_angle_rad:
            self.resets += 1
            self._start(t_s, bx, by, bz, DATA_GAP)
            return True
        # process noise: ω a random walk (q_ω), B a random walk (field motion, q_B). |B| and ω·B are
        # the same before and after the step's rotation about ω, so they are taken from B here.
        b2 = b0 * b0 + b1 * b1 + b2_ * b2_
        wb = wx * b0 + wy * b1 + wz * b2_
        wp2 = max(w2 - wb * wb / b2, 0.0) if b2 > 0 else w2
        # κ|ω||ω⊥| rather than κ|ω|²: the part of ω along B is seen only through the dynamics, and a
        # noise that grew with its (unobserved) size would let it run away
        acc = tun.kappa * math.sqrt(w2 * wp2)
        q_w = (min(self.adapt, 1.0) * acc * acc / 3.0 + self.adapt * tun.rate_accel_radps2 ** 2) * dt
        q_b = tun.field_rate_radps ** 2 * b2 * dt * dt
        phi = math.exp(-dt / tun.rate_time_constant_s)
        rate_kf.predict(x, self._P, dt, q_w, q_b, phi, self._F, self._T)
        z = self._z
        z[0], z[1], z[2] = bx, by, bz
        self.nis = rate_kf.update(x, self._P, z, self._r, self._K, self._T)
        self.t_s = t_s
        self._publish(DATA_GAP if gap else 0)
        return True

    # -- steps ------------------------------------------------------------------------------------
    def _start(self, t_s: float, bx: float, by: float, bz: float, flags: int = 0) -> None:
        r = self._r
        s0 = self.tuning.sigma_rate0_radps ** 2
        x, P = self.x, self._P
        x[0], x[1], x[2] = bx, by, bz
        x[3:] = 0.0
        P[:, :] = 0.0
        P[0, 0] = P[1, 1] = P[2, 2] = r
        P[3, 3] = P[4, 4] = P[5, 5] = s0
        self._started = True
        self._bad = 0
        self.adapt = 1.0
        self._nis_mean = 3.0
        self.t_s = t_s
        self.omega_radps[:] = 0.0
        self.sigma_radps[:] = SIGMA_UNOBSERVED_RADPS
        self.flags = NO_ESTIMATE | flags

    def _publish(self, flags: int) -> None:
        P = self._P
        bx, by, bz, wx, wy, wz = self.x.tolist()
        p0, p4, p8 = float(P[3, 3]), float(P[4, 4]), float(P[5, 5])
        # a NaN or inf anywhere makes the sum non-finite
        if not math.isfinite(wx + wy + wz + p0 + p4 + p8 + bx + by + bz) or p0 < 0 or p4 < 0 or p8 < 0:
            self.resets += 1
            if not math.isfinite(bx + by + bz):
                bx = by = bz = 0.0
            self._start(self.t_s, bx, by, bz, DEGENERATE | flags)
            return
        tun = self.tuning
        self._bad = self._bad + 1 if self.nis > tun.nis_reset else 0
        self.adapt = adapt_noise(self, tun.adapt_samples, tun.adapt_max, tun.adapt_min)
        sx, sy, sz = math.sqrt(p0), math.sqrt(p4), math.sqrt(p8)
        if max(sx, sy, sz) > tun.sigma_flag_radps or bx * bx + by * by + bz * bz < 9.0 * self._r:
            flags |= DEGENERATE
        if self._bad >= 3:  # lost: the innovations are far outside what P allows
            flags |= DEGENERATE
            self.resets += 1
            self._start(self.t_s, bx, by, bz, flags)
            return
        om, sg = self.omega_radps, self.sigma_radps
        om[0], om[1], om[2] = wx, wy, wz
        sg[0], sg[1], sg[2] = (min(sx, SIGMA_UNOBSERVED_RADPS), min(sy, SIGMA_UNOBSERVED_RADPS),
                               min(sz, SIGMA_UNOBSERVED_RADPS))
        self.flags = flags


def adapt_noise(kf, samples: float, max_factor: float, min_factor: float = 1.0) -> float:
    """Innovation-driven scale of the rate's process noise (a fading-memory variant of Mehra 1970):
    the exponential mean of NIS/3 over about `samples` samples; the factor doubles while the mean
    exceeds 1.5 and shrinks by 1.25 while it is below 0.7, within [`min_factor`, `max_factor`]."""
    kf._nis_mean += (min(kf.nis, 100.0) - kf._nis_mean) / samples
    f = kf.adapt
    if kf._nis_mean > 4.5:
        f = min(2.0 * f, max_factor)
    elif kf._nis_mean < 2.1:
        f = max(f / 1.25, min_factor)
    return f


def kalman_rate(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, tuning: RateKalmanTuning | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run :class:`RateKalman` over a recording: ω (N, 3) rad/s, 1-σ (N, 3) and flags (N,); rows
    without an estimate (NO_ESTIMATE) are NaN; no information (a sample without a field, σ at the
    link's "unobserved" value) is σ = inf, flagged DEGENERATE (`rate_formulas.unobserved_sigma`)."""
    kf = RateKalman(sigma_b_T, tuning)
    return run_stream(kf, t_s, b_T, sigma_b_T)


def run_stream(kf, t_s, b_T, sigma_b_T: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run a streaming estimator (`update(t_s, b_T)` → published?, `omega_radps`, `sigma_radps`,
    `flags`) over a recording: ω (N, 3) rad/s, 1-σ (N, 3) and flags (N,), as :func:`kalman_rate`."""
    if sigma_b_T is None:
        sigma_b_T = kf.sigma_b_T if hasattr(kf, "sigma_b_T") else kf.main.sigma_b_T
    t = np.asarray(t_s, float)
    b = np.asarray(b_T, float)
    n = len(t)
    w = np.full((n, 3), np.nan)
    s = np.full((n, 3), np.nan)
    flags = np.full(n, NO_ESTIMATE, dtype=int)
    for k in range(n):
        if kf.update(t[k], b[k]):
            flags[k] = kf.flags
            if not kf.flags & NO_ESTIMATE:
                w[k] = kf.omega_radps
                s[k] = kf.sigma_radps
    s = unobserved_sigma(s, b, sigma_b_T)
    flags[np.isinf(s).any(axis=1)] |= DEGENERATE
    return w, s, flags

