"""Serial bridge protocol, and the driver over SerialBus over a real pty to the emulated MMC5983MA."""

import time

import numpy as np
import pytest

from fsw.bus import BusError, RegisterBus
from fsw.drivers.mmc5983ma import MagState, Mmc5983ma
from fsw.drivers.mmc5983ma_regs import Bandwidth, Register
from fsw.drivers.serial_bus import (
    OP_READ,
    OP_WRITE,
    RESPONSE_SYNC,
    STATUS_BAD_REQUEST,
    STATUS_DEVICE_FAULT,
    STATUS_NAK,
    STATUS_OK,
    SerialBus,
    crc8,
    encode_request,
    encode_response,
)
from hil.mmc5983ma import EmulatedMmc5983ma
from hil.pty_link import PtyBridge, serve_request, split_requests

B_TRUE_T = np.array([20e-6, -5e-6, 45e-6])
TIMEOUT_S = 0.2  # generous: the machine may be busy; only the drop test waits for it


def test_crc8_smbus_check_value_and_chaining():
    assert crc8(b"123456789") == 0xF4
    assert crc8(b"") == 0
    assert crc8(b"6789", crc8(b"12345")) == 0xF4


def test_frame_layout():
    assert encode_request(OP_READ, 0x00, 7) == bytes((0xA5, 0x52, 0x00, 0x07, crc8(b"\x52\x00\x07")))
    response = encode_response(b"\x52\x2f\x01", STATUS_OK, b"\x30")
    assert response[:3] == bytes((RESPONSE_SYNC, STATUS_OK, 0x30))
    assert response[3] == crc8(b"\x52\x2f\x01\x00\x30")
    # the CRC binds a response to its request: the same bytes do not check against another request
    assert response[3] != crc8(b"\x00\x30", crc8(b"\x52\x08\x01"))


def test_split_requests_resynchronises():
    good1, good2 = encode_request(OP_READ, 0x2F, 1), encode_request(OP_WRITE, 0x09, 0x01)
    corrupted = bytearray(encode_request(OP_READ, 0x00, 7))
    corrupted[3] ^= 0x04
    buffer = bytearray(b"\x00\xff" + good1 + bytes(corrupted) + good2 + good1[:3])
    assert split_requests(buffer) == [good1[1:4], good2[1:4]]
    assert buffer == good1[:3]  # the incomplete frame waits for its tail
    buffer += good1[3:]
    assert split_requests(buffer) == [good1[1:4]] and buffer == b""


class _Device:
    def __init__(self, error=None):
        self.error = error
        self.writes = []

    def read_registers(self, address, count):
        if self.error:
            raise self.error
        return bytes(range(address, address + count))

    def write_register(self, address, value):
        if self.error:
            raise self.error
        self.writes.append((address, value))


@pytest.mark.parametrize(
    "device, body, status, data",
    [
        (_Device(), bytes((OP_READ, 3, 4)), STATUS_OK, bytes((3, 4, 5, 6))),
        (_Device(), bytes((OP_WRITE, 9, 1)), STATUS_OK, b""),
        (_Device(BusError("nak")), bytes((OP_READ, 0, 7)), STATUS_NAK, b""),
        (_Device(), bytes((0x00, 0, 7)), STATUS_BAD_REQUEST, b""),
        (_Device(), bytes((OP_READ, 0, 0)), STATUS_BAD_REQUEST, b""),
        (_Device(RuntimeError("bug")), bytes((OP_WRITE, 9, 1)), STATUS_DEVICE_FAULT, b""),
    ],
)
def test_serve_request(device, body, status, data):
    assert serve_request(device, body) == encode_response(body, status, data)


@pytest.fixture
def link():
    t0 = time.monotonic()

    def clock():  # the real-time edge: the emulator runs on the wall clock here
        return time.monotonic() - t0

    emu = EmulatedMmc5983ma(lambda t: B_TRUE_T, clock, np.random.default_rng(5))
    bridge = PtyBridge(emu, rng=np.random.default_rng(6))
    with bridge, SerialBus(bridge.port_name, timeout_s=TIMEOUT_S) as bus:
        yield emu, bridge, bus, clock


def test_serial_bus_register_access(link):
    emu, bridge, bus, _ = link
    assert isinstance(bus, RegisterBus)
    assert bus.read_registers(Register.PRODUCT_ID_1, 1) == b"\x30"
    bus.write_register(Register.STATUS, 0x01)
    assert bus.read_registers(Register.STATUS, 1) == b"\x10"
    assert len(bus.read_registers(Register.XOUT0, 9)) == 9
    assert bridge.requests == 4 and emu.transfers == 4


def test_device_nak_is_a_bus_error(link):
    emu, _, bus, _ = link
    emu.fault_bus_error_rate = 1.0
    with pytest.raises(BusError, match="NAK"):
        bus.read_registers(Register.PRODUCT_ID_1, 1)
    emu.fault_bus_error_rate = 0.0
    assert bus.read_registers(Register.PRODUCT_ID_1, 1) == b"\x30"
    assert bus.status_errors == 1


@pytest.mark.parametrize("fault", ["corrupt", "drop"])
def test_link_faults_raise_then_resynchronise(link, fault):
    _, bridge, bus, _ = link
    for _ in range(5):  # corruption may hit any byte, SYNC included
        if fault == "corrupt":
            bridge.corrupt_next = 1
        else:
            bridge.drop_rate = 1.0
        with pytest.raises(BusError):
            bus.read_registers(Register.XOUT0, 7)
        bridge.drop_rate = 0.0
        assert bus.read_registers(Register.PRODUCT_ID_1, 1) == b"\x30"
    if fault == "corrupt":
        assert bridge.corrupted == 5 and bus.crc_errors + bus.timeouts == 5
    else:
        assert bridge.dropped == 5 and bus.timeouts == 5


def test_driver_over_pty_reads_the_field_and_survives_a_corrupted_response(link):
    emu, bridge, bus, clock = link
    driver = Mmc5983ma(bus)

    def run_until(samples):
        deadline = clock() + 20.0  # guard only; the assertions are on counts, not on time
        while driver.samples < samples and clock() < deadline:
            driver.update(clock())
            time.sleep(2e-4)

    run_until(30)
    assert driver.state is MagState.MEASURE and driver.resets == 1 and driver.bad_id == 0
    sigma = Bandwidth.BW_100HZ.noise_rms_T
    np.testing.assert_allclose(driver.offset_T, emu.bridge_offset_T, atol=5 * sigma)
    np.testing.assert_allclose(driver.b_body_T, B_TRUE_T, atol=7 * sigma)
    errors_before = driver.bus_errors
    bridge.corrupt_next = 1
    run_until(driver.samples + 20)
    assert bridge.corrupted == 1 and bus.crc_errors + bus.timeouts >= 1
    assert driver.bus_errors >= errors_before + 1 and driver.state is MagState.MEASURE
    np.testing.assert_allclose(driver.b_body_T, B_TRUE_T, atol=7 * sigma)
    assert emu.write_only_reads == 0


@pytest.mark.parametrize("offset_s, drift_ppm", [(0.0, 0.0), (2.0, 1000.0), (-2.0, -500.0)])
def test_the_real_time_device_runs_the_world_on_the_box_s_clock(offset_s, drift_ppm):
    """Behind the pty the wall clock is the box's: with a scenario's [clock] the world is advanced to the
    true time at which the box's clock reads what it reads (hil.sitl's mapping: the box starts reading
    max(0, offset) when the world starts)."""
    import dataclasses

    from hil import scenario
    from hil.box_clock import BoxClock
    from hil.pty_link import RealTimeDevice
    from hil.sim import Simulator

    clock = BoxClock(offset_s=offset_s, drift_ppm=drift_ppm)
    sim = Simulator(dataclasses.replace(scenario.load("isoi"), clock=clock), seed=0, max_step_s=0.05)
    wall = [100.0]
    dev = RealTimeDevice(sim, clock=lambda: wall[0])
    wall[0] += 10.0
    dev.read_registers(0x08, 1)
    box_reads = max(0.0, offset_s) + 10.0
    assert sim.t_s == pytest.approx((box_reads - offset_s) / (1 + drift_ppm * 1e-6), abs=1e-9)
    assert clock.start_s == max(0.0, offset_s)
