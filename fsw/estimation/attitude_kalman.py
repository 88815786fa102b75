"""The attitude filter: a multiplicative EKF on attitude and rate (Markley 2003; Trawny & Roumeliotis 2005),
with the field along the orbit and, once the rate is found, Euler's equations.

Nominal state q (body → ECI), ω, optional inertia shape p, optional inertial field β; error state δθ
(body axes), δω, δp, δβ. With a field model B_I(t) along the orbit it removes the 0.1–0.2 °/s floor that
the fixed-field assumption of :class:`~fsw.estimation.rate_kalman.RateKalman` leaves (the field turns at
about twice the orbital rate); with Euler's equations (a known tensor, or the shape
J = diag(1, e^p₁, e^p₂) estimated) it follows the rate of an asymmetric tumbling body instead of lagging
it. It keeps what the RTS smoother needs (ground/smoother/). Banks of it (shape hypotheses, rate
models) are in :mod:`fsw.estimation.filter_banks`.

The arithmetic of a step is compiled (:mod:`fsw.estimation.mekf`: the random-walk step, the process noise, the
measurement update; :mod:`fsw.estimation.euler_step`: Euler's equations' RK4 substeps and their transition):
a bank runs a dozen of these filters per sample. Units inside: field in µT, rate in rad/s, time in s; the
public interfaces take tesla.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numba import njit

from . import euler_step, mekf
from .rate_formulas import FIELD_MIN_SIGMAS, SIGMA_UNOBSERVED_RADPS
from .rate_kalman import DATA_GAP, DEGENERATE, NO_ESTIMATE, PERPENDICULAR_ONLY, UT_PER_T, adapt_noise, run_stream
from .rotations import quat_aligning, quat_to_dcm, skew

@njit(cache=True, error_model="numpy")
def physical_shape(p) -> bool:
    """J = diag(1, e^p₁, e^p₂) obeys the triangle inequalities J_i ≤ J_j + J_k (with a margin). Compiled: the
    ground's compiled RTS passes check it too."""
    j = (1.0, math.exp(p[0]), math.exp(p[1]))
    for i in range(3):
        if not j[i] <= 1.02 * (j[(i + 1) % 3] + j[(i + 2) % 3]):
            return False
    return True


FieldFn = Callable[[float], np.ndarray]
"""B_I(t): the inertial (ECI) field [T] at time t [s] along the orbit (fsw/estimation/field_motion.py)."""


@dataclass
class AttitudeKalmanTuning:
    """Settings of :class:`AttitudeRateKalman` (SI units).

    Dynamics: with neither `inertia_kgm2` nor `estimate_inertia`, ω is a random walk as in
    :class:`~.rate_kalman.RateKalman` (`kappa`, `rate_accel_radps2`); with Euler's equations only
    `rate_accel_radps2` remains (unmodelled torques), and `inertia_shape_rate` lets the shape drift.
    sigma_log_inertia0: 1-σ of ln(J₂/J₁), ln(J₃/J₁) before any data (0.7: a factor of two).
    field_sigma_T: 1-σ per axis of the field model's error, added to the measurement noise; with no
      field model, `field_rate_radps` lets the (unknown, fixed) inertial field drift instead.
    max_substep_rad: rotation per integration substep of Euler's equations (RK4).
    along_b_perp_factor, along_b_sweep_power, along_b_field_turn_rel, along_b_memory_s: the floor of the
      published rate's 1-σ along the field (:meth:`AttitudeRateKalman.rate_cov_published`; factor 0: none).
      The part of ω along B shows only as B moves in the body; until it has, the linearised filter takes
      its first large corrections as information (on a 1 °/s tumble its σ along B fell to 0.3 °/s while it
      was 2–5 °/s off, for a minute). In the random-walk phase the floor is `along_b_perp_factor` × the σ
      perpendicular to B over sin(sweep)^`along_b_sweep_power`, sweep the largest angle B has moved in the
      body since the start (none when the start took another filter's rate and covariance, which has seen
      B move: the flown filter's hand-over); without a field model, plus `along_b_field_turn_rel` ×
      `field_rate_radps` (the field's unmodelled turn, which the filter reads as the body's rate ⊥B and
      carries along B as B moves) over sin of B's angle to its direction low-passed over `along_b_memory_s`.
      The floor is at most `sigma_rate0_radps`, and a Gauss–Markov rate's stationary spread (`rate_tau_s`).
    about_b_turn_rad, about_b_sigma_rad: with a field model, the floor of the attitude's 1-σ about the
      field inside the filter: `about_b_sigma_rad` (0: none, the default; the published σ is floored
      by :func:`attitude_cov` with a uniform angle's π/√3) until the inertial field has turned by `about_b_turn_rad`
      from its direction at the start, then shrinking as (turn₀/turn)² (:meth:`AttitudeRateKalman.
      about_b_floor_rad`). The rotation about B is seen only through that turn; without the floor the
      linearised update takes the large early corrections about B as information and the σ collapses to
      a few degrees within a minute while the angle is still 100–180° off.
    shape_step_cut_sigmas: in Euler's equations, an update that takes the shape out of the physical region
      from inside it has its step in the shape cut at the edge when the edge is within this many σ of the
      shape along the step (:meth:`AttitudeRateKalman._cut_shape_step`); 0 (the default): no cut, the filter
      goes back to acquisition. The shape trial's hypotheses cut (`filter_banks.SHAPE_STEP_CUT_SIGMAS`).
    rate_tau_s: with a finite value the random-walk phase's ω is a first-order Gauss–Markov process
      instead, ω̇ = −ω/τ + w (stationary 1-σ per axis `rate_accel_radps2`·√(τ/2)): a motion that stays
      bounded about zero (a libration about a held attitude). The component of ω along B, which the
      samples see only as B turns in the body, then falls back to zero with a σ that grows back to
      the stationary one instead of wandering off. Infinite (the default): a random walk.
    adapt_samples, adapt_max: the innovation-driven scale of the process noise's floor, as
      :class:`~.rate_kalman.RateKalmanTuning`'s (`euler_adapt_max` once Euler's equations run), never below 1
      here: letting it shrink the κ bound too, as `RateKalman` does, was tried (1/256) and not kept. The
      near-symmetric rows' RMS fell ×0.53–0.80, but on the realistic slow heavy tumble (`bench.realistic
      slow_heavy --score`, seed 0, with the TLE) the 1-σ covered 50 % instead of 65 %, and in a bank of these
      filters (`RateModelBank`) the random walk won a libration (orbital/asymmetric/1 s/1.5 µT 0.83 → 1.21 °/s,
      4 runs).
    """

    kappa: float = 0.5
    rate_accel_radps2: float = 1e-4
    rate_tau_s: float = math.inf
    inertia_shape_rate: float = 0.0
    field_rate_radps: float = 2.5e-3
    field_sigma_T: float = 0.0
    sigma_rate0_radps: float = 0.5
    sigma_log_inertia0: float = 0.7
    max_substep_rad: float = 0.1
    max_substeps: int = 200
    euler_after_samples: int = 20
    euler_sigma_rate_radps: float = 0.01
    euler_sigma_rate_rel: float = 0.3
    euler_nis_max: float = 6.0
    nis_reset: float = 1e3
    adapt_samples: float = 10.0
    adapt_max: float = 1e4
    euler_adapt_max: float | None = None
    max_rate_radps: float = 100.0
    max_step_angle_rad: float = 2.5
    max_gap_s: float = 60.0
    gap_factor: float = 1.8
    sigma_flag_radps: float = 0.1
    about_b_turn_rad: float = math.radians(20.0)
    about_b_sigma_rad: float = 0.0
    along_b_perp_factor: float = 3.0
    along_b_sweep_power: float = 3.0
    along_b_field_turn_rel: float = 0.5
    along_b_memory_s: float = 60.0
    shape_step_cut_sigmas: float = 0.0


class AttitudeRateKalman:
    """Multiplicative EKF on attitude and rate, one sample at a time.

    Nominal state: q (body → ECI, or → the body's own axes at the first sample when no field model is
    given), ω (rad/s), p = (ln J₂/J₁, ln J₃/J₁) when the inertia shape is estimated, β = the inertial
    field (µT) when no field model is given. Error state δx = [δθ, δω, δp, δβ] with the true attitude
    R = R̂ exp([δθ]ₓ) (body-frame error): δθ̇ = −[ω]ₓ δθ + δω.

    Measurement: z = Rᵀ (B_I(t) + β) + v, H = [[h]ₓ, 0, 0, Rᵀ].

    Without a field model the attitude is defined relative to the first sample (P_θ = 0 there) and the
    field is the state β: equivalent to :class:`~.rate_kalman.RateKalman` plus optional Euler dynamics.
    With a field model the rotation about B at the first sample is unknown: `angle_about_b_rad` picks one
    and the covariance about B starts at π²/3 (the smoother tries several).

    Acquisition: Euler's equations are switched on only once the random-walk model has found the rate
    (`euler_after_samples` samples and every 1-σ of ω below `euler_sigma_rate_radps` +
    `euler_sigma_rate_rel`·|ω|); before that the
    shape would absorb the large early errors and the filter would diverge. Innovations far outside S
    (NIS > `nis_reset` three times in a row) send it back to acquisition.

    `store=True` keeps, per sample, the predicted and filtered states, covariances, transition
    matrices and normalised innovations (NIS) for the RTS smoother (ground/smoother/).
    """

    PERPENDICULAR_ONLY, DEGENERATE, NO_ESTIMATE, DATA_GAP = PERPENDICULAR_ONLY, DEGENERATE, NO_ESTIMATE, DATA_GAP
    gap_history = 0

    def __init__(self, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
                 inertia_kgm2: np.ndarray | None = None, estimate_inertia: bool = False,
                 torque_Nm: Callable[[float], np.ndarray] | None = None,
                 tuning: AttitudeKalmanTuning | None = None, angle_about_b_rad: float = 0.0,
                 store: bool = False) -> None:
        if not sigma_b_T > 0:
            raise ValueError(f"sigma_b_T must be > 0, got {sigma_b_T!r}")
        if inertia_kgm2 is not None and estimate_inertia:
            raise ValueError("give a known inertia tensor or estimate its shape, not both")
        if torque_Nm is not None and inertia_kgm2 is None:
            raise ValueError("a known torque needs the absolute inertia tensor")
        self.sigma_b_T = float(sigma_b_T)
        self.tuning = tun = tuning or AttitudeKalmanTuning()
        if not tun.rate_tau_s > 0:
            raise ValueError(f"rate_tau_s must be > 0 (inf for a random walk), got {tun.rate_tau_s!r}")
        self.field = field_eci_T
        self.J = None if inertia_kgm2 is None else np.array(inertia_kgm2, float)
        self.J_inv = None if self.J is None else np.linalg.inv(self.J)
        self.torque = torque_Nm
        self.n_p = 2 if estimate_inertia else 0
        self.n_beta = 0 if field_eci_T is not None else 3
        self.n = 6 + self.n_p + self.n_beta
        self.i_beta = 6 + self.n_p
        self.euler_model = self.J is not None or estimate_inertia
        self.euler = False
        self.angle_about_b_rad = float(angle_about_b_rad)
        self.R = ((self.sigma_b_T ** 2 + tun.field_sigma_T ** 2) * UT_PER_T ** 2) * np.eye(3)
        self.store = store
        self.log: dict[str, list] = {k: [] for k in ("t", "qp", "xp", "Pp", "F", "q", "x", "P", "restart",
                                                     "nis")}
        self.omega_radps = np.zeros(3)
        self.sigma_radps = np.full(3, SIGMA_UNOBSERVED_RADPS)
        self.flags = NO_ESTIMATE
        self.t_s = 0.0
        self.nll = 0.0
        self.nis = 0.0
        self.resets = 0
        self._started = False
        self._gap = False
        self._dt_nominal = math.inf
        self._b_i0 = None  # the inertial field's direction at the start (the floor about B)
        self._b_ref = None  # the field's direction in the body, low-passed (the rate's floor along B)
        self._handed_over = False
        self.field_turn_rad = 0.0

    # -- public -----------------------------------------------------------------------------------
    def reset(self) -> None:
        self._started = False
        self.omega_radps[:] = 0.0
        self.sigma_radps[:] = SIGMA_UNOBSERVED_RADPS
        self.flags = NO_ESTIMATE

    def start(self, t_s: float, b_T, *, q: np.ndarray | None = None, omega_radps: np.ndarray | None = None,
              p: np.ndarray | None = None, beta_uT: np.ndarray | None = None, P: np.ndarray | None = None,
              rate_cov: np.ndarray | None = None) -> None:
        """Start from the sample (t_s, b_T) with optional initial values (a smoother's restart);
        missing ones take the defaults. `rate_cov`: the 3×3 covariance of `omega_radps` instead of the
        default σ (another filter's estimate handed over; ignored with `P`). Updates with the sample."""
        tun = self.tuning
        z = np.asarray(b_T, float) * UT_PER_T
        if self.field is not None and np.linalg.norm(z) <= FIELD_MIN_SIGMAS * math.sqrt(self.R[0, 0]):
            # no field, no direction to align the attitude with: wait for a sample that has one
            self.omega_radps[:] = 0.0
            self.sigma_radps[:] = SIGMA_UNOBSERVED_RADPS
            self.flags = NO_ESTIMATE | DEGENERATE
            return
        self.w = np.zeros(3) if omega_radps is None else np.array(omega_radps, float)
        self.p = np.zeros(self.n_p) if p is None else np.array(p, float)
        n = self.n
        P0 = np.zeros((n, n))
        sb = math.sqrt(self.R[0, 0])
        if self.field is None:
            self.q = np.array([1.0, 0.0, 0.0, 0.0]) if q is None else np.array(q, float)
            self.beta = z.copy() if beta_uT is None else np.array(beta_uT, float)
            P0[self.i_beta:, self.i_beta:] = sb ** 2 * np.eye(3)
        else:
            b_i = np.asarray(self.field(t_s), float) * UT_PER_T
            self.q = quat_aligning(z, b_i, self.angle_about_b_rad) if q is None else np.array(q, float)
            self.beta = np.zeros(0)
            bh = z / np.linalg.norm(z)
            self._b_i0 = b_i / np.linalg.norm(b_i)
            self.field_turn_rad = 0.0
            P0[:3, :3] = (sb / np.linalg.norm(z)) ** 2 * np.eye(3) + (math.pi ** 2 / 3) * np.outer(bh, bh)
        P0[3:6, 3:6] = tun.sigma_rate0_radps ** 2 * np.eye(3) if rate_cov is None else np.asarray(rate_cov, float)
        P0[6:6 + self.n_p, 6:6 + self.n_p] = tun.sigma_log_inertia0 ** 2 * np.eye(self.n_p)
        self.P = P0 if P is None else np.array(P, float)
        self.euler = self.euler_model and omega_radps is not None and P is not None
        self.adapt = 1.0
        self._nis_mean = 3.0
        self._samples = 0
        self._bad = 0
        self._started = True
        self.t_s = t_s
        self._b_ref = None
        # a rate handed over with its covariance (another filter's, which has seen B move) needs no floor
        self._handed_over = rate_cov is not None and omega_radps is not None
        self._keep_shape_before()
        self._record_prediction(t_s, np.eye(n), restart=True)
        self._update(t_s, z)
        # a rate handed over with its covariance is an estimate from the first sample on
        self._publish(NO_ESTIMATE if rate_cov is None or omega_radps is None else 0)

    def set_nominal(self, t_s: float, q: np.ndarray, omega_radps: np.ndarray, p: np.ndarray | None = None,
                    beta_uT: np.ndarray | None = None, euler: bool | None = None) -> None:
        """Set the nominal state at `t_s` without a measurement (a propagator for batch fits)."""
        self.q = np.array(q, float)
        self.w = np.array(omega_radps, float)
        self.p = np.zeros(self.n_p) if p is None else np.array(p, float)
        if self.n_beta:
            self.beta = np.zeros(3) if beta_uT is None else np.array(beta_uT, float)
        else:
            self.beta = np.zeros(0)
        self.P = np.zeros((self.n, self.n))
        self.t_s = t_s
        self.euler = self.euler_model if euler is None else euler
        self._started = True

    def update(self, t_s: float, b_T) -> bool:
        """Add a field sample (tesla, body axes) taken at `t_s`; True when an estimate was published."""
        b = np.asarray(b_T, float)
        if not np.all(np.isfinite(b)):
            self._gap = True
            return False
        if not self._started:
            self.start(t_s, b)
            return True
        dt = t_s - self.t_s
        if not dt > 0:
            return False
        tun = self.tuning
        gap = self._gap or dt > tun.gap_factor * self._dt_nominal
        self._gap = False
        self._dt_nominal = min(self._dt_nominal, dt)
        if dt > tun.max_gap_s:
            self.resets += 1
            self.start(t_s, b)
            self.flags |= DATA_GAP
            return True
        marks = {k: len(v) for k, v in self.log.items()}
        self._keep_shape_before()
        try:
            # a state that blows up is caught just below (non-finite → restart, counted), not warned about
            with np.errstate(invalid="ignore", over="ignore"):
                F = self.propagate(dt)
                self.P = mekf.predict_covariance(F, self.P, self._process_noise(dt))
                self.t_s = t_s
                self._record_prediction(t_s, F)
                self._update(t_s, b * UT_PER_T)
        except (ValueError, OverflowError, FloatingPointError, np.linalg.LinAlgError):
            ok = False
        else:
            wn = float(np.linalg.norm(self.w))
            # beyond about half a turn per step the samples alias: a rate that fast is a lost filter
            ok = bool(np.all(np.isfinite(self.P)) and wn < tun.max_rate_radps
                      and wn * min(dt, self._dt_nominal) < tun.max_step_angle_rad)
        if not ok:  # diverged: start again from this sample, flagged (the smoother's log keeps the restart)
            self.resets += 1
            for k, v in self.log.items():
                del v[marks[k]:]
            self.start(t_s, b)
            self.flags |= DEGENERATE | DATA_GAP
            return True
        self._publish(DATA_GAP if gap else 0)
        return True

    @property
    def inertia_shape(self) -> np.ndarray:
        """Estimated J / J₁ = diag(1, e^p₁, e^p₂) (ones when not estimated)."""
        return np.concatenate([[1.0], np.exp(self.p)]) if self.n_p else np.ones(3)

    def clone(self) -> AttitudeRateKalman:
        """An independent copy of the running filter (state, covariance, adaptation; no stored log):
        a hypothesis to run in parallel (:class:`~.filter_banks.EulerAcquisitionKalman`)."""
        new = AttitudeRateKalman.__new__(AttitudeRateKalman)
        new.__dict__.update(self.__dict__)
        for k in ("q", "w", "p", "beta", "P", "omega_radps", "sigma_radps"):
            if k in self.__dict__:
                setattr(new, k, np.array(getattr(self, k), float))
        new.store = False
        new.log = {k: [] for k in self.log}
        return new

    def start_euler(self, p: np.ndarray, sigma_p: float) -> None:
        """Switch Euler's equations on now, from the shape `p` (ln J₂/J₁, ln J₃/J₁) with 1-σ `sigma_p`
        (uncorrelated with the rest); the noise adaptation of the random-walk phase starts again."""
        if not self.n_p:
            raise ValueError("start_euler needs a filter that estimates the inertia shape")
        self.euler = True
        self.p = np.array(p, float)
        ip = slice(6, 6 + self.n_p)
        self.P[ip, :] = 0.0
        self.P[:, ip] = 0.0
        self.P[ip, ip] = sigma_p ** 2 * np.eye(self.n_p)
        self.adapt = 1.0
        self._nis_mean = 3.0

    def back_to_acquisition(self) -> None:
        """Lost (innovations far outside S): back to the random-walk phase, the shape from a sphere with its
        prior σ and the rate's covariance widened by its prior (counted in `resets`)."""
        tun = self.tuning
        self._bad = 0
        self.resets += 1
        self.euler = False
        self._samples = 0
        if self.n_p:
            self.p[:] = 0.0
            ip = slice(6, 6 + self.n_p)
            self.P[ip, :] = 0.0
            self.P[:, ip] = 0.0
            self.P[ip, ip] = tun.sigma_log_inertia0 ** 2 * np.eye(self.n_p)
        self.P[3:6, 3:6] += tun.sigma_rate0_radps ** 2 * np.eye(3)

    def rate_found(self) -> bool:
        """The acquisition test of the random-walk phase: enough samples and every published 1-σ of ω (its
        part along B floored by :meth:`rate_cov_published`: Euler's equations wait for it) below
        `euler_sigma_rate_radps` + `euler_sigma_rate_rel`·|ω| (the innovation test excluded)."""
        tun = self.tuning
        return (self._started and self._samples >= tun.euler_after_samples
                and float(self.sigma_radps.max()) < tun.euler_sigma_rate_radps
                + tun.euler_sigma_rate_rel * float(np.linalg.norm(self.w)))

    # -- model ------------------------------------------------------------------------------------
    def propagate(self, dt: float) -> np.ndarray:
        """Advance the nominal state by dt; return the error-state transition Φ (n×n)."""
        n = self.n
        if not self.euler:
            decay, mean = self._rate_decay(dt)
            self.q, self.w, F = mekf.rw_propagate(self.q, self.w, decay, mean, dt, n)
            return F
        tun = self.tuning
        wn = math.sqrt(float(self.w @ self.w))
        if not math.isfinite(wn) or not np.all(np.isfinite(self.p)):
            raise ValueError("non-finite state")
        m = min(tun.max_substeps, max(1, int(math.ceil(wn * dt / tun.max_substep_rad))))
        mode, j2, j3, J, K = self.euler_args()
        torques = euler_step.TORQUE_FREE
        if self.torque is not None:  # at each substep's start, middle and end
            h = dt / m
            torques = np.array([[self.torque(self.t_s + (i + f) * h) for f in (0.0, 0.5, 1.0)] for i in range(m)],
                               float).reshape(m, 3, 3)
        self.q, self.w, F = euler_step.propagate(self.q, self.w, dt, m, mode, j2, j3, J, K, self.n_p, n, torques)
        return F

    def euler_args(self) -> tuple[int, float, float, np.ndarray, np.ndarray]:
        """Euler's equations as the compiled kernels take them (:mod:`fsw.estimation.euler_step`): (mode, J₂/J₁,
        J₃/J₁, J, J⁻¹) — the known tensor (J, J⁻¹ row-major), or the shape of the state p (a ratio beyond
        the float range is inf: the propagation's state is then not finite)."""
        if self.J is not None:
            return euler_step.TENSOR, 1.0, 1.0, self.J.ravel(), self.J_inv.ravel()
        with np.errstate(over="ignore"):
            j2, j3 = np.exp(self.p)
        return euler_step.SHAPE, float(j2), float(j3), euler_step.NO_TENSOR, euler_step.NO_TENSOR

    def _rate_decay(self, dt: float) -> tuple[float, float]:
        """Gauss–Markov ω over a step: (e^(−dt/τ), mean of e^(−s/τ) over the step); (1, 1) for a
        random walk."""
        tau = self.tuning.rate_tau_s
        if not math.isfinite(tau):
            return 1.0, 1.0
        x = dt / tau
        return math.exp(-x), -math.expm1(-x) / x

    def _process_noise(self, dt: float) -> np.ndarray:
        tun = self.tuning
        q_w = self.adapt * tun.rate_accel_radps2 ** 2 * dt
        if not self.euler:  # κ|ω||ω⊥| (see RateKalman)
            if math.isfinite(tun.rate_tau_s):  # Gauss–Markov: a²τ/2 (1 − e^(−2dt/τ)) per step
                q_w *= -math.expm1(-2.0 * dt / tun.rate_tau_s) * tun.rate_tau_s / (2.0 * dt)
            w0, w1, w2_ = self.w
            b0, b1, b2 = self._bhat
            w2 = w0 * w0 + w1 * w1 + w2_ * w2_
            wb = w0 * b0 + w1 * b1 + w2_ * b2
            q_w += tun.kappa ** 2 * w2 * max(w2 - wb * wb, 0.0) / 3.0 * dt
        # ω a random walk with per-step variance q_w; its effect on the attitude over the step
        return mekf.process_noise(self.n, self.n_p, float(q_w), dt, tun.inertia_shape_rate, tun.field_rate_radps,
                                  self.beta)

    def _b_inertial_uT(self, t_s: float) -> np.ndarray:
        """The inertial field at `t_s` (µT): the model's along the orbit, or the state β without one."""
        return np.asarray(self.field(t_s), float).reshape(3) * UT_PER_T if self.field is not None else self.beta

    def measurement(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Predicted field h (µT, body) and H = ∂h/∂δx at the nominal state."""
        C = quat_to_dcm(self.q)
        b_i = self._b_inertial_uT(t_s)
        h = C.T @ b_i
        H = np.zeros((3, self.n))
        H[:, :3] = skew(h)
        if self.n_beta:
            H[:, self.i_beta:] = C.T
        return h, H

    def _update(self, t_s: float, z: np.ndarray) -> None:
        b_i = self._b_inertial_uT(t_s)
        self._bhat = z / max(math.sqrt(z[0] * z[0] + z[1] * z[1] + z[2] * z[2]), 1e-30)
        self.q, self.w, self.p, self.beta, self.P, nis, nll = mekf.update(self.q, self.w, self.p, self.beta, self.P,
                                                                          z, b_i, self.R)
        self.nis = float(nis)
        self.nll += nll
        if self.euler and self.n_p and not physical_shape(self.p):
            self._cut_shape_step()  # the update's step in the shape stopped at the edge of the physical region
        if self._b_i0 is not None and not self.store and self.tuning.about_b_sigma_rad > 0:
            self._floor_about_b(t_s)
        self._track_sweep(z)
        if self.store:
            lg = self.log
            lg["q"].append(self.q.copy())
            lg["x"].append(self._x())
            lg["P"].append(self.P.copy())
            lg["nis"].append(self.nis)

    def _track_sweep(self, z: np.ndarray) -> None:
        """How far the field has moved in the body (for :meth:`rate_cov_published`): the largest angle from
        its direction at the start, and its angle to its direction low-passed over `along_b_memory_s`."""
        u = z / max(float(np.linalg.norm(z)), 1e-30)
        self._u = u
        if self._b_ref is None:
            self._b_ref, self._b_first, self._ref_t = u.copy(), u.copy(), self.t_s
            self._sweep0 = self._sweep1 = 0.0
            return
        a = min(1.0, max(self.t_s - self._ref_t, 0.0) / self.tuning.along_b_memory_s)
        r = self._b_ref + a * (u - self._b_ref)
        self._b_ref = r / max(float(np.linalg.norm(r)), 1e-30)
        self._ref_t = self.t_s
        self._sweep0 = max(self._sweep0, _angle(u, self._b_first))
        self._sweep1 = _angle(u, self._b_ref)

    def _keep_shape_before(self) -> None:
        """The shape before this update, for :meth:`_cut_shape_step`: kept only where the cut is on (the
        shape trial's hypotheses), so the flown filter's update allocates nothing for it."""
        if self.n_p and self.tuning.shape_step_cut_sigmas > 0:
            self._p_before = self.p.copy()

    def _cut_shape_step(self) -> bool:
        """The last update took the shape out of the physical region from inside it: cut its step in the
        shape back to the region's edge (the projection of a constrained Kalman filter's estimate, Simon 2010
        §3, along the step), when the edge is within `shape_step_cut_sigmas` of the shape's 1-σ of the step
        start. An elongated body (a 3U cubesat, J₃/J₁ = 0.19) lies 0.17 in ln J₂/J₁ from the edge, less than
        the shape prior's σ: its first corrections crossed the edge and sent the right hypothesis back to
        acquisition. False: no cut (a step from outside, or an edge too far: the filter is lost)."""
        p0 = getattr(self, "_p_before", None)
        k = self.tuning.shape_step_cut_sigmas
        if p0 is None or not k > 0 or not physical_shape(p0):
            return False
        d = self.p - p0
        lo, hi = 0.0, 1.0
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            if physical_shape(p0 + mid * d):
                lo = mid
            else:
                hi = mid
        ip = slice(6, 6 + self.n_p)
        s = math.sqrt(max(float(d @ self.P[ip, ip] @ d) / max(float(d @ d), 1e-300), 0.0))
        if not lo * float(np.linalg.norm(d)) <= k * s:
            return False
        self.p = p0 + lo * d
        return True

    def rate_cov_published(self) -> np.ndarray:
        """The 3×3 covariance of ω to publish: the filter's own, its variance along the field held at or
        above the floor of `AttitudeKalmanTuning.along_b_perp_factor` (see there): what the field's motion
        in the body has shown of the part along B so far. Inside the filter P stays as it is (a floor
        there let the first samples' noise into the part along B: 2× the error)."""
        Pw = np.array(self.P[3:6, 3:6], float)
        tun = self.tuning
        if self._b_ref is None or not tun.along_b_perp_factor > 0:
            return Pw
        u = self._u
        v = float(u @ Pw @ u)
        s_perp = math.sqrt(max(float(np.trace(Pw)) - v, 0.0) / 2.0)
        fs = 0.0  # Euler's equations carry the part along B through the dynamics; a handed-over P has seen it
        if not (self.euler or self._handed_over):
            fs = tun.along_b_perp_factor * s_perp / max(math.sin(min(self._sweep0, math.pi / 2))
                                                        ** tun.along_b_sweep_power, 1e-9)
        ft = 0.0
        if self.field is None:
            ft = tun.along_b_field_turn_rel * tun.field_rate_radps / max(math.sin(min(self._sweep1, math.pi / 2)),
                                                                         1e-6)
        cap = tun.sigma_rate0_radps
        if math.isfinite(tun.rate_tau_s):  # a Gauss–Markov rate: no farther off than its stationary spread
            cap = min(cap, tun.rate_accel_radps2 * math.sqrt(self.adapt * tun.rate_tau_s / 2.0))
        floor = min(cap, math.hypot(fs, ft))
        if v < floor * floor:
            Pw += (floor * floor - v) * np.outer(u, u)
        return Pw

    def about_b_floor_rad(self) -> float:
        """The floor of the attitude's 1-σ about the field at the inertial field's turn so far
        (`AttitudeKalmanTuning.about_b_turn_rad`, `about_b_sigma_rad`)."""
        tun = self.tuning
        turn0 = tun.about_b_turn_rad
        if not turn0 > 0:
            return 0.0
        return tun.about_b_sigma_rad * min(1.0, (turn0 / max(self.field_turn_rad, 1e-12)) ** 2)

    def _floor_about_b(self, t_s: float) -> None:
        """The field's inertial turn from its direction at the start updated (the field along the orbit at
        `t_s`); with `about_b_sigma_rad`, the attitude's variance about the field held at
        :meth:`about_b_floor_rad` or above. With the floor it runs at each update; without, when the
        attitude is published (:func:`attitude_cov`)."""
        b_i = np.asarray(self.field(t_s), float)
        nb = float(np.linalg.norm(b_i))
        if not nb > 0:
            return
        b_i = b_i / nb
        turn = math.acos(max(-1.0, min(1.0, float(b_i @ self._b_i0))))
        self.field_turn_rad = max(self.field_turn_rad, turn)
        if not self.tuning.about_b_sigma_rad > 0:
            return
        u = quat_to_dcm(self.q).T @ b_i
        floor2 = self.about_b_floor_rad() ** 2
        v = float(u @ self.P[:3, :3] @ u)
        if v < floor2:
            self.P[:3, :3] += (floor2 - v) * np.outer(u, u)

    def _x(self) -> np.ndarray:
        return np.concatenate([self.w, self.p, self.beta])

    def _record_prediction(self, t_s: float, F: np.ndarray, restart: bool = False) -> None:
        if self.store:
            lg = self.log
            lg["restart"].append(restart)
            lg["t"].append(t_s)
            lg["qp"].append(self.q.copy())
            lg["xp"].append(self._x())
            lg["Pp"].append(self.P.copy())
            lg["F"].append(F)

    def _publish(self, flags: int) -> None:
        w = self.w
        s = np.sqrt(np.clip(np.diagonal(self.P)[3:6], 0.0, None))
        if not (np.all(np.isfinite(w)) and np.all(np.isfinite(s)) and np.all(np.isfinite(self.q))):
            self.omega_radps[:] = 0.0
            self.sigma_radps[:] = SIGMA_UNOBSERVED_RADPS
            self.flags = DEGENERATE | flags | NO_ESTIMATE
            self.resets += 1
            self._started = False
            return
        tun = self.tuning
        self._samples += 1
        self._bad = self._bad + 1 if self.nis > tun.nis_reset else 0
        amax = tun.adapt_max if not self.euler or tun.euler_adapt_max is None else tun.euler_adapt_max
        if amax > 1.0:
            self.adapt = adapt_noise(self, tun.adapt_samples, amax)
        if self._bad >= 3:  # lost: back to acquisition
            self.back_to_acquisition()
            flags |= DEGENERATE
        elif (self.euler_model and not self.euler and self._samples >= tun.euler_after_samples
              and self._nis_mean < tun.euler_nis_max
              and s.max() < tun.euler_sigma_rate_radps + tun.euler_sigma_rate_rel * float(np.linalg.norm(w))):
            self.euler = True
        elif self.euler and self.n_p and not physical_shape(self.p):
            # a shape no body has (a principal moment above the sum of the other two): start the
            # shape again from a sphere, back in acquisition
            self.euler = False
            self._samples = 0
            self.p[:] = 0.0
            ip = slice(6, 6 + self.n_p)
            self.P[ip, :] = 0.0
            self.P[:, ip] = 0.0
            self.P[ip, ip] = tun.sigma_log_inertia0 ** 2 * np.eye(self.n_p)
            flags |= DEGENERATE
        if s.max() > tun.sigma_flag_radps:
            flags |= DEGENERATE
        s = np.sqrt(np.clip(np.diagonal(self.rate_cov_published()), 0.0, None))
        self.omega_radps[:] = w
        self.sigma_radps[:] = np.minimum(s, SIGMA_UNOBSERVED_RADPS)
        self.flags = flags


def _angle(u: np.ndarray, x: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, float(u @ x))))


#: 1-σ of an angle uniform over a turn: the attitude about B before the field has turned
ABOUT_B_SIGMA_UNIFORM_RAD = math.pi / math.sqrt(3.0)


def attitude_cov(kf: AttitudeRateKalman) -> np.ndarray:
    """The 3×3 covariance of `kf`'s attitude error (body axes) to publish: its own, the variance about the
    field held at or above the floor of a uniform angle (:meth:`AttitudeRateKalman.about_b_floor_rad` with
    `about_b_sigma_rad` = π/√3) at the field's inertial turn so far."""
    P = np.array(kf.P[:3, :3], float)
    if kf.field is None or kf._b_i0 is None:
        return P
    if not kf.store:
        kf._floor_about_b(kf.t_s)  # the field's turn so far (the floor inside, if any, holds already)
    h, _ = kf.measurement(kf.t_s)
    u = h / np.linalg.norm(h)
    turn0 = kf.tuning.about_b_turn_rad
    if not turn0 > 0:
        return P
    shrink = min(1.0, (turn0 / max(kf.field_turn_rad, 1e-12)) ** 2)
    f = max(kf.tuning.about_b_sigma_rad, ABOUT_B_SIGMA_UNIFORM_RAD * shrink)
    P += max(0.0, f * f - float(u @ P @ u)) * np.outer(u, u)
    return P


def attitude_kalman_rate(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, **kwargs
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run :class:`AttitudeRateKalman` (keyword arguments as its constructor) over a recording, as
    :func:`fsw.estimation.rate_kalman.kalman_rate`."""
    return run_stream(AttitudeRateKalman(sigma_b_T, **kwargs), t_s, b_T, sigma_b_T)
