"""End to end on target: `fsw.main --mag-i2c` / `--mag-spi` run the flight software through the real I2C
(smbus2 `i2c_rdwr`) and SPI (spidev `xfer2`) code paths, the libraries' device calls answered by the
emulated chip (`hil.linux_buses`), with injected kernel errors counted, not raised."""
import errno
import re
import sys
import time

import numpy as np
import pytest
import smbus2

from fsw import main as fsw_main
from hil.linux_buses import smbus_factory, spidev_module
from hil.mmc5983ma import EmulatedMmc5983ma
from support import free_udp_port

B_TRUE_T = np.array([20e-6, -5e-6, 45e-6])


def emulated_chip():
    t0 = time.monotonic()
    return EmulatedMmc5983ma(lambda t: B_TRUE_T, lambda: time.monotonic() - t0, np.random.default_rng(5))


def run_target(option, device, capsys):
    status = fsw_main.main([option, device, "--link", f"udpout:127.0.0.1:{free_udp_port()}", "--rate", "100",
                            "--sample-rate", "50", "--duration", "3", "--quiet"])
    return status, capsys.readouterr()


def counts(text):
    m = re.search(r"magnetometer: (\d+) samples, (\d+) bus errors", text)
    b = re.search(r"magnetometer bus: (\d+) NACKs, (\d+) timeouts, (\d+) I/O errors", text)
    return int(m.group(1)), int(m.group(2)), tuple(int(x) for x in b.groups())


def test_fsw_main_on_i2c(monkeypatch, capsys):
    opened = []
    monkeypatch.setattr(smbus2, "SMBus", smbus_factory(emulated_chip(), opened=opened,
                                                         rng=np.random.default_rng(7)))
    status, out = run_target("--mag-i2c", "/dev/i2c-1", capsys)
    assert status == 0, out.err
    samples, bus_errors, failed = counts(out.out)
    assert samples >= 120 and bus_errors == 0 and failed == (0, 0, 0)   # 3 s at 50 Hz, start-up aside
    (smbus,) = opened
    assert smbus.bus == "/dev/i2c-1" and smbus.closed
    bursts = [t for t in smbus.log if len(t) == 2 and t[0][2] == b"\x00"]
    assert len(bursts) >= samples and all(t[1] == (0x30, smbus2.smbus2.I2C_M_RD, 7) for t in bursts)


def test_fsw_main_on_i2c_counts_kernel_errors(monkeypatch, capsys):
    opened = []
    make = smbus_factory(emulated_chip(), opened=opened, rng=np.random.default_rng(7))

    def flaky(bus=None, force=False):
        smbus = make(bus)
        smbus.fail_rate, smbus.fail_errno = 0.05, errno.EREMOTEIO
        smbus.fail_next = [errno.EIO, errno.ETIMEDOUT]
        return smbus
    monkeypatch.setattr(smbus2, "SMBus", flaky)
    status, out = run_target("--mag-i2c", "/dev/i2c-1", capsys)
    assert status == 0 and "Traceback" not in out.err
    samples, bus_errors, (nacks, timeouts, io_errors) = counts(out.out)
    assert (timeouts, io_errors) == (1, 1) and nacks >= 10
    assert bus_errors == nacks + timeouts + io_errors and samples >= 100


def test_fsw_main_on_spi(monkeypatch, capsys):
    opened = []
    monkeypatch.setitem(sys.modules, "spidev", spidev_module(emulated_chip(), opened=opened))
    status, out = run_target("--mag-spi", "/dev/spidev0.0", capsys)
    assert status == 0, out.err
    samples, bus_errors, failed = counts(out.out)
    assert samples >= 120 and bus_errors == 0 and failed == (0, 0, 0)
    (dev,) = opened
    assert dev.opened == (0, 0) and dev.closed
    assert {(mode, hz) for mode, hz, _ in dev.log} == {(3, 4_000_000)}
    assert sum(frame == bytes([0x80]) + bytes(7) for _, _, frame in dev.log) >= samples


def test_spi_without_spidev_is_one_line(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "spidev", None)
    with pytest.raises(SystemExit) as e:
        fsw_main.main(["--mag-spi", "/dev/spidev0.0", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and "--mag-spi" in err[-1] and "spidev" in err[-1] and "Traceback" not in "".join(err)


@pytest.mark.parametrize("argv", [["--mag-i2c", "/dev/i2c-1", "--mag-serial", "/dev/ttyUSB0"],
                                  ["--mag-spi", "/dev/spidev0.0", "--mag-i2c", "/dev/i2c-1"],
                                  ["--mag-spi", "/dev/i2c-1"], []])
def test_bus_options_are_checked(argv, capsys):
    with pytest.raises(SystemExit) as e:
        fsw_main.main([*argv, "--quiet"])
    assert e.value.code == 2 and "Traceback" not in capsys.readouterr().err


def test_missing_i2c_adapter_is_one_line(capsys, tmp_path):
    assert fsw_main.main(["--mag-i2c", str(tmp_path / "i2c-9"), "--quiet", "--duration", "1"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "i2c-9" in err[0]
