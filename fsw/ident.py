"""The onboard inertia identification experiment (sedelnikov2023's algorithm, run by the box).

Sequence, started by MAV_CMD_DEBRIS_IDENT_START (54000) and stopped by MAV_CMD_DEBRIS_IDENT_STOP (54001):

    OBSERVE_FREE (param2 s) → TORQUE (param3 s) → OBSERVE_AFTER (param4 s) → DONE   (or ABORTED)

- the known torque comes from a tug (DEBRIS_TORQUE_SOURCE_TUG: a force F at a known point r, sent as
  the moment M = r × F in body axes, params 5–7) or from the box's own magnets
  (DEBRIS_TORQUE_SOURCE_MAGNETS: their capsules open, M = p × B with p the dipole they report);
- every magnetometer sample of the experiment is kept (and goes to the ground with the usual
  telemetry); while the experiment runs, the output-error fit of :mod:`fsw.estimation.euler_fit` is
  re-run on the samples so far (a running estimate with its 95 % / 99 % intervals, sent as
  DEBRIS_INERTIA_ESTIMATE), and once more on all of them at the end (the final estimate, state DONE);
- the fit is a generator advanced a bounded amount of work per loop tick (``work_per_tick``), so it
  never holds the loop; the ground repeats it on the decoded recording (``python -m ground.inertia``).

Handlers follow `fsw.commands`: ``(msg, now_s) -> MAV_RESULT``; an out-of-range parameter raises
`BadParam` (→ DENIED); a second start while one runs → TEMPORARILY_REJECTED. Time is the loop's
``now_s``, never the wall clock. The flight software must not import the simulator: the field model
along the orbit and the actuators come in as callables. The field may also come from a provider with
``field_now(now_s) -> (field or None, why)`` (on target: `fsw.timeorbit.TimeOrbit`, the TLE and UTC on
board); the field in force at the start is the one the experiment's fits use.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from .commands import BadParam, float_param, int_param
from .estimation import euler_fit as ef
from .estimation.euler_fit import field_error
from .estimation.orbital_attitude import SpacecraftModel, orbit_position_fn
from .estimation import inertia as inr
from .telemetry.dialect import mavlink

FieldFn = ef.FieldFn

IDLE = mavlink.DEBRIS_IDENT_STATE_IDLE
OBSERVE_FREE = mavlink.DEBRIS_IDENT_STATE_OBSERVE_FREE
TORQUE = mavlink.DEBRIS_IDENT_STATE_TORQUE
OBSERVE_AFTER = mavlink.DEBRIS_IDENT_STATE_OBSERVE_AFTER
DONE = mavlink.DEBRIS_IDENT_STATE_DONE
ABORTED = mavlink.DEBRIS_IDENT_STATE_ABORTED
RUNNING = (OBSERVE_FREE, TORQUE, OBSERVE_AFTER)
STATE_NAMES = {IDLE: "idle", OBSERVE_FREE: "observe free", TORQUE: "torque", OBSERVE_AFTER: "observe after",
               DONE: "done", ABORTED: "aborted"}

TUG = mavlink.DEBRIS_TORQUE_SOURCE_TUG
MAGNETS = mavlink.DEBRIS_TORQUE_SOURCE_MAGNETS


class Tug(Protocol):
    """The tug's side of a TUG experiment: the known moment M = r × F (body axes, about the centre of
    mass) over [start, start + duration), or stopped early."""

    def apply(self, start_s: float, duration_s: float, moment_Nm: np.ndarray) -> None: ...

    def stop(self, now_s: float) -> None: ...


class FieldProvider(Protocol):
    """Where the field along the orbit comes from when it may be missing or stale (`fsw.timeorbit`)."""

    def field_now(self, now_s: float) -> tuple[FieldFn | None, str]: ...   # (field, "") or (None, why)


class AnnouncedTug:
    """A tug commanded on its own (by the ground or the tug's operator), not by the box: the START
    command announces the moment it will apply and when; the box records it and acts on nothing."""

    def __init__(self) -> None:
        self.announced: list[tuple[float, float, np.ndarray]] = []

    def apply(self, start_s: float, duration_s: float, moment_Nm: np.ndarray) -> None:
        self.announced.append((float(start_s), float(duration_s), np.array(moment_Nm, float)))

    def stop(self, now_s: float) -> None:
        pass


class Magnets(Protocol):
    """The box's magnets for a MAGNETS experiment (the de-orbit kit behind an adapter)."""

    def open(self, now_s: float) -> bool: ...          # unscreen; False if refused (busy, fault, safe mode)

    def close(self, now_s: float) -> None: ...

    def dipole_body_Am2(self) -> np.ndarray: ...       # the dipole acting now (zeros while screened)


@dataclass
class IdentConfig:
    """Limits and settings of the experiment (SI)."""

    max_duration_s: float = 4 * 3600.0       # free + torque + after
    max_moment_Nm: float = 50.0              # |M| accepted from the ground (TUG)
    min_torque_s: float = 1.0
    inertia_guess_kgm2: float = 100.0        # starting tensor: this times the identity; the fit's weak prior
    update_every_s: float = 120.0            # a new running estimate at most this often (loop time)
    work_per_tick: int = 15000               # fit work per tick (euler_fit.evaluate_steps units, ~3 ms)
    tlm_period_s: float = 5.0                # DEBRIS_INERTIA_ESTIMATE period while not idle
    max_samples: int = 20000                 # the record kept: past it, every other sample (again as needed)
    fit: ef.FitOptions = field(default_factory=ef.FitOptions)
    # with the kit's magnets as the torque: prior 1-σ of the offset their compensation may leave while they
    # are open, fitted (`FitOptions.kit_offset_sigma_T`); None: the compensation taken as exact
    kit_offset_sigma_T: float | None = 10e-6
    # the host's hard iron drifting from its calibration over the experiment, fitted (`FitOptions.drift_degree`:
    # `field_error.degree_for` the record's length; prior 1-σ `drift_rate_T_per_s` × its length, at most
    # `drift_max_T`: a thermal cycle of ~2 µT over an orbit changes by at most ~2.2 nT/s); False: constant
    drift: bool = True
    drift_rate_T_per_s: float = 2.2e-9
    drift_max_T: float = 2e-6
    # the gravity gradient in the fit's model when the field along the orbit says where the orbit is
    # (`euler_fit.KnownAction.with_orbit`): on a body of ~20 kg·m² with moments ~10 kg·m² apart it is a few %
    # of the kit's magnets' moment, and the fit left without it puts ~1 % of scale into the tensor
    gravity_gradient: bool = True
    # with it, the box's model of the spacecraft (`orbital_attitude.SpacecraftModel`, e.g. the kit's
    # attitude estimate's): its aerodynamic moment in the fit's model too (None: left out)
    drag: SpacecraftModel | None = None
    # the field model's error along the record fitted and marginalised, as the ground's fit does
    # (`FitOptions.field_error_degree`, `field_error.degree_for` the record's length), with the soft iron's
    # error the host's calibration leaves (1-σ per element: it stated 0.2 % at convergence; on the mission's
    # host it left up to ~0.85 %); and with it the robust covariance (`field_error.robust_cov`). False: the
    # field model taken as exact, the curvature's covariance
    field_error: bool = True
    soft_iron_sigma: float = 0.005
    # the profile of the cost along the tensor's scale (`FitOptions.scale_profile`): Ixx held at the fit's
    # times each of these; the tensor's interval along its scale is the profile's where that is wider
    scale_profile: tuple = (0.98, 1.02, 0.96, 1.04)

    def fit_options(self, span_s: float, source: int) -> ef.FitOptions:
        """`fit` with the terms above for a record of `span_s` seconds of a `source` experiment."""
        opts = self.fit
        if source == MAGNETS and opts.kit_offset_sigma_T is None:
            opts = dataclasses.replace(opts, kit_offset_sigma_T=self.kit_offset_sigma_T)
        if self.drift and opts.drift_degree is None:
            opts = dataclasses.replace(opts, drift_degree=field_error.degree_for(span_s),
                                       drift_sigma_T=min(self.drift_max_T, self.drift_rate_T_per_s * span_s))
        if self.scale_profile and not opts.scale_profile:
            opts = dataclasses.replace(opts, scale_profile=tuple(self.scale_profile))
        if self.field_error and opts.field_error_degree is None:
            opts = dataclasses.replace(opts, field_error_degree=field_error.degree_for(span_s),
                                       soft_iron_sigma=self.soft_iron_sigma, robust_cov=True)
        return opts


@dataclass
class IdentResult:
    """A finished fit of the samples so far."""

    estimate: inr.InertiaEstimate
    fit: ef.FitResult
    t_s: float            # loop time it finished
    t_data_end_s: float   # time of the last sample it used
    final: bool


class IdentExperiment:
    """The experiment's state machine, its samples, and the fit jobs that run on them; an onboard
    application (`fsw.app.App`): every tick, with the sample of that tick."""

    name = "ident"
    rate_hz = math.inf  # every tick: it keeps every sample
    budget = 0.3

    def __init__(self, *, sigma_b_T: float, b_inertial: FieldFn | FieldProvider | None, tug: Tug | None = None,
                 magnets: Magnets | None = None, config: IdentConfig | None = None) -> None:
        self.sigma_b_T = float(sigma_b_T)
        self.b_inertial = b_inertial
        self._b_fit: FieldFn | None = None   # the field of the experiment in progress
        self.tug = tug
        self.magnets = magnets
        self.cfg = config or IdentConfig()
        self.state = IDLE
        self.source = 0
        self.moment_Nm = np.zeros(3)
        self.t_start_s = self.t_torque_s = self.t_after_s = self.t_end_s = math.nan
        self.t: list[float] = []
        self.b: list[np.ndarray] = []
        self._offered, self.thinned = 0, 0
        self.dipoles: list[tuple[float, np.ndarray]] = []   # (time, dipole) whenever it changed (MAGNETS)
        self.result: IdentResult | None = None
        self.history: list[IdentResult] = []
        #: the estimate restored after a restart (`restore`), sent until a new experiment's
        self.restored: dict | None = None
        self.jobs_started = 0
        self.last_error = ""
        self._job = None
        self._job_meta: tuple[int, float, bool] | None = None
        self._last_job_s = -math.inf
        self._torque_stop_s = math.nan
        self._state_changed = False
        self._next_tlm_s = -math.inf

    # --- commands ------------------------------------------------------------------------------
    def register(self, router) -> None:
        """Register the START/STOP handlers with a `fsw.commands.CommandRouter`."""
        router.register(mavlink.MAV_CMD_DEBRIS_IDENT_START, self.cmd_start, changes_state=True,
                        long_only=True)  # params 5-6: moments, fractional
        router.register(mavlink.MAV_CMD_DEBRIS_IDENT_STOP, self.cmd_stop, changes_state=True)

    def cmd_start(self, msg, now_s: float) -> int:
        """MAV_CMD_DEBRIS_IDENT_START: param1 source, param2–4 durations [s], param5–7 moment [N·m] (TUG)."""
        source = int_param(msg.param1, TUG, MAGNETS, "source")
        cap = self.cfg.max_duration_s
        free = float_param(msg.param2, 0.0, cap, "observe free s")
        torque = float_param(msg.param3, self.cfg.min_torque_s, cap, "torque s")
        after = float_param(msg.param4, 0.0, cap, "observe after s")
        if free + torque + after > cap:
            raise BadParam(f"experiment of {free + torque + after:g} s longer than {cap:g} s")
        moment = np.zeros(3)
        if source == TUG:
            lim = self.cfg.max_moment_Nm
            moment = np.array([float_param(getattr(msg, f"param{i}"), -lim, lim, f"M{a}")
                               for i, a in zip((5, 6, 7), "xyz")])
            if not np.any(moment):
                raise BadParam("TUG experiment with a zero moment")
            if self.tug is None:
                raise BadParam("no tug interface on board")
        elif self.magnets is None:
            raise BadParam("MAGNETS source: no magnets interface on board")
        b_fit, why = self._field_now(now_s)
        if b_fit is None:
            raise BadParam(f"no orbit/field model on board: {why}")
        if self.state in RUNNING:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        self._reset()
        self._b_fit = b_fit
        self.source, self.moment_Nm = source, moment
        self.t_start_s = now_s
        self._last_job_s = now_s          # the first running estimate comes update_every_s later at most
        self.t_torque_s = now_s + free
        self.t_after_s = self.t_torque_s + torque
        self.t_end_s = self.t_after_s + after
        self._set_state(OBSERVE_FREE)
        return mavlink.MAV_RESULT_ACCEPTED

    def cmd_stop(self, msg, now_s: float) -> int:
        """MAV_CMD_DEBRIS_IDENT_STOP: abort a running experiment (the torque is released at once)."""
        if self.state in RUNNING:
            self._release(now_s)
            self._job = None
            self._set_state(ABORTED)
        return mavlink.MAV_RESULT_ACCEPTED

    def _field_now(self, now_s: float) -> tuple[FieldFn | None, str]:
        provider = getattr(self.b_inertial, "field_now", None)
        if provider is not None:
            return provider(now_s)
        return self.b_inertial, "the fit needs B along the orbit"

    # --- loop ------------------------------------------------------------------------------------
    def tick(self, now_s: float, sample) -> None:
        """The application's task: the sample of this tick, then the phases and a slice of the fit."""
        if sample is not None:
            self.on_sample(sample.t_s, sample.b_T)
        self.step(now_s)

    def telemetry(self, now_s: float, tlm) -> None:
        """DEBRIS_INERTIA_ESTIMATE when one is due (`telemetry_due`)."""
        if self.telemetry_due(now_s):
            tlm.inertia_estimate(now_s, **self.message_fields())

    def on_sample(self, t_s: float, b_T: np.ndarray) -> None:
        """A magnetometer sample (the flight loop's latched, gated sample). The record spans the whole
        experiment: when it reaches `max_samples` it keeps every other sample, and every other one from then
        on (`thinned` times: a 4 h experiment at 10 Hz is kept at 1.25 Hz, not cut after 33 min)."""
        if self.state in RUNNING and t_s <= self.t_end_s and (not self.t or t_s > self.t[-1]):
            self._offered += 1
            if (self._offered - 1) % (1 << self.thinned):
                return
            self.t.append(float(t_s))
            self.b.append(np.array(b_T, float))
            if len(self.t) >= self.cfg.max_samples:
                del self.t[1::2], self.b[1::2]
                self.thinned += 1

    def step(self, now_s: float) -> None:
        """Advance the phases and a slice of the fit (called every loop tick)."""
        if self.state == OBSERVE_FREE and now_s >= self.t_torque_s:
            self._apply(now_s)
            self._set_state(TORQUE)
        if self.state == TORQUE:
            if self.source == MAGNETS:
                self._note_dipole(now_s)
            if now_s >= self.t_after_s:
                self._release(now_s)
                self._set_state(OBSERVE_AFTER)
        self._fit_work(now_s)

    # --- actuators ---------------------------------------------------------------------------------
    def _apply(self, now_s: float) -> None:
        self.t_torque_s = now_s                    # the action starts at this tick
        if self.source == TUG:
            self.tug.apply(now_s, self.t_after_s - now_s, self.moment_Nm.copy())
        elif not self.magnets.open(now_s):
            self.last_error = "magnets refused to open"
            self._set_state(ABORTED)
            return
        self._note_dipole(now_s)

    def _release(self, now_s: float) -> None:
        if self.state != TORQUE:
            return
        self._torque_stop_s = min(now_s, self.t_after_s)
        if self.source == TUG:
            if now_s < self.t_after_s:
                self.tug.stop(now_s)
        else:
            self.magnets.close(now_s)
            self.dipoles.append((now_s, np.zeros(3)))

    def _note_dipole(self, now_s: float) -> None:
        p = np.array(self.magnets.dipole_body_Am2(), float) if self.magnets is not None else np.zeros(3)
        if not self.dipoles or np.any(self.dipoles[-1][1] != p):
            self.dipoles.append((now_s, p))

    def known_action(self) -> ef.KnownAction:
        """The known action of the experiment so far (moment pulse, or the magnets' dipole timeline)."""
        if self.source == TUG:
            end = self._torque_stop_s if math.isfinite(self._torque_stop_s) else self.t_after_s
            if self.state == OBSERVE_FREE or end <= self.t_torque_s:
                return ef.KnownAction.none()
            return ef.KnownAction.pulses([(self.t_torque_s, end - self.t_torque_s, self.moment_Nm)])
        if not self.dipoles:
            return ef.KnownAction.none()
        t = np.array([d[0] for d in self.dipoles])
        p = np.array([d[1] for d in self.dipoles])
        return ef.KnownAction(t, np.zeros_like(p), p)

    def _orbit_of(self, field) -> ef.PositionFn | None:
        """Where the body is along the orbit its fit's field is computed on (None: not known, or not wanted)."""
        if not self.cfg.gravity_gradient:
            return None
        try:
            return orbit_position_fn(field)
        except ValueError:
            return None

    # --- the fit ---------------------------------------------------------------------------------------
    def _fit_work(self, now_s: float) -> None:
        if self._job is None:
            self._maybe_start_job(now_s)
            return
        try:
            next(self._job)
        except StopIteration as stop:
            n, t_end, final = self._job_meta
            self._job = None
            fr = stop.value[0]
            est = fr.estimate("output-error fit onboard" + (" (final)" if final else ""))
            self.result = IdentResult(est, fr, now_s, t_end, final)
            self.history.append(self.result)
            if final:
                self._set_state(DONE)
            self._state_changed = True
        except (ValueError, np.linalg.LinAlgError) as e:   # a degenerate record: reported, never raised
            self._job = None
            self.last_error = f"fit failed: {e}"
            if self.state == OBSERVE_AFTER and now_s >= self.t_end_s:
                self._set_state(DONE)

    def _maybe_start_job(self, now_s: float) -> None:
        if self.state not in (TORQUE, OBSERVE_AFTER) or len(self.t) < 20:
            return
        final = self.state == OBSERVE_AFTER and now_s >= self.t_end_s
        if not final and now_s - self._last_job_s < self.cfg.update_every_s:
            return
        if not final and now_s < self.t_torque_s + min(60.0, self.t_after_s - self.t_torque_s):
            return
        t = np.array(self.t)
        b = np.array(self.b)
        g = self.cfg.inertia_guess_kgm2
        b_fit = self._b_fit if self._b_fit is not None else self.b_inertial
        opts = self.cfg.fit_options(float(t[-1] - t[0]), self.source)
        action = self.known_action().with_orbit(self._orbit_of(b_fit), self.cfg.drag)
        self._job = ef.identify_steps(t, b[None], b_fit, action, self.sigma_b_T,
                                      np.array([g, g, g, 0.0, 0.0, 0.0]), opts, chunk=self.cfg.work_per_tick)
        self._job_meta = (len(t), float(t[-1]), final)
        self._last_job_s = now_s
        self.jobs_started += 1

    # --- state and telemetry ------------------------------------------------------------------------
    def _reset(self) -> None:
        self.t, self.b, self.dipoles = [], [], []
        self._offered, self.thinned = 0, 0     # samples offered to the record; times it kept every other one
        self.result = None
        self.restored = None
        self.history = []
        self._job = None
        self._last_job_s = -math.inf
        self._torque_stop_s = math.nan
        self.last_error = ""

    def _set_state(self, state: int) -> None:
        if state != self.state:
            self.state = state
            self._state_changed = True

    @property
    def busy(self) -> bool:
        return self._job is not None

    def telemetry_due(self, now_s: float) -> bool:
        """True when a DEBRIS_INERTIA_ESTIMATE should go out: a state change, a new estimate, or the period."""
        if self.state == IDLE and not self._state_changed:
            return False
        if self._state_changed or now_s >= self._next_tlm_s:
            self._state_changed = False
            self._next_tlm_s = now_s + self.cfg.tlm_period_s
            return True
        return False

    def adopt(self, estimate: inr.InertiaEstimate) -> None:
        """An estimate of the same tensor from this experiment and earlier ones (the mission's attempts
        combined, `fsw.deorbit.mission.combine_estimates`) becomes the result: sent at once in
        DEBRIS_INERTIA_ESTIMATE and kept across a restart, as the experiment's own final fit would be."""
        r = self.result
        if r is None or not r.final:
            raise ValueError("only a finished experiment's result can be replaced by a combined one")
        self.result = dataclasses.replace(r, estimate=estimate)
        self.history.append(self.result)
        self._state_changed = True

    # --- across a restart (`fsw.persist`) ---------------------------------------------------------
    def snapshot(self) -> dict | None:
        """The latest estimate to keep (None before one): DEBRIS_INERTIA_ESTIMATE's fields, its covariance."""
        if self.result is None:
            return self.restored
        return {**self.message_fields(), "cov": [[float(x) for x in row] for row in self.result.estimate.cov]}

    def restore(self, snap: dict) -> None:
        """The estimate from before a restart, sent again (DEBRIS_INERTIA_ESTIMATE at the next telemetry and
        every period after) until a new experiment starts; an experiment the restart cut short is ABORTED.
        ValueError when `snap` is not one."""
        fields = {k: [float(x) for x in snap[k]] for k in ("inertia", "ci95", "ci99")}
        cov = [[float(x) for x in row] for row in snap["cov"]]
        if any(len(v) != 6 or not all(map(math.isfinite, v)) for v in fields.values()) or len(cov) != 6 \
                or any(len(row) != 6 for row in cov):
            raise ValueError("inertia estimate fields of the wrong shape or not finite")
        state = int(snap["state"])
        self.restored = {**fields, "samples": int(snap["samples"]), "flags": int(snap["flags"]), "cov": cov,
                         "state": DONE if state in (DONE, IDLE) else ABORTED}
        self._set_state(self.restored["state"])

    def message_fields(self) -> dict:
        """The fields of DEBRIS_INERTIA_ESTIMATE for the current estimate (zeros before the first; the one
        restored after a restart until a new one)."""
        r = self.result
        if r is None and self.restored is not None:
            return {k: v for k, v in self.restored.items() if k != "cov"} | {"state": self.state}
        if r is None:
            z = [0.0] * 6
            return {"samples": 0, "inertia": z, "ci95": z, "ci99": z, "state": self.state, "flags": 0}
        e = r.estimate
        return {"samples": int(e.samples_used), "inertia": [float(x) for x in e.p],
                "ci95": [float(x) for x in e.ci95], "ci99": [float(x) for x in e.ci99],
                "state": self.state, "flags": int(e.flags)}
