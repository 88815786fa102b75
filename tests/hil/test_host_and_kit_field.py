"""What the magnetometer measures besides the Earth's field: the host's iron and the kit's magnets."""
import dataclasses

import numpy as np
import pytest

from hil import scenario
from hil.deorbit_kit import DeorbitKitEmulator
from hil.deorbit_sim import DeorbitSimulator
from hil.host_magnetics import HostMagnetics
from hil.kit_field import KitFieldAtSensor, dipole_field_T
from hil.sim import Simulator

UT = 1e-6


def test_measurement_is_soft_iron_times_truth_plus_hard_iron_with_its_drift():
    S = np.array([[1.05, 0.02, -0.03], [0.01, 0.96, 0.04], [-0.02, 0.03, 1.08]])
    host = HostMagnetics(np.array([30.0, -45.0, 12.0]) * UT, S, np.array([1.0, 0.0, -0.5]) * UT, 5400.0, 0.0)
    b = np.array([20.0, -10.0, 35.0]) * UT
    # by hand: S b + h0 at t = 0 (sin 0 = 0); a quarter period later the drift is at its crest
    np.testing.assert_allclose(host.measured_T(b, 0.0), S @ b + [30e-6, -45e-6, 12e-6], rtol=0, atol=1e-15)
    np.testing.assert_allclose(host.measured_T(b, 1350.0) - host.measured_T(b, 0.0), [1e-6, 0, -0.5e-6],
                               rtol=0, atol=1e-15)
    np.testing.assert_allclose(host.true_from_measured_T(host.measured_T(b, 77.0), 77.0), b, rtol=0, atol=1e-15)
    many = np.tile(b, (4, 1))
    assert host.measured_T(many, np.arange(4.0)).shape == (4, 3)


def test_host_drift_period_defaults_to_the_orbit():
    scn = dataclasses.replace(scenario.load("isoi"),
                              host=HostMagnetics(drift_T=np.array([1.0, 0, 0]) * UT))
    sim = Simulator(scn)
    assert sim.host.drift_period_s == pytest.approx(sim.orbit.period_s)


def test_the_chip_sees_the_host_and_the_truth_does_not():
    base = scenario.load("isoi")
    S = np.diag([1.1, 0.95, 1.0])
    scn = dataclasses.replace(base, host=HostMagnetics(np.array([40.0, 0.0, -20.0]) * UT, S))
    sim = Simulator(scn)
    sim.advance_to(1.0)
    tr = sim.truth(0.5)
    np.testing.assert_allclose(sim.measured_field_T(0.5), S @ tr.b_body_T + [40e-6, 0, -20e-6], rtol=0, atol=1e-15)
    plain = Simulator(base)
    plain.advance_to(1.0)
    np.testing.assert_array_equal(plain.truth(0.5).b_body_T, tr.b_body_T)   # the truth is the Earth's field


@pytest.mark.parametrize("table,message", [
    ({"hard_iron_uT": [300.0, 0.0, 0.0]}, "hard iron"),
    ({"soft_iron": [[1.0, 0.0], [0.0, 1.0]]}, "shape"),
    ({"soft_iron": [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]}, "identity"),
    ({"hard_iron_uT": ["1", 0.0, 0.0]}, "not strings"),
    ({"hard_iron": [1.0, 0.0, 0.0]}, "unknown key"),
    ({"drift_period_s": -5.0}, "drift_period_s"),
])
def test_bad_host_tables_are_refused(tmp_path, table, message):
    import json
    text = (scenario.SCENARIO_DIR / "isoi.toml").read_text().split("\n[host]")[0] + "\n[host]\n" + "".join(
        f"{k} = {json.dumps(v)}\n" for k, v in table.items())
    p = tmp_path / "host.toml"
    p.write_text(text)
    with pytest.raises(scenario.ScenarioError, match=message):
        scenario.load(str(p))


def test_dipole_formula_by_hand():
    """15 A·m² at 0.3 m: on the axis μ0/(4π)·2m/r³ = 1e-7·30/0.027 = 111.1 µT, across it half, opposite."""
    m = np.array([0.0, 0.0, 15.0])
    np.testing.assert_allclose(dipole_field_T(m, [0, 0, 0.3]), [0, 0, 111.111e-6], rtol=1e-4, atol=1e-12)
    np.testing.assert_allclose(dipole_field_T(m, [0, 0, -0.3]), [0, 0, 111.111e-6], rtol=1e-4, atol=1e-12)
    np.testing.assert_allclose(dipole_field_T(m, [0.3, 0, 0]), [0, 0, -55.556e-6], rtol=1e-4, atol=1e-12)


def test_kit_field_follows_rotor_and_shutter():
    kit = DeorbitKitEmulator()
    # pitch magnet 0.3 m along +z from the sensor: its home axis is +z, so on its axis
    f = KitFieldAtSensor(kit, [(0.0, 0.0, 0.3), (5.0, 0.0, 0.0)], leakage=0.02)
    far = dipole_field_T(0.02 * 15.0 * np.array([0, 1.0, 0]), [-5.0, 0, 0])   # the yaw magnet, 5 m away
    np.testing.assert_allclose(f.b_body_T() - far, [0, 0, 0.02 * 111.111e-6], rtol=1e-4, atol=1e-12)   # closed: leakage
    kit.channels[0].shutter = 0.5
    np.testing.assert_allclose(f.b_body_T() - far, [0, 0, 0.51 * 111.111e-6], rtol=1e-4, atol=1e-12)   # half open
    kit.channels[0].shutter = 1.0
    np.testing.assert_allclose(f.b_body_T() - far, [0, 0, 111.111e-6], rtol=1e-4, atol=1e-12)          # open
    kit.channels[0].rotor_steps = 100   # half a turn: the polarity flips
    np.testing.assert_allclose(f.b_body_T() - far, [0, 0, -111.111e-6], rtol=1e-4, atol=1e-12)
    kit.channels[0].rotor_steps = 50    # a quarter turn: Rx(90°) z = −y, across the axis
    np.testing.assert_allclose(f.b_body_T() - far, [0, 55.556e-6, 0], rtol=1e-4, atol=1e-12)


def test_deorbit_simulator_adds_the_magnets_to_the_measurement():
    scn = scenario.load("amds_deorbit")
    sim = DeorbitSimulator(scn)
    sim.advance_to(0.1)
    closed = sim.measured_field_T(0.1) - sim.host.measured_T(sim.truth(0.1).b_body_T, 0.1)
    spec = scn.deorbit
    expect = sum(dipole_field_T(spec.capsule_leakage * 15.0 * np.array(ax), -np.array(p))
                 for ax, p in (((0, 0, 1.0), spec.pitch_magnet_position_m), ((0, 1.0, 0), spec.yaw_magnet_position_m)))
    np.testing.assert_allclose(closed, expect, rtol=1e-9, atol=1e-15)
    sim.kit.channels[0].shutter = 1.0
    opened = sim.measured_field_T(0.1) - sim.host.measured_T(sim.truth(0.1).b_body_T, 0.1)
    assert 40e-6 < np.linalg.norm(opened) < 120e-6   # tens of µT: two to five times the Earth's field
