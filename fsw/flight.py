"""The flight software: the task table that ties driver → estimation → telemetry together.

Tasks (base rate = the loop rate):

| task      | rate       | budget        | does                                                      |
|-----------|------------|---------------|-----------------------------------------------------------|
| sensor    | loop rate  | 20 % of period| advances the magnetometer driver; latches a new sample   |
| estimator | loop rate  | 30 % of period| runs the rate estimators on a new sample                  |
| telemetry | loop rate  | 30 % of period| sends the sample, the estimates (and SITL truth)          |
| status    | 1 Hz       | 50 % of period| HEARTBEAT, SYS_STATUS, loop timing, driver health         |

Time comes from the caller of :meth:`FlightSoftware.tick`: the simulator's clock in SITL, a monotonic
clock on target. Nothing in here reads the wall clock.
"""
from __future__ import annotations

from typing import Callable, Protocol

import numpy as np

from .estimation.rate_formulas import BoerStream, DerivativeStream
from .scheduler import Scheduler, Task
from .telemetry.dialect import mavlink
from .telemetry.telemetry import Telemetry


class FieldSource(Protocol):
    """Anything that delivers magnetometer samples: the MMC5983MA driver, a recording replay."""

    b_body_T: np.ndarray
    sample_time_s: float

    def update(self, now_s: float) -> bool: ...


#: (method id, estimator) pairs run on every sample, in telemetry order
METHODS = {"boer": mavlink.DEBRIS_RATE_METHOD_BOER, "derivative": mavlink.DEBRIS_RATE_METHOD_DERIVATIVE}


class FlightSoftware:
    def __init__(self, source: FieldSource, telemetry: Telemetry, *, rate_hz: float, sigma_b_T: float,
                 truth: Callable[[float], object] | None = None, max_sample_tlm_hz: float = 20.0,
                 sample_rate_hz: float | None = None) -> None:
        self.source = source
        self.tlm = telemetry
        self.truth = truth
        self.estimators = {"boer": BoerStream(sigma_b_T), "derivative": DerivativeStream(sigma_b_T)}
        self.new_sample = False
        self.new_estimate = {name: False for name in self.estimators}
        self.samples = 0
        self.sample_t_s = 0.0
        self.sample_b_T = np.zeros(3)
        # at most max_sample_tlm_hz samples (with their estimates) go out on the link
        self._tlm_every = max(1, int(np.ceil((sample_rate_hz or rate_hz) / max_sample_tlm_hz)))
        period = 1.0 / rate_hz
        self.scheduler = Scheduler(rate_hz, [
            Task("sensor", self._sensor, rate_hz, 0.2 * period),
            Task("estimator", self._estimate, rate_hz, 0.3 * period),
            Task("telemetry", self._telemetry, rate_hz, 0.3 * period),
            Task("status", self._status, min(1.0, rate_hz), 0.5 * period),
        ])

    def tick(self, now_s: float) -> float:
        return self.scheduler.tick(now_s)

    # --- tasks ---------------------------------------------------------------------------------
    def _sensor(self, now_s: float) -> None:
        self.new_sample = self.source.update(now_s)
        if self.new_sample:
            self.samples += 1
            self.sample_t_s = self.source.sample_time_s
            self.sample_b_T[:] = self.source.b_body_T

    def _estimate(self, now_s: float) -> None:
        for name, est in self.estimators.items():
            self.new_estimate[name] = self.new_sample and est.update(self.sample_t_s, self.sample_b_T)

    def _telemetry(self, now_s: float) -> None:
        if not self.new_sample or (self.samples - 1) % self._tlm_every:
            return
        t = self.sample_t_s
        self.tlm.mag_sample(t, self.sample_b_T)
        for name, est in self.estimators.items():
            if self.new_estimate[name]:
                self.tlm.rate_estimate(t, est.omega_radps, est.sigma_radps, METHODS[name], est.flags)
        if self.truth is not None:
            tr = self.truth(t)
            self.tlm.sim_state(t, tr.omega_radps, tr.q_body_to_eci, tr.b_body_T, tr.moment_Nm)

    def _status(self, now_s: float) -> None:
        st = self.scheduler.stats
        mean_us, p50_us, p99_us, max_us = st.summary_us()
        src = self.source
        healthy = getattr(src, "state", None) is None or int(src.state) == mavlink.DEBRIS_MAG_STATE_MEASURE
        self.tlm.heartbeat()
        self.tlm.sys_status(mag_healthy=healthy,
                            load_permille=int(mean_us * 1e-3 / self.scheduler.period_s),
                            errors_comm=getattr(src, "bus_errors", 0) + self.tlm.send_errors)
        self.tlm.loop_status(now_s, ticks=st.ticks, overruns=st.overruns, task_overruns=st.task_overruns,
                             period_s=self.scheduler.period_s, mean_us=mean_us, p50_us=p50_us, p99_us=p99_us,
                             max_us=max_us)
        if hasattr(src, "offset_T"):
            self.tlm.mag_status(now_s, src)
        st.reset_window()
