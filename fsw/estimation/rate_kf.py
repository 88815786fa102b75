"""The onboard rate filter's predict and update as compiled pure functions over (x, P).

State x = [B (µT, body axes), ω (rad/s)], covariance P (6×6); the model is the one documented in
:mod:`fsw.estimation.rate_kalman` (:class:`~fsw.estimation.rate_kalman.RateKalman` is the stateful wrapper):

    B⁻ = E B,  E = exp(−[φ]ₓ),  φ = ω Δt        (the field turns rigidly in the body; exact for constant ω)
    ω⁻ = ϕ ω,  ϕ = exp(−Δt/τ)                     (a random walk; τ = ∞ unless a pull to zero is asked for)
    F  = [[E, G], [0, ϕI]],  G = ∂B⁻/∂ω = Δt [B⁻]ₓ J_r(φ)
    P⁻ = F P Fᵀ + Q,  Q = [[f₃[B⁻]ₓ[B⁻]ₓᵀ + q_B I, f₂[B⁻]ₓ], [f₂[B⁻]ₓᵀ, q_ω I]],
    f₃ = q_ω Δt²/3, f₂ = q_ω Δt/2 (ω a random walk of per-step variance q_ω, B integrating it)

    z = H x + v,  H = [I 0],  R = r I:
    y = z − B⁻,  S = P_BB + R,  K = P Hᵀ S⁻¹,  x⁺ = x + K y,  P⁺ = P − K H P   (Bar-Shalom et al. 2001, 5.2)

Compiled with numba (nopython, cached on disk): a step is a fraction of a microsecond of arithmetic, and
the call itself allocates nothing — every array is the caller's, including the work space. The
rotation arithmetic (E, J_r, [B]ₓ) is written out inline here rather than calling the numpy helpers of
:mod:`fsw.estimation.rotations`, which would allocate per step; only the compiled
:func:`~fsw.estimation.rotations.jr_coefficients` is shared.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .rotations import jr_coefficients


@njit(cache=True)
def _add_skew(M: np.ndarray, k: float, px: float, py: float, pz: float) -> None:
    """M[:3, :3] += k [φ]ₓ (M may be a view: a block of a larger matrix)."""
    M[0, 1] -= k * pz
    M[0, 2] += k * py
    M[1, 0] += k * pz
    M[1, 2] -= k * px
    M[2, 0] -= k * py
    M[2, 1] += k * px


@njit(cache=True)
def predict(x: np.ndarray, P: np.ndarray, dt: float, q_w: float, q_b: float, phi: float,
            F: np.ndarray, T: np.ndarray) -> None:
    """x, P ← x⁻, P⁻ over `dt` seconds, in place.

    q_w: the rate's per-step process variance ((rad/s)² per axis); q_b: the field's random walk over
    the step (µT² per axis); phi: exp(−Δt/τ). F and T are 6×6 work arrays.
    """
    px, py, pz = x[3] * dt, x[4] * dt, x[5] * dt
    th2 = px * px + py * py + pz * pz
    a, c = jr_coefficients(th2)
    s = 1.0 - th2 * c                                 # sin θ/θ
    # E = I − s[φ]ₓ + a[φ]ₓ²,  J_r = I − a[φ]ₓ + c[φ]ₓ²,  [φ]ₓ² = φφᵀ − θ² I
    ph = (px, py, pz)
    F[:, :] = 0.0
    for i in range(3):
        for j in range(3):
            k2 = ph[i] * ph[j] - (th2 if i == j else 0.0)
            F[i, j] = (1.0 if i == j else 0.0) + a * k2
            T[i, j] = (1.0 if i == j else 0.0) + c * k2   # J_r, kept in T's corner for a moment
    _add_skew(F, -s, px, py, pz)
    _add_skew(T, -a, px, py, pz)
    bx = F[0, 0] * x[0] + F[0, 1] * x[1] + F[0, 2] * x[2]
    by = F[1, 0] * x[0] + F[1, 1] * x[1] + F[1, 2] * x[2]
    bz = F[2, 0] * x[0] + F[2, 1] * x[1] + F[2, 2] * x[2]
    # G = Δt [B⁻]ₓ J_r
    for j in range(3):
        F[0, 3 + j] = dt * (-bz * T[1, j] + by * T[2, j])
        F[1, 3 + j] = dt * (bz * T[0, j] - bx * T[2, j])
        F[2, 3 + j] = dt * (-by * T[0, j] + bx * T[1, j])
    for i in range(3, 6):
        F[i, i] = phi
    # P⁻ = F P Fᵀ + Q
    for i in range(6):
        for j in range(6):
            acc = 0.0
            for k in range(6):
                acc += F[i, k] * P[k, j]
            T[i, j] = acc
    for i in range(6):
        for j in range(i, 6):
            acc = 0.0
            for k in range(6):
                acc += T[i, k] * F[j, k]
            P[i, j] = acc
            P[j, i] = acc
    f3, f2 = q_w * dt * dt / 3.0, q_w * dt / 2.0
    b2 = bx * bx + by * by + bz * bz
    bv = (bx, by, bz)
    for i in range(3):
        for j in range(3):
            q = f3 * ((b2 if i == j else 0.0) - bv[i] * bv[j])   # [B]ₓ[B]ₓᵀ = |B|² I − B Bᵀ
            P[i, j] += q
        P[i, i] += q_b
        P[3 + i, 3 + i] += q_w
    # Q_Bω = f₂ [B⁻]ₓ and its transpose
    _add_skew(P[:3, 3:], f2, bx, by, bz)
    for i in range(3):
        for j in range(3, 6):
            P[j, i] = P[i, j]
    x[0], x[1], x[2] = bx, by, bz
    x[3] *= phi
    x[4] *= phi
    x[5] *= phi


@njit(cache=True)
def update(x: np.ndarray, P: np.ndarray, z: np.ndarray, r: float, K: np.ndarray, T: np.ndarray) -> float:
    """x, P ← x⁺, P⁺ with the field sample z (µT) of per-axis variance r, in place; returns the
    normalised innovation squared yᵀ S⁻¹ y (χ² with 3 degrees of freedom when the model holds).
    K (6×3) holds the gain afterwards; T (6×6) is work space."""
    s0, s1, s2 = P[0, 0] + r, P[0, 1], P[0, 2]
    s4, s5, s8 = P[1, 1] + r, P[1, 2], P[2, 2] + r
    # S⁻¹ by the adjugate (S symmetric positive definite)
    c0, c1, c2 = s4 * s8 - s5 * s5, s2 * s5 - s1 * s8, s1 * s5 - s2 * s4
    c4, c5, c8 = s0 * s8 - s2 * s2, s1 * s2 - s0 * s5, s0 * s4 - s1 * s1
    inv = 1.0 / (s0 * c0 + s1 * c1 + s2 * c2)
    c0 *= inv
    c1 *= inv
    c2 *= inv
    c4 *= inv
    c5 *= inv
    c8 *= inv
    yx, yy, yz = z[0] - x[0], z[1] - x[1], z[2] - x[2]
    nis = (yx * (c0 * yx + c1 * yy + c2 * yz) + yy * (c1 * yx + c4 * yy + c5 * yz)
           + yz * (c2 * yx + c5 * yy + c8 * yz))
    # K = P Hᵀ S⁻¹ = P[:, :3] S⁻¹;  x⁺ = x + K y
    for i in range(6):
        p0, p1, p2 = P[i, 0], P[i, 1], P[i, 2]
        K[i, 0] = p0 * c0 + p1 * c1 + p2 * c2
        K[i, 1] = p0 * c1 + p1 * c4 + p2 * c5
        K[i, 2] = p0 * c2 + p1 * c5 + p2 * c8
        x[i] += K[i, 0] * yx + K[i, 1] * yy + K[i, 2] * yz
    # P⁺ = P − K (H P), H P = P[:3, :]; computed into T, then written back symmetric
    for i in range(6):
        for j in range(i, 6):
            T[i, j] = P[i, j] - (K[i, 0] * P[0, j] + K[i, 1] * P[1, j] + K[i, 2] * P[2, j])
    for i in range(6):
        for j in range(i, 6):
            P[i, j] = T[i, j]
            P[j, i] = T[i, j]
    return nis
