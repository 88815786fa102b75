"""Step/direction driver for a magnet-turning micro stepper: non-blocking, time injected, never raises.

Hardware (lapkhanov2019, section 6; spec §5): NEMA-17 class micro stepper, 1.8° per step (200 steps per
turn), at most 500 rpm, two windings of 1.8 A at 3.25 V: 11.7 W while it moves. It turns a 15 A·m²
permanent magnet; 100 steps (180°) flip the dipole's sign. A home switch marks the magnet's reference
position, where the dipole points along +axis (polarity +1); it is closed over a small window of
`home_window_steps` (odd) steps centred on home.

Motion: trapezoidal profile (acceleration `accel_sps2`, cruise `speed_sps`) computed from the time of
the move's start; each `update(now_s)` emits the steps that the profile has reached since the previous
call as one pulse burst (`DigitalLines.pulse_output`). With the defaults a 180° turn takes 1.0 s (the
paper's figure): 0.2 s ramps at 625 steps/s² to 125 steps/s (37.5 rpm) and back. The winding is enabled
only while moving, so the energy ledger is 11.7 W × time moving (`energy_J`).

Homing (re-reference on the switch), at one or two steps per update so the switch window is never
stepped over: back off the switch if it is closed; seek forwards until it closes (at most one turn plus
the window); step through the window one step per update until it opens again: that is
`home_window_steps // 2 + 1` steps past home; step back to the centre. Position := 0.

Stall detection (missed steps, detected by the home switch): at the end of every move the switch must
read closed if and only if the counted position is home (mod 200). A mismatch is a stall: the position
is no longer known (state FAULT, fault STALL, `stalls` counted) until the next successful homing.
Homing that does not find the switch within one turn is a FAULT too (STALL); one that cannot leave
the switch reports STALL and SWITCH_DISAGREE (a stalled motor and a switch stuck closed look alike). Every
motion has a deadline (profile time + margin);
a motion that cannot complete (pulse generator failing) ends in FAULT with TIMEOUT.

States (values = DEBRIS_MAGNET_STATE): IDLE, HOMING, TURNING, FAULT, UNHOMED (position unknown, the
state after power-up). `move` and `home` only start from IDLE / UNHOMED (home) and are refused
otherwise; the interlocks (capsule closed) are *not* checked here but in the sequencer, the single gate
every command passes through. A GpioError is counted (`io_errors`) and the step retried at the next
update; nothing raises out of this class.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from enum import IntEnum

from .gpio import DigitalLines, line

STEPS_PER_TURN = 200
STEP_DEG = 360.0 / STEPS_PER_TURN
HALF_TURN_STEPS = STEPS_PER_TURN // 2
MAX_RPM = 500.0
MAX_SPEED_SPS = MAX_RPM * STEPS_PER_TURN / 60.0
MOTOR_POWER_W = 11.7
"""Two windings of 1.8 A at 3.25 V (lapkhanov2019: P_r,m = 2 U_r I_r = 11.7 W)."""

FAULT_STALL = 1
FAULT_SHUTTER_STUCK = 2
FAULT_SWITCH_DISAGREE = 4
FAULT_TIMEOUT = 8
"""Fault bits; the values of DEBRIS_DEORBIT_FAULT."""


class MagnetState(IntEnum):
    """Stepper/magnet state; the values are DEBRIS_MAGNET_STATE of the telemetry dialect."""

    IDLE = 0
    HOMING = 1
    TURNING = 2
    FAULT = 3
    UNHOMED = 4


@dataclass(frozen=True)
class StepperLimits:
    speed_sps: float = 125.0
    accel_sps2: float = 625.0
    home_window_steps: int = 5
    home_batch_steps: int = 2
    timeout_margin_s: float = 0.5
    homing_timeout_s: float = 60.0
    max_io_errors: int = 10  # consecutive failing updates while moving before the motion is given up

    def __post_init__(self) -> None:
        if not 0.0 < self.speed_sps <= MAX_SPEED_SPS:
            raise ValueError(f"speed must be in (0, {MAX_SPEED_SPS:.1f}] steps/s (500 rpm), got {self.speed_sps}")
        if not self.accel_sps2 > 0.0:
            raise ValueError(f"acceleration must be > 0 steps/s², got {self.accel_sps2}")
        if self.home_window_steps < 1 or self.home_window_steps % 2 == 0:
            raise ValueError("home_window_steps must be odd and >= 1")
        if not 1 <= self.home_batch_steps < self.home_window_steps:
            raise ValueError("home_batch_steps must be >= 1 and smaller than the home window")


def profile_duration_s(steps: int, speed_sps: float, accel_sps2: float) -> float:
    """Duration of a trapezoidal (or triangular) move of |steps| steps."""
    d = abs(steps)
    if d == 0:
        return 0.0
    d_ramps = speed_sps * speed_sps / accel_sps2  # distance of both ramps at full speed
    if d >= d_ramps:
        return 2.0 * speed_sps / accel_sps2 + (d - d_ramps) / speed_sps
    return 2.0 * math.sqrt(d / accel_sps2)


def profile_position(t_s: float, steps: int, speed_sps: float, accel_sps2: float) -> float:
    """Distance covered (>= 0, <= |steps|) t_s after the start of a trapezoidal move of |steps| steps."""
    d = abs(steps)
    total = profile_duration_s(d, speed_sps, accel_sps2)
    if t_s <= 0.0 or d == 0:
        return 0.0
    if t_s >= total:
        return float(d)
    a = accel_sps2
    v = min(speed_sps, math.sqrt(d * a))  # peak speed
    t_ramp = v / a
    if t_s < t_ramp:
        return 0.5 * a * t_s * t_s
    d_ramp = 0.5 * v * t_ramp
    t_cruise_end = total - t_ramp
    if t_s <= t_cruise_end:
        return d_ramp + v * (t_s - t_ramp)
    tr = total - t_s
    return d - 0.5 * a * tr * tr


class _Homing(IntEnum):
    BACK_OFF = 0  # switch closed at the start: step backwards until it opens
    SEEK = 1  # forwards until it closes
    THROUGH = 2  # forwards one step per update until it opens again
    CENTRE = 3  # backwards to the centre of the window


class Stepper:
    """One magnet's stepper on `DigitalLines` channel `channel`; call `update(now_s)` every loop tick."""

    def __init__(self, io: DigitalLines, channel: int, limits: StepperLimits = StepperLimits(),
                 power_W: float = MOTOR_POWER_W) -> None:
        self._io = io
        self.channel = int(channel)
        self.limits = limits
        self.power_W = float(power_W)
        self._l_step = line(channel, "step")
        self._l_dir = line(channel, "dir")
        self._l_enable = line(channel, "enable")
        self._l_home = line(channel, "home")
        self.state = MagnetState.UNHOMED
        self.position_steps = 0  # counted position from home, [0, 200) once homed
        self.steps_total = 0
        self.energy_J = 0.0
        self.moves = 0  # moves started
        self.turns = 0  # completed moves of a half turn or more (dipole flips)
        self.homings = 0  # homings completed
        self.stalls = 0
        self.io_errors = 0
        self.fault = 0
        self.last_error = ""
        self._target = 0  # signed steps of the current move
        self._issued = 0  # |steps| issued so far in the current move
        self._dir = 1
        self._t0 = 0.0
        self._deadline = math.inf
        self._t_last = math.nan
        self._lines_set = False
        self._homing = _Homing.SEEK
        self._homing_steps = 0
        self._homing_limit = 0
        self._errors_in_row = 0

    # --- queries --------------------------------------------------------------------------------
    @property
    def moving(self) -> bool:
        return self.state in (MagnetState.TURNING, MagnetState.HOMING)

    @property
    def homed(self) -> bool:
        return self.state in (MagnetState.IDLE, MagnetState.TURNING)

    @property
    def polarity(self) -> int:
        """+1 at home, −1 half a turn away, 0 anywhere else or when the position is unknown."""
        if self.state is not MagnetState.IDLE:
            return 0
        p = self.position_steps % STEPS_PER_TURN
        return 1 if p == 0 else -1 if p == HALF_TURN_STEPS else 0

    def expected_home_switch(self, position_steps: int) -> bool | None:
        """What the home switch must read at a counted position: closed within one step less than half
        the window from home, open beyond one step more; None on the window's edge (no check)."""
        p = position_steps % STEPS_PER_TURN
        d = min(p, STEPS_PER_TURN - p)
        half = self.limits.home_window_steps // 2
        if d <= half - 1:
            return True
        if d >= half + 1:
            return False
        return None

    def move_duration_s(self, steps: int) -> float:
        return profile_duration_s(steps, self.limits.speed_sps, self.limits.accel_sps2)

    # --- commands (return True when started) ----------------------------------------------------
    def move(self, steps: int, now_s: float) -> bool:
        """Start a relative move of `steps` (signed) from IDLE; refused otherwise."""
        if self.state is not MagnetState.IDLE or not isinstance(steps, numbers.Integral):
            return False
        steps = int(steps)
        self._update_energy(now_s)
        if steps == 0:
            return True
        self._begin(MagnetState.TURNING, now_s)
        self._target = steps
        self._dir = 1 if steps > 0 else -1
        self._deadline = now_s + self.move_duration_s(steps) + self.limits.timeout_margin_s
        self.moves += 1
        return True

    def home(self, now_s: float) -> bool:
        """Start homing from IDLE or UNHOMED (FAULT needs `clear_fault` first)."""
        if self.state not in (MagnetState.IDLE, MagnetState.UNHOMED):
            return False
        self._update_energy(now_s)
        self._begin(MagnetState.HOMING, now_s)
        self._homing_steps = 0
        self._deadline = now_s + self.limits.homing_timeout_s
        self._homing = _Homing.SEEK
        self._homing_limit = STEPS_PER_TURN + self.limits.home_window_steps + 2
        try:
            if self._io.read_input(self._l_home):
                self._homing = _Homing.BACK_OFF
                self._homing_limit = self.limits.home_window_steps + 2
        except Exception as error:  # noqa: BLE001 - counted, the first update reads again
            self._io_error(error)
        return True

    def stop(self, now_s: float) -> None:
        """Abort any motion at once. The count is kept; a magnet stopped mid-move is at no polarity."""
        if not self.moving:
            return
        self._update_energy(now_s)
        homing = self.state is MagnetState.HOMING
        self._finish(MagnetState.UNHOMED if homing else MagnetState.IDLE)

    def clear_fault(self) -> None:
        """Leave FAULT for UNHOMED (the position is unknown until the next homing)."""
        if self.state is MagnetState.FAULT:
            self.state = MagnetState.UNHOMED
            self.fault = 0

    # --- the state machine ----------------------------------------------------------------------
    def update(self, now_s: float) -> None:
        """Advance the motion to `now_s`: emit the due steps, check the home switch at the end."""
        try:
            self._update_energy(now_s)
            if self.state is MagnetState.TURNING:
                self._turn(now_s)
            elif self.state is MagnetState.HOMING:
                self._home_step(now_s)
            self._errors_in_row = 0
        except Exception as error:  # noqa: BLE001 - a driver never raises into the loop
            self._io_error(error)
            self._errors_in_row += 1
            if self.moving and self._errors_in_row >= self.limits.max_io_errors:
                self._fail(FAULT_TIMEOUT, f"lines failing ({self.last_error})")
        if self.moving and now_s > self._deadline:
            self._fail(FAULT_TIMEOUT, f"motion not finished by its deadline ({self._deadline:.2f} s)")

    def _turn(self, now_s: float) -> None:
        if not self._set_lines():
            return
        due = int(math.floor(profile_position(now_s - self._t0, self._target, self.limits.speed_sps,
                                              self.limits.accel_sps2) + 1e-9))
        n = due - self._issued
        if n > 0:
            self._pulse(n)  # a burst spread over the next loop period: checked at the next update
            return
        if self._issued < abs(self._target):
            return
        # move done: the home switch must agree with the counted position
        home = self._io.read_input(self._l_home)
        self.position_steps %= STEPS_PER_TURN
        if abs(self._target) >= HALF_TURN_STEPS:
            self.turns += 1
        expected = self.expected_home_switch(self.position_steps)
        if expected is not None and home != expected:
            self.stalls += 1
            self._fail(FAULT_STALL, f"home switch {'closed' if home else 'open'} at counted position "
                                    f"{self.position_steps}: missed steps")
            return
        self._finish(MagnetState.IDLE)

    def _home_step(self, now_s: float) -> None:
        if not self._set_lines():
            return
        lim = self.limits
        closed = self._io.read_input(self._l_home)
        phase = self._homing
        if phase is _Homing.BACK_OFF:
            if not closed:
                self._homing, self._homing_steps = _Homing.SEEK, 0
                self._homing_limit = STEPS_PER_TURN + lim.home_window_steps + 2
                return self._home_step_forward(lim.home_batch_steps)
            if self._homing_steps >= self._homing_limit:  # a stalled motor or a switch stuck closed
                return self._fail(FAULT_STALL | FAULT_SWITCH_DISAGREE, "home switch does not open when backing off")
            return self._home_pulse(-1, 1)
        if phase is _Homing.SEEK:
            if closed:
                self._homing, self._homing_steps = _Homing.THROUGH, 0
                self._homing_limit = lim.home_window_steps + 2
                return self._home_pulse(1, 1)
            if self._homing_steps >= self._homing_limit:
                return self._fail(FAULT_STALL, "home switch not found within one turn")
            return self._home_step_forward(lim.home_batch_steps)
        if phase is _Homing.THROUGH:
            if not closed:  # one step past the window: home is half a window + 1 behind
                self._homing = _Homing.CENTRE
                self._homing_steps = 0
                self._homing_limit = lim.home_window_steps // 2 + 1
                self.position_steps = self._homing_limit
                return self._home_pulse(-1, 1)
            if self._homing_steps >= self._homing_limit:
                return self._fail(FAULT_STALL | FAULT_SWITCH_DISAGREE, "home switch does not open past its window")
            return self._home_pulse(1, 1)
        # CENTRE: the pulses of the previous updates went out; done when the count is back at 0
        if self.position_steps != 0:
            return self._home_pulse(-1, 1)
        if not closed:
            return self._fail(FAULT_SWITCH_DISAGREE, "home switch open at the centre of its window")
        self.homings += 1
        self._finish(MagnetState.IDLE)

    def _home_step_forward(self, n: int) -> None:
        self._home_pulse(1, n)

    def _home_pulse(self, direction: int, n: int) -> None:
        if direction != self._dir:
            self._dir = direction
            self._io.write_output(self._l_dir, direction > 0)
        if self._pulse(n):
            self._homing_steps += n

    # --- helpers --------------------------------------------------------------------------------
    def _begin(self, state: MagnetState, now_s: float) -> None:
        self.state = state
        self._t0 = now_s
        self._issued = 0
        self._dir = 1
        self._lines_set = False
        self._t_last = now_s

    def _set_lines(self) -> bool:
        """Direction and enable, once per motion (retried at the next update on a GpioError)."""
        if not self._lines_set:
            self._io.write_output(self._l_dir, self._dir > 0)
            self._io.write_output(self._l_enable, True)
            self._lines_set = True
        return True

    def _pulse(self, n: int) -> bool:
        self._io.pulse_output(self._l_step, n)
        self._issued += n
        self.steps_total += n
        self.position_steps += self._dir * n
        return True

    def _finish(self, state: MagnetState) -> None:
        try:
            self._io.write_output(self._l_enable, False)
        except Exception as error:  # noqa: BLE001
            self._io_error(error)
        self.state = state
        self._deadline = math.inf
        self.position_steps %= STEPS_PER_TURN

    def _fail(self, bit: int, why: str) -> None:
        self.fault |= bit
        self._finish(MagnetState.FAULT)
        self.last_error = why

    def _io_error(self, error: Exception) -> None:
        self.io_errors += 1
        self.last_error = f"{type(error).__name__}: {error}"

    def _update_energy(self, now_s: float) -> None:
        """11.7 W while the winding is enabled (from the update that set the lines to the one that ends
        the motion)."""
        if self.moving and self._lines_set and not math.isnan(self._t_last) and now_s > self._t_last:
            self.energy_J += self.power_W * (now_s - self._t_last)
        self._t_last = now_s
