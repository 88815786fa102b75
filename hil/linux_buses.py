"""The emulated MMC5983MA behind the calls of `smbus2.SMBus` and `spidev.SpiDev`.

`EmulatedSMBus` and `EmulatedSpiDev` stand where the kernel's I2C adapter and SPI controller are on
target, so the flight software's `fsw.drivers.i2c_bus` / `fsw.drivers.spi_bus` run their real code
(the real `smbus2.i2c_msg` structures included) against the register-level emulator. Each decodes
the wire framing of the MMC5983MA datasheet itself (DS p17 for I2C, pp. 4-8 for SPI) rather than
trusting the bus module's, keeps every transfer in `log` for byte-for-byte checks, and fails like a
kernel does: `fail_next` (a list of errno values, one transfer each) and `fail_rate` (seeded) raise
OSError(errno); the emulator's own NAK (power-on, injected bus faults) is EREMOTEIO on I2C, and on SPI
(no acknowledge) a read of 0xFF bytes.

`smbus_factory(chip)` / `spidev_module(chip)` give what a test installs in place of the libraries
(`monkeypatch.setattr(smbus2, "SMBus", ...)`, `sys.modules["spidev"] = ...`).
"""
from __future__ import annotations

import errno
import types

import numpy as np
from smbus2 import i2c_msg  # noqa: F401 - the real message structure the flight code builds
from smbus2.smbus2 import I2C_M_RD

from fsw.bus import BusError, RegisterBus

MMC5983MA_ADDRESS = 0x30


class _Faults:
    def __init__(self, rng: np.random.Generator | None) -> None:
        self.fail_next: list[int] = []
        self.fail_rate = 0.0
        self.fail_errno = errno.EIO
        self._rng = rng if rng is not None else np.random.default_rng(0)
        self.log: list[tuple] = []

    def _maybe_fail(self) -> None:
        if self.fail_next:
            code = self.fail_next.pop(0)
            raise OSError(code, errno.errorcode.get(code, str(code)))
        if self.fail_rate > 0.0 and self._rng.random() < self.fail_rate:
            raise OSError(self.fail_errno, errno.errorcode.get(self.fail_errno, ""))


class EmulatedSMBus(_Faults):
    """`smbus2.SMBus` on an I2C bus with `chip` at 0x30: `i2c_rdwr`, `write_byte_data`, `read_byte_data`,
    `read_i2c_block_data`, `close`."""

    def __init__(self, chip: RegisterBus, bus=None, *, rng: np.random.Generator | None = None) -> None:
        super().__init__(rng)
        self.chip = chip
        self.bus = bus
        self.closed = False

    def i2c_rdwr(self, *msgs) -> None:
        """A combined transaction: each message after the first begins with a repeated start."""
        self._maybe_fail()
        self.log.append(tuple((m.addr, m.flags, bytes(m)) if not m.flags & I2C_M_RD else
                              (m.addr, m.flags, m.len) for m in msgs))
        pointer = None
        for m in msgs:
            if m.addr != MMC5983MA_ADDRESS:
                raise OSError(errno.EREMOTEIO, "no device acknowledges this address")
            if m.flags & I2C_M_RD:
                if pointer is None:
                    raise OSError(errno.EIO, "read without a register address")  # the emulator's choice
                data = self._chip(lambda a=pointer, n=m.len: self.chip.read_registers(a, n))
                for i, b in enumerate(data):
                    m.buf[i] = bytes((b,))
                pointer = (pointer + m.len) & 0xFF
            else:
                payload = bytes(m)
                pointer = payload[0]
                for offset, value in enumerate(payload[1:]):  # single-byte writes are what the DS shows
                    self._chip(lambda a=pointer + offset, v=value: self.chip.write_register(a, v))

    def write_byte_data(self, i2c_addr: int, register: int, value: int, force=None) -> None:
        self.i2c_rdwr(i2c_msg.write(i2c_addr, [register, value]))

    def read_byte_data(self, i2c_addr: int, register: int, force=None) -> int:
        return self.read_i2c_block_data(i2c_addr, register, 1)[0]

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int, force=None) -> list[int]:
        read = i2c_msg.read(i2c_addr, length)
        self.i2c_rdwr(i2c_msg.write(i2c_addr, [register]), read)
        return list(read)

    def close(self) -> None:
        self.closed = True

    @staticmethod
    def _chip(call):
        try:
            return call()
        except BusError as error:
            raise OSError(errno.EREMOTEIO, f"NACK: {error}") from error


class EmulatedSpiDev(_Faults):
    """`spidev.SpiDev` with `chip` on its chip select: `open`, `close`, `xfer2`, `mode`, `max_speed_hz`,
    `bits_per_word`. The frame is decoded as the datasheet draws it (16 clocks + 8 per extra byte,
    first byte R/W | don't care | A5..A0)."""

    def __init__(self, chip: RegisterBus, *, rng: np.random.Generator | None = None) -> None:
        super().__init__(rng)
        self.chip = chip
        self.mode = 0
        self.max_speed_hz = 125_000_000  # spidev's default before it is set
        self.bits_per_word = 8
        self.opened: tuple[int, int] | None = None
        self.closed = False

    def open(self, bus: int, device: int) -> None:
        self.opened = (bus, device)

    def close(self) -> None:
        self.closed = True

    def xfer2(self, values: list[int]) -> list[int]:
        self._maybe_fail()
        frame = bytes(values)
        self.log.append((self.mode, self.max_speed_hz, frame))
        if len(frame) < 2:
            return [0xFF] * len(frame)
        address = frame[0] & 0x3F
        try:
            if frame[0] & 0x80:
                return [0xFF, *self.chip.read_registers(address, len(frame) - 1)]
            for i, value in enumerate(frame[1:]):
                self.chip.write_register(address + i, value)
        except BusError:
            pass  # no acknowledge on SPI: the chip just does not drive MISO
        return [0xFF] * len(frame)


def smbus_factory(chip: RegisterBus, *, rng: np.random.Generator | None = None, opened: list | None = None):
    """A stand-in for the class `smbus2.SMBus`: each call opens an `EmulatedSMBus` on `chip` (appended to
    `opened`, so that a test reaches the instance the flight software made)."""
    def make(bus=None, force=False):
        smbus = EmulatedSMBus(chip, bus, rng=rng)
        if opened is not None:
            opened.append(smbus)
        return smbus
    return make


def spidev_module(chip: RegisterBus, *, rng: np.random.Generator | None = None, opened: list | None = None):
    """A stand-in for the module `spidev` whose `SpiDev()` is an `EmulatedSpiDev` on `chip`."""
    def make():
        dev = EmulatedSpiDev(chip, rng=rng)
        if opened is not None:
            opened.append(dev)
        return dev
    return types.SimpleNamespace(SpiDev=make)
