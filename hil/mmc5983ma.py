"""Register-level emulator of the MEMSIC MMC5983MA magnetometer.

It satisfies `fsw.bus.RegisterBus`, so the flight driver runs against it unchanged, directly or
through the serial bridge (`hil.pty_link`). Datasheet behaviour reproduced (MMC5983MA datasheet
Rev A, [DS pN]; numbers collected in `docs/spec/mmc5983ma.md`):

- Product ID 1 (0x2F) reads 0x30; Status (0x08) is read/write, writing 1 to a done bit clears it;
  Internal Control 0-3 (0x09-0x0C) are write-only [DS p13-16].
- TM_M starts one measurement taking the BW's time (8 / 4 / 2 / 0.5 ms); Meas_M_Done goes to 0 at
  the command and to 1 when it finishes, then stays 1 until the next command or a clear
  [DS p13-16]. A TM_M while a measurement runs is ignored.
- Outputs are 18-bit unsigned offset-binary, 16384 counts/G around 131072, split over Out0, Out1
  and XYZout2 [DS p2, p12-16], clipped to 0...262143 (+-8 G).
- Output = polarity * H + bridge offset + noise, polarity +1 after SET and -1 after RESET
  [DS p18]. Noise is Gaussian per axis with the datasheet RMS for the BW (0.4 / 0.6 / 0.8 /
  1.2 mG) [DS p2], combined in quadrature with `extra_noise_T` (environmental disturbance).
- SW_RST (Internal Control 1 bit 7) returns every register to its power-on value; the chip needs
  the 10 ms power-on time [DS p13-16].
- Continuous mode: Cmm_en with Cm_freq != 000 [DS p13-16]; Prd_set / En_prd_set periodic SET.
- Temperature: TM_T, Meas_T_Done and Tout with T = -75 + 0.8 * Tout degC [DS p13-16].

Modelling choices where the datasheet is silent:

- Power-on (and SW_RST) polarity is RESET, so a driver that never issues SET reads all three axes
  sign-inverted. A freshly constructed emulator is already powered and ready; `power_cycle()`
  models a power-on.
- During the 10 ms after SW_RST or power-on every access raises `BusError`, as an I2C device
  that does not acknowledge its address.
- Reading a write-only control register returns the bitwise complement of the last value written
  to it: garbage that never equals what was written, so read-modify-write visibly breaks
  (SparkFun issues #8/#9). Such reads are counted in `write_only_reads`.
- The field is sampled at the middle of the measurement window, t_TM_M + t_meas / 2 (the
  decimation filter's centre). It is evaluated lazily, at the first access after the
  measurement ended, so `field_T` is called with times up to one caller step in the past.
- Status reads OTP_Rd_Done = 1 whenever the chip answers (MEMSIC: it should always be 1).
- The polarity used is the one when the measurement starts; the 1 ms settling after a SET/RESET
  pulse is not modelled. A SET or RESET bit written together with TM_M is applied first
  (PX4 does this). SET and RESET in one write are applied in that order (ends RESET).
- TM_M and TM_T in one write: only the field measurement runs. TM_T takes 2 ms (not in the DS).
- Continuous mode starts at the write of Internal Control 2 that enables it (TM_M is not needed
  and is ignored while it runs), with period max(1 / Cm_freq, t_meas): 1000 Hz is only reached
  with BW=11, and a too slow BW lowers the rate; measurement time and period are latched then.
  Meas_M_Done is set at every completed measurement; with lazy evaluation only the newest one
  draws noise. Clearing Cmm_en abandons a measurement in progress.
- Auto_SR_en alone has no effect; with En_prd_set and Cmm_en a SET precedes measurements
  0, N, 2N, ... (N from Prd_set).
- X_inhibit / YZ_inhibit (both YZ bits) leave the inhibited outputs unchanged. The self-test
  bits, INT_meas_done_en, OTP_Read and Spi_3w are stored and have no modelled effect.
- Reserved addresses read 0x00; writes to read-only or reserved addresses are ignored.

Fault-injection hooks (plain attributes, read at every access): `fault_no_data_ready` (a
measurement finishes without setting Meas_M_Done or updating outputs), `fault_bus_error_rate`
(probability that a transfer raises BusError), `fault_wrong_id` (0x2F reads 0xFF, the SPI symptom
of fact-sheet section 5), `fault_stuck` (outputs frozen while Meas_M_Done still comes),
`fault_field_T` (a field added to the true one, e.g. a magnet or a current pulse nearby: spikes,
saturation beyond ±8 G). `hil.faults` schedules them.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from fsw.bus import BusError
from fsw.drivers.mmc5983ma_regs import (
    BW_MASK,
    CM_FREQ_MASK,
    COUNTS_MAX_18,
    NULL_FIELD_18,
    PERIODIC_SET_MEASUREMENTS,
    POWER_ON_TIME_S,
    PRD_SET_SHIFT,
    PRODUCT_ID,
    TEMPERATURE_C_PER_LSB,
    TEMPERATURE_OFFSET_C,
    TESLA_PER_COUNT_18,
    Bandwidth,
    ContinuousFrequency,
    InternalControl0,
    InternalControl1,
    InternalControl2,
    Register,
    Status,
    encode_xyz18,
)

DEFAULT_BRIDGE_OFFSET_T = (4.0e-7, -2.5e-7, 6.0e-7)
"""Default bridge offset per axis: +4.0, -2.5, +6.0 mG (DS: null-field drift with SET/RESET 3 mG)."""

TEMPERATURE_MEASUREMENT_TIME_S = 0.002
"""TM_T to Meas_T_Done. Not in the DS; SparkFun allows 5 ms."""

_PERSISTENT_CTRL0 = int(InternalControl0.INT_MEAS_DONE_EN | InternalControl0.AUTO_SR_EN)
_YZ_INHIBIT = int(InternalControl1.YZ_INHIBIT)
_CONTROL = {
    int(Register.INTERNAL_CONTROL_0): 0,
    int(Register.INTERNAL_CONTROL_1): 1,
    int(Register.INTERNAL_CONTROL_2): 2,
    int(Register.INTERNAL_CONTROL_3): 3,
}
SET, RESET = +1, -1
"""Polarity values: +1 after a SET pulse, -1 after a RESET pulse (and at power-on)."""


class EmulatedMmc5983ma:
    """One MMC5983MA on a register bus; the true field comes from `field_T(t)` in sensor axes.

    `clock()` returns the simulation time in seconds; every access reads it once. Randomness comes
    from `rng` (measurement noise) and a child generator spawned from it (fault injection), so
    enabling faults does not change the noise sequence.
    """

    def __init__(
        self,
        field_T: Callable[[float], np.ndarray],
        clock: Callable[[], float],
        rng: np.random.Generator,
        bridge_offset_T=DEFAULT_BRIDGE_OFFSET_T,
        extra_noise_T: float = 0.0,
    ) -> None:
        self._field_T = field_T
        self._clock = clock
        self._rng = rng
        self._fault_rng = rng.spawn(1)[0]
        self.bridge_offset_T = np.array(bridge_offset_T, dtype=float)
        self.extra_noise_T = float(extra_noise_T)
        self.temperature_C = 25.0
        # fault hooks
        self.fault_no_data_ready = False
        self.fault_bus_error_rate = 0.0
        self.fault_wrong_id = False
        self.fault_stuck = False
        self.fault_field_T = np.zeros(3)
        # observability for tests and the simulator
        self.transfers = 0
        self.write_only_reads = 0
        self.measurements = 0
        #: continuous-mode outputs overwritten by the next before the driver read them: samples lost in the chip
        self.overwritten = 0
        self._power_on(ready_at=-math.inf)

    # --- RegisterBus ----------------------------------------------------------------------------

    def read_registers(self, address: int, count: int) -> bytes:
        if count < 1 or not 0 <= address <= 0xFF:
            raise ValueError(f"bad read of {count} registers at {address:#x}")
        self._access()
        return bytes(self._read_one((address + i) & 0xFF) for i in range(count))

    def write_register(self, address: int, value: int) -> None:
        if not 0 <= address <= 0xFF or not 0 <= value <= 0xFF:
            raise ValueError(f"bad write of {value} at {address}")
        now = self._access()
        if address == Register.STATUS:
            self._status &= ~(value & int(Status.MEAS_M_DONE | Status.MEAS_T_DONE))
        elif address == Register.INTERNAL_CONTROL_0:
            self._ctrl_written[0] = value
            self._write_ctrl0(value, now)
        elif address == Register.INTERNAL_CONTROL_1:
            self._ctrl_written[1] = value
            if value & InternalControl1.SW_RST:
                self._power_on(ready_at=now + POWER_ON_TIME_S)
            else:
                self._ctrl[1] = value
        elif address == Register.INTERNAL_CONTROL_2:
            self._ctrl_written[2] = value
            self._ctrl[2] = value
            self._write_ctrl2(value, now)
        elif address == Register.INTERNAL_CONTROL_3:
            self._ctrl_written[3] = value
            self._ctrl[3] = value

    # --- public helpers -------------------------------------------------------------------------

    def settle(self) -> None:
        """Complete the measurements that have finished by now (the simulation clock), as the chip does on
        its own: SITL calls this when it advances the world, so that the chip's physics (the truth at the
        measurement's time, its noise) is the simulator's work, not the flight loop's register access."""
        now = self._clock()
        if now >= self._ready_at:
            self._advance(now)

    def power_cycle(self) -> None:
        """Power the chip off and on: power-on state, unresponsive for the power-on time."""
        self._power_on(ready_at=self._clock() + POWER_ON_TIME_S)

    @property
    def polarity(self) -> int:
        """+1 (SET) or -1 (RESET): the sign of H in the outputs."""
        return self._polarity

    @property
    def bandwidth(self) -> Bandwidth:
        return Bandwidth(self._ctrl[1] & BW_MASK)

    @property
    def continuous(self) -> bool:
        return self._cm_start is not None

    # --- internals ------------------------------------------------------------------------------

    def _power_on(self, ready_at: float) -> None:
        self._ready_at = ready_at
        self._ctrl = [0, 0, 0, 0]  # the effective (persistent) control bits
        self._ctrl_written = [0, 0, 0, 0]  # last byte written, for the garbage read-back
        self._status = int(Status.OTP_READ_DONE)
        self._out = encode_xyz18(0, 0, 0)
        self._tout = 0
        self._polarity = RESET
        self._pending: tuple[str, float, float, int] | None = None  # kind, start, done, polarity
        self._cm_start: float | None = None
        self._cm_period = 0.0
        self._cm_tmeas = 0.0
        self._cm_done = 0

    def _access(self) -> float:
        now = self._clock()
        if now < self._ready_at:
            raise BusError("MMC5983MA NAK: power-on / soft reset in progress")
        if self.fault_bus_error_rate > 0.0 and self._fault_rng.random() < self.fault_bus_error_rate:
            raise BusError("MMC5983MA NAK (injected fault)")
        self.transfers += 1
        self._advance(now)
        return now

    def _read_one(self, address: int) -> int:
        if address <= Register.XYZOUT2:
            return self._out[address]
        if address == Register.TOUT:
            return self._tout
        if address == Register.STATUS:
            return self._status
        if address in _CONTROL:
            self.write_only_reads += 1
            return ~self._ctrl_written[_CONTROL[address]] & 0xFF
        if address == Register.PRODUCT_ID_1:
            return 0xFF if self.fault_wrong_id else PRODUCT_ID
        return 0x00

    def _write_ctrl0(self, value: int, now: float) -> None:
        self._ctrl[0] = value & _PERSISTENT_CTRL0
        if value & InternalControl0.SET:
            self._polarity = SET
        if value & InternalControl0.RESET:
            self._polarity = RESET
        if value & InternalControl0.OTP_READ:
            self._status |= Status.OTP_READ_DONE
        busy = self._pending is not None or self._cm_start is not None
        if value & InternalControl0.TM_M:
            if not busy:
                self._status &= ~Status.MEAS_M_DONE
                t_meas = self.bandwidth.measurement_time_s
                self._pending = ("M", now, now + t_meas, self._polarity)
        elif value & InternalControl0.TM_T:
            if not busy:
                self._status &= ~Status.MEAS_T_DONE
                self._pending = ("T", now, now + TEMPERATURE_MEASUREMENT_TIME_S, self._polarity)

    def _write_ctrl2(self, value: int, now: float) -> None:
        freq = ContinuousFrequency(value & CM_FREQ_MASK)
        if value & InternalControl2.CMM_EN and freq is not ContinuousFrequency.OFF:
            t_meas = self.bandwidth.measurement_time_s
            self._pending = None
            self._cm_start = now
            self._cm_tmeas = t_meas
            self._cm_period = max(1.0 / freq.rate_hz, t_meas)
            self._cm_done = 0
        else:
            self._cm_start = None

    def _advance(self, now: float) -> None:
        """Complete whatever measurement has finished by `now`."""
        p = self._pending
        if p is not None and now >= p[2]:
            self._pending = None
            kind, start, done, polarity = p
            if kind == "M":
                self._complete_field(start + 0.5 * (done - start), polarity)
            else:
                tout = round((self.temperature_C - TEMPERATURE_OFFSET_C) / TEMPERATURE_C_PER_LSB)
                self._tout = min(max(tout, 0), 255)
                self._status |= Status.MEAS_T_DONE
        if self._cm_start is not None and now >= self._cm_start + self._cm_tmeas:
            n = int((now - self._cm_start - self._cm_tmeas) // self._cm_period) + 1
            if n > self._cm_done:
                if (
                    self._ctrl[0] & InternalControl0.AUTO_SR_EN
                    and self._ctrl[2] & InternalControl2.EN_PRD_SET
                ):
                    every = PERIODIC_SET_MEASUREMENTS[(self._ctrl[2] >> PRD_SET_SHIFT) & 0x7]
                    if -(-self._cm_done // every) * every <= n - 1:
                        self._polarity = SET
                t_start = self._cm_start + (n - 1) * self._cm_period
                self.overwritten += n - self._cm_done - 1  # outputs that came and went between two accesses
                self._cm_done = n
                self._complete_field(t_start + 0.5 * self._cm_tmeas, self._polarity)

    def _complete_field(self, t_mid: float, polarity: int) -> None:
        if self.fault_no_data_ready:
            return
        self.measurements += 1
        if self._cm_start is not None and self._status & Status.MEAS_M_DONE:
            self.overwritten += 1  # continuous mode: the previous output was never read (and cleared)
        if not self.fault_stuck:
            sigma = math.hypot(self.bandwidth.noise_rms_T, self.extra_noise_T)
            b = polarity * (np.asarray(self._field_T(t_mid), dtype=float) + self.fault_field_T) + self.bridge_offset_T
            b = b + self._rng.normal(0.0, sigma, 3)
            # nearest count (half to even, as np.rint), clipped to the 18-bit range
            cx, cy, cz = (min(max(round(v / TESLA_PER_COUNT_18) + NULL_FIELD_18, 0), COUNTS_MAX_18) for v in b.tolist())
            old = self._out
            if self._ctrl[1] & InternalControl1.X_INHIBIT:
                cx = (old[0] << 10) | (old[1] << 2) | (old[6] >> 6)
            if self._ctrl[1] & _YZ_INHIBIT == _YZ_INHIBIT:
                cy = (old[2] << 10) | (old[3] << 2) | ((old[6] >> 4) & 0x3)
                cz = (old[4] << 10) | (old[5] << 2) | ((old[6] >> 2) & 0x3)
            self._out = encode_xyz18(cx, cy, cz)
        self._status |= Status.MEAS_M_DONE
