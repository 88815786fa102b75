"""The free motion of the host relative to the orbital frame (circular orbit), compiled (numba, cached on disk):
its right-hand side under the gravity gradient and the sail (:func:`relative_rhs`), an RK4 step with the
attitude re-orthonormalised (:func:`rk4_step`, :func:`orthonormal_rows`) and the motion over many steps
(:func:`free_motion`). The de-orbit controller's plans (:mod:`.controller`) and the energy law's forecasts
(:mod:`.energy_horizon`) both stand on it. R = R_bo (body → orbital frame: rows the orbital axes in body axes),
ω_rel the rate relative to the orbital frame (rad/s, body axes), J the principal moments (kg·m²), n the mean
motion (rad/s), ka the sail's small-angle stiffness (N·m/rad).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def relative_rhs(R, w, J, n, ka, sail_share):
    """(Ṙ_bo, ω̇_rel) of the free motion relative to the orbital frame (circular orbit): gravity gradient
    3n² ĉ × Jĉ (ĉ nadir in body axes) and the sail's moment k_a·f·(x_b × v̂) (f the share of the area the
    flow sees, 1 when broadside: k_a is the small-angle stiffness), Euler's equations in the inertial rate."""
    wo = -n * R[1, :]  # the orbital frame's rate (n about −y_o) in body axes
    c = R[2, :]  # nadir
    vh = R[0, :]  # the flight direction
    Jc = J * c
    M = 3.0 * n * n * np.array((c[1] * Jc[2] - c[2] * Jc[1], c[2] * Jc[0] - c[0] * Jc[2], c[0] * Jc[1] - c[1] * Jc[0]))
    f = sail_share * abs(vh[0]) + (1.0 - sail_share)
    M[1] -= ka * f * vh[2]
    M[2] += ka * f * vh[1]
    wa = w + wo
    Jw = J * wa
    gyro = np.array((wa[1] * Jw[2] - wa[2] * Jw[1], wa[2] * Jw[0] - wa[0] * Jw[2], wa[0] * Jw[1] - wa[1] * Jw[0]))
    wdot = (M - gyro) / J + np.array((w[1] * wo[2] - w[2] * wo[1], w[2] * wo[0] - w[0] * wo[2],
                                      w[0] * wo[1] - w[1] * wo[0]))
    K = np.zeros((3, 3))
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -w[2], w[1], w[2], -w[0], -w[1], w[0]
    return R @ K, wdot


@njit(cache=True)
def _rhs(R, w, J, n, ka, sail_share, m, b_o):
    """relative_rhs, plus the body-fixed dipole m's moment m × B (B = b_o in body axes) when m is given."""
    dR, dw = relative_rhs(R, w, J, n, ka, sail_share)
    if m is not None:
        dw = dw + np.cross(m, b_o @ R) / J
    return dR, dw


@njit(cache=True)
def rk4_step(R, w, J, n, ka, sail_share, h, m=None, b_o=None):
    """One RK4 step of h of the relative motion, R re-orthonormalised; with the body-fixed dipole m [A·m²]
    in the field b_o [T] (orbital axes, constant over the step) when given (numba compiles the free form
    without it)."""
    dR1, dw1 = _rhs(R, w, J, n, ka, sail_share, m, b_o)
    dR2, dw2 = _rhs(R + 0.5 * h * dR1, w + 0.5 * h * dw1, J, n, ka, sail_share, m, b_o)
    dR3, dw3 = _rhs(R + 0.5 * h * dR2, w + 0.5 * h * dw2, J, n, ka, sail_share, m, b_o)
    dR4, dw4 = _rhs(R + h * dR3, w + h * dw3, J, n, ka, sail_share, m, b_o)
    R = R + h / 6.0 * (dR1 + 2.0 * dR2 + 2.0 * dR3 + dR4)
    w = w + h / 6.0 * (dw1 + 2.0 * dw2 + 2.0 * dw3 + dw4)
    return orthonormal_rows(R), w


@njit(cache=True)
def orthonormal_rows(R):
    """R made a rotation again after an integration step: Gram-Schmidt on its rows."""
    r0 = R[0] / math.sqrt(R[0] @ R[0])
    r1 = R[1] - (R[1] @ r0) * r0
    r1 = r1 / math.sqrt(r1 @ r1)
    out = np.empty((3, 3))
    out[0], out[1] = r0, r1
    out[2] = np.array((r0[1] * r1[2] - r0[2] * r1[1], r0[2] * r1[0] - r0[0] * r1[2], r0[0] * r1[1] - r0[1] * r1[0]))
    return out


@njit(cache=True)
def free_motion(R_bo, w_rel, J, n, ka, sail_share, h, steps):
    """The free (unactuated) motion relative to the orbital frame from (R_bo, ω_rel), RK4 in `steps` steps
    of `h` (R re-orthonormalised after each); returns R (steps+1, 3, 3) and ω_rel (steps+1, 3), entry k at
    k·h. The controller's prediction of where the attitude goes when the magnets stay screened, valid at
    any angle (the linear model is not, at tens of degrees)."""
    Rs = np.empty((steps + 1, 3, 3))
    ws = np.empty((steps + 1, 3))
    R, w = R_bo.copy(), w_rel.copy()
    Rs[0], ws[0] = R, w
    for k in range(steps):
        R, w = rk4_step(R, w, J, n, ka, sail_share, h)
        Rs[k + 1], ws[k + 1] = R, w
    return Rs, ws
