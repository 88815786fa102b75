"""The rate filter the box flies (DEBRIS_RATE_METHOD_KALMAN), chosen in the run's configuration, and its
hand-over from the fixed-field filter to the filter with the field along the orbit.

Filters (`RunConfig.rate_filter`, ``--rate-filter``), the accuracy benchmark's onboard methods
(docs/rate-estimation.md):

- ``fixed`` — :class:`~.rate_kalman.RateKalman`: the field assumed fixed in inertial space; needs no
  orbit, but leaves the component of ω along B poorly observed (~3.5 °/s RMS error on a fast tumble);
- ``orbit`` — :class:`~.attitude_kalman.AttitudeRateKalman` with the field along the orbit, ω a random
  walk (the benchmark's ``kalman_orbit``);
- ``euler`` (default) — :class:`~.filter_banks.EulerAcquisitionKalman`: that plus Euler's equations with
  the inertia shape acquired by parallel hypotheses: the best onboard method of every tumbling row of
  the accuracy table (undirected and −Ḃ, 0.05–0.25 of Boer ⊥);
- ``mm`` — :class:`~.filter_banks.RateModelBank`: random-walk and Gauss–Markov rates side by side, the
  best onboard method of the orbital-orientation rows (a slow libration about a held attitude).

The orbit filters need the field along the orbit and samples that are the Earth's field: a provider
(`field_now(now_s)` → (field with ``b_eci_T``, "") or (None, why)); on board :class:`CalibratedField`:
the time-and-orbit application's field once the box has a UTC and a usable TLE (or a field known for
the whole run), and the host-magnetics calibration applied to the samples. Until then, and whenever the
field goes away again (a stale TLE), the fixed-field filter publishes and :attr:`FlownFilter.why` says
why. The fixed-field filter runs on every sample (it is cheap, compiled), so that a fall-back has an
estimate at once. When the field arrives the orbit filter starts from the fixed filter's ω and its
covariance before that sample (:meth:`FlownFilter.seed`; on board the sample that brings the field is
the host calibration's first corrected one, a step the fixed filter takes as a rotation), so the
published rate does not jump; the attitude about B, which
the fixed filter does not know, starts wide. A new TLE or UTC (a new field object) is taken at the next
sample without a restart. The attitude (:meth:`FlownFilter.attitude`) carries the field along the orbit
onto the measured one; its angle about the field shows only as the field turns along the orbit: its σ
there is held wide until the field has turned (`AttitudeKalmanTuning.about_b_turn_rad`,
:func:`~.attitude_kalman.attitude_cov`), and the Euler filter runs hypotheses over that angle whose
spread widens it (:meth:`~.filter_banks.EulerAcquisitionKalman.attitude`) and the best of which takes
over when the publishing filter's own copy falls clearly behind it (docs/rate-estimation.md).

The Euler filter's shape trial (34 hypotheses a sample for 15 samples and at least 15 s) and its hypotheses
over the angle about B (six, on samples a second apart) run in the loop's ticks between samples
(:meth:`FlownFilter.work`, a few filter updates a tick), not in the tick of the sample.
"""
from __future__ import annotations

import math

import numpy as np

from .attitude_kalman import AttitudeRateKalman, attitude_cov
from .filter_banks import ABOUT_B_HYPOTHESES, EulerAcquisitionKalman, RateModelBank
from .rate_kalman import NO_ESTIMATE, RateKalman

#: the choices of `RunConfig.rate_filter`, and the method names of the accuracy benchmark they fly
FILTERS = {"fixed": "kalman", "orbit": "kalman_orbit", "euler": "kalman_euler", "mm": "kalman_mm"}
#: the default: the best onboard method of the accuracy table's tumbling rows (docs/rate-estimation.md)
DEFAULT_FILTER = "euler"
#: telemetry ids of the filter publishing (DEBRIS_ATTITUDE_SIGMA.filter): 0 = fixed field
FILTER_IDS = {"fixed": 0, "orbit": 1, "euler": 2, "mm": 3}


class CalibratedField:
    """The field along the orbit for the orbit filters: `provider`'s (`field_now`), once the host-magnetics
    calibration (`fsw.host_calibration.HostCalibration`) applies a calibration to the samples. Before, the
    samples carry the host's iron (tens of µT, the size of the Earth's field): they do not fit the field
    along the orbit in any attitude, and the fixed-field filter, which assumes nothing about the
    field's size, flies."""

    def __init__(self, provider, calibration) -> None:
        self.provider = provider
        self.calibration = calibration

    @property
    def calibration_steps_T(self) -> np.ndarray:
        """The steps the calibration's changes made in the corrected samples, summed (`HostCalibration.steps_T`)."""
        return self.calibration.steps_T

    def field_now(self, now_s: float):
        if self.provider is None:
            return None, "no orbit/field model on board"
        field, why = self.provider.field_now(now_s)
        if field is None:
            return None, why
        if not self.calibration.cal.good:
            return None, "the host-magnetics calibration is not applied yet"
        return field, ""


def make_orbit_filter(kind: str, sigma_b_T: float, field_eci_T):
    """The filter `kind` (not "fixed") with the field along the orbit `field_eci_T(t_s)` [T]."""
    if kind == "orbit":
        return AttitudeRateKalman(sigma_b_T, field_eci_T=field_eci_T)
    if kind == "euler":
        # the shape trial's hypotheses and those over the angle about B run in the loop's ticks (FlownFilter.work)
        return EulerAcquisitionKalman(sigma_b_T, field_eci_T=field_eci_T, deferred=True,
                                      about_b_hypotheses=ABOUT_B_HYPOTHESES)
    if kind == "mm":
        return RateModelBank(sigma_b_T, field_eci_T=field_eci_T)
    raise ValueError(f"unknown rate filter {kind!r}: choose from {', '.join(FILTERS)}")


def members(kf) -> list[AttitudeRateKalman]:
    """The attitude filters inside `kf` (a bank's members, or the filter itself)."""
    if isinstance(kf, RateModelBank):
        return list(kf.members)
    if isinstance(kf, EulerAcquisitionKalman):
        return [kf.main]
    return [kf]


class FlownFilter:
    """The flown rate filter: `kind` (one of :data:`FILTERS`) once the field along the orbit is on board
    (`provider`), the fixed-field filter before. Interface of the flight loop's estimators
    (`fsw.flight.Estimator`) plus the attitude (:meth:`attitude`) and which filter publishes."""

    gap_history = 0  # filters: they propagate across a gap themselves
    PERPENDICULAR_ONLY, DEGENERATE, NO_ESTIMATE, DATA_GAP = (RateKalman.PERPENDICULAR_ONLY, RateKalman.DEGENERATE,
                                                             RateKalman.NO_ESTIMATE, RateKalman.DATA_GAP)

    def __init__(self, sigma_b_T: float, kind: str = DEFAULT_FILTER, provider=None) -> None:
        if kind not in FILTERS:
            raise ValueError(f"unknown rate filter {kind!r}: choose from {', '.join(FILTERS)}")
        self.sigma_b_T = float(sigma_b_T)
        self.kind = kind
        self.provider = provider
        self.fixed = RateKalman(sigma_b_T)
        #: the filter with the field along the orbit (None: none yet, or the field went away)
        self.orbit = None
        self._field = None
        #: why the fixed-field filter publishes ("" when the orbit filter does)
        self.why = "fixed-field filter chosen" if kind == "fixed" else (
            "no orbit/field model on board" if provider is None else "waiting for the field along the orbit")
        self.handovers = 0
        self.fallbacks = 0
        self.field_errors = 0

    # -- what publishes ----------------------------------------------------------------------------
    @property
    def active(self):
        return self.orbit if self.orbit is not None else self.fixed

    @property
    def name(self) -> str:
        """The publishing filter's name (one of :data:`FILTERS`)."""
        return self.kind if self.orbit is not None else "fixed"

    @property
    def omega_radps(self) -> np.ndarray:
        return self.active.omega_radps

    @property
    def sigma_radps(self) -> np.ndarray:
        return self.active.sigma_radps

    @property
    def flags(self) -> int:
        return self.active.flags

    def attitude(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(q body → ECI [w, x, y, z], 1-σ of the attitude error per body axis [rad]) of the publishing
        filter, or None (the fixed-field filter has no attitude; nor has a filter not started)."""
        if self.orbit is None or self.orbit.flags & NO_ESTIMATE:
            return None
        kf = members(self.orbit)[0] if not isinstance(self.orbit, RateModelBank) else self.orbit.main
        if not getattr(kf, "_started", False):
            return None
        q, P = self.orbit.attitude() if hasattr(self.orbit, "attitude") else (kf.q, attitude_cov(kf))
        s = np.sqrt(np.clip(np.diagonal(P), 0.0, None))
        return np.array(q, float), np.minimum(s, math.pi)

    # -- the loop ------------------------------------------------------------------------------------
    def reset(self) -> None:
        """After a long data gap: both filters start afresh (the orbit filter from the fixed one)."""
        self.fixed.reset()
        self.orbit = None

    def update(self, t_s: float, b_T) -> bool:
        """Add a field sample (tesla, body axes) at `t_s`; True when an estimate was published."""
        if self.kind == "fixed":
            return self.fixed.update(t_s, b_T)
        # the seed of a hand-over: the fixed filter's estimate before this sample (the sample that brings
        # the field may also be the first the host calibration corrects: a step the fixed filter takes
        # as a rotation, and the orbit filter, which expects the Earth's field, does not)
        seed = None if self.fixed.flags & NO_ESTIMATE else (self.fixed.omega_radps.copy(), self.fixed.P[3:6, 3:6])
        out = self.fixed.update(t_s, b_T)
        field = self._field_now(t_s)
        if field is None:
            if self.orbit is not None:  # the field went away: the fixed filter (running all along) takes over
                self.orbit = None
                self.fallbacks += 1
            return out
        self._field = field
        if self.orbit is None:
            if seed is None:
                return out  # nothing to seed from yet: the fixed filter's first sample
            self.orbit = make_orbit_filter(self.kind, self.sigma_b_T, self._b_eci_T)
            self.handovers += 1
            self.why = ""
            try:
                self.seed(t_s, b_T, *seed)
            except (ValueError, ArithmeticError) as e:
                return self._field_failed(e, out)
            return True
        try:
            return self.orbit.update(t_s, b_T)
        except (ValueError, ArithmeticError) as e:  # the field could not be evaluated at t_s (an SGP4 error)
            return self._field_failed(e, out)

    def work(self, max_updates: int) -> int:
        """Background work of the orbit filter, at most `max_updates` filter updates (the shape trial's
        hypotheses and those over the angle about B, :meth:`~.filter_banks.EulerAcquisitionKalman.work`);
        the flight loop calls it every tick. Returns the updates done."""
        if self.orbit is None or not hasattr(self.orbit, "work"):
            return 0
        try:
            return self.orbit.work(max_updates)
        except (ValueError, ArithmeticError) as e:
            self._field_failed(e, False)
            return 0

    def seed(self, t_s: float, b_T, w: np.ndarray, P: np.ndarray) -> None:
        """Start the orbit filter with the sample (t_s, b_T), the rate `w` and its covariance `P` (the fixed
        filter's), the attitude about B unknown, as at any start."""
        for kf in members(self.orbit):
            kf.start(t_s, b_T, omega_radps=w, rate_cov=P)

    def _b_eci_T(self, t_s):
        return self._field.b_eci_T(t_s)

    def _field_now(self, t_s: float):
        if self.provider is None:
            return None
        field, why = self.provider.field_now(t_s)
        if field is None:
            self.why = f"no orbit/field model on board ({why})" if why else "no orbit/field model on board"
        return field

    def _field_failed(self, e: Exception, out: bool) -> bool:
        self.field_errors += 1
        self.orbit = None
        self.fallbacks += 1
        self.why = f"field model: {e}"
        return out

    def status(self) -> str:
        """One phrase for the run's header and status: which filter publishes and why."""
        if self.orbit is not None:
            return f"{self.kind} filter with the field along the orbit ({FILTERS[self.kind]})"
        return f"fixed-field filter ({self.why})" if self.kind != "fixed" else "fixed-field filter (chosen)"
