"""Which bus the magnetometer is on, and opening it: a serial register bridge, Linux I2C or Linux SPI.

`MagBus` is what the command line (`--mag-serial` / `--mag-i2c` / `--mag-spi`) or the box's
configuration file (`fsw.box_config`) names; :func:`open_register_bus` opens it as a
`fsw.bus.RegisterBus`; :func:`bus_counters_line` says what failed on it, by kind, for the summary.
"""
from __future__ import annotations

from dataclasses import dataclass

from fsw.drivers.i2c_bus import MMC5983MA_I2C_ADDRESS
from fsw.drivers.spi_bus import DEFAULT_SPEED_HZ

KINDS = ("serial", "i2c", "spi")


@dataclass(frozen=True)
class MagBus:
    """The magnetometer's bus: `kind` one of KINDS, the device path, the I2C address, the SPI clock."""

    kind: str
    device: str
    i2c_address: int = MMC5983MA_I2C_ADDRESS
    spi_speed_hz: int = DEFAULT_SPEED_HZ

    def describe(self) -> str:
        if self.kind == "i2c":
            return f"I2C {self.device} at {self.i2c_address:#04x}"
        if self.kind == "spi":
            return f"SPI {self.device} mode 3 at {self.spi_speed_hz / 1e6:g} MHz"
        return f"serial register bridge {self.device}"


def open_register_bus(bus: MagBus):
    """The `RegisterBus` of `bus` (OSError if the device cannot be opened; `fsw.drivers.spi_bus.MissingLibrary`
    without spidev)."""
    if bus.kind == "i2c":
        from fsw.drivers.i2c_bus import I2cBus
        return I2cBus(bus.device, bus.i2c_address)
    if bus.kind == "spi":
        from fsw.drivers.spi_bus import SpiBus
        return SpiBus(bus.device, bus.spi_speed_hz)
    if bus.kind == "serial":
        from fsw.drivers.serial_bus import SerialBus
        return SerialBus(bus.device)
    raise ValueError(f"unknown magnetometer bus {bus.kind!r} (one of {', '.join(KINDS)})")


def bus_counters_line(register_bus) -> str | None:
    """'bus: N NACKs, N timeouts, N I/O errors' for a Linux bus; None for others."""
    c = getattr(register_bus, "counters", None)
    if c is None:
        return None
    return f"magnetometer bus: {c.nacks} NACKs, {c.timeouts} timeouts, {c.io_errors} I/O errors"
