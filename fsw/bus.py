"""Register-bus interface between sensor drivers and the hardware (or its emulator).

A driver sees a device as a small register file reached through two operations, which is all that
an I2C or SPI sensor such as the MMC5983MA needs (MMC5983MA datasheet Rev A, p9 and p17:
auto-incrementing multi-byte reads, single-byte writes). Anything that implements them can be
plugged under a driver: a Linux I2C/SPI device, a serial bridge (`fsw.drivers.serial_bus`) or the
register-level emulator (`hil.mmc5983ma`).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable


class BusError(Exception):
    """A transfer that failed: NAK, timeout, CRC error or a status error reported by a bridge."""


@runtime_checkable
class RegisterBus(Protocol):
    """Register-level access to one device."""

    def read_registers(self, address: int, count: int) -> bytes:
        """Burst-read `count` registers starting at `address` (the register pointer auto-increments).

        Raises BusError if the transfer fails; the returned object has exactly `count` bytes.
        """
        ...

    def write_register(self, address: int, value: int) -> None:
        """Write one byte `value` to register `address`. Raises BusError if the transfer fails."""
        ...
