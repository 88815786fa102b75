"""Digital-line interface between the de-orbit kit's drivers and the hardware (or its emulator).

The kit is wired with plain digital lines, one set per channel (0 = pitch, 1 = yaw):

| line                | dir | what                                                          |
|---------------------|-----|---------------------------------------------------------------|
| `<ch>.step`         | out | step pulses to the stepper driver (a timer-driven pulse train) |
| `<ch>.dir`          | out | stepper direction (high = forward)                            |
| `<ch>.enable`       | out | stepper driver enable (winding current on)                    |
| `<ch>.home`         | in  | home switch of the magnet shaft (high at home)                |
| `<ch>.shutter_drive`| out | capsule shutter motor (opens the shutters against the spring) |
| `<ch>.shutter_release` | out | releases the shutter latch: the spring closes the capsule  |
| `<ch>.closed`       | in  | shutters-closed end switch                                    |
| `<ch>.open`         | in  | shutters-open end switch                                      |

Anything that implements :class:`DigitalLines` can be plugged under the drivers: a Linux GPIO chip
with a PWM/timer peripheral for the step train, a serial I/O expander, or the emulator
(`hil.deorbit_kit`). The step train is a *count* of pulses because at a 10 Hz loop the flight software
cannot toggle a line per step: like a timer in one-pulse mode (or a step generator in the motor driver)
it emits `count` pulses spread over the next loop period.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable


class GpioError(Exception):
    """A line operation that failed: the expander did not answer, a line is not configured."""


@runtime_checkable
class DigitalLines(Protocol):
    """Digital inputs, outputs and a step-pulse generator, lines named as in the module docstring."""

    def read_input(self, line: str) -> bool:
        """Level of input `line`. Raises GpioError if it cannot be read."""
        ...

    def write_output(self, line: str, level: bool) -> None:
        """Drive output `line` high (True) or low. Raises GpioError if it cannot be written."""
        ...

    def pulse_output(self, line: str, count: int) -> None:
        """Emit `count` >= 0 pulses on output `line` (spread over the next loop period).

        Raises GpioError if the pulse generator cannot be programmed (no pulse is then emitted).
        """
        ...


def line(channel: int, name: str) -> str:
    """The name of line `name` of channel `channel` (0 = pitch, 1 = yaw): e.g. ``"0.home"``."""
    return f"{channel}.{name}"
