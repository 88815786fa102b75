"""The kit's detumbling law (`fsw.deorbit.detumble`) against a rigid body integrated independently
(`hil.dynamics.RigidBody`): the field fixed in inertial space, the dipoles as the kit would put them
(closed while a capsule opens or a magnet turns over). Tolerances in physical units."""
import math

import numpy as np
import pytest

from fsw.deorbit.detumble import DetumbleConfig, DetumbleLaw, rotate_about, work_J
from fsw.deorbit.kit_field import DESIGN
from hil.dynamics import RigidBody

pytestmark = pytest.mark.fsw

J = np.array([[22.494, 0.35, -0.25], [0.35, 24.853, 0.30], [-0.25, 0.30, 12.215]])
B_INERTIAL_T = np.array([18e-6, -25e-6, 30e-6])
FIELD_TURN_RADPS = 2 * 1.083e-3   # the field along a polar orbit turns at about twice the orbit's rate


def b_inertial(t_s: float) -> np.ndarray:
    """The field in inertial space, turning about z as along an orbit (the law assumes it fixed over a pulse;
    a field fixed for ever would keep H·B, so no magnetic torque could take that part out)."""
    c, s = math.cos(FIELD_TURN_RADPS * t_s), math.sin(FIELD_TURN_RADPS * t_s)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ B_INERTIAL_T
AXES = [m.moment_Am2 * np.asarray(m.home_axis, float) for m in DESIGN]


class Channel:
    """What the law reads of a sequencer channel: the magnet's polarity now."""

    def __init__(self):
        self.polarity = 1


def fly(seconds: float, omega0_dps, *, invert: bool = False, sigma_dps: float = 0.0, dt: float = 0.5,
        rate_error_dps=(0.0, 0.0, 0.0)):
    """The law deciding every period on the true rate (+ `rate_error_dps`) and the true field; the kit's
    delays as in `DetumbleConfig`. Returns times and kinetic energies (every decision) and the law."""
    cfg = DetumbleConfig()
    law = DetumbleLaw(cfg, inertia_kgm2=J)
    body = RigidBody(J, np.array([1.0, 0.0, 0.0, 0.0]), np.radians(omega0_dps))
    chans = [Channel(), Channel()]
    acting = [0, 0]          # polarity acting on the body per channel (0: screened)
    live_from = [0.0, 0.0]   # when a commanded opening starts acting
    close_at = [0.0, 0.0]
    t, next_decision = 0.0, 0.0
    ts, energies = [], []
    while t < seconds:
        if t >= next_decision - 1e-9:
            b_body = body.dcm.T @ b_inertial(t)
            law.update_rate(body.omega_radps + np.radians(rate_error_dps), math.radians(sigma_dps))
            law.update_field(t, b_body)
            ts.append(t)
            energies.append(body.kinetic_energy_J())
            for cmd in law.decide(t, chans):
                i, s = cmd.channel, -cmd.polarity if invert else cmd.polarity
                if s == 0:
                    acting[i], close_at[i] = 0, t
                    continue
                if s != acting[i]:  # closed (and turned over) first: the kit's delays
                    delay = cfg.open_delay_s + (cfg.turn_delay_s if s != chans[i].polarity else 0.0)
                    live_from[i] = t + delay
                    chans[i].polarity = s
                    acting[i] = s
                close_at[i] = t + cmd.width_s
            next_decision += cfg.period_s
        p = sum(AXES[i] * acting[i] for i in range(2) if live_from[i] <= t < close_at[i])
        body.step(dt, np.cross(p, body.dcm.T @ b_inertial(t)) if np.ndim(p) else np.zeros(3))
        t += dt
    return np.array(ts), np.array(energies), law


def test_predicted_work_is_the_work_done_on_a_rigid_body():
    """∫ ω·(p × B) dt predicted from ω and B now equals the change of kinetic energy of a body that turns
    with a held dipole, within 3 % over 8 s of a 3 °/s tumble."""
    omega = np.radians([1.5, -2.0, 1.2])
    body = RigidBody(J, np.array([1.0, 0.0, 0.0, 0.0]), omega)
    p = AXES[0] * 1.0
    b0 = body.dcm.T @ B_INERTIAL_T
    predicted = work_J(body.omega_radps, b0, p, 0.0, 8.0, J, step_s=0.1)
    e0 = body.kinetic_energy_J()
    for _ in range(800):
        body.step(0.01, np.cross(p, body.dcm.T @ B_INERTIAL_T))
    assert abs(predicted) > 1e-6
    assert body.kinetic_energy_J() - e0 == pytest.approx(predicted, rel=0.03)


def test_rotate_about_is_the_body_view_of_a_fixed_vector():
    v = np.array([1.0, 2.0, -0.5])
    turned = rotate_about(v, np.array([0.0, 0.0, math.pi / 2]))
    np.testing.assert_allclose(turned, [-2.0, 1.0, -0.5], atol=1e-12)


@pytest.mark.parametrize("omega0_dps, ratio", [((2.0, -2.5, 1.5), 0.3), ((0.3, 4.5, -1.0), 0.7)])
def test_detumbling_takes_energy_out_of_the_tumble(omega0_dps, ratio):
    """From 3.5 and 4.6 °/s: √(energy) (∝ |ω| for a given axis) down to `ratio` of the start within
    2,000 s, and the energy never rises over a decision period by more than 0.1 % of the start (the kit
    never spins the tumble up)."""
    ts, e, law = fly(2000.0, omega0_dps)
    assert math.sqrt(e[-1] / e[0]) < ratio
    assert np.max(np.diff(e)) < 0.001 * e[0]
    assert law.held == 0


def test_the_opposite_polarity_spins_it_up():
    """The test can tell: the law's polarities inverted put energy in."""
    _, e, _ = fly(1000.0, (2.0, -2.5, 1.5), invert=True)
    assert e[-1] > 1.3 * e[0]


def test_an_untrusted_rate_keeps_the_capsules_closed():
    law = DetumbleLaw()
    law.update_rate(np.radians([2.0, 0.0, 0.0]), math.radians(1.0))
    law.update_field(0.0, B_INERTIAL_T)
    cmds = law.decide(1.0, [Channel(), Channel()])
    assert [c.polarity for c in cmds] == [0, 0]
    assert "rate sigma" in law.reason
    law.update_rate(np.radians([2.0, 0.0, 0.0]), math.radians(0.01))
    cmds = law.decide(100.0, [Channel(), Channel()])   # the field sample is 100 s old
    assert [c.polarity for c in cmds] == [0, 0] and "field" in law.reason
