"""Rigid-body attitude dynamics and kinematics for the tumbling host.

Conventions (see ``docs/spec/physics-and-seeds.md`` §2):

* Quaternion ``q = [w, x, y, z]`` (scalar first) rotates body -> inertial:
  ``v_inertial = R(q) v_body`` with ``R = quat_to_dcm(q)`` = R_bodyToInertial
  (the quaternion helpers are in ``fsw.estimation.rotations``).
* ``omega`` is the body rate relative to inertial space, in body axes [rad/s].
* Kinematics: ``q_dot = 1/2 q ⊗ [0, omega]``, equivalently ``R_dot = R [omega×]``.
* Dynamics (Euler, about the centre of mass, body axes):
  ``J omega_dot + omega × (J omega) = M``.

For an inertially fixed vector ``B_I``, ``B_body = R^T B_I`` then obeys
``dB_body/dt = B_body × omega``.
"""

from __future__ import annotations

import numpy as np

from fsw.estimation.rotations import quat_normalize, quat_to_dcm

__all__ = [
    "quat_from_euler_deg",
    "quat_derivative",
    "euler_rhs",
    "validate_inertia",
    "RigidBody",
]


def quat_from_euler_deg(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body -> inertial quaternion from aerospace ZYX (yaw-pitch-roll) Euler angles in degrees.

    Sequence: starting from the inertial axes, rotate by ``yaw`` about z, then by
    ``pitch`` about the new y, then by ``roll`` about the new x. The result is
    ``R_bodyToInertial = Rz(yaw) · Ry(pitch) · Rx(roll)`` (each an active,
    right-handed rotation), i.e. ``q = q_z(yaw) ⊗ q_y(pitch) ⊗ q_x(roll)``.
    """
    hr, hp, hy = np.radians([roll, pitch, yaw]) / 2.0
    cr, sr = np.cos(hr), np.sin(hr)
    cp, sp = np.cos(hp), np.sin(hp)
    cy, sy = np.cos(hy), np.sin(hy)
    return np.array(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ]
    )


def quat_derivative(q: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """Kinematics ``q_dot = 1/2 q ⊗ [0, omega]`` with ``omega`` the body rate in body axes [rad/s]."""
    w, x, y, z = q
    p, r_, s = omega
    return 0.5 * np.array(
        [
            -x * p - y * r_ - z * s,
            w * p + y * s - z * r_,
            w * r_ - x * s + z * p,
            w * s + x * r_ - y * p,
        ]
    )


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3-vector cross product (``np.cross`` is several times slower for single vectors)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def euler_rhs(J: np.ndarray, J_inv: np.ndarray, omega: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Euler's rotational equation solved for the rate: ``dω/dt = J⁻¹ (M − ω × J ω)``.

    ``J`` [kg·m²] about the centre of mass in body axes, ``omega`` [rad/s],
    ``M`` [N·m] about the centre of mass in body axes.
    """
    return J_inv @ (M - _cross(omega, J @ omega))


def validate_inertia(J_kgm2: np.ndarray, rel_tol: float = 1e-9) -> np.ndarray:
    """Check that ``J`` is a physical inertia tensor and return it as a float (3, 3) array.

    Requirements: finite, symmetric, positive definite, and the principal moments
    satisfy the triangle inequalities ``I_i <= I_j + I_k`` (equality is a flat
    lamina). ``rel_tol`` is relative to the largest principal moment.
    """
    J = np.asarray(J_kgm2, dtype=float)
    if J.shape != (3, 3):
        raise ValueError(f"inertia tensor must have shape (3, 3), got {J.shape}")
    if not np.all(np.isfinite(J)):
        raise ValueError("inertia tensor must be finite")
    scale = float(np.max(np.abs(J)))
    if scale == 0.0:
        raise ValueError("inertia tensor is zero; it must be positive definite")
    if np.max(np.abs(J - J.T)) > rel_tol * scale:
        raise ValueError(f"inertia tensor must be symmetric, got\n{J}")
    J = 0.5 * (J + J.T)
    principal = np.linalg.eigvalsh(J)
    if principal[0] <= 0.0:
        raise ValueError(
            f"inertia tensor must be positive definite; principal moments {principal} kg·m²"
        )
    i1, i2, i3 = principal  # ascending
    if i3 > (i1 + i2) * (1.0 + rel_tol):
        raise ValueError(
            "principal moments violate the triangle inequality "
            f"I3 <= I1 + I2: {i3:.6g} > {i1:.6g} + {i2:.6g} kg·m²"
        )
    return J


def _state_rhs(
    y: np.ndarray, J: list[list[float]], J_inv: list[list[float]], M: list[float]
) -> np.ndarray:
    """Time derivative of the state ``y = [q (4), ω (3)]``.

    The same equations as :func:`quat_derivative` and :func:`euler_rhs`, written
    out on scalars because this is the simulator's inner loop (about 4x faster
    than composing the small-array functions; ``tests/test_dynamics.py`` checks
    that the two agree).
    """
    w, x, y_, z, p, q, r = y.tolist()
    (J11, J12, J13), (J21, J22, J23), (J31, J32, J33) = J
    (K11, K12, K13), (K21, K22, K23), (K31, K32, K33) = J_inv
    # angular momentum in body axes, H = J ω
    H1 = J11 * p + J12 * q + J13 * r
    H2 = J21 * p + J22 * q + J23 * r
    H3 = J31 * p + J32 * q + J33 * r
    # M − ω × H
    e1 = M[0] - (q * H3 - r * H2)
    e2 = M[1] - (r * H1 - p * H3)
    e3 = M[2] - (p * H2 - q * H1)
    return np.array(
        (
            0.5 * (-x * p - y_ * q - z * r),
            0.5 * (w * p + y_ * r - z * q),
            0.5 * (w * q - x * r + z * p),
            0.5 * (w * r + x * q - y_ * p),
            K11 * e1 + K12 * e2 + K13 * e3,
            K21 * e1 + K22 * e2 + K23 * e3,
            K31 * e1 + K32 * e2 + K33 * e3,
        )
    )


class RigidBody:
    """Torque-driven rigid body with a full inertia tensor, integrated by fixed-step RK4.

    State: ``q`` (body -> inertial, scalar first, unit norm), ``omega_radps``
    (body rate in body axes), ``t_s``. ``step`` holds the torque constant over the
    step (zero-order hold, as a flight computer applies it) and renormalises ``q``.
    """

    def __init__(self, J_kgm2: np.ndarray, q0: np.ndarray, omega0_radps: np.ndarray) -> None:
        self.J_kgm2 = validate_inertia(J_kgm2)
        self.J_inv = np.linalg.inv(self.J_kgm2)
        self._J_rows = self.J_kgm2.tolist()
        self._J_inv_rows = self.J_inv.tolist()
        self.q = quat_normalize(q0)
        omega0 = np.asarray(omega0_radps, dtype=float)
        if omega0.shape != (3,) or not np.all(np.isfinite(omega0)):
            raise ValueError(f"omega0_radps must be a finite 3-vector, got {omega0_radps!r}")
        self.omega_radps = omega0.copy()
        self.t_s = 0.0

    def step(self, dt_s: float, torque_body_Nm: np.ndarray) -> None:
        """Advance one fixed step ``dt_s`` with classical RK4 on (q, ω), torque held constant."""
        if not (dt_s > 0.0 and np.isfinite(dt_s)):
            raise ValueError(f"dt_s must be positive and finite, got {dt_s!r}")
        M = np.asarray(torque_body_Nm, dtype=float)
        if M.shape != (3,):
            raise ValueError(f"torque_body_Nm must be a 3-vector, got shape {M.shape}")
        h = float(dt_s)
        M_list = M.tolist()
        J, J_inv = self._J_rows, self._J_inv_rows
        y0 = np.concatenate((self.q, self.omega_radps))
        k1 = _state_rhs(y0, J, J_inv, M_list)
        k2 = _state_rhs(y0 + (0.5 * h) * k1, J, J_inv, M_list)
        k3 = _state_rhs(y0 + (0.5 * h) * k2, J, J_inv, M_list)
        k4 = _state_rhs(y0 + h * k3, J, J_inv, M_list)
        y = y0 + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
        q = y[:4]
        self.q = q / np.sqrt(q @ q)
        self.omega_radps = y[4:]
        self.t_s += h

    @property
    def dcm(self) -> np.ndarray:
        """R_bodyToInertial of the current attitude."""
        return quat_to_dcm(self.q)

    def kinetic_energy_J(self) -> float:
        """Rotational kinetic energy ``T = 1/2 ωᵀ J ω`` [J]."""
        w = self.omega_radps
        return 0.5 * float(w @ (self.J_kgm2 @ w))

    def angular_momentum_inertial(self) -> np.ndarray:
        """Angular momentum about the centre of mass in inertial axes, ``H_I = R J ω`` [N·m·s]."""
        return quat_to_dcm(self.q) @ (self.J_kgm2 @ self.omega_radps)
