"""Sequencer of the de-orbit kit against the emulator: every transition, every interlock, every fault.

After every scenario the emulator's own interlock monitor (truth: a step pulse with the shutter not
fully closed, the shutter motor started while a step burst runs) and the sequencer's monitor must both
read 0."""
import pytest

from fsw.deorbit.sequencer import KitMode, Outcome, Phase, Sequencer, Source, Step
from fsw.drivers.capsule import CapsuleState
from fsw.drivers.stepper import (
    FAULT_SHUTTER_STUCK,
    FAULT_STALL,
    FAULT_SWITCH_DISAGREE,
    FAULT_TIMEOUT,
    MagnetState,
)
from hil.deorbit_kit import DeorbitKitEmulator

DT = 0.1
PITCH, YAW = 0, 1


class Rig:
    def __init__(self, home=True):
        self.kit = DeorbitKitEmulator()
        self.events = []
        self.seq = Sequencer(self.kit, on_event=self.events.append)
        self.t = 0.0
        self.seq.update(0.0)
        if home:
            for ch in (PITCH, YAW):
                assert self.seq.request_home(ch, self.t) is Outcome.STARTED
            self.run_until(lambda: all(c.stepper.state is MagnetState.IDLE for c in self.seq.channels))
            self.events.clear()

    def step(self):
        self.t = round(self.t + DT, 9)
        self.kit.advance_to(self.t)
        self.seq.update(self.t)

    def run(self, seconds):
        for _ in range(int(round(seconds / DT))):
            self.step()

    def run_until(self, done, limit_s=60.0):
        t_end = self.t + limit_s
        while not done():
            assert self.t < t_end, "timed out"
            self.step()

    def ch(self, i):
        return self.seq.channels[i]

    def phases(self, channel):
        return [(e.old, e.new) for e in self.events if e.what == "phase" and e.channel == channel]

    def assert_no_violation(self):
        assert self.kit.interlock_violations == 0, self.kit.violation_log
        assert self.seq.interlock_violations == 0


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.assert_no_violation()


def test_homing_transitions_are_reported():
    r = Rig(home=False)
    assert r.ch(PITCH).stepper.state is MagnetState.UNHOMED
    r.seq.request_home(PITCH, 0.0)
    r.run_until(lambda: not r.ch(PITCH).busy)
    assert r.phases(PITCH) == [("IDLE", "HOMING"), ("HOMING", "IDLE")]
    magnet = [(e.old, e.new) for e in r.events if e.what == "magnet" and e.channel == PITCH]
    assert magnet == [("UNHOMED", "HOMING"), ("HOMING", "IDLE")]
    assert r.ch(PITCH).polarity == 1
    r.assert_no_violation()


def test_open_hold_close_by_ground(rig):
    r = rig
    assert r.seq.request_capsule(YAW, True, r.t) is Outcome.STARTED
    assert r.ch(YAW).phase is Phase.OPENING
    r.run_until(lambda: r.ch(YAW).capsule.state is CapsuleState.OPEN)
    assert r.ch(YAW).phase is Phase.OPEN and r.ch(YAW).acting == 1
    assert r.seq.request_capsule(YAW, True, r.t) is Outcome.DONE
    r.seq.request_capsule(YAW, False, r.t)
    r.run_until(lambda: r.ch(YAW).capsule.closed)
    r.step()
    assert r.phases(YAW) == [("IDLE", "OPENING"), ("OPENING", "OPEN"), ("OPEN", "CLOSING"), ("CLOSING", "IDLE")]
    caps = [(e.old, e.new) for e in r.events if e.what == "capsule" and e.channel == YAW]
    assert caps == [("CLOSED", "OPENING"), ("OPENING", "OPEN"), ("OPEN", "CLOSING"), ("CLOSING", "CLOSED")]


def test_magnet_never_turns_while_its_capsule_is_not_closed(rig):
    r = rig
    r.seq.request_capsule(PITCH, True, r.t)
    r.step()
    pulses = r.kit.channels[PITCH].pulses
    for request in (lambda: r.seq.request_turn(PITCH, 100, r.t), lambda: r.seq.request_polarity(PITCH, -1, r.t),
                    lambda: r.seq.request_home(PITCH, r.t)):
        assert request() is Outcome.BUSY  # opening under way: the channel is busy
    r.run_until(lambda: r.ch(PITCH).capsule.state is CapsuleState.OPEN)
    r.step()
    for request in (lambda: r.seq.request_turn(PITCH, 100, r.t), lambda: r.seq.request_polarity(PITCH, -1, r.t),
                    lambda: r.seq.request_home(PITCH, r.t)):
        assert request() is Outcome.INTERLOCK  # open: rule 1
    assert r.seq.interlock_refusals == 3
    assert r.kit.channels[PITCH].pulses == pulses
    assert sum(e.what == "refused" for e in r.events) == 6


def test_capsule_never_opens_while_its_magnet_moves(rig):
    r = rig
    assert r.seq.request_polarity(YAW, -1, r.t) is Outcome.STARTED
    r.step()
    assert r.ch(YAW).stepper.moving
    assert r.seq.permit(r.ch(YAW), Step.OPEN, Source.GROUND) is Outcome.INTERLOCK  # rule 2 at the gate
    assert r.seq.request_capsule(YAW, True, r.t) is Outcome.BUSY
    assert r.kit.channels[YAW].openings == 0
    r.run_until(lambda: not r.ch(YAW).busy)
    assert r.ch(YAW).polarity == -1 and r.kit.channels[YAW].rotor_steps == 100
    assert r.seq.request_capsule(YAW, True, r.t) is Outcome.STARTED


def test_opening_an_unhomed_magnet_is_refused():
    r = Rig(home=False)
    assert r.seq.request_capsule(PITCH, True, 0.0) is Outcome.UNHOMED
    assert r.seq.request_turn(PITCH, 10, 0.0) is Outcome.UNHOMED
    r.assert_no_violation()


def test_turn_by_an_angle_and_back_through_home(rig):
    r = rig
    assert r.seq.request_turn(PITCH, 200, r.t) is Outcome.STARTED  # a full turn, home switch checked
    r.run_until(lambda: not r.ch(PITCH).busy)
    assert r.ch(PITCH).stepper.state is MagnetState.IDLE and r.ch(PITCH).polarity == 1
    assert r.kit.channels[PITCH].rotor_steps == 200
    assert r.seq.request_turn(PITCH, -50, r.t) is Outcome.STARTED
    r.run_until(lambda: not r.ch(PITCH).busy)
    assert r.ch(PITCH).stepper.position_steps == 150 and r.ch(PITCH).polarity == 0
    assert r.seq.request_polarity(PITCH, 1, r.t) is Outcome.STARTED  # forwards 50 to home
    r.run_until(lambda: not r.ch(PITCH).busy)
    assert r.ch(PITCH).polarity == 1 and r.kit.channels[PITCH].rotor_steps == 200
    assert r.seq.request_polarity(PITCH, 1, r.t) is Outcome.DONE
    assert r.seq.request_polarity(PITCH, 0, r.t) is Outcome.INVALID


def test_controller_pulse_turns_then_opens_holds_and_closes(rig):
    r = rig
    assert r.seq.start_controller(r.t) is Outcome.STARTED
    t0 = r.t
    assert r.seq.pulse(PITCH, -1, 80.0, r.t) is Outcome.STARTED
    r.run_until(lambda: r.ch(PITCH).capsule.state is CapsuleState.OPEN)
    t_open = r.t
    assert r.ch(PITCH).polarity == -1 and r.ch(PITCH).acting == -1
    r.run_until(lambda: r.ch(PITCH).phase is Phase.IDLE, limit_s=200)
    assert r.phases(PITCH) == [("IDLE", "TURNING"), ("TURNING", "OPENING"), ("OPENING", "OPEN"),
                               ("OPEN", "CLOSING"), ("CLOSING", "IDLE")]
    # exposure ≈ the width: ramps of 2 s (open) and 0.5 s (close) count half
    open_s = [e.t_s for e in r.events if e.what == "capsule" and e.new == "OPEN"][0]
    closing_s = [e.t_s for e in r.events if e.what == "capsule" and e.new == "CLOSING"][0]
    assert closing_s - open_s + 1.0 + 0.25 == pytest.approx(80.0, abs=2 * DT)
    assert t_open - t0 == pytest.approx(1.0 + 2.0, abs=3 * DT)  # turn, then open
    assert r.kit.channels[PITCH].openings == 1


def test_pulse_with_the_same_polarity_extends_without_a_new_opening(rig):
    r = rig
    r.seq.start_controller(r.t)
    r.seq.pulse(YAW, 1, 80.0, r.t)
    r.run(50.0)
    assert r.seq.pulse(YAW, 1, 80.0, r.t) is Outcome.DONE
    t_ext = r.t
    r.run_until(lambda: r.ch(YAW).phase is Phase.IDLE, limit_s=200)
    closing = [e.t_s for e in r.events if e.what == "capsule" and e.new == "CLOSING"][0]
    assert closing == pytest.approx(t_ext + 80.0, abs=2 * DT)
    assert r.kit.channels[YAW].openings == 1


def test_pulse_with_the_other_polarity_closes_turns_and_reopens(rig):
    r = rig
    r.seq.start_controller(r.t)
    r.seq.pulse(YAW, 1, 80.0, r.t)
    r.run(30.0)
    r.seq.pulse(YAW, -1, 80.0, r.t)
    r.run_until(lambda: r.ch(YAW).acting == -1 and r.ch(YAW).capsule.state is CapsuleState.OPEN)
    assert r.phases(YAW)[:2] == [("IDLE", "OPENING"), ("OPENING", "OPEN")]
    assert r.phases(YAW)[2:] == [("OPEN", "CLOSING"), ("CLOSING", "TURNING"), ("TURNING", "OPENING"),
                                             ("OPENING", "OPEN")]
    assert r.kit.channels[YAW].openings == 2


def test_the_controller_owns_the_kit(rig):
    r = rig
    r.seq.start_controller(r.t)
    assert r.seq.request_capsule(PITCH, True, r.t) is Outcome.CONTROLLER
    assert r.seq.request_turn(PITCH, 100, r.t) is Outcome.CONTROLLER
    assert r.seq.request_home(PITCH, r.t) is Outcome.CONTROLLER
    r.seq.pulse(PITCH, 1, 80.0, r.t)
    r.run(5.0)
    assert r.seq.request_capsule(PITCH, False, r.t) is Outcome.STARTED  # closing is always allowed
    r.run_until(lambda: r.ch(PITCH).capsule.closed)
    r.seq.pulse(PITCH, 1, 80.0, r.t)
    r.run(5.0)
    assert r.seq.stop_controller(r.t) is Outcome.STARTED and r.seq.mode is KitMode.OFF
    r.run_until(lambda: r.ch(PITCH).capsule.closed)
    assert r.seq.pulse(PITCH, 1, 80.0, r.t) is Outcome.INVALID  # no pulses unless running


def test_safe_mode_closes_everything_and_refuses_motion(rig):
    r = rig
    r.seq.start_controller(r.t)
    r.seq.pulse(PITCH, 1, 80.0, r.t)
    r.seq.pulse(YAW, -1, 80.0, r.t)
    r.run(2.0)
    assert r.ch(YAW).stepper.moving or r.ch(YAW).capsule.state is not CapsuleState.CLOSED
    assert r.seq.enter_safe(r.t, "test") is Outcome.STARTED
    assert r.seq.mode is KitMode.SAFE and not r.ch(YAW).stepper.moving
    r.run_until(lambda: all(c.capsule.closed for c in r.seq.channels))
    r.step()
    assert all(c.phase is Phase.IDLE for c in r.seq.channels)
    for call in (lambda: r.seq.request_capsule(PITCH, True, r.t), lambda: r.seq.request_turn(PITCH, 100, r.t),
                 lambda: r.seq.request_home(YAW, r.t), lambda: r.seq.pulse(PITCH, 1, 80, r.t),
                 lambda: r.seq.start_controller(r.t)):
        assert call() is Outcome.SAFE
    assert r.seq.request_capsule(PITCH, False, r.t).accepted
    assert r.seq.leave_safe(r.t) is Outcome.STARTED and r.seq.mode is KitMode.OFF
    modes = [(e.old, e.new) for e in r.events if e.what == "mode"]
    assert modes == [("OFF", "RUNNING"), ("RUNNING", "SAFE"), ("SAFE", "OFF")]
    assert r.seq.safe_entries == 1
    # the yaw magnet was stopped mid-turn: at no polarity, so it is turned before it may open again
    assert r.seq.request_capsule(YAW, True, r.t) in (Outcome.UNHOMED, Outcome.STARTED)


# --- faults ---------------------------------------------------------------------------------------
def test_stall_during_a_pulse_is_recovered_by_rehoming_and_one_retry(rig):
    r = rig
    r.seq.start_controller(r.t)
    r.kit.inject(PITCH, "stall", 1.0)  # the rotor stays home: the switch stays closed
    r.seq.pulse(PITCH, -1, 80.0, r.t)
    r.run_until(lambda: r.seq.recoveries == 1, limit_s=5)
    r.kit.clear_faults()  # a transient stall: the motor turns again
    r.run_until(lambda: r.ch(PITCH).phase is Phase.IDLE and not r.ch(PITCH).busy)
    assert r.seq.recoveries == 1 and r.seq.mode is KitMode.RUNNING
    assert r.ch(PITCH).fault & FAULT_STALL  # reported (latched bits), not fatal
    assert r.ch(PITCH).polarity == -1 and r.kit.channels[PITCH].rotor_steps % 200 == 100
    assert ("TURNING", "RECOVERING") in r.phases(PITCH)
    kinds = [e.what for e in r.events if e.channel == PITCH]
    assert "fault" in kinds and "recovery" in kinds


def test_persistent_stall_ends_in_safe_mode_with_the_fault_reported(rig):
    r = rig
    r.seq.start_controller(r.t)
    r.kit.inject(PITCH, "stall", 1.0)
    r.seq.pulse(PITCH, -1, 80.0, r.t)
    r.run_until(lambda: r.seq.mode is KitMode.SAFE)
    r.run_until(lambda: all(c.capsule.closed for c in r.seq.channels))
    assert r.ch(PITCH).phase is Phase.FAULT and r.ch(PITCH).fault & FAULT_STALL
    assert r.seq.recoveries == 1 and "pitch" in r.seq.last_safe_reason
    assert r.ch(YAW).phase is not Phase.FAULT
    # leaving safe mode clears the latch; the magnet must be homed again
    r.kit.clear_faults()
    assert r.seq.leave_safe(r.t) is Outcome.STARTED
    assert r.ch(PITCH).phase is Phase.IDLE and r.ch(PITCH).stepper.state is MagnetState.UNHOMED
    assert r.seq.request_home(PITCH, r.t) is Outcome.STARTED


def test_shutter_stuck_half_open_ends_in_safe_mode_and_the_magnet_never_turns(rig):
    r = rig
    r.seq.start_controller(r.t)
    r.kit.inject(YAW, "stuck", 0.5)
    r.seq.pulse(YAW, 1, 80.0, r.t)
    r.run_until(lambda: r.seq.mode is KitMode.SAFE, limit_s=30)
    r.run(5.0)
    assert r.ch(YAW).phase is Phase.FAULT and r.ch(YAW).fault & FAULT_SHUTTER_STUCK
    assert r.kit.channels[YAW].shutter == 0.5 and r.kit.channels[YAW].release
    assert r.seq.recoveries == 1  # the spring was given its chance
    pulses = r.kit.channels[YAW].pulses
    assert r.seq.request_polarity(YAW, -1, r.t) is Outcome.SAFE
    assert r.seq.leave_safe(r.t) is Outcome.FAULT  # not confirmed closed: stays safe
    assert r.seq.mode is KitMode.SAFE and r.kit.channels[YAW].pulses == pulses
    r.kit.clear_faults(YAW)  # freed on the ground's orders... the spring closes it
    r.run(2.0)
    assert r.seq.leave_safe(r.t) is Outcome.STARTED


def test_a_transient_opening_failure_is_retried_once(rig):
    r = rig
    r.seq.start_controller(r.t)
    r.kit.inject(PITCH, "switch", ("open", False))  # the open switch does not report once
    r.seq.pulse(PITCH, 1, 80.0, r.t)
    r.run_until(lambda: r.seq.recoveries == 1, limit_s=10)
    r.kit.clear_faults()
    r.run_until(lambda: r.ch(PITCH).capsule.state is CapsuleState.OPEN, limit_s=10)
    assert r.seq.mode is KitMode.RUNNING and r.ch(PITCH).fault & FAULT_SHUTTER_STUCK
    assert r.kit.channels[PITCH].openings == 2


def test_a_lying_closed_switch_is_caught_and_ends_safe(rig):
    r = rig
    r.seq.start_controller(r.t)
    r.kit.inject(YAW, "switch", ("closed", True))
    r.seq.pulse(YAW, 1, 80.0, r.t)
    r.run_until(lambda: r.seq.mode is KitMode.SAFE, limit_s=20)
    assert r.ch(YAW).fault & FAULT_SWITCH_DISAGREE and r.seq.recoveries == 1
    r.run_until(lambda: r.kit.channels[YAW].shutter == 0.0)


def test_a_switch_disagreement_at_rest_ends_safe_at_once(rig):
    r = rig
    r.kit.inject(PITCH, "switch", ("open", True))
    r.step()
    r.step()
    assert r.seq.mode is KitMode.SAFE and r.ch(PITCH).phase is Phase.FAULT
    assert r.ch(PITCH).fault & FAULT_SWITCH_DISAGREE


def test_stall_while_homing_from_the_ground_is_latched(rig):
    r = rig
    r.kit.inject(YAW, "switch", ("home", False))
    r.seq.request_home(YAW, r.t)
    r.run_until(lambda: r.seq.mode is KitMode.SAFE, limit_s=120)
    assert r.ch(YAW).fault & FAULT_STALL


def test_gpio_failure_ends_safe_without_an_exception(rig):
    r = rig
    r.seq.start_controller(r.t)
    r.seq.pulse(PITCH, -1, 80.0, r.t)
    r.step()
    r.kit.inject(PITCH, "gpio")
    r.run_until(lambda: r.seq.mode is KitMode.SAFE, limit_s=30)
    assert r.ch(PITCH).fault & (FAULT_TIMEOUT | FAULT_SHUTTER_STUCK)
    r.kit.clear_faults()
    r.run(3.0)


def test_every_driver_transition_is_an_event(rig):
    r = rig
    r.seq.start_controller(r.t)
    seen = {}
    for ch in (PITCH, YAW):
        seen[ch] = [(r.ch(ch).stepper.state.name, r.ch(ch).capsule.state.name)]
    r.seq.pulse(PITCH, -1, 80.0, r.t)
    r.seq.pulse(YAW, -1, 80.0, r.t)
    while r.t < 100.0:
        r.step()
        for ch in (PITCH, YAW):
            now = (r.ch(ch).stepper.state.name, r.ch(ch).capsule.state.name)
            if now != seen[ch][-1]:
                seen[ch].append(now)
    for ch in (PITCH, YAW):
        changes = sum(a[0] != b[0] for a, b in zip(seen[ch], seen[ch][1:])) + \
            sum(a[1] != b[1] for a, b in zip(seen[ch], seen[ch][1:]))
        reported = sum(e.what in ("magnet", "capsule") for e in r.events if e.channel == ch)
        assert reported == changes > 0
    assert all(e.text().startswith("deorbit ") for e in r.events)
