"""The energy-descent law (`fsw.deorbit.energy_horizon`) against independent truth: scipy's integration of
the motion relative to the orbital frame with the simulator's own torques (`hil.environment`) and the
kit's moment p × B in a field that turns along the orbit."""
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from fsw.deorbit import energy_horizon as eh
from fsw.deorbit.controller import (
    AttitudeInput,
    ControllerConfig,
    DiscreteController,
    aero_stiffness_Nm_per_rad,
    discrete_moment_Nm,
)
from fsw.estimation.rotations import rotvec_from_dcm, so3_right_jacobian
from hil.environment import aero_torque_Nm, dcm_from_euler_zyx, gravity_gradient_torque_Nm
from hil.orbit import A_WGS84_M, MU_EARTH_M3S2

J = np.array([17.995, 20.711, 15.269])
R_ORBIT = A_WGS84_M + 600e3
N = math.sqrt(MU_EARTH_M3S2 / R_ORBIT**3)
RHO, SPEED = 1.454e-13, R_ORBIT * N
KA = aero_stiffness_Nm_per_rad(RHO, SPEED, 2.2, 5.58, 0.12)
SHARE = 5.0 / 5.58
DIPOLE = 15.0
T, S = 100.0, 5


def b_orbital_T(t):
    """A field that turns along the orbit like a dipole's (orbital axes) [T]."""
    u = N * np.asarray(t, float)
    return np.stack((20e-6 * np.cos(u + 0.3), 3e-6 * np.ones_like(u), 40e-6 * np.sin(u + 0.3)), axis=-1)


def _rhs(t, x, m_body):
    """Motion relative to the orbital frame, x = (rotation vector of R_bo, ω_rel), the simulator's
    gravity gradient and aerodynamic moment plus m × B."""
    R = Rotation.from_rotvec(x[:3]).as_matrix()
    w = x[3:]
    wo = R.T @ np.array([0.0, -N, 0.0])
    M = gravity_gradient_torque_Nm(R.T @ np.array([0.0, 0.0, -R_ORBIT]), np.diag(J)) + aero_torque_Nm(
        R.T @ np.array([SPEED, 0.0, 0.0]), RHO, 2.2, 5.0, np.array([1.0, 0.0, 0.0]), 0.58, np.array([-0.12, 0, 0]))
    M = M + np.cross(m_body, R.T @ b_orbital_T(t))
    wa = w + wo
    wdot = (M - np.cross(wa, J * wa)) / J + np.cross(w, wo)
    return np.concatenate((np.linalg.solve(so3_right_jacobian(x[:3]), w), wdot))


def truth_after(R0, w0, periods):
    """The state after periods of (move) from t = 0: a move is (pol_pitch, steps_pitch, pol_yaw, steps_yaw)."""
    x = np.concatenate((rotvec_from_dcm(R0), w0))
    t = 0.0
    for move in periods:
        cuts = sorted({0, move[1], move[3], S})
        for a, b in zip(cuts[:-1], cuts[1:]):
            m = np.zeros(3)
            if a < move[1]:
                m[2] += DIPOLE * move[0]
            if a < move[3]:
                m[1] += DIPOLE * move[2]
            if b > a:
                sol = solve_ivp(_rhs, (t + a * T / S, t + b * T / S), x, args=(m,), rtol=1e-9, atol=1e-12)
                x = sol.y[:, -1]
        t += T
    return Rotation.from_rotvec(x[:3]).as_matrix(), x[3:]


def energy(R, w):
    return float(eh.jacobi_energy(R, w, J, N, KA, SHARE))


START = (dcm_from_euler_zyx(math.radians(60), math.radians(45), 0.3), np.array([2e-4, -3e-4, 4e-4]))


def test_the_energy_is_the_integral_of_the_free_motion_and_least_at_the_target():
    R0, w0 = START
    E0 = energy(R0, w0)
    R1, w1 = truth_after(R0, w0, [(0, 0, 0, 0)] * 20)  # 2,000 s coasting, the simulator's torques
    e_min = energy(np.eye(3), np.zeros(3))
    assert abs(energy(R1, w1) - E0) < 1e-4 * (E0 - e_min)
    # near the target it is the LVLH libration energy ½kθ² + ½Jω²
    k_pitch = 3 * N * N * (J[0] - J[2]) + KA
    assert energy(dcm_from_euler_zyx(0.0, 0.01, 0.0), np.array([0.0, 1e-5, 0.0])) - e_min == pytest.approx(
        0.5 * k_pitch * 0.01**2 + 0.5 * J[1] * 1e-5**2, rel=1e-3)
    # the kit changes it by the work of its moment: at a high pitch rate (B_x > 0 here), the pitch magnet
    # against the rate takes energy out, with it puts energy in
    w_fast = np.array([0.0, 3e-3, 0.0])
    E_fast = energy(np.eye(3), w_fast)
    assert energy(*truth_after(np.eye(3), w_fast, [(-1, S, 0, 0)])) < E_fast
    assert energy(*truth_after(np.eye(3), w_fast, [(1, S, 0, 0)])) > E_fast


def test_predicted_sequence_energies_are_the_propagated_truths():
    R0, w0 = START
    first = eh.moves((80.0, 100.0), T, S)
    cont = eh.continuation_moves(S)
    b = b_orbital_T(T / S * (np.arange(2 * S) + 0.5))
    E = eh.sequence_energies(R0, w0, J, N, KA, SHARE, T / S, S, b, first, cont, 2, DIPOLE)
    assert E.shape == (25, 9)
    E0 = energy(R0, w0)
    rng = np.random.default_rng(3)
    for f, k in [(0, 0), (24, 8)] + [tuple(rng.integers((25, 9))) for _ in range(4)]:
        R, w = truth_after(R0, w0, [first[f], cont[k]])
        # within 2 % of what the two pulses moved (the law holds the field constant over a 20-s step)
        assert E[f, k] == pytest.approx(energy(R, w), abs=0.02 * abs(energy(R, w) - E0) + 1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_choice_is_the_move_of_least_energy_of_the_propagated_truth(seed):
    rng = np.random.default_rng(seed)
    R0 = Rotation.from_rotvec(rng.normal(size=3) * 0.5).as_matrix()
    w0 = rng.normal(size=3) * 5e-4
    b = b_orbital_T(T / S * (np.arange(S) + 0.5))
    move, worth, first, E0 = eh.choose(R0, w0, b, J=J, n=N, ka=KA, sail_share=SHARE, dipole_Am2=DIPOLE, period_s=T,
                                       substeps=S, horizon=1, widths_s=(80.0, 100.0), acting=(0, 0),
                                       polarity=(0, 0), opening_J=23.4, turn_J=11.7, energy_price=0.0, margin=0.0,
                                       deadband_J=0.0)
    truth = np.array([energy(*truth_after(R0, w0, [m])) for m in first])
    best = int(np.argmin(truth))
    assert truth[best] < E0  # some pulse takes energy out from these states
    k = int(np.flatnonzero((first == move).all(axis=1))[0])
    assert truth[k] - truth[best] <= 0.02 * (E0 - truth[best])


def test_margin_price_and_deadband_keep_the_capsules_closed():
    R0, w0 = dcm_from_euler_zyx(0.2, 0.1, 0.0), np.array([0.0, 3e-3, 0.0])
    b = b_orbital_T(T / S * (np.arange(3 * S) + 0.5))
    kw = dict(J=J, n=N, ka=KA, sail_share=SHARE, dipole_Am2=DIPOLE, period_s=T, substeps=S, horizon=3,
              widths_s=(80.0, 100.0), acting=(0, 0), polarity=(0, 0), opening_J=23.4, turn_J=11.7)
    move, worth, _, E0 = eh.choose(R0, w0, b, energy_price=0.0, margin=0.0, deadband_J=0.0, **kw)
    assert any(move[[0, 2]]) and worth.min() < worth[0]
    dead = E0 - energy(np.eye(3), np.zeros(3)) + 1e-12
    for extra in (dict(energy_price=1.0, margin=0.0, deadband_J=0.0), dict(energy_price=0.0, margin=1e6,
                  deadband_J=0.0), dict(energy_price=0.0, margin=0.0, deadband_J=dead)):
        m, *_ = eh.choose(R0, w0, b, **kw, **extra)
        assert not any(m[[0, 2]])
    # at rest on the target nothing opens
    m, *_ = eh.choose(np.eye(3), np.zeros(3), b, energy_price=1e-9, margin=0.1, deadband_J=0.0, **kw)
    assert not any(m[[0, 2]])


def test_the_sequences_joules_count_openings_and_turns():
    first = np.array([(0, 0, 0, 0), (1, 4, 0, 0), (1, 5, -1, 5)])
    cont = np.array([(0, 0, 0, 0), (1, 5, 0, 0)])
    j = eh.sequence_joules(first, cont, 2, (0, 0), (1, 1), 23.4, 11.7, S)
    assert j[0].tolist() == pytest.approx([0.0, 23.4])  # closed, then an opening at the magnet's polarity
    assert j[1].tolist() == pytest.approx([23.4, 46.8])  # an 80-s pulse closes: the next one opens again
    # pitch opened, yaw turned and opened; a full-period pitch pulse is extended by the next at no cost
    assert j[2].tolist() == pytest.approx([23.4 + 35.1, 23.4 + 35.1])
    # already open at that polarity: extending costs nothing
    assert eh.sequence_joules(first[1:2], cont, 2, (1, 0), (1, 1), 23.4, 11.7, S)[0].tolist() == pytest.approx(
        [0.0, 23.4])


def test_the_controller_law_energy_gives_eq5_pulses():
    R0, w0 = dcm_from_euler_zyx(0.2, 0.1, 0.0), np.array([0.0, 3e-3, -2e-3])
    b_o = b_orbital_T(0.0)
    att = AttitudeInput(R0, w0, R0.T @ b_o, b_orbital_T)
    cfg = ControllerConfig(law="energy", mean_motion_radps=N, aero_stiffness_Nm_per_rad=KA, energy_price_J_per_J=0.0,
                           energy_margin=0.0)
    cmds = DiscreteController(cfg).decide(0.0, att)
    assert any(c.polarity for c in cmds)
    for c in cmds:
        if c.polarity:
            assert c.width_s in (80.0, 100.0)
            assert c.width_s == pytest.approx(abs(c.m_theor_Nm) * 100.0 / c.m_ctrl_Nm, rel=1e-9)
            pol = (c.polarity, 0) if c.channel == 0 else (0, c.polarity)
            m = discrete_moment_Nm(*pol, 15.0, att.b_body_T)
            assert np.sign(m[1 + c.channel]) == np.sign(c.m_theor_Nm)
    with pytest.raises(ValueError):
        ControllerConfig(law="energy", energy_horizon=0)


def test_the_guard_flags_the_moves_that_pump_energy_into_the_propagated_truth():
    R0, w0 = np.eye(3), np.array([0.0, 3e-3, 0.0])
    b = b_orbital_T(T / S * (np.arange(S) + 0.5))
    kw = dict(J=J, n=N, ka=KA, sail_share=SHARE, dipole_Am2=DIPOLE, period_s=T, substeps=S, horizon=1)
    E0 = energy(R0, w0)
    for move in [(1, S, 0, 0), (-1, S, 0, 0), (0, 0, 1, 4), (0, 0, -1, 4)]:
        truth_pumps = energy(*truth_after(R0, w0, [move])) > E0
        assert eh.pumps(R0, w0, b, np.array(move), floor_J=0.0, **kw) == truth_pumps
        assert not eh.pumps(R0, w0, b, np.array(move), floor_J=2 * (E0 - energy(np.eye(3), np.zeros(3))), **kw)


def test_the_guard_hands_a_pumping_move_to_the_energy_law_without_looping():
    """The guard of "mpc" hands a move that pumps energy to the energy law's own choice, whatever the switch
    (which would hand it back to "mpc")."""
    rng = np.random.default_rng(0)  # a state where the linear plan's first move pumps (5 of 12 such states)
    R0 = Rotation.from_rotvec(rng.normal(size=3) * 0.6).as_matrix()
    att = AttitudeInput(R0, rng.normal(size=3) * 4e-4, R0.T @ b_orbital_T(0.0), b_orbital_T)
    both = DiscreteController(ControllerConfig(law="mpc", nonlinear_guard_rad=1e-3, energy_switch_rad=10.0,
                                               mean_motion_radps=N, aero_stiffness_Nm_per_rad=KA))
    cmds = both.decide(0.0, att)
    assert both.guarded == 1
    # the replacement does not pump, by the law's prediction
    move = [(c.polarity, int(round(c.width_s / 20.0))) for c in cmds]
    b = b_orbital_T(T / S * (np.arange(3 * S) + 0.5))
    assert not eh.pumps(att.R_bo, att.omega_rel_radps, b, np.array([*move[0], *move[1]]), J=J, n=N, ka=KA,
                        sail_share=SHARE, dipole_Am2=DIPOLE, period_s=T, substeps=S, horizon=3, floor_J=0.0)
