"""Banks of attitude filters run side by side, one publishing: parallel inertia-shape hypotheses for the
switch to Euler's equations (:class:`EulerAcquisitionKalman`) and multiple models of the rate's process
(:class:`RateModelBank`). Each member is a :class:`~fsw.estimation.attitude_kalman.AttitudeRateKalman`.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .attitude_kalman import AttitudeKalmanTuning, AttitudeRateKalman, FieldFn, physical_shape
from .rate_kalman import run_stream


#: half-width of the default shape grid, in steps of 0.35: ln J ratios to ±1.75, principal moments up to
#: 5.8 times apart — an elongated body as a 3U cubesat (J₃/J₁ = 0.19, ln = −1.66) is on the grid. With ±0.7
#: (2 steps) such a body's hypotheses started 1 in ln J off and the filter settled on a wrong shape: on
#: a 27 °/s, 0.5 s, 1.5 µT cubesat tumble it stayed at 0.2–0.6 of Boer's error after 30 s.
SHAPE_GRID_HALF_WIDTH = 5


def shape_grid(step: float = 0.35, half_width: int = SHAPE_GRID_HALF_WIDTH) -> tuple[tuple[float, float], ...]:
    """Inertia shapes (ln J₂/J₁, ln J₃/J₁) on a square grid of `step` (2·`half_width` + 1 values per
    axis, centred on the sphere), those a body can have (:func:`physical_shape`)."""
    v = [step * i for i in range(-half_width, half_width + 1)]
    return tuple((a, b) for a in v for b in v if physical_shape((a, b)))


#: Cap of the innovation-driven process-noise factor once Euler's equations run (the bank's default):
#: unmodelled torques up to √30 × `rate_accel_radps2`; above, a persistent NIS excess (e.g. a
#: magnetorquer's field on the magnetometer) would let the poorly observed component along B wander.
EULER_ADAPT_MAX = 30.0
#: the shape trial's least step between the samples it takes (:class:`EulerAcquisitionKalman`)
TRIAL_STEP_S = 0.5


class _Bank:
    """Several :class:`AttitudeRateKalman` run side by side; the one in `main` publishes."""

    main: AttitudeRateKalman
    gap_history = 0  # filters: they propagate across a gap

    @property
    def omega_radps(self) -> np.ndarray:
        return self.main.omega_radps

    @property
    def sigma_radps(self) -> np.ndarray:
        return self.main.sigma_radps

    @property
    def flags(self) -> int:
        return self.main.flags


class EulerAcquisitionKalman(_Bank):
    """:class:`AttitudeRateKalman` with the inertia shape estimated, acquired by parallel hypotheses.

    A single filter switching Euler's equations on from a sphere fails at large steps (3 s at
    15–28 °/s, 45–84° of rotation a step): the random-walk phase lags an ω that turns by 5–10 °/s a
    step, its innovations stay at NIS ≈ 10–25, so the single filter's innovation test never lets it
    switch, and when it does switch the first update throws the shape out of the physical region
    (e.g. ln J₃/J₁ = 1.1 for a true 0.49) and back to acquisition.

    Here the random-walk filter (`main`) runs until it has found the rate (:meth:`AttitudeRateKalman.
    rate_found`); then one Euler hypothesis per shape of `shapes` (default :func:`shape_grid`, 1-σ
    `sigma_shape` about each) is started from a copy of it, all run in parallel with the random-walk
    filter for `trial_samples` samples and at least `trial_s` seconds (at a 0.5 s step 30 samples: with
    15 the trial on a fast, noisy tumble of an elongated body sometimes kept a shape that fitted the
    random-walk phase's lagging rate, and the filter then took a minute to walk to the right one), and
    the one with the least negative log-likelihood of its
    innovations over the trial (Σ ½(NIS + ln det S), Bar-Shalom et al. 2001 §11.6) becomes `main`.
    A hypothesis that restarts or leaves the physical region is dropped. When the random-walk filter
    wins, the trial is repeated after `retry_samples`. An Euler filter that is lost (its own NIS test,
    a shape no body has) falls back to the random-walk phase and the bank acquires again. Causal: each
    sample is used once, when it arrives; the published estimate is `main`'s (the random-walk filter's
    during a trial).

    The trial's cost is bounded whatever the sample rate: it takes samples at least `trial_step_s` apart
    (0.5 s: at most two a second, ~70 filter updates a second for 34 shapes, which the loop's
    background work keeps up with); when that leaves out samples `main` takes, the random-walk filter's
    score over the window is that of a copy of it run on the trial's samples.
    A trial that falls behind anyway (a loop too slow, or one that never calls :meth:`work`) catches
    up by two rounds of its hypotheses with each sample it takes, never all at once (a 50 Hz sensor
    once stalled the loop for 27 s that way).
    """

    def __init__(self, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
                 tuning: AttitudeKalmanTuning | None = None, shapes=None, sigma_shape: float = 0.2,
                 trial_samples: int = 15, trial_s: float = 15.0, retry_samples: int = 15,
                 angle_about_b_rad: float = 0.0, trial_step_s: float = TRIAL_STEP_S,
                 deferred: bool = False) -> None:
        # the bank decides when Euler's equations start: the filters' own innovation test is off
        tun = replace(tuning or AttitudeKalmanTuning(euler_adapt_max=EULER_ADAPT_MAX), euler_nis_max=-math.inf)
        self.main = AttitudeRateKalman(sigma_b_T, field_eci_T=field_eci_T, estimate_inertia=True, tuning=tun,
                                       angle_about_b_rad=angle_about_b_rad)
        self.shapes = tuple(tuple(map(float, p)) for p in (shape_grid() if shapes is None else shapes))
        self.sigma_shape = float(sigma_shape)
        self.trial_samples = int(trial_samples)
        self.trial_s = float(trial_s)
        self.trial_step_s = float(trial_step_s)
        self._window = self.trial_samples  # the running trial's length in samples
        self.retry_samples = int(retry_samples)
        #: the hypotheses' updates wait for :meth:`work` (the flight loop's ticks between samples) instead of
        #: running with each sample: a trial's ~30 filter updates a sample then never land in one tick
        self.deferred = bool(deferred)
        self.trials = 0
        #: the trial: [filter, its nll at the start, its resets at the start, samples taken, nll at the
        #: end of the trial window] per hypothesis (the first: the random-walk filter's copy, the
        #: reference), and the samples since the trial started
        self._trial: list[list] = []
        self._samples: list[tuple[float, np.ndarray]] = []
        self._next = 0
        self._wait = 0
        self._ref: list | None = None
        self._main_nll = math.nan

    @property
    def euler(self) -> bool:
        return self.main.euler

    @property
    def inertia_shape(self) -> np.ndarray:
        return self.main.inertia_shape

    @property
    def pending(self) -> int:
        """Hypothesis updates still to do (0 outside a trial)."""
        n = len(self._samples)
        return sum(n - h[3] for h in self._trial)

    def update(self, t_s: float, b_T) -> bool:
        """Add a field sample (tesla, body axes) at `t_s` to the publishing filter and to the trial's
        hypotheses (at once, or with `deferred` in :meth:`work`); True when an estimate was published."""
        main = self.main
        resets = main.resets
        out = main.update(t_s, b_T)
        if self._trial:
            if main.resets != resets:  # the random-walk filter restarted: the trial's start is void
                self._trial, self._samples = [], []
            elif not self._samples or t_s - self._samples[-1][0] >= self.trial_step_s - 1e-9:
                self._samples.append((t_s, np.array(b_T, float)))
                if self._ref is None and len(self._samples) == self._window:
                    self._main_nll = main.nll - self._nll0
                if not self.deferred:
                    self.work()
                elif len(self._samples) > 2 * self._window:  # a loop too slow for the trial: two rounds of
                    self.work(2 * len(self._trial))           # the hypotheses a sample, never all at once
        elif self._wait > 0:
            self._wait -= 1
        elif not main.euler and main.rate_found():
            self._start_trial()
        return out

    def work(self, max_updates: int | None = None) -> int:
        """Advance the trial's hypotheses through the samples taken since it started, at most `max_updates`
        filter updates (None: all), round robin; decide once every hypothesis has taken every sample and
        the trial window is full. Returns the updates done."""
        done = 0
        n = len(self._samples)
        while self._trial and (max_updates is None or done < max_updates):
            behind = [h for h in self._trial if h[3] < n]
            if not behind:
                break
            h = behind[self._next % len(behind)]
            self._next += 1
            kf = h[0]
            t, b = self._samples[h[3]]
            with np.errstate(all="ignore"):  # a wrong hypothesis may diverge: it is dropped below
                kf.update(t, b)
            h[3] += 1
            if h[3] == self._window:
                h[4] = kf.nll - h[1]
            done += 1
            if kf.resets != h[2] or not (kf.euler or h is self._ref):
                self._trial.remove(h)
                if h is self._ref:  # the reference lost: no comparison to make, try again later
                    self._trial, self._samples = [], []
                    self._wait = self.retry_samples
                    return done
        if n >= self._window and all(h[3] >= n for h in self._trial):
            self._decide()
        return done

    def _start_trial(self) -> None:
        self.trials += 1
        self._trial, self._samples = [], []
        dt = max(self.main._dt_nominal, self.trial_step_s)  # the trial's sample step
        self._window = max(self.trial_samples, int(math.ceil(self.trial_s / dt - 1e-9)) if dt > 0 else 0)
        self._ref = None
        if self.main._dt_nominal < self.trial_step_s - 1e-9:  # the trial leaves samples out: score a copy
            ref = self.main.clone()
            self._ref = [ref, ref.nll, ref.resets, 0, math.nan]
            self._trial.append(self._ref)
        self._nll0 = self.main.nll
        self._main_nll = math.nan
        for p in self.shapes:
            kf = self.main.clone()
            kf.start_euler(np.array(p), self.sigma_shape)
            self._trial.append([kf, kf.nll, kf.resets, 0, math.nan])

    def _decide(self) -> None:
        best, best_nll = None, self._main_nll if self._ref is None else self._ref[4]
        for h in self._trial:
            kf, d = h[0], h[4]
            if h is not self._ref and d < best_nll:
                best, best_nll = kf, d
        self._trial, self._samples = [], []
        if best is None:
            self._wait = self.retry_samples
        else:
            self.main = best


#: the process models of :class:`RateModelBank`: (τ s, a rad/s²) of a Gauss–Markov rate, stationary 1-σ
#: a√(τ/2) per axis 0.2–2.2 °/s (a libration, a held attitude); (∞, None) is the random walk of the
#: tuning given (the tumble). The ground smoother's likelihood picks from the same family.
RATE_MODELS = ((math.inf, None), (30.0, 1e-3), (30.0, 3e-3), (10.0, 3e-3), (10.0, 1e-2), (30.0, 1e-2))


class RateModelBank(_Bank):
    """Multiple-model estimation over the rate's process model (Magill 1965; Bar-Shalom et al. 2001
    §11.6): one :class:`AttitudeRateKalman` per model of `models`, all updated with every sample.

    The component of ω along B shows only as B turns in the body. A random walk lets it wander without
    bound when B barely turns (a slow libration: 1.3–4 °/s RMS error for a motion of 1.5 °/s); a
    Gauss–Markov rate, ω̇ = −ω/τ + w, brings it back to zero with its stationary spread, but would drag
    a tumble down. Each member's negative log-likelihood of its innovations, ½(NIS + ln det S), is summed
    with a forgetting factor 1 − 1/`memory_samples`, and the member with the least sum publishes. The
    Gauss–Markov members take the tuning (its innovation-driven noise adaptation included) with κ set to
    `kappa_gm`. Causal, one sample at a time; a member that restarts keeps its score (its restarts show
    in its innovations). The likelihood judges the part of the motion the samples see; along B, where
    they see little, it cannot tell the models apart, and a random walk that fits the perpendicular part
    a little better can still win there (see the README's orbital rows).
    """

    def __init__(self, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
                 tuning: AttitudeKalmanTuning | None = None, models=RATE_MODELS, memory_samples: float = 200.0,
                 kappa_gm: float = 0.03, angle_about_b_rad: float = 0.0) -> None:
        base = tuning or AttitudeKalmanTuning()
        if not memory_samples >= 1.0:
            raise ValueError(f"memory_samples must be >= 1, got {memory_samples!r}")
        self.models = tuple((float(tau), a) for tau, a in models)
        self.members = []
        for tau, a in self.models:
            tun = base if not math.isfinite(tau) else replace(base, rate_tau_s=tau, rate_accel_radps2=float(a),
                                                                kappa=kappa_gm)
            self.members.append(AttitudeRateKalman(sigma_b_T, field_eci_T=field_eci_T, tuning=tun,
                                                   angle_about_b_rad=angle_about_b_rad))
        self.forget = 1.0 - 1.0 / float(memory_samples)
        self.score = np.zeros(len(self.members))
        self.best = 0

    @property
    def main(self) -> AttitudeRateKalman:
        return self.members[self.best]

    @property
    def model(self) -> tuple[float, float | None]:
        """(τ, a) of the publishing member."""
        return self.models[self.best]

    def update(self, t_s: float, b_T) -> bool:
        """Add a field sample (tesla, body axes) at `t_s` to every member; True when an estimate was
        published."""
        out = False
        for i, kf in enumerate(self.members):
            nll0 = kf.nll
            published = kf.update(t_s, b_T)
            out = out or published
            d = kf.nll - nll0
            self.score[i] = self.forget * self.score[i] + (d if math.isfinite(d) else 1e6)
        self.best = int(np.argmin(self.score))
        return out


def euler_acquisition_rate(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, **kwargs
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run :class:`EulerAcquisitionKalman` (keyword arguments as its constructor) over a recording, as
    :func:`fsw.estimation.rate_kalman.kalman_rate`."""
    return run_stream(EulerAcquisitionKalman(sigma_b_T, **kwargs), t_s, b_T, sigma_b_T)


def rate_model_bank_rate(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, **kwargs
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run :class:`RateModelBank` (keyword arguments as its constructor) over a recording, as
    :func:`fsw.estimation.rate_kalman.kalman_rate`."""
    return run_stream(RateModelBank(sigma_b_T, **kwargs), t_s, b_T, sigma_b_T)
