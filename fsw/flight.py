"""The flight software: the task table that ties driver → estimation → applications → telemetry together.

Tasks (base rate = the loop rate), in the order they run within a tick:

| task      | rate         | budget         | does                                                       |
|-----------|--------------|----------------|------------------------------------------------------------|
| uplink    | loop rate    | 10 % of period | the link's service (signing time, retry, stored frames);   |
|           |              |                | reads the ground's frames, verifies, runs commands (ACK)   |
| sensor    | loop rate    | 10 % of period | advances the magnetometer driver; a new sample goes into   |
|           |              |                | the sample queue (`fsw.sample_queue`)                      |
| latch (*) | loop rate    | 10 % of period | takes the oldest queued sample when the tick's budget has  |
|           |              |                | room for it; the de-orbit kit's field taken out            |
|           |              |                | (`deorbit.kit_field`; skipped while a shutter or magnet    |
|           |              |                | moves: sent, not used), refused if implausible             |
|           |              |                | (`estimation.sample_gate`)                                 |
| calibration (*) | loop rate | 40 % of period | host hard/soft iron taken out of the sample (needs the    |
|           |              |                | field along the orbit: `fsw.host_calibration`), then       |
|           |              |                | DEBRIS_MAGCAL every 10 s; a solve a minute (~2 ms) and a   |
|           |              |                | knot of the field a minute (~2 ms) are its peaks           |
| estimator (*) | loop rate  | 30 % of period | runs the rate estimators on a new sample                   |
| *app*     | the app's    | the app's      | each onboard application (`fsw.app.App`): its tick with    |
|           |              |                | the sample of this tick, then its telemetry — the inertia  |
|           |              |                | identification experiment (`fsw.ident`, every tick, (*)),    |
|           |              |                | the de-orbit kit (`fsw.deorbit.kit`, 10 Hz)                |
| telemetry (*) | loop rate  | 20 % of period | numbers and stores the sample, its frames (the sample, the |
|           |              |                | estimates, SITL's truth) into the outbox; samples the      |
|           |              |                | ground asked for again, within their budget                |
| downlink  | loop rate    | 20 % of period | the outbox's frames: one a tick, more while they fit       |
| calibration take | loop rate | 40 % of period | the calibration's update with the sample it held (1 Hz,   |
|           |              |                | ~0.3 ms): in the first tick with room, at most 0.1 s late  |
| status    | 1 Hz, spread | 20 % of period | HEARTBEAT, SYS_STATUS, DEBRIS_LINK_STATUS, loop timing,    |
|           |              |                | driver health, DEBRIS_SAMPLE_STORE: once a second, one     |
|           |              |                | step a tick on a fast loop (all in one tick on a slow one) |

(*) the sample pipeline: run again in the same tick, one queued sample a pass, while samples wait and the
tick's measured work plus a sample's measured cost fits 70 % of the period (`fsw.scheduler`). At 1 Hz
(`_status_rate`, `fsw.sample_rate`) the box compares the work a second with its budget and lowers the
magnetometer's output rate when the configured one does not fit.

Commands: handlers register with `self.commands` (`fsw.commands.CommandRouter`), parameters with
`self.params`; the uplink (`telemetry.uplink`) runs them when they arrive signed with the mission key.
The MAVLink services ground software expects (PING, TIMESYNC, REQUEST_MESSAGE, AUTOPILOT_VERSION,
message intervals, FTP refused) are `self.services` (`telemetry.services`); the messages set faster
than their own rate go out in the telemetry task.

Time comes from the caller of :meth:`FlightSoftware.tick`: the simulator's clock in SITL, a monotonic
clock on target. Nothing in here reads the wall clock.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Callable, Iterable, Protocol, runtime_checkable

import numpy as np

from .app import App
from .commands import CommandRouter, ParamTable
from .estimation.attitude_kalman import AttitudeRateKalman
from .estimation.rate_formulas import BoerStream, DerivativeStream
from .estimation.flown_filter import FILTER_IDS
from .estimation.rate_kalman import RateKalman
from .estimation.sample_gate import SampleGate, mark_gap
from .host_calibration import FixedField, HostCalibration
from . import sample_rate
from .percentiles import percentile_pair
from .sample_queue import SampleQueue
from .scheduler import Scheduler, Task, robust_mean
from .telemetry.dialect import mavlink
from .telemetry.sample_store import Resender, SampleStore
from .telemetry.services import Services
from .telemetry.telemetry import Telemetry
from .telemetry.uplink import LINK_STATUS_FIELDS, Uplink


class FieldSource(Protocol):
    """Anything that delivers magnetometer samples: the MMC5983MA driver, a recording replay."""

    b_body_T: np.ndarray
    sample_time_s: float

    def update(self, now_s: float) -> bool: ...


@runtime_checkable
class SensorDriver(Protocol):
    """A field source that is a device driver with health of its own (the MMC5983MA driver): its state
    and error counters go into SYS_STATUS and DEBRIS_MAG_STATUS."""

    state: int
    samples: int
    bus_errors: int
    timeouts: int
    bad_id: int
    resets: int
    offset_T: np.ndarray
    offset_jumps: int
    offset_outliers: int
    offset_disturbed: int


class Estimator(Protocol):
    """A rate estimator run on every sample (`fsw.estimation`)."""

    omega_radps: np.ndarray
    sigma_radps: np.ndarray
    flags: int
    #: how many estimates after a data gap still span it (a filter: 0, it propagates across the gap)
    gap_history: int

    def update(self, t_s: float, b_T: np.ndarray) -> bool: ...

    def reset(self) -> None: ...


@dataclass
class LatchedSample:
    """The magnetometer sample accepted this tick (what the applications get)."""

    t_s: float = 0.0
    b_T: np.ndarray = field(default_factory=lambda: np.zeros(3))


#: (method id, estimator) pairs run on every sample, in telemetry order
METHODS = {"boer": mavlink.DEBRIS_RATE_METHOD_BOER, "derivative": mavlink.DEBRIS_RATE_METHOD_DERIVATIVE,
           "kalman": mavlink.DEBRIS_RATE_METHOD_KALMAN}


#: the flown filter's attitude (ATTITUDE_QUATERNION, DEBRIS_ATTITUDE_SIGMA) goes out with its estimate at
#: most this often (s): every sample at the default 1 Hz, not 20 times a second at the link's sample cap
ATTITUDE_TLM_PERIOD_S = 1.0

#: the tick's work so far (share of the period) below which its first queued sample is processed whatever
#: its measured cost
FIRST_SAMPLE_BUSY = 0.25

#: loop rate from which the status messages go out one step a tick
SPREAD_STATUS_HZ = 200.0

#: the share of the period a tick may fill with deferrable work (a frame, the calibration's update)
ROOM = 0.9


class DeferredCost:
    """The measured cost of a piece of deferrable work [s]: the median of its last few runs (a rare slow
    one does not count), and whether the tick has room for it."""

    def __init__(self, last: int = 5) -> None:
        self._runs: deque = deque(maxlen=last)
        self.s = 0.0

    def fits(self, sched) -> bool:
        return sched.elapsed_s() + self.s <= ROOM * sched.period_s

    def run(self, sched, work: Callable[[], object]) -> None:
        t0 = sched.elapsed_s()
        work()
        self._runs.append(sched.elapsed_s() - t0)
        self.s = sorted(self._runs)[len(self._runs) // 2]


#: frames the outbox holds before a busy tick sends one all the same
OUTBOX_WAIT = 16

#: the longest the calibration's held sample waits for a tick with room (s); below the loop rate most ticks
#: have no sample and room, at a sample every tick there may be none (the update then overruns its tick)
TAKE_WAIT_S = 0.1

#: the longest the kit-field model's step fits wait for a tick with room for an iteration (s)
KIT_FIT_WAIT_S = 1.0

#: filter updates of an estimator's background work per tick (`FlownFilter.work`): the Euler filter's shape
#: trial, 34 hypotheses a sample, spread over the ticks between samples (about 1 ms each on the target)
ESTIMATOR_WORK_PER_TICK = 2


def _version() -> str:
    """The installed package's version (AUTOPILOT_VERSION), "0.0.0" when it is not installed."""
    try:
        from importlib.metadata import version

        return version("debris-box")
    except Exception:  # noqa: BLE001 - a source tree without metadata
        return "0.0.0"


def load_compiled_kernels() -> None:
    """Run the estimators' compiled kernels once on throwaway instances, so that loading them from the
    on-disk cache (or compiling them, the first time) happens before the loop, not in its first ticks."""
    b_T = np.array([20e-6, -10e-6, 30e-6])
    for est in (BoerStream(1e-7), DerivativeStream(1e-7), RateKalman(1e-7)):
        for k in range(3):
            est.update(0.1 * k, b_T + 1e-7 * k)
    # the attitude filter's step (fsw.estimation.mekf) with and without a field model, and Euler's equations
    # (fsw.estimation.euler_step) with the shape and with a known tensor and torque
    shape = AttitudeRateKalman(1e-7, field_eci_T=lambda t: b_T, estimate_inertia=True)
    tensor = AttitudeRateKalman(1e-7, inertia_kgm2=np.diag([1.0, 2.0, 3.0]), torque_Nm=lambda t: np.zeros(3))
    for kf in (shape, tensor):
        for k in range(3):
            kf.update(0.1 * k, b_T + 1e-7 * k)
        kf.euler = True
        kf.update(0.3, b_T)


class FlightSoftware:
    def __init__(self, source: FieldSource, telemetry: Telemetry, *, rate_hz: float, sigma_b_T: float,
                 truth: Callable[[float], object] | None = None, max_sample_tlm_hz: float = 20.0,
                 sample_rate_hz: float | None = None, uplink=None, key: bytes | None = None,
                 apps: Iterable[App] = (), rate_filter=None, sample_store: SampleStore | None = None,
                 field=None, field_provider=None, adapt_sample_rate: bool = False) -> None:
        """`uplink`: the connection commands arrive on (usually the telemetry link itself, `telemetry.conn`;
        None: no uplink); `key`: the mission key (None: every state-changing command is refused);
        `apps`: the onboard applications (`fsw.app.App`: the identification experiment, the de-orbit
        kit), run in this order after the estimators;
        `rate_filter`: the Kalman filter sent as DEBRIS_RATE_METHOD_KALMAN (default
        `estimation.rate_kalman.RateKalman`; `fsw.system.build_flight` gives the configured
        `estimation.flown_filter.FlownFilter`, whose attitude goes out as ATTITUDE_QUATERNION and
        DEBRIS_ATTITUDE_SIGMA with each of its estimates);
        `sample_store`: where the numbered samples are kept for the ground's requests (default: in
        memory, run id 0); `field`: the field along the orbit on board for the whole run (an
        `estimation.field_motion.OrbitField`), which the host-magnetics calibration needs, or
        `field_provider`: where it comes from when it may come and go (the time-and-orbit application);
        neither: the calibration is inactive and says so. `adapt_sample_rate`: once a second, the sample rate
        chosen from the loop's budget (`fsw.sample_rate`; needs a driver that can change its rate). The
        samples sent and stored are the sensor's own; the
        estimators and the applications get them calibrated."""
        self.source = source
        self.driver = source if isinstance(source, SensorDriver) else None
        self.tlm = telemetry
        self.truth = truth
        load_compiled_kernels()
        self.estimators: dict[str, Estimator] = {
            "boer": BoerStream(sigma_b_T), "derivative": DerivativeStream(sigma_b_T),
            "kalman": rate_filter if rate_filter is not None else RateKalman(sigma_b_T)}
        self.new_sample = False
        self.new_estimate = {name: False for name in self.estimators}
        #: samples received from the source; they wait in `queue` until the pipeline takes them
        self.samples = 0
        self.queue = SampleQueue()
        self._took = False  # the pipeline's pass took a sample from the queue
        self._dropped_seen = 0
        self._overruns_seen = 0
        self._over_windows = 0  # status rounds in a row whose figures did not fit the rate in force
        #: the live samples' frames waiting for `_downlink` (a handful: one sample's every `_tlm_every`)
        self.outbox: deque = deque()
        self._frame_cost_s = 0.0
        self._take_cost = DeferredCost()  # a calibration take's (a knot's or a solve's are rare)
        self._kit_fit_cost = DeferredCost()  # an iteration of the kit-field model's step fit
        self._kit_fit_idle_s = 0.0
        #: called after each sample's pass through the pipeline (a tick may take more than one): e.g. SITL's
        #: scoring, which copies the estimates there; keep them cheap, their time counts in the tick's
        self.sample_listeners: list[Callable[[], None]] = []
        self._taken_this_tick = 0
        self.latched = LatchedSample()
        #: the sensor's own sample (what is sent and stored), before the calibration
        self.raw_b_T = np.zeros(3)
        self._raw_kit_T = np.zeros(3)  # the kit's field taken out of raw_b_T
        self._gate_calibration = 0
        self.calibration = HostCalibration(sigma_b_T, FixedField(field) if field is not None else field_provider)
        # at most max_sample_tlm_hz samples (with their estimates) go out on the link
        #: the magnetometer's rate in force, and the one configured (`_status_rate` may lower the former)
        self.sample_rate_hz = self.configured_sample_rate_hz = float(sample_rate_hz or rate_hz)
        self.adapt_sample_rate = adapt_sample_rate and callable(getattr(source, "set_sample_rate", None))
        #: (loop time, from Hz, to Hz) of each change of the sample rate
        self.rate_changes: list[tuple[float, float, float]] = []
        self._max_sample_tlm_hz = max_sample_tlm_hz
        self._set_tlm_every()
        self.gate = SampleGate(sigma_b_T, 1.0 / (sample_rate_hz or rate_hz))
        self.tlm_samples = 0  # samples handed to telemetry
        self._next_attitude_s = -np.inf
        self.sample_store = sample_store if sample_store is not None else SampleStore()
        self.resender = Resender(self.sample_store)
        self._gap, self._gap_left = 0, {}
        #: estimator restarts after long gaps (refused or missing samples; never for kit-flagged ones)
        self.estimator_resets = 0
        self.commands = CommandRouter()
        self.params = ParamTable()
        self._register_params(sample_rate_hz or rate_hz)
        self.apps: dict[str, App] = {}
        messages = {"DEBRIS_SAMPLE_REQUEST": self._sample_request}
        for app in apps:
            if app.name in self.apps:
                raise ValueError(f"two applications named {app.name!r}")
            app.register(self.commands)
            if hasattr(app, "register_params"):
                app.register_params(self.params)
            for kind, handler in (app.message_handlers() if hasattr(app, "message_handlers") else {}).items():
                if kind in messages:
                    raise ValueError(f"two handlers for {kind}")
                messages[kind] = handler
            self.apps[app.name] = app
        utc_app = next((a for a in self.apps.values() if callable(getattr(a, "utc_s", None))), None)
        self.services = Services(telemetry, producers={
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: lambda now_s: self.tlm.heartbeat(),
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: lambda now_s: self._sys_status(self._link_counters()),
            mavlink.MAVLINK_MSG_ID_DEBRIS_LINK_STATUS: lambda now_s: self.tlm.link_status(
                now_s, **self._link_counters()),
            mavlink.MAVLINK_MSG_ID_DEBRIS_SAMPLE_STORE: lambda now_s: self.tlm.sample_store_status(
                now_s, self.sample_store, self.resender)},
            utc_s=None if utc_app is None else utc_app.utc_s, flight_sw_version=_version())
        self.services.register(self.commands)
        for kind, handler in self.services.message_handlers().items():
            messages.setdefault(kind, handler)  # an application's (the time's TIMESYNC, with the UTC) first
        # the de-orbit kit's field at the sensor (`fsw.deorbit.kit_field`): taken out of every sample before
        # the gate, the calibration and the estimators; samples taken while it moves are skipped by them
        self.kit_field = next((a.sensor_field for a in self.apps.values()
                               if getattr(a, "sensor_field", None) is not None), None)
        if self.kit_field is not None:
            self.kit_field.sigma_T = sigma_b_T
            self.kit_field.guard_s = max(self.kit_field.guard_s, 1.0 / rate_hz)
            self.kit_field.host = self._host_calibration_at  # its step fits on the host-calibrated field
            if self.driver is not None and hasattr(self.driver, "disturbed"):
                # the driver's offset measurements are kept from the kit's motions (`Mmc5983ma.disturbed`)
                self.driver.disturbed = self.kit_field.moved_between
        self.kit_T = np.zeros(3)
        self.kit_skip = False  # the latest sample was taken while the kit moved
        self.kit_skipped = 0
        self._kit_skips_in_gap = 0
        self._refused_gap = 0
        self.uplink = None if uplink is None else Uplink(
            uplink, self.commands, sysid=telemetry.mav.srcSystem, compid=telemetry.mav.srcComponent, key=key,
            clock=telemetry.clock, reply=telemetry.send_now if uplink is telemetry.conn else None,
            params=self.params, handlers=messages, answer_limit=self.services.allow)
        period = 1.0 / rate_hz
        self._status_steps = [self._status_health, self._status_link, self._status_rate, self._status_loop,
                              self._status_mag, self._status_store]
        self._status_step = len(self._status_steps)
        self._status_divider = max(1, round(rate_hz))  # ticks a second
        # one step a tick on a fast loop (periods of 5 ms or less), all in one tick on a slower one
        self._status_per_tick = 1 if rate_hz >= SPREAD_STATUS_HZ else len(self._status_steps)
        # and half a second after the 1 Hz tasks (the time-and-orbit application) there
        self._status_phase = self._status_divider // 2 if rate_hz >= SPREAD_STATUS_HZ else 0
        self.scheduler = Scheduler(rate_hz, [
            Task("uplink", self._uplink, rate_hz, 0.1 * period),
            Task("sensor", self._sensor, rate_hz, 0.1 * period),
            Task("latch", self._latch, rate_hz, 0.1 * period, per_sample=True),
            Task("calibration", self._calibrate, rate_hz, 0.4 * period, per_sample=True),
            Task("estimator", self._estimate, rate_hz, 0.3 * period, per_sample=True),
            *(Task(app.name, self._app_task(app), min(app.rate_hz, rate_hz), app.budget * period,
                   per_sample=app.rate_hz >= rate_hz) for app in self.apps.values()),
            Task("telemetry", self._telemetry, rate_hz, 0.2 * period, per_sample=True),
            Task("downlink", self._downlink, rate_hz, 0.2 * period),
            Task("calibration take", self._calibration_take, rate_hz, 0.4 * period),
            Task("status", self._status, rate_hz, 0.2 * period),
        ], backlog=self.queue.__len__, taken=lambda: self._took)

    @property
    def sample_t_s(self) -> float:
        return self.latched.t_s

    @property
    def sample_b_T(self) -> np.ndarray:
        return self.latched.b_T

    def _app_task(self, app: App) -> Callable[[float], None]:
        def run(now_s: float) -> None:
            app.tick(now_s, self.latched if self.new_sample and not self.kit_skip else None)
            app.telemetry(now_s, self.tlm)
        return run

    def tick(self, now_s: float) -> float:
        return self.scheduler.tick(now_s)

    def _register_params(self, sample_rate_hz: float) -> None:
        def set_tlm_hz(hz: float) -> None:
            self._max_sample_tlm_hz = hz
            self._set_tlm_every()

        self.params.register("TLM_SAMPLE_HZ", lambda: self.sample_rate_hz / self._tlm_every, set_tlm_hz, 0.01, 1000.0)
        rs = self.resender
        self.params.register("RESEND_BPS", lambda: rs.bytes_per_s, lambda v: setattr(rs, "bytes_per_s", v), 0.0, 1e6)
        store = self.tlm.store
        if store is not None:
            self.params.register("SF_REPLAY_BPS", lambda: store.replay_bytes_per_s,
                                 lambda v: setattr(store, "replay_bytes_per_s", v), 0.0, 1e6)

    def _set_tlm_every(self) -> None:
        """Every how many samples one goes out on the link: at most `_max_sample_tlm_hz` at the rate in force."""
        self._tlm_every = max(1, int(np.ceil(self.sample_rate_hz / self._max_sample_tlm_hz)))

    def _sample_request(self, msg, now_s: float, authenticated: bool) -> None:
        """DEBRIS_SAMPLE_REQUEST: queue the range for the resender (signed only, with a mission key: the
        uplink drops unauthenticated frames before they get here)."""
        self.resender.request(msg.first_seq, msg.count)

    def _link_counters(self) -> dict:
        if self.uplink is not None:
            return self.uplink.link_counters()
        return dict.fromkeys(LINK_STATUS_FIELDS, 0)

    # --- tasks ---------------------------------------------------------------------------------
    def _uplink(self, now_s: float) -> None:
        # first in the tick: the signing time, the link's retry and stored frames, before anything is sent
        self.tlm.service(now_s)
        if self.uplink is not None:
            self.uplink.poll(now_s)

    def _sensor(self, now_s: float) -> None:
        """The source's new sample, if any, into the queue (a full queue refuses it, counted)."""
        if self.kit_field is not None:
            self.kit_field.poll(now_s)
        self._taken_this_tick = 0
        if self.source.update(now_s):
            self.samples += 1
            self.queue.push(self.source.sample_time_s, self.source.b_body_T)

    def _may_take(self) -> bool:
        """Whether the pipeline takes a queued sample in this pass: when its measured cost fits the tick's
        budget; the first of a tick also when the tick has done little so far (a sample costlier than the
        budget is processed all the same, one a tick: the tick overruns, counted, and the sample rate's
        choice has to act) or the queue is a quarter full. A sample waits when the tick is already busy
        (the status task, a calibration solve, the OS's preemption) or in a catch-up pass without room."""
        sched = self.scheduler
        if sched.fits():
            return True
        return not self._taken_this_tick and (
            sched.elapsed_s() <= FIRST_SAMPLE_BUSY * sched.period_s or len(self.queue) >= self.queue.capacity // 4)

    def _latch(self, now_s: float) -> None:
        """The oldest queued sample latched for this pass of the pipeline: kit field, gate."""
        self.new_sample = self._took = False
        self.kit_skip = False
        if not self.queue.depth:
            return
        if not self._may_take():
            self.queue.deferred += 1
            return
        self._took = self.new_sample = True
        self._taken_this_tick += 1
        self.latched.t_s = self.queue.pop_into(self.latched.b_T)
        if self.kit_field is not None:
            kit_T, self.kit_skip = self.kit_field.field_at(self.sample_t_s)
            self.kit_T[:] = kit_T
            if self.kit_skip:  # a shutter or a magnet moves: sent and stored, neither judged nor used
                self.kit_skipped += 1
                self._kit_skips_in_gap += 1
                return
        # an implausible sample (saturated, stuck, spike) is neither estimated on nor sent; the host's
        # magnetism moves the field the chip sees with the attitude: the gate judges the calibrated
        # sample and allows for what the calibration may have left (all of it before there is one)
        if self.calibration.version != self._gate_calibration:  # the reference in the new calibration
            self._gate_calibration = self.calibration.version
            self.gate.rebase(self.calibration.for_gate(self.raw_b_T - self._raw_kit_T)[0])
        judged, self.gate.host_bound_T = self.calibration.for_gate(self.sample_b_T - self.kit_T)
        self.new_sample = self.gate.check(self.sample_t_s, self.sample_b_T, judged)
        if self.new_sample:
            # samples skipped while the kit moved are no reason to restart (the filter propagates
            # across them; the formulas' estimates across them are flagged DATA_GAP)
            self._refused_gap = self.gate.gap_samples - self._kit_skips_in_gap
            self._kit_skips_in_gap = 0
            if self.kit_field is not None:
                version = self.kit_field.version
                self.kit_field.record(self.sample_t_s, self.sample_b_T, advance=False)
                self._kit_fit(now_s)
                if self.kit_field.version != version:  # a new calibration: this sample and the gate's
                    self.kit_T[:] = self.kit_field.model_T()  # reference re-expressed in it
                    self.gate.rebase(self.calibration.for_gate(self.sample_b_T - self.kit_T)[0])
        if self.new_sample and self._refused_gap > self.gate.reset_after_gap:
            self.estimator_resets += 1
            for est in self.estimators.values():  # history too old to difference against
                est.reset()

    def _kit_fit(self, now_s: float) -> None:
        """The kit-field model's step fits advanced by the iterations due for this sample
        (`KitFieldModel.due`), each in the tick's room for an iteration's measured cost; an iteration is
        done all the same when none has been for `KIT_FIT_WAIT_S` (the fit then overruns its tick)."""
        kf, sched = self.kit_field, self.scheduler
        if not kf.evaluating:
            self._kit_fit_idle_s = now_s
            return
        for _ in range(kf.due()):
            if not (self._kit_fit_cost.fits(sched) or now_s - self._kit_fit_idle_s > KIT_FIT_WAIT_S):
                return
            self._kit_fit_cost.run(sched, kf.advance)
            self._kit_fit_idle_s = now_s
            if not kf.evaluating:
                return

    def _host_calibration_at(self, t_s: float):
        """The host's calibration applied at `t_s` (`fsw.estimation.magcal.Calibration`: b, D), None before
        a good one."""
        cal = self.calibration.cal
        return cal.calibration_at(t_s) if cal.good else None

    def _calibrate(self, now_s: float) -> None:
        if self.new_sample:
            self.raw_b_T[:] = self.latched.b_T
            kit = self.kit_T if self.kit_field is not None else None
            # the calibration's 1 Hz update (~0.3 ms) is held for `_calibration_take`, at the tick's end; it
            # learns from no sample taken while a magnet is unscreened (`KitFieldModel.unscreened`)
            keep_out = self.kit_skip or (self.kit_field is not None and self.kit_field.unscreened)
            self.latched.b_T[:] = self.calibration.process(self.sample_t_s, self.raw_b_T, kit, keep_out,
                                                           hold=True)
            if not self.kit_skip:
                self._raw_kit_T[:] = self.kit_T
        self.calibration.telemetry(now_s, self.tlm)

    def _calibration_take(self, now_s: float) -> None:
        """The calibration's held sample taken in, a step a tick (`HostCalibration.take_step`: the field's |B|,
        then the update), each in the first tick with room for a step's measured cost, or after
        `TAKE_WAIT_S` whatever the tick."""
        held = self.calibration.held
        if held is None:
            return
        sched = self.scheduler
        if not (self._take_cost.fits(sched) or now_s - held[0] > TAKE_WAIT_S):
            return
        self._take_cost.run(sched, self.calibration.take_step)

    def _estimate(self, now_s: float) -> None:
        for name, est in self.estimators.items():
            self.new_estimate[name] = (self.new_sample and not self.kit_skip
                                       and est.update(self.sample_t_s, self.sample_b_T))
            if hasattr(est, "work"):  # work spread over the ticks (the Euler filter's shape trial)
                est.work(ESTIMATOR_WORK_PER_TICK)
        self._flag_gaps()

    def _flag_gaps(self) -> None:
        """After samples went missing (refused, or the driver re-initialising): the estimates whose
        samples span the gap are flagged DATA_GAP with σ widened (`sample_gate.mark_gap`): one for a
        two-sample formula, two for a three-sample one (history length − 1); after a long gap the
        estimators start afresh."""
        if not self.new_sample or self.kit_skip:
            return
        gap = self.gate.gap_samples
        if self._refused_gap > self.gate.reset_after_gap:
            self._gap_left = {}  # the estimators were reset in _sensor
            return
        if gap:
            self._gap = gap
            # a filter propagates its covariance across the gap itself (gap_history = 0)
            self._gap_left = {name: est.gap_history for name, est in self.estimators.items()}
        for name, est in self.estimators.items():
            if self._gap_left.get(name, 0) > 0 and self.new_estimate[name]:
                self._gap_left[name] -= 1
                mark_gap(est, self._gap)

    def _telemetry(self, now_s: float) -> None:
        self.services.tick(now_s)
        self._live_sample()
        self.resender.service(now_s, self.tlm.resend_sample)
        if self._took:
            for listener in self.sample_listeners:
                listener()

    def _live_sample(self) -> None:
        """A sample for the link (every `_tlm_every`-th): numbered and stored now, its frames (the sample, the
        estimates, the attitude, SITL's truth) into the outbox with copies of what they carry, for
        `_downlink` to send a frame a tick on a fast loop."""
        if not self.new_sample or (self.queue.popped - 1) % self._tlm_every:
            return
        t = self.sample_t_s
        self.tlm_samples += 1
        flags = mavlink.DEBRIS_SAMPLE_FLAGS_KIT_MOVING if self.kit_skip else 0
        kit = self.kit_T.copy() if self.kit_field is not None else None  # what _calibrate took out of raw_b_T
        seq = self.sample_store.append(t, self.raw_b_T, flags, kit)
        out = self.outbox
        out.append((self.tlm.mag_sample, (t, self.raw_b_T.copy(), seq, self.sample_store.run_id, flags, kit)))
        for name, est in self.estimators.items():
            if self.new_estimate[name]:
                out.append((self.tlm.rate_estimate, (t, est.omega_radps.copy(), est.sigma_radps.copy(), METHODS[name],
                                                     est.flags)))
        kf = self.estimators["kalman"]
        if self.new_estimate["kalman"] and hasattr(kf, "attitude") and t >= self._next_attitude_s:
            self._next_attitude_s = t + ATTITUDE_TLM_PERIOD_S * (1 - 1e-9)
            att = kf.attitude()
            self.tlm.attitude(t, None if att is None else att[0], kf.omega_radps, None if att is None else att[1],
                              kf.sigma_radps, filter_id=FILTER_IDS[kf.name], flags=kf.flags, handovers=kf.handovers)
        if self.truth is not None:
            out.append((self._sim_state, (t,)))

    def _sim_state(self, t_s: float) -> None:
        tr = self.truth(t_s)
        self.tlm.sim_state(t_s, tr.omega_radps, tr.q_body_to_eci, tr.b_body_T, tr.moment_Nm)

    def _downlink(self, now_s: float) -> None:
        """The outbox's frames: the oldest one (unless the tick has no room left for it and few wait), then more
        while the tick's budget has room for the measured cost of one (so a sample's frames spread over the
        next ticks of a fast loop; a slow one sends them all in the tick)."""
        out, sched = self.outbox, self.scheduler
        if out and len(out) <= OUTBOX_WAIT and sched.elapsed_s() + self._frame_cost_s > ROOM * sched.period_s:
            return  # a busy tick: the frames wait for the next (a few at most)
        while out:
            t0 = sched.elapsed_s()
            send, args = out.popleft()
            send(*args)
            self._frame_cost_s = robust_mean(self._frame_cost_s, sched.elapsed_s() - t0)
            if not sched.fits(self._frame_cost_s):
                break

    def _status(self, now_s: float) -> None:
        """Once a second, the status messages: in one tick on a slow loop, one step a tick on a fast one (each
        step well under a 1 kHz period, where the whole set would take most of it)."""
        if self.scheduler.stats.ticks % self._status_divider == self._status_phase:
            self._status_step = 0
        steps = self._status_steps
        end = min(len(steps), self._status_step + self._status_per_tick)
        while self._status_step < end:
            steps[self._status_step](now_s)
            self._status_step += 1

    def _status_health(self, now_s: float) -> None:
        self.tlm.heartbeat()
        self._sys_status(self._link_counters())

    def _sys_status(self, link: dict) -> None:
        drv = self.driver
        healthy = (drv is None or int(drv.state) == mavlink.DEBRIS_MAG_STATE_MEASURE) and not self.gate.rejecting
        mean_us = self.scheduler.stats.window_mean_s() * 1e6
        self.tlm.sys_status(mag_healthy=healthy,
                            load_permille=int(mean_us * 1e-3 / self.scheduler.period_s),
                            errors_comm=(drv.bus_errors if drv else 0) + self.tlm.send_errors,
                            errors_count=(self.gate.rejected, drv.resets if drv else 0,
                                          sum(v for k, v in link.items() if k.startswith("rejected_")),
                                          self.tlm.store.dropped if self.tlm.store is not None else 0))

    def _status_link(self, now_s: float) -> None:
        self.tlm.link_status(now_s, **self._link_counters())

    def _status_loop(self, now_s: float) -> None:
        st = self.scheduler.stats
        mean_us, p50_us, p99_us, max_us = st.summary_us()
        q = self.queue
        self.tlm.loop_status(now_s, ticks=st.ticks, overruns=st.overruns, task_overruns=st.task_overruns,
                             period_s=self.scheduler.period_s, mean_us=mean_us, p50_us=p50_us, p99_us=p99_us,
                             max_us=max_us, sample_rate_hz=self.sample_rate_hz,
                             configured_sample_rate_hz=self.configured_sample_rate_hz,
                             sample_cost_us=st.window_sample_work_s / max(1, st.window_samples) * 1e6,
                             samples_taken=q.popped, samples_dropped=q.dropped, queue_depth=q.depth,
                             queue_max_depth=q.max_depth)
        st.reset_window()

    def _status_rate(self, now_s: float) -> None:
        """The sample rate from the loop's budget over the last second (`fsw.sample_rate`): lowered, with a
        STATUSTEXT, when the rate in force does not fit or the queue falls behind."""
        st = self.scheduler.stats
        if not self.adapt_sample_rate or st.window_ticks() < self._status_divider // 2 or not st.window_samples:
            return
        n = st.window_ticks()
        median_s = percentile_pair(st.window[:n], 50.0, 50.0)[0]
        budget = sample_rate.Budget.from_window(self.scheduler.rate_hz, median_s, st.window_samples / n,
                                                st.sample_cost_s)
        q = self.queue
        behind = q.dropped > self._dropped_seen or q.depth > q.capacity // 2
        self._dropped_seen = q.dropped
        overruns, self._overruns_seen = st.overruns - self._overruns_seen, st.overruns
        # overrunning ticks cost samples in the chip only when a sample comes every tick or two
        late = overruns > sample_rate.OVERRUN_SHARE * n and 2 * self.sample_rate_hz > self.scheduler.rate_hz
        over = budget.work_share(self.sample_rate_hz) > sample_rate.WORK_SHARE or late
        self._over_windows = self._over_windows + 1 if over else 0
        if not behind and self._over_windows < 2:
            return
        rate = sample_rate.choose(budget, self.sample_rate_hz, self.source.available_rates_hz(self.sample_rate_hz),
                                  behind=behind or over)
        if rate >= self.sample_rate_hz:
            return
        was = self.sample_rate_hz
        self.sample_rate_hz = self.source.set_sample_rate(rate)
        self.gate.sample_period_s = 1.0 / self.sample_rate_hz
        self._set_tlm_every()
        self.rate_changes.append((now_s, was, self.sample_rate_hz))
        self.tlm.statustext(f"mag rate {was:g}->{self.sample_rate_hz:g} Hz: load {budget.work_share(was):.2f}",
                            mavlink.MAV_SEVERITY_WARNING)

    def _status_mag(self, now_s: float) -> None:
        if self.driver is not None:
            self.tlm.mag_status(now_s, self.driver)

    def _status_store(self, now_s: float) -> None:
        self.tlm.sample_store_status(now_s, self.sample_store, self.resender)
        self.sample_store.sync()
