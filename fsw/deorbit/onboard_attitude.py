"""The de-orbit controller's attitude from the box's own estimate (`fsw.estimation.orbital_attitude`), and
the gate that decides whether the controller may act on it.

:class:`EstimatedAttitude` is an `fsw.deorbit.kit.AttitudeSource`. The kit hands it every calibrated,
kit-compensated sample with the dipole its sequencer has unscreened (`observe`); it asks it for the
attitude at each controller decision (`attitude`). The field along the orbit comes from the flight
software's provider (`field_now`: the time-and-orbit application's, or a field fixed for the run) once the
host-magnetics calibration is applied to the samples (`fsw.estimation.flown_filter.CalibratedField`);
until then there is no estimate. A change of that calibration is a known step of what it leaves in the
samples (`HostCalibration.steps_T`): the filter's bias is moved by it before the next sample, not left to
take it as an error of the attitude.

Trust (:class:`TrustGate`). The controller gets an attitude only when the estimate has run at least
`min_run_s`, its pointing σ about body y and z and its rate σ are within their limits (`hysteresis` times
wider once trusted), its samples fit
(the running mean of the normalised innovation squared, 3 expected, below `max_nis_mean`) and the
hypotheses still running agree on where the sail normal points. Otherwise `attitude` returns None and
the kit holds both capsules closed for that period (`DeorbitKit.decisions_without_attitude`, reported in
DEBRIS_DEORBIT_ATTITUDE.held with the reason as STATUSTEXT): a pulse on a wrong attitude spins the
spacecraft up, a period waited costs a period.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fsw.estimation.orbital_attitude import (OrbitalAttitudeBank, OrbitalAttitudeTuning, OrbitInputs,
                                             SpacecraftModel, orbital_field_forecast)
from fsw.estimation.rotations import quat_to_dcm
from fsw.telemetry.dialect import mavlink

from .controller import AttitudeInput, euler_zyx


@dataclass(frozen=True)
class TrustGate:
    min_run_s: float = 900.0
    max_pointing_sigma_rad: float = 0.1
    max_rate_sigma_radps: float = math.radians(0.02)
    max_nis_mean: float = 9.0
    nis_window_samples: float = 60.0
    max_spread_rad: float = 0.2
    #: once trusted, the σ limits widen by this factor before trust is withdrawn (no flapping between
    #: acting and holding on an estimate whose σ breathes with the pulses)
    hysteresis: float = 2.0


@dataclass(frozen=True)
class AttitudeReport:
    """What DEBRIS_DEORBIT_ATTITUDE carries (SI; NaN where there is nothing)."""

    yaw_rad: float = math.nan
    pitch_rad: float = math.nan
    roll_rad: float = math.nan
    rate_radps: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    pointing_sigma_rad: tuple[float, float] = (math.nan, math.nan)
    rate_sigma_radps: float = math.nan
    source: int = mavlink.DEBRIS_CONTROLLER_ATTITUDE_NONE
    hypotheses: int = 0


def report_of(att: AttitudeInput | None, source: int, pointing_sigma=(0.0, 0.0), rate_sigma: float = 0.0,
              hypotheses: int = 0) -> AttitudeReport:
    if att is None:
        return AttitudeReport(source=source, hypotheses=hypotheses)
    yaw, pitch, roll = euler_zyx(att.R_bo)
    return AttitudeReport(yaw, pitch, roll, tuple(float(x) for x in att.omega_rel_radps),
                          tuple(float(x) for x in pointing_sigma), float(rate_sigma), source, hypotheses)


@dataclass
class EstimatedAttitude:
    """The onboard estimate as the controller's attitude source. `provider`: the field along the orbit
    (``field_now(now_s) -> (field | None, why)``; set by the flight software's composition)."""

    sigma_b_T: float
    model: SpacecraftModel = field(default_factory=SpacecraftModel)
    tuning: OrbitalAttitudeTuning = field(default_factory=OrbitalAttitudeTuning)
    gate: TrustGate = field(default_factory=TrustGate)
    provider: object = None
    description: str = ("onboard estimate (calibrated, kit-compensated magnetometer; field along the orbit on "
                        "board; gravity gradient, sail and the kit's p x B in the dynamics)")
    bank: OrbitalAttitudeBank | None = None
    reason: str = "no sample yet"
    trusted: bool = False
    nis_mean: float = 3.0
    _field: object = None
    _inputs: OrbitInputs | None = None
    _steps_seen_T: np.ndarray | None = None

    def observe(self, t_s: float, b_T: np.ndarray, dipole_body_Am2: np.ndarray,
                mean_dipole_body_Am2: np.ndarray | None = None, kit_step_cov_T2: np.ndarray | None = None) -> None:
        """A calibrated, kit-compensated sample, the kit's dipole acting from now on and, when known, its
        mean since the previous sample and the covariance of the step the kit-field model's error may have
        made since then."""
        fld, why = (None, "no orbit/field model on board") if self.provider is None else self.provider.field_now(t_s)
        if fld is None:
            self.reason = why or "no field along the orbit"
            return
        if fld is not self._field:  # a new field (a TLE, a calibration): the estimate starts again
            try:
                inputs = OrbitInputs(fld)
            except ValueError as e:
                self.reason = str(e)
                return
            self._field, self._inputs = fld, inputs
            self.bank = OrbitalAttitudeBank(self.sigma_b_T, inputs, self.model, self.tuning)
            self.nis_mean = 3.0
            self._steps_seen_T = None
        # the host calibration's changes since the last sample, a known step of what it leaves in the samples
        # (a new array at each change, never changed in place: the one seen is kept, not copied)
        steps = getattr(self.provider, "calibration_steps_T", None)
        if steps is not None and steps is not self._steps_seen_T:
            if self._steps_seen_T is not None:
                self.bank.shift_bias(steps - self._steps_seen_T)
            self._steps_seen_T = steps
        try:
            self.bank.update(t_s, b_T, dipole_body_Am2, mean_dipole_body_Am2, kit_step_cov_T2)
        except ValueError as e:  # the orbit cannot be evaluated (SGP4): no estimate from this sample
            self.reason = str(e)
            return
        best = self.bank.best
        if best is not None and self.bank.samples > 1:
            k = 1.0 / self.gate.nis_window_samples
            self.nis_mean += k * (best.nis - self.nis_mean)

    def _check(self, now_s: float, est) -> str:
        g, bank = self.gate, self.bank
        if now_s - bank.t_start_s < g.min_run_s:
            return f"estimate running {now_s - bank.t_start_s:.0f} s of {g.min_run_s:.0f} s"
        _, _, sp, sw, _ = est
        k = g.hysteresis if self.trusted else 1.0
        if max(sp) > k * g.max_pointing_sigma_rad:
            return f"pointing sigma {max(sp):.3f} rad > {k * g.max_pointing_sigma_rad:g}"
        if float(np.max(sw)) > k * g.max_rate_sigma_radps:
            return (f"rate sigma {math.degrees(float(np.max(sw))):.4f} deg/s > "
                    f"{math.degrees(k * g.max_rate_sigma_radps):g}")
        if self.nis_mean > g.max_nis_mean:
            return f"samples do not fit (mean NIS {self.nis_mean:.1f} > {g.max_nis_mean:g})"
        spread = bank.spread_rad()
        if spread > g.max_spread_rad:
            return f"{len(bank.members)} hypotheses disagree by {spread:.2f} rad"
        return ""

    def attitude(self, now_s: float) -> AttitudeInput | None:
        """The attitude at `now_s` for a decision, or None (reason in `reason`) when it is not trusted."""
        bank = self.bank
        if bank is None or not bank.started:
            self.trusted = False
            return None
        gap_s = now_s - bank.t_s
        if gap_s > bank.tuning.max_gap_s:
            # no sample taken in for longer than the bank bridges (a stale TLE, a dead sensor): not carried
            # across the gap (a step every 2 s: a day of it is ~0.8 s of work), started again by the next
            self.trusted, self.reason = False, f"no sample for {gap_s:.0f} s"
            return None
        try:
            est = bank.orbital(now_s)
            why = self._check(now_s, est)
            b_eci = None if why else np.asarray(self._field.b_eci_T(now_s), float)
        except ValueError as e:  # the orbit cannot be evaluated now (SGP4): no attitude for this decision
            why = str(e)
        if why:
            self.trusted, self.reason = False, why
            return None
        self.trusted, self.reason = True, ""
        R_bo, w_rel, _, _, q = est
        return AttitudeInput(R_bo, w_rel, quat_to_dcm(q).T @ b_eci, orbital_field_forecast(self._inputs))

    def report(self) -> AttitudeReport:
        """The estimate at its latest sample, for telemetry (no propagation)."""
        if self.bank is None or not self.bank.started:
            return AttitudeReport()
        R_bo, w_rel, sp, sw, _ = self.bank.orbital(self.bank.t_s)
        src = (mavlink.DEBRIS_CONTROLLER_ATTITUDE_TRUSTED if self.trusted
               else mavlink.DEBRIS_CONTROLLER_ATTITUDE_UNTRUSTED)
        return report_of(AttitudeInput(R_bo, w_rel, np.zeros(3)), src, sp, float(np.max(sw)), len(self.bank.members))
