"""Stepper driver against the kit emulator: motion profile, homing, stall detection, timeouts, energy."""
import math

import numpy as np
import pytest

from fsw.drivers.gpio import DigitalLines, GpioError
from fsw.drivers.stepper import (
    FAULT_STALL,
    FAULT_SWITCH_DISAGREE,
    FAULT_TIMEOUT,
    MAX_SPEED_SPS,
    MOTOR_POWER_W,
    MagnetState,
    Stepper,
    StepperLimits,
    profile_duration_s,
    profile_position,
)
from hil.deorbit_kit import DeorbitKitEmulator

DT = 0.1  # the 10 Hz loop of the benchmark


def run(kit, stepper, t0, t1, dt=DT):
    """Advance emulator and driver in lockstep from t0 (exclusive) to t1; returns the last time."""
    t = t0
    for k in range(1, int(round((t1 - t0) / dt)) + 1):
        t = t0 + k * dt
        kit.advance_to(t)
        stepper.update(t)
    return t


def run_until(kit, stepper, t0, done, limit_s=60.0, dt=DT):
    t = t0
    while not done() and t < t0 + limit_s:
        t += dt
        kit.advance_to(t)
        stepper.update(t)
    return t


def homed(kit=None, rotor=0):
    kit = kit or DeorbitKitEmulator()
    kit.channels[0].rotor_steps = rotor
    st = Stepper(kit, 0)
    assert st.home(0.0)
    t = run_until(kit, st, 0.0, lambda: st.state is MagnetState.IDLE)
    return kit, st, t


def test_emulator_implements_the_protocol():
    assert isinstance(DeorbitKitEmulator(), DigitalLines)


def test_half_turn_profile_takes_the_papers_second():
    lim = StepperLimits()
    assert profile_duration_s(100, lim.speed_sps, lim.accel_sps2) == pytest.approx(1.0)
    # a short move never reaches cruise speed: triangular, 2 sqrt(d/a)
    assert profile_duration_s(4, lim.speed_sps, lim.accel_sps2) == pytest.approx(2 * math.sqrt(4 / 625))


@pytest.mark.parametrize("steps", [3, 20, 100, 200, 437])
def test_profile_respects_speed_and_acceleration_limits(steps):
    lim = StepperLimits()
    T = profile_duration_s(steps, lim.speed_sps, lim.accel_sps2)
    t = np.linspace(0, T, 4001)
    x = np.array([profile_position(ti, steps, lim.speed_sps, lim.accel_sps2) for ti in t])
    v = np.gradient(x, t)
    a = np.diff(v) / np.diff(t)
    assert x[0] == 0 and x[-1] == steps and np.all(np.diff(x) >= -1e-9)
    assert v.max() <= lim.speed_sps * (1 + 1e-3)
    assert np.abs(a[5:-5]).max() <= lim.accel_sps2 * 1.05


def test_speed_limit_is_500_rpm():
    assert MAX_SPEED_SPS == pytest.approx(500 * 200 / 60)
    StepperLimits(speed_sps=MAX_SPEED_SPS)
    with pytest.raises(ValueError):
        StepperLimits(speed_sps=MAX_SPEED_SPS + 1)
    with pytest.raises(ValueError):
        StepperLimits(home_window_steps=4)


@pytest.mark.parametrize("rotor", [0, 1, -2, 3, 57, 100, 199])
def test_homing_finds_the_centre_of_the_switch_window(rotor):
    kit, st, t = homed(rotor=rotor)
    assert st.state is MagnetState.IDLE and st.position_steps == 0 and st.polarity == 1
    assert kit.channels[0].rotor_steps % 200 == 0
    assert st.homings == 1 and st.fault == 0
    # energy: 11.7 W while the winding is enabled, the same as the emulator's truth
    assert st.energy_J == pytest.approx(kit.channels[0].stepper_energy_J, rel=1e-9)
    assert t < 25.0  # one turn at two steps per 0.1 s


def test_half_turn_flips_polarity_in_one_second_for_11_7_joules():
    kit, st, t0 = homed()
    e0 = st.energy_J
    assert st.move(100, t0)
    t = run_until(kit, st, t0, lambda: not st.moving)
    assert st.state is MagnetState.IDLE and st.polarity == -1 and st.position_steps == 100
    assert kit.channels[0].rotor_steps == 100 and st.turns == 1
    assert t - t0 == pytest.approx(1.1, abs=1e-9)  # 1.0 s of motion, checked at the next tick
    assert st.energy_J - e0 == pytest.approx(MOTOR_POWER_W * 1.0, rel=1e-6)  # the paper's 11.7 J a turn
    assert st.energy_J == pytest.approx(kit.channels[0].stepper_energy_J, rel=1e-9)  # = the truth
    assert kit.channels[0].enable is False  # winding off at rest
    assert st.move(100, t) and run_until(kit, st, t, lambda: not st.moving)
    assert st.polarity == 1 and st.steps_total >= 200


def test_backwards_move_and_counts():
    kit, st, t0 = homed()
    steps0 = st.steps_total
    assert st.move(-25, t0)
    run_until(kit, st, t0, lambda: not st.moving)
    assert st.position_steps == 175 and kit.channels[0].rotor_steps == -25
    assert st.steps_total - steps0 == 25 and st.polarity == 0


def test_total_stall_is_detected_at_once():
    kit, st, t0 = homed()
    kit.inject(0, "stall", 1.0)  # no step moves the rotor: the home switch stays closed
    st.move(100, t0)
    run_until(kit, st, t0, lambda: not st.moving)
    assert st.state is MagnetState.FAULT and st.fault == FAULT_STALL and st.stalls == 1
    assert kit.channels[0].missed_steps == 100


def test_partial_stall_is_caught_when_home_should_be_reached():
    kit, st, t0 = homed()
    kit.inject(0, "stall", 0.2)  # one pulse in five lost
    st.move(100, t0)
    t = run_until(kit, st, t0, lambda: not st.moving)
    assert st.state is MagnetState.IDLE  # 80 steps away from home: the switch cannot tell
    st.move(100, t)
    run_until(kit, st, t, lambda: not st.moving)
    assert st.state is MagnetState.FAULT and st.fault & FAULT_STALL
    assert st.polarity == 0
    # recovery: clear, re-home (the rotor turns again once the fault is gone), position known again
    kit.clear_faults()
    st.clear_fault()
    assert st.state is MagnetState.UNHOMED and st.home(t + 1)
    run_until(kit, st, t + 1, lambda: not st.moving)
    assert st.state is MagnetState.IDLE and kit.channels[0].rotor_steps % 200 == 0


def test_homing_with_a_dead_home_switch_faults_instead_of_turning_forever():
    kit = DeorbitKitEmulator()
    kit.inject(0, "switch", ("home", False))
    st = Stepper(kit, 0)
    st.home(0.0)
    run_until(kit, st, 0.0, lambda: not st.moving)
    assert st.state is MagnetState.FAULT and st.fault == FAULT_STALL
    assert st.steps_total <= 200 + 5 + 4


def test_homing_with_a_switch_stuck_closed_faults():
    kit = DeorbitKitEmulator()
    kit.inject(0, "switch", ("home", True))
    st = Stepper(kit, 0)
    st.home(0.0)
    run_until(kit, st, 0.0, lambda: not st.moving)
    assert st.state is MagnetState.FAULT and st.fault == FAULT_SWITCH_DISAGREE | FAULT_STALL


def test_a_lying_home_switch_after_a_turn_is_a_stall():
    kit, st, t0 = homed()
    kit.inject(0, "switch", ("home", True))
    st.move(100, t0)
    run_until(kit, st, t0, lambda: not st.moving)
    assert st.state is MagnetState.FAULT and st.fault == FAULT_STALL


def test_gpio_failure_never_raises_and_ends_in_timeout():
    kit, st, t0 = homed()
    kit.inject(0, "gpio")
    assert st.move(100, t0)
    run(kit, st, t0, t0 + 3.0)
    assert st.state is MagnetState.FAULT and st.fault & FAULT_TIMEOUT
    assert st.io_errors >= 10 and "GpioError" in st.last_error


def test_commands_refused_out_of_state():
    kit = DeorbitKitEmulator()
    st = Stepper(kit, 0)
    assert st.state is MagnetState.UNHOMED and st.polarity == 0
    assert not st.move(100, 0.0)  # position unknown
    kit, st, t0 = homed()
    assert st.move(0, t0) and st.state is MagnetState.IDLE  # nothing to do
    assert not st.move(1.5, t0)
    assert st.move(100, t0)
    assert not st.move(100, t0) and not st.home(t0)  # busy
    st.stop(t0 + 0.5)
    assert st.state is MagnetState.IDLE and not st.moving


def test_expected_home_switch_window():
    st = Stepper(DeorbitKitEmulator(), 0)
    assert [st.expected_home_switch(p) for p in (0, 1, 199, 2, 198, 3, 197, 100)] == \
        [True, True, True, None, None, False, False, False]


class RaisingLines:
    """Every operation raises something unexpected."""

    def read_input(self, line):
        raise OSError("bus gone")

    def write_output(self, line, level):
        raise RuntimeError("odd")

    def pulse_output(self, line, count):
        raise GpioError("no timer")


def test_driver_survives_any_exception_and_gives_up_after_ten_failing_updates():
    st = Stepper(RaisingLines(), 1)
    st.home(0.0)
    for k in range(1, 30):
        st.update(k * DT)
    assert st.state is MagnetState.FAULT and st.fault & FAULT_TIMEOUT
    assert 10 < st.io_errors <= 12  # the read in home(), ten updates, the final enable write
    assert "lines failing" in st.last_error
