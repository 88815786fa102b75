"""Ground smoothers of the body rate: every sample of a recording informs every estimate.

Two models, both on the attitude filter of the flight software (fsw/estimation/attitude_kalman.py), with the
field model along the orbit when one is given (which removes the field-motion floor) and the field
fixed in inertial space otherwise (laboratory recordings):

- :func:`rts_smooth` — fixed-interval Rauch–Tung–Striebel smoother (Rauch, Tung & Striebel 1965;
  Bar-Shalom et al. 2001 §8.6) over the multiplicative EKF with ω a random walk. Works for any
  motion; the strength of the random walk (κ, the scale of the torque-free |ω̇| ≤ κ|ω|²) is chosen by
  maximum likelihood over a small grid, the pass is repeated from the smoothed start
  (re-linearisation), and with a field model the passes from several initial angles about B are
  combined as a Gaussian sum (`ground.angle_sum`: the samples barely fix that angle).
- :func:`euler_fit` — output-error fit of the torque-free Euler equations and the kinematics to the
  whole record (batch nonlinear least squares, Gauss–Newton / Levenberg–Marquardt): parameters are
  the attitude and rate at the first sample, the inertia shape ln(J₂/J₁), ln(J₃/J₁) (torque-free
  motion depends only on the ratios) or a known tensor, and, with no field model, the inertial field.
  Residual Jacobians come from the error-state transition matrices of the same propagation; the
  record is brought in over growing windows (continuation), so that a rate known only roughly at
  first never has to be extrapolated far. 1-σ from s²(JᵀJ)⁻¹ mapped through the transition matrices,
  widened by the spread between the fit's near-equivalent minima.
  An asymmetric tumbling body has ω varying in body axes; a random walk then lags, this model does not.
- :func:`smooth` — both, and the Euler fit kept when it explains the data (χ²/dof ≤ `chi2_accept`) and
  agrees with the Euler RTS smoother within their combined σ (:func:`auto_choice`).

The rule of "auto" (:func:`auto_result`): it never returns a solution that another solution's σ
excludes. The candidates are the batch Euler fit, the Euler RTS smoother and the random-walk RTS
smoother; one excludes another when the other lies more than 3 of its σ away on some axis at more than
a quarter of the samples (:func:`excludes`); only the candidates that explain the data judge (χ²/dof
≤ 1.5; the random-walk smoother always, it assumes least; a batch fit already rejected as in a wrong
minimum does not). The first of the order Euler fit → Euler RTS →
random walk that no judge excludes is returned; when each is excluded by another (they disagree beyond
their σ and the data do not say which is right), the first is returned with its σ widened to cover
the others (:func:`covering`). Without a field model the ground tool then widens every σ by the field's
own turning (`fsw.estimation.rate_formulas.widen_for_field_turn`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from fsw.estimation import attitude_kalman as ak
from fsw.estimation import filter_banks as fb
from fsw.estimation.rate_formulas import unobserved_sigma
from fsw.estimation import rate_kalman as rk
from fsw.estimation import rotations as rot
from ground import angle_sum
from ground import euler_trajectory as et
from ground import rts_pass

FieldFn = Callable[[float], np.ndarray]
SHAPE_SIGMA_FLOOR = 0.01  # 1-σ floor of ln(J₂/J₁), ln(J₃/J₁) carried into the Euler RTS smoother
#: other minima of the batch fit: polished when within MODE_SEARCH_DCHI2 of the best after their first
#: iterations, kept in σ (weight e^(−Δχ²/2)) when within MODE_KEEP_DCHI2 after polishing
MODE_SEARCH_DCHI2, MODE_KEEP_DCHI2 = 30.0, 20.0


@dataclass
class Smoothed:
    """A smoothed rate history: ω and 1-σ per sample (rad/s), the attitude (body → ECI, or → the first
    sample's body axes with no field model), and what the model says about itself."""

    t_s: np.ndarray
    w_radps: np.ndarray
    sigma_radps: np.ndarray
    q: np.ndarray
    method: str
    chi2_dof: float = math.nan
    inertia_shape: np.ndarray | None = None
    info: dict = field(default_factory=dict)


def tabulated(field_eci_T: FieldFn | None, t_s: np.ndarray) -> FieldFn | None:
    """The field model evaluated once at the sample times (vectorised when it allows), served from a
    table at those times and by the model elsewhere."""
    if field_eci_T is None:
        return None
    t = np.asarray(t_s, float)
    try:
        values = np.asarray(field_eci_T(t), float).reshape(len(t), 3)
    except (TypeError, ValueError):
        values = np.array([np.asarray(field_eci_T(x), float) for x in t])
    table = {float(x): v for x, v in zip(t, values)}

    def field(t_query: float) -> np.ndarray:
        v = table.get(float(t_query))
        return v if v is not None else np.asarray(field_eci_T(t_query), float)
    field.at_samples = (t, values)  # the compiled propagation reads it whole
    return field


# --- RTS over the attitude filter ------------------------------------------------------------------

def rts(log: dict, n_att: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rauch–Tung–Striebel backward pass over a stored :class:`AttitudeRateKalman` pass.

    C_k = P_k Φ_{k+1}ᵀ (P⁻_{k+1})⁻¹;  δ_{k+1} = x^s_{k+1} ⊖ x⁻_{k+1} (attitude part: the body-frame
    rotation vector of q⁻⁻¹ ⊗ q^s);  x^s_k = x_k ⊕ C_k δ_{k+1};  P^s_k = P_k + C_k (P^s_{k+1} − P⁻_{k+1}) C_kᵀ.
    Returns the smoothed attitudes (N, 4), additive states (N, m) and covariances (N, n, n). Where the
    filter restarted (a gap, a divergence) the pass does not link the two sides.
    """
    q_f, x_f, P_f = (np.array(log[k], float) for k in ("q", "x", "P"))
    q_p, x_p, P_p, F = (np.array(log[k], float) for k in ("qp", "xp", "Pp", "F"))
    N = len(q_f)
    # where the filter started afresh at k + 1, nothing links the two stretches
    restart = np.array(log.get("restart", [False] * N), bool)
    return rts_pass.backward(q_f, x_f, P_f, q_p, x_p, P_p, F, restart, n_att)  # compiled


def variance_scale(log: dict, skip: int = 10) -> float:
    """Variance of unit weight of a filter pass from its normalised innovations (NIS, 3 per sample):
    ĉ = Σ yᵀS⁻¹y / (3 n) over the samples at least `skip` after a (re)start, where the prior still
    dominates. For a linear-Gaussian model with every covariance (P₀, Q, R) scaled by c, ĉ is the
    maximum-likelihood c (Bar-Shalom et al. 2001 §5.4, the filter's χ² consistency test); the
    smoothed covariance scales by it too. Returns max(1, ĉ): the noise levels are known or fitted
    at least as large, a smaller ĉ is the samples' scatter, not a reason to trust the model more."""
    nis = np.asarray(log.get("nis", []), float)
    restart = np.asarray(log.get("restart", [False] * len(nis)), bool)[:len(nis)]
    since = np.zeros(len(nis), int)
    c = skip
    for k in range(len(nis)):
        c = 0 if restart[k] else c + 1
        since[k] = c
    use = (since >= skip) & np.isfinite(nis)
    if use.sum() < 3:
        return 1.0
    return max(1.0, float(np.mean(nis[use])) / 3.0)


def _forward(t, b, sigma_b_T, field_eci_T, noise, angle, start=None, store=False):
    """One pass of the random-walk attitude filter over (t, b) from `start` (or the first sample);
    `noise` = (κ, rate floor [rad/s²], factor on σ_B, Gauss–Markov time of ω [s], ∞ for a random walk)."""
    kappa, accel, sfac, tau = noise
    kf = ak.AttitudeRateKalman(sigma_b_T * sfac, field_eci_T=field_eci_T,
                               tuning=ak.AttitudeKalmanTuning(kappa=kappa, rate_accel_radps2=accel, adapt_max=1.0,
                                                              rate_tau_s=tau),
                               angle_about_b_rad=angle, store=store)
    return rts_pass.forward(kf, t, b, start or {})  # compiled (the filter's own updates where it cannot be)


def _reversed(t, b, field_eci_T):
    """The record in reversed time τ = −t: the body turns at −ω, the field is B_I(−τ)."""
    fld = None if field_eci_T is None else (lambda tau: field_eci_T(-tau))
    return -t[::-1], b[::-1], fld


def rts_smooth(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
               kappas: tuple[float, ...] = (0.03, 0.1, 0.3, 0.6),
               accels_radps2: tuple[float, ...] = (1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0),
               sigma_factors: tuple[float, ...] = (1.0, 3.0),
               rate_taus_s: tuple[float, ...] = (math.inf, 300.0, 100.0, 30.0, 10.0), angles: int = 6) -> Smoothed:
    """RTS smoother with ω a random walk, or a first-order Gauss–Markov process (ω̇ = −ω/τ + w) for a
    motion bounded about zero such as a libration, whichever the likelihood prefers.

    The pass is linearised where the filter has converged: first a filter runs backwards in time (τ = −t,
    the body turning at −ω) and its end state at t₀ — which has seen the whole record — becomes the
    start of the forward filter, its covariance inflated tenfold (so that the samples it has seen count
    only a tenth again); the RTS pass then runs over that forward filter. The random walk's strength
    (κ for the torque-free part, a floor for other torques: 10⁻⁴ rad/s² for a tumbling body up to
    100 rad/s² for a hand-held sensor), a factor on σ_B (a field that is not quite uniform, a sensor
    not quite calibrated), the Gauss–Markov time τ (∞: the random walk) and, with a field model, the
    starting angle about B are chosen by maximum likelihood on the backward pass (a search over the
    grids: the floor and τ jointly, then κ and the factor, then the floor and τ again). A finite τ matters where
    the samples say little about ω along B (a slow motion:
    B barely turns in the body): that component then falls back to zero with the process's stationary
    spread instead of wandering off.

    With a field model the attitude about B is weakly fixed (by the field's slow turning only): the
    smoothed pass is run from each of the `angles` starting angles and the passes are combined as a
    Gaussian sum weighted by their likelihoods (`ground.angle_sum`): ω the mixture's mean, σ its spread
    with each pass's own; q, χ², `angle_about_b_rad` and ``info["w_pass_radps"]`` are those of the pass
    from the angle the backward search chose (an attitude and a rate that belong together: the batch
    fit starts from them).
    """
    t = np.asarray(t_s, float)
    b = np.asarray(b_T, float)
    field_eci_T = tabulated(field_eci_T, t)
    tr, br, fr = _reversed(t, b, field_eci_T)
    mid = (kappas[len(kappas) // 2], accels_radps2[min(2, len(accels_radps2) - 1)], sigma_factors[0], rate_taus_s[0])
    angle = 0.0
    if fr is not None:
        angle = min((2 * math.pi * a / angles for a in range(angles)),
                    key=lambda g: _forward(tr, br, sigma_b_T, fr, mid, g).nll)
    # search: the floor and the Gauss–Markov time together (the stationary spread a√(τ/2) couples them,
    # and one at a time sticks: a random walk at 10⁻² rad/s² can beat every τ at that floor while
    # τ = 10 s at the same floor beats both), then κ, the measurement-noise factor, and the pair again
    runs = {}

    def nll(n):
        if n not in runs:
            runs[n] = _forward(tr, br, sigma_b_T, fr, n, angle)
        return runs[n].nll

    noise = mid
    for axes, values in (((1, 3), [(a, tau) for a in accels_radps2 for tau in rate_taus_s]),
                         ((0,), [(k,) for k in kappas]), ((2,), [(f,) for f in sigma_factors]),
                         ((1, 3), [(a, tau) for a in accels_radps2 for tau in rate_taus_s])):
        def with_(v, noise=noise, axes=axes):
            n = list(noise)
            for i, x in zip(axes, v):
                n[i] = x
            return tuple(n)
        noise = min((with_(v) for v in values), key=nll)
    if fr is None:
        kf, q_s, x_s, P_s = _smoothed_pass(t, b, sigma_b_T, field_eci_T, noise, runs[noise], angle)
        c = variance_scale(kf.log)
        sig = np.sqrt(c * np.clip(np.einsum("kii->ki", P_s[:, 3:6, 3:6]), 0.0, None))
        w_s, mix = x_s[:, :3].copy(), {}
    else:  # every starting angle about B, as a Gaussian sum (ground.angle_sum)
        passes = [_smoothed_pass(t, b, sigma_b_T, field_eci_T, noise, runs[noise] if g == angle else
                                 _forward(tr, br, sigma_b_T, fr, noise, g), g)
                  for g in (2 * math.pi * a / angles for a in range(angles))]
        # the pass from the angle the backward search chose (as before the sum): its attitude and rate
        # belong together, and the batch fit starts from them
        kf, q_s, x_s, P_s = next(p for p in passes if p[0].angle_about_b_rad == angle)
        c = variance_scale(kf.log)
        w_s, var, wt = angle_sum.mixture([p[0].nll for p in passes], [p[2][:, :3] for p in passes],
                                         [c * np.einsum("kii->ki", p[3][:, 3:6, 3:6]) for p in passes],
                                         angle_sum.pass_temper(c))
        sig = np.sqrt(var)
        mix = {"angle_weights": wt[:, 0].tolist(), "w_pass_radps": x_s[:, :3].copy()}
    chi2 = _chi2(t, b, sigma_b_T * noise[2], q_s, x_s, field_eci_T)
    return Smoothed(t, w_s, unobserved_sigma(sig, b, sigma_b_T), q_s, "smoother",
                    chi2 / max(3 * len(t) - 6, 1), info={"kappa": noise[0], "rate_accel_radps2": noise[1],
                                                          "sigma_factor": noise[2], "rate_tau_s": noise[3],
                                                          "angle_about_b_rad": angle,
                                                          "nll": kf.nll, "variance_scale": c, **mix})


def _smoothed_pass(t, b, sigma_b_T, field_eci_T, noise, back, angle):
    """The forward filter started from a backward pass's end at t₀ and its RTS pass: (filter, q, x, P).
    The backward estimate's covariance (block-diagonal, the reversed rate's sign irrelevant there) is
    inflated tenfold, so that the samples it has seen weigh only a tenth again."""
    P0 = np.zeros_like(back.P)
    for blk in (slice(0, 3), slice(3, 6), slice(6, back.n)):
        P0[blk, blk] = 10.0 * back.P[blk, blk]
    start = {"q": back.q, "omega_radps": -back.w, "P": P0}
    if field_eci_T is None:
        start["beta_uT"] = back.beta
    kf = _forward(t, b, sigma_b_T, field_eci_T, noise, angle, start=start, store=True)
    return (kf, *rts(kf.log))


def _chi2(t, b, sigma_b_T, q, x, field_eci_T) -> float:
    """Σ |z − h|² / σ² of a smoothed trajectory."""
    total = 0.0
    for k in range(len(t)):
        C = rot.quat_to_dcm(q[k])
        b_i = np.asarray(field_eci_T(t[k]), float) if field_eci_T is not None else x[k, -3:] / rk.UT_PER_T
        r = b[k] - C.T @ b_i
        total += float(r @ r)
    return total / sigma_b_T ** 2


# --- batch output-error fit of the torque-free motion ----------------------------------------------

@dataclass
class _Trajectory:
    q: np.ndarray          # (N, 4) nominal attitudes
    w: np.ndarray          # (N, 3)
    Phi: np.ndarray        # (N, n, n) transition from the first sample
    r: np.ndarray          # (N, 3) residuals / σ
    Jr: np.ndarray         # (N, 3, n) ∂r/∂δx₀


def _trajectory(kf: ak.AttitudeRateKalman, t, z_uT, sb_uT, n, jacobian: bool = True) -> _Trajectory:
    """Propagate the filter's nominal state (no updates, torque-free Euler) across the first n samples,
    compiled (:func:`ground.euler_trajectory.trajectory`; the filter's own propagation is its reference in
    tests/ground/test_euler_trajectory.py). Without `jacobian` only q, ω and r (Φ and Jr empty: an LM
    trial's cost)."""
    if not kf.euler or kf.torque is not None:
        raise NotImplementedError("the batch fit's propagation is torque-free Euler")
    if not np.all(np.abs(kf.p) < _LN_RATIO_MAX):  # NaN too; beyond, a ratio is 0 or inf in floating point
        raise ValueError("non-finite state")
    if kf.J is not None:
        mode, j2, j3, J, K = et.TENSOR, 1.0, 1.0, kf.J.ravel().copy(), kf.J_inv.ravel().copy()
    else:
        mode, j2, j3, J, K = et.SHAPE, math.exp(kf.p[0]), math.exp(kf.p[1]), _NO_TENSOR, _NO_TENSOR
    b_i = _NO_FIELD if kf.field is None else _field_at_samples(kf.field, t, n)
    tun = kf.tuning
    Q, W, Phi, r, Jr, ok = et.trajectory(np.asarray(kf.q, float), np.asarray(kf.w, float), mode, j2, j3, J, K,
                                         int(kf.n_p), np.asarray(kf.beta, float), b_i,
                                         np.ascontiguousarray(t, dtype=float),
                                         np.ascontiguousarray(z_uT, dtype=float), float(sb_uT), int(n),
                                         float(tun.max_substep_rad), int(tun.max_substeps), jacobian)
    if not ok:
        raise ValueError("non-finite state")
    return _Trajectory(Q, W, Phi, r, Jr)


#: |ln J₂/J₁|, |ln J₃/J₁| beyond which exp() is 0 or overflows (an LM trial may step there)
_LN_RATIO_MAX = 700.0
_NO_FIELD = np.zeros((0, 3))
_NO_TENSOR = np.zeros(9)


def _field_at_samples(field_eci_T: FieldFn, t: np.ndarray, n: int) -> np.ndarray:
    """B_I (µT) at the first n samples: the table of :func:`tabulated` when it holds these times."""
    table = getattr(field_eci_T, "at_samples", None)
    if table is not None and len(table[0]) >= n and (table[0] is t or np.array_equal(table[0][:n], t[:n])):
        values = table[1][:n]
    else:
        values = np.array([np.asarray(field_eci_T(x), float) for x in t[:n]]).reshape(n, 3)
    return np.ascontiguousarray(values * rk.UT_PER_T)


def euler_fit(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
              inertia_kgm2: np.ndarray | None = None, init: Smoothed | None = None,
              first_window: int = 8, growth: float = 1.4, iterations: int = 10, starts_about_b: int = 24,
              wahba_rounds: int = 2,
              max_substep_rad: float = 0.25) -> Smoothed:
    """Torque-free Euler + kinematics fitted to the whole record: :func:`_euler_minimum`, then the other minima
    as good in σ (:meth:`_Minimum.finish`)."""
    return _euler_minimum(t_s, b_T, sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2, init=init,
                          first_window=first_window, growth=growth, iterations=iterations,
                          starts_about_b=starts_about_b, wahba_rounds=wahba_rounds,
                          max_substep_rad=max_substep_rad).finish()


def _euler_minimum(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
                   inertia_kgm2: np.ndarray | None = None, init: Smoothed | None = None,
                   first_window: int = 8, growth: float = 1.4, iterations: int = 10, starts_about_b: int = 24,
                   wahba_rounds: int = 2, max_substep_rad: float = 0.25) -> "_Minimum":
    """Torque-free Euler + kinematics fitted to the whole record (see the module docstring).

    `init` gives the starting attitude and rate (default: :func:`rts_smooth`). With a field model the
    attitude about B is fixed only by the field's slow turning and the cost has several minima in
    that angle: after the growing windows the whole record is fitted from `starts_about_b` angles
    about B_I(t₀) (a few iterations each), the best is polished, then the attitude at t₀ is solved
    globally for the fitted relative motion (Wahba's problem, :func:`_wahba_start`) and the record
    fitted again from there while that lowers the cost.

    1-σ: the posterior can have several modes as good as the best within a few units of χ² (another
    attitude about B with a slightly different motion: truths 60–100° away in attitude and 0.1–0.2 °/s
    in ω, a Mahalanobis distance of thousands in the best minimum's own covariance). Every other start
    that ends within `MODE_SEARCH_DCHI2` is polished; the distinct minima within `MODE_KEEP_DCHI2` are
    weighted by e^(−Δχ²/2s²) and σ² is the mixture's second moment about the best: Σ wᵢ (σᵢ² +
    (ωᵢ − ω̂)²). The estimate stays the best minimum's.
    """
    t = np.asarray(t_s, float)
    b = np.asarray(b_T, float)
    N = len(t)
    field_eci_T = tabulated(field_eci_T, t)
    init = init or rts_smooth(t, b, sigma_b_T, field_eci_T=field_eci_T)
    tun = ak.AttitudeKalmanTuning(max_substep_rad=max_substep_rad, max_substeps=400)

    def filt():
        return ak.AttitudeRateKalman(sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2,
                                     estimate_inertia=inertia_kgm2 is None, tuning=tun)

    kf = filt()
    if field_eci_T is None:  # the first sample's body axes are the frame; β the field in it
        beta = rot.quat_to_dcm(init.q[0]) @ (b[0] * rk.UT_PER_T)
        kf.set_nominal(t[0], np.array([1.0, 0.0, 0.0, 0.0]), init.w_radps[0], beta_uT=beta, euler=True)
    else:
        kf.set_nominal(t[0], init.q[0], init.info.get("w_pass_radps", init.w_radps)[0], euler=True)
    z = b * rk.UT_PER_T
    sb = sigma_b_T * rk.UT_PER_T
    nn = kf.n
    free = np.ones(nn, bool)
    if field_eci_T is None:
        free[:3] = False  # δθ₀ is the gauge
    prior_w = np.zeros(nn)
    prior_w[6:6 + kf.n_p] = 1.0  # weak prior on the shape: 1-σ of a factor e
    windows = []
    n = min(N, max(first_window, 5))
    while True:
        windows.append(n)
        if n >= N:
            break
        n = min(N, int(math.ceil(n * growth)))
    # rate and shape over growing windows, then the angle about B over the whole record: the angle is
    # fixed only by the field's slow turning, so short windows cannot choose it and the cost has
    # several minima in it
    for n in windows:
        kf, cost = _lm(kf, t, z, sb, n, free, prior_w, iterations)
    cands = [(kf, cost)]
    if field_eci_T is not None:
        b_i0 = np.asarray(field_eci_T(t[0]), float)
        axis = b_i0 / np.linalg.norm(b_i0)
        for a in range(1, starts_about_b):
            other = _apply(kf, np.zeros(int(free.sum())), free)
            other.q = rot.quat_mul(rot.quat_exp(axis * (2 * math.pi * a / starts_about_b)), kf.q)
            cands.append(_lm(other, t, z, sb, N, free, prior_w, 3))
        cands.sort(key=lambda kc: kc[1])
        kf, cost = _lm(cands[0][0], t, z, sb, N, free, prior_w, iterations)
        for _ in range(wahba_rounds):
            other = _apply(kf, np.zeros(int(free.sum())), free)
            other.q = _wahba_start(kf, t, z, field_eci_T, N)
            other, c = _lm(other, t, z, sb, N, free, prior_w, iterations)
            if not np.isfinite(c) or c >= cost - 1e-6:
                break
            kf, cost = other, c
        cands.insert(0, (kf, cost))
    cands.sort(key=lambda kc: kc[1])
    return _Minimum(cands, t, z, sb, b, sigma_b_T, N, free, prior_w, windows, iterations)


@dataclass
class _Minimum:
    """The batch fit's best minimum (its χ²/dof final), before the search for other minima as good (which
    widens σ only): :func:`euler_fit_checked` compares two fits by χ²/dof and finishes only the one it keeps."""
    cands: list            # (start, cost) best first
    t: np.ndarray
    z: np.ndarray
    sb: float
    b: np.ndarray
    sigma_b_T: float
    N: int
    free: np.ndarray
    prior_w: np.ndarray
    windows: list
    iterations: int
    chi2_dof: float = math.nan

    def __post_init__(self):
        kf = self.cands[0][0]
        self.local = _local_solution(kf, self.t, self.z, self.sb, self.N, self.free, self.prior_w)
        self.chi2_dof = self.local[3] / max(3 * self.N - int(self.free.sum()), 1)

    def finish(self) -> Smoothed:
        """The fit's result, σ including the other minima as good as the best."""
        t, z, sb, N, free, prior_w, iterations = self.t, self.z, self.sb, self.N, self.free, self.prior_w, \
            self.iterations
        cands = self.cands
        kf, cost = cands[0]
        traj, cov, var, chi2, s2 = self.local
        # other minima as good as this one within a few units of χ² (another attitude about B with a slightly
        # different motion): the posterior has several modes, and the spread between them belongs in σ
        modes = [(0.0, traj.w, var)]
        seen = [kf]  # starts polished, before and after: one that starts where another did ends where it did
        for other, c in cands[1:]:
            if not c - cost < MODE_SEARCH_DCHI2 * s2:
                continue
            if any(_same_start(other, s) for s in seen):
                continue  # its polish would find a minimum already seen (most starts end in the best one)
            seen.append(other)
            other, c = _lm(other, t, z, sb, N, free, prior_w, iterations)
            seen.append(other)
            if not (np.isfinite(c) and c - cost < MODE_KEEP_DCHI2 * s2):
                continue
            o_traj, _, o_var, _, _ = _local_solution(other, t, z, sb, N, free, prior_w, s2)
            if any(np.max(np.abs(o_traj.w - w_m) / np.sqrt(v + 1e-18)) < 0.3 for _, w_m, v in modes):
                continue  # the same minimum again (within a third of its σ)
            modes.append((max(c - cost, 0.0) / s2, o_traj.w, o_var))
        weights = np.exp(-0.5 * np.array([d for d, _, _ in modes]))
        weights /= weights.sum()
        between = sum(wt * (w_m - traj.w) ** 2 for wt, (_, w_m, _) in zip(weights, modes))
        sig = np.sqrt(sum(wt * v for wt, (_, _, v) in zip(weights, modes)) + between)
        shape = kf.inertia_shape if kf.n_p else None
        return Smoothed(t, traj.w, unobserved_sigma(sig, self.b, self.sigma_b_T), traj.q, "euler", self.chi2_dof,
                        shape, info={"s2": s2, "windows": self.windows, "cov_x0": cov, "beta_uT": kf.beta.copy(),
                                     "p": kf.p.copy(), "minima_chi2": [c for _, c in cands],
                                     "modes_dchi2": [d for d, _, _ in modes], "modes_weight": weights.tolist(),
                                     "modes_var_radps2": between})


def _local_solution(kf, t, z, sb, n, free, prior_w, s2: float | None = None):
    """The trajectory at a minimum, its state covariance s²(JᵀJ + W²)⁻¹ at t₀ (s² = max(1, χ²/dof)
    unless given) and the variance of ω at every sample through the transition matrices;
    (trajectory, covariance, ω variances (n, 3), χ², s²)."""
    nn = kf.n
    traj = _trajectory(kf, t, z, sb, n)
    A = traj.Jr.reshape(-1, nn)[:, free]
    r = traj.r.reshape(-1)
    chi2 = float(r @ r)
    if s2 is None:
        s2 = max(1.0, chi2 / max(r.size - int(free.sum()), 1))
    cov = np.zeros((nn, nn))
    cov[np.ix_(free, free)] = s2 * np.linalg.pinv(A.T @ A + np.diag(prior_w[free] ** 2))
    Pw = traj.Phi[:, 3:6, :] @ cov @ traj.Phi[:, 3:6, :].transpose(0, 2, 1)
    return traj, cov, np.clip(np.einsum("kii->ki", Pw), 0.0, None), chi2, s2


def euler_fit_from_filter(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *,
                          field_eci_T: FieldFn | None = None) -> Smoothed | None:
    """:func:`_minimum_from_filter`, finished (the other minima as good in σ); None where it gives none."""
    m = _minimum_from_filter(t_s, b_T, sigma_b_T, field_eci_T=field_eci_T)
    return None if m is None else m.finish()


def _minimum_from_filter(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *,
                         field_eci_T: FieldFn | None = None) -> "_Reversed | None":
    """The batch fit of :func:`euler_fit` started from where the parallel-hypothesis Euler filter
    (:class:`fsw.estimation.filter_banks.EulerAcquisitionKalman`) ends, for the records where the random-walk
    start leads the fit astray (a 3 s step at 15–28 °/s: the random-walk smoother lags the turning ω).
    The filter's estimate is good at the record's end, not at its start, so the fit runs in reversed
    time: t' = t_N − t, ω'(t') = −ω(t_N − t'), the same attitudes in reverse order; torque-free Euler
    and the kinematics are the same equations in t' (J ω̇' = −ω' × Jω', q̇' = ½ q' ⊗ ω'). The result
    is mapped back. None when the filter did not lock on Euler's equations or a field model is missing
    (without one the attitude's gauge is the first sample's)."""
    if field_eci_T is None:
        return None
    t = np.asarray(t_s, float)
    b = np.asarray(b_T, float)
    kf = fb.EulerAcquisitionKalman(sigma_b_T, field_eci_T=field_eci_T)
    with np.errstate(all="ignore"):  # a wrong hypothesis may diverge: the filter drops it
        for k in range(len(t)):
            kf.update(t[k], b[k])
    if not kf.euler or kf.flags & rk.NO_ESTIMATE:
        return None
    t_end = float(t[-1])
    tr = t_end - t[::-1]
    n = len(t)
    init = Smoothed(tr, np.tile(-kf.omega_radps, (n, 1)), np.tile(kf.sigma_radps, (n, 1)),
                    np.tile(kf.main.q, (n, 1)), "euler_acquisition")
    rev = _euler_minimum(tr, b[::-1], sigma_b_T, field_eci_T=lambda s: field_eci_T(t_end - s), init=init)
    return _Reversed(rev, t)


@dataclass
class _Reversed:
    """A minimum of the fit in reversed time, finished and mapped back to forward time."""
    rev: "_Minimum"
    t: np.ndarray

    @property
    def chi2_dof(self) -> float:
        return self.rev.chi2_dof

    def finish(self) -> Smoothed:
        rev, t = self.rev.finish(), self.t
        return _to_forward_time(rev, t)


def _to_forward_time(rev: Smoothed, t: np.ndarray) -> Smoothed:
    """A reversed-time fit's result in forward time."""
    # the fit's state covariance is at t_N; only the shape's block (time-invariant) holds at t₀
    cov = np.zeros_like(rev.info["cov_x0"])
    cov[6:, 6:] = rev.info["cov_x0"][6:, 6:]
    info = dict(rev.info, reversed=True, cov_x0=cov, modes_var_radps2=rev.info["modes_var_radps2"][::-1].copy())
    return Smoothed(t, -rev.w_radps[::-1].copy(), rev.sigma_radps[::-1].copy(), rev.q[::-1].copy(), "euler",
                    rev.chi2_dof, rev.inertia_shape, info=info)


def euler_fit_checked(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
                      inertia_kgm2: np.ndarray | None = None, init: Smoothed | None = None,
                      chi2_accept: float = 1.5) -> Smoothed:
    """:func:`euler_fit`; when it does not explain the data (χ²/dof > `chi2_accept`) and the tensor is
    not known, again from the Euler filter's end (:func:`euler_fit_from_filter`), keeping the better."""
    # the two fits compared by their best minima's χ²/dof: only the one kept searches for other minima (the
    # search, which widens σ only, polishes every start within 30·s² of the best: all of them on a fit that
    # does not explain the data, most of the cost of the fit)
    eu = _euler_minimum(t_s, b_T, sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2, init=init)
    if inertia_kgm2 is not None or (np.isfinite(eu.chi2_dof) and eu.chi2_dof <= chi2_accept):
        return eu.finish()
    try:
        other = _minimum_from_filter(t_s, b_T, sigma_b_T, field_eci_T=tabulated(field_eci_T, t_s))
        if other is not None and np.isfinite(other.chi2_dof) and not other.chi2_dof >= eu.chi2_dof:
            res = other.finish()
            res.info["first_chi2_dof"] = eu.chi2_dof
            return res
    except (RuntimeError, ValueError, np.linalg.LinAlgError):
        pass
    return eu.finish()


def _wahba_start(kf, t, z, field_eci_T, n) -> np.ndarray:
    """The attitude at t₀ that best explains all samples for the fitted relative motion.

    With R(t_k) = R₀ R_rel,k: min over R₀ of Σ |R₀ R_rel,k z_k − B_I(t_k)|² (Wahba 1965), solved by
    the SVD of Σ B_I,k (R_rel,k z_k)ᵀ (Markley 1988): the global optimum, whatever the angle about B.
    """
    traj_q = _trajectory(kf, t, z, 1.0, n, jacobian=False).q
    C0t = rot.quat_to_dcm(kf.q).T
    Bm = np.zeros((3, 3))
    for k in range(n):
        u = C0t @ (rot.quat_to_dcm(traj_q[k]) @ z[k])
        Bm += np.outer(np.asarray(field_eci_T(t[k]), float), u)
    U, _, Vt = np.linalg.svd(Bm)
    D = np.diag([1.0, 1.0, np.linalg.det(U) * np.linalg.det(Vt)])
    R0 = U @ D @ Vt
    return rot.quat_from_dcm(R0)


def _same_start(a, b, tol_rad: float = 0.02) -> bool:
    d = rot.quat_log(rot.quat_mul(rot.quat_conj(a.q), b.q))
    return float(np.linalg.norm(d)) < tol_rad and float(np.linalg.norm(a.w - b.w)) < 1e-3


def _lm(kf, t, z, sb, n, free, prior_w, iterations, lam: float = 1e-3):
    """Levenberg–Marquardt on the first n samples from the filter's nominal start; (start, cost)."""
    nn = kf.n
    cost = math.inf
    for _ in range(iterations):
        traj = _trajectory(kf, t, z, sb, n)
        A = traj.Jr.reshape(-1, nn)[:, free]
        r = traj.r.reshape(-1)
        cost = float(r @ r) + _prior_cost(kf, prior_w)
        if not np.isfinite(cost):
            return kf, math.inf
        # (AᵀA + W² + λ diag) δ = −(Aᵀr + W² p)
        g = A.T @ r + _prior_grad(kf, prior_w)[free]
        JtJ = A.T @ A + np.diag(prior_w[free] ** 2)
        improved = False
        for _ in range(6):
            step = np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ) + 1e-12), -g)
            trial = _apply(kf, step, free)
            try:
                with np.errstate(invalid="ignore", over="ignore"):  # a step too far: a non-finite cost, refused
                    tr = _trajectory(trial, t, z, sb, n, jacobian=False)
                tc = float(tr.r.reshape(-1) @ tr.r.reshape(-1)) + _prior_cost(trial, prior_w)
            except (ValueError, OverflowError, FloatingPointError):
                tc = math.inf
            if np.isfinite(tc) and tc < cost:
                kf, improved = trial, True
                lam = max(lam / 5.0, 1e-9)
                break
            lam *= 10.0
        if not improved:
            break
        if cost - tc < 1e-3 * max(1.0, 1e-3 * cost):
            cost = tc
            break
        cost = tc
    return kf, cost


def _prior_cost(kf, w) -> float:
    if not kf.n_p:
        return 0.0
    return float(np.sum((w[6:6 + kf.n_p] * kf.p) ** 2))


def _prior_grad(kf, w) -> np.ndarray:
    g = np.zeros(kf.n)
    if kf.n_p:
        g[6:6 + kf.n_p] = w[6:6 + kf.n_p] ** 2 * kf.p
    return g


def _apply(kf: ak.AttitudeRateKalman, step: np.ndarray, free: np.ndarray) -> ak.AttitudeRateKalman:
    """A copy of the filter's nominal start state moved by the error-state step."""
    d = np.zeros(kf.n)
    d[free] = step
    new = ak.AttitudeRateKalman.__new__(ak.AttitudeRateKalman)
    new.__dict__.update(kf.__dict__)
    new.q = rot.quat_mul(kf.q, rot.quat_exp(d[:3]))
    new.q /= np.linalg.norm(new.q)
    new.w = kf.w + d[3:6]
    new.p = kf.p + d[6:6 + kf.n_p]
    new.beta = kf.beta + d[kf.i_beta:] if kf.n_beta else kf.beta
    return new


# --- both ------------------------------------------------------------------------------------------

def euler_rts_smooth(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
                     inertia_kgm2: np.ndarray | None = None, init: Smoothed | None = None,
                     accels_radps2: tuple[float, ...] = (1e-5, 1e-4, 1e-3, 1e-2)) -> Smoothed:
    """RTS over the Euler-aware attitude filter, for a body that is not quite torque-free.

    Euler's equations, with the tensor known or the shape found by the batch fit (`init`, default
    :func:`euler_fit`), carry the rate between samples; what they do not explain (a magnetic torque,
    an imperfect shape) is process noise on ω, its level chosen by maximum likelihood. The filter
    starts from the batch fit with a loose prior, so it is linearised on a good trajectory from the
    first sample.
    """
    t = np.asarray(t_s, float)
    b = np.asarray(b_T, float)
    field_eci_T = tabulated(field_eci_T, t)
    init = init or euler_fit(t, b, sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2)
    J = inertia_kgm2
    shape = None
    if J is None:
        if init.inertia_shape is not None:
            shape = init.inertia_shape
        else:
            J = np.eye(3)

    def run(accel, store):
        tun = ak.AttitudeKalmanTuning(rate_accel_radps2=accel, adapt_max=1.0, max_substep_rad=0.25,
                                      max_substeps=400)
        kf = ak.AttitudeRateKalman(sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=J,
                                   estimate_inertia=shape is not None, store=store, tuning=tun)
        n = kf.n
        P0 = np.zeros((n, n))
        P0[3:6, 3:6] = 0.05 ** 2 * np.eye(3)
        start = {"q": init.q[0], "omega_radps": init.w_radps[0], "P": P0}
        if shape is not None:  # the fitted shape with its uncertainty (the fit's covariance, floored)
            start["p"] = np.log(shape[1:])
            cov_p = np.asarray(init.info.get("cov_x0", np.zeros((n, n))))[6:8, 6:8]
            P0[6:8, 6:8] = cov_p + SHAPE_SIGMA_FLOOR ** 2 * np.eye(2)
        if field_eci_T is None:
            start["beta_uT"] = init.info.get("beta_uT")
            P0[kf.i_beta:, kf.i_beta:] = (3 * sigma_b_T * rk.UT_PER_T) ** 2 * np.eye(3)
        else:
            P0[:3, :3] = 0.1 ** 2 * np.eye(3)
        return rts_pass.forward(kf, t, b, start)  # compiled (the filter's own updates where it cannot be)

    fits = {}
    for a in accels_radps2:
        try:
            fits[a] = run(a, False).nll
        except (ValueError, np.linalg.LinAlgError):
            fits[a] = math.inf
    accel = min(fits, key=fits.get)
    kf = run(accel, True)
    q_s, x_s, P_s = rts(kf.log)
    c = variance_scale(kf.log)
    # the batch fit's other minima (another attitude about B, another motion as good): their spread
    # is not in this pass's covariance, which is linearised about one of them
    between = np.asarray(init.info.get("modes_var_radps2", 0.0))
    sig = np.sqrt(c * np.clip(np.einsum("kii->ki", P_s[:, 3:6, 3:6]), 0.0, None) + between)
    chi2 = _chi2(t, b, sigma_b_T, q_s, x_s, field_eci_T)
    if shape is not None:
        shape = np.concatenate([[1.0], np.exp(x_s[0, 3:5])])
    return Smoothed(t, x_s[:, :3].copy(), unobserved_sigma(sig, b, sigma_b_T), q_s, "euler_rts",
                    chi2 / max(3 * len(t) - kf.n, 1), init.inertia_shape if shape is None else shape,
                    info={"rate_accel_radps2": accel, "nll": kf.nll, "resets": kf.resets, "variance_scale": c})


def disagreement(a: Smoothed, b: Smoothed) -> float:
    """RMS over the samples and axes of (ω_a − ω_b) / √(σ_a² + σ_b²): how far two solutions of the same
    record are apart in units of their combined 1-σ. Two estimates from the same data are positively
    correlated, so the variance of their difference is at most σ_a² + σ_b²: for two consistent
    solutions the figure is below about 1; a solution in another minimum of the fit is many σ away."""
    ok = (np.all(np.isfinite(a.w_radps), axis=1) & np.all(np.isfinite(b.w_radps), axis=1)
          & np.all(np.isfinite(a.sigma_radps), axis=1) & np.all(np.isfinite(b.sigma_radps), axis=1))
    if not np.any(ok):
        return math.inf
    v = a.sigma_radps[ok] ** 2 + b.sigma_radps[ok] ** 2
    d2 = (a.w_radps[ok] - b.w_radps[ok]) ** 2 / np.maximum(v, 1e-30)
    return float(np.sqrt(np.mean(d2)))


#: one solution's σ excludes another's estimate when, at more than EXCLUDE_SHARE of the samples, the other
#: lies more than EXCLUDE_Z of the first one's σ away on some axis
EXCLUDE_Z, EXCLUDE_SHARE = 3.0, 0.25


def excludes(by: Smoothed, other: Smoothed, z: float = EXCLUDE_Z, share: float = EXCLUDE_SHARE) -> bool:
    """Whether `by`'s 1-σ excludes `other`'s estimate: |ω_other − ω_by| > z σ_by on some axis at more than
    `share` of the samples where both have one. A precise solution excludes a coarse one that strays
    from it (that is the precise one's claim); a coarse one excludes a precise one only when the precise
    one lies outside the coarse one's own band."""
    ok = (np.all(np.isfinite(by.w_radps), axis=1) & np.all(np.isfinite(other.w_radps), axis=1)
          & np.all(np.isfinite(by.sigma_radps), axis=1))
    if not np.any(ok):
        return False
    d = np.abs(other.w_radps[ok] - by.w_radps[ok]) / np.maximum(by.sigma_radps[ok], 1e-30)
    return float(np.mean(np.max(d, axis=1) > z)) > share


def _explains(res: Smoothed | None, chi2_accept: float) -> bool:
    return res is not None and np.isfinite(res.chi2_dof) and res.chi2_dof <= chi2_accept


def auto_order(eu: Smoothed | None, er: Smoothed | None, chi2_accept: float = 1.5,
               z_accept: float = 3.0) -> list[str]:
    """The candidates of "auto" in its order of preference: the batch fit when it explains the data and
    agrees with the Euler RTS smoother, that smoother when it ran without a restart, the random walk."""
    order = []
    if _explains(eu, chi2_accept) and (er is None or disagreement(eu, er) <= z_accept):
        order.append("euler")
    if er is not None and er.info.get("resets", 1) == 0:
        order.append("euler_rts")
    order.append("random_walk")
    return order


def auto_choice(eu: Smoothed | None, er: Smoothed | None, chi2_accept: float = 1.5, z_accept: float = 3.0,
                rw: Smoothed | None = None) -> str:
    """The model "auto" keeps: "euler" (the batch fit) when it explains the data (χ²/dof ≤ `chi2_accept`)
    and agrees with the Euler RTS smoother (:func:`disagreement` ≤ `z_accept`; a χ² test alone accepts
    a fit in a wrong minimum: χ²/dof 1.12 with 5.7 °/s of error where the RTS smoother had 0.64 °/s);
    else "euler_rts" when that smoother ran without a restart; else "random_walk".

    And never a fit that another solution's σ excludes (:func:`excludes`), among the candidates of that
    order (:func:`auto_order`) that explain the data (χ²/dof ≤ `chi2_accept`; the random-walk smoother
    `rw` always counts: it assumes least): the first that no other candidate excludes. When every one is excluded by
    another (the solutions disagree beyond their σ and the data do not say which is right), the first
    is kept and :func:`auto_smooth` widens its σ to cover the others."""
    order = auto_order(eu, er, chi2_accept, z_accept)
    sols = {"euler": eu, "euler_rts": er, "random_walk": rw}
    judges = [(name, res) for name, res in sols.items() if res is not None and name in order
              and (name == "random_walk" or _explains(res, chi2_accept))]
    for name in order:
        if sols[name] is None or not any(excludes(res, sols[name]) for other, res in judges if other != name):
            return name
    return order[0]


def covering(chosen: Smoothed, others: list[Smoothed]) -> Smoothed:
    """`chosen` with its 1-σ widened so that each of `others` whose σ excludes it lies within 1-σ:
    σ² + max over them of (ω_other − ω_chosen)², per sample and axis (the spread between solutions that
    the data do not tell apart is part of the uncertainty). A coarser solution that `chosen` excludes
    but whose own σ admits `chosen` widens nothing."""
    var = chosen.sigma_radps ** 2
    extra = np.zeros_like(var)
    for o in others:
        if excludes(o, chosen):
            d2 = (o.w_radps - chosen.w_radps) ** 2
            extra = np.fmax(extra, np.where(np.isfinite(d2), d2, 0.0))
    if not np.any(extra):
        return chosen
    info = dict(chosen.info, widened_to_cover="other solutions")
    return Smoothed(chosen.t_s, chosen.w_radps, np.sqrt(var + extra), chosen.q, chosen.method, chosen.chi2_dof,
                    chosen.inertia_shape, info=info)


def smooth(t_s: np.ndarray, b_T: np.ndarray, sigma_b_T: float, *, field_eci_T: FieldFn | None = None,
           model: str = "auto", inertia_kgm2: np.ndarray | None = None, chi2_accept: float = 1.5,
           z_accept: float = 3.0) -> Smoothed:
    """Smooth a recording. `model`: "random_walk" (:func:`rts_smooth`), "euler" (:func:`euler_fit`),
    "euler_rts" (:func:`euler_rts_smooth`) or "auto" (:func:`auto_choice`): the batch Euler fit when it
    explains the data (χ²/dof ≤ `chi2_accept`) and agrees with the Euler-aware RTS smoother started
    from it (within `z_accept` combined σ), else that smoother, else (if it had to restart: the motion
    is not Euler's) the random-walk RTS smoother."""
    if model not in ("auto", "random_walk", "euler", "euler_rts"):
        raise ValueError(f"model must be auto, random_walk, euler or euler_rts, got {model!r}")
    rw = rts_smooth(t_s, b_T, sigma_b_T, field_eci_T=field_eci_T)
    if model == "random_walk":
        return rw
    try:
        eu = euler_fit_checked(t_s, b_T, sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2, init=rw,
                               chi2_accept=chi2_accept)
    except (RuntimeError, ValueError, np.linalg.LinAlgError):
        if model == "auto":
            return rw
        raise
    if model == "euler":
        eu.info["rts_chi2_dof"] = rw.chi2_dof
        return eu
    er = euler_rts_smooth(t_s, b_T, sigma_b_T, field_eci_T=field_eci_T, inertia_kgm2=inertia_kgm2, init=eu)
    z = disagreement(eu, er)
    for res in (rw, eu, er):
        res.info.update(euler_chi2_dof=eu.chi2_dof, rts_chi2_dof=rw.chi2_dof, euler_vs_rts_z=z)
    if model == "euler_rts":
        return er
    return auto_result(rw, eu, er, chi2_accept, z_accept)


def auto_result(rw: Smoothed, eu: Smoothed | None, er: Smoothed | None, chi2_accept: float = 1.5,
                z_accept: float = 3.0) -> Smoothed:
    """What "auto" returns: :func:`auto_choice`'s solution; when another solution that explains the data
    excludes it (all of them exclude each other), with its σ widened to cover them (:func:`covering`)."""
    sols = {"euler": eu, "euler_rts": er, "random_walk": rw}
    choice = auto_choice(eu, er, chi2_accept, z_accept, rw=rw)
    chosen = sols[choice]
    order = auto_order(eu, er, chi2_accept, z_accept)
    others = [res for name, res in sols.items() if name != choice and res is not None and name in order
              and (name == "random_walk" or _explains(res, chi2_accept))]
    out = covering(chosen, others)
    out.info["auto_choice"] = choice
    return out
