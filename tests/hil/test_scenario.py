"""Scenario files: the shipped ones load with the papers' numbers; bad files give clear errors."""
import numpy as np
import pytest

from hil import scenario


def test_shipped_scenarios_carry_the_papers_numbers():
    assert {"isoi", "aist2d", "amds"} <= set(scenario.scenario_names())
    a = scenario.load("aist2d")
    np.testing.assert_array_equal(np.diag(a.inertia_kgm2), [175, 200, 285])   # sedelnikov2023
    assert a.mass_kg == 530
    assert max(np.abs(p.moment_Nm).max() for p in a.torques) == pytest.approx(0.2)
    m = scenario.load("amds")
    np.testing.assert_array_equal(np.diag(m.inertia_kgm2), [17.995, 20.711, 15.269])  # lapkhanov2019
    assert m.altitude_m == pytest.approx(600e3)
    i = scenario.load("isoi")
    assert i.altitude_m == pytest.approx(485e3) and i.inclination_deg == 97.5          # sedelnikov2024
    assert i.noise_T == 0.0 and scenario.load("isoi_disturbed").noise_T == pytest.approx(1.5e-6)
    assert 8.0 < np.degrees(np.linalg.norm(i.omega0_radps)) < 12.0                    # ~10 deg/s


def test_torque_schedule_sums_active_pulses():
    a = scenario.load("aist2d")
    np.testing.assert_array_equal(a.moment_Nm(0.0), 0.0)
    np.testing.assert_array_equal(a.moment_Nm(61.0), [0.2, 0, 0])
    np.testing.assert_array_equal(a.moment_Nm(120.0), 0.0)   # the pulse ends at start + duration


BASE = (scenario.SCENARIO_DIR / "isoi.toml").read_text()


@pytest.mark.parametrize("edit,message", [
    (("inertia_kgm2 = [[0.058, 0.0, 0.0], [0.0, 0.058, 0.0], [0.0, 0.0, 0.011]]",
      "inertia_kgm2 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 3.0]]"), "triangle"),
    (("inertia_kgm2 = [[0.058, 0.0, 0.0], [0.0, 0.058, 0.0], [0.0, 0.0, 0.011]]",
      "inertia_kgm2 = [[0.058, 0.01, 0.0], [0.0, 0.058, 0.0], [0.0, 0.0, 0.011]]"), "symmetric"),
    (("bandwidth_hz = 100", "bandwidth_hz = 150"), "bandwidth_hz"),
    (("sample_rate_hz = 1.0", "sample_rate_hz = 2000.0"), "sample_rate_hz"),
    (("noise_uT = 0.0", "noise_ut = 0.0"), "unknown key"),
    (("altitude_km = 485.0", "altitude_km = \"high\""), "altitude_km"),
    (("omega_dps = [6.0, -5.0, 6.5]", "omega_dps = [6.0, -5.0]"), "omega_dps"),
])
def test_bad_scenarios_rejected_with_the_key_named(tmp_path, edit, message):
    p = tmp_path / "bad.toml"
    assert edit[0] in BASE
    p.write_text(BASE.replace(edit[0], edit[1]))
    with pytest.raises(scenario.ScenarioError, match=message) as e:
        scenario.load(str(p))
    assert str(p) in str(e.value)


def test_unknown_name_lists_the_shipped_ones():
    with pytest.raises(scenario.ScenarioError, match="isoi"):
        scenario.load("no-such-scenario")


ORBIT = "[orbit]\naltitude_km = 485.0\ninclination_deg = 97.5\nraan_deg = 40.0\narg_lat0_deg = 0.0\n"
TORQUE = '\n[[torque]]\nstart_s = 10.0\nduration_s = 5.0\nmoment_Nm = [0.2, 0.0, 0.0]\n'


@pytest.mark.parametrize("text, key, words", [
    pytest.param(BASE + TORQUE.replace("start_s = 10.0", 'start_s = "10"'), "torque[0].start_s", "not a string",
                 id="time as a string"),
    pytest.param(BASE + TORQUE.replace("duration_s = 5.0", "duration_s = true"), "torque[0].duration_s",
                 "finite number", id="time as a boolean"),
    pytest.param(BASE + TORQUE.replace("[0.2, 0.0, 0.0]", '["0.2", 0.0, 0.0]'), "torque[0].moment_Nm",
                 "3 finite numbers", id="moment as strings"),
    pytest.param("torque = 5\n" + BASE, "torque", "array of tables", id="torque a scalar"),
    pytest.param(BASE + "\n[torque]\nstart_s = 1.0\nduration_s = 1.0\nmoment_Nm = [1.0, 0.0, 0.0]\n", "torque",
                 "array of tables", id="torque a single table"),
    pytest.param(BASE.replace("omega_dps = [6.0, -5.0, 6.5]", 'omega_dps = ["6.0", -5.0, 6.5]'), "initial.omega_dps",
                 "not strings", id="vector with a string"),
    pytest.param(BASE.replace("omega_dps = [6.0, -5.0, 6.5]", "omega_dps = [true, -5.0, 6.5]"), "initial.omega_dps",
                 "not strings", id="vector with a boolean"),
    pytest.param(BASE.replace("omega_dps = [6.0, -5.0, 6.5]", "omega_dps = 6.0"), "initial.omega_dps",
                 "expected list", id="vector a scalar"),
    pytest.param(BASE + '\n[deorbit]\nsail_area_m2 = "5"\n', "deorbit.sail_area_m2", "not strings",
                 id="deorbit number as a string"),
    pytest.param(BASE + '\n[deorbit]\ninitial_ypr_deg = [60, "45", 0]\n', "deorbit.initial_ypr_deg", "not strings",
                 id="deorbit vector with a string"),
    pytest.param("deorbit = 3\n" + BASE, "[deorbit]", "must be a table", id="deorbit a scalar"),
    pytest.param("orbit = 485.0\n" + BASE.replace(ORBIT, ""), "[orbit]", "must be a table", id="orbit a scalar"),
    pytest.param('name = 5\n' + BASE.replace('name = "isoi"', ""), "name", "expected a string", id="name a number"),
])
def test_wrong_kinds_of_values_are_refused_with_the_key_named(tmp_path, text, key, words):
    """A number written as a string was read as a number (or raised a TypeError); a scalar where a
    table belongs raised a TypeError."""
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(scenario.ScenarioError) as e:
        scenario.load(str(p))
    assert f"{p}: {key}: " in str(e.value) and words in str(e.value)


@pytest.mark.parametrize("old, new, key", [
    pytest.param("mass_kg = 5.5", "mass_kg = 1" + "0" * 400, "body.mass_kg", id="number no float holds"),
    pytest.param("omega_dps = [6.0, -5.0, 6.5]", "omega_dps = [6.0, -5.0, 1" + "0" * 400 + "]", "initial.omega_dps",
                 id="in a vector"),
    pytest.param("mass_kg = 5.5", "mass_kg = " + "9" * 5000, "not valid TOML", id="5000 digits"),
    pytest.param("mass_kg = 5.5", "mass_kg = " + "[" * 5000 + "]" * 5000, "nested too deeply", id="nested 5000 deep"),
    pytest.param("bridge_offset_uT = [1.2, -0.8, 0.5]", "bridge_offset_uT = [1.2, -0.8, 0.5]\n[[torque]]\nstart_s = 1"
                 + "0" * 400 + "\nduration_s = 1.0\nmoment_Nm = [0.1, 0.0, 0.0]", "torque[0].start_s",
                 id="pulse start no float holds"),
])
def test_numbers_and_nesting_no_float_or_parser_can_hold_are_scenario_errors(tmp_path, old, new, key):
    """Found by the fuzz (tests/test_fuzz_readers.py): these raised OverflowError, ValueError and
    RecursionError, which the tools do not catch (a traceback)."""
    p = tmp_path / "bad.toml"
    assert old in BASE
    p.write_text(BASE.replace(old, new))
    with pytest.raises(scenario.ScenarioError) as e:
        scenario.load(str(p))
    assert str(e.value).startswith(f"{p}: ") and key in str(e.value)

