"""Emulated de-orbit kit behind the `fsw.drivers.gpio.DigitalLines` lines: two magnets turned by steppers,
each in a screening capsule with a motor-opened, spring-closed shutter and two end switches.

Physics and timing (lapkhanov2019 section 6; spec §5), per channel (0 = pitch, 1 = yaw):

- Magnet: 15 A·m² dipole on a shaft turned by a stepper (200 steps per turn). The shaft is along body x;
  at rotor angle φ the dipole is p·Rx(φ)·a with a = +z (pitch magnet) or +y (yaw magnet): φ = 0 is
  home (polarity +1), φ = 180° flips the sign. Each step pulse moves the rotor one step in the
  direction line's sense while `enable` is high. The home switch is closed for rotor positions within
  ±`home_half_window` steps of home.
- Shutter: opening s ∈ [0, 1] (0 closed). Motor on, latch engaged: ds/dt = 1/`open_time_s` (2 s);
  release on (motor off): the spring closes at ds/dt = −1/`close_time_s` (0.5 s); otherwise it holds.
  The closed switch is on for s ≤ 0.01, the open switch for s ≥ 0.99. The unscreened part of the dipole
  is s·p (shutters half open leave half the field out).
- Power (truth ledger): 11.7 W per motor while the stepper is enabled or the shutter motor is on.

Faults (:meth:`DeorbitKitEmulator.inject`): `stall` (a fraction of the step pulses is lost: missed
steps, 1.0 = the rotor does not move), `stuck` (the shutter sticks at an opening, e.g. 0.5 = half open,
and moves no further either way), `switch` (a switch — "home", "closed" or "open" — reads a fixed
level whatever the mechanism does: a lying switch), `gpio` (every line operation raises GpioError).

Interlock monitor (truth, independent of the flight software): a step pulse while the shutter is not
fully closed (s > 0.01), or the shutter motor switched on while a pulse burst is still running (the
magnet still moving), counts in `interlock_violations`. The flight software's own count is separate;
both must stay 0.

Time: the owner calls :meth:`advance_to` with the loop time before each flight-loop tick (lockstep, like
`hil.sim.Simulator`). A burst of step pulses is spread over the loop period that follows it: the rotor
position is updated at once (the switches are read at the next tick), and the magnet counts as moving
until the next `advance_to`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fsw.drivers.gpio import GpioError

STEPS_PER_TURN = 200
MOTOR_POWER_W = 11.7
DIPOLE_AM2 = 15.0
CHANNEL_NAMES = ("pitch", "yaw")
#: dipole direction at home per channel, body axes: the pitch magnet along z (M_y = p_z B_x), the yaw
#: magnet along y (M_z = −p_y B_x) — lapkhanov2019 eq. 5
HOME_AXIS = (np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0]))
CLOSED_BELOW = 0.01
OPEN_ABOVE = 0.99


@dataclass
class ChannelEmulator:
    """Truth state of one channel."""

    index: int
    dipole_Am2: float = DIPOLE_AM2
    open_time_s: float = 2.0
    close_time_s: float = 0.5
    home_half_window: int = 2
    rotor_steps: int = 0  # true rotor position (mod 200 when read)
    shutter: float = 0.0  # 0 closed .. 1 open
    dir_forward: bool = True
    enable: bool = False
    drive: bool = False
    release: bool = False
    # faults
    stall_fraction: float = 0.0
    stuck_at: float | None = None
    switch_lies: dict = field(default_factory=dict)
    # truth counters
    pulses: int = 0
    missed_steps: int = 0
    openings: int = 0
    stepper_energy_J: float = 0.0
    shutter_energy_J: float = 0.0
    burst_running: bool = False  # a pulse burst issued since the last advance (spread over that period)
    _stall_acc: float = 0.0

    def home_switch(self) -> bool:
        if "home" in self.switch_lies:
            return self.switch_lies["home"]
        r = self.rotor_steps % STEPS_PER_TURN
        return min(r, STEPS_PER_TURN - r) <= self.home_half_window

    def closed_switch(self) -> bool:
        if "closed" in self.switch_lies:
            return self.switch_lies["closed"]
        return self.shutter <= CLOSED_BELOW

    def open_switch(self) -> bool:
        if "open" in self.switch_lies:
            return self.switch_lies["open"]
        return self.shutter >= OPEN_ABOVE

    def axis_body(self) -> np.ndarray:
        """The magnet's axis in body axes at the rotor's angle φ: Rx(φ) a (a unit vector)."""
        phi = 2.0 * math.pi * (self.rotor_steps % STEPS_PER_TURN) / STEPS_PER_TURN
        c, s = math.cos(phi), math.sin(phi)
        a = HOME_AXIS[self.index]
        return np.array([a[0], c * a[1] - s * a[2], s * a[1] + c * a[2]])

    def dipole_body_Am2(self) -> np.ndarray:
        """The unscreened dipole in body axes: shutter opening × p × Rx(φ) a."""
        if self.shutter <= 0.0:
            return np.zeros(3)
        return self.shutter * self.dipole_Am2 * self.axis_body()

    def advance(self, dt_s: float) -> None:
        if dt_s <= 0.0:
            return
        self.burst_running = False
        if self.enable:
            self.stepper_energy_J += MOTOR_POWER_W * dt_s
        if self.drive:
            self.shutter_energy_J += MOTOR_POWER_W * dt_s
        rate = 0.0
        if self.drive and not self.release:
            rate = 1.0 / self.open_time_s
        elif self.release and not self.drive:
            rate = -1.0 / self.close_time_s
        if rate == 0.0:
            return
        s = min(1.0, max(0.0, self.shutter + rate * dt_s))
        if self.stuck_at is not None:
            lo, hi = sorted((self.shutter, s))
            if lo <= self.stuck_at <= hi or self.shutter == self.stuck_at:
                s = self.stuck_at
        self.shutter = s


class DeorbitKitEmulator:
    """Both channels of the kit as `DigitalLines`; `advance_to(t)` before each flight-loop tick."""

    def __init__(self, *, dipole_Am2: float = DIPOLE_AM2, open_time_s: float = 2.0, close_time_s: float = 0.5,
                 home_half_window: int = 2) -> None:
        self.channels = [ChannelEmulator(i, dipole_Am2, open_time_s, close_time_s, home_half_window)
                         for i in range(2)]
        self.t_s = 0.0
        self.interlock_violations = 0
        self.violation_log: list[tuple[float, int, str]] = []
        self.gpio_fail = False
        self.operations = 0

    # --- time -----------------------------------------------------------------------------------
    def advance_to(self, t_s: float) -> None:
        dt = t_s - self.t_s
        if dt < -1e-12:
            raise ValueError(f"time runs forward only: at {self.t_s} s, asked for {t_s} s")
        for ch in self.channels:
            ch.advance(dt)
        self.t_s = max(self.t_s, t_s)

    # --- DigitalLines ---------------------------------------------------------------------------
    def _channel(self, line: str) -> tuple[ChannelEmulator, str]:
        self.operations += 1
        if self.gpio_fail:
            raise GpioError(f"{line}: I/O expander not answering")
        try:
            idx, name = line.split(".", 1)
            return self.channels[int(idx)], name
        except (ValueError, IndexError):
            raise GpioError(f"no such line {line!r}") from None

    def read_input(self, line: str) -> bool:
        ch, name = self._channel(line)
        if name == "home":
            return ch.home_switch()
        if name == "closed":
            return ch.closed_switch()
        if name == "open":
            return ch.open_switch()
        raise GpioError(f"{line!r} is not an input")

    def write_output(self, line: str, level: bool) -> None:
        ch, name = self._channel(line)
        level = bool(level)
        if name == "dir":
            ch.dir_forward = level
        elif name == "enable":
            ch.enable = level
        elif name == "shutter_drive":
            if level and not ch.drive:
                ch.openings += 1
                if ch.burst_running:
                    self._violation(ch, "shutter motor started while the magnet was moving")
            ch.drive = level
        elif name == "shutter_release":
            ch.release = level
        else:
            raise GpioError(f"{line!r} is not an output")

    def pulse_output(self, line: str, count: int) -> None:
        ch, name = self._channel(line)
        if name != "step":
            raise GpioError(f"{line!r} is not a pulse output")
        if count < 0:
            raise GpioError(f"negative pulse count {count}")
        if count == 0 or not ch.enable:
            return
        if ch.shutter > CLOSED_BELOW:
            self._violation(ch, f"magnet stepped with the shutter {ch.shutter:.2f} open")
        ch.pulses += count
        ch.burst_running = True
        moved = count
        if ch.stall_fraction > 0.0:
            ch._stall_acc += count * ch.stall_fraction
            lost = min(count, int(ch._stall_acc))
            ch._stall_acc -= lost
            ch.missed_steps += lost
            moved = count - lost
        ch.rotor_steps += moved if ch.dir_forward else -moved

    # --- faults ---------------------------------------------------------------------------------
    def inject(self, channel: int, kind: str, value=None) -> None:
        """Inject a fault: `stall` (fraction of pulses lost, default 1.0), `stuck` (opening where the
        shutter sticks, default 0.5), `switch` (value = (name, level), a lying switch), `gpio` (all
        line operations fail)."""
        ch = self.channels[channel]
        if kind == "stall":
            ch.stall_fraction = 1.0 if value is None else float(value)
        elif kind == "stuck":
            ch.stuck_at = 0.5 if value is None else float(value)
        elif kind == "switch":
            name, level = value
            if name not in ("home", "closed", "open"):
                raise ValueError(f"no switch {name!r}")
            ch.switch_lies[name] = bool(level)
        elif kind == "gpio":
            self.gpio_fail = True
        else:
            raise ValueError(f"unknown fault {kind!r} (stall, stuck, switch, gpio)")

    def clear_faults(self, channel: int | None = None) -> None:
        for ch in self.channels if channel is None else [self.channels[channel]]:
            ch.stall_fraction = 0.0
            ch.stuck_at = None
            ch.switch_lies.clear()
        self.gpio_fail = False

    # --- outputs for the dynamics and the bench -------------------------------------------------
    def dipole_body_Am2(self) -> np.ndarray:
        """Sum of the unscreened dipoles, body axes [A·m²] (what M = p × B acts with)."""
        return self.channels[0].dipole_body_Am2() + self.channels[1].dipole_body_Am2()

    @property
    def energy_J(self) -> float:
        return sum(ch.stepper_energy_J + ch.shutter_energy_J for ch in self.channels)

    def _violation(self, ch: ChannelEmulator, why: str) -> None:
        self.interlock_violations += 1
        self.violation_log.append((self.t_s, ch.index, why))
