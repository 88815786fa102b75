"""Command sequencer of the de-orbit kit: explicit states, one interlock gate, recovery, safe mode.

Two channels (0 = pitch, 1 = yaw), each a magnet turned by a stepper (`fsw.drivers.stepper`) inside a
screening capsule (`fsw.drivers.capsule`). Everything that moves hardware — ground commands, the
automatic controller's pulses, recovery — is a *plan* (a short list of steps: turn, home, open, hold,
close) executed step by step; every step is started by :meth:`Sequencer._start_step`, which asks the one
interlock gate :meth:`Sequencer.permit` first. The gate's rules:

1. a magnet is turned or homed only while its capsule is confirmed closed (state CLOSED, closed switch
   on, open switch off): no torque transients;
2. a capsule is opened only while its magnet is at rest at a known polarity;
3. nothing but closing in SAFE mode or on a channel latched in FAULT; nothing but closing from the
   ground while the automatic controller runs (it owns the kit).

Refused requests are counted (`interlock_refusals` for rules 1-2). Independently, a monitor checks the
drivers every tick — a magnet moving while its capsule is not closed, a shutter motor running while its
magnet moves — and counts `interlock_violations`, which stays 0 because the gate refuses, not because
nobody checks.

Channel phases (:class:`Phase`): IDLE (closed, at rest: the only phase motion starts from), TURNING,
HOMING, OPENING, OPEN (the magnet acts; a pulse holds until its end time), CLOSING, RECOVERING, FAULT.

Timeouts: each driver bounds its own motion (stepper: profile time + margin, homing 60 s; capsule:
opening 4 s, closing 2 s). A step that ends in a driver fault starts the recovery of its channel:

- stepper fault (stall seen by the home switch, timeout): re-home (capsule closed), then retry the
  failed step once;
- capsule fault while opening or open (stuck, switches disagree): the spring closes it; once confirmed
  closed the fault is cleared and the opening retried once;
- anything else, a failed recovery or a second fault in the same plan: the channel latches FAULT and
  the whole kit goes to SAFE: every capsule released (the springs close them), every motion stopped,
  the controller stopped. Leaving SAFE (a ground command) needs every capsule confirmed closed; it
  clears the latched faults and leaves the magnets unhomed (they are re-homed before their next use).

Every transition — of the kit mode, of a channel phase, of a capsule or magnet state — and every
refusal and fault is reported as an :class:`Event` to `on_event` and kept in `events`.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Callable

from fsw.drivers.capsule import Capsule, CapsuleState, CapsuleTiming
from fsw.drivers.gpio import DigitalLines
from fsw.drivers.stepper import (
    HALF_TURN_STEPS,
    STEPS_PER_TURN,
    MagnetState,
    Stepper,
    StepperLimits,
)

from .energy import CHANNEL_NAMES, EnergyLedger


class KitMode(IntEnum):
    """The kit's mode; the values are DEBRIS_CONTROLLER_STATE."""

    OFF = 0  # manual: ground commands only
    RUNNING = 1  # the automatic controller drives the kit
    SAFE = 2


class Phase(IntEnum):
    IDLE = 0
    TURNING = 1
    HOMING = 2
    OPENING = 3
    OPEN = 4
    CLOSING = 5
    RECOVERING = 6
    FAULT = 7


class Source(IntEnum):
    GROUND = 0
    CONTROLLER = 1
    RECOVERY = 2


class Outcome(IntEnum):
    """Answer of the gate / of a request."""

    STARTED = 0  # accepted, motion under way
    DONE = 1  # accepted, nothing to do
    BUSY = 2  # the channel is busy with another plan
    INTERLOCK = 3  # an interlock forbids it now (capsule not closed, magnet moving)
    CONTROLLER = 4  # the automatic controller owns the kit
    SAFE = 5  # the kit is in SAFE mode
    FAULT = 6  # the channel is latched in FAULT
    UNHOMED = 7  # the magnet's position is unknown: home it first
    INVALID = 8  # a bad argument

    @property
    def accepted(self) -> bool:
        return self in (Outcome.STARTED, Outcome.DONE)


class Step(IntEnum):
    TURN = 0  # arg: target position (steps from home, absolute) or None with rel
    HOME = 1
    OPEN = 2
    HOLD = 3  # arg: width of the pulse [s]
    CLOSE = 4


@dataclass
class PlanStep:
    kind: Step
    target: int = 0  # TURN: absolute target position [steps from home]
    relative: int | None = None  # TURN: exactly this many steps (signed) instead of forwards to target
    width_s: float = 0.0  # HOLD


@dataclass(frozen=True)
class Event:
    t_s: float
    channel: int  # -1: the kit
    what: str  # "mode", "phase", "capsule", "magnet", "fault", "refused", "violation", "recovery"
    old: str
    new: str
    reason: str = ""

    def text(self) -> str:
        where = "kit" if self.channel < 0 else CHANNEL_NAMES[self.channel]
        arrow = f"{self.old}->{self.new}" if self.old or self.new else ""
        return f"deorbit {where} {self.what} {arrow} {self.reason}".strip()


@dataclass(frozen=True)
class SequencerConfig:
    open_ramp_s: float = 2.0  # nominal shutter opening time (the dipole ramps up meanwhile)
    close_ramp_s: float = 0.5  # nominal spring closing time
    retries: int = 1
    event_history: int = 512


@dataclass
class Channel:
    """One channel: its drivers, its plan and its phase."""

    index: int
    stepper: Stepper
    capsule: Capsule
    phase: Phase = Phase.IDLE
    plan: deque = field(default_factory=deque)
    step: PlanStep | None = None
    source: Source = Source.GROUND
    retries_left: int = 1
    fault: int = 0  # latched DEBRIS_DEORBIT_FAULT bits
    pulse_polarity: int = 0  # polarity of the running pulse (0: none)
    close_at_s: float = math.inf
    t_step_s: float = 0.0
    faults_seen: int = 0
    last_magnet: MagnetState = MagnetState.UNHOMED
    last_capsule: CapsuleState = CapsuleState.CLOSED

    @property
    def name(self) -> str:
        return CHANNEL_NAMES[self.index]

    @property
    def busy(self) -> bool:
        return self.step is not None or bool(self.plan)

    @property
    def polarity(self) -> int:
        return self.stepper.polarity

    @property
    def acting(self) -> int:
        """Polarity of the dipole acting now (capsule opening or open), 0 when screened."""
        if self.capsule.state in (CapsuleState.OPENING, CapsuleState.OPEN):
            return self.stepper.polarity
        return 0


class Sequencer:
    """The kit's two channels behind one interlock gate; call :meth:`update` every loop tick."""

    def __init__(self, io: DigitalLines, *, limits: StepperLimits = StepperLimits(),
                 timing: CapsuleTiming = CapsuleTiming(), config: SequencerConfig = SequencerConfig(),
                 on_event: Callable[[Event], None] | None = None) -> None:
        self.config = config
        self.channels = [Channel(i, Stepper(io, i, limits), Capsule(io, i, timing), retries_left=config.retries)
                         for i in range(2)]
        self.mode = KitMode.OFF
        self.on_event = on_event
        self.events: deque[Event] = deque(maxlen=config.event_history)
        self.events_total = 0
        self.interlock_refusals = 0
        self.interlock_violations = 0
        self.refusals = 0
        self.safe_entries = 0
        self.recoveries = 0
        self.last_safe_reason = ""
        self._now = 0.0

    # --- the gate -------------------------------------------------------------------------------
    def permit(self, ch: Channel, kind: Step, source: Source) -> Outcome:
        """The single interlock gate: may `source` start step `kind` on `ch` now?"""
        if kind is Step.CLOSE:
            return Outcome.STARTED
        if self.mode is KitMode.SAFE:
            return Outcome.SAFE
        if ch.phase is Phase.FAULT:
            return Outcome.FAULT
        if source is Source.GROUND and self.mode is KitMode.RUNNING:
            return Outcome.CONTROLLER
        st, cap = ch.stepper, ch.capsule
        if kind in (Step.TURN, Step.HOME):
            if not cap.closed:
                return Outcome.INTERLOCK  # rule 1: turn only while screened
            if st.moving:
                return Outcome.BUSY
            if kind is Step.TURN and st.state is not MagnetState.IDLE:
                return Outcome.UNHOMED
            if st.state is MagnetState.FAULT:
                return Outcome.FAULT
            return Outcome.STARTED
        if kind is Step.OPEN:
            if st.moving:
                return Outcome.INTERLOCK  # rule 2: never open while the magnet moves
            if st.polarity == 0:
                return Outcome.UNHOMED
            if cap.state is not CapsuleState.CLOSED or not cap.closed:
                return Outcome.BUSY if cap.state is not CapsuleState.FAULT else Outcome.FAULT
            return Outcome.STARTED
        return Outcome.STARTED  # HOLD: the capsule is already open

    # --- requests from the ground and the controller --------------------------------------------
    def request_capsule(self, channel: int, open_: bool, now_s: float, source: Source = Source.GROUND) -> Outcome:
        ch = self.channels[channel]
        if not open_:
            return self._run(ch, [PlanStep(Step.CLOSE)], now_s, source, replace=True)
        if ch.capsule.state is CapsuleState.OPEN:
            return Outcome.DONE
        return self._run(ch, [PlanStep(Step.OPEN)], now_s, source)

    def request_turn(self, channel: int, steps: int, now_s: float, source: Source = Source.GROUND) -> Outcome:
        ch = self.channels[channel]
        if steps == 0:
            return Outcome.DONE
        target = (ch.stepper.position_steps + steps) % STEPS_PER_TURN
        return self._run(ch, [PlanStep(Step.TURN, target, relative=int(steps))], now_s, source)

    def request_polarity(self, channel: int, polarity: int, now_s: float, source: Source = Source.GROUND) -> Outcome:
        if polarity not in (1, -1):
            return Outcome.INVALID
        ch = self.channels[channel]
        if ch.stepper.state is MagnetState.IDLE and ch.stepper.polarity == polarity and not ch.busy:
            return Outcome.DONE
        return self._run(ch, [PlanStep(Step.TURN, self._polarity_target(ch, polarity))], now_s, source)

    def request_home(self, channel: int, now_s: float, source: Source = Source.GROUND) -> Outcome:
        return self._run(self.channels[channel], [PlanStep(Step.HOME)], now_s, source)

    def pulse(self, channel: int, polarity: int, width_s: float, now_s: float) -> Outcome:
        """The controller's pulse: dipole `polarity` unscreened for `width_s` seconds.

        Open with the same polarity: the pulse is extended. Otherwise: close if needed, turn if needed
        (home first if unhomed), open, hold, close.
        """
        if polarity not in (1, -1) or not width_s > 0.0:
            return Outcome.INVALID
        ch = self.channels[channel]
        if self.mode is not KitMode.RUNNING:
            return Outcome.SAFE if self.mode is KitMode.SAFE else Outcome.INVALID
        if ch.phase is Phase.FAULT:
            return Outcome.FAULT
        if ch.phase in (Phase.RECOVERING,):
            return Outcome.BUSY
        if ch.pulse_polarity == polarity and ch.phase in (Phase.OPENING, Phase.OPEN):
            if ch.step is not None and ch.step.kind is Step.HOLD:
                ch.close_at_s = max(ch.close_at_s, now_s + width_s)
            else:
                for s in ch.plan:
                    if s.kind is Step.HOLD:
                        s.width_s = max(s.width_s, width_s)
            return Outcome.DONE
        plan: list[PlanStep] = []
        if ch.capsule.state is not CapsuleState.CLOSED:
            plan.append(PlanStep(Step.CLOSE))
        if ch.stepper.state in (MagnetState.UNHOMED,):
            plan.append(PlanStep(Step.HOME))
            plan.append(PlanStep(Step.TURN, 0 if polarity == 1 else HALF_TURN_STEPS))
        elif ch.stepper.polarity != polarity or ch.stepper.moving:
            plan.append(PlanStep(Step.TURN, self._polarity_target(ch, polarity)))
        plan += [PlanStep(Step.OPEN), PlanStep(Step.HOLD, width_s=width_s), PlanStep(Step.CLOSE)]
        out = self._run(ch, plan, now_s, Source.CONTROLLER, replace=True)
        if out.accepted:
            ch.pulse_polarity = polarity
        return out

    def end_pulse(self, channel: int, now_s: float) -> None:
        """Close the channel now if a controller pulse holds it open."""
        ch = self.channels[channel]
        if ch.source is Source.CONTROLLER and ch.busy:
            self._run(ch, [PlanStep(Step.CLOSE)], now_s, Source.CONTROLLER, replace=True)

    # --- modes ----------------------------------------------------------------------------------
    def start_controller(self, now_s: float) -> Outcome:
        if self.mode is KitMode.SAFE:
            return Outcome.SAFE
        if any(ch.phase is Phase.FAULT for ch in self.channels):
            return Outcome.FAULT
        if any(ch.busy and ch.source is Source.GROUND for ch in self.channels):
            return Outcome.BUSY
        self._set_mode(KitMode.RUNNING, now_s, "controller started")
        return Outcome.STARTED

    def stop_controller(self, now_s: float) -> Outcome:
        if self.mode is not KitMode.RUNNING:
            return Outcome.DONE
        for ch in self.channels:
            if ch.busy and ch.source is Source.CONTROLLER:
                self._run(ch, [PlanStep(Step.CLOSE)], now_s, Source.CONTROLLER, replace=True)
        self._set_mode(KitMode.OFF, now_s, "controller stopped")
        return Outcome.STARTED

    def enter_safe(self, now_s: float, reason: str) -> Outcome:
        """SAFE: every motion stopped, every capsule released (closed by its spring)."""
        self.last_safe_reason = reason
        if self.mode is not KitMode.SAFE:
            self.safe_entries += 1
            self._set_mode(KitMode.SAFE, now_s, reason)
        for ch in self.channels:
            ch.plan.clear()
            ch.step = None
            ch.pulse_polarity = 0
            ch.stepper.stop(now_s)
            ch.capsule.close(now_s)  # release: the spring closes it
            if ch.phase is not Phase.FAULT:
                ch.source = Source.RECOVERY
                ch.step = PlanStep(Step.CLOSE)  # watched: confirmed closed, or a latched fault
                ch.t_step_s = now_s
                self._set_phase(ch, Phase.CLOSING, now_s, "safe mode")
        return Outcome.STARTED

    def leave_safe(self, now_s: float) -> Outcome:
        """Back to OFF if every capsule is confirmed closed and nothing moves; clears latched faults."""
        if self.mode is not KitMode.SAFE:
            return Outcome.DONE
        for ch in self.channels:
            ch.capsule.update(now_s)
            if ch.stepper.moving or not ch.capsule.clear_fault(now_s) or not ch.capsule.closed:
                self._event(now_s, ch.index, "refused", "", "", "leave safe: capsule not confirmed closed")
                self.refusals += 1
                return Outcome.FAULT
        for ch in self.channels:
            if ch.stepper.state is MagnetState.FAULT:
                ch.stepper.clear_fault()
            ch.step = None
            ch.plan.clear()
            ch.fault = 0
            ch.faults_seen = 0
            ch.retries_left = self.config.retries
            self._set_phase(ch, Phase.IDLE, now_s, "left safe mode")
        self._set_mode(KitMode.OFF, now_s, "safe mode left")
        return Outcome.STARTED

    # --- the loop -------------------------------------------------------------------------------
    def update(self, now_s: float) -> None:
        """Drivers, then plans (fault handling, next steps), then the interlock monitor."""
        self._now = now_s
        for ch in self.channels:
            ch.stepper.update(now_s)
            ch.capsule.update(now_s)
            self._report_drivers(ch, now_s)
            self._advance(ch, now_s)
        self._monitor(now_s)

    def _advance(self, ch: Channel, now_s: float) -> None:
        if ch.step is None and not ch.plan and ch.phase is not Phase.FAULT and (
                ch.capsule.state is CapsuleState.FAULT or ch.stepper.state is MagnetState.FAULT):
            # a fault at rest (a switch that changes while nothing moves): nothing to retry
            self._latch(ch, now_s, ch.capsule.last_error or ch.stepper.last_error)
            return
        for _ in range(4):  # a few steps may complete in one tick (e.g. hold -> close)
            if ch.step is not None:
                done, failed = self._step_status(ch, now_s)
                if failed:
                    self._on_fault(ch, now_s, failed)
                    return
                if not done:
                    return
                ch.step = None
            if not ch.plan:
                if ch.phase not in (Phase.FAULT,):
                    self._set_phase(ch, self._rest_phase(ch), now_s, "plan done")
                    if ch.phase is Phase.IDLE:
                        ch.pulse_polarity = 0
                        ch.retries_left = self.config.retries
                return
            nxt = ch.plan.popleft()
            out = self._start_step(ch, nxt, now_s)
            if not out.accepted:
                ch.plan.clear()
                self._set_phase(ch, self._rest_phase(ch), now_s, f"plan aborted: {out.name}")
                return

    def _rest_phase(self, ch: Channel) -> Phase:
        if ch.phase is Phase.FAULT:
            return Phase.FAULT
        return Phase.OPEN if ch.capsule.state is CapsuleState.OPEN else Phase.IDLE

    def _start_step(self, ch: Channel, s: PlanStep, now_s: float) -> Outcome:
        out = self.permit(ch, s.kind, ch.source)
        if not out.accepted:
            self._refused(ch, s.kind, out, now_s)
            return out
        st, cap = ch.stepper, ch.capsule
        ch.step = s
        ch.t_step_s = now_s
        recovering = ch.source is Source.RECOVERY
        if s.kind is Step.TURN:
            # polarity changes go forwards: the home switch is passed once a turn (stall check)
            d = s.relative if s.relative is not None else (s.target - st.position_steps) % STEPS_PER_TURN
            if d == 0:
                ch.step = None
                return Outcome.DONE
            st.move(d, now_s)
            phase, what = Phase.TURNING, f"turn {d} steps"
        elif s.kind is Step.HOME:
            st.home(now_s)
            phase, what = Phase.HOMING, "home"
        elif s.kind is Step.OPEN:
            cap.open(now_s)
            phase, what = Phase.OPENING, "open"
        elif s.kind is Step.HOLD:
            ramps = 0.5 * (self.config.open_ramp_s + self.config.close_ramp_s)
            ch.close_at_s = now_s + max(0.0, s.width_s - ramps)
            phase, what = Phase.OPEN, f"hold {s.width_s:.0f} s"
        else:  # CLOSE (the spring; always allowed)
            cap.close(now_s)
            if cap.state is CapsuleState.CLOSED and cap.closed:
                ch.step = None
                return Outcome.DONE
            phase, what = Phase.CLOSING, "close"
        self._set_phase(ch, Phase.RECOVERING if recovering else phase, now_s, what)
        return Outcome.STARTED

    def _step_status(self, ch: Channel, now_s: float) -> tuple[bool, str]:
        """(done, failure) of the running step."""
        s, st, cap = ch.step, ch.stepper, ch.capsule
        if s.kind in (Step.TURN, Step.HOME):
            if st.state is MagnetState.FAULT:
                return False, f"magnet: {st.last_error}"
            if cap.state is CapsuleState.FAULT:
                return False, f"capsule: {cap.last_error}"
            return not st.moving, ""
        if s.kind is Step.OPEN:
            if cap.state is CapsuleState.FAULT:
                return False, f"capsule: {cap.last_error}"
            return cap.state is CapsuleState.OPEN, ""
        if s.kind is Step.HOLD:
            if cap.state is not CapsuleState.OPEN:
                return False, f"capsule: {cap.last_error or cap.state.name} while open"
            return now_s >= ch.close_at_s, ""
        # CLOSE: a capsule in FAULT has been released; once its switches say closed it is closed
        if cap.state is CapsuleState.FAULT:
            if cap.sw_closed and not cap.sw_open and cap.clear_fault(now_s):
                return cap.closed, ""
            if now_s - ch.t_step_s > cap.timing.close_timeout_s:
                return False, f"capsule not confirmed closed: {cap.last_error}"
            return False, ""
        return cap.closed, ""

    # --- faults and recovery --------------------------------------------------------------------
    def _on_fault(self, ch: Channel, now_s: float, why: str) -> None:
        s = ch.step
        bits = ch.stepper.fault | ch.capsule.fault
        ch.fault |= bits
        ch.faults_seen += 1
        self._event(now_s, ch.index, "fault", "", f"{bits:#x}", f"{s.kind.name}: {why}")
        ch.step = None
        ch.plan.clear()
        ch.pulse_polarity = 0
        retry_ok = ch.retries_left > 0 and ch.source is not Source.RECOVERY and self.mode is not KitMode.SAFE
        if s.kind in (Step.TURN, Step.HOME) and ch.stepper.state is MagnetState.FAULT and retry_ok:
            ch.retries_left -= 1
            self.recoveries += 1
            ch.stepper.clear_fault()
            retry = [PlanStep(Step.HOME)]
            if s.kind is Step.TURN:
                retry.append(PlanStep(Step.TURN, s.target % STEPS_PER_TURN))
            self._event(now_s, ch.index, "recovery", "", "", "re-home, then retry once")
            if self._run(ch, retry, now_s, Source.RECOVERY, replace=True, force=True).accepted:
                return
        if s.kind in (Step.OPEN, Step.HOLD) and ch.capsule.state is CapsuleState.FAULT and retry_ok:
            ch.retries_left -= 1
            self.recoveries += 1
            retry = [PlanStep(Step.CLOSE)] + ([PlanStep(Step.OPEN)] if s.kind is Step.OPEN else [])
            self._event(now_s, ch.index, "recovery", "", "", "the spring closes the capsule"
                        + (", then retry once" if s.kind is Step.OPEN else ""))
            if self._run(ch, retry, now_s, Source.RECOVERY, replace=True, force=True).accepted:
                return
        self._latch(ch, now_s, why)

    def _latch(self, ch: Channel, now_s: float, why: str) -> None:
        ch.fault |= ch.stepper.fault | ch.capsule.fault
        self._set_phase(ch, Phase.FAULT, now_s, why)
        self.enter_safe(now_s, f"{ch.name}: {why}")

    # --- monitor and reporting ------------------------------------------------------------------
    def _monitor(self, now_s: float) -> None:
        for ch in self.channels:
            st, cap = ch.stepper, ch.capsule
            if st.moving and not cap.closed:
                self._violation(ch, now_s, "magnet moving while its capsule is not closed")
            if st.moving and cap.motor_on:
                self._violation(ch, now_s, "shutter motor running while the magnet moves")

    def _violation(self, ch: Channel, now_s: float, why: str) -> None:
        self.interlock_violations += 1
        self._event(now_s, ch.index, "violation", "", "", why)

    def _refused(self, ch: Channel, kind: Step, out: Outcome, now_s: float) -> None:
        self.refusals += 1
        if out is Outcome.INTERLOCK:
            self.interlock_refusals += 1
        self._event(now_s, ch.index, "refused", "", kind.name, out.name)

    def _report_drivers(self, ch: Channel, now_s: float) -> None:
        m, c = ch.stepper.state, ch.capsule.state
        if m is not ch.last_magnet:
            self._event(now_s, ch.index, "magnet", ch.last_magnet.name, m.name, ch.stepper.last_error
                        if m is MagnetState.FAULT else "")
            ch.last_magnet = m
        if c is not ch.last_capsule:
            self._event(now_s, ch.index, "capsule", ch.last_capsule.name, c.name, ch.capsule.last_error
                        if c is CapsuleState.FAULT else "")
            ch.last_capsule = c

    def _set_phase(self, ch: Channel, phase: Phase, now_s: float, reason: str) -> None:
        if phase is not ch.phase:
            self._event(now_s, ch.index, "phase", ch.phase.name, phase.name, reason)
            ch.phase = phase

    def _set_mode(self, mode: KitMode, now_s: float, reason: str) -> None:
        if mode is not self.mode:
            self._event(now_s, -1, "mode", self.mode.name, mode.name, reason)
            self.mode = mode

    def _event(self, now_s: float, channel: int, what: str, old: str, new: str, reason: str = "") -> None:
        e = Event(now_s, channel, what, old, new, reason)
        self.events.append(e)
        self.events_total += 1
        if self.on_event is not None:
            try:
                self.on_event(e)
            except Exception:  # noqa: BLE001 - reporting never stops the sequencer
                pass

    # --- plans ----------------------------------------------------------------------------------
    def _run(self, ch: Channel, steps: list[PlanStep], now_s: float, source: Source, *,
             replace: bool = False, force: bool = False) -> Outcome:
        """Start `steps` on `ch` (its first step through the gate now).

        A busy channel refuses a new plan unless `replace` and the running plan has the same source
        (the controller re-plans its own pulses; a close always replaces) or `force` (recovery).
        """
        closing_only = all(s.kind is Step.CLOSE for s in steps)
        first = self.permit(ch, steps[0].kind, source)
        if first in (Outcome.SAFE, Outcome.FAULT, Outcome.CONTROLLER):  # not a matter of waiting
            self._refused(ch, steps[0].kind, first, now_s)
            return first
        if ch.busy and not force:
            same = ch.source is source or closing_only
            if not (replace and same):
                self._refused(ch, steps[0].kind, Outcome.BUSY, now_s)
                return Outcome.BUSY
        if not first.accepted:
            self._refused(ch, steps[0].kind, first, now_s)
            return first
        if ch.step is not None and ch.step.kind in (Step.TURN, Step.HOME) and ch.stepper.moving:
            # the magnet is turning: let that step finish, then run the new plan
            ch.plan = deque(steps)
            ch.source = source
            return Outcome.STARTED
        ch.plan = deque(steps)
        ch.step = None
        ch.source = source
        self._advance(ch, now_s)
        return Outcome.STARTED if ch.busy or ch.phase is not Phase.FAULT else Outcome.FAULT

    @staticmethod
    def _polarity_target(ch: Channel, polarity: int) -> int:
        return 0 if polarity == 1 else HALF_TURN_STEPS

    # --- telemetry ------------------------------------------------------------------------------
    def energy(self) -> EnergyLedger:
        return EnergyLedger.of([c.stepper for c in self.channels], [c.capsule for c in self.channels])
