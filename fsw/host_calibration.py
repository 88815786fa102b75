"""The flight loop's host-magnetics calibration step: every accepted sample goes through it before the
estimators and the applications.

It feeds the recursive TWOSTEP calibration (`fsw.estimation.magcal.MagCal`) with the sample and the
field's magnitude along the orbit from a :class:`FieldProvider`: the time-and-orbit application
(`fsw.timeorbit.TimeOrbit`: the field from the TLE and UTC on board, once both are there and usable) or
:class:`FixedField` (a field known for the whole run: SITL's scenario, a replay), at most one sample every
`sample_every_s` (`SAMPLE_EVERY_S`, 0.2 s: the magnitude changes over minutes, but the σ goals come with the number of
samples — on bench.calibration's 20 hosts with 1.5 µT of noise, within the orbit for 19 after a median
2,640 s at 5 Hz, for 16 after 4,729 s at 1 Hz; at 10 Hz the field model's error, which is not white,
begins to show: σ 25 % narrow, docs/calibration.md), and applies the last
good calibration to every sample: B = (I + D)(B_meas − b). Without a field on board the step is inactive
(DEBRIS_MAGCAL_STATE_NO_FIELD) and samples pass unchanged; a field that cannot be evaluated at a time
(an SGP4 error) is counted and that sample not taken. A calibration that failed its checks never
reaches the samples: the last good one stays applied and the state says REJECTED. DEBRIS_MAGCAL goes
out every `tlm_every_s`. A calibration restored after a restart (`restore`, from `fsw.persist`) is
applied from the first sample, with or without a field on board (the host's iron does not need one), and
judged by the new samples once there is one (`fsw.estimation.magcal.MagCal.restore`).
"""
from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from .estimation import field_motion as fm
from .estimation import magcal as mc
from .percentiles import percentile_pair
from .telemetry.telemetry import Telemetry


#: the calibration takes at most one sample every this many seconds (the module's docstring says why)
SAMPLE_EVERY_S = 0.2

#: the host's magnetism the flight software allows for before it has a calibration: hard iron up to 50 µT,
#: soft iron up to 10 % (scale and misalignment) — what a spacecraft's bus puts at a sensor on a short boom
HARD_IRON_MAX_T = 50e-6
SOFT_IRON_MAX = 0.10
#: the window of |B| the host's field is bounded from before a calibration, and how often it is looked at
SPREAD_SAMPLES, SPREAD_MIN_SAMPLES, SPREAD_EVERY = 256, 8, 4


def orbit_period_s(field) -> float | None:
    """The period of the orbit a field is along [s] (an SGP4 element set's mean motion, a circular orbit's
    altitude), None when it does not say: the hard iron's thermal drift is a cycle per orbit."""
    for obj in (field, getattr(field, "orbit_field", None)):
        orbit = getattr(obj, "orbit", obj)
        n_rad_per_min = getattr(getattr(orbit, "sat", None), "no_kozai", None)
        if n_rad_per_min:
            return 2.0 * math.pi * 60.0 / float(n_rad_per_min)
        alt = getattr(orbit, "altitude_m", None)
        if alt is not None:
            return 2.0 * math.pi * math.sqrt((fm.A_WGS84_M + alt) ** 3 / fm.MU_EARTH_M3S2)
    return None



class FieldProvider(Protocol):
    def field_now(self, now_s: float) -> tuple[object | None, str]:
        """(the field along the orbit, with ``b_eci_T(t_s)``, and ""), or (None, why there is none now)."""


class FixedField:
    """The field along the orbit known for the whole run (an `fsw.estimation.field_motion.OrbitField`)."""

    def __init__(self, field) -> None:
        self.field = field

    def field_now(self, now_s: float) -> tuple[object | None, str]:
        return self.field, ""


class HostCalibration:
    """`provider`: the field along the orbit (None: inactive); `sigma_T`: the sensor's noise per axis."""

    name = "calibration"

    def __init__(self, sigma_T: float, provider: FieldProvider | None = None, *, sample_every_s: float = SAMPLE_EVERY_S,
                 tlm_every_s: float = 10.0, **magcal_options) -> None:
        self.provider = provider
        #: the field along the orbit in use (None: none on board now) and why not
        self.field = None
        self._no_field = "no orbit/field model on board: calibration inactive"
        self.cal = mc.MagCal(sigma_T, **{"sigma_model_T": mc.MODEL_SIGMA_T, **magcal_options})
        self.sample_every_s = sample_every_s
        self.tlm_every_s = tlm_every_s
        self.field_errors = 0
        self.applied = 0  # samples the last good calibration was applied to
        self.skipped = 0  # samples not taken in: the kit's field unknown or unscreened (process's skip)
        self._t_taken: float | None = None
        #: a sample due to be taken in, held for `take_held` (process's `hold`): (t, b) or None
        self.held: tuple[float, np.ndarray] | None = None
        self._held_mag_T: float | None = None
        self._held_b_T = np.zeros(3)
        # |B| of the latest accepted samples (raw), for the host's field before a calibration
        self._mags = np.zeros(SPREAD_SAMPLES)
        self._n_mags = 0
        self._spread_T: float | None = None
        # what the applied calibration may have left in a sample (for_gate), and for which calibration
        self._left_for = -1
        self._left_T = self._left_per_T = 0.0
        self._t_tlm: float | None = None
        #: the steps a change of the calibration applied made in the corrected samples, summed [T] (body axes;
        #: each taken at the sample that made it, and counted from the first sample corrected after it): a
        #: filter that estimates what the calibration leaves in the samples moves its estimate by the
        #: difference of this sum between two of its samples instead of meeting the step as an error (a new
        #: array at each change, never changed in place)
        self.steps_T = np.zeros(3)
        self._step_pending_T: np.ndarray | None = None

    @property
    def state(self) -> int:
        return mc.NO_FIELD if self.field is None else self.cal.state

    @property
    def reason(self) -> str | None:
        if self.field is None:
            return self._no_field
        return self.cal.reason

    def for_gate(self, b_meas_T: np.ndarray) -> tuple[np.ndarray, float]:
        """(the sample as the sample gate should judge it, a bound on the host's field left in it [T]).
        With a calibration: the calibrated sample, and what the calibration may have left (3 σ of b and
        D, and `mc.MODEL_SIGMA_T`'s drift). Before one: the raw sample, and what the samples have shown —
        twice half the spread (2nd to 98th percentile) of |B| over the last `SPREAD_SAMPLES` accepted
        samples, as the host's field adds to or takes from the Earth's as the body turns — or, until there
        are enough of them, `HARD_IRON_MAX_T` + `SOFT_IRON_MAX` |B|."""
        m = float(np.linalg.norm(b_meas_T))
        if not self.cal.good:
            worst = HARD_IRON_MAX_T + SOFT_IRON_MAX * m
            return b_meas_T, (worst if self._spread_T is None
                              else min(worst, self._spread_T + 6.0 * self.cal.sigma_uT * 1e-6))
        if self._left_for != self.cal.published:  # 3 σ of b, of D per |B|: once per calibration
            sig = self.cal.calibration.sigma
            self._left_for = self.cal.published
            self._left_T = 3.0 * float(np.linalg.norm(sig[:3])) + 3.0 * mc.MODEL_SIGMA_T
            self._left_per_T = 3.0 * float(np.max(sig[3:]))
        return self.cal.apply(b_meas_T), self._left_T + self._left_per_T * m

    @property
    def version(self) -> int:
        """Changes whenever the calibration applied changes (the gate's reference must follow)."""
        return self.cal.published

    def _track_spread(self, b_meas_T: np.ndarray) -> None:
        self._mags[self._n_mags % SPREAD_SAMPLES] = math.sqrt(float(np.dot(b_meas_T, b_meas_T)))
        self._n_mags += 1
        if self._n_mags >= SPREAD_MIN_SAMPLES and self._n_mags % SPREAD_EVERY == 0:
            lo, hi = percentile_pair(self._mags[:min(self._n_mags, SPREAD_SAMPLES)], 2.0, 98.0)
            self._spread_T = hi - lo  # twice half the spread

    def process(self, t_s: float, b_meas_T: np.ndarray, extra_T: np.ndarray | None = None,
                skip: bool = False, hold: bool = False) -> np.ndarray:
        """The sample at `t_s` taken into the calibration (when due) and returned corrected. `extra_T`: a
        field at the sensor known on board, taken out first (the de-orbit kit's magnets,
        `fsw.deorbit.kit_field`); `skip`: that field is not known now (a shutter moves) or not well enough
        (a magnet is unscreened): the sample is not taken into the calibration (counted in `skipped`),
        only corrected. `hold`: a sample due is copied into `held` instead (the field along the orbit and
        the calibration's update, about 0.3 ms, left to :meth:`take_held` in a tick with room: the flight
        loop's choice)."""
        if self._step_pending_T is not None:  # a change made since the last sample: this one is corrected by it
            self.steps_T = self.steps_T + self._step_pending_T
            self._step_pending_T = None
        if extra_T is not None:
            b_meas_T = b_meas_T - extra_T
        if skip:
            self.skipped += 1
            return self.cal.apply(b_meas_T) if self.cal.good else b_meas_T
        self._track_spread(b_meas_T)
        if self.provider is None:
            return self.cal.apply(b_meas_T, t_s) if self.cal.good else b_meas_T  # restored: applied
        self.field, why = self.provider.field_now(t_s)
        if self.field is None:
            self._no_field = f"no orbit/field model on board ({why}): calibration inactive"
            return self.cal.apply(b_meas_T, t_s) if self.cal.good else b_meas_T  # restored: applied
        if self.cal.samples == 0 and self.cal.published == 0 and self.cal.drift_period_s is not None:
            # the drift's cycle is the orbit's: set before the first sample (the sums depend on it)
            self.cal.drift_period_s = orbit_period_s(self.field) or self.cal.drift_period_s
        if self._t_taken is None or t_s - self._t_taken >= self.sample_every_s * (1 - 1e-9):
            self._t_taken = t_s
            if hold:
                if self.held is not None:  # the one held before has waited its turn: taken in now
                    self.take_held()
                self._held_b_T[:] = b_meas_T
                self.held, self._held_mag_T = (t_s, self._held_b_T), None
            else:
                self._take(t_s, b_meas_T)
        if not self.cal.good:
            return b_meas_T
        self.applied += 1
        return self.cal.apply(b_meas_T, t_s)

    def take_held(self) -> None:
        """Take the held sample into the calibration (see :meth:`process`'s `hold`)."""
        while self.held is not None:
            self.take_step()

    def take_step(self) -> None:
        """The held sample's next step into the calibration, each about half of the work: |B| of the field
        along the orbit at its time, then the calibration's update."""
        if self.held is None:
            return
        t_s, b_meas_T = self.held
        if self._held_mag_T is None and self.field is not None:
            self._held_mag_T = self._model_mag_T(t_s)
            if self._held_mag_T is not None:
                return
        if self._held_mag_T is not None:
            self._update(t_s, b_meas_T, self._held_mag_T)
        self.held = self._held_mag_T = None

    def _update(self, t_s: float, b_meas_T: np.ndarray, mag_T: float) -> None:
        """The calibration's update with a sample; a change of the calibration applied adds the step it makes
        in that sample's correction to `steps_T`, from the next sample on (the first calibration's and a
        dropped one's too: what is applied before and after, none counted as the sample itself)."""
        c, published = self.cal, self.cal.published
        before = c.apply(b_meas_T, t_s) if c.good else b_meas_T  # none applied: the sample as it is
        c.update(b_meas_T, mag_T, t_s)
        if c.published != published:
            step = (c.apply(b_meas_T, t_s) if c.good else b_meas_T) - before
            if np.all(np.isfinite(step)):
                self._step_pending_T = step if self._step_pending_T is None else self._step_pending_T + step

    def _model_mag_T(self, t_s: float) -> float | None:
        """|B| of the field along the orbit at `t_s`; None (counted in `field_errors`) when it has none."""
        try:
            mag_T = float(np.linalg.norm(self.field.b_eci_T(t_s)))
        except (ValueError, ArithmeticError):
            self.field_errors += 1
            return None
        if math.isfinite(mag_T) and mag_T > 0:
            return mag_T
        self.field_errors += 1
        return None

    def _take(self, t_s: float, b_meas_T: np.ndarray) -> None:
        mag_T = self._model_mag_T(t_s)
        if mag_T is not None:
            self._update(t_s, b_meas_T, mag_T)

    def telemetry(self, now_s: float, tlm: Telemetry) -> None:
        """DEBRIS_MAGCAL every `tlm_every_s`."""
        if self._t_tlm is not None and now_s - self._t_tlm < self.tlm_every_s * (1 - 1e-9):
            return
        self._t_tlm = now_s
        c = self.cal
        tlm.magcal(now_s, c.calibration, state=self.state, samples=c.samples, dropped=c.dropped,
                   rejections=c.rejections, residual=c.chi2_dof, rate_T_per_s=c.rate_T_per_s,
                   drift_period_s=c.drift_period_s, restored=c.restored)

    # --- across a restart (`fsw.persist`) -------------------------------------------------------------
    def snapshot(self) -> dict | None:
        """The applied calibration to keep (`fsw.estimation.magcal.MagCal.snapshot`; None before one)."""
        return self.cal.snapshot()

    def restore(self, snap: dict, shift_s: float | None, t_s: float = 0.0, *, restart: bool = True) -> str:
        """A snapshot from before a restart applied from the next sample and flagged (DEBRIS_MAGCAL's
        `restored`), then judged by the new samples (`MagCal.restore`; ValueError if not one)."""
        period = snap.get("drift_period_s")
        if self.cal.drift_period_s is not None and isinstance(period, (int, float)) and period > 0:
            self.cal.drift_period_s = float(period)  # the drift's terms were solved on that period
        return self.cal.restore(snap, shift_s, t_s, restart=restart)
