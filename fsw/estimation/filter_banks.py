"""Banks of attitude filters run side by side, one publishing: parallel inertia-shape hypotheses for the
switch to Euler's equations (:class:`EulerAcquisitionKalman`) and multiple models of the rate's process
(:class:`RateModelBank`). Each member is a :class:`~fsw.estimation.attitude_kalman.AttitudeRateKalman`.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .attitude_kalman import AttitudeKalmanTuning, AttitudeRateKalman, FieldFn, attitude_cov, physical_shape
from .rate_formulas import SIGMA_UNOBSERVED_RADPS
from .rate_kalman import NO_ESTIMATE, run_stream
from .rotations import quat_conj, quat_exp, quat_log, quat_mul, quat_to_dcm


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
#: the trial's hypotheses cut a step of their shape that leaves the physical region at its edge when the edge
#: is within this many σ (`AttitudeKalmanTuning.shape_step_cut_sigmas`)
SHAPE_STEP_CUT_SIGMAS = 3.0
#: a trial that falls behind catches up by this many rounds of its hypotheses with each sample it takes
CATCH_UP_ROUNDS = 2

#: the share of the shape trial's window its hypotheses take to converge from the random-walk filter's
#: state before their likelihoods are compared (:class:`EulerAcquisitionKalman`)
TRIAL_BURN_IN = 0.5

#: an Euler filter is lost when the exponential mean of its NIS (3 degrees of freedom: mean 3) stays above this
#: with its process noise at the cap for a trial window (:meth:`EulerAcquisitionKalman._watch_lost`). Off (inf)
#: by default: an unmodelled torque (a −Ḃ law's, with its coils' field on the magnetometer) keeps the NIS of
#: the best filter there above 20 at the cap, and acquiring again made it worse (the accuracy benchmark's
#: bdot/asymmetric/dt3/0.5uT, 4 runs: 0.67 → 1.67 °/s). `EulerAcquisitionKalman(lost_nis_mean=20)`: ten
#: samples' mean above 20 is a χ²₃₀ above 600, never by chance on a torque-free body (at 10 it also fired on a
#: right winner still converging from the random-walk phase's rate on a 27 °/s cubesat tumble, NIS 5–15 for
#: 10 s); it finds a winner on a wrong shape (tests/fsw/test_kalman.py).
LOST_NIS_MEAN = math.inf

#: while the bank acquires, the published 1-σ of ω along the field is at least this share of |ω|
#: (:meth:`EulerAcquisitionKalman.sigma_radps`). The random walk reads the part of ω along B from the curvature of
#: the field's path in the body, which a rate turning in the body (a tumble of an asymmetric body) also bends: on
#: the lock-on tumbles (bench.lockon's, 10-40 °/s, 20-40 seeds each) its own σ along B covered its error on
#: 28-39 % of the samples before Euler's equations ran (median error 0.3-0.4 |ω|; 20 °/s off at a σ of
#: 1-4 °/s where ω lies near B); this floor makes that 60-76 %
ACQUISITION_ALONG_B_REL = 0.5

#: hypotheses over the attitude's angle about the field once Euler's equations run (:class:`EulerAcquisitionKalman`)
ABOUT_B_HYPOTHESES = 6
#: their least step between the samples they take (s): the angle about B shows only as the field turns along
#: the orbit (7–12° a minute), which samples a second apart see as well as every sample; at a 50 Hz sensor six
#: hypotheses then cost 6 filter updates a second, not 300
ABOUT_B_STEP_S = 1.0
#: at most this many of their updates in one call of :meth:`EulerAcquisitionKalman.work` (a loop tick): they need
#: six a second, a loop ticks 50–100 times a second; two in a tick with the sample's own update overran the
#: estimator task's 3 ms budget at 100 Hz a hundred times in 400 s, one kept it to main's
ABOUT_B_WORK_PER_CALL = 1
#: a hypothesis whose log-likelihood is this far below the best one's is dropped (odds e⁻⁵⁰), once the inertial
#: field has turned by twice `AttitudeKalmanTuning.about_b_turn_rad` (before, the wrong hypotheses'
#: transients can briefly beat the right one by 10–30); the publishing filter's own copy dropped so, the
#: best hypothesis takes over
ABOUT_B_DROP_NLL = 50.0
#: the best hypothesis takes over from the publishing filter's copy when it leads it by this much (a likelihood
#: ratio of e³ ≈ 20) once the field has turned by twice `about_b_turn_rad`, and their attitudes differ by more
#: than `ABOUT_B_SAME_RAD` (closer, they are the same solution). The likelihoods tell the angle about B
#: apart slowly: on a 10 °/s tumble (1 s, 0.5 µT) the publishing filter's copy settled 80–170° off 3–4
#: behind the best (the right one) for ten minutes, then fell behind by 10–20 as the field kept turning
ABOUT_B_SWITCH_NLL = 3.0
ABOUT_B_SAME_RAD = math.radians(10.0)
#: the likelihood's temper in the mixture's weights, exp(−Δnll/T): the filters' likelihoods are over-sure of
#: the angle about B (a wrong hypothesis leads the right one by 10–40 for minutes on some tumbles: the
#: rate's random walk and the field model's error absorb part of the misfit)
ABOUT_B_TEMPER = 10.0


#: no hypotheses over the angle about B: the reference alone, nothing added to its covariances (read-only)
_NO_SPREAD = np.zeros((3, 3))
_NO_SPREAD.flags.writeable = False
_NO_MIX = (1.0, _NO_SPREAD, _NO_SPREAD)


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
    rate_found`); then Euler hypotheses per shape of `shapes` (default :func:`shape_grid`, 1-σ
    `sigma_shape` about each) are started from copies of it, all run in parallel
    with the random-walk filter for `trial_samples` samples and at least `trial_s` seconds, and the one
    with the least negative log-likelihood of its innovations (Σ ½(NIS + ln det S), Bar-Shalom et al.
    2001 §11.6) over the window's last part (after `TRIAL_BURN_IN` of it: each hypothesis first converges
    from the random-walk filter's rate; scored from the start, the right shape's transient lost it the
    trial against the random-walk filter) becomes `main`. A hypothesis's step out of the physical region
    is cut at its edge (`SHAPE_STEP_CUT_SIGMAS`: an elongated body lies within the shape prior's σ of
    the edge); one that restarts or leaves the region anyway is dropped. When the random-walk filter
    wins, the trial is repeated after `retry_samples`. An Euler filter that is lost (its own NIS test,
    a shape no body has, or innovations far outside S with its process noise at the cap,
    :meth:`_watch_lost`) falls back to the random-walk phase and the bank acquires again. Causal: each
    sample is used once, when it arrives; the published estimate is `main`'s (the random-walk filter's
    during a trial).

    The trial's cost is bounded whatever the sample rate: it takes samples at least `trial_step_s` apart
    (`TRIAL_STEP_S`, 0.5 s: at most two a second, ~70 filter updates a second for 34 shapes, which the
    loop's background work keeps up with); when that leaves out
    samples `main` takes, the random-walk filter's score over the window is that of a copy of it
    run on the trial's samples.
    A trial that falls behind anyway (a loop too slow, or one that never calls :meth:`work`) catches
    up by `CATCH_UP_ROUNDS` rounds of its hypotheses with each sample it takes, never all at once (a 50 Hz
    sensor once stalled the loop for 27 s that way).

    The attitude's angle about the field shows only as the field turns along the orbit, and a single
    filter can settle 100–180° off there with a σ of a few degrees. With `about_b_hypotheses` (the flown
    filter: `ABOUT_B_HYPOTHESES`; 0, none, by default, as the ground's estimates run it), once Euler's
    equations run, `about_b_hypotheses` copies of `main` turned k·2π/K about the inertial field (the first: `main`'s own
    copy, the reference) take samples at least `about_b_step_s` apart, in :meth:`work` as the trial's
    hypotheses do (with each sample when not `deferred`; a loop that falls behind catches up by one round
    a sample). Each keeps its σ about B at least a uniform angle's over its 2π/K inside
    (`AttitudeKalmanTuning.about_b_sigma_rad`). The published estimate stays `main`'s; the hypotheses'
    spread, weighted by their tempered likelihoods, widens its attitude's covariance (:meth:`attitude`).
    Once the field has turned by twice `about_b_turn_rad`, a hypothesis `ABOUT_B_DROP_NLL` behind the best
    is dropped, and when the best leads the reference by `ABOUT_B_SWITCH_NLL` at an attitude more than
    `ABOUT_B_SAME_RAD` away, `main` becomes a copy of it (it is the reference from then on; counted in
    `about_b_switches`). When only the reference is left the hypotheses stop. They cost one filter
    update a second each, at most `ABOUT_B_WORK_PER_CALL` a call of :meth:`work`, none in :meth:`update`
    while the loop keeps up.
    """

    def __init__(self, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
                 tuning: AttitudeKalmanTuning | None = None, shapes=None, sigma_shape: float = 0.2,
                 trial_samples: int = 15, trial_s: float = 15.0, retry_samples: int = 15,
                 angle_about_b_rad: float = 0.0, trial_step_s: float = TRIAL_STEP_S,
                 about_b_hypotheses: int = 0, about_b_step_s: float = ABOUT_B_STEP_S,
                 deferred: bool = False,
                 lost_nis_mean: float = LOST_NIS_MEAN) -> None:
        # the bank decides when Euler's equations start: the filters' own innovation test is off
        tun = replace(tuning or AttitudeKalmanTuning(euler_adapt_max=EULER_ADAPT_MAX), euler_nis_max=-math.inf)
        #: the trial's hypotheses cut a shape step at the physical edge; the winner, as `main`, does not (a shape
        #: pushed to the edge there is a model that does not fit: back to acquisition)
        self._trial_tuning = replace(tun, shape_step_cut_sigmas=SHAPE_STEP_CUT_SIGMAS)
        self.main = AttitudeRateKalman(sigma_b_T, field_eci_T=field_eci_T, estimate_inertia=True, tuning=tun,
                                       angle_about_b_rad=angle_about_b_rad)
        self.shapes = tuple(tuple(map(float, p)) for p in (shape_grid() if shapes is None else shapes))
        self.sigma_shape = float(sigma_shape)
        self.trial_samples = int(trial_samples)
        self.trial_s = float(trial_s)
        self.trial_step_s = float(trial_step_s)
        self._window = self.trial_samples  # the running trial's length in samples
        self._burn = 0  # the samples of the running trial before its scores count
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
        self.about_b_hypotheses = int(about_b_hypotheses)
        self.about_b_step_s = float(about_b_step_s)
        #: the hypotheses over the angle about B: [filter, its nll at the start, its resets at the start,
        #: samples taken] each (empty: none running); the first `main`'s copy (the reference) until a switch
        self._about_b: list[list] = []
        self._about_b_ref: list | None = None
        self._about_b_samples: list[tuple[float, np.ndarray]] = []
        self._about_b_want = False  # start them at the next sample (main in Euler's equations, none running)
        #: the hypotheses' share of the attitude's and the rate's covariance, from their last full round: (the
        #: reference's weight, Σ the others' weight × (covariance + offset offsetᵀ) of the attitude, the same of
        #: the rate)
        self._about_b_mix: tuple[float, np.ndarray, np.ndarray] = _NO_MIX
        self.about_b_switches = 0
        self.about_b_updates = 0
        #: Euler filters found lost (:meth:`_watch_lost`), and the samples in a row the test has held
        self.lost = 0
        self._lost_run = 0
        self.lost_nis_mean = float(lost_nis_mean)

    @property
    def euler(self) -> bool:
        return self.main.euler

    @property
    def sigma_radps(self) -> np.ndarray:
        """`main`'s 1-σ of ω; while the bank acquires (the random-walk phase), its part along B at least
        `ACQUISITION_ALONG_B_REL` of |ω|; with the hypotheses over the angle about B running, the
        mixture's (as :meth:`attitude`'s): another attitude about B is another field turn read as rate."""
        s = self.main.sigma_radps
        if not self.main.euler:
            return self._acquiring_sigma(s)
        if not self._about_b:
            return s
        w_ref, _, spread = self._about_b_mix
        with np.errstate(invalid="ignore"):
            return np.sqrt(w_ref * s ** 2 + np.diag(spread))

    def _acquiring_sigma(self, s: np.ndarray) -> np.ndarray:
        """The published 1-σ `s` of the random-walk phase with its variance along the measured field raised to
        (`ACQUISITION_ALONG_B_REL` · |ω|)² where it is below (the filter's own covariance is left as it is:
        the acquisition test and the trial's hypotheses read it)."""
        main = self.main
        u = getattr(main, "_u", None)
        if u is None or not main._started or main.flags & NO_ESTIMATE:
            return s
        floor = ACQUISITION_ALONG_B_REL * float(np.linalg.norm(main.omega_radps))
        Pw = main.rate_cov_published()
        v = float(u @ Pw @ u)
        if not v < floor * floor:
            return s
        Pw = Pw + (floor * floor - v) * np.outer(u, u)
        return np.minimum(np.sqrt(np.clip(np.diagonal(Pw), 0.0, None)), SIGMA_UNOBSERVED_RADPS)

    @property
    def inertia_shape(self) -> np.ndarray:
        return self.main.inertia_shape

    @property
    def pending(self) -> int:
        """Hypothesis updates still to do (the shape trial's and those over the angle about B)."""
        n, m = len(self._samples), len(self._about_b_samples)
        return sum(n - h[3] for h in self._trial) + sum(m - h[3] for h in self._about_b)

    @property
    def about_b_running(self) -> int:
        """Hypotheses over the angle about B running (0: none)."""
        return len(self._about_b)

    def update(self, t_s: float, b_T) -> bool:
        """Add a field sample (tesla, body axes) at `t_s` to the publishing filter and to the trial's
        hypotheses (at once, or with `deferred` in :meth:`work`); True when an estimate was published."""
        main = self.main
        resets = main.resets
        out = main.update(t_s, b_T)
        if main.euler and main.resets == resets:
            self._watch_lost(main)
        if self._trial:
            if main.resets != resets:  # the random-walk filter restarted: the trial's start is void
                self._trial, self._samples = [], []
            elif not self._samples or t_s - self._samples[-1][0] >= self.trial_step_s - 1e-9:
                self._samples.append((t_s, np.array(b_T, float)))
                if self._ref is None and len(self._samples) == self._burn:
                    self._nll0 = main.nll
                if self._ref is None and len(self._samples) == self._window:
                    self._main_nll = main.nll - self._nll0
                if not self.deferred:
                    self._work_trial()
                elif len(self._samples) > 2 * self._window:  # a loop too slow for the trial: a few rounds
                    self._work_trial(CATCH_UP_ROUNDS * len(self._trial))  # a sample, never all at once
        elif self._wait > 0:
            self._wait -= 1
        elif not main.euler and main.rate_found():
            self._start_trial()
        self._about_b_sample(t_s, b_T, main.resets != resets)
        return out

    def _watch_lost(self, main: AttitudeRateKalman) -> None:
        """An Euler filter whose innovations stay far outside S although its process noise is at its cap is
        lost (a trial's wrong winner): back to acquisition, and the shape trial runs again. The test: the
        exponential mean of NIS over ~`adapt_samples` samples above `lost_nis_mean` (`LOST_NIS_MEAN`: off by
        default) for a trial window's samples in a row."""
        cap = main.tuning.euler_adapt_max
        if main._nis_mean > self.lost_nis_mean and (cap is None or main.adapt >= cap):
            self._lost_run += 1
        else:
            self._lost_run = 0
        if self._lost_run >= self._window:
            self._lost_run = 0
            self.lost += 1
            main.back_to_acquisition()

    def work(self, max_updates: int | None = None) -> int:
        """Background work, at most `max_updates` filter updates (None: all): the shape trial's hypotheses
        (:meth:`_work_trial`) first, then those over the angle about B (:meth:`_work_about_b`, at most
        `ABOUT_B_WORK_PER_CALL`). Returns the updates done."""
        done = self._work_trial(max_updates)
        if max_updates is None:
            return done + self._work_about_b()
        return done + self._work_about_b(min(max_updates - done, ABOUT_B_WORK_PER_CALL))

    def _work_trial(self, max_updates: int | None = None) -> int:
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
            if h[3] == self._burn:
                h[1] = kf.nll
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
        self._burn = int(TRIAL_BURN_IN * self._window)
        self._ref = None
        if self.main._dt_nominal < self.trial_step_s - 1e-9:  # the trial leaves samples out: score a copy
            ref = self.main.clone()
            self._ref = [ref, ref.nll, ref.resets, 0, math.nan]
            self._trial.append(self._ref)
        self._nll0 = self.main.nll
        self._main_nll = math.nan
        for p in self.shapes:
            kf = self.main.clone()
            kf.tuning = self._trial_tuning
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
            best.tuning = self.main.tuning
            self.main = best
            self._stop_about_b()
            self._about_b_want = True

    # -- the angle about B -------------------------------------------------------------------------
    def _about_b_sample(self, t_s: float, b_T, restarted: bool) -> None:
        """`main` took the sample (t_s, b_T): the hypotheses over the angle about B start, stop (`main`
        restarted or out of Euler's equations: they are void) or keep it for :meth:`work`."""
        main = self.main
        if restarted or not main.euler:
            self._stop_about_b()
            self._about_b_want = False
            return
        if self._about_b_want:
            self._about_b_want = False
            self._start_about_b()
            return
        if not self._about_b:
            return
        last = self._about_b_samples[-1][0] if self._about_b_samples else self._about_b_ref[0].t_s
        if t_s - last < self.about_b_step_s - 1e-9:
            return
        self._about_b_samples.append((t_s, np.array(b_T, float)))
        if not self.deferred:
            self._work_about_b()
        elif len(self._about_b_samples) > 2:  # a loop too slow for them: one round a sample, never all at once
            self._work_about_b(len(self._about_b))

    def _start_about_b(self) -> None:
        """The hypotheses over the attitude's angle about the field: `main` turned about the inertial field by
        k·2π/K, each with the floor of its σ about B at a uniform angle over its 2π/K (the linearisation holds
        within it)."""
        k = self.about_b_hypotheses
        main = self.main
        self._stop_about_b()
        if k < 2 or main.field is None or main.store or not main._started:
            return
        h, _ = main.measurement(main.t_s)
        u = h / np.linalg.norm(h)
        b_i = quat_to_dcm(main.q) @ u
        tun = replace(main.tuning, about_b_sigma_rad=2.0 * math.pi / k / math.sqrt(12.0))
        for j in range(k):
            kf = main.clone()
            kf.tuning = tun
            if j:
                kf.q = quat_mul(quat_exp(b_i * (2.0 * math.pi * j / k)), kf.q)
            _condition_about_b(kf, u, tun.about_b_sigma_rad)
            self._about_b.append([kf, kf.nll, kf.resets, 0])
        self._about_b_ref = self._about_b[0]

    def _stop_about_b(self) -> None:
        self._about_b, self._about_b_ref, self._about_b_samples = [], None, []
        self._about_b_mix = _NO_MIX

    def _work_about_b(self, max_updates: int | None = None) -> int:
        """Advance the hypotheses over the angle about B through their samples, at most `max_updates` filter
        updates (None: all), round robin; after each full round, weigh them (:meth:`_judge_about_b`).
        Returns the updates done."""
        done = 0
        while self._about_b and (max_updates is None or done < max_updates):
            n = len(self._about_b_samples)
            h = min(self._about_b, key=lambda g: g[3])  # the one furthest behind: rounds stay level
            if h[3] >= n:
                break
            t, b = self._about_b_samples[h[3]]
            with np.errstate(all="ignore"):  # a wrong hypothesis may diverge: it is dropped below
                h[0].update(t, b)
            h[3] += 1
            done += 1
            if all(g[3] == h[3] for g in self._about_b):
                self._judge_about_b()
        self.about_b_updates += done
        if self._about_b:  # the samples every hypothesis has taken are not kept
            first = min(h[3] for h in self._about_b)
            if first:
                del self._about_b_samples[:first]
                for h in self._about_b:
                    h[3] -= first
        return done

    def _judge_about_b(self) -> None:
        """After a full round: the lost hypotheses (restarted, or out of Euler's equations) and, once the
        field has turned by twice `about_b_turn_rad`, those `ABOUT_B_DROP_NLL` behind the best are dropped;
        the reference dropped so, `main` becomes a copy of the best; the mixture's covariance about the
        reference is kept for :meth:`attitude`."""
        ref = self._about_b_ref
        live = [h for h in self._about_b if h[0].resets == h[2] and h[0].euler]
        if ref not in live:  # `main`'s copy lost while `main` goes on: the hypotheses start again from it
            self._stop_about_b()
            self._about_b_want = True
            return
        scores = np.array([h[0].nll - h[1] for h in live])
        best_i = int(np.argmin(scores))
        best = live[best_i]
        if ref[0].field_turn_rad >= 2.0 * ref[0].tuning.about_b_turn_rad:
            ref_score = ref[0].nll - ref[1]
            live = [h for h, sc in zip(live, scores) if sc - scores[best_i] < ABOUT_B_DROP_NLL or h is best]
            scores = np.array([h[0].nll - h[1] for h in live])
            apart = np.linalg.norm(quat_log(quat_mul(quat_conj(ref[0].q), best[0].q))) > ABOUT_B_SAME_RAD
            if ref not in live or (ref_score - scores.min() >= ABOUT_B_SWITCH_NLL and apart):
                self._switch_about_b(best)  # clearly worse than the best: the best flies
                ref = best
        self._about_b = live
        if len(live) == 1:  # settled: `main` goes on alone
            self._stop_about_b()
            return
        w = np.exp(-(scores - scores.min()) / ABOUT_B_TEMPER)
        w /= w.sum()
        spread, rate_spread = np.zeros((3, 3)), np.zeros((3, 3))
        w_ref = 1.0
        for wj, h in zip(w, live):
            if h is ref:
                w_ref = float(wj)
                continue
            d = quat_log(quat_mul(quat_conj(ref[0].q), h[0].q))
            spread += wj * (h[0].P[:3, :3] + np.outer(d, d))
            dw = h[0].omega_radps - ref[0].omega_radps
            rate_spread += wj * (h[0].rate_cov_published() + np.outer(dw, dw))
        self._about_b_mix = (w_ref, spread, rate_spread)

    def _switch_about_b(self, best: list) -> None:
        """`main` becomes a copy of the hypothesis `best` (at its last sample; `main`'s samples since then are
        left out, the filter propagates across them), with `main`'s tuning (no floor about B inside)."""
        main = self.main
        new = best[0].clone()
        new.tuning = main.tuning
        new._dt_nominal = main._dt_nominal
        new.resets = main.resets
        self.main = new
        self._about_b_ref = best
        self.about_b_switches += 1

    def attitude(self) -> tuple[np.ndarray, np.ndarray]:
        """(q body → ECI of `main`, the 3×3 covariance of its attitude error in body axes): `main`'s
        (:func:`~.attitude_kalman.attitude_cov`, its σ about B held wide until the field has turned) and,
        with the hypotheses over the angle about B running, the mixture's about it (each hypothesis weighted
        by its tempered likelihood, its offset from `main`'s copy included), so that the σ covers the
        hypotheses not yet excluded."""
        w_ref, spread, _ = self._about_b_mix
        return np.array(self.main.q, float), w_ref * attitude_cov(self.main) + spread


def _condition_about_b(kf: AttitudeRateKalman, u: np.ndarray, sigma_rad: float) -> None:
    """`kf`'s attitude variance about the body axis `u` set to `sigma_rad`²: lowered by conditioning on a
    pseudo-measurement of that angle (the correlated rate, shape and field lowered with it), raised by adding
    along `u` alone. Overwriting a lowered variance in place, the correlations kept, left the covariance
    indefinite (a rate variance below zero within 20 s on a libration the Euler filter does not fit)."""
    H = np.zeros(kf.n)
    H[:3] = u
    v = float(H @ kf.P @ H)
    s2 = sigma_rad ** 2
    if v > s2:
        r = s2 * v / (v - s2)   # posterior v·r/(v + r) = σ²
        PH = kf.P @ H
        kf.P = kf.P - np.outer(PH, PH) / (v + r)
        kf.P = 0.5 * (kf.P + kf.P.T)
    else:
        kf.P[:3, :3] += (s2 - v) * np.outer(u, u)


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
