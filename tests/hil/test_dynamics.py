"""Rigid-body dynamics: conventions, conservation laws, analytic solutions, RK4 order."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fsw.estimation.rotations import quat_mul, quat_to_dcm
from hil.dynamics import (
    RigidBody,
    _state_rhs,
    euler_rhs,
    quat_derivative,
    quat_from_euler_deg,
    validate_inertia,
)

DEG = np.pi / 180.0
Q_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_angle_rad(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of the rotation R_a^T R_b (0 when the two attitudes agree).

    Taken from the rotation vector, not arccos of the trace, which cannot resolve
    angles below ~1e-8 rad in double precision.
    """
    return float(Rotation.from_matrix(R_a.T @ R_b).magnitude())


def aist2d_full_tensor() -> np.ndarray:
    """Aist-2D principal moments diag(175, 200, 285) kg·m² seen from skewed body axes."""
    C = rot_z(0.4) @ rot_y(-0.3) @ rot_x(0.7)
    return C @ np.diag([175.0, 200.0, 285.0]) @ C.T


def propagate(body: RigidBody, duration_s: float, dt_s: float, torque=(0.0, 0.0, 0.0)) -> None:
    torque = np.asarray(torque, dtype=float)
    for _ in range(int(round(duration_s / dt_s))):
        body.step(dt_s, torque)


# --- quaternion and frame conventions -------------------------------------------------


def test_quat_to_dcm_matches_independent_rotation_library() -> None:
    rng = np.random.default_rng(7)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        expected = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()  # scipy: scalar last
        np.testing.assert_allclose(quat_to_dcm(q), expected, rtol=0, atol=1e-14)
        # a non-unit quaternion describes the same rotation
        np.testing.assert_allclose(quat_to_dcm(3.7 * q), expected, rtol=0, atol=1e-14)


def test_quat_multiply_composes_like_rotation_matrices() -> None:
    rng = np.random.default_rng(8)
    for _ in range(20):
        p, q = rng.normal(size=(2, 4))
        p /= np.linalg.norm(p)
        q /= np.linalg.norm(q)
        np.testing.assert_allclose(
            quat_to_dcm(quat_mul(p, q)), quat_to_dcm(p) @ quat_to_dcm(q), rtol=0, atol=1e-14
        )
    np.testing.assert_allclose(quat_mul(Q_IDENTITY, q), q, rtol=0, atol=0)
    # Hamilton: i ⊗ j = k
    i, j, k = np.eye(4)[1:]
    np.testing.assert_allclose(quat_mul(i, j), k, rtol=0, atol=0)


def test_euler_zyx_sequence_is_body_to_inertial() -> None:
    for roll, pitch, yaw in [(10.0, -20.0, 30.0), (-170.0, 80.0, 250.0), (0.0, 0.0, 0.0)]:
        R = quat_to_dcm(quat_from_euler_deg(roll, pitch, yaw))
        expected = rot_z(yaw * DEG) @ rot_y(pitch * DEG) @ rot_x(roll * DEG)
        np.testing.assert_allclose(R, expected, rtol=0, atol=1e-14)
    # yaw 90°: the body x axis points along inertial +y (v_inertial = R v_body)
    R = quat_to_dcm(quat_from_euler_deg(0.0, 0.0, 90.0))
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], rtol=0, atol=1e-15)
    # pitch 90°: the body x axis points along inertial -z (nose up in a z-down world)
    R = quat_to_dcm(quat_from_euler_deg(0.0, 90.0, 0.0))
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], rtol=0, atol=1e-15)


def test_spin_about_body_z_gives_rz_of_omega_t() -> None:
    omega = 10.0 * DEG
    body = RigidBody(np.diag([1.0, 2.0, 2.5]), Q_IDENTITY, np.array([0.0, 0.0, omega]))
    for _ in range(5):
        propagate(body, 7.0, 0.01)
        np.testing.assert_allclose(quat_to_dcm(body.q), rot_z(omega * body.t_s), rtol=0, atol=1e-12)
    assert body.t_s == pytest.approx(35.0, abs=1e-9)


def test_fixed_inertial_vector_obeys_dB_body_dt_equals_B_body_cross_omega() -> None:
    J = aist2d_full_tensor()
    body = RigidBody(J, quat_from_euler_deg(20.0, -35.0, 110.0), np.array([0.15, -0.12, 0.2]))
    B_I = np.array([18e-6, -7e-6, 35e-6])  # tesla, fixed in inertial space
    h = 0.01
    propagate(body, 13.0, h)  # any tumbling state
    samples = []
    for _ in range(3):
        samples.append((quat_to_dcm(body.q).T @ B_I, body.omega_radps.copy()))
        body.step(h, np.zeros(3))
    (B_prev, _), (B_mid, omega_mid), (B_next, _) = samples
    dB_dt = (B_next - B_prev) / (2.0 * h)
    expected = np.cross(B_mid, omega_mid)
    scale = np.linalg.norm(B_I) * np.linalg.norm(omega_mid)  # T/s
    assert np.linalg.norm(dB_dt - expected) < 1e-5 * scale
    # and the opposite sign would be grossly wrong
    assert np.linalg.norm(dB_dt + expected) > 1.0 * scale


# --- equations of motion -----------------------------------------------------------------


def test_inner_loop_rhs_matches_textbook_functions() -> None:
    rng = np.random.default_rng(11)
    J = aist2d_full_tensor()
    J_inv = np.linalg.inv(J)
    for _ in range(10):
        q = rng.normal(size=4)
        omega, M = rng.normal(size=(2, 3))
        y_dot = _state_rhs(np.concatenate((q, omega)), J.tolist(), J_inv.tolist(), M.tolist())
        np.testing.assert_allclose(y_dot[:4], quat_derivative(q, omega), rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(y_dot[4:], euler_rhs(J, J_inv, omega, M), rtol=1e-12, atol=1e-15)
        # Euler's equation itself: J ω̇ + ω × Jω = M
        np.testing.assert_allclose(J @ y_dot[4:] + np.cross(omega, J @ omega), M, rtol=0, atol=1e-12)
        # q̇ = ½ q ⊗ [0, ω]
        np.testing.assert_allclose(
            y_dot[:4], 0.5 * quat_mul(q, np.concatenate(([0.0], omega))), rtol=0, atol=1e-15
        )


def test_torque_free_asymmetric_body_conserves_energy_and_inertial_momentum() -> None:
    J = aist2d_full_tensor()
    omega0 = 10.0 * DEG * np.array([0.6, -0.5, 0.62])
    body = RigidBody(J, quat_from_euler_deg(5.0, 15.0, -40.0), omega0)
    T0 = body.kinetic_energy_J()
    H0 = body.angular_momentum_inertial()
    propagate(body, 1000.0, 0.01)
    assert abs(body.kinetic_energy_J() - T0) < 1e-9 * T0  # J
    assert np.linalg.norm(body.angular_momentum_inertial() - H0) < 1e-9 * np.linalg.norm(H0)
    # the rate really moved (not a trivial spin about a principal axis)
    assert np.linalg.norm(body.omega_radps - omega0) > 0.1 * np.linalg.norm(omega0)


def test_conservation_error_shrinks_with_step_like_fourth_order() -> None:
    J = aist2d_full_tensor()
    omega0 = 10.0 * DEG * np.array([0.6, -0.5, 0.62])
    drift_T, drift_H = [], []
    for dt in (0.4, 0.2):
        body = RigidBody(J, Q_IDENTITY, omega0)
        T0, H0 = body.kinetic_energy_J(), body.angular_momentum_inertial()
        propagate(body, 1000.0, dt)
        drift_T.append(abs(body.kinetic_energy_J() - T0))
        drift_H.append(np.linalg.norm(body.angular_momentum_inertial() - H0))
    assert 12.0 < drift_H[0] / drift_H[1] < 20.0
    assert 12.0 < drift_T[0] / drift_T[1] < 40.0  # energy drift is at least 4th order


@pytest.mark.parametrize("I_t, I_3", [(0.058, 0.011), (175.0, 285.0)])  # prolate ISOI, oblate
def test_axisymmetric_free_precession_matches_analytic_solution(I_t: float, I_3: float) -> None:
    J = np.diag([I_t, I_t, I_3])
    w_perp, phi0, omega3 = 4.0 * DEG, 0.3, 9.0 * DEG
    omega0 = np.array([w_perp * np.cos(phi0), w_perp * np.sin(phi0), omega3])
    R0 = quat_to_dcm(quat_from_euler_deg(30.0, -20.0, 75.0))
    body = RigidBody(J, Rotation.from_matrix(R0).as_quat(scalar_first=True), omega0)

    lam = (I_3 - I_t) / I_t * omega3  # body-frame precession rate of ω⊥ about the symmetry axis
    H_I = R0 @ (J @ omega0)
    H = np.linalg.norm(H_I)
    dt = 0.02
    for _ in range(4):
        propagate(body, 75.0, dt)
        t = body.t_s
        expected_omega = np.array(
            [w_perp * np.cos(lam * t + phi0), w_perp * np.sin(lam * t + phi0), omega3]
        )
        assert np.linalg.norm(body.omega_radps - expected_omega) < 1e-10  # rad/s
        # attitude: R(t) = Rot(Ĥ, |H| t / I_t) · R0 · Rz(−λ t)
        R_expected = (
            Rotation.from_rotvec(H_I / H * (H / I_t * t)).as_matrix() @ R0 @ rot_z(-lam * t)
        )
        assert rotation_angle_rad(quat_to_dcm(body.q), R_expected) < 1e-9  # rad


@pytest.mark.parametrize("axis, stable", [(1, True), (2, True), (0, False)])
def test_spin_about_major_and_minor_axes_is_stable_intermediate_is_not(axis: int, stable: bool) -> None:
    # AMDS spacecraft (lapkhanov2019): x intermediate, y major, z minor
    J = np.diag([17.995, 20.711, 15.269])
    omega0 = np.full(3, 1e-4)
    omega0[axis] = 10.0 * DEG
    body = RigidBody(J, Q_IDENTITY, omega0)
    T0 = body.kinetic_energy_J()
    max_tilt_rad, min_axial = 0.0, np.inf
    for _ in range(600):
        propagate(body, 1.0, 0.05)
        w = body.omega_radps
        max_tilt_rad = max(max_tilt_rad, np.arccos(abs(w[axis]) / np.linalg.norm(w)))
        min_axial = min(min_axial, w[axis])
    assert abs(body.kinetic_energy_J() - T0) < 1e-9 * T0
    if stable:
        assert max_tilt_rad < 0.01
        assert min_axial > 0.99 * omega0[axis]
    else:  # Dzhanibekov flip: the spin component about the intermediate axis reverses
        assert max_tilt_rad > 1.0
        assert min_axial < -0.5 * omega0[axis]


def test_constant_torque_on_spherical_body_is_exact_linear_spin_up() -> None:
    I = 2.5
    omega0 = np.array([0.1, -0.2, 0.05])
    M = np.array([0.01, 0.02, -0.03])
    body = RigidBody(I * np.eye(3), quat_from_euler_deg(10.0, 20.0, 30.0), omega0)
    propagate(body, 10.0, 0.1, torque=M)
    np.testing.assert_allclose(body.omega_radps, omega0 + M * body.t_s / I, rtol=0, atol=1e-14)


def test_rk4_global_error_falls_sixteenfold_when_step_halves() -> None:
    J = aist2d_full_tensor()
    omega0 = np.array([0.15, -0.12, 0.2])
    q0 = quat_from_euler_deg(20.0, -35.0, 110.0)
    M = np.array([0.3, -0.1, 0.2])  # N·m, constant in body axes

    def final_state(dt: float) -> tuple[np.ndarray, np.ndarray]:
        body = RigidBody(J, q0, omega0)
        propagate(body, 40.0, dt, torque=M)
        return quat_to_dcm(body.q), body.omega_radps

    R_ref, w_ref = final_state(0.025)
    (R1, w1), (R2, w2) = final_state(0.4), final_state(0.2)
    ratio_omega = np.linalg.norm(w1 - w_ref) / np.linalg.norm(w2 - w_ref)
    ratio_att = rotation_angle_rad(R1, R_ref) / rotation_angle_rad(R2, R_ref)
    assert 13.0 < ratio_omega < 19.0
    assert 13.0 < ratio_att < 19.0


# --- input validation ----------------------------------------------------------------------


@pytest.mark.parametrize(
    "J, message",
    [
        (np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "symmetric"),
        (np.diag([1.0, -1.0, 1.0]), "positive definite"),
        (np.diag([1.0, 1.0, 2.5]), "triangle"),
        (np.eye(2), "shape"),
        (np.diag([1.0, np.nan, 1.0]), "finite"),
    ],
)
def test_unphysical_inertia_is_rejected(J: np.ndarray, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        RigidBody(J, Q_IDENTITY, np.zeros(3))


def test_flat_plate_inertia_is_accepted() -> None:
    # thin square plate: I_z = I_x + I_y exactly (triangle inequality with equality)
    np.testing.assert_array_equal(validate_inertia(np.diag([1.0, 1.0, 2.0])), np.diag([1.0, 1.0, 2.0]))


def test_bad_quaternion_rate_and_step_are_rejected() -> None:
    with pytest.raises(ValueError, match="nonzero"):
        RigidBody(np.eye(3), np.zeros(4), np.zeros(3))
    with pytest.raises(ValueError, match="shape"):
        RigidBody(np.eye(3), np.ones(3), np.zeros(3))
    with pytest.raises(ValueError, match="omega0"):
        RigidBody(np.eye(3), Q_IDENTITY, np.zeros(4))
    body = RigidBody(np.eye(3), 2.0 * Q_IDENTITY, np.zeros(3))
    np.testing.assert_array_equal(body.q, Q_IDENTITY)  # normalised on entry
    with pytest.raises(ValueError, match="dt_s"):
        body.step(0.0, np.zeros(3))
    with pytest.raises(ValueError, match="torque"):
        body.step(0.1, np.zeros(2))
