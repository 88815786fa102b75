"""Screening capsule: shutter motor, spring, latch and two end switches. Non-blocking, time injected,
never raises.

Hardware (lapkhanov2019, section 6): the magnet sits in a capsule of copper and magnetic layers whose
shutters are opened by a motor in about 2 s and closed by a spring at (practically) no energy. Here the
motor drives the shutters open against the spring through a self-locking gear, which holds them open
with the motor off; `shutter_release` disengages the gear and the spring closes the capsule (and keeps
it closed). Two end switches: `closed` (shutters home, magnet screened) and `open` (fully open).

States (values = DEBRIS_CAPSULE_STATE): CLOSED, OPENING, OPEN, CLOSING, FAULT.

- `open(now_s)` from CLOSED: motor on, release off. OPENING ends in OPEN when the open switch closes
  (motor off: 11.7 W × the opening time goes to `energy_J`). The closed switch must have let go within
  `release_check_s`; the open switch must be reached within `open_timeout_s`.
- `close(now_s)` from any state: motor off, release on. CLOSING ends in CLOSED when the closed switch
  closes (release off, the spring holds), within `close_timeout_s`.
- A fault (SHUTTER_STUCK: an end switch not reached in time; SWITCH_DISAGREE: both switches closed, the
  closed switch not letting go, a switch changing while at rest) leaves the capsule releasing (the
  spring closes whatever can close) in FAULT until `clear_fault`, which goes back to CLOSED only if the
  switches then say closed.

At start the capsule is taken to be CLOSED, and the first update checks it: a capsule the switches do not
show closed (the flight software restarted while it was open or moving: the self-locking gear holds the
shutters where they were) is closed by the spring as by `close` (CLOSING, counted in `found_open`),
not taken for a switch fault.

The capsule is *closed* (`closed` property) only in state CLOSED with the closed switch closed and the
open switch open as read at the latest update. The interlocks that use it are in the sequencer.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

from .gpio import DigitalLines, line
from .stepper import FAULT_SHUTTER_STUCK, FAULT_SWITCH_DISAGREE, MOTOR_POWER_W


class CapsuleState(IntEnum):
    """Capsule state; the values are DEBRIS_CAPSULE_STATE of the telemetry dialect."""

    CLOSED = 0
    OPENING = 1
    OPEN = 2
    CLOSING = 3
    FAULT = 4


@dataclass(frozen=True)
class CapsuleTiming:
    open_timeout_s: float = 4.0  # nominal 2 s
    close_timeout_s: float = 2.0  # nominal 0.5 s (spring)
    release_check_s: float = 0.5  # the closed switch must let go within this after the motor starts


class Capsule:
    """One screening capsule on `DigitalLines` channel `channel`; call `update(now_s)` every loop tick."""

    def __init__(self, io: DigitalLines, channel: int, timing: CapsuleTiming = CapsuleTiming(),
                 power_W: float = MOTOR_POWER_W) -> None:
        self._io = io
        self.channel = int(channel)
        self.timing = timing
        self.power_W = float(power_W)
        self._l_drive = line(channel, "shutter_drive")
        self._l_release = line(channel, "shutter_release")
        self._l_closed = line(channel, "closed")
        self._l_open = line(channel, "open")
        self.state = CapsuleState.CLOSED
        self.sw_closed = True  # switch levels at the latest update
        self.sw_open = False
        self.openings = 0  # openings started (each costs motor energy)
        self.found_open = 0  # found not closed at the first update, and closed
        self._checked = False  # the first update's check done
        self.energy_J = 0.0
        self.io_errors = 0
        self.fault = 0
        self.last_error = ""
        self._t_start = 0.0
        self._t_last = math.nan
        self._outputs_pending = False  # outputs of the current state not yet written (GpioError)
        self._drive = False
        self._release = False
        self._released_closed = False  # OPENING: the closed switch has let go

    @property
    def closed(self) -> bool:
        """Confirmed closed: state CLOSED and the switches agree (closed switch on, open switch off)."""
        return self.state is CapsuleState.CLOSED and self.sw_closed and not self.sw_open

    @property
    def motor_on(self) -> bool:
        return self._drive

    # --- commands -------------------------------------------------------------------------------
    def open(self, now_s: float) -> bool:
        """Start opening from CLOSED; refused (False) in any other state."""
        if self.state is not CapsuleState.CLOSED:
            return False
        self._account(now_s)
        self.state = CapsuleState.OPENING
        self._t_start = now_s
        self._released_closed = False
        self.openings += 1
        self._set_outputs(drive=True, release=False)
        return True

    def close(self, now_s: float) -> bool:
        """Release the spring from any state (always accepted; idempotent when closed)."""
        self._account(now_s)
        if self.state is CapsuleState.CLOSED:
            return True
        if self.state is not CapsuleState.FAULT:
            self.state = CapsuleState.CLOSING
            self._t_start = now_s
        self._set_outputs(drive=False, release=True)
        return True

    def clear_fault(self, now_s: float) -> bool:
        """Leave FAULT for CLOSED if the switches say closed now; True if cleared."""
        if self.state is not CapsuleState.FAULT:
            return True
        try:
            self._read()
        except Exception as error:  # noqa: BLE001
            self._io_error(error)
            return False
        if self.sw_closed and not self.sw_open:
            self.state = CapsuleState.CLOSED
            self.fault = 0
            self._set_outputs(drive=False, release=False)
            return True
        return False

    # --- state machine --------------------------------------------------------------------------
    def update(self, now_s: float) -> None:
        self._account(now_s)
        try:
            if self._outputs_pending:
                self._write_outputs()
            self._read()
            self._step(now_s)
        except Exception as error:  # noqa: BLE001 - a driver never raises into the loop
            self._io_error(error)
            self._check_timeout(now_s)

    def _step(self, now_s: float) -> None:
        st = self.state
        c, o = self.sw_closed, self.sw_open
        if c and o:
            if st is not CapsuleState.FAULT:
                self._fail(FAULT_SWITCH_DISAGREE, "closed and open switches both on")
            return
        if not self._checked:
            self._checked = True
            if st is CapsuleState.CLOSED and not c:
                self.found_open += 1
                self.last_error = "not closed at start: closing it"
                self.state = CapsuleState.CLOSING
                self._t_start = now_s
                self._set_outputs(drive=False, release=True)
                return
        if st is CapsuleState.OPENING:
            if not c:
                self._released_closed = True
            elif now_s - self._t_start > self.timing.release_check_s:
                self._fail(FAULT_SWITCH_DISAGREE, "closed switch still on after the shutters started")
                return
            if o:
                self.state = CapsuleState.OPEN
                self._set_outputs(drive=False, release=False)
                return
        elif st is CapsuleState.CLOSING:
            if c:
                self.state = CapsuleState.CLOSED
                self._set_outputs(drive=False, release=False)
                return
        elif st is CapsuleState.OPEN:
            if not o:
                self._fail(FAULT_SWITCH_DISAGREE, "open switch let go while open")
            return
        elif st is CapsuleState.CLOSED:
            if not c:
                self._fail(FAULT_SWITCH_DISAGREE, "closed switch let go while closed")
            return
        self._check_timeout(now_s)

    def _check_timeout(self, now_s: float) -> None:
        st = self.state
        if st is CapsuleState.OPENING and now_s - self._t_start > self.timing.open_timeout_s:
            self._fail(FAULT_SHUTTER_STUCK, f"open switch not reached in {self.timing.open_timeout_s} s")
        elif st is CapsuleState.CLOSING and now_s - self._t_start > self.timing.close_timeout_s:
            self._fail(FAULT_SHUTTER_STUCK, f"closed switch not reached in {self.timing.close_timeout_s} s")

    # --- helpers --------------------------------------------------------------------------------
    def _read(self) -> None:
        self.sw_closed = bool(self._io.read_input(self._l_closed))
        self.sw_open = bool(self._io.read_input(self._l_open))

    def _fail(self, bit: int, why: str) -> None:
        self.fault |= bit
        self.last_error = why
        self.state = CapsuleState.FAULT
        self._set_outputs(drive=False, release=True)

    def _set_outputs(self, *, drive: bool, release: bool) -> None:
        self._drive, self._release = drive, release
        try:
            self._write_outputs()
        except Exception as error:  # noqa: BLE001 - retried at the next update
            self._io_error(error)

    def _write_outputs(self) -> None:
        self._outputs_pending = True
        # motor off before releasing, release off before the motor starts: never both on
        if self._drive:
            self._io.write_output(self._l_release, False)
            self._io.write_output(self._l_drive, True)
        else:
            self._io.write_output(self._l_drive, False)
            self._io.write_output(self._l_release, self._release)
        self._outputs_pending = False

    def _io_error(self, error: Exception) -> None:
        self.io_errors += 1
        self.last_error = f"{type(error).__name__}: {error}"

    def _account(self, now_s: float) -> None:
        if self._drive and not math.isnan(self._t_last) and now_s > self._t_last:
            self.energy_J += self.power_W * (now_s - self._t_last)
        self._t_last = now_s
