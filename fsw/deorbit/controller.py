"""The de-orbit kit's discrete magnetic controller (lapkhanov2019 eq. 4-6).

Frames (see also `hil.environment`): the orbital frame o has x_o along the orbital velocity (the
flight direction; the atmosphere flows along −x_o), z_o to nadir, y_o = z_o × x_o. The body attitude
w.r.t. it is R_bo = Rz(ψ) Ry(θ) Rx(φ) (yaw ψ, pitch θ, roll φ; v_o = R_bo v_b). The sail's normal is
body x, so ψ and θ are the azimuth and elevation of the sail normal w.r.t. the flight direction and do
not depend on roll; ψ = θ = 0 is the sail broadside to the flow. The controller's errors are roll-free
too: with f = R_boᵀ x_o (the flight direction in body axes) and α = acos(f_x) the angle between the sail
normal and the flow, δ = α / sin α · (f_z, −f_y) = (δ_y, δ_z) ≈ (θ, ψ) for small angles: the rotation
about body y and z that would bring the sail normal onto the flow, negated.

The law (eq. 4-6):

- eq. 4: M = p × B, p the unscreened dipoles, B the geomagnetic field (body axes);
- eq. 5: p = (0, p_my, p_mz) (yaw magnet along y, pitch magnet along z):
  M_x = p_my B_z − p_mz B_y (roll: not controlled), M_y = sign(δ_y)·p_mz·B_x, M_z = sign(δ_z)·(−p_my·B_x);
  so the pitch magnet's polarity is sign(M_y)·sign(B_x), the yaw magnet's −sign(M_z)·sign(B_x);
- eq. 6: pulse width t_imp = M_theor·T / M_ctrl with M_ctrl = p·|B_x| the moment of the open channel
  and T the controller period; pulses shorter than `min_impulse_s` (80 s in the paper) are not
  generated, longer ones are limited to T.

What produces M_theor (the moment the regulator asks for in each channel) is `law`:

- ``"paper"``: a PD law per channel, M_theor = −k_p δ − k_d ω_rel (ω_rel the body rate relative to the
  orbital frame), with k_d = J/T (a pulse cancels the rate error in one period) and k_p = k_d/τ.
  In the full dynamics (the roll moment M_x of eq. 5 included) this spins the roll axis up: the yaw
  magnet's roll moment p_my·B_z is up to twice its yaw moment away from the magnetic equator.
- ``"mpc"`` (default): a receding-horizon choice. The linearised motion about the target (LVLH,
  gravity gradient, aerodynamic stiffness, roll-yaw gyroscopic coupling: :func:`lvlh_model`) is
  predicted over `horizon` periods with the field along the orbit (`b_orbital_forecast`, attitude frozen
  over the horizon) and the full moment of each channel, roll included. For each discrete first move
  (each channel closed, or open with polarity ±1 for one of `widths_s` seconds, none shorter than the
  minimum impulse) the best continuation is found: duty cycles u ∈ [−1, 1] per period and channel (a
  pulse cannot be longer than its period) minimising Σ_k x_kᵀQx_k + r Σ u² + λ Σ |u| + w·x_Nᵀ P x_N,
  where the ℓ1 term λ stands for the cost of the later openings (it makes the continuation sparse:
  pulses when the field gives the most moment per opening) and x_NᵀPx_N is the squared amplitude of the
  oscillation that is left to coast after the horizon (:func:`coast_amplitude_sqrt`). Box and ℓ1 make it a
  small box-constrained lasso, solved by coordinate descent for all first moves at once
  (:func:`box_lasso`). The first move of least cost + `energy_price` × its joules (an opening 23.4 J, a
  turn 11.7 J) wins. M_theor is then the chosen width × M_ctrl / T (eq. 6 read backwards), so the
  pulses still obey eq. 5 and eq. 6.

  The continuation's price (`continuation_reweight`, off by default). Per unit of duty, λ makes a small
  trim later look almost free (a duty of 0.05 costs λ/20), while the kit pays an opening for any pulse and
  cannot open for less than the minimum impulse: the plan then keeps deferring the trim of a swing of
  0.1–0.2 rad, period after period, and the libration coasts. With `continuation_reweight` passes of a
  reweighted ℓ1 (:meth:`DiscreteController.reweighted`) the price of each later pulse is about
  `continuation_pulse_price` whatever its width, the fixed price an opening has.

  The energy guard (`energy_guard_rad`, off by default). With 80-s pulses of 15 A·m², one pulse changes
  a rate by ~1·10⁻³ rad/s, as much as a whole swing: a pulse takes energy out of the libration only when
  the rate along its angular impulse ΔL exceeds |ΔL|/2J (ΔE = ω·ΔL + ½ΔLᵀJ⁻¹ΔL), i.e. at high rates or
  where the field's components are weak. The plan alone often picks pulses that add energy now, counting
  on later pulses, timed on its model of the field along the orbit, to take it out again; from large
  angles that bet can fail (the model is linear about the target, the field frozen in body axes), and
  under the IGRF-14 degree-13 field from 45° along the orbit the swing was pumped over 180°. With the
  guard, outside the pitch/yaw libration energy of an `energy_guard_rad` swing (the LVLH model's), a
  first move may not leave more of it after its period than coasting would. Counting roll as well, the
  guard blocked every pulse from the 60°/45° start (no pulse can take energy out at those rates with
  roll kicks counted). Pitch and yaw only, from 45° under the degree-13 field it brought yaw and pitch
  within 0.05 rad by 3,300 s, then the pulses' roll kicks spun the roll up and the roll-yaw coupling
  took yaw to 1.5 rad (990 J); from 225° it held (0.200 / 0.129 rad, 447 J). With the roll's own
  libration energy guarded too (outside a `roll_guard_rad` swing) too few pulses pass (0°, 45°, 225°:
  0.95, 0.87, 1.46 rad in yaw). Hence off by default.

  What the plan is linearised about (`prediction`): "linear" (default), the LVLH model from the
  attitude now with the field at that attitude frozen over the horizon; "nonlinear", the free motion
  from the attitude now at any angle (:func:`free_motion`), the field turned into body axes along it
  and every later state's response to each period's pulse propagated along it (:func:`impulse_responses`,
  a secant over a twentieth of a pulse). Near the target the two are the same model (tested); from the
  60°/45° start at 225° along the orbit the nonlinear one spun the roll up within 300 s (the secant of a
  twentieth of a pulse says little about a whole one at large angles), so it is not the default.
  Neither option has yet been measured to hold all eight starts.
- ``"energy"``: candidate pulse sequences over a few periods predicted on the nonlinear motion in the
  forecast field and scored by the energy of the libration (`fsw.deorbit.energy_horizon`); below the energy
  of an `energy_switch_rad` yaw swing the ``"mpc"`` choice decides. `nonlinear_guard_rad` applies the same
  prediction as a guard of the ``"mpc"`` choice (off by default).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numba import njit
from scipy.linalg import expm

from ..estimation.rotations import rotvec_from_dcm
from . import energy_horizon as eh
from .relative_motion import free_motion, rk4_step

MU_EARTH_M3S2 = 3.986004418e14
OPENING_J = 2.0 * 11.7
TURN_J = 1.0 * 11.7
#: home direction of each channel's dipole in body axes: pitch magnet along z, yaw magnet along y
CHANNEL_AXIS = (np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0]))


# --- pure functions -------------------------------------------------------------------------------
def euler_zyx(R_bo: np.ndarray) -> tuple[float, float, float]:
    """(yaw ψ, pitch θ, roll φ) [rad] with R_bo = Rz(ψ) Ry(θ) Rx(φ)."""
    return (float(math.atan2(R_bo[1, 0], R_bo[0, 0])), float(-math.asin(max(-1.0, min(1.0, R_bo[2, 0])))),
            float(math.atan2(R_bo[2, 1], R_bo[2, 2])))


def pointing_error(R_bo: np.ndarray) -> tuple[float, float]:
    """(δ_y, δ_z) [rad]: the sail normal's error about body y and z (≈ (θ, ψ) when small), roll-free."""
    f = R_bo[0, :]  # x_o in body axes
    s = math.hypot(f[1], f[2])
    alpha = math.acos(max(-1.0, min(1.0, f[0])))
    k = alpha / s if s > 1e-12 else 1.0
    return float(f[2] * k), float(-f[1] * k)


def magnet_moment_Nm(p_body_Am2: np.ndarray, b_body_T: np.ndarray) -> np.ndarray:
    """Eq. 4: M = p × B."""
    return np.cross(p_body_Am2, b_body_T)


def discrete_moment_Nm(polarity_pitch: int, polarity_yaw: int, dipole_Am2: float, b_body_T: np.ndarray) -> np.ndarray:
    """Eq. 5 with p = (0, p_my, p_mz): (p_my B_z − p_mz B_y, p_mz B_x, −p_my B_x); 0 = screened."""
    p_my, p_mz = polarity_yaw * dipole_Am2, polarity_pitch * dipole_Am2
    bx, by, bz = b_body_T
    return np.array([p_my * bz - p_mz * by, p_mz * bx, -p_my * bx])


def polarity_for(channel: int, m_theor_Nm: float, b_x_T: float) -> int:
    """Eq. 5 solved for the sign: pitch (0) sign(M_y)·sign(B_x), yaw (1) −sign(M_z)·sign(B_x); 0 if either is 0."""
    s = int(np.sign(m_theor_Nm) * np.sign(b_x_T))
    return s if channel == 0 else -s


def pulse_width_s(m_theor_Nm: float, m_ctrl_Nm: float, period_s: float, min_impulse_s: float) -> float:
    """Eq. 6: t_imp = |M_theor|·T / M_ctrl, 0 when shorter than the minimum impulse, at most T."""
    if m_ctrl_Nm <= 0.0:
        return 0.0
    t = abs(m_theor_Nm) * period_s / m_ctrl_Nm
    return 0.0 if t < min_impulse_s else min(t, period_s)


def aero_stiffness_Nm_per_rad(rho_kgm3: float, speed_mps: float, cd: float, area_m2: float,
                              cp_offset_m: float) -> float:
    """Weathervane stiffness of a sail behind the centre of mass: |r_cp|·½ρv²C_d·S [N·m/rad]."""
    return abs(cp_offset_m) * 0.5 * rho_kgm3 * speed_mps**2 * cd * area_m2


def lvlh_model(J_diag_kgm2: np.ndarray, mean_motion_radps: float, k_aero_Nm_per_rad: float) -> np.ndarray:
    """A (6×6) of x = (φ, θ, ψ, ω_rel) about the target, ẋ = A x + [0; J⁻¹] M (Wie, Space Vehicle
    Dynamics and Control, gravity-gradient attitude in LVLH with x along-track, z nadir) plus the
    aerodynamic stiffness on pitch and yaw:

        J1 φ̈ + 4n²(J2−J3) φ − n(J1−J2+J3) ψ̇ = M1
        J2 θ̈ + (3n²(J1−J3) + k_a) θ         = M2
        J3 ψ̈ + (n²(J2−J1) + k_a) ψ + n(J1−J2+J3) φ̇ = M3
    """
    J1, J2, J3 = (float(x) for x in J_diag_kgm2)
    n, ka = float(mean_motion_radps), float(k_aero_Nm_per_rad)
    g = n * (J1 - J2 + J3)
    A = np.zeros((6, 6))
    A[0:3, 3:6] = np.eye(3)
    A[3, 0] = -4.0 * n * n * (J2 - J3) / J1
    A[3, 5] = g / J1
    A[4, 1] = -(3.0 * n * n * (J1 - J3) + ka) / J2
    A[5, 2] = -(n * n * (J2 - J1) + ka) / J3
    A[5, 3] = -g / J3
    return A


def coast_amplitude_sqrt(A: np.ndarray, q_angle: tuple[float, float, float]) -> np.ndarray:
    """L (6×6) with xᵀLᵀLx = Σ_a q_a·(amplitude of angle a)² of the free motion ẋ = A x from x.

    For a conservative A (imaginary eigenvalues, distinct frequencies) the motion is a sum of modes,
    angle_a(t) = Σ_m V_am c_m e^{λ_m t} with c = V⁻¹x, and the time average of angle_a² is Σ_m |V_am|²|c_m|²
    (the cross terms average out); twice that is the squared amplitude of a sinusoid. So
    P = 2 Σ_m (Σ_a q_a |V_am|²) w_mᴴ w_m with w_m the rows of V⁻¹, and L is its symmetric square root.
    """
    lam, V = np.linalg.eig(A)
    W = np.linalg.inv(V)
    weight = 2.0 * (np.asarray(q_angle, dtype=float)[:, None] * np.abs(V[:3, :]) ** 2).sum(axis=0)
    P = ((W.conj().T * weight) @ W).real
    P = 0.5 * (P + P.T)
    w, U = np.linalg.eigh(P)
    return (U * np.sqrt(np.maximum(w, 0.0))).T


def unwrapped_rotvecs(R0: np.ndarray, Rs: np.ndarray) -> list[np.ndarray]:
    """The rotation vectors of the attitudes `Rs` (k, 3, 3) along a motion from `R0`, continued across 180°
    (each the representative nearest the previous: φ or φ − 2π φ̂ or φ + 2π φ̂), so that a predicted tumble
    costs more the further it turns instead of jumping back to a small angle at 180°."""
    prev = rotvec_from_dcm(R0)
    out = []
    for R in Rs:
        prev = _nearest_rotvec(rotvec_from_dcm(R), prev)
        out.append(prev)
    return out


def _nearest_rotvec(v: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Of the rotation vectors of one rotation (v, v ∓ 2π v̂), the one nearest `ref`."""
    a = float(np.linalg.norm(v))
    if a <= 1e-9:
        return v
    u = v / a
    return min((v, v - 2.0 * math.pi * u, v + 2.0 * math.pi * u), key=lambda c: float(np.sum((c - ref) ** 2)))


@njit(cache=True)
def _rotvec_near(R, ref):
    """The rotation vector of R (as `rotations.rotvec_from_dcm`) of the representatives φ, φ ∓ 2π φ̂ nearest `ref`."""
    c = max(-1.0, min(1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    angle = math.acos(c)
    w = np.array((R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]))
    if angle < 1e-9:
        return 0.5 * w
    if math.pi - angle < 1e-6:
        axis = np.sqrt(np.maximum((np.array((R[0, 0], R[1, 1], R[2, 2])) + 1.0) / 2.0, 0.0))
        i = int(np.argmax(axis))
        axis[(i + 1) % 3] = math.copysign(axis[(i + 1) % 3], R[i, (i + 1) % 3])
        axis[(i + 2) % 3] = math.copysign(axis[(i + 2) % 3], R[i, (i + 2) % 3])
        v = angle * axis / math.sqrt(axis @ axis)
    else:
        v = angle / (2.0 * math.sin(angle)) * w
    u = v / math.sqrt(v @ v)
    best, dbest = v, ((v - ref) ** 2).sum()
    for s in (-1.0, 1.0):
        cand = v + s * 2.0 * math.pi * u
        d = ((cand - ref) ** 2).sum()
        if d < dbest:
            best, dbest = cand, d
    return best


@njit(cache=True)
def response_matrix(Rp, wp, rv_free, w_free, scale):
    """pred (6N, 2N) of the linear plan from :func:`impulse_responses`: row 6k+a the state at (k+1)·T
    (rotation vector a < 3, ω_rel a ≥ 3), column 2j+c period j's channel c, per unit of duty (÷ `scale`)."""
    N, C = Rp.shape[0], Rp.shape[1]
    pred = np.zeros((6 * N, C * N))
    for j in range(N):
        for c in range(C):
            for k in range(j, N):
                rv = _rotvec_near(Rp[j, c, k], rv_free[k])
                for a in range(3):
                    pred[6 * k + a, C * j + c] = (rv[a] - rv_free[k, a]) / scale
                    pred[6 * k + 3 + a, C * j + c] = (wp[j, c, k, a] - w_free[k, a]) / scale
    return pred


@njit(cache=True)
def impulse_responses(Rs, ws, dw, J, n, ka, sail_share, h, substeps, periods):
    """The motion after a rate change `dw[j, c]` (body axes) at the middle of period j along the free motion
    (`Rs`, `ws` from :func:`free_motion` with `substeps` steps a period): R (N, C, N, 3, 3) and ω (N, C, N, 3)
    at the ends of the periods k = j..N−1 (entry [j, c, k] is the state at (k+1)·T; earlier entries are
    the free motion's)."""
    N, C = periods, dw.shape[1]
    Rout = np.empty((N, C, N, 3, 3))
    wout = np.empty((N, C, N, 3))
    half = substeps // 2
    for j in range(N):
        for c in range(C):
            for k in range(j):
                Rout[j, c, k] = Rs[(k + 1) * substeps]
                wout[j, c, k] = ws[(k + 1) * substeps]
            i0 = j * substeps + half
            R, w = Rs[i0].copy(), ws[i0] + dw[j, c]
            for i in range(i0, N * substeps):
                R, w = rk4_step(R, w, J, n, ka, sail_share, h)
                if (i + 1) % substeps == 0:
                    k = (i + 1) // substeps - 1
                    Rout[j, c, k] = R
                    wout[j, c, k] = w
    return Rout, wout


@njit(cache=True)
def box_lasso_weighted(H: np.ndarray, B: np.ndarray, Lam: np.ndarray, V0: np.ndarray, sweeps: int,
                       tol: float = 1e-9) -> np.ndarray:
    """:func:`box_lasso` with a price per unknown and column, min vᵀHv − 2bᵀv + Σ_i Λ_ic |v_i| for each column c
    (Lam (n, C)), started from V0 (n, C): the passes of a reweighted ℓ1 (:meth:`DiscreteController._mpc`)."""
    n, C = B.shape
    V = V0.copy()
    HV = H @ V
    for _ in range(sweeps):
        moved = 0.0
        for i in range(n):
            d = H[i, i]
            for c in range(C):
                t = B[i, c] - HV[i, c] + d * V[i, c]
                a = abs(t) - 0.5 * Lam[i, c]
                new = 0.0
                if a > 0.0:
                    new = min(1.0, max(-1.0, math.copysign(a, t) / d))
                delta = new - V[i, c]
                if delta != 0.0:
                    for j in range(n):
                        HV[j, c] += H[j, i] * delta
                    V[i, c] = new
                    moved = max(moved, abs(delta))
        if moved < tol:
            break
    return V


@njit(cache=True)
def box_lasso(H: np.ndarray, B: np.ndarray, lam: float, sweeps: int, tol: float = 1e-9) -> np.ndarray:
    """min over v ∈ [−1, 1]ⁿ of vᵀHv − 2bᵀv + λ‖v‖₁, for each column b of B (n, C); H = MᵀM (n×n) with a
    positive diagonal. Cyclic coordinate descent: per coordinate the 1-D minimiser is the soft-threshold
    of t = b_i − Σ_{j≠i} H_ij v_j by λ/2, divided by H_ii and clipped to the box (exact for a convex 1-D
    problem); stops after `sweeps` sweeps or when no coordinate moved by more than `tol`. Returns V (n, C).
    Compiled (numba, cached on disk): ~40 sweeps over 38 × 49 unknowns in a few milliseconds."""
    n, C = B.shape
    return box_lasso_weighted(H, B, np.full((n, C), lam), np.zeros((n, C)), sweeps, tol)


# --- the controller -------------------------------------------------------------------------------
@dataclass
class AttitudeInput:
    """What the controller needs at a decision (SI, body axes unless named)."""

    R_bo: np.ndarray  # body -> orbital
    omega_rel_radps: np.ndarray  # body rate relative to the orbital frame
    b_body_T: np.ndarray  # geomagnetic field now
    b_orbital_forecast: Callable[[np.ndarray], np.ndarray] | None = None  # times (N,) -> field (N, 3), orbital axes


@dataclass(frozen=True)
class ControllerConfig:
    law: str = "mpc"
    period_s: float = 100.0
    min_impulse_s: float = 80.0
    dipole_Am2: float = 15.0
    # the controller's model of the spacecraft (lapkhanov2019 Table 1, 600 km)
    inertia_kgm2: tuple[float, float, float] = (17.995, 20.711, 15.269)
    mean_motion_radps: float = 1.0831e-3
    aero_stiffness_Nm_per_rad: float = 6.1e-6
    # "mpc"
    horizon: int = 20
    widths_s: tuple[float, ...] = (80.0, 90.0, 100.0)
    q_angle: tuple[float, float, float] = (0.05, 1.0, 1.0)  # roll, pitch, yaw [1/rad²]
    q_rate: float = 1e4  # [1/(rad/s)²]
    r_duty: float = 1e-3
    continuation_l1: float = 0.03  # λ: price of the continuation's pulses (per unit duty cycle)
    terminal_weight: float = 10.0  # w: weight of the amplitude left after the horizon
    energy_price_per_J: float = 1e-3
    lasso_sweeps: int = 40
    #: the continuation's pulses priced per pulse, as the kit pays (an opening whatever the width), not per
    #: unit of duty: this many passes of a reweighted ℓ1 after the lasso, each unknown's price
    #: `continuation_pulse_price`·(1 + ε)/(|u| + ε) at the previous pass (ε `reweight_eps`), so that a pulse
    #: of any width costs about `continuation_pulse_price`; 0 (the default): the ℓ1 price alone
    continuation_reweight: int = 0
    continuation_pulse_price: float = 0.06
    reweight_eps: float = 0.05
    #: the motion the plan starts from: "nonlinear" (:func:`free_motion`, the field turned with the attitude
    #: along it) or "linear" (the LVLH model from the attitude now, the field at the attitude frozen)
    prediction: str = "linear"
    #: outside the pitch/yaw libration energy of this pointing error (the LVLH model's), a first move may not
    #: leave more of it than coasting would (0, the default: no guard; see the module docstring)
    energy_guard_rad: float = 0.0
    #: with the guard: the roll's own libration energy is held the same way outside a swing of this size
    roll_guard_rad: float = 1.0
    free_motion_substeps: int = 10  # RK4 steps per period (even: the mid-point is a step)
    sail_share: float = 5.0 / 5.58  # the sail's share of the area the flow sees broadside (the rest: the body)
    # "energy" (`fsw.deorbit.energy_horizon`)
    energy_horizon: int = 3  # periods predicted: the first move and horizon − 1 periods of continuation
    energy_substeps: int = 5  # RK4 steps a period (the widths must be whole steps)
    energy_widths_s: tuple[float, ...] = (80.0, 100.0)  # the first move's pulse widths
    #: the price of the kit's joules in the spacecraft's libration energy [J per J]
    energy_price_J_per_J: float = 0.0
    #: a pulse must beat staying closed by this fraction of the energy it moves (field-model error)
    energy_margin: float = 0.0
    #: no opening while the libration energy is below that of a yaw swing of this size
    deadband_rad: float = 0.0
    #: below the energy of a swing of this size (pitch and yaw: `energy_switch_axes`) the "mpc" choice
    #: decides (its linear model holds there); 0: the energy law everywhere
    energy_switch_rad: float = 0.8
    energy_switch_axes: str = "total"  # "total": the Jacobi energy; "pitch-yaw": the LVLH pitch/yaw part
    #: "mpc": above the energy of a yaw swing of this size, a first move that the nonlinear prediction
    #: (`energy_horizon.pumps`, `energy_substeps_guard` steps a period) says ends the energy horizon with more
    #: energy than staying closed is replaced by the "energy" law's choice (0: no guard)
    nonlinear_guard_rad: float = 0.0
    energy_substeps_guard: int = 10
    # "paper"
    kd_Nm_s: float | None = None  # default J/T
    tau_s: float = 600.0  # k_p = k_d / τ

    def __post_init__(self) -> None:
        if self.law not in ("mpc", "paper", "energy"):
            raise ValueError(f"law must be 'mpc', 'paper' or 'energy', got {self.law!r}")
        if not (self.energy_horizon >= 1 and self.energy_substeps >= 1 and self.energy_margin >= 0
                and self.energy_price_J_per_J >= 0 and self.deadband_rad >= 0):
            raise ValueError("need energy_horizon >= 1, energy_substeps >= 1, energy_margin >= 0, "
                             "energy_price_J_per_J >= 0, deadband_rad >= 0")
        if self.prediction not in ("nonlinear", "linear"):
            raise ValueError(f"prediction must be 'nonlinear' or 'linear', got {self.prediction!r}")
        if self.free_motion_substeps < 2 or self.free_motion_substeps % 2 or not 0.0 <= self.sail_share <= 1.0:
            raise ValueError("need an even free_motion_substeps >= 2 and 0 <= sail_share <= 1")
        if not self.energy_guard_rad >= 0.0:
            raise ValueError("need energy_guard_rad >= 0")
        if not self.period_s > 0 or not 0 <= self.min_impulse_s <= self.period_s:
            raise ValueError("need period_s > 0 and 0 <= min_impulse_s <= period_s")
        if any(not self.min_impulse_s <= w <= self.period_s for w in self.widths_s):
            raise ValueError("widths_s must lie in [min_impulse_s, period_s]")
        if not (self.r_duty > 0 and self.continuation_l1 >= 0 and self.terminal_weight >= 0 and self.horizon >= 2
                and self.lasso_sweeps >= 1):
            raise ValueError("need r_duty > 0, continuation_l1 >= 0, terminal_weight >= 0, horizon >= 2, "
                             "lasso_sweeps >= 1")
        if not (self.continuation_reweight >= 0 and self.continuation_pulse_price >= 0 and self.reweight_eps > 0):
            raise ValueError("need continuation_reweight >= 0, continuation_pulse_price >= 0, reweight_eps > 0")


@dataclass
class ChannelCommand:
    """One channel's decision: polarity ±1 for width_s seconds (polarity 0: screened)."""

    channel: int
    polarity: int
    width_s: float
    m_theor_Nm: float
    m_ctrl_Nm: float


class DiscreteController:
    """Decides the pulses of both channels once per period; pure computation, no hardware."""

    #: the fraction of a full pulse whose response is propagated to linearise about the nonlinear motion
    FD_DUTY = 0.05

    def __init__(self, config: ControllerConfig = ControllerConfig()) -> None:
        self.config = config
        c = config
        self.J = np.array(c.inertia_kgm2, dtype=float)
        self.A = lvlh_model(self.J, c.mean_motion_radps, c.aero_stiffness_Nm_per_rad)
        T, N = c.period_s, c.horizon
        Bu = np.vstack((np.zeros((3, 3)), np.diag(1.0 / self.J)))
        self._Phi = expm(self.A * T)
        self._Phi_half_B = expm(self.A * T / 2.0) @ Bu
        powers = [np.eye(6)]
        for _ in range(N):
            powers.append(self._Phi @ powers[-1])
        self._Phi_stack = np.array(powers)  # Φ^0 .. Φ^N
        self._q_sqrt = np.sqrt(np.array(list(c.q_angle) + [c.q_rate] * 3))
        self._terminal = math.sqrt(c.terminal_weight) * coast_amplitude_sqrt(self.A, c.q_angle)
        box_lasso(np.eye(2), np.ones((2, 1)), 0.0, 1)  # load (or compile) the kernels now (the weighted one with it)
        free_motion(np.eye(3), np.zeros(3), self.J, c.mean_motion_radps, 0.0, 0.0, 1.0, 1)
        self.decisions = 0
        self.guarded = 0  # "mpc" first moves replaced by the nonlinear guard
        self.last: list[ChannelCommand] = []
        self.last_error_rad = (math.nan, math.nan)

    # --- the two regulators ---------------------------------------------------------------------
    def decide(self, now_s: float, att: AttitudeInput, acting: tuple[int, int] = (0, 0),
               polarity: tuple[int, int] = (0, 0)) -> list[ChannelCommand]:
        """Pulses for the period starting now. `acting`: polarity open now per channel (0 closed);
        `polarity`: the magnets' polarity now (0 unknown)."""
        self.decisions += 1
        self.last_error_rad = pointing_error(att.R_bo)
        if self.config.law == "paper":
            cmds = self._paper(att)
        elif self.config.law == "energy":
            cmds = self._energy(now_s, att, acting, polarity)
        else:
            cmds = self._mpc(now_s, att, acting, polarity)
        self.last = cmds
        return cmds

    def _paper(self, att: AttitudeInput) -> list[ChannelCommand]:
        c = self.config
        dy, dz = pointing_error(att.R_bo)
        w = att.omega_rel_radps
        bx = float(att.b_body_T[0])
        m_ctrl = c.dipole_Am2 * abs(bx)
        out = []
        for ch, (delta, rate, J) in enumerate(((dy, w[1], self.J[1]), (dz, w[2], self.J[2]))):
            kd = c.kd_Nm_s if c.kd_Nm_s is not None else J / c.period_s
            m_theor = -kd * (delta / c.tau_s + rate)
            width = pulse_width_s(m_theor, m_ctrl, c.period_s, c.min_impulse_s)
            pol = polarity_for(ch, m_theor, bx) if width > 0 else 0
            out.append(ChannelCommand(ch, pol, width if pol else 0.0, m_theor, m_ctrl))
        return out

    def _mpc(self, now_s: float, att: AttitudeInput, acting: tuple[int, int],
             polarity: tuple[int, int]) -> list[ChannelCommand]:
        c = self.config
        T, N = c.period_s, c.horizon
        t_mid = now_s + T * (np.arange(N) + 0.5)
        b_orbital = (np.asarray(att.b_orbital_forecast(t_mid)) if att.b_orbital_forecast is not None
                     else np.tile(att.R_bo @ att.b_body_T, (N, 1)))
        if c.prediction == "nonlinear":
            free, pred = self._nonlinear_plan(att, b_orbital)
        else:
            x0 = np.concatenate((rotvec_from_dcm(att.R_bo), att.omega_rel_radps))
            free = (self._Phi_stack[1:] @ x0).reshape(-1)
            b_body = b_orbital @ att.R_bo  # attitude frozen over the horizon
            # per period and channel: the state change of a full-period pulse (impulse at mid-period)
            G = np.empty((N, 6, 2))
            for ch in range(2):
                moment = np.cross(c.dipole_Am2 * CHANNEL_AXIS[ch], b_body) * T  # (N, 3) N·m·s
                G[:, :, ch] = moment @ self._Phi_half_B.T
            # x_k = Φ^k x0 + Σ_{j<k} Φ^(k−1−j) G_j u_j, k = 1..N, stacked
            blocks = np.einsum("dab,jbc->djac", self._Phi_stack[:N], G)  # Φ^d G_j
            k_idx, j_idx = np.tril_indices(N)  # k−1 >= j
            pred4 = np.zeros((N, N, 6, 2))
            pred4[k_idx, j_idx] = blocks[k_idx - j_idx, j_idx]
            pred = pred4.transpose(0, 2, 1, 3).reshape(6 * N, 2 * N)
        wq = np.tile(self._q_sqrt, N)
        M = np.vstack((wq[:, None] * pred, math.sqrt(c.r_duty) * np.eye(2 * N), self._terminal @ pred[-6:]))
        rhs = np.concatenate((-wq * free, np.zeros(2 * N), -self._terminal @ free[-6:]))
        M0, Mr = M[:, :2], M[:, 2:]
        options = [0.0] + [s * w / T for s in (1.0, -1.0) for w in c.widths_s]
        U0 = np.array([(a, b) for a in options for b in options])  # (C, 2) first moves
        R = rhs[:, None] - M0 @ U0.T  # (rows, C): what the continuation has to answer
        H, Bm = Mr.T @ Mr, Mr.T @ R
        V = box_lasso(H, Bm, c.continuation_l1, c.lasso_sweeps)
        if c.continuation_reweight:
            V, price = self.reweighted(H, Bm, V)
        else:
            price = c.continuation_l1 * np.abs(V).sum(0)
        cost = (V * (H @ V)).sum(0) - 2.0 * (Bm * V).sum(0) + (R * R).sum(0) + price
        joules = np.array([self._move_joules(0, a, acting, polarity) + self._move_joules(1, b, acting, polarity)
                           for a, b in U0])
        total = cost + c.energy_price_per_J * joules
        if c.energy_guard_rad > 0.0:
            total = np.where(self.adds_energy(free[:6], pred[:6, :2], U0), np.inf, total)
        k = int(np.argmin(total))
        if c.nonlinear_guard_rad > 0.0 and np.any(U0[k] != 0.0):

            S, H = c.energy_substeps_guard, c.energy_horizon
            steps = [int(round(abs(u) * S)) for u in U0[k]]
            move = (int(np.sign(U0[k][0])), steps[0], int(np.sign(U0[k][1])), steps[1])
            n, ka = c.mean_motion_radps, c.aero_stiffness_Nm_per_rad
            t = now_s + (T / S) * (np.arange(H * S) + 0.5)
            b_o = (np.asarray(att.b_orbital_forecast(t)) if att.b_orbital_forecast is not None
                   else np.tile(att.R_bo @ att.b_body_T, (H * S, 1)))
            if eh.pumps(att.R_bo, att.omega_rel_radps, b_o, move, J=self.J, n=n, ka=ka, sail_share=c.sail_share,
                        dipole_Am2=c.dipole_Am2, period_s=T, substeps=S, horizon=H,
                        floor_J=eh.deadband_energy_J(self.J, n, ka, c.nonlinear_guard_rad)):
                self.guarded += 1
                return self._energy(now_s, att, acting, polarity, switch=False)
        bx = float(att.b_body_T[0])
        m_ctrl = c.dipole_Am2 * abs(bx)
        out = []
        for ch, u in enumerate(float(v) for v in U0[k]):
            pol = int(np.sign(u))
            # the moment this pulse makes about the channel's axis, averaged over T (eq. 6 backwards)
            m_theor = abs(u) * m_ctrl * pol * float(np.sign(bx)) * (1.0 if ch == 0 else -1.0)
            out.append(ChannelCommand(ch, pol, abs(u) * T, m_theor, m_ctrl))
        return out

    def reweighted(self, H: np.ndarray, Bm: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The continuations V (n, C) after `continuation_reweight` passes of the reweighted ℓ1, and each
        column's price of its pulses, Σ k·|u|/(|u| + ε) with k = `continuation_pulse_price`·(1 + ε): about k
        a pulse whatever its width (a full one exactly k), the fixed price of an opening the ℓ1 price per
        unit of duty misses. With it a small trim later is no longer nearly free, so the plan does not keep
        deferring it (see the module docstring)."""
        c = self.config
        eps = c.reweight_eps
        k = c.continuation_pulse_price * (1.0 + eps)
        for _ in range(c.continuation_reweight):
            V = box_lasso_weighted(H, Bm, k / (np.abs(V) + eps), V, c.lasso_sweeps)
        return V, k * (np.abs(V) / (np.abs(V) + eps)).sum(0)

    def _energy(self, now_s: float, att: AttitudeInput, acting: tuple[int, int],
                polarity: tuple[int, int], switch: bool = True) -> list[ChannelCommand]:
        """The energy-descent choice over a few pulses (`fsw.deorbit.energy_horizon`); with `switch`, the
        "mpc" choice below the energy of an `energy_switch_rad` swing."""

        c = self.config
        T, S, H = c.period_s, c.energy_substeps, c.energy_horizon
        n, ka = c.mean_motion_radps, c.aero_stiffness_Nm_per_rad
        if switch and c.energy_switch_rad > 0.0:
            e_switch = eh.deadband_energy_J(self.J, n, ka, c.energy_switch_rad)
            if c.energy_switch_axes == "total":
                e = float(eh.jacobi_energy(np.asarray(att.R_bo, float), np.asarray(att.omega_rel_radps, float),
                                           self.J, n, ka, c.sail_share)) - eh._e_min(self.J, n, ka, c.sail_share)
            else:
                dy, dz = pointing_error(att.R_bo)
                x = np.array([0.0, dy, dz, 0.0, att.omega_rel_radps[1], att.omega_rel_radps[2]])
                e = float(self.libration_energy(x))
            self.last_energy_J = e
            if e < e_switch:
                return self._mpc(now_s, att, acting, polarity)
        t = now_s + (T / S) * (np.arange(H * S) + 0.5)
        b_orbital = (np.asarray(att.b_orbital_forecast(t)) if att.b_orbital_forecast is not None
                     else np.tile(att.R_bo @ att.b_body_T, (H * S, 1)))
        move, _, _, _ = eh.choose(
            att.R_bo, att.omega_rel_radps, b_orbital, J=self.J, n=n, ka=ka, sail_share=c.sail_share,
            dipole_Am2=c.dipole_Am2, period_s=T, substeps=S, horizon=H, widths_s=c.energy_widths_s, acting=acting,
            polarity=polarity, opening_J=OPENING_J, turn_J=TURN_J, energy_price=c.energy_price_J_per_J,
            margin=c.energy_margin, deadband_J=eh.deadband_energy_J(self.J, n, ka, c.deadband_rad))
        bx = float(att.b_body_T[0])
        m_ctrl = c.dipole_Am2 * abs(bx)
        out = []
        for ch, (pol, steps) in enumerate(((int(move[0]), int(move[1])), (int(move[2]), int(move[3])))):
            width = eh.width_s(steps, T, S) if pol else 0.0
            m_theor = width / T * m_ctrl * pol * float(np.sign(bx)) * (1.0 if ch == 0 else -1.0)
            out.append(ChannelCommand(ch, pol if width > 0 else 0, width, m_theor, m_ctrl))
        return out

    def _nonlinear_plan(self, att: AttitudeInput, b_orbital: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(free (6N,), pred (6N, 2N)) about the nonlinear motion: the free motion from the attitude now
        (:func:`free_motion`), the field in body axes along it, and the response of every later state to
        each period's pulse by propagating a small rate change at the period's middle along it
        (:func:`impulse_responses`, a secant over `FD_DUTY` of a full pulse): the model a linear plan
        stands on, valid at tens of degrees where the LVLH linearisation about the target is not."""
        c = self.config
        T, N, S = c.period_s, c.horizon, c.free_motion_substeps
        args = (self.J, c.mean_motion_radps, c.aero_stiffness_Nm_per_rad, c.sail_share, T / S)
        Rs, ws = free_motion(np.asarray(att.R_bo, float), np.asarray(att.omega_rel_radps, float), *args, N * S)
        rv_free = unwrapped_rotvecs(att.R_bo, Rs[S::S])
        free = np.concatenate([np.concatenate((v, ws[(k + 1) * S])) for k, v in enumerate(rv_free)])
        b_body = np.einsum("ja,jab->jb", b_orbital, Rs[S // 2::S][:N])
        dw = np.empty((N, 2, 3))
        for ch in range(2):
            dw[:, ch] = np.cross(c.dipole_Am2 * CHANNEL_AXIS[ch], b_body) * (T * self.FD_DUTY) / self.J
        Rp, wp = impulse_responses(Rs, ws, dw, *args, S, N)
        return free, response_matrix(Rp, wp, np.array(rv_free), ws[S::S], self.FD_DUTY)

    def libration_energy(self, x: np.ndarray) -> np.ndarray:
        """½ xᵀWx of states x (6, ...) of the LVLH model, pitch and yaw: their stiffnesses and inertias [J]
        (roll, which nothing controls and the pulses' roll moments kick, is left out; the roll-yaw coupling
        trades some of it with roll, which is why moves are compared with coasting, not with now)."""
        A, J = self.A, self.J
        w = np.array([0.0, -A[4, 1] * J[1], -A[5, 2] * J[2], 0.0, J[1], J[2]])  # pitch and yaw only
        return 0.5 * np.tensordot(w, np.asarray(x) ** 2, axes=1)

    def adds_energy(self, x1_free: np.ndarray, pred1: np.ndarray, U0: np.ndarray) -> np.ndarray:
        """Per first move (rows of U0), whether it leaves the libration more energy after the first period
        than coasting (`x1_free`) would, while above the energy of an `energy_guard_rad` swing in yaw: the
        kit never pumps a large swing up, whatever the plan's model makes of the field along the orbit.
        The closed move is always allowed."""
        A, J = self.A, self.J
        floor = 0.5 * min(-A[4, 1] * J[1], -A[5, 2] * J[2]) * self.config.energy_guard_rad ** 2
        x1 = x1_free[:, None] + pred1 @ U0.T
        e_free = float(self.libration_energy(x1_free))
        adds = self.libration_energy(x1) > max(e_free, floor)
        # the roll: each pulse kicks it (p_my·B_z, −p_mz·B_y); nothing may pump it past a roll_guard_rad swing
        k_roll = -A[3, 0] * J[0]
        roll = 0.5 * (k_roll * x1[0] ** 2 + J[0] * x1[3] ** 2)
        roll_free = 0.5 * (k_roll * x1_free[0] ** 2 + J[0] * x1_free[3] ** 2)
        adds |= roll > max(roll_free, 0.5 * k_roll * self.config.roll_guard_rad ** 2)
        return adds & np.any(U0 != 0.0, axis=1)

    @staticmethod
    def _move_joules(ch: int, u: float, acting: tuple[int, int], polarity: tuple[int, int]) -> float:
        if u == 0.0:
            return 0.0
        pol = 1 if u > 0 else -1
        if acting[ch] == pol:
            return 0.0  # already open with this polarity: the pulse is extended
        return OPENING_J + (TURN_J if polarity[ch] != pol else 0.0)
