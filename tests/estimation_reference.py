"""Reference implementations the estimation tests check against; the flight and ground code do not use
them: the textbook Kalman steps on (x, P) (Bar-Shalom, Li & Kirubarajan 2001, ch. 5), the error bounds
printed in sedelnikov2024 (eqs. 5 and 10), the Kotelnikov series summed directly (sedelnikov2023
eq. 9), and the attitude filter's propagation with Euler's equations as it was written before it was compiled,
on tuples of floats (fsw.estimation.euler_step and ground.euler_trajectory are compared with it; `par` is
("shape", J₂/J₁, J₃/J₁) or ("J", J (9), J⁻¹ (9)))."""
from __future__ import annotations

import math

import numpy as np

from fsw.estimation import kotelnikov as ko
from fsw.estimation.rotations import quat_mul_tuple, so3_exp_jr_tuple

# --- textbook Kalman steps ---------------------------------------------------------------------------


def predict(x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray,
            fx: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """x⁻ = F x (or `fx`, the nonlinear propagation, for an EKF); P⁻ = F P Fᵀ + Q."""
    return (F @ x if fx is None else np.asarray(fx, float)), F @ P @ F.T + Q


def update(x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray,
           hx: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Measurement update; returns (x⁺, P⁺, innovation y, its covariance S).

    y = z − H x (or z − `hx` for an EKF), S = H P Hᵀ + R, K = P Hᵀ S⁻¹, x⁺ = x + K y and the Joseph
    form P⁺ = (I − KH) P (I − KH)ᵀ + K R Kᵀ, which stays symmetric positive semi-definite.
    """
    z = np.asarray(z, float).reshape(-1)
    y = z - (H @ x if hx is None else np.asarray(hx, float).reshape(-1))
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    IKH = np.eye(len(x)) - K @ H
    return x + K @ y, IKH @ P @ IKH.T + K @ R @ K.T, y, S


# --- the papers' printed error bounds ------------------------------------------------------------------

def boer_error_bound_eq5(t_s: np.ndarray, b_T: np.ndarray, delta_b_T: float) -> np.ndarray:
    """Per-axis error bound of the Boer formula, sedelnikov2024 eq. 5 (row 0 NaN).

    δω_x = 2δ_B √(B_y² + B_z² + ΔB_y² + ΔB_z²) / (Δt |B|²), and cyclically.
    """
    t, b = np.asarray(t_s, float), np.asarray(b_T, float)
    out = np.full(b.shape, np.nan)
    if len(t) > 1:
        bk, db = b[1:], b[1:] - b[:-1]
        s = bk**2 + db**2
        num = np.sqrt(s.sum(axis=1, keepdims=True) - s)  # drop the own axis
        out[1:] = 2.0 * delta_b_T * num / (np.diff(t) * (bk**2).sum(axis=1))[:, None]
    return out


def derivative_error_bound_eq10(t_s: np.ndarray, b_T: np.ndarray, delta_b_T: float) -> np.ndarray:
    """Per-axis error bound of the derivative formula, sedelnikov2024 eq. 10 (rows 0, 1 NaN).

    δω_x = δ* √(ΔB_y,k² + ΔB_z,k² + ΔB_y,k−1² + ΔB_z,k−1²) / (Δt |ΔB_k|²), δ* = 2δ_B + δ_B Δt
    (the paper's δ*, which mixes units of T and T·s; kept as printed with Δt in seconds).
    """
    t, b = np.asarray(t_s, float), np.asarray(b_T, float)
    out = np.full(b.shape, np.nan)
    if len(t) > 2:
        dt = np.diff(t)[1:]
        dk, d1 = b[2:] - b[1:-1], b[1:-1] - b[:-2]
        s = dk**2 + d1**2
        num = np.sqrt(s.sum(axis=1, keepdims=True) - s)
        den = dt * (dk**2).sum(axis=1)
        delta_star = 2.0 * delta_b_T + delta_b_T * dt
        with np.errstate(divide="ignore", invalid="ignore"):
            out[2:] = delta_star[:, None] * num / den[:, None]
    return out


# --- the Kotelnikov series -----------------------------------------------------------------------------

def kotelnikov_series(t_s: np.ndarray, b: np.ndarray, t_eval: np.ndarray) -> np.ndarray:
    """B(t_eval) from uniform samples by the series itself (eq. 9), direct sum (O(N·M)); (M, 3)."""
    t, b = np.asarray(t_s, float), np.asarray(b, float)
    dt = float(np.median(np.diff(t)))
    x = (np.asarray(t_eval, float)[:, None] - t[None, :]) / dt
    return np.sinc(x) @ b


def kotelnikov_boer_rate(t_s: np.ndarray, b_T: np.ndarray, **kw) -> np.ndarray:
    """Perpendicular rate ω⊥ = (Ḃ × B)/|B|² with the series' analytic Ḃ (fsw's kotelnikov_derivatives)."""
    b = np.asarray(b_T, float)
    _, db, _ = ko.kotelnikov_derivatives(t_s, b, **kw)
    return np.cross(db, b) / np.einsum("ij,ij->i", b, b)[:, None]


# --- the attitude filter's propagation with Euler's equations, on floats ---------------------------------

def _m3(a, b):
    """3×3 product of row-major 9-tuples."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = b
    return (a0 * b0 + a1 * b3 + a2 * b6, a0 * b1 + a1 * b4 + a2 * b7, a0 * b2 + a1 * b5 + a2 * b8,
            a3 * b0 + a4 * b3 + a5 * b6, a3 * b1 + a4 * b4 + a5 * b7, a3 * b2 + a4 * b5 + a5 * b8,
            a6 * b0 + a7 * b3 + a8 * b6, a6 * b1 + a7 * b4 + a8 * b7, a6 * b2 + a7 * b5 + a8 * b8)


def euler_rate(par, w, torque=None) -> tuple[float, float, float]:
    """ω̇ from Euler's equations J ω̇ + ω × (J ω) = M, on floats.

    `par` is ("shape", J₂/J₁, J₃/J₁) for a diagonal tensor known up to scale (torque-free: then
    ω̇ = (k₁ω₂ω₃, k₂ω₃ω₁, k₃ω₁ω₂) with k₁ = (J₂ − J₃)/J₁ and cyclically), or ("J", J (9), J⁻¹ (9)).
    """
    w1, w2, w3 = w
    if par[0] == "shape":
        j2, j3 = par[1], par[2]
        return ((j2 - j3) * w2 * w3, (j3 - 1.0) / j2 * w3 * w1, (1.0 - j2) / j3 * w1 * w2)
    J, K = par[1], par[2]
    h1 = J[0] * w1 + J[1] * w2 + J[2] * w3
    h2 = J[3] * w1 + J[4] * w2 + J[5] * w3
    h3 = J[6] * w1 + J[7] * w2 + J[8] * w3
    e1, e2, e3 = -(w2 * h3 - w3 * h2), -(w3 * h1 - w1 * h3), -(w1 * h2 - w2 * h1)
    if torque is not None:
        e1, e2, e3 = e1 + torque[0], e2 + torque[1], e3 + torque[2]
    return (K[0] * e1 + K[1] * e2 + K[2] * e3, K[3] * e1 + K[4] * e2 + K[5] * e3,
            K[6] * e1 + K[7] * e2 + K[8] * e3)


def euler_jacobians(par, w) -> tuple[tuple, tuple]:
    """∂ω̇/∂ω (row-major 9-tuple) and ∂ω̇/∂(ln J₂/J₁, ln J₃/J₁) (row-major 3×2 6-tuple; zeros for a
    known tensor)."""
    w1, w2, w3 = w
    if par[0] == "shape":
        j2, j3 = par[1], par[2]
        k1, k2, k3 = j2 - j3, (j3 - 1.0) / j2, (1.0 - j2) / j3
        A = (0.0, k1 * w3, k1 * w2, k2 * w3, 0.0, k2 * w1, k3 * w2, k3 * w1, 0.0)
        Ap = (j2 * w2 * w3, -j3 * w2 * w3, -k2 * w3 * w1, j3 / j2 * w3 * w1, -j2 / j3 * w1 * w2, -k3 * w1 * w2)
        return A, Ap
    J, K = par[1], par[2]
    # ∂/∂ω of −J⁻¹ (ω × Jω) = −J⁻¹ ([ω]ₓ J − [Jω]ₓ)
    h1 = J[0] * w1 + J[1] * w2 + J[2] * w3
    h2 = J[3] * w1 + J[4] * w2 + J[5] * w3
    h3 = J[6] * w1 + J[7] * w2 + J[8] * w3
    W = (0.0, -w3, w2, w3, 0.0, -w1, -w2, w1, 0.0)
    Hx = (0.0, -h3, h2, h3, 0.0, -h1, -h2, h1, 0.0)
    M = tuple(u - v for u, v in zip(_m3(W, J), Hx))
    return tuple(-v for v in _m3(K, M)), (0.0,) * 6


def _rk4_attitude(par, q, w, h, m0, m_mid, m1):
    """One RK4 step of q̇ = ½ q ⊗ [0, ω], ω̇ = euler_rate; returns (q, ω, the midpoint rate)."""
    def qdot(qq, ww):
        d = quat_mul_tuple(qq, (0.0, ww[0], ww[1], ww[2]))
        return (0.5 * d[0], 0.5 * d[1], 0.5 * d[2], 0.5 * d[3])

    def add(a, b, f):
        return tuple(x + f * y for x, y in zip(a, b))

    k1w = euler_rate(par, w, m0)
    k1q = qdot(q, w)
    w2 = add(w, k1w, 0.5 * h)
    k2w = euler_rate(par, w2, m_mid)
    k2q = qdot(add(q, k1q, 0.5 * h), w2)
    w3 = add(w, k2w, 0.5 * h)
    k3w = euler_rate(par, w3, m_mid)
    k3q = qdot(add(q, k2q, 0.5 * h), w3)
    w4 = add(w, k3w, h)
    k4w = euler_rate(par, w4, m1)
    k4q = qdot(add(q, k3q, h), w4)
    f = h / 6.0
    qn = tuple(a + f * (b + 2.0 * c + 2.0 * d + e) for a, b, c, d, e in zip(q, k1q, k2q, k3q, k4q))
    nq = math.sqrt(sum(v * v for v in qn))
    wn = tuple(a + f * (b + 2.0 * c + 2.0 * d + e) for a, b, c, d, e in zip(w, k1w, k2w, k3w, k4w))
    return tuple(v / nq for v in qn), wn, tuple(0.5 * (a + b) for a, b in zip(w2, w3))


def _substep_transition(par, wm, h, n, npar) -> np.ndarray:
    """Error-state transition over a substep h at the midpoint rate ω_m (first order in the rate's
    change): Φ_θθ = exp(−[ω_m h]ₓ), Φ_θω = h J_r(ω_m h) + ½h²A, Φ_ωω = I + Ah + ½(Ah)²,
    Φ_ωp = (I + ½Ah) A_p h, Φ_θp = ½h² A_p; A = ∂ω̇/∂ω, A_p = ∂ω̇/∂p."""
    A, Ap = euler_jacobians(par, wm)
    E, _ = so3_exp_jr_tuple(-wm[0] * h, -wm[1] * h, -wm[2] * h)
    _, Jr = so3_exp_jr_tuple(wm[0] * h, wm[1] * h, wm[2] * h)
    Ah = tuple(v * h for v in A)
    Ah2 = _m3(Ah, Ah)
    tw = tuple(h * j + 0.5 * h * a for j, a in zip(Jr, Ah))
    ww = tuple((1.0 if i in (0, 4, 8) else 0.0) + a + 0.5 * a2 for i, (a, a2) in enumerate(zip(Ah, Ah2)))
    F = np.eye(n)
    F[:3, :3] = np.reshape(E, (3, 3))
    F[:3, 3:6] = np.reshape(tw, (3, 3))
    F[3:6, 3:6] = np.reshape(ww, (3, 3))
    if npar:
        Aph = np.reshape(Ap, (3, 2)) * h
        F[3:6, 6:8] = Aph + 0.5 * (np.reshape(Ah, (3, 3)) @ Aph)
        F[:3, 6:8] = 0.5 * h * Aph
    return F


def propagate(kf, dt: float, torque=None):
    """AttitudeRateKalman.propagate with Euler's equations, here: (q, ω, Φ) of `kf`'s nominal state over dt
    (kf is not changed); `torque(t)` N·m with a known tensor."""
    tun = kf.tuning
    n = kf.n
    F = np.eye(n)
    wn = math.sqrt(float(kf.w @ kf.w))
    m = min(tun.max_substeps, max(1, int(math.ceil(wn * dt / tun.max_substep_rad))))
    h = dt / m
    par = (("J", tuple(kf.J.ravel()), tuple(kf.J_inv.ravel())) if kf.J is not None
           else ("shape", math.exp(kf.p[0]), math.exp(kf.p[1])))
    q = tuple(float(v) for v in kf.q)
    w = tuple(float(v) for v in kf.w)
    t = kf.t_s

    def m_at(x):
        return None if torque is None else tuple(float(v) for v in torque(x))
    for _ in range(m):
        q, w, wm = _rk4_attitude(par, q, w, h, m_at(t), m_at(t + 0.5 * h), m_at(t + h))
        F = _substep_transition(par, wm, h, n, kf.n_p) @ F
        t += h
    return np.array(q), np.array(w), F
