"""MMC5983MA driver: a non-blocking state machine on a register bus, time injected.

Shaped like the PX4 / ArduPilot drivers (fact sheet `docs/spec/mmc5983ma.md` section 4) with their known
defects avoided; [DS pN] cites the MMC5983MA datasheet Rev A.

States (values = DEBRIS_MAG_STATE in fsw/telemetry/debris.xml):

- PROBE: read Product ID 1 (0x2F), expect 0x30, retry every 5 ms up to `probe_retries` attempts
  (ArduPilot retries 10x because SPI reads sometimes return 0xFF). Wrong ids count in `bad_id`.
- RESET: SW_RST is bit 7 of Internal Control 1 = 0x0A [DS p13-16] (PX4 writes 0x80 to 0x0B, which
  sets En_prd_set instead). Wait 15 ms (power-on time 10 ms).
- CONFIGURE: write BW. Control registers are write-only [DS p13-16]: the driver keeps a shadow of
  each and always writes whole bytes; it never reads them (SparkFun issues #8/#9).
- CALIBRATE: SET/RESET offset removal [DS p18]. RESET, measure R1; SET, measure S; RESET, measure
  R2; SET. With R = (R1 + R2) / 2, the brackets of the DS formulas,
      H = (S - R) / 2,   offset = (S + R) / 2,
  with R1 and R2 taken symmetrically around S, so a field that changes linearly in time (a
  tumbling body) leaves no first-order error in the offset; with only R1 it would be biased by
  half the field change between the two measurements. Every TM_M follows a SET/RESET pulse by
  >= 1 ms. It ends in SET polarity, where the package axis signs hold. S - offset = H is delivered
  as a sample. Each triple measures the bridge offset with 0.6 of a reading's noise per axis; the
  offset subtracted from the readings (`offset_T`) is the mean of the triples, running over the last
  `offset_averaging` of them (a mean of all up to that count, then an exponential average with that
  weight), so that re-measuring it does not step the samples by the triples' noise (at 1.5 uT a
  reading, 1-2 uT steps). The bridge offset changes slowly (null-field drift 3 mG over the whole
  temperature range [DS p2]). A triple more than `OFFSET_JUMP_T` away from the mean on any axis is kept
  out of it and counted in `offset_outliers`: the field changed while it was measured (the triple's
  readings are spread over the calls to `update`, 0.8 s on a 5 Hz loop, and a capsule of the de-orbit
  kit closing meanwhile steps the field by tens of uT; a step Δ between the readings moves the triple's
  offset by Δ/4). When the next triple agrees with it within `OFFSET_JUMP_T` the offset has really
  moved (a magnetising disturbance): the mean restarts from the two, counted in `offset_jumps`. A new
  PROBE (the chip may have been replaced) restarts it too. `offset_measured_T` is the latest triple's
  own offset. When the host knows what else moves the field (`disturbed(t0_s, t1_s)`: the flight
  software asks the de-orbit kit whether a capsule or magnet moved in that span), a triple measured
  across such a motion is kept out too, counted in `offset_disturbed` (with no mean yet, as after a
  start while the kit moves, its offset is used until the first undisturbed triple replaces it). The SET
  reading of a triple kept out is delivered as a sample with the mean's offset.
- MEASURE, single measurement mode: at each sample time write TM_M; from TM_M + t_meas poll
  Status for Meas_M_Done (TM_M clears it [DS p13-16], so no clearing write is needed), read the
  7-byte burst from 0x00, decode, subtract the offset. No data-ready within 4 t_meas + 1 ms
  (SparkFun's timeout) counts a timeout and re-triggers.
  Continuous mode (`continuous` != OFF): clear Meas_M_Done (the calibration left it set), write
  Cmm_en + Cm_freq to Internal Control 2, poll Status at every update, read when Meas_M_Done is
  set, then clear it by writing 1; no data within 4 periods + 1 ms counts a timeout and rewrites
  Internal Control 2. To recalibrate, continuous mode is stopped for one measurement time first.
  CALIBRATE runs again every `calibration_interval` samples (0: only after initialisation), and not
  sooner than `calibration_period_s` after the last one: the chip makes no sample while it calibrates
  (about 7 ms), so at a fast rate a count alone would cost a sample in 140 (1 kHz, every 1000 samples).
  The flight software re-measures every `RECALIBRATION_PERIOD_S` (10 s, the reference driver's 1000
  readings at 100 Hz) at any rate (`calibration_interval` 1): at a slow rate a count of 1000 samples
  would leave the offset unmeasured for 1000 s.
- BACKOFF: after `max_consecutive_errors` failed transfers in a row, wait 100 ms (doubling up to
  1 s on repeated back-offs, back to 100 ms after a good sample), then PROBE again.

A failed transfer raises BusError in the bus; `update` catches it (and any other exception from
the bus), counts it and retries the same step at the next call. Nothing raises out of `update`.

Sample time: `sample_time_s` is the time TM_M was issued plus half the measurement time, the centre
of the decimation window. In continuous mode the chip's schedule is not visible, so it is the
middle of the interval in which Meas_M_Done was seen to rise, minus half the measurement time.

The MEASURE path allocates no numpy arrays: `b_body_T` and `offset_T` are preallocated and
overwritten in place (keep a copy if the previous sample is needed).
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import Callable

import numpy as np

from fsw.bus import BusError, RegisterBus
from fsw.drivers.mmc5983ma_regs import (
    OUTPUT_BYTES,
    PRODUCT_ID,
    SET_RESET_SETTLE_S,
    Bandwidth,
    ContinuousFrequency,
    InternalControl0,
    InternalControl1,
    InternalControl2,
    Register,
    Status,
    decode_field_T,
)

PROBE_INTERVAL_S = 0.005
"""Spacing of product-id reads (ArduPilot: 10 tries, 5 ms apart)."""
RESET_WAIT_S = 0.015
"""Wait after SW_RST; power-on time is 10 ms [DS p13-16], drivers wait 15-20 ms."""
BACKOFF_INITIAL_S = 0.1
BACKOFF_MAX_S = 1.0
TIMEOUT_MARGIN_S = 0.001
"""Data-ready timeout = 4 t_meas + 1 ms (SparkFun v1.1.3)."""
RECALIBRATION_PERIOD_S = 10.0
"""The flight software's time between two SET/RESET calibrations (`calibration_period_s`)."""
RECALIBRATION_INTERVAL = 1
"""The flight software's `calibration_interval`: the period alone sets when the offset is re-measured."""
FLIGHT_SCHEDULE = {"calibration_interval": RECALIBRATION_INTERVAL, "calibration_period_s": RECALIBRATION_PERIOD_S}
"""The flight software's SET/RESET schedule, as keywords of :class:`Mmc5983ma` (target and SITL alike)."""
OFFSET_AVERAGING = 32
"""Triples in the running mean of the bridge offset: 320 s at the flight software's period, 0.1 of a
reading's noise per axis."""
OFFSET_JUMP_T = 10e-6
"""A triple this far from the running mean on any axis is kept out of it, and restarts it when the next
triple confirms it (11 times the triple's noise at 1.5 uT a reading, 30 times the datasheet's
null-field drift)."""

_TM_M = int(InternalControl0.TM_M)
_SET = int(InternalControl0.SET)
_RESET = int(InternalControl0.RESET)
_MEAS_M_DONE = int(Status.MEAS_M_DONE)
_CAL_PULSES = (_RESET, _SET, _RESET)  # then a final SET
_MAX_STEPS = 8  # state-machine steps chained within one update()
_EPS_S = 1e-6  # schedule slack, so that float rounding of the caller's clock cannot slip a tick


class MagState(IntEnum):
    """Driver state; the values are DEBRIS_MAG_STATE of the telemetry dialect."""

    PROBE = 0
    RESET = 1
    CONFIGURE = 2
    CALIBRATE = 3
    MEASURE = 4
    BACKOFF = 5


class _Phase(IntEnum):
    START = 0  # issue the state's first command
    SETTLE = 1  # after a SET/RESET pulse, before TM_M
    WAIT = 2  # TM_M issued, waiting for Meas_M_Done
    IDLE = 3  # waiting for the next sample time (single) / polling (continuous)
    CLEAR = 4  # continuous: data read, Meas_M_Done to be cleared
    FINAL = 5  # calibration: final SET pulse


class Mmc5983ma:
    """MMC5983MA on a `RegisterBus`; call `update(now_s)` often (at least at the sample rate).

    Outputs: `b_body_T` (latest field, tesla, sensor axes = body axes, SET polarity, offset
    removed; NaN before the first sample), `sample_time_s`, `state`, `offset_T` (the running mean
    subtracted), `offset_measured_T` (the latest triple's) and the counters `samples`, `bus_errors`,
    `timeouts`, `bad_id`, `resets`, `calibrations`, `offset_jumps`, `offset_outliers`,
    `offset_disturbed`. `disturbed`: None, or a callable (t0_s, t1_s) → whether something besides the
    body's motion changed the field between the two times (the driver's clock, `update`'s `now`).
    """

    def __init__(
        self,
        bus: RegisterBus,
        bandwidth: Bandwidth = Bandwidth.BW_100HZ,
        sample_period_s: float = 0.01,
        calibration_interval: int = 1000,
        probe_retries: int = 10,
        calibration_period_s: float = 0.0,
        continuous: ContinuousFrequency = ContinuousFrequency.OFF,
        max_consecutive_errors: int = 5,
        offset_averaging: int = OFFSET_AVERAGING,
        disturbed: Callable[[float, float], bool] | None = None,
    ) -> None:
        self.disturbed = disturbed
        self.bandwidth = Bandwidth(bandwidth)
        self.continuous = ContinuousFrequency(continuous)
        t_meas = self.bandwidth.measurement_time_s
        if self.continuous is ContinuousFrequency.OFF:
            if not sample_period_s >= t_meas:
                raise ValueError(
                    f"sample period {sample_period_s} s shorter than the {t_meas} s measurement "
                    f"time of {self.bandwidth.name}"
                )
            self.sample_period_s = float(sample_period_s)
            period = self.sample_period_s
        else:
            if not self.continuous.fits(self.bandwidth):
                raise ValueError(
                    f"{self.continuous.name} needs a measurement time <= "
                    f"{1.0 / self.continuous.rate_hz} s, {self.bandwidth.name} takes {t_meas} s"
                )
            period = 1.0 / self.continuous.rate_hz
            self.sample_period_s = period
        if (probe_retries < 1 or max_consecutive_errors < 1 or offset_averaging < 1 or calibration_interval < 0
                or not calibration_period_s >= 0.0):
            raise ValueError("probe_retries, max_consecutive_errors, offset_averaging >= 1; calibration_interval, "
                             "calibration_period_s >= 0")
        self.offset_averaging = int(offset_averaging)
        self.calibration_period_s = float(calibration_period_s)
        self._bus = bus
        self.calibration_interval = int(calibration_interval)
        self.probe_retries = int(probe_retries)
        self.max_consecutive_errors = int(max_consecutive_errors)
        self._t_meas = t_meas
        self._timeout_s = 4.0 * t_meas + TIMEOUT_MARGIN_S
        self._cm_timeout_s = 4.0 * max(period, t_meas) + TIMEOUT_MARGIN_S

        self.b_body_T = np.full(3, np.nan)
        self.offset_T = np.zeros(3)
        self.offset_measured_T = np.zeros(3)
        self.sample_time_s = math.nan
        self.samples = 0
        self.bus_errors = 0
        self.timeouts = 0
        self.bad_id = 0
        self.resets = 0
        self.calibrations = 0
        self.offset_jumps = 0
        self.offset_outliers = 0  # triples kept out of the mean (the field changed while they were measured)
        self.offset_disturbed = 0  # triples kept out because `disturbed` said the field was moved meanwhile
        self._offset_count = 0  # triples in the running mean (0: none yet, or restarted by a PROBE)
        self._jump_T = np.zeros(3)  # the latest triple kept out, which the next one may confirm
        self._jump_pending = False
        self.chip_resets_detected = 0
        self.last_error = ""

        self._shadow = bytearray(4)  # Internal Control 0..3 as last written (ctrl0: lasting bits)
        self._cal_T = np.zeros((3, 3))  # R1, S, R2
        self._cal_trigger_s = [0.0, 0.0, 0.0]
        self._cal_index = 0
        self._samples_since_cal = 0
        self._cal_end_s = -math.inf
        self._probe_attempts = 0
        self._consecutive_errors = 0
        self._backoff_s = BACKOFF_INITIAL_S
        self._t_next = -math.inf  # when the current phase may act
        self._t_grid = math.nan  # next sample time in single measurement mode
        self._t_trigger = 0.0
        self._t_poll = 0.0
        self._t_data = 0.0
        self._new_sample = False
        self._rate_request: tuple[ContinuousFrequency, float] | None = None
        self.state = MagState.PROBE
        self._phase = _Phase.START

    @property
    def shadow(self) -> bytes:
        """Shadow copies of Internal Control 0..3 (Internal Control 0 without self-clearing bits)."""
        return bytes(self._shadow)

    def sample_rate_hz(self) -> float:
        """The output rate in force (a requested change takes effect at the next sample)."""
        return 1.0 / self.sample_period_s

    def available_rates_hz(self, up_to_hz: float) -> list[float]:
        """The output rates this bandwidth allows at or below `up_to_hz`, highest first: `up_to_hz` itself
        (continuous mode if the chip has that rate, else single measurements) and the continuous-mode
        rates below it whose measurement fits [DS p13-16]."""
        rates = {float(f.rate_hz) for f in ContinuousFrequency if f.fits(self.bandwidth) and f.rate_hz <= up_to_hz}
        if 1.0 / up_to_hz >= self._t_meas:
            rates.add(float(up_to_hz))
        return sorted(rates, reverse=True)

    def set_sample_rate(self, rate_hz: float) -> float:
        """Change the output rate, keeping the bandwidth (and so the noise the estimators assume): continuous
        mode at `rate_hz` if the chip has that rate and its measurement fits, else single measurements every
        1/`rate_hz` s. In MEASURE the change goes through a SET/RESET calibration right after the next sample
        (continuous mode stopped first, the grid restarted from it); in any other state it takes effect when
        MEASURE is entered. Returns the rate; ValueError for one the bandwidth cannot deliver."""
        cm = next((f for f in ContinuousFrequency if f.rate_hz == rate_hz and f.fits(self.bandwidth)),
                  ContinuousFrequency.OFF)
        if cm is ContinuousFrequency.OFF and not (rate_hz > 0 and 1.0 / rate_hz >= self._t_meas):
            raise ValueError(f"sample rate {rate_hz!r} Hz: {self.bandwidth.name}'s measurement takes {self._t_meas} s")
        request = (cm, 1.0 / rate_hz)
        if self.state is MagState.MEASURE:
            self._rate_request = request
        else:
            self._apply_rate(request)
        return float(rate_hz)

    def _apply_rate(self, request: tuple[ContinuousFrequency, float]) -> None:
        self.continuous, self.sample_period_s = request
        self._cm_timeout_s = 4.0 * max(self.sample_period_s, self._t_meas) + TIMEOUT_MARGIN_S
        self._rate_request = None

    # --- public step ----------------------------------------------------------------------------

    def update(self, now_s: float) -> bool:
        """Advance the state machine to `now_s`; True when a new sample is in `b_body_T`."""
        self._new_sample = False
        try:
            for _ in range(_MAX_STEPS):
                if not self._step(now_s):
                    break
        except Exception as error:  # noqa: BLE001 - a driver must survive any bus failure
            self.bus_errors += 1
            self.last_error = f"{type(error).__name__}: {error}"
            if not isinstance(error, BusError):
                self.last_error = "unexpected " + self.last_error
            if self.state is not MagState.PROBE:
                self._consecutive_errors += 1
                if self._consecutive_errors >= self.max_consecutive_errors:
                    self._enter_backoff(now_s)
        else:
            self._consecutive_errors = 0
        return self._new_sample

    # --- state machine --------------------------------------------------------------------------

    def _step(self, now: float) -> bool:
        """One step of the current state; True if the next step may follow at once."""
        state = self.state
        if state is MagState.MEASURE:
            if self.continuous is ContinuousFrequency.OFF:
                return self._measure_single(now)
            return self._measure_continuous(now)
        if state is MagState.CALIBRATE:
            return self._calibrate(now)
        if state is MagState.PROBE:
            return self._probe(now)
        if state is MagState.RESET:
            return self._reset(now)
        if state is MagState.CONFIGURE:
            return self._configure(now)
        return self._backoff(now)

    def _enter(self, state: MagState, t_next: float) -> None:
        self.state = state
        self._phase = _Phase.START
        self._t_next = t_next

    def _enter_backoff(self, now: float) -> None:
        self._enter(MagState.BACKOFF, now + self._backoff_s)
        self._backoff_s = min(2.0 * self._backoff_s, BACKOFF_MAX_S)
        self._consecutive_errors = 0

    def _probe(self, now: float) -> bool:
        if now + _EPS_S < self._t_next:
            return False
        self._t_next = now + PROBE_INTERVAL_S
        self._probe_attempts += 1
        try:
            raw = self._read(Register.PRODUCT_ID_1, 1)
        except BusError as error:
            self.bus_errors += 1
            self.last_error = f"BusError: {error}"
            raw = None
        if raw is not None and raw[0] == PRODUCT_ID:
            self._probe_attempts = 0
            self._enter(MagState.RESET, now)
            return True
        if raw is not None:
            self.bad_id += 1
        if self._probe_attempts >= self.probe_retries:
            self._probe_attempts = 0
            self._enter_backoff(now)
        return False

    def _reset(self, now: float) -> bool:
        if self._phase is _Phase.START:
            self._bus.write_register(Register.INTERNAL_CONTROL_1, int(InternalControl1.SW_RST))
            self.resets += 1
            self._shadow[:] = b"\x00\x00\x00\x00"  # SW_RST returns every register to 0x00
            self._phase = _Phase.WAIT
            self._t_next = now + RESET_WAIT_S
            return False
        if now + _EPS_S < self._t_next:
            return False
        self._enter(MagState.CONFIGURE, now)
        return True

    def _configure(self, now: float) -> bool:
        self._write_ctrl(1, int(self.bandwidth))
        self._enter(MagState.CALIBRATE, now)
        self._cal_index = 0
        return True

    def _calibrate(self, now: float) -> bool:
        phase = self._phase
        if phase is _Phase.START:
            if now + _EPS_S < self._t_next:
                return False
            self._write_ctrl(0, self._shadow[0] | _CAL_PULSES[self._cal_index])
            self._phase = _Phase.SETTLE
            self._t_next = now + SET_RESET_SETTLE_S
            return True
        if phase is _Phase.SETTLE:
            if now + _EPS_S < self._t_next:
                return False
            self._trigger(now)
            return False
        if phase is _Phase.WAIT:
            if not self._data_ready(now):
                return False
            decode_field_T(self._read(Register.XOUT0, OUTPUT_BYTES), self._cal_T[self._cal_index])
            self._cal_trigger_s[self._cal_index] = self._t_trigger
            self._cal_index += 1
            if self._cal_index < len(_CAL_PULSES):
                self._phase = _Phase.START
                self._t_next = now
            else:
                self._phase = _Phase.FINAL
            return True
        # FINAL: back to SET polarity, then solve [DS p18]
        self._write_ctrl(0, self._shadow[0] | _SET)
        r1, s, r2 = self._cal_T
        measured = self.offset_measured_T
        np.add(r1, r2, out=measured)
        measured *= 0.5  # R, centred on S
        np.subtract(s, measured, out=self.b_body_T)
        self.b_body_T *= 0.5  # H = (S - R) / 2
        np.add(s, measured, out=measured)
        measured *= 0.5  # offset = (S + R) / 2
        if self.disturbed is not None and self.disturbed(self._cal_trigger_s[0], now):
            self.offset_disturbed += 1
            if not self._offset_count:  # no mean yet: this offset until an undisturbed triple replaces it
                self.offset_T[:] = measured
            taken = False
        else:
            taken = self._average_offset()
        if not taken:  # the field changed during the triple: S with the mean's offset
            np.subtract(s, self.offset_T, out=self.b_body_T)
        # The SET reading is a sample too. It is delivered when it does not crowd the previous one
        # (at start-up always, and then the sample grid starts from it); a periodic re-calibration
        # just after a sample would otherwise add an off-grid sample with a tiny time step.
        t_cal = self._cal_trigger_s[1] + 0.5 * self._t_meas
        first = math.isnan(self._t_grid)
        if first or not t_cal - self.sample_time_s < 0.5 * self.sample_period_s:
            self._deliver(t_cal)
        self.calibrations += 1
        self._samples_since_cal = 0
        self._cal_end_s = now
        t_ready = now + SET_RESET_SETTLE_S
        if first:
            self._t_grid = t_cal + self.sample_period_s
        if self._t_grid < t_ready:
            self._t_grid += math.ceil((t_ready - self._t_grid) / self.sample_period_s) * self.sample_period_s
        self._enter(MagState.MEASURE, t_ready)
        self._phase = _Phase.IDLE if self.continuous is ContinuousFrequency.OFF else _Phase.START
        return True

    def _average_offset(self) -> bool:
        """The latest triple's offset into the running mean; False when it is kept out (an outlier)."""
        measured = self.offset_measured_T
        if self._offset_count and _max_abs_diff(measured, self.offset_T) > OFFSET_JUMP_T:
            if self._jump_pending and _max_abs_diff(measured, self._jump_T) <= OFFSET_JUMP_T:
                # confirmed by a second triple: the offset moved; the mean restarts from the two
                self.offset_jumps += 1
                self._jump_pending = False
                for i in range(3):
                    self.offset_T[i] = 0.5 * (float(self._jump_T[i]) + float(measured[i]))
                self._offset_count = 2
                return True
            self.offset_outliers += 1
            self._jump_T[:] = measured
            self._jump_pending = True
            return False
        self._jump_pending = False
        self._offset_count = min(self._offset_count + 1, self.offset_averaging)
        weight = 1.0 / self._offset_count
        for i in range(3):
            self.offset_T[i] += weight * (float(measured[i]) - float(self.offset_T[i]))
        return True

    def _measure_single(self, now: float) -> bool:
        if self._phase is _Phase.WAIT:
            if not self._data_ready(now):
                return False
            self._read_sample(self._t_trigger + 0.5 * self._t_meas)
            self._phase = _Phase.IDLE
            if self._calibration_due(now):
                self._enter(MagState.CALIBRATE, now)
                self._cal_index = 0
                self._take_rate_request()
            return True
        if now + _EPS_S < self._t_grid:
            return False
        # Meas_M_Done stays 1 after the last measurement until the next command [DS p15]; a chip that
        # reset behind the driver's back (brown-out) reads 0 here, has lost its bandwidth and is in
        # RESET polarity (inverted axes): configure and calibrate again.
        if not self._read(Register.STATUS, 1)[0] & _MEAS_M_DONE:
            self.chip_resets_detected += 1
            self.last_error = "chip reset detected (Meas_M_Done lost)"
            self._enter(MagState.CONFIGURE, now)
            return True
        self._trigger(now)
        period = self.sample_period_s
        self._t_grid += (math.floor((now + _EPS_S - self._t_grid) / period) + 1) * period
        return False

    def _measure_continuous(self, now: float) -> bool:
        phase = self._phase
        if phase is _Phase.START:
            if now + _EPS_S < self._t_next:
                return False
            self._bus.write_register(Register.STATUS, _MEAS_M_DONE)  # left set by the calibration
            self._write_ctrl(2, int(InternalControl2.CMM_EN) | int(self.continuous))
            self._t_poll = self._t_data = now
            self._phase = _Phase.IDLE
            return False
        if phase is _Phase.CLEAR:
            self._bus.write_register(Register.STATUS, _MEAS_M_DONE)
            self._phase = _Phase.IDLE
            if self._calibration_due(now):
                self._write_ctrl(2, 0)  # stop, let a running measurement end, then calibrate
                self._enter(MagState.CALIBRATE, now + self._t_meas)
                self._cal_index = 0
                self._take_rate_request()
            return False
        status = self._read(Register.STATUS, 1)[0]
        t_previous_poll, self._t_poll = self._t_poll, now
        if status & _MEAS_M_DONE:
            self._read_sample(0.5 * (t_previous_poll + now) - 0.5 * self._t_meas)
            self._t_data = now
            self._phase = _Phase.CLEAR
            return True
        if now - self._t_data > self._cm_timeout_s:
            self.timeouts += 1
            self._phase = _Phase.START
            self._t_next = now
            return True
        return False

    def _backoff(self, now: float) -> bool:
        if now + _EPS_S < self._t_next:
            return False
        self._probe_attempts = 0
        self._offset_count = 0
        self._jump_pending = False
        self._enter(MagState.PROBE, now)
        return True

    # --- helpers --------------------------------------------------------------------------------

    def _read(self, address: int, count: int) -> bytes:
        raw = self._bus.read_registers(address, count)
        if len(raw) != count:
            raise BusError(f"short read: {len(raw)} of {count} bytes at {address:#04x}")
        return raw

    def _write_ctrl(self, index: int, value: int) -> None:
        """Write Internal Control `index` as a whole byte and keep its shadow."""
        self._bus.write_register(Register.INTERNAL_CONTROL_0 + index, value)
        if index == 0:
            value &= int(InternalControl0.INT_MEAS_DONE_EN | InternalControl0.AUTO_SR_EN)
        self._shadow[index] = value

    def _trigger(self, now: float) -> None:
        self._write_ctrl(0, self._shadow[0] | _TM_M)
        self._t_trigger = now
        self._phase = _Phase.WAIT

    def _data_ready(self, now: float) -> bool:
        """Poll Meas_M_Done once the measurement can be done; on timeout count it and re-trigger."""
        if now < self._t_trigger + self._t_meas:
            return False
        if self._read(Register.STATUS, 1)[0] & _MEAS_M_DONE:
            return True
        if now >= self._t_trigger + self._timeout_s:
            # No data-ready: a glitch, or a chip that reset and lost the measurement (and with it
            # bandwidth and polarity). Configure and calibrate again rather than trust it.
            self.timeouts += 1
            self.last_error = "data-ready timeout"
            self._enter(MagState.CONFIGURE, now)
        return False

    def _read_sample(self, sample_time_s: float) -> None:
        decode_field_T(self._read(Register.XOUT0, OUTPUT_BYTES), self.b_body_T)
        self.b_body_T -= self.offset_T
        self._deliver(sample_time_s)

    def _deliver(self, sample_time_s: float) -> None:
        self.sample_time_s = sample_time_s
        self.samples += 1
        self._samples_since_cal += 1
        self._new_sample = True
        self._backoff_s = BACKOFF_INITIAL_S

    def _calibration_due(self, now: float) -> bool:
        return self._rate_request is not None or (0 < self.calibration_interval <= self._samples_since_cal
                                                  and now - self._cal_end_s >= self.calibration_period_s)

    def _take_rate_request(self) -> None:
        """A requested rate comes into force as the calibration starts (its end sets up the new mode and grid)."""
        if self._rate_request is not None:
            self._apply_rate(self._rate_request)


def _max_abs_diff(a: np.ndarray, b: np.ndarray) -> float:
    """max_i |a_i - b_i| of two 3-vectors, without allocating."""
    return max(abs(float(a[0]) - float(b[0])), abs(float(a[1]) - float(b[1])), abs(float(a[2]) - float(b[2])))
