"""The de-orbit kit on board: drivers + sequencer + discrete controller + ground commands + status.

`DeorbitKit.tick(now_s)` runs in the flight loop's "deorbit" task: the sequencer advances the drivers
and the plans; while the controller runs, a decision is taken at the start of each controller period
(`ControllerConfig.period_s`) from the attitude source, and turned into pulses of the sequencer.

Attitude: the controller needs the attitude w.r.t. the orbital frame, the rate relative to it, the
field in body axes and a forecast of the field along the orbit, from an `AttitudeSource`: the box's own
estimate (`fsw.deorbit.onboard_attitude.EstimatedAttitude`, fed here with every calibrated,
kit-compensated sample and the dipole the sequencer has unscreened), or in SITL and the benchmark the
simulator's truth for comparison (as lapkhanov2019 assumes). A source that has no attitude it trusts
returns None: the kit then holds both capsules closed for that period and counts it
(`decisions_without_attitude`); the reason goes out as STATUSTEXT when it changes, the controller's
inputs as DEBRIS_DEORBIT_ATTITUDE at 1 Hz.

Ground commands (COMMAND_LONG, dialect `debris.xml`), each a handler `(msg, now_s) -> MAV_RESULT` with
`msg.param1..param7`:

| command                          | params                                    |
|----------------------------------|-------------------------------------------|
| MAV_CMD_DEBRIS_CAPSULE 54010     | channel 0/1, open 1 / close 0             |
| MAV_CMD_DEBRIS_MAGNET_TURN 54011 | channel, angle deg in [−360, 360], k·1.8° |
| MAV_CMD_DEBRIS_MAGNET_POLARITY 54012 | channel, polarity ±1                  |
| MAV_CMD_DEBRIS_CONTROLLER 54013  | run 1 / stop 0, period s (0 keep), min impulse s (0 keep) |
| MAV_CMD_DEBRIS_SAFE_MODE 54014   | enter 1 / leave 0                         |
| MAV_CMD_DEBRIS_MAGNET_HOME 54015 | channel                                   |

Results: malformed or out-of-range parameters → DENIED (nothing executed); refused by an interlock,
a busy channel or the running controller → TEMPORARILY_REJECTED; SAFE mode, a latched fault or an
unhomed magnet → FAILED; accepted → ACCEPTED (the motion runs on; its end shows in the status).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from typing import Callable, Protocol


import numpy as np

from fsw.drivers.capsule import CapsuleState, CapsuleTiming
from fsw.drivers.gpio import DigitalLines
from fsw.drivers.stepper import STEP_DEG, StepperLimits
from fsw.telemetry.dialect import mavlink

from .controller import AttitudeInput, ChannelCommand, ControllerConfig, DiscreteController
from .energy import EnergyLedger
from .kit_field import DESIGN, KitFieldModel, MagnetGeometry
from .onboard_attitude import report_of
from .sequencer import Event, KitMode, Outcome, Sequencer, SequencerConfig

MAV_RESULT_OF = {
    Outcome.STARTED: mavlink.MAV_RESULT_ACCEPTED,
    Outcome.DONE: mavlink.MAV_RESULT_ACCEPTED,
    Outcome.BUSY: mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
    Outcome.INTERLOCK: mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
    Outcome.CONTROLLER: mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
    Outcome.SAFE: mavlink.MAV_RESULT_FAILED,
    Outcome.FAULT: mavlink.MAV_RESULT_FAILED,
    Outcome.UNHOMED: mavlink.MAV_RESULT_FAILED,
    Outcome.INVALID: mavlink.MAV_RESULT_DENIED,
}
MAX_PERIOD_S = 3600.0


class AttitudeSource(Protocol):
    """Where the controller's attitude comes from; `description` is shown with the results. Optional:
    ``observe(t_s, b_T, dipole_body_Am2, mean_dipole_body_Am2, kit_step_cov_T2)`` (each calibrated,
    kit-compensated sample with the kit's dipole from then on, its mean since the previous sample and how
    much the kit-field model's error may have stepped since then), ``report()`` (an
    `onboard_attitude.AttitudeReport` for telemetry) and ``reason`` (why there is no attitude)."""

    description: str

    def attitude(self, now_s: float) -> AttitudeInput | None: ...


@dataclass(frozen=True)
class DeorbitStatus:
    """The fields of DEBRIS_DEORBIT_STATUS (channel 0 = pitch, 1 = yaw)."""

    t_s: float
    position_steps: tuple[int, int]
    steps_total: tuple[int, int]
    energy_J: tuple[float, float]
    capsule_openings: tuple[int, int]
    magnet_turns: tuple[int, int]
    interlock_violations: int
    capsule_state: tuple[int, int]
    magnet_state: tuple[int, int]
    polarity: tuple[int, int]
    fault: tuple[int, int]
    controller_state: int


@dataclass(frozen=True)
class PulseRecord:
    """A controller decision applied to one channel (for plots and the benchmark)."""

    t_s: float
    channel: int
    polarity: int
    width_s: float
    m_theor_Nm: float
    m_ctrl_Nm: float
    outcome: Outcome


def _param(msg, i: int) -> float:
    v = getattr(msg, f"param{i}", math.nan)
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _choice(v: float, allowed: tuple[int, ...]) -> int | None:
    """`v` as one of the integers `allowed`, or None (NaN, fractional, out of range)."""
    if not math.isfinite(v) or v != round(v) or int(round(v)) not in allowed:
        return None
    return int(round(v))


class DeorbitKit:
    """The kit on `io` (the GPIO lines or the emulator); controller decisions from `attitude`. An onboard
    application (`fsw.app.App`): its task at 10 Hz, DEBRIS_DEORBIT_STATUS at 1 Hz, its transitions,
    refusals and faults as STATUSTEXT (the last `MAX_EVENTS` waiting; older ones counted as dropped)."""

    name = "deorbit"
    rate_hz = 10.0
    budget = 0.5
    MAX_EVENTS = 32
    STATUS_PERIOD_S = 1.0

    def __init__(self, io: DigitalLines, attitude: AttitudeSource | None = None, *,
                 controller: ControllerConfig = ControllerConfig(), limits: StepperLimits = StepperLimits(),
                 timing: CapsuleTiming = CapsuleTiming(), sequencer: SequencerConfig = SequencerConfig(),
                 on_event: Callable[[Event], None] | None = None, keep_pulses: bool = False,
                 magnets: tuple[MagnetGeometry, ...] = DESIGN, field_tlm_every_s: float = 10.0) -> None:
        """`magnets`: where the magnets sit relative to the magnetometer and how they are built (the kit's
        field at the sensor, `sensor_field`, is modelled from them and the channels' states)."""
        self._on_event = on_event
        self.events: deque[Event] = deque(maxlen=self.MAX_EVENTS)  # waiting for telemetry
        self.events_dropped = 0
        self._next_status_s = -math.inf
        self.sequencer = Sequencer(io, limits=limits, timing=timing, config=sequencer, on_event=self._event)
        self.controller = DiscreteController(controller)
        #: the kit's field at the magnetometer (`fsw.deorbit.kit_field`): the flight loop takes it out of
        #: every sample and skips the samples taken while something moves
        self.sensor_field = KitFieldModel(self.sequencer.channels, magnets)
        self.field_tlm_every_s = field_tlm_every_s
        self._next_field_tlm_s = -math.inf
        self.attitude = attitude
        self.next_decision_s = math.inf
        self.decisions_without_attitude = 0
        self.last_input: AttitudeInput | None = None
        self.hold_reason = ""
        # the dipole's time integral since the last sample handed to the attitude source (a moving
        # shutter counted as half open: the mean of its ramp)
        self._impulse_Am2s = np.zeros(3)
        self._impulse_t_s: float | None = None
        self._impulse_from_s: float | None = None
        self._dipole_now_Am2 = np.zeros(3)
        # the kit-field model at the last sample handed over: its coefficients, and its calibration (the
        # model replaces P at every calibration, so the reference and the version are the calibration then)
        self._kit_c: np.ndarray | None = None
        self._kit_P: np.ndarray | None = None
        self._kit_version = -1
        self._hold_reason_sent = ""
        #: the magnets' build and placement (`MagnetGeometry`, one per channel), for the laws that plan with them
        self.magnets = magnets
        self.pulses: list[PulseRecord] | None = [] if keep_pulses else None
        #: another pulse law in place of the controller while the kit runs (the mission's detumbling,
        #: `fsw.deorbit.detumble.DetumbleLaw`): its `period_s`, `decide(now_s, channels) -> [ChannelCommand]`
        self.law = None
        #: SITL only: loop time -> the simulation's true (yaw, pitch, roll) [rad], sent beside the controller's
        #: inputs in DEBRIS_DEORBIT_ATTITUDE.truth_ypr so that the ground can score them (None on the target)
        self.truth_ypr: Callable[[float], tuple[float, float, float]] | None = None
        self.truth_errors = 0
        self.handlers: dict[int, Callable] = {
            mavlink.MAV_CMD_DEBRIS_CAPSULE: self.cmd_capsule,
            mavlink.MAV_CMD_DEBRIS_MAGNET_TURN: self.cmd_magnet_turn,
            mavlink.MAV_CMD_DEBRIS_MAGNET_POLARITY: self.cmd_magnet_polarity,
            mavlink.MAV_CMD_DEBRIS_CONTROLLER: self.cmd_controller,
            mavlink.MAV_CMD_DEBRIS_SAFE_MODE: self.cmd_safe_mode,
            mavlink.MAV_CMD_DEBRIS_MAGNET_HOME: self.cmd_magnet_home,
        }

    @property
    def mode(self) -> KitMode:
        return self.sequencer.mode

    def _event(self, event: Event) -> None:
        if len(self.events) == self.events.maxlen:
            self.events_dropped += 1
        self.events.append(event)
        if self._on_event is not None:
            self._on_event(event)

    # --- the loop -------------------------------------------------------------------------------
    def tick(self, now_s: float, sample=None) -> None:
        """A due controller decision first (so that a pulse ending now can be extended rather than
        closed and reopened), then the sequencer: drivers, plans, interlock monitor."""
        seq = self.sequencer
        if self._impulse_t_s is not None and now_s > self._impulse_t_s:
            self._impulse_Am2s += self._dipole_now_Am2 * (now_s - self._impulse_t_s)
        self._impulse_t_s = now_s
        if sample is not None and hasattr(self.attitude, "observe"):
            span = now_s - self._impulse_from_s if self._impulse_from_s is not None else 0.0
            mean = self._impulse_Am2s / span if span > 0.0 else None
            self.attitude.observe(sample.t_s, sample.b_T, self.known_dipole_body_Am2(), mean, self._kit_step_cov())
            self._impulse_Am2s.fill(0.0)
            self._impulse_from_s = now_s
        if seq.mode is KitMode.RUNNING:
            if math.isinf(self.next_decision_s):
                self.next_decision_s = now_s
            if now_s + 1e-9 >= self.next_decision_s:
                if self.law is not None:
                    self.next_decision_s = max(self.next_decision_s + self.law.period_s, now_s)
                    for cmd in self.law.decide(now_s, seq.channels):
                        self._apply(cmd, now_s)
                else:
                    self.next_decision_s += self.controller.config.period_s
                    self._decide(now_s)
        else:
            self.next_decision_s = math.inf
        seq.update(now_s)
        self._dipole_now_Am2 = self.known_dipole_body_Am2(moving=0.5)

    def _kit_step_cov(self) -> np.ndarray | None:
        """How much the kit-compensated samples' error may have stepped since the previous sample [T², 3×3]:
        a channel's change of state by the kit-field model's uncertainty of that change, a calibration taken in
        by the variance it removed from the current state's field; None while a channel moves."""
        kf = self.sensor_field
        c = kf.coefficients()
        if c is None:
            return None
        cov = np.zeros((3, 3))
        if self._kit_c is not None:
            if np.any(c != self._kit_c):
                cov += kf.error_cov_T2(c - self._kit_c)
            if kf.version != self._kit_version:
                cov += kf.error_cov_T2(c, self._kit_P) - kf.error_cov_T2(c)
        self._kit_c, self._kit_P, self._kit_version = c, kf.P, kf.version
        return cov

    def _decide(self, now_s: float) -> None:
        seq = self.sequencer
        att = self.attitude.attitude(now_s) if self.attitude is not None else None
        self.last_input = att
        why = "" if att is not None else getattr(self.attitude, "reason", "") or "no attitude source"
        if att is not None:
            chans = seq.channels
            try:
                cmds = self.controller.decide(now_s, att, acting=tuple(c.acting for c in chans),
                                              polarity=tuple(c.polarity for c in chans))
            except ValueError as e:  # the field forecast along the orbit failed (SGP4 over the horizon)
                why = f"field forecast: {e}"
        if why:
            self.decisions_without_attitude += 1
            self.hold_reason = why
            for i in range(2):
                seq.end_pulse(i, now_s)
            return
        self.hold_reason = ""
        for cmd in cmds:
            self._apply(cmd, now_s)

    def _apply(self, cmd: ChannelCommand, now_s: float) -> None:
        seq = self.sequencer
        if cmd.polarity == 0 or cmd.width_s <= 0.0:
            seq.end_pulse(cmd.channel, now_s)
            out = Outcome.DONE
        else:
            out = seq.pulse(cmd.channel, cmd.polarity, cmd.width_s, now_s)
        if self.pulses is not None:
            self.pulses.append(PulseRecord(now_s, cmd.channel, cmd.polarity, cmd.width_s, cmd.m_theor_Nm,
                                           cmd.m_ctrl_Nm, out))

    # --- status ---------------------------------------------------------------------------------
    def telemetry(self, now_s: float, tlm) -> None:
        """The events since the last call as STATUSTEXT (faults and violations as errors),
        DEBRIS_DEORBIT_STATUS once a second, DEBRIS_KIT_FIELD (per channel) every `field_tlm_every_s`."""
        while self.events:
            event = self.events.popleft()
            severity = (mavlink.MAV_SEVERITY_ERROR if event.what in ("fault", "violation") else
                        mavlink.MAV_SEVERITY_WARNING if event.what in ("refused", "recovery") or
                        (event.what == "mode" and event.new == "SAFE") else mavlink.MAV_SEVERITY_INFO)
            tlm.statustext(event.text(), severity)
        if self.hold_reason != self._hold_reason_sent:
            self._hold_reason_sent = self.hold_reason
            tlm.statustext(f"deorbit: capsules held closed: {self.hold_reason}" if self.hold_reason else
                           "deorbit: controller acting on a trusted attitude", mavlink.MAV_SEVERITY_INFO)
        if now_s >= self._next_status_s:
            self._next_status_s = max(self._next_status_s + self.STATUS_PERIOD_S, now_s)
            tlm.deorbit_status(now_s, self.status(now_s))
            truth = (math.nan,) * 3
            if self.truth_ypr is not None:
                try:
                    truth = self.truth_ypr(now_s)
                except Exception:  # noqa: BLE001 - SITL's scoring aid never brings the loop down
                    self.truth_errors += 1
            tlm.deorbit_attitude(now_s, self.attitude_report(), self.decisions_without_attitude, truth)
        if now_s >= self._next_field_tlm_s:
            self._next_field_tlm_s = max(self._next_field_tlm_s + self.field_tlm_every_s, now_s)
            self.sensor_field.telemetry(now_s, tlm)

    def status(self, now_s: float) -> DeorbitStatus:
        chs = self.sequencer.channels

        def pair(f):
            return tuple(f(c) for c in chs)

        return DeorbitStatus(
            t_s=now_s, position_steps=pair(lambda c: int(c.stepper.position_steps)),
            steps_total=pair(lambda c: int(c.stepper.steps_total)),
            energy_J=pair(lambda c: float(c.stepper.energy_J + c.capsule.energy_J)),
            capsule_openings=pair(lambda c: int(c.capsule.openings)),
            magnet_turns=pair(lambda c: int(c.stepper.turns)),
            interlock_violations=int(self.sequencer.interlock_violations),
            capsule_state=pair(lambda c: int(c.capsule.state)), magnet_state=pair(lambda c: int(c.stepper.state)),
            polarity=pair(lambda c: int(c.stepper.polarity)),
            fault=pair(lambda c: int(c.fault | c.stepper.fault | c.capsule.fault) & 0xFF),
            controller_state=int(self.sequencer.mode))

    def known_dipole_body_Am2(self, moving: float | None = None) -> np.ndarray:
        """The kit's unscreened dipole in body axes as the sequencer knows it: each channel acting
        (capsule opening or open) with its polarity, along its magnet's home axis (polarity −1: half a
        turn about the shaft) [A·m²]. `moving`: the fraction counted for a capsule opening or closing
        (None: opening counts whole, closing not at all)."""
        p = np.zeros(3)
        for ch, mag in zip(self.sequencer.channels, self.magnets):
            if moving is not None and ch.capsule.state in (CapsuleState.OPENING, CapsuleState.CLOSING):
                w = moving * ch.polarity
            else:
                w = ch.acting
            if w:
                p += w * mag.moment_Am2 * np.asarray(mag.home_axis, float)
        return p

    def attitude_report(self):
        """The controller's inputs for DEBRIS_DEORBIT_ATTITUDE: the source's own report, or (a source
        without one: the truth) the attitude of the last decision with zero σ."""
        if hasattr(self.attitude, "report"):
            return self.attitude.report()
        src = (mavlink.DEBRIS_CONTROLLER_ATTITUDE_NONE if self.last_input is None
               else mavlink.DEBRIS_CONTROLLER_ATTITUDE_TRUTH)
        return report_of(self.last_input, src)

    def energy(self) -> EnergyLedger:
        return self.sequencer.energy()

    # --- ground commands ------------------------------------------------------------------------
    def register(self, router) -> None:
        """Register the handlers with a command router (`router.register(cmd, handler, changes_state=...)`)."""
        for cmd, handler in self.handlers.items():
            router.register(cmd, handler, changes_state=True)

    def handle_command(self, msg, now_s: float) -> int:
        """Dispatch a COMMAND_LONG-like `msg` (when no router is used); never raises."""
        handler = self.handlers.get(int(getattr(msg, "command", -1)))
        if handler is None:
            return mavlink.MAV_RESULT_UNSUPPORTED
        try:
            return handler(msg, now_s)
        except Exception:  # noqa: BLE001 - a command never brings the loop down
            return mavlink.MAV_RESULT_FAILED

    def cmd_capsule(self, msg, now_s: float) -> int:
        ch, op = _choice(_param(msg, 1), (0, 1)), _choice(_param(msg, 2), (0, 1))
        if ch is None or op is None:
            return mavlink.MAV_RESULT_DENIED
        return MAV_RESULT_OF[self.sequencer.request_capsule(ch, bool(op), now_s)]

    def cmd_magnet_turn(self, msg, now_s: float) -> int:
        ch, angle = _choice(_param(msg, 1), (0, 1)), _param(msg, 2)
        if ch is None or not math.isfinite(angle) or abs(angle) > 360.0:
            return mavlink.MAV_RESULT_DENIED
        steps = angle / STEP_DEG
        if abs(steps - round(steps)) > 1e-4:
            return mavlink.MAV_RESULT_DENIED  # not a whole number of 1.8° steps
        return MAV_RESULT_OF[self.sequencer.request_turn(ch, int(round(steps)), now_s)]

    def cmd_magnet_polarity(self, msg, now_s: float) -> int:
        ch, pol = _choice(_param(msg, 1), (0, 1)), _choice(_param(msg, 2), (1, -1))
        if ch is None or pol is None:
            return mavlink.MAV_RESULT_DENIED
        return MAV_RESULT_OF[self.sequencer.request_polarity(ch, pol, now_s)]

    def cmd_magnet_home(self, msg, now_s: float) -> int:
        ch = _choice(_param(msg, 1), (0, 1))
        if ch is None:
            return mavlink.MAV_RESULT_DENIED
        return MAV_RESULT_OF[self.sequencer.request_home(ch, now_s)]

    def cmd_safe_mode(self, msg, now_s: float) -> int:
        enter = _choice(_param(msg, 1), (0, 1))
        if enter is None:
            return mavlink.MAV_RESULT_DENIED
        seq = self.sequencer
        out = seq.enter_safe(now_s, "ground command") if enter else seq.leave_safe(now_s)
        return MAV_RESULT_OF[out]

    def cmd_controller(self, msg, now_s: float) -> int:
        run = _choice(_param(msg, 1), (0, 1))
        period, t_min = _param(msg, 2), _param(msg, 3)
        if run is None or not (math.isfinite(period) and math.isfinite(t_min)) or period < 0 or t_min < 0:
            return mavlink.MAV_RESULT_DENIED
        cfg = self.controller.config
        if run and (period > 0 or t_min > 0):
            new_period = period if period > 0 else cfg.period_s
            new_min = t_min if t_min > 0 else cfg.min_impulse_s
            if not (new_min <= new_period <= MAX_PERIOD_S):
                return mavlink.MAV_RESULT_DENIED
            if (new_period, new_min) != (cfg.period_s, cfg.min_impulse_s):
                widths = tuple(sorted({new_min, 0.5 * (new_min + new_period), new_period}))
                try:
                    self.controller = DiscreteController(replace(cfg, period_s=new_period, min_impulse_s=new_min,
                                                                 widths_s=widths))
                except ValueError:
                    return mavlink.MAV_RESULT_DENIED
        seq = self.sequencer
        out = seq.start_controller(now_s) if run else seq.stop_controller(now_s)
        if run and out.accepted:
            self.next_decision_s = now_s
        return MAV_RESULT_OF[out]

