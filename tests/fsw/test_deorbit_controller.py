"""The discrete controller (lapkhanov2019 eq. 4-6) against independent truth: cross products, Euler
angles, a numerical linearisation of the full nonlinear dynamics."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fsw.deorbit.controller import (
    AttitudeInput,
    ControllerConfig,
    DiscreteController,
    aero_stiffness_Nm_per_rad,
    box_lasso,
    box_lasso_weighted,
    coast_amplitude_sqrt,
    discrete_moment_Nm,
    euler_zyx,
    lvlh_model,
    magnet_moment_Nm,
    pointing_error,
    polarity_for,
    pulse_width_s,
)
from fsw.estimation.rotations import rotvec_from_dcm
from hil.environment import (
    aero_torque_Nm,
    dcm_from_euler_zyx,
    gravity_gradient_torque_Nm,
)
from hil.orbit import A_WGS84_M, MU_EARTH_M3S2

J = np.array([17.995, 20.711, 15.269])
RNG = np.random.default_rng(5)


def test_eq4_and_eq5_are_the_cross_product():
    for _ in range(20):
        b = RNG.normal(size=3) * 30e-6
        for pp in (-1, 0, 1):
            for py in (-1, 0, 1):
                p = np.array([0.0, py * 15.0, pp * 15.0])
                np.testing.assert_allclose(discrete_moment_Nm(pp, py, 15.0, b), np.cross(p, b), atol=1e-18)
                np.testing.assert_allclose(magnet_moment_Nm(p, b), np.cross(p, b))


def test_polarity_gives_the_requested_sign():
    for _ in range(50):
        b = RNG.normal(size=3) * 30e-6
        m = RNG.normal()
        pitch = polarity_for(0, m, b[0])
        yaw = polarity_for(1, m, b[0])
        assert np.sign(discrete_moment_Nm(pitch, 0, 15.0, b)[1]) == np.sign(m)  # M_y = p_mz B_x
        assert np.sign(discrete_moment_Nm(0, yaw, 15.0, b)[2]) == np.sign(m)  # M_z = −p_my B_x
    assert polarity_for(0, 1.0, 0.0) == 0


def test_eq6_pulse_width():
    assert pulse_width_s(1e-4, 3e-4, 300.0, 80.0) == pytest.approx(100.0)
    assert pulse_width_s(-1e-4, 3e-4, 300.0, 80.0) == pytest.approx(100.0)
    assert pulse_width_s(0.5e-4, 3e-4, 300.0, 80.0) == 0.0  # 50 s < the 80 s minimum: not generated
    assert pulse_width_s(9e-4, 3e-4, 300.0, 80.0) == 300.0  # at most one period
    assert pulse_width_s(1e-4, 0.0, 300.0, 80.0) == 0.0


@pytest.mark.parametrize("roll", [0.0, 0.7, -2.5])
def test_yaw_pitch_are_the_sail_normal_direction_whatever_the_roll(roll):
    yaw, pitch = 0.4, -0.25
    R = dcm_from_euler_zyx(yaw, pitch, roll)
    assert euler_zyx(R) == pytest.approx((yaw, pitch, roll))
    np.testing.assert_allclose(R[:, 0], [math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw),
                                         -math.sin(pitch)])
    dy, dz = pointing_error(R)
    # the error's size is the angle between the sail normal and the flight direction
    assert math.hypot(dy, dz) == pytest.approx(math.acos(R[0, 0]))
    # and at zero roll, for small angles, it is (pitch, yaw)
    dy0, dz0 = pointing_error(dcm_from_euler_zyx(0.01, -0.02, 0.0))
    assert (dy0, dz0) == pytest.approx((-0.02, 0.01), rel=1e-3)


def test_rotvec_round_trip():
    for _ in range(20):
        v = RNG.normal(size=3)
        v *= min(1.0, 3.0 / np.linalg.norm(v))
        np.testing.assert_allclose(rotvec_from_dcm(Rotation.from_rotvec(v).as_matrix()), v, atol=1e-9)


def _relative_rhs(x, n, r, rho, speed):
    """Nonlinear motion relative to the orbital frame: x = (rotation vector, ω_rel), body axes."""
    R = Rotation.from_rotvec(x[:3]).as_matrix()  # body -> orbital
    w = x[3:]
    wo = R.T @ np.array([0.0, -n, 0.0])
    M = gravity_gradient_torque_Nm(R.T @ np.array([0.0, 0.0, -r]), np.diag(J)) + aero_torque_Nm(
        R.T @ np.array([speed, 0.0, 0.0]), rho, 2.2, 5.0, np.array([1.0, 0.0, 0.0]), 0.58, np.array([-0.12, 0, 0]))
    wa = w + wo
    wdot = (M - np.cross(wa, J * wa)) / J
    return np.concatenate((w, wdot + np.cross(w, wo)))


def test_lvlh_model_is_the_linearisation_of_the_full_dynamics():
    r = A_WGS84_M + 600e3
    n = math.sqrt(MU_EARTH_M3S2 / r**3)
    rho, speed = 1.454e-13, r * n
    ka = aero_stiffness_Nm_per_rad(rho, speed, 2.2, 5.58, 0.12)
    A = lvlh_model(J, n, ka)
    eps = 1e-6
    A_num = np.column_stack([(_relative_rhs(e, n, r, rho, speed) - _relative_rhs(-e, n, r, rho, speed)) / (2 * eps)
                             for e in np.eye(6) * eps])
    np.testing.assert_allclose(A, A_num, atol=1e-12)
    # neutrally stable (Lagrange region J_y > J_x > J_z, weathervane): purely imaginary eigenvalues
    assert np.abs(np.linalg.eigvals(A).real).max() < 1e-12


def _att(R_bo, w=(0.0, 0.0, 0.0), b_o=(20e-6, 2e-6, 10e-6)):
    b_o = np.array(b_o)
    return AttitudeInput(R_bo, np.array(w, float), R_bo.T @ b_o, lambda t: np.tile(b_o, (len(t), 1)))


def test_mpc_leaves_a_resting_spacecraft_alone():
    c = DiscreteController(ControllerConfig(law="mpc"))
    cmds = c.decide(0.0, _att(np.eye(3)))
    assert [(k.polarity, k.width_s) for k in cmds] == [(0, 0.0), (0, 0.0)]


@pytest.mark.parametrize("law", ["mpc", "paper"])
@pytest.mark.parametrize("axis", [1, 2])
@pytest.mark.parametrize("sign", [1, -1])
def test_a_rate_error_is_braked_by_the_right_channel(law, axis, sign):
    w = np.zeros(3)
    w[axis] = sign * 2e-3
    c = DiscreteController(ControllerConfig(law=law))
    att = _att(np.eye(3), w)
    cmds = c.decide(0.0, att)
    ch = 0 if axis == 1 else 1  # pitch channel acts about y, yaw about z
    cmd = cmds[ch]
    assert cmd.polarity != 0 and 80.0 <= cmd.width_s <= 100.0
    pol = (cmd.polarity, 0) if ch == 0 else (0, cmd.polarity)
    moment = discrete_moment_Nm(*pol, 15.0, att.b_body_T)
    assert np.sign(moment[axis]) == -sign  # opposes the rate
    assert np.sign(cmd.m_theor_Nm) == -sign
    assert cmd.m_ctrl_Nm == pytest.approx(15.0 * abs(att.b_body_T[0]))


def test_paper_law_is_eq5_and_eq6():
    cfg = ControllerConfig(law="paper", period_s=300.0, tau_s=600.0)
    c = DiscreteController(cfg)
    R = dcm_from_euler_zyx(0.0, 0.5, 0.0)  # pitch 0.5 rad, at rest
    att = _att(R)
    cmd = c.decide(0.0, att)[0]
    kd = J[1] / 300.0
    dy, _ = pointing_error(R)
    m_theor = -kd * dy / 600.0
    m_ctrl = 15.0 * abs(att.b_body_T[0])
    assert cmd.m_theor_Nm == pytest.approx(m_theor)
    assert cmd.width_s == pytest.approx(pulse_width_s(m_theor, m_ctrl, 300.0, 80.0))
    assert cmd.polarity == polarity_for(0, m_theor, att.b_body_T[0])


def test_energy_price_trades_pulses_for_error():
    att = _att(dcm_from_euler_zyx(0.1, 0.1, 0.0), (0.0, 5e-4, 5e-4))
    cheap = DiscreteController(ControllerConfig(law="mpc", energy_price_per_J=0.0)).decide(0.0, att)
    dear = DiscreteController(ControllerConfig(law="mpc", energy_price_per_J=1e3)).decide(0.0, att)
    assert any(k.polarity for k in cheap)
    assert not any(k.polarity for k in dear)
    # an open capsule with the right polarity costs nothing to keep open
    kept = DiscreteController(ControllerConfig(law="mpc", energy_price_per_J=1e3, energy_guard_rad=0.0)).decide(
        0.0, att, acting=tuple(k.polarity for k in cheap), polarity=tuple(k.polarity for k in cheap))
    assert [k.polarity for k in kept] == [k.polarity for k in cheap]


def test_config_is_validated():
    with pytest.raises(ValueError):
        ControllerConfig(law="bang")
    with pytest.raises(ValueError):
        ControllerConfig(period_s=60.0, min_impulse_s=80.0)
    with pytest.raises(ValueError):
        ControllerConfig(widths_s=(50.0,))
    with pytest.raises(ValueError):
        ControllerConfig(continuation_l1=-1.0)
    with pytest.raises(ValueError):
        ControllerConfig(r_duty=0.0)
    with pytest.raises(ValueError):
        ControllerConfig(continuation_reweight=-1)
    with pytest.raises(ValueError):
        ControllerConfig(reweight_eps=0.0)


def _lasso_objective(H, b, lam, v):
    return v @ H @ v - 2.0 * b @ v + lam * np.abs(v).sum()


@pytest.mark.parametrize("lam", [0.0, 0.03, 1.0])
def test_box_lasso_reaches_the_optimum_of_a_box_constrained_lasso(lam):
    rng = np.random.default_rng(5)
    M = rng.normal(size=(30, 8))
    H = M.T @ M
    B = rng.normal(scale=8.0, size=(8, 4))  # large enough that the box binds
    V = box_lasso(H, B, lam, sweeps=500, tol=1e-13)
    assert np.all(np.abs(V) <= 1.0)
    for c in range(B.shape[1]):
        v, b = V[:, c], B[:, c]
        # KKT of vᵀHv − 2bᵀv + λ|v|₁ on the box: g = 2(Hv − b)
        g = 2.0 * (H @ v - b)
        for i in range(len(v)):
            if abs(v[i]) < 1e-12:
                assert abs(g[i]) <= lam + 1e-8  # zero: the subgradient contains 0
            elif abs(v[i]) < 1.0 - 1e-12:
                assert g[i] + lam * np.sign(v[i]) == pytest.approx(0.0, abs=1e-7)  # interior: stationary
            else:
                assert (g[i] + lam * np.sign(v[i])) * np.sign(v[i]) <= 1e-8  # at the bound: pushes outwards
        # and no random feasible point does better
        trials = np.clip(v + rng.normal(scale=0.05, size=(200, len(v))), -1.0, 1.0)
        best = _lasso_objective(H, b, lam, v)
        assert all(_lasso_objective(H, b, lam, t) >= best - 1e-9 for t in trials)


def test_box_lasso_weighted_reaches_the_optimum_with_a_price_per_unknown():
    rng = np.random.default_rng(8)
    M = rng.normal(size=(30, 8))
    H = M.T @ M
    B = rng.normal(scale=8.0, size=(8, 3))
    Lam = rng.uniform(0.0, 20.0, size=(8, 3))
    V = box_lasso_weighted(H, B, Lam, rng.uniform(-1, 1, size=(8, 3)), sweeps=2000, tol=1e-14)
    for c in range(3):
        v, g, lam = V[:, c], 2.0 * (H @ V[:, c] - B[:, c]), Lam[:, c]
        for i in range(8):
            if abs(v[i]) < 1e-12:
                assert abs(g[i]) <= lam[i] + 1e-8
            elif abs(v[i]) < 1.0 - 1e-12:
                assert g[i] + lam[i] * np.sign(v[i]) == pytest.approx(0.0, abs=1e-7)
            else:
                assert (g[i] + lam[i] * np.sign(v[i])) * np.sign(v[i]) <= 1e-8
    # one price for all: the plain lasso's optimum, from any start
    same = box_lasso_weighted(H, B, np.full((8, 3), 0.5), np.zeros((8, 3)), sweeps=2000, tol=1e-14)
    assert same == pytest.approx(box_lasso(H, B, 0.5, sweeps=2000, tol=1e-14), abs=1e-9)


def test_the_reweighted_continuation_prices_a_pulse_not_its_duty():
    """Each pass is the majorise-minimise step of the log price Σ k·log(|u| + ε): it never raises it; the
    price reported is k·|u|/(|u| + ε) per pulse, `continuation_pulse_price` for a full one; and the plan's
    small trims (the ℓ1's duties of a few per cent, nearly free at λ per unit duty) go."""
    cfg = ControllerConfig(continuation_reweight=3, continuation_pulse_price=0.06, lasso_sweeps=2000)
    ctl = DiscreteController(cfg)
    rng = np.random.default_rng(9)
    M = rng.normal(size=(60, 12))
    H = M.T @ M
    B = rng.normal(scale=0.4, size=(12, 5))
    eps, k = cfg.reweight_eps, cfg.continuation_pulse_price * (1 + cfg.reweight_eps)

    def log_objective(V):
        return (V * (H @ V)).sum(0) - 2.0 * (B * V).sum(0) + k * np.log(np.abs(V) + eps).sum(0)

    V = box_lasso(H, B, cfg.continuation_l1, 2000, 1e-14)
    small_l1 = int(np.sum((np.abs(V) > 1e-9) & (np.abs(V) < 0.05)))
    for _ in range(3):
        V1 = box_lasso_weighted(H, B, k / (np.abs(V) + eps), V, 2000, 1e-14)
        assert np.all(log_objective(V1) <= log_objective(V) + 1e-9)
        V = V1
    W, price = ctl.reweighted(H, B, box_lasso(H, B, cfg.continuation_l1, 2000, 1e-14))
    assert W == pytest.approx(V, abs=1e-9)
    # a pulse of any width costs at most the price of a full one, a full one exactly that
    nonzero = (np.abs(W) > 1e-12).sum(0)
    assert nonzero.sum() >= 3 and np.all(price <= 0.06 * nonzero + 1e-12)
    big = 1000.0 * B  # the box binds
    W, price = ctl.reweighted(H, big, box_lasso(H, big, cfg.continuation_l1, 2000, 1e-14))
    full = (np.abs(W) >= 1.0 - 1e-12).sum(0)
    assert full.sum() >= 5 and np.all(price >= 0.06 * full - 1e-12)
    assert np.all(price <= 0.06 * (np.abs(W) > 1e-12).sum(0) + 1e-12)
    assert small_l1 >= 5 and int(np.sum((np.abs(W) > 1e-9) & (np.abs(W) < 0.05))) < small_l1


def test_box_lasso_without_box_or_l1_is_least_squares():
    rng = np.random.default_rng(6)
    M = rng.normal(size=(20, 5))
    y = rng.normal(scale=0.1, size=20)
    v = box_lasso(M.T @ M, (M.T @ y)[:, None], 0.0, sweeps=2000, tol=1e-15)[:, 0]
    assert v == pytest.approx(np.linalg.lstsq(M, y, rcond=None)[0], abs=1e-9)


def test_coast_amplitude_is_the_amplitude_of_the_free_libration():
    n, ka = 1.0831e-3, 6.1e-6
    A = lvlh_model(J, n, ka)
    q = (0.05, 1.0, 1.0)
    L = coast_amplitude_sqrt(A, q)
    # pitch is decoupled: θ(t) = θ0 cos ω t + θ̇0/ω sin ω t, amplitude² = θ0² + (θ̇0/ω)²
    w_pitch = math.sqrt((3 * n * n * (J[0] - J[2]) + ka) / J[1])
    x = np.array([0.0, 0.1, 0.0, 0.0, 2e-4, 0.0])
    assert float(np.sum((L @ x) ** 2)) == pytest.approx(q[1] * (0.1**2 + (2e-4 / w_pitch) ** 2), rel=1e-9)
    # roll-yaw (coupled, two frequencies): 2 × the time average of Σ q_a angle_a², by propagation
    from scipy.linalg import expm

    x = np.array([0.05, 0.0, 0.1, 1e-4, 0.0, -1e-4])
    ts = np.linspace(0.0, 2e6, 200_001)
    step = expm(A * (ts[1] - ts[0]))
    xs = np.empty((len(ts), 6))
    xs[0] = x
    for k in range(1, len(ts)):
        xs[k] = step @ xs[k - 1]
    mean_sq = 2.0 * np.mean(q[0] * xs[:, 0] ** 2 + q[2] * xs[:, 2] ** 2)
    assert float(np.sum((L @ x) ** 2)) == pytest.approx(mean_sq, rel=0.01)


def test_free_motion_is_the_nonlinear_motion_at_large_angles():
    """The plan's free motion (RK4 on R_bo, ω_rel) against scipy's integration of the full relative
    dynamics with the simulator's own torques (`hil.environment`), from yaw 60°, pitch 45° (the benchmark's
    start), where the LVLH linearisation is tens of degrees off after a quarter libration."""
    from scipy.integrate import solve_ivp

    from fsw.deorbit.relative_motion import free_motion

    r = A_WGS84_M + 600e3
    n = math.sqrt(MU_EARTH_M3S2 / r**3)
    rho, speed = 1.454e-13, r * n
    ka = aero_stiffness_Nm_per_rad(rho, speed, 2.2, 5.58, 0.12)
    R0 = dcm_from_euler_zyx(math.radians(60), math.radians(45), 0.0)
    w0 = np.array([1e-4, -2e-4, 3e-4])
    Rs, ws = free_motion(R0, w0, J, n, ka, 5.0 / 5.58, 10.0, 200)
    x0 = np.concatenate((rotvec_from_dcm(R0), w0))
    sol = solve_ivp(lambda t, x: _relative_rhs_exact(x, n, r, rho, speed), (0.0, 2000.0), x0, rtol=1e-10, atol=1e-12)
    R_ref = Rotation.from_rotvec(sol.y[:3, -1]).as_matrix()
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(Rs[-1].T @ R_ref).as_rotvec())) < 0.01
    np.testing.assert_allclose(ws[-1], sol.y[3:, -1], atol=1e-8)
    # and the linear model is not (why the plan starts from this motion)
    from scipy.linalg import expm
    x_lin = expm(lvlh_model(J, n, ka) * 2000.0) @ x0
    assert np.linalg.norm(Rotation.from_matrix(Rotation.from_rotvec(x_lin[:3]).as_matrix().T @ R_ref).as_rotvec()) > 0.2


def _relative_rhs_exact(x, n, r, rho, speed):
    """`_relative_rhs` with the rotation vector's kinematics (ṗ from ω_rel), for an ODE solver."""
    from fsw.estimation.rotations import so3_right_jacobian

    rhs = _relative_rhs(x, n, r, rho, speed)
    Jr = so3_right_jacobian(x[:3])
    return np.concatenate((np.linalg.solve(Jr, x[3:]), rhs[3:]))


@pytest.mark.parametrize("prediction", ["linear", "nonlinear"])
def test_small_angles_plan_the_same_either_way(prediction):
    """Near the target the nonlinear plan's model is the LVLH linearisation: the same decisions."""
    b_o = np.array((20e-6, 2e-6, 10e-6))
    R = dcm_from_euler_zyx(0.05, -0.04, 0.02)
    att = AttitudeInput(R, np.array([0.0, 3e-4, -3e-4]), R.T @ b_o, lambda t: np.tile(b_o, (len(t), 1)))
    ref = DiscreteController(ControllerConfig(law="mpc", prediction="linear")).decide(0.0, att)
    got = DiscreteController(ControllerConfig(law="mpc", prediction=prediction)).decide(0.0, att)
    assert [(k.polarity, k.width_s) for k in got] == [(k.polarity, k.width_s) for k in ref]


def _impulse_energy_J(w_rel, cmds, b_body):
    """Change of the pitch/yaw libration's kinetic energy by the first pulses' angular impulse ΔL (body
    axes): ω·ΔL + ½ΔLᵀJ⁻¹ΔL over y and z (the potential does not change in the instant of an impulse)."""
    dL = np.zeros(3)
    for k in cmds:
        if k.polarity:
            dL += k.polarity * k.width_s * magnet_moment_Nm(15.0 * (np.array([0, 0, 1.0]) if k.channel == 0
                                                                    else np.array([0, 1.0, 0])), b_body)
    return float(w_rel[1:] @ dL[1:] + 0.5 * dL[1:] @ (dL[1:] / J[1:]))  # pitch and yaw


def test_away_from_the_target_no_pulse_adds_libration_energy():
    """Swings of 0.1-0.8 rad with rates of a few 1e-4 rad/s: the plan alone (no guard) picks pulses that
    add energy in most of them (it counts on later pulses, timed on its model's field, to take it out
    again); with the guard no chosen pulse adds energy."""
    rng = np.random.default_rng(3)
    b_o = np.array((20e-6, 2e-6, 10e-6))
    free, guarded = (DiscreteController(ControllerConfig(law="mpc")),
                     DiscreteController(ControllerConfig(law="mpc", energy_guard_rad=0.2)))
    added = 0
    for _ in range(12):
        ypr = rng.uniform(-0.8, 0.8, 3) * np.array([1.0, 1.0, 0.3])
        w = rng.normal(0.0, 4e-4, 3)
        R = dcm_from_euler_zyx(*ypr)
        att = AttitudeInput(R, w, R.T @ b_o, lambda t: np.tile(b_o, (len(t), 1)))
        added += _impulse_energy_J(w, free.decide(0.0, att), att.b_body_T) > 0.0
        assert _impulse_energy_J(w, guarded.decide(0.0, att), att.b_body_T) <= 1e-7  # J
    assert added >= 8
