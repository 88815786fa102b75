"""`RegisterBus` on a Linux SPI device (/dev/spidevB.D) through `spidev`: the MMC5983MA on 4-wire SPI.

Framing (MMC5983MA datasheet Rev A, pp. 4-8, "SPI interface" and its timing diagrams;
`docs/spec/mmc5983ma.md` section 1):

- a frame is the first byte, MSB first: bit 7 R/W (1 = read), bit 6 don't care (sent 0), bits 5:0 the
  register address; then one data byte per register, 16 clocks for one register, 8 more for each
  further one (the address auto-increments on reads);
- read of `count` registers: `xfer2([0x80 | address, 0, ... 0])` (count zero bytes clocked out), the
  data are the `count` bytes received after the first; write: `xfer2([address, value])`. `xfer2`
  keeps chip select asserted over the whole frame;
- SCK idles high, data change on the falling edge and are sampled on the rising edge: SPI mode 3
  (CPOL 1, CPHA 1), from the same pages' timing diagrams. (SparkFun's library and ArduPilot run it
  in mode 0, which samples on the same edge; mode 3 is what the datasheet draws);
- t_SCK >= 100 ns, 10 MHz at most (DS pp. 4-8, SPI timing): `max_speed_hz` is refused above it; 4 MHz by default,
  ArduPilot's low speed, margin for wiring that is not a board trace.

SPI has no acknowledge: a missing chip reads 0xFF or 0x00, which the driver's Product ID check
catches. What the kernel reports (an OSError: EIO, ETIMEDOUT) is counted by kind (`counters`,
`fsw.drivers.linux_errors`) and raised as `BusError`. `spidev` needs a compiler and Linux headers: it
is the `target` extra (`pip install .[target]`), imported when a bus is opened; without it
:func:`require_spidev` names the missing package.
"""
from __future__ import annotations

import re

from fsw.bus import BusError
from fsw.drivers.linux_errors import TransferCounters

SPI_MODE = 3
READ_BIT = 0x80
ADDRESS_MASK = 0x3F
MAX_SPEED_HZ = 10_000_000
DEFAULT_SPEED_HZ = 4_000_000
_DEVICE = re.compile(r"^/dev/spidev(\d+)\.(\d+)$")


class MissingLibrary(RuntimeError):
    """A target library that is not installed; the message says which and how to install it."""


def require_spidev():
    """The `spidev` module, or MissingLibrary with a one-line explanation."""
    try:
        import spidev  # noqa: PLC0415 - the target extra, imported only when SPI is used
    except ImportError:
        raise MissingLibrary("SPI needs the spidev package, not installed: pip install '.[target]' in the "
                             "repository on the flight computer") from None
    return spidev


def spidev_numbers(device: str) -> tuple[int, int]:
    """(bus, chip select) of a device path /dev/spidevB.D (ValueError otherwise)."""
    m = _DEVICE.match(device)
    if not m:
        raise ValueError(f"{device!r} is not an SPI device path /dev/spidevB.D")
    return int(m.group(1)), int(m.group(2))


class SpiBus:
    """The device on `device` (/dev/spidevB.D) in mode 3 at `speed_hz` (<= 10 MHz)."""

    def __init__(self, device: str, speed_hz: int = DEFAULT_SPEED_HZ) -> None:
        if not 0 < speed_hz <= MAX_SPEED_HZ:
            raise ValueError(f"SPI clock {speed_hz} Hz outside 1...{MAX_SPEED_HZ} Hz (MMC5983MA DS pp. 4-8)")
        bus, cs = spidev_numbers(device)
        spi = require_spidev().SpiDev()
        spi.open(bus, cs)
        try:
            spi.mode = SPI_MODE
            spi.max_speed_hz = int(speed_hz)
            spi.bits_per_word = 8
        except BaseException:
            spi.close()
            raise
        self.device = device
        self._spi = spi
        self.counters = TransferCounters()

    def read_registers(self, address: int, count: int) -> bytes:
        if not (0 <= address <= ADDRESS_MASK and 1 <= count <= 0xFF):
            raise ValueError(f"bad read of {count} registers at {address}")
        rx = self._transfer([READ_BIT | address] + [0] * count, what=f"read at {address:#04x}")
        if len(rx) != count + 1:
            raise BusError(f"SPI {self.device}: {len(rx)} of {count + 1} bytes back")
        return bytes(rx[1:])

    def write_register(self, address: int, value: int) -> None:
        if not (0 <= address <= ADDRESS_MASK and 0 <= value <= 0xFF):
            raise ValueError(f"bad write of {value} at {address}")
        self._transfer([address, value], what=f"write at {address:#04x}")

    def close(self) -> None:
        self._spi.close()

    def __enter__(self) -> SpiBus:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _transfer(self, frame: list[int], *, what: str) -> list[int]:
        try:
            return self._spi.xfer2(frame)
        except OSError as error:
            kind = self.counters.count(error)
            raise BusError(f"SPI {kind} on {self.device}, {what}: {error}") from error
