"""The attitude filter's arithmetic (:class:`fsw.estimation.attitude_kalman.AttitudeRateKalman`) as pure
functions over the nominal state (q, ω, shape p, inertial field β) and the error-state covariance P,
compiled (numba, cached on disk): the random-walk step's nominal propagation and transition Φ, the process
noise Q, the covariance prediction Φ P Φᵀ + Q and the multiplicative measurement update.

The filter runs once per sample per hypothesis — a bank runs a dozen — and a 9×9 step in NumPy's small-array
calls cost ~0.6 ms; compiled, a few microseconds. The ground smoothers' compiled passes
(:mod:`ground.rts_pass`) call the same functions, so the two cannot drift apart.

Error state δx = [δθ, δω, δp, δβ] (body-frame attitude error, rad; rate, rad/s; ln-shape; field, µT):
n = 6 + len(p) + len(β). Units: field in µT, rate in rad/s, time in s. Division as NumPy does it
(``error_model="numpy"``): a state that blows up shows as non-finite numbers, which the filter's checks catch.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from .rotations import quat_exp_nb, quat_mul_nb, quat_to_dcm_nb, skew_nb


@njit(cache=True, error_model="numpy")
def _norm4(q):
    return math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])


@njit(cache=True, error_model="numpy")
def rw_transition(phi, decay, mean_dt, n):
    """Φ (n×n) of the random-walk / Gauss–Markov step with rotation φ = ω·mean·dt: exp(−[φ]ₓ),
    (mean·dt) J_r(φ), decay·I on the rate, identity elsewhere."""
    F = np.eye(n)
    th2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    K = skew_nb(-phi)
    if th2 < 1e-12:
        E = np.eye(3) + K + 0.5 * K @ K
    else:
        th = math.sqrt(th2)
        E = np.eye(3) + (math.sin(th) / th) * K + ((1.0 - math.cos(th)) / th2) * K @ K
    if th2 < 1e-6:
        a, c = 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    else:
        th = math.sqrt(th2)
        a, c = (1.0 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)
    Kp = skew_nb(phi)
    Jr = np.eye(3) - a * Kp + c * Kp @ Kp
    F[:3, :3] = E
    F[:3, 3:6] = mean_dt * Jr
    for i in range(3):
        F[3 + i, 3 + i] = decay
    return F


@njit(cache=True, error_model="numpy")
def rw_propagate(q, w, decay, mean, dt, n):
    """The random-walk / Gauss–Markov step over dt: (q, ω, Φ) — q advanced by exp(ω·mean·dt) and normalised,
    ω scaled by `decay` (1 and 1 for a random walk; e^(−dt/τ) and the mean of e^(−s/τ) over the step for
    a Gauss–Markov rate)."""
    phi = w * (mean * dt)
    q1 = quat_mul_nb(q, quat_exp_nb(phi))
    q1 = q1 / _norm4(q1)
    return q1, w * decay, rw_transition(phi, decay, mean * dt, n)


@njit(cache=True, error_model="numpy")
def process_noise(n, npar, q_w, dt, shape_rate, field_rate, beta):
    """Q (n×n): ω a random walk with per-step variance q_w and its effect on the attitude over dt; the shape
    drifting at `shape_rate` (per √s); β, when in the state, at `field_rate`·|β| (per s)."""
    Q = np.zeros((n, n))
    for i in range(3):
        Q[i, i] = q_w * dt * dt / 3.0
        Q[i, 3 + i] = Q[3 + i, i] = q_w * dt / 2.0
        Q[3 + i, 3 + i] = q_w
    for i in range(npar):
        Q[6 + i, 6 + i] = shape_rate ** 2 * dt
    nb = beta.shape[0]
    if nb:
        ib = 6 + npar
        b2 = beta[0] * beta[0] + beta[1] * beta[1] + beta[2] * beta[2]
        for i in range(3):
            Q[ib + i, ib + i] = field_rate ** 2 * b2 * dt * dt
    return Q


@njit(cache=True, error_model="numpy")
def predict_covariance(F, P, Q):
    """Φ P Φᵀ + Q."""
    return F @ P @ F.T + Q


@njit(cache=True, error_model="numpy")
def update(q, w, p, beta, P, z, b_i, R):
    """The measurement update with z (µT, body) and the inertial field b_i (µT; ignored when β is in the
    state: then b_i = β): h = Rᵀ b_i, H = [[h]ₓ, 0, 0, Rᵀ], Joseph-form covariance. Returns (q, ω, p, β, P,
    NIS, ½(NIS + ln det S)) — the last the sample's negative log-likelihood up to a constant."""
    npar = p.shape[0]
    nb = beta.shape[0]
    ib = 6 + npar
    n = ib + nb
    C = quat_to_dcm_nb(q)
    bi = beta if nb else b_i
    h = C.T @ bi
    H = np.zeros((3, n))
    H[:, :3] = skew_nb(h)
    if nb:
        H[:, ib:] = C.T
    y = z - h
    S = H @ P @ H.T + R
    Kg = np.linalg.solve(S, H @ P).T
    dx = Kg @ y
    IKH = np.eye(n) - Kg @ H
    P2 = IKH @ P @ IKH.T + Kg @ R @ Kg.T
    nis = y @ np.linalg.solve(S, y)
    nll = 0.5 * (nis + math.log(max(np.linalg.det(S), 1e-300)))
    q2 = quat_mul_nb(q, quat_exp_nb(dx[:3]))
    q2 = q2 / _norm4(q2)
    beta2 = beta + dx[ib:] if nb else beta
    return q2, w + dx[3:6], p + dx[6:ib], beta2, P2, nis, nll
