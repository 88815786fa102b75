"""The attitude w.r.t. the orbital frame from the magnetometer alone: a multiplicative EKF on attitude and rate
driven by the environment's torques and the de-orbit kit's own known moments.

Why it works with one vector sensor. A field sample gives the attitude about two axes only (the rotation
about B is unseen). What makes the third observable over time is the dynamics: gravity gradient and the
sail's weathervane moment depend on the attitude, the kit's moments M = p × B are known (the sequencer
knows which capsule is open with which polarity), and the field turns in the orbital frame by about two
turns an orbit, so the unseen axis changes. A filter that propagates Euler's equations with these torques
sees a wrong rotation about B as a growing misfit of later samples.

State and frames. Nominal q (body → inertial, scalar first as in `rotations`), ω (inertial rate, body
axes); error δx = (δθ, δω), the true attitude R = R̂ exp([δθ]ₓ) (body-frame error, as in
`attitude_kalman.AttitudeRateKalman`, whose measurement model and update this shares). The outputs are in
the orbital frame o (x_o along the velocity, z_o nadir, y_o = z_o × x_o): R_bo = R_oiᵀ R(q) and
ω_rel = ω − R(q)ᵀ ω_oi with ω_oi = r × v / |r|². The body-frame error's y and z components are exactly
the sail normal's pointing error about body y and z (what the controller acts on), so their σ is the
pointing σ the controller's trust gate reads.

Dynamics (:func:`_torque`, compiled): J ω̇ = −ω × Jω + M_gg + M_aero + p × B with
M_gg = 3μ/r³ · r̂ × J r̂, M_aero = r_cp × F for a flat sail plus body in free molecular flow
(F = −½ρ|v|²C_d(S_sail|n·v̂| + S_body) v̂, the air at rest in inertial space), p the kit's unscreened
dipoles reported by the sequencer and B = R(q)ᵀ B_I. The model is the box's `SpacecraftModel`: its
inertia (the design value until the identification supplies one), sail and density guess. Integration:
RK4 with the orbit position, velocity and field held over the step (≤ 2 s); error transition
Φ = I + Fh + (Fh)²/2 with ∂M/∂δθ by central differences.

Start (:class:`OrbitalAttitudeBank`): the first sample fixes two axes; `hypotheses` attitudes evenly
spaced about B, each at rest in the orbital frame (σ `sigma_rate0_radps`), run side by side; their
cumulative negative log-likelihoods pick one (the others are dropped once they trail by
`drop_nll`). A start from a tumble is not this filter's job (the rate filters find that rate first).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numba import njit

from .field_motion import A_WGS84_M
from .rotations import quat_aligning, quat_exp, quat_mul, quat_to_dcm, skew
from .rotations import quat_exp_nb as _qexp, quat_mul_nb as _qmul, quat_to_dcm_nb as _dcm, skew_nb as _skew

UT_PER_T = 1e6


@dataclass(frozen=True)
class SpacecraftModel:
    """What the box knows of the spacecraft it is bolted to (SI, body axes about the centre of mass).

    Density: an exponential atmosphere ρ0·exp(−(h − h0)/H) at the orbit's altitude — by default Vallado's
    Table 8-4 band for 600-700 km at mean solar activity (the box cannot measure density; its error is
    process noise on the rate)."""

    inertia_kgm2: tuple = (17.995, 20.711, 15.269)  # diagonal (3,) or full (3, 3)
    sail_area_m2: float = 5.0
    body_area_m2: float = 0.58
    drag_coefficient: float = 2.2
    cp_offset_m: tuple[float, float, float] = (-0.12, 0.0, 0.0)
    sail_normal_body: tuple[float, float, float] = (1.0, 0.0, 0.0)
    density_kgm3: float = 1.454e-13
    density_ref_alt_km: float = 600.0
    density_scale_height_km: float = 71.835

    def J(self) -> np.ndarray:
        j = np.asarray(self.inertia_kgm2, float)
        return np.diag(j) if j.shape == (3,) else j

    def density_at_kgm3(self, r_m):
        """ρ at the distance `r_m` [m] (a float, or an array of them) from the Earth's centre."""
        h_km = (np.asarray(r_m, float) - A_WGS84_M) * 1e-3
        return self.density_kgm3 * np.exp(-(h_km - self.density_ref_alt_km) / self.density_scale_height_km)


@dataclass(frozen=True)
class Inputs:
    """The known inputs over a propagation step (inertial axes): position, velocity, the field along the
    orbit, and the kit's dipole in body axes."""

    r_eci_m: np.ndarray
    v_eci_mps: np.ndarray
    b_eci_T: np.ndarray
    dipole_body_Am2: np.ndarray


@dataclass
class OrbitalAttitudeTuning:
    """Noise and start settings (SI).

    accel_psd: spectral density of the unmodelled angular acceleration [(rad/s²)²/Hz] (density and
      inertia errors, what the shutters' ramps and the magnets' real moment leave): (1.1e-7 rad/s²)² over
      100 s of correlation by default, chosen on the de-orbit benchmark's closed loop from its 0° start
      (yaw error RMS from 3,600 s, with the dipole then held between samples, and how often the σ about
      body z covered the error): (3.5e-7)² 0.097 rad, the σ covering 55 %
      of it; (1.1e-7)² 0.033 rad, 96 %; (3.5e-8)² 0.075 rad, 50 % (overconfident after the pulses).
    field_sigma_T: the onboard field model's error per axis, added to the sensor's noise.
    sigma_bias0_T, bias_psd_T2_per_s: the sample's slowly varying error in body axes (what the host
      calibration leaves, the hard iron's thermal drift, the kit's field the compensation misses), a
      random walk from σ `sigma_bias0_T`; a change of the host calibration, known on board, moves it
      (`OrbitalAttitudeBank.shift_bias`). What the kit-field model misses changes with the channels'
      states: given the model's covariance of a change (the kit's, `fsw.deorbit.kit_field`: ~8 µT per axis
      before its first calibration steps, a few tenths after), the bias opens by that plus
      `kit_step_floor_sigma_T` per axis (the leakage and the unobserved F_b, left at the design's); without
      it, by `kit_change_bias_sigma_T` per axis whenever the kit's dipole changes.
    """

    accel_psd: float = (1.1e-7) ** 2 * 100.0
    field_sigma_T: float = 0.3e-6
    sigma_bias0_T: float = 2e-6
    bias_psd_T2_per_s: float = (1e-6) ** 2 / 1000.0
    kit_change_bias_sigma_T: float = 1e-6
    kit_step_floor_sigma_T: float = 0.3e-6
    sigma_angle0_rad: float = 0.05  # perpendicular to B at the first sample (plus the sample's noise)
    sigma_about_b0_rad: float = 0.5  # about B, per hypothesis
    sigma_rate0_radps: float = 1e-3
    hypotheses: int = 8
    drop_nll: float = 25.0
    max_step_s: float = 2.0
    max_gap_s: float = 600.0
    decide_after_s: float = 1200.0  # then only the best hypothesis runs on


# --- pure functions ----------------------------------------------------------------------------------

def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a × b of two 3-vectors (np.cross costs ten times more per call on single vectors)."""
    return np.array((a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]))


def orbital_frame(r_eci_m: np.ndarray, v_eci_mps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R_oi with columns x_o, y_o, z_o in inertial axes, ω_oi in inertial axes)."""
    z = -r_eci_m / np.linalg.norm(r_eci_m)
    x = v_eci_mps - np.dot(v_eci_mps, z) * z
    x = x / np.linalg.norm(x)
    return np.column_stack((x, _cross(z, x), z)), _cross(r_eci_m, v_eci_mps) / float(r_eci_m @ r_eci_m)


def predict(q: np.ndarray, w: np.ndarray, P: np.ndarray, dt_s: float, u: Inputs, model: SpacecraftModel,
            tuning: "OrbitalAttitudeTuning") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, ω, P) propagated by `dt_s` with the inputs `u` held: the midpoint rule (RK2) in steps of at
    most `tuning.max_step_s` (the rates here are ~10⁻³ rad/s: a step turns the body by milliradians);
    the bias (the last three states) is a random walk and keeps its value. The steps run compiled
    (:func:`_propagate`: a call of numpy per 3-vector cost more than the arithmetic; the tests hold it
    against the same model written with numpy)."""
    if dt_s <= 0.0:
        return q, w, P
    J = model.J()
    Jinv = np.linalg.inv(J)
    n = max(1, int(math.ceil(dt_s / tuning.max_step_s)))
    h = dt_s / n
    qa, qb = tuning.accel_psd, tuning.bias_psd_T2_per_s * UT_PER_T ** 2
    Q = np.zeros((9, 9))
    Q[:3, :3] = qa * h ** 3 / 3.0 * np.eye(3)
    Q[:3, 3:6] = Q[3:6, :3] = qa * h ** 2 / 2.0 * np.eye(3)
    Q[3:6, 3:6] = qa * h * np.eye(3)
    Q[6:, 6:] = qb * h * np.eye(3)
    r = np.asarray(u.r_eci_m, float)
    rho = float(model.density_at_kgm3(math.sqrt(float(r @ r)))) if model.density_kgm3 > 0.0 else 0.0
    return _propagate(np.asarray(q, float), np.asarray(w, float), np.asarray(P, float), h, n, r,
                      np.asarray(u.v_eci_mps, float), np.asarray(u.b_eci_T, float),
                      np.asarray(u.dipole_body_Am2, float), J, Jinv, np.asarray(model.cp_offset_m, float),
                      np.asarray(model.sail_normal_body, float), float(model.sail_area_m2),
                      float(model.body_area_m2), float(model.drag_coefficient), rho, Q)


# --- the compiled propagation (tests/fsw/test_orbital_attitude_propagation.py: the same model in numpy) ---

@njit(cache=True)
def _c3(a, b):
    out = np.empty(3)
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
    return out


@njit(cache=True)
def _so3(phi):
    th2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    K = _skew(phi)
    if th2 < 1e-12:
        return np.eye(3) + K + 0.5 * K @ K
    th = math.sqrt(th2)
    return np.eye(3) + (math.sin(th) / th) * K + ((1.0 - math.cos(th)) / th2) * K @ K


@njit(cache=True)
def _torque(R, r, v, b, p, J, cp, sail_n, s_sail, s_body, cd, rho):
    RT = R.T.copy()
    r_b = RT @ r
    rn = math.sqrt(r_b[0] * r_b[0] + r_b[1] * r_b[1] + r_b[2] * r_b[2])
    rh = r_b / rn
    m = (3.0 * 3.986004418e14 / rn ** 3) * _c3(rh, J @ rh)
    v_b = RT @ v
    speed = math.sqrt(v_b[0] * v_b[0] + v_b[1] * v_b[1] + v_b[2] * v_b[2])
    if speed > 0.0 and rho > 0.0:
        vh = v_b / speed
        area = s_sail * abs(sail_n[0] * vh[0] + sail_n[1] * vh[1] + sail_n[2] * vh[2]) + s_body
        force = -0.5 * rho * speed * speed * cd * area * vh
        m = m + _c3(cp, force)
    return m + _c3(p, RT @ b)


@njit(cache=True)
def _propagate(q, w, P, h, n, r, v, b, p, J, Jinv, cp, sail_n, s_sail, s_body, cd, rho, Q):
    eye9 = np.eye(9)
    for _ in range(n):
        R = _dcm(q)
        F = np.zeros((9, 9))
        F[:3, :3] = -_skew(w)
        F[:3, 3:6] = np.eye(3)
        F[3:6, 3:6] = Jinv @ (_skew(J @ w) - _skew(w) @ J)
        eps = 1e-4
        for i in range(3):
            d = np.zeros(3)
            d[i] = eps
            mp = _torque(R @ _so3(d), r, v, b, p, J, cp, sail_n, s_sail, s_body, cd, rho)
            mm = _torque(R @ _so3(-d), r, v, b, p, J, cp, sail_n, s_sail, s_body, cd, rho)
            F[3:6, i] = Jinv @ (mp - mm) / (2.0 * eps)
        Fh = F * h
        Phi = eye9 + Fh + 0.5 * Fh @ Fh
        P = Phi @ P @ Phi.T + Q
        k1 = Jinv @ (_torque(R, r, v, b, p, J, cp, sail_n, s_sail, s_body, cd, rho) - _c3(w, J @ w))
        wm = w + 0.5 * h * k1
        qm = _qmul(q, _qexp(0.5 * h * w))
        k2 = Jinv @ (_torque(_dcm(qm), r, v, b, p, J, cp, sail_n, s_sail, s_body, cd, rho) - _c3(wm, J @ wm))
        q = _qmul(q, _qexp(h * wm))
        q = q / math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        w = w + h * k2
    return q, w, 0.5 * (P + P.T)


def update(q: np.ndarray, w: np.ndarray, beta_uT: np.ndarray, P: np.ndarray, z_body_T: np.ndarray,
           b_eci_T: np.ndarray, sigma_T: float):
    """One field sample, z = R(q)ᵀ B_I + β + v: (q, ω, β [µT], P, NIS, the sample's negative
    log-likelihood). Units inside µT (as `attitude_kalman`)."""
    z = np.asarray(z_body_T, float) * UT_PER_T
    h = quat_to_dcm(q).T @ (np.asarray(b_eci_T, float) * UT_PER_T)
    H = np.zeros((3, 9))
    H[:, :3] = skew(h)
    H[:, 6:] = np.eye(3)
    Rm = (sigma_T * UT_PER_T) ** 2 * np.eye(3)
    y = z - h - beta_uT
    S = H @ P @ H.T + Rm
    K = np.linalg.solve(S, H @ P).T
    dx = K @ y
    IKH = np.eye(9) - K @ H
    P = IKH @ P @ IKH.T + K @ Rm @ K.T
    nis = float(y @ np.linalg.solve(S, y))
    nll = 0.5 * (nis + math.log(max(float(np.linalg.det(S)), 1e-300)))
    q = quat_mul(q, quat_exp(dx[:3]))
    return q / np.linalg.norm(q), w + dx[3:6], beta_uT + dx[6:], 0.5 * (P + P.T), nis, nll


def start_state(z_body_T: np.ndarray, b_eci_T: np.ndarray, omega_oi_eci: np.ndarray, angle_about_b_rad: float,
                tuning: OrbitalAttitudeTuning, sigma_T: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A hypothesis from the first sample: aligned with the field, turned by `angle_about_b_rad` about it,
    at rest in the orbital frame; (q, ω, P)."""
    q = quat_aligning(np.asarray(z_body_T, float), np.asarray(b_eci_T, float), angle_about_b_rad)
    w = quat_to_dcm(q).T @ omega_oi_eci
    bh = np.asarray(z_body_T, float) / np.linalg.norm(z_body_T)
    s_perp2 = tuning.sigma_angle0_rad ** 2 + (math.hypot(sigma_T, tuning.sigma_bias0_T)
                                              / float(np.linalg.norm(z_body_T))) ** 2
    P = np.zeros((9, 9))
    P[:3, :3] = s_perp2 * (np.eye(3) - np.outer(bh, bh)) + tuning.sigma_about_b0_rad ** 2 * np.outer(bh, bh)
    P[3:6, 3:6] = tuning.sigma_rate0_radps ** 2 * np.eye(3)
    P[6:, 6:] = (tuning.sigma_bias0_T * UT_PER_T) ** 2 * np.eye(3)
    return q, w, P


# --- the stateful bank -------------------------------------------------------------------------------

@dataclass
class Member:
    q: np.ndarray
    w: np.ndarray
    P: np.ndarray
    beta_uT: np.ndarray = field(default_factory=lambda: np.zeros(3))
    nll: float = 0.0
    nis: float = 0.0
    angle0_rad: float = 0.0


@dataclass
class OrbitalAttitudeBank:
    """The filter one sample at a time: `update(t_s, b_T, dipole_body_Am2, mean_dipole_body_Am2)` with the
    calibrated, kit-free sample, the kit's dipole from now on and its mean since the previous sample (the
    sequencer's: a shutter's ramp counted); `best` the member of least cumulative NLL.

    `inputs_at(t_s)` gives the orbit's position, velocity and field at a time (:class:`OrbitInputs`)."""

    sigma_b_T: float
    inputs_at: Callable[[float], tuple[np.ndarray, np.ndarray, np.ndarray]]
    model: SpacecraftModel = field(default_factory=SpacecraftModel)
    tuning: OrbitalAttitudeTuning = field(default_factory=OrbitalAttitudeTuning)
    members: list = field(default_factory=list)
    t_s: float = math.nan
    t_start_s: float = math.nan
    samples: int = 0
    restarts: int = 0
    _dipole: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def sigma_T(self) -> float:
        return math.hypot(self.sigma_b_T, self.tuning.field_sigma_T)

    @property
    def started(self) -> bool:
        return bool(self.members)

    @property
    def best(self) -> Member | None:
        return min(self.members, key=lambda m: m.nll) if self.members else None

    def reset(self) -> None:
        self.members = []
        self.t_s = math.nan

    def update(self, t_s: float, b_T: np.ndarray, dipole_body_Am2: np.ndarray | None = None,
               mean_dipole_body_Am2: np.ndarray | None = None, kit_step_cov_T2: np.ndarray | None = None) -> None:
        """A sample; the kit's dipole acting from now on (held until the next sample when its mean over
        the step, `mean_dipole_body_Am2`, is not given then); `kit_step_cov_T2`: how much the sample's error
        may have stepped since the previous one with the kit's state (the kit-field model's covariance of
        that change, plus `kit_step_floor_sigma_T`² per axis at a change of the dipole); without it a change
        of the dipole opens the bias by `kit_change_bias_sigma_T`."""
        b = np.asarray(b_T, float)
        if not np.all(np.isfinite(b)):
            return
        r, v, b_eci = self.inputs_at(t_s)
        if not self.members or t_s - self.t_s > self.tuning.max_gap_s or t_s <= self.t_s:
            if self.members:
                self.restarts += 1
            self._start(t_s, b, r, v, b_eci)
        else:
            # the inputs held over the step: the orbit at its middle, the dipole that acted since the last sample
            tm = 0.5 * (self.t_s + t_s)
            rm, vm, bm = self.inputs_at(tm)
            u = Inputs(rm, vm, bm, self._dipole if mean_dipole_body_Am2 is None
                       else np.asarray(mean_dipole_body_Am2, float))
            dt = t_s - self.t_s
            for m in self.members:
                m.q, m.w, m.P = predict(m.q, m.w, m.P, dt, u, self.model, self.tuning)
                m.q, m.w, m.beta_uT, m.P, m.nis, nll = update(m.q, m.w, m.beta_uT, m.P, b, b_eci, self.sigma_T)
                m.nll += nll
            best = min(self.members, key=lambda m: m.nll)
            if t_s - self.t_start_s >= self.tuning.decide_after_s:
                self.members = [best]
            else:
                self.members = [m for m in self.members if m.nll - best.nll <= self.tuning.drop_nll]
        self.t_s = t_s
        self.samples += 1
        if dipole_body_Am2 is not None:
            p = np.asarray(dipole_body_Am2, float)
            changed = bool(np.any(p != self._dipole))
            if kit_step_cov_T2 is not None:  # the kit-field model's own uncertainty of the step
                jump = np.asarray(kit_step_cov_T2, float) * UT_PER_T ** 2
                if changed:
                    jump = jump + (self.tuning.kit_step_floor_sigma_T * UT_PER_T) ** 2 * np.eye(3)
            elif changed:  # the kit's field at the sensor changes with it
                jump = (self.tuning.kit_change_bias_sigma_T * UT_PER_T) ** 2 * np.eye(3)
            else:
                jump = None
            if jump is not None:
                for m in self.members:
                    m.P[6:, 6:] += jump
            self._dipole = p.copy()

    def shift_bias(self, step_T: np.ndarray) -> None:
        """The samples from now on carry `step_T` more (body axes): a change of the host calibration applied
        to them, known on board. Each member's bias moves by it, so that the step is not met as an error of
        the attitude (the bias's σ is unchanged: what the member knew of the error left is still known)."""
        d = np.asarray(step_T, float) * UT_PER_T
        for m in self.members:
            m.beta_uT = m.beta_uT + d

    def spread_rad(self) -> float:
        """The largest angle between the best hypothesis's sail normal (body x) and another's [rad]."""
        best = self.best
        if best is None:
            return math.nan
        x0 = quat_to_dcm(best.q)[:, 0]
        return max((math.acos(max(-1.0, min(1.0, float(quat_to_dcm(m.q)[:, 0] @ x0)))) for m in self.members),
                   default=0.0)

    def _start(self, t_s: float, b: np.ndarray, r: np.ndarray, v: np.ndarray, b_eci: np.ndarray) -> None:
        _, w_oi = orbital_frame(r, v)
        n = max(1, int(self.tuning.hypotheses))
        self.members = []
        for k in range(n):
            angle = 2.0 * math.pi * k / n
            q, w, P = start_state(b, b_eci, w_oi, angle, self.tuning, self.sigma_T)
            q, w, beta, P, nis, _ = update(q, w, np.zeros(3), P, b, b_eci, self.sigma_T)
            self.members.append(Member(q, w, P, beta, 0.0, nis, angle))
        self.t_start_s = t_s

    def orbital(self, t_s: float, member: Member | None = None):
        """(R_bo, ω_rel body axes, σ of the pointing error about body y and z [rad], σ of ω [rad/s] per axis)
        of `member` (default the best) propagated to `t_s` without a sample; None before the start."""
        m = member or self.best
        if m is None:
            return None
        q, w, P = m.q, m.w, m.P
        if t_s > self.t_s:
            r, v, b_eci = self.inputs_at(0.5 * (self.t_s + t_s))
            q, w, P = predict(q, w, P, t_s - self.t_s, Inputs(r, v, b_eci, self._dipole), self.model, self.tuning)
        r, v, _ = self.inputs_at(t_s)
        R_oi, w_oi = orbital_frame(r, v)
        R_bi = quat_to_dcm(q)
        R_bo = R_oi.T @ R_bi
        w_rel = w - R_bi.T @ w_oi
        sd = np.sqrt(np.maximum(np.diag(P), 0.0))
        return R_bo, w_rel, (float(sd[1]), float(sd[2])), sd[3:6].copy(), q


class OrbitInputs:
    """`inputs_at(t_s)` for the bank from an onboard field along the orbit (an
    `onboard_field.OnboardOrbitField` or `InterpolatedOrbitField`): position (SGP4 or the circular orbit),
    velocity by a central difference of positions 1 s apart, and B_I(t)."""

    def __init__(self, field) -> None:
        self.field = field
        self._position = orbit_position_fn(field)

    def __call__(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r3 = np.asarray(self._position(np.array([t_s - 1.0, t_s, t_s + 1.0])), float)
        return r3[1], 0.5 * (r3[2] - r3[0]), np.asarray(self.field.b_eci_T(t_s), float)


def orbit_position_fn(field) -> Callable[[np.ndarray], np.ndarray]:
    """Positions (N, 3) [m, inertial] at box times (N,) along the orbit a field is computed on: a TLE's
    (SGP4 at the field's UTC) or a circular orbit's (`field_motion.CircularOrbitModel`)."""
    field = getattr(field, "__self__", field)   # a field's bound b_eci_T: the field itself
    sat, utc_of = getattr(field, "sat", None), getattr(field, "utc_of", None)
    if sat is not None and utc_of is not None:
        def tle_position(t):
            days = np.asarray(utc_of(np.asarray(t, float)), float) / 86400.0
            whole = np.floor(days)
            err, r_km, _ = sat.sgp4_array(whole + 2440587.5, days - whole)
            if np.any(err):
                raise ValueError(f"SGP4 error codes {sorted(set(err[err != 0].tolist()))}")
            return r_km * 1e3
        return tle_position
    for obj in (field, getattr(field, "orbit_field", None)):
        orbit = getattr(obj, "orbit", None)
        if orbit is not None and hasattr(orbit, "position_eci_m"):
            return orbit.position_eci_m
    raise ValueError("the field along the orbit does not say where the orbit is")


def orbital_field_forecast(inputs: OrbitInputs) -> Callable[[np.ndarray], np.ndarray]:
    """times (N,) -> the field along the orbit in orbital axes (N, 3) [T]: the controller's forecast."""
    def forecast(t_s):
        t = np.atleast_1d(np.asarray(t_s, float))
        out = np.empty((t.size, 3))
        for k, tk in enumerate(t):
            r, v, b = inputs(float(tk))
            out[k] = orbital_frame(r, v)[0].T @ b
        return out
    return forecast
