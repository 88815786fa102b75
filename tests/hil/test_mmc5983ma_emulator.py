"""The MMC5983MA emulator against datasheet behaviours one by one, then in closed loop with the driver."""

import math

import numpy as np
import pytest

from fsw.bus import BusError, RegisterBus
from fsw.drivers.mmc5983ma import MagState, Mmc5983ma
from fsw.drivers.mmc5983ma_regs import (
    COUNTS_MAX_18,
    TESLA_PER_COUNT_18,
    Bandwidth,
    ContinuousFrequency,
    InternalControl0,
    InternalControl1,
    InternalControl2,
    Register,
    Status,
    decode_field_T,
    decode_xyz18,
    tout_to_celsius,
)
from hil.mmc5983ma import DEFAULT_BRIDGE_OFFSET_T, TEMPERATURE_MEASUREMENT_TIME_S, EmulatedMmc5983ma

B_TRUE_T = np.array([20e-6, -5e-6, 45e-6])
LSB_T = TESLA_PER_COUNT_18
TM_M = int(InternalControl0.TM_M)
SET = int(InternalControl0.SET)
RESET = int(InternalControl0.RESET)
CTRL0, CTRL1, CTRL2, CTRL3 = (int(r) for r in (Register.INTERNAL_CONTROL_0, Register.INTERNAL_CONTROL_1,
                                                Register.INTERNAL_CONTROL_2, Register.INTERNAL_CONTROL_3))
STATUS = int(Register.STATUS)


class Clock:
    def __init__(self, t: float = 1.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def make(field=lambda t: B_TRUE_T, seed=1, **kwargs):
    clock = Clock()
    return EmulatedMmc5983ma(field, clock, np.random.default_rng(seed), **kwargs), clock


def status(emu) -> int:
    return emu.read_registers(STATUS, 1)[0]


def measure(emu, clock, command=TM_M) -> np.ndarray:
    """One single measurement: TM_M, advance past the measurement time, decode."""
    emu.write_register(CTRL0, command)
    clock.t += emu.bandwidth.measurement_time_s + 1e-6
    assert status(emu) & Status.MEAS_M_DONE
    return decode_field_T(emu.read_registers(Register.XOUT0, 7), np.zeros(3))


def test_satisfies_register_bus():
    emu, _ = make()
    assert isinstance(emu, RegisterBus)


def test_product_id():
    emu, _ = make()
    assert emu.read_registers(Register.PRODUCT_ID_1, 1) == b"\x30"


@pytest.mark.parametrize(
    "register, values",
    [(CTRL0, (0x00, 0x20, 0x04)), (CTRL1, (0x00, 0x03, 0x1C)), (CTRL2, (0x00, 0x70)), (CTRL3, (0x02, 0x40))],
)
def test_control_registers_are_write_only(register, values):
    emu, _ = make()
    assert emu.read_registers(register, 1) != b"\x00"  # power-on value 0x00 is not what reads back
    for value in values:
        emu.write_register(register, value)
        assert emu.read_registers(register, 1)[0] != value
    assert emu.write_only_reads == len(values) + 1
    emu.read_registers(Register.XOUT0, 9)  # outputs, Tout and Status do not touch them
    assert emu.write_only_reads == len(values) + 1


@pytest.mark.parametrize("bw", list(Bandwidth))
def test_measurement_time_and_done_flag(bw):
    emu, clock = make()
    emu.write_register(CTRL1, int(bw))
    measure(emu, clock)
    assert status(emu) & Status.MEAS_M_DONE  # stays 1 until the next command
    t0 = clock.t
    emu.write_register(CTRL0, TM_M)
    assert not status(emu) & Status.MEAS_M_DONE  # 0 at the command
    clock.t = t0 + bw.measurement_time_s - 1e-6
    assert not status(emu) & Status.MEAS_M_DONE
    clock.t = t0 + bw.measurement_time_s + 1e-9
    assert status(emu) & Status.MEAS_M_DONE


def test_tm_m_during_a_measurement_is_ignored():
    emu, clock = make()
    t0 = clock.t
    emu.write_register(CTRL0, TM_M)
    clock.t = t0 + 0.002
    emu.write_register(CTRL0, TM_M)
    clock.t = t0 + 0.008 + 1e-9  # done at the first command's time, not t0 + 10 ms
    assert status(emu) & Status.MEAS_M_DONE
    assert emu.measurements == 1


def test_writing_one_clears_done_bits():
    emu, clock = make()
    measure(emu, clock)
    emu.write_register(STATUS, 0x02)  # clearing Meas_T_Done leaves Meas_M_Done
    assert status(emu) & Status.MEAS_M_DONE
    emu.write_register(STATUS, int(Status.MEAS_M_DONE))
    assert status(emu) == Status.OTP_READ_DONE


def test_power_on_polarity_is_reset_and_set_reset_algebra():
    """Power-on polarity RESET (modelling choice): without SET the axes read inverted [DS p18]."""
    offset = np.array(DEFAULT_BRIDGE_OFFSET_T)
    emu, clock = make()
    assert emu.polarity == -1
    tol = 5 * Bandwidth.BW_100HZ.noise_rms_T + LSB_T
    np.testing.assert_allclose(measure(emu, clock), -B_TRUE_T + offset, atol=tol)
    s = measure(emu, clock, SET | TM_M)  # a pulse written with TM_M is applied first
    assert emu.polarity == +1
    np.testing.assert_allclose(s, B_TRUE_T + offset, atol=tol)
    emu.write_register(CTRL0, RESET)
    assert emu.polarity == -1
    r = measure(emu, clock)
    np.testing.assert_allclose((s - r) / 2, B_TRUE_T, atol=tol)
    np.testing.assert_allclose((s + r) / 2, offset, atol=tol)


def test_field_is_sampled_mid_window():
    k = 2e-3  # T/s along X: 16 mG across an 8 ms window
    emu, clock = make(field=lambda t: np.array([k * (t - 1.0), 0.0, 0.0]), bridge_offset_T=(0, 0, 0))
    emu.write_register(CTRL0, SET)
    b = measure(emu, clock)  # TM_M at t = 1.0
    tm = Bandwidth.BW_100HZ.measurement_time_s
    assert b[0] == pytest.approx(k * tm / 2, abs=5 * Bandwidth.BW_100HZ.noise_rms_T + LSB_T)


def test_output_layout_is_18_bit_offset_binary():
    emu, clock = make(bridge_offset_T=(0, 0, 0))
    emu.write_register(CTRL0, SET)
    emu.write_register(CTRL0, TM_M)
    clock.t += 0.01
    raw = emu.read_registers(Register.XOUT0, 7)
    assert raw[6] & 0x03 == 0
    counts = np.array(decode_xyz18(raw))
    expected = B_TRUE_T / LSB_T + 131072
    np.testing.assert_allclose(counts, expected, atol=5 * Bandwidth.BW_100HZ.noise_rms_T / LSB_T + 1)
    # the 16-bit view is the top 16 bits of the same counts
    assert [(raw[2 * i] << 8) | raw[2 * i + 1] for i in range(3)] == [int(c) >> 2 for c in counts]


@pytest.mark.parametrize("bw", list(Bandwidth))
def test_noise_matches_datasheet_per_bandwidth(bw):
    emu, clock = make(field=lambda t: np.zeros(3), seed=7)
    emu.write_register(CTRL1, int(bw))
    samples = np.array([measure(emu, clock) for _ in range(400)])
    sigma = samples.std(axis=0, ddof=1)  # per axis: 3.5 % standard error
    np.testing.assert_allclose(sigma, bw.noise_rms_T, rtol=0.15)
    np.testing.assert_allclose(samples.mean(axis=0), emu.bridge_offset_T, atol=5 * bw.noise_rms_T / 20)


def test_extra_noise_adds_in_quadrature():
    extra = 1e-7  # 1 mG
    emu, clock = make(field=lambda t: np.zeros(3), seed=8, extra_noise_T=extra)
    samples = np.array([measure(emu, clock) for _ in range(400)])
    expected = math.hypot(Bandwidth.BW_100HZ.noise_rms_T, extra)  # 1.077 mG
    np.testing.assert_allclose(samples.std(axis=0, ddof=1), expected, rtol=0.15)


def test_saturation_clips_at_full_scale():
    emu, clock = make(field=lambda t: np.array([1e-3, -1e-3, 0.0]), bridge_offset_T=(0, 0, 0))  # +-10 G
    emu.write_register(CTRL0, SET)
    emu.write_register(CTRL0, TM_M)
    clock.t += 0.01
    cx, cy, cz = decode_xyz18(emu.read_registers(Register.XOUT0, 7))
    assert (cx, cy) == (COUNTS_MAX_18, 0)
    assert abs(cz - 131072) < 5 * Bandwidth.BW_100HZ.noise_rms_T / LSB_T


def test_soft_reset_is_a_power_on():
    emu, clock = make()
    emu.write_register(CTRL1, int(Bandwidth.BW_800HZ))
    measure(emu, clock, SET | TM_M)
    assert emu.polarity == +1
    t0 = clock.t
    emu.write_register(CTRL1, int(InternalControl1.SW_RST))
    for dt in (0.0, 0.005, 0.0099):
        clock.t = t0 + dt
        with pytest.raises(BusError):
            emu.read_registers(Register.PRODUCT_ID_1, 1)
        with pytest.raises(BusError):
            emu.write_register(CTRL0, TM_M)
    clock.t = t0 + 0.0101
    assert emu.read_registers(Register.PRODUCT_ID_1, 1) == b"\x30"
    assert status(emu) == Status.OTP_READ_DONE
    assert emu.read_registers(Register.XOUT0, 7) == bytes(7)
    assert emu.polarity == -1 and emu.bandwidth is Bandwidth.BW_100HZ  # registers back to 0x00
    t1 = clock.t
    emu.write_register(CTRL0, TM_M)
    clock.t = t1 + 0.0079
    assert not status(emu) & Status.MEAS_M_DONE  # 8 ms again


def test_power_cycle_is_unresponsive_for_power_on_time():
    emu, clock = make()
    emu.power_cycle()
    with pytest.raises(BusError):
        emu.read_registers(Register.PRODUCT_ID_1, 1)
    clock.t += 0.0101
    assert emu.read_registers(Register.PRODUCT_ID_1, 1) == b"\x30"


@pytest.mark.parametrize(
    "freq, bw, period",
    [
        (ContinuousFrequency.HZ_100, Bandwidth.BW_100HZ, 0.010),
        (ContinuousFrequency.HZ_200, Bandwidth.BW_200HZ, 0.005),
        (ContinuousFrequency.HZ_200, Bandwidth.BW_100HZ, 0.008),  # the BW limits the rate
        (ContinuousFrequency.HZ_1000, Bandwidth.BW_800HZ, 0.001),
        (ContinuousFrequency.HZ_1000, Bandwidth.BW_400HZ, 0.002),
    ],
)
def test_continuous_mode_rate(freq, bw, period):
    emu, clock = make()
    emu.write_register(CTRL1, int(bw))
    t0 = clock.t
    emu.write_register(CTRL2, int(InternalControl2.CMM_EN) | int(freq))
    dt, duration = 1e-4, 0.05
    done_times = []
    for k in range(1, round(duration / dt) + 1):
        clock.t = t0 + k * dt
        if status(emu) & Status.MEAS_M_DONE:
            done_times.append(clock.t - t0)
            emu.write_register(STATUS, int(Status.MEAS_M_DONE))
    tm = bw.measurement_time_s
    expected = [tm + i * period for i in range(int((duration - tm) / period + 1e-9) + 1)]
    np.testing.assert_allclose(done_times, expected, atol=dt + 1e-9)
    emu.write_register(CTRL0, TM_M)  # ignored: continuous mode owns the converter
    assert emu.measurements == len(expected)
    emu.write_register(CTRL2, 0)  # Cmm_en off: no more measurements
    clock.t += 0.1
    assert not status(emu) & Status.MEAS_M_DONE


def test_periodic_set_in_continuous_mode():
    emu, clock = make()
    emu.write_register(CTRL0, int(InternalControl0.AUTO_SR_EN))
    ctrl2 = InternalControl2.EN_PRD_SET | InternalControl2.CMM_EN
    emu.write_register(CTRL2, int(ctrl2) | int(ContinuousFrequency.HZ_100))
    assert emu.polarity == -1
    clock.t += 0.0085
    assert status(emu) & Status.MEAS_M_DONE and emu.polarity == +1
    b = decode_field_T(emu.read_registers(Register.XOUT0, 7), np.zeros(3))
    np.testing.assert_allclose(b - emu.bridge_offset_T, B_TRUE_T, atol=5 * Bandwidth.BW_100HZ.noise_rms_T + LSB_T)


def test_temperature_measurement():
    emu, clock = make()
    for temperature_C in (25.0, -75.0, 200.0):
        emu.temperature_C = temperature_C
        emu.write_register(CTRL0, int(InternalControl0.TM_T))
        assert not status(emu) & Status.MEAS_T_DONE
        clock.t += TEMPERATURE_MEASUREMENT_TIME_S + 1e-6
        assert status(emu) & Status.MEAS_T_DONE
        tout = emu.read_registers(Register.TOUT, 1)[0]
        assert tout_to_celsius(tout) == pytest.approx(min(temperature_C, tout_to_celsius(255)), abs=0.4)


def test_x_inhibit_keeps_x_output():
    emu, clock = make()
    first = measure(emu, clock)
    emu.write_register(CTRL1, int(InternalControl1.X_INHIBIT))
    emu.bridge_offset_T[:] = 1e-5  # a change that would show on every enabled axis
    second = measure(emu, clock)
    assert second[0] == first[0]
    assert np.all(np.abs(second[1:] - first[1:]) > 5e-6)


def test_fault_hooks():
    emu, clock = make()
    emu.fault_wrong_id = True
    assert emu.read_registers(Register.PRODUCT_ID_1, 1) == b"\xff"
    emu.fault_wrong_id = False
    emu.fault_bus_error_rate = 1.0
    with pytest.raises(BusError):
        emu.read_registers(Register.XOUT0, 7)
    with pytest.raises(BusError):
        emu.write_register(CTRL0, TM_M)
    emu.fault_bus_error_rate = 0.0
    emu.fault_no_data_ready = True
    emu.write_register(CTRL0, TM_M)
    clock.t += 0.1
    assert not status(emu) & Status.MEAS_M_DONE
    emu.fault_no_data_ready = False
    first = measure(emu, clock)
    emu.fault_stuck = True
    emu.bridge_offset_T[:] = 1e-5
    assert np.array_equal(measure(emu, clock), first)  # Meas_M_Done comes, data do not change


def test_fault_rng_does_not_change_noise():
    def retry(transfer):
        while True:
            try:
                return transfer()
            except BusError:
                pass

    runs = []
    for rate in (0.0, 0.3):
        emu, clock = make(seed=3)
        emu.fault_bus_error_rate = rate
        values = []
        for _ in range(20):
            retry(lambda emu=emu: emu.write_register(CTRL0, TM_M))
            clock.t += 0.01
            values.append(retry(lambda emu=emu: emu.read_registers(Register.XOUT0, 7)))
        runs.append(values)
    assert runs[0] == runs[1]


def test_closed_loop_driver_follows_tumbling_field():
    """Driver + emulator: every sample equals the true field at its time stamp, within noise."""
    omega = np.array([0.3, -0.2, 1.0])  # rad/s

    def field(t):  # a fixed inertial field seen from a body spinning at omega (Rodrigues rotation)
        b0 = np.array([30e-6, 10e-6, -40e-6])
        w = np.linalg.norm(omega)
        k, a = omega / w, -w * t
        return b0 * math.cos(a) + np.cross(k, b0) * math.sin(a) + k * (k @ b0) * (1 - math.cos(a))

    emu, clock = make(field=field, seed=11)
    driver = Mmc5983ma(emu, calibration_interval=100)
    errors = []
    for k in range(3000):  # 3 s at 1 kHz
        clock.t = 1.0 + k * 1e-3
        if driver.update(clock.t):
            errors.append(driver.b_body_T - field(driver.sample_time_s))
    errors = np.array(errors)
    sigma = Bandwidth.BW_100HZ.noise_rms_T
    assert driver.state is MagState.MEASURE and len(errors) > 280 and driver.calibrations >= 3
    assert np.abs(errors).max() < 6 * sigma
    np.testing.assert_allclose(errors.mean(axis=0), 0.0, atol=sigma)
    assert emu.write_only_reads == 0
