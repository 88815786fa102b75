"""The mission on the box's own estimates: tumbling → identified → detumbled → stabilised to the flow.

An onboard application (`fsw.app.App`, "mission") that drives the identification experiment
(`fsw.ident`) and the de-orbit kit (`fsw.deorbit.kit`) through the phases of DEBRIS_MISSION_PHASE.
Every change is automatic on the criterion below, or commanded (signed MAV_CMD_DEBRIS_MISSION_PHASE
54016 / MAV_CMD_DEBRIS_MISSION_SAFE 54017); each is reported as STATUSTEXT and in DEBRIS_MISSION_STATUS
(1 Hz: phase, time in phase, reason, the tumble, the identification, the kit's energy per phase).

Phases, what the box does in each, and when it leaves (automatic):

- TUMBLING: the flown rate filter runs on the calibrated samples. → RATES_KNOWN when the rate's 1-σ
  (largest axis) stays ≤ `rate_sigma_max_radps` for `rates_hold_s`.
- RATES_KNOWN: both magnets homed (capsules closed). → IDENTIFYING when both are homed and the experiment
  starts (or DETUMBLING at once with a tensor kept across a restart that meets the accuracy).
- IDENTIFYING: the experiment (`fsw.ident`, source MAGNETS) with the kit's magnets as the known torque:
  both capsules open at the homed polarity for `ident_torque_s` between free observations, M = p × B
  with p as the sequencer reports it, the output-error fit. → DETUMBLING when the final fit's 95 %
  half-widths are all ≤ `ident_ci95_frac` of the largest moment; else another attempt, SAFE after
  `ident_attempts`. A later attempt's tensor is combined with the earlier attempts' that agree with it
  (:func:`combine_estimates`: independent experiments, their information adds), and judged so.
- DETUMBLING: the kit's pulses on `fsw.deorbit.detumble.DetumbleLaw`. → STABILISING when |ω| stays
  ≤ `detumbled_radps` for `detumbled_hold_s`; SAFE on a spin-up or after `detumble_max_s`.
- STABILISING: the de-orbit controller (`fsw.deorbit.controller`) on the onboard attitude estimate
  (`fsw.deorbit.onboard_attitude`), both given the identified tensor. → STABILISED when the trusted
  estimate's yaw and pitch stay within `stabilised_rad` for `stabilised_hold_s`.
- STABILISED: the controller runs on.
- SAFE: the kit's safe mode (capsules closed), no pulses; left only by command (the kit must be able to
  leave its safe mode: every capsule confirmed closed).

Spin-up guard: while the kit detumbles, |ω| (smoothed over `spin_up_smoothing_s`: the estimate's own
noise is a few tenths of a °/s on a tumble) above `spin_up_factor` × its lowest value since the phase began
(and above that lowest value by `spin_up_margin_radps` plus `spin_up_sigmas` times the rate estimate's σ:
an estimate still settling after a restart, locked ~1 °/s low with a σ of 0.2 °/s, moves up by its own
error as it converges) sends the mission to SAFE: the kit never spins the tumble up for long. The kit
going to its own safe mode (a latched fault) sends the mission to SAFE with the kit's reason. After a
restart the mission starts again in TUMBLING; an identified tensor kept across the restart
(`fsw.persist`) that meets the accuracy is used without a new experiment.

Rates: `rates` is the flown rate filter (``omega_radps``, ``sigma_radps``, ``flags``), handed over by
`fsw.system.build_flight`. Time is the loop's `now_s`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import IntEnum
from types import SimpleNamespace
from typing import Callable

import numpy as np

from fsw.commands import BadParam, int_param
from fsw.estimation import inertia as inr
from fsw.ident import ABORTED, DONE, RUNNING
from fsw.telemetry.dialect import mavlink

from .controller import DiscreteController
from .detumble import DetumbleConfig, DetumbleLaw
from .kit import DeorbitKit
from .sequencer import KitMode, Outcome


class Phase(IntEnum):
    """DEBRIS_MISSION_PHASE."""

    TUMBLING = 0
    RATES_KNOWN = 1
    IDENTIFYING = 2
    DETUMBLING = 3
    STABILISING = 4
    STABILISED = 5
    SAFE = 6


class Reason(IntEnum):
    """DEBRIS_MISSION_REASON."""

    START = 0
    AUTOMATIC = 1
    COMMANDED = 2
    KIT_SAFE = 3
    SPIN_UP = 4
    TIMEOUT = 5
    IDENT_FAILED = 6


@dataclass(frozen=True)
class MissionConfig:
    rate_sigma_max_radps: float = math.radians(0.25)
    rates_hold_s: float = 120.0
    ident_free_s: float = 300.0
    ident_torque_s: float = 1500.0
    ident_after_s: float = 300.0
    # the tensor the controller is handed: 95 % half-widths within this fraction of the largest moment. The
    # fit's intervals are honest (the field model's and the calibration's errors marginalised, the robust
    # covariance) and on a 1,500-s experiment 2-5 %; the law and the controller held the sail with tensors
    # up to 5 % off
    ident_ci95_frac: float = 0.05
    ident_attempts: int = 2
    ident_retry_s: float = 10.0            # a refused start (no field on board yet) is tried again this often
    detumbled_radps: float = math.radians(0.15)
    detumbled_hold_s: float = 300.0
    detumble_max_s: float = 6 * 3600.0
    spin_up_factor: float = 1.3
    spin_up_margin_radps: float = math.radians(0.5)
    spin_up_sigmas: float = 3.0            # and beyond that margin by this many σ of the rate estimate
    spin_up_smoothing_s: float = 300.0     # the guard watches |ω| smoothed over this (the estimate's noise)
    #: while detumbling, the controller's attitude estimate (identified tensor, the kit's p × B in its
    #: dynamics) starts once the smoothed |ω| is below this, the kit's pulses held meanwhile (a slow body,
    #: and the estimate converges on it undisturbed); trusted for `detumbled_hold_s`, it hands over to
    #: STABILISING; not trusted `estimate_retry_s` after its start, it is dropped and the pulses resume for
    #: as long before the next start (the rate filter, which does not know the kit's torques, is a few
    #: tenths of a °/s off on a body the kit has nearly stopped)
    estimate_start_radps: float = math.radians(0.5)
    estimate_retry_s: float = 2400.0
    stabilised_rad: float = 0.2
    stabilised_hold_s: float = 1800.0
    status_period_s: float = 1.0


class KitMagnets:
    """The kit as the identification experiment's magnets (`fsw.ident.Magnets`): both capsules opened at
    the polarity the magnets are homed at, the dipole as the sequencer knows it."""

    def __init__(self, kit: DeorbitKit) -> None:
        self.kit = kit

    def open(self, now_s: float) -> bool:
        seq = self.kit.sequencer
        outs = [seq.request_capsule(i, True, now_s) for i in range(len(seq.channels))]
        return all(o.accepted for o in outs)

    def close(self, now_s: float) -> None:
        seq = self.kit.sequencer
        for i in range(len(seq.channels)):
            seq.request_capsule(i, False, now_s)

    def dipole_body_Am2(self) -> np.ndarray:
        return self.kit.known_dipole_body_Am2()


def over_kit(kit: DeorbitKit, ident, inertia_guess_kgm2, **options) -> "Mission":
    """The mission composed over the kit `kit` and the experiment `ident` (SITL's and the target's one
    composition): the experiment's magnets are the kit's (:class:`KitMagnets`), its fit starts from the box's
    rough guess `inertia_guess_kgm2` (3,) (the mean of its diagonal: a weak prior); `options`:
    :class:`Mission`'s keywords. The experiment's fit takes the body's drag from the spacecraft model of
    the kit's attitude estimate (its sail, its atmosphere). Its `rates` is the flown rate filter, handed
    over by `fsw.system.build_flight`."""
    guess = np.asarray(inertia_guess_kgm2, float)
    ident.magnets = KitMagnets(kit)
    ident.cfg.inertia_guess_kgm2 = float(np.mean(guess))
    model = getattr(kit.attitude, "model", None)   # the spacecraft the kit's attitude estimate knows
    if model is not None and ident.cfg.drag is None:
        ident.cfg.drag = model
    return Mission(kit, ident, inertia_guess_kgm2=tuple(float(x) for x in guess), **options)


def tensor_and_ci95(estimate) -> tuple[np.ndarray, np.ndarray]:
    """(Ixx, Iyy, Izz, Ixy, Ixz, Iyz) and their 95 % half-widths of a tensor estimate
    (`fsw.estimation.inertia.InertiaEstimate` or the fields of DEBRIS_INERTIA_ESTIMATE)."""
    if isinstance(estimate, dict):
        return np.asarray(estimate["inertia"], float), np.asarray(estimate["ci95"], float)
    return np.asarray(estimate.p, float), np.asarray(estimate.ci95, float)


def ci95_pct(estimate) -> float:
    """The worst 95 % half-width of a tensor estimate (as :func:`tensor_and_ci95` takes) in % of its
    largest moment."""
    p, ci = tensor_and_ci95(estimate)
    big = float(np.max(p[:3]))
    if not (big > 0 and np.all(np.isfinite(ci))) or not np.any(ci):
        return math.nan
    return 100.0 * float(np.max(ci)) / big


#: two attempts' tensors are combined only when they agree: χ² of their difference below its 99 % point
#: for 6 degrees of freedom
AGREE_CHI2 = 16.81


def combine_estimates(estimates: list) -> tuple[np.ndarray, np.ndarray, int]:
    """The tensor of the latest attempt combined with the earlier ones that agree with it: each attempt is
    an experiment of its own (its own samples, a weak prior), so their information adds — the
    covariance-weighted mean. An earlier attempt whose difference from the latest is not within
    `AGREE_CHI2` of their joint covariance is left out (something changed between them). Returns (p (6,),
    cov (6, 6), attempts used)."""
    p, cov = estimates[-1]
    info = np.linalg.pinv(cov)
    acc_info, acc = info.copy(), info @ p
    n = 1
    for q, c in estimates[:-1]:
        d = q - p
        if float(d @ np.linalg.pinv(cov + c) @ d) > AGREE_CHI2:
            continue
        ic = np.linalg.pinv(c)
        acc_info += ic
        acc += ic @ q
        n += 1
    if n == 1:
        return p, cov, 1
    cov_c = np.linalg.pinv(acc_info)
    return cov_c @ acc, cov_c, n


class Mission:
    """The mission's phases over the kit `kit` and the experiment `ident`; `inertia_guess_kgm2` the
    box's rough guess (3,) until the tensor is identified."""

    name = "mission"
    rate_hz = math.inf   # every sample (the detumbling law's field)
    budget = 0.1

    def __init__(self, kit: DeorbitKit, ident, *, inertia_guess_kgm2=(17.995, 20.711, 15.269),
                 config: MissionConfig = MissionConfig(), detumble: DetumbleConfig | None = None,
                 rates=None, on_phase: Callable[[float, Phase, Phase, str], None] | None = None) -> None:
        self.kit, self.ident, self.cfg, self.rates = kit, ident, config, rates
        self.law = DetumbleLaw(detumble or DetumbleConfig(), kit.magnets, np.diag(inertia_guess_kgm2))
        self.inertia_guess = np.asarray(inertia_guess_kgm2, float)
        self.J_kgm2: np.ndarray | None = None  # the identified tensor (3, 3)
        self.ci95_kgm2: np.ndarray | None = None  # its 95 % half-widths (Ixx, Iyy, Izz, Ixy, Ixz, Iyz)
        self.ci95_pct = math.nan
        self._estimates: list = []  # (p, cov) of each attempt's final fit
        self.on_phase = on_phase
        # the controller's attitude source waits for STABILISING (its filter needs the identified tensor):
        # taken off the kit at the first tick, after the flight software's composition gave it its field
        self._attitude_template = None
        # the detumbling's attitude estimate: started, trusted since, the sample it was last judged at,
        # the earliest next start
        self._estimate_t_s = self._estimate_since = self._estimate_seen_t_s = math.nan
        self._estimate_next_s = -math.inf
        self.phase = Phase.TUMBLING
        self.reason = Reason.START
        self.reason_text = "start"
        self.t_phase_s = math.nan
        self.energy_J = [0.0] * len(Phase)
        self._energy_mark = self._kit_energy()
        self.transitions: list[tuple[float, int, int, str]] = []
        self.attempts = 0
        self._held_since = math.nan
        self._min_rate = math.inf
        self._smooth_rate, self._smooth_t = math.nan, math.nan
        self._next_status_s = -math.inf
        self._texts: list[str] = []
        self._refused, self._next_start_s = "", -math.inf   # the last refusal of a start, said once
        self.omega_radps: np.ndarray | None = None
        self.rate_sigma_radps = math.nan

    # --- commands --------------------------------------------------------------------------------
    def register(self, router) -> None:
        router.register(mavlink.MAV_CMD_DEBRIS_MISSION_PHASE, self.cmd_phase, changes_state=True)
        router.register(mavlink.MAV_CMD_DEBRIS_MISSION_SAFE, self.cmd_safe, changes_state=True)

    def cmd_safe(self, msg, now_s: float) -> int:
        self._enter(now_s, Phase.SAFE, Reason.COMMANDED, "ground command")
        return mavlink.MAV_RESULT_ACCEPTED

    def cmd_phase(self, msg, now_s: float) -> int:
        """MAV_CMD_DEBRIS_MISSION_PHASE: param1 the phase (IDENTIFYING: via RATES_KNOWN, which homes the
        magnets first). FAILED: STABILISING/STABILISED without an identified tensor, or the kit refusing to
        leave its safe mode (a capsule not confirmed closed)."""
        try:
            phase = Phase(int_param(getattr(msg, "param1", math.nan), 0, len(Phase) - 1, "phase"))
        except BadParam:
            return mavlink.MAV_RESULT_DENIED
        if phase is Phase.SAFE:
            return self.cmd_safe(msg, now_s)
        if phase in (Phase.STABILISING, Phase.STABILISED) and self.J_kgm2 is None:
            return mavlink.MAV_RESULT_FAILED
        seq = self.kit.sequencer
        if seq.mode is KitMode.SAFE and not seq.leave_safe(now_s).accepted:
            return mavlink.MAV_RESULT_FAILED
        if phase is Phase.IDENTIFYING:
            phase = Phase.RATES_KNOWN
        self._enter(now_s, phase, Reason.COMMANDED, "ground command")
        return mavlink.MAV_RESULT_ACCEPTED

    # --- the loop ---------------------------------------------------------------------------------
    def tick(self, now_s: float, sample) -> None:
        if math.isnan(self.t_phase_s):
            self._attitude_template, self.kit.attitude = self.kit.attitude, None
            self._enter(now_s, Phase.TUMBLING, Reason.START, "start")
        if sample is not None:
            self.law.update_field(sample.t_s, sample.b_T)
        self._read_rates()
        if self.phase is not Phase.SAFE and self.kit.sequencer.mode is KitMode.SAFE:
            why = self.kit.sequencer.last_safe_reason or "kit safe mode"
            self._enter(now_s, Phase.SAFE, Reason.KIT_SAFE, why)
            return
        getattr(self, f"_in_{self.phase.name.lower()}")(now_s)

    def _read_rates(self) -> None:
        r = self.rates
        if r is None or r.flags & getattr(r, "NO_ESTIMATE", 0):
            self.omega_radps, self.rate_sigma_radps = None, math.nan
            return
        self.omega_radps = np.array(r.omega_radps, float)
        self.rate_sigma_radps = float(np.max(r.sigma_radps))
        self.law.update_rate(self.omega_radps, self.rate_sigma_radps)

    @property
    def rate_radps(self) -> float:
        return math.nan if self.omega_radps is None else float(np.linalg.norm(self.omega_radps))

    def _held(self, now_s: float, ok: bool, hold_s: float) -> bool:
        """True once `ok` has held for `hold_s` in a row."""
        if not ok:
            self._held_since = math.nan
            return False
        if math.isnan(self._held_since):
            self._held_since = now_s
        return now_s - self._held_since >= hold_s

    def _in_tumbling(self, now_s: float) -> None:
        ok = self.rate_sigma_radps <= self.cfg.rate_sigma_max_radps
        if self._held(now_s, ok, self.cfg.rates_hold_s):
            self._enter(now_s, Phase.RATES_KNOWN, Reason.AUTOMATIC,
                        f"rate sigma {math.degrees(self.rate_sigma_radps):.3f} dps")

    def _in_rates_known(self, now_s: float) -> None:
        restored = getattr(self.ident, "restored", None)
        if self.J_kgm2 is None and restored is not None and ci95_pct(restored) <= 100 * self.cfg.ident_ci95_frac:
            self._identified(restored)
            self._enter(now_s, Phase.DETUMBLING, Reason.AUTOMATIC, f"tensor kept, ci95 {self.ci95_pct:.1f} %")
            return
        seq = self.kit.sequencer
        homed = all(ch.stepper.polarity != 0 and not ch.busy and not ch.stepper.moving for ch in seq.channels)
        if not homed:
            for i, ch in enumerate(seq.channels):
                if ch.stepper.polarity == 0 and not ch.busy:
                    seq.request_home(i, now_s)
            return
        if now_s < self._next_start_s:
            return
        msg = SimpleNamespace(param1=mavlink.DEBRIS_TORQUE_SOURCE_MAGNETS, param2=self.cfg.ident_free_s,
                              param3=self.cfg.ident_torque_s, param4=self.cfg.ident_after_s, param5=0.0,
                              param6=0.0, param7=0.0)
        try:
            result = self.ident.cmd_start(msg, now_s)
        except BadParam as e:  # e.g. no field along the orbit on board: said once, tried again later
            self._next_start_s = now_s + self.cfg.ident_retry_s
            if str(e) != self._refused:
                self._refused = str(e)
                self._say(f"mission: identification refused: {e}")
            return
        self._refused = ""
        if result == mavlink.MAV_RESULT_ACCEPTED:
            self.attempts += 1
            self._enter(now_s, Phase.IDENTIFYING, Reason.AUTOMATIC, "magnets homed")

    def _in_identifying(self, now_s: float) -> None:
        if self.ident.state not in (DONE, ABORTED):
            return
        res = self.ident.result
        est = res.estimate if res is not None and res.final else None
        pct, how = math.nan, "tensor"
        if est is not None and np.all(np.isfinite(est.p)) and np.all(np.isfinite(est.cov)):
            self._estimates.append((np.asarray(est.p, float), np.asarray(est.cov, float)))
            p, cov, n = combine_estimates(self._estimates)
            if n > 1:  # the experiment's result from now on: what the ground is sent and a restart keeps
                est = inr.InertiaEstimate(p, cov, f"{est.method}, {n} attempts combined", est.samples_used,
                                          full=est.full, extra=dict(est.extra))
                self.ident.adopt(est)
                how = f"tensor of {n} attempts"
            pct = ci95_pct(est)
        if pct <= 100 * self.cfg.ident_ci95_frac:
            self._identified(est)
            self._enter(now_s, Phase.DETUMBLING, Reason.AUTOMATIC, f"{how} ci95 {pct:.1f} %")
        elif self.attempts < self.cfg.ident_attempts:
            self._say(f"mission: identification ci95 {pct:.1f} %, again")
            self._enter(now_s, Phase.RATES_KNOWN, Reason.IDENT_FAILED, f"ci95 {pct:.1f} %")
        else:
            self._enter(now_s, Phase.SAFE, Reason.IDENT_FAILED, f"identification ci95 {pct:.1f} %")

    def _identified(self, estimate) -> None:
        """The tensor of `estimate` (as :func:`tensor_and_ci95` takes) taken, with its intervals."""
        p6, self.ci95_kgm2 = tensor_and_ci95(estimate)
        self.J_kgm2 = inr.tensor(p6)
        self.ci95_pct = ci95_pct(estimate)
        self.law.J_kgm2 = self.J_kgm2  # the detumbling law predicts ω with it

    def _in_detumbling(self, now_s: float) -> None:
        c, w = self.cfg, self.rate_radps
        if now_s - self.t_phase_s > c.detumble_max_s:
            self._enter(now_s, Phase.SAFE, Reason.TIMEOUT, f"still {math.degrees(w):.2f} dps")
            return
        trusted = self.rate_sigma_radps <= self.law.config.max_rate_sigma_radps
        quiet = bool(self.law.quiet_reason)  # no pulse while the estimate converges: nothing to spin up
        if trusted:
            if math.isnan(self._smooth_rate):
                self._smooth_rate, self._smooth_t = w, now_s
            k = min(1.0, (now_s - self._smooth_t) / c.spin_up_smoothing_s)
            self._smooth_rate += k * (w - self._smooth_rate)
            self._smooth_t = now_s
            ws = self._smooth_rate
            self._min_rate = min(self._min_rate, ws)
            rise = c.spin_up_margin_radps + c.spin_up_sigmas * self.rate_sigma_radps  # beyond the estimate's own error
            if not quiet and ws > c.spin_up_factor * self._min_rate and ws > self._min_rate + rise:
                self._enter(now_s, Phase.SAFE, Reason.SPIN_UP,
                            f"rate {math.degrees(ws):.2f} dps up from {math.degrees(self._min_rate):.2f}")
                return
        if self._held(now_s, trusted and w <= c.detumbled_radps, c.detumbled_hold_s):
            self._enter(now_s, Phase.STABILISING, Reason.AUTOMATIC, f"rate {math.degrees(w):.3f} dps")
            return
        self._watch_estimate(now_s, trusted)

    def _watch_estimate(self, now_s: float, trusted: bool) -> None:
        """The controller's attitude estimate while the kit detumbles: started (again) on a slow enough
        tumble, and STABILISING once it has been trusted for `detumbled_hold_s`."""
        c, kit = self.cfg, self.kit
        est = kit.attitude
        if est is None:
            if (now_s >= self._estimate_next_s and trusted and self._smooth_rate <= c.estimate_start_radps
                    and self._attitude_template is not None):
                kit.attitude = self._estimate_for(self.J_kgm2)
                self._estimate_t_s, self._estimate_since = now_s, math.nan
                self.law.quiet_reason = "attitude estimate converging"
                self._say(f"mission: attitude estimate started at {math.degrees(self._smooth_rate):.2f} dps, "
                          "pulses held")
            return
        if self.law.t_b_s == self._estimate_seen_t_s:  # it changes with a sample only (a check is ~0.2 ms)
            return
        self._estimate_seen_t_s = self.law.t_b_s
        est.attitude(now_s)  # its trust, as the controller would see it
        if not est.trusted and now_s - self._estimate_t_s > c.estimate_retry_s:
            kit.attitude, self.law.quiet_reason = None, ""
            self._estimate_next_s = now_s + c.estimate_retry_s
            self._say(f"mission: attitude estimate not trusted after {c.estimate_retry_s:.0f} s "
                      f"({getattr(est, 'reason', '')}): dropped, pulses resume")
            return
        if not est.trusted:
            self._estimate_since = math.nan
        elif math.isnan(self._estimate_since):
            self._estimate_since = now_s
        elif now_s - self._estimate_since >= c.detumbled_hold_s:
            self._enter(now_s, Phase.STABILISING, Reason.AUTOMATIC,
                        f"attitude estimate trusted for {now_s - self._estimate_since:.0f} s")

    def _in_stabilising(self, now_s: float) -> None:
        att = self.kit.attitude
        rep = att.report() if att is not None and hasattr(att, "report") else None
        ok = (rep is not None and getattr(att, "trusted", True) and abs(rep.yaw_rad) <= self.cfg.stabilised_rad
              and abs(rep.pitch_rad) <= self.cfg.stabilised_rad)
        if self._held(now_s, bool(ok), self.cfg.stabilised_hold_s):
            self._enter(now_s, Phase.STABILISED, Reason.AUTOMATIC,
                        f"yaw {rep.yaw_rad:+.2f} pitch {rep.pitch_rad:+.2f} rad")

    def _in_stabilised(self, now_s: float) -> None:
        pass

    def _in_safe(self, now_s: float) -> None:
        pass

    # --- phase changes ------------------------------------------------------------------------------
    def _kit_energy(self) -> float:
        return float(self.kit.energy().total_J)

    def _enter(self, now_s: float, phase: Phase, reason: Reason, why: str) -> None:
        e = self._kit_energy()
        if not math.isnan(self.t_phase_s):
            self.energy_J[self.phase] += e - self._energy_mark
        self._energy_mark = e
        old = self.phase
        self._leave(now_s, old, phase)
        self.phase, self.reason, self.reason_text, self.t_phase_s = phase, reason, why, now_s
        self._held_since = math.nan
        self.transitions.append((now_s, int(old), int(phase), why))
        self._say(f"mission {phase.name}: {why}")
        self._start(now_s, phase)
        if self.on_phase is not None:
            self.on_phase(now_s, old, phase, why)

    def _leave(self, now_s: float, old: Phase, new: Phase) -> None:
        seq = self.kit.sequencer
        if old is Phase.IDENTIFYING and new is not Phase.IDENTIFYING and self.ident.state in RUNNING:
            self.ident.cmd_stop(None, now_s)
        if old is Phase.DETUMBLING:
            self.kit.law = None
        if new in (Phase.TUMBLING, Phase.RATES_KNOWN, Phase.IDENTIFYING) and seq.mode is KitMode.RUNNING:
            seq.stop_controller(now_s)
            self.kit.law = None

    def _start(self, now_s: float, phase: Phase) -> None:
        kit, seq = self.kit, self.kit.sequencer
        if phase is Phase.SAFE:
            kit.law = None
            if self.ident.state in RUNNING:
                self.ident.cmd_stop(None, now_s)
            seq.enter_safe(now_s, f"mission: {self.reason_text}")
        elif phase is Phase.DETUMBLING:
            self._min_rate, self._smooth_rate = math.inf, math.nan
            self._estimate_t_s = self._estimate_since = self._estimate_seen_t_s = math.nan
            self._estimate_next_s = -math.inf
            self.law.quiet_reason = ""
            kit.attitude = None
            kit.law = self.law
            if seq.mode is not KitMode.RUNNING:
                out = seq.start_controller(now_s)
                if out is not Outcome.STARTED:
                    self._say(f"mission: kit refused to run: {out.name}")
            kit.next_decision_s = now_s
        elif phase is Phase.STABILISING:
            self._hand_over(now_s)

    def _estimate_for(self, J):
        """A new attitude source like the kit's own (its template) with the tensor `J` (3, 3) in its model."""
        tpl = self._attitude_template
        if tpl is not None and hasattr(tpl, "model") and J is not None:
            return type(tpl)(tpl.sigma_b_T, replace(tpl.model, inertia_kgm2=tuple(map(tuple, J))),
                             tpl.tuning, tpl.gate, tpl.provider)
        return tpl

    def _hand_over(self, now_s: float) -> None:
        """The controller and its attitude filter get the identified tensor; the controller drives the kit."""
        kit, seq = self.kit, self.kit.sequencer
        kit.law = None
        J = self.J_kgm2 if self.J_kgm2 is not None else np.diag(self.inertia_guess)
        cfg = kit.controller.config
        kit.controller = DiscreteController(replace(cfg, inertia_kgm2=tuple(float(x) for x in np.diag(J))))
        if kit.attitude is None or not getattr(kit.attitude, "trusted", False):  # else the one that ran on
            kit.attitude = self._estimate_for(J)
        if seq.mode is not KitMode.RUNNING:
            seq.start_controller(now_s)
        kit.next_decision_s = now_s

    # --- telemetry ------------------------------------------------------------------------------------
    def _say(self, text: str) -> None:
        self._texts.append(text)
        del self._texts[:-16]

    def energy_by_phase(self) -> dict:
        """{phase name: J} including the running phase's energy so far."""
        e = list(self.energy_J)
        if not math.isnan(self.t_phase_s):
            e[self.phase] += self._kit_energy() - self._energy_mark
        return {p.name: round(e[p], 1) for p in Phase}

    def telemetry(self, now_s: float, tlm) -> None:
        while self._texts:
            text = self._texts.pop(0)
            sev = mavlink.MAV_SEVERITY_WARNING if "SAFE" in text or "refused" in text else mavlink.MAV_SEVERITY_INFO
            tlm.statustext(text, sev)
        if now_s >= self._next_status_s and not math.isnan(self.t_phase_s):
            self._next_status_s = max(self._next_status_s + self.cfg.status_period_s, now_s)
            J = self.J_kgm2 if self.J_kgm2 is not None else np.diag(self.inertia_guess)
            tlm.mission_status(now_s, int(self.phase), int(self.reason), now_s - self.t_phase_s, self.rate_radps,
                               self.rate_sigma_radps, self.ci95_pct, np.diag(J),
                               list(self.energy_by_phase().values()))
