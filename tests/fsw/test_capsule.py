"""Capsule driver against the kit emulator: motor opening, spring closing, end switches, faults, energy."""
import pytest

from fsw.drivers.capsule import Capsule, CapsuleState
from fsw.drivers.gpio import line
from fsw.drivers.stepper import FAULT_SHUTTER_STUCK, FAULT_SWITCH_DISAGREE, MOTOR_POWER_W
from hil.deorbit_kit import DeorbitKitEmulator

DT = 0.1


def run_until(kit, cap, t0, done, limit_s=10.0):
    t = t0
    while not done() and t < t0 + limit_s:
        t += DT
        kit.advance_to(t)
        cap.update(t)
    return t


def fresh(channel=1):
    kit = DeorbitKitEmulator()
    cap = Capsule(kit, channel)
    kit.advance_to(0.0)
    cap.update(0.0)
    return kit, cap


def test_opens_in_two_seconds_with_motor_energy_and_closes_by_spring_for_free():
    kit, cap = fresh()
    emu = kit.channels[1]
    assert cap.closed and cap.state is CapsuleState.CLOSED
    assert cap.open(0.0) and cap.state is CapsuleState.OPENING and cap.motor_on
    assert not cap.closed
    t = run_until(kit, cap, 0.0, lambda: cap.state is CapsuleState.OPEN)
    assert t == pytest.approx(2.0, abs=DT + 1e-9)
    assert emu.shutter == 1.0 and not emu.drive and not cap.motor_on  # the gear holds it open
    assert cap.energy_J == pytest.approx(MOTOR_POWER_W * 2.0, abs=MOTOR_POWER_W * DT)  # the paper's 23.4 J
    assert cap.energy_J == pytest.approx(emu.shutter_energy_J, abs=MOTOR_POWER_W * DT)
    assert kit.dipole_body_Am2() == pytest.approx([0.0, 15.0, 0.0])  # yaw magnet along +y at home
    # held open: no energy
    e_open = cap.energy_J
    t2 = run_until(kit, cap, t, lambda: False, limit_s=30.0)
    assert cap.energy_J == e_open and cap.state is CapsuleState.OPEN
    assert cap.close(t2) and cap.state is CapsuleState.CLOSING
    t3 = run_until(kit, cap, t2, lambda: cap.state is CapsuleState.CLOSED)
    assert t3 - t2 == pytest.approx(0.5, abs=DT + 1e-9)
    assert cap.closed and cap.energy_J == e_open and cap.openings == 1
    assert not emu.release  # the spring holds it closed, the latch is off again
    assert kit.dipole_body_Am2() == pytest.approx([0.0, 0.0, 0.0])


def test_open_is_refused_unless_closed_and_close_is_idempotent():
    kit, cap = fresh()
    assert cap.close(0.0) and cap.state is CapsuleState.CLOSED
    cap.open(0.0)
    assert not cap.open(0.1)
    assert cap.openings == 1


def test_close_while_opening_reverses_at_once():
    kit, cap = fresh()
    cap.open(0.0)
    t = run_until(kit, cap, 0.0, lambda: False, limit_s=1.0)
    cap.close(t)
    assert not kit.channels[1].drive and kit.channels[1].release
    run_until(kit, cap, t, lambda: cap.closed)
    assert cap.closed


def test_shutter_stuck_half_open_is_a_fault_and_the_spring_is_released():
    kit, cap = fresh()
    kit.inject(1, "stuck", 0.5)
    cap.open(0.0)
    t = run_until(kit, cap, 0.0, lambda: cap.state is CapsuleState.FAULT)
    assert cap.fault == FAULT_SHUTTER_STUCK and 4.0 < t <= 4.0 + 2 * DT
    emu = kit.channels[1]
    assert emu.shutter == 0.5 and emu.release and not emu.drive
    assert kit.dipole_body_Am2() == pytest.approx([0.0, 7.5, 0.0])  # half the dipole out
    assert not cap.clear_fault(t)  # the switches do not say closed: stays in FAULT
    assert cap.state is CapsuleState.FAULT and not cap.closed


def test_closed_switch_stuck_on_is_caught_at_the_next_opening():
    kit, cap = fresh()
    kit.inject(1, "switch", ("closed", True))
    cap.open(0.0)
    t = run_until(kit, cap, 0.0, lambda: cap.state is CapsuleState.FAULT)
    assert cap.fault == FAULT_SWITCH_DISAGREE and t <= 0.5 + 2 * DT
    assert "closed switch" in cap.last_error
    # the spring takes the shutter back; once the (lying) switch agrees it can be cleared
    run_until(kit, cap, t, lambda: kit.channels[1].shutter == 0.0)
    assert cap.clear_fault(t + 1.0) and cap.closed


def test_open_switch_stuck_on_at_rest_is_a_disagreement():
    kit, cap = fresh()
    kit.inject(1, "switch", ("open", True))
    kit.advance_to(0.1)
    cap.update(0.1)
    assert cap.state is CapsuleState.FAULT and cap.fault == FAULT_SWITCH_DISAGREE and not cap.closed


def test_open_switch_dead_times_out_then_spring_closes_and_fault_clears():
    kit, cap = fresh()
    kit.inject(1, "switch", ("open", False))
    cap.open(0.0)
    t = run_until(kit, cap, 0.0, lambda: cap.state is CapsuleState.FAULT)
    assert cap.fault == FAULT_SHUTTER_STUCK
    t = run_until(kit, cap, t, lambda: kit.channels[1].shutter == 0.0)
    kit.clear_faults()
    assert cap.clear_fault(t) and cap.state is CapsuleState.CLOSED and cap.fault == 0


def test_closing_timeout_when_the_spring_cannot_close():
    kit, cap = fresh()
    cap.open(0.0)
    t = run_until(kit, cap, 0.0, lambda: cap.state is CapsuleState.OPEN)
    kit.inject(1, "stuck", 1.0)  # jammed open
    cap.close(t)
    t2 = run_until(kit, cap, t, lambda: cap.state is CapsuleState.FAULT)
    assert cap.fault == FAULT_SHUTTER_STUCK and t2 - t == pytest.approx(2.0 + DT, abs=DT + 1e-9)


def test_gpio_failure_never_raises_and_timeouts_still_run():
    kit, cap = fresh()
    cap.open(0.0)
    kit.inject(1, "gpio")
    t = run_until(kit, cap, 0.0, lambda: cap.state is CapsuleState.FAULT)
    assert cap.fault == FAULT_SHUTTER_STUCK and cap.io_errors > 0 and t < 5.0


@pytest.mark.parametrize("shutter", [1.0, 0.4])
def test_a_capsule_found_open_at_start_is_closed_by_the_spring_not_taken_for_a_fault(shutter):
    """The flight software restarted with the capsule open (or half-way, the gear holding it): the new
    driver's first update sees the closed switch off and closes it as `close` does."""
    kit, old = fresh()
    emu = kit.channels[1]
    old.open(0.0)
    t = run_until(kit, old, 0.0, lambda: emu.shutter >= shutter)
    kit.write_output(line(1, "shutter_drive"), False)  # the old flight software stops: its motor line drops
    kit.advance_to(t + 1.0)
    assert emu.shutter >= shutter - 0.06 and kit.dipole_body_Am2()[1] > 0.3 * 15.0
    cap = Capsule(kit, 1)  # the new flight software's
    cap.update(t + 1.0)
    assert cap.state is CapsuleState.CLOSING and cap.found_open == 1 and cap.fault == 0
    t2 = run_until(kit, cap, t + 1.0, lambda: cap.state is CapsuleState.CLOSED)
    assert cap.closed and t2 - (t + 1.0) <= 0.5 + DT + 1e-9 and cap.energy_J == 0.0
    assert kit.dipole_body_Am2() == pytest.approx([0.0, 0.0, 0.0])


def test_a_capsule_closed_at_start_is_left_alone():
    kit, cap = fresh()
    assert cap.closed and cap.found_open == 0 and cap.last_error == ""
