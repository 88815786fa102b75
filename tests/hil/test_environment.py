"""Torques on the AMDS spacecraft and its orbital frame, against textbook closed forms; the de-orbit
simulator's initial state and the kit emulator's dipole."""
import math

import numpy as np
import pytest

from fsw.estimation.rotations import quat_from_dcm, quat_to_dcm
from hil import dynamics, scenario
from hil.deorbit_kit import DeorbitKitEmulator
from hil.deorbit_sim import DeorbitSimulator
from hil.environment import (
    VALLADO_600KM,
    aero_torque_Nm,
    dcm_from_euler_zyx,
    euler_zyx_from_dcm,
    gravity_gradient_torque_Nm,
    magnetic_torque_Nm,
    orbital_frame_dcm,
)
from hil.orbit import MU_EARTH_M3S2, CircularOrbit
from hil.sim import Simulator

J = np.diag([17.995, 20.711, 15.269])
R_M = 6378137.0 + 600e3


def test_orbital_frame_axes():
    orbit = CircularOrbit(600e3, 97.8, 30.0, 10.0)
    for t in (0.0, 1234.0):
        r, v = orbit.position_eci_m(t), orbit.velocity_eci_mps(t)
        R = orbital_frame_dcm(r, v)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(R[:, 0], v / np.linalg.norm(v), atol=1e-12)  # x along the velocity
        np.testing.assert_allclose(R[:, 2], -r / np.linalg.norm(r), atol=1e-12)  # z to nadir
        h = np.cross(r, v)
        np.testing.assert_allclose(R[:, 1], -h / np.linalg.norm(h), atol=1e-12)  # y = −orbit normal


@pytest.mark.parametrize("theta", [0.05, 0.4, -0.7])
def test_gravity_gradient_pitch_torque_closed_form(theta):
    R_bo = dcm_from_euler_zyx(0.0, theta, 0.0)
    r_body = R_bo.T @ np.array([0.0, 0.0, -R_M])  # the Earth's centre is along +z_o from the spacecraft
    M = gravity_gradient_torque_Nm(-r_body, J)  # position of the spacecraft from the Earth's centre
    k = 3 * MU_EARTH_M3S2 / R_M**3
    assert M[1] == pytest.approx(-k * (J[0, 0] - J[2, 2]) * math.sin(theta) * math.cos(theta), rel=1e-9)
    assert abs(M[0]) < 1e-15 and abs(M[2]) < 1e-15


def test_aero_torque_is_a_weathervane_with_the_expected_stiffness():
    rho = VALLADO_600KM.density_kgm3(600e3)
    assert rho == pytest.approx(1.454e-13)
    v = 7558.0
    k = 0.12 * 0.5 * rho * v * v * 2.2 * (5.0 + 0.58)
    for yaw, pitch in ((0.01, 0.0), (0.0, -0.01), (0.3, 0.2)):
        R_bo = dcm_from_euler_zyx(yaw, pitch, 0.0)
        v_body = R_bo.T @ np.array([v, 0.0, 0.0])
        M = aero_torque_Nm(v_body, rho, 2.2, 5.0, np.array([1.0, 0.0, 0.0]), 0.58, np.array([-0.12, 0.0, 0.0]))
        # turns the sail normal (body x) towards the flight direction: restoring
        f = v_body / v
        assert np.dot(M, np.cross([1.0, 0.0, 0.0], f)) > 0
        if abs(yaw) + abs(pitch) < 0.02:
            assert M[2] == pytest.approx(-k * yaw, rel=1e-3) if yaw else M[1] == pytest.approx(-k * pitch, rel=1e-3)
    assert np.all(aero_torque_Nm(np.array([v, 0, 0]), rho, 2.2, 5.0, np.array([1.0, 0, 0]), 0.58,
                                 np.array([-0.12, 0, 0])) == 0)


def test_magnet_torque_is_p_cross_b():
    p, b = np.array([0.0, 15.0, -15.0]), np.array([20e-6, -3e-6, 40e-6])
    np.testing.assert_allclose(magnetic_torque_Nm(p, b), np.cross(p, b))


def test_euler_round_trip_and_quaternion():
    for ypr in ((0.3, -0.2, 1.0), (-2.0, 1.2, -0.5)):
        R = dcm_from_euler_zyx(*ypr)
        assert euler_zyx_from_dcm(R) == pytest.approx(ypr)
        np.testing.assert_allclose(quat_to_dcm(quat_from_dcm(R)), R, atol=1e-12)
    # the hil.dynamics convention: quat_from_euler_deg(roll, pitch, yaw) is the same ZYX sequence
    q = dynamics.quat_from_euler_deg(20.0, -10.0, 35.0)
    np.testing.assert_allclose(quat_to_dcm(q), dcm_from_euler_zyx(*np.radians([35.0, -10.0, 20.0])),
                               atol=1e-12)


def test_deorbit_scenario_starts_at_yaw_60_pitch_45_at_rest_in_the_orbital_frame():
    scn = scenario.load("amds_deorbit")
    assert scn.deorbit.initial_ypr_deg == (60.0, 45.0, 0.0) and scn.deorbit.sail_area_m2 == 5.0
    assert scn.deorbit.cp_offset_m == (-0.12, 0.0, 0.0) and scn.deorbit.duration_s == 10800.0
    sim = DeorbitSimulator(scn)
    R_bo, w_rel, _ = sim.attitude_orbital()
    assert np.degrees(euler_zyx_from_dcm(R_bo)) == pytest.approx([60.0, 45.0, 0.0])
    np.testing.assert_allclose(w_rel, 0.0, atol=1e-15)
    # [initial] holds the same state in ECI terms for the plain simulator
    plain = Simulator(scn)
    assert abs(np.dot(plain.body.q, sim.body.q)) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(plain.body.omega_radps, sim.body.omega_radps, atol=1e-8)


def test_deorbit_scenario_table_is_checked(tmp_path):
    text = (scenario.SCENARIO_DIR / "amds_deorbit.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("sail_area_m2 = 5.0", "sail_area_m = 5.0"))
    with pytest.raises(scenario.ScenarioError, match="unknown key"):
        scenario.load(str(bad))
    bad.write_text(text.replace("cp_offset_m = [-0.12, 0.0, 0.0]", "cp_offset_m = [-0.12, 0.0]"))
    with pytest.raises(scenario.ScenarioError, match="cp_offset_m"):
        scenario.load(str(bad))
    bad.write_text(text.replace("settle_s = 3600.0", "settle_s = 20000.0"))
    with pytest.raises(scenario.ScenarioError, match="settle_s"):
        scenario.load(str(bad))
    assert scenario.load("amds").deorbit is None


def test_torque_free_passive_motion_keeps_the_jacobi_integral():
    """No magnets: aerodynamic and gravity-gradient torques are conservative in the rotating orbital
    frame (circular orbit), so the Jacobi integral ½ω_relᵀJω_rel + U is constant; checked on the
    linear model's energy for a small oscillation."""
    scn = scenario.load("amds_deorbit")
    sim = DeorbitSimulator(scn, max_step_s=0.5)
    sim.set_attitude_orbital(dcm_from_euler_zyx(0.05, -0.04, 0.03), np.zeros(3))
    n = sim.orbit.mean_motion_radps
    k_a = 0.12 * 0.5 * sim.env.rho_kgm3 * (R_M * n) ** 2 * 2.2 * 5.58
    Jd = np.diag(J)

    def jacobi():
        R, w, _ = sim.attitude_orbital()
        yaw, pitch, roll = euler_zyx_from_dcm(R)
        U = 0.5 * (4 * n * n * (Jd[1] - Jd[2]) * roll**2 + (3 * n * n * (Jd[0] - Jd[2]) + k_a) * pitch**2
                   + (n * n * (Jd[1] - Jd[0]) + k_a) * yaw**2)
        return 0.5 * w @ (Jd * w) + U

    e0 = jacobi()
    for k in range(1, 41):
        sim.advance_to(50.0 * k)
    assert jacobi() == pytest.approx(e0, rel=0.01)


def test_emulated_dipole_follows_rotor_and_shutter():
    kit = DeorbitKitEmulator()
    pitch, yaw = kit.channels
    pitch.shutter, yaw.shutter = 1.0, 0.5
    np.testing.assert_allclose(kit.dipole_body_Am2(), [0.0, 7.5, 15.0], atol=1e-12)
    pitch.rotor_steps, yaw.rotor_steps = 100, 300
    np.testing.assert_allclose(kit.dipole_body_Am2(), [0.0, -7.5, -15.0], atol=1e-12)
    pitch.rotor_steps = 50  # 90°: the pitch magnet's dipole lies along −y
    np.testing.assert_allclose(pitch.dipole_body_Am2(), [0.0, -15.0, 0.0], atol=1e-12)
