"""The MMC5983MA on Linux I2C (smbus2) and SPI (spidev) buses: the flight code's transfers checked byte for
byte against the datasheet's framing (DS p17 for I2C, pp. 4-8 for SPI), through stand-ins of the
libraries' calls on the register-level emulator; failed transfers counted by kind and by the driver,
never raised out of it."""
import errno
import sys

import numpy as np
import pytest
import smbus2
from smbus2.smbus2 import I2C_M_RD

from fsw.bus import BusError
from fsw.drivers.i2c_bus import I2cBus
from fsw.drivers.mmc5983ma import MagState, Mmc5983ma
from fsw.drivers.mmc5983ma_regs import TESLA_PER_COUNT_18
from fsw.drivers.spi_bus import MissingLibrary, SpiBus, require_spidev, spidev_numbers
from hil.linux_buses import EmulatedSMBus, smbus_factory, spidev_module
from hil.mmc5983ma import EmulatedMmc5983ma

B_TRUE_T = np.array([20e-6, -5e-6, 45e-6])
SIGMA_T = 0.6e-7  # BW 100 Hz noise 0.6 mG


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def chip(clock, seed=1):
    return EmulatedMmc5983ma(lambda t: B_TRUE_T, clock, np.random.default_rng(seed))


@pytest.fixture
def i2c(monkeypatch):
    clock = Clock()
    emu, opened = chip(clock), []
    monkeypatch.setattr(smbus2, "SMBus", smbus_factory(emu, opened=opened, rng=np.random.default_rng(3)))
    bus = I2cBus("/dev/i2c-1")
    return bus, opened[0], emu, clock


@pytest.fixture
def spi(monkeypatch):
    clock = Clock()
    emu, opened = chip(clock), []
    monkeypatch.setitem(sys.modules, "spidev", spidev_module(emu, opened=opened, rng=np.random.default_rng(3)))
    bus = SpiBus("/dev/spidev0.1")
    return bus, opened[0], emu, clock


def run(driver, clock, duration_s, dt=1e-3):
    n = 0
    for _ in range(round(duration_s / dt)):
        clock.t += dt
        n += driver.update(clock.t)
    return n


# --- framing ------------------------------------------------------------------------------------------


def test_i2c_burst_read_is_one_combined_transaction_with_a_repeated_start(i2c):
    bus, smbus, emu, clock = i2c
    assert bus.read_registers(0x2F, 1) == b"\x30"                      # Product ID 1 (DS p16)
    bus.write_register(0x09, 0x01)                                       # TM_M
    clock.t += 0.02
    burst = bus.read_registers(0x00, 7)
    # write of the register pointer, then (repeated start) a read of 7 bytes, both at 0x30: DS p17
    assert smbus.log == [((0x30, 0, b"\x2f"), (0x30, I2C_M_RD, 1)),
                         ((0x30, 0, b"\x09\x01"),),
                         ((0x30, 0, b"\x00"), (0x30, I2C_M_RD, 7))]
    assert burst == emu.read_registers(0x00, 7)                          # the chip's own outputs
    counts = [(burst[2 * i] << 10) | (burst[2 * i + 1] << 2) | (burst[6] >> (6 - 2 * i) & 3) for i in range(3)]
    # RESET polarity after power-on (the emulator's choice): -H + offset
    field = (np.array(counts) - 131072) * TESLA_PER_COUNT_18
    np.testing.assert_allclose(field, -B_TRUE_T + emu.bridge_offset_T, atol=6 * SIGMA_T)


def test_smbus_stand_in_answers_the_smbus_calls(i2c):
    _, smbus, emu, _ = i2c
    assert smbus.read_byte_data(0x30, 0x2F) == 0x30
    smbus.write_byte_data(0x30, 0x0A, 0x01)
    assert emu.bandwidth == 1
    assert smbus.read_i2c_block_data(0x30, 0x2F, 1) == [0x30]
    with pytest.raises(OSError) as e:
        smbus.read_byte_data(0x31, 0x2F)
    assert e.value.errno == errno.EREMOTEIO


def test_spi_frames_are_the_datasheets(spi):
    bus, dev, emu, clock = spi
    assert (dev.opened, dev.mode, dev.max_speed_hz, dev.bits_per_word) == ((0, 1), 3, 4_000_000, 8)
    assert bus.read_registers(0x2F, 1) == b"\x30"
    bus.write_register(0x0A, 0x80)                                       # SW_RST
    clock.t += 0.02
    bus.write_register(0x09, 0x01)
    clock.t += 0.02
    assert bus.read_registers(0x00, 7) == emu.read_registers(0x00, 7)
    # first byte R/W (1 = read) | don't care | A5..A0, one data byte per register: DS pp. 4-8
    assert [frame for _, _, frame in dev.log] == [bytes([0xAF, 0]), bytes([0x0A, 0x80]), bytes([0x09, 0x01]),
                                                 bytes([0x80]) + bytes(7)]
    assert all((mode, hz) == (3, 4_000_000) for mode, hz, _ in dev.log)


def test_spi_clock_above_the_datasheets_10_mhz_and_bad_paths_refused(spi):
    with pytest.raises(ValueError, match="10000000"):
        SpiBus("/dev/spidev0.0", speed_hz=12_000_000)
    assert spidev_numbers("/dev/spidev1.2") == (1, 2)
    for bad in ("/dev/i2c-1", "/dev/spidev0", "spidev0.0"):
        with pytest.raises(ValueError):
            spidev_numbers(bad)
    with pytest.raises(ValueError):
        spi[0].read_registers(0x40, 1)  # six address bits


def test_missing_spidev_is_named(monkeypatch):
    monkeypatch.setitem(sys.modules, "spidev", None)
    with pytest.raises(MissingLibrary, match="spidev.*target"):
        require_spidev()


# --- failures -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["i2c", "spi"])
def test_kernel_errors_are_counted_by_kind_and_raised_as_bus_errors(kind, request):
    bus, dev, _, _ = request.getfixturevalue(kind)
    dev.fail_next = [errno.EIO, errno.EREMOTEIO, errno.ETIMEDOUT, errno.ENXIO, errno.EIO]
    for _ in range(5):
        with pytest.raises(BusError):
            bus.read_registers(0x00, 7)
    c = bus.counters
    assert (c.nacks, c.timeouts, c.io_errors) == (2, 1, 2)
    assert bus.read_registers(0x2F, 1) == b"\x30"


@pytest.mark.parametrize("kind", ["i2c", "spi"])
def test_driver_on_a_flaky_linux_bus_counts_every_failure_and_keeps_measuring(kind, request):
    bus, dev, emu, clock = request.getfixturevalue(kind)
    driver = Mmc5983ma(bus, sample_period_s=0.01, calibration_interval=50)
    run(driver, clock, 0.5)
    dev.fail_rate, dev.fail_errno = 0.1, errno.EREMOTEIO if kind == "i2c" else errno.EIO
    failed_before = bus.counters.nacks + bus.counters.timeouts + bus.counters.io_errors
    errors_before = driver.bus_errors
    dev.fail_next = [errno.ETIMEDOUT] * 3
    samples = []
    for _ in range(2000):
        clock.t += 1e-3
        if driver.update(clock.t):
            samples.append(driver.b_body_T - B_TRUE_T)
    failed = bus.counters.nacks + bus.counters.timeouts + bus.counters.io_errors - failed_before
    assert failed >= 50 and bus.counters.timeouts == 3
    assert driver.bus_errors - errors_before == failed         # each failed transfer counted once by the driver
    assert len(samples) > 120 and driver.state is MagState.MEASURE
    assert np.abs(np.array(samples)).max() < 6 * SIGMA_T + 2e-7
    assert emu.write_only_reads == 0


def test_i2c_chip_in_power_on_does_not_acknowledge(i2c):
    bus, _, emu, clock = i2c
    emu.power_cycle()
    with pytest.raises(BusError, match="NACK"):
        bus.read_registers(0x2F, 1)
    assert bus.counters.nacks == 1
    clock.t += 0.011
    assert bus.read_registers(0x2F, 1) == b"\x30"


def test_closed_with_the_bus(i2c):
    bus, smbus, _, _ = i2c
    assert isinstance(smbus, EmulatedSMBus)
    bus.close()
    assert smbus.closed
