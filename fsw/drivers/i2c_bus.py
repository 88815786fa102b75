"""`RegisterBus` on a Linux I2C adapter (/dev/i2c-N) through `smbus2`: the MMC5983MA at 0x30.

Framing (MMC5983MA datasheet Rev A, p17, "I2C interface"; `docs/spec/mmc5983ma.md` section 1):

- burst read of `count` registers from `address`: START, 0x30 W, `address`, repeated START, 0x30 R,
  `count` bytes (the register pointer auto-increments), STOP. Sent as one `i2c_rdwr` of two messages
  (a write of the register address, a read of `count` bytes), which the kernel turns into one
  combined transaction with a repeated start, so no other master can move the pointer in between and
  a 7-byte output burst (0x00-0x06) comes from one measurement;
- write of one register: START, 0x30 W, `address`, `value`, STOP: one `i2c_rdwr` write message.
  `i2c_rdwr` needs no I2C_SLAVE binding, so a kernel driver that claimed the address cannot make
  the write fail with EBUSY where the reads succeed.

The chip runs I2C at up to 400 kHz (DS p3); the adapter's clock is the kernel's (device tree,
e.g. `dtparam=i2c_arm_baudrate=400000` on a Raspberry Pi), not this module's.

A failed transfer (an OSError from the ioctl: EREMOTEIO/ENXIO for a NACK, ETIMEDOUT, EIO) is counted
by kind (`counters`, `fsw.drivers.linux_errors`) and raised as `BusError`, which the driver counts
and survives; a short read is the driver's to catch. `smbus2` is imported when a bus is opened.
"""
from __future__ import annotations

from fsw.bus import BusError
from fsw.drivers.linux_errors import TransferCounters

MMC5983MA_I2C_ADDRESS = 0x30


class I2cBus:
    """One I2C device at `address` on the adapter `device` (a path such as /dev/i2c-1)."""

    def __init__(self, device: str, address: int = MMC5983MA_I2C_ADDRESS) -> None:
        import smbus2  # noqa: PLC0415 - the library is the target's, imported when a bus is opened

        if not 0x08 <= address <= 0x77:
            raise ValueError(f"I2C address {address:#04x} outside 0x08...0x77")
        self.device = device
        self.address = int(address)
        self._msg = smbus2.i2c_msg
        self._bus = smbus2.SMBus(device)
        self.counters = TransferCounters()

    def read_registers(self, address: int, count: int) -> bytes:
        if not (0 <= address <= 0xFF and 1 <= count <= 0xFF):
            raise ValueError(f"bad read of {count} registers at {address}")
        read = self._msg.read(self.address, count)
        self._transfer(self._msg.write(self.address, [address]), read, what=f"read at {address:#04x}")
        return bytes(read)

    def write_register(self, address: int, value: int) -> None:
        if not (0 <= address <= 0xFF and 0 <= value <= 0xFF):
            raise ValueError(f"bad write of {value} at {address}")
        self._transfer(self._msg.write(self.address, [address, value]), what=f"write at {address:#04x}")

    def close(self) -> None:
        self._bus.close()

    def __enter__(self) -> I2cBus:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _transfer(self, *msgs, what: str) -> None:
        try:
            self._bus.i2c_rdwr(*msgs)
        except OSError as error:
            kind = self.counters.count(error)
            raise BusError(f"I2C {kind} on {self.device} at {self.address:#04x}, {what}: {error}") from error
