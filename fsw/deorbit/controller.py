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
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numba import njit
from scipy.linalg import expm

from ..estimation.rotations import rotvec_from_dcm

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


@njit(cache=True)
def box_lasso(H: np.ndarray, B: np.ndarray, lam: float, sweeps: int, tol: float = 1e-9) -> np.ndarray:
    """min over v ∈ [−1, 1]ⁿ of vᵀHv − 2bᵀv + λ‖v‖₁, for each column b of B (n, C); H = MᵀM (n×n) with a
    positive diagonal. Cyclic coordinate descent: per coordinate the 1-D minimiser is the soft-threshold
    of t = b_i − Σ_{j≠i} H_ij v_j by λ/2, divided by H_ii and clipped to the box (exact for a convex 1-D
    problem); stops after `sweeps` sweeps or when no coordinate moved by more than `tol`. Returns V (n, C).
    Compiled (numba, cached on disk): ~40 sweeps over 38 × 49 unknowns in a few milliseconds."""
    n, C = B.shape
    V = np.zeros((n, C))
    HV = np.zeros((n, C))  # H V, kept current
    half = 0.5 * lam
    for _ in range(sweeps):
        moved = 0.0
        for i in range(n):
            d = H[i, i]
            for c in range(C):
                t = B[i, c] - HV[i, c] + d * V[i, c]
                a = abs(t) - half
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
    # "paper"
    kd_Nm_s: float | None = None  # default J/T
    tau_s: float = 600.0  # k_p = k_d / τ

    def __post_init__(self) -> None:
        if self.law not in ("mpc", "paper"):
            raise ValueError(f"law must be 'mpc' or 'paper', got {self.law!r}")
        if not self.period_s > 0 or not 0 <= self.min_impulse_s <= self.period_s:
            raise ValueError("need period_s > 0 and 0 <= min_impulse_s <= period_s")
        if any(not self.min_impulse_s <= w <= self.period_s for w in self.widths_s):
            raise ValueError("widths_s must lie in [min_impulse_s, period_s]")
        if not (self.r_duty > 0 and self.continuation_l1 >= 0 and self.terminal_weight >= 0 and self.horizon >= 2
                and self.lasso_sweeps >= 1):
            raise ValueError("need r_duty > 0, continuation_l1 >= 0, terminal_weight >= 0, horizon >= 2, "
                             "lasso_sweeps >= 1")


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
        box_lasso(np.eye(2), np.ones((2, 1)), 0.0, 1)  # load (or compile) the kernel now, not at a decision
        self.decisions = 0
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
        x0 = np.concatenate((rotvec_from_dcm(att.R_bo), att.omega_rel_radps))
        # field in body axes at the mid-points of the periods (attitude frozen over the horizon)
        if att.b_orbital_forecast is not None:
            t_mid = now_s + T * (np.arange(N) + 0.5)
            b_body = np.asarray(att.b_orbital_forecast(t_mid)) @ att.R_bo
        else:
            b_body = np.tile(att.b_body_T, (N, 1))
        # per period and channel: the state change of a full-period pulse (impulse at mid-period)
        G = np.empty((N, 6, 2))
        for ch in range(2):
            moment = np.cross(c.dipole_Am2 * CHANNEL_AXIS[ch], b_body) * T  # (N, 3) N·m·s
            G[:, :, ch] = moment @ self._Phi_half_B.T
        # x_k = Φ^k x0 + Σ_{j<k} Φ^(k−1−j) G_j u_j, k = 1..N, stacked
        free = (self._Phi_stack[1:] @ x0).reshape(-1)
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
        cost = (V * (H @ V)).sum(0) - 2.0 * (Bm * V).sum(0) + (R * R).sum(0) + c.continuation_l1 * np.abs(V).sum(0)
        joules = np.array([self._move_joules(0, a, acting, polarity) + self._move_joules(1, b, acting, polarity)
                           for a, b in U0])
        k = int(np.argmin(cost + c.energy_price_per_J * joules))
        bx = float(att.b_body_T[0])
        m_ctrl = c.dipole_Am2 * abs(bx)
        out = []
        for ch, u in enumerate(float(v) for v in U0[k]):
            pol = int(np.sign(u))
            # the moment this pulse makes about the channel's axis, averaged over T (eq. 6 backwards)
            m_theor = abs(u) * m_ctrl * pol * float(np.sign(bx)) * (1.0 if ch == 0 else -1.0)
            out.append(ChannelCommand(ch, pol, abs(u) * T, m_theor, m_ctrl))
        return out

    @staticmethod
    def _move_joules(ch: int, u: float, acting: tuple[int, int], polarity: tuple[int, int]) -> float:
        if u == 0.0:
            return 0.0
        pol = 1 if u > 0 else -1
        if acting[ch] == pol:
            return 0.0  # already open with this polarity: the pulse is extended
        return OPENING_J + (TURN_J if polarity[ch] != pol else 0.0)
