"""Euler's equations and the attitude kinematics over one integration substep, compiled (numba, cached on
disk): the RK4 step of the nominal state and the error-state transition at the substep's midpoint rate —
the attitude filter's propagation with Euler's equations
(:meth:`fsw.estimation.attitude_kalman.AttitudeRateKalman.propagate`, :func:`propagate` below) and the ground's
batch fit and smoothers (:mod:`ground.euler_trajectory`, :mod:`ground.rts_pass`) share them.

Error-state transition over a substep h at the midpoint rate ω_m (first order in the rate's change):
Φ_θθ = exp(−[ω_m h]ₓ), Φ_θω = h J_r(ω_m h) + ½h²A, Φ_ωω = I + Ah + ½(Ah)², Φ_ωp = (I + ½Ah) A_p h,
Φ_θp = ½h² A_p; A = ∂ω̇/∂ω, A_p = ∂ω̇/∂p (p = ln J₂/J₁, ln J₃/J₁). State layout as the filter's error state:
δθ (3), δω (3), δp (2, when the shape is estimated), δβ (3, the inertial field, without a field model).
Units: rate rad/s, time s, torque N·m with J in kg·m². Division as NumPy does it (``error_model="numpy"``):
a state that divides by zero gives inf/NaN, which the callers refuse as non-finite.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

#: `mode`: the inertia shape (J₂/J₁, J₃/J₁) in the state, or a known tensor (J and K = J⁻¹ as row-major 9-arrays)
SHAPE, TENSOR = 0, 1
#: J and K of the shape's mode (not read), and the torques of a torque-free body (:func:`propagate`)
NO_TENSOR = np.zeros(9)
TORQUE_FREE = np.zeros((0, 3, 3))


@njit(cache=True, error_model="numpy")
def _euler_rate(mode, j2, j3, J, K, w1, w2, w3, M, i):
    """ω̇ from Euler's equations J ω̇ + ω × (J ω) = M: with the shape, torque-free (then ω̇ = (k₁ω₂ω₃, k₂ω₃ω₁,
    k₃ω₁ω₂), k₁ = (J₂ − J₃)/J₁ and cyclically); with the tensor, the torque M[i] when `M` has rows."""
    if mode == SHAPE:
        return (j2 - j3) * w2 * w3, (j3 - 1.0) / j2 * w3 * w1, (1.0 - j2) / j3 * w1 * w2
    h1 = J[0] * w1 + J[1] * w2 + J[2] * w3
    h2 = J[3] * w1 + J[4] * w2 + J[5] * w3
    h3 = J[6] * w1 + J[7] * w2 + J[8] * w3
    e1, e2, e3 = -(w2 * h3 - w3 * h2), -(w3 * h1 - w1 * h3), -(w1 * h2 - w2 * h1)
    if M.shape[0]:
        e1, e2, e3 = e1 + M[i, 0], e2 + M[i, 1], e3 + M[i, 2]
    return (K[0] * e1 + K[1] * e2 + K[2] * e3, K[3] * e1 + K[4] * e2 + K[5] * e3,
            K[6] * e1 + K[7] * e2 + K[8] * e3)


@njit(cache=True, error_model="numpy")
def _m3(a, b, out):
    """out = a b for row-major 3×3 arrays of 9 (the filter's _m3 order)."""
    for i in range(3):
        for j in range(3):
            out[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j]


@njit(cache=True, error_model="numpy")
def _jacobians(mode, j2, j3, J, K, w, A, Ap):
    """∂ω̇/∂ω into A (9) and ∂ω̇/∂p into Ap (6, zeros for a known tensor)."""
    w1, w2, w3 = w[0], w[1], w[2]
    if mode == SHAPE:
        k1, k2, k3 = j2 - j3, (j3 - 1.0) / j2, (1.0 - j2) / j3
        A[0], A[1], A[2] = 0.0, k1 * w3, k1 * w2
        A[3], A[4], A[5] = k2 * w3, 0.0, k2 * w1
        A[6], A[7], A[8] = k3 * w2, k3 * w1, 0.0
        Ap[0], Ap[1] = j2 * w2 * w3, -j3 * w2 * w3
        Ap[2], Ap[3] = -k2 * w3 * w1, j3 / j2 * w3 * w1
        Ap[4], Ap[5] = -j2 / j3 * w1 * w2, -k3 * w1 * w2
        return
    h1 = J[0] * w1 + J[1] * w2 + J[2] * w3
    h2 = J[3] * w1 + J[4] * w2 + J[5] * w3
    h3 = J[6] * w1 + J[7] * w2 + J[8] * w3
    W = np.array((0.0, -w3, w2, w3, 0.0, -w1, -w2, w1, 0.0))
    Hx = np.array((0.0, -h3, h2, h3, 0.0, -h1, -h2, h1, 0.0))
    WJ = np.empty(9)
    _m3(W, J, WJ)
    M = WJ - Hx
    KM = np.empty(9)
    _m3(K, M, KM)
    for i in range(9):
        A[i] = -KM[i]
    for i in range(6):
        Ap[i] = 0.0


@njit(cache=True, error_model="numpy")
def _exp_jr(px, py, pz, E, Jr):
    """exp([φ]ₓ) into E and J_r(φ) into Jr (row-major 9; rotations.so3_exp_jr_tuple's order)."""
    th2 = px * px + py * py + pz * pz
    if th2 < 1e-6:
        a, c = 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    else:
        th = math.sqrt(th2)
        a, c = (1.0 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)
    s = 1.0 - th2 * c
    k2 = (px * px - th2, px * py, px * pz, px * py, py * py - th2, py * pz, px * pz, py * pz, pz * pz - th2)
    Kx = (0.0, -pz, py, pz, 0.0, -px, -py, px, 0.0)
    for i in range(9):
        eye = 1.0 if i == 0 or i == 4 or i == 8 else 0.0
        E[i] = eye + s * Kx[i] + a * k2[i]
        Jr[i] = eye - a * Kx[i] + c * k2[i]


@njit(cache=True, error_model="numpy")
def _qdot(q0, q1, q2, q3, w1, w2, w3):
    """½ q ⊗ [0, ω]."""
    return (0.5 * (q0 * 0.0 - q1 * w1 - q2 * w2 - q3 * w3), 0.5 * (q0 * w1 + q1 * 0.0 + q2 * w3 - q3 * w2),
            0.5 * (q0 * w2 - q1 * w3 + q2 * 0.0 + q3 * w1), 0.5 * (q0 * w3 + q1 * w2 - q2 * w1 + q3 * 0.0))


@njit(cache=True, error_model="numpy")
def rk4_substep(mode, j2, j3, J, K, q, w, h, wm, M):
    """One RK4 substep of q̇ = ½ q ⊗ [0, ω], ω̇ from Euler's equations, in place on q (4) and w (3); the
    midpoint rate into wm. `M` (3 × 3): the torque at the substep's start, middle and end (N·m; a known
    tensor only), or no rows: torque-free."""
    hh = 0.5 * h
    k1w = _euler_rate(mode, j2, j3, J, K, w[0], w[1], w[2], M, 0)
    k1q = _qdot(q[0], q[1], q[2], q[3], w[0], w[1], w[2])
    a1, a2, a3 = w[0] + hh * k1w[0], w[1] + hh * k1w[1], w[2] + hh * k1w[2]
    k2w = _euler_rate(mode, j2, j3, J, K, a1, a2, a3, M, 1)
    k2q = _qdot(q[0] + hh * k1q[0], q[1] + hh * k1q[1], q[2] + hh * k1q[2], q[3] + hh * k1q[3], a1, a2, a3)
    b1, b2, b3 = w[0] + hh * k2w[0], w[1] + hh * k2w[1], w[2] + hh * k2w[2]
    k3w = _euler_rate(mode, j2, j3, J, K, b1, b2, b3, M, 1)
    k3q = _qdot(q[0] + hh * k2q[0], q[1] + hh * k2q[1], q[2] + hh * k2q[2], q[3] + hh * k2q[3], b1, b2, b3)
    c1, c2, c3 = w[0] + h * k3w[0], w[1] + h * k3w[1], w[2] + h * k3w[2]
    k4w = _euler_rate(mode, j2, j3, J, K, c1, c2, c3, M, 2)
    k4q = _qdot(q[0] + h * k3q[0], q[1] + h * k3q[1], q[2] + h * k3q[2], q[3] + h * k3q[3], c1, c2, c3)
    f = h / 6.0
    qn = np.empty(4)
    for i in range(4):
        qn[i] = q[i] + f * (k1q[i] + 2.0 * k2q[i] + 2.0 * k3q[i] + k4q[i])
    nq = math.sqrt(qn[0] * qn[0] + qn[1] * qn[1] + qn[2] * qn[2] + qn[3] * qn[3])
    for i in range(3):
        w[i] = w[i] + f * (k1w[i] + 2.0 * k2w[i] + 2.0 * k3w[i] + k4w[i])
    for i in range(4):
        q[i] = qn[i] / nq
    wm[0], wm[1], wm[2] = 0.5 * (a1 + b1), 0.5 * (a2 + b2), 0.5 * (a3 + b3)


@njit(cache=True, error_model="numpy")
def substep_rows(mode, j2, j3, J, K, wm, h, npar, S):
    """The substep's transition, rows δθ and δω (6 × n) into S (the other rows are the identity's)."""
    A = np.empty(9)
    Ap = np.empty(6)
    _jacobians(mode, j2, j3, J, K, wm, A, Ap)
    E = np.empty(9)
    Jr = np.empty(9)
    unused = np.empty(9)
    _exp_jr(-wm[0] * h, -wm[1] * h, -wm[2] * h, E, unused)
    _exp_jr(wm[0] * h, wm[1] * h, wm[2] * h, unused, Jr)
    Ah = np.empty(9)
    for i in range(9):
        Ah[i] = A[i] * h
    Ah2 = np.empty(9)
    _m3(Ah, Ah, Ah2)
    S[:, :] = 0.0
    for i in range(3):
        for j in range(3):
            m = 3 * i + j
            S[i, j] = E[m]
            S[i, 3 + j] = h * Jr[m] + 0.5 * h * Ah[m]
            S[3 + i, 3 + j] = (1.0 if i == j else 0.0) + Ah[m] + 0.5 * Ah2[m]
    if npar:
        for i in range(3):
            for j in range(2):
                aph = Ap[2 * i + j] * h
                S[i, 6 + j] = 0.5 * h * aph
        for i in range(3):
            for j in range(2):
                acc = 0.0
                for k in range(3):
                    acc += Ah[3 * i + k] * (Ap[2 * k + j] * h)
                S[3 + i, 6 + j] = Ap[2 * i + j] * h + 0.5 * acc


@njit(cache=True, error_model="numpy")
def substep_transition(S, F, top):
    """F ← S F on rows δθ, δω (a substep's transition S: its other rows are the identity's); `top` (6 × n)
    is the scratch."""
    n = F.shape[1]
    for i in range(6):
        for j in range(n):
            acc = 0.0
            for l in range(S.shape[1]):
                acc += S[i, l] * F[l, j]
            top[i, j] = acc
    F[:6, :] = top


@njit(cache=True, error_model="numpy")
def propagate(q, w, dt, m, mode, j2, j3, J, K, npar, n, torques):
    """The nominal state (q, ω) advanced over dt in m RK4 substeps and the error-state transition Φ (n × n)
    over them: (q, ω, Φ). `torques` (m × 3 × 3): each substep's torque at its start, middle and end (a known
    tensor), or no rows: torque-free."""
    h = dt / m
    q1 = q.copy()
    w1 = w.copy()
    F = np.eye(n)
    S = np.zeros((6, n))
    top = np.empty((6, n))
    wm = np.empty(3)
    none = np.zeros((0, 3))
    for i in range(m):
        rk4_substep(mode, j2, j3, J, K, q1, w1, h, wm, torques[i] if torques.shape[0] else none)
        substep_rows(mode, j2, j3, J, K, wm, h, npar, S)
        substep_transition(S, F, top)
    return q1, w1, F
