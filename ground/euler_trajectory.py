"""The batch Euler fit's propagation, compiled: the nominal trajectory of torque-free Euler + kinematics from
the state at the first sample, its error-state transition matrices and the residuals' Jacobians.

The same arithmetic as :meth:`fsw.estimation.attitude_kalman.AttitudeRateKalman.propagate` with Euler's
equations and no torque (RK4 substeps of at most `max_substep_rad` of rotation: the kernels of
:mod:`fsw.estimation.euler_step`, which the filter runs too) and as its measurement, for every sample of the
window at once: the Levenberg–Marquardt fit of :mod:`ground.smoother` runs it a few hundred times per record.
Units: field µT, rate rad/s, time s. tests/ground/test_euler_trajectory.py compares it with a NumPy reference
of the filter's propagation.

Division as numpy does it (``error_model="numpy"``): a state that divides by zero gives inf/NaN, as the
reference does, and the caller refuses it as non-finite — never a ZeroDivisionError out of a worker.

State layout as the filter's error state: δθ (3), δω (3), δp (2, the shape ln J₂/J₁, ln J₃/J₁, when
estimated), δβ (3, the inertial field, without a field model).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from fsw.estimation.euler_step import SHAPE, TENSOR, rk4_substep, substep_rows, substep_transition

__all__ = ["SHAPE", "TENSOR", "trajectory"]


@njit(cache=True, error_model="numpy")
def trajectory(q0, w0, mode, j2, j3, J, K, npar, beta, b_i, t, z, sb, n, max_substep_rad, max_substeps,
               jacobian):
    """The nominal trajectory over the first n samples from (q0, ω0) at t[0] and, with `jacobian`, the
    transition from the first sample and ∂r/∂δx₀: (q (n, 4), ω (n, 3), Φ (n, nx, nx), r (n, 3),
    Jr (n, 3, nx), ok). r = (z − h)/sb; h = Rᵀ B_I with `b_i` (n, 3) the inertial field at the samples
    [µT], or Rᵀ β when `b_i` has no rows (β then in the state). Without `jacobian`, Φ and Jr have no rows.
    ok False: a non-finite rate met (the filter's ValueError), the arrays after it unfilled."""
    nbeta = 3 if b_i.shape[0] == 0 else 0
    nx = 6 + npar + nbeta
    ib = 6 + npar
    Q = np.zeros((n, 4))
    W = np.zeros((n, 3))
    r = np.zeros((n, 3))
    nj = n if jacobian else 0
    Phi = np.zeros((nj, nx, nx))
    Jr = np.zeros((nj, 3, nx))
    q = q0.copy()
    w = w0.copy()
    F = np.eye(nx)
    S = np.zeros((6, nx))
    top = np.empty((6, nx))
    wm = np.empty(3)
    for k in range(n):
        if k:
            dt = t[k] - t[k - 1]
            wn = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
            if not math.isfinite(wn):
                return Q, W, Phi, r, Jr, False
            m = min(max_substeps, max(1, int(math.ceil(wn * dt / max_substep_rad))))
            h = dt / m
            for _ in range(m):
                rk4_substep(mode, j2, j3, J, K, q, w, h, wm, _TORQUE_FREE)
                if jacobian:
                    substep_rows(mode, j2, j3, J, K, wm, h, npar, S)
                    substep_transition(S, F, top)
        # the measurement: h = Rᵀ b
        s = 2.0 / (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        xx, yy, zz = s * q[1] * q[1], s * q[2] * q[2], s * q[3] * q[3]
        xy, xz, yz = s * q[1] * q[2], s * q[1] * q[3], s * q[2] * q[3]
        wx, wy, wz = s * q[0] * q[1], s * q[0] * q[2], s * q[0] * q[3]
        C = np.empty((3, 3))
        C[0, 0], C[0, 1], C[0, 2] = 1.0 - (yy + zz), xy - wz, xz + wy
        C[1, 0], C[1, 1], C[1, 2] = xy + wz, 1.0 - (xx + zz), yz - wx
        C[2, 0], C[2, 1], C[2, 2] = xz - wy, yz + wx, 1.0 - (xx + yy)
        b = beta if nbeta else b_i[k]
        hv = np.empty(3)
        for i in range(3):
            hv[i] = C[0, i] * b[0] + C[1, i] * b[1] + C[2, i] * b[2]
        Q[k] = q
        W[k] = w
        for i in range(3):
            r[k, i] = (z[k, i] - hv[i]) / sb
        if jacobian:
            Phi[k] = F
            # H = [[h]ₓ, 0, 0, Rᵀ]; Jr = −H F / sb
            H = np.zeros((3, nx))
            H[0, 1], H[0, 2] = -hv[2], hv[1]
            H[1, 0], H[1, 2] = hv[2], -hv[0]
            H[2, 0], H[2, 1] = -hv[1], hv[0]
            if nbeta:
                for i in range(3):
                    for j in range(3):
                        H[i, ib + j] = C[j, i]
            for i in range(3):
                for j in range(nx):
                    acc = 0.0
                    for l in range(nx):
                        acc += H[i, l] * F[l, j]
                    Jr[k, i, j] = -acc / sb
    return Q, W, Phi, r, Jr, True


#: rk4_substep's torque argument for a torque-free body
_TORQUE_FREE = np.zeros((0, 3))
