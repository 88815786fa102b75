"""The de-orbit kit's ground commands (COMMAND_LONG → MAV_RESULT), its status message and its task in
the flight software."""
import math
from types import SimpleNamespace

import pytest

from fsw.commands import CommandRouter
from fsw.deorbit.kit import DeorbitKit
from fsw.deorbit.sequencer import KitMode
from fsw.drivers.capsule import CapsuleState
from fsw.drivers.stepper import MagnetState
from fsw.telemetry.dialect import mavlink
from fsw.telemetry.telemetry import Telemetry
from hil.deorbit_kit import DeorbitKitEmulator
from support import Capture

ACCEPTED, TEMP, DENIED, FAILED, UNSUPPORTED = (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
                                               mavlink.MAV_RESULT_DENIED, mavlink.MAV_RESULT_FAILED,
                                               mavlink.MAV_RESULT_UNSUPPORTED)
CAPSULE, TURN, POLARITY = (mavlink.MAV_CMD_DEBRIS_CAPSULE, mavlink.MAV_CMD_DEBRIS_MAGNET_TURN,
                           mavlink.MAV_CMD_DEBRIS_MAGNET_POLARITY)
CONTROLLER, SAFE, HOME = (mavlink.MAV_CMD_DEBRIS_CONTROLLER, mavlink.MAV_CMD_DEBRIS_SAFE_MODE,
                          mavlink.MAV_CMD_DEBRIS_MAGNET_HOME)
DT = 0.1


def cmd(command, *params):
    p = list(params) + [0.0] * (7 - len(params))
    return SimpleNamespace(command=command, confirmation=0, **{f"param{i + 1}": float(v) for i, v in enumerate(p)})


class Box:
    def __init__(self):
        self.emu = DeorbitKitEmulator()
        self.kit = DeorbitKit(self.emu)
        self.t = 0.0

    def send(self, command, *params):
        return self.kit.handle_command(cmd(command, *params), self.t)

    def run(self, seconds):
        for _ in range(int(round(seconds / DT))):
            self.t = round(self.t + DT, 9)
            self.emu.advance_to(self.t)
            self.kit.tick(self.t)

    def ch(self, i):
        return self.kit.sequencer.channels[i]


@pytest.fixture
def box():
    b = Box()
    assert b.send(HOME, 0) == ACCEPTED and b.send(HOME, 1) == ACCEPTED
    b.run(3.0)
    yield b
    assert b.emu.interlock_violations == 0 and b.kit.sequencer.interlock_violations == 0


@pytest.mark.parametrize("command, params", [
    (CAPSULE, (2, 1)), (CAPSULE, (-1, 1)), (CAPSULE, (0.5, 1)), (CAPSULE, (math.nan, 1)), (CAPSULE, (0, 2)),
    (CAPSULE, (0, math.inf)), (TURN, (0, 1.0)), (TURN, (0, 361.0)), (TURN, (0, math.nan)), (TURN, (3, 180)),
    (POLARITY, (0, 0)), (POLARITY, (0, 2)), (POLARITY, (1, 0.5)), (HOME, (7,)), (SAFE, (2,)), (SAFE, (math.nan,)),
    (CONTROLLER, (2,)), (CONTROLLER, (1, -5)), (CONTROLLER, (1, 50, 80)), (CONTROLLER, (1, 7200)),
    (CONTROLLER, (1, math.nan)),
])
def test_malformed_or_out_of_range_commands_are_denied_and_not_executed(box, command, params):
    before = (box.emu.channels[0].pulses, box.emu.channels[1].pulses, box.emu.channels[0].openings,
              box.emu.channels[1].openings, box.kit.mode, box.kit.controller.config)
    assert box.send(command, *params) == DENIED
    box.run(1.0)
    assert (box.emu.channels[0].pulses, box.emu.channels[1].pulses, box.emu.channels[0].openings,
            box.emu.channels[1].openings, box.kit.mode, box.kit.controller.config) == before


def test_capsule_and_magnet_commands(box):
    assert box.send(TURN, 0, 180.0) == ACCEPTED
    assert box.send(CAPSULE, 0, 1) == TEMP  # the magnet is turning
    box.run(2.0)
    assert box.ch(0).polarity == -1
    assert box.send(CAPSULE, 0, 1) == ACCEPTED
    box.run(0.5)
    assert box.send(POLARITY, 0, 1) == TEMP  # busy opening
    box.run(3.0)
    assert box.ch(0).capsule.state is CapsuleState.OPEN
    assert box.send(POLARITY, 0, 1) == TEMP  # interlock: the capsule is open
    assert box.send(TURN, 0, 1.8) == TEMP
    assert box.send(HOME, 0) == TEMP
    assert box.send(CAPSULE, 0, 0) == ACCEPTED
    box.run(1.0)
    assert box.send(POLARITY, 0, 1) == ACCEPTED
    box.run(2.0)
    assert box.ch(0).polarity == 1 and box.send(POLARITY, 0, 1) == ACCEPTED  # already there
    assert box.send(TURN, 1, -360.0) == ACCEPTED  # a full turn backwards, home switch checked
    box.run(5.0)
    assert box.ch(1).stepper.state is MagnetState.IDLE and box.ch(1).polarity == 1
    assert box.send(9999) == UNSUPPORTED


def test_unhomed_magnets_refuse_motion_with_failed():
    b = Box()
    assert b.send(CAPSULE, 1, 1) == FAILED
    assert b.send(TURN, 1, 18.0) == FAILED
    assert b.send(POLARITY, 1, -1) == FAILED  # turning needs a known position: home first
    assert b.send(HOME, 1) == ACCEPTED


def test_controller_commands_and_safe_mode(box):
    assert box.send(CONTROLLER, 1, 150, 90) == ACCEPTED
    assert box.kit.mode is KitMode.RUNNING
    cfg = box.kit.controller.config
    assert (cfg.period_s, cfg.min_impulse_s) == (150.0, 90.0) and min(cfg.widths_s) == 90.0
    assert box.send(CAPSULE, 0, 1) == TEMP  # the controller owns the kit
    assert box.send(CAPSULE, 0, 0) == ACCEPTED  # closing is always allowed
    assert box.send(CONTROLLER, 0) == ACCEPTED and box.kit.mode is KitMode.OFF
    assert box.send(CONTROLLER, 0) == ACCEPTED  # already off
    assert box.send(SAFE, 1) == ACCEPTED and box.kit.mode is KitMode.SAFE
    for command, params in ((CAPSULE, (0, 1)), (TURN, (0, 180)), (POLARITY, (1, -1)), (HOME, (1,)),
                            (CONTROLLER, (1,))):
        assert box.send(command, *params) == FAILED
    box.run(1.0)
    assert box.send(SAFE, 0) == ACCEPTED and box.kit.mode is KitMode.OFF
    assert box.send(SAFE, 0) == ACCEPTED


def test_leaving_safe_mode_with_a_capsule_stuck_open_fails(box):
    box.emu.inject(1, "stuck", 0.5)
    assert box.send(CAPSULE, 1, 1) == ACCEPTED
    box.run(12.0)
    assert box.kit.mode is KitMode.SAFE  # opening timed out, the spring could not close it
    assert box.send(SAFE, 0) == FAILED
    status = box.kit.status(box.t)
    assert status.controller_state == mavlink.DEBRIS_CONTROLLER_STATE_SAFE
    assert status.fault[1] & mavlink.DEBRIS_DEORBIT_FAULT_SHUTTER_STUCK
    assert status.capsule_state[1] == mavlink.DEBRIS_CAPSULE_STATE_FAULT


def test_handlers_register_with_the_router(box):
    router = CommandRouter()
    box.kit.register(router)
    msg = cmd(CAPSULE, 1, 1)
    assert router.handle(msg, box.t, authenticated=True) == ACCEPTED
    assert router.handle(cmd(CAPSULE, 1, 1), box.t, authenticated=False) == DENIED  # unsigned: refused


def test_handlers_survive_strange_messages(box):
    assert box.kit.handle_command(SimpleNamespace(command=CAPSULE), box.t) == DENIED  # no params at all
    assert box.kit.handle_command(SimpleNamespace(command=TURN, param1="x", param2=None), box.t) == DENIED
    assert box.kit.handle_command(object(), box.t) == UNSUPPORTED


def test_status_message_round_trip(box):
    box.send(POLARITY, 1, -1)
    box.run(2.0)
    box.send(CAPSULE, 1, 1)
    box.run(3.0)
    st = box.kit.status(box.t)
    assert st.polarity == (1, -1) and st.position_steps == (0, 100)
    assert st.capsule_state == (mavlink.DEBRIS_CAPSULE_STATE_CLOSED, mavlink.DEBRIS_CAPSULE_STATE_OPEN)
    assert st.magnet_state == (mavlink.DEBRIS_MAGNET_STATE_IDLE,) * 2
    assert st.capsule_openings == (0, 1) and st.magnet_turns == (0, 1)
    assert st.energy_J[1] > st.energy_J[0] > 0  # homing for both, a turn and an opening for yaw
    link = Capture()
    tlm = Telemetry(link)
    tlm.deorbit_status(box.t, st)
    tlm.statustext(box.kit.sequencer.events[-1].text())
    msgs = link.messages()
    m = [x for x in msgs if x.get_type() == "DEBRIS_DEORBIT_STATUS"][0]
    assert list(m.position_steps) == [0, 100] and list(m.polarity) == [1, -1]
    assert list(m.capsule_state) == list(st.capsule_state) and m.controller_state == 0
    assert m.energy[1] == pytest.approx(st.energy_J[1], rel=1e-6) and m.interlock_violations == 0
    assert [x for x in msgs if x.get_type() == "STATUSTEXT"][0].text.startswith("deorbit yaw")
