"""The identification pipeline: the tensor (and the motion) from records of magnetometer samples.

The parameters — the tensor, the initial state and the offset — are those that make the predicted
B_body(t_k) closest to the measured samples, in least squares weighted by the sensor noise σ_B.
Fitting the samples themselves, rather than Euler's equations on rates differentiated from them,
removes the errors-in-variables bias of the linear methods (fsw/estimation/inertia.py): the only noisy
quantity is the measurement. Torque-free data fix the tensor only up to scale (the motion is the same
for λJ); a known torque fixes it. A torque whose size is not to be relied on is modelled as a constant
moment of unknown size on its interval (``unknown_moments``): the record on both sides of it, and the
interval itself, then all serve the shape. The attitude about B_I is fixed only by the field's motion
along the orbit (about twice the orbital rate), which is why the field model is part of the model.

The fit starts with multiple shooting (:mod:`~.shooting`): each segment first fits its own arc, then
the defects bring in Euler's equations (the rate change across a segment is what J predicts). The
chain of segments is fixed by the data only up to a rotation about the field: after the first (loose)
stage the segment attitudes are re-chained end to start, candidate chains wound about the mean field
direction at a few rates are carried through the tightening stages (the dynamics tell the windings
apart), and single shooting is started from a few angles about B_I(t₀); the lowest cost wins. Single
shooting polishes the result and gives the estimate and its covariance s²(JᵀJ)⁻¹.

:func:`identify_steps` is a generator that yields every few integration steps (``chunk``): the flight
software advances it once per loop tick, inside the task's budget; :func:`identify` runs it to the end.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .. import inertia as inr
from .. import sampled_moment as sm
from ..rotations import quat_exp, quat_mul, quat_to_dcm
from . import field_error, profile
from .initial import chain_attitudes, initial_rates, segment_length
from .model import FieldFn, InertiaParam, KnownAction
from .propagation import segment_bounds
from .shooting import ErrorTerms, MultipleShooting, SingleShooting
from .solver import LMRuns, Prior, complete, lm, lm_steps

# --- the identification pipeline --------------------------------------------------------------------

def error_columns(t_s: np.ndarray, action: KnownAction, opts: "FitOptions") -> tuple[np.ndarray, np.ndarray, int]:
    """The error terms of `opts` over the record `t_s` (:class:`~.shooting.ErrorTerms`): their columns
    (m, n, 3) (per unit parameter, in units of σ_B), their prior 1-σ (m,) [T], and the number of dipole
    states G (the first 3G terms)."""
    t = np.asarray(t_s, float)
    cols, sig = [np.zeros((0, len(t), 3))], [np.zeros(0)]
    G = 0
    if opts.kit_offset_sigma_T is not None:
        groups = action.dipole_groups(t)
        G = int(groups.max()) + 1 if groups.size else 0
        on = (groups[None, :] == np.arange(G)[:, None]).astype(float)             # (G, n)
        cols.append(np.einsum("gn,ab->ganb", on, np.eye(3)).reshape(3 * G, len(t), 3))
        sig.append(np.full(3 * G, float(opts.kit_offset_sigma_T)))
    if opts.drift_degree:                          # the host's drift as the field-error model has it
        d = int(opts.drift_degree)
        cols.append(field_error.body_columns(t, None, d, 1.0, soft_iron=False))
        sig.append(np.full(3 * d, float(opts.drift_sigma_T)))
    return np.concatenate(cols), np.concatenate(sig), G


@dataclass
class FitResult:
    """Outcome of an output-error fit (one run)."""

    p: np.ndarray                 # (6,) tensor components, kg·m²
    cov_p: np.ndarray             # (6, 6)
    omega0_radps: np.ndarray
    q0: np.ndarray
    bias_T: np.ndarray
    chi2: float
    dof: int
    samples_used: int
    iterations: int
    converged: bool
    mode: str
    theta: np.ndarray
    cov_theta: np.ndarray
    unknown_intervals: tuple = ()              # (t0, t1) of the moments fitted as unknowns
    moment_sigma_Nm: tuple = ()                # their prior 1-σ (3,) each (inf: free)
    moments_Nm: np.ndarray | None = None       # (K, 3) their fitted values (in the tensor's scale)
    cov_moments: np.ndarray | None = None      # (3K, 3K)
    moment_unknown_samples: int = 0            # samples whose moment was unknown (NaN): fitted
    field_error: object = None                 # field_error.FieldError when fitted (FitOptions.field_error_degree)
    errors: ErrorTerms | None = None           # the samples' error terms fitted (FitOptions' kit and drift)

    @property
    def s2(self) -> float:
        return self.chi2 / max(self.dof, 1)

    def estimate(self, method: str | None = None) -> inr.InertiaEstimate:
        return inr.InertiaEstimate(self.p.copy(), self.cov_p.copy(),
                                   method or f"output-error fit ({self.mode})", self.samples_used,
                                   self.mode in ("full", "shape", "scale"),
                                   extra={"chi2_per_dof": self.s2})


@dataclass
class FitOptions:
    """Settings of :func:`identify` (defaults suit 1 Hz samples and rates of a few °/s)."""

    mode: str = "full"
    fit_bias: bool = True
    bias_sigma_T: float = 10e-6            # prior 1-σ of the offset
    inertia_prior_rel: float = 3.0         # prior 1-σ of each tensor component relative to the guess
    segment_samples: int = 30             # at most; fewer for a fast turn (segment_angle_rad per segment)
    segment_angle_rad: float = 1.2
    h_max_s: float = 1.0
    defect_schedule: tuple = ((1e3, 3e-3), (0.03, 3e-4), (3e-3, 3e-5))  # (σ_q rad, σ_ω rad/s)
    ms_iter: tuple = (40, 20, 20)            # LM iterations per stage
    ms_rtol: float = 1e-4
    ss_iter: int = 30
    ss_first_window: int = 150
    ss_growth: float = 1.6
    # (turn α deg, winding Ω deg/s) of the re-chained segments about their field direction, tried
    chain_candidates: tuple = ((0, 0), (90, 0), (180, 0), (270, 0), (0, -0.3), (0, 0.3))
    starts_about_b: int = 2                # single-shooting starts turned about B_I(t0) (best kept)
    omega_scale: float = 0.01
    # the field model's error along the record fitted and marginalised (`field_error`): the Legendre degree
    # in time (`field_error.degree_for` gives it for a record's length), None: the field model taken as exact
    field_error_degree: int | None = None
    # with it, the soft iron's error left by the host's calibration: its 1-σ per element (None: not fitted)
    soft_iron_sigma: float | None = None
    # with it, the joint covariance the robust one (`field_error.robust_cov`: each variance at least the
    # Newey-West sandwich's); False: the curvature's
    robust_cov: bool = False
    # the field at the sensor of the magnets that make the known dipole, left by their compensation: an
    # offset of its own (body axes, constant) per dipole state, fitted by single shooting with this prior
    # 1-σ [T] (None: the samples taken as compensated exactly). The compensation is calibrated from the
    # field's steps as the capsules open, against the trend of a tumbling body's field; a few µT left in
    # it act like the torque's own signature on the samples while the torque acts
    kit_offset_sigma_T: float | None = None
    # the host's hard iron drifting from its calibration over the record (a thermal cycle of about an
    # orbit: ~1 µT): Legendre polynomials of degree 1…`drift_degree` in time per body axis, fitted by single
    # shooting, each coefficient with prior 1-σ `drift_sigma_T` (None: the calibration taken as constant)
    drift_degree: int | None = None
    drift_sigma_T: float = 2e-6
    # the whole record's single shooting also starts from the tensor scaled by each of these: a long record
    # of a tumbling body has local minima a few % apart along the tensor's scale (the free motion does
    # not depend on it; only the known torque's response does), and the fit ends in the one nearest its
    # start; the best of all is kept
    scale_starts: tuple = (0.96, 1.04)
    # the profile of the cost along the scale (`profile`): Ixx held at the fit's times each of these, the
    # rest fitted again; where the profile's 95 % interval is wider than the curvature's, the tensor's
    # variance along its scale is raised to it (modes full and diag; empty: no profile)
    scale_profile: tuple = ()


def identify(t_s: np.ndarray, b_meas: np.ndarray, b_inertial: FieldFn, action: KnownAction,
             sigma_b_T: float, p_guess: np.ndarray, opts: FitOptions | None = None, *,
             p_shape: np.ndarray | None = None, b_samples: np.ndarray | None = None,
             unknown_moments=(), log: Callable[[str], None] | None = None) -> list[FitResult]:
    """Identify the tensor (and the motion) from R runs of samples ``b_meas`` (R, n, 3) at ``t_s`` (n,).

    ``b_inertial`` the field model along the orbit, ``action`` the known moment/dipole, ``sigma_b_T``
    the per-axis noise, ``p_guess`` (6,) the starting tensor (also the mean of the weak prior),
    ``p_shape`` (R, 6) the fixed shape for mode ``"scale"``. ``unknown_moments``: (t0, t1) intervals on
    which a constant moment of unknown size acts (added to ``action``; fitted, started at zero, no
    prior) — with mode ``"shape"`` the whole record, pulses included, gives the tensor up to scale
    without relying on the size of the torque. Returns one :class:`FitResult` per run.
    """
    return complete(identify_steps(t_s, b_meas, b_inertial, action, sigma_b_T, p_guess, opts,
                                   p_shape=p_shape, b_samples=b_samples, unknown_moments=unknown_moments,
                                   log=log))


def identify_steps(t_s: np.ndarray, b_meas: np.ndarray, b_inertial: FieldFn, action: KnownAction,
                   sigma_b_T: float, p_guess: np.ndarray, opts: FitOptions | None = None, *,
                   p_shape: np.ndarray | None = None, b_samples: np.ndarray | None = None,
                   unknown_moments=(), log: Callable[[str], None] | None = None, chunk: int | None = None):
    """Generator form of :func:`identify`: yields every ``chunk`` integration steps; its value (the
    ``StopIteration`` value) is the list of results.

    The segments' length is ``opts.segment_angle_rad`` of the field's turn, at most
    ``opts.segment_samples``. When that cap shortened them and a run's fit ends with a χ² more than
    `RETRY_Z` of its standard deviations above its dof (:func:`implausible`), the fit runs again with
    segments up to twice as long, and each run keeps the lower χ²: the field's turn misses the rate along
    B, so on a fast tumble sampled fast the capped segments may turn too little to tell it, and the chain
    of segments goes wrong."""
    opts = opts or FitOptions()
    t = np.asarray(t_s, float)
    b_meas = np.asarray(b_meas, float)
    if b_meas.ndim == 2:
        b_meas = b_meas[None]
    if b_samples is None:
        b_samples = np.asarray(b_inertial(t), float).reshape(-1, 3)
    args = (t, b_meas, b_inertial, action, sigma_b_T, p_guess, opts)
    kw = dict(p_shape=p_shape, b_samples=b_samples, unknown_moments=unknown_moments, log=log, chunk=chunk)
    length = segment_length(t, b_meas[0], opts.segment_samples, opts.segment_angle_rad)
    out = yield from _identify_once(*args, length, **kw)
    longer = segment_length(t, b_meas[0], 2 * opts.segment_samples, opts.segment_angle_rad)
    if longer > length and any(implausible(r) for r in out):
        if log:
            log(f"χ²/dof {' '.join(f'{r.s2:.3f}' for r in out)} with {length}-sample segments: again with {longer}")
        again = yield from _identify_once(*args, longer, **kw)
        out = [b if np.isfinite(b.chi2) and not (a.chi2 <= b.chi2) else a for a, b in zip(out, again)]
    return out


#: the χ², in its standard deviations above its dof, past which a fit on capped segments runs again with longer
#: ones. A wrong chain of segments need not end far above: on a record of the target identification test
#: (400 samples at 10 Hz, ~1,200 dof) it ended at χ²/dof 1.112, 2.7 σ, with the tensor 9-17 % off, and the
#: longer segments found 0.950 and the truth within its intervals. The run again keeps the lower χ², so a
#: right fit that crosses this (2.3 % of them) costs a second fit's time, never its result.
RETRY_Z = 2.0


def implausible(res: "FitResult", z: float = RETRY_Z) -> bool:
    """The fit's χ² is more than `z` of its standard deviations above its dof (the noise σ_B as given),
    or not finite: the fit ended away from the best one, or the model misses part of the signal."""
    return not np.isfinite(res.chi2) or res.chi2 > res.dof + z * math.sqrt(2.0 * max(res.dof, 1))


def _identify_once(t: np.ndarray, b_meas: np.ndarray, b_inertial: FieldFn, action: KnownAction,
                   sigma_b_T: float, p_guess: np.ndarray, opts: FitOptions, seg_len: int, *,
                   p_shape: np.ndarray | None, b_samples: np.ndarray, unknown_moments,
                   log: Callable[[str], None] | None, chunk: int | None):
    """:func:`identify_steps` with segments of `seg_len` samples."""
    R, n, _ = b_meas.shape
    I_ref = float(np.mean(np.asarray(p_guess, float)[:3]))
    par = InertiaParam(opts.mode, I_ref, p_shape, *sm.merged(unknown_moments, action.unknown_intervals,
                                                             action.unknown_sigma_Nm))
    if any(b <= t[0] or a >= t[-1] for a, b in par.unknown_intervals):
        raise ValueError("an unknown-moment interval lies outside the record: nothing could fix its moment")
    bounds = segment_bounds(n, seg_len)
    G = len(bounds) - 1
    n_I = par.n
    th_I0 = np.array([par.from_p(p_guess, r) for r in range(R)])
    q_ref = np.zeros((R, G, 4))
    theta0 = np.zeros((R, n_I + 6 * G + (3 if opts.fit_bias else 0)))
    for r in range(R):
        w_g = initial_rates(t, b_meas[r], bounds)
        q_ref[r] = chain_attitudes(t, b_meas[r], b_samples, bounds, w_g)
        theta0[r, :n_I] = th_I0[r]
        seg = np.zeros((G, 6))
        seg[:, :3] = w_g / opts.omega_scale
        theta0[r, n_I:n_I + 6 * G] = seg.ravel()
    cols, cols_sigma, n_kit = error_columns(t, action, opts)
    ms = MultipleShooting(t, b_meas, b_samples, action, b_inertial, par, bounds, q_ref, sigma_b_T,
                          fit_bias=opts.fit_bias, omega_scale=opts.omega_scale, h_max_s=opts.h_max_s)
    prior = fit_prior(ms.n_params, n_I, th_I0[0], opts, sigma_b_T, par)
    runs = LMRuns(theta0)
    # stage 1: segments fitted to their own arcs, tied only loosely by the rate, then re-chained
    ms.sigma_q, ms.sigma_w = opts.defect_schedule[0]
    yield from lm_steps(ms, runs, prior, opts.ms_iter[0], rtol=opts.ms_rtol, chunk=chunk)
    runs.theta = ms.rechain(runs.theta, np.arange(R), b_samples)
    if chunk is not None:
        yield
    if log:
        log(f"multiple shooting, {G} segments, loose: χ²/(3n) "
            + " ".join(f"{c / (3 * n):.3f}" for c in runs.data_cost[:8]))
    # The re-chained chain is known only up to turns of its segments about their own field direction,
    # which one sample per segment cannot see: a common turn α (fixed only by the field's motion along
    # the orbit) and a winding Ω·t (each segment's rate along B is its least certain part; the
    # dynamics tell windings apart). A few candidates go through the tightening stages; the best of
    # each run is kept.
    cand = np.radians(np.asarray(opts.chain_candidates, float))
    W = len(cand)
    msw, thw = _turned(ms, runs.theta, np.broadcast_to(cand, (R, W, 2)), t, b_samples,
                       np.repeat(np.arange(R), W))
    if chunk is not None:
        yield
    wruns = LMRuns(thw)
    wrun = np.repeat(np.arange(R), W)                    # run of each candidate
    for stage in range(1, len(opts.defect_schedule)):
        msw.sigma_q, msw.sigma_w = opts.defect_schedule[stage]
        yield from lm_steps(msw, wruns, prior, opts.ms_iter[min(stage, len(opts.ms_iter) - 1)],
                            rtol=opts.ms_rtol, chunk=chunk)
        if log:
            log(f"multiple shooting σ_q={msw.sigma_q:g} rad σ_ω={msw.sigma_w:g} rad/s, {len(wrun)} chains: "
                "χ²/(3n) " + " ".join(f"{c / (3 * n):.3f}" for c in wruns.data_cost[:8]))
        if stage < len(opts.defect_schedule) - 1:
            # candidates that reached the same chain as a better one, or a clearly worse one, stop here
            keep = _distinct_best(wrun, wruns.theta[:, :n_I], wruns.cost, tol=2e-3, same_cost=0.5)
            msw, wrun = msw.subset(keep), wrun[keep]
            sub = LMRuns(wruns.theta[keep].copy())
            sub.cost, sub.data_cost = wruns.cost[keep], wruns.data_cost[keep]
            wruns = sub
    wc = np.where(np.isfinite(wruns.cost), wruns.cost, np.inf)
    pick = np.array([np.flatnonzero(wrun == r)[np.argmin(wc[wrun == r])] for r in range(R)])
    best_theta = wruns.theta[pick]
    best_q = msw.q_ref[pick]
    # The chain is fixed up to a rotation about B_I(t0), to which the defects are blind: single shooting
    # from segment 0 turned by each of S angles about B_I(t0) (virtual runs), over windows growing to
    # the end; the best of each run is kept.
    S = max(1, opts.starts_about_b)
    V = R * S
    vrun = np.repeat(np.arange(R), S)
    bv = b_meas[vrun]
    p_shape_v = None if p_shape is None else np.asarray(p_shape, float)[vrun]
    q0 = quat_mul(best_q[:, 0], quat_exp(best_theta[:, n_I + 3:n_I + 6]))[vrun]
    bI0 = b_samples[0] / np.linalg.norm(b_samples[0])
    q0 = quat_mul(quat_exp(np.outer(2 * np.pi * (np.arange(V) % S) / S, bI0)), q0)
    theta = np.zeros((V, n_I + 6 + (3 if opts.fit_bias else 0) + len(cols)))
    theta[:, :n_I] = best_theta[vrun, :n_I]
    theta[:, n_I:n_I + 3] = best_theta[vrun, n_I:n_I + 3]
    if opts.fit_bias:
        theta[:, n_I + 6:n_I + 9] = best_theta[vrun, -3:]
    alive = np.arange(V)
    windows = _ss_windows(n, opts.ss_first_window, opts.ss_growth)
    for wi, nw in enumerate(windows):
        last = wi == len(windows) - 1
        starts = theta[alive]
        if last:
            # the whole record: each start also from its tensor scaled by each of `scale_starts`
            starts = np.concatenate([starts] + [_scaled(starts, par, k) for k in scale_starts(par, opts)])
            alive = np.tile(alive, len(starts) // len(alive))
        pv = InertiaParam(opts.mode, I_ref, None if p_shape_v is None else p_shape_v[alive], par.unknown_intervals,
                          par.moment_sigma_Nm)
        ss = SingleShooting(t, bv[alive], b_samples, action, b_inertial, pv, q0[alive], sigma_b_T, n=nw,
                            fit_bias=opts.fit_bias, omega_scale=opts.omega_scale, h_max_s=opts.h_max_s,
                            error_columns=cols)
        prior = fit_prior(ss.n_params, n_I, th_I0[0], opts, sigma_b_T, pv, cols_sigma)
        # the tensor stays at the multiple-shooting value until the whole record is fitted: a prefix
        # alone determines it less well and would pull it off
        frozen = None if last else np.arange(ss.n_params) < n_I
        sruns = LMRuns(starts.copy())
        yield from lm_steps(ss, sruns, prior, opts.ss_iter, frozen=frozen, chunk=chunk)
        if log:
            log(f"single shooting, {nw} samples, {alive.size} starts: χ²/dof "
                + " ".join(f"{c / sruns.dof:.3f}" for c in sruns.data_cost[:8]))
        if not last:
            theta[alive] = sruns.theta
            phys = np.delete(theta[alive], np.arange(n_I + 3, n_I + 6), axis=1)
            alive = alive[_distinct_best(vrun[alive], phys, sruns.cost)]
    allres = results(ss, sruns, prior, n_kit)
    for res in allres:
        res.moment_unknown_samples = sm.samples_in(t, action.unknown_intervals)
    out = []
    for r in range(R):
        idx = np.flatnonzero(vrun[alive] == r)
        costs = np.array([allres[j].chi2 + prior.cost(allres[j].theta) for j in idx])
        j = int(idx[int(np.argmin(np.where(np.isfinite(costs), costs, np.inf)))])
        res = allres[j]
        prof, at = None, (ss, sruns.theta[j], j)         # the problem, θ and run of the result
        if opts.scale_profile and par.mode in ("full", "diag") and np.isfinite(res.chi2):
            res, prof, at = yield from _scale_profile(ss, j, sruns.theta[j], res, prior, opts, n_kit, chunk)
            res.moment_unknown_samples = sm.samples_in(t, action.unknown_intervals)
        if opts.field_error_degree is not None and np.isfinite(res.chi2):
            res = field_error.apply(at[0], at[1], prior, res, int(opts.field_error_degree), run=at[2],
                                    soft_iron_sigma=opts.soft_iron_sigma, robust=opts.robust_cov)
            if chunk is not None:
                yield
        if prof is not None:
            res = dataclasses.replace(res, cov_p=profile.widened_cov(res.p, res.cov_p, prof))
        out.append(res)
    return out


def _scale_profile(ss: SingleShooting, j: int, theta: np.ndarray, res: FitResult, prior: Prior,
                   opts: FitOptions, n_kit: int, chunk: int | None):
    """The profile of run `j` of the whole record's problem `ss` at its minimum `theta` (result `res`):
    one run per factor of `opts.scale_profile` with Ixx held there (`profile`). A point below the minimum
    is a better fit: the fit continues from it and the profile is taken about that one. Returns (the
    result, its ScaleProfile, (the problem, θ and run the result is at))."""
    par = ss.inertia
    k = np.asarray(opts.scale_profile, float)
    K = len(k)
    pk = ss.replicated(j, K)
    starts = np.repeat(theta[None], K, 0)
    starts[:, :par.n_tensor] *= k[:, None]
    frozen = np.zeros(pk.n_params, bool)
    frozen[0] = True                                     # θ_I[0] = Ixx / I_ref in modes full and diag
    pruns = LMRuns(starts)
    yield from lm_steps(pk, pruns, prior, opts.ss_iter, frozen=frozen, chunk=chunk)
    ixx = pk.inertia.to_p(pruns.theta[:, :par.n], np.zeros(K, int))[:, 0]
    cost = pruns.cost.copy()
    cost_min = float(res.chi2 + prior.cost(theta))
    at = (ss, theta, j)
    i = int(np.argmin(np.where(np.isfinite(cost), cost, np.inf)))
    if cost[i] < cost_min - res.s2:                      # a better fit than the minimum: go on from it
        better = LMRuns(pruns.theta[i:i + 1].copy())
        yield from lm_steps(pk, better, prior, opts.ss_iter, chunk=chunk)
        new = results(pk, better, prior, n_kit)[0]
        new_cost = float(new.chi2 + prior.cost(better.theta[0]))
        if np.isfinite(new_cost) and new_cost < cost_min:
            ixx = np.append(np.delete(ixx, i), res.p[0])
            cost = np.append(np.delete(cost, i), cost_min)
            res, cost_min, at = new, new_cost, (pk, better.theta[0].copy(), 0)
    curv = float(inr.half_width(res.cov_p, 0.95)[0]) / float(res.p[0])
    return res, profile.profile_of(ixx, cost, float(res.p[0]), cost_min, res.s2, curv), at


def scale_starts(par: InertiaParam, opts: FitOptions) -> tuple:
    """The factors of `FitOptions.scale_starts` where the tensor's parameters scale with it (modes full,
    diag, scale), else none."""
    return tuple(opts.scale_starts) if par.mode in ("full", "diag", "scale") else ()


def _scaled(theta: np.ndarray, par: InertiaParam, k: float) -> np.ndarray:
    """Starts with the tensor scaled by `k` (mode scale fits the inverse of the scale), the rest as is."""
    out = theta.copy()
    out[:, :par.n_tensor] *= (1.0 / k) if par.mode == "scale" else k
    return out


def _distinct_best(run_of: np.ndarray, theta: np.ndarray, cost: np.ndarray, tol: float = 1e-3,
                   margin: float = 100.0, same_cost: float = 0.1) -> np.ndarray:
    """Indices to keep: per run, drop starts that reached the same point as a better one (``theta``
    within ``tol`` in scaled units and cost within ``same_cost``) and starts whose cost exceeds the
    run's best by more than ``margin`` + 50 %."""
    keep = []
    for r in np.unique(run_of):
        idx = np.flatnonzero(run_of == r)
        order = idx[np.argsort(np.where(np.isfinite(cost[idx]), cost[idx], np.inf))]
        best = cost[order[0]]
        kept: list[int] = []
        for i in order:
            if not np.isfinite(cost[i]) or cost[i] > best + margin + 0.5 * abs(best):
                continue
            if any(np.max(np.abs(theta[i] - theta[j])) < tol and abs(cost[i] - cost[j]) < same_cost
                   for j in kept):
                continue
            kept.append(i)
        keep.extend(kept or [order[0]])
    return np.array(sorted(keep))


def _turned(ms: "MultipleShooting", theta: np.ndarray, cand: np.ndarray, t: np.ndarray,
            b_samples: np.ndarray, vrun: np.ndarray) -> tuple["MultipleShooting", np.ndarray]:
    """Copies of a multiple-shooting problem, one per (run, candidate): candidate (α, Ω) turns every
    segment's attitude about its own field direction B̂_I(t_g) by α + Ω·(t_g − t_mid) and adds Ω B̂
    (body axes) to its rate — what one sample per segment cannot see: α turns the chain about the
    field, Ω winds it.
    ``cand`` (R, C, 2) in rad and rad/s; virtual run v = r·C + c."""
    R, C, _ = cand.shape
    n_I, G = ms.inertia.n, ms.G
    a = b_samples[ms.bounds[:-1]]
    a = a / np.linalg.norm(a, axis=1, keepdims=True)              # B̂_I at each segment start
    tg = t[ms.bounds[:-1]] - t[ms.bounds[G // 2]]
    q_new = np.zeros((R * C, G, 4))
    th = np.repeat(theta, C, axis=0)
    for r in range(R):
        own = theta[r, n_I:n_I + 6 * G].reshape(G, 6)
        qg = quat_mul(ms.q_ref[r], quat_exp(own[:, 3:]))
        for j in range(C):
            alpha, om = cand[r, j]
            v = r * C + j
            q_new[v] = quat_mul(quat_exp((alpha + om * tg)[:, None] * a), qg)
            o = own.copy()
            o[:, :3] += om * np.einsum("gij,gj->gi", quat_to_dcm(q_new[v]).swapaxes(1, 2), a) / ms.omega_scale
            o[:, 3:] = 0.0
            th[v, n_I:n_I + 6 * G] = o.ravel()
    par = ms.inertia
    parw = par.subset(vrun)
    msw = MultipleShooting(ms.t, ms.b_meas[vrun], b_samples, ms.action, ms.b_inertial, parw, ms.bounds, q_new,
                           ms.sigma, fit_bias=ms.fit_bias, omega_scale=ms.omega_scale, h_max_s=ms.h_max_s,
                           fd_step=ms.step, sigma_q_rad=ms.sigma_q, sigma_w_radps=ms.sigma_w)
    return msw, th


def _ss_windows(n: int, first: int, growth: float) -> list[int]:
    out = [min(n, max(first, 10))]
    while out[-1] < n:
        out.append(min(n, int(math.ceil(out[-1] * growth))))
    return out


def fit_prior(P: int, n_I: int, th_I0: np.ndarray, opts: FitOptions, sigma_b_T: float,
              par: InertiaParam, errors_sigma_T: np.ndarray | None = None) -> Prior:
    """The fit's prior on θ (P parameters, the first n_I dynamic): the tensor part about its guess
    ``th_I0`` (1-σ ``opts.inertia_prior_rel``), the unknown moments free unless ``par`` gives their 1-σ,
    the offset with 1-σ ``opts.bias_sigma_T`` and the error terms that follow it (the last of θ) with
    ``errors_sigma_T`` [T]; none on the initial states."""
    mean = np.zeros(P)
    sig = np.full(P, np.inf)
    mean[:n_I] = th_I0
    rel = opts.inertia_prior_rel
    nt = par.n_tensor
    sig[:nt] = rel if par.mode != "scale" else rel * max(abs(th_I0[0]), 1.0)
    for k, s in enumerate(par.moment_sigma_Nm):                  # the unknown moments: free unless given
        sig[nt + 3 * k:nt + 3 * k + 3] = np.asarray(s, float) / par.moment_scale_Nm
    m = 0 if errors_sigma_T is None else len(errors_sigma_T)
    if opts.fit_bias:
        sig[P - m - 3:P - m] = opts.bias_sigma_T / sigma_b_T
    if m:
        sig[P - m:] = np.asarray(errors_sigma_T, float) / sigma_b_T
    return Prior(mean, sig)


def results(ss: SingleShooting, runs: LMRuns, prior: Prior | None, n_kit: int = 0) -> list[FitResult]:
    """FitResults of single-shooting runs: tensor, covariance s²(JᵀJ + prior)⁻¹ with s² = χ²/dof."""
    par = ss.inertia
    n_I = par.n
    R, P = runs.theta.shape
    w2 = prior.w ** 2 if prior is not None else np.zeros(P)
    inv = runs.A.inverse(np.broadcast_to(w2, (R, P)))
    out = []
    for r in range(R):
        s2 = runs.data_cost[r] / max(runs.dof, 1)
        cov = s2 * inv[r]
        T = par.jacobian(runs.theta[r, :n_I], r)
        p = par.to_p(runs.theta[r:r + 1, :n_I], np.array([r]))[0]
        pp, q0, w0, bias = ss.unpack(runs.theta[r:r + 1], np.array([r]))
        mom, cov_m = par.moments_of(runs.theta[r, :n_I], cov[:n_I, :n_I]) if par.n_moments else (None, None)
        out.append(FitResult(p, T @ cov[:n_I, :n_I] @ T.T, w0[0], q0[0], bias[0], float(runs.data_cost[r]),
                             runs.dof, ss.n, int(runs.iterations[r]), bool(runs.converged[r]), par.mode,
                             runs.theta[r].copy(), cov, par.unknown_intervals, par.moment_sigma_Nm, mom, cov_m,
                             errors=ss.error_terms(runs.theta[r], cov, n_kit)))
    return out


def single_shooting_for(t_s: np.ndarray, b_meas: np.ndarray, b_inertial: FieldFn, action: KnownAction,
                        sigma_b_T: float, result: FitResult, opts: FitOptions | None = None, *,
                        n: int | None = None, b_samples: np.ndarray | None = None,
                        p_shape: np.ndarray | None = None) -> tuple[SingleShooting, np.ndarray]:
    """The single-shooting problem of one run (``b_meas`` (n, 3)) and the θ of ``result`` in it."""
    opts = opts or FitOptions(mode=result.mode)
    t = np.asarray(t_s, float)
    if b_samples is None:
        b_samples = np.asarray(b_inertial(t), float).reshape(-1, 3)
    p_ref = result.p if p_shape is None else np.asarray(p_shape, float)
    par = InertiaParam(result.mode, float(np.mean(p_ref[:3])) if result.mode != "shape" else float(result.p[0]),
                       None if p_shape is None else np.atleast_2d(p_shape), result.unknown_intervals,
                       result.moment_sigma_Nm)
    cols = error_columns(t, action, opts)[0]
    ss = SingleShooting(t, np.asarray(b_meas, float)[None], b_samples, action, b_inertial, par,
                        result.q0[None], sigma_b_T, n=n, fit_bias=opts.fit_bias, omega_scale=opts.omega_scale,
                        h_max_s=opts.h_max_s, error_columns=cols)
    theta = np.zeros(ss.n_params)
    theta[:par.n] = par.from_p(result.p, moments_Nm=result.moments_Nm)
    theta[par.n:par.n + 3] = result.omega0_radps / opts.omega_scale
    if opts.fit_bias:
        theta[par.n + 6:par.n + 9] = result.bias_T / sigma_b_T
    if len(cols) and len(result.theta) == ss.n_params:
        theta[ss.error_index:] = result.theta[ss.error_index:]
    return ss, theta


def trajectory(t_s: np.ndarray, b_meas: np.ndarray, b_inertial: FieldFn, action: KnownAction,
               sigma_b_T: float, result: FitResult, opts: FitOptions | None = None, *,
               p_shape: np.ndarray | None = None) -> dict:
    """The fitted motion at the samples: ``b_body_T`` (predicted field), ``q``, ``omega_radps``."""
    ss, theta = single_shooting_for(t_s, b_meas, b_inertial, action, sigma_b_T, result, opts, p_shape=p_shape)
    return ss.trajectory(theta)


def prefix_fits(t_s: np.ndarray, b_meas: np.ndarray, b_inertial: FieldFn, action: KnownAction,
                sigma_b_T: float, final: FitResult, lengths: list[int], p_guess: np.ndarray,
                opts: FitOptions | None = None, *, b_samples: np.ndarray | None = None) -> list[FitResult]:
    """The running estimate: the fit of the first n samples for each n in ``lengths`` (one run,
    ``b_meas`` (n, 3)), each warm-started from the fit of the whole record, which puts it in the right
    basin. A short prefix (before any torque) leaves the scale to the weak prior: its band is wide."""
    opts = opts or FitOptions(mode=final.mode)
    t = np.asarray(t_s, float)
    if b_samples is None:
        b_samples = np.asarray(b_inertial(t), float).reshape(-1, 3)
    _, cols_sigma, n_kit = error_columns(t, action, opts)
    out = []
    for n in lengths:
        ss, theta = single_shooting_for(t, b_meas, b_inertial, action, sigma_b_T, final, opts, n=int(n),
                                        b_samples=b_samples)
        th_I0 = ss.inertia.from_p(np.asarray(p_guess, float))
        prior = fit_prior(ss.n_params, ss.inertia.n, th_I0, opts, sigma_b_T, ss.inertia, cols_sigma)
        runs = lm(ss, LMRuns(theta[None].copy()), prior, opts.ss_iter)
        out.append(results(ss, runs, prior, n_kit)[0])
    return out
